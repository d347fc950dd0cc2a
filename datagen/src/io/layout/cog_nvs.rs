//! The cog-nvs layout (the public CogNVS code's per-video folder): `gt_rgb.mp4` +
//! `cam_info/megasam_depth.npy` (N,H,W), optional `cam_info/megasam_intrinsics.npy` (3,3) and
//! `cam_info/megasam_c2ws.npy` (N,4,4) world_from_camera. Depth at another resolution than the
//! video is resampled and K scaled; missing intrinsics and poses take the public code's fallbacks
//! ([`crate::io::reconstruction::assemble`]).

use std::path::Path;

use crate::error::Result;
use crate::io::npy::{Axis, read_npy_f64, read_npy_f64_shaped};
use crate::io::reconstruction::{DepthStack, Parts, Reconstruction, assemble};

/// The video of the layout.
pub const VIDEO_FILE: &str = "gt_rgb.mp4";
/// The folder of the reconstruction's arrays.
pub const CAM_INFO_DIR: &str = "cam_info";

/// Whether `dir` holds the layout's files: `gt_rgb.mp4` or `cam_info/`.
pub fn recognised(dir: &Path) -> bool {
    dir.join(CAM_INFO_DIR).is_dir() || dir.join(VIDEO_FILE).is_file()
}

/// Reads the cog-nvs folder `dir`: its video and reconstruction.
pub(crate) fn read(dir: &Path) -> Result<Parts> {
    let video_path = dir.join(VIDEO_FILE);
    // Decoding is mostly serial: read the reconstruction meanwhile.
    let (video, parts) = rayon::join(|| foundation::video::decode_video(&video_path), || reconstruction(dir));
    let video = video?;
    assemble(video.fps, video.frames, &video_path, parts?)
}

/// The reconstruction of the cog-nvs folder `dir` (no frames).
pub(crate) fn reconstruction(dir: &Path) -> Result<Reconstruction> {
    let cam = dir.join(CAM_INFO_DIR);
    let depth_path = cam.join("megasam_depth.npy");
    let depth = DepthStack::read_npy(&depth_path)?;
    let intrinsics_path = cam.join("megasam_intrinsics.npy");
    let intrinsics = if intrinsics_path.is_file() {
        let k = read_npy_f64_shaped(&intrinsics_path, &[Axis::Is(3), Axis::Is(3)])?;
        Some((intrinsics_path, k))
    } else {
        None
    };
    let poses_path = cam.join("megasam_c2ws.npy");
    let poses = if poses_path.is_file() { Some((poses_path.clone(), read_npy_f64(&poses_path)?)) } else { None };
    Ok(Reconstruction { depth_path, depth, intrinsics, poses })
}
