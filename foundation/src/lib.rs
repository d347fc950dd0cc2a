//! `foundation`: what the toolkit's crates share below their own work: the pinhole camera and
//! the pose and intrinsics checks every reader applies ([`camera`]), the depth map
//! ([`depth`]), video through FFmpeg ([`video`]) and image frames ([`frames`]), content digests
//! ([`hashing`]), contact sheets ([`contact_sheet`]) and the checked join of names read from
//! files with the identity of folders ([`paths`]). `datagen` and `trainer` both build on it;
//! it depends on neither.

pub mod camera;
pub mod contact_sheet;
pub mod depth;
pub mod error;
pub mod frames;
pub mod hashing;
pub mod paths;
pub mod video;

pub use error::{Error, Result};
