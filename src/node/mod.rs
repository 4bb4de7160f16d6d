//! The ROS 2 node on ros2-client / RustDDS: thin glue around [`core::NodeCore`].
//!
//! DDS callbacks (an async task) pair depth and IR by stamp and queue the
//! pairs; one processing thread takes them, runs the pipeline and publishes;
//! a Rerun thread logs without blocking either.

pub mod core;
pub mod echo;
pub mod inbox;
pub mod latency;
pub mod peer;
pub mod rlog;
pub mod ros_args;

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use futures::StreamExt;
use log::{error, info, warn};
use ros2_client::{
    qos::{Durability, History},
    Context, ContextOptions, MessageTypeName, Name, NodeName, NodeOptions, ParameterValue, Publisher, QosProfile,
    ServiceMapping, ServiceTypeName,
};
use serde::Serialize;

use crate::msgs::translucent_tof::TranslucencyEstimate;
use crate::msgs::{CameraInfo, Image, PointCloud2, TriggerRequest, TriggerResponse};
use crate::pipeline::PipelineConfig;
use crate::viz::{FrameViz, RerunTarget, VizSink};

use self::core::{DropCause, NodeCore};
use self::inbox::{Command, Inbox, Intake, Next, StampPairer};
use self::ros_args::{NameResolver, ParamValue};

impl ros2_client::Message for Image {}
impl ros2_client::Message for CameraInfo {}
impl ros2_client::Message for PointCloud2 {}
impl ros2_client::Message for TranslucencyEstimate {}
impl ros2_client::Message for TriggerRequest {}
impl ros2_client::Message for TriggerResponse {}

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
}

/// Everything the node needs to run (built from `--ros-args` by the CLI layer).
#[derive(Debug, Clone)]
pub struct NodeSettings {
    /// The pipeline.
    pub config: PipelineConfig,
    /// Frames averaged per latch (`background_frames`).
    pub background_frames: usize,
    /// A latch gives up after this long.
    pub latch_timeout: Duration,
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
    /// Parameters as given (declared on the node, readable with `ros2 param`).
    pub params: Vec<(String, ParamValue)>,
    /// Write counters and timings here on exit.
    pub stats_json: Option<PathBuf>,
    /// Stop after this many processed frames (tests, benchmarks).
    pub max_frames: Option<u64>,
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
    /// Drops by cause.
    pub dropped: std::collections::BTreeMap<DropCause, u64>,
    /// Latch requests, clear requests.
    pub services: [u64; 2],
    /// Frames Rerun could not take.
    pub rerun_dropped: u64,
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
#[derive(Debug, Clone, Copy)]
enum Service {
    Latch,
    Clear,
}

type Token = (Service, ros2_client::service::RmwRequestId);

struct Outputs {
    corrected: Publisher<Image>,
    mask: Publisher<Image>,
    points: Publisher<PointCloud2>,
    estimate: Publisher<TranslucencyEstimate>,
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

fn to_parameter(v: &ParamValue) -> ParameterValue {
    match v {
        ParamValue::Bool(b) => ParameterValue::Boolean(*b),
        ParamValue::Integer(i) => ParameterValue::Integer(*i),
        ParamValue::Double(x) => ParameterValue::Double(*x),
        ParamValue::String(s) => ParameterValue::String(s.clone()),
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
    let mut options = NodeOptions::new().enable_rosout(true);
    for (k, v) in &s.params {
        options = options.declare_parameter(k, to_parameter(v));
    }
    let node_name = NodeName::new(&s.names.namespace, &s.names.node)
        .map_err(|e| anyhow::anyhow!("node name {}: {e:?}", s.names.node_fqn()))?;
    let mut node = ctx
        .new_node(node_name.clone(), options)
        .map_err(|e| anyhow::anyhow!("creating node {}: {e:?}", s.names.node_fqn()))?;
    let spinner = node.spinner().map_err(|e| anyhow::anyhow!("node spinner: {e:?}"))?;
    tokio::spawn(spinner.spin());

    let r = |n: &str| s.names.resolve(n);
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

    let out_q = qos_outputs();
    let publisher = |name: &str, ty: &str| -> anyhow::Result<_> {
        let full = r(name)?;
        let t = topic(&full, "sensor_msgs", ty, &out_q)?;
        Ok((full, t))
    };
    let (corrected_n, corrected_t) = publisher(names::CORRECTED, "Image")?;
    let (mask_n, mask_t) = publisher(names::MASK, "Image")?;
    let (points_n, points_t) = publisher(names::POINTS, "PointCloud2")?;
    let est_n = r(names::TRANSLUCENCY)?;
    let est_q = qos_estimate();
    let est_t = topic(&est_n, "translucent_tof", "TranslucencyEstimate", &est_q)?;
    let pe = |n: &str| {
        let n = n.to_string();
        move |e| anyhow::anyhow!("publisher {n}: {e:?}")
    };
    let outputs = Outputs {
        corrected: node
            .create_publisher(&corrected_t, Some(out_q.clone()))
            .map_err(pe(&corrected_n))?,
        mask: node
            .create_publisher(&mask_t, Some(out_q.clone()))
            .map_err(pe(&mask_n))?,
        points: node
            .create_publisher(&points_t, Some(out_q.clone()))
            .map_err(pe(&points_n))?,
        estimate: node.create_publisher(&est_t, Some(est_q)).map_err(pe(&est_n))?,
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
        "{} up on domain {}{}: depth {depth_t}, IR {ir_t}, camera_info {info_t}; publishes {corrected_n}, {points_n}, {mask_n}, {est_n}; services {latch_n}, {clear_n} ({:?} mapping); background_frames {}, xi {}",
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

    let inbox: Arc<Inbox<Token>> = Arc::new(Inbox::new(s.queue_depth));
    let (reply_tx, mut reply_rx) = tokio::sync::mpsc::unbounded_channel::<(Token, TriggerResponse)>();
    let (done_tx, mut done_rx) = tokio::sync::mpsc::unbounded_channel::<NodeStats>();
    let worker = {
        let inbox = inbox.clone();
        let settings = s.clone();
        std::thread::Builder::new()
            .name("pipeline".into())
            .spawn(move || worker(settings, inbox, outputs, viz, reply_tx, done_tx))?
    };

    let mut depth_stream = std::pin::pin!(depth_sub.async_stream());
    let mut ir_stream = std::pin::pin!(ir_sub.async_stream());
    let mut info_stream = std::pin::pin!(info_sub.async_stream());
    let mut latch_stream = std::pin::pin!(latch_srv.receive_request_stream());
    let mut clear_stream = std::pin::pin!(clear_srv.receive_request_stream());
    let mut pairer = StampPairer::new(s.queue_depth.max(4) * 2);
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
                    if let Some(pair) = img.and_then(|img| pairer.depth(img)) { counts.pairs += 1; inbox.push_frame(pair); }
                }
                Some(Err(e)) => intake.unreadable(&depth_t, &e),
                None => break,
            },
            m = ir_stream.next() => match m {
                Some(Ok((img, _))) => {
                    counts.ir_received += 1;
                    let img = intake.image(&ir_t, img, last_info.as_ref());
                    if let Some(pair) = img.and_then(|img| pairer.ir(img)) { counts.pairs += 1; inbox.push_frame(pair); }
                }
                Some(Err(e)) => intake.unreadable(&ir_t, &e),
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
                let (srv, name) = match which { Service::Latch => (&latch_srv, &latch_n), Service::Clear => (&clear_srv, &clear_n) };
                if resp.success { info!("{name}: {}", resp.message); } else { warn!("{name}: {}", resp.message); }
                if let Err(e) = srv.async_send_response(id, resp).await { warn!("sending a service reply: {e:?}"); }
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
    stats.depth_received = counts.depth_received;
    stats.ir_received = counts.ir_received;
    stats.info_received = counts.info_received;
    stats.pairs = counts.pairs;
    stats.services = counts.services;
    let unpaired = pairer.unpaired;
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
        crate::cli::write_atomic(p, text.as_bytes())?;
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
    let mut core: NodeCore<Token> = NodeCore::new(s.config.clone(), s.background_frames, s.latch_timeout);
    let mut latencies: Vec<f64> = Vec::with_capacity(LATENCY_WINDOW);
    let mut last_report = Instant::now();
    let (mut last_sample, mut last_trim) = (Instant::now(), Instant::now());
    sample_memory(&mut stats);
    let mut reported_drops = 0u64;
    let reply = |t: Token, r: TriggerResponse| {
        let _ = replies.send((t, r));
    };
    loop {
        if let Some((t, r)) = core.check_latch_timeout() {
            reply(t, r);
        }
        match inbox.next(Duration::from_millis(100)) {
            Next::Idle => {}
            Next::Command(Command::Shutdown) => break,
            Next::Command(Command::CameraInfo(ci)) => match core.on_camera_info(&ci) {
                Ok(Some(note)) => warn!("{note}"),
                Ok(None) => {}
                Err(cause) => {
                    if core.drops.record(cause) {
                        warn!(
                            "camera_info {}x{} K {:?} not usable ({})",
                            ci.width,
                            ci.height,
                            ci.k,
                            cause.advice()
                        );
                    }
                }
            },
            Next::Command(Command::Latch(t)) => {
                info!("latch requested: averaging the next {} frames", s.background_frames);
                if let Err((t, r)) = core.start_latch(t) {
                    reply(t, r);
                }
            }
            Next::Command(Command::Clear(t)) => {
                let (r, cancelled) = core.clear();
                if let Some((t2, r2)) = cancelled {
                    reply(t2, r2);
                }
                reply(t, r);
            }
            Next::Frame(pair) => {
                let start = Instant::now();
                let (depth, ir) = *pair;
                let latching = core.background().is_none();
                let res = core.on_frame(&depth, &ir);
                for (t, r) in res.replies {
                    reply(t, r);
                }
                if let Some((cause, first)) = res.dropped {
                    if let Some(msg) = first {
                        warn!("{msg}; further {cause:?} drops are counted");
                    }
                } else if res.outputs.is_none() && latching {
                    stats.latched_frames += 1;
                }
                if let Some(mut o) = res.outputs {
                    // The corrected depth first (most consumers wait for it alone), then the
                    // rest is made and published.
                    let first = out.corrected.publish(std::mem::take(&mut o.corrected)).err();
                    let c = o.companions();
                    let mut results = vec![
                        first.map(|e| format!("{e:?}")),
                        out.mask.publish(c.mask).err().map(|e| format!("{e:?}")),
                        out.points.publish(c.points).err().map(|e| format!("{e:?}")),
                    ];
                    for e in c.estimates {
                        results.push(out.estimate.publish(e).err().map(|e| format!("{e:?}")));
                    }
                    if let Some(e) = results.into_iter().flatten().next() {
                        error!("publishing: {e}");
                    }
                    stats.published += 1;
                    let xi = &o.frame.xi;
                    stats.xi = Some([xi.xi, xi.interval[0], xi.interval[1]]);
                    if latencies.len() == LATENCY_WINDOW {
                        latencies.remove(0);
                    }
                    latencies.push(start.elapsed().as_secs_f64() * 1e3);
                    if let (Some(v), Some(k)) = (&viz, core.intrinsics()) {
                        let raw = crate::image::depth_mm(&depth).ok();
                        if let Some(raw) = raw {
                            v.log(FrameViz {
                                stamp_ns: o.frame.stamp_ns,
                                frame: stats.published,
                                intrinsics: k,
                                raw_z_mm: raw,
                                recovered_z_mm: o.frame.corrected_z_mm,
                                mask: o.frame.mask,
                                xi: Some((o.frame.xi.xi, o.frame.xi.interval)),
                            });
                        }
                    }
                    if s.max_frames.is_some_and(|m| stats.published >= m) {
                        break;
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
