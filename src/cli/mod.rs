//! The `translucent_tof` command line: one binary, one subcommand per job.

mod audit;
mod calibrate;
mod common;
mod recording;
mod replay;
mod simulate;

use clap::{Parser, Subcommand};

pub use common::PhysicsFile;

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
    /// Compare the model with a ground-truthed recording: locate, name and fit the physics it leaves out.
    Audit(audit::AuditArgs),
}

/// Parses the arguments and runs the subcommand.
pub fn run() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Replay(a) => replay::run(a),
        Command::Simulate(a) => simulate::run(a),
        Command::CalibrateXi(a) => calibrate::run_xi(a),
        Command::CalibrateLin(a) => calibrate::run_lin(a),
        Command::Audit(a) => audit::run(a),
    }
}
