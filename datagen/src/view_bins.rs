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

use std::sync::Mutex;

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
    /// The arrays, taken from [`POOL`] and given back on drop.
    buffers: BinBuffers,
}

/// A primitive's widened projected box (x0, y0, x1, y1) and nearest corner depth, read by the
/// rays of its bins (outside the box or ending before that depth: no exact test), and the
/// inclusive pixel range it is binned into ([`UNBINNED`] in `x0` when it is not).
#[derive(Clone, Copy)]
struct Footprint {
    bounds: [f32; 5],
    pixels: [u32; 4],
}

/// `Footprint::pixels[0]` of a primitive in no bin (outside the image, or tested by every ray).
const UNBINNED: u32 = u32::MAX;

/// The arrays of one view's bins. They are the size of the image and of the mesh, tens of MB at
/// 480×720: allocating them anew per view had the kernel clear ~40 MB of fresh pages per view
/// (~10 % of `datagen pairs`' CPU), so they are kept in a pool and reused.
#[derive(Default)]
struct BinBuffers {
    /// Per primitive id.
    footprints: Vec<Footprint>,
    /// Per pixel (row-major) its entries: `ids[starts[p]..starts[p + 1]]`.
    starts: Vec<u32>,
    ids: Vec<u32>,
    /// The next free slot of each pixel while the bins are filled.
    next: Vec<u32>,
    /// Primitives every ray is tested against (see [`NEAR_FRACTION`]).
    everywhere: Vec<u32>,
}

/// Buffers of dropped views; at most as many as views were ever alive at once (one per thread).
static POOL: Mutex<Vec<BinBuffers>> = Mutex::new(Vec::new());

impl Drop for ViewBins {
    fn drop(&mut self) {
        let buffers = std::mem::take(&mut self.buffers);
        POOL.lock().unwrap_or_else(std::sync::PoisonError::into_inner).push(buffers);
    }
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
        let mut buffers = POOL.lock().unwrap_or_else(std::sync::PoisonError::into_inner).pop().unwrap_or_default();
        let outside = Footprint { bounds: [0.0; 5], pixels: [UNBINNED; 4] };
        let everywhere = Footprint { bounds: [f32::NAN; 5], pixels: [UNBINNED; 4] };
        (0..count)
            .into_par_iter()
            .map(|id| {
                let Some(corners) = corners(id) else { return outside };
                let nearest = corners.iter().map(|c| c.z).fold(f64::INFINITY, f64::min);
                if nearest.is_nan() || nearest <= near {
                    return everywhere;
                }
                let pixels = corners.map(|c| DVec2::new(c.x, c.y));
                let lo = pixels.iter().fold(DVec2::INFINITY, |a, &p| a.min(p)) - MARGIN_PIXELS;
                let hi = pixels.iter().fold(DVec2::NEG_INFINITY, |a, &p| a.max(p)) + MARGIN_PIXELS;
                // Pixel k owns [k − 0.5, k + 0.5); truncation is floor once clamped at 0.
                if hi.x + 0.5 < 0.0 || hi.y + 0.5 < 0.0 {
                    return outside;
                }
                let (x0, y0) = ((lo.x + 0.5).max(0.0) as u32, (lo.y + 0.5).max(0.0) as u32);
                let x1 = ((hi.x + 0.5) as u32).min(width as u32 - 1);
                let y1 = ((hi.y + 0.5) as u32).min(height as u32 - 1);
                if x0 > x1 || y0 > y1 {
                    return outside;
                }
                let bounds = [lo.x as f32, lo.y as f32, hi.x as f32, hi.y as f32, nearest as f32];
                Footprint { bounds, pixels: [x0, x1, y0, y1] }
            })
            .collect_into_vec(&mut buffers.footprints);
        let BinBuffers { footprints, starts, ids, next, everywhere } = &mut buffers;
        starts.clear();
        starts.resize(width * height + 1, 0);
        everywhere.clear();
        for (id, footprint) in footprints.iter().enumerate() {
            let [x0, x1, y0, y1] = footprint.pixels;
            if x0 != UNBINNED {
                for y in y0..=y1 {
                    let row = y as usize * width + 1;
                    for count in &mut starts[row + x0 as usize..=row + x1 as usize] {
                        *count += 1;
                    }
                }
            } else if footprint.bounds[4].is_nan() {
                everywhere.push(id as u32);
            }
        }
        for p in 0..width * height {
            starts[p + 1] += starts[p];
        }
        ids.clear();
        ids.resize(starts[width * height] as usize, 0);
        next.clear();
        next.extend_from_slice(&starts[..width * height]);
        for (id, footprint) in footprints.iter().enumerate() {
            let [x0, x1, y0, y1] = footprint.pixels;
            if x0 == UNBINNED {
                continue;
            }
            for y in y0..=y1 {
                let row = y as usize * width;
                for slot in &mut next[row + x0 as usize..=row + x1 as usize] {
                    ids[*slot as usize] = id as u32;
                    *slot += 1;
                }
            }
        }
        Self { width, height, novel_from_world, intrinsics, buffers }
    }

    /// Where the rays towards `point` (world space) meet the image: pixel coordinates, the bin,
    /// and the point's depth; None outside the image or behind the camera.
    fn bin_of(&self, point: DVec3) -> Option<(DVec2, usize, f64)> {
        let in_novel = self.novel_from_world.transform_point3(point);
        let p = self.intrinsics * (in_novel / in_novel.z);
        self.bin_of_projected(DVec2::new(p.x, p.y), in_novel.z).map(|bin| (DVec2::new(p.x, p.y), bin, in_novel.z))
    }

    /// The bin of a point already projected: `pixel` = K · (p / p.z) and `depth` = p.z for the
    /// point p in the novel camera; None outside the image or behind the camera.
    fn bin_of_projected(&self, pixel: DVec2, depth: f64) -> Option<usize> {
        if depth.is_nan() || depth <= 0.0 {
            return None;
        }
        let (x, y) = (pixel.x + 0.5, pixel.y + 0.5);
        // Pixel k owns [k − 0.5, k + 0.5): truncation is floor for the non-negative values kept.
        let inside = x >= 0.0 && y >= 0.0 && x < self.width as f64 && y < self.height as f64;
        inside.then(|| y as usize * self.width + x as usize)
    }

    /// The binned primitives whose box holds `pixel` and that reach nearer than `limit`.
    fn candidates(&self, bin: usize, pixel: DVec2, limit: f64) -> impl Iterator<Item = u32> {
        let (x, y, limit) = (pixel.x as f32, pixel.y as f32, limit as f32);
        let BinBuffers { footprints, starts, ids, .. } = &self.buffers;
        let range = starts[bin] as usize..starts[bin + 1] as usize;
        ids[range].iter().copied().filter(move |&id| {
            let [x0, y0, x1, y1, nearest] = footprints[id as usize].bounds;
            nearest <= limit && x >= x0 && x <= x1 && y >= y0 && y <= y1
        })
    }

    /// Calls `test(id, binned)` for each primitive that may cross the segment from the camera's
    /// centre to `point`, until it returns true; whether it did. `binned` is false for the
    /// primitives tested by every ray. None when `point` is outside the image or behind the
    /// camera (not binned).
    pub fn any_towards(&self, point: DVec3, test: impl FnMut(u32, bool) -> bool) -> Option<bool> {
        let (pixel, _, depth) = self.bin_of(point)?;
        self.any_towards_projected(pixel, depth, test)
    }

    /// [`Self::any_towards`] for a point already projected into the novel camera: `pixel` =
    /// K · (p / p.z) and `depth` = p.z, p the point in camera coordinates (`novel_from_world`
    /// applied), computed exactly so, which gives the same bin and answers.
    pub fn any_towards_projected(
        &self,
        pixel: DVec2,
        depth: f64,
        mut test: impl FnMut(u32, bool) -> bool,
    ) -> Option<bool> {
        let bin = self.bin_of_projected(pixel, depth)?;
        let limit = depth * (1.0 + DEPTH_SLACK);
        let binned = self.candidates(bin, pixel, limit).any(|id| test(id, true));
        Some(binned || self.buffers.everywhere.iter().any(|&id| test(id, false)))
    }

    /// The nearest of `hit(id)` (a ray distance, +∞ for a miss) over the primitives that may
    /// cross the ray through `point`. None when `point` is not binned (see [`Self::any_towards`]).
    pub fn nearest_towards(&self, point: DVec3, hit: impl Fn(u32) -> f32) -> Option<f32> {
        let (pixel, bin, _) = self.bin_of(point)?;
        let candidates = self.candidates(bin, pixel, f64::INFINITY).chain(self.buffers.everywhere.iter().copied());
        Some(candidates.map(hit).fold(f32::INFINITY, f32::min))
    }

    /// Number of bin entries, and of primitives tested by every ray.
    pub fn sizes(&self) -> (usize, usize) {
        (self.buffers.ids.len(), self.buffers.everywhere.len())
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
