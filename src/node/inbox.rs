//! Between the DDS callbacks and the processing thread: samples that did not
//! decode and images too large for the camera dropped and counted
//! ([`Intake`]), depth and IR paired by exact stamp, then a bounded queue that
//! drops the oldest frame when the processing falls behind, and an unbounded
//! lane for service commands (never dropped).

use std::collections::{BTreeMap, VecDeque};
use std::sync::{Condvar, Mutex};
use std::time::Duration;

use super::core::{DropCause, DropCounters};
use crate::msgs::{CameraInfo, Image};

/// Most pixels of a camera the node takes (2048 x 2048): the background
/// latch and the pipeline hold some 50 bytes a pixel, allocated when the
/// camera_info comes, before any image has shown that size.
pub const MAX_CAMERA_PIXELS: u64 = 2048 * 2048;

/// Most bytes of image data the node takes before any camera_info has come
/// (a 2048 x 2048 `32FC1` image with rows padded to twice their length);
/// once one has, an image may not have more pixels than it says, nor more
/// data than its own `step x height`.
pub const MAX_IMAGE_BYTES: usize = 32 << 20;

/// Why an input was refused before pairing, for the log line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Refused {
    /// The cause it is counted under.
    pub cause: DropCause,
    /// What was wrong with it.
    pub detail: String,
}

/// The first check of every sample the node receives, before pairing: a
/// sample that did not decode ([`DropCause::Malformed`]) or an image larger
/// than the camera ([`DropCause::Oversized`]) is dropped here, counted by
/// cause, and logged the first time its cause is seen.
#[derive(Debug, Default)]
pub struct Intake {
    /// Samples dropped here, by cause.
    pub drops: DropCounters,
}

impl Intake {
    /// A sample on `topic` that could not be read (`error` as the DDS layer
    /// gave it): counted as malformed; the first one is logged.
    pub fn unreadable(&mut self, topic: &str, error: &dyn std::fmt::Display) {
        self.refuse(
            topic,
            Refused {
                cause: DropCause::Malformed,
                detail: format!("sample did not decode: {error}"),
            },
        );
    }

    /// A camera_info on `topic`: `Some` to pass it on, `None` when it
    /// describes a camera larger than [`MAX_CAMERA_PIXELS`] (counted as
    /// oversized; the first logged).
    pub fn camera_info(&mut self, topic: &str, info: CameraInfo) -> Option<CameraInfo> {
        let pixels = u64::from(info.width) * u64::from(info.height);
        if pixels <= MAX_CAMERA_PIXELS {
            return Some(info);
        }
        self.refuse(
            topic,
            Refused {
                cause: DropCause::Oversized,
                detail: format!(
                    "camera_info for a {}x{} camera ({pixels} pixels; the node takes at most {MAX_CAMERA_PIXELS})",
                    info.width, info.height
                ),
            },
        );
        None
    }

    /// An image on `topic`: `Some` to pass it on, `None` when it was
    /// dropped (counted; the first of its cause logged).
    pub fn image(&mut self, topic: &str, img: Image, info: Option<&CameraInfo>) -> Option<Image> {
        match check_size(&img, info) {
            Ok(()) => Some(img),
            Err(r) => {
                self.refuse(topic, r);
                None
            }
        }
    }

    fn refuse(&mut self, topic: &str, r: Refused) {
        if self.drops.record(r.cause) {
            log::warn!(
                "{topic}: {}; dropped ({}); further {:?} drops are counted",
                r.detail,
                r.cause.advice(),
                r.cause
            );
        }
    }
}

/// Whether an image is within what the node takes: at most
/// [`MAX_IMAGE_BYTES`] of data; with `info`, no more pixels than it says and
/// no more data than the image's own `step x height`; and not less data than that.
pub fn check_size(img: &Image, info: Option<&CameraInfo>) -> Result<(), Refused> {
    let oversized = |detail: String| Refused {
        cause: DropCause::Oversized,
        detail,
    };
    let (w, h) = (u64::from(img.width), u64::from(img.height));
    if img.data.len() > MAX_IMAGE_BYTES {
        return Err(oversized(format!(
            "{}x{} image with {} bytes of data (the node takes at most {MAX_IMAGE_BYTES})",
            w,
            h,
            img.data.len()
        )));
    }
    if let Some(info) = info {
        let (cw, ch) = (u64::from(info.width), u64::from(info.height));
        if w * h > cw * ch {
            return Err(oversized(format!(
                "{w}x{h} image from a {cw}x{ch} camera (camera_info)"
            )));
        }
        let declared = u64::from(img.step) * h;
        if img.data.len() as u64 > declared {
            return Err(oversized(format!(
                "{w}x{h} image with {} bytes of data, more than its step x height = {declared}",
                img.data.len()
            )));
        }
    }
    // A truncated image: refused here, by its own cause, rather than left to wait for a
    // partner that pairs it with a frame nothing can read.
    let declared = u64::from(img.step) * h;
    if (img.data.len() as u64) < declared {
        return Err(Refused {
            cause: DropCause::BadImage,
            detail: format!(
                "{w}x{h} image truncated: {} bytes of data, less than its step x height = {declared}",
                img.data.len()
            ),
        });
    }
    Ok(())
}

/// Pairs depth and IR images by exact header stamp. Each side keeps at most
/// `capacity` images waiting; an image evicted without its partner is unpaired.
#[derive(Debug)]
pub struct StampPairer {
    capacity: usize,
    depth: BTreeMap<u64, Image>,
    ir: BTreeMap<u64, Image>,
    /// Images that never found their partner.
    pub unpaired: u64,
}

impl StampPairer {
    /// A pairer holding at most `capacity` unmatched images per side.
    pub fn new(capacity: usize) -> Self {
        Self {
            capacity: capacity.max(1),
            depth: BTreeMap::new(),
            ir: BTreeMap::new(),
            unpaired: 0,
        }
    }

    /// A depth image; returns the pair if its IR is here.
    pub fn depth(&mut self, img: Image) -> Option<(Image, Image)> {
        let stamp = img.header.stamp.as_log_time_ns();
        if let Some(ir) = self.ir.remove(&stamp) {
            self.expire_older(stamp);
            return Some((img, ir));
        }
        self.unpaired += insert_bounded(&mut self.depth, stamp, img, self.capacity);
        None
    }

    /// An IR image; returns the pair if its depth is here.
    pub fn ir(&mut self, img: Image) -> Option<(Image, Image)> {
        let stamp = img.header.stamp.as_log_time_ns();
        if let Some(d) = self.depth.remove(&stamp) {
            self.expire_older(stamp);
            return Some((d, img));
        }
        self.unpaired += insert_bounded(&mut self.ir, stamp, img, self.capacity);
        None
    }

    /// Once a stamp pairs, images older than it will not pair any more (a
    /// driver stamps in order): they are unpaired.
    fn expire_older(&mut self, stamp: u64) {
        for side in [&mut self.depth, &mut self.ir] {
            let keep = side.split_off(&stamp);
            self.unpaired += side.len() as u64;
            *side = keep;
        }
    }
}

/// One frame for the processing thread: depth and IR of one stamp and, from a
/// multi-frequency camera, its phasor images in the order of `k`.
#[derive(Debug, Clone)]
pub struct PairedFrame {
    /// Depth.
    pub depth: Image,
    /// IR.
    pub ir: Image,
    /// `phasor_<k>/image_raw` (empty for a single-frequency camera).
    pub phasors: Vec<Image>,
}

impl From<(Image, Image)> for PairedFrame {
    fn from((depth, ir): (Image, Image)) -> Self {
        Self {
            depth,
            ir,
            phasors: vec![],
        }
    }
}

/// Gathers the depth, IR and `K` phasor images of one stamp (a multi-frequency
/// camera): slot 0 depth, 1 IR, `2 + k` phasor `k`. At most `capacity` stamps
/// wait; the oldest is evicted (its images unpaired), and once a stamp is
/// complete the older ones will not be (a driver stamps in order).
#[derive(Debug)]
pub struct FramePairer {
    slots: usize,
    capacity: usize,
    waiting: BTreeMap<u64, Vec<Option<Image>>>,
    /// Images that never completed their frame.
    pub unpaired: u64,
}

impl FramePairer {
    /// A pairer for depth, IR and `phasors` phasor images.
    pub fn new(phasors: usize, capacity: usize) -> Self {
        Self {
            slots: 2 + phasors,
            capacity: capacity.max(1),
            waiting: BTreeMap::new(),
            unpaired: 0,
        }
    }

    /// The image for `slot`; returns the frame when it completes it.
    pub fn offer(&mut self, slot: usize, img: Image) -> Option<PairedFrame> {
        if slot >= self.slots {
            self.unpaired += 1;
            return None;
        }
        let stamp = img.header.stamp.as_log_time_ns();
        let entry = self.waiting.entry(stamp).or_insert_with(|| vec![None; self.slots]);
        // A repeated image replaces the earlier one: that one is unpaired.
        self.unpaired += u64::from(entry[slot].replace(img).is_some());
        if entry.iter().all(Option::is_some) {
            let images: Vec<Image> = self.waiting.remove(&stamp)?.into_iter().flatten().collect();
            let newer = self.waiting.split_off(&stamp);
            self.unpaired += self
                .waiting
                .values()
                .map(|v| v.iter().flatten().count() as u64)
                .sum::<u64>();
            self.waiting = newer;
            let mut it = images.into_iter();
            let (depth, ir) = (it.next()?, it.next()?);
            return Some(PairedFrame {
                depth,
                ir,
                phasors: it.collect(),
            });
        }
        while self.waiting.len() > self.capacity {
            if let Some((_, lost)) = self.waiting.pop_first() {
                self.unpaired += lost.iter().flatten().count() as u64;
            }
        }
        None
    }
}

fn insert_bounded(side: &mut BTreeMap<u64, Image>, stamp: u64, img: Image, capacity: usize) -> u64 {
    // A repeated stamp replaces the earlier image: that one is unpaired.
    let mut lost = u64::from(side.insert(stamp, img).is_some());
    while side.len() > capacity {
        side.pop_first();
        lost += 1;
    }
    lost
}

/// Work for the processing thread.
#[derive(Debug)]
pub enum Command<T> {
    /// New intrinsics.
    CameraInfo(Box<CameraInfo>),
    /// `~/latch_background`, with the pending request's token.
    Latch(T),
    /// `~/clear_background`.
    Clear(T),
    /// Parameters changed at run time (`forget_evidence`: ξ's pooled evidence no longer applies).
    Reconfigure(Box<super::RuntimeSettings>, bool),
    /// Finish.
    Shutdown,
}

#[derive(Debug)]
struct Lanes<T> {
    frames: VecDeque<PairedFrame>,
    commands: VecDeque<Command<T>>,
    dropped: u64,
}

/// Bounded frame queue (drop-oldest) plus a command lane, for one consumer.
#[derive(Debug)]
pub struct Inbox<T> {
    capacity: usize,
    lanes: Mutex<Lanes<T>>,
    ready: Condvar,
}

/// What the consumer takes next.
#[derive(Debug)]
pub enum Next<T> {
    /// A command (commands go first).
    Command(Command<T>),
    /// A paired frame.
    Frame(Box<PairedFrame>),
    /// Nothing within the wait.
    Idle,
}

impl<T> Inbox<T> {
    /// A queue holding at most `capacity` frames.
    pub fn new(capacity: usize) -> Self {
        Self {
            capacity: capacity.max(1),
            lanes: Mutex::new(Lanes {
                frames: VecDeque::new(),
                commands: VecDeque::new(),
                dropped: 0,
            }),
            ready: Condvar::new(),
        }
    }

    fn lanes(&self) -> std::sync::MutexGuard<'_, Lanes<T>> {
        // A panic while holding the lock cannot leave the queues inconsistent.
        self.lanes.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Queues a frame; when full, the oldest frame is dropped (and counted).
    pub fn push_frame(&self, frame: impl Into<PairedFrame>) {
        let mut l = self.lanes();
        if l.frames.len() >= self.capacity {
            l.frames.pop_front();
            l.dropped += 1;
        }
        l.frames.push_back(frame.into());
        self.ready.notify_one();
    }

    /// Queues a command (never dropped).
    pub fn push_command(&self, c: Command<T>) {
        self.lanes().commands.push_back(c);
        self.ready.notify_one();
    }

    /// Frames dropped because the queue was full.
    pub fn dropped(&self) -> u64 {
        self.lanes().dropped
    }

    /// Takes the next command, else the next frame, waiting up to `wait`.
    pub fn next(&self, wait: Duration) -> Next<T> {
        let mut l = self.lanes();
        if l.commands.is_empty() && l.frames.is_empty() {
            l = self
                .ready
                .wait_timeout_while(l, wait, |l| l.commands.is_empty() && l.frames.is_empty())
                .map(|(g, _)| g)
                .unwrap_or_else(|p| p.into_inner().0);
        }
        if let Some(c) = l.commands.pop_front() {
            return Next::Command(c);
        }
        match l.frames.pop_front() {
            Some(f) => Next::Frame(Box::new(f)),
            None => Next::Idle,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::Header;

    fn img(stamp_ns: u64) -> Image {
        Image {
            header: Header::new(stamp_ns, "cam"),
            ..Image::default()
        }
    }

    #[test]
    fn pairs_by_exact_stamp_in_either_order_and_counts_the_rest() {
        let mut p = StampPairer::new(4);
        assert!(p.depth(img(10)).is_none());
        assert!(p.ir(img(11)).is_none());
        let (d, i) = p.ir(img(10)).expect("pair at 10");
        assert_eq!(d.header.stamp.as_log_time_ns(), 10);
        assert_eq!(i.header.stamp.as_log_time_ns(), 10);
        // 11 (IR) is newer than 10: still waiting.
        assert_eq!(p.unpaired, 0);
        assert!(p.depth(img(12)).is_none());
        assert!(p.ir(img(12)).is_some());
        // 11 had no depth and is now older than a paired stamp.
        assert_eq!(p.unpaired, 1);
    }

    #[test]
    fn frames_of_a_multi_frequency_camera_complete_in_any_order() {
        let mut p = FramePairer::new(2, 3);
        // Stamp 10: phasor 1, depth, phasor 0, IR.
        for slot in [3, 0, 2] {
            assert!(p.offer(slot, img(10)).is_none());
        }
        assert!(p.offer(0, img(11)).is_none());
        let f = p.offer(1, img(10)).expect("complete at 10");
        assert_eq!((f.phasors.len(), f.depth.header.stamp.as_log_time_ns()), (2, 10));
        assert_eq!(p.unpaired, 0);
        // 11 waits; 12 completes and leaves 11's depth unpaired.
        for slot in 0..3 {
            assert!(p.offer(slot, img(12)).is_none());
        }
        assert!(p.offer(3, img(12)).is_some());
        assert_eq!(p.unpaired, 1);
        // Bounded: the oldest incomplete stamps are evicted; a slot past the last is unpaired.
        for s in 20..30 {
            assert!(p.offer(0, img(s)).is_none());
        }
        assert_eq!(p.unpaired, 8);
        assert!(p.offer(9, img(40)).is_none());
        assert_eq!(p.unpaired, 9);
    }

    #[test]
    fn pairer_is_bounded() {
        let mut p = StampPairer::new(3);
        for s in 0..10 {
            assert!(p.depth(img(s)).is_none());
        }
        assert_eq!(p.unpaired, 7);
        assert!(p.ir(img(9)).is_some());
        assert_eq!(p.unpaired, 9);
    }

    #[test]
    fn intake_drops_oversized_images_and_unreadable_samples_by_cause() {
        let info = CameraInfo {
            width: 4,
            height: 2,
            ..CameraInfo::default()
        };
        let sized = |w: u32, h: u32, step: u32, bytes: usize| Image {
            width: w,
            height: h,
            step,
            encoding: "16UC1".into(),
            data: vec![0; bytes],
            ..img(1)
        };
        let mut intake = Intake::default();
        // As the camera says, or smaller (a size mismatch, for the pipeline to report).
        assert!(intake.image("/d", sized(4, 2, 8, 16), Some(&info)).is_some());
        assert!(intake.image("/d", sized(2, 2, 4, 8), Some(&info)).is_some());
        // More pixels than the camera has.
        assert!(intake.image("/d", sized(8, 2, 16, 32), Some(&info)).is_none());
        // More data than step x height.
        assert!(intake.image("/d", sized(4, 2, 8, 17), Some(&info)).is_none());
        // Less data than step x height: truncated.
        assert!(intake.image("/d", sized(4, 2, 8, 15), Some(&info)).is_none());
        assert!(intake.image("/d", sized(4, 2, 8, 15), None).is_none());
        // Before any camera_info only the absolute limit applies.
        assert!(intake.image("/d", sized(8, 2, 16, 33), None).is_some());
        assert!(intake.image("/d", sized(1, 1, 2, MAX_IMAGE_BYTES + 1), None).is_none());
        intake.unreadable("/d", &"Deserialization error: Eof");
        // A camera_info of an absurd camera (its latch would allocate for every pixel).
        let vast = CameraInfo {
            width: u32::MAX,
            height: 3,
            ..info.clone()
        };
        assert!(intake.camera_info("/i", vast).is_none());
        assert!(intake.camera_info("/i", info.clone()).is_some());
        assert_eq!(intake.drops.get(DropCause::Oversized), 4);
        assert_eq!(intake.drops.get(DropCause::Malformed), 1);
        assert_eq!(intake.drops.get(DropCause::BadImage), 2);
        assert_eq!(intake.drops.total(), 7);
        // Absurd dimensions do not overflow.
        let huge = sized(u32::MAX, u32::MAX, u32::MAX, 4);
        assert_eq!(check_size(&huge, None).map_err(|r| r.cause), Err(DropCause::BadImage));
        assert_eq!(
            check_size(&huge, Some(&info)).map_err(|r| r.cause),
            Err(DropCause::Oversized)
        );
    }

    #[test]
    fn inbox_drops_oldest_frames_never_commands() {
        let q: Inbox<u32> = Inbox::new(2);
        for s in 0..5 {
            q.push_frame((img(s), img(s)));
        }
        q.push_command(Command::Latch(7));
        assert_eq!(q.dropped(), 3);
        assert!(matches!(q.next(Duration::ZERO), Next::Command(Command::Latch(7))));
        let Next::Frame(f) = q.next(Duration::ZERO) else {
            panic!("expected a frame")
        };
        assert_eq!(f.depth.header.stamp.as_log_time_ns(), 3);
        assert!(matches!(q.next(Duration::ZERO), Next::Frame(_)));
        assert!(matches!(q.next(Duration::from_millis(5)), Next::Idle));
    }
}
