//! The `translucent_tof` command line: one binary, one subcommand per job.

mod audit;
mod bench;
mod calibrate;
pub(crate) mod common;
mod demo;
mod node;
pub(crate) mod recording;
mod replay;
mod replay_multifreq;
mod simulate;
mod through_engine;

use clap::{Parser, Subcommand};

pub use common::{write_atomic, PhysicsFile, TopicArgs};
pub use recording::{load as load_recording, Recording};

/// Recovers the true depth of translucent objects seen by a continuous-wave
/// Time-of-Flight camera (Shim & Lee's two-layer model).
#[derive(Debug, Parser)]
#[command(name = "translucent_tof", version, about, long_about = None)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run the pipeline over a recorded ROS 2 bag and write the node's outputs as a new bag.
    Replay(replay::ReplayArgs),
    /// Render a scene (TOML) into a ROS 2 bag with depth, IR, camera_info and ground truth.
    Simulate(simulate::SimulateArgs),
    /// Fit a material's ξ from a recording with known foreground distances (paper Sec. V-A).
    CalibrateXi(calibrate::CalibrateXiArgs),
    /// Emitted-light map from a recording of a white plane (paper Eq. 13-14).
    CalibrateLin(calibrate::CalibrateLinArgs),
    /// The ROS 2 node: subscribes to a ToF camera, latches a background on
    /// ~/latch_background, publishes corrected depth, points, mask and ξ.
    #[command(after_help = node::parameters_help())]
    Node(node::NodeArgs),
    /// The whole graph on loopback: a bundled bag played as a driver, the node, the latch service; a summary.
    Demo(demo::DemoArgs),
    /// Time the real-time path (recovery, segmentation, ξ estimation, replay) against the plain 1 mm grid search.
    Bench(bench::BenchArgs),
    /// Read a multi-frequency recording's phasors through a camera's depth engine: the depth + IR bag its driver would publish.
    ThroughEngine(through_engine::ThroughEngineArgs),
    /// Compare the model with a ground-truthed recording: locate, name and fit the physics it leaves out.
    Audit(audit::AuditArgs),
    /// The latency benchmark's transport baseline: answers each frame with same-size outputs once its depth and IR images are both in.
    #[command(hide = true)]
    DdsEcho(EchoArgs),
}

/// Arguments of the hidden `dds-echo`.
#[derive(Debug, clap::Args)]
struct EchoArgs {
    /// Namespace of the inputs.
    #[arg(long, default_value = "/tof")]
    namespace: String,
    /// Fully qualified name to answer as.
    #[arg(long, default_value = "/tof/translucent_tof")]
    node: String,
}

/// Parses the arguments and runs the subcommand.
pub fn run() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Replay(a) => replay::run(a),
        Command::Simulate(a) => simulate::run(a),
        Command::CalibrateXi(a) => calibrate::run_xi(a),
        Command::CalibrateLin(a) => calibrate::run_lin(a),
        Command::Node(a) => node::run(a).map(|_| ()),
        Command::Demo(a) => demo::run(a),
        Command::ThroughEngine(a) => through_engine::run(a),
        Command::DdsEcho(a) => {
            let domain = std::env::var("ROS_DOMAIN_ID")
                .ok()
                .and_then(|v| v.parse().ok())
                .unwrap_or(0);
            crate::node::echo::run(domain, &a.namespace, &a.node)
        }
        Command::Bench(a) => bench::run(a),
        Command::Audit(a) => audit::run(a),
    }
}
