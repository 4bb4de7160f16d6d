//! `demo`: the whole graph on loopback. A bundled bag is played as a ToF
//! driver would (at its recorded rate, fresh stamps), the node runs as a
//! separate process, the latch service is called while the empty scene
//! streams, then the object frames play; the outputs are collected, compared
//! with the bag's ground truth, and kept as a bag and a Rerun recording.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use serde_json::json;

use crate::bag::BagWriter;
use crate::image::depth_mm;
use crate::msgs::Header;
use crate::node::peer::{bag_frames, restamp, Peer};
use crate::pipeline::{PipelineConfig, TruthError};

use super::common::{OutputArgs, TopicArgs};
use super::recording::load;

/// Arguments of `demo`.
#[derive(Debug, Args)]
pub struct DemoArgs {
    /// The bag to play (default: the bundled, physically rendered document holder).
    #[arg(long)]
    pub bag: Option<PathBuf>,
    /// Where the output bag, the Rerun recording and the node's log go.
    #[arg(long, default_value = "out/demo")]
    pub out_dir: PathBuf,
    /// Fix ξ in the node (default: the node estimates it).
    #[arg(long)]
    pub xi: Option<f64>,
    /// Rerun: a .rrd path, a viewer address, or off (default: OUT_DIR/demo.rrd).
    #[arg(long)]
    pub rerun: Option<String>,
    /// DDS domain (default: ROS_DOMAIN_ID, else 0). Traffic stays on 127.0.0.1.
    #[arg(long)]
    pub domain_id: Option<u16>,
    /// Play this many times faster than recorded.
    #[arg(long, default_value_t = 1.0)]
    pub speed: f64,
    /// The node's queue of paired frames (its `queue_depth`): the demo keeps
    /// every frame by default; a live robot keeps 2 and drops the oldest.
    #[arg(long, default_value_t = 64)]
    pub queue_depth: usize,
    #[command(flatten)]
    pub output: OutputArgs,
}

/// The demo's bag: the physically rendered document holder of the paper's Fig. 5a.
pub const DEMO_BAG: &str = "bags/rendered/paper_document_holder.mcap";

/// Where a bundled file is: under the working directory, else under a folder above the
/// running binary (a checkout's `target/release/..`). `None` when neither has it.
pub fn bundled(relative: &str) -> Option<PathBuf> {
    let here = PathBuf::from(relative);
    if here.is_file() {
        return Some(here);
    }
    let exe = std::env::current_exe().ok()?;
    exe.ancestors().skip(1).map(|d| d.join(relative)).find(|p| p.is_file())
}

fn now_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0)
}

struct NodeProcess {
    child: Child,
}

impl NodeProcess {
    fn interrupt_and_wait(mut self, timeout: Duration) -> Result<std::process::ExitStatus> {
        let pid = self.child.id().to_string();
        let _ = Command::new("kill").args(["-INT", &pid]).status();
        let t0 = Instant::now();
        loop {
            if let Some(st) = self.child.try_wait()? {
                return Ok(st);
            }
            if t0.elapsed() > timeout {
                let _ = self.child.kill();
                bail!("the node did not exit within {:.0} s of SIGINT", timeout.as_secs_f64());
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for NodeProcess {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

/// Runs `demo`.
pub fn run(a: DemoArgs) -> Result<()> {
    let bag = match &a.bag {
        Some(b) => b.clone(),
        None => bundled(DEMO_BAG).with_context(|| {
            format!("the demo's bag {DEMO_BAG} is neither under the working directory nor above the binary: run the demo from the repository, or give --bag BAG")
        })?,
    };
    if !(a.speed.is_finite() && a.speed > 0.0) {
        bail!("--speed must be positive, got {}", a.speed);
    }
    std::fs::create_dir_all(&a.out_dir).with_context(|| format!("creating {}", a.out_dir.display()))?;
    let stage = |s: &str| {
        if !a.output.json_on_stdout() {
            eprintln!("demo: {s}");
        }
    };
    stage(&format!("reading {}", bag.display()));
    let rec = load(&bag, &TopicArgs::default())?;
    let config = PipelineConfig::default();
    let bg = rec.background_frames(None, &config)?;
    let (raw_info, raw_pairs) = bag_frames(&bag)?;
    if raw_pairs.len() != rec.frames.len() {
        bail!("{}: paired frames differ between readers", bag.display());
    }
    let period_ns = {
        let s: Vec<u64> = rec.frames.iter().map(|f| f.stamp_ns).collect();
        let d: Vec<u64> = s
            .windows(2)
            .map(|w| w[1].saturating_sub(w[0]))
            .filter(|d| *d > 0)
            .collect();
        let mut d = d;
        d.sort_unstable();
        d.get(d.len() / 2).copied().unwrap_or(100_000_000)
    };
    let period = Duration::from_nanos((period_ns as f64 / a.speed) as u64);
    let domain = match a.domain_id {
        Some(d) => d,
        None => std::env::var("ROS_DOMAIN_ID")
            .ok()
            .and_then(|v| v.trim().parse().ok())
            .unwrap_or(0),
    };
    let latch_frames = bg.count.clamp(1, 10);
    let rerun = a.rerun.clone().unwrap_or_else(|| {
        if cfg!(feature = "rerun") {
            a.out_dir.join("demo.rrd").display().to_string()
        } else {
            "off".into()
        }
    });
    let stats_path = a.out_dir.join("node_stats.json");
    let log_path = a.out_dir.join("node.log");
    let mut cmd = Command::new(std::env::current_exe().context("locating this executable")?);
    cmd.arg("node")
        .arg("--stats-json")
        .arg(&stats_path)
        .args(["--ros-args", "-r", "__ns:=/tof"])
        .args(["-p", &format!("background_frames:={latch_frames}")])
        .args(["-p", &format!("rerun:={rerun}")])
        .args(["-p", "latch_timeout_s:=30"])
        .args(["-p", &format!("queue_depth:={}", a.queue_depth.max(1))])
        .env("ROS_DOMAIN_ID", domain.to_string())
        .env("ROS_LOCALHOST_ONLY", "1")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log_path).with_context(|| format!("creating {}", log_path.display()))?);
    if let Some(x) = a.xi {
        cmd.args(["-p", &format!("xi:={x}")]);
    }
    stage(&format!(
        "starting the node (domain {domain}, localhost only; log {})",
        log_path.display()
    ));
    let mut node = NodeProcess {
        child: cmd.spawn().context("starting the node process")?,
    };

    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()?;
    let played = rt.block_on(async {
        let ctx = crate::node::context(domain, true)?;
        let mut peer = Peer::new(
            &ctx,
            "tof_driver",
            "/tof",
            "/tof/translucent_tof",
            ros2_client::ServiceMapping::Enhanced,
        )?;
        stage("waiting for the node on DDS");
        peer.wait_for_node(Duration::from_secs(30)).await?;
        // The empty scene streams (cycling the background frames) while the latch runs.
        stage(&format!(
            "streaming the empty scene and calling ~/latch_background ({latch_frames} frames)"
        ));
        let mut next = now_ns();
        let reply = peer
            .latch_while_streaming(&raw_info, &raw_pairs[..bg.count], period, &mut next, period_ns)
            .await?;
        let mut tick = tokio::time::interval(period);
        if !reply.success {
            bail!("~/latch_background failed: {}", reply.message);
        }
        stage(&format!("latched: {}", reply.message));
        stage(&format!(
            "playing {} object frames at {:.1} Hz",
            raw_pairs.len() - bg.count,
            1e9 / period.as_nanos() as f64
        ));
        let mut stamps = BTreeMap::new();
        for (j, (d, ir)) in raw_pairs.iter().enumerate().skip(bg.count) {
            tick.tick().await;
            next += period_ns;
            let mut info = raw_info.clone();
            info.header = Header::new(next, raw_info.header.frame_id.clone());
            peer.publish(&info, &restamp(d, next), &restamp(ir, next))?;
            stamps.insert(next, j);
            peer.drain();
        }
        // The last frame's outputs, or give up after a while.
        let last = *stamps
            .keys()
            .next_back()
            .ok_or_else(|| anyhow!("the bag has no object frames"))?;
        // The node may still be working through its queue.
        peer.wait_for(last, Duration::from_secs(120)).await;
        tokio::time::sleep(Duration::from_millis(300)).await;
        peer.drain();
        Ok::<_, anyhow::Error>((std::mem::take(&mut peer.received), stamps, reply))
    });
    let (peer_received, stamps, latch_reply) = match played {
        Ok(v) => v,
        Err(e) => {
            let exited = node.child.try_wait().ok().flatten();
            let log = std::fs::read_to_string(&log_path).unwrap_or_default();
            let tail: Vec<&str> = log
                .lines()
                .rev()
                .take(5)
                .collect::<Vec<_>>()
                .into_iter()
                .rev()
                .collect();
            return Err(e.context(format!(
                "the node {} (last lines of {}:\n{})",
                exited
                    .map(|s| format!("exited with {s}"))
                    .unwrap_or_else(|| "is running".into()),
                log_path.display(),
                tail.join("\n")
            )));
        }
    };
    stage("stopping the node");
    let status = node.interrupt_and_wait(Duration::from_secs(30))?;
    if !status.success() {
        bail!("the node exited with {status}; see {}", log_path.display());
    }
    let node_stats: serde_json::Value = std::fs::read_to_string(&stats_path)
        .ok()
        .and_then(|t| serde_json::from_str(&t).ok())
        .unwrap_or(serde_json::Value::Null);

    // Outputs against the bag's ground truth.
    let mut errors = TruthError::default();
    let out_bag = a.out_dir.join("demo.mcap");
    let mut w = BagWriter::create(&out_bag).with_context(|| format!("creating {}", out_bag.display()))?;
    let mut translucent = 0usize;
    // The object frames' outputs (the background frames came back as they went, `passthrough`).
    for (stamp, img) in peer_received.corrected.iter().filter(|(s, _)| stamps.contains_key(s)) {
        w.write("/tof/translucent_tof/depth/corrected", *stamp, img)?;
        if let Some(m) = peer_received.mask.get(stamp) {
            w.write("/tof/translucent_tof/translucent_mask", *stamp, m)?;
        }
        if let Some(p) = peer_received.points.get(stamp) {
            w.write("/tof/translucent_tof/points", *stamp, p)?;
        }
        let (Some(&j), Some(mask_img)) = (stamps.get(stamp), peer_received.mask.get(stamp)) else {
            continue;
        };
        let frame = &rec.frames[j];
        let Some(truth) = rec.truth.get(&frame.stamp_ns) else {
            continue;
        };
        let corrected = depth_mm(img)?;
        let mut mask = crate::physics::ImageBuf::filled(corrected.width, corrected.height, false);
        for (k, v) in mask_img.data.iter().enumerate().take(mask.len()) {
            mask.data[k] = *v == 255;
        }
        translucent += (0..mask.len())
            .filter(|&k| mask.data[k] && corrected.data[k].is_finite())
            .count();
        errors.add(&corrected, &frame.z_mm, truth, &mask);
    }
    for est in &peer_received.estimates {
        w.write(
            "/tof/translucent_tof/translucency",
            est.header.stamp.as_log_time_ns(),
            est,
        )?;
    }
    w.finish()?;
    // The last estimate of a recovered frame (those of frames passed through say why instead).
    let last = peer_received
        .estimates
        .iter()
        .rev()
        .find(|e| !e.method.starts_with("passthrough"));
    let object_frames = stamps.len();
    let object_frames_back = peer_received
        .corrected
        .keys()
        .filter(|s| stamps.contains_key(s))
        .count();
    let mut report = json!({
        "bag": bag.display().to_string(),
        "latch": latch_reply.message,
        "object_frames_played": object_frames,
        "frames_received": object_frames_back,
        "xi": last.map(|e| e.xi),
        "xi_interval": last.map(|e| [e.xi_lower, e.xi_upper]),
        "xi_method": last.map(|e| e.method.clone()),
        "xi_mode": "online",
        "translucent_pixels": translucent,
        "out_bag": out_bag.display().to_string(),
        "rerun": rerun,
        "node": node_stats,
    });
    if let serde_json::Value::Object(m) = errors.json() {
        for (k, v) in m {
            report[k] = v;
        }
    }
    let mut s = format!(
        "demo over DDS on loopback: {} of {} object frames came back from the node\n",
        object_frames_back, object_frames
    );
    if let Some(e) = last {
        s.push_str(&format!(
            "xi = {:.3} [{:.3}, {:.3}] by {} over {} frames{}\n",
            e.xi,
            e.xi_lower,
            e.xi_upper,
            e.method,
            e.frames_pooled,
            if a.xi.is_some() {
                " (given)"
            } else {
                " (online, as the node estimates it: each frame with the evidence up to it; replay --xi-mode online does the same offline)"
            }
        ));
    }
    if let Some(line) = errors.summary_line() {
        s.push_str(&line);
        s.push('\n');
    }
    s.push_str(&format!("wrote {} and {}", out_bag.display(), rerun));
    a.output.summary(&s);
    a.output.write_json(&report)
}
