//! Exact co-visibility: a source pixel with surface point X is co-visible from a novel camera iff X
//! lies in front of it, projects inside its image, and the segment from the novel camera's centre
//! to X crosses no triangle of the frame's depth mesh before X (up to a relative epsilon; the
//! triangles having X as a corner are its own surface and never occlude it). One mesh per frame
//! serves every trajectory; pixels are independent, so the mask is bit-identical whatever the
//! thread count.

use serde::{Deserialize, Serialize};

use crate::config_file::{Checked, Validate, check_float};
use crate::geometry::depth_mesh::{DepthMesh, MeshConfig};
use foundation::camera::PinholeCamera;

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
