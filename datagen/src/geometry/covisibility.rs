//! Exact co-visibility: a source pixel with surface point X is co-visible from a novel camera iff X
//! lies in front of it, projects inside its image, and the segment from the novel camera's centre
//! to X crosses no triangle of the frame's depth mesh before X (up to a relative epsilon; the
//! triangles having X as a corner are its own surface and never occlude it). One mesh per frame
//! serves every trajectory; pixels are independent, so the mask is bit-identical whatever the
//! thread count.
//!
//! The same test answers the multi-view question ([`target_visibility_mask`]): which surface
//! points of another camera, lifted from its own depth, the mesh's camera sees first, and not
//! from behind.

use glam::DVec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::config_file::{Checked, Validate, check_float};
use crate::geometry::depth_mesh::{Accelerator, DepthMesh, Footprint, MeshConfig};
use foundation::camera::PinholeCamera;
use foundation::depth::DepthMap;

/// Occlusion-test settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CovisibilityConfig {
    /// How the depth mesh is cut and how unobserved space behind edges is treated.
    pub mesh: MeshConfig,
    /// Relative length by which a visibility segment is shortened at the surface point, so
    /// round-off on the point's own surface never counts as occlusion. Valid: finite, in
    /// [0, [`MAX_EPSILON`]].
    pub epsilon: f64,
}

/// Largest `epsilon`: past 1 % of the segment the test starts to ignore real occluders just in
/// front of a surface (a hand on a table), which is no longer round-off.
pub const MAX_EPSILON: f64 = 0.01;

impl Validate for CovisibilityConfig {
    fn validate(&self) -> Checked {
        self.mesh.validate().map_err(|e| e.under("mesh"))?;
        check_float("epsilon", self.epsilon, 0.0..=MAX_EPSILON)
    }
}

impl Default for CovisibilityConfig {
    fn default() -> Self {
        Self { mesh: MeshConfig::default(), epsilon: DEFAULT_EPSILON }
    }
}

/// f32 BVH arithmetic at distances of ~10 units resolves ~1e-6 relative; 1e-4 leaves margin
/// while staying far below a pixel's footprint.
pub const DEFAULT_EPSILON: f64 = 1e-4;

/// Co-visibility of every source pixel (row-major) from `novel`.
pub fn covisibility_mask(
    mesh: &DepthMesh,
    source: &PinholeCamera,
    novel: &PinholeCamera,
    config: &CovisibilityConfig,
) -> Vec<bool> {
    debug_assert_eq!(mesh.width(), source.width as usize, "the mesh is lifted from the source camera");
    mesh.view(novel).covisibility(config.epsilon)
}

/// Exact visibility of another camera's surface from the camera the mesh was lifted from: per
/// pixel of `target` (row-major), whether its surface point (its depth in `target_depth` lifted
/// along its pixel ray) is the first surface `source` sees along the ray to it. The point must lie
/// in front of `source` and inside its image, and the segment from `source`'s centre to it,
/// shortened by `epsilon`, must cross no triangle of `mesh` (skirts included), as in the monocular
/// kernel; and as there a point's own surface never hides it: a point at the depth of the source
/// pixel whose footprint holds its image is that pixel's surface, and the pixel's triangles are
/// excluded ([`DepthMesh::footprint_of`]), while a point behind a pixel's sample where no triangle
/// joins it to its neighbours is hidden by it. A point whose surface, as the target's depth mesh
/// has it, turns its back to `source` is hidden by that surface itself
/// ([`DepthMesh::faces_away_from`]): the source sees its other side. The multi-view pairs' mask
/// where the target has depth; pixels without valid depth are not visible.
pub fn target_visibility_mask(
    mesh: &DepthMesh,
    source: &PinholeCamera,
    target_depth: &DepthMap,
    target: &PinholeCamera,
    config: &CovisibilityConfig,
) -> Vec<bool> {
    debug_assert_eq!(mesh.width(), source.width as usize, "the mesh is lifted from the source camera");
    debug_assert_eq!(target_depth.width, target.width as usize, "the depth is the target camera's");
    let width = target_depth.width;
    let footprints: Vec<Option<(DVec3, Footprint)>> = target_depth
        .values
        .par_iter()
        .enumerate()
        .map(|(i, &depth)| {
            let valid = depth > 0.0 && depth.is_finite();
            let point = valid.then(|| target.unproject((i % width) as f64, (i / width) as f64, f64::from(depth)))?;
            Some((point, mesh.footprint_of(point, config.epsilon)))
        })
        .collect();
    let points: Vec<Option<(DVec3, Option<u32>)>> = footprints
        .iter()
        .map(|f| {
            f.map(|(point, footprint)| match footprint {
                Footprint::Own(p) => (point, Some(p)),
                Footprint::Behind | Footprint::Elsewhere => (point, None),
            })
        })
        .collect();
    let visible = mesh.view(source).visibility_of(&points, width, config.epsilon);
    // The target's own surface, cut as the source's, for its orientation only: no ray meets it,
    // so neither skirts nor a BVH are built.
    let plain = MeshConfig { occluder_thickness: 0.0, accelerator: Accelerator::ImageGrids, ..config.mesh.clone() };
    let target_mesh = DepthMesh::new(target_depth, target, &plain);
    let eye = source.center();
    visible
        .into_par_iter()
        .zip(footprints)
        .enumerate()
        .map(|(i, (visible, f))| {
            visible
                && !matches!(f, Some((_, Footprint::Behind)))
                && !target_mesh.faces_away_from(i, eye, config.epsilon)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use glam::{DMat3, DVec3};

    use super::{CovisibilityConfig, target_visibility_mask};
    use crate::geometry::depth_mesh::{DepthMesh, MeshConfig};
    use crate::synth::look_at;
    use foundation::camera::PinholeCamera;
    use foundation::depth::DepthMap;

    /// A small camera at `eye` looking at the origin.
    fn camera(eye: DVec3) -> PinholeCamera {
        let (width, height, focal) = (16, 12, 20.0);
        PinholeCamera {
            width,
            height,
            intrinsics: DMat3::from_cols(
                DVec3::new(focal, 0.0, 0.0),
                DVec3::new(0.0, focal, 0.0),
                DVec3::new(7.5, 5.5, 1.0),
            ),
            world_from_camera: look_at(eye, DVec3::ZERO),
        }
    }

    /// The depth of the plane z = 0 seen by `camera`.
    fn plane_depth(camera: &PinholeCamera) -> DepthMap {
        let (width, height) = (camera.width as usize, camera.height as usize);
        let values = (0..width * height)
            .map(|i| {
                let ray = camera.pixel_ray((i % width) as f64, (i / width) as f64);
                (-camera.center().z / ray.z) as f32
            })
            .collect();
        DepthMap { width, height, values }
    }

    #[test]
    fn a_surface_is_kept_from_its_front_and_hidden_from_its_back() {
        let source = camera(DVec3::new(0.0, 0.0, -5.0));
        let mesh = DepthMesh::new(&plane_depth(&source), &source, &MeshConfig::default());
        let config = CovisibilityConfig::default();
        // Its points inside the source's image: the plane's whole view from either side.
        let inside = |target: &PinholeCamera| -> Vec<bool> {
            let depth = plane_depth(target);
            (0..depth.values.len())
                .map(|i| {
                    let point = target.unproject(
                        (i % depth.width) as f64,
                        (i / depth.width) as f64,
                        f64::from(depth.values[i]),
                    );
                    source.project(point).is_some_and(|(at, _)| source.contains(at))
                })
                .collect()
        };
        // From the source's side, every point the source's image holds is seen.
        let front = camera(DVec3::new(1.5, 0.5, -5.0));
        let kept = target_visibility_mask(&mesh, &source, &plane_depth(&front), &front, &config);
        assert!(inside(&front).iter().any(|&i| i));
        assert_eq!(kept, inside(&front));
        // From the other side, the target sees the face the source does not: nothing is kept,
        // although every point lies on the source's surface.
        let back = camera(DVec3::new(1.5, 0.5, 5.0));
        let kept = target_visibility_mask(&mesh, &source, &plane_depth(&back), &back, &config);
        assert!(inside(&back).iter().filter(|&&i| i).count() > 100);
        assert!(kept.iter().all(|&k| !k), "{} target pixels kept", kept.iter().filter(|&&k| k).count());
    }
}
