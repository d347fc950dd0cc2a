//! Kubric-4D scenes as GCD distributes them (basilevh/gcd `data-gen/export_kub_mv.py`, read by
//! `data-gen/convert_pcl_kubric.py`; Kubric's `kubric/file_io.py` and `kubric/core/cameras.py`):
//! a scene folder `scnXXXXX/` holding, per view v (16 in Kubric-4D),
//!
//! - `scnXXXXX_p0_v{v}.json`, Kubric's metadata: `scene.resolution` (W, H), `scene.num_frames`,
//!   `scene.frame_rate`; `camera.K` (3×3, **normalised** to the unit image, Kubric's signs
//!   `[[fx, 0, −cx], [0, −fy, −cy], [0, 0, −1]]`), `camera.focal_length` and
//!   `camera.sensor_width` (mm; checked against K), `camera.positions` (T, 3) and
//!   `camera.quaternions` (T, 4, order **w, x, y, z**): the camera-to-world pose of a Blender
//!   camera (x right, **y up, z backward**) in Kubric's Z-up world, in metres;
//! - `frames_p0_v{v}/rgba_{t:05}.png` (RGBA, alpha dropped), `depth_{t:05}.tiff` (float32, one
//!   sample: the **distance to the camera centre** along the pixel's ray, metres) and
//!   `segmentation_{t:05}.png` (palette indices: 0 the dome and floor, k the k-th instance).
//!
//! Converted at the door: world_from_camera = [R · diag(1, −1, −1) | position] (Blender camera
//! axes to OpenCV, the world kept Z-up in metres, as GCD does); K in pixels with
//! fx = |K₀₀|·W, fy = |K₁₁|·H and the principal point |K₀₂|·W − 0.5, |K₁₂|·H − 0.5 (Kubric's
//! normalised image puts pixel k's centre at (k + 0.5)/W); depth divided by
//! √(1 + ((u − cx)/fx)² + ((v − cy)/fy)²) to z-depth, the exact inverse of Kubric's
//! `process_depth`. Segmentation becomes the per-frame moving-object masks (Kubric-4D's
//! instances are its dynamic objects). Other per-frame files (`forward_flow_*`, `normal_*`,
//! `object_coordinates_*`, `data_ranges.json`) and the `.mp4` previews are not read.
//!
//! GCD's evaluation feeds view 4 (azimuth 15°, elevation 5°) as the input video and judges
//! renders of the merged 16-view point cloud from other viewpoints: the split is view 4 as
//! input, every other view held out.

use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4, DQuat, DVec3};
use image::GrayImage;
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::io::json_fields::{JsonFile, list, numbers};
use crate::io::multiview::{CameraView, EvalSplit, MultiViewScene};
use crate::io::npy::MAX_SIDE_PX;
use crate::io::sequence::Sequence;
use foundation::camera::{
    PinholeCamera, ROTATION_TOLERANCE, checked_intrinsics, checked_pose, json_matrix, mat4_to_row_major,
};
use foundation::depth::DepthMap;
use foundation::frames::read_frames;

/// The view GCD's Kubric-4D evaluation takes as input (`kubric_arbit.py`: the input camera's
/// `spherical_start` is view 4's pose).
pub const GCD_INPUT_VIEW: u32 = 4;

/// Kubric's focal length and sensor width agree with K to this relative error (float32 JSON).
const FOCAL_TOLERANCE: f64 = 1e-5;

/// The metadata file of view `view` of scene `scene_id`.
pub fn metadata_path(dir: &Path, scene_id: &str, view: u32) -> PathBuf {
    dir.join(format!("{scene_id}_p0_v{view}.json"))
}

/// The frames folder of view `view`.
pub fn frames_dir(dir: &Path, view: u32) -> PathBuf {
    dir.join(format!("frames_p0_v{view}"))
}

fn scene_id(dir: &Path) -> String {
    dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()
}

/// Whether `dir` is a Kubric-4D scene folder: view 0's metadata and frames folder.
pub fn is_kubric4d(dir: &Path) -> bool {
    metadata_path(dir, &scene_id(dir), 0).is_file() && frames_dir(dir, 0).is_dir()
}

/// The views of the scene: every `frames_p0_v{v}/` folder, sorted, each with its metadata file.
fn views(dir: &Path, scene_id: &str) -> Result<Vec<u32>> {
    let mut views = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))? {
        let name = entry.map_err(|e| Error::io(dir, e))?.file_name().to_string_lossy().into_owned();
        let view = name.strip_prefix("frames_p0_v").and_then(|v| v.parse::<u32>().ok());
        let view = view.or_else(|| {
            let rest = name.strip_prefix(&format!("{scene_id}_p0_v"))?.strip_suffix(".json")?;
            rest.parse::<u32>().ok()
        });
        if let Some(view) = view
            && !views.contains(&view)
        {
            views.push(view);
        }
    }
    views.sort_unstable();
    for &view in &views {
        let (metadata, frames) = (metadata_path(dir, scene_id, view), frames_dir(dir, view));
        if !metadata.is_file() {
            return Err(Error::invalid(metadata, "metadata", format!("missing, while {} exists", frames.display())));
        }
        if !frames.is_dir() {
            return Err(Error::invalid(frames, "frames", format!("missing, while {} exists", metadata.display())));
        }
    }
    if views.len() < 2 {
        let reason = "a Kubric-4D scene needs two or more views (frames_p0_v{v}/ with scnXXXXX_p0_v{v}.json)";
        return Err(Error::invalid(dir, "views", reason));
    }
    Ok(views)
}

/// Reads the Kubric-4D scene folder `dir`.
pub fn read_kubric4d(dir: &Path) -> Result<MultiViewScene> {
    let scene_id = scene_id(dir);
    let views = views(dir, &scene_id)?;
    let folders: Vec<PathBuf> = views.iter().map(|&view| frames_dir(dir, view)).collect();
    crate::io::multiview::check_distinct_folders(dir, "views", &folders)?;
    let cameras = views.iter().map(|&view| read_view(dir, &scene_id, view)).collect::<Result<Vec<_>>>()?;
    let first = &cameras[0];
    for camera in &cameras[1..] {
        let path = metadata_path(dir, &scene_id, camera.id.parse().unwrap_or_default());
        if camera.sequence.len() != first.sequence.len() {
            let reason = format!(
                "{} frames, while view {} has {}: synchronised views film the same instants",
                camera.sequence.len(),
                first.id,
                first.sequence.len()
            );
            return Err(Error::invalid(path, "scene.num_frames", reason));
        }
        if camera.sequence.fps != first.sequence.fps {
            let reason = format!(
                "{} fps, while view {} has {}: synchronised views film the same instants",
                camera.sequence.fps, first.id, first.sequence.fps
            );
            return Err(Error::invalid(path, "scene.frame_rate", reason));
        }
    }
    let input = GCD_INPUT_VIEW.to_string();
    let split = cameras.iter().any(|c| c.id == input).then(|| EvalSplit {
        held_out: cameras.iter().filter(|c| c.id != input).map(|c| c.id.clone()).collect(),
        input,
    });
    Ok(MultiViewScene { scene_id, path: dir.to_owned(), cameras, split })
}

/// One view: its metadata, frames, depth and segmentation.
fn read_view(dir: &Path, scene_id: &str, view: u32) -> Result<CameraView> {
    let path = metadata_path(dir, scene_id, view);
    let metadata = JsonFile::read(&path, "metadata")?;
    let resolution = metadata.vector("scene.resolution", 2)?;
    if let Some(v) = resolution.iter().find(|&&v| !(v >= 1.0 && v.fract() == 0.0 && v <= MAX_SIDE_PX as f64)) {
        let reason = format!("expected pixel counts (W, H) of 1 to {MAX_SIDE_PX}, found {v}");
        return Err(Error::invalid(&path, "scene.resolution", reason));
    }
    let (width, height) = (resolution[0] as u32, resolution[1] as u32);
    let frames = metadata.u64("scene.num_frames")? as usize;
    if frames == 0 {
        return Err(Error::invalid(&path, "scene.num_frames", "no frames"));
    }
    let fps = metadata.f64("scene.frame_rate")?;
    if fps <= 0.0 {
        return Err(Error::invalid(&path, "scene.frame_rate", format!("must be positive, found {fps}")));
    }
    let intrinsics = read_intrinsics(&metadata, width, height)?;
    let poses = read_poses(&metadata, frames)?;
    let cameras: Vec<PinholeCamera> = poses
        .into_iter()
        .map(|world_from_camera| PinholeCamera { width, height, intrinsics, world_from_camera })
        .collect();

    let folder = frames_dir(dir, view);
    let file = |kind: &str, ext: &str, t: usize| folder.join(format!("{kind}_{t:05}.{ext}"));
    let rgba: Vec<PathBuf> = (0..frames).map(|t| file("rgba", "png", t)).collect();
    let images = read_frames(&rgba)?;
    if let Some(first) = images.first()
        && first.dimensions() != (width, height)
    {
        let reason =
            format!("{}x{} in the metadata, {}x{} in the frames", width, height, first.width(), first.height());
        return Err(Error::invalid(&rgba[0], "scene.resolution", reason));
    }
    let camera = cameras[0];
    let depth = (0..frames)
        .into_par_iter()
        .map(|t| {
            let ray_length = read_depth_tiff(&file("depth", "tiff", t), width as usize, height as usize)?;
            Ok(z_depth_from_ray_length(&ray_length, &camera))
        })
        .collect::<Result<Vec<_>>>()?;
    let segmentation: Vec<PathBuf> = (0..frames).map(|t| file("segmentation", "png", t)).collect();
    let dynamic_masks = if segmentation.iter().any(|p| p.is_file()) {
        let masks = segmentation
            .par_iter()
            .map(|p| {
                let mask = crate::io::annotations::read_id_png(p)?;
                if mask.dimensions() != (width, height) {
                    let reason = format!("{}x{}, the frames {width}x{height}", mask.width(), mask.height());
                    return Err(Error::invalid(p, "segmentation", reason));
                }
                Ok(mask)
            })
            .collect::<Result<Vec<GrayImage>>>()?;
        Some(masks)
    } else {
        None
    };
    let sequence = Sequence {
        source_id: format!("{scene_id}_v{view}"),
        path: folder,
        fps,
        frames: images,
        depth,
        cameras,
        dynamic_masks,
        second_depth: None,
    };
    let timestamps = Some((0..frames).map(|t| t as f64 / fps).collect());
    Ok(CameraView {
        id: view.to_string(),
        sequence,
        timestamps,
        time_ids: (0..frames).collect(),
        has_depth: true,
        covisible: None,
    })
}

/// `camera.K` in pixels with centres at integers, checked against `camera.focal_length` /
/// `camera.sensor_width` where the metadata has them.
fn read_intrinsics(metadata: &JsonFile, width: u32, height: u32) -> Result<DMat3> {
    let path = &metadata.path;
    let k = json_matrix(metadata.get("camera.K")?, 3, 3).map_err(|e| Error::invalid(path, "camera.K", e))?;
    let (w, h) = (f64::from(width), f64::from(height));
    // Kubric's signs (−fy, −cx, −cy, −1) undone as GCD does, by absolute values.
    let pixels = [
        k[0].abs() * w,
        k[1] * w,
        k[2].abs() * w - 0.5,
        k[3] * h,
        k[4].abs() * h,
        k[5].abs() * h - 0.5,
        k[6],
        k[7],
        k[8].abs(),
    ];
    let intrinsics = checked_intrinsics(path, "camera.K", &pixels)?;
    if let (Some(_), Some(_)) = (metadata.find("camera.focal_length"), metadata.find("camera.sensor_width")) {
        let (focal, sensor) = (metadata.f64("camera.focal_length")?, metadata.f64("camera.sensor_width")?);
        let normalised = focal / sensor;
        if !normalised.is_finite() || (normalised - k[0].abs()).abs() > FOCAL_TOLERANCE * normalised {
            let reason = format!(
                "{focal} mm on a {sensor} mm sensor is {normalised} of the image width, but camera.K[0][0] is {}",
                k[0]
            );
            return Err(Error::invalid(path, "camera.focal_length", reason));
        }
    }
    Ok(intrinsics)
}

/// `camera.positions` and `camera.quaternions` (w, x, y, z) as OpenCV world_from_camera poses.
fn read_poses(metadata: &JsonFile, frames: usize) -> Result<Vec<glam::DMat4>> {
    let path = &metadata.path;
    let positions = list(path, "camera.positions", metadata.get("camera.positions")?)?;
    let quaternions = list(path, "camera.quaternions", metadata.get("camera.quaternions")?)?;
    for (field, len) in [("camera.positions", positions.len()), ("camera.quaternions", quaternions.len())] {
        if len != frames {
            return Err(Error::invalid(path, field, format!("{len} entries for {frames} frames (scene.num_frames)")));
        }
    }
    let mut poses = Vec::with_capacity(frames);
    for t in 0..frames {
        let position = numbers(path, &format!("camera.positions[{t}]"), &positions[t], Some(3))?;
        let label = format!("camera.quaternions[{t}]");
        let q = numbers(path, &label, &quaternions[t], Some(4))?;
        let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        if (norm - 1.0).abs() > ROTATION_TOLERANCE {
            let reason = format!("norm {norm}: not a unit quaternion (w, x, y, z), so not a rotation");
            return Err(Error::invalid(path, label, reason));
        }
        let blender = DMat3::from_quat(DQuat::from_xyzw(q[1], q[2], q[3], q[0]));
        // Blender camera axes (x right, y up, z backward) to OpenCV's (x right, y down, z forward).
        let rotation = DMat3::from_cols(blender.x_axis, -blender.y_axis, -blender.z_axis);
        let row_major = mat4_to_row_major(&DMat4::from_mat3_translation(
            rotation,
            DVec3::new(position[0], position[1], position[2]),
        ));
        poses.push(checked_pose(path, &label, &row_major)?);
    }
    Ok(poses)
}

/// Reads a one-sample float TIFF (Kubric's depth) of `width` × `height`.
pub fn read_depth_tiff(path: &Path, width: usize, height: usize) -> Result<Vec<f32>> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let bad = |reason: String| Error::invalid(path, "depth", reason);
    let mut decoder =
        tiff::decoder::Decoder::new(std::io::BufReader::new(file)).map_err(|e| bad(format!("unreadable TIFF: {e}")))?;
    let (w, h) = decoder.dimensions().map_err(|e| bad(format!("unreadable TIFF: {e}")))?;
    if (w as usize, h as usize) != (width, height) {
        return Err(bad(format!("{w}x{h}, the frames {width}x{height}")));
    }
    let colour = decoder.colortype().map_err(|e| bad(format!("unreadable TIFF: {e}")))?;
    if !matches!(colour, tiff::ColorType::Gray(_)) {
        return Err(bad(format!("expected one sample per pixel (a depth map), found {colour:?}")));
    }
    let values = match decoder.read_image().map_err(|e| bad(format!("unreadable TIFF: {e}")))? {
        tiff::decoder::DecodingResult::F32(values) => values,
        tiff::decoder::DecodingResult::F64(values) => values.into_iter().map(|v| v as f32).collect(),
        tiff::decoder::DecodingResult::F16(values) => values.into_iter().map(f32::from).collect(),
        _ => return Err(bad(format!("expected float samples (metres), found integer {colour:?}"))),
    };
    if values.len() != width * height {
        return Err(bad(format!("{} values for {width}x{height} pixels", values.len())));
    }
    Ok(values)
}

/// Kubric's ray length (distance to the camera centre) to z-depth along the optical axis; values
/// that are not finite and positive become 0 (invalid).
pub fn z_depth_from_ray_length(ray_length: &[f32], camera: &PinholeCamera) -> DepthMap {
    let (width, height) = (camera.width as usize, camera.height as usize);
    let k = camera.intrinsics;
    let (fx, fy, cx, cy) = (k.x_axis.x, k.y_axis.y, k.z_axis.x, k.z_axis.y);
    let values = ray_length
        .iter()
        .enumerate()
        .map(|(i, &d)| {
            if !(d.is_finite() && d > 0.0) {
                return 0.0;
            }
            let ray = DVec3::new(((i % width) as f64 - cx) / fx, ((i / width) as f64 - cy) / fy, 1.0);
            (f64::from(d) / ray.length()) as f32
        })
        .collect();
    DepthMap { width, height, values }
}
