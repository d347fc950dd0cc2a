//! Triangle bins over a novel camera's image: the structure for the two per-view batches of
//! DESIGN §4, the co-visibility segments from the novel camera to every source point and the
//! render rays through every novel pixel. All those rays leave the novel camera's centre, so a
//! triangle can only be hit by the rays whose image point falls inside the triangle's projection.
//! Binning each triangle into the novel pixels its projected bounding box overlaps (a counting
//! sort, linear in the triangles) leaves each ray a handful of candidates, nearly all culled by
//! comparing depths before the exact f32 triangle test runs.
//!
//! Exactness: boxes are widened by [`MARGIN_PIXELS`], depths by [`DEPTH_SLACK`], and triangles
//! reaching close to or behind the camera's image plane (whose projection is unbounded or
//! numerically unstable) are tested by every ray, so answers equal a brute-force loop over every
//! triangle. Sub-pixel ray points are binned by their nearest pixel centre.

use glam::{DMat3, DMat4, DVec2, DVec3};
use rayon::prelude::*;

/// Widening of every triangle's projected box. f32 corners and rays place a hit's projection
/// within ~1e-3 px of the exact one for triangles beyond the near limit; this leaves ×50.
pub const MARGIN_PIXELS: f64 = 0.05;

/// Relative widening of depth comparisons, far above f32 ray/triangle round-off (~1e-6).
pub const DEPTH_SLACK: f64 = 1e-4;

/// Primitives with a corner nearer the camera than this fraction of the nearest surface depth are
/// not binned but tested by every ray: close to the image plane, projection amplifies f32
/// round-off beyond the margin.
pub const NEAR_FRACTION: f64 = 0.1;

/// The bins of one novel view.
pub struct ViewBins {
    width: usize,
    height: usize,
    novel_from_world: DMat4,
    intrinsics: DMat3,
    /// Per pixel (row-major) its entries: `ids[starts[p]..starts[p + 1]]`.
    starts: Vec<u32>,
    ids: Vec<u32>,
    /// Per primitive id: its widened projected box (x0, y0, x1, y1) and nearest corner depth;
    /// rays outside the box or ending before that depth skip the exact test.
    boxes: Vec<[f32; 5]>,
    /// Triangles every ray is tested against (see [`NEAR_FRACTION`]).
    everywhere: Vec<u32>,
}

/// A binned primitive's pixel range (inclusive), widened box and nearest depth, or the
/// near-plane case.
enum Footprint {
    Pixels { x0: u32, x1: u32, y0: u32, y1: u32, bounds: [f32; 5] },
    Everywhere,
    Outside,
}

impl ViewBins {
    /// Bins primitives `0..count` for a camera at `novel_from_world` with intrinsics K and image
    /// size. `corners(id)` gives the corners of a primitive (a triangle or a group of them) as
    /// (pixel x, pixel y, depth) in the novel camera, None for no primitive with that id;
    /// `nearest_surface`, the smallest depth of the scene, scales the near limit.
    pub fn new<const N: usize>(
        count: u32,
        corners: impl Fn(u32) -> Option<[DVec3; N]> + Sync,
        novel_from_world: DMat4,
        intrinsics: DMat3,
        (width, height): (usize, usize),
        nearest_surface: f64,
    ) -> Self {
        let near = nearest_surface * NEAR_FRACTION;
        let footprints: Vec<Footprint> = (0..count)
            .into_par_iter()
            .map(|id| {
                let Some(corners) = corners(id) else { return Footprint::Outside };
                let nearest = corners.iter().map(|c| c.z).fold(f64::INFINITY, f64::min);
                if nearest.is_nan() || nearest <= near {
                    return Footprint::Everywhere;
                }
                let pixels = corners.map(|c| DVec2::new(c.x, c.y));
                let lo = pixels.iter().fold(DVec2::INFINITY, |a, &p| a.min(p)) - MARGIN_PIXELS;
                let hi = pixels.iter().fold(DVec2::NEG_INFINITY, |a, &p| a.max(p)) + MARGIN_PIXELS;
                // Pixel k owns [k − 0.5, k + 0.5); truncation is floor once clamped at 0.
                if hi.x + 0.5 < 0.0 || hi.y + 0.5 < 0.0 {
                    return Footprint::Outside;
                }
                let (x0, y0) = ((lo.x + 0.5).max(0.0) as u32, (lo.y + 0.5).max(0.0) as u32);
                let x1 = ((hi.x + 0.5) as u32).min(width as u32 - 1);
                let y1 = ((hi.y + 0.5) as u32).min(height as u32 - 1);
                if x0 > x1 || y0 > y1 {
                    return Footprint::Outside;
                }
                let bounds = [lo.x as f32, lo.y as f32, hi.x as f32, hi.y as f32, nearest as f32];
                Footprint::Pixels { x0, x1, y0, y1, bounds }
            })
            .collect();
        let mut starts = vec![0u32; width * height + 1];
        let mut everywhere = Vec::new();
        for (id, footprint) in footprints.iter().enumerate() {
            match *footprint {
                Footprint::Pixels { x0, x1, y0, y1, .. } => {
                    for y in y0..=y1 {
                        for x in x0..=x1 {
                            starts[y as usize * width + x as usize + 1] += 1;
                        }
                    }
                }
                Footprint::Everywhere => everywhere.push(id as u32),
                Footprint::Outside => {}
            }
        }
        for p in 0..width * height {
            starts[p + 1] += starts[p];
        }
        let mut ids = vec![0u32; starts[width * height] as usize];
        let mut boxes = vec![[0f32; 5]; count as usize];
        let mut next: Vec<u32> = starts[..width * height].to_vec();
        for (id, footprint) in footprints.iter().enumerate() {
            if let Footprint::Pixels { x0, x1, y0, y1, bounds } = *footprint {
                boxes[id] = bounds;
                for y in y0..=y1 {
                    for x in x0..=x1 {
                        let slot = &mut next[y as usize * width + x as usize];
                        ids[*slot as usize] = id as u32;
                        *slot += 1;
                    }
                }
            }
        }
        Self { width, height, novel_from_world, intrinsics, starts, ids, boxes, everywhere }
    }

    /// Where the rays towards `point` (world space) meet the image: pixel coordinates, the bin,
    /// and the point's depth; None outside the image or behind the camera.
    fn bin_of(&self, point: DVec3) -> Option<(DVec2, usize, f64)> {
        let in_novel = self.novel_from_world.transform_point3(point);
        if in_novel.z.is_nan() || in_novel.z <= 0.0 {
            return None;
        }
        let p = self.intrinsics * (in_novel / in_novel.z);
        let (x, y) = (p.x + 0.5, p.y + 0.5);
        // Pixel k owns [k − 0.5, k + 0.5): truncation is floor for the non-negative values kept.
        let inside = x >= 0.0 && y >= 0.0 && x < self.width as f64 && y < self.height as f64;
        inside.then(|| (DVec2::new(p.x, p.y), y as usize * self.width + x as usize, in_novel.z))
    }

    /// The binned primitives whose box holds `pixel` and that reach nearer than `limit`.
    fn candidates(&self, bin: usize, pixel: DVec2, limit: f64) -> impl Iterator<Item = u32> {
        let (x, y, limit) = (pixel.x as f32, pixel.y as f32, limit as f32);
        let range = self.starts[bin] as usize..self.starts[bin + 1] as usize;
        self.ids[range].iter().copied().filter(move |&id| {
            let [x0, y0, x1, y1, nearest] = self.boxes[id as usize];
            nearest <= limit && x >= x0 && x <= x1 && y >= y0 && y <= y1
        })
    }

    /// Calls `test(id, binned)` for each primitive that may cross the segment from the camera's
    /// centre to `point`, until it returns true; whether it did. `binned` is false for the
    /// primitives tested by every ray. None when `point` is outside the image or behind the
    /// camera (not binned).
    pub fn any_towards(&self, point: DVec3, mut test: impl FnMut(u32, bool) -> bool) -> Option<bool> {
        let (pixel, bin, depth) = self.bin_of(point)?;
        let limit = depth * (1.0 + DEPTH_SLACK);
        let binned = self.candidates(bin, pixel, limit).any(|id| test(id, true));
        Some(binned || self.everywhere.iter().any(|&id| test(id, false)))
    }

    /// The nearest of `hit(id)` (a ray distance, +∞ for a miss) over the primitives that may
    /// cross the ray through `point`. None when `point` is not binned (see [`Self::any_towards`]).
    pub fn nearest_towards(&self, point: DVec3, hit: impl Fn(u32) -> f32) -> Option<f32> {
        let (pixel, bin, _) = self.bin_of(point)?;
        let candidates = self.candidates(bin, pixel, f64::INFINITY).chain(self.everywhere.iter().copied());
        Some(candidates.map(hit).fold(f32::INFINITY, f32::min))
    }

    /// Number of bin entries, and of primitives tested by every ray.
    pub fn sizes(&self) -> (usize, usize) {
        (self.ids.len(), self.everywhere.len())
    }
}

/// Whether the line through `a` and `b` (pixel coordinates) has `point` farther than
/// `margins` × [`MARGIN_PIXELS`] on one side and `other` on the other side or on the line. A
/// binned triangle with edge a–b and third corner `other` then cannot be hit by a ray through the
/// image point `point` (the margin argument of the module documentation, which makes the bins'
/// boxes exact, holds for any separating line).
pub fn line_separates(a: DVec2, b: DVec2, point: DVec2, other: DVec2, margins: f64) -> bool {
    let edge = b - a;
    let (point_side, other_side) = (edge.perp_dot(point - a), edge.perp_dot(other - a));
    // |edge|₁ ≥ |edge|₂: a conservative distance bound without a square root.
    let margin = margins * MARGIN_PIXELS * (edge.x.abs() + edge.y.abs());
    (point_side > margin && other_side <= 0.0) || (point_side < -margin && other_side >= 0.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_line_separates_only_beyond_the_margin_and_with_the_triangle_on_the_other_side() {
        let (a, b) = (DVec2::new(0.0, 0.0), DVec2::new(1.0, 1.0));
        let (left, right) = (DVec2::new(0.0, 1.0), DVec2::new(1.0, 0.0));
        assert!(line_separates(a, b, left, right, 1.0));
        assert!(line_separates(a, b, right, left, 1.0));
        // Third corner on the line: the triangle is degenerate but still on one side.
        assert!(line_separates(a, b, left, DVec2::new(2.0, 2.0), 1.0));
        // Both on the same side: no separation.
        assert!(!line_separates(a, b, left, DVec2::new(0.2, 0.9), 1.0));
        // Within the margin of the line (0.05 px; the bound uses |edge|₁ = 2, so ≈ 0.07 px).
        let close = DVec2::new(0.5, 0.5) + DVec2::new(-1.0, 1.0).normalize() * 0.06;
        assert!(!line_separates(a, b, close, right, 1.0));
        let far = DVec2::new(0.5, 0.5) + DVec2::new(-1.0, 1.0).normalize() * 0.08;
        assert!(line_separates(a, b, far, right, 1.0));
        // A zero-length edge separates nothing.
        assert!(!line_separates(a, a, left, right, 1.0));
    }
}
