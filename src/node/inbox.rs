//! Between the DDS callbacks and the processing thread: depth and IR paired
//! by exact stamp, then a bounded queue that drops the oldest frame when the
//! processing falls behind, and an unbounded lane for service commands
//! (never dropped).

use std::collections::{BTreeMap, VecDeque};
use std::sync::{Condvar, Mutex};
use std::time::Duration;

use crate::msgs::{CameraInfo, Image};

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
    frames: VecDeque<(Image, Image)>,
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
    Frame(Box<(Image, Image)>),
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
    pub fn push_frame(&self, pair: (Image, Image)) {
        let mut l = self.lanes();
        if l.frames.len() >= self.capacity {
            l.frames.pop_front();
            l.dropped += 1;
        }
        l.frames.push_back(pair);
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
        assert_eq!(f.0.header.stamp.as_log_time_ns(), 3);
        assert!(matches!(q.next(Duration::ZERO), Next::Frame(_)));
        assert!(matches!(q.next(Duration::from_millis(5)), Next::Idle));
    }
}
