//! `datagen view`: a sequence (and the pairs made from it) as a recording for the Rerun viewer
//! (rerun-io/rerun, the open-source viewer for 4D data; `pip install rerun-sdk`, `rerun FILE.rrd`).
//! Per frame: the coloured point cloud of the depth map in world coordinates, the source camera
//! (pose, pinhole, its image), and from a shard of pairs each sampled novel trajectory's camera as
//! a frustum and its co-visibility mask in the source image.
//!
//! The recording is written by `scripts/rerun_view.py` with the Rerun SDK (the `.rrd` encoding is
//! the SDK's): this module writes what it needs into a folder beside the output (`view.json` with
//! cameras and trajectories, `frame_*.png`, `points_*.npy`, `colors_*.npy`, `mask_*.png`), runs the
//! script, which writes `FILE.rrd.tmp`, and renames that to `FILE.rrd` only once it succeeded; the
//! folder is removed either way, so a failed run leaves nothing.

use std::path::{Path, PathBuf};
use std::process::Command;

use rayon::prelude::*;
use serde::Serialize;

use crate::error::{Error, Result};
use crate::io::sequence::Sequence;
use foundation::camera::{mat3_to_row_major, mat4_to_row_major};

/// The script that writes the recording, as installed with the sources.
pub const DEFAULT_SCRIPT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../scripts/rerun_view.py");

/// Every `DEFAULT_POINT_STRIDE`-th pixel in x and y becomes a point: a quarter of the pixels,
/// ~86k points for a 480×720 frame, which the viewer draws at interactive rates over 49 frames.
pub const DEFAULT_POINT_STRIDE: u32 = 2;

/// How the recording is made.
#[derive(Debug, Clone)]
pub struct ViewOptions {
    /// The Python interpreter with `rerun-sdk` installed.
    pub python: PathBuf,
    /// The script that writes the recording.
    pub script: PathBuf,
    /// Pixel stride of the point clouds.
    pub point_stride: u32,
}

impl Default for ViewOptions {
    fn default() -> Self {
        Self {
            python: PathBuf::from("python3"),
            script: PathBuf::from(DEFAULT_SCRIPT),
            point_stride: DEFAULT_POINT_STRIDE,
        }
    }
}

/// What went into the recording.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ViewSummary {
    /// Frames.
    pub frames: usize,
    /// Points over all frames.
    pub points: usize,
    /// Novel trajectories from the shard.
    pub trajectories: usize,
}

#[derive(Serialize)]
struct TrajectoryView {
    name: String,
    clip_start: u32,
    intrinsics: Vec<[f64; 9]>,
    world_from_camera: Vec<[f64; 16]>,
    masks: Vec<String>,
}

#[derive(Serialize)]
struct SequenceView {
    source_id: String,
    fps: f64,
    width: u32,
    height: u32,
    frames: usize,
    intrinsics: Vec<[f64; 9]>,
    world_from_camera: Vec<[f64; 16]>,
    trajectories: Vec<TrajectoryView>,
}

/// Writes the recording of `sequence` (with the pairs of `shard`, if given) to `out`.
pub fn write_recording(
    sequence: &Sequence,
    shard: Option<&Path>,
    out: &Path,
    options: &ViewOptions,
) -> Result<ViewSummary> {
    if options.point_stride == 0 {
        return Err(Error::parameter("point-stride", "must be at least 1"));
    }
    let parts = out.with_extension("rrd.parts");
    let temporary = out.with_extension("rrd.tmp");
    let result = write_parts(sequence, shard, &parts, options.point_stride)
        .and_then(|summary| run_script(options, &parts, &temporary).map(|()| summary))
        .and_then(|summary| std::fs::rename(&temporary, out).map(|()| summary).map_err(|e| Error::io(out, e)));
    let _ = std::fs::remove_dir_all(&parts);
    if result.is_err() {
        let _ = std::fs::remove_file(&temporary);
    }
    result
}

fn run_script(options: &ViewOptions, parts: &Path, out: &Path) -> Result<()> {
    let output = Command::new(&options.python)
        .arg(&options.script)
        .arg(parts)
        .arg(out)
        .output()
        .map_err(|e| Error::io(&options.python, e))?;
    if !output.status.success() {
        let stderr = String::from_utf8_lossy(&output.stderr);
        return Err(Error::parameter(
            "python",
            format!(
                "{} {} failed ({}): {} (the interpreter needs `pip install rerun-sdk`)",
                options.python.display(),
                options.script.display(),
                output.status,
                stderr.trim().lines().last().unwrap_or("")
            ),
        ));
    }
    // An interpreter that is not Python (`--python /bin/true`), or a script that did nothing,
    // exits 0 without a recording: say so, with what it printed, rather than fail at the rename.
    if !std::fs::metadata(out).is_ok_and(|m| m.is_file() && m.len() > 0) {
        let printed = |bytes: &[u8]| {
            let text = String::from_utf8_lossy(bytes).trim().to_string();
            if text.is_empty() { "nothing".to_string() } else { format!("`{text}`") }
        };
        return Err(Error::parameter(
            "python",
            format!(
                "{} {} exited successfully but wrote no recording to {} (is it a Python interpreter with `pip install \
                 rerun-sdk`?); it printed {} on stdout and {} on stderr",
                options.python.display(),
                options.script.display(),
                out.display(),
                printed(&output.stdout),
                printed(&output.stderr)
            ),
        ));
    }
    Ok(())
}

fn write_parts(sequence: &Sequence, shard: Option<&Path>, parts: &Path, stride: u32) -> Result<ViewSummary> {
    if parts.exists() {
        std::fs::remove_dir_all(parts).map_err(|e| Error::io(parts, e))?;
    }
    std::fs::create_dir_all(parts).map_err(|e| Error::io(parts, e))?;
    let points = (0..sequence.len())
        .into_par_iter()
        .map(|i| write_frame(sequence, i, parts, stride as usize))
        .collect::<Result<Vec<usize>>>()?;
    let trajectories = match shard {
        Some(path) => trajectories(sequence, path, parts)?,
        None => Vec::new(),
    };
    let summary = ViewSummary { frames: sequence.len(), points: points.iter().sum(), trajectories: trajectories.len() };
    let (width, height) = sequence.size();
    let view = SequenceView {
        source_id: sequence.source_id.clone(),
        fps: sequence.fps,
        width,
        height,
        frames: sequence.len(),
        intrinsics: sequence.cameras.iter().map(|c| mat3_to_row_major(&c.intrinsics)).collect(),
        world_from_camera: sequence.cameras.iter().map(|c| mat4_to_row_major(&c.world_from_camera)).collect(),
        trajectories,
    };
    let path = parts.join("view.json");
    std::fs::write(&path, serde_json::to_vec(&view).expect("serialisable")).map_err(|e| Error::io(&path, e))?;
    Ok(summary)
}

/// Writes frame `i`'s image and its point cloud (every `stride`-th valid pixel lifted to world
/// coordinates, with its colour); returns the number of points.
fn write_frame(sequence: &Sequence, i: usize, parts: &Path, stride: usize) -> Result<usize> {
    let frame = &sequence.frames[i];
    let path = parts.join(format!("frame_{i:05}.png"));
    frame.save(&path).map_err(|e| Error::Image { context: path.display().to_string(), reason: e.to_string() })?;
    let camera = &sequence.cameras[i];
    let depth = &sequence.depth[i];
    let (mut points, mut colours) = (Vec::new(), Vec::new());
    for v in (0..depth.height).step_by(stride) {
        for u in (0..depth.width).step_by(stride) {
            let d = depth.values[v * depth.width + u];
            if !(d.is_finite() && d > 0.0) {
                continue;
            }
            let point = camera.unproject(u as f64, v as f64, f64::from(d));
            points.extend([point.x as f32, point.y as f32, point.z as f32]);
            colours.extend_from_slice(&frame.get_pixel(u as u32, v as u32).0);
        }
    }
    let n = points.len() / 3;
    crate::io::npy::write_npy(&parts.join(format!("points_{i:05}.npy")), &[n, 3], &points)?;
    crate::io::npy::write_npy(&parts.join(format!("colors_{i:05}.npy")), &[n, 3], &colours)?;
    Ok(n)
}

/// The novel trajectories of the shard's clips of `sequence`, their masks written as PNG files.
fn trajectories(sequence: &Sequence, shard: &Path, parts: &Path) -> Result<Vec<TrajectoryView>> {
    let clips = schemas::read_shard(shard)?;
    let ours: Vec<_> = clips.iter().filter(|c| c.source_id == sequence.source_id).collect();
    if ours.is_empty() {
        let found: Vec<&str> = clips.iter().map(|c| c.source_id.as_str()).collect();
        return Err(Error::invalid(
            shard,
            "source_id",
            format!("no clip of sequence `{}` (the shard holds {found:?})", sequence.source_id),
        ));
    }
    let mut views = Vec::new();
    for clip in ours {
        if (clip.width, clip.height) != sequence.size() || clip.clip_start as usize + clip.frames.len() > sequence.len()
        {
            return Err(Error::invalid(
                shard,
                format!("{}: frames", clip.clip_id),
                format!(
                    "clip of {}x{} frames {}..{} does not fit the sequence's {} frames of {:?}",
                    clip.width,
                    clip.height,
                    clip.clip_start,
                    clip.clip_start as usize + clip.frames.len(),
                    sequence.len(),
                    sequence.size()
                ),
            ));
        }
        for trajectory in &clip.trajectories {
            let name = format!("{}_t{}", clip.clip_id, trajectory.index);
            let mut masks = Vec::new();
            for (f, png) in trajectory.covisible_mask.iter().enumerate() {
                let file = format!("mask_{name}_{f:05}.png").replace(['/', '\\'], "~");
                let path = parts.join(&file);
                std::fs::write(&path, png).map_err(|e| Error::io(&path, e))?;
                masks.push(file);
            }
            views.push(TrajectoryView {
                name,
                clip_start: clip.clip_start,
                intrinsics: clip.intrinsics.clone(),
                world_from_camera: trajectory.world_from_camera.clone(),
                masks,
            });
        }
    }
    Ok(views)
}
