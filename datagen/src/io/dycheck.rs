//! DyCheck's iPhone dataset and the Nerfies layout it extends, read as the public dycheck code
//! reads them (KAIR-BAIR/dycheck `dycheck/datasets/{nerfies,iphone}.py`,
//! `dycheck/geometry/camera.py`; google/nerfies README, "Datasets"), converted at the door:
//!
//! - `dataset.json`: `ids` (every item), `count`, `num_exemplars`, `train_ids`, `val_ids`;
//! - `metadata.json`: per item `warp_id` (the time id) and `camera_id` (`appearance_id`, a NeRF
//!   appearance code index, is not used, as in dycheck's iPhone parser);
//! - `scene.json`: `scale`, `center`, `near`, `far` ([`DycheckInfo`]; poses and depth keep the
//!   dataset's unnormalised world units, where `position` and the depth files are);
//! - `extra.json` (iPhone; absent in Nerfies captures): `factor` (the default resolution factor,
//!   2 for iPhone), `fps`, `bbox`, `lookat`, `up`;
//! - `camera/<item>.json`: `orientation` (rotation **camera_from_world**, rows the camera's
//!   axes, OpenCV axes), `position` (the camera centre), `focal_length` and `principal_point`
//!   (pixels at 1x, principal point in DyCheck's pixel-corner convention, pixel k spanning
//!   [k, k+1)), `skew`, `pixel_aspect_ratio` (fy = focal_length × ratio), `radial_distortion`
//!   (k1, k2, k3), `tangential_distortion` (p1, p2; older files call it `tangential`),
//!   `image_size` (W, H at 1x). At factor f, K is divided by f (dycheck's
//!   `rescale_image_domain`) and the principal point moved by −0.5 to the toolkit's centres at
//!   integers. A non-zero skew or distortion coefficient is refused naming the file and field:
//!   these cameras are not undistorted here, and treating them as pinholes would misplace pixels;
//! - `rgb/<f>x/<item>.png`: the frames (an alpha channel, DyCheck's LiDAR-coverage flag, is
//!   dropped: invalid depth already says it);
//! - `depth/<f>x/<item>.npy`, else `depth/1x/<item>.npy` area-averaged to factor f as dycheck
//!   does (a pixel is invalid unless all f × f source pixels are valid): (H, W, 1) or (H, W)
//!   float z-depth, 0 = invalid. Only the training camera has depth;
//! - `covisible/<f>x/val/<item>.png`: per held-out frame, non-zero where the training camera
//!   sees the pixel's surface;
//! - `splits/{train,val}.json`: `frame_names`, `time_ids`, `camera_ids` (without them,
//!   `dataset.json`'s `train_ids`/`val_ids`, else dycheck's rule: camera 0 trains, the others
//!   are held out).
//!
//! The evaluation split is the training split's one camera as input and the validation split's
//! cameras as held out; a held-out camera keeps only the frames the validation split lists.
//! `points.npy`, `keypoint/`, `emf.json` and `camera-paths/` are not read (see the README).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use glam::DVec3;
use image::GrayImage;
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::io::json_fields::{JsonFile, integer, numbers};
use crate::io::multiview::{CameraView, EvalSplit, MultiViewScene};
use crate::io::npy::MAX_SIDE_PX;
use crate::io::sequence::Sequence;
use crate::io::tool_output::check_depth_sign;
use foundation::camera::{PinholeCamera, checked_intrinsics, checked_pose, json_matrix};
use foundation::depth::DepthMap;
use foundation::frames::read_frames;
use foundation::paths::check_name;

/// The item list; with [`METADATA_FILE`] and [`CAMERA_DIR`], the mark of the layout.
pub const DATASET_FILE: &str = "dataset.json";
/// Per-item time and camera ids.
pub const METADATA_FILE: &str = "metadata.json";
/// Scene normalisation.
pub const SCENE_FILE: &str = "scene.json";
/// iPhone extras (default factor, frame rate, bounds).
pub const EXTRA_FILE: &str = "extra.json";
/// One JSON camera per item.
pub const CAMERA_DIR: &str = "camera";

/// DyCheck's principal point is in pixel-corner coordinates (its rays go through pixel
/// (i, j)'s centre at (j + 0.5, i + 0.5): `Camera.get_pixels` with `use_center`), the toolkit's
/// in centre-at-integer ones: subtract this.
pub const PIXEL_CORNER_OFFSET: f64 = 0.5;

/// What `scene.json` and `extra.json` say about the scene besides its cameras.
#[derive(Debug, Clone, PartialEq)]
pub struct DycheckInfo {
    /// The resolution factor the scene was read at (`rgb/<factor>x/`).
    pub factor: u32,
    /// `scene.json` `scale`: dycheck normalises positions as `(position − center) · scale`.
    pub scale: f64,
    /// `scene.json` `center`, in the dataset's (unnormalised) world units.
    pub center: DVec3,
    /// `scene.json` `near`, in normalised units (dycheck's ray length).
    pub near: f64,
    /// `scene.json` `far`, in normalised units.
    pub far: f64,
    /// `extra.json` `fps`, if the scene has that file.
    pub fps: Option<f64>,
    /// `extra.json` `bbox` (min, max), in normalised units.
    pub bbox: Option<[DVec3; 2]>,
    /// `extra.json` `lookat`, in normalised units.
    pub lookat: Option<DVec3>,
    /// `extra.json` `up` (a direction).
    pub up: Option<DVec3>,
}

/// One item of `dataset.json`.
#[derive(Debug, Clone)]
struct Item {
    name: String,
    time_id: usize,
    camera_id: u64,
}

/// Whether `dir` is in the DyCheck/Nerfies layout: `dataset.json`, `metadata.json` and `camera/`.
pub fn is_dycheck(dir: &Path) -> bool {
    dir.join(DATASET_FILE).is_file() && dir.join(METADATA_FILE).is_file() && dir.join(CAMERA_DIR).is_dir()
}

/// Reads the DyCheck scene `dir` at resolution factor `factor` (`None`: `extra.json`'s, else 1).
pub fn read_dycheck(dir: &Path, factor: Option<u32>) -> Result<MultiViewScene> {
    Ok(read_dycheck_with_info(dir, factor)?.0)
}

/// [`read_dycheck`], with what `scene.json` and `extra.json` say.
pub fn read_dycheck_with_info(dir: &Path, factor: Option<u32>) -> Result<(MultiViewScene, DycheckInfo)> {
    let info = read_info(dir, factor)?;
    let (items, listed) = read_items(dir)?;
    let camera_ids: BTreeSet<u64> = items.iter().map(|item| item.camera_id).collect();
    let splits = read_splits(dir, &items, &camera_ids)?.or(listed).or_else(|| default_splits(&items));
    let split = splits.as_ref().and_then(|(train, val)| eval_split(&items, train, val));
    let scene_id = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let mut cameras = Vec::with_capacity(camera_ids.len());
    for &camera_id in &camera_ids {
        let held_out = split.as_ref().is_some_and(|s| s.held_out.contains(&camera_id.to_string()));
        let mut own: Vec<&Item> = items
            .iter()
            .filter(|item| item.camera_id == camera_id)
            .filter(|item| !held_out || splits.as_ref().is_some_and(|(_, val)| val.contains(&item.name)))
            .collect();
        own.sort_by_key(|item| item.time_id);
        if let Some(pair) = own.windows(2).find(|pair| pair[0].time_id == pair[1].time_id) {
            return Err(Error::invalid(
                dir.join(METADATA_FILE),
                format!("{}.warp_id", pair[1].name),
                format!("camera {camera_id} films time {} twice (also item `{}`)", pair[1].time_id, pair[0].name),
            ));
        }
        cameras.push(read_camera_view(dir, &scene_id, camera_id, &own, &info, held_out)?);
    }
    if let Some(split) = &split {
        check_held_out_times(dir, &cameras, split, &items)?;
    }
    Ok((MultiViewScene { scene_id, path: dir.to_owned(), cameras, split }, info))
}

/// `scene.json` and `extra.json`, and the factor to read at.
fn read_info(dir: &Path, factor: Option<u32>) -> Result<DycheckInfo> {
    let scene = JsonFile::read(&dir.join(SCENE_FILE), "scene")?;
    let scale = scene.f64("scale")?;
    if scale <= 0.0 {
        return Err(Error::invalid(&scene.path, "scale", format!("must be positive, found {scale}")));
    }
    let center = vec3(&scene.vector("center", 3)?);
    let (near, far) = (scene.f64("near")?, scene.f64("far")?);
    let extra_path = dir.join(EXTRA_FILE);
    let (mut info_factor, mut fps, mut bbox, mut lookat, mut up) = (None, None, None, None, None);
    if extra_path.is_file() {
        let extra = JsonFile::read(&extra_path, "extra")?;
        let stated = extra.u64("factor")?;
        if !(1..=u64::from(u32::MAX)).contains(&stated) {
            return Err(Error::invalid(&extra.path, "factor", format!("must be a positive integer, found {stated}")));
        }
        info_factor = Some(stated as u32);
        let rate = extra.f64("fps")?;
        if rate <= 0.0 {
            return Err(Error::invalid(&extra.path, "fps", format!("must be positive, found {rate}")));
        }
        fps = Some(rate);
        let corners = json_matrix(extra.get("bbox")?, 2, 3).map_err(|e| Error::invalid(&extra.path, "bbox", e))?;
        if let Some(v) = corners.iter().find(|v| !v.is_finite()) {
            return Err(Error::invalid(&extra.path, "bbox", format!("non-finite value {v}")));
        }
        bbox = Some([vec3(&corners[..3]), vec3(&corners[3..])]);
        lookat = Some(vec3(&extra.vector("lookat", 3)?));
        up = Some(vec3(&extra.vector("up", 3)?));
    }
    let factor = factor.or(info_factor).unwrap_or(1);
    if factor == 0 {
        return Err(Error::parameter("factor", "must be a positive integer (the rgb/<factor>x folder), got 0"));
    }
    Ok(DycheckInfo { factor, scale, center, near, far, fps, bbox, lookat, up })
}

fn vec3(values: &[f64]) -> DVec3 {
    DVec3::new(values[0], values[1], values[2])
}

/// Training and validation item names.
type Splits = (BTreeSet<String>, BTreeSet<String>);

/// The items of `dataset.json` with their `metadata.json` ids, and its `train_ids`/`val_ids`
/// when it lists them.
fn read_items(dir: &Path) -> Result<(Vec<Item>, Option<Splits>)> {
    let dataset = JsonFile::read(&dir.join(DATASET_FILE), "dataset")?;
    let ids = dataset.strings("ids")?;
    if dataset.find("count").is_some() && dataset.u64("count")? != ids.len() as u64 {
        let reason = format!("{} for {} `ids`", dataset.u64("count")?, ids.len());
        return Err(Error::invalid(&dataset.path, "count", reason));
    }
    if ids.is_empty() {
        return Err(Error::invalid(&dataset.path, "ids", "no items"));
    }
    let mut seen = BTreeSet::new();
    for (i, id) in ids.iter().enumerate() {
        // Every file of an item is named after its id (`camera/<id>.json`, `rgb/<f>x/<id>.png`,
        // ...); the split files and `metadata.json` can only name ids listed here.
        check_name(id).map_err(|reason| Error::invalid(&dataset.path, format!("ids[{i}]"), reason))?;
        if !seen.insert(id.as_str()) {
            return Err(Error::invalid(&dataset.path, format!("ids[{i}]"), format!("`{id}` is listed twice")));
        }
    }
    let mut listed = Vec::new();
    for key in ["train_ids", "val_ids"] {
        let Some(_) = dataset.find(key) else { break };
        let names = dataset.strings(key)?;
        if let Some(i) = names.iter().position(|n| !seen.contains(n.as_str())) {
            let reason = format!("`{}` is not in `ids`", names[i]);
            return Err(Error::invalid(&dataset.path, format!("{key}[{i}]"), reason));
        }
        listed.push(names.into_iter().collect::<BTreeSet<_>>());
    }
    if let (Some(_), Some(train)) = (dataset.find("num_exemplars"), listed.first())
        && dataset.u64("num_exemplars")? != train.len() as u64
    {
        let reason = format!("{} for {} `train_ids`", dataset.u64("num_exemplars")?, train.len());
        return Err(Error::invalid(&dataset.path, "num_exemplars", reason));
    }
    let listed = (listed.len() == 2).then(|| (listed[0].clone(), listed[1].clone()));

    let metadata = JsonFile::read(&dir.join(METADATA_FILE), "metadata")?;
    let mut items = Vec::with_capacity(ids.len());
    for name in ids {
        let entry = metadata.value.get(&name).ok_or_else(|| {
            Error::invalid(&metadata.path, &name, "missing: every item of dataset.json needs an entry")
        })?;
        let field = |key: &str| {
            let label = format!("{name}.{key}");
            let value = entry.get(key).ok_or_else(|| Error::invalid(&metadata.path, &label, "missing"))?;
            integer(&metadata.path, &label, value)
        };
        let time_id = field("warp_id")? as usize;
        let camera_id = field("camera_id")?;
        items.push(Item { name, time_id, camera_id });
    }
    Ok((items, listed))
}

/// `splits/train.json` and `splits/val.json`, if the scene has them, checked against the items.
fn read_splits(dir: &Path, items: &[Item], camera_ids: &BTreeSet<u64>) -> Result<Option<Splits>> {
    let paths = ["train", "val"].map(|name| dir.join("splits").join(format!("{name}.json")));
    if !paths.iter().all(|p| p.is_file()) {
        return Ok(None);
    }
    let by_name: BTreeMap<&str, &Item> = items.iter().map(|item| (item.name.as_str(), item)).collect();
    let mut splits = Vec::with_capacity(2);
    for path in &paths {
        let split = JsonFile::read(path, "split")?;
        let names = split.strings("frame_names")?;
        let times = split.integers("time_ids")?;
        let cameras = split.integers("camera_ids")?;
        for (field, len) in [("time_ids", times.len()), ("camera_ids", cameras.len())] {
            if len != names.len() {
                let reason = format!("{len} values for {} `frame_names`", names.len());
                return Err(Error::invalid(path, field, reason));
            }
        }
        for (i, name) in names.iter().enumerate() {
            if !camera_ids.contains(&cameras[i]) {
                let known: Vec<String> = camera_ids.iter().map(u64::to_string).collect();
                let reason =
                    format!("camera {} does not exist: the scene's cameras are {}", cameras[i], known.join(", "));
                return Err(Error::invalid(path, format!("camera_ids[{i}]"), reason));
            }
            let item = by_name.get(name.as_str()).ok_or_else(|| {
                Error::invalid(path, format!("frame_names[{i}]"), format!("`{name}` is not an item of dataset.json"))
            })?;
            if item.camera_id != cameras[i] {
                let reason =
                    format!("{} for `{name}`, whose metadata.json camera_id is {}", cameras[i], item.camera_id);
                return Err(Error::invalid(path, format!("camera_ids[{i}]"), reason));
            }
            if item.time_id as u64 != times[i] {
                let reason = format!("{} for `{name}`, whose metadata.json warp_id is {}", times[i], item.time_id);
                return Err(Error::invalid(path, format!("time_ids[{i}]"), reason));
            }
        }
        splits.push(names.into_iter().collect::<BTreeSet<_>>());
    }
    Ok(Some((splits[0].clone(), splits[1].clone())))
}

/// dycheck's iPhone rule when no split is given: camera 0 trains, the others are held out.
fn default_splits(items: &[Item]) -> Option<Splits> {
    let (train, val): (Vec<&Item>, Vec<&Item>) = items.iter().partition(|item| item.camera_id == 0);
    (!train.is_empty()).then(|| {
        let names = |list: Vec<&Item>| list.into_iter().map(|item| item.name.clone()).collect();
        (names(train), names(val))
    })
}

/// The split's one training camera as input, the validation cameras as held out; none when the
/// training items span several cameras (Nerfies captures may train on two).
fn eval_split(items: &[Item], train: &BTreeSet<String>, val: &BTreeSet<String>) -> Option<EvalSplit> {
    let cameras = |names: &BTreeSet<String>| -> BTreeSet<u64> {
        items.iter().filter(|item| names.contains(&item.name)).map(|item| item.camera_id).collect()
    };
    let input = cameras(train);
    let &[input] = input.iter().collect::<Vec<_>>().as_slice() else { return None };
    let held_out = cameras(val).into_iter().filter(|c| c != input).map(|c| c.to_string()).collect();
    Some(EvalSplit { input: input.to_string(), held_out })
}

/// Every held-out frame films an instant the input camera films too.
fn check_held_out_times(dir: &Path, cameras: &[CameraView], split: &EvalSplit, items: &[Item]) -> Result<()> {
    let Some(input) = cameras.iter().find(|c| c.id == split.input) else { return Ok(()) };
    let input_times: BTreeSet<usize> = input.time_ids.iter().copied().collect();
    for camera in cameras.iter().filter(|c| split.held_out.contains(&c.id)) {
        if let Some(&time) = camera.time_ids.iter().find(|t| !input_times.contains(t)) {
            let name = items
                .iter()
                .find(|item| item.camera_id.to_string() == camera.id && item.time_id == time)
                .map_or_else(String::new, |item| item.name.clone());
            let reason = format!(
                "held-out camera {} films time {time}, which the input camera {} does not: the cameras are not \
                 synchronised",
                camera.id, split.input
            );
            return Err(Error::invalid(dir.join(METADATA_FILE), format!("{name}.warp_id"), reason));
        }
    }
    Ok(())
}

/// One camera's frames, depth, cameras and co-visibility masks.
fn read_camera_view(
    dir: &Path,
    scene_id: &str,
    camera_id: u64,
    items: &[&Item],
    info: &DycheckInfo,
    held_out: bool,
) -> Result<CameraView> {
    let factor = info.factor;
    let rgb_dir = dir.join("rgb").join(format!("{factor}x"));
    if !rgb_dir.is_dir() {
        let reason = format!(
            "no frames at factor {factor} (folder {} missing); choose a factor the scene has",
            rgb_dir.display()
        );
        return Err(Error::invalid(dir.join("rgb"), "factor", reason));
    }
    let cameras = items
        .par_iter()
        .map(|item| read_camera_file(&dir.join(CAMERA_DIR).join(format!("{}.json", item.name)), factor))
        .collect::<Result<Vec<_>>>()?;
    let paths: Vec<PathBuf> = items.iter().map(|item| rgb_dir.join(format!("{}.png", item.name))).collect();
    let frames = read_frames(&paths)?;
    for ((path, frame), camera) in paths.iter().zip(&frames).zip(&cameras) {
        if frame.dimensions() != (camera.width, camera.height) {
            let reason = format!(
                "frame is {}x{}, but the camera's image_size at factor {factor} is {}x{}",
                frame.width(),
                frame.height(),
                camera.width,
                camera.height
            );
            return Err(Error::invalid(path, "image_size", reason));
        }
    }
    let (width, height) = frames.first().map_or((0, 0), |f| (f.width() as usize, f.height() as usize));
    let depth = items
        .par_iter()
        .enumerate()
        .map(|(k, item)| read_depth(dir, &item.name, factor, k, width, height))
        .collect::<Result<Vec<_>>>()?;
    let has_depth = depth.iter().any(Option::is_some);
    if has_depth && let Some(k) = depth.iter().position(Option::is_none) {
        let path = dir.join("depth").join(format!("{factor}x")).join(format!("{}.npy", items[k].name));
        let reason = format!("missing (nor at 1x), while other frames of camera {camera_id} have depth");
        return Err(Error::invalid(path, "depth", reason));
    }
    let depth = depth
        .into_iter()
        .map(|d| d.unwrap_or_else(|| DepthMap { width, height, values: vec![0.0; width * height] }))
        .collect();
    let covisible_dir = dir.join("covisible").join(format!("{factor}x")).join("val");
    let covisible = if held_out && covisible_dir.is_dir() {
        let masks = items
            .par_iter()
            .map(|item| read_mask(&covisible_dir.join(format!("{}.png", item.name)), width, height))
            .collect::<Result<Vec<_>>>()?;
        Some(masks)
    } else {
        None
    };
    let time_ids: Vec<usize> = items.iter().map(|item| item.time_id).collect();
    let timestamps = info.fps.map(|fps| time_ids.iter().map(|&t| t as f64 / fps).collect());
    let sequence = Sequence {
        source_id: format!("{scene_id}_{camera_id}"),
        path: dir.to_owned(),
        fps: info.fps.unwrap_or(0.0),
        frames,
        depth,
        cameras,
        dynamic_masks: None,
        second_depth: None,
    };
    Ok(CameraView { id: camera_id.to_string(), sequence, timestamps, time_ids, has_depth, covisible })
}

/// A `camera/<item>.json` at resolution factor `factor`, in the toolkit's conventions.
pub fn read_camera_file(path: &Path, factor: u32) -> Result<PinholeCamera> {
    let json = JsonFile::read(path, "camera")?;
    let orientation =
        json_matrix(json.get("orientation")?, 3, 3).map_err(|e| Error::invalid(path, "orientation", e))?;
    let position = json.vector("position", 3)?;
    let focal_length = json.f64("focal_length")?;
    let principal_point = json.vector("principal_point", 2)?;
    let skew = json.f64("skew")?;
    let pixel_aspect_ratio = json.f64("pixel_aspect_ratio")?;
    let radial = numbers(path, "radial_distortion", json.get("radial_distortion")?, Some(3))?;
    // dycheck's `Camera.fromjson` maps the old key onto the new one.
    let tangential_key = if json.find("tangential_distortion").is_none() && json.find("tangential").is_some() {
        "tangential"
    } else {
        "tangential_distortion"
    };
    let tangential = numbers(path, tangential_key, json.get(tangential_key)?, Some(2))?;
    let image_size = json.get("image_size")?;
    let image_size = numbers(path, "image_size", image_size, Some(2))?;

    for (field, values, names) in
        [("radial_distortion", &radial, ["k1", "k2", "k3"].as_slice()), (tangential_key, &tangential, &["p1", "p2"])]
    {
        if let Some(i) = values.iter().position(|&v| v != 0.0) {
            let reason = format!(
                "{} = {} (a distorted camera): this reader does not undistort; undistort the frames first \
                 (dycheck's `use_undistort` writes undistorted frames and zero coefficients)",
                names[i], values[i]
            );
            return Err(Error::invalid(path, field, reason));
        }
    }
    if skew != 0.0 {
        let reason = format!("{skew}: cameras here have K = [fx 0 cx; 0 fy cy; 0 0 1], without skew");
        return Err(Error::invalid(path, "skew", reason));
    }
    // Both are finite (read as such): only the sign is left to check.
    if focal_length <= 0.0 {
        return Err(Error::invalid(path, "focal_length", format!("must be positive, found {focal_length}")));
    }
    if pixel_aspect_ratio <= 0.0 {
        let reason = format!("must be positive, found {pixel_aspect_ratio}");
        return Err(Error::invalid(path, "pixel_aspect_ratio", reason));
    }
    if let Some(v) = image_size.iter().find(|&&v| !(v >= 1.0 && v.fract() == 0.0)) {
        return Err(Error::invalid(path, "image_size", format!("expected positive integers (W, H), found {v}")));
    }
    let f = f64::from(factor);
    // dycheck's `rescale_image_domain`: sizes rounded as numpy rounds (half to even).
    let (width, height) = ((image_size[0] / f).round_ties_even(), (image_size[1] / f).round_ties_even());
    if width < 1.0 || height < 1.0 {
        let reason = format!("{}x{} is below one pixel at factor {factor}", image_size[0], image_size[1]);
        return Err(Error::invalid(path, "image_size", reason));
    }
    // Narrowed to u32 below: a size beyond any readable frame is refused, not saturated.
    if width > MAX_SIDE_PX as f64 || height > MAX_SIDE_PX as f64 {
        let reason = format!("{width}x{height} at factor {factor}: more than {MAX_SIDE_PX} px a side");
        return Err(Error::invalid(path, "image_size", reason));
    }
    let (fx, fy) = (focal_length / f, focal_length * pixel_aspect_ratio / f);
    let (cx, cy) = (principal_point[0] / f - PIXEL_CORNER_OFFSET, principal_point[1] / f - PIXEL_CORNER_OFFSET);
    let intrinsics = checked_intrinsics(path, "focal_length", &[fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0])?;
    // world_from_camera = [orientationᵀ | position].
    let mut row_major = [0.0; 16];
    for r in 0..3 {
        for c in 0..3 {
            row_major[r * 4 + c] = orientation[c * 3 + r];
        }
        row_major[r * 4 + 3] = position[r];
    }
    row_major[15] = 1.0;
    let world_from_camera = checked_pose(path, "orientation", &row_major)?;
    Ok(PinholeCamera { width: width as u32, height: height as u32, intrinsics, world_from_camera })
}

/// The depth of item `name` at factor `factor`: `depth/<f>x/` as it is, else `depth/1x/`
/// area-averaged; `None` if neither exists.
fn read_depth(
    dir: &Path,
    name: &str,
    factor: u32,
    frame: usize,
    width: usize,
    height: usize,
) -> Result<Option<DepthMap>> {
    let at = |f: u32| dir.join("depth").join(format!("{f}x")).join(format!("{name}.npy"));
    let (own, full) = (at(factor), at(1));
    if own.is_file() {
        let values = read_depth_npy(&own, frame, width, height)?;
        return Ok(Some(DepthMap { width, height, values }));
    }
    if !full.is_file() {
        return Ok(None);
    }
    let f = factor as usize;
    let values = read_depth_npy(&full, frame, width * f, height * f)?;
    Ok(Some(area_downsample(&values, width, height, f)))
}

/// A (H, W, 1) or (H, W) depth `.npy` of `width` × `height`, checked.
fn read_depth_npy(path: &Path, frame: usize, width: usize, height: usize) -> Result<Vec<f32>> {
    let header = crate::io::npy::read_npy_header(path)?;
    let shape = header.shape.as_slice();
    if shape != [height, width, 1] && shape != [height, width] {
        let reason = format!(
            "expected shape ({height}, {width}, 1) or ({height}, {width}) (the frame's size at this factor), found {shape:?}"
        );
        return Err(Error::invalid(path, "depth", reason));
    }
    let values = crate::io::npy::read_npy_f32(path)?.data;
    check_depth_sign(path, "depth", frame, &values)?;
    Ok(values)
}

/// `values` (`width·f` × `height·f`) averaged over f × f blocks, a block with any invalid value
/// (≤ 0 or not finite) invalid (0): dycheck's `_rescale_depth` (INTER_AREA of depth and of its
/// validity, kept where the validity stays 1).
fn area_downsample(values: &[f32], width: usize, height: usize, f: usize) -> DepthMap {
    let mut out = vec![0.0f32; width * height];
    for (i, value) in out.iter_mut().enumerate() {
        let (x, y) = (i % width, i / width);
        let mut sum = 0.0f64;
        let mut valid = true;
        for dy in 0..f {
            for dx in 0..f {
                let v = values[(y * f + dy) * width * f + x * f + dx];
                valid &= v.is_finite() && v > 0.0;
                sum += f64::from(v);
            }
        }
        if valid {
            *value = (sum / (f * f) as f64) as f32;
        }
    }
    DepthMap { width, height, values: out }
}

/// A co-visibility mask PNG (non-zero = co-visible) of the frame's size.
fn read_mask(path: &Path, width: usize, height: usize) -> Result<GrayImage> {
    let mask =
        image::open(path).map_err(|e| Error::invalid(path, "covisible", format!("unreadable image: {e}")))?.to_luma8();
    if mask.dimensions() != (width as u32, height as u32) {
        let reason = format!("mask is {}x{}, the frames {width}x{height}", mask.width(), mask.height());
        return Err(Error::invalid(path, "covisible", reason));
    }
    Ok(mask)
}

/// The CogNVS evaluation bundle's frame correspondence of a DyCheck scene
/// (`dycheck_<scene>_source_target_correspondence.txt`, read by the official
/// `eval/eval_metrics.py`, `load_correspondence`): one frame name per line, `<camera>_<frame>.png`
/// with camera `0` the source camera and any other a held-out camera, `<frame>` its frame index
/// (e.g. `0_00042.png`, `1_00042.png`). Blank lines are skipped, as the official reader skips them.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct FrameCorrespondence {
    /// Per line with a name, in file order: (camera, frame index).
    pub entries: Vec<(u32, usize)>,
}

/// The source camera's id in a [`FrameCorrespondence`].
pub const CORRESPONDENCE_SOURCE_CAMERA: u32 = 0;

impl FrameCorrespondence {
    /// The frame indices of `camera`, in file order (the official reader's `source_indices` for
    /// camera 0, its `target_indices` for a held-out camera).
    pub fn frames(&self, camera: u32) -> Vec<usize> {
        self.entries.iter().filter(|(c, _)| *c == camera).map(|&(_, f)| f).collect()
    }
}

/// The correspondence file name of `scene` in a CogNVS evaluation bundle's `dycheck/` folder.
pub fn correspondence_file_name(scene: &str) -> String {
    format!("dycheck_{scene}_source_target_correspondence.txt")
}

/// Reads a [`FrameCorrespondence`]. A line that is not `<camera>_<frame>.png` (decimal numbers,
/// the camera without leading zeros, since the official reader matches it as the text of the
/// camera number) is refused naming the file and the line.
pub fn read_correspondence(path: &Path) -> Result<FrameCorrespondence> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let mut entries = Vec::new();
    for (number, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        let field = format!("line {}", number + 1);
        let bad = |why: &str| Error::invalid(path, &field, format!("`{line}`: {why}; expected `<camera>_<frame>.png`"));
        let stem = line.strip_suffix(".png").ok_or_else(|| bad("not a .png frame name"))?;
        let (camera, frame) = stem.split_once('_').ok_or_else(|| bad("no `_` between camera and frame"))?;
        let decimal = |t: &str| !t.is_empty() && t.bytes().all(|b| b.is_ascii_digit());
        if !decimal(camera) || (camera.len() > 1 && camera.starts_with('0')) {
            return Err(bad("the camera is not a number without leading zeros"));
        }
        if !decimal(frame) {
            return Err(bad("the frame index is not a number"));
        }
        let camera: u32 = camera.parse().map_err(|_| bad("the camera number is too large"))?;
        let frame: usize = frame.parse().map_err(|_| bad("the frame index is too large"))?;
        entries.push((camera, frame));
    }
    Ok(FrameCorrespondence { entries })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn correspondence_lines_are_read_and_bad_ones_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(correspondence_file_name("apple"));
        std::fs::write(&path, "0_00000.png\n1_00003.png\n\n0_00001.png\n2_00010.png\n1_00004.png\n").unwrap();
        let read = read_correspondence(&path).unwrap();
        assert_eq!(read.frames(CORRESPONDENCE_SOURCE_CAMERA), [0, 1]);
        assert_eq!(read.frames(1), [3, 4]);
        assert_eq!(read.frames(2), [10]);
        for (bad, why) in [
            ("1_00003.jpg", "not a .png"),
            ("100003.png", "no `_`"),
            ("01_00003.png", "leading zeros"),
            ("1_x3.png", "frame index"),
        ] {
            std::fs::write(&path, format!("0_00000.png\n{bad}\n")).unwrap();
            let message = read_correspondence(&path).unwrap_err().to_string();
            assert!(message.contains("line 2") && message.contains(why) && message.contains("apple"), "{message}");
        }
    }

    #[test]
    fn area_downsampling_averages_blocks_and_drops_partly_invalid_ones() {
        // 4×2 at 1x → 2×1 at 2x: the first block is valid, the second has a hole.
        let values = [1.0, 2.0, 5.0, 0.0, 3.0, 4.0, 5.0, 5.0];
        let depth = area_downsample(&values, 2, 1, 2);
        assert_eq!(depth.values, vec![2.5, 0.0]);
    }

    #[test]
    fn camera_file_converts_corner_principal_point_and_orientation() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("0_00000.json");
        // A camera turned 90° about y, at (1, 2, 3).
        let json = serde_json::json!({
            "orientation": [[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]],
            "position": [1.0, 2.0, 3.0],
            "focal_length": 500.0,
            "principal_point": [360.0, 480.0],
            "skew": 0.0,
            "pixel_aspect_ratio": 1.5,
            "radial_distortion": [0.0, 0.0, 0.0],
            "tangential": [0.0, 0.0],
            "image_size": [720, 960],
        });
        std::fs::write(&path, json.to_string()).unwrap();
        let camera = read_camera_file(&path, 2).unwrap();
        assert_eq!((camera.width, camera.height), (360, 480));
        let k = camera.intrinsics;
        assert_eq!((k.x_axis.x, k.y_axis.y, k.z_axis.x, k.z_axis.y), (250.0, 375.0, 179.5, 239.5));
        // Camera z (forward) is the third row of the orientation, in world coordinates.
        assert_eq!(camera.world_from_camera.z_axis.truncate(), DVec3::new(1.0, 0.0, 0.0));
        assert_eq!(camera.center(), DVec3::new(1.0, 2.0, 3.0));
        // The world point straight ahead lands on the principal point.
        let (pixel, depth) = camera.project(DVec3::new(3.0, 2.0, 3.0)).unwrap();
        assert_eq!((pixel.x, pixel.y, depth), (179.5, 239.5, 2.0));
    }
}
