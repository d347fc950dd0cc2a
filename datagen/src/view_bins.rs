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
        let (x, y) = ((p.x + 0.5).floor(), (p.y + 0.5).floor());
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

    /// Calls `test(id)` for each primitive that may cross the segment from the camera's centre
    /// to `point`, until it returns true; whether it did. None when `point` is outside the image
    /// or behind the camera (not binned).
    pub fn any_towards(&self, point: DVec3, test: impl FnMut(u32) -> bool) -> Option<bool> {
        let (pixel, bin, depth) = self.bin_of(point)?;
        let limit = depth * (1.0 + DEPTH_SLACK);
        Some(self.candidates(bin, pixel, limit).chain(self.everywhere.iter().copied()).any(test))
    }

    /// The nearest of `hit(id)` (a ray distance, +∞ for a miss) over the primitives that may
    /// cross the ray through `point`. None when `point` is not binned (see [`Self::any_towards`]).
    pub fn nearest_towards(&self, point: DVec3, hit: impl FnMut(u32) -> f32) -> Option<f32> {
        let (pixel, bin, _) = self.bin_of(point)?;
        let candidates = self.candidates(bin, pixel, f64::INFINITY).chain(self.everywhere.iter().copied());
        Some(candidates.map(hit).fold(f32::INFINITY, f32::min))
    }

    /// Number of bin entries, and of primitives tested by every ray.
    pub fn sizes(&self) -> (usize, usize) {
        (self.ids.len(), self.everywhere.len())
    }
}
