//! ROS 2's QoS override parameters for the node's publishers:
//! `qos_overrides./FULL/TOPIC.publisher.reliability|durability|history|depth`
//! (the topic as resolved, after namespace and remaps), read at start-up.

use std::collections::BTreeMap;

use ros2_client::qos::{Durability, History, Reliability};
use ros2_client::QosProfile;

use super::ros_args::ParamValue;

/// The policies a publisher's QoS override may set.
pub const POLICIES: [&str; 4] = ["reliability", "durability", "history", "depth"];

/// An override that cannot be applied.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum QosOverrideError {
    /// A value the policy does not take.
    #[error("parameter {name}: {value:?} is not one of {expected}")]
    BadValue {
        /// The parameter.
        name: String,
        /// Its value.
        value: String,
        /// What it takes.
        expected: &'static str,
    },
    /// A topic this node does not publish, or a policy that is not overridable.
    #[error("parameter {name}: not a QoS override of this node's publishers ({known})")]
    Unknown {
        /// The parameter.
        name: String,
        /// The names it could be.
        known: String,
    },
}

/// `qos_overrides.TOPIC.publisher.POLICY`.
pub fn parameter_name(topic: &str, policy: &str) -> String {
    format!("qos_overrides.{topic}.publisher.{policy}")
}

/// Whether `name` is a QoS override parameter (of any topic).
pub fn is_override(name: &str) -> bool {
    name.starts_with("qos_overrides.")
}

/// `base` with the overrides among `params` for the publisher of `topic` applied.
pub fn apply(
    base: &QosProfile,
    topic: &str,
    params: &BTreeMap<String, ParamValue>,
) -> Result<QosProfile, QosOverrideError> {
    let mut q = base.clone();
    let get = |policy: &str| {
        let name = parameter_name(topic, policy);
        params.get(&name).map(|v| (name, v.as_text().to_ascii_lowercase()))
    };
    if let Some((name, v)) = get("reliability") {
        q.reliability = match v.as_str() {
            "reliable" => QosProfile::publisher_default().reliability,
            "best_effort" => Reliability::BestEffort,
            "system_default" => base.reliability,
            _ => return Err(bad(name, v, "reliable, best_effort, system_default")),
        };
    }
    if let Some((name, v)) = get("durability") {
        q.durability = match v.as_str() {
            "volatile" => Durability::Volatile,
            "transient_local" => Durability::TransientLocal,
            "system_default" => base.durability,
            _ => return Err(bad(name, v, "volatile, transient_local, system_default")),
        };
    }
    let depth = match get("depth") {
        None => None,
        Some((name, v)) => match v.parse::<i32>() {
            Ok(d) if d >= 1 => Some(d as usize),
            _ => return Err(bad(name, v, "a whole number >= 1")),
        },
    };
    let keep_last = |q: &QosProfile| match q.history {
        History::KeepLast { depth } => depth,
        History::KeepAll => 10,
    };
    if let Some((name, v)) = get("history") {
        q.history = match v.as_str() {
            "keep_last" => History::KeepLast { depth: keep_last(base) },
            "keep_all" => History::KeepAll,
            "system_default" => base.history,
            _ => return Err(bad(name, v, "keep_last, keep_all, system_default")),
        };
    }
    if let (Some(d), History::KeepLast { .. }) = (depth, q.history) {
        q.history = History::KeepLast { depth: d };
    }
    Ok(q)
}

/// Checks that every `qos_overrides.*` parameter names one of `topics` and a policy.
pub fn check_names<'a>(
    params: impl IntoIterator<Item = &'a String>,
    topics: &[String],
) -> Result<(), QosOverrideError> {
    for name in params.into_iter().filter(|n| is_override(n)) {
        let known = topics
            .iter()
            .any(|t| POLICIES.iter().any(|p| *name == parameter_name(t, p)));
        if !known {
            return Err(QosOverrideError::Unknown {
                name: name.clone(),
                known: format!(
                    "qos_overrides.TOPIC.publisher.{{{}}} for TOPIC in {}",
                    POLICIES.join(","),
                    topics.join(", ")
                ),
            });
        }
    }
    Ok(())
}

/// The parameter values that describe `q` (declared read-only on the node,
/// so that `ros2 param get` shows what each publisher uses).
pub fn describe(topic: &str, q: &QosProfile) -> Vec<(String, ParamValue)> {
    let s = |x: &str| ParamValue::String(x.into());
    let (history, depth) = match q.history {
        History::KeepLast { depth } => ("keep_last", depth),
        History::KeepAll => ("keep_all", 0),
    };
    vec![
        (
            parameter_name(topic, "reliability"),
            s(match q.reliability {
                Reliability::BestEffort => "best_effort",
                Reliability::Reliable { .. } => "reliable",
            }),
        ),
        (
            parameter_name(topic, "durability"),
            s(match q.durability {
                Durability::Volatile => "volatile",
                Durability::TransientLocal => "transient_local",
            }),
        ),
        (parameter_name(topic, "history"), s(history)),
        (
            parameter_name(topic, "depth"),
            ParamValue::Integer(i64::try_from(depth).unwrap_or(i64::MAX)),
        ),
    ]
}

fn bad(name: String, value: String, expected: &'static str) -> QosOverrideError {
    QosOverrideError::BadValue { name, value, expected }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params(kv: &[(&str, &str)]) -> BTreeMap<String, ParamValue> {
        kv.iter().map(|(k, v)| (k.to_string(), ParamValue::parse(v))).collect()
    }

    #[test]
    fn overrides_change_only_their_topic() {
        let base = QosProfile::publisher_default().history(History::KeepLast { depth: 5 });
        let p = params(&[
            ("qos_overrides./n/points.publisher.reliability", "best_effort"),
            ("qos_overrides./n/points.publisher.depth", "2"),
            ("qos_overrides./n/mask.publisher.durability", "transient_local"),
        ]);
        let q = apply(&base, "/n/points", &p).unwrap();
        assert_eq!(q.reliability, Reliability::BestEffort);
        assert_eq!(q.history, History::KeepLast { depth: 2 });
        assert_eq!(q.durability, Durability::Volatile);
        let m = apply(&base, "/n/mask", &p).unwrap();
        assert_eq!(m.durability, Durability::TransientLocal);
        assert!(matches!(m.reliability, Reliability::Reliable { .. }));
        assert_eq!(m.history, History::KeepLast { depth: 5 });
        let d = describe("/n/points", &q);
        assert_eq!(d[0].1, ParamValue::String("best_effort".into()));
        assert_eq!(d[3].1, ParamValue::Integer(2));
    }

    #[test]
    fn bad_values_and_names_are_refused() {
        let base = QosProfile::publisher_default();
        let p = params(&[("qos_overrides./n/points.publisher.reliability", "sometimes")]);
        assert!(matches!(
            apply(&base, "/n/points", &p),
            Err(QosOverrideError::BadValue { .. })
        ));
        let p = params(&[("qos_overrides./n/points.publisher.depth", "0")]);
        assert!(apply(&base, "/n/points", &p).is_err());
        let p = params(&[("qos_overrides./n/pointz.publisher.depth", "3")]);
        let topics = vec!["/n/points".to_string()];
        assert!(matches!(
            check_names(p.keys(), &topics),
            Err(QosOverrideError::Unknown { .. })
        ));
        let p = params(&[("qos_overrides./n/points.publisher.depth", "3"), ("xi", "0.5")]);
        assert_eq!(check_names(p.keys(), &topics), Ok(()));
    }
}
