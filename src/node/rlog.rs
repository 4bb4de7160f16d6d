//! Log lines as ROS 2 prints them (`[INFO] [1700000000.123456789] [node]: message`)
//! on standard error, through the `log` facade. The node's own records go at
//! the chosen level; the DDS stack's only at errors. Once the node is up
//! ([`attach_rosout`]), the node's own records also go to `/rosout`.

use std::io::Write;
use std::sync::OnceLock;

struct RosStyle {
    node: String,
    level: log::LevelFilter,
}

static LOGGER: OnceLock<RosStyle> = OnceLock::new();
static ROSOUT: OnceLock<ros2_client::NodeLoggingHandle> = OnceLock::new();

/// Sends the node's own log records to `/rosout` too, from now on.
pub fn attach_rosout(handle: ros2_client::NodeLoggingHandle) {
    let _ = ROSOUT.set(handle);
}

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
        let ours = r.target().starts_with("translucent_tof");
        let who = if ours { self.node.as_str() } else { r.target() };
        if let (true, Some(h)) = (ours, ROSOUT.get()) {
            use ros2_client::RosoutRaw;
            let level = match r.level() {
                log::Level::Error => ros2_client::log::LogLevel::Error,
                log::Level::Warn => ros2_client::log::LogLevel::Warn,
                log::Level::Info => ros2_client::log::LogLevel::Info,
                log::Level::Debug | log::Level::Trace => ros2_client::log::LogLevel::Debug,
            };
            let stamp = ros2_client::builtin_interfaces::Time::now();
            h.rosout_raw(
                stamp,
                level,
                &self.node.trim_start_matches('/').replace('/', "."),
                &r.args().to_string(),
                r.file().unwrap_or(""),
                r.module_path().unwrap_or(""),
                r.line().unwrap_or(0),
            );
        }
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
