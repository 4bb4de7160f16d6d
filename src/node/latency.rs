//! The node's added latency over DDS on loopback, against a bare
//! publish/subscribe of the same messages ([`super::echo`]), and its memory
//! over a long run. Both run as separate processes of this binary; the
//! driver here publishes a bag's object frames at a fixed rate and times each
//! frame from its publication to the arrival of its `~/depth/corrected`.

use std::collections::BTreeMap;
use std::path::PathBuf;

use futures::StreamExt;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use serde::Serialize;

use super::peer::{restamp, Peer};
use crate::msgs::{CameraInfo, Image};

/// What to measure.
#[derive(Debug, Clone)]
pub struct LatencyConfig {
    /// A bag with depth, IR, camera_info (the first `background` pairs are the empty scene).
    pub bag: PathBuf,
    /// Background pairs at the start of the bag.
    pub background: usize,
    /// Object frames to publish (cycling the bag's).
    pub frames: usize,
    /// Publication rate, Hz.
    pub rate_hz: f64,
    /// Extra `-p` parameters for the node (e.g. `xi:=0.65`).
    pub node_params: Vec<String>,
    /// DDS domain.
    pub domain_id: u16,
}

/// One side of the comparison.
#[derive(Debug, Clone, Serialize)]
pub struct LatencyRun {
    /// Frames published.
    pub sent: usize,
    /// Frames whose output came back.
    pub received: usize,
    /// Publication to output arrival, ms: median, 95th percentile, max.
    pub latency_ms: [f64; 3],
    /// The median per object frame of the bag, in the bag's order (NaN for a frame
    /// none of whose outputs came back).
    pub frame_median_ms: Vec<f64>,
}

/// One object frame of the bag, through both.
#[derive(Debug, Clone, Serialize)]
pub struct FrameLatency {
    /// Its place among the bag's object frames.
    pub frame: usize,
    /// Share of the image the node's segmentation marks translucent (a pipeline
    /// with default settings, latched on the bag's background frames).
    pub translucent_fraction: f64,
    /// Median through the bare echo, ms.
    pub bare_median_ms: f64,
    /// Median through the node, ms.
    pub node_median_ms: f64,
    /// Their difference, ms.
    pub added_median_ms: f64,
}

/// The comparison.
#[derive(Debug, Clone, Serialize)]
pub struct LatencyReport {
    /// Through the bare echo (transport only).
    pub bare: LatencyRun,
    /// Through the node.
    pub node: LatencyRun,
    /// Node median minus bare median, ms.
    pub added_median_ms: f64,
    /// Node 95th percentile minus bare 95th percentile, ms.
    pub added_p95_ms: f64,
    /// The same per object frame of the bag: how the added time grows with the
    /// translucent share, as recovery's does.
    pub frames: Vec<FrameLatency>,
    /// The node's own counters and timings (`--stats-json`).
    pub node_stats: serde_json::Value,
}

struct Proc(Child);

impl Proc {
    fn stop(mut self) -> Result<()> {
        let _ = Command::new("kill").args(["-INT", &self.0.id().to_string()]).status();
        let t0 = Instant::now();
        while self.0.try_wait()?.is_none() {
            if t0.elapsed() > Duration::from_secs(30) {
                let _ = self.0.kill();
                bail!("process {} did not stop on SIGINT", self.0.id());
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        Ok(())
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        if let Ok(None) = self.0.try_wait() {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
}

/// Plays the frames to whatever serves `/tof/translucent_tof` and times them.
async fn drive(cfg: &LatencyConfig, info: &CameraInfo, pairs: &[(Image, Image)], tag: &str) -> Result<LatencyRun> {
    let ctx = super::context(cfg.domain_id, true)?;
    let peer = Peer::new(
        &ctx,
        &format!("latency_driver_{tag}"),
        "/tof",
        "/tof/translucent_tof",
        ros2_client::ServiceMapping::Enhanced,
    )?;
    peer.wait_for_node(Duration::from_secs(30)).await?;
    let mut stamp = 1_000_000_000u64;
    let bg = cfg.background.max(1).min(pairs.len());
    let reply = peer
        .latch_while_streaming(info, &pairs[..bg], Duration::from_millis(30), &mut stamp, 1_000_000)
        .await?;
    if !reply.success {
        bail!("latch failed: {}", reply.message);
    }
    let objects = &pairs[bg..];
    if objects.is_empty() {
        bail!("{}: no object frames after {bg} background frames", cfg.bag.display());
    }
    let period = Duration::from_secs_f64(1.0 / cfg.rate_hz);
    let mut tick = tokio::time::interval(period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    // Warm-up: the first frames (page faults, first allocations) are not timed.
    let warmup = 5.min(cfg.frames);
    let mut sent: BTreeMap<u64, (Instant, usize)> = BTreeMap::new();
    let mut lat: Vec<f64> = Vec::with_capacity(cfg.frames);
    let mut by_frame: Vec<Vec<f64>> = vec![vec![]; objects.len()];
    let mut last = 0;
    {
        let arrivals = peer.corrected_arrivals();
        tokio::pin!(arrivals);
        let mut j = 0;
        let mut deadline: Option<tokio::time::Instant> = None;
        loop {
            tokio::select! {
                _ = tick.tick(), if j < cfg.frames + warmup => {
                    let (d, i) = &objects[j % objects.len()];
                    stamp += 1_000_000;
                    let t0 = Instant::now();
                    peer.publish(info, &restamp(d, stamp), &restamp(i, stamp))?;
                    if j >= warmup {
                        sent.insert(stamp, (t0, j % objects.len()));
                    }
                    last = stamp;
                    j += 1;
                    if j == cfg.frames + warmup {
                        deadline = Some(tokio::time::Instant::now() + Duration::from_secs(10));
                    }
                }
                Some((s, t1)) = arrivals.next() => {
                    if let Some((t0, k)) = sent.remove(&s) {
                        let ms = t1.duration_since(t0).as_secs_f64() * 1e3;
                        lat.push(ms);
                        by_frame[k].push(ms);
                    }
                    if s == last && j == cfg.frames + warmup {
                        break;
                    }
                }
                _ = tokio::time::sleep_until(deadline.unwrap_or_else(|| tokio::time::Instant::now() + Duration::from_secs(3600))), if deadline.is_some() => break,
            }
        }
    }
    let received = lat.len();
    Ok(LatencyRun {
        sent: cfg.frames,
        received,
        latency_ms: super::percentiles(&mut lat),
        frame_median_ms: by_frame.iter_mut().map(|v| super::percentiles(v)[0]).collect(),
    })
}

/// Each object frame's share of pixels the node's segmentation marks translucent,
/// against a background latched from the first `background` pairs, as the driver
/// latches it.
fn translucent_shares(info: &CameraInfo, pairs: &[(Image, Image)], background: usize) -> Result<Vec<f64>> {
    use crate::image::{depth_mm, ir_counts};
    use crate::pipeline::{DepthFrame, Pipeline, PipelineConfig};
    let k = crate::physics::Intrinsics::from_camera_info(info).context("the bag's camera_info is not usable")?;
    let frame = |(d, i): &(Image, Image)| -> Result<DepthFrame> {
        Ok(DepthFrame {
            stamp_ns: d.header.stamp.as_log_time_ns(),
            z_mm: depth_mm(d)?,
            ir: ir_counts(i)?,
        })
    };
    let bg = background.max(1).min(pairs.len());
    let latch: Vec<DepthFrame> = pairs[..bg].iter().map(frame).collect::<Result<_>>()?;
    let pipe = Pipeline::latched(PipelineConfig::default(), k, &latch)?;
    pairs[bg..]
        .iter()
        .map(|p| Ok(pipe.observe(&frame(p)?)?.translucent_pixels as f64 / (k.width * k.height) as f64))
        .collect()
}

/// Runs the bare echo, then the node, on the same frames; compares.
pub fn measure(cfg: &LatencyConfig) -> Result<LatencyReport> {
    if !(cfg.rate_hz.is_finite() && cfg.rate_hz > 0.0) {
        bail!("rate must be positive");
    }
    let (info, pairs) = super::peer::bag_frames(&cfg.bag)?;
    let exe = std::env::current_exe().context("locating this executable")?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()?;
    let quiet = |c: &mut Command| {
        c.env("ROS_DOMAIN_ID", cfg.domain_id.to_string())
            .env("ROS_LOCALHOST_ONLY", "1")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null());
    };
    let mut echo = Command::new(&exe);
    echo.args(["dds-echo", "--namespace", "/tof", "--node", "/tof/translucent_tof"]);
    quiet(&mut echo);
    let echo = Proc(echo.spawn().context("starting the echo")?);
    let bare = rt.block_on(drive(cfg, &info, &pairs, "bare"))?;
    echo.stop()?;

    let dir = std::env::temp_dir().join(format!("ttof_latency_{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let stats = dir.join("node_stats.json");
    let mut node = Command::new(&exe);
    node.arg("node").arg("--stats-json").arg(&stats);
    node.args(["--ros-args", "-r", "__ns:=/tof", "-p", "background_frames:=5"]);
    for p in &cfg.node_params {
        node.args(["-p", p]);
    }
    quiet(&mut node);
    let node = Proc(node.spawn().context("starting the node")?);
    let through = rt.block_on(drive(cfg, &info, &pairs, "node"))?;
    node.stop()?;
    let node_stats = std::fs::read_to_string(&stats)
        .ok()
        .and_then(|t| serde_json::from_str(&t).ok())
        .unwrap_or(serde_json::Value::Null);
    let _ = std::fs::remove_dir_all(&dir);
    let shares = translucent_shares(&info, &pairs, cfg.background)?;
    let frames = shares
        .iter()
        .enumerate()
        .map(|(k, &share)| {
            let (b, n) = (bare.frame_median_ms[k], through.frame_median_ms[k]);
            FrameLatency {
                frame: k,
                translucent_fraction: share,
                bare_median_ms: b,
                node_median_ms: n,
                added_median_ms: n - b,
            }
        })
        .collect();
    Ok(LatencyReport {
        frames,
        added_median_ms: through.latency_ms[0] - bare.latency_ms[0],
        added_p95_ms: through.latency_ms[1] - bare.latency_ms[1],
        bare,
        node: through,
        node_stats,
    })
}
