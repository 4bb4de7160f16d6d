//! `--ros-args`: remaps (`-r FROM:=TO`, `__node`, `__ns`), parameters
//! (`-p NAME:=VALUE`) and the log level, and ROS 2 name resolution
//! (relative names under the namespace, `~` under the node, remaps matched
//! on fully qualified names), as rcl does them.

use std::collections::BTreeMap;

/// Why the command line could not be taken.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RosArgsError {
    /// An option needs a value and has none.
    #[error("--ros-args: {0} needs an argument")]
    MissingValue(String),
    /// A remap or parameter without `:=`.
    #[error("--ros-args: {what} {arg:?} is not of the form NAME:=VALUE")]
    NoAssignment {
        /// `-r` or `-p`.
        what: &'static str,
        /// The argument.
        arg: String,
    },
    /// A name that ROS 2 would refuse.
    #[error("invalid ROS name {name:?}: {why}")]
    InvalidName {
        /// The name.
        name: String,
        /// Which rule it breaks.
        why: &'static str,
    },
    /// Something rcl knows but this node does not.
    #[error(
        "--ros-args: {0} is not supported by this node (supported: -r/--remap, -p/--param, --params-file, --log-level)"
    )]
    Unsupported(String),
}

/// A parameter value as given on the command line (YAML scalars, as rcl reads them).
#[derive(Debug, Clone, PartialEq)]
pub enum ParamValue {
    /// `true` / `false`.
    Bool(bool),
    /// An integer.
    Integer(i64),
    /// A floating-point number.
    Double(f64),
    /// Anything else (quotes removed).
    String(String),
    /// A YAML flow sequence of numbers, `[20e6, 50e6, 100e6]`.
    DoubleArray(Vec<f64>),
}

impl ParamValue {
    /// Reads a YAML scalar the way `-p` does.
    pub fn parse(text: &str) -> Self {
        let t = text.trim();
        match t {
            "true" | "True" | "TRUE" => return ParamValue::Bool(true),
            "false" | "False" | "FALSE" => return ParamValue::Bool(false),
            _ => {}
        }
        if let Ok(i) = t.parse::<i64>() {
            return ParamValue::Integer(i);
        }
        if let Ok(x) = t.parse::<f64>() {
            return ParamValue::Double(x);
        }
        if let Some(v) = Self::numbers(t) {
            return ParamValue::DoubleArray(v);
        }
        let unquoted = t
            .strip_prefix('"')
            .and_then(|s| s.strip_suffix('"'))
            .or_else(|| t.strip_prefix('\'').and_then(|s| s.strip_suffix('\'')))
            .unwrap_or(t);
        ParamValue::String(unquoted.to_string())
    }

    /// `[a, b, ...]` of numbers (integers too), else `None`.
    fn numbers(t: &str) -> Option<Vec<f64>> {
        let inner = t.strip_prefix('[')?.strip_suffix(']')?.trim();
        if inner.is_empty() {
            return Some(vec![]);
        }
        inner.split(',').map(|v| v.trim().parse::<f64>().ok()).collect()
    }

    /// As a number (integers too).
    pub fn as_f64(&self) -> Option<f64> {
        match self {
            ParamValue::Integer(i) => Some(*i as f64),
            ParamValue::Double(x) => Some(*x),
            _ => None,
        }
    }

    /// As text (numbers and booleans spelled out).
    pub fn as_text(&self) -> String {
        match self {
            ParamValue::Bool(b) => b.to_string(),
            ParamValue::Integer(i) => i.to_string(),
            ParamValue::Double(x) => x.to_string(),
            ParamValue::String(s) => s.clone(),
            ParamValue::DoubleArray(v) => {
                format!("[{}]", v.iter().map(|x| x.to_string()).collect::<Vec<_>>().join(", "))
            }
        }
    }
}

/// What `--ros-args` said.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RosArgs {
    /// `__node:=` if given.
    pub node_name: Option<String>,
    /// `__ns:=` if given.
    pub namespace: Option<String>,
    /// `FROM:=TO` remaps in order (the first match wins, as in rcl).
    pub remaps: Vec<(String, String)>,
    /// `-p` parameters (the last one given wins).
    pub params: BTreeMap<String, ParamValue>,
    /// `--params-file` files, each with the number of `-p` given before it: a
    /// file overrides the `-p` before it and is overridden by those after, as
    /// in rcl.
    pub params_files: Vec<(std::path::PathBuf, usize)>,
    /// Every `-p` in the order given.
    pub param_order: Vec<(String, ParamValue)>,
    /// `--log-level` (`debug`, `info`, `warn`, `error`, `fatal`), if given.
    pub log_level: Option<String>,
}

impl RosArgs {
    /// Parses the arguments after the subcommand. Arguments outside
    /// `--ros-args ... [--]` are returned untouched for the caller's own parser.
    pub fn parse<I: IntoIterator<Item = String>>(args: I) -> Result<(RosArgs, Vec<String>), RosArgsError> {
        let mut out = RosArgs::default();
        let mut rest = vec![];
        let mut it = args.into_iter();
        let mut in_ros = false;
        while let Some(a) = it.next() {
            if !in_ros {
                if a == "--ros-args" {
                    in_ros = true;
                } else {
                    rest.push(a);
                }
                continue;
            }
            match a.as_str() {
                "--" => in_ros = false,
                "--ros-args" => {}
                "-r" | "--remap" => {
                    let v = it.next().ok_or_else(|| RosArgsError::MissingValue(a.clone()))?;
                    out.remap(&v)?;
                }
                "-p" | "--param" => {
                    let v = it.next().ok_or_else(|| RosArgsError::MissingValue(a.clone()))?;
                    let (k, val) = v.split_once(":=").ok_or(RosArgsError::NoAssignment {
                        what: "-p",
                        arg: v.clone(),
                    })?;
                    out.params.insert(k.to_string(), ParamValue::parse(val));
                    out.param_order.push((k.to_string(), ParamValue::parse(val)));
                }
                "--params-file" => {
                    let v = it.next().ok_or_else(|| RosArgsError::MissingValue(a.clone()))?;
                    out.params_files.push((v.into(), out.param_order.len()));
                }
                "--log-level" => {
                    let v = it.next().ok_or_else(|| RosArgsError::MissingValue(a.clone()))?;
                    // `--log-level NAME:=LEVEL` sets one logger; this node has one.
                    let level = v.rsplit_once(":=").map(|p| p.1).unwrap_or(&v);
                    out.log_level = Some(level.to_ascii_lowercase());
                }
                other => return Err(RosArgsError::Unsupported(other.to_string())),
            }
        }
        Ok((out, rest))
    }

    fn remap(&mut self, v: &str) -> Result<(), RosArgsError> {
        let (from, to) = v.split_once(":=").ok_or(RosArgsError::NoAssignment {
            what: "-r",
            arg: v.to_string(),
        })?;
        match from {
            "__node" | "__name" => self.node_name = Some(to.to_string()),
            "__ns" => self.namespace = Some(to.to_string()),
            _ => self.remaps.push((from.to_string(), to.to_string())),
        }
        Ok(())
    }

    /// The parameters for the node `node_fqn`: the parameter files' entries for it
    /// and the `-p` ones, in the order given (a later one wins).
    pub fn resolved_params(
        &self,
        node_fqn: &str,
    ) -> Result<BTreeMap<String, ParamValue>, super::params_file::ParamsFileError> {
        let mut out = BTreeMap::new();
        let mut taken = 0;
        for (file, before) in &self.params_files {
            out.extend(self.param_order[taken..*before].iter().cloned());
            taken = *before;
            out.extend(super::params_file::load(file, node_fqn)?);
        }
        out.extend(self.param_order[taken..].iter().cloned());
        Ok(out)
    }
}

/// A node's identity and its remaps: resolves topic and service names.
#[derive(Debug, Clone, PartialEq)]
pub struct NameResolver {
    /// Absolute namespace (`/` for none).
    pub namespace: String,
    /// Node name.
    pub node: String,
    remaps: Vec<(String, String)>,
}

impl NameResolver {
    /// The node `default_name` as `args` rename and remap it.
    pub fn new(default_name: &str, args: &RosArgs) -> Result<Self, RosArgsError> {
        let node = args.node_name.clone().unwrap_or_else(|| default_name.to_string());
        check_token(&node)?;
        let ns = args.namespace.clone().unwrap_or_else(|| "/".into());
        let namespace = if ns.starts_with('/') { ns } else { format!("/{ns}") };
        let namespace = if namespace.len() > 1 {
            namespace.trim_end_matches('/').to_string()
        } else {
            namespace
        };
        for part in namespace.split('/').filter(|p| !p.is_empty()) {
            check_token(part)?;
        }
        let mut r = NameResolver {
            namespace,
            node,
            remaps: vec![],
        };
        for (from, to) in &args.remaps {
            // A `node:from:=to` remap applies to that node only.
            let (target, from) = match from.split_once(':') {
                Some((n, f)) if !f.starts_with('=') => (Some(n), f),
                _ => (None, from.as_str()),
            };
            if target.is_some_and(|n| n != r.node) {
                continue;
            }
            let from = r.expand(from)?;
            let to = r.expand(to)?;
            r.remaps.push((from, to));
        }
        Ok(r)
    }

    /// The fully qualified node name, e.g. `/tof/translucent_tof`.
    pub fn node_fqn(&self) -> String {
        if self.namespace == "/" {
            format!("/{}", self.node)
        } else {
            format!("{}/{}", self.namespace, self.node)
        }
    }

    /// Expands a name (relative, absolute or `~`) without remapping.
    pub fn expand(&self, name: &str) -> Result<String, RosArgsError> {
        let full = if let Some(rest) = name.strip_prefix('~') {
            format!("{}{}", self.node_fqn(), rest)
        } else if name.starts_with('/') {
            name.to_string()
        } else if self.namespace == "/" {
            format!("/{name}")
        } else {
            format!("{}/{name}", self.namespace)
        };
        if full.len() > 1 && full.ends_with('/') {
            return Err(RosArgsError::InvalidName {
                name: name.into(),
                why: "ends with '/'",
            });
        }
        for part in full.split('/').skip(1) {
            if part.is_empty() {
                return Err(RosArgsError::InvalidName {
                    name: name.into(),
                    why: "has an empty token ('//')",
                });
            }
            check_token(part).map_err(|_| RosArgsError::InvalidName {
                name: name.into(),
                why: "tokens are letters, digits and '_', not starting with a digit",
            })?;
        }
        Ok(full)
    }

    /// Expands and remaps a topic or service name to its fully qualified form.
    pub fn resolve(&self, name: &str) -> Result<String, RosArgsError> {
        let full = self.expand(name)?;
        Ok(self
            .remaps
            .iter()
            .find(|(from, _)| *from == full)
            .map(|(_, to)| to.clone())
            .unwrap_or(full))
    }
}

fn check_token(t: &str) -> Result<(), RosArgsError> {
    let ok = !t.is_empty()
        && !t.starts_with(|c: char| c.is_ascii_digit())
        && t.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
    if ok {
        Ok(())
    } else {
        Err(RosArgsError::InvalidName {
            name: t.into(),
            why: "tokens are letters, digits and '_', not starting with a digit",
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(s: &str) -> Vec<String> {
        s.split_whitespace().map(String::from).collect()
    }

    #[test]
    fn remaps_params_and_passthrough() {
        let (r, rest) = RosArgs::parse(args(
            "--stats-json x.json --ros-args -r __node:=tt -r __ns:=/robot -r depth/image_raw:=/cam/depth -p xi:=0.7 -p threshold_mm:=25 -p rerun:=off -p flag:=true -- --other",
        ))
        .unwrap();
        assert_eq!(rest, args("--stats-json x.json --other"));
        assert_eq!(r.node_name.as_deref(), Some("tt"));
        assert_eq!(r.namespace.as_deref(), Some("/robot"));
        assert_eq!(r.params["xi"], ParamValue::Double(0.7));
        assert_eq!(r.params["threshold_mm"], ParamValue::Integer(25));
        assert_eq!(
            ParamValue::parse("[2e7, 5e7,100000000]"),
            ParamValue::DoubleArray(vec![2e7, 5e7, 1e8])
        );
        assert_eq!(ParamValue::parse("[]"), ParamValue::DoubleArray(vec![]));
        assert_eq!(ParamValue::parse("[2e7, x]"), ParamValue::String("[2e7, x]".into()));
        assert_eq!(ParamValue::DoubleArray(vec![2e7, 1.5]).as_text(), "[20000000, 1.5]");
        assert_eq!(r.params["rerun"], ParamValue::String("off".into()));
        assert_eq!(r.params["flag"], ParamValue::Bool(true));
        let n = NameResolver::new("translucent_tof", &r).unwrap();
        assert_eq!(n.node_fqn(), "/robot/tt");
        assert_eq!(n.resolve("depth/image_raw").unwrap(), "/cam/depth");
        assert_eq!(n.resolve("ir/image_raw").unwrap(), "/robot/ir/image_raw");
        assert_eq!(n.resolve("~/points").unwrap(), "/robot/tt/points");
        assert_eq!(n.resolve("/abs/x").unwrap(), "/abs/x");
    }

    #[test]
    fn remap_of_private_and_absolute_names_and_node_specific() {
        let (r, _) = RosArgs::parse(args(
            "--ros-args -r ~/points:=/cloud -r /tof/ir/image_raw:=/ir -r other:depth/image_raw:=/nope",
        ))
        .unwrap();
        let n = NameResolver::new(
            "translucent_tof",
            &RosArgs {
                namespace: Some("tof".into()),
                ..r
            },
        )
        .unwrap();
        assert_eq!(n.resolve("~/points").unwrap(), "/cloud");
        assert_eq!(n.resolve("ir/image_raw").unwrap(), "/ir");
        assert_eq!(n.resolve("depth/image_raw").unwrap(), "/tof/depth/image_raw");
    }

    #[test]
    fn bad_arguments_say_what_is_wrong() {
        assert_eq!(
            RosArgs::parse(args("--ros-args -p xi")).unwrap_err(),
            RosArgsError::NoAssignment {
                what: "-p",
                arg: "xi".into()
            }
        );
        assert!(matches!(
            RosArgs::parse(args("--ros-args -r")).unwrap_err(),
            RosArgsError::MissingValue(_)
        ));
        assert!(matches!(
            RosArgs::parse(args("--ros-args --enclave /x")).unwrap_err(),
            RosArgsError::Unsupported(_)
        ));
        let (r, _) = RosArgs::parse(args("--ros-args -r __node:=9bad")).unwrap();
        assert!(NameResolver::new("translucent_tof", &r).is_err());
        let n = NameResolver::new("translucent_tof", &RosArgs::default()).unwrap();
        assert!(n.resolve("a//b").is_err());
        assert!(n.resolve("a/").is_err());
        assert!(n.resolve("a-b").is_err());
    }

    #[test]
    fn param_values_read_as_yaml_scalars() {
        assert_eq!(ParamValue::parse("3e7"), ParamValue::Double(3e7));
        assert_eq!(ParamValue::parse("'sum'"), ParamValue::String("sum".into()));
        assert_eq!(ParamValue::parse("-4"), ParamValue::Integer(-4));
        assert_eq!(ParamValue::parse("-4").as_f64(), Some(-4.0));
        assert_eq!(ParamValue::parse("x.rrd").as_f64(), None);
    }
}
