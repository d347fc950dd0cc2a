//! What a reconstruction tool's reader hands to the sequence reader: depth, intrinsics and
//! `world_from_camera` poses already converted to the project's conventions (docs/ARCHITECTURE.md,
//! Conventions), with the files they came from, and the frames when the tool's folder holds them.
//! The per-tool readers ([`super::vipe`], [`super::vggt`], [`super::colmap`], [`super::gen3c`],
//! [`super::depth_only`]) build one; [`super::reconstruction`] checks it against the frames like any
//! other layout. The helpers here are the conversions more than one tool needs.

use std::path::{Path, PathBuf};

use glam::DMat4;
use image::RgbImage;

use crate::error::{Error, Result};
use foundation::camera::{checked_pose, mat4_to_row_major};

/// Frames read from the tool's own folder.
#[derive(Debug, Clone)]
pub struct ToolFrames {
    /// Frame rate (0 if the files do not say).
    pub fps: f64,
    /// RGB frames, in order.
    pub frames: Vec<RgbImage>,
    /// The file or folder they came from (named in errors).
    pub path: PathBuf,
}

/// A tool's reconstruction in the project's conventions.
#[derive(Debug, Clone)]
pub struct ToolOutput {
    /// Frames, when the tool's folder holds them (ViPE's `rgb/`, VGGT's `images`, ...).
    pub frames: Option<ToolFrames>,
    /// The depth file (or folder), named in errors.
    pub depth_path: PathBuf,
    /// Depth map width and height.
    pub depth_size: (usize, usize),
    /// z-depth per frame, row-major; unreliable pixels (a confidence below the tool's threshold,
    /// a validity mask's false) are already NaN, i.e. invalid.
    pub depth: Vec<Vec<f32>>,
    /// The file the intrinsics came from.
    pub intrinsics_path: PathBuf,
    /// The image size K is expressed at (K is rescaled to the depth maps' size from it).
    pub intrinsics_size: (u32, u32),
    /// K per frame, row-major, pixel centres at integer coordinates.
    pub intrinsics: Vec<[f64; 9]>,
    /// The file the poses came from.
    pub poses_path: PathBuf,
    /// `world_from_camera` per frame, row-major, OpenCV axes, checked rigid.
    pub world_from_camera: Vec<[f64; 16]>,
}

/// A tool's output with its frames decoded from `video_path`, the video decoded while `read`
/// reads the reconstruction (decoding is mostly serial).
pub fn with_video(video_path: PathBuf, read: impl FnOnce() -> Result<ToolOutput> + Send) -> Result<ToolOutput> {
    let (video, reconstruction) = rayon::join(|| foundation::video::decode_video(&video_path), read);
    let video = video?;
    let mut output = reconstruction?;
    output.frames = Some(ToolFrames { fps: video.fps, frames: video.frames, path: video_path });
    Ok(output)
}

/// The `world_from_camera` of a `camera_from_world` given as 12 (a 3×4 `[R | t]`) or 16
/// row-major values: the given matrix is checked rigid first (the error names `field` of `path`
/// as the file spells it), then inverted.
pub fn invert_camera_from_world(path: &Path, field: &str, row_major: &[f64]) -> Result<[f64; 16]> {
    let mut values = row_major.to_vec();
    match values.len() {
        12 => values.extend_from_slice(&[0.0, 0.0, 0.0, 1.0]),
        16 => {}
        n => return Err(Error::invalid(path, field, format!("expected a 3×4 or 4×4 matrix, found {n} values"))),
    }
    let camera_from_world = checked_pose(path, field, &values)?;
    Ok(mat4_to_row_major(&rigid_inverse(&camera_from_world)))
}

/// The inverse of a rigid transform, exactly `[Rᵀ | −Rᵀt]` (no general 4×4 inverse round-off).
pub fn rigid_inverse(transform: &DMat4) -> DMat4 {
    let rotation = glam::DMat3::from_mat4(*transform).transpose();
    let translation = -(rotation * transform.w_axis.truncate());
    DMat4::from_cols(
        rotation.x_axis.extend(0.0),
        rotation.y_axis.extend(0.0),
        rotation.z_axis.extend(0.0),
        translation.extend(1.0),
    )
}

/// Share of a frame's finite non-zero depth values that are negative above which the depth is
/// taken as OpenGL-style (the camera looks down −z, so visible points have negative z) rather
/// than a few outliers: a clear majority.
pub const NEGATIVE_DEPTH_SHARE: f64 = 0.5;

/// Refuses depth whose finite non-zero values are mostly negative: z-depth along an OpenCV
/// camera's +z is positive, so such a map is in another convention (OpenGL's −z, or a disparity
/// with a sign flip) and would otherwise just read as "all invalid".
pub fn check_depth_sign(path: &Path, field: &str, frame: usize, values: &[f32]) -> Result<()> {
    let (mut negative, mut total) = (0usize, 0usize);
    for &v in values {
        if v.is_finite() && v != 0.0 {
            total += 1;
            negative += usize::from(v < 0.0);
        }
    }
    if total > 0 && negative as f64 > NEGATIVE_DEPTH_SHARE * total as f64 {
        return Err(Error::invalid(
            path,
            format!("{field}[{frame}]"),
            format!(
                "{negative} of {total} depth values are negative: z-depth in front of an OpenCV camera is positive \
                 (OpenGL-style depth along −z? negate it, or declare the right layout)"
            ),
        ));
    }
    Ok(())
}

/// Sets depth to NaN (invalid) where `confidence` is below `threshold`. Every confidence value
/// must be finite: a NaN confidence is an error naming the file, field, frame and pixel, never a
/// silently kept or dropped depth.
pub fn mask_by_confidence(
    path: &Path,
    field: &str,
    frame: usize,
    width: usize,
    depth: &mut [f32],
    confidence: &[f32],
    threshold: f32,
) -> Result<()> {
    assert_eq!(depth.len(), confidence.len(), "depth and confidence planes have one size");
    if let Some(i) = confidence.iter().position(|c| !c.is_finite()) {
        return Err(Error::invalid(
            path,
            format!("{field}[{frame}]"),
            format!("non-finite confidence {} at pixel (x {}, y {})", confidence[i], i % width, i / width),
        ));
    }
    for (d, &c) in depth.iter_mut().zip(confidence) {
        if c < threshold {
            *d = f32::NAN;
        }
    }
    Ok(())
}

/// Frame indices a tool lists beside its per-frame values (ViPE's `inds`): they must be exactly
/// 0, 1, ..., n − 1 in order, so that value k belongs to frame k; anything else (a gap where the
/// tool lost track, a repeat) is an error naming the first index that differs.
pub fn check_frame_indices(path: &Path, field: &str, indices: &[f64]) -> Result<()> {
    if let Some(k) = indices.iter().enumerate().position(|(k, &i)| i != k as f64) {
        return Err(Error::invalid(
            path,
            field,
            format!(
                "entry {k} is for frame {}, expected frame {k}: every frame needs its own value, in order \
                 (frames the tool skipped have no pose or depth, and none is invented)",
                indices[k]
            ),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{DQuat, DVec3};

    #[test]
    fn rigid_inverse_undoes_the_transform() {
        let pose = DMat4::from_rotation_translation(
            DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -0.2, 1.1),
            DVec3::new(1.0, -2.0, 3.0),
        );
        assert!((rigid_inverse(&pose) * pose).abs_diff_eq(DMat4::IDENTITY, 1e-12));
    }

    #[test]
    fn a_scaled_camera_from_world_is_refused_before_inversion() {
        let scaled = [2.0, 0.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 0.0, 2.0, 0.0];
        let error = invert_camera_from_world(Path::new("p.npz"), "extrinsic[3]", &scaled).unwrap_err().to_string();
        assert!(error.contains("p.npz") && error.contains("extrinsic[3]") && error.contains("rigid"), "{error}");
    }

    #[test]
    fn mostly_negative_depth_is_refused_a_few_negatives_are_not() {
        let path = Path::new("d");
        assert!(check_depth_sign(path, "depth", 0, &[-1.0, -2.0, 3.0]).is_err());
        assert!(check_depth_sign(path, "depth", 0, &[1.0, -2.0, 3.0]).is_ok());
    }

    #[test]
    fn nan_confidence_is_an_error_naming_the_pixel() {
        let mut depth = [1.0, 2.0, 3.0, 4.0];
        let error = mask_by_confidence(Path::new("c"), "conf", 2, 2, &mut depth, &[1.0, 1.0, f32::NAN, 1.0], 0.5)
            .unwrap_err()
            .to_string();
        assert!(error.contains("conf[2]") && error.contains("x 0, y 1"), "{error}");
        mask_by_confidence(Path::new("c"), "conf", 0, 2, &mut depth, &[1.0, 0.1, 1.0, 1.0], 0.5).unwrap();
        assert!(depth[1].is_nan() && depth[0] == 1.0);
    }
}
