//! [`BagWriter`]: ROS 2 MCAP output that appears atomically.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use mcap::records::MessageHeader;

use super::BagError;
use crate::msgs::{ros2msg_schema, to_cdr, RosMessage};

/// The `offered_qos_profiles` rosbag2 records for a plain reliable,
/// volatile publisher (numeric enums, as Humble and later read them):
/// `ros2 bag play` offers this again, which matches reliable and
/// best-effort subscribers alike.
pub const DEFAULT_QOS_PROFILES: &str = "- history: 3
  depth: 0
  reliability: 1
  durability: 2
  deadline:
    sec: 2147483647
    nsec: 4294967295
  lifespan:
    sec: 2147483647
    nsec: 4294967295
  liveliness: 1
  liveliness_lease_duration:
    sec: 2147483647
    nsec: 4294967295
  avoid_ros_namespace_conventions: false
";

struct Channel {
    id: u16,
    type_name: &'static str,
    sequence: u32,
}

/// Writes a ROS 2 bag as one MCAP file, the way rosbag2 does: header
/// profile `ros2`, a `ros2msg` schema per type, `cdr` channels, zstd chunks
/// with message indexes and a summary so readers can seek.
///
/// Output goes to `PATH.partial` and is renamed to `PATH` by
/// [`finish`](Self::finish); dropped unfinished, the partial file is removed.
pub struct BagWriter {
    path: PathBuf,
    partial: PathBuf,
    mcap: Option<mcap::Writer<BufWriter<File>>>,
    schemas: HashMap<&'static str, u16>,
    channels: HashMap<String, Channel>,
}

impl BagWriter {
    /// Starts a bag at `path` (written to `path` + `.partial` until finished).
    pub fn create(path: &Path) -> Result<Self, BagError> {
        let partial = crate::files::partial_path(path);
        let file = File::create(&partial).map_err(|source| BagError::Io {
            path: partial.clone(),
            what: "creating bag",
            source,
        })?;
        let options = mcap::WriteOptions::new()
            .profile("ros2")
            .library(concat!("translucent_tof ", env!("CARGO_PKG_VERSION")))
            .compression(Some(mcap::Compression::Zstd))
            .compression_threads(0);
        let mcap = options.create(BufWriter::new(file)).map_err(|source| {
            let _ = std::fs::remove_file(&partial);
            BagError::Write {
                path: partial.clone(),
                source,
            }
        })?;
        Ok(Self {
            path: path.to_path_buf(),
            partial,
            mcap: Some(mcap),
            schemas: HashMap::new(),
            channels: HashMap::new(),
        })
    }

    /// The final path of the bag.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn write_error(&self, source: mcap::McapError) -> BagError {
        BagError::Write {
            path: self.partial.clone(),
            source,
        }
    }

    fn finished_error(&self) -> BagError {
        BagError::Io {
            path: self.partial.clone(),
            what: "writing",
            source: std::io::Error::other("the bag was already finished"),
        }
    }

    /// The channel of `topic` (created with its schema on first use) and
    /// the next sequence number on it.
    fn next_on_channel<M: RosMessage>(&mut self, topic: &str) -> Result<(u16, u32), BagError> {
        if let Some(channel) = self.channels.get_mut(topic) {
            if channel.type_name != M::TYPE_NAME {
                return Err(BagError::TopicTypeConflict {
                    path: self.partial.clone(),
                    topic: topic.to_string(),
                    existing: channel.type_name.to_string(),
                    new: M::TYPE_NAME,
                });
            }
            channel.sequence = channel.sequence.wrapping_add(1);
            return Ok((channel.id, channel.sequence));
        }
        let Some(mcap) = self.mcap.as_mut() else {
            return Err(self.finished_error());
        };
        let schema_id = match self.schemas.get(M::TYPE_NAME) {
            Some(&id) => id,
            None => {
                let text = ros2msg_schema::<M>();
                let id = mcap
                    .add_schema(M::TYPE_NAME, "ros2msg", text.as_bytes())
                    .map_err(|source| BagError::Write {
                        path: self.partial.clone(),
                        source,
                    })?;
                self.schemas.insert(M::TYPE_NAME, id);
                id
            }
        };
        let metadata = BTreeMap::from([("offered_qos_profiles".to_string(), DEFAULT_QOS_PROFILES.to_string())]);
        let id = mcap
            .add_channel(schema_id, topic, "cdr", &metadata)
            .map_err(|source| BagError::Write {
                path: self.partial.clone(),
                source,
            })?;
        self.channels.insert(
            topic.to_string(),
            Channel {
                id,
                type_name: M::TYPE_NAME,
                sequence: 1,
            },
        );
        Ok((id, 1))
    }

    /// Appends `msg` on `topic` with log time = publish time = `log_time_ns`
    /// (pass the header stamp in ns, see
    /// [`Time::as_log_time_ns`](crate::msgs::Time::as_log_time_ns)).
    /// Each topic keeps the type it was first written with.
    pub fn write<M: RosMessage>(&mut self, topic: &str, log_time_ns: u64, msg: &M) -> Result<(), BagError> {
        let data = to_cdr(msg).map_err(|source| BagError::Encode {
            path: self.partial.clone(),
            topic: topic.to_string(),
            source,
        })?;
        let (channel_id, sequence) = self.next_on_channel::<M>(topic)?;
        let header = MessageHeader {
            channel_id,
            sequence,
            log_time: log_time_ns,
            publish_time: log_time_ns,
        };
        let result = match self.mcap.as_mut() {
            Some(mcap) => mcap.write_to_known_channel(&header, &data),
            None => return Err(self.finished_error()),
        };
        result.map_err(|source| self.write_error(source))
    }

    /// Writes an MCAP metadata record (`name` and its key-value strings). Written
    /// before the first message, it is in the file however early a recording is cut.
    pub fn write_metadata(&mut self, name: &str, entries: BTreeMap<String, String>) -> Result<(), BagError> {
        let record = mcap::records::Metadata {
            name: name.to_string(),
            metadata: entries,
        };
        let result = match self.mcap.as_mut() {
            Some(mcap) => mcap.write_metadata(&record),
            None => return Err(self.finished_error()),
        };
        result.map_err(|source| self.write_error(source))
    }

    /// Writes the physics the recording was made with (a physics file's TOML) as its
    /// [`PHYSICS_RECORD`](super::PHYSICS_RECORD), which replay, calibrate-xi and audit read.
    pub fn write_physics_record(&mut self, physics_toml: String) -> Result<(), BagError> {
        let entries = BTreeMap::from([(super::PHYSICS_RECORD_KEY.to_string(), physics_toml)]);
        self.write_metadata(super::PHYSICS_RECORD, entries)
    }

    /// Writes the summary and footer, syncs, and renames `PATH.partial` to `PATH`.
    pub fn finish(mut self) -> Result<(), BagError> {
        // On error, drop removes the partial file.
        self.finish_inner()
    }

    fn finish_inner(&mut self) -> Result<(), BagError> {
        let Some(mut mcap) = self.mcap.take() else {
            return Ok(());
        };
        mcap.finish().map_err(|source| self.write_error(source))?;
        let file = mcap.into_inner().into_inner().map_err(|e| BagError::Io {
            path: self.partial.clone(),
            what: "flushing bag",
            source: e.into_error(),
        })?;
        file.sync_all().map_err(|source| BagError::Io {
            path: self.partial.clone(),
            what: "syncing bag",
            source,
        })?;
        drop(file);
        std::fs::rename(&self.partial, &self.path).map_err(|source| BagError::Io {
            path: self.path.clone(),
            what: "renaming the finished .partial file",
            source,
        })?;
        self.partial.clear();
        Ok(())
    }
}

impl Drop for BagWriter {
    fn drop(&mut self) {
        // Unfinished (or failed): close the file, then remove it.
        drop(self.mcap.take());
        if !self.partial.as_os_str().is_empty() {
            let _ = std::fs::remove_file(&self.partial);
        }
    }
}
