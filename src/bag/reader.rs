//! [`BagReader`]: a ROS 2 MCAP bag in memory, messages in log-time order.

use std::collections::{BTreeMap, HashMap};
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
    stops: Vec<ReadStop>,
    metadata: Vec<MetadataRecord>,
}

/// The longest record (or chunk, compressed or not) a file of `file_len`
/// bytes is allowed to declare: 32 times the file (zstd rarely packs ROS
/// messages tighter), at least 64 MiB, at most 4 GiB. A corrupt length past it
/// is an error before anything is allocated for it.
pub fn record_length_limit(file_len: usize) -> usize {
    const FLOOR: usize = 64 << 20;
    const CEILING: u64 = 4 << 30;
    let limit = file_len.saturating_mul(32).max(FLOOR);
    usize::try_from(CEILING).map_or(limit, |c| limit.min(c))
}

/// Why a file's records could not be read.
#[derive(Debug, thiserror::Error)]
pub enum McapProblem {
    /// What the MCAP parser said.
    #[error(transparent)]
    Mcap(#[from] mcap::McapError),
    /// A schema, channel or message record whose fields do not fit it.
    #[error("{0}")]
    Record(String),
}

/// A message record's fields, borrowing its data.
struct MessageRecord<'a> {
    channel_id: u16,
    log_time: u64,
    data: &'a [u8],
}

/// Little-endian fields off the front of a record, each checked against what is left.
struct Fields<'a> {
    what: &'static str,
    rest: &'a [u8],
}

impl<'a> Fields<'a> {
    fn take(&mut self, n: usize, field: &str) -> Result<&'a [u8], McapProblem> {
        if n > self.rest.len() {
            return Err(McapProblem::Record(format!(
                "{} record: {field} needs {n} bytes, {} left in the record",
                self.what,
                self.rest.len()
            )));
        }
        let (head, tail) = self.rest.split_at(n);
        self.rest = tail;
        Ok(head)
    }

    fn array<const N: usize>(&mut self, field: &str) -> Result<[u8; N], McapProblem> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N, field)?);
        Ok(a)
    }

    fn u16(&mut self, field: &str) -> Result<u16, McapProblem> {
        self.array(field).map(u16::from_le_bytes)
    }

    fn u64(&mut self, field: &str) -> Result<u64, McapProblem> {
        self.array(field).map(u64::from_le_bytes)
    }

    /// A `u32` byte length and that many bytes.
    fn prefixed(&mut self, field: &str) -> Result<&'a [u8], McapProblem> {
        let n = u32::from_le_bytes(self.array(field)?);
        self.take(usize::try_from(n).unwrap_or(usize::MAX), field)
    }

    fn string(&mut self, field: &str) -> Result<String, McapProblem> {
        let b = self.prefixed(field)?;
        std::str::from_utf8(b)
            .map(str::to_string)
            .map_err(|_| McapProblem::Record(format!("{} record: {field} is not UTF-8", self.what)))
    }
}

/// An MCAP metadata record: its name and key-value pairs.
pub type MetadataRecord = (String, BTreeMap<String, String>);

/// A metadata record's name and its map (`u32` byte length, then key and value strings).
fn parse_metadata(data: &[u8]) -> Result<MetadataRecord, McapProblem> {
    let mut f = Fields {
        what: "metadata",
        rest: data,
    };
    let name = f.string("name")?;
    let mut map = Fields {
        what: "metadata",
        rest: f.prefixed("map")?,
    };
    let mut pairs = BTreeMap::new();
    while !map.rest.is_empty() {
        let key = map.string("key")?;
        pairs.insert(key, map.string("value")?);
    }
    Ok((name, pairs))
}

/// The maps a file's records fill as they are read.
#[derive(Default)]
struct Definitions {
    schemas: HashMap<u16, String>,
    channels: HashMap<u16, (String, String, String)>,
    metadata: Vec<MetadataRecord>,
}

/// Takes what the reader needs from one record: schemas' type names,
/// channels and metadata into `defs`, a message out; other records are skipped.
fn parse_record<'a>(
    opcode: u8,
    data: &'a [u8],
    defs: &mut Definitions,
) -> Result<Option<MessageRecord<'a>>, McapProblem> {
    use mcap::records::op;
    let Definitions {
        schemas,
        channels,
        metadata,
    } = defs;
    match opcode {
        op::METADATA => {
            metadata.push(parse_metadata(data)?);
            Ok(None)
        }
        op::SCHEMA => {
            let mut f = Fields {
                what: "schema",
                rest: data,
            };
            let id = f.u16("id")?;
            let name = f.string("name")?;
            f.string("encoding")?;
            f.prefixed("data")?;
            if id == 0 {
                return Err(McapProblem::Mcap(mcap::McapError::InvalidSchemaId));
            }
            match schemas.get(&id) {
                Some(known) if *known != name => Err(McapProblem::Mcap(mcap::McapError::ConflictingSchemas(name))),
                _ => {
                    schemas.insert(id, name);
                    Ok(None)
                }
            }
        }
        op::CHANNEL => {
            let mut f = Fields {
                what: "channel",
                rest: data,
            };
            let id = f.u16("id")?;
            let schema_id = f.u16("schema id")?;
            let topic = f.string("topic")?;
            let encoding = f.string("message encoding")?;
            f.prefixed("metadata")?;
            let schema = match schema_id {
                0 => String::new(),
                s => schemas
                    .get(&s)
                    .cloned()
                    .ok_or_else(|| McapProblem::Mcap(mcap::McapError::UnknownSchema(topic.clone(), s)))?,
            };
            let channel = (topic, encoding, schema);
            match channels.get(&id) {
                Some(known) if *known != channel => {
                    Err(McapProblem::Mcap(mcap::McapError::ConflictingChannels(channel.0)))
                }
                _ => {
                    channels.insert(id, channel);
                    Ok(None)
                }
            }
        }
        op::MESSAGE => {
            let mut f = Fields {
                what: "message",
                rest: data,
            };
            let channel_id = f.u16("channel id")?;
            f.take(4, "sequence")?;
            let log_time = f.u64("log time")?;
            f.u64("publish time")?;
            if !channels.contains_key(&channel_id) {
                return Err(McapProblem::Record(format!(
                    "message record on channel {channel_id}, which no channel record defined"
                )));
            }
            Ok(Some(MessageRecord {
                channel_id,
                log_time,
                data: f.rest,
            }))
        }
        _ => Ok(None),
    }
}

/// Where a file's reading stopped before its end (a recording cut short by a
/// crash, or damaged), and why.
#[derive(Debug)]
pub struct ReadStop {
    /// File concerned.
    pub file: PathBuf,
    /// Bytes of the file read when the reader stopped.
    pub offset: u64,
    /// The file's length.
    pub len: u64,
    /// Messages read from this file before the stop.
    pub messages_kept: u64,
    /// Latest log time among them, ns.
    pub last_log_time_ns: Option<u64>,
    /// What stopped it.
    pub source: McapProblem,
}

impl ReadStop {
    fn into_error(self) -> BagError {
        if matches!(self.source, McapProblem::Mcap(mcap::McapError::UnexpectedEof)) {
            BagError::Truncated { path: self.file }
        } else {
            BagError::Corrupt {
                path: self.file,
                offset: self.offset,
                len: self.len,
                source: self.source,
            }
        }
    }
}

impl std::fmt::Display for ReadStop {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let why = match self.source {
            McapProblem::Mcap(mcap::McapError::UnexpectedEof) => {
                "the file ends in the middle of a record (cut short)".to_string()
            }
            ref e => e.to_string(),
        };
        write!(
            f,
            "{}: read stopped at byte {} of {}: {why}; kept the {} messages before it",
            self.file.display(),
            self.offset,
            self.len,
            self.messages_kept
        )?;
        if let Some(t) = self.last_log_time_ns {
            write!(f, " (up to log time {t} ns)")?;
        }
        Ok(())
    }
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
            stops: Vec::new(),
            metadata: Vec::new(),
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
        let options = mcap::sans_io::LinearReaderOptions::default()
            .with_record_length_limit(record_length_limit(bytes.len()))
            // A chunk's records are checked against its CRC before any is taken.
            .with_prevalidate_chunk_crcs(true);
        let mut stream = mcap::sans_io::LinearReader::new_with_options(options);
        let mut rest: &[u8] = &bytes;
        let first_entry = self.entries.len();
        // The records this reader needs are parsed here, every length checked against the
        // record's own (mcap 0.26's parser reserves a string's declared length first).
        let mut defs = Definitions::default();
        // (channel id) -> topic index, for this file.
        let mut by_channel: HashMap<u16, usize> = HashMap::new();
        while let Some(event) = stream.next_event() {
            let record = match event {
                Ok(mcap::sans_io::LinearReadEvent::ReadRequest(need)) => {
                    // Never more than the file has left: a corrupt length asks for no more.
                    let n = need.min(rest.len());
                    let (head, tail) = rest.split_at(n);
                    stream.insert(n).copy_from_slice(head);
                    stream.notify_read(n);
                    rest = tail;
                    continue;
                }
                Ok(mcap::sans_io::LinearReadEvent::Record { opcode, data }) => parse_record(opcode, data, &mut defs),
                Err(e) => Err(McapProblem::Mcap(e)),
            };
            let message = match record {
                Ok(Some(m)) => m,
                Ok(None) => continue,
                Err(source) => {
                    let offset = (bytes.len() - rest.len()) as u64;
                    let kept = (self.entries.len() - first_entry) as u64;
                    let stop = ReadStop {
                        file: file.to_path_buf(),
                        offset,
                        len: bytes.len() as u64,
                        messages_kept: kept,
                        last_log_time_ns: self.entries[first_entry..].iter().map(|e| e.log_time_ns).max(),
                        source,
                    };
                    if kept == 0 {
                        return Err(stop.into_error());
                    }
                    self.stops.push(stop);
                    self.metadata.append(&mut defs.metadata);
                    return Ok(());
                }
            };
            let Some((topic_name, encoding, schema_name)) = defs.channels.get(&message.channel_id) else {
                continue;
            };
            let topic = match by_channel.get(&message.channel_id) {
                Some(&t) => t,
                None => {
                    let type_name = normalize_type_name(schema_name);
                    let found = self.topics.iter().position(|t| {
                        t.info.name == *topic_name && t.info.type_name == type_name && t.encoding == *encoding
                    });
                    let t = match found {
                        Some(t) => t,
                        None => {
                            self.topics.push(Topic {
                                info: TopicInfo {
                                    name: topic_name.clone(),
                                    type_name,
                                    message_count: 0,
                                },
                                encoding: encoding.clone(),
                                file: file.to_path_buf(),
                            });
                            self.topics.len() - 1
                        }
                    };
                    by_channel.insert(message.channel_id, t);
                    t
                }
            };
            if let Some(t) = self.topics.get_mut(topic) {
                t.info.message_count += 1;
            }
            let start = self.arena.len();
            self.arena.extend_from_slice(message.data);
            self.entries.push(Entry {
                topic,
                log_time_ns: message.log_time,
                data: start..self.arena.len(),
            });
        }
        self.metadata.append(&mut defs.metadata);
        Ok(())
    }

    /// Where reading stopped short of a file's end, one entry per such file:
    /// the messages before that point are read, the rest of the file is not.
    /// Empty when every file was read to its end magic.
    pub fn stops(&self) -> &[ReadStop] {
        &self.stops
    }

    /// The metadata records of the bag's files, in the order read.
    pub fn metadata(&self) -> &[MetadataRecord] {
        &self.metadata
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
    fn metadata_records_are_read() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.mcap");
        let mut w = BagWriter::create(&path).unwrap();
        let pairs = BTreeMap::from([("k".to_string(), "v".to_string()), ("a".to_string(), String::new())]);
        w.write_metadata("rec", pairs.clone()).unwrap();
        w.write("/a", 1, &image(1, 1)).unwrap();
        w.finish().unwrap();
        let r = BagReader::open(&path).unwrap();
        assert_eq!(r.metadata(), [("rec".to_string(), pairs)]);
        assert_eq!(r.messages().count(), 1);
        // A map whose length runs past the record is a record error, not a panic.
        assert!(parse_metadata(&[1, 0, 0, 0, b'x', 200, 0, 0, 0]).is_err());
        assert!(parse_metadata(&[1, 0, 0, 0, b'x', 4, 0, 0, 0, 9, 0, 0, 0]).is_err());
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

        // Cut after its one message (in the index and summary): the message, and a stop.
        let cut = dir.path().join("cut.mcap");
        std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
        let r = BagReader::open(&cut).unwrap();
        assert_eq!((r.messages().count(), r.stops().len()), (1, 1));
        // Cut before it: an error.
        std::fs::write(&cut, &bytes[..20]).unwrap();
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

    /// A bag of `n` incompressible 64 KiB images (several zstd chunks).
    fn big_bag(path: &Path, n: u64) {
        let mut w = BagWriter::create(path).unwrap();
        let mut x = 0x2545_f491_4f6c_dd1du64;
        for s in 0..n {
            let data = (0..65_536)
                .map(|_| {
                    x ^= x << 13;
                    x ^= x >> 7;
                    x ^= x << 17;
                    x as u8
                })
                .collect();
            let img = Image {
                width: 65_536,
                step: 65_536,
                data,
                ..image(s + 1, 0)
            };
            w.write("/a", s + 1, &img).unwrap();
        }
        w.finish().unwrap();
    }

    #[test]
    fn a_bag_cut_short_keeps_its_complete_chunks_and_says_where_it_stopped() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.mcap");
        big_bag(&path, 40);
        let bytes = std::fs::read(&path).unwrap();
        let whole = BagReader::open(&path).unwrap();
        assert!(whole.stops().is_empty());
        assert_eq!(whole.messages().count(), 40);

        let cut = dir.path().join("cut.mcap");
        std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
        let r = BagReader::open(&cut).unwrap();
        let kept: Vec<u64> = r.messages().map(|m| m.unwrap().log_time_ns).collect();
        assert!(!kept.is_empty() && kept.len() < 40, "{} messages", kept.len());
        // A prefix of the recording, each message whole.
        assert_eq!(kept, (1..=kept.len() as u64).collect::<Vec<_>>());
        for m in r.messages() {
            assert_eq!(BagReader::decode::<Image>(&m.unwrap()).unwrap().data.len(), 65_536);
        }
        let [stop] = r.stops() else {
            panic!("one stop expected: {:?}", r.stops())
        };
        assert!(
            matches!(stop.source, McapProblem::Mcap(mcap::McapError::UnexpectedEof)),
            "{stop}"
        );
        assert_eq!(stop.len, (bytes.len() * 2 / 3) as u64);
        assert_eq!(stop.messages_kept, kept.len() as u64);
        let text = stop.to_string();
        assert!(
            text.contains("cut.mcap")
                && text.contains("cut short")
                && text.contains(&format!("kept the {} messages", kept.len())),
            "{text}"
        );
    }

    #[test]
    fn a_damaged_chunk_stops_the_read_before_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.mcap");
        big_bag(&path, 40);
        let mut bytes = std::fs::read(&path).unwrap();
        // One byte in the middle of the file: inside a chunk after the first.
        let at = bytes.len() / 2;
        bytes[at] ^= 0x40;
        let bad = dir.path().join("bad.mcap");
        std::fs::write(&bad, &bytes).unwrap();
        let r = BagReader::open(&bad).unwrap();
        let [stop] = r.stops() else {
            panic!("one stop expected: {:?}", r.stops())
        };
        assert!(stop.offset > at as u64 && stop.messages_kept > 0, "{stop}");
        assert_eq!(r.messages().count() as u64, stop.messages_kept);
        // Damage before the first message is an error naming the place.
        let mut early = std::fs::read(&path).unwrap();
        // Past the magic and the header record: the first chunk, which holds the schema,
        // the channel and the first messages.
        let header_len = u64::from_le_bytes(early[9..17].try_into().unwrap()) as usize;
        early[17 + header_len + 200] ^= 0x40;
        std::fs::write(&bad, &early).unwrap();
        let err = BagReader::open(&bad).err().unwrap();
        assert!(matches!(err, BagError::Corrupt { .. }), "{err}");
        assert!(
            err.to_string().contains("bad.mcap") && err.to_string().contains("at byte"),
            "{err}"
        );
    }

    #[test]
    fn the_record_length_limit_follows_the_file() {
        assert_eq!(record_length_limit(0), 64 << 20);
        assert_eq!(record_length_limit(10 << 20), 320 << 20);
        assert_eq!(record_length_limit(usize::MAX), 4 << 30);
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
