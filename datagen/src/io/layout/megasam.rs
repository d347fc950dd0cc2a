//! MegaSAM's native output: `*_sgd_cvd_hr.npz` with `images` (N,H,W,3) u8, `depths` (N,H,W),
//! `intrinsic` (3,3) and `cam_c2w` (N,4,4) world_from_camera.

use std::path::{Path, PathBuf};

use image::RgbImage;

use crate::error::{Error, Result};
use crate::io::npy::{Axis, NdArray, NpzReader};
use crate::io::reconstruction::{DepthStack, Parts, Reconstruction, assemble, list};

/// The ending of MegaSAM's archive name.
pub const ARCHIVE_SUFFIX: &str = "_sgd_cvd_hr.npz";

/// The first MegaSAM archive of `dir` (sorted by name), if it holds one.
pub fn archive(dir: &Path) -> Result<Option<PathBuf>> {
    Ok(list(dir)?.into_iter().find(|p| p.to_string_lossy().ends_with(ARCHIVE_SUFFIX)))
}

/// The NumPy dtype (`<f4`, `|u1`, `|b1`, ...) of member `name` of the `.npz` at `path`, from the
/// member's header only; `None` if the archive has no such member.
fn npz_member_dtype(path: &Path, name: &str) -> Result<Option<String>> {
    let mut archive = NpzReader::open(path)?;
    if !archive.contains(name) {
        return Ok(None);
    }
    Ok(Some(archive.header(name, None)?.dtype))
}

/// MegaSAM stores `images` as uint8 0–255. A bool array is a mask, and a float array may hold 0–1
/// or 0–255 values: guessing would silently give black or saturated frames, so both are errors
/// (integer arrays are accepted when every value is in 0–255, checked when they are converted).
fn check_image_dtype(path: &Path, field: &str, dtype: &str) -> Result<()> {
    let kind = dtype.trim_start_matches(['<', '>', '|', '=']).chars().next();
    let reason = match kind {
        Some('b') => "is a boolean array (a mask?), not RGB images",
        Some('f') => {
            "is a float array: ambiguous (0–1 or 0–255?); store uint8 0–255, e.g. (images * 255).round().astype(np.uint8) for 0–1 values"
        }
        Some('u' | 'i') => return Ok(()),
        _ => "is not an integer array",
    };
    Err(Error::invalid(path, field, format!("dtype `{dtype}` {reason}")))
}

/// Reads the MegaSAM archive `path`: frames and reconstruction.
pub(crate) fn read(path: &Path) -> Result<Parts> {
    if let Some(dtype) = npz_member_dtype(path, "images")? {
        check_image_dtype(path, "images", &dtype)?;
    }
    let (images, reconstruction) = reconstruction(path, true)?;
    let images = images.ok_or_else(|| Error::array(path, Some("images.npy"), "missing from the archive"))?;
    let (n, h, w) = (images.shape[0], images.shape[1], images.shape[2]);
    if n == 0 || h == 0 || w == 0 {
        return Err(Error::invalid(path, "images", format!("zero-size frames: shape {:?}", images.shape)));
    }
    if let Some(i) = images.data.iter().position(|&v| !(0.0..=f32::from(u8::MAX)).contains(&v)) {
        return Err(Error::invalid(
            path,
            "images",
            format!("value {} in frame {} is outside 0–255 (RGB u8 expected)", images.data[i], i / (h * w * 3)),
        ));
    }
    let frames = images
        .data
        .chunks_exact(h * w * 3)
        .map(|frame| RgbImage::from_raw(w as u32, h as u32, frame.iter().map(|&v| v as u8).collect()).expect("sized"))
        .collect();
    // The MegaSAM depth is at the image resolution; `assemble` resamples if it is not.
    assemble(0.0, frames, path, reconstruction)
}

/// The arrays of a MegaSAM archive: the images (read only `with_images`: frames decoded
/// elsewhere replace them), and the reconstruction. Every member's header is checked against
/// the frame count of `images` first, so no member is inflated before its shape agrees with
/// its siblings'.
pub(crate) fn reconstruction(path: &Path, with_images: bool) -> Result<(Option<NdArray<f32>>, Reconstruction)> {
    let mut archive = NpzReader::open(path)?;
    let images_shape = archive.header("images", Some(&[Axis::Any, Axis::Pixels, Axis::Pixels, Axis::Is(3)]))?.shape;
    let images_spec: Vec<Axis> = images_shape.iter().map(|&n| Axis::Is(n)).collect();
    let frames = images_spec[0];
    let depth_spec = [frames, Axis::Pixels, Axis::Pixels];
    let intrinsic_spec = [Axis::Is(3), Axis::Is(3)];
    let poses_spec = [frames, Axis::Is(4), Axis::Is(4)];
    for (name, spec) in [("depths", &depth_spec[..]), ("intrinsic", &intrinsic_spec), ("cam_c2w", &poses_spec)] {
        archive.header(name, Some(spec))?;
    }
    // u8 values (other dtypes are refused first), exact in f32 at half the memory of f64.
    let images = if with_images { Some(archive.read_f32("images", &images_spec)?) } else { None };
    let depth = DepthStack::from_array(archive.read_f32("depths", &depth_spec)?);
    let intrinsic = archive.read_f64("intrinsic", &intrinsic_spec)?;
    let poses = archive.read_f64("cam_c2w", &poses_spec)?;
    let reconstruction = Reconstruction {
        depth_path: path.to_owned(),
        depth,
        intrinsics: Some((path.to_owned(), intrinsic)),
        poses: Some((path.to_owned(), poses)),
    };
    Ok((images, reconstruction))
}
