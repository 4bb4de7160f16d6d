//! ROS 2 message types as plain serde structs, one module per ROS package,
//! shared by bags and DDS.
//!
//! CDR is positional: every struct's field order is its `.msg` file's.
//! [`to_cdr`] / [`from_cdr`] add and check the 4-byte encapsulation header
//! that ROS 2 puts in front of every serialized message.
#![deny(missing_docs)]

pub mod builtin_interfaces;
pub mod diagnostic_msgs;
pub mod sensor_msgs;
pub mod std_msgs;
pub mod std_srvs;
pub mod translucent_tof;

pub use builtin_interfaces::Time;
pub use sensor_msgs::{CameraInfo, Image, PointCloud2, PointField, RegionOfInterest};
pub use std_msgs::Header;
pub use std_srvs::{TriggerRequest, TriggerResponse};

use byteorder::{BigEndian, LittleEndian};

/// Encapsulation header of little-endian plain CDR (`CDR_LE`).
pub const CDR_LE_HEADER: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// Why a message could not be (de)serialized.
#[derive(Debug, thiserror::Error)]
pub enum MsgError {
    /// Fewer bytes than the 4-byte encapsulation header.
    #[error("{type_name}: {len} bytes is too short for a CDR message (need a 4-byte encapsulation header)")]
    TooShort {
        /// ROS type being decoded.
        type_name: &'static str,
        /// Bytes given.
        len: usize,
    },
    /// An encapsulation other than plain CDR (e.g. XCDR2 or parameter lists).
    #[error("{type_name}: unsupported CDR encapsulation {id:#06x} (supported: 0x0000 CDR_BE, 0x0001 CDR_LE)")]
    UnsupportedEncapsulation {
        /// ROS type being decoded.
        type_name: &'static str,
        /// The encapsulation identifier found.
        id: u16,
    },
    /// The CDR body does not match the type (too short, bad bool, bad UTF-8, ...).
    #[error("{type_name}: CDR decoding failed")]
    Decode {
        /// ROS type being decoded.
        type_name: &'static str,
        /// What the CDR decoder said.
        source: cdr_encoding::Error,
    },
    /// The message could not be encoded (e.g. a sequence longer than `u32::MAX`).
    #[error("{type_name}: CDR encoding failed")]
    Encode {
        /// ROS type being encoded.
        type_name: &'static str,
        /// What the CDR encoder said.
        source: cdr_encoding::Error,
    },
}

/// A ROS 2 message type: its name, its `.msg` definition and those it uses.
pub trait RosMessage: serde::Serialize + serde::de::DeserializeOwned {
    /// Full ROS 2 type name, e.g. `"sensor_msgs/msg/Image"`.
    const TYPE_NAME: &'static str;
    /// The `.msg` definition text of this type alone (as in the ROS 2
    /// distribution; comments dropped).
    fn definition() -> &'static str;
    /// Types this one uses, transitively, each once: `(TYPE_NAME, definition)`.
    fn dependencies() -> Vec<(&'static str, &'static str)>;
}

/// Separator between the definitions of a `ros2msg` schema: exactly 80 `=`.
pub const SCHEMA_SEPARATOR: &str = "================================================================================";

/// `pkg/msg/Name` → `pkg/Name`, the spelling rosbag2 uses after `MSG:`.
pub fn short_type_name(type_name: &str) -> String {
    let parts: Vec<&str> = type_name.split('/').collect();
    match parts.as_slice() {
        [pkg, "msg" | "srv" | "action", name] => format!("{pkg}/{name}"),
        _ => type_name.to_string(),
    }
}

/// The `ros2msg` schema text as rosbag2 writes it: the definition, then for
/// each dependency a line of exactly 80 `=`, a line `MSG: pkg/Name` and its
/// definition.
pub fn ros2msg_schema<M: RosMessage>() -> String {
    let mut out = M::definition().trim_end().to_string();
    out.push('\n');
    for (name, def) in M::dependencies() {
        out.push_str(SCHEMA_SEPARATOR);
        out.push_str("\nMSG: ");
        out.push_str(&short_type_name(name));
        out.push('\n');
        let def = def.trim_end();
        out.push_str(def);
        if !def.is_empty() {
            out.push('\n');
        }
    }
    out
}

/// Serializes to little-endian CDR with the encapsulation header
/// [`CDR_LE_HEADER`] in front.
pub fn to_cdr<M: RosMessage>(msg: &M) -> Result<Vec<u8>, MsgError> {
    let body = cdr_encoding::to_vec::<M, LittleEndian>(msg).map_err(|source| MsgError::Encode {
        type_name: M::TYPE_NAME,
        source,
    })?;
    let mut out = Vec::with_capacity(body.len() + 4);
    out.extend_from_slice(&CDR_LE_HEADER);
    out.extend_from_slice(&body);
    Ok(out)
}

/// Deserializes CDR with its encapsulation header: `CDR_LE` (0x0001) or
/// `CDR_BE` (0x0000). Alignment is relative to the end of the header.
/// Trailing bytes (ROS pads messages to 4) are ignored.
pub fn from_cdr<M: RosMessage>(bytes: &[u8]) -> Result<M, MsgError> {
    let type_name = M::TYPE_NAME;
    let (head, body) = match bytes.split_first_chunk::<4>() {
        Some(split) => split,
        None => {
            return Err(MsgError::TooShort {
                type_name,
                len: bytes.len(),
            })
        }
    };
    let id = u16::from_be_bytes([head[0], head[1]]);
    let decoded = match id {
        0x0001 => cdr_encoding::from_bytes::<M, LittleEndian>(body),
        0x0000 => cdr_encoding::from_bytes::<M, BigEndian>(body),
        _ => return Err(MsgError::UnsupportedEncapsulation { type_name, id }),
    };
    decoded
        .map(|(msg, _)| msg)
        .map_err(|source| MsgError::Decode { type_name, source })
}

/// `uint8[]` fields in CDR as one block of bytes instead of element by
/// element: cdr-encoding 0.11 (the CDR RustDDS 0.15 uses on the wire too)
/// writes and reads `serialize_bytes` as a CDR sequence, a `u32` length then
/// the bytes. (0.10 wrote no length; mixing the two put the length inside
/// the data of every image sent over DDS, caught by the demo test.)
pub(crate) mod cdr_bytes {
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(data: &[u8], s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(data)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<u8>, D::Error> {
        serde_bytes::ByteBuf::deserialize(d).map(serde_bytes::ByteBuf::into_vec)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn big_endian_header_accepted() {
        // Time { sec: 1, nanosec: 2 } in CDR_BE
        let bytes = [0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 2];
        assert_eq!(from_cdr::<Time>(&bytes).unwrap(), Time { sec: 1, nanosec: 2 });
    }

    #[test]
    fn bad_headers_are_clear_errors() {
        let err = from_cdr::<Time>(&[0, 1]).unwrap_err();
        assert!(matches!(err, MsgError::TooShort { len: 2, .. }), "{err}");
        let err = from_cdr::<Time>(&[0, 7, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0]).unwrap_err();
        assert!(err.to_string().contains("0x0007"), "{err}");
        let err = from_cdr::<Image>(&[0, 1, 0, 0, 1, 0]).unwrap_err();
        assert!(matches!(err, MsgError::Decode { .. }), "{err}");
        assert!(err.to_string().starts_with("sensor_msgs/msg/Image"), "{err}");
    }

    #[test]
    fn huge_declared_length_is_an_error_not_a_panic() {
        // Image whose data length claims 4 GiB.
        let mut img = to_cdr(&Image::default()).unwrap();
        let n = img.len();
        img[n - 4..].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(from_cdr::<Image>(&img).is_err());
    }

    #[test]
    fn short_names() {
        assert_eq!(short_type_name("sensor_msgs/msg/Image"), "sensor_msgs/Image");
        assert_eq!(short_type_name("sensor_msgs/Image"), "sensor_msgs/Image");
    }

    #[test]
    fn image_schema_text() {
        let s = ros2msg_schema::<Image>();
        let sep = "=".repeat(80);
        let expected = format!(
            "{}{sep}\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n\
             {sep}\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n",
            Image::definition()
        );
        assert_eq!(s, expected);
    }
}
