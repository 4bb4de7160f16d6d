//! ROS 2 bags in MCAP, as rosbag2 writes and reads them.
//!
//! - [`BagWriter`]: profile `ros2`, one `ros2msg` schema per type (with its
//!   dependencies), `cdr` channels with `offered_qos_profiles`, zstd chunks
//!   with message indexes and a summary; the file appears atomically.
//! - [`BagReader`]: a whole `.mcap` (or a rosbag2 directory) in memory,
//!   messages in log-time order, decoding checked against the type name.
//! - [`select_topics`]: which topics of a bag are depth, IR, camera info
//!   and ground truth; [`phasor_topics`] and [`recorded_frequencies`]: a
//!   multi-frequency camera's phasor images and their frequencies.
#![deny(missing_docs)]

mod discover;
mod phasors;
mod reader;
mod writer;

use std::path::PathBuf;

pub use discover::{select_topics, SelectedTopics, TopicOverrides};
pub use phasors::{
    frequencies_metadata, parse_frequencies, phasor_topic, phasor_topics, recorded_frequencies, FREQUENCIES_KEY,
    METADATA_NAME,
};
pub use reader::{record_length_limit, BagMetadata, BagReader, McapProblem, RawMessage, ReadStop, TopicInfo};
pub use writer::{BagWriter, DEFAULT_QOS_PROFILES};

use crate::msgs::MsgError;

/// Name of the MCAP metadata record that holds the physics a recording was
/// made with (`simulate` and `scripts/render/render_set.py` write it).
pub const PHYSICS_RECORD: &str = "translucent_tof.physics";

/// The key of [`PHYSICS_RECORD`] whose value is the physics file (TOML, as
/// `--physics FILE` reads it, its preset named).
pub const PHYSICS_RECORD_KEY: &str = "physics_toml";

/// Why a bag could not be written, read or understood.
#[derive(Debug, thiserror::Error)]
pub enum BagError {
    /// The file system refused (open, read, write, rename).
    #[error("{}: {what}", path.display())]
    Io {
        /// File concerned.
        path: PathBuf,
        /// What was being done.
        what: &'static str,
        /// The OS error.
        source: std::io::Error,
    },
    /// The file does not start with the MCAP magic bytes.
    #[error("{}: not an MCAP file (no MCAP magic at its start)", path.display())]
    NotMcap {
        /// File concerned.
        path: PathBuf,
    },
    /// The file starts as MCAP but ends before its first message (e.g. the
    /// recorder was killed); a file cut later is read up to the cut
    /// ([`BagReader::stops`]).
    #[error("{}: truncated MCAP file (it ends in the middle of a record, before any message); the recording was not finished", path.display())]
    Truncated {
        /// File concerned.
        path: PathBuf,
    },
    /// MCAP records that do not parse (bad CRC, bad lengths, bad
    /// compression...) before any message could be read.
    #[error("{}: corrupt MCAP (reading stopped at byte {offset} of {len})", path.display())]
    Corrupt {
        /// File concerned.
        path: PathBuf,
        /// Bytes read when the parser stopped.
        offset: u64,
        /// The file's length.
        len: u64,
        /// What the MCAP parser said.
        source: reader::McapProblem,
    },
    /// A directory with no `.mcap` file to read.
    #[error("{}: no .mcap file in this directory (a rosbag2 bag recorded with the sqlite3 storage must be converted to MCAP first)", path.display())]
    NoMcapInDirectory {
        /// Directory concerned.
        path: PathBuf,
    },
    /// A message on a channel whose encoding is not `cdr`.
    #[error("{}: topic {topic} has message encoding {encoding:?}; only \"cdr\" (ROS 2) is supported", path.display())]
    UnsupportedMessageEncoding {
        /// File concerned.
        path: PathBuf,
        /// Topic of the channel.
        topic: String,
        /// Its message encoding.
        encoding: String,
    },
    /// A message decoded as a type other than its channel's.
    #[error("topic {topic}: holds {found}, not {expected}")]
    TypeMismatch {
        /// Topic of the message.
        topic: String,
        /// Type asked for.
        expected: &'static str,
        /// Type recorded in the bag.
        found: String,
    },
    /// A message whose CDR does not decode.
    #[error("topic {topic}")]
    Decode {
        /// Topic of the message.
        topic: String,
        /// The decoding error.
        source: MsgError,
    },
    /// A message that could not be encoded for writing.
    #[error("{}: topic {topic}", path.display())]
    Encode {
        /// File being written.
        path: PathBuf,
        /// Topic being written.
        topic: String,
        /// The encoding error.
        source: MsgError,
    },
    /// One topic written with two message types.
    #[error("{}: topic {topic} already has type {existing}; cannot also write {new}", path.display())]
    TopicTypeConflict {
        /// File being written.
        path: PathBuf,
        /// Topic concerned.
        topic: String,
        /// Its type so far.
        existing: String,
        /// The type now offered.
        new: &'static str,
    },
    /// The MCAP writer failed.
    #[error("{}: writing MCAP", path.display())]
    Write {
        /// File being written.
        path: PathBuf,
        /// What the MCAP writer said.
        source: mcap::McapError,
    },
    /// Multi-frequency input that cannot be used (phasor topics, frequencies).
    #[error("multi-frequency input: {0}")]
    MultiFrequency(String),
    /// No topic fits a role (depth, IR).
    #[error(
        "no {role} topic found (looked for {looked_for}); the bag has: {available}. Pass {flag} TOPIC to choose one"
    )]
    NoTopic {
        /// `depth`, `IR`, ...
        role: &'static str,
        /// What was looked for.
        looked_for: &'static str,
        /// The bag's topics, with types.
        available: String,
        /// Command-line option that picks the topic.
        flag: &'static str,
    },
    /// Two or more topics fit a role equally well.
    #[error("{role} topic is ambiguous: {} all fit equally well; pass {flag} TOPIC to choose one", candidates.join(", "))]
    AmbiguousTopic {
        /// `depth`, `IR`, `camera info`.
        role: &'static str,
        /// The equally good topics.
        candidates: Vec<String>,
        /// Command-line option that picks the topic.
        flag: &'static str,
    },
    /// A topic named on the command line that the bag does not have (with that type).
    #[error("{flag} {topic}: {problem}; the bag has: {available}")]
    BadOverride {
        /// Command-line option concerned.
        flag: &'static str,
        /// The topic given.
        topic: String,
        /// Not in the bag, or the wrong type.
        problem: String,
        /// The bag's topics, with types.
        available: String,
    },
}

/// `pkg/Name` → `pkg/msg/Name`; other spellings unchanged. Bags written by
/// ROS 1 tools or older converters use the short form.
pub fn normalize_type_name(type_name: &str) -> String {
    let parts: Vec<&str> = type_name.split('/').collect();
    match parts.as_slice() {
        [pkg, name] if !pkg.is_empty() && !name.is_empty() => format!("{pkg}/msg/{name}"),
        _ => type_name.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn type_names_normalize() {
        assert_eq!(normalize_type_name("sensor_msgs/Image"), "sensor_msgs/msg/Image");
        assert_eq!(normalize_type_name("sensor_msgs/msg/Image"), "sensor_msgs/msg/Image");
        assert_eq!(
            normalize_type_name("std_srvs/srv/Trigger_Request"),
            "std_srvs/srv/Trigger_Request"
        );
    }
}
