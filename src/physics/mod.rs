//! The physics of a continuous-wave ToF pixel looking through a translucent
//! layer (Shim & Lee): the forward model, its inversion, segmentation,
//! calibration and the estimation of the translucency ξ.
//!
//! Plain numbers and image buffers in, numbers out: no ROS, no I/O, no async.
//! Distances are millimetres, phases radians.
#![deny(missing_docs)]

pub mod buffer;

pub use buffer::{ImageBuf, Region, SparseImage};
pub mod coverage;
pub mod depth_engine;
pub mod diffuse;
pub mod model;
pub mod multifreq;
pub mod near_wall;
pub mod sensor;

pub use depth_engine::DepthEngine;
pub use model::{ForwardModel, IrMode, LayerScene, Measurement, ModelOptions, Preset, Return};
pub use sensor::{Sensor, Waveform};
pub mod inversion;
pub use inversion::{
    foreground_distance, foreground_distance_without_slopes, foreground_distances, InversionBounds, LayerEstimate,
    PixelObservation,
};
pub mod camera;
pub mod distortion;
pub mod emitted_light;
pub mod segmentation;
pub mod stats;
pub mod surface;
pub use camera::Intrinsics;
pub mod catalog;
pub mod materials;
pub mod translucency;
pub use translucency::{XiEstimate, XiMethod};
pub mod audit;
pub mod noise;
pub mod parallel;
pub mod trig;
pub mod vector;
