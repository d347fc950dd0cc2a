//! The pinhole camera of DESIGN §2: intrinsics K in pixels with pixel centres at integer
//! coordinates, pose as `world_from_camera` with OpenCV axes (x right, y down, z forward), and
//! z-depth along the optical axis.

use glam::{DMat3, DMat4, DVec2, DVec3};

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
        let pixel = self.intrinsics * (in_camera / in_camera.z);
        Some((DVec2::new(pixel.x, pixel.y), in_camera.z))
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

    #[test]
    fn row_major_round_trips() {
        let values: Vec<f64> = (0..16).map(f64::from).collect();
        assert_eq!(mat4_to_row_major(&mat4_from_row_major(&values)).to_vec(), values);
        assert_eq!(mat4_from_row_major(&values).w_axis.x, 3.0, "row-major: translation x is element 3");
    }
}
