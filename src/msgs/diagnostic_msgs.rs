//! `diagnostic_msgs`: the `/diagnostics` array of named statuses.

use serde::{Deserialize, Serialize};

use super::std_msgs::Header;
use super::RosMessage;

/// `diagnostic_msgs/msg/KeyValue`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct KeyValue {
    /// What is measured.
    pub key: String,
    /// Its value, as text.
    pub value: String,
}

/// `diagnostic_msgs/msg/DiagnosticStatus`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct DiagnosticStatus {
    /// [`DiagnosticStatus::OK`], `WARN`, `ERROR` or `STALE`.
    pub level: u8,
    /// Name of the component, e.g. `translucent_tof: pipeline`.
    pub name: String,
    /// One line on its state.
    pub message: String,
    /// The device (here: the node's fully qualified name).
    pub hardware_id: String,
    /// Figures.
    pub values: Vec<KeyValue>,
}

impl DiagnosticStatus {
    /// All is well.
    pub const OK: u8 = 0;
    /// Working, with a problem.
    pub const WARN: u8 = 1;
    /// Not working.
    pub const ERROR: u8 = 2;
    /// No recent data.
    pub const STALE: u8 = 3;
}

/// `diagnostic_msgs/msg/DiagnosticArray`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct DiagnosticArray {
    /// When.
    pub header: Header,
    /// One status per component.
    pub status: Vec<DiagnosticStatus>,
}

impl RosMessage for KeyValue {
    const TYPE_NAME: &'static str = "diagnostic_msgs/msg/KeyValue";
    fn definition() -> &'static str {
        "string key\nstring value\n"
    }
    fn dependencies() -> Vec<(&'static str, &'static str)> {
        vec![]
    }
}

impl RosMessage for DiagnosticStatus {
    const TYPE_NAME: &'static str = "diagnostic_msgs/msg/DiagnosticStatus";
    fn definition() -> &'static str {
        "byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\nbyte level\nstring name\nstring message\nstring hardware_id\nKeyValue[] values\n"
    }
    fn dependencies() -> Vec<(&'static str, &'static str)> {
        vec![(KeyValue::TYPE_NAME, KeyValue::definition())]
    }
}

impl RosMessage for DiagnosticArray {
    const TYPE_NAME: &'static str = "diagnostic_msgs/msg/DiagnosticArray";
    fn definition() -> &'static str {
        "std_msgs/Header header\nDiagnosticStatus[] status\n"
    }
    fn dependencies() -> Vec<(&'static str, &'static str)> {
        let mut deps = vec![(Header::TYPE_NAME, Header::definition())];
        deps.extend(Header::dependencies());
        deps.push((DiagnosticStatus::TYPE_NAME, DiagnosticStatus::definition()));
        deps.extend(DiagnosticStatus::dependencies());
        deps
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::{from_cdr, to_cdr};

    #[test]
    fn round_trips() {
        let m = DiagnosticArray {
            header: Header::new(1_700_000_000_000_000_001, ""),
            status: vec![DiagnosticStatus {
                level: DiagnosticStatus::WARN,
                name: "n".into(),
                message: "m".into(),
                hardware_id: "h".into(),
                values: vec![KeyValue {
                    key: "k".into(),
                    value: "v".into(),
                }],
            }],
        };
        let bytes = to_cdr(&m).unwrap();
        assert_eq!(from_cdr::<DiagnosticArray>(&bytes).unwrap(), m);
    }
}
