//! What every single-camera layout is read into and checked as: the frames beside a
//! reconstruction (depth stack, optional intrinsics and poses, with the files they came from),
//! assembled into frame-resolution depth and one camera per frame. Each layout's module
//! ([`super::layout`] lists them) reads its files into a [`Reconstruction`]; [`assemble`] checks
//! counts, sizes and values across the parts, resamples depth to the frames (nearest, so depth
//! edges stay sharp) and scales K. Missing intrinsics: focal [`FALLBACK_FOCAL_PX`] at the depth
//! resolution, centred principal point; missing poses: identity (the public cog-nvs code's
//! fallbacks). Every check failure names the file and the field.

use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4, DVec3};
use image::RgbImage;
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::io::npy::{Axis, NdArray, read_npy_f32_planes};
use crate::io::tool_output::{ToolFrames, ToolOutput};
use foundation::camera::{PinholeCamera, checked_intrinsics, checked_pose};
use foundation::depth::DepthMap;

/// Focal length in pixels (at the depth resolution) assumed when intrinsics are missing: the
/// public cog-nvs code's fallback.
pub const FALLBACK_FOCAL_PX: f64 = 500.0;

/// A read sequence's parts: frame rate, frames, frame-resolution depth and one camera per frame.
pub(crate) type Parts = (f64, Vec<RgbImage>, Vec<DepthMap>, Vec<PinholeCamera>);

/// Depth maps at the reconstruction's resolution, one plane (row-major) per frame, in `f32`, the
/// precision they are kept in: no `f64` or whole-stack copy of a 49×480×720 stack (68 MB as f32).
#[derive(Debug, Clone, PartialEq)]
pub struct DepthStack {
    /// (frames, height, width) as the file declares it.
    pub shape: Vec<usize>,
    /// One map per frame.
    pub planes: Vec<Vec<f32>>,
}

impl DepthStack {
    /// A stack read whole, split into its planes.
    pub(crate) fn from_array(array: NdArray<f32>) -> Self {
        Self { shape: array.shape.clone(), planes: array.into_planes() }
    }

    /// An `(N, H, W)` `.npy` stack, read plane by plane.
    pub(crate) fn read_npy(path: &Path) -> Result<Self> {
        let (shape, planes) = read_npy_f32_planes(path, &[Axis::Any, Axis::Pixels, Axis::Pixels])?;
        Ok(Self { shape, planes })
    }
}

/// The reconstruction part of a sequence: depth (N,H,W), optional K and poses, with their files.
pub(crate) struct Reconstruction {
    /// The depth's file or folder, for messages.
    pub depth_path: PathBuf,
    /// The depth maps.
    pub depth: DepthStack,
    /// K (3, 3) or (N, 3, 3) at the depth resolution, with its file.
    pub intrinsics: Option<(PathBuf, NdArray<f64>)>,
    /// world_from_camera (N, 4, 4), with its file.
    pub poses: Option<(PathBuf, NdArray<f64>)>,
}

/// A tool's output as the parts [`assemble`] checks: its frames (if it has them) and the
/// reconstruction, with K moved from the size it is given at to the depth maps' size.
pub(crate) fn tool_reconstruction(output: ToolOutput) -> (Option<ToolFrames>, Reconstruction) {
    let ToolOutput {
        frames,
        depth_path,
        depth_size: (width, height),
        depth,
        intrinsics_path,
        intrinsics_size,
        intrinsics,
        poses_path,
        world_from_camera,
    } = output;
    let n = depth.len();
    let k_at_depth: Vec<f64> = intrinsics
        .iter()
        .flat_map(|k| {
            let camera = PinholeCamera {
                width: intrinsics_size.0,
                height: intrinsics_size.1,
                intrinsics: foundation::camera::mat3_from_row_major(k),
                world_from_camera: DMat4::IDENTITY,
            };
            let at_depth = if intrinsics_size == (width as u32, height as u32) {
                camera
            } else {
                camera.resized(width as u32, height as u32)
            };
            foundation::camera::mat3_to_row_major(&at_depth.intrinsics)
        })
        .collect();
    let reconstruction = Reconstruction {
        depth_path,
        depth: DepthStack { shape: vec![n, height, width], planes: depth },
        intrinsics: Some((intrinsics_path, NdArray { shape: vec![intrinsics.len(), 3, 3], data: k_at_depth })),
        poses: Some((
            poses_path,
            NdArray { shape: vec![world_from_camera.len(), 4, 4], data: world_from_camera.concat() },
        )),
    };
    (frames, reconstruction)
}

/// A tool's output that holds its frames, checked and assembled like any layout.
pub(crate) fn assemble_tool(output: ToolOutput) -> Result<Parts> {
    let (frames, reconstruction) = tool_reconstruction(output);
    let frames = frames.expect("the tools' full readers decode their frames");
    assemble(frames.fps, frames.frames, &frames.path, reconstruction)
}

/// Checks counts and values across the parts and builds frame-resolution depth and cameras.
pub(crate) fn assemble(
    fps: f64,
    frames: Vec<RgbImage>,
    frames_path: &Path,
    reconstruction: Reconstruction,
) -> Result<Parts> {
    let Reconstruction { depth_path, depth, intrinsics, poses } = reconstruction;
    let depth_path = depth_path.as_path();
    let n = frames.len();
    let (width, height) = frames.first().map(RgbImage::dimensions).unwrap_or((0, 0));
    if n == 0 || width == 0 || height == 0 {
        return Err(Error::invalid(frames_path, "frames", "no frames or zero-size frames"));
    }
    if let Some(i) = frames.iter().position(|f| f.dimensions() != (width, height)) {
        let (found_w, found_h) = frames[i].dimensions();
        return Err(Error::invalid(
            frames_path,
            format!("frames[{i}]"),
            format!("size {found_w}x{found_h} differs from frame 0's {width}x{height}"),
        ));
    }
    if depth.shape.len() != 3 || depth.shape[0] != n {
        return Err(Error::invalid(
            depth_path,
            "depth",
            format!(
                "shape {:?} does not hold one (H, W) map per frame: {} has {n} frames",
                depth.shape,
                frames_path.display()
            ),
        ));
    }
    let (depth_h, depth_w) = (depth.shape[1], depth.shape[2]);
    if depth_h == 0 || depth_w == 0 {
        return Err(Error::invalid(depth_path, "depth", "zero-size depth maps"));
    }
    check_depth_orientation(depth_path, "depth", depth_w, depth_h, width, height)?;

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
                .collect::<foundation::Result<_>>()?
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
            p.data
                .chunks_exact(16)
                .enumerate()
                .map(|(i, v)| checked_pose(path, &format!("world_from_camera[{i}]"), v))
                .collect::<foundation::Result<_>>()?
        }
    };
    let cameras: Vec<PinholeCamera> = intrinsics_per_frame
        .iter()
        .zip(&poses_per_frame)
        .map(|(k, pose)| PinholeCamera { world_from_camera: *pose, ..at_depth_resolution(*k).resized(width, height) })
        .collect();

    let depth_maps = resample_stack(depth, width as usize, height as usize);
    if let Some(i) = depth_maps.iter().position(|d| !d.values.iter().any(|&v| v.is_finite() && v > 0.0)) {
        return Err(Error::invalid(depth_path, format!("depth[{i}]"), "every value is invalid (≤ 0, NaN or inf)"));
    }
    Ok((fps, frames, depth_maps, cameras))
}

/// Relative tolerance when comparing a depth map's aspect ratio with the frames': depth computed
/// at a reduced size rounds each side to a multiple of 8 or so (480×854 → 288×512 differs by
/// 0.1 %), far below the gap between a non-square aspect and its transpose.
const ASPECT_TOLERANCE: f64 = 0.01;

/// Depth at another resolution than the frames is legal (it is resampled, K scaled per axis), but
/// depth whose aspect ratio is the frames' transposed (and not also the frames' own, as for
/// near-square frames) was stored as (N, W, H): resampling it would silently stretch a rotated
/// depth map over the frames, so it is an error naming both shapes.
fn check_depth_orientation(
    path: &Path,
    field: &str,
    depth_w: usize,
    depth_h: usize,
    width: u32,
    height: u32,
) -> Result<()> {
    let aspect = |w: f64, h: f64| w / h;
    let frames_aspect = aspect(f64::from(width), f64::from(height));
    let close = |a: f64| (a / frames_aspect - 1.0).abs() <= ASPECT_TOLERANCE;
    let (depth_w, depth_h) = (depth_w as f64, depth_h as f64);
    if close(aspect(depth_h, depth_w)) && !close(aspect(depth_w, depth_h)) {
        return Err(Error::invalid(
            path,
            field,
            format!(
                "depth maps are {depth_h}x{depth_w} (H×W) but the frames are {height}x{width} (H×W): the depth looks \
                 stored transposed as (N, W, H); save it as (N, H, W) (e.g. depth.transpose(0, 2, 1))"
            ),
        ));
    }
    Ok(())
}

/// A folder of per-frame `*.exr` depth maps (sorted by name) as an `[N, H, W]` array; every map
/// must have the first one's size.
pub fn read_exr_folder(depth_dir: &Path) -> Result<DepthStack> {
    let depth_files = with_extension(depth_dir, &["exr"])?;
    let contents =
        depth_files.par_iter().map(|p| std::fs::read(p).map_err(|e| Error::io(p, e))).collect::<Result<Vec<_>>>()?;
    let context = |i: usize| depth_files[i].display().to_string();
    // Every header first: a map declaring another size fails before any is decoded.
    let sizes = contents
        .par_iter()
        .enumerate()
        .map(|(i, bytes)| crate::io::depth_exr::depth_exr_size(bytes, &context(i)))
        .collect::<Result<Vec<_>>>()?;
    let Some(&(w, h)) = sizes.first() else {
        return Err(Error::invalid(depth_dir, "depth", "no .exr files"));
    };
    if let Some(i) = sizes.iter().position(|&size| size != (w, h)) {
        let (found_w, found_h) = sizes[i];
        return Err(Error::invalid(
            &depth_files[i],
            "depth",
            format!("{found_w}x{found_h} differs from the first map's {w}x{h}"),
        ));
    }
    let depth_maps = contents
        .par_iter()
        .enumerate()
        .map(|(i, bytes)| crate::io::depth_exr::decode_depth_exr_of_size(bytes, &context(i), w, h))
        .collect::<Result<Vec<_>>>()?;
    Ok(DepthStack { shape: vec![depth_maps.len(), h, w], planes: depth_maps.into_iter().map(|m| m.values).collect() })
}

/// Per-frame depth maps from a folder of `*.exr` files or an `(N, H, W)` `.npy` array, resampled
/// (nearest) to `width × height`; there must be exactly `frames` of them.
pub fn read_depth_stack(path: &Path, frames: usize, width: u32, height: u32) -> Result<Vec<DepthMap>> {
    let stack = if path.is_dir() { read_exr_folder(path)? } else { DepthStack::read_npy(path)? };
    let (n, h, w) = (stack.shape[0], stack.shape[1], stack.shape[2]);
    if n != frames {
        return Err(Error::invalid(path, "depth", format!("{n} depth maps for {frames} frames")));
    }
    if h == 0 || w == 0 {
        return Err(Error::invalid(path, "depth", "zero-size depth maps"));
    }
    check_depth_orientation(path, "depth", w, h, width, height)?;
    Ok(resample_stack(stack, width as usize, height as usize))
}

/// Every map of a checked stack at `width × height`: moved as they are when they already have
/// that size, else resampled ([`resample_nearest`]).
fn resample_stack(stack: DepthStack, width: usize, height: usize) -> Vec<DepthMap> {
    let (h, w) = (stack.shape[1], stack.shape[2]);
    if (w, h) == (width, height) {
        return stack.planes.into_iter().map(|values| DepthMap { width, height, values }).collect();
    }
    stack.planes.par_iter().map(|map| resample_nearest(map, w, h, width, height)).collect()
}

/// Nearest-neighbour resampling with pixel centres at integer coordinates (no blending across
/// depth edges, which would invent surfaces between foreground and background).
pub fn resample_nearest(values: &[f32], width: usize, height: usize, to_width: usize, to_height: usize) -> DepthMap {
    let map = |to: usize, to_size: usize, size: usize| {
        (((to as f64 + 0.5) * size as f64 / to_size as f64 - 0.5).round().max(0.0) as usize).min(size - 1)
    };
    // The source column of each output column, computed once (not once per pixel).
    let columns: Vec<usize> = (0..to_width).map(|u| map(u, to_width, width)).collect();
    let mut out = Vec::with_capacity(to_width * to_height);
    for v in 0..to_height {
        let row = &values[map(v, to_height, height) * width..][..width];
        out.extend(columns.iter().map(|&u| row[u]));
    }
    DepthMap { width: to_width, height: to_height, values: out }
}

/// The entries of `dir`, sorted by path.
pub(crate) fn list(dir: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    let mut paths: Vec<PathBuf> = entries.filter_map(|e| e.ok().map(|e| e.path())).collect();
    paths.sort();
    Ok(paths)
}

/// The files of `dir` (sorted) whose extension is one of `extensions`, in any case.
pub(crate) fn with_extension(dir: &Path, extensions: &[&str]) -> Result<Vec<PathBuf>> {
    Ok(list(dir)?
        .into_iter()
        .filter(|p| {
            p.extension().and_then(|e| e.to_str()).is_some_and(|e| extensions.iter().any(|x| e.eq_ignore_ascii_case(x)))
        })
        .collect())
}
