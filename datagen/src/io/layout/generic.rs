//! The toolkit's own generic layout: `frames/*.png|jpg` (or the folder's one input video,
//! [`frames_video`]), `depth/*.exr` (one float channel), `cameras.json`: `{"intrinsics": K or
//! [K per frame], "world_from_camera": [4×4 per frame]}` with matrices as nested row lists or
//! 9/16 row-major values. The frames and `cameras.json` readers serve the depth-only layout too
//! ([`crate::io::depth_only`]).

use std::path::{Path, PathBuf};

use image::RgbImage;

use crate::error::{Error, Result};
use crate::io::npy::NdArray;
use crate::io::reconstruction::{Parts, Reconstruction, assemble, read_exr_folder, with_extension};
use foundation::frames::read_frames;

/// The layout's cameras file.
pub const CAMERAS_FILE: &str = "cameras.json";

/// Whether the generic layout's files are in `dir`: `depth/*.exr`, or `cameras.json` with a
/// `depth/` folder or without a depth-only tool's archive beside it.
pub fn recognised(dir: &Path) -> Result<bool> {
    let depth = dir.join("depth");
    if depth.is_dir() && !with_extension(&depth, &["exr"])?.is_empty() {
        return Ok(true);
    }
    Ok(dir.join(CAMERAS_FILE).is_file() && (depth.is_dir() || crate::io::depth_only::depth_only_files(dir)?.is_empty()))
}

/// Reads the generic folder `dir`: frames and reconstruction.
pub(crate) fn read(dir: &Path) -> Result<Parts> {
    // Decoding is mostly serial: read the reconstruction meanwhile.
    let (frames, parts) = rayon::join(|| read_frames_or_video(dir), || reconstruction(dir));
    let (fps, frames, frames_source) = frames?;
    assemble(fps, frames, &frames_source, parts?)
}

/// The reconstruction of the generic folder `dir` (no frames): `depth/*.exr` and `cameras.json`.
pub(crate) fn reconstruction(dir: &Path) -> Result<Reconstruction> {
    let depth_dir = dir.join("depth");
    let depth = read_exr_folder(&depth_dir)?;
    let (cameras_path, _, intrinsics, poses) = read_cameras_json(dir)?;
    let intrinsics = Some((cameras_path.clone(), intrinsics));
    Ok(Reconstruction { depth_path: depth_dir, depth, intrinsics, poses: Some((cameras_path, poses)) })
}

/// `cameras.json` of `dir`: its path, the parsed document, and its `intrinsics` and
/// `world_from_camera` arrays.
pub(crate) fn read_cameras_json(dir: &Path) -> Result<(PathBuf, serde_json::Value, NdArray<f64>, NdArray<f64>)> {
    let cameras_path = dir.join(CAMERAS_FILE);
    let text = std::fs::read_to_string(&cameras_path).map_err(|e| Error::io(&cameras_path, e))?;
    let cameras: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| Error::invalid(&cameras_path, "cameras", format!("invalid JSON: {e}")))?;
    if !cameras.is_object() {
        return Err(Error::invalid(
            &cameras_path,
            "cameras",
            "expected an object with `intrinsics` and `world_from_camera`",
        ));
    }
    let key = |name: &str| {
        cameras.get(name).ok_or_else(|| {
            Error::invalid(&cameras_path, name, "missing: cameras.json needs `intrinsics` and `world_from_camera`")
        })
    };
    let intrinsics = json_intrinsics(&cameras_path, key("intrinsics")?)?;
    let poses = json_poses(&cameras_path, key("world_from_camera")?)?;
    Ok((cameras_path, cameras, intrinsics, poses))
}

/// The `intrinsics` of `cameras.json` as an `(3, 3)` (one K for all frames) or `(N, 3, 3)`
/// array. A single K is 9 numbers or 3 rows of 3; a per-frame list holds one such K per frame.
/// A list of 3 lists of 3 numbers is therefore one nested K, never 3 frames' K (a flat K has 9).
fn json_intrinsics(path: &Path, value: &serde_json::Value) -> Result<NdArray<f64>> {
    let field = "intrinsics";
    let single =
        |value| foundation::camera::json_matrix(value, 3, 3).map_err(|reason| Error::invalid(path, field, reason));
    let serde_json::Value::Array(items) = value else {
        return Err(single(value).unwrap_err());
    };
    let is_number_list =
        |v: &serde_json::Value| v.as_array().is_some_and(|r| r.iter().all(serde_json::Value::is_number));
    let one_k = items.iter().all(serde_json::Value::is_number)
        || (items.len() == 3 && items.iter().all(|r| is_number_list(r) && r.as_array().is_some_and(|r| r.len() == 3)));
    if one_k {
        return Ok(NdArray { shape: vec![3, 3], data: single(value)? });
    }
    let mut data = Vec::with_capacity(items.len() * 9);
    for (i, k) in items.iter().enumerate() {
        let values = foundation::camera::json_matrix(k, 3, 3)
            .map_err(|reason| Error::invalid(path, format!("{field}[{i}]"), reason))?;
        data.extend(values);
    }
    Ok(NdArray { shape: vec![items.len(), 3, 3], data })
}

/// The `world_from_camera` of `cameras.json`: one 4×4 pose per frame (nested rows or 16 values).
fn json_poses(path: &Path, value: &serde_json::Value) -> Result<NdArray<f64>> {
    let field = "world_from_camera";
    let Some(items) = value.as_array() else {
        return Err(Error::invalid(path, field, "expected a list of per-frame 4×4 matrices"));
    };
    let is_row = |v: &serde_json::Value| {
        v.as_array().is_some_and(|r| r.len() == 4 && r.iter().all(serde_json::Value::is_number))
    };
    if !items.is_empty()
        && (items.iter().all(serde_json::Value::is_number) || (items.len() == 4 && items.iter().all(is_row)))
    {
        return Err(Error::invalid(
            path,
            field,
            "a single matrix: expected a list of per-frame 4×4 matrices, one per frame",
        ));
    }
    let mut data = Vec::with_capacity(items.len() * 16);
    for (i, pose) in items.iter().enumerate() {
        let values = foundation::camera::json_matrix(pose, 4, 4)
            .map_err(|reason| Error::invalid(path, format!("{field}[{i}]"), reason))?;
        data.extend(values);
    }
    Ok(NdArray { shape: vec![items.len(), 4, 4], data })
}

/// The frames of `dir`: `frames/*.png|jpg`, else its one input video ([`frames_video`]).
pub(crate) fn read_frames_or_video(dir: &Path) -> Result<(f64, Vec<RgbImage>, PathBuf)> {
    let frames_dir = dir.join("frames");
    if frames_dir.is_dir() {
        let files = with_extension(&frames_dir, &["png", "jpg", "jpeg"])?;
        return Ok((0.0, read_frames(&files)?, frames_dir));
    }
    let video = frames_video(dir)?;
    let decoded = foundation::video::decode_video(&video)?;
    Ok((decoded.fps, decoded.frames, video))
}

/// Video file extensions a folder's frames may come in.
const VIDEO_EXTENSIONS: [&str; 5] = ["mp4", "mov", "mkv", "avi", "webm"];

/// Stem suffixes of the videos depth-only tools write *beside* their input, never frames:
/// DepthCrafter's `run.py` writes `NAME_depth.mp4` (the depth as grey video) and `NAME_vis.mp4`
/// (coloured); Video Depth Anything's `run.py` writes `NAME_vis.mp4` (Tencent/DepthCrafter and
/// DepthAnything/Video-Depth-Anything, `run.py`). `_depths` is Video Depth Anything's name for
/// its depth files, taken for a depth video too.
const TOOL_OUTPUT_VIDEO_SUFFIXES: [&str; 3] = ["_depth", "_depths", "_vis"];

/// Stem suffixes of the input video those tools save with their output, the frames their depth
/// belongs to (resized to the tool's working resolution): DepthCrafter's `NAME_input.mp4`, Video
/// Depth Anything's `NAME_src.mp4`.
const TOOL_INPUT_VIDEO_SUFFIXES: [&str; 2] = ["_input", "_src"];

/// The one video of `dir` that holds the frames. Videos a depth tool writes beside its input
/// (depth and visualisation videos, [`TOOL_OUTPUT_VIDEO_SUFFIXES`]) are never frames. Among the
/// rest, the tool's saved input `NAME_input`/`NAME_src` ([`TOOL_INPUT_VIDEO_SUFFIXES`]) wins over
/// the original `NAME` video it was made from: the depth belongs to the saved input's frames
/// (DepthCrafter's `--target-fps` drops frames, both tools resize). Any other choice between
/// several videos (or none) is an error naming them: a video is never picked by its sort order.
pub fn frames_video(dir: &Path) -> Result<PathBuf> {
    let videos = with_extension(dir, &VIDEO_EXTENSIONS)?;
    let stem = |p: &Path| p.file_stem().and_then(|s| s.to_str()).unwrap_or("").to_owned();
    let name = |p: &PathBuf| p.file_name().unwrap_or_default().to_string_lossy().into_owned();
    let (outputs, candidates): (Vec<PathBuf>, Vec<PathBuf>) =
        videos.into_iter().partition(|p| TOOL_OUTPUT_VIDEO_SUFFIXES.iter().any(|s| stem(p).ends_with(s)));
    let names = |paths: &[PathBuf]| paths.iter().map(name).collect::<Vec<_>>().join(", ");
    // The tool's saved input, when the other candidates are only the original it was made from.
    let original_of = |p: &Path| {
        let stem = stem(p);
        TOOL_INPUT_VIDEO_SUFFIXES.iter().find_map(|s| stem.strip_suffix(s).map(str::to_owned))
    };
    let tool_inputs: Vec<(&PathBuf, String)> =
        candidates.iter().filter_map(|p| original_of(p).map(|original| (p, original))).collect();
    if let [(input, original)] = tool_inputs.as_slice()
        && candidates.iter().all(|p| p == *input || stem(p) == *original)
    {
        return Ok((*input).clone());
    }
    match candidates.as_slice() {
        [one] => Ok(one.clone()),
        [] if outputs.is_empty() => Err(Error::invalid(dir, "frames", "no frames/ folder and no video file")),
        [] => Err(Error::invalid(
            dir,
            "frames",
            format!(
                "no input video: {} are a depth tool's depth or visualisation videos (names ending in {}), not frames; \
                 add the tool's input video (DepthCrafter's NAME_input.mp4, Video Depth Anything's NAME_src.mp4) or frames/",
                names(&outputs),
                TOOL_OUTPUT_VIDEO_SUFFIXES.join(", ")
            ),
        )),
        several => Err(Error::invalid(
            dir,
            "frames",
            format!(
                "ambiguous: several videos could be the frames ({}){}; keep only the one the depth was computed from \
                 (DepthCrafter's NAME_input.mp4, Video Depth Anything's NAME_src.mp4) or put the frames in frames/",
                names(several),
                if outputs.is_empty() {
                    String::new()
                } else {
                    format!(" besides the tool outputs {}", names(&outputs))
                }
            ),
        )),
    }
}
