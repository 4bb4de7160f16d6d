//! Log lines as ROS 2 prints them (`[INFO] [1700000000.123456789] [node]: message`)
//! on standard error, through the `log` facade. The node's own records go at
//! the chosen level; the DDS stack's only at warnings and above.

use std::io::Write;
use std::sync::OnceLock;

struct RosStyle {
    node: String,
    level: log::LevelFilter,
}

static LOGGER: OnceLock<RosStyle> = OnceLock::new();

impl log::Log for RosStyle {
    fn enabled(&self, m: &log::Metadata) -> bool {
        let ours = m.target().starts_with("translucent_tof") || self.level == log::LevelFilter::Debug;
        m.level()
            <= if ours {
                self.level
            } else {
                log::LevelFilter::Error.min(self.level)
            }
    }

    fn log(&self, r: &log::Record) {
        if !self.enabled(r.metadata()) {
            return;
        }
        let t = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default();
        let level = match r.level() {
            log::Level::Error => "ERROR",
            log::Level::Warn => "WARN",
            log::Level::Info => "INFO",
            log::Level::Debug | log::Level::Trace => "DEBUG",
        };
        let who = if r.target().starts_with("translucent_tof") {
            self.node.as_str()
        } else {
            r.target()
        };
        let _ = writeln!(
            std::io::stderr().lock(),
            "[{level}] [{}.{:09}] [{who}]: {}",
            t.as_secs(),
            t.subsec_nanos(),
            r.args()
        );
    }

    fn flush(&self) {}
}

/// Installs the logger for node `node` (its ROS logger name) at `level`
/// (`debug`, `info`, `warn`, `error` or `fatal`). Only the first call counts.
pub fn init(node: &str, level: &str) -> Result<(), String> {
    let level = match level {
        "debug" => log::LevelFilter::Debug,
        "info" => log::LevelFilter::Info,
        "warn" => log::LevelFilter::Warn,
        "error" | "fatal" => log::LevelFilter::Error,
        other => {
            return Err(format!(
                "--log-level {other:?}: expected debug, info, warn, error or fatal"
            ))
        }
    };
    let logger = LOGGER.get_or_init(|| RosStyle {
        node: node.to_string(),
        level,
    });
    if log::set_logger(logger).is_ok() {
        log::set_max_level(level);
    }
    Ok(())
}
