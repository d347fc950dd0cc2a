//! `foundation`: what the toolkit's crates share below their own work: the pinhole camera and
//! the pose and intrinsics checks every reader applies ([`camera`]), the depth map
//! ([`depth`]), video through FFmpeg ([`video`]) and image frames ([`frames`]), content digests
//! ([`hashing`]) and contact sheets ([`contact_sheet`]). `datagen` and `trainer` both build on it;
//! it depends on neither.

pub mod camera;
pub mod contact_sheet;
pub mod depth;
pub mod error;
pub mod frames;
pub mod hashing;
pub mod video;

pub use error::{Error, Result};
