//! COLMAP workspaces (colmap/colmap: `src/colmap/scene/reconstruction_io.cc` for the sparse model,
//! `src/colmap/mvs/mat.h` for dense depth maps, and the formats page of its documentation): a
//! folder with
//!
//! - `images/`: the frames, in the order of their file names;
//! - a sparse model in `sparse/0/` or `sparse/` (the undistorted workspace's), binary
//!   (`cameras.bin`, `images.bin`; read when both forms exist) or text (`cameras.txt`,
//!   `images.txt`). Each registered image stores `qvec` (w, x, y, z) and `tvec` of its
//!   **camera_from_world** (OpenCV axes), checked and inverted here. Camera models: `PINHOLE`
//!   and `SIMPLE_PINHOLE` are read; `SIMPLE_RADIAL`, `RADIAL` and `OPENCV` only when their
//!   distortion is exactly zero; every other model, and non-zero distortion, is refused by name
//!   (undistort with `colmap image_undistorter`, whose output is `PINHOLE`). COLMAP puts pixel
//!   centres at +0.5 (the top-left pixel's centre is (0.5, 0.5)), so cx and cy are moved by
//!   −0.5 to the project's integer centres.
//! - `stereo/depth_maps/NAME.geometric.bin` (else `NAME.photometric.bin`) per image, from its MVS
//!   (`patch_match_stereo`): an ASCII header `width&height&channels&` then float32 values, x
//!   fastest then y (then channel): z-depth in the model's units; 0 = no depth.
//!
//! Every file in `images/` must be a registered image of the model and every registered image a
//! file: anything else is an error listing the first names that differ. `points3D` is not read
//! (the dense maps carry the depth).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::{DMat4, DQuat, DVec3};
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::io::npy::MAX_SIDE_PX;
use crate::io::tool_output::{ToolFrames, ToolOutput, check_depth_sign, invert_camera_from_world};
use foundation::camera::mat4_to_row_major;
use foundation::paths::check_name;

/// How far a stored quaternion's norm may be from 1: COLMAP writes unit quaternions in full
/// double precision, and a text model rounds them to 17 significant digits.
const QUATERNION_NORM_TOLERANCE: f64 = 1e-6;

/// Names listed in a mismatch error before "...".
const LISTED_NAMES: usize = 5;

/// Bytes of one 2D point in `images.bin`: x, y (f64) and its 3D point id (i64).
const POINT2D_BYTES: u64 = 24;

/// Image file extensions read from `images/`.
const IMAGE_EXTENSIONS: [&str; 3] = ["png", "jpg", "jpeg"];

/// COLMAP's camera models by id (`CAMERA_MODEL_CASES` in `src/colmap/sensor/models.h`), with
/// their parameter counts.
const CAMERA_MODELS: [(&str, usize); 11] = [
    ("SIMPLE_PINHOLE", 3),
    ("PINHOLE", 4),
    ("SIMPLE_RADIAL", 4),
    ("RADIAL", 5),
    ("OPENCV", 8),
    ("OPENCV_FISHEYE", 8),
    ("FULL_OPENCV", 12),
    ("FOV", 5),
    ("SIMPLE_RADIAL_FISHEYE", 4),
    ("RADIAL_FISHEYE", 5),
    ("THIN_PRISM_FISHEYE", 12),
];

/// One camera of the model.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapCamera {
    /// Model name (`PINHOLE`, ...).
    pub model: String,
    /// Image width and height, checked within 1..=[`MAX_SIDE_PX`] when read.
    pub width: u32,
    /// See `width`.
    pub height: u32,
    /// The model's parameters in COLMAP's order.
    pub params: Vec<f64>,
}

/// One registered image of the model.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapImage {
    /// Its camera's id.
    pub camera_id: i64,
    /// Rotation of camera_from_world as (w, x, y, z).
    pub qvec: [f64; 4],
    /// Translation of camera_from_world.
    pub tvec: [f64; 3],
}

/// A sparse model: cameras by id, images by name.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ColmapModel {
    /// Cameras by id.
    pub cameras: BTreeMap<i64, ColmapCamera>,
    /// Registered images by name.
    pub images: BTreeMap<String, ColmapImage>,
}

/// The folder of the sparse model under `dir` (`sparse/0/` or `sparse/`), if any.
pub fn sparse_model_dir(dir: &Path) -> Option<PathBuf> {
    [dir.join("sparse").join("0"), dir.join("sparse")]
        .into_iter()
        .find(|d| ["cameras.bin", "cameras.txt"].iter().any(|f| d.join(f).is_file()))
}

/// Reads the sparse model in `model_dir`: binary if `cameras.bin` is there, else text.
pub fn read_model(model_dir: &Path) -> Result<ColmapModel> {
    if model_dir.join("cameras.bin").is_file() {
        let cameras = parse_cameras_bin(&model_dir.join("cameras.bin"))?;
        let images = parse_images_bin(&model_dir.join("images.bin"))?;
        Ok(ColmapModel { cameras, images })
    } else {
        let cameras = parse_cameras_txt(&model_dir.join("cameras.txt"))?;
        let images = parse_images_txt(&model_dir.join("images.txt"))?;
        Ok(ColmapModel { cameras, images })
    }
}

/// Reads the COLMAP workspace `dir`: frames from `images/`, cameras from the sparse model, depth
/// from the dense maps.
pub fn read_colmap(dir: &Path) -> Result<ToolOutput> {
    let mut output = read_colmap_reconstruction(dir)?;
    let images_dir = dir.join("images");
    let names = image_names(&images_dir)?;
    let frames = decode_frames(&images_dir, &names)?;
    output.frames = Some(ToolFrames { fps: 0.0, frames, path: images_dir });
    Ok(output)
}

/// The reconstruction of the workspace `dir` (no frames decoded).
pub fn read_colmap_reconstruction(dir: &Path) -> Result<ToolOutput> {
    let model_dir = sparse_model_dir(dir).ok_or_else(|| {
        Error::invalid(dir, "sparse", "no sparse model: expected sparse/0/ or sparse/ with cameras.bin or cameras.txt")
    })?;
    let model = read_model(&model_dir)?;
    let images_dir = dir.join("images");
    let names = image_names(&images_dir)?;
    check_names_match(&model_dir, &images_dir, &names, &model)?;

    let mut intrinsics = Vec::with_capacity(names.len());
    let mut world_from_camera = Vec::with_capacity(names.len());
    let mut size = None;
    let images_file = model_dir.join(if model_dir.join("cameras.bin").is_file() { "images.bin" } else { "images.txt" });
    let cameras_file =
        model_dir.join(if model_dir.join("cameras.bin").is_file() { "cameras.bin" } else { "cameras.txt" });
    for name in &names {
        let image = &model.images[name];
        let camera = model.cameras.get(&image.camera_id).ok_or_else(|| {
            Error::invalid(
                &images_file,
                format!("{name}: camera_id"),
                format!("camera {} is not in the model", image.camera_id),
            )
        })?;
        let field = format!("camera {}", image.camera_id);
        intrinsics.push(pinhole_k(&cameras_file, &field, camera)?);
        let camera_size = (camera.width, camera.height);
        if *size.get_or_insert(camera_size) != camera_size {
            return Err(Error::invalid(
                &cameras_file,
                field,
                format!(
                    "size {}x{} differs from the first image's camera: every frame must have one size",
                    camera.width, camera.height
                ),
            ));
        }
        world_from_camera.push(pose_of(&images_file, name, image)?);
    }
    let (width, height) = size.ok_or_else(|| Error::invalid(&images_dir, "images", "no images"))?;
    let depth_dir = dir.join("stereo").join("depth_maps");
    let maps = names
        .par_iter()
        .map(|name| {
            let path = ["geometric", "photometric"]
                .iter()
                .map(|kind| depth_dir.join(format!("{name}.{kind}.bin")))
                .find(|p| p.is_file())
                .ok_or_else(|| {
                    Error::invalid(
                        &depth_dir,
                        name.as_str(),
                        "no dense depth map NAME.geometric.bin or NAME.photometric.bin (run COLMAP's patch_match_stereo)",
                    )
                })?;
            read_depth_map(&path).map(|map| (path, map))
        })
        .collect::<Result<Vec<_>>>()?;
    let (first_path, (depth_w, depth_h, _)) = &maps[0];
    let depth_size = (*depth_w, *depth_h);
    let mut depth = Vec::with_capacity(maps.len());
    for (i, (path, (w, h, values))) in maps.iter().enumerate() {
        if (*w, *h) != depth_size {
            return Err(Error::invalid(
                path,
                "depth",
                format!("{w}x{h} differs from {}'s {depth_w}x{depth_h}", first_path.display()),
            ));
        }
        check_depth_sign(path, "depth", i, values)?;
        depth.push(values.clone());
    }
    Ok(ToolOutput {
        frames: None,
        depth_path: depth_dir,
        depth_size,
        depth,
        intrinsics_path: cameras_file,
        intrinsics_size: (width, height),
        intrinsics,
        poses_path: images_file,
        world_from_camera,
    })
}

fn image_names(images_dir: &Path) -> Result<Vec<String>> {
    let entries = std::fs::read_dir(images_dir).map_err(|e| Error::io(images_dir, e))?;
    let mut names: Vec<String> = entries
        .filter_map(|e| e.ok())
        .filter_map(|e| e.file_name().to_str().map(str::to_owned))
        .filter(|n| {
            Path::new(n)
                .extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| IMAGE_EXTENSIONS.iter().any(|x| e.eq_ignore_ascii_case(x)))
        })
        .collect();
    names.sort();
    Ok(names)
}

fn decode_frames(images_dir: &Path, names: &[String]) -> Result<Vec<image::RgbImage>> {
    let frames = names
        .par_iter()
        .map(|name| {
            let path = images_dir.join(name);
            image::open(&path)
                .map(|i| i.to_rgb8())
                .map_err(|e| Error::invalid(&path, "frame", format!("unreadable image: {e}")))
        })
        .collect::<Result<Vec<_>>>()?;
    if let Some(first) = frames.first()
        && let Some(i) = frames.iter().position(|f| f.dimensions() != first.dimensions())
    {
        return Err(Error::invalid(
            images_dir.join(&names[i]),
            "frame",
            format!("size {:?} differs from {}'s {:?}", frames[i].dimensions(), names[0], first.dimensions()),
        ));
    }
    Ok(frames)
}

/// The frames in `images/` and the model's registered images must be the same set of names.
fn check_names_match(model_dir: &Path, images_dir: &Path, names: &[String], model: &ColmapModel) -> Result<()> {
    let list = |missing: Vec<&String>| {
        let shown: Vec<&str> = missing.iter().take(LISTED_NAMES).map(|s| s.as_str()).collect();
        let more = missing.len().saturating_sub(LISTED_NAMES);
        format!("{}{}", shown.join(", "), if more > 0 { format!(" and {more} more") } else { String::new() })
    };
    let unregistered: Vec<&String> = names.iter().filter(|n| !model.images.contains_key(*n)).collect();
    if !unregistered.is_empty() {
        return Err(Error::invalid(
            model_dir,
            "images",
            format!(
                "{} frame(s) of {} are not registered images of the model: {} (a model of other frames, or images COLMAP could not register)",
                unregistered.len(),
                images_dir.display(),
                list(unregistered)
            ),
        ));
    }
    let on_disk: std::collections::BTreeSet<&String> = names.iter().collect();
    let absent: Vec<&String> = model.images.keys().filter(|n| !on_disk.contains(n)).collect();
    if !absent.is_empty() {
        return Err(Error::invalid(
            model_dir,
            "images",
            format!("{} registered image(s) have no file in {}: {}", absent.len(), images_dir.display(), list(absent)),
        ));
    }
    Ok(())
}

/// K (row-major, integer pixel centres) of a camera whose model is a pinhole or has zero
/// distortion; anything else is refused naming the model.
fn pinhole_k(path: &Path, field: &str, camera: &ColmapCamera) -> Result<[f64; 9]> {
    let p = &camera.params;
    let (fx, fy, cx, cy, distortion): (f64, f64, f64, f64, &[f64]) = match camera.model.as_str() {
        "SIMPLE_PINHOLE" => (p[0], p[0], p[1], p[2], &[]),
        "PINHOLE" => (p[0], p[1], p[2], p[3], &[]),
        "SIMPLE_RADIAL" | "RADIAL" => (p[0], p[0], p[1], p[2], &p[3..]),
        "OPENCV" => (p[0], p[1], p[2], p[3], &p[4..]),
        other => {
            return Err(Error::invalid(
                path,
                field,
                format!(
                    "camera model {other} is not read: undistort with `colmap image_undistorter` (its output is PINHOLE) and read the undistorted workspace"
                ),
            ));
        }
    };
    if distortion.iter().any(|&d| d != 0.0) {
        return Err(Error::invalid(
            path,
            field,
            format!(
                "camera model {} has distortion {distortion:?}: undistort with `colmap image_undistorter` (its output is PINHOLE) and read the undistorted workspace",
                camera.model
            ),
        ));
    }
    // COLMAP's pixel centres are at +0.5, ours at integers.
    Ok([fx, 0.0, cx - 0.5, 0.0, fy, cy - 0.5, 0.0, 0.0, 1.0])
}

/// `world_from_camera` of a registered image, from its `qvec` and `tvec`.
fn pose_of(path: &Path, name: &str, image: &ColmapImage) -> Result<[f64; 16]> {
    let [w, x, y, z] = image.qvec;
    let norm = (w * w + x * x + y * y + z * z).sqrt();
    if !norm.is_finite() || (norm - 1.0).abs() > QUATERNION_NORM_TOLERANCE {
        return Err(Error::invalid(
            path,
            format!("{name}: qvec"),
            format!(
                "{:?} is not a unit quaternion (norm {norm}): COLMAP stores (w, x, y, z) of camera_from_world",
                image.qvec
            ),
        ));
    }
    if let Some(t) = image.tvec.iter().find(|t| !t.is_finite()) {
        return Err(Error::invalid(path, format!("{name}: tvec"), format!("non-finite value {t}")));
    }
    let rotation = DQuat::from_xyzw(x, y, z, w);
    let camera_from_world = DMat4::from_rotation_translation(rotation, DVec3::from_array(image.tvec));
    invert_camera_from_world(path, &format!("{name}: qvec/tvec"), &mat4_to_row_major(&camera_from_world))
}

/// A dense depth map: width, height and the values (row-major), refusing more than one channel.
pub fn read_depth_map(path: &Path) -> Result<(usize, usize, Vec<f32>)> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let mut fields = Vec::with_capacity(3);
    let mut start = 0;
    for (i, &b) in bytes.iter().enumerate().take(64) {
        if b == b'&' {
            fields.push(&bytes[start..i]);
            start = i + 1;
            if fields.len() == 3 {
                break;
            }
        }
    }
    let header_error = || {
        Error::invalid(path, "header", "expected an ASCII header `width&height&channels&` (COLMAP's dense map format)")
    };
    if fields.len() != 3 {
        return Err(header_error());
    }
    let numbers = fields
        .iter()
        .map(|f| std::str::from_utf8(f).ok().and_then(|s| s.trim().parse::<usize>().ok()))
        .collect::<Option<Vec<usize>>>()
        .ok_or_else(header_error)?;
    let (width, height, channels) = (numbers[0], numbers[1], numbers[2]);
    if width == 0 || height == 0 || width > MAX_SIDE_PX || height > MAX_SIDE_PX {
        return Err(Error::invalid(path, "header", format!("size {width}x{height} outside 1–{MAX_SIDE_PX} px")));
    }
    if channels != 1 {
        return Err(Error::invalid(
            path,
            "header",
            format!("{channels} channels: a depth map has 1 (a normal map has 3)"),
        ));
    }
    let data = &bytes[start..];
    let expected = width * height * std::mem::size_of::<f32>();
    if data.len() != expected {
        return Err(Error::invalid(
            path,
            "data",
            format!("{} bytes after the header, expected {expected} for {width}x{height} float32 values", data.len()),
        ));
    }
    let values = data.chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().expect("4 bytes"))).collect();
    Ok((width, height, values))
}

/// A bounded little-endian reader over a binary model file.
struct Cursor<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Cursor<'a> {
    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8]> {
        if self.bytes.len() - self.at < n {
            return Err(Error::invalid(self.path, what, format!("file ends at byte {} (truncated)", self.bytes.len())));
        }
        let out = &self.bytes[self.at..self.at + n];
        self.at += n;
        Ok(out)
    }
    fn u64(&mut self, what: &str) -> Result<u64> {
        Ok(u64::from_le_bytes(self.take(8, what)?.try_into().expect("8")))
    }
    fn i32(&mut self, what: &str) -> Result<i32> {
        Ok(i32::from_le_bytes(self.take(4, what)?.try_into().expect("4")))
    }
    fn f64(&mut self, what: &str) -> Result<f64> {
        Ok(f64::from_le_bytes(self.take(8, what)?.try_into().expect("8")))
    }
    fn remaining(&self) -> u64 {
        (self.bytes.len() - self.at) as u64
    }
    /// A count of records of at least `min_bytes` each, refused when the rest of the file
    /// cannot hold them (before anything is allocated for them).
    fn count(&mut self, what: &str, min_bytes: u64) -> Result<u64> {
        let n = self.u64(what)?;
        if n.saturating_mul(min_bytes) > self.remaining() {
            return Err(Error::invalid(
                self.path,
                what,
                format!("declares {n} records, more than the {} bytes left can hold", self.remaining()),
            ));
        }
        Ok(n)
    }
}

fn model_name(path: &Path, field: &str, id: i32) -> Result<(&'static str, usize)> {
    usize::try_from(id)
        .ok()
        .and_then(|i| CAMERA_MODELS.get(i).copied())
        .ok_or_else(|| Error::invalid(path, field, format!("unknown camera model id {id}")))
}

fn parse_cameras_bin(path: &Path) -> Result<BTreeMap<i64, ColmapCamera>> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let mut cursor = Cursor { path, bytes: &bytes, at: 0 };
    // camera_id, model_id (i32 each), width, height (u64 each), at least 3 parameters.
    let n = cursor.count("num_cameras", 4 + 4 + 8 + 8 + 3 * 8)?;
    let mut cameras = BTreeMap::new();
    for i in 0..n {
        let field = format!("camera[{i}]");
        let id = cursor.i32(&field)?;
        let (model, count) = model_name(path, &field, cursor.i32(&field)?)?;
        let (width, height) = image_size(path, &field, cursor.u64(&field)?, cursor.u64(&field)?)?;
        let params = (0..count).map(|_| cursor.f64(&field)).collect::<Result<Vec<_>>>()?;
        cameras.insert(i64::from(id), ColmapCamera { model: model.to_owned(), width, height, params });
    }
    Ok(cameras)
}

fn parse_images_bin(path: &Path) -> Result<BTreeMap<String, ColmapImage>> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let mut cursor = Cursor { path, bytes: &bytes, at: 0 };
    // image_id, qvec, tvec, camera_id, a name of at least its terminating NUL, num_points2D.
    let n = cursor.count("num_reg_images", 4 + 7 * 8 + 4 + 1 + 8)?;
    let mut images = BTreeMap::new();
    for i in 0..n {
        let field = format!("image[{i}]");
        let _image_id = cursor.i32(&field)?;
        let mut q = [0.0; 4];
        for v in &mut q {
            *v = cursor.f64(&field)?;
        }
        let mut t = [0.0; 3];
        for v in &mut t {
            *v = cursor.f64(&field)?;
        }
        let camera_id = cursor.i32(&field)?;
        let rest = &cursor.bytes[cursor.at..];
        let end = rest
            .iter()
            .position(|&b| b == 0)
            .ok_or_else(|| Error::invalid(path, field.as_str(), "name is not NUL-terminated (truncated)"))?;
        let name = String::from_utf8(rest[..end].to_vec())
            .map_err(|_| Error::invalid(path, field.as_str(), "name is not UTF-8"))?;
        check_name(&name).map_err(|reason| Error::invalid(path, field.as_str(), reason))?;
        cursor.at += end + 1;
        let points = cursor.count(&format!("{field} ({name}): num_points2D"), POINT2D_BYTES)?;
        cursor.take((points * POINT2D_BYTES) as usize, &field)?;
        if images.insert(name.clone(), ColmapImage { camera_id: i64::from(camera_id), qvec: q, tvec: t }).is_some() {
            return Err(Error::invalid(path, field, format!("image name {name} registered twice")));
        }
    }
    Ok(images)
}

/// The data lines of a COLMAP text file (comments dropped), with their 1-based line numbers.
fn data_lines(path: &Path) -> Result<Vec<(usize, String)>> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    Ok(text.lines().enumerate().filter(|(_, l)| !l.starts_with('#')).map(|(i, l)| (i + 1, l.to_owned())).collect())
}

fn numbers(path: &Path, line: usize, fields: &[&str]) -> Result<Vec<f64>> {
    fields
        .iter()
        .map(|f| {
            f.parse::<f64>().map_err(|_| Error::invalid(path, format!("line {line}"), format!("`{f}` is not a number")))
        })
        .collect()
}

/// An integer field of a text model (an id or a size): a number with a fraction or beyond
/// `i64` is refused, not truncated.
fn integer<T: std::str::FromStr>(path: &Path, line: usize, field: &str) -> Result<T> {
    field
        .parse::<T>()
        .map_err(|_| Error::invalid(path, format!("line {line}"), format!("`{field}` is not an integer in range")))
}

/// A camera's `width` and `height` as read, refused outside 1..=[`MAX_SIDE_PX`] (a size that
/// wraps when narrowed would silently give another image size).
fn image_size<T: TryInto<u32> + Copy + std::fmt::Display>(
    path: &Path,
    field: &str,
    width: T,
    height: T,
) -> Result<(u32, u32)> {
    let side = |n: T| n.try_into().ok().filter(|&n| n >= 1 && n as usize <= MAX_SIDE_PX);
    match (side(width), side(height)) {
        (Some(w), Some(h)) => Ok((w, h)),
        _ => Err(Error::invalid(path, field, format!("size {width}x{height} outside 1–{MAX_SIDE_PX} px"))),
    }
}

fn parse_cameras_txt(path: &Path) -> Result<BTreeMap<i64, ColmapCamera>> {
    let mut cameras = BTreeMap::new();
    for (line, text) in data_lines(path)? {
        let fields: Vec<&str> = text.split_whitespace().collect();
        if fields.is_empty() {
            continue;
        }
        let field = format!("line {line}");
        if fields.len() < 4 {
            return Err(Error::invalid(path, field, "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]"));
        }
        let (model, count) = CAMERA_MODELS
            .iter()
            .copied()
            .find(|(name, _)| *name == fields[1])
            .ok_or_else(|| Error::invalid(path, field.as_str(), format!("unknown camera model {}", fields[1])))?;
        let values = numbers(path, line, &fields[4..])?;
        if values.len() != count {
            return Err(Error::invalid(path, field, format!("{model} has {count} parameters, found {}", values.len())));
        }
        let [id, width, height] = [fields[0], fields[2], fields[3]].map(|f| integer(path, line, f));
        let (width, height) = image_size(path, &field, width?, height?)?;
        cameras.insert(id?, ColmapCamera { model: model.to_owned(), width, height, params: values });
    }
    Ok(cameras)
}

fn parse_images_txt(path: &Path) -> Result<BTreeMap<String, ColmapImage>> {
    let lines = data_lines(path)?;
    let mut images = BTreeMap::new();
    let mut rows = lines.iter();
    while let Some((line, text)) = rows.next() {
        if text.trim().is_empty() {
            continue;
        }
        let fields: Vec<&str> = text.split_whitespace().collect();
        let field = format!("line {line}");
        if fields.len() < 10 {
            return Err(Error::invalid(path, field, "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"));
        }
        let values = numbers(path, *line, &fields[1..8])?;
        let name = fields[9..].join(" ");
        check_name(&name).map_err(|reason| Error::invalid(path, field.as_str(), reason))?;
        let image = ColmapImage {
            camera_id: integer(path, *line, fields[8])?,
            qvec: [values[0], values[1], values[2], values[3]],
            tvec: [values[4], values[5], values[6]],
        };
        if images.insert(name.clone(), image).is_some() {
            return Err(Error::invalid(path, field, format!("image name {name} registered twice")));
        }
        // The POINTS2D line that follows every image line (possibly empty).
        rows.next();
    }
    Ok(images)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_lying_record_count_is_refused_before_allocation() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cameras.bin");
        std::fs::write(&path, u64::MAX.to_le_bytes()).unwrap();
        let error = parse_cameras_bin(&path).unwrap_err().to_string();
        assert!(
            error.contains("cameras.bin") && error.contains("num_cameras") && error.contains("declares"),
            "{error}"
        );
    }

    #[test]
    fn a_truncated_image_record_names_the_record() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("images.bin");
        let mut bytes = 1u64.to_le_bytes().to_vec();
        bytes.extend(1i32.to_le_bytes());
        bytes.extend([0u8; 7 * 8 + 4]);
        bytes.extend(b"a.png-no-terminator");
        std::fs::write(&path, &bytes).unwrap();
        let error = parse_images_bin(&path).unwrap_err().to_string();
        assert!(error.contains("images.bin") && error.contains("image[0]") && error.contains("NUL"), "{error}");
    }

    #[test]
    fn depth_map_headers_and_sizes_are_checked() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.png.geometric.bin");
        let mut bytes = b"2&2&1&".to_vec();
        bytes.extend([1.0f32, 2.0, 3.0, 4.0].iter().flat_map(|v| v.to_le_bytes()));
        std::fs::write(&path, &bytes).unwrap();
        assert_eq!(read_depth_map(&path).unwrap(), (2, 2, vec![1.0, 2.0, 3.0, 4.0]));
        std::fs::write(&path, &bytes[..bytes.len() - 4]).unwrap();
        assert!(read_depth_map(&path).unwrap_err().to_string().contains("12 bytes after the header"));
        std::fs::write(&path, b"2&2&3&").unwrap();
        assert!(read_depth_map(&path).unwrap_err().to_string().contains("3 channels"));
        std::fs::write(&path, b"99999&2&1&").unwrap();
        assert!(read_depth_map(&path).unwrap_err().to_string().contains("outside"));
        std::fs::write(&path, b"no header").unwrap();
        assert!(read_depth_map(&path).unwrap_err().to_string().contains("width&height&channels&"));
    }

    #[test]
    fn zero_distortion_is_a_pinhole_and_principal_points_move_to_integer_centres() {
        let camera =
            |model: &str, params: Vec<f64>| ColmapCamera { model: model.into(), width: 64, height: 48, params };
        let path = Path::new("cameras.txt");
        let k = pinhole_k(path, "camera 1", &camera("SIMPLE_RADIAL", vec![50.0, 32.0, 24.0, 0.0])).unwrap();
        assert_eq!(k, [50.0, 0.0, 31.5, 0.0, 50.0, 23.5, 0.0, 0.0, 1.0]);
        let k =
            pinhole_k(path, "camera 1", &camera("OPENCV", vec![50.0, 60.0, 32.0, 24.0, 0.0, 0.0, 0.0, 0.0])).unwrap();
        assert_eq!((k[0], k[4]), (50.0, 60.0));
        let error = pinhole_k(path, "camera 1", &camera("RADIAL", vec![50.0, 32.0, 24.0, 0.0, 0.01])).unwrap_err();
        assert!(error.to_string().contains("RADIAL has distortion"), "{error}");
    }
}
