//! `translucent_tof`: recovers the true depth of translucent objects seen by a
//! continuous-wave Time-of-Flight camera, after Shim & Lee, "Recovering
//! Translucent Objects using a Single Time-of-Flight Depth Camera".
//!
//! Layers, each readable on its own:
//! - [`physics`]: the forward model, inversion and ξ estimation (no I/O);
//! - [`msgs`]: ROS 2 message types (CDR), shared by bags and DDS;
//! - [`bag`]: ROS 2 MCAP bags as rosbag2 writes them;
//! - [`image`]: sensor_msgs/Image encodings <-> physics buffers;
//! - [`sim`]: the scene simulator;
//! - [`pipeline`]: background latch, segmentation, recovery per frame;
//! - [`outputs`]: the node's output messages for a frame;
//! - [`node`]: the ROS 2 node (ros2-client / RustDDS);
//! - [`viz`]: Rerun logging off the processing path;
//! - [`bench`]: benchmark frames, cases and the plain reference inversion;
//! - [`cli`]: the subcommands.

// Image code indexes several parallel buffers by pixel, and `!(x > 0.0)` is
// meant: it rejects NaN too.
#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord)]

pub mod affinity;
pub mod alloc;
pub mod audit;
pub mod bag;
pub mod bench;
pub mod cli;
pub mod files;
pub mod image;
pub mod msgs;
pub mod node;
pub mod outputs;
pub mod physics;
pub mod pipeline;
pub mod sim;
pub mod viz;
