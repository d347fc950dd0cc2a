//! Exact co-visibility: a source pixel with surface point X is co-visible from a novel camera iff X
//! lies in front of it, projects inside its image, and the segment from the novel camera's centre
//! to X crosses no triangle of the frame's depth mesh before X (up to a relative epsilon; the
//! triangles having X as a corner are its own surface and never occlude it). One mesh per frame
//! serves every trajectory; pixels are independent, so the mask is bit-identical whatever the
//! thread count.
//!
//! The same test answers the multi-view question ([`target_visibility_mask`]): which surface
//! points of another camera, lifted from its own depth, the mesh's camera sees first.

use glam::DVec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::config_file::{Checked, Validate, check_float};
use crate::geometry::depth_mesh::{DepthMesh, Footprint, MeshConfig};
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
/// joins it to its neighbours is hidden by it. The multi-view pairs' mask where the target has
/// depth; pixels without valid depth are not visible.
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
    visible
        .into_iter()
        .zip(footprints)
        .map(|(visible, f)| visible && !matches!(f, Some((_, Footprint::Behind))))
        .collect()
}
