//! The scene simulator: a ToF camera (SR4000 by default), a background plane,
//! translucent planes and cylinders, shot noise; rendered with the one
//! forward model of [`crate::physics`].

pub mod artefacts;
pub mod render;
pub mod scene;

pub use artefacts::Artefacts;
pub use render::{render, render_all, SimFrame};
pub use scene::{Scene, SceneError};
