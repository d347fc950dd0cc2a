//! Depth from depth-only video tools, whose output has no cameras:
//!
//! - Video Depth Anything (DepthAnything/Video-Depth-Anything, `run.py --save_npz`):
//!   `NAME_depths.npz`, member `depths` (T, H, W);
//! - DepthCrafter (Tencent/DepthCrafter, `run.py`): `NAME.npz`, member `depth` (T, H, W).
//!
//! Their relative models write affine-invariant **disparity** (inverse depth up to an unknown scale
//! and shift), which no reader can turn into z-depth; only the metric models write depth. So the
//! folder must say which it is: the sequence reader takes poses and intrinsics from a
//! `cameras.json` beside the file (as the generic layout's, with `intrinsics` and
//! `world_from_camera`, from another tool: COLMAP, a SLAM system, a capture rig) whose
//! `depth_kind` must be `"z_depth"`; `"disparity"` is refused with what to do. Missing cameras
//! are an error: poses are never invented for depth-only output.

use std::path::{Path, PathBuf};

use crate::error::{Error, Result};
use crate::io::npy::{Axis, NpzReader};
use crate::io::tool_output::check_depth_sign;

/// The `cameras.json` key declaring what the depth file holds.
pub const DEPTH_KIND_KEY: &str = "depth_kind";
/// The one accepted [`DEPTH_KIND_KEY`] value.
pub const Z_DEPTH: &str = "z_depth";

/// Archive names of other layouts, never taken for a depth-only tool's file.
const OTHER_TOOLS_FILES: [&str; 4] = ["predictions.npz", "camera.npz", "depth.npz", "mask.npz"];

/// The depth-only tool's archive in `dir`: a `*_depths.npz` (Video Depth Anything) or another
/// `.npz` (DepthCrafter names it after the video), not one of another layout's files. Several
/// candidates are returned sorted, for the caller to refuse as ambiguous.
pub fn depth_only_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
            name.ends_with(".npz") && !name.ends_with("_sgd_cvd_hr.npz") && !OTHER_TOOLS_FILES.contains(&name)
        })
        .collect();
    files.sort();
    Ok(files)
}

/// Checks the `depth_kind` declaration of `cameras.json` (already parsed).
pub fn check_depth_kind(cameras_path: &Path, cameras: &serde_json::Value, depth_path: &Path) -> Result<()> {
    match cameras.get(DEPTH_KIND_KEY).and_then(serde_json::Value::as_str) {
        Some(Z_DEPTH) => Ok(()),
        Some(other) => Err(Error::invalid(
            cameras_path,
            DEPTH_KIND_KEY,
            format!(
                "`{other}` is not read: only `{Z_DEPTH}` is. Relative disparity has an unknown scale and shift; align it to \
                 the poses first (or run the tool's metric model) and declare `{Z_DEPTH}`"
            ),
        )),
        None => Err(Error::invalid(
            cameras_path,
            DEPTH_KIND_KEY,
            format!(
                "missing: {} comes from a depth-only tool whose relative models write disparity, not depth; \
                 declare `\"{DEPTH_KIND_KEY}\": \"{Z_DEPTH}\"` once it holds z-depth in the poses' units",
                depth_path.display()
            ),
        )),
    }
}

/// The (T, H, W) depth of a depth-only archive: member `depths` (Video Depth Anything) or `depth`
/// (DepthCrafter), returned as its shape and one row-major plane per frame.
pub fn read_depth_only(path: &Path) -> Result<(Vec<usize>, Vec<Vec<f32>>)> {
    let mut archive = NpzReader::open(path)?;
    let member = ["depths", "depth"].into_iter().find(|m| archive.contains(m)).ok_or_else(|| {
        Error::array(path, None, "no `depths` (Video Depth Anything) or `depth` (DepthCrafter) member")
    })?;
    let array = archive.read_f32(member, &[Axis::Any, Axis::Pixels, Axis::Pixels])?;
    let shape = array.shape.clone();
    let planes = array.into_planes();
    for (i, plane) in planes.iter().enumerate() {
        check_depth_sign(path, member, i, plane)?;
    }
    Ok((shape, planes))
}
