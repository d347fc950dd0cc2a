//! ParallelDomain-4D scenes as GCD reads them (basilevh/gcd `data-gen/convert_pcl_pardom.py`,
//! `gcd-model/sgm/data/pardom_arbit.py`), the only public description of the layout: a scene
//! folder `scene_XXXXXX/` with
//!
//! - `rgb/<view>/<ts>.png` per view (`camera0` … `camera15`, `yaw-0`, `yaw-60`, `yaw-neg-60`),
//!   `<ts>` the 18-digit `t·10 + 5` of frame t (10 fps, GCD's `avail_fps`);
//! - `depth/<view>/<ts>.npz`, member `data` (H, W): z-depth in metres (GCD unprojects it along
//!   K⁻¹ without a ray-length correction; the sky holds huge values, kept as they are);
//! - `calibration/<one>.json`: parallel lists `names`, `intrinsics` (`fx`, `fy`, `cx`, `cy` in
//!   pixels, centres at integers as GCD uses them) and `extrinsics` (`rotation` {`qw`, `qx`,
//!   `qy`, `qz`}, `translation` {`x`, `y`, `z`}): each view's world_from_camera with OpenCV axes
//!   in the ego rig's frame, constant over the scene (GCD: "Camera parameters do not vary over
//!   time").
//!
//! Frames missing from some view (the released data lacks a few) are dropped for every view, as
//! GCD skips them; `time_ids` keep the instants. Layouts GCD does not read (several calibration
//! files, other extrinsic keys, timestamps not of the form t·10 + 5) are refused by name.
//! `semantic_segmentation_2d/`, `instance_segmentation_2d/`, `motion_vectors_2d/`,
//! `surface_normals_2d/` and `ontology/` are not read. GCD's evaluation feeds the ego camera
//! `yaw-0` as input; the split holds every other view out.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4, DQuat, DVec3};
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::io::json_fields::{JsonFile, list, number};
use crate::io::multiview::{CameraView, EvalSplit, MultiViewScene};
use crate::io::npy::{Axis, NpzReader};
use crate::io::sequence::Sequence;
use crate::io::tool_output::check_depth_sign;
use foundation::camera::{PinholeCamera, ROTATION_TOLERANCE, checked_intrinsics, checked_pose, mat4_to_row_major};
use foundation::depth::DepthMap;
use foundation::frames::read_frames;

/// The view GCD's ParallelDomain-4D evaluation takes as input (the forward ego camera).
pub const GCD_INPUT_VIEW: &str = "yaw-0";

/// Frame rate of the released frames (GCD's `avail_fps`).
pub const FPS: f64 = 10.0;

/// Timestamp units per frame and offset: frame t is file `t·10 + 5` (GCD's loaders).
const TIMESTAMP_STEP: u64 = 10;
const TIMESTAMP_OFFSET: u64 = 5;

/// Whether `dir` is a ParallelDomain-4D scene folder: `rgb/`, `depth/` and `calibration/`.
pub fn is_pardom4d(dir: &Path) -> bool {
    ["rgb", "depth", "calibration"].iter().all(|sub| dir.join(sub).is_dir())
}

/// Reads the ParallelDomain-4D scene folder `dir`.
pub fn read_pardom4d(dir: &Path) -> Result<MultiViewScene> {
    let calibration = read_calibration(dir)?;
    let rgb_dir = dir.join("rgb");
    let mut views = Vec::new();
    for entry in std::fs::read_dir(&rgb_dir).map_err(|e| Error::io(&rgb_dir, e))? {
        let path = entry.map_err(|e| Error::io(&rgb_dir, e))?.path();
        if path.is_dir() {
            views.push(path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default());
        }
    }
    views.sort();
    if views.len() < 2 {
        return Err(Error::invalid(&rgb_dir, "views", "a multi-view scene needs two or more view folders"));
    }
    let folders: Vec<PathBuf> = views.iter().map(|view| rgb_dir.join(view)).collect();
    crate::io::multiview::check_distinct_folders(&rgb_dir, "views", &folders)?;
    // The instants every view has both a frame and a depth map for.
    let mut common: Option<BTreeSet<u64>> = None;
    for view in &views {
        let rgb = timestamps_in(&rgb_dir.join(view), "png")?;
        let depth = timestamps_in(&dir.join("depth").join(view), "npz")?;
        let both: BTreeSet<u64> = rgb.intersection(&depth).copied().collect();
        common = Some(common.map_or(both.clone(), |c| c.intersection(&both).copied().collect()));
    }
    let times: Vec<u64> = common.unwrap_or_default().into_iter().collect();
    if times.is_empty() {
        return Err(Error::invalid(dir, "frames", "no instant has a frame and a depth map in every view"));
    }
    let scene_id = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let mut cameras = Vec::with_capacity(views.len());
    for view in &views {
        let (intrinsics, world_from_camera) = calibration.view(view)?;
        cameras.push(read_view(dir, &scene_id, view, &times, intrinsics, world_from_camera)?);
    }
    let split = views.iter().any(|v| v == GCD_INPUT_VIEW).then(|| EvalSplit {
        input: GCD_INPUT_VIEW.to_owned(),
        held_out: views.iter().filter(|v| *v != GCD_INPUT_VIEW).cloned().collect(),
    });
    Ok(MultiViewScene { scene_id, path: dir.to_owned(), cameras, split })
}

/// The timestamps of the `<ts>.<ext>` files of `folder`, each checked to be `t·10 + 5`.
fn timestamps_in(folder: &Path, ext: &str) -> Result<BTreeSet<u64>> {
    let mut found = BTreeSet::new();
    for entry in std::fs::read_dir(folder).map_err(|e| Error::io(folder, e))? {
        let path = entry.map_err(|e| Error::io(folder, e))?.path();
        if path.extension().is_none_or(|e| e != ext) {
            continue;
        }
        let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        let ts = stem.parse::<u64>().ok().filter(|ts| ts % TIMESTAMP_STEP == TIMESTAMP_OFFSET);
        let ts = ts.ok_or_else(|| {
            let reason =
                "file names must be the 18-digit timestamps t·10 + 5 GCD reads; other layouts are not documented";
            Error::invalid(&path, "timestamp", reason)
        })?;
        found.insert(ts);
    }
    Ok(found)
}

/// `calibration/*.json`.
struct Calibration {
    file: JsonFile,
    names: Vec<String>,
}

fn read_calibration(dir: &Path) -> Result<Calibration> {
    let folder = dir.join("calibration");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&folder)
        .map_err(|e| Error::io(&folder, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "json"))
        .collect();
    files.sort();
    let [path] = files.as_slice() else {
        let reason = format!("expected one calibration JSON (GCD reads the first), found {}", files.len());
        return Err(Error::invalid(folder, "calibration", reason));
    };
    let file = JsonFile::read(path, "calibration")?;
    let names = file.strings("names")?;
    // View names are folder names under rgb/ and depth/.
    for (i, name) in names.iter().enumerate() {
        foundation::paths::check_name(name)
            .map_err(|reason| Error::invalid(&file.path, format!("names[{i}]"), reason))?;
    }
    for key in ["intrinsics", "extrinsics"] {
        let len = list(&file.path, key, file.get(key)?)?.len();
        if len != names.len() {
            return Err(Error::invalid(&file.path, key, format!("{len} entries for {} `names`", names.len())));
        }
    }
    Ok(Calibration { file, names })
}

impl Calibration {
    /// The intrinsics and world_from_camera of `view`.
    fn view(&self, view: &str) -> Result<(glam::DMat3, glam::DMat4)> {
        let path = &self.file.path;
        let i = self.names.iter().position(|n| n == view).ok_or_else(|| {
            Error::invalid(path, "names", format!("no calibration for view `{view}` (a folder of rgb/)"))
        })?;
        let get = |key: &str, sub: &str| -> Result<f64> {
            let label = format!("{key}[{i}].{sub}");
            let value = self.file.value[key][i].get(sub).ok_or_else(|| Error::invalid(path, &label, "missing"))?;
            number(path, &label, value)
        };
        let (fx, fy, cx, cy) =
            (get("intrinsics", "fx")?, get("intrinsics", "fy")?, get("intrinsics", "cx")?, get("intrinsics", "cy")?);
        let intrinsics =
            checked_intrinsics(path, &format!("intrinsics[{i}]"), &[fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0])?;
        if self.file.value["extrinsics"][i].get("rotation").is_none() {
            let reason = "missing: GCD reads `rotation` {qw, qx, qy, qz} and `translation` {x, y, z}; other keys are not documented";
            return Err(Error::invalid(path, format!("extrinsics[{i}].rotation"), reason));
        }
        let rotation = &self.file.value["extrinsics"][i]["rotation"];
        let translation = &self.file.value["extrinsics"][i]["translation"];
        let component = |value: &serde_json::Value, key: &str, label: &str| -> Result<f64> {
            let label = format!("extrinsics[{i}].{label}.{key}");
            let v = value.get(key).ok_or_else(|| Error::invalid(path, &label, "missing"))?;
            number(path, &label, v)
        };
        let (w, x, y, z) = (
            component(rotation, "qw", "rotation")?,
            component(rotation, "qx", "rotation")?,
            component(rotation, "qy", "rotation")?,
            component(rotation, "qz", "rotation")?,
        );
        let norm = (w * w + x * x + y * y + z * z).sqrt();
        if (norm - 1.0).abs() > ROTATION_TOLERANCE {
            let reason = format!("norm {norm}: not a unit quaternion, so not a rotation");
            return Err(Error::invalid(path, format!("extrinsics[{i}].rotation"), reason));
        }
        let position = [
            component(translation, "x", "translation")?,
            component(translation, "y", "translation")?,
            component(translation, "z", "translation")?,
        ];
        let rotation = DMat3::from_quat(DQuat::from_xyzw(x, y, z, w));
        let row_major = mat4_to_row_major(&DMat4::from_mat3_translation(
            rotation,
            DVec3::new(position[0], position[1], position[2]),
        ));
        let pose = checked_pose(path, &format!("extrinsics[{i}]"), &row_major)?;
        Ok((intrinsics, pose))
    }
}

/// One view's frames and depth at the instants `times`.
fn read_view(
    dir: &Path,
    scene_id: &str,
    view: &str,
    times: &[u64],
    intrinsics: glam::DMat3,
    world_from_camera: glam::DMat4,
) -> Result<CameraView> {
    let name = |sub: &str, ts: u64, ext: &str| dir.join(sub).join(view).join(format!("{ts:018}.{ext}"));
    let paths: Vec<PathBuf> = times.iter().map(|&ts| name("rgb", ts, "png")).collect();
    let frames = read_frames(&paths)?;
    let (width, height) = frames[0].dimensions();
    let depth = times
        .par_iter()
        .enumerate()
        .map(|(k, &ts)| {
            let path = name("depth", ts, "npz");
            let mut archive = NpzReader::open(&path)?;
            let values = archive.read_f32("data", &[Axis::Is(height as usize), Axis::Is(width as usize)])?.data;
            check_depth_sign(&path, "data", k, &values)?;
            Ok(DepthMap { width: width as usize, height: height as usize, values })
        })
        .collect::<Result<Vec<_>>>()?;
    let camera = PinholeCamera { width, height, intrinsics, world_from_camera };
    let time_ids: Vec<usize> = times.iter().map(|ts| (ts / TIMESTAMP_STEP) as usize).collect();
    let sequence = Sequence {
        source_id: format!("{scene_id}_{view}"),
        path: dir.join("rgb").join(view),
        fps: FPS,
        cameras: vec![camera; frames.len()],
        frames,
        depth,
        dynamic_masks: None,
        second_depth: None,
    };
    Ok(CameraView {
        id: view.to_owned(),
        sequence,
        timestamps: Some(time_ids.iter().map(|&t| t as f64 / FPS).collect()),
        time_ids,
        has_depth: true,
        covisible: None,
    })
}
