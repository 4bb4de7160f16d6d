//! `std_srvs`: the `Trigger` service.
//!
//! ROS names the halves of a service `Trigger_Request` / `Trigger_Response`;
//! the Rust types are [`TriggerRequest`] / [`TriggerResponse`], with the ROS
//! spellings as aliases.

use serde::{Deserialize, Serialize};

use super::RosMessage;

/// `std_srvs/srv/Trigger_Request`: empty. An empty IDL struct cannot exist,
/// so ROS 2 gives it one `uint8` placeholder member; CDR carries that byte.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct TriggerRequest {
    /// Placeholder, always 0.
    pub structure_needs_at_least_one_member: u8,
}

/// `std_srvs/srv/Trigger_Response`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct TriggerResponse {
    /// Whether the trigger did what was asked.
    pub success: bool,
    /// Informational, e.g. what was latched or why it failed.
    pub message: String,
}

/// The ROS spelling of [`TriggerRequest`].
#[allow(non_camel_case_types)]
pub type Trigger_Request = TriggerRequest;
/// The ROS spelling of [`TriggerResponse`].
#[allow(non_camel_case_types)]
pub type Trigger_Response = TriggerResponse;

impl RosMessage for TriggerRequest {
    const TYPE_NAME: &'static str = "std_srvs/srv/Trigger_Request";
    fn definition() -> &'static str {
        ""
    }
    fn dependencies() -> Vec<(&'static str, &'static str)> {
        Vec::new()
    }
}

impl RosMessage for TriggerResponse {
    const TYPE_NAME: &'static str = "std_srvs/srv/Trigger_Response";
    fn definition() -> &'static str {
        "bool success\nstring message\n"
    }
    fn dependencies() -> Vec<(&'static str, &'static str)> {
        Vec::new()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::{from_cdr, to_cdr};

    #[test]
    fn empty_request_is_one_byte() {
        let bytes = to_cdr(&TriggerRequest::default()).unwrap();
        assert_eq!(bytes, vec![0, 1, 0, 0, 0]);
        assert_eq!(from_cdr::<TriggerRequest>(&bytes).unwrap(), TriggerRequest::default());
    }

    #[test]
    fn response_layout() {
        let r = TriggerResponse {
            success: true,
            message: "ok".into(),
        };
        let bytes = to_cdr(&r).unwrap();
        // bool, pad to 4, u32 length 3 (with NUL), "ok\0"
        assert_eq!(bytes, vec![0, 1, 0, 0, 1, 0, 0, 0, 3, 0, 0, 0, b'o', b'k', 0]);
        assert_eq!(from_cdr::<TriggerResponse>(&bytes).unwrap(), r);
    }
}
