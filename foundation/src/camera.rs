//! The pinhole camera: intrinsics K in pixels with pixel centres at integer coordinates, pose as
//! `world_from_camera` with OpenCV axes (x right, y down, z forward), and z-depth along the optical
//! axis (see docs/ARCHITECTURE.md, Conventions).

use std::path::Path;

use glam::{DMat3, DMat4, DVec2, DVec3};

use crate::error::{Error, Result};

/// Tolerance on `RᵀR = I` and `det R = +1` for a pose's rotation to count as rigid: float32
/// poses are orthonormal to ~1e-6 and float16 ones to ~5e-4, while a scale, shear or wrong
/// layout is off by far more.
pub const ROTATION_TOLERANCE: f64 = 1e-3;
/// Tolerance on entries that must be exactly 0 or 1 (a pose's last row `0 0 0 1`, K's last row
/// `0 0 1`; K's zero off-diagonal terms relative to the focal length): 0 and 1 are exact in every
/// float format, so only round-off from a float32 matrix product is allowed.
pub const ZERO_ONE_TOLERANCE: f64 = 1e-6;

/// The pixel coordinates of K · (p / p.z) for a camera-space point p with finite p.z > 0, bit
/// for bit: p.z / p.z is then exactly 1, so its division and K's third row, which per-pixel loops
/// would pay for, are left out (the sums run in the order of `DMat3 * DVec3`).
#[inline]
pub fn pixel_of(intrinsics: &DMat3, in_camera: DVec3) -> DVec2 {
    let (u, v) = (in_camera.x / in_camera.z, in_camera.y / in_camera.z);
    let (c0, c1, c2) = (intrinsics.x_axis, intrinsics.y_axis, intrinsics.z_axis);
    DVec2::new(c0.x * u + c1.x * v + c2.x, c0.y * u + c1.y * v + c2.y)
}

/// A calibrated camera at one instant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PinholeCamera {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Intrinsics K (pixels): `[fx 0 cx; 0 fy cy; 0 0 1]`.
    pub intrinsics: DMat3,
    /// Pose: maps camera coordinates to world coordinates.
    pub world_from_camera: DMat4,
}

impl PinholeCamera {
    /// The inverse pose.
    pub fn camera_from_world(&self) -> DMat4 {
        self.world_from_camera.inverse()
    }

    /// Optical centre in world coordinates.
    pub fn center(&self) -> DVec3 {
        self.world_from_camera.w_axis.truncate()
    }

    /// World-space direction through the centre of pixel (u, v), scaled so that its camera-space
    /// z component is 1 (so `center + depth * ray` is the point at z-depth `depth`).
    pub fn pixel_ray(&self, u: f64, v: f64) -> DVec3 {
        let in_camera = self.intrinsics.inverse() * DVec3::new(u, v, 1.0);
        self.world_from_camera.transform_vector3(in_camera)
    }

    /// World point seen at pixel (u, v) with z-depth `depth`.
    pub fn unproject(&self, u: f64, v: f64, depth: f64) -> DVec3 {
        self.center() + depth * self.pixel_ray(u, v)
    }

    /// Pixel coordinates and z-depth of a world point; `None` if it is not in front (z ≤ 0).
    pub fn project(&self, point_in_world: DVec3) -> Option<(DVec2, f64)> {
        let in_camera = self.camera_from_world().transform_point3(point_in_world);
        if in_camera.z <= 0.0 {
            return None;
        }
        Some((pixel_of(&self.intrinsics, in_camera), in_camera.z))
    }

    /// Whether pixel coordinates fall inside the image (pixel centres at integers, so the image
    /// spans −0.5 .. W−0.5).
    pub fn contains(&self, pixel: DVec2) -> bool {
        pixel.x >= -0.5 && pixel.y >= -0.5 && pixel.x < self.width as f64 - 0.5 && pixel.y < self.height as f64 - 0.5
    }

    /// The same camera for an image resampled to `width` × `height` (K scaled; pixel centres kept
    /// at integer coordinates, so the principal point maps as (c + 0.5)·s − 0.5).
    pub fn resized(&self, width: u32, height: u32) -> Self {
        let (sx, sy) = (width as f64 / self.width as f64, height as f64 / self.height as f64);
        let k = self.intrinsics;
        let intrinsics = DMat3::from_cols(
            DVec3::new(k.x_axis.x * sx, 0.0, 0.0),
            DVec3::new(k.y_axis.x * sx, k.y_axis.y * sy, 0.0),
            DVec3::new((k.z_axis.x + 0.5) * sx - 0.5, (k.z_axis.y + 0.5) * sy - 0.5, 1.0),
        );
        Self { width, height, intrinsics, world_from_camera: self.world_from_camera }
    }
}

/// Row-major 3×3 values → DMat3.
pub fn mat3_from_row_major(values: &[f64]) -> DMat3 {
    DMat3::from_cols_slice(values).transpose()
}

/// Row-major 4×4 values → DMat4.
pub fn mat4_from_row_major(values: &[f64]) -> DMat4 {
    DMat4::from_cols_slice(values).transpose()
}

/// DMat3 → row-major array (the shard layout).
pub fn mat3_to_row_major(matrix: &DMat3) -> [f64; 9] {
    matrix.transpose().to_cols_array()
}

/// DMat4 → row-major array (the shard layout).
pub fn mat4_to_row_major(matrix: &DMat4) -> [f64; 16] {
    matrix.transpose().to_cols_array()
}

/// Checks a `world_from_camera` pose given as 16 row-major values and returns it: every value
/// finite, last row `0 0 0 1` (within [`ZERO_ONE_TOLERANCE`]; returned exact), rotation
/// orthonormal with determinant +1 (within [`ROTATION_TOLERANCE`]). The one pose check of the
/// crate: every reader (sequence layouts, `cameras.json`, trajectory files, shards) calls it, so
/// a pose is either usable by the geometry or an error naming `path` and `field`.
pub fn checked_pose(path: &Path, field: &str, row_major: &[f64]) -> Result<DMat4> {
    let invalid = |reason: String| Error::invalid(path, field, reason);
    if row_major.len() != 16 {
        return Err(invalid(format!("a 4×4 pose needs 16 values, found {}", row_major.len())));
    }
    if let Some(i) = row_major.iter().position(|v| !v.is_finite()) {
        return Err(invalid(format!("non-finite value {} at row {}, column {}", row_major[i], i / 4, i % 4)));
    }
    let last_row = &row_major[12..];
    if last_row.iter().zip([0.0, 0.0, 0.0, 1.0]).any(|(v, want)| (v - want).abs() > ZERO_ONE_TOLERANCE) {
        return Err(invalid(format!(
            "not a rigid transform: last row is {last_row:?}, expected [0, 0, 0, 1] (a camera pose, not a projection)"
        )));
    }
    let mut values = row_major.to_vec();
    values[12..].copy_from_slice(&[0.0, 0.0, 0.0, 1.0]);
    let pose = mat4_from_row_major(&values);
    let rotation = DMat3::from_mat4(pose);
    let gram = rotation.transpose() * rotation - DMat3::IDENTITY;
    let off = gram.to_cols_array().iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if off > ROTATION_TOLERANCE {
        return Err(invalid(format!(
            "not a rigid transform: the rotation is not orthonormal (max |RᵀR − I| = {off:.3e}; scaled, sheared or not a pose?)"
        )));
    }
    let determinant = rotation.determinant();
    if (determinant - 1.0).abs() > ROTATION_TOLERANCE {
        return Err(invalid(format!(
            "not a rigid transform: rotation determinant {determinant:.6}, expected +1 (a mirrored, left-handed frame; poses use OpenCV axes)"
        )));
    }
    Ok(pose)
}

/// Checks intrinsics K given as 9 row-major values and returns them: every value finite,
/// `fx, fy > 0`, last row `0 0 1` and zero skew and `K[1][0]` (within [`ZERO_ONE_TOLERANCE`],
/// relative to the focal length for the pixel-valued terms; returned exact), since every
/// camera here is `[fx 0 cx; 0 fy cy; 0 0 1]` ([`PinholeCamera::resized`] and the shard layout
/// assume it). The one K check of the crate, used by every reader.
pub fn checked_intrinsics(path: &Path, field: &str, row_major: &[f64]) -> Result<DMat3> {
    let invalid = |reason: String| Error::invalid(path, field, reason);
    if row_major.len() != 9 {
        return Err(invalid(format!("a 3×3 K needs 9 values, found {}", row_major.len())));
    }
    if let Some(i) = row_major.iter().position(|v| !v.is_finite()) {
        return Err(invalid(format!("non-finite value {} at row {}, column {}", row_major[i], i / 3, i % 3)));
    }
    let (fx, fy) = (row_major[0], row_major[4]);
    if fx <= 0.0 || fy <= 0.0 {
        return Err(invalid(format!("focal lengths must be positive, found fx = {fx}, fy = {fy}")));
    }
    let last_row = &row_major[6..];
    if last_row.iter().zip([0.0, 0.0, 1.0]).any(|(v, want)| (v - want).abs() > ZERO_ONE_TOLERANCE) {
        return Err(invalid(format!("last row is {last_row:?}, expected [0, 0, 1] (K = [fx 0 cx; 0 fy cy; 0 0 1])")));
    }
    let focal = fx.max(fy);
    for (index, name) in [(1, "skew K[0][1]"), (3, "K[1][0]")] {
        if row_major[index].abs() > ZERO_ONE_TOLERANCE * focal {
            return Err(invalid(format!(
                "{name} = {} must be 0: cameras here are K = [fx 0 cx; 0 fy cy; 0 0 1]",
                row_major[index]
            )));
        }
    }
    Ok(DMat3::from_cols(
        DVec3::new(fx, 0.0, 0.0),
        DVec3::new(0.0, fy, 0.0),
        DVec3::new(row_major[2], row_major[5], 1.0),
    ))
}

/// A `rows × cols` matrix written in JSON as nested rows (`[[a, b], [c, d]]`) or as row-major
/// flat values (`[a, b, c, d]`), as row-major values; the error says what was found instead.
pub fn json_matrix(value: &serde_json::Value, rows: usize, cols: usize) -> Result<Vec<f64>, String> {
    let expected =
        format!("expected a {rows}×{cols} matrix ({rows} rows of {cols} numbers, or {} numbers)", rows * cols);
    let numbers =
        |items: &[serde_json::Value]| items.iter().map(serde_json::Value::as_f64).collect::<Option<Vec<f64>>>();
    let serde_json::Value::Array(items) = value else {
        return Err(format!("{expected}, found {}", json_kind(value)));
    };
    let values = if items.iter().all(serde_json::Value::is_array) && !items.is_empty() {
        if items.len() != rows {
            return Err(format!("{expected}, found {} rows", items.len()));
        }
        let mut values = Vec::with_capacity(rows * cols);
        for (r, row) in items.iter().enumerate() {
            let row = row.as_array().map(Vec::as_slice).unwrap_or_default();
            match numbers(row) {
                Some(row_values) if row_values.len() == cols => values.extend(row_values),
                Some(row_values) => return Err(format!("{expected}, row {r} has {} numbers", row_values.len())),
                None => return Err(format!("{expected}, row {r} holds a non-number")),
            }
        }
        values
    } else {
        match numbers(items) {
            Some(values) if values.len() == rows * cols => values,
            Some(values) => return Err(format!("{expected}, found {} numbers", values.len())),
            None => return Err(format!("{expected}, found a list mixing numbers and other values")),
        }
    };
    Ok(values)
}

/// What a JSON value is, for messages.
fn json_kind(value: &serde_json::Value) -> &'static str {
    match value {
        serde_json::Value::Null => "null",
        serde_json::Value::Bool(_) => "a boolean",
        serde_json::Value::Number(_) => "a number",
        serde_json::Value::String(_) => "a string",
        serde_json::Value::Array(_) => "a list",
        serde_json::Value::Object(_) => "an object",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> PinholeCamera {
        let pose = DMat4::from_rotation_y(0.3) * DMat4::from_translation(DVec3::new(0.5, -1.0, 2.0));
        PinholeCamera {
            width: 64,
            height: 48,
            intrinsics: mat3_from_row_major(&[50.0, 0.0, 31.5, 0.0, 55.0, 23.5, 0.0, 0.0, 1.0]),
            world_from_camera: pose,
        }
    }

    #[test]
    fn unproject_then_project_is_identity() {
        let camera = camera();
        let point = camera.unproject(10.0, 40.0, 3.25);
        let (pixel, depth) = camera.project(point).unwrap();
        assert!((pixel - DVec2::new(10.0, 40.0)).length() < 1e-9);
        assert!((depth - 3.25).abs() < 1e-12);
        assert!(camera.project(camera.center() - camera.world_from_camera.z_axis.truncate()).is_none(), "behind");
    }

    #[test]
    fn resizing_keeps_pixel_centres_consistent() {
        let camera = camera();
        let half = camera.resized(32, 24);
        // The point at the centre of the big image's central 2×2 block lands on the small image's
        // pixel whose centre it is.
        let point = camera.unproject(31.5, 23.5, 2.0);
        let (pixel, _) = half.project(point).unwrap();
        assert!((pixel - DVec2::new(15.5, 11.5)).length() < 1e-9, "{pixel}");
    }

    fn pose_error(values: &[f64]) -> String {
        checked_pose(Path::new("poses.npy"), "world_from_camera[0]", values).unwrap_err().to_string()
    }

    #[test]
    fn pose_check_rejects_every_kind_of_non_rigid_matrix() {
        let pose = mat4_to_row_major(&camera().world_from_camera);
        assert_eq!(checked_pose(Path::new("p"), "f", &pose).unwrap(), camera().world_from_camera);
        let with = |index: usize, value: f64| {
            let mut values = pose;
            values[index] = value;
            values
        };
        assert!(pose_error(&with(3, f64::NAN)).contains("non-finite"));
        assert!(pose_error(&with(12, 0.1)).contains("last row"));
        assert!(pose_error(&with(15, 2.0)).contains("last row"));
        assert!(pose_error(&with(0, pose[0] * 2.0)).contains("orthonormal"));
        let mirrored = mat4_to_row_major(&(camera().world_from_camera * DMat4::from_scale(DVec3::new(-1.0, 1.0, 1.0))));
        assert!(pose_error(&mirrored).contains("determinant"));
        assert!(pose_error(&pose[..12]).contains("16 values"));
        let first = pose_error(&with(12, 0.1));
        assert!(first.lines().next().unwrap().contains("poses.npy: field `world_from_camera[0]`"), "{first}");
    }

    #[test]
    fn intrinsics_check_wants_a_pinhole_k() {
        let k = [50.0, 0.0, 31.5, 0.0, 55.0, 23.5, 0.0, 0.0, 1.0];
        let error = |index: usize, value: f64| {
            let mut values = k;
            values[index] = value;
            checked_intrinsics(Path::new("k.npy"), "intrinsics", &values).unwrap_err().to_string()
        };
        assert_eq!(checked_intrinsics(Path::new("k"), "k", &k).unwrap(), camera().intrinsics);
        assert!(error(0, -50.0).contains("positive"));
        assert!(error(4, f64::INFINITY).contains("non-finite"));
        assert!(error(6, 0.5).contains("last row"));
        assert!(error(8, 2.0).contains("last row"));
        assert!(error(1, 0.5).contains("skew"));
        assert!(error(3, 0.5).contains("K[1][0]"));
    }

    #[test]
    fn json_matrices_nested_or_flat() {
        let nested = serde_json::json!([[1, 2, 3], [4, 5, 6], [7, 8, 9]]);
        let flat = serde_json::json!([1, 2, 3, 4, 5, 6, 7, 8, 9]);
        let expected: Vec<f64> = (1..=9).map(f64::from).collect();
        assert_eq!(json_matrix(&nested, 3, 3).unwrap(), expected);
        assert_eq!(json_matrix(&flat, 3, 3).unwrap(), expected);
        assert!(json_matrix(&serde_json::json!([[1, 2], [3, 4], [5, 6]]), 3, 3).unwrap_err().contains("row 0 has 2"));
        assert!(json_matrix(&serde_json::json!([1, 2, 3]), 3, 3).unwrap_err().contains("found 3 numbers"));
        assert!(json_matrix(&serde_json::json!("K"), 3, 3).unwrap_err().contains("a string"));
    }

    #[test]
    fn row_major_round_trips() {
        let values: Vec<f64> = (0..16).map(f64::from).collect();
        assert_eq!(mat4_to_row_major(&mat4_from_row_major(&values)).to_vec(), values);
        assert_eq!(mat4_from_row_major(&values).w_axis.x, 3.0, "row-major: translation x is element 3");
    }
}
