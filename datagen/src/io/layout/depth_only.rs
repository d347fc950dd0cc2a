//! The depth-only layout: a depth-only tool's archive (Video Depth Anything, DepthCrafter:
//! [`crate::io::depth_only`] reads it) with the frames as the generic layout has them and a
//! `cameras.json` from another tool declaring `depth_kind` ([`super::generic`] reads both).

use std::path::{Path, PathBuf};

use crate::error::{Error, Result};
use crate::io::layout::generic::{CAMERAS_FILE, read_cameras_json, read_frames_or_video};
use crate::io::reconstruction::{DepthStack, Parts, Reconstruction, assemble};

/// The depth-only archives of `dir` when it has `cameras.json` and no `depth/` folder (which
/// would make it generic): one is the layout, several are ambiguous.
pub fn archives(dir: &Path) -> Result<Vec<PathBuf>> {
    if dir.join(CAMERAS_FILE).is_file() && !dir.join("depth").is_dir() {
        crate::io::depth_only::depth_only_files(dir)
    } else {
        Ok(Vec::new())
    }
}

/// A depth-only tool's archive `depth_path` with the cameras of `cameras.json` in `dir`.
pub(crate) fn reconstruction(dir: &Path, depth_path: &Path) -> Result<Reconstruction> {
    let cameras_file = dir.join(CAMERAS_FILE);
    if !cameras_file.is_file() {
        return Err(Error::invalid(
            &cameras_file,
            "cameras",
            format!(
                "missing: {} holds depth only; depth-only tools give no cameras and none are invented: \
                 add cameras.json with `intrinsics` and `world_from_camera` from another tool",
                depth_path.display()
            ),
        ));
    }
    let (cameras_path, cameras, intrinsics, poses) = read_cameras_json(dir)?;
    crate::io::depth_only::check_depth_kind(&cameras_path, &cameras, depth_path)?;
    let (shape, planes) = crate::io::depth_only::read_depth_only(depth_path)?;
    Ok(Reconstruction {
        depth_path: depth_path.to_owned(),
        depth: DepthStack { shape, planes },
        intrinsics: Some((cameras_path.clone(), intrinsics)),
        poses: Some((cameras_path, poses)),
    })
}

/// Reads the depth-only folder `dir` with its archive `depth_path`.
pub(crate) fn read(dir: &Path, depth_path: &Path) -> Result<Parts> {
    let (frames, parts) = rayon::join(|| read_frames_or_video(dir), || reconstruction(dir, depth_path));
    let (fps, frames, frames_source) = frames?;
    assemble(fps, frames, &frames_source, parts?)
}
