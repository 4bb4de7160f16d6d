//! The processing thread: takes paired frames and commands from the inbox, runs
//! [`NodeCore`] (and the multi-frequency path beside it), publishes the outputs and
//! keeps the counters that /diagnostics and the final summary read.

use super::core::NodeOutputs;
use super::*;

/// How many frames' processing times the latency percentiles look back over.
const LATENCY_WINDOW: usize = 8192;

/// The thread's state between inbox items.
struct Worker {
    s: NodeSettings,
    out: Outputs,
    viz: Option<VizSink>,
    replies: tokio::sync::mpsc::UnboundedSender<(Token, TriggerResponse)>,
    live: Arc<Mutex<Live>>,
    stats: NodeStats,
    core: NodeCore<Token>,
    multi: Option<MultiFrequencyNode>,
    /// Processing times of the last published frames, ms.
    latencies: Vec<f64>,
    clocks: Clocks,
    reported_drops: u64,
}

/// When the periodic chores last ran.
struct Clocks {
    live: Instant,
    report: Instant,
    memory: Instant,
    trim: Instant,
}

/// Runs the processing thread until a shutdown command (or `max_frames`), then sends
/// its counters on `done`.
pub(super) fn worker(
    s: NodeSettings,
    inbox: Arc<Inbox<Token>>,
    out: Outputs,
    viz: Option<VizSink>,
    replies: tokio::sync::mpsc::UnboundedSender<(Token, TriggerResponse)>,
    done: tokio::sync::mpsc::UnboundedSender<NodeStats>,
    live: Arc<Mutex<Live>>,
) {
    let mut stats = NodeStats::default();
    // The processing pool, this thread its first worker (see `pool_on_current_thread`).
    let _pool = processing_pool(&s, &mut stats);
    let mut w = Worker::new(s, out, viz, replies, live, stats);
    loop {
        w.share_live();
        if let Some((t, r)) = w.core.check_latch_timeout() {
            w.reply(t, r);
        }
        match inbox.next(Duration::from_millis(100)) {
            Next::Idle => {}
            Next::Command(Command::Shutdown) => break,
            Next::Command(c) => w.on_command(c),
            Next::Frame(frame) => {
                if w.on_frame(*frame) {
                    break;
                }
            }
        }
        w.chores();
    }
    let _ = done.send(w.finish());
}

/// The rayon pool on this thread, its CPUs in `stats` (none: rayon's global pool works).
fn processing_pool(s: &NodeSettings, stats: &mut NodeStats) -> Option<rayon::ThreadPool> {
    match crate::affinity::pool_on_current_thread(0, s.pin_threads) {
        Ok((pool, cpus)) => {
            if s.pin_threads {
                info!("pin_threads: the processing pool's workers pinned to CPUs {cpus:?}");
            }
            stats.pinned_cpus = cpus;
            Some(pool)
        }
        Err(e) => {
            warn!("the processing pool could not be built on the pipeline thread; rayon's global pool does the work ({e})");
            None
        }
    }
}

impl Worker {
    fn new(
        s: NodeSettings,
        out: Outputs,
        viz: Option<VizSink>,
        replies: tokio::sync::mpsc::UnboundedSender<(Token, TriggerResponse)>,
        live: Arc<Mutex<Live>>,
        mut stats: NodeStats,
    ) -> Self {
        let core = NodeCore::new(s.config.clone(), s.background_frames, s.latch_timeout)
            .with_watch(s.passthrough, s.relatch_on_move);
        let multi = s
            .multi_frequency
            .clone()
            .map(|f| MultiFrequencyNode::new(f, &s.config, s.no_latch));
        sample_memory(&mut stats);
        let now = Instant::now();
        Self {
            s,
            out,
            viz,
            replies,
            live,
            stats,
            core,
            multi,
            latencies: Vec::with_capacity(LATENCY_WINDOW),
            clocks: Clocks {
                live: now - Duration::from_secs(1),
                report: now,
                memory: now,
                trim: now,
            },
            reported_drops: 0,
        }
    }

    fn reply(&self, t: Token, r: TriggerResponse) {
        let _ = self.replies.send((t, r));
    }

    /// What /diagnostics reports, refreshed every 250 ms.
    fn share_live(&mut self) {
        if self.clocks.live.elapsed() < Duration::from_millis(250) {
            return;
        }
        if let Ok(mut l) = self.live.lock() {
            *l = Live {
                published: self.stats.published,
                latched_frames: self.stats.latched_frames,
                dropped: self.core.drops.by_cause.clone(),
                passed: self.core.passed.clone(),
                camera_moved: self.core.camera_moved(),
                camera_moves: self.core.moves,
                parameter_changes: self.stats.parameter_changes,
                publish_failures: self.stats.publish_failures,
                latch: self.latch_state(),
                xi: self.stats.xi,
                xi_method: match self.multi {
                    Some(_) => crate::physics::XiMethod::MultiFrequency.as_str().to_string(),
                    None => self.core.xi_method().to_string(),
                },
                processing_ms: percentiles(&mut self.latencies.clone()),
            };
        }
        self.clocks.live = Instant::now();
    }

    fn latch_state(&self) -> &'static str {
        if self.core.latching() {
            "latching"
        } else if self.core.background().is_some() && self.multi.as_ref().is_none_or(|m| m.latched()) {
            "latched"
        } else {
            "none"
        }
    }

    fn on_command(&mut self, c: Command<Token>) {
        match c {
            Command::CameraInfo(ci) => self.on_camera_info(&ci),
            Command::Latch(t) => self.on_latch(t),
            Command::Reconfigure(r, forget_evidence) => {
                let RuntimeSettings {
                    config,
                    background_frames,
                    latch_timeout,
                } = *r;
                self.stats.parameter_changes += 1;
                self.core
                    .reconfigure(config, background_frames, latch_timeout, forget_evidence);
            }
            Command::Clear(t) => {
                let (r, cancelled) = self.core.clear();
                if let Some(m) = &mut self.multi {
                    m.clear();
                }
                if let Some((t2, r2)) = cancelled {
                    self.reply(t2, r2);
                }
                self.reply(t, r);
            }
            // The loop stops on it before a command reaches here.
            Command::Shutdown => {}
        }
    }

    fn on_camera_info(&mut self, ci: &CameraInfo) {
        match self.core.on_camera_info(ci) {
            Ok(note) => {
                if let Some(note) = note {
                    warn!("{note}");
                }
                if let Some(Err(e)) = self.multi.as_mut().map(|m| m.on_camera_info(&self.core)) {
                    warn!("camera_info {}x{}: {e}", ci.width, ci.height);
                }
            }
            Err((cause, why)) => {
                if self.core.drops.record(cause) {
                    warn!(
                        "camera_info {}x{} K {:?} not usable: {why} ({})",
                        ci.width,
                        ci.height,
                        ci.k,
                        cause.advice()
                    );
                }
            }
        }
    }

    fn on_latch(&mut self, t: Token) {
        info!(
            "latch requested: averaging the next {} frames",
            self.core.background_frames()
        );
        let started = if t.0 == Service::OnStart {
            self.core.start_latch_waiting(t)
        } else {
            self.core.start_latch(t)
        };
        match started {
            Err((t, r)) => self.reply(t, r),
            Ok(()) => {
                if let Some(m) = &mut self.multi {
                    m.on_latch_started();
                }
            }
        }
    }

    /// Processes and publishes one frame; true when `max_frames` are published.
    fn on_frame(&mut self, frame: PairedFrame) -> bool {
        let start = Instant::now();
        let latching = self.core.latching();
        let MultiFrequencyResult {
            frame: res,
            translucency,
        } = match &mut self.multi {
            Some(m) => m.on_frame(&mut self.core, &frame),
            None => MultiFrequencyResult {
                frame: self.core.on_frame(&frame.depth, &frame.ir),
                translucency: None,
            },
        };
        for (t, r) in res.replies {
            self.reply(t, r);
        }
        for (level, note) in &res.notes {
            log::log!(*level, "{note}");
        }
        if let Some((cause, first)) = res.dropped {
            if let Some(msg) = first {
                warn!("{msg}; further {cause:?} drops are counted");
            }
        } else if latching {
            self.stats.latched_frames += 1;
        }
        let Some(mut o) = res.outputs else {
            return false;
        };
        self.publish(&mut o, translucency);
        // A frame passed through is not a recovered one.
        if o.frame.passthrough.is_some() {
            return false;
        }
        self.count_recovered(&o, start);
        self.log_viz(o, &frame.depth);
        self.s.max_frames.is_some_and(|m| self.stats.published >= m)
    }

    /// Publishes a frame's outputs: the corrected depth first (most consumers wait for it
    /// alone), then the rest is made and published. A failure is warned of once, then counted.
    fn publish(&mut self, o: &mut NodeOutputs, translucency: Option<Image>) {
        let out = &self.out;
        let first = out.corrected.publish(std::mem::take(&mut o.corrected)).err();
        let info = o.camera_info.take().and_then(|ci| out.corrected_info.publish(ci).err());
        let mut results = vec![first.map(|e| format!("{e:?}")), info.map(|e| format!("{e:?}"))];
        match o.companions() {
            Ok(c) => {
                results.push(out.sigma.publish(c.sigma).err().map(|e| format!("{e:?}")));
                results.push(out.mask.publish(c.mask).err().map(|e| format!("{e:?}")));
                if let Some(points) = c.points {
                    results.push(out.points.publish(points).err().map(|e| format!("{e:?}")));
                }
                for e in c.estimates {
                    results.push(out.estimate.publish(e).err().map(|e| format!("{e:?}")));
                }
                if let (Some(p), Some(t)) = (&out.translucency_image, translucency) {
                    results.push(p.publish(t).err().map(|e| format!("{e:?}")));
                }
            }
            Err(e) => results.push(Some(format!("Companions {e}"))),
        }
        if let Some(e) = results.into_iter().flatten().next() {
            // The error's kind only: its Debug form carries the whole message.
            let kind = e.split([' ', '{', '(']).next().unwrap_or("").to_string();
            self.stats.publish_failures += 1;
            if self.stats.publish_failures == 1 {
                warn!("publishing an output failed ({kind}; a reliable reader is not keeping up?); further failures are counted (publish_failures)");
            }
        }
    }

    /// Counts a recovered frame: its ξ and its processing time.
    fn count_recovered(&mut self, o: &NodeOutputs, start: Instant) {
        self.stats.published += 1;
        let xi = &o.frame.xi;
        self.stats.xi = Some([xi.xi, xi.interval[0], xi.interval[1]]);
        if self.latencies.len() == LATENCY_WINDOW {
            self.latencies.remove(0);
        }
        self.latencies.push(start.elapsed().as_secs_f64() * 1e3);
    }

    /// Hands a recovered frame to the Rerun thread, if one logs.
    fn log_viz(&self, o: NodeOutputs, depth: &Image) {
        let (Some(v), Some(rays)) = (&self.viz, self.core.shared_rays()) else {
            return;
        };
        let Ok(raw) = crate::image::depth_mm(depth) else {
            return;
        };
        v.log(FrameViz {
            stamp_ns: o.frame.stamp_ns,
            frame: self.stats.published,
            rays,
            raw_z_mm: raw,
            recovered_z_mm: o.frame.corrected_z_mm,
            mask: o.frame.mask,
            xi: Some((o.frame.xi.xi, o.frame.xi.interval)),
            objects: FrameViz::objects_of(&o.frame.regions),
        });
    }

    /// Memory sampled every second (the DDS writers' samples are freed every 6 s, and a
    /// coarser sampling would alias that sawtooth), free heap handed back every 5 s, and
    /// the drops so far logged at most every 5 s when they changed.
    fn chores(&mut self) {
        if self.clocks.memory.elapsed() >= Duration::from_secs(1) {
            if self.clocks.trim.elapsed() >= Duration::from_secs(5) {
                release_free_heap();
                self.clocks.trim = Instant::now();
            }
            sample_memory(&mut self.stats);
            self.clocks.memory = Instant::now();
        }
        let drops = self.core.drops.total();
        if drops != self.reported_drops && self.clocks.report.elapsed() > Duration::from_secs(5) {
            let by: Vec<String> = self
                .core
                .drops
                .by_cause
                .iter()
                .map(|(c, n)| format!("{c:?} {n}"))
                .collect();
            info!(
                "{} frames published; dropped so far: {}",
                self.stats.published,
                by.join(", ")
            );
            self.reported_drops = drops;
            self.clocks.report = Instant::now();
        }
    }

    /// The final counters; the Rerun recording finished.
    fn finish(mut self) -> NodeStats {
        sample_memory(&mut self.stats);
        self.stats.dropped = self.core.drops.by_cause.clone();
        self.stats.passed_through = self.core.passed.clone();
        self.stats.camera_moves = self.core.moves;
        self.stats.added_latency_ms = percentiles(&mut self.latencies);
        if let Some(v) = self.viz {
            self.stats.rerun_dropped = v.dropped();
            if let Err(e) = v.finish() {
                error!("{e}");
            }
        }
        self.stats
    }
}
