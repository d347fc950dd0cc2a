//! A bounding-volume hierarchy that exploits what a depth mesh is: a regular grid of quads seen
//! from one camera. Every quad projects into the source image as the unit square between its
//! four pixel centres, so the source image partitions space into frustum columns, one per quad.
//! The hierarchy is a quadtree of those columns (2ᵏ × 2ᵏ quads per node) holding, per node, the
//! range of source-camera depth of the triangles inside; building it is a min/max reduction
//! (milliseconds) instead of a generic BVH build.
//!
//! A ray is traversed in source-camera terms: with `p(t) = K·x(t)` linear in the ray parameter,
//! "projects inside a node's rectangle" is four linear inequalities in `t` and the ray's depth is
//! linear in `t`, so each node is entered over an exact `t` interval and culled when the ray is
//! entirely in front of or behind the node's depth range (the screen-space "hierarchical-Z"
//! march, made exact). Leaves hand their quads to the caller's exact triangle test. Rectangles
//! are widened by [`MARGIN_PIXELS`] and depth ranges by [`DEPTH_SLACK`], so the f32 triangle
//! test can never hit outside what the traversal visits: answers equal a brute-force loop over
//! every triangle.

use glam::{DMat3, DMat4, DVec3};

/// Widening of every node's image rectangle. Quad corners are f32 world points whose projections
/// sit within ~1e-4 px of their pixel centres for scenes of sensible scale; this leaves ×100.
pub const MARGIN_PIXELS: f64 = 1e-2;

/// Relative widening of every node's depth range, far above f32 ray/triangle round-off (~1e-6).
pub const DEPTH_SLACK: f64 = 1e-4;

/// Per node: the [min, max] source-camera depth of its triangles ([+∞, −∞] when empty).
type Range = [f32; 2];

const EMPTY: Range = [f32::INFINITY, f32::NEG_INFINITY];

struct Level {
    width: usize,
    height: usize,
    ranges: Vec<Range>,
}

/// The quadtree over a depth mesh's quads.
pub struct DepthPyramid {
    camera_from_world: DMat4,
    intrinsics: DMat3,
    /// Level 0 has one node per quad; the last level has a single node.
    levels: Vec<Level>,
}

/// A ray in the source camera's projective terms: `p(t) = origin + t·step`, `p = K·x_camera`.
struct ProjectedRay {
    origin: DVec3,
    step: DVec3,
}

impl ProjectedRay {
    /// Narrows `[t0, t1]` to where `a(t) = α + β·t ≥ 0`.
    fn keep_nonnegative(alpha: f64, beta: f64, t0: &mut f64, t1: &mut f64) {
        if beta > 0.0 {
            *t0 = t0.max(-alpha / beta);
        } else if beta < 0.0 {
            *t1 = t1.min(-alpha / beta);
        } else if alpha < 0.0 {
            *t1 = f64::NEG_INFINITY;
        }
    }

    /// The part of `[t0, t1]` whose projection lies in `u0 ≤ u ≤ u1`, `v0 ≤ v ≤ v1` (the ray
    /// being in front of the camera there).
    fn clip(&self, [u0, u1, v0, v1]: [f64; 4], mut t0: f64, mut t1: f64) -> Option<(f64, f64)> {
        let (o, s) = (self.origin, self.step);
        Self::keep_nonnegative(o.x - u0 * o.z, s.x - u0 * s.z, &mut t0, &mut t1);
        Self::keep_nonnegative(u1 * o.z - o.x, u1 * s.z - s.x, &mut t0, &mut t1);
        Self::keep_nonnegative(o.y - v0 * o.z, s.y - v0 * s.z, &mut t0, &mut t1);
        Self::keep_nonnegative(v1 * o.z - o.y, v1 * s.z - s.y, &mut t0, &mut t1);
        (t0 <= t1).then_some((t0, t1))
    }

    fn depth(&self, t: f64) -> f64 {
        self.origin.z + t * self.step.z
    }
}

/// One pending node: level, position, and the ray interval inside it.
#[derive(Clone, Copy)]
struct Node {
    level: u8,
    x: u32,
    y: u32,
    t0: f64,
    t1: f64,
}

/// Deep enough for any image: a pop pushes at most four nodes one level down.
const STACK: usize = 4 * 32;

impl DepthPyramid {
    /// Builds the hierarchy over `width` × `height` quads from each quad's depth range.
    pub fn new(width: usize, height: usize, ranges: Vec<Range>, camera_from_world: DMat4, intrinsics: DMat3) -> Self {
        assert_eq!(ranges.len(), width * height, "one depth range per quad");
        let mut levels = vec![Level { width, height, ranges }];
        while levels.last().is_some_and(|l| l.width > 1 || l.height > 1) {
            let below = levels.last().expect("non-empty");
            let (width, height) = (below.width.div_ceil(2), below.height.div_ceil(2));
            let mut ranges = vec![EMPTY; width * height];
            for y in 0..below.height {
                for x in 0..below.width {
                    let [lo, hi] = below.ranges[y * below.width + x];
                    let range = &mut ranges[(y / 2) * width + x / 2];
                    range[0] = range[0].min(lo);
                    range[1] = range[1].max(hi);
                }
            }
            levels.push(Level { width, height, ranges });
        }
        Self { camera_from_world, intrinsics, levels }
    }

    /// The image rectangle of a node, widened by the margin.
    fn rectangle(&self, level: u8, x: u32, y: u32) -> [f64; 4] {
        let base = &self.levels[0];
        let size = 1u64 << level;
        let (x0, y0) = (x as u64 * size, y as u64 * size);
        let x1 = (x0 + size).min(base.width as u64);
        let y1 = (y0 + size).min(base.height as u64);
        [x0 as f64 - MARGIN_PIXELS, x1 as f64 + MARGIN_PIXELS, y0 as f64 - MARGIN_PIXELS, y1 as f64 + MARGIN_PIXELS]
    }

    /// The ray interval of a node, or None when the ray misses its rectangle or its depth range.
    fn enter(&self, ray: &ProjectedRay, level: u8, x: u32, y: u32, t0: f64, t1: f64) -> Option<Node> {
        let l = &self.levels[level as usize];
        let [lo, hi] = l.ranges[y as usize * l.width + x as usize];
        if lo > hi {
            return None;
        }
        let (t0, t1) = ray.clip(self.rectangle(level, x, y), t0, t1)?;
        let (z0, z1) = (ray.depth(t0), ray.depth(t1));
        let (near, far) = (z0.min(z1), z0.max(z1));
        if far < f64::from(lo) * (1.0 - DEPTH_SLACK) || near > f64::from(hi) * (1.0 + DEPTH_SLACK) {
            return None;
        }
        Some(Node { level, x, y, t0, t1 })
    }

    /// Visits the quads the ray `origin + t·direction`, `0 ≤ t ≤ t_max` (world space) may hit, in
    /// roughly increasing `t`. `hit(column, row)` returns the hit distance in that quad or +∞. With
    /// `first_only`, returns the first hit found; otherwise the nearest, skipping nodes entered
    /// beyond the nearest hit so far.
    pub fn traverse(
        &self,
        origin: DVec3,
        direction: DVec3,
        t_max: f64,
        first_only: bool,
        mut hit: impl FnMut(usize, usize) -> f32,
    ) -> Option<f32> {
        let top = self.levels.last().expect("at least one level");
        let [lo, hi] = top.ranges[0];
        if lo > hi {
            return None;
        }
        let ray = ProjectedRay {
            origin: self.intrinsics * self.camera_from_world.transform_point3(origin),
            step: self.intrinsics * self.camera_from_world.transform_vector3(direction),
        };
        // Only where the ray is at a depth some triangle has: in front of the camera, so that the
        // rectangle inequalities mean what they say, and t finite for unbounded rays.
        let (mut t0, mut t1) = (0.0, t_max);
        let near = f64::from(lo) * (1.0 - DEPTH_SLACK);
        let far = f64::from(hi) * (1.0 + DEPTH_SLACK);
        ProjectedRay::keep_nonnegative(ray.origin.z - near, ray.step.z, &mut t0, &mut t1);
        ProjectedRay::keep_nonnegative(far - ray.origin.z, -ray.step.z, &mut t0, &mut t1);
        if t0.is_nan() || t1.is_nan() || t0 > t1 {
            return None;
        }
        let root_level = (self.levels.len() - 1) as u8;
        let mut stack = [Node { level: 0, x: 0, y: 0, t0: 0.0, t1: 0.0 }; STACK];
        let mut depth = 0;
        if let Some(root) = self.enter(&ray, root_level, 0, 0, t0, t1) {
            stack[0] = root;
            depth = 1;
        }
        let mut nearest = f32::INFINITY;
        // Hit distances are f32 along an f32 direction; a node entered this much past the
        // nearest hit cannot hold a nearer one.
        let beyond = |t0: f64, nearest: f32| t0 > f64::from(nearest) * (1.0 + DEPTH_SLACK) + DEPTH_SLACK;
        while depth > 0 {
            depth -= 1;
            let node = stack[depth];
            if beyond(node.t0, nearest) {
                continue;
            }
            if node.level == 0 {
                let t = hit(node.x as usize, node.y as usize);
                if t < nearest {
                    nearest = t;
                    if first_only {
                        return Some(t);
                    }
                }
                continue;
            }
            let below = &self.levels[node.level as usize - 1];
            let mut children = [node; 4];
            let mut count = 0;
            for k in 0..4u32 {
                let (x, y) = (2 * node.x + (k & 1), 2 * node.y + (k >> 1));
                if (x as usize) < below.width
                    && (y as usize) < below.height
                    && let Some(child) = self.enter(&ray, node.level - 1, x, y, node.t0, node.t1)
                {
                    // Insertion by decreasing t0: the nearest ends on top of the stack.
                    let mut at = count;
                    while at > 0 && children[at - 1].t0 < child.t0 {
                        children[at] = children[at - 1];
                        at -= 1;
                    }
                    children[at] = child;
                    count += 1;
                }
            }
            stack[depth..depth + count].copy_from_slice(&children[..count]);
            depth += count;
        }
        nearest.is_finite().then_some(nearest)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fronto-parallel camera at the origin looking down +z with a 4×4-quad grid.
    fn pyramid(ranges: Vec<Range>) -> DepthPyramid {
        let intrinsics =
            DMat3::from_cols(DVec3::new(10.0, 0.0, 0.0), DVec3::new(0.0, 10.0, 0.0), DVec3::new(2.0, 2.0, 1.0));
        DepthPyramid::new(4, 4, ranges, DMat4::IDENTITY, intrinsics)
    }

    fn visited(pyramid: &DepthPyramid, origin: DVec3, direction: DVec3, t_max: f64) -> Vec<usize> {
        let mut quads = Vec::new();
        pyramid.traverse(origin, direction, t_max, false, |x, y| {
            quads.push(y * 4 + x);
            f32::INFINITY
        });
        quads.sort_unstable();
        quads
    }

    #[test]
    fn levels_halve_until_one_node_and_hold_the_range_of_their_quads() {
        let ranges: Vec<Range> = (0..16).map(|i| [1.0 + i as f32, 2.0 + i as f32]).collect();
        let p = pyramid(ranges);
        assert_eq!(p.levels.len(), 3);
        assert_eq!(p.levels[1].ranges[3], [11.0, 17.0], "quads 10, 11, 14, 15");
        assert_eq!(p.levels[2].ranges[0], [1.0, 17.0]);
    }

    #[test]
    fn a_ray_visits_only_quads_it_crosses_at_their_depth() {
        // Every quad at depth [5, 5]: a ray along the optical axis through quad (1, 1)'s column...
        let p = pyramid(vec![[5.0, 5.0]; 16]);
        let through = |u: f64, v: f64| DVec3::new((u - 2.0) / 10.0, (v - 2.0) / 10.0, 1.0);
        assert_eq!(visited(&p, DVec3::ZERO, through(1.5, 1.5), 10.0), vec![5]);
        // ...stopping short of the depth visits nothing,
        assert!(visited(&p, DVec3::ZERO, through(1.5, 1.5), 4.9).is_empty());
        // and a ray crossing the grid sideways at depth 5 visits the row it sweeps.
        let sideways = visited(&p, DVec3::new(-1.0, -0.05, 5.0), DVec3::X, 2.0);
        assert_eq!(sideways, vec![4, 5, 6, 7]);
    }

    #[test]
    fn empty_quads_are_never_visited() {
        let mut ranges = vec![EMPTY; 16];
        ranges[10] = [3.0, 4.0];
        let p = pyramid(ranges);
        let sideways = visited(&p, DVec3::new(-1.0, 0.05, 3.5), DVec3::X, 2.0);
        assert_eq!(sideways, vec![10]);
    }
}
