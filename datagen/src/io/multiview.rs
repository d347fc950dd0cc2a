//! Synchronised multi-camera scenes: several cameras filming one dynamic scene at the same
//! instants, in one world frame (the input of multi-view pairs, where one camera's real frames
//! are the target for another's render).
//!
//! The generic layout is a scene folder with one sub-folder per camera, each a sequence folder in
//! any layout [`crate::io::sequence`] reads (typically the generic one: `frames/`, `depth/*.exr`,
//! `cameras.json`). Camera ids are the sub-folder names, in sorted order; every sub-folder but
//! hidden ones must be a camera. Every camera must have
//! the same number of frames, frame k of every camera being the same instant. A camera's
//! `cameras.json` may give `timestamps` (seconds, one per frame, increasing); where one camera
//! has them, all must, and they must agree within [`TIMESTAMP_TOLERANCE`] of a frame interval.
//! The poses of all cameras are read as one world frame (nothing here can check that).
//!
//! [`read_multiview_as`] also reads the benchmark datasets' own layouts ([`MultiViewLayoutName`]:
//! DyCheck iPhone / Nerfies, Kubric-4D, ParallelDomain-4D), detected from their files.

use std::path::{Path, PathBuf};

use image::GrayImage;

use crate::error::{Error, Result};
use crate::io::sequence::{Sequence, detect_layout, read_sequence};
use foundation::paths::FolderIdentity;

/// Largest disagreement between the cameras' timestamps of one frame, as a fraction of the
/// median frame interval: half an interval would pair a frame with its neighbour's instant.
pub const TIMESTAMP_TOLERANCE: f64 = 0.25;

/// One camera of a [`MultiViewScene`].
#[derive(Debug, Clone)]
pub struct CameraView {
    /// The camera's id (its sub-folder's name, or the dataset's camera id).
    pub id: String,
    /// Its video and reconstruction. Where the dataset ships no depth for this camera
    /// (`has_depth` false: DyCheck's held-out cameras), every depth value is 0 (invalid).
    pub sequence: Sequence,
    /// Seconds of each frame, if its files give them.
    pub timestamps: Option<Vec<f64>>,
    /// The scene instant of each frame: frame k of this camera and frame j of another film the
    /// same instant when `time_ids[k] == time_ids[j]`. `0..n` in the generic layout, where every
    /// camera films every instant; datasets that drop frames of some cameras (DyCheck's
    /// held-out cameras) list the instants kept.
    pub time_ids: Vec<usize>,
    /// Whether `sequence.depth` is the dataset's depth (false: all invalid, none shipped).
    pub has_depth: bool,
    /// Per-frame co-visibility masks the dataset ships for this camera (non-zero = seen by the
    /// input camera; DyCheck's `covisible/`), at the frames' size.
    pub covisible: Option<Vec<GrayImage>>,
}

/// The evaluation protocol a benchmark dataset fixes for a scene: the camera the method sees and
/// the held-out cameras it is judged on.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EvalSplit {
    /// The input (training) camera's id.
    pub input: String,
    /// The held-out cameras' ids.
    pub held_out: Vec<String>,
}

/// A synchronised multi-camera scene.
#[derive(Debug, Clone)]
pub struct MultiViewScene {
    /// The scene's id (its folder's name).
    pub scene_id: String,
    /// The folder it was read from.
    pub path: PathBuf,
    /// Its cameras, by id.
    pub cameras: Vec<CameraView>,
    /// The dataset's evaluation split, where the format has one.
    pub split: Option<EvalSplit>,
}

impl MultiViewScene {
    /// Frames of the first camera (in the generic layout, of every camera).
    pub fn frames(&self) -> usize {
        self.cameras.first().map_or(0, |c| c.sequence.len())
    }

    /// The camera with id `id`.
    pub fn camera(&self, id: &str) -> Option<&CameraView> {
        self.cameras.iter().find(|c| c.id == id)
    }
}

/// The camera sub-folders of `dir` (sorted), if it is a multi-camera folder: it holds no sequence
/// files itself and at least two sub-folders that do.
pub fn camera_folders(dir: &Path) -> Option<Vec<PathBuf>> {
    if detect_layout(dir).is_ok() {
        return None;
    }
    let mut folders: Vec<PathBuf> = std::fs::read_dir(dir)
        .ok()?
        .filter_map(|entry| entry.ok().map(|e| e.path()))
        .filter(|path| path.is_dir() && detect_layout(path).is_ok())
        .collect();
    folders.sort();
    (folders.len() >= 2).then_some(folders)
}

/// Reads the multi-camera scene in `dir` (see the module documentation); an error names the file
/// and field at fault, the camera's folder for disagreements between cameras.
pub fn read_multiview(dir: &Path) -> Result<MultiViewScene> {
    let Some(folders) = camera_folders(dir) else {
        // A scene of two cameras, one of them broken, has one camera folder: name the broken one.
        if detect_layout(dir).is_err() {
            check_camera_folders(dir, &[])?;
        }
        return Err(Error::invalid(
            dir,
            "cameras",
            "not a multi-camera folder: expected two or more camera sub-folders, each a sequence folder",
        ));
    };
    check_camera_folders(dir, &folders)?;
    check_distinct_folders(dir, "cameras", &folders)?;
    let mut cameras = Vec::with_capacity(folders.len());
    for folder in &folders {
        let id = folder.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let sequence = read_sequence(folder)?;
        let timestamps = read_timestamps(folder, sequence.len())?;
        let time_ids = (0..sequence.len()).collect();
        cameras.push(CameraView { id, sequence, timestamps, time_ids, has_depth: true, covisible: None });
    }
    let first = &cameras[0];
    for camera in &cameras[1..] {
        if camera.sequence.len() != first.sequence.len() {
            return Err(Error::invalid(
                &camera.sequence.path,
                "frames",
                format!(
                    "camera `{}` has {} frames where camera `{}` has {}: synchronised cameras need one frame per instant each",
                    camera.id,
                    camera.sequence.len(),
                    first.id,
                    first.sequence.len()
                ),
            ));
        }
    }
    check_timestamps(&cameras)?;
    let scene_id = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    Ok(MultiViewScene { scene_id, path: dir.to_owned(), cameras, split: None })
}

/// Refuses a scene whose camera (or view) folders include one folder under two names (a link
/// `cam02 -> cam00`): its multi-view pairs would pair a camera with itself, and its co-visibility
/// would count one camera's frames twice. The error names both.
pub(crate) fn check_distinct_folders(dir: &Path, field: &str, folders: &[PathBuf]) -> Result<()> {
    let mut seen = std::collections::BTreeMap::new();
    for folder in folders {
        if let Some(first) = seen.insert(FolderIdentity::of(folder), folder) {
            let name = |p: &Path| p.file_name().map_or_else(String::new, |n| n.to_string_lossy().into_owned());
            let reason = format!(
                "`{}` and `{}` are the same folder ({}): every camera must be its own",
                name(first),
                name(folder),
                FolderIdentity::of(folder).path().display()
            );
            return Err(Error::invalid(dir, field, reason));
        }
    }
    Ok(())
}

/// Every sub-folder of `dir` but hidden ones and `readable` is a camera whose files are missing or
/// unrecognised: the error names it.
fn check_camera_folders(dir: &Path, readable: &[PathBuf]) -> Result<()> {
    for entry in std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))? {
        let path = entry.map_err(|e| Error::io(dir, e))?.path();
        let hidden = path.file_name().is_some_and(|n| n.to_string_lossy().starts_with('.'));
        if path.is_dir() && !hidden && !readable.contains(&path) {
            detect_layout(&path)?;
        }
    }
    Ok(())
}

/// `timestamps` of the camera's `cameras.json`, if it has one: `frames` finite, increasing numbers.
fn read_timestamps(folder: &Path, frames: usize) -> Result<Option<Vec<f64>>> {
    let path = folder.join("cameras.json");
    let Ok(text) = std::fs::read_to_string(&path) else { return Ok(None) };
    let json: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| Error::invalid(&path, "cameras", format!("invalid JSON: {e}")))?;
    let Some(value) = json.get("timestamps") else { return Ok(None) };
    let list = value.as_array().ok_or_else(|| Error::invalid(&path, "timestamps", "expected a list of seconds"))?;
    if list.len() != frames {
        return Err(Error::invalid(&path, "timestamps", format!("{} values for {frames} frames", list.len())));
    }
    let mut seconds = Vec::with_capacity(frames);
    for (i, value) in list.iter().enumerate() {
        let t = value.as_f64().filter(|t| t.is_finite());
        let t = t.ok_or_else(|| {
            Error::invalid(&path, format!("timestamps[{i}]"), format!("`{value}` is not a finite number"))
        })?;
        if seconds.last().is_some_and(|&previous| t <= previous) {
            return Err(Error::invalid(
                &path,
                format!("timestamps[{i}]"),
                format!("{t} does not follow {}", seconds[i - 1]),
            ));
        }
        seconds.push(t);
    }
    Ok(Some(seconds))
}

/// All cameras have timestamps or none, and frame k's agree within [`TIMESTAMP_TOLERANCE`] of the
/// median frame interval of the first camera that has them.
fn check_timestamps(cameras: &[CameraView]) -> Result<()> {
    let Some(reference) = cameras.iter().find(|c| c.timestamps.is_some()) else { return Ok(()) };
    let times = reference.timestamps.as_deref().unwrap_or_default();
    let mut intervals: Vec<f64> = times.windows(2).map(|w| w[1] - w[0]).collect();
    intervals.sort_by(f64::total_cmp);
    let interval = intervals.get(intervals.len() / 2).copied().unwrap_or(f64::INFINITY);
    for camera in cameras {
        let path = camera.sequence.path.join("cameras.json");
        let Some(own) = &camera.timestamps else {
            let reason =
                format!("missing, while camera `{}` gives them: give every camera timestamps or none", reference.id);
            return Err(Error::invalid(path, "timestamps", reason));
        };
        for (i, (a, b)) in own.iter().zip(times).enumerate() {
            if (a - b).abs() > TIMESTAMP_TOLERANCE * interval {
                let reason = format!(
                    "{a} s, but camera `{}` films frame {i} at {b} s (frame interval {interval} s)",
                    reference.id
                );
                return Err(Error::invalid(path, format!("timestamps[{i}]"), reason));
            }
        }
    }
    Ok(())
}
