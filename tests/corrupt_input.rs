//! Damaged input never takes the process down: seeded mutants of the bundled
//! bags (bit flips, overwritten byte runs, truncations, spliced slices, absurd
//! lengths written over record headers), each read in this process by the bag
//! reader and by `replay`'s load path, and mutants of serialized samples of
//! every message type decoded from CDR. Each must end in an error that names
//! the problem, a partial read that says where it stopped, or a whole read;
//! never a panic, an abort or an allocation out of proportion to the file.
//!
//! This binary counts every allocation (its global allocator): the peak of
//! live heap bytes over each mutant is measured against a bound, and a single
//! request past [`HARD_CAP`] is refused (the process then aborts, after
//! printing which mutant asked).
//!
//! A few hundred mutants run with the other tests; the thousands behind
//! `#[ignore]` run with `scripts/corruption` (or
//! `cargo test --test corrupt_input -- --ignored --nocapture`).
//! `TTOF_MUTANTS` (mutants per bag or per message type) and
//! `TTOF_MUTANT_SEED` change the draw.

use std::alloc::{GlobalAlloc, Layout, System};
use std::fmt;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Mutex;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use translucent_tof::bag::{record_length_limit, BagReader, RawMessage};
use translucent_tof::cli::{load_recording, TopicArgs};
use translucent_tof::image::{depth_mm, ir_counts, organized_cloud};
use translucent_tof::msgs::translucent_tof::TranslucencyEstimate;
use translucent_tof::msgs::{
    from_cdr, to_cdr, CameraInfo, Header, Image, PointCloud2, RosMessage, Time, TriggerRequest, TriggerResponse,
};
use translucent_tof::physics::ImageBuf;

/// A single allocation, or live bytes in all, past this is refused.
const HARD_CAP: usize = 2 << 30;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);
/// The mutant being read (for the message before an abort), `u64::MAX` for none.
static CURRENT: AtomicU64 = AtomicU64::new(u64::MAX);

struct Counting;

/// Writes `what` and the current mutant's number to stderr without allocating.
fn refuse(what: &[u8], size: usize) {
    let mut buf = [0u8; 160];
    let mut n = 0;
    let mut put = |b: &[u8]| {
        for &c in b {
            if n < buf.len() {
                buf[n] = c;
                n += 1;
            }
        }
    };
    let digits = |mut v: u64, out: &mut [u8; 20]| -> usize {
        let mut k = out.len();
        loop {
            k -= 1;
            out[k] = b'0' + (v % 10) as u8;
            v /= 10;
            if v == 0 {
                return k;
            }
        }
    };
    let mut d = [0u8; 20];
    put(b"corrupt_input: refused ");
    put(what);
    put(b" of ");
    let k = digits(size as u64, &mut d);
    put(&d[k..]);
    put(b" bytes while reading mutant ");
    let k = digits(CURRENT.load(Ordering::Relaxed), &mut d);
    put(&d[k..]);
    put(b"\n");
    // SAFETY: writes an initialized buffer to stderr.
    unsafe {
        libc::write(2, buf.as_ptr().cast(), n);
    }
}

// SAFETY: every call goes to the system allocator with the caller's layout;
// the counters only observe.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let size = layout.size();
        let live = LIVE.load(Ordering::Relaxed);
        if size > HARD_CAP || live.saturating_add(size) > HARD_CAP {
            refuse(b"an allocation", size);
            return std::ptr::null_mut();
        }
        let p = System.alloc(layout);
        if !p.is_null() {
            let now = LIVE.fetch_add(size, Ordering::Relaxed) + size;
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let size = layout.size();
        let live = LIVE.load(Ordering::Relaxed);
        if size > HARD_CAP || live.saturating_add(size) > HARD_CAP {
            refuse(b"a zeroed allocation", size);
            return std::ptr::null_mut();
        }
        let p = System.alloc_zeroed(layout);
        if !p.is_null() {
            let now = LIVE.fetch_add(size, Ordering::Relaxed) + size;
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout);
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let old = layout.size();
        let live = LIVE.load(Ordering::Relaxed);
        if new_size > HARD_CAP || (new_size > old && live.saturating_add(new_size - old) > HARD_CAP) {
            refuse(b"a reallocation", new_size);
            return std::ptr::null_mut();
        }
        let p = System.realloc(ptr, layout, new_size);
        if !p.is_null() {
            if new_size >= old {
                let now = LIVE.fetch_add(new_size - old, Ordering::Relaxed) + (new_size - old);
                PEAK.fetch_max(now, Ordering::Relaxed);
            } else {
                LIVE.fetch_sub(old - new_size, Ordering::Relaxed);
            }
        }
        p
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// The peak of live heap bytes while `f` runs, above what was live when it started.
fn peak_during<R>(f: impl FnOnce() -> R) -> (R, usize) {
    let base = LIVE.load(Ordering::Relaxed);
    PEAK.store(base, Ordering::Relaxed);
    let r = f();
    (r, PEAK.load(Ordering::Relaxed).saturating_sub(base))
}

/// One test at a time measures (the counters are the process's).
static SERIAL: Mutex<()> = Mutex::new(());

fn serial() -> std::sync::MutexGuard<'static, ()> {
    SERIAL.lock().unwrap_or_else(|e| e.into_inner())
}

fn mutants_per_item(default: usize) -> usize {
    std::env::var("TTOF_MUTANTS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn seed() -> u64 {
    std::env::var("TTOF_MUTANT_SEED")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(25)
}

fn bundled_bags() -> Vec<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("bags");
    let mut bags: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
        .collect();
    bags.sort();
    assert!(bags.len() >= 10, "bundled bags: {bags:?}");
    bags
}

/// What was done to the bytes.
#[derive(Debug, Clone)]
enum Mutation {
    /// Bits flipped at these bit positions.
    BitFlips(Vec<usize>),
    /// `len` bytes from `at` overwritten (random, all 0x00 or all 0xFF).
    ByteRun { at: usize, len: usize, fill: &'static str },
    /// Cut to `len` bytes.
    Truncate { len: usize },
    /// `len` bytes from `from` of `source` written over the bytes at `to`.
    Splice {
        source: String,
        from: usize,
        len: usize,
        to: usize,
    },
    /// A large little-endian integer of `width` bytes written at `at`, inside
    /// the first bytes of a record (its opcode, length or header).
    LengthBomb { at: usize, width: usize, value: u64 },
}

impl fmt::Display for Mutation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Mutation::BitFlips(bits) => write!(f, "bits flipped at {bits:?}"),
            Mutation::ByteRun { at, len, fill } => write!(f, "{len} bytes at {at} overwritten ({fill})"),
            Mutation::Truncate { len } => write!(f, "cut to {len} bytes"),
            Mutation::Splice { source, from, len, to } => {
                write!(f, "{len} bytes from {from} of {source} written at {to}")
            }
            Mutation::LengthBomb { at, width, value } => write!(f, "{width}-byte value {value:#x} written at {at}"),
        }
    }
}

/// Byte offsets where top-level records start (MCAP: magic, then opcode + u64 length + body).
fn record_starts(bytes: &[u8], magic_len: usize) -> Vec<usize> {
    let mut out = vec![];
    let mut pos = magic_len;
    while let Some(head) = bytes.get(pos..pos + 9) {
        out.push(pos);
        let mut len = [0u8; 8];
        len.copy_from_slice(&head[1..9]);
        let len = u64::from_le_bytes(len);
        match usize::try_from(len).ok().and_then(|l| (pos + 9).checked_add(l)) {
            Some(next) if next <= bytes.len() => pos = next,
            _ => break,
        }
    }
    out
}

const BOMBS: [u64; 7] = [
    u64::MAX,
    1 << 62,
    0x10f0_0000_0000_0009, // what the abort asked for, in kind
    1 << 40,
    u32::MAX as u64,
    1 << 31,
    0x7fff_ffff,
];

/// Draws a mutation of `bytes` (with `others` to splice from; `headers`:
/// offsets where length bombs go, e.g. record starts).
fn draw(rng: &mut ChaCha8Rng, bytes: &[u8], headers: &[usize], others: &[(String, &[u8])]) -> (Mutation, Vec<u8>) {
    let n = bytes.len();
    let mut out = bytes.to_vec();
    let m = match rng.random_range(0..5u32) {
        0 => {
            let k = rng.random_range(1..=8);
            let bits: Vec<usize> = (0..k).map(|_| rng.random_range(0..n * 8)).collect();
            for &b in &bits {
                out[b / 8] ^= 1 << (b % 8);
            }
            Mutation::BitFlips(bits)
        }
        1 => {
            let len = rng.random_range(1..=64.min(n));
            let at = rng.random_range(0..=n - len);
            let fill = match rng.random_range(0..3u32) {
                0 => {
                    rng.fill(&mut out[at..at + len]);
                    "random"
                }
                1 => {
                    out[at..at + len].fill(0);
                    "zeros"
                }
                _ => {
                    out[at..at + len].fill(0xff);
                    "0xff"
                }
            };
            Mutation::ByteRun { at, len, fill }
        }
        2 => {
            let len = rng.random_range(0..n);
            out.truncate(len);
            Mutation::Truncate { len }
        }
        3 => {
            let (name, src) = &others[rng.random_range(0..others.len())];
            let len = rng.random_range(1..=(src.len().min(n) / 4).max(1));
            let from = rng.random_range(0..=src.len() - len);
            let to = rng.random_range(0..=n - len);
            out[to..to + len].copy_from_slice(&src[from..from + len]);
            Mutation::Splice {
                source: name.clone(),
                from,
                len,
                to,
            }
        }
        _ => {
            let width = if rng.random_bool(0.5) { 8 } else { 4 };
            let value = BOMBS[rng.random_range(0..BOMBS.len())];
            let start = if headers.is_empty() {
                0
            } else {
                headers[rng.random_range(0..headers.len())]
            };
            let at = (start + rng.random_range(0..64)).min(n.saturating_sub(width));
            let w = width.min(n - at);
            out[at..at + w].copy_from_slice(&value.to_le_bytes()[..w]);
            Mutation::LengthBomb { at, width, value }
        }
    };
    (m, out)
}

/// Decodes a bag's message by its type, and an image's pixels as depth and IR.
fn decode_any(raw: &RawMessage) -> Result<(), String> {
    match raw.type_name {
        "sensor_msgs/msg/Image" => {
            let img: Image = BagReader::decode(raw).map_err(|e| chain(&e))?;
            let _ = depth_mm(&img);
            let _ = ir_counts(&img);
        }
        "sensor_msgs/msg/CameraInfo" => {
            BagReader::decode::<CameraInfo>(raw).map_err(|e| chain(&e))?;
        }
        "sensor_msgs/msg/PointCloud2" => {
            BagReader::decode::<PointCloud2>(raw).map_err(|e| chain(&e))?;
        }
        "translucent_tof_msgs/msg/TranslucencyEstimate" => {
            BagReader::decode::<TranslucencyEstimate>(raw).map_err(|e| chain(&e))?;
        }
        _ => {}
    }
    Ok(())
}

/// The chain of an error, as the binary prints it.
fn chain(e: &(dyn std::error::Error + 'static)) -> String {
    let mut s = e.to_string();
    let mut cur = e.source();
    while let Some(c) = cur {
        s.push_str(": ");
        s.push_str(&c.to_string());
        cur = c.source();
    }
    s
}

/// How a mutant's reads ended.
#[derive(Debug, Default)]
struct Tally {
    mutants: usize,
    /// Read to its end (the damage was where the reader does not look, or harmless).
    whole: usize,
    /// Read up to a point, which it names.
    partial: usize,
    /// Refused by the bag reader with an error.
    refused: usize,
    /// Messages in a readable bag that did not decode (each a clear error).
    undecodable_messages: usize,
    /// replay's load path: Ok, or refused with an error.
    load_ok: usize,
    load_err: usize,
    /// The largest peak of live heap bytes over one mutant, and its bound.
    peak: usize,
    peak_bound: usize,
    /// Error kinds seen (first words), with counts.
    kinds: std::collections::BTreeMap<String, usize>,
}

/// Reads one mutant with the bag reader (every message decoded) and with
/// replay's load path; returns a failure in words.
fn read_mutant(path: &Path, name: &str, tally: &mut Tally) -> Result<(), String> {
    let opened =
        catch_unwind(AssertUnwindSafe(|| BagReader::open(path))).map_err(|_| "the bag reader panicked".to_string())?;
    match opened {
        Ok(reader) => {
            if reader.stops().is_empty() {
                tally.whole += 1;
            } else {
                tally.partial += 1;
                for s in reader.stops() {
                    let t = s.to_string();
                    if !(t.contains(name) && t.contains("read stopped at byte")) {
                        return Err(format!("a partial read that does not say where: {t}"));
                    }
                }
            }
            for raw in reader.messages() {
                let Ok(raw) = raw else { continue };
                let decoded =
                    catch_unwind(AssertUnwindSafe(|| decode_any(&raw))).map_err(|_| "decoding panicked".to_string())?;
                if let Err(e) = decoded {
                    if !e.contains(raw.topic) {
                        return Err(format!("a decoding error that does not name its topic: {e}"));
                    }
                    tally.undecodable_messages += 1;
                }
            }
        }
        Err(e) => {
            tally.refused += 1;
            let text = chain(&e);
            if !text.contains(name) {
                return Err(format!("an error that does not name the file: {text}"));
            }
            let kind: String = e.to_string().replace(&path.display().to_string(), "BAG");
            let kind: String = kind
                .split(|c: char| c.is_ascii_digit())
                .next()
                .unwrap_or("")
                .to_string();
            *tally.kinds.entry(kind).or_insert(0) += 1;
        }
    }
    let loaded = catch_unwind(AssertUnwindSafe(|| load_recording(path, &TopicArgs::default())))
        .map_err(|_| "replay's load path panicked".to_string())?;
    match loaded {
        Ok(rec) => {
            tally.load_ok += 1;
            if rec.frames.is_empty() {
                return Err("replay's load path returned no frames without an error".into());
            }
        }
        Err(e) => {
            tally.load_err += 1;
            let text = format!("{e:#}");
            if text.len() < 20 {
                return Err(format!("an error too terse to act on: {text}"));
            }
        }
    }
    Ok(())
}

fn bag_mutants(per_bag: usize) {
    let _guard = serial();
    let bags = bundled_bags();
    let originals: Vec<(String, Vec<u8>)> = bags
        .iter()
        .map(|p| {
            (
                p.file_name().unwrap().to_string_lossy().into_owned(),
                std::fs::read(p).unwrap(),
            )
        })
        .collect();
    let others: Vec<(String, &[u8])> = originals.iter().map(|(n, b)| (n.clone(), b.as_slice())).collect();
    let dir = tempfile::tempdir().unwrap();
    let mut tally = Tally::default();
    let mut failures = vec![];
    let mut number = 0u64;
    for (k, (name, bytes)) in originals.iter().enumerate() {
        // The intact bag, read the same way, gives the scale of the bound.
        let path = dir.path().join(name);
        std::fs::write(&path, bytes).unwrap();
        let mut intact = Tally::default();
        let (r, intact_peak) = peak_during(|| read_mutant(&path, name, &mut intact));
        r.unwrap();
        assert_eq!((intact.whole, intact.load_ok), (1, 1), "{name} itself does not read");
        let headers = record_starts(bytes, 8);
        let mut rng = ChaCha8Rng::seed_from_u64(seed().wrapping_mul(1_000_003).wrapping_add(k as u64));
        for _ in 0..per_bag {
            let (m, mutated) = draw(&mut rng, bytes, &headers, &others);
            std::fs::write(&path, &mutated).unwrap();
            // Twice the intact read, plus the longest record the reader lets the file declare.
            let bound = 2 * intact_peak + record_length_limit(mutated.len());
            CURRENT.store(number, Ordering::Relaxed);
            let (r, peak) = peak_during(|| read_mutant(&path, name, &mut tally));
            CURRENT.store(u64::MAX, Ordering::Relaxed);
            tally.mutants += 1;
            tally.peak = tally.peak.max(peak);
            tally.peak_bound = tally.peak_bound.max(bound);
            if let Err(e) = r {
                failures.push(format!("mutant {number} of {name} ({m}): {e}"));
            } else if peak > bound {
                failures.push(format!(
                    "mutant {number} of {name} ({m}): peak heap {peak} bytes, bound {bound}"
                ));
            }
            number += 1;
        }
    }
    eprintln!(
        "bag mutants: {} ({} bags, seed {}): {} read whole, {} read in part, {} refused by the bag reader; {} messages of readable mutants did not decode; replay's load path: {} loaded, {} refused; peak live heap over one mutant {:.1} MiB (largest bound {:.1} MiB)",
        tally.mutants,
        originals.len(),
        seed(),
        tally.whole,
        tally.partial,
        tally.refused,
        tally.undecodable_messages,
        tally.load_ok,
        tally.load_err,
        tally.peak as f64 / (1 << 20) as f64,
        tally.peak_bound as f64 / (1 << 20) as f64
    );
    for (kind, n) in &tally.kinds {
        eprintln!("  {n:5} refused: {kind}");
    }
    assert!(
        failures.is_empty(),
        "{} failures:\n{}",
        failures.len(),
        failures.join("\n")
    );
    // Every outcome occurs: the draw reaches the reader's paths.
    assert!(tally.whole > 0 && tally.partial > 0 && tally.refused > 0, "{tally:?}");
}

/// Mutants of one message type's serialized sample, decoded; `after` runs on what decodes.
fn cdr_mutants<M: RosMessage>(sample: &M, per_type: usize, k: u64, after: impl Fn(&M), tally: &mut CdrTally) {
    let bytes = to_cdr(sample).unwrap();
    let back: M = from_cdr(&bytes).unwrap();
    after(&back);
    // Length bombs anywhere in the body, on 4-byte boundaries (where CDR puts lengths).
    let aligned: Vec<usize> = (4..bytes.len()).step_by(4).collect();
    let others = [(M::TYPE_NAME.to_string(), bytes.as_slice())];
    let mut rng = ChaCha8Rng::seed_from_u64(seed().wrapping_mul(7_919).wrapping_add(k));
    for j in 0..per_type {
        let (m, mutated) = draw(&mut rng, &bytes, &aligned, &others);
        let bound = 4 * bytes.len() + (2 << 20);
        let (r, peak) = peak_during(|| {
            catch_unwind(AssertUnwindSafe(|| match from_cdr::<M>(&mutated) {
                Ok(msg) => {
                    after(&msg);
                    Ok(())
                }
                Err(e) => Err(e.to_string()),
            }))
        });
        tally.mutants += 1;
        tally.peak = tally.peak.max(peak);
        match r {
            Err(_) => tally
                .failures
                .push(format!("{} mutant {j} ({m}): panicked", M::TYPE_NAME)),
            Ok(Ok(())) => tally.decoded += 1,
            Ok(Err(e)) => {
                tally.refused += 1;
                if !e.starts_with(M::TYPE_NAME) {
                    tally.failures.push(format!(
                        "{} mutant {j} ({m}): error without the type: {e}",
                        M::TYPE_NAME
                    ));
                }
            }
        }
        if peak > bound {
            tally.failures.push(format!(
                "{} mutant {j} ({m}): peak heap {peak} bytes for {} bytes of CDR",
                M::TYPE_NAME,
                bytes.len()
            ));
        }
    }
}

#[derive(Debug, Default)]
struct CdrTally {
    mutants: usize,
    decoded: usize,
    refused: usize,
    peak: usize,
    failures: Vec<String>,
}

fn all_cdr_mutants(per_type: usize) {
    let _guard = serial();
    let bag = Path::new(env!("CARGO_MANIFEST_DIR")).join("bags/document_holder.mcap");
    let reader = BagReader::open(&bag).unwrap();
    let (mut depth, mut ir, mut info) = (None, None, None);
    for raw in reader.messages() {
        let raw = raw.unwrap();
        match raw.topic {
            "/tof/depth/image_raw" if depth.is_none() => depth = Some(BagReader::decode::<Image>(&raw).unwrap()),
            "/tof/ir/image_raw" if ir.is_none() => ir = Some(BagReader::decode::<Image>(&raw).unwrap()),
            "/tof/depth/camera_info" if info.is_none() => info = Some(BagReader::decode::<CameraInfo>(&raw).unwrap()),
            _ => {}
        }
    }
    let (depth, ir, info) = (depth.unwrap(), ir.unwrap(), info.unwrap());
    let header = Header::new(1_700_000_000_123_456_789, "tof_optical_frame");
    let xyz = ImageBuf::from_vec(4, 3, (0..12).map(|i| [i as f32, 0.5, 1.0]).collect()).unwrap();
    let inten = ImageBuf::from_vec(4, 3, vec![100.0; 12]).unwrap();
    let mask = ImageBuf::from_vec(4, 3, (0..12).map(|i| i % 2 == 0).collect()).unwrap();
    let cloud = organized_cloud(&header, &xyz, &inten, &mask, &ImageBuf::filled(4, 3, 0.01f32));
    let estimate = TranslucencyEstimate {
        header: header.clone(),
        xi: 0.65,
        xi_lower: 0.63,
        xi_upper: 0.67,
        method: "one_material".into(),
        translucent_pixels: 1234,
        fit_residual_mm: 0.5,
        frames_pooled: 8,
        region_id: 2,
        region_pixels: 900,
        opaque: false,
        material: "folder".into(),
        class_probability: 0.9,
    };
    let image_after = |m: &Image| {
        let _ = depth_mm(m);
        let _ = ir_counts(m);
    };
    let mut t = CdrTally::default();
    cdr_mutants(&depth, per_type, 1, image_after, &mut t);
    cdr_mutants(&ir, per_type, 2, image_after, &mut t);
    cdr_mutants(&info, per_type, 3, |_| {}, &mut t);
    cdr_mutants(&cloud, per_type, 4, |_| {}, &mut t);
    cdr_mutants(&cloud.fields[0], per_type, 5, |_| {}, &mut t);
    cdr_mutants(&info.roi, per_type, 6, |_| {}, &mut t);
    cdr_mutants(&header, per_type, 7, |_| {}, &mut t);
    cdr_mutants(&Time { sec: 5, nanosec: 6 }, per_type, 8, |_| {}, &mut t);
    cdr_mutants(&TriggerRequest::default(), per_type, 9, |_| {}, &mut t);
    cdr_mutants(
        &TriggerResponse {
            success: true,
            message: "latched 3 frames".into(),
        },
        per_type,
        10,
        |_| {},
        &mut t,
    );
    cdr_mutants(&estimate, per_type, 11, |_| {}, &mut t);
    eprintln!(
        "CDR mutants: {} (11 message types, seed {}): {} decoded, {} refused with an error naming the type; peak live heap over one mutant {:.2} MiB",
        t.mutants,
        seed(),
        t.decoded,
        t.refused,
        t.peak as f64 / (1 << 20) as f64
    );
    assert!(
        t.failures.is_empty(),
        "{} failures:\n{}",
        t.failures.len(),
        t.failures.join("\n")
    );
    assert!(t.decoded > 0 && t.refused > 0, "{t:?}");
}

#[test]
fn bag_mutants_read_to_an_error_or_a_stated_stop() {
    bag_mutants(mutants_per_item(24).min(24));
}

#[test]
fn cdr_mutants_of_every_message_type_decode_or_fail_clearly() {
    all_cdr_mutants(mutants_per_item(30).min(30));
}

#[test]
#[ignore = "thousands of mutants: scripts/corruption"]
fn many_bag_mutants() {
    bag_mutants(mutants_per_item(300));
}

#[test]
#[ignore = "thousands of mutants: scripts/corruption"]
fn many_cdr_mutants() {
    all_cdr_mutants(mutants_per_item(400));
}
