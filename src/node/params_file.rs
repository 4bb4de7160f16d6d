//! `--params-file FILE`: ROS 2 parameter YAML, as rcl reads it.
//!
//! ```yaml
//! /**:                      # every node
//!   ros__parameters:
//!     threshold_mm: 30
//! /tof/translucent_tof:     # this node only (fully qualified, or with `*` / `**`)
//!   ros__parameters:
//!     xi: 0.65
//!     qos_overrides:        # nested keys are joined with '.'
//!       /tof/translucent_tof/points:
//!         publisher: {reliability: best_effort, depth: 2}
//! ```
//!
//! Sections whose key matches the node with a wildcard apply first, an exact
//! match last (it wins), as in rclcpp.

use std::path::Path;

use yaml_rust2::{Yaml, YamlLoader};

use super::ros_args::ParamValue;

/// Why a parameter file could not be used.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ParamsFileError {
    /// The file could not be read.
    #[error("--params-file {path}: {why}")]
    Read {
        /// The file.
        path: String,
        /// The I/O error.
        why: String,
    },
    /// Not YAML, or not the ROS 2 layout.
    #[error("--params-file {path}: {why}")]
    Layout {
        /// The file.
        path: String,
        /// What is wrong, and where.
        why: String,
    },
}

/// The parameters `text` (the contents of `path`) gives the node `node_fqn`
/// (e.g. `/tof/translucent_tof`), in the order they apply.
pub fn parse(path: &str, text: &str, node_fqn: &str) -> Result<Vec<(String, ParamValue)>, ParamsFileError> {
    let layout = |why: String| ParamsFileError::Layout {
        path: path.to_string(),
        why,
    };
    let docs = YamlLoader::load_from_str(text).map_err(|e| layout(e.to_string()))?;
    let mut wildcard = vec![];
    let mut exact = vec![];
    for doc in &docs {
        let Yaml::Hash(top) = doc else {
            if matches!(doc, Yaml::Null) {
                continue;
            }
            return Err(layout("the top level must map node names to `ros__parameters`".into()));
        };
        for (key, section) in top {
            let Some(key) = key.as_str() else {
                return Err(layout(format!("node key {key:?} is not a name")));
            };
            let pattern = if key.starts_with('/') {
                key.to_string()
            } else {
                format!("/{key}")
            };
            let Some(params) = section
                .as_hash()
                .and_then(|h| h.get(&Yaml::String("ros__parameters".into())))
            else {
                return Err(layout(format!("{key}: expected a `ros__parameters` map under it")));
            };
            let mut flat = vec![];
            flatten("", params, &mut flat).map_err(|w| layout(format!("{key}: {w}")))?;
            if pattern == node_fqn {
                exact.extend(flat);
            } else if matches_node(&pattern, node_fqn) {
                wildcard.extend(flat);
            }
        }
    }
    wildcard.extend(exact);
    Ok(wildcard)
}

/// Reads and parses a parameter file for `node_fqn`.
pub fn load(path: &Path, node_fqn: &str) -> Result<Vec<(String, ParamValue)>, ParamsFileError> {
    let shown = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| ParamsFileError::Read {
        path: shown.clone(),
        why: e.to_string(),
    })?;
    parse(&shown, &text, node_fqn)
}

fn flatten(prefix: &str, y: &Yaml, out: &mut Vec<(String, ParamValue)>) -> Result<(), String> {
    let Yaml::Hash(h) = y else {
        return Err("`ros__parameters` must be a map of names to values".into());
    };
    for (k, v) in h {
        let name = match k {
            Yaml::String(s) => s.clone(),
            Yaml::Integer(i) => i.to_string(),
            other => return Err(format!("parameter key {other:?} is not a name")),
        };
        let full = if prefix.is_empty() {
            name
        } else {
            format!("{prefix}.{name}")
        };
        let value = match v {
            Yaml::Hash(_) => {
                flatten(&full, v, out)?;
                continue;
            }
            Yaml::Boolean(b) => ParamValue::Bool(*b),
            Yaml::Integer(i) => ParamValue::Integer(*i),
            Yaml::Real(r) => match v.as_f64() {
                Some(x) => ParamValue::Double(x),
                None => return Err(format!("{full}: {r:?} is not a number")),
            },
            Yaml::String(s) => ParamValue::String(s.clone()),
            Yaml::Array(items) => {
                let numbers: Option<Vec<f64>> = items
                    .iter()
                    .map(|i| i.as_f64().or_else(|| i.as_i64().map(|v| v as f64)))
                    .collect();
                match numbers {
                    Some(v) => ParamValue::DoubleArray(v),
                    None => return Err(format!("{full}: an array of numbers is the only array this node takes")),
                }
            }
            Yaml::Null => return Err(format!("{full}: no value")),
            Yaml::Alias(_) | Yaml::BadValue => return Err(format!("{full}: unsupported YAML value")),
        };
        out.push((full, value));
    }
    Ok(())
}

/// Whether a node key with wildcards (`*`: one token, `**`: any number)
/// matches the fully qualified node name.
pub fn matches_node(pattern: &str, node_fqn: &str) -> bool {
    let p: Vec<&str> = pattern.split('/').filter(|t| !t.is_empty()).collect();
    let n: Vec<&str> = node_fqn.split('/').filter(|t| !t.is_empty()).collect();
    fn go(p: &[&str], n: &[&str]) -> bool {
        match p.split_first() {
            None => n.is_empty(),
            Some((&"**", rest)) => (0..=n.len()).any(|k| go(rest, &n[k..])),
            Some((tok, rest)) => n
                .split_first()
                .is_some_and(|(first, nrest)| (*tok == "*" || tok == first) && go(rest, nrest)),
        }
    }
    go(&p, &n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

    const FILE: &str = "
/**:
  ros__parameters:
    threshold_mm: 25
    xi: 0.5
/tof/translucent_tof:
  ros__parameters:
    xi: 0.65
    physics: ''
    qos_overrides:
      /tof/translucent_tof/points:
        publisher:
          reliability: best_effort
          depth: 2
/other/node:
  ros__parameters:
    xi: 0.1
";

    #[test]
    fn wildcards_first_then_the_exact_node_nested_keys_joined() {
        let p = parse("f.yaml", FILE, "/tof/translucent_tof").unwrap();
        let names: Vec<&str> = p.iter().map(|(k, _)| k.as_str()).collect();
        assert_eq!(
            names,
            [
                "threshold_mm",
                "xi",
                "xi",
                "physics",
                "qos_overrides./tof/translucent_tof/points.publisher.reliability",
                "qos_overrides./tof/translucent_tof/points.publisher.depth"
            ]
        );
        // The later (exact) value wins when collected into a map.
        let map: BTreeMap<_, _> = p.into_iter().collect();
        assert_eq!(map["xi"], ParamValue::Double(0.65));
        assert_eq!(map["threshold_mm"], ParamValue::Integer(25));
        assert_eq!(
            map["qos_overrides./tof/translucent_tof/points.publisher.depth"],
            ParamValue::Integer(2)
        );
        // Another node sees only the wildcard section.
        let other = parse("f.yaml", FILE, "/elsewhere/translucent_tof").unwrap();
        assert_eq!(other.len(), 2);
    }

    #[test]
    fn node_keys_match_as_rcl_does() {
        assert!(matches_node("/**", "/translucent_tof"));
        assert!(matches_node("/**", "/a/b/translucent_tof"));
        assert!(matches_node("/**/translucent_tof", "/tof/translucent_tof"));
        assert!(matches_node("/*/translucent_tof", "/tof/translucent_tof"));
        assert!(!matches_node("/*/translucent_tof", "/translucent_tof"));
        assert!(!matches_node("/tof/*", "/tof/a/b"));
        // A key without a leading slash is a name in the root namespace.
        let p = parse(
            "f",
            "translucent_tof:\n  ros__parameters:\n    xi: 0.3\n",
            "/translucent_tof",
        )
        .unwrap();
        assert_eq!(p, [("xi".to_string(), ParamValue::Double(0.3))]);
    }

    #[test]
    fn a_wrong_layout_says_where() {
        let e = parse("f", "/**:\n  xi: 0.3\n", "/n").unwrap_err();
        assert!(e.to_string().contains("ros__parameters"), "{e}");
        let e = parse("f", "/**:\n  ros__parameters:\n    xi: [a, 2]\n", "/n").unwrap_err();
        assert!(
            e.to_string().contains("xi: an array of numbers is the only array"),
            "{e}"
        );
        let p = parse("f", "/**:\n  ros__parameters:\n    f: [2.0e7, 100000000]\n", "/n").unwrap();
        assert_eq!(p, [("f".to_string(), ParamValue::DoubleArray(vec![2e7, 1e8]))]);
        let e = parse("f", "/**: [\n", "/n").unwrap_err();
        assert!(matches!(e, ParamsFileError::Layout { .. }));
        assert!(matches!(
            load(Path::new("/nonexistent/params.yaml"), "/n"),
            Err(ParamsFileError::Read { .. })
        ));
    }
}
