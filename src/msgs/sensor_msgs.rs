//! `sensor_msgs`: images, camera calibration and point clouds.

use serde::{Deserialize, Serialize};

use super::std_msgs::Header;
use super::{cdr_bytes, RosMessage};

/// `sensor_msgs/msg/Image`: an uncompressed image.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Image {
    /// Acquisition time and the camera's optical frame.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Pixel encoding, e.g. `16UC1`, `32FC1`, `mono8`, `mono16`.
    pub encoding: String,
    /// 1 when multi-byte samples are big-endian.
    pub is_bigendian: u8,
    /// Bytes per row, including any padding.
    pub step: u32,
    /// `step * height` bytes.
    #[serde(with = "cdr_bytes")]
    pub data: Vec<u8>,
}

/// `sensor_msgs/msg/RegionOfInterest`: a sub-window of the full image.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RegionOfInterest {
    /// Leftmost column, pixels.
    pub x_offset: u32,
    /// Topmost row, pixels.
    pub y_offset: u32,
    /// Rows, pixels (0: full resolution).
    pub height: u32,
    /// Columns, pixels (0: full resolution).
    pub width: u32,
    /// Whether a rectified sub-window should be computed.
    pub do_rectify: bool,
}

/// `sensor_msgs/msg/CameraInfo`: intrinsic calibration of a pinhole camera.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraInfo {
    /// Stamp and optical frame of the image this describes.
    pub header: Header,
    /// Calibrated rows.
    pub height: u32,
    /// Calibrated columns.
    pub width: u32,
    /// Distortion model, e.g. `plumb_bob`.
    pub distortion_model: String,
    /// Distortion parameters (sequence; for `plumb_bob`: k1 k2 t1 t2 k3).
    pub d: Vec<f64>,
    /// Intrinsic matrix, row-major 3x3: fx 0 cx / 0 fy cy / 0 0 1, pixels.
    pub k: [f64; 9],
    /// Rectification rotation, row-major 3x3.
    pub r: [f64; 9],
    /// Projection matrix, row-major 3x4, pixels.
    pub p: [f64; 12],
    /// Horizontal binning (0 or 1: none).
    pub binning_x: u32,
    /// Vertical binning (0 or 1: none).
    pub binning_y: u32,
    /// Region of interest (all zero: full image).
    pub roi: RegionOfInterest,
}

/// `sensor_msgs/msg/PointField`: one field of a [`PointCloud2`] point.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct PointField {
    /// Field name, e.g. `x`.
    pub name: String,
    /// Byte offset within the point.
    pub offset: u32,
    /// One of the datatype constants ([`PointField::FLOAT32`], ...).
    pub datatype: u8,
    /// Number of elements.
    pub count: u32,
}

impl PointField {
    /// `int8`.
    pub const INT8: u8 = 1;
    /// `uint8`.
    pub const UINT8: u8 = 2;
    /// `int16`.
    pub const INT16: u8 = 3;
    /// `uint16`.
    pub const UINT16: u8 = 4;
    /// `int32`.
    pub const INT32: u8 = 5;
    /// `uint32`.
    pub const UINT32: u8 = 6;
    /// `float32`.
    pub const FLOAT32: u8 = 7;
    /// `float64`.
    pub const FLOAT64: u8 = 8;

    /// Size in bytes of one element of a datatype; `None` for an unknown one.
    pub fn datatype_size(datatype: u8) -> Option<usize> {
        match datatype {
            Self::INT8 | Self::UINT8 => Some(1),
            Self::INT16 | Self::UINT16 => Some(2),
            Self::INT32 | Self::UINT32 | Self::FLOAT32 => Some(4),
            Self::FLOAT64 => Some(8),
            _ => None,
        }
    }
}

/// `sensor_msgs/msg/PointCloud2`: points as packed records.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PointCloud2 {
    /// Stamp and frame of the points.
    pub header: Header,
    /// Rows (1 for an unorganized cloud).
    pub height: u32,
    /// Columns (points per row).
    pub width: u32,
    /// Layout of one point.
    pub fields: Vec<PointField>,
    /// Whether multi-byte fields are big-endian.
    pub is_bigendian: bool,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row.
    pub row_step: u32,
    /// `row_step * height` bytes.
    #[serde(with = "cdr_bytes")]
    pub data: Vec<u8>,
    /// True when no point is invalid (NaN).
    pub is_dense: bool,
}

const HEADER_DEP: (&str, &str) = (
    "std_msgs/msg/Header",
    "builtin_interfaces/Time stamp\nstring frame_id\n",
);
const TIME_DEP: (&str, &str) = ("builtin_interfaces/msg/Time", "int32 sec\nuint32 nanosec\n");

const IMAGE_DEF: &str = "std_msgs/Header header
uint32 height
uint32 width
string encoding
uint8 is_bigendian
uint32 step
uint8[] data
";

const ROI_DEF: &str = "uint32 x_offset
uint32 y_offset
uint32 height
uint32 width
bool do_rectify
";

const CAMERA_INFO_DEF: &str = "std_msgs/Header header
uint32 height
uint32 width
string distortion_model
float64[] d
float64[9] k
float64[9] r
float64[12] p
uint32 binning_x
uint32 binning_y
RegionOfInterest roi
";

const POINT_FIELD_DEF: &str = "uint8 INT8=1
uint8 UINT8=2
uint8 INT16=3
uint8 UINT16=4
uint8 INT32=5
uint8 UINT32=6
uint8 FLOAT32=7
uint8 FLOAT64=8
string name
uint32 offset
uint8 datatype
uint32 count
";

const POINT_CLOUD2_DEF: &str = "std_msgs/Header header
uint32 height
uint32 width
PointField[] fields
bool is_bigendian
uint32 point_step
uint32 row_step
uint8[] data
bool is_dense
";

impl RosMessage for Image {
    const TYPE_NAME: &'static str = "sensor_msgs/msg/Image";
    fn definition() -> &'static str {
        IMAGE_DEF
    }
    fn dependencies() -> Vec<(&'static str, &'static str)> {
        vec![HEADER_DEP, TIME_DEP]
    }
}

impl RosMessage for RegionOfInterest {
    const TYPE_NAME: &'static str = "sensor_msgs/msg/RegionOfInterest";
    fn definition() -> &'static str {
        ROI_DEF
    }
    fn dependencies() -> Vec<(&'static str, &'static str)> {
        Vec::new()
    }
}

impl RosMessage for CameraInfo {
    const TYPE_NAME: &'static str = "sensor_msgs/msg/CameraInfo";
    fn definition() -> &'static str {
        CAMERA_INFO_DEF
    }
    fn dependencies() -> Vec<(&'static str, &'static str)> {
        vec![HEADER_DEP, TIME_DEP, (RegionOfInterest::TYPE_NAME, ROI_DEF)]
    }
}

impl RosMessage for PointField {
    const TYPE_NAME: &'static str = "sensor_msgs/msg/PointField";
    fn definition() -> &'static str {
        POINT_FIELD_DEF
    }
    fn dependencies() -> Vec<(&'static str, &'static str)> {
        Vec::new()
    }
}

impl RosMessage for PointCloud2 {
    const TYPE_NAME: &'static str = "sensor_msgs/msg/PointCloud2";
    fn definition() -> &'static str {
        POINT_CLOUD2_DEF
    }
    fn dependencies() -> Vec<(&'static str, &'static str)> {
        vec![HEADER_DEP, TIME_DEP, (PointField::TYPE_NAME, POINT_FIELD_DEF)]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::{from_cdr, ros2msg_schema, to_cdr, Time};

    #[test]
    fn shared_dependency_texts_match_their_types() {
        assert_eq!(HEADER_DEP, (Header::TYPE_NAME, Header::definition()));
        assert_eq!(TIME_DEP, (Time::TYPE_NAME, Time::definition()));
    }

    fn tiny_image() -> Image {
        Image {
            header: Header {
                stamp: Time { sec: 1, nanosec: 2 },
                frame_id: "f".into(),
            },
            height: 1,
            width: 2,
            encoding: "16UC1".into(),
            is_bigendian: 0,
            step: 4,
            data: vec![0x10, 0x00, 0x20, 0x00],
        }
    }

    #[test]
    fn tiny_image_byte_layout() {
        let bytes = to_cdr(&tiny_image()).unwrap();
        #[rustfmt::skip]
        let expected: Vec<u8> = vec![
            0x00, 0x01, 0x00, 0x00,             // encapsulation: CDR_LE
            1, 0, 0, 0,                         // 0: stamp.sec
            2, 0, 0, 0,                         // 4: stamp.nanosec
            2, 0, 0, 0, b'f', 0,                // 8: frame_id "f\0"
            0, 0,                               // 14: pad to 4
            1, 0, 0, 0,                         // 16: height
            2, 0, 0, 0,                         // 20: width
            6, 0, 0, 0, b'1', b'6', b'U', b'C', b'1', 0, // 24: encoding
            0,                                  // 34: is_bigendian
            0,                                  // 35: pad to 4
            4, 0, 0, 0,                         // 36: step
            4, 0, 0, 0, 0x10, 0x00, 0x20, 0x00, // 40: data: u32 length + raw bytes
        ];
        assert_eq!(bytes, expected);
        assert_eq!(from_cdr::<Image>(&expected).unwrap(), tiny_image());
    }

    #[test]
    fn camera_info_f64_alignment_and_fixed_arrays() {
        let mut info = CameraInfo {
            header: Header {
                stamp: Time::default(),
                frame_id: String::new(),
            },
            distortion_model: "plumb_bob".into(),
            d: vec![0.5],
            ..Default::default()
        };
        info.k[0] = 500.0;
        info.p[11] = 7.0;
        info.roi.do_rectify = true;
        let bytes = to_cdr(&info).unwrap();
        let payload = &bytes[4..];
        // stamp 8, frame_id len 4 + "\0" -> 13, pad to 16, height, width -> 24,
        // distortion_model: 4 + 10 -> 38, pad to 40: d length 1 -> 44, pad to 48: d[0]
        assert_eq!(&payload[40..44], &1u32.to_le_bytes());
        assert_eq!(&payload[48..56], &0.5f64.to_le_bytes());
        // k follows without a length prefix
        assert_eq!(&payload[56..64], &500.0f64.to_le_bytes());
        // k 9 + r 9 + p 12 doubles = 240 bytes; then binning (2 x u32) and roi (4 x u32 + bool)
        assert_eq!(&payload[56 + 29 * 8..56 + 30 * 8], &7.0f64.to_le_bytes());
        assert_eq!(payload.len(), 56 + 240 + 8 + 16 + 1);
        assert_eq!(from_cdr::<CameraInfo>(&bytes).unwrap(), info);
    }

    #[test]
    fn point_cloud_round_trip() {
        let cloud = PointCloud2 {
            header: Header::new(5, "cam"),
            height: 1,
            width: 1,
            fields: vec![PointField {
                name: "x".into(),
                offset: 0,
                datatype: PointField::FLOAT32,
                count: 1,
            }],
            is_bigendian: false,
            point_step: 4,
            row_step: 4,
            data: 1.5f32.to_le_bytes().to_vec(),
            is_dense: true,
        };
        let bytes = to_cdr(&cloud).unwrap();
        assert_eq!(from_cdr::<PointCloud2>(&bytes).unwrap(), cloud);
    }

    #[test]
    fn schema_lists_dependencies_once() {
        let s = ros2msg_schema::<CameraInfo>();
        assert!(s.starts_with(CAMERA_INFO_DEF));
        let sep = "=".repeat(80);
        assert_eq!(s.matches(&format!("\n{sep}\nMSG: ")).count(), 3);
        assert!(s.contains("MSG: std_msgs/Header\n"));
        assert!(s.contains("MSG: builtin_interfaces/Time\n"));
        assert!(s.contains("MSG: sensor_msgs/RegionOfInterest\n"));
    }
}
