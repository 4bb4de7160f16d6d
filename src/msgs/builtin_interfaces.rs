//! `builtin_interfaces`: time stamps.

use serde::{Deserialize, Serialize};

use super::RosMessage;

/// `builtin_interfaces/msg/Time`: a point in time, seconds and nanoseconds
/// since the epoch of the clock that stamped it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct Time {
    /// Whole seconds.
    pub sec: i32,
    /// Nanoseconds past `sec`, in `0..1_000_000_000`.
    pub nanosec: u32,
}

impl Time {
    /// The time `ns` nanoseconds after the epoch. Seconds past `i32::MAX`
    /// (the year 2038 for wall time) saturate.
    pub fn from_nanos(ns: u64) -> Self {
        let sec = ns / 1_000_000_000;
        let nanosec = (ns % 1_000_000_000) as u32;
        match i32::try_from(sec) {
            Ok(sec) => Self { sec, nanosec },
            Err(_) => Self {
                sec: i32::MAX,
                nanosec: 999_999_999,
            },
        }
    }

    /// Nanoseconds since the epoch, exactly (negative before it).
    pub fn as_nanos(&self) -> i128 {
        i128::from(self.sec) * 1_000_000_000 + i128::from(self.nanosec)
    }

    /// Nanoseconds since the epoch as an MCAP log time: times before the
    /// epoch give 0.
    pub fn as_log_time_ns(&self) -> u64 {
        u64::try_from(self.as_nanos()).unwrap_or(0)
    }
}

impl RosMessage for Time {
    const TYPE_NAME: &'static str = "builtin_interfaces/msg/Time";
    fn definition() -> &'static str {
        "int32 sec\nuint32 nanosec\n"
    }
    fn dependencies() -> Vec<(&'static str, &'static str)> {
        Vec::new()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nanos_round_trip() {
        let t = Time::from_nanos(1_700_000_000_123_456_789);
        assert_eq!(
            t,
            Time {
                sec: 1_700_000_000,
                nanosec: 123_456_789
            }
        );
        assert_eq!(t.as_nanos(), 1_700_000_000_123_456_789);
        assert_eq!(t.as_log_time_ns(), 1_700_000_000_123_456_789);
    }

    #[test]
    fn before_epoch_and_saturation() {
        let t = Time {
            sec: -1,
            nanosec: 500_000_000,
        };
        assert_eq!(t.as_nanos(), -500_000_000);
        assert_eq!(t.as_log_time_ns(), 0);
        assert_eq!(Time::from_nanos(u64::MAX).sec, i32::MAX);
    }
}
