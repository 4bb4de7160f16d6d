//! The ROS 2 node on ros2-client / RustDDS: thin glue around [`core::NodeCore`].
//!
//! DDS callbacks (an async task) pair depth and IR by stamp and queue the
//! pairs; one processing thread takes them, runs the pipeline and publishes;
//! a Rerun thread logs without blocking either.

pub mod core;
pub mod echo;
pub mod inbox;
pub mod latency;
pub mod multifreq;
pub mod params_file;
pub mod peer;
pub mod qos_overrides;
pub mod rlog;
pub mod ros_args;
mod worker;

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use futures::StreamExt;
use log::{error, info, warn};
use ros2_client::{
    qos::{Durability, History},
    Context, ContextOptions, MessageTypeName, Name, NodeName, NodeOptions, ParameterValue, Publisher, QosProfile,
    ServiceMapping, ServiceTypeName,
};
use serde::Serialize;

use crate::msgs::diagnostic_msgs::{DiagnosticArray, DiagnosticStatus, KeyValue};
use crate::msgs::translucent_tof::TranslucencyEstimate;
use crate::msgs::{CameraInfo, Header, Image, PointCloud2, TriggerRequest, TriggerResponse};
use crate::pipeline::PipelineConfig;
use crate::viz::{FrameViz, RerunTarget, VizSink};

use self::core::{DropCause, NodeCore};
use self::inbox::{Command, FramePairer, Inbox, Intake, Next, PairedFrame, StampPairer};
use self::multifreq::{MultiFrequencyNode, MultiFrequencyResult};
use self::ros_args::{NameResolver, ParamValue};

impl ros2_client::Message for Image {}
impl ros2_client::Message for CameraInfo {}
impl ros2_client::Message for PointCloud2 {}
impl ros2_client::Message for TranslucencyEstimate {}
impl ros2_client::Message for TriggerRequest {}
impl ros2_client::Message for TriggerResponse {}
impl ros2_client::Message for DiagnosticArray {}

/// Relative names of the node's interfaces (interfaces.md).
pub mod names {
    /// Depth input.
    pub const DEPTH: &str = "depth/image_raw";
    /// IR input.
    pub const IR: &str = "ir/image_raw";
    /// Intrinsics input.
    pub const INFO: &str = "depth/camera_info";
    /// Latch service.
    pub const LATCH: &str = "~/latch_background";
    /// Clear service.
    pub const CLEAR: &str = "~/clear_background";
    /// Corrected depth.
    pub const CORRECTED: &str = "~/depth/corrected";
    /// Organized cloud.
    pub const POINTS: &str = "~/points";
    /// ξ estimate.
    pub const TRANSLUCENCY: &str = "~/translucency";
    /// Mask.
    pub const MASK: &str = "~/translucent_mask";
    /// The camera beside the corrected depth.
    pub const CORRECTED_INFO: &str = "~/depth/camera_info";
    /// The corrected depth's standard deviation.
    pub const CORRECTED_SIGMA: &str = "~/depth/corrected_sigma";
    /// ROS 2's diagnostics topic.
    pub const DIAGNOSTICS: &str = "/diagnostics";
    /// Per-pixel ξ (multi-frequency path).
    pub const TRANSLUCENCY_IMAGE: &str = "~/translucency_image";

    /// A multi-frequency camera's phasor image at frequency `k`.
    pub fn phasor(k: usize) -> String {
        format!("phasor_{k}/image_raw")
    }
}

/// The settings that may change while the node runs (`ros2 param set`).
#[derive(Debug, Clone)]
pub struct RuntimeSettings {
    /// The pipeline (`xi`, `xi_method`, `threshold_mm`, `physics`, `prior_radius_px`).
    pub config: PipelineConfig,
    /// `background_frames`.
    pub background_frames: usize,
    /// `latch_timeout_s`.
    pub latch_timeout: Duration,
}

/// Reads the run-time settings from the whole parameter set; the error is
/// the reason a change is refused.
pub type Reconfigure = fn(&BTreeMap<String, ParamValue>) -> Result<RuntimeSettings, String>;

/// Everything the node needs to run (built from `--ros-args` by the CLI layer).
#[derive(Debug, Clone)]
pub struct NodeSettings {
    /// The pipeline.
    pub config: PipelineConfig,
    /// Frames averaged per latch (`background_frames`).
    pub background_frames: usize,
    /// A latch gives up after this long.
    pub latch_timeout: Duration,
    /// Latch as soon as frames flow (`latch_on_start`).
    pub latch_on_start: bool,
    /// Publish the input uncorrected while nothing can be recovered (`passthrough`).
    pub passthrough: bool,
    /// Latch again once a moved camera's view holds still (`relatch_on_move`).
    pub relatch_on_move: bool,
    /// Paired frames waiting for processing; more and the oldest is dropped.
    pub queue_depth: usize,
    /// The processing pool's workers pinned one per CPU ([`crate::affinity`]).
    pub pin_threads: bool,
    /// Request/reply mapping of the services.
    pub service_mapping: ServiceMapping,
    /// Node name, namespace, remaps.
    pub names: NameResolver,
    /// `ROS_DOMAIN_ID`.
    pub domain_id: u16,
    /// Keep discovery and traffic on 127.0.0.1 (`ROS_LOCALHOST_ONLY=1` or
    /// `ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`).
    pub localhost_only: bool,
    /// Rerun output.
    pub rerun: RerunTarget,
    /// Parameters as given (`-p`, `--params-file`).
    pub params: Vec<(String, ParamValue)>,
    /// Every parameter of the node with its value (`None`: unset), declared on
    /// the node for `ros2 param list/get/set`.
    pub declared: Vec<(String, Option<ParamValue>)>,
    /// The parameters that may change at run time.
    pub runtime_params: Vec<&'static str>,
    /// Turns a changed parameter set into the run-time settings.
    pub reconfigure: Reconfigure,
    /// `/diagnostics` period (zero: not published).
    pub diagnostics_period: Duration,
    /// Write counters and timings here on exit.
    pub stats_json: Option<PathBuf>,
    /// Stop after this many processed frames (tests, benchmarks).
    pub max_frames: Option<u64>,
    /// A multi-frequency camera's frequencies, Hz (`modulation_frequencies_hz`):
    /// subscribe to `phasor_<k>/image_raw` and take the multi-frequency path.
    pub multi_frequency: Option<Vec<f64>>,
    /// With the multi-frequency path: latch nothing, every frame from two free returns
    /// per pixel (`no_latch`, a moving camera).
    pub no_latch: bool,
}

/// Counters and timings, logged on exit and written with `--stats-json`.
#[derive(Debug, Clone, Default, Serialize)]
pub struct NodeStats {
    /// Depth images received.
    pub depth_received: u64,
    /// IR images received.
    pub ir_received: u64,
    /// Phasor images received, by frequency (multi-frequency path; empty otherwise).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub phasor_received: Vec<u64>,
    /// camera_info messages received.
    pub info_received: u64,
    /// Depth + IR pairs queued.
    pub pairs: u64,
    /// Frames published.
    pub published: u64,
    /// Frames averaged into backgrounds.
    pub latched_frames: u64,
    /// Frames whose input was published uncorrected, by reason (`passthrough`).
    pub passed_through: std::collections::BTreeMap<crate::pipeline::Passthrough, u64>,
    /// Drops by cause.
    pub dropped: std::collections::BTreeMap<DropCause, u64>,
    /// Latch requests, clear requests.
    pub services: [u64; 2],
    /// Frames Rerun could not take.
    pub rerun_dropped: u64,
    /// Frames of which an output could not be handed to DDS (a reliable
    /// writer's window full: a reader not acknowledging).
    pub publish_failures: u64,
    /// Times depth frames resumed after none came for [`INPUT_GAP`] (a driver
    /// restarted, a camera unplugged and back).
    pub input_gaps: u64,
    /// Times the camera was seen to move after the latch.
    pub camera_moves: u64,
    /// Run-time parameter changes applied (`ros2 param set`).
    pub parameter_changes: u64,
    /// Processing time per published frame, ms (from taking the pair off the
    /// queue to its four outputs handed to DDS): median, 95th percentile, max
    /// over the last 8192 frames.
    pub added_latency_ms: [f64; 3],
    /// Resident memory, kB, every second of the run (and at exit).
    pub rss_kb: Vec<u64>,
    /// Heap bytes in live allocations, kB, at the same times (glibc's
    /// `mallinfo2`, empty elsewhere): what the node holds, as against what the
    /// allocator keeps resident.
    pub heap_in_use_kb: Vec<u64>,
    /// ξ last published, with its interval.
    pub xi: Option<[f64; 3]>,
    /// The CPU each worker of the processing pool is pinned to (`pin_threads`;
    /// empty: unpinned).
    pub pinned_cpus: Vec<usize>,
}

/// A pause in the depth input this long or longer is counted as a gap (`input_gaps`).
pub const INPUT_GAP: Duration = Duration::from_secs(1);

/// Which service a pending request belongs to.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Service {
    Latch,
    Clear,
    /// The latch `latch_on_start` asks for (no one waits for its reply).
    OnStart,
}

type Token = (Service, ros2_client::service::RmwRequestId);

struct Outputs {
    corrected: Publisher<Image>,
    corrected_info: Publisher<CameraInfo>,
    sigma: Publisher<Image>,
    mask: Publisher<Image>,
    points: Publisher<PointCloud2>,
    estimate: Publisher<TranslucencyEstimate>,
    /// `~/translucency_image` (multi-frequency path only).
    translucency_image: Option<Publisher<Image>>,
}

fn qos_sensor() -> QosProfile {
    // rclcpp's SensorDataQoS: best effort, volatile, keep last 5.
    QosProfile::subscription_default().history(History::KeepLast { depth: 5 })
}

fn qos_outputs() -> QosProfile {
    // Reliable keep-last: matches reliable and best-effort readers alike.
    QosProfile::publisher_default().history(History::KeepLast { depth: 5 })
}

fn qos_estimate() -> QosProfile {
    QosProfile::publisher_default()
        .durability(Durability::TransientLocal)
        .history(History::KeepLast { depth: 1 })
}

fn qos_diagnostics() -> QosProfile {
    // As diagnostic_updater publishes: reliable, volatile.
    QosProfile::publisher_default().history(History::KeepLast { depth: 10 })
}

fn qos_service() -> QosProfile {
    QosProfile::publisher_default().history(History::KeepLast { depth: 10 })
}

/// Bytes in live heap allocations, kB (glibc: small and large ones), `None` elsewhere.
pub fn heap_in_use_kb() -> Option<u64> {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: mallinfo2 only reads the allocator's counters.
        let m = unsafe { libc::mallinfo2() };
        // glibc's in-use bytes and mappings, and the binary allocator's own mappings.
        Some(((m.uordblks + m.hblkhd + crate::alloc::mapped_bytes()) / 1024) as u64)
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    None
}

/// Appends the resident memory and the live heap to the run's samples.
fn sample_memory(stats: &mut NodeStats) {
    stats.rss_kb.push(rss_kb());
    stats.heap_in_use_kb.extend(heap_in_use_kb());
}

/// Resident set size, kB (Linux), 0 elsewhere.
pub fn rss_kb() -> u64 {
    std::fs::read_to_string("/proc/self/statm")
        .ok()
        .and_then(|s| s.split_whitespace().nth(1).and_then(|v| v.parse::<u64>().ok()))
        .map(|pages| pages * 4)
        .unwrap_or(0)
}

fn ros_name(full: &str) -> anyhow::Result<Name> {
    Name::parse(full).map_err(|e| anyhow::anyhow!("ROS name {full:?}: {e:?}"))
}

fn from_parameter(name: &str, v: &ParameterValue) -> Result<ParamValue, String> {
    Ok(match v {
        ParameterValue::Boolean(b) => ParamValue::Bool(*b),
        ParameterValue::Integer(i) => ParamValue::Integer(*i),
        ParameterValue::Double(x) => ParamValue::Double(*x),
        ParameterValue::String(s) => ParamValue::String(s.clone()),
        ParameterValue::DoubleArray(v) => ParamValue::DoubleArray(v.clone()),
        ParameterValue::NotSet => {
            return Err(format!(
                "{name} cannot be unset at run time (restart the node without it)"
            ))
        }
        _ => {
            return Err(format!(
                "{name}: arrays other than of doubles are not among this node's parameter types"
            ))
        }
    })
}

/// The parameter services' rules: before the node is up every declared value
/// passes (they were checked at start-up); after, a parameter that may change
/// at run time is checked by building the settings it would give, and taken
/// to the processing thread, which applies it from the next frame; the others
/// are refused with the reason.
#[derive(Clone)]
struct ParamGate {
    started: Arc<AtomicBool>,
    current: Arc<Mutex<BTreeMap<String, ParamValue>>>,
    runtime: Vec<&'static str>,
    reconfigure: Reconfigure,
    inbox: Arc<Inbox<Token>>,
}

impl ParamGate {
    fn new(s: &NodeSettings, inbox: Arc<Inbox<Token>>) -> Self {
        // The parameters as given: the settings read from them at start-up are the node's.
        let current = s.params.iter().cloned().collect();
        Self {
            started: Arc::new(AtomicBool::new(false)),
            current: Arc::new(Mutex::new(current)),
            runtime: s.runtime_params.clone(),
            reconfigure: s.reconfigure,
            inbox,
        }
    }

    fn start(&self) {
        self.started.store(true, Ordering::SeqCst);
    }

    fn with_change(&self, name: &str, value: &ParameterValue) -> Result<BTreeMap<String, ParamValue>, String> {
        if qos_overrides::is_override(name) {
            return Err(format!(
                "{name} is read at start-up: restart the node with it (-p or --params-file)"
            ));
        }
        if !self.runtime.contains(&name) {
            return Err(format!(
                "{name} cannot change at run time: restart the node with it (-p or --params-file); run-time parameters: {}",
                self.runtime.join(", ")
            ));
        }
        let v = from_parameter(name, value)?;
        let mut p = self
            .current
            .lock()
            .map_err(|_| "parameter state poisoned".to_string())?
            .clone();
        p.insert(name.to_string(), v);
        Ok(p)
    }

    fn check(&self, name: &str, value: &ParameterValue) -> Result<(), String> {
        if !self.started.load(Ordering::SeqCst) {
            return Ok(());
        }
        let p = self.with_change(name, value)?;
        (self.reconfigure)(&p).map(|_| ())
    }

    fn apply(&self, name: &str, value: &ParameterValue) -> Result<(), String> {
        if !self.started.load(Ordering::SeqCst) {
            return Ok(());
        }
        let p = self.with_change(name, value)?;
        let settings = (self.reconfigure)(&p)?;
        if let Ok(mut c) = self.current.lock() {
            *c = p;
        }
        let forget_evidence = matches!(name, "xi" | "xi_method" | "physics");
        self.inbox
            .push_command(Command::Reconfigure(Box::new(settings), forget_evidence));
        info!("parameter {name} set to {value:?}: applies from the next frame");
        Ok(())
    }
}

/// What the processing thread reports for `/diagnostics`.
#[derive(Debug, Clone, Default)]
struct Live {
    published: u64,
    latched_frames: u64,
    dropped: BTreeMap<DropCause, u64>,
    passed: BTreeMap<crate::pipeline::Passthrough, u64>,
    camera_moved: bool,
    camera_moves: u64,
    parameter_changes: u64,
    publish_failures: u64,
    latch: &'static str,
    xi: Option<[f64; 3]>,
    xi_method: String,
    processing_ms: [f64; 3],
}

/// What the DDS side counted.
struct Inputs<'a> {
    counts: &'a NodeStats,
    unpaired: u64,
    queue_full: u64,
    /// Samples refused before pairing (malformed, oversized), by cause.
    intake: &'a std::collections::BTreeMap<DropCause, u64>,
}

/// The node's `/diagnostics` message: one status with its figures.
fn diagnostics_message(node_fqn: &str, stamp_ns: u64, i: &Inputs, l: &Live) -> DiagnosticArray {
    let mut dropped = l.dropped.clone();
    for (cause, n) in [(DropCause::Unpaired, i.unpaired), (DropCause::QueueFull, i.queue_full)]
        .into_iter()
        .chain(i.intake.iter().map(|(c, n)| (*c, *n)))
    {
        if n > 0 {
            *dropped.entry(cause).or_insert(0) += n;
        }
    }
    let kv = |k: &str, v: String| KeyValue {
        key: k.into(),
        value: v,
    };
    let mut values = vec![
        kv("depth_received", i.counts.depth_received.to_string()),
        kv("ir_received", i.counts.ir_received.to_string()),
        kv("camera_info_received", i.counts.info_received.to_string()),
        kv("frames_in", i.counts.pairs.to_string()),
        kv("frames_out", l.published.to_string()),
        kv("latched_frames", l.latched_frames.to_string()),
        kv("latch", l.latch.to_string()),
    ];
    values.push(kv("camera_moved", l.camera_moved.to_string()));
    for (k, n) in [
        ("camera_moves", l.camera_moves),
        ("latch_requests", i.counts.services[0]),
        ("clear_requests", i.counts.services[1]),
        ("parameter_changes", l.parameter_changes),
        ("input_gaps", i.counts.input_gaps),
        ("publish_failures", l.publish_failures),
    ] {
        values.push(kv(k, n.to_string()));
    }
    for (why, n) in &l.passed {
        let name = serde_json::to_value(why)
            .ok()
            .and_then(|v| v.as_str().map(String::from))
            .unwrap_or_else(|| format!("{why:?}"));
        values.push(kv(&format!("passed_through_{name}"), n.to_string()));
    }
    for (cause, n) in &dropped {
        let name = serde_json::to_value(cause)
            .ok()
            .and_then(|v| v.as_str().map(String::from))
            .unwrap_or_else(|| format!("{cause:?}"));
        values.push(kv(&format!("dropped_{name}"), n.to_string()));
    }
    if let Some([xi, lo, hi]) = l.xi {
        values.push(kv("xi", format!("{xi:.4}")));
        values.push(kv("xi_interval", format!("[{lo:.4}, {hi:.4}]")));
        values.push(kv("xi_method", l.xi_method.clone()));
    }
    let [median, p95, max] = l.processing_ms;
    if median.is_finite() {
        values.push(kv("processing_ms_median", format!("{median:.2}")));
        values.push(kv("processing_ms_p95", format!("{p95:.2}")));
        values.push(kv("processing_ms_max", format!("{max:.2}")));
    }
    let (level, message) = if l.camera_moved {
        (
            DiagnosticStatus::WARN,
            "the camera moved after the latch: not correcting (relatch_on_move, or call ~/latch_background)".into(),
        )
    } else if l.latch != "latched" {
        (
            DiagnosticStatus::WARN,
            format!("no background latched ({}); call ~/latch_background", l.latch),
        )
    } else if l.published == 0 {
        (
            DiagnosticStatus::WARN,
            "background latched; no frame published yet".into(),
        )
    } else {
        (DiagnosticStatus::OK, format!("{} frames published", l.published))
    };
    DiagnosticArray {
        header: Header::new(stamp_ns, ""),
        status: vec![DiagnosticStatus {
            level,
            name: format!("{}: pipeline", node_fqn.trim_start_matches('/')),
            message,
            hardware_id: node_fqn.to_string(),
            values,
        }],
    }
}

fn to_parameter(v: &ParamValue) -> ParameterValue {
    match v {
        ParamValue::Bool(b) => ParameterValue::Boolean(*b),
        ParamValue::Integer(i) => ParameterValue::Integer(*i),
        ParamValue::Double(x) => ParameterValue::Double(*x),
        ParamValue::String(s) => ParameterValue::String(s.clone()),
        ParamValue::DoubleArray(v) => ParameterValue::DoubleArray(v.clone()),
    }
}

/// The DDS participant: on the given domain, only on loopback when asked.
pub fn context(domain_id: u16, localhost_only: bool) -> anyhow::Result<Context> {
    if localhost_only {
        let dp = rustdds::DomainParticipantBuilder::new(domain_id)
            .with_only_networks([std::net::IpAddr::from([127, 0, 0, 1])])
            .build()
            .map_err(|e| anyhow::anyhow!("creating the DDS participant on domain {domain_id}: {e:?}"))?;
        Context::from_domain_participant(dp).map_err(|e| anyhow::anyhow!("ROS 2 context: {e:?}"))
    } else {
        Context::with_options(ContextOptions::new().domain_id(domain_id))
            .map_err(|e| anyhow::anyhow!("creating the DDS participant on domain {domain_id}: {e:?}"))
    }
}

/// Sets glibc's mmap threshold to 32 KiB (unless the environment sets
/// one). By default it rises to the largest buffer freed so far, after which
/// every image-sized buffer (the inputs, their DDS fragments, the outputs:
/// 25 KB-1 MB, allocated and freed per frame on several threads) comes from
/// the heap arenas, which fragment and keep their high-water mark: under a
/// 100 Hz stream the node's resident memory climbed to 430 MB within 30 s
/// with the default (README, The node: `bench --cases node_latency`, `rss_kb`).
fn fix_mmap_threshold() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    if std::env::var_os("MALLOC_MMAP_THRESHOLD_").is_none() {
        // SAFETY: mallopt only sets an allocator parameter; called before the node's threads.
        let ok = unsafe { libc::mallopt(libc::M_MMAP_THRESHOLD, 32 * 1024) };
        if ok != 1 {
            warn!("could not set the allocator's mmap threshold; memory may creep under load");
        }
    }
}

/// Hands the heap arenas' free pages back to the system (glibc's
/// `malloc_trim`): what the smaller per-frame buffers, freed on other
/// threads, leave behind in the middle of an arena.
fn release_free_heap() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only returns free pages; safe at any time.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// Runs the node until SIGINT / SIGTERM (or `max_frames`).
pub fn run(s: NodeSettings) -> anyhow::Result<NodeStats> {
    fix_mmap_threshold();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()?;
    rt.block_on(run_async(s))
}

async fn run_async(s: NodeSettings) -> anyhow::Result<NodeStats> {
    // Rerun first: a bad target is an error before anything appears on DDS.
    let viz = VizSink::start(&s.rerun, "translucent_tof", 2).map_err(|e| anyhow::anyhow!(e))?;
    let ctx = context(s.domain_id, s.localhost_only)?;
    let given: BTreeMap<String, ParamValue> = s.params.iter().cloned().collect();
    let outputs_qos = output_qos(&s, &given)?;
    let inbox: Arc<Inbox<Token>> = Arc::new(Inbox::new(s.queue_depth));
    let gate = ParamGate::new(&s, inbox.clone());
    let node_name = NodeName::new(&s.names.namespace, &s.names.node)
        .map_err(|e| anyhow::anyhow!("node name {}: {e:?}", s.names.node_fqn()))?;
    let mut node = ctx
        .new_node(node_name.clone(), node_options(&s, &outputs_qos, &gate))
        .map_err(|e| anyhow::anyhow!("creating node {}: {e:?}", s.names.node_fqn()))?;
    gate.start();
    rlog::attach_rosout(node.logging_handle());
    let spinner = node.spinner().map_err(|e| anyhow::anyhow!("node spinner: {e:?}"))?;
    let spin_task = tokio::spawn(spinner.spin());

    let topics = Topics {
        ctx: &ctx,
        node_name: &node_name,
        outputs_qos: &outputs_qos,
    };
    let inputs = subscribe(&mut node, &topics, &s)?;
    let (outputs, diagnostics, published) = advertise(&mut node, &topics, &s)?;
    let services = Services::create(&mut node, &s)?;
    announce(&s, &inputs, &published, &services)?;

    let live = Arc::new(Mutex::new(Live::default()));
    let (reply_tx, reply_rx) = tokio::sync::mpsc::unbounded_channel::<(Token, TriggerResponse)>();
    let (done_tx, mut done_rx) = tokio::sync::mpsc::unbounded_channel::<NodeStats>();
    let worker = {
        let inbox = inbox.clone();
        let settings = s.clone();
        let live = live.clone();
        std::thread::Builder::new()
            .name("pipeline".into())
            .spawn(move || worker::worker(settings, inbox, outputs, viz, reply_tx, done_tx, live))?
    };
    if s.latch_on_start {
        info!(
            "latch_on_start: the background is latched from the first {} frames",
            s.background_frames
        );
        inbox.push_command(Command::Latch((Service::OnStart, Default::default())));
    }
    let mut events = Events {
        s: &s,
        inbox: &inbox,
        live: &live,
        node: &node,
        diagnostics,
        multi: !inputs.phasor_t.is_empty(),
        pairer: StampPairer::new(s.queue_depth.max(4) * 2),
        frame_pairer: FramePairer::new(inputs.phasor_t.len(), s.queue_depth.max(4) * 2),
        counts: NodeStats {
            phasor_received: vec![0; inputs.phasor_t.len()],
            ..NodeStats::default()
        },
        last_info: None,
        intake: Intake::default(),
        last_depth: None,
    };
    let final_stats = events.serve(&inputs, &services, reply_rx, &mut done_rx).await?;
    inbox.push_command(Command::Shutdown);
    let stats = match final_stats {
        Some(st) => st,
        None => done_rx.recv().await.unwrap_or_default(),
    };
    let _ = worker.join();
    let Events {
        counts,
        pairer,
        frame_pairer,
        intake,
        ..
    } = events;
    // The spinner's entities (parameter services, /rosout, /clock) go before the
    // participant: dropped after it, RustDDS logs an error for each of them.
    drop(node);
    if tokio::time::timeout(Duration::from_secs(2), spin_task).await.is_err() {
        warn!("the node's spinner did not stop within 2 s");
    }
    let stats = with_intake_counts(stats, &counts, pairer.unpaired + frame_pairer.unpaired, &inbox, intake);
    report(&s, stats)
}

/// The final counters in the log and, if asked, in a JSON file.
fn report(s: &NodeSettings, stats: NodeStats) -> anyhow::Result<NodeStats> {
    info!("{}", summary(&stats));
    if let Some(p) = &s.stats_json {
        let text = serde_json::to_string_pretty(&stats)?;
        crate::files::write_atomic(p, text.as_bytes())?;
    }
    Ok(stats)
}

/// Each output's full name and QoS: the default, changed by `qos_overrides./TOPIC.publisher.*`
/// (an override for a topic the node does not publish is an error).
fn output_qos(s: &NodeSettings, given: &BTreeMap<String, ParamValue>) -> anyhow::Result<Vec<(String, QosProfile)>> {
    let multi_outputs = s
        .multi_frequency
        .as_ref()
        .map(|_| (names::TRANSLUCENCY_IMAGE, qos_outputs()));
    let outputs_qos: Vec<(String, QosProfile)> = [
        (names::CORRECTED, qos_outputs()),
        (names::CORRECTED_INFO, qos_outputs()),
        (names::CORRECTED_SIGMA, qos_outputs()),
        (names::MASK, qos_outputs()),
        (names::POINTS, qos_outputs()),
        (names::TRANSLUCENCY, qos_estimate()),
        (names::DIAGNOSTICS, qos_diagnostics()),
    ]
    .into_iter()
    .chain(multi_outputs)
    .map(|(n, base)| {
        let full = s.names.resolve(n)?;
        let q = qos_overrides::apply(&base, &full, given)?;
        Ok((full, q))
    })
    .collect::<anyhow::Result<_>>()?;
    let topics: Vec<String> = outputs_qos.iter().map(|(t, _)| t.clone()).collect();
    qos_overrides::check_names(given.keys(), &topics)?;
    Ok(outputs_qos)
}

/// The node's options: its parameters declared (the outputs' QoS overrides among them, read
/// only), checked and applied through `gate`.
fn node_options(s: &NodeSettings, outputs_qos: &[(String, QosProfile)], gate: &ParamGate) -> NodeOptions {
    let mut options = NodeOptions::new().enable_rosout(true);
    for (k, v) in &s.declared {
        options = options.declare_parameter(k, v.as_ref().map(to_parameter).unwrap_or(ParameterValue::NotSet));
    }
    for (t, q) in outputs_qos {
        for (k, v) in qos_overrides::describe(t, q) {
            options = options.declare_parameter(&k, to_parameter(&v));
        }
    }
    let (g1, g2) = (gate.clone(), gate.clone());
    options
        .parameter_validator(Box::new(move |n, v| g1.check(n, v)))
        .parameter_set_action(Box::new(move |n, v| g2.apply(n, v)))
}

/// What the node's topics are made with.
struct Topics<'a> {
    ctx: &'a Context,
    node_name: &'a NodeName,
    outputs_qos: &'a [(String, QosProfile)],
}

impl Topics<'_> {
    /// A topic straight on the participant (as ros2-client's create_topic does), with
    /// resource limits equal to its KeepLast depth: RustDDS otherwise keeps 64 whole messages
    /// in each reader's cache, and up to 8192 not yet acknowledged in each writer's (a
    /// KeepLast writer of the DDS spec keeps its depth; RustDDS keeps what a reliable reader
    /// has not acknowledged). Readers and writers inherit the limits from the topic.
    fn topic(&self, name: &str, pkg: &str, ty: &str, qos: &QosProfile) -> anyhow::Result<rustdds::Topic> {
        let depth = match qos.history {
            History::KeepLast { depth } => i32::try_from(depth).unwrap_or(i32::MAX).max(1),
            History::KeepAll => 64, // RustDDS's own default (no topic of this node keeps all)
        };
        let limits = rustdds::policy::ResourceLimits {
            max_samples: depth,
            max_instances: 1,
            max_samples_per_instance: depth,
        };
        let qos = rustdds::QosPolicies::from(qos)
            .modify_by(&rustdds::QosPolicyBuilder::new().resource_limits(limits).build());
        self.ctx
            .domain_participant()
            .create_topic(
                ros_name(name)?.to_dds_name("rt", self.node_name, ""),
                MessageTypeName::new(pkg, ty).dds_msg_type(),
                &qos,
                rustdds::TopicKind::NoKey,
            )
            .map_err(|e| anyhow::anyhow!("topic {name}: {e:?}"))
    }

    /// An output's QoS (its overrides applied).
    fn qos_of(&self, full: &str) -> QosProfile {
        self.outputs_qos
            .iter()
            .find(|(t, _)| t == full)
            .map(|(_, q)| q.clone())
            .unwrap_or_else(qos_outputs)
    }

    /// A publisher of an output; its full name.
    fn publisher<M: ros2_client::Message>(
        &self,
        node: &mut ros2_client::Node,
        s: &NodeSettings,
        name: &str,
        (pkg, ty): (&str, &str),
    ) -> anyhow::Result<(Publisher<M>, String)> {
        let full = s.names.resolve(name)?;
        let q = self.qos_of(&full);
        let t = self.topic(&full, pkg, ty, &q)?;
        let p = node
            .create_publisher(&t, Some(q))
            .map_err(|e| anyhow::anyhow!("publisher {full}: {e:?}"))?;
        Ok((p, full))
    }

    /// A subscription to `full` with the sensor-data QoS.
    fn subscription<M: 'static>(
        &self,
        node: &mut ros2_client::Node,
        full: &str,
        (pkg, ty): (&str, &str),
    ) -> anyhow::Result<ros2_client::Subscription<M>> {
        let sensor = qos_sensor();
        let t = self.topic(full, pkg, ty, &sensor)?;
        node.create_subscription::<M>(&t, Some(sensor))
            .map_err(|e| anyhow::anyhow!("subscribing {full}: {e:?}"))
    }
}

/// The node's subscriptions and their full names.
struct Subscribed {
    depth_t: String,
    ir_t: String,
    info_t: String,
    /// A multi-frequency camera's phasor images, one topic per frequency.
    phasor_t: Vec<String>,
    depth: ros2_client::Subscription<Image>,
    ir: ros2_client::Subscription<Image>,
    info: ros2_client::Subscription<CameraInfo>,
    phasors: Vec<ros2_client::Subscription<Image>>,
}

fn subscribe(node: &mut ros2_client::Node, topics: &Topics, s: &NodeSettings) -> anyhow::Result<Subscribed> {
    const IMAGE: (&str, &str) = ("sensor_msgs", "Image");
    let (depth_t, ir_t, info_t) = (
        s.names.resolve(names::DEPTH)?,
        s.names.resolve(names::IR)?,
        s.names.resolve(names::INFO)?,
    );
    let frequencies = s.multi_frequency.as_ref().map_or(0, |f| f.len());
    let phasor_t: Vec<String> = (0..frequencies)
        .map(|k| s.names.resolve(&names::phasor(k)))
        .collect::<Result<_, _>>()?;
    Ok(Subscribed {
        depth: topics.subscription(node, &depth_t, IMAGE)?,
        ir: topics.subscription(node, &ir_t, IMAGE)?,
        info: topics.subscription(node, &info_t, ("sensor_msgs", "CameraInfo"))?,
        phasors: phasor_t
            .iter()
            .map(|name| topics.subscription(node, name, IMAGE))
            .collect::<anyhow::Result<_>>()?,
        depth_t,
        ir_t,
        info_t,
        phasor_t,
    })
}

/// The output publishers, /diagnostics's, and the outputs' full names (for the log).
fn advertise(
    node: &mut ros2_client::Node,
    topics: &Topics,
    s: &NodeSettings,
) -> anyhow::Result<(Outputs, Publisher<DiagnosticArray>, Vec<String>)> {
    const IMAGE: (&str, &str) = ("sensor_msgs", "Image");
    let (corrected, corrected_n) = topics.publisher(node, s, names::CORRECTED, IMAGE)?;
    let (corrected_info, cinfo_n) = topics.publisher(node, s, names::CORRECTED_INFO, ("sensor_msgs", "CameraInfo"))?;
    let (sigma, sigma_n) = topics.publisher(node, s, names::CORRECTED_SIGMA, IMAGE)?;
    let (mask, mask_n) = topics.publisher(node, s, names::MASK, IMAGE)?;
    let (points, points_n) = topics.publisher(node, s, names::POINTS, ("sensor_msgs", "PointCloud2"))?;
    let estimate_type = (crate::msgs::translucent_tof::PACKAGE, "TranslucencyEstimate");
    let (estimate, est_n) = topics.publisher(node, s, names::TRANSLUCENCY, estimate_type)?;
    let (diagnostics, diag_n) =
        topics.publisher(node, s, names::DIAGNOSTICS, ("diagnostic_msgs", "DiagnosticArray"))?;
    let translucency_image = match s.multi_frequency {
        Some(_) => Some(topics.publisher(node, s, names::TRANSLUCENCY_IMAGE, IMAGE)?.0),
        None => None,
    };
    let outputs = Outputs {
        corrected,
        corrected_info,
        sigma,
        mask,
        points,
        estimate,
        translucency_image,
    };
    Ok((
        outputs,
        diagnostics,
        vec![corrected_n, cinfo_n, sigma_n, points_n, mask_n, est_n, diag_n],
    ))
}

/// The latch and clear services and their full names.
struct Services {
    latch_n: String,
    clear_n: String,
    latch: ros2_client::Server<TriggerRequest, TriggerResponse>,
    clear: ros2_client::Server<TriggerRequest, TriggerResponse>,
}

impl Services {
    fn create(node: &mut ros2_client::Node, s: &NodeSettings) -> anyhow::Result<Self> {
        let trigger = ServiceTypeName::new("std_srvs", "Trigger");
        let mut server = |full: &str| {
            node.create_server::<TriggerRequest, TriggerResponse>(
                s.service_mapping,
                &ros_name(full)?,
                &trigger,
                qos_service(),
                qos_service(),
            )
            .map_err(|e| anyhow::anyhow!("service {full}: {e:?}"))
        };
        let (latch_n, clear_n) = (s.names.resolve(names::LATCH)?, s.names.resolve(names::CLEAR)?);
        Ok(Self {
            latch: server(&latch_n)?,
            clear: server(&clear_n)?,
            latch_n,
            clear_n,
        })
    }

    /// Sends a service's reply (the latch on start has no caller: its outcome is logged).
    async fn reply(&self, (which, id): Token, resp: TriggerResponse) {
        let (srv, name) = match which {
            Service::Latch => (&self.latch, &self.latch_n),
            Service::Clear => (&self.clear, &self.clear_n),
            Service::OnStart => {
                if resp.success {
                    info!("latch_on_start: {}", resp.message);
                } else {
                    warn!("latch_on_start: {}", resp.message);
                }
                return;
            }
        };
        if resp.success {
            info!("{name}: {}", resp.message);
        } else {
            warn!("{name}: {}", resp.message);
        }
        if let Err(e) = srv.async_send_response(id, resp).await {
            warn!("sending a service reply: {e:?}");
        }
    }
}

/// The node's first log line: what it reads, publishes and serves.
fn announce(s: &NodeSettings, i: &Subscribed, published: &[String], services: &Services) -> anyhow::Result<()> {
    info!(
        "{} up on domain {}{}: depth {}, IR {}, camera_info {}; publishes {}; services {}, {} ({:?} mapping); background_frames {}, xi {}",
        s.names.node_fqn(),
        s.domain_id,
        if s.localhost_only { " (localhost only)" } else { "" },
        i.depth_t,
        i.ir_t,
        i.info_t,
        published.join(", "),
        services.latch_n,
        services.clear_n,
        s.service_mapping,
        s.background_frames,
        match s.config.xi {
            crate::pipeline::XiChoice::Fixed(x) => format!("fixed {x}"),
            crate::pipeline::XiChoice::Estimate(m) => format!("estimated ({})", m.as_str()),
        }
    );
    if let Some(e) = s.config.model.sensor.depth_engine() {
        info!(
            "depth engine: depth and IR unwrapped from {:?} Hz{}",
            e.frequencies_hz,
            e.max_disagreement_mm.map_or(String::new(), |mm| format!(
                ", pixels invalid past {mm} mm of disagreement"
            ))
        );
    }
    if let Some(f) = &s.multi_frequency {
        info!(
            "multi-frequency path: phasors at {f:?} Hz on {}; publishes {}{}",
            i.phasor_t.join(", "),
            s.names.resolve(names::TRANSLUCENCY_IMAGE)?,
            if s.no_latch {
                "; no latch: every frame from two free returns per pixel, xi not measured"
            } else {
                ""
            }
        );
    }
    Ok(())
}

/// The DDS side of the node: pairs what arrives, queues it for the worker, answers the
/// services and publishes /diagnostics.
struct Events<'a> {
    s: &'a NodeSettings,
    inbox: &'a Arc<Inbox<Token>>,
    live: &'a Arc<Mutex<Live>>,
    node: &'a ros2_client::Node,
    diagnostics: Publisher<DiagnosticArray>,
    /// A multi-frequency camera: frames are completed by [`FramePairer`].
    multi: bool,
    pairer: StampPairer,
    frame_pairer: FramePairer,
    counts: NodeStats,
    last_info: Option<CameraInfo>,
    intake: Intake,
    /// When the last depth image arrived (for `input_gaps`).
    last_depth: Option<Instant>,
}

/// Where an image arrived: depth, IR, or frequency `k`'s phasors.
#[derive(Clone, Copy)]
enum Slot {
    Depth,
    Ir,
    Phasor(usize),
}

impl Events<'_> {
    /// Serves until the inputs end, a signal, or the worker is done (its counters then).
    async fn serve(
        &mut self,
        i: &Subscribed,
        services: &Services,
        mut replies: tokio::sync::mpsc::UnboundedReceiver<(Token, TriggerResponse)>,
        done: &mut tokio::sync::mpsc::UnboundedReceiver<NodeStats>,
    ) -> anyhow::Result<Option<NodeStats>> {
        let s = self.s;
        let mut diag_tick = tokio::time::interval(if s.diagnostics_period.is_zero() {
            Duration::from_secs(3600 * 24 * 365)
        } else {
            s.diagnostics_period
        });
        diag_tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut depth_stream = std::pin::pin!(i.depth.async_stream());
        let mut ir_stream = std::pin::pin!(i.ir.async_stream());
        let mut info_stream = std::pin::pin!(i.info.async_stream());
        let mut latch_stream = std::pin::pin!(services.latch.receive_request_stream());
        let mut clear_stream = std::pin::pin!(services.clear.receive_request_stream());
        let multi = !i.phasors.is_empty();
        let mut phasor_stream = futures::stream::select_all(
            i.phasors
                .iter()
                .enumerate()
                .map(|(k, sub)| Box::pin(sub.async_stream().map(move |m| (k, m)))),
        );
        // Both listeners live across the loop: a `ctrl_c()` made anew each turn misses a
        // signal that arrives while a turn's branch runs.
        let mut sigint = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::interrupt())?;
        let mut sigterm = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
        loop {
            tokio::select! {
                m = depth_stream.next() => match m {
                    Some(Ok((img, _))) => self.on_image(Slot::Depth, &i.depth_t, img),
                    Some(Err(e)) => self.intake.unreadable(&i.depth_t, &e),
                    None => return Ok(None),
                },
                m = ir_stream.next() => match m {
                    Some(Ok((img, _))) => self.on_image(Slot::Ir, &i.ir_t, img),
                    Some(Err(e)) => self.intake.unreadable(&i.ir_t, &e),
                    None => return Ok(None),
                },
                m = phasor_stream.next(), if multi => match m {
                    Some((k, Ok((img, _)))) => self.on_image(Slot::Phasor(k), &i.phasor_t[k], img),
                    Some((k, Err(e))) => self.intake.unreadable(&i.phasor_t[k], &e),
                    None => return Ok(None),
                },
                m = info_stream.next() => match m {
                    Some(Ok((ci, _))) => self.on_camera_info(&i.info_t, ci),
                    Some(Err(e)) => self.intake.unreadable(&i.info_t, &e),
                    None => return Ok(None),
                },
                m = latch_stream.next() => match m {
                    Some(Ok((id, _))) => { self.counts.services[0] += 1; self.inbox.push_command(Command::Latch((Service::Latch, id))); }
                    Some(Err(e)) => warn!("{}: unreadable request ({e:?})", services.latch_n),
                    None => return Ok(None),
                },
                m = clear_stream.next() => match m {
                    Some(Ok((id, _))) => { self.counts.services[1] += 1; self.inbox.push_command(Command::Clear((Service::Clear, id))); }
                    Some(Err(e)) => warn!("{}: unreadable request ({e:?})", services.clear_n),
                    None => return Ok(None),
                },
                Some((token, resp)) = replies.recv() => services.reply(token, resp).await,
                _ = diag_tick.tick(), if !s.diagnostics_period.is_zero() => self.publish_diagnostics(),
                st = done.recv() => return Ok(st),
                _ = sigint.recv() => { info!("SIGINT: shutting down"); return Ok(None); },
                _ = sigterm.recv() => { info!("SIGTERM: shutting down"); return Ok(None); },
            }
        }
    }

    /// Takes an image in and queues the frame it completes, if any.
    fn on_image(&mut self, slot: Slot, topic: &str, img: Image) {
        match slot {
            Slot::Depth => {
                self.counts.depth_received += 1;
                let now = Instant::now();
                if let Some(gap) = self.last_depth.map(|t| now - t).filter(|g| *g >= INPUT_GAP) {
                    self.counts.input_gaps += 1;
                    info!(
                        "depth frames resumed after {:.1} s without (input_gaps)",
                        gap.as_secs_f64()
                    );
                }
                self.last_depth = Some(now);
            }
            Slot::Ir => self.counts.ir_received += 1,
            Slot::Phasor(k) => {
                if let Some(n) = self.counts.phasor_received.get_mut(k) {
                    *n += 1;
                }
            }
        }
        let Some(img) = self.intake.image(topic, img, self.last_info.as_ref()) else {
            return;
        };
        let frame = match (slot, self.multi) {
            (Slot::Depth, false) => self.pairer.depth(img).map(PairedFrame::from),
            (Slot::Ir, false) => self.pairer.ir(img).map(PairedFrame::from),
            (Slot::Depth, true) => self.frame_pairer.offer(0, img),
            (Slot::Ir, true) => self.frame_pairer.offer(1, img),
            (Slot::Phasor(k), _) => self.frame_pairer.offer(2 + k, img),
        };
        if let Some(f) = frame {
            self.counts.pairs += 1;
            self.inbox.push_frame(f);
        }
    }

    /// Takes a camera_info in; only a change of the camera concerns the pipeline.
    fn on_camera_info(&mut self, topic: &str, ci: CameraInfo) {
        self.counts.info_received += 1;
        let Some(ci) = self.intake.camera_info(topic, ci) else {
            return;
        };
        let changed = self
            .last_info
            .as_ref()
            .is_none_or(|l| l.k != ci.k || l.width != ci.width || l.height != ci.height || l.d != ci.d);
        if changed {
            self.inbox.push_command(Command::CameraInfo(Box::new(ci.clone())));
            self.last_info = Some(ci);
        }
    }

    fn publish_diagnostics(&self) {
        let inputs = Inputs {
            counts: &self.counts,
            unpaired: self.pairer.unpaired + self.frame_pairer.unpaired,
            queue_full: self.inbox.dropped(),
            intake: &self.intake.drops.by_cause,
        };
        let snapshot = self.live.lock().map(|l| l.clone()).unwrap_or_default();
        let stamp = self.node.time_now().to_nanos();
        let msg = diagnostics_message(
            &self.s.names.node_fqn(),
            u64::try_from(stamp).unwrap_or(0),
            &inputs,
            &snapshot,
        );
        if let Err(e) = self.diagnostics.publish(msg) {
            warn!("publishing {}: {e:?}", names::DIAGNOSTICS);
        }
    }
}

/// The worker's counters with what the DDS side counted: inputs received, pairs, service
/// calls, and the frames dropped before the worker saw them.
fn with_intake_counts(
    mut stats: NodeStats,
    counts: &NodeStats,
    unpaired: u64,
    inbox: &Inbox<Token>,
    intake: Intake,
) -> NodeStats {
    stats.depth_received = counts.depth_received;
    stats.input_gaps = counts.input_gaps;
    stats.ir_received = counts.ir_received;
    stats.phasor_received.clone_from(&counts.phasor_received);
    stats.info_received = counts.info_received;
    stats.pairs = counts.pairs;
    stats.services = counts.services;
    if unpaired > 0 {
        stats.dropped.insert(DropCause::Unpaired, unpaired);
    }
    let queue = inbox.dropped();
    if queue > 0 {
        stats.dropped.insert(DropCause::QueueFull, queue);
    }
    for (cause, n) in intake.drops.by_cause {
        *stats.dropped.entry(cause).or_insert(0) += n;
    }
    stats
}

/// One line of counters.
pub fn summary(st: &NodeStats) -> String {
    let drops: Vec<String> = st.dropped.iter().map(|(c, n)| format!("{c:?} {n}")).collect();
    format!(
        "received depth {} IR {} camera_info {}; {} pairs, {} latched, {} published; dropped: {}; added latency median {:.2} ms, p95 {:.2} ms",
        st.depth_received,
        st.ir_received,
        st.info_received,
        st.pairs,
        st.latched_frames,
        st.published,
        if drops.is_empty() { "none".into() } else { drops.join(", ") },
        st.added_latency_ms[0],
        st.added_latency_ms[1]
    )
}

/// Median, 95th percentile and maximum (NaN for none).
pub fn percentiles(v: &mut [f64]) -> [f64; 3] {
    if v.is_empty() {
        return [f64::NAN; 3];
    }
    v.sort_by(f64::total_cmp);
    let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
    [at(0.5), at(0.95), v[v.len() - 1]]
}
