//! GEN3C's per-video archive (nv-tlabs/GEN3C, the "distributed format" its dynamic-video
//! inference loads, `cosmos_predict1/diffusion/inference/data_loader_utils.py`): a folder with
//!
//! - `rgb.mp4`: the frames;
//! - `depth.npz`, member `depth` (T, H, W) (float16 as written): z-depth (GEN3C's depth comes from
//!   ViPE/MoGe, near-metric);
//! - `mask.npz`, member `mask` (T, H, W) bool: where the depth is valid (false masks it);
//!   optional;
//! - `camera.npz`, members `w2c` (T, 4, 4): **camera_from_world**, OpenCV axes, checked rigid and
//!   inverted; and `intrinsics` (T, 3, 3): K in pixels at the depth resolution.
//!
//! The older packaged `.pt` file (a pickled tuple of torch tensors) is refused by name: a pickle
//! cannot be read safely.

use std::path::Path;

use crate::error::{Error, Result};
use crate::io::npy::{Axis, NpzReader};
use crate::io::tool_output::{ToolOutput, check_depth_sign, invert_camera_from_world, with_video};

/// The archive's camera file: its presence marks the layout.
pub const CAMERA_FILE: &str = "camera.npz";
/// The depth file.
pub const DEPTH_FILE: &str = "depth.npz";
/// The optional validity mask.
pub const MASK_FILE: &str = "mask.npz";
/// The frames.
pub const VIDEO_FILE: &str = "rgb.mp4";

/// Reads the GEN3C archive folder `dir`, decoding `rgb.mp4`.
pub fn read_gen3c(dir: &Path) -> Result<ToolOutput> {
    with_video(dir.join(VIDEO_FILE), || read_gen3c_reconstruction(dir))
}

/// The reconstruction of the GEN3C archive folder `dir` (no frames).
pub fn read_gen3c_reconstruction(dir: &Path) -> Result<ToolOutput> {
    let camera_path = dir.join(CAMERA_FILE);
    let mut camera = NpzReader::open(&camera_path)?;
    let w2c_header = camera.header("w2c", Some(&[Axis::Any, Axis::Is(4), Axis::Is(4)]))?;
    let frames = w2c_header.shape[0];
    if frames == 0 {
        return Err(Error::array(&camera_path, Some("w2c.npy"), "no frames"));
    }
    let n = Axis::Is(frames);
    let w2c = camera.read_f64("w2c", &[n, Axis::Is(4), Axis::Is(4)])?;
    let k = camera.read_f64("intrinsics", &[n, Axis::Is(3), Axis::Is(3)])?;

    let depth_path = dir.join(DEPTH_FILE);
    let mut depth_archive = NpzReader::open(&depth_path)?;
    let depth = depth_archive.read_f32("depth", &[n, Axis::Pixels, Axis::Pixels])?;
    let (height, width) = (depth.shape[1], depth.shape[2]);
    let mut planes = depth.into_planes();
    for (i, plane) in planes.iter().enumerate() {
        check_depth_sign(&depth_path, "depth", i, plane)?;
    }
    let mask_path = dir.join(MASK_FILE);
    if mask_path.is_file() {
        let mut archive = NpzReader::open(&mask_path)?;
        // A mask, not a measurement: read as f64, where booleans are accepted (0 or 1).
        let mask = archive.read_f64("mask", &[n, Axis::Is(height), Axis::Is(width)])?;
        for (i, (plane, valid)) in planes.iter_mut().zip(mask.into_planes()).enumerate() {
            // NaN compares unequal to 0 and would mark its pixel valid: refused as in depth.
            if let Some(p) = valid.iter().position(|v| !v.is_finite()) {
                let reason =
                    format!("frame {i}, pixel ({}, {}): {} is not a finite mask value", p % width, p / width, valid[p]);
                return Err(Error::array(&mask_path, Some("mask.npy"), reason));
            }
            for (d, v) in plane.iter_mut().zip(valid) {
                if v == 0.0 {
                    *d = f32::NAN;
                }
            }
        }
    }
    let world_from_camera = w2c
        .data
        .chunks_exact(16)
        .enumerate()
        .map(|(i, m)| invert_camera_from_world(&camera_path, &format!("w2c[{i}]"), m))
        .collect::<Result<Vec<_>>>()?;
    Ok(ToolOutput {
        frames: None,
        depth_path,
        depth_size: (width, height),
        depth: planes,
        intrinsics_path: camera_path.clone(),
        intrinsics_size: (width as u32, height as u32),
        intrinsics: k.data.chunks_exact(9).map(|k| k.try_into().expect("9 values")).collect(),
        poses_path: camera_path,
        world_from_camera,
    })
}
