//! `bench`: times the real-time path on simulated frames (a document holder
//! before a wall) and prints a table; `--json` for the rows.

use anyhow::{bail, Context, Result};
use clap::Args;
use serde_json::json;

use crate::bench::{
    run_case, run_multi_frequency, BenchScene, Case, MultiFrequencyBench, RunSettings, BENCH_FREQUENCIES_HZ, BENCH_XI,
    STAGES_MM,
};

use super::common::OutputArgs;

/// Arguments of `bench`.
#[derive(Debug, Args)]
pub struct BenchArgs {
    /// Timed repetitions per case (after one warm-up run); the table gives their median and 95th percentile.
    #[arg(long, default_value_t = 50)]
    pub frames: usize,
    /// Seconds each case may spend on its repetitions (at least 3 are timed).
    #[arg(long, default_value_t = 10.0)]
    pub max_seconds: f64,
    /// Worker-thread counts to run each case with, comma-separated (1 = one core).
    #[arg(long, value_delimiter = ',', default_value = "1,2")]
    pub threads: Vec<usize>,
    /// Image sizes, comma-separated WIDTHxHEIGHT.
    #[arg(long, value_delimiter = ',', default_value = "176x144,640x480")]
    pub sizes: Vec<String>,
    /// Cases to run, comma-separated.
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "recover,recover_per_pixel,recover_with_interval,observe,xi_estimate,replay,publish"
    )]
    pub cases: Vec<CaseArg>,
    /// node_latency: object frames published (cycling the bag's).
    #[arg(long, default_value_t = 200)]
    pub node_frames: usize,
    /// node_latency: publication rate, Hz.
    #[arg(long, default_value_t = 10.0)]
    pub node_rate_hz: f64,
    /// node_latency: the node's `xi` (fixed; `estimate` to let it estimate).
    #[arg(long, default_value = "0.65")]
    pub node_xi: String,
    /// node_latency: the bag played (default: the bundled document holder).
    #[arg(long)]
    pub node_bag: Option<std::path::PathBuf>,
    /// Skip the plain 1 mm grid-search reference (it takes seconds per frame).
    #[arg(long)]
    pub no_reference: bool,
    /// Idle time before each timed repetition, ms (0: back to back). A camera's frame period
    /// (33 at 30 Hz) shows what a node pays when its cores idle between frames.
    #[arg(long, default_value_t = 0.0)]
    pub pause_ms: f64,
    /// Pin the pool's workers one per CPU of the process's affinity mask (the node's
    /// `pin_threads`): after idling, a scheduler that packs idle CPUs can leave two workers
    /// sharing one core.
    #[arg(long)]
    pub pin_threads: bool,
    /// The layer's distance in the frames recover, recover_per_pixel, observe and xi_estimate
    /// time, mm, comma-separated: 500 (57 % of the image translucent), 750, 1000 or 1750 (5 %).
    /// `replay` runs over all of them once.
    #[arg(long, value_delimiter = ',', default_value = "500")]
    pub stage_mm: Vec<f64>,
    #[command(flatten)]
    pub output: OutputArgs,
}

fn parse_size(s: &str) -> Result<(usize, usize)> {
    let parsed = s
        .split_once('x')
        .and_then(|(w, h)| Some((w.trim().parse().ok()?, h.trim().parse().ok()?)));
    match parsed {
        Some((w, h)) if w >= 16 && h >= 16 => Ok((w, h)),
        _ => bail!("--sizes {s:?}: expected WIDTHxHEIGHT, at least 16x16"),
    }
}

/// `--cases`: what `bench` times.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
#[value(rename_all = "snake_case")]
pub enum CaseArg {
    /// Recovery of one frame at a fixed ξ (inversion, noise gate, smooth-surface prior).
    Recover,
    /// Recovery without the smooth-surface prior.
    RecoverPerPixel,
    /// Recovery at an estimated ξ with an interval (its share of the depth's sigma).
    RecoverWithInterval,
    /// Segmentation of one frame.
    Observe,
    /// ξ estimation on one frame.
    #[value(alias = "xi")]
    XiEstimate,
    /// The pipeline over the object frames, ξ estimated online; per frame.
    Replay,
    /// The node's messages for one recovered frame (cloud included) built and serialised to CDR.
    Publish,
    /// The multi-frequency path (20, 50 and 100 MHz) on one frame, against a plain
    /// per-pixel grid fit of two returns (not in the default list: its reference takes
    /// seconds).
    MultiFrequency,
    /// The node over DDS on loopback against a bare publish/subscribe of the same messages.
    NodeLatency,
}

impl CaseArg {
    /// The library's case (`None`: node_latency, which runs apart).
    fn case(self) -> Option<Case> {
        match self {
            CaseArg::Recover => Some(Case::Recover),
            CaseArg::RecoverPerPixel => Some(Case::RecoverPerPixel),
            CaseArg::RecoverWithInterval => Some(Case::RecoverWithInterval),
            CaseArg::Observe => Some(Case::Observe),
            CaseArg::XiEstimate => Some(Case::XiEstimate),
            CaseArg::Replay => Some(Case::Replay),
            CaseArg::Publish => Some(Case::Publish),
            CaseArg::MultiFrequency => Some(Case::MultiFrequency),
            CaseArg::NodeLatency => None,
        }
    }
}

fn ms(v: Option<f64>) -> String {
    v.map_or_else(|| "-".into(), |v| format!("{v:.3}"))
}

/// Runs `bench`.
pub fn run(a: BenchArgs) -> Result<()> {
    let sizes: Vec<(usize, usize)> = a.sizes.iter().map(|s| parse_size(s)).collect::<Result<_>>()?;
    let node_latency = a.cases.contains(&CaseArg::NodeLatency);
    let cases: Vec<Case> = a.cases.iter().filter_map(|c| c.case()).collect();
    if a.threads.contains(&0) || a.threads.is_empty() {
        bail!("--threads: counts of at least 1");
    }
    if a.frames == 0 {
        bail!("--frames must be at least 1");
    }
    if !(a.pause_ms.is_finite() && (0.0..=10_000.0).contains(&a.pause_ms)) {
        bail!("--pause-ms {}: expected 0 to 10000 ms", a.pause_ms);
    }
    let mut stages = vec![];
    for &mm in &a.stage_mm {
        let Some(stage) = STAGES_MM.iter().position(|&s| s == mm) else {
            bail!("--stage-mm {mm}: expected one or more of {STAGES_MM:?}");
        };
        stages.push(stage);
    }
    if stages.is_empty() {
        bail!("--stage-mm: expected one or more of {STAGES_MM:?}");
    }
    // `replay` takes every frame, from the first: once, not once per stage.
    let runs: Vec<(Case, usize)> = cases
        .iter()
        .flat_map(|&case| {
            let per_stage = if case == Case::Replay { vec![0] } else { stages.clone() };
            per_stage.into_iter().map(move |stage| (case, stage))
        })
        .collect();
    let total = (sizes.len() * runs.len() * a.threads.len()) as u64;
    let pb = a.output.progress(total, "bench");
    let mut rows = vec![];
    for &(w, h) in &sizes {
        pb.set_message(format!("rendering {w}x{h}"));
        let scene = BenchScene::new(w, h);
        let multi = cases
            .contains(&Case::MultiFrequency)
            .then(|| MultiFrequencyBench::new(w, h));
        for &(case, stage) in &runs {
            for (k, &threads) in a.threads.iter().enumerate() {
                pb.set_message(format!(
                    "{} {w}x{h} at {} mm, {threads} thread(s)",
                    case.name(),
                    STAGES_MM[stage]
                ));
                let settings = RunSettings {
                    samples: a.frames,
                    budget_s: a.max_seconds,
                    threads,
                    // The reference is single-threaded: once per case and size.
                    reference: !a.no_reference && k == 0,
                    pause: std::time::Duration::from_secs_f64(a.pause_ms / 1e3),
                    stage,
                    pin: a.pin_threads,
                };
                rows.push(match (&multi, case) {
                    (Some(m), Case::MultiFrequency) => run_multi_frequency(m, &settings),
                    _ => run_case(&scene, case, &settings),
                });
                pb.inc(1);
            }
        }
    }
    pb.finish_and_clear();
    let node = if node_latency {
        Some(node_latency_run(&a)?)
    } else {
        None
    };
    let machine = crate::bench::Machine::this();
    let mut text = format!("machine: {}\n", machine.describe());
    text.push_str(&format!(
        "document holder (xi {BENCH_XI}, 240x310 mm) before a wall at 2000 mm; recover, observe and xi_estimate on the frame at {:?} mm, replay over the frames at {:?} mm; up to {} timed runs each (at most {} s a case){}{}\n",
        a.stage_mm,
        STAGES_MM,
        a.frames,
        a.max_seconds,
        if a.pause_ms > 0.0 {
            format!(", each after {} ms idle", a.pause_ms)
        } else {
            String::new()
        },
        if a.pin_threads { ", workers pinned one per CPU" } else { "" }
    ));
    text.push_str(&format!(
        "{:<17} {:>8} {:>6} {:>7} {:>5} {:>10} {:>10} {:>10} {:>13} {:>9} {:>9} {}\n",
        "case",
        "size",
        "mm",
        "threads",
        "runs",
        "median ms",
        "p95 ms",
        "target ms",
        "reference ms",
        "speedup",
        "transl.",
        "agreement (fast vs 1 mm grid)"
    ));
    for r in &rows {
        let agree = r.agreement.map_or_else(String::new, |g| {
            format!(
                "{} px compared, {} differ by > {} mm, max {:.2} mm ({} px with several roots not compared)",
                g.compared, g.disagree, g.tolerance_mm, g.max_diff_mm, g.several_roots
            )
        });
        text.push_str(&format!(
            "{:<17} {:>8} {:>6} {:>7} {:>5} {:>10.3} {:>10.3} {:>10} {:>13} {:>9} {:>8.0}% {}\n",
            r.name,
            r.size,
            r.stage_mm,
            r.threads,
            r.samples,
            r.median_ms,
            r.p95_ms,
            ms(r.target_ms),
            ms(r.reference_ms),
            r.speedup.map_or_else(|| "-".into(), |s| format!("{s:.0}x")),
            100.0 * r.translucent_fraction,
            agree
        ));
    }
    if cases.contains(&Case::MultiFrequency) {
        text.push_str(&format!(
            "multi_frequency: the same frames with phasors at {:?} MHz: every pixel tested against the latched background, the changed ones inverted (layer or opaque); reference: the plain fit of two returns on a 1 mm grid per changed pixel, one thread; agreement over the mask's layer distances\n",
            BENCH_FREQUENCIES_HZ.map(|f| f / 1e6)
        ));
    }
    if let Some(n) = &node {
        text.push_str(&format!(
            "node_latency ({} frames at {} Hz, xi {}): publication -> ~/depth/corrected arrival, median (p95): bare publish/subscribe of the same messages {:.2} ({:.2}) ms over {} of {} frames; through the node {:.2} ({:.2}) ms over {} of {}; added {:.2} ms median, {:.2} ms p95; node memory, peak of each minute: resident {} MB, live heap {} MB\n",
            a.node_frames,
            a.node_rate_hz,
            a.node_xi,
            n.bare.latency_ms[0],
            n.bare.latency_ms[1],
            n.bare.received,
            n.bare.sent,
            n.node.latency_ms[0],
            n.node.latency_ms[1],
            n.node.received,
            n.node.sent,
            n.added_median_ms,
            n.added_p95_ms,
            per_minute_peaks_mb(&n.node_stats["rss_kb"]),
            per_minute_peaks_mb(&n.node_stats["heap_in_use_kb"]),
        ));
        let per_frame: Vec<String> = n
            .frames
            .iter()
            .map(|f| {
                format!(
                    "frame {} ({:.0} % translucent) {:.2} ms",
                    f.frame,
                    100.0 * f.translucent_fraction,
                    f.added_median_ms
                )
            })
            .collect();
        text.push_str(&format!(
            "node_latency added, median per frame of the bag: {}\n",
            per_frame.join("; ")
        ));
    }
    a.output.summary(text.trim_end());
    a.output.write_json(&json!({
        "scene": {
            "xi": BENCH_XI,
            "stages_mm": STAGES_MM,
            "wall_mm": 2000.0,
        },
        "frames": a.frames,
        "max_seconds": a.max_seconds,
        "cores": machine.cores,
        "machine": machine,
        "rows": rows,
        "node_latency": node,
    }))?;
    Ok(())
}

/// The largest of each minute's samples (the node samples once a second), MB, as `[a, b, ...]`.
fn per_minute_peaks_mb(series_kb: &serde_json::Value) -> String {
    let kb: Vec<u64> = series_kb
        .as_array()
        .map(|v| v.iter().filter_map(|x| x.as_u64()).collect())
        .unwrap_or_default();
    let peaks: Vec<String> = kb
        .chunks(60)
        .map(|m| format!("{:.0}", m.iter().copied().max().unwrap_or(0) as f64 / 1024.0))
        .collect();
    format!("[{}]", peaks.join(", "))
}

fn node_latency_run(a: &BenchArgs) -> Result<crate::node::latency::LatencyReport> {
    let mut params = vec!["queue_depth:=2".to_string()];
    if a.pin_threads {
        params.push("pin_threads:=true".to_string());
    }
    match a.node_xi.as_str() {
        "estimate" => {}
        x => {
            let v: f64 = x
                .parse()
                .map_err(|_| anyhow::anyhow!("--node-xi {x:?}: a number in [0, 1) or `estimate`"))?;
            params.push(format!("xi:={v}"));
        }
    }
    if !a.output.json_on_stdout() {
        eprintln!(
            "node_latency: {} frames at {} Hz through a bare echo, then through the node (localhost only)",
            a.node_frames, a.node_rate_hz
        );
    }
    let bag = match &a.node_bag {
        Some(b) => b.clone(),
        None => super::demo::bundled(super::demo::DEMO_BAG)
            .with_context(|| format!("{} not found: give --node-bag BAG", super::demo::DEMO_BAG))?,
    };
    crate::node::latency::measure(&crate::node::latency::LatencyConfig {
        bag,
        background: 10,
        frames: a.node_frames.max(1),
        rate_hz: a.node_rate_hz,
        node_params: params,
        domain_id: std::env::var("ROS_DOMAIN_ID")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(0),
    })
}
