//! [`BagReader`]: a ROS 2 MCAP bag in memory, messages in log-time order.

use std::collections::HashMap;
use std::ops::Range;
use std::path::{Path, PathBuf};

use super::{normalize_type_name, BagError};
use crate::msgs::{from_cdr, RosMessage};

/// One topic of a bag.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TopicInfo {
    /// Topic name, e.g. `/tof/depth/image_raw`.
    pub name: String,
    /// ROS type as `pkg/msg/Name` (short `pkg/Name` spellings are normalized).
    pub type_name: String,
    /// Messages on it.
    pub message_count: u64,
}

/// One undecoded message, borrowed from its [`BagReader`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RawMessage<'a> {
    /// Topic name.
    pub topic: &'a str,
    /// ROS type as `pkg/msg/Name`.
    pub type_name: &'a str,
    /// Log time, ns.
    pub log_time_ns: u64,
    /// CDR bytes, with their encapsulation header.
    pub data: &'a [u8],
}

struct Topic {
    info: TopicInfo,
    encoding: String,
    file: PathBuf,
}

struct Entry {
    topic: usize,
    log_time_ns: u64,
    data: Range<usize>,
}

/// A ROS 2 bag read whole into memory.
///
/// Opens one `.mcap` file, or a rosbag2 directory (its `.mcap` files, as
/// listed in `metadata.yaml` or found by extension, merged).
pub struct BagReader {
    path: PathBuf,
    topics: Vec<Topic>,
    entries: Vec<Entry>,
    arena: Vec<u8>,
}

/// The `.mcap` files of a rosbag2 directory: those `metadata.yaml` lists
/// under `relative_file_paths`, else every `*.mcap` in it, sorted.
fn files_of_directory(dir: &Path) -> Result<Vec<PathBuf>, BagError> {
    let io = |what, source| BagError::Io {
        path: dir.to_path_buf(),
        what,
        source,
    };
    let mut files = Vec::new();
    let meta = dir.join("metadata.yaml");
    if let Ok(text) = std::fs::read_to_string(&meta) {
        let mut in_list = false;
        for line in text.lines() {
            let trimmed = line.trim();
            if trimmed.starts_with("relative_file_paths:") {
                in_list = true;
                continue;
            }
            if in_list {
                if let Some(item) = trimmed.strip_prefix("- ") {
                    let name = item.trim().trim_matches(|c| c == '"' || c == '\'');
                    // rosbag2 writes paths relative to the bag directory.
                    let file = dir.join(Path::new(name).file_name().unwrap_or_default());
                    if name.ends_with(".mcap") && file.is_file() {
                        files.push(file);
                    }
                } else if !trimmed.is_empty() {
                    in_list = false;
                }
            }
        }
    }
    if files.is_empty() {
        let listing = std::fs::read_dir(dir).map_err(|e| io("listing directory", e))?;
        for entry in listing {
            let entry = entry.map_err(|e| io("listing directory", e))?;
            let p = entry.path();
            if p.is_file() && p.extension().is_some_and(|e| e == "mcap") {
                files.push(p);
            }
        }
        files.sort();
    }
    if files.is_empty() {
        return Err(BagError::NoMcapInDirectory {
            path: dir.to_path_buf(),
        });
    }
    Ok(files)
}

impl BagReader {
    /// Reads a `.mcap` file, or the `.mcap` files of a rosbag2 directory.
    pub fn open(path: &Path) -> Result<Self, BagError> {
        let files = if path.is_dir() {
            files_of_directory(path)?
        } else {
            vec![path.to_path_buf()]
        };
        let mut reader = Self {
            path: path.to_path_buf(),
            topics: Vec::new(),
            entries: Vec::new(),
            arena: Vec::new(),
        };
        for file in &files {
            reader.load(file)?;
        }
        // Log-time order; ties keep file order.
        reader.entries.sort_by_key(|e| e.log_time_ns);
        Ok(reader)
    }

    fn load(&mut self, file: &Path) -> Result<(), BagError> {
        let bytes = std::fs::read(file).map_err(|source| BagError::Io {
            path: file.to_path_buf(),
            what: "reading bag",
            source,
        })?;
        if !bytes.starts_with(mcap::MAGIC) {
            return Err(BagError::NotMcap {
                path: file.to_path_buf(),
            });
        }
        if bytes.len() < 2 * mcap::MAGIC.len() || !bytes.ends_with(mcap::MAGIC) {
            return Err(BagError::Truncated {
                path: file.to_path_buf(),
            });
        }
        let corrupt = |source| BagError::Corrupt {
            path: file.to_path_buf(),
            source,
        };
        let stream = mcap::MessageStream::new(&bytes).map_err(corrupt)?;
        // (channel id) -> topic index, for this file.
        let mut by_channel: HashMap<u16, usize> = HashMap::new();
        for message in stream {
            let message = message.map_err(corrupt)?;
            let channel = &message.channel;
            let topic = match by_channel.get(&channel.id) {
                Some(&t) => t,
                None => {
                    let type_name = channel
                        .schema
                        .as_ref()
                        .map(|s| normalize_type_name(&s.name))
                        .unwrap_or_default();
                    let found = self.topics.iter().position(|t| {
                        t.info.name == channel.topic
                            && t.info.type_name == type_name
                            && t.encoding == channel.message_encoding
                    });
                    let t = match found {
                        Some(t) => t,
                        None => {
                            self.topics.push(Topic {
                                info: TopicInfo {
                                    name: channel.topic.clone(),
                                    type_name,
                                    message_count: 0,
                                },
                                encoding: channel.message_encoding.clone(),
                                file: file.to_path_buf(),
                            });
                            self.topics.len() - 1
                        }
                    };
                    by_channel.insert(channel.id, t);
                    t
                }
            };
            if let Some(t) = self.topics.get_mut(topic) {
                t.info.message_count += 1;
            }
            let start = self.arena.len();
            self.arena.extend_from_slice(&message.data);
            self.entries.push(Entry {
                topic,
                log_time_ns: message.log_time,
                data: start..self.arena.len(),
            });
        }
        Ok(())
    }

    /// The path opened.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Topics with their types and message counts, in order of first message.
    pub fn topics(&self) -> Vec<TopicInfo> {
        self.topics.iter().map(|t| t.info.clone()).collect()
    }

    /// All messages in log-time order. A message on a channel whose
    /// encoding is not `cdr` comes as
    /// [`BagError::UnsupportedMessageEncoding`]; skip it or stop.
    pub fn messages(&self) -> impl Iterator<Item = Result<RawMessage<'_>, BagError>> {
        self.entries.iter().map(move |e| {
            // Entries only ever index topics and arena ranges pushed with them.
            let topic = &self.topics[e.topic];
            if topic.encoding != "cdr" {
                return Err(BagError::UnsupportedMessageEncoding {
                    path: topic.file.clone(),
                    topic: topic.info.name.clone(),
                    encoding: topic.encoding.clone(),
                });
            }
            Ok(RawMessage {
                topic: &topic.info.name,
                type_name: &topic.info.type_name,
                log_time_ns: e.log_time_ns,
                data: &self.arena[e.data.clone()],
            })
        })
    }

    /// Decodes a message as `M`, after checking that its type is `M`'s
    /// (`pkg/Name` and `pkg/msg/Name` spellings both match).
    pub fn decode<M: RosMessage>(raw: &RawMessage) -> Result<M, BagError> {
        if normalize_type_name(raw.type_name) != M::TYPE_NAME {
            return Err(BagError::TypeMismatch {
                topic: raw.topic.to_string(),
                expected: M::TYPE_NAME,
                found: raw.type_name.to_string(),
            });
        }
        from_cdr(raw.data).map_err(|source| BagError::Decode {
            topic: raw.topic.to_string(),
            source,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bag::BagWriter;
    use crate::msgs::{Header, Image, TriggerResponse};

    fn image(stamp_ns: u64, v: u8) -> Image {
        Image {
            header: Header::new(stamp_ns, "cam"),
            height: 1,
            width: 1,
            encoding: "mono8".into(),
            is_bigendian: 0,
            step: 1,
            data: vec![v],
        }
    }

    #[test]
    fn round_trip_in_log_time_order() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.mcap");
        let mut w = BagWriter::create(&path).unwrap();
        w.write("/b", 20, &image(20, 2)).unwrap();
        w.write("/a", 10, &image(10, 1)).unwrap();
        w.write(
            "/r",
            15,
            &TriggerResponse {
                success: true,
                message: "x".into(),
            },
        )
        .unwrap();
        assert!(!path.exists());
        w.finish().unwrap();
        assert!(path.exists());
        assert!(!dir.path().join("a.mcap.partial").exists());

        let r = BagReader::open(&path).unwrap();
        let topics = r.topics();
        assert_eq!(topics.len(), 3);
        assert!(topics.contains(&TopicInfo {
            name: "/b".into(),
            type_name: "sensor_msgs/msg/Image".into(),
            message_count: 1
        }));
        let msgs: Vec<RawMessage> = r.messages().collect::<Result<_, _>>().unwrap();
        let times: Vec<u64> = msgs.iter().map(|m| m.log_time_ns).collect();
        assert_eq!(times, [10, 15, 20]);
        let first: Image = BagReader::decode(&msgs[0]).unwrap();
        assert_eq!(first, image(10, 1));
        let err = BagReader::decode::<Image>(&msgs[1]).unwrap_err();
        assert!(matches!(err, BagError::TypeMismatch { .. }), "{err}");
    }

    #[test]
    fn topic_keeps_its_type() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = BagWriter::create(&dir.path().join("a.mcap")).unwrap();
        w.write("/a", 1, &image(1, 1)).unwrap();
        let err = w.write("/a", 2, &TriggerResponse::default()).unwrap_err();
        assert!(matches!(err, BagError::TopicTypeConflict { .. }), "{err}");
    }

    #[test]
    fn directory_and_short_type_names() {
        let dir = tempfile::tempdir().unwrap();
        let bag = dir.path().join("bag");
        std::fs::create_dir(&bag).unwrap();
        let mut w = BagWriter::create(&bag.join("bag_0.mcap")).unwrap();
        w.write("/a", 1, &image(1, 7)).unwrap();
        w.finish().unwrap();
        std::fs::write(
            bag.join("metadata.yaml"),
            "rosbag2_bagfile_information:\n  relative_file_paths:\n    - bag_0.mcap\n  storage_identifier: mcap\n",
        )
        .unwrap();
        let r = BagReader::open(&bag).unwrap();
        let m = r.messages().next().unwrap().unwrap();
        let short = RawMessage {
            type_name: "sensor_msgs/Image",
            ..m
        };
        assert_eq!(BagReader::decode::<Image>(&short).unwrap().data, vec![7]);

        let empty = dir.path().join("empty");
        std::fs::create_dir(&empty).unwrap();
        assert!(matches!(
            BagReader::open(&empty),
            Err(BagError::NoMcapInDirectory { .. })
        ));
    }

    #[test]
    fn bad_files() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.mcap");
        let mut w = BagWriter::create(&path).unwrap();
        w.write("/a", 1, &image(1, 1)).unwrap();
        w.finish().unwrap();
        let bytes = std::fs::read(&path).unwrap();

        let cut = dir.path().join("cut.mcap");
        std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
        let err = BagReader::open(&cut).err().unwrap();
        assert!(matches!(err, BagError::Truncated { .. }), "{err}");
        assert!(err.to_string().contains("cut.mcap"), "{err}");

        let text = dir.path().join("t.mcap");
        std::fs::write(&text, b"hello").unwrap();
        assert!(matches!(BagReader::open(&text), Err(BagError::NotMcap { .. })));

        let missing = dir.path().join("none.mcap");
        let err = BagReader::open(&missing).err().unwrap();
        assert!(
            matches!(err, BagError::Io { .. }) && err.to_string().contains("none.mcap"),
            "{err}"
        );
    }

    #[test]
    fn dropped_writer_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.mcap");
        let mut w = BagWriter::create(&path).unwrap();
        w.write("/a", 1, &image(1, 1)).unwrap();
        assert!(dir.path().join("a.mcap.partial").exists());
        drop(w);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }
}
