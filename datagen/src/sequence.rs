//! Reading one sequence folder (a video plus its reconstruction) in any of the three layouts of
//! DESIGN §3, into frames, frame-resolution depth, per-frame cameras and optional dynamic masks:
//!
//! - **cog-nvs**: `gt_rgb.mp4` + `cam_info/megasam_depth.npy` (N,H,W), optional
//!   `cam_info/megasam_intrinsics.npy` (3,3) and `cam_info/megasam_c2ws.npy` (N,4,4). Depth at
//!   another resolution than the video is resampled (nearest, so depth edges stay sharp) and K
//!   scaled. Missing intrinsics: focal 500 px at the depth resolution, centred principal point;
//!   missing poses: identity (the public code's fallbacks).
//! - **MegaSAM native**: `*_sgd_cvd_hr.npz` with `images` (N,H,W,3) u8, `depths` (N,H,W),
//!   `intrinsic` (3,3) and `cam_c2w` (N,4,4).
//! - **generic**: `frames/*.png|jpg` (or a single video file in the folder), `depth/*.exr` (one
//!   float channel), `cameras.json`: `{"intrinsics": K or [K per frame], "world_from_camera":
//!   [4×4 per frame]}` with matrices as nested row lists or 9/16 row-major values.
//!
//! Optional `masks/*.png` (palette or greyscale ids: 0 static, >0 object, 255 void) in any layout.
//! Every check failure names the file and the field.

use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4, DVec3};
use image::{GrayImage, RgbImage};
use rayon::prelude::*;

use crate::camera::{PinholeCamera, mat3_from_row_major, mat4_from_row_major};
use crate::depth_exr::DepthMap;
use crate::error::{Error, Result};
use crate::npy::{NdArray, read_array_f64, read_npy_f64};

/// Focal length in pixels (at the depth resolution) assumed when intrinsics are missing: the
/// public cog-nvs code's fallback.
pub const FALLBACK_FOCAL_PX: f64 = 500.0;
/// Tolerance on `RᵀR = I` and `det R = 1` for a pose to count as rigid.
const RIGIDITY_TOLERANCE: f64 = 1e-3;

/// A video with its reconstruction, all at the video's resolution.
#[derive(Debug, Clone)]
pub struct Sequence {
    /// Id of the sequence (its folder name).
    pub source_id: String,
    /// The folder it was read from.
    pub path: PathBuf,
    /// Frame rate (0 if unknown).
    pub fps: f64,
    /// RGB frames.
    pub frames: Vec<RgbImage>,
    /// z-depth per frame at frame resolution.
    pub depth: Vec<DepthMap>,
    /// Camera per frame.
    pub cameras: Vec<PinholeCamera>,
    /// Dynamic-object id masks per frame, if the folder has them.
    pub dynamic_masks: Option<Vec<GrayImage>>,
    /// A second, more accurate depth per frame (LiDAR, a monocular estimator) for measured depth
    /// noise, if the user gave one ([`Sequence::load_second_depth`]).
    pub second_depth: Option<Vec<DepthMap>>,
}

impl Sequence {
    /// Reads a second depth source (a folder of `*.exr` or an `(N, H, W)` `.npy`, one map per
    /// frame), resampled to the frames' size.
    pub fn load_second_depth(&mut self, path: &Path) -> Result<()> {
        let (width, height) = self.size();
        self.second_depth = Some(read_depth_stack(path, self.len(), width, height)?);
        Ok(())
    }

    /// The sequence a stored clip was cut from, for its frames: decoded frames, depth and
    /// dynamic masks, and its cameras. Errors name the clip and the field.
    pub fn from_clip(record: &schemas::ClipRecord) -> Result<Self> {
        let id = &record.clip_id;
        let image = |bytes: &[u8], field: String| {
            image::load_from_memory_with_format(bytes, image::ImageFormat::Png)
                .map_err(|e| Error::Image { context: format!("{id}: {field}"), reason: e.to_string() })
        };
        let frames = record
            .frames
            .par_iter()
            .enumerate()
            .map(|(i, png)| Ok(image(png, format!("frames[{i}]"))?.to_rgb8()))
            .collect::<Result<Vec<_>>>()?;
        let depth = record
            .depth
            .par_iter()
            .enumerate()
            .map(|(i, exr)| crate::depth_exr::decode_depth_exr(exr, &format!("{id}: depth[{i}]")))
            .collect::<Result<Vec<_>>>()?;
        let dynamic_masks = match &record.dynamic_mask {
            Some(masks) => Some(
                masks
                    .par_iter()
                    .enumerate()
                    .map(|(i, png)| Ok(image(png, format!("dynamic_mask[{i}]"))?.to_luma8()))
                    .collect::<Result<Vec<_>>>()?,
            ),
            None => None,
        };
        let cameras = record
            .intrinsics
            .iter()
            .zip(&record.world_from_camera)
            .map(|(k, pose)| PinholeCamera {
                width: record.width,
                height: record.height,
                intrinsics: mat3_from_row_major(k),
                world_from_camera: mat4_from_row_major(pose),
            })
            .collect();
        Ok(Self {
            source_id: record.source_id.clone(),
            path: PathBuf::from(&record.source_path),
            fps: record.fps,
            frames,
            depth,
            cameras,
            dynamic_masks,
            second_depth: None,
        })
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// Whether the sequence has no frames (never true for a sequence returned by a reader).
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Frame width and height.
    pub fn size(&self) -> (u32, u32) {
        self.frames[0].dimensions()
    }
}

/// Which layout a folder is in.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Layout {
    /// `gt_rgb.mp4` + `cam_info/`.
    CogNvs,
    /// A `*_sgd_cvd_hr.npz`.
    MegaSam(PathBuf),
    /// `frames/` or a video, `depth/*.exr`, `cameras.json`.
    Generic,
}

/// Detects the layout of `dir`, or says what is missing.
pub fn detect_layout(dir: &Path) -> Result<Layout> {
    if !dir.is_dir() {
        return Err(Error::io(dir, std::io::Error::new(std::io::ErrorKind::NotFound, "sequence folder not found")));
    }
    if dir.join("cam_info").is_dir() || dir.join("gt_rgb.mp4").is_file() {
        return Ok(Layout::CogNvs);
    }
    let mut npz: Vec<PathBuf> =
        list(dir)?.into_iter().filter(|p| p.to_string_lossy().ends_with("_sgd_cvd_hr.npz")).collect();
    npz.sort();
    if let Some(first) = npz.into_iter().next() {
        return Ok(Layout::MegaSam(first));
    }
    if dir.join("depth").is_dir() || dir.join("cameras.json").is_file() {
        return Ok(Layout::Generic);
    }
    Err(Error::invalid(
        dir,
        "layout",
        "not a sequence folder: expected gt_rgb.mp4 + cam_info/ (cog-nvs), *_sgd_cvd_hr.npz (MegaSAM) or frames/ + depth/ + cameras.json (generic)",
    ))
}

fn list(dir: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    let mut paths: Vec<PathBuf> = entries.filter_map(|e| e.ok().map(|e| e.path())).collect();
    paths.sort();
    Ok(paths)
}

fn with_extension(dir: &Path, extensions: &[&str]) -> Result<Vec<PathBuf>> {
    Ok(list(dir)?
        .into_iter()
        .filter(|p| {
            p.extension().and_then(|e| e.to_str()).is_some_and(|e| extensions.iter().any(|x| e.eq_ignore_ascii_case(x)))
        })
        .collect())
}

/// Decodes image files (PNG, JPEG) as RGB frames, in parallel, in the given order.
pub fn read_frames(paths: &[PathBuf]) -> Result<Vec<RgbImage>> {
    paths
        .par_iter()
        .map(|p| {
            image::open(p)
                .map(|i| i.to_rgb8())
                .map_err(|e| Error::invalid(p, "frame", format!("unreadable image: {e}")))
        })
        .collect()
}

/// Reads the sequence folder `dir` in whichever layout it is.
pub fn read_sequence(dir: &Path) -> Result<Sequence> {
    let (fps, frames, depth_arrays, cameras) = match detect_layout(dir)? {
        Layout::CogNvs => read_cog_nvs(dir)?,
        Layout::MegaSam(npz) => read_megasam(&npz)?,
        Layout::Generic => read_generic(dir)?,
    };
    let source_id = dir.file_name().unwrap_or_default().to_string_lossy().into_owned();
    let dynamic_masks = read_masks(dir, &frames)?;
    Ok(Sequence {
        source_id,
        path: dir.to_owned(),
        fps,
        frames,
        depth: depth_arrays,
        cameras,
        dynamic_masks,
        second_depth: None,
    })
}

type Parts = (f64, Vec<RgbImage>, Vec<DepthMap>, Vec<PinholeCamera>);

/// The reconstruction part of a sequence: depth (N,H,W), optional K and poses, with their files.
struct Reconstruction {
    depth_path: PathBuf,
    depth: NdArray<f64>,
    intrinsics: Option<(PathBuf, NdArray<f64>)>,
    poses: Option<(PathBuf, NdArray<f64>)>,
}

fn read_cog_nvs(dir: &Path) -> Result<Parts> {
    let video_path = dir.join("gt_rgb.mp4");
    // Decoding is mostly serial: read the reconstruction meanwhile.
    let (video, reconstruction) =
        rayon::join(|| crate::video::decode_video(&video_path), || cog_nvs_reconstruction(dir));
    let video = video?;
    assemble(video.fps, video.frames, &video_path, reconstruction?)
}

/// Reads the reconstruction at `reconstruction` (a cog-nvs folder with `cam_info/`, a MegaSAM
/// `*_sgd_cvd_hr.npz` or a folder holding one, or a generic folder with `depth/` and
/// `cameras.json`) for frames decoded elsewhere (a dataset's video or JPEG folder).
pub fn read_with_frames(
    source_id: &str,
    reconstruction: &Path,
    fps: f64,
    frames: Vec<RgbImage>,
    frames_path: &Path,
) -> Result<Sequence> {
    let parts = if reconstruction.is_file() {
        megasam_reconstruction(reconstruction)?.1
    } else {
        match detect_layout(reconstruction)? {
            Layout::CogNvs => cog_nvs_reconstruction(reconstruction)?,
            Layout::MegaSam(npz) => megasam_reconstruction(&npz)?.1,
            Layout::Generic => generic_reconstruction(reconstruction)?,
        }
    };
    let (fps, frames, depth, cameras) = assemble(fps, frames, frames_path, parts)?;
    let path = reconstruction.to_owned();
    Ok(Sequence {
        source_id: source_id.to_owned(),
        path,
        fps,
        frames,
        depth,
        cameras,
        dynamic_masks: None,
        second_depth: None,
    })
}

fn cog_nvs_reconstruction(dir: &Path) -> Result<Reconstruction> {
    let cam = dir.join("cam_info");
    let depth_path = cam.join("megasam_depth.npy");
    let depth = read_npy_f64(&depth_path)?;
    depth.expect_shape(&depth_path, "megasam_depth", &[None, None, None])?;
    let intrinsics_path = cam.join("megasam_intrinsics.npy");
    let intrinsics = if intrinsics_path.is_file() {
        let k = read_npy_f64(&intrinsics_path)?;
        k.expect_shape(&intrinsics_path, "megasam_intrinsics", &[Some(3), Some(3)])?;
        Some((intrinsics_path, k))
    } else {
        None
    };
    let poses_path = cam.join("megasam_c2ws.npy");
    let poses = if poses_path.is_file() { Some((poses_path.clone(), read_npy_f64(&poses_path)?)) } else { None };
    Ok(Reconstruction { depth_path, depth, intrinsics, poses })
}

fn read_npz_member(
    archive: &mut npyz::npz::NpzArchive<std::io::BufReader<std::fs::File>>,
    path: &Path,
    name: &str,
) -> Result<Option<NdArray<f64>>> {
    let npy =
        archive.by_name(name).map_err(|e| Error::invalid(path, name, format!("unreadable archive member: {e}")))?;
    npy.map(|npy| read_array_f64(npy, path, name)).transpose()
}

fn read_megasam(path: &Path) -> Result<Parts> {
    let (images, reconstruction) = megasam_reconstruction(path)?;
    let (n, h, w) = (images.shape[0], images.shape[1], images.shape[2]);
    if n == 0 || h == 0 || w == 0 {
        return Err(Error::invalid(path, "images", format!("zero-size frames: shape {:?}", images.shape)));
    }
    let frames = images
        .data
        .chunks_exact(h * w * 3)
        .map(|frame| {
            RgbImage::from_raw(w as u32, h as u32, frame.iter().map(|&v| v.clamp(0.0, 255.0) as u8).collect())
                .expect("sized")
        })
        .collect();
    // The MegaSAM depth is at the image resolution; `assemble` resamples if it is not.
    assemble(0.0, frames, path, reconstruction)
}

/// The arrays of a MegaSAM archive: the images, and the reconstruction.
fn megasam_reconstruction(path: &Path) -> Result<(NdArray<f64>, Reconstruction)> {
    let mut archive = npyz::npz::NpzArchive::open(path)
        .map_err(|e| Error::invalid(path, "archive", format!("not a readable .npz: {e}")))?;
    let missing = |name: &str| Error::invalid(path, name, "array missing from the archive");
    let images = read_npz_member(&mut archive, path, "images")?.ok_or_else(|| missing("images"))?;
    images.expect_shape(path, "images", &[None, None, None, Some(3)])?;
    let depth = read_npz_member(&mut archive, path, "depths")?.ok_or_else(|| missing("depths"))?;
    let intrinsic = read_npz_member(&mut archive, path, "intrinsic")?.ok_or_else(|| missing("intrinsic"))?;
    intrinsic.expect_shape(path, "intrinsic", &[Some(3), Some(3)])?;
    let poses = read_npz_member(&mut archive, path, "cam_c2w")?.ok_or_else(|| missing("cam_c2w"))?;
    let reconstruction = Reconstruction {
        depth_path: path.to_owned(),
        depth,
        intrinsics: Some((path.to_owned(), intrinsic)),
        poses: Some((path.to_owned(), poses)),
    };
    Ok((images, reconstruction))
}

#[derive(serde::Deserialize)]
#[serde(untagged)]
enum JsonMatrix {
    Nested(Vec<Vec<f64>>),
    Flat(Vec<f64>),
}

impl JsonMatrix {
    fn flatten(self) -> Vec<f64> {
        match self {
            Self::Nested(rows) => rows.into_iter().flatten().collect(),
            Self::Flat(values) => values,
        }
    }
}

#[derive(serde::Deserialize)]
#[serde(untagged)]
enum JsonIntrinsics {
    PerFrame(Vec<JsonMatrix>),
    Shared(JsonMatrix),
}

#[derive(serde::Deserialize)]
struct CamerasJson {
    intrinsics: JsonIntrinsics,
    world_from_camera: Vec<JsonMatrix>,
}

fn read_generic(dir: &Path) -> Result<Parts> {
    let frames_dir = dir.join("frames");
    let read_frames_or_video = || -> Result<(f64, Vec<RgbImage>, PathBuf)> {
        if frames_dir.is_dir() {
            let files = with_extension(&frames_dir, &["png", "jpg", "jpeg"])?;
            return Ok((0.0, read_frames(&files)?, frames_dir.clone()));
        }
        let video = with_extension(dir, &["mp4", "mov", "mkv", "avi", "webm"])?
            .into_iter()
            .next()
            .ok_or_else(|| Error::invalid(dir, "frames", "no frames/ folder and no video file"))?;
        let decoded = crate::video::decode_video(&video)?;
        Ok((decoded.fps, decoded.frames, video))
    };
    // Decoding is mostly serial: read the reconstruction meanwhile.
    let (frames, reconstruction) = rayon::join(read_frames_or_video, || generic_reconstruction(dir));
    let (fps, frames, frames_source) = frames?;
    assemble(fps, frames, &frames_source, reconstruction?)
}

fn generic_reconstruction(dir: &Path) -> Result<Reconstruction> {
    let depth_dir = dir.join("depth");
    let depth = read_exr_folder(&depth_dir)?;
    let cameras_path = dir.join("cameras.json");
    let text = std::fs::read_to_string(&cameras_path).map_err(|e| Error::io(&cameras_path, e))?;
    let cameras: CamerasJson = serde_json::from_str(&text)
        .map_err(|e| Error::invalid(&cameras_path, "cameras", format!("invalid JSON: {e}")))?;
    let intrinsics = match cameras.intrinsics {
        JsonIntrinsics::Shared(k) => NdArray { shape: vec![3, 3], data: k.flatten() },
        JsonIntrinsics::PerFrame(list) => {
            let count = list.len();
            NdArray { shape: vec![count, 3, 3], data: list.into_iter().flat_map(JsonMatrix::flatten).collect() }
        }
    };
    let pose_count = cameras.world_from_camera.len();
    let poses = NdArray {
        shape: vec![pose_count, 4, 4],
        data: cameras.world_from_camera.into_iter().flat_map(JsonMatrix::flatten).collect(),
    };
    for (field, array) in [("intrinsics", &intrinsics), ("world_from_camera", &poses)] {
        if array.data.len() != array.shape.iter().product::<usize>() {
            return Err(Error::invalid(
                &cameras_path,
                field,
                "every matrix must have 3×3 (intrinsics) or 4×4 (poses) values",
            ));
        }
    }
    let intrinsics = Some((cameras_path.clone(), intrinsics));
    Ok(Reconstruction { depth_path: depth_dir, depth, intrinsics, poses: Some((cameras_path, poses)) })
}

/// Checks counts and values across the parts and builds frame-resolution depth and cameras.
fn assemble(fps: f64, frames: Vec<RgbImage>, frames_path: &Path, reconstruction: Reconstruction) -> Result<Parts> {
    let Reconstruction { depth_path, depth, intrinsics, poses } = reconstruction;
    let depth_path = depth_path.as_path();
    let n = frames.len();
    let (width, height) = frames.first().map(RgbImage::dimensions).unwrap_or((0, 0));
    if n == 0 || width == 0 || height == 0 {
        return Err(Error::invalid(frames_path, "frames", "no frames or zero-size frames"));
    }
    if depth.shape.len() != 3 || depth.shape[0] != n {
        return Err(Error::invalid(
            depth_path,
            "depth",
            format!("shape {:?} does not hold {n} frames (the video has {n})", depth.shape),
        ));
    }
    let (depth_h, depth_w) = (depth.shape[1], depth.shape[2]);
    if depth_h == 0 || depth_w == 0 {
        return Err(Error::invalid(depth_path, "depth", "zero-size depth maps"));
    }

    // Intrinsics at the depth resolution (the reconstruction's), then scaled to the frames.
    let at_depth_resolution = |k: DMat3| PinholeCamera {
        width: depth_w as u32,
        height: depth_h as u32,
        intrinsics: k,
        world_from_camera: DMat4::IDENTITY,
    };
    let intrinsics_per_frame: Vec<DMat3> = match &intrinsics {
        None => vec![
            DMat3::from_cols(
                DVec3::new(FALLBACK_FOCAL_PX, 0.0, 0.0),
                DVec3::new(0.0, FALLBACK_FOCAL_PX, 0.0),
                DVec3::new(depth_w as f64 / 2.0 - 0.5, depth_h as f64 / 2.0 - 0.5, 1.0),
            );
            n
        ],
        Some((path, k)) if k.shape == [3, 3] => vec![checked_intrinsics(path, "intrinsics", &k.data)?; n],
        Some((path, k)) if k.shape.len() == 3 && k.shape[1..] == [3, 3] => {
            if k.shape[0] != n {
                return Err(Error::invalid(path, "intrinsics", format!("{} matrices for {n} frames", k.shape[0])));
            }
            k.data
                .chunks_exact(9)
                .enumerate()
                .map(|(i, v)| checked_intrinsics(path, &format!("intrinsics[{i}]"), v))
                .collect::<Result<_>>()?
        }
        Some((path, k)) => {
            return Err(Error::invalid(
                path,
                "intrinsics",
                format!("expected shape (3, 3) or (N, 3, 3), found {:?}", k.shape),
            ));
        }
    };
    let poses_per_frame: Vec<DMat4> = match &poses {
        None => vec![DMat4::IDENTITY; n],
        Some((path, p)) => {
            if p.shape.len() != 3 || p.shape[1..] != [4, 4] {
                return Err(Error::invalid(
                    path,
                    "world_from_camera",
                    format!("expected shape (N, 4, 4), found {:?}", p.shape),
                ));
            }
            if p.shape[0] != n {
                return Err(Error::invalid(path, "world_from_camera", format!("{} poses for {n} frames", p.shape[0])));
            }
            p.data.chunks_exact(16).enumerate().map(|(i, v)| checked_pose(path, i, v)).collect::<Result<_>>()?
        }
    };
    let cameras: Vec<PinholeCamera> = intrinsics_per_frame
        .iter()
        .zip(&poses_per_frame)
        .map(|(k, pose)| PinholeCamera { world_from_camera: *pose, ..at_depth_resolution(*k).resized(width, height) })
        .collect();

    let plane = depth_h * depth_w;
    let depth_maps: Vec<DepthMap> = (0..n)
        .into_par_iter()
        .map(|i| {
            resample_nearest(&depth.data[i * plane..(i + 1) * plane], depth_w, depth_h, width as usize, height as usize)
        })
        .collect();
    if let Some(i) = depth_maps.iter().position(|d| !d.values.iter().any(|&v| v.is_finite() && v > 0.0)) {
        return Err(Error::invalid(depth_path, format!("depth[{i}]"), "every value is invalid (≤ 0, NaN or inf)"));
    }
    Ok((fps, frames, depth_maps, cameras))
}

fn checked_intrinsics(path: &Path, field: &str, values: &[f64]) -> Result<DMat3> {
    let k = mat3_from_row_major(values);
    let finite = values.iter().all(|v| v.is_finite());
    if !finite || k.x_axis.x <= 0.0 || k.y_axis.y <= 0.0 {
        return Err(Error::invalid(path, field, format!("not a valid K (finite, positive focal lengths): {values:?}")));
    }
    Ok(k)
}

fn checked_pose(path: &Path, index: usize, values: &[f64]) -> Result<DMat4> {
    let field = format!("world_from_camera[{index}]");
    if !values.iter().all(|v| v.is_finite()) {
        return Err(Error::invalid(path, field, "non-finite values"));
    }
    let pose = mat4_from_row_major(values);
    let rotation = DMat3::from_mat4(pose);
    let orthonormal = (rotation.transpose() * rotation).abs_diff_eq(DMat3::IDENTITY, RIGIDITY_TOLERANCE);
    let bottom = [values[12], values[13], values[14], values[15]];
    if !orthonormal || (rotation.determinant() - 1.0).abs() > RIGIDITY_TOLERANCE || bottom != [0.0, 0.0, 0.0, 1.0] {
        return Err(Error::invalid(
            path,
            field,
            "not a rigid transform (rotation must be orthonormal with det 1, last row 0 0 0 1)",
        ));
    }
    Ok(pose)
}

/// A folder of per-frame `*.exr` depth maps (sorted by name) as an `[N, H, W]` array; every map
/// must have the first one's size.
pub fn read_exr_folder(depth_dir: &Path) -> Result<NdArray<f64>> {
    let depth_files = with_extension(depth_dir, &["exr"])?;
    let depth_maps = depth_files
        .par_iter()
        .map(|p| {
            let bytes = std::fs::read(p).map_err(|e| Error::io(p, e))?;
            crate::depth_exr::decode_depth_exr(&bytes, &p.display().to_string())
        })
        .collect::<Result<Vec<_>>>()?;
    let (n, h, w) = match depth_maps.first() {
        Some(first) => (depth_maps.len(), first.height, first.width),
        None => return Err(Error::invalid(depth_dir, "depth", "no .exr files")),
    };
    if let Some((i, map)) = depth_maps.iter().enumerate().find(|(_, m)| (m.width, m.height) != (w, h)) {
        return Err(Error::invalid(
            &depth_files[i],
            "depth",
            format!("{}x{} differs from the first map's {w}x{h}", map.width, map.height),
        ));
    }
    Ok(NdArray {
        shape: vec![n, h, w],
        data: depth_maps.iter().flat_map(|m| m.values.iter().map(|&v| f64::from(v))).collect(),
    })
}

/// Per-frame depth maps from a folder of `*.exr` files or an `(N, H, W)` `.npy` array, resampled
/// (nearest) to `width × height`; there must be exactly `frames` of them.
pub fn read_depth_stack(path: &Path, frames: usize, width: u32, height: u32) -> Result<Vec<DepthMap>> {
    let array = if path.is_dir() {
        read_exr_folder(path)?
    } else {
        let array = crate::npy::read_npy_f64(path)?;
        array.expect_shape(path, "depth", &[None, None, None])?;
        array
    };
    let (n, h, w) = (array.shape[0], array.shape[1], array.shape[2]);
    if n != frames {
        return Err(Error::invalid(path, "depth", format!("{n} depth maps for {frames} frames")));
    }
    Ok(array.data.chunks(h * w).map(|map| resample_nearest(map, w, h, width as usize, height as usize)).collect())
}

/// Nearest-neighbour resampling with pixel centres at integer coordinates (no blending across
/// depth edges, which would invent surfaces between foreground and background).
pub fn resample_nearest(values: &[f64], width: usize, height: usize, to_width: usize, to_height: usize) -> DepthMap {
    let map = |to: usize, to_size: usize, size: usize| {
        (((to as f64 + 0.5) * size as f64 / to_size as f64 - 0.5).round().max(0.0) as usize).min(size - 1)
    };
    let mut out = Vec::with_capacity(to_width * to_height);
    for v in 0..to_height {
        let row = map(v, to_height, height) * width;
        for u in 0..to_width {
            out.push(values[row + map(u, to_width, width)] as f32);
        }
    }
    DepthMap { width: to_width, height: to_height, values: out }
}

fn read_masks(dir: &Path, frames: &[RgbImage]) -> Result<Option<Vec<GrayImage>>> {
    let masks_dir = dir.join("masks");
    if !masks_dir.is_dir() {
        return Ok(None);
    }
    let files = with_extension(&masks_dir, &["png"])?;
    if files.len() != frames.len() {
        return Err(Error::invalid(&masks_dir, "masks", format!("{} masks for {} frames", files.len(), frames.len())));
    }
    let (width, height) = frames[0].dimensions();
    files
        .par_iter()
        .map(|path| {
            let mask = crate::corpus::annotations::read_id_png(path)?;
            Ok(if mask.dimensions() == (width, height) {
                mask
            } else {
                image::imageops::resize(&mask, width, height, image::imageops::FilterType::Nearest)
            })
        })
        .collect::<Result<Vec<_>>>()
        .map(Some)
}
