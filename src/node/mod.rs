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
use self::inbox::{Command, FramePairer, Inbox, Intake, Next, StampPairer};
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
    let r = |n: &str| s.names.resolve(n);
    // Each output's QoS: the default, changed by `qos_overrides./TOPIC.publisher.*`.
    let given: BTreeMap<String, ParamValue> = s.params.iter().cloned().collect();
    let multi_outputs = s
        .multi_frequency
        .as_ref()
        .map(|_| (names::TRANSLUCENCY_IMAGE, qos_outputs()));
    let outputs_qos: Vec<(String, QosProfile)> = [
        (names::CORRECTED, qos_outputs()),
        (names::CORRECTED_INFO, qos_outputs()),
        (names::MASK, qos_outputs()),
        (names::POINTS, qos_outputs()),
        (names::TRANSLUCENCY, qos_estimate()),
        (names::DIAGNOSTICS, qos_diagnostics()),
    ]
    .into_iter()
    .chain(multi_outputs)
    .map(|(n, base)| {
        let full = r(n)?;
        let q = qos_overrides::apply(&base, &full, &given)?;
        Ok((full, q))
    })
    .collect::<anyhow::Result<_>>()?;
    let topics: Vec<String> = outputs_qos.iter().map(|(t, _)| t.clone()).collect();
    qos_overrides::check_names(given.keys(), &topics)?;
    let qos_of = |full: &str| {
        outputs_qos
            .iter()
            .find(|(t, _)| t == full)
            .map(|(_, q)| q.clone())
            .unwrap_or_else(qos_outputs)
    };

    let inbox: Arc<Inbox<Token>> = Arc::new(Inbox::new(s.queue_depth));
    let gate = ParamGate::new(&s, inbox.clone());
    let mut options = NodeOptions::new().enable_rosout(true);
    for (k, v) in &s.declared {
        options = options.declare_parameter(k, v.as_ref().map(to_parameter).unwrap_or(ParameterValue::NotSet));
    }
    for (t, q) in &outputs_qos {
        for (k, v) in qos_overrides::describe(t, q) {
            options = options.declare_parameter(&k, to_parameter(&v));
        }
    }
    let (g1, g2) = (gate.clone(), gate.clone());
    options = options
        .parameter_validator(Box::new(move |n, v| g1.check(n, v)))
        .parameter_set_action(Box::new(move |n, v| g2.apply(n, v)));
    let node_name = NodeName::new(&s.names.namespace, &s.names.node)
        .map_err(|e| anyhow::anyhow!("node name {}: {e:?}", s.names.node_fqn()))?;
    let mut node = ctx
        .new_node(node_name.clone(), options)
        .map_err(|e| anyhow::anyhow!("creating node {}: {e:?}", s.names.node_fqn()))?;
    gate.start();
    rlog::attach_rosout(node.logging_handle());
    let spinner = node.spinner().map_err(|e| anyhow::anyhow!("node spinner: {e:?}"))?;
    let spin_task = tokio::spawn(spinner.spin());

    // Every topic straight on the participant (as ros2-client's create_topic does), with
    // resource limits equal to its KeepLast depth: RustDDS otherwise keeps 64 whole messages
    // in each reader's cache, and up to 8192 not yet acknowledged in each writer's (a
    // KeepLast writer of the DDS spec keeps its depth; RustDDS keeps what a reliable reader
    // has not acknowledged). Readers and writers inherit the limits from the topic.
    let topic = |name: &str, pkg: &str, ty: &str, qos: &QosProfile| -> anyhow::Result<rustdds::Topic> {
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
        ctx.domain_participant()
            .create_topic(
                ros_name(name)?.to_dds_name("rt", &node_name, ""),
                MessageTypeName::new(pkg, ty).dds_msg_type(),
                &qos,
                rustdds::TopicKind::NoKey,
            )
            .map_err(|e| anyhow::anyhow!("topic {name}: {e:?}"))
    };
    let (depth_t, ir_t, info_t) = (r(names::DEPTH)?, r(names::IR)?, r(names::INFO)?);
    let sensor = qos_sensor();
    let t = topic(&depth_t, "sensor_msgs", "Image", &sensor)?;
    let depth_sub = node
        .create_subscription::<Image>(&t, Some(sensor.clone()))
        .map_err(|e| anyhow::anyhow!("subscribing {depth_t}: {e:?}"))?;
    let t = topic(&ir_t, "sensor_msgs", "Image", &sensor)?;
    let ir_sub = node
        .create_subscription::<Image>(&t, Some(sensor.clone()))
        .map_err(|e| anyhow::anyhow!("subscribing {ir_t}: {e:?}"))?;
    let t = topic(&info_t, "sensor_msgs", "CameraInfo", &sensor)?;
    let info_sub = node
        .create_subscription::<CameraInfo>(&t, Some(sensor.clone()))
        .map_err(|e| anyhow::anyhow!("subscribing {info_t}: {e:?}"))?;
    // A multi-frequency camera's phasor images, one topic per frequency.
    let frequencies = s.multi_frequency.as_ref().map_or(0, |f| f.len());
    let phasor_t: Vec<String> = (0..frequencies)
        .map(|k| r(&names::phasor(k)))
        .collect::<Result<_, _>>()?;
    let phasor_subs = phasor_t
        .iter()
        .map(|name| {
            let t = topic(name, "sensor_msgs", "Image", &sensor)?;
            node.create_subscription::<Image>(&t, Some(sensor.clone()))
                .map_err(|e| anyhow::anyhow!("subscribing {name}: {e:?}"))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;

    let publisher = |name: &str, pkg: &str, ty: &str| -> anyhow::Result<_> {
        let full = r(name)?;
        let q = qos_of(&full);
        let t = topic(&full, pkg, ty, &q)?;
        Ok((full, t, q))
    };
    let pe = |n: &str| {
        let n = n.to_string();
        move |e| anyhow::anyhow!("publisher {n}: {e:?}")
    };
    let (corrected_n, t, q) = publisher(names::CORRECTED, "sensor_msgs", "Image")?;
    let corrected = node.create_publisher(&t, Some(q)).map_err(pe(&corrected_n))?;
    let (cinfo_n, t, q) = publisher(names::CORRECTED_INFO, "sensor_msgs", "CameraInfo")?;
    let corrected_info = node.create_publisher(&t, Some(q)).map_err(pe(&cinfo_n))?;
    let (sigma_n, t, q) = publisher(names::CORRECTED_SIGMA, "sensor_msgs", "Image")?;
    let sigma = node.create_publisher(&t, Some(q)).map_err(pe(&sigma_n))?;
    let (mask_n, t, q) = publisher(names::MASK, "sensor_msgs", "Image")?;
    let mask = node.create_publisher(&t, Some(q)).map_err(pe(&mask_n))?;
    let (points_n, t, q) = publisher(names::POINTS, "sensor_msgs", "PointCloud2")?;
    let points = node.create_publisher(&t, Some(q)).map_err(pe(&points_n))?;
    let (est_n, t, q) = publisher(
        names::TRANSLUCENCY,
        crate::msgs::translucent_tof::PACKAGE,
        "TranslucencyEstimate",
    )?;
    let estimate = node.create_publisher(&t, Some(q)).map_err(pe(&est_n))?;
    let (diag_n, t, q) = publisher(names::DIAGNOSTICS, "diagnostic_msgs", "DiagnosticArray")?;
    let diagnostics: Publisher<DiagnosticArray> = node.create_publisher(&t, Some(q)).map_err(pe(&diag_n))?;
    let translucency_image = match s.multi_frequency {
        Some(_) => {
            let (n, t, q) = publisher(names::TRANSLUCENCY_IMAGE, "sensor_msgs", "Image")?;
            Some(node.create_publisher(&t, Some(q)).map_err(pe(&n))?)
        }
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

    let trigger = ServiceTypeName::new("std_srvs", "Trigger");
    let (latch_n, clear_n) = (r(names::LATCH)?, r(names::CLEAR)?);
    let latch_srv = node
        .create_server::<TriggerRequest, TriggerResponse>(
            s.service_mapping,
            &ros_name(&latch_n)?,
            &trigger,
            qos_service(),
            qos_service(),
        )
        .map_err(|e| anyhow::anyhow!("service {latch_n}: {e:?}"))?;
    let clear_srv = node
        .create_server::<TriggerRequest, TriggerResponse>(
            s.service_mapping,
            &ros_name(&clear_n)?,
            &trigger,
            qos_service(),
            qos_service(),
        )
        .map_err(|e| anyhow::anyhow!("service {clear_n}: {e:?}"))?;

    info!(
        "{} up on domain {}{}: depth {depth_t}, IR {ir_t}, camera_info {info_t}; publishes {corrected_n}, {cinfo_n}, {points_n}, {mask_n}, {est_n}, {diag_n}; services {latch_n}, {clear_n} ({:?} mapping); background_frames {}, xi {}",
        s.names.node_fqn(),
        s.domain_id,
        if s.localhost_only { " (localhost only)" } else { "" },
        s.service_mapping,
        s.background_frames,
        match s.config.xi {
            crate::pipeline::XiChoice::Fixed(x) => format!("fixed {x}"),
            crate::pipeline::XiChoice::Estimate(m) => format!("estimated ({})", m.as_str()),
        }
    );
    if let Some(f) = &s.multi_frequency {
        info!(
            "multi-frequency path: phasors at {f:?} Hz on {}; publishes {}{}",
            phasor_t.join(", "),
            r(names::TRANSLUCENCY_IMAGE)?,
            if s.no_latch {
                "; no latch: every frame from two free returns per pixel, xi not measured"
            } else {
                ""
            }
        );
    }

    let live = Arc::new(Mutex::new(Live::default()));
    let (reply_tx, mut reply_rx) = tokio::sync::mpsc::unbounded_channel::<(Token, TriggerResponse)>();
    let (done_tx, mut done_rx) = tokio::sync::mpsc::unbounded_channel::<NodeStats>();
    let worker = {
        let inbox = inbox.clone();
        let settings = s.clone();
        let live = live.clone();
        std::thread::Builder::new()
            .name("pipeline".into())
            .spawn(move || worker(settings, inbox, outputs, viz, reply_tx, done_tx, live))?
    };
    if s.latch_on_start {
        info!(
            "latch_on_start: the background is latched from the first {} frames",
            s.background_frames
        );
        inbox.push_command(Command::Latch((Service::OnStart, Default::default())));
    }
    let mut diag_tick = tokio::time::interval(if s.diagnostics_period.is_zero() {
        Duration::from_secs(3600 * 24 * 365)
    } else {
        s.diagnostics_period
    });
    diag_tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);

    let mut depth_stream = std::pin::pin!(depth_sub.async_stream());
    let mut ir_stream = std::pin::pin!(ir_sub.async_stream());
    let mut info_stream = std::pin::pin!(info_sub.async_stream());
    let mut latch_stream = std::pin::pin!(latch_srv.receive_request_stream());
    let mut clear_stream = std::pin::pin!(clear_srv.receive_request_stream());
    let mut pairer = StampPairer::new(s.queue_depth.max(4) * 2);
    let mut frame_pairer = FramePairer::new(frequencies, s.queue_depth.max(4) * 2);
    let multi = frequencies > 0;
    let mut phasor_stream = futures::stream::select_all(
        phasor_subs
            .iter()
            .enumerate()
            .map(|(k, sub)| Box::pin(sub.async_stream().map(move |m| (k, m)))),
    );
    let mut counts = NodeStats::default();
    let mut last_info: Option<CameraInfo> = None;
    let mut intake = Intake::default();
    let mut sigterm = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
    let mut final_stats = None;
    loop {
        tokio::select! {
            m = depth_stream.next() => match m {
                Some(Ok((img, _))) => {
                    counts.depth_received += 1;
                    let img = intake.image(&depth_t, img, last_info.as_ref());
                    if multi {
                        if let Some(f) = img.and_then(|img| frame_pairer.offer(0, img)) { counts.pairs += 1; inbox.push_frame(f); }
                    } else if let Some(pair) = img.and_then(|img| pairer.depth(img)) { counts.pairs += 1; inbox.push_frame(pair); }
                }
                Some(Err(e)) => intake.unreadable(&depth_t, &e),
                None => break,
            },
            m = ir_stream.next() => match m {
                Some(Ok((img, _))) => {
                    counts.ir_received += 1;
                    let img = intake.image(&ir_t, img, last_info.as_ref());
                    if multi {
                        if let Some(f) = img.and_then(|img| frame_pairer.offer(1, img)) { counts.pairs += 1; inbox.push_frame(f); }
                    } else if let Some(pair) = img.and_then(|img| pairer.ir(img)) { counts.pairs += 1; inbox.push_frame(pair); }
                }
                Some(Err(e)) => intake.unreadable(&ir_t, &e),
                None => break,
            },
            m = phasor_stream.next(), if multi => match m {
                Some((k, Ok((img, _)))) => {
                    let img = intake.image(&phasor_t[k], img, last_info.as_ref());
                    if let Some(f) = img.and_then(|img| frame_pairer.offer(2 + k, img)) { counts.pairs += 1; inbox.push_frame(f); }
                }
                Some((k, Err(e))) => intake.unreadable(&phasor_t[k], &e),
                None => break,
            },
            m = info_stream.next() => match m {
                Some(Ok((ci, _))) => {
                    counts.info_received += 1;
                    let Some(ci) = intake.camera_info(&info_t, ci) else { continue };
                    // Only a change of the camera concerns the pipeline.
                    let changed = last_info.as_ref().is_none_or(|l| l.k != ci.k || l.width != ci.width || l.height != ci.height || l.d != ci.d);
                    if changed {
                        inbox.push_command(Command::CameraInfo(Box::new(ci.clone())));
                        last_info = Some(ci);
                    }
                }
                Some(Err(e)) => intake.unreadable(&info_t, &e),
                None => break,
            },
            m = latch_stream.next() => match m {
                Some(Ok((id, _))) => { counts.services[0] += 1; inbox.push_command(Command::Latch((Service::Latch, id))); }
                Some(Err(e)) => warn!("{latch_n}: unreadable request ({e:?})"),
                None => break,
            },
            m = clear_stream.next() => match m {
                Some(Ok((id, _))) => { counts.services[1] += 1; inbox.push_command(Command::Clear((Service::Clear, id))); }
                Some(Err(e)) => warn!("{clear_n}: unreadable request ({e:?})"),
                None => break,
            },
            Some(((which, id), resp)) = reply_rx.recv() => {
                let (srv, name) = match which {
                    Service::Latch => (&latch_srv, &latch_n),
                    Service::Clear => (&clear_srv, &clear_n),
                    Service::OnStart => {
                        if resp.success { info!("latch_on_start: {}", resp.message); } else { warn!("latch_on_start: {}", resp.message); }
                        continue;
                    }
                };
                if resp.success { info!("{name}: {}", resp.message); } else { warn!("{name}: {}", resp.message); }
                if let Err(e) = srv.async_send_response(id, resp).await { warn!("sending a service reply: {e:?}"); }
            },
            _ = diag_tick.tick(), if !s.diagnostics_period.is_zero() => {
                let inputs = Inputs {
                    counts: &counts,
                    unpaired: pairer.unpaired + frame_pairer.unpaired,
                    queue_full: inbox.dropped(),
                    intake: &intake.drops.by_cause,
                };
                let snapshot = live.lock().map(|l| l.clone()).unwrap_or_default();
                let stamp = node.time_now().to_nanos();
                let msg = diagnostics_message(&s.names.node_fqn(), u64::try_from(stamp).unwrap_or(0), &inputs, &snapshot);
                if let Err(e) = diagnostics.publish(msg) { warn!("publishing {diag_n}: {e:?}"); }
            },
            st = done_rx.recv() => { final_stats = st; break; },
            _ = tokio::signal::ctrl_c() => { info!("SIGINT: shutting down"); break; },
            _ = sigterm.recv() => { info!("SIGTERM: shutting down"); break; },
        }
    }
    inbox.push_command(Command::Shutdown);
    let mut stats = match final_stats {
        Some(st) => st,
        None => done_rx.recv().await.unwrap_or_default(),
    };
    let _ = worker.join();
    // The spinner's entities (parameter services, /rosout, /clock) go before the
    // participant: dropped after it, RustDDS logs an error for each of them.
    drop(node);
    if tokio::time::timeout(Duration::from_secs(2), spin_task).await.is_err() {
        warn!("the node's spinner did not stop within 2 s");
    }
    stats.depth_received = counts.depth_received;
    stats.ir_received = counts.ir_received;
    stats.info_received = counts.info_received;
    stats.pairs = counts.pairs;
    stats.services = counts.services;
    let unpaired = pairer.unpaired + frame_pairer.unpaired;
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
    info!("{}", summary(&stats));
    if let Some(p) = &s.stats_json {
        let text = serde_json::to_string_pretty(&stats)?;
        crate::files::write_atomic(p, text.as_bytes())?;
    }
    Ok(stats)
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

const LATENCY_WINDOW: usize = 8192;

fn worker(
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
    let _pool = match crate::affinity::pool_on_current_thread(0, s.pin_threads) {
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
    };
    let mut core: NodeCore<Token> = NodeCore::new(s.config.clone(), s.background_frames, s.latch_timeout)
        .with_watch(s.passthrough, s.relatch_on_move);
    let mut multi = s
        .multi_frequency
        .clone()
        .map(|f| MultiFrequencyNode::new(f, &s.config, s.no_latch));
    let mut latencies: Vec<f64> = Vec::with_capacity(LATENCY_WINDOW);
    let mut last_report = Instant::now();
    let (mut last_sample, mut last_trim) = (Instant::now(), Instant::now());
    sample_memory(&mut stats);
    let mut reported_drops = 0u64;
    let reply = |t: Token, r: TriggerResponse| {
        let _ = replies.send((t, r));
    };
    let mut last_live = Instant::now() - Duration::from_secs(1);
    loop {
        if last_live.elapsed() >= Duration::from_millis(250) {
            if let Ok(mut l) = live.lock() {
                *l = Live {
                    published: stats.published,
                    latched_frames: stats.latched_frames,
                    dropped: core.drops.by_cause.clone(),
                    passed: core.passed.clone(),
                    camera_moved: core.camera_moved(),
                    latch: if core.latching() {
                        "latching"
                    } else if core.background().is_some() && multi.as_ref().is_none_or(|m| m.latched()) {
                        "latched"
                    } else {
                        "none"
                    },
                    xi: stats.xi,
                    xi_method: match multi {
                        Some(_) => crate::physics::XiMethod::MultiFrequency.as_str().to_string(),
                        None => core.xi_method().to_string(),
                    },
                    processing_ms: percentiles(&mut latencies.clone()),
                };
            }
            last_live = Instant::now();
        }
        if let Some((t, r)) = core.check_latch_timeout() {
            reply(t, r);
        }
        match inbox.next(Duration::from_millis(100)) {
            Next::Idle => {}
            Next::Command(Command::Shutdown) => break,
            Next::Command(Command::CameraInfo(ci)) => match core.on_camera_info(&ci) {
                Ok(note) => {
                    if let Some(note) = note {
                        warn!("{note}");
                    }
                    if let Some(Err(e)) = multi.as_mut().map(|m| m.on_camera_info(&core)) {
                        warn!("camera_info {}x{}: {e}", ci.width, ci.height);
                    }
                }
                Err((cause, why)) => {
                    if core.drops.record(cause) {
                        warn!(
                            "camera_info {}x{} K {:?} not usable: {why} ({})",
                            ci.width,
                            ci.height,
                            ci.k,
                            cause.advice()
                        );
                    }
                }
            },
            Next::Command(Command::Latch(t)) => {
                info!(
                    "latch requested: averaging the next {} frames",
                    core.background_frames()
                );
                let started = if t.0 == Service::OnStart {
                    core.start_latch_waiting(t)
                } else {
                    core.start_latch(t)
                };
                match started {
                    Err((t, r)) => reply(t, r),
                    Ok(()) => {
                        if let Some(m) = &mut multi {
                            m.on_latch_started();
                        }
                    }
                }
            }
            Next::Command(Command::Reconfigure(r, forget_evidence)) => {
                let RuntimeSettings {
                    config,
                    background_frames,
                    latch_timeout,
                } = *r;
                core.reconfigure(config, background_frames, latch_timeout, forget_evidence);
            }
            Next::Command(Command::Clear(t)) => {
                let (r, cancelled) = core.clear();
                if let Some(m) = &mut multi {
                    m.clear();
                }
                if let Some((t2, r2)) = cancelled {
                    reply(t2, r2);
                }
                reply(t, r);
            }
            Next::Frame(frame) => {
                let start = Instant::now();
                let latching = core.latching();
                let MultiFrequencyResult {
                    frame: res,
                    translucency,
                } = match &mut multi {
                    Some(m) => m.on_frame(&mut core, &frame),
                    None => MultiFrequencyResult {
                        frame: core.on_frame(&frame.depth, &frame.ir),
                        translucency: None,
                    },
                };
                let depth = frame.depth;
                for (t, r) in res.replies {
                    reply(t, r);
                }
                for (level, note) in &res.notes {
                    log::log!(*level, "{note}");
                }
                if let Some((cause, first)) = res.dropped {
                    if let Some(msg) = first {
                        warn!("{msg}; further {cause:?} drops are counted");
                    }
                } else if latching {
                    stats.latched_frames += 1;
                }
                let passed = res.outputs.as_ref().and_then(|o| o.frame.passthrough);
                if let Some(mut o) = res.outputs {
                    // The corrected depth first (most consumers wait for it alone), then the
                    // rest is made and published.
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
                        stats.publish_failures += 1;
                        if stats.publish_failures == 1 {
                            warn!("publishing an output failed ({kind}; a reliable reader is not keeping up?); further failures are counted (publish_failures)");
                        }
                    }
                    // A frame passed through is not a recovered one.
                    if passed.is_none() {
                        stats.published += 1;
                        let xi = &o.frame.xi;
                        stats.xi = Some([xi.xi, xi.interval[0], xi.interval[1]]);
                        if latencies.len() == LATENCY_WINDOW {
                            latencies.remove(0);
                        }
                        latencies.push(start.elapsed().as_secs_f64() * 1e3);
                        if let (Some(v), Some(rays)) = (&viz, core.shared_rays()) {
                            let raw = crate::image::depth_mm(&depth).ok();
                            if let Some(raw) = raw {
                                v.log(FrameViz {
                                    stamp_ns: o.frame.stamp_ns,
                                    frame: stats.published,
                                    rays,
                                    raw_z_mm: raw,
                                    recovered_z_mm: o.frame.corrected_z_mm,
                                    mask: o.frame.mask,
                                    xi: Some((o.frame.xi.xi, o.frame.xi.interval)),
                                    objects: FrameViz::objects_of(&o.frame.regions),
                                });
                            }
                        }
                        if s.max_frames.is_some_and(|m| stats.published >= m) {
                            break;
                        }
                    }
                }
            }
        }
        // Memory sampled every second: the DDS writers' samples are freed every 6 s, and a
        // coarser sampling would alias that sawtooth. Free heap handed back every 5 s.
        if last_sample.elapsed() >= Duration::from_secs(1) {
            if last_trim.elapsed() >= Duration::from_secs(5) {
                release_free_heap();
                last_trim = Instant::now();
            }
            sample_memory(&mut stats);
            last_sample = Instant::now();
        }
        let drops = core.drops.total();
        if drops != reported_drops && last_report.elapsed() > Duration::from_secs(5) {
            let by: Vec<String> = core.drops.by_cause.iter().map(|(c, n)| format!("{c:?} {n}")).collect();
            info!(
                "{} frames published; dropped so far: {}",
                stats.published,
                by.join(", ")
            );
            reported_drops = drops;
            last_report = Instant::now();
        }
    }
    sample_memory(&mut stats);
    stats.dropped = core.drops.by_cause.clone();
    stats.passed_through = core.passed.clone();
    stats.added_latency_ms = percentiles(&mut latencies);
    if let Some(v) = viz {
        stats.rerun_dropped = v.dropped();
        if let Err(e) = v.finish() {
            error!("{e}");
        }
    }
    let _ = done.send(stats);
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
