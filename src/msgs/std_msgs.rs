//! `std_msgs`: the standard header.

use serde::{Deserialize, Serialize};

use super::builtin_interfaces::Time;
use super::RosMessage;

/// `std_msgs/msg/Header`: when and in which coordinate frame data was taken.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Header {
    /// Acquisition time.
    pub stamp: Time,
    /// Coordinate frame (REP 105 / REP 103; optical frames end in `_optical_frame`).
    pub frame_id: String,
}

impl Header {
    /// A header with the given stamp (ns since the epoch) and frame.
    pub fn new(stamp_ns: u64, frame_id: impl Into<String>) -> Self {
        Self {
            stamp: Time::from_nanos(stamp_ns),
            frame_id: frame_id.into(),
        }
    }
}

impl RosMessage for Header {
    const TYPE_NAME: &'static str = "std_msgs/msg/Header";
    fn definition() -> &'static str {
        "builtin_interfaces/Time stamp\nstring frame_id\n"
    }
    fn dependencies() -> Vec<(&'static str, &'static str)> {
        vec![(Time::TYPE_NAME, Time::definition())]
    }
}
