//! Depth maps in memory: one float per pixel, z-depth along the optical axis in the
//! reconstruction's own units (valid: finite and > 0). Their file formats live with the readers
//! that use them (datagen's `io::depth_exr`, `io::npy`).

/// A single-channel float raster, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthMap {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// `width * height` values, rows top to bottom.
    pub values: Vec<f32>,
}
