//! Static-background stacking, for renders of videos longer than one frame: the
//! static (non-dynamic) surface points of many frames are fused into one coloured world-space
//! point set, deduplicated on a voxel grid, and rendered into each novel frame to fill the holes
//! of that frame's own render: background hidden behind a moving object or outside the frame's
//! view in one frame is often seen in another.
//!
//! Points come from pixels with valid depth that are neither dynamic (mask non-zero, dilated by
//! `dynamic_margin_px`) nor on a depth edge (inverse depth off the line through its neighbours by
//! more than the mesh's discontinuity ratio allows, where reconstructions put "flying" points;
//! slanted planes pass). Without dynamic-object masks
//! every pixel counts as static. Each voxel keeps the mean position and colour of its points; the
//! voxel edge is `voxel_relative` × the median depth of the sequence's first frame, so the grid
//! follows the reconstruction's scale. A point renders as a square splat of its voxel's
//! projected size, nearest point winning.

use std::collections::HashMap;
use std::ops::Bound;

use glam::DVec3;
use image::{GrayImage, Luma, Rgb, RgbImage};
use serde::{Deserialize, Serialize};

use crate::config_file::{Checked, Validate, check_count, check_float};
use crate::io::sequence::Sequence;
use foundation::camera::PinholeCamera;
use foundation::depth::DepthMap;

/// Stacking settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StackingConfig {
    /// Voxel edge as a fraction of the first frame's median depth. Valid: finite, in (0, 1]
    /// (a voxel as large as the scene's depth already fuses it into a few blobs).
    pub voxel_relative: f64,
    /// Use every n-th frame (1: all). Valid: at least 1.
    pub frame_step: u32,
    /// Pixels this close to a dynamic-object pixel are not static. Valid: 0 to
    /// [`MAX_DYNAMIC_MARGIN_PX`].
    pub dynamic_margin_px: u32,
}

/// Widest dilation of the dynamic masks: the dilation costs (2 × margin + 1)² per dynamic
/// pixel, and 64 px already covers the motion blur and mask slop of any annotated video.
pub const MAX_DYNAMIC_MARGIN_PX: u32 = 64;

impl Validate for StackingConfig {
    fn validate(&self) -> Checked {
        check_float("voxel_relative", self.voxel_relative, (Bound::Excluded(0.0), Bound::Included(1.0)))?;
        check_count("frame_step", self.frame_step, 1, u64::MAX)?;
        check_count("dynamic_margin_px", self.dynamic_margin_px, 0, MAX_DYNAMIC_MARGIN_PX.into())
    }
}

impl Default for StackingConfig {
    fn default() -> Self {
        Self { voxel_relative: 0.004, frame_step: 1, dynamic_margin_px: 2 }
    }
}

/// The fused static points of a sequence.
#[derive(Debug, Clone)]
pub struct StaticBackground {
    points: Vec<DVec3>,
    colours: Vec<Rgb<u8>>,
    voxel: f64,
}

#[derive(Default)]
struct VoxelSum {
    position: DVec3,
    colour: [u32; 3],
    count: u32,
}

impl StaticBackground {
    /// Fuses the static points of `sequence`'s frames (every `frame_step`-th). Voxels are filled
    /// in frame order, so the result does not depend on the thread count.
    pub fn from_sequence(sequence: &Sequence, config: &StackingConfig, discontinuity_ratio: f64) -> Self {
        let voxel = config.voxel_relative * median_depth(&sequence.depth[0]).unwrap_or(1.0);
        let mut voxels: HashMap<[i64; 3], VoxelSum> = HashMap::new();
        let mut order: Vec<[i64; 3]> = Vec::new();
        for i in (0..sequence.len()).step_by(config.frame_step.max(1) as usize) {
            let depth = &sequence.depth[i];
            let camera = &sequence.cameras[i];
            let dynamic = sequence.dynamic_masks.as_ref().map(|m| dilate(&m[i], config.dynamic_margin_px));
            let frame = &sequence.frames[i];
            for p in 0..depth.width * depth.height {
                if dynamic.as_ref().is_some_and(|d| d[p]) || !static_surface(depth, p, discontinuity_ratio) {
                    continue;
                }
                let (x, y) = (p % depth.width, p / depth.width);
                let point = camera.unproject(x as f64, y as f64, f64::from(depth.values[p]));
                let key = (point / voxel).floor().as_i64vec3().to_array();
                let sum = voxels.entry(key).or_insert_with(|| {
                    order.push(key);
                    VoxelSum::default()
                });
                sum.position += point;
                let colour = frame.get_pixel(x as u32, y as u32).0;
                for (total, c) in sum.colour.iter_mut().zip(colour) {
                    *total += u32::from(c);
                }
                sum.count += 1;
            }
        }
        let mut points = Vec::with_capacity(order.len());
        let mut colours = Vec::with_capacity(order.len());
        for key in order {
            let sum = &voxels[&key];
            let n = sum.count;
            points.push(sum.position / f64::from(n));
            colours.push(Rgb(sum.colour.map(|c| ((c + n / 2) / n) as u8)));
        }
        Self { points, colours, voxel }
    }

    /// Number of fused points.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// Whether no static point was found.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The points rendered from `camera`: per pixel the nearest point's colour, if any.
    pub fn render(&self, camera: &PinholeCamera) -> Vec<Option<Rgb<u8>>> {
        let (w, h) = (camera.width as i64, camera.height as i64);
        let mut nearest = vec![f64::INFINITY; (w * h) as usize];
        let mut colour = vec![None; (w * h) as usize];
        let focal = camera.intrinsics.x_axis.x.max(camera.intrinsics.y_axis.y);
        let camera_from_world = camera.camera_from_world();
        for (point, c) in self.points.iter().zip(&self.colours) {
            let in_camera = camera_from_world.transform_point3(*point);
            let z = in_camera.z;
            if z <= 0.0 {
                continue;
            }
            let pixel = foundation::camera::pixel_of(&camera.intrinsics, in_camera);
            // Half the voxel's projected size, at least the pixel the point falls in.
            let reach = ((self.voxel * focal / z) * 0.5 - 0.5).ceil().max(0.0) as i64;
            let (cx, cy) = (pixel.x.round() as i64, pixel.y.round() as i64);
            for y in (cy - reach).max(0)..=(cy + reach).min(h - 1) {
                for x in (cx - reach).max(0)..=(cx + reach).min(w - 1) {
                    let i = (y * w + x) as usize;
                    if z < nearest[i] {
                        nearest[i] = z;
                        colour[i] = Some(*c);
                    }
                }
            }
        }
        colour
    }

    /// Fills the holes (255 in `holes`) of a render from `camera` with the stacked background;
    /// filled pixels are cleared in `holes`. Returns how many were filled.
    pub fn fill_holes(&self, image: &mut RgbImage, holes: &mut GrayImage, camera: &PinholeCamera) -> usize {
        let background = self.render(camera);
        let width = image.width();
        let mut filled = 0;
        for (i, colour) in background.into_iter().enumerate() {
            let (x, y) = (i as u32 % width, i as u32 / width);
            if let Some(colour) = colour
                && holes.get_pixel(x, y).0[0] != 0
            {
                image.put_pixel(x, y, colour);
                holes.put_pixel(x, y, Luma([0]));
                filled += 1;
            }
        }
        filled
    }
}

fn median_depth(depth: &DepthMap) -> Option<f64> {
    let mut valid: Vec<f32> = depth.values.iter().copied().filter(|d| d.is_finite() && *d > 0.0).collect();
    if valid.is_empty() {
        return None;
    }
    let middle = valid.len() / 2;
    let (_, median, _) = valid.select_nth_unstable_by(middle, f32::total_cmp);
    Some(f64::from(*median))
}

/// Whether pixel `p` lies on a smooth surface: valid depth, and along each image axis its inverse
/// depth agrees with the mean of its two neighbours' (inverse depth is affine in pixel coordinates
/// on a plane, so slanted floors pass at any angle) within `ratio − 1` relative; at the border,
/// the one neighbour's depth must be within `ratio`. Pixels on depth edges, where reconstructions
/// put "flying" points between foreground and background, fail.
fn static_surface(depth: &DepthMap, p: usize, ratio: f64) -> bool {
    let (w, h) = (depth.width, depth.height);
    let at = |x: usize, y: usize| -> Option<f64> {
        let d = *depth.values.get(y.checked_mul(w)? + x).filter(|_| x < w && y < h)?;
        (d.is_finite() && d > 0.0).then_some(f64::from(d))
    };
    let (x, y) = (p % w, p / w);
    let Some(d) = at(x, y) else { return false };
    let tolerance = ratio - 1.0;
    let axis = |before: Option<f64>, after: Option<f64>, exists: (bool, bool)| match (before, after) {
        (Some(a), Some(b)) => ((2.0 / d - 1.0 / a - 1.0 / b) * d).abs() <= 2.0 * tolerance,
        (Some(n), None) | (None, Some(n)) if !(exists.0 && exists.1) => d.max(n) / d.min(n) <= ratio,
        _ => false,
    };
    let horizontal = axis(x.checked_sub(1).and_then(|u| at(u, y)), at(x + 1, y), (x > 0, x + 1 < w));
    let vertical = axis(y.checked_sub(1).and_then(|v| at(x, v)), at(x, y + 1), (y > 0, y + 1 < h));
    horizontal && vertical
}

/// Non-zero pixels of `mask`, dilated by `radius` (square neighbourhood).
fn dilate(mask: &GrayImage, radius: u32) -> Vec<bool> {
    let (w, h) = (mask.width() as i64, mask.height() as i64);
    let r = i64::from(radius);
    let mut out = vec![false; (w * h) as usize];
    for (x, y, pixel) in mask.enumerate_pixels() {
        if pixel.0[0] == 0 {
            continue;
        }
        let (x, y) = (i64::from(x), i64::from(y));
        for v in (y - r).max(0)..=(y + r).min(h - 1) {
            for u in (x - r).max(0)..=(x + r).min(w - 1) {
                out[(v * w + u) as usize] = true;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slanted_planes_are_surface_and_steps_are_edges() {
        // A plane seen at a grazing angle: inverse depth affine in x, depth ratio per pixel ~1.3.
        let (w, h) = (8, 3);
        let plane =
            DepthMap { width: w, height: h, values: (0..w * h).map(|i| 1.0 / (0.9 - 0.1 * (i % w) as f32)).collect() };
        // Interior pixels pass; at the left/right border only the plain ratio test applies.
        assert!((0..w * h).filter(|p| p % w != 0 && p % w != w - 1).all(|p| static_surface(&plane, p, 1.05)));
        // A step from depth 1 to 2 between columns 3 and 4: those columns are edges, others not.
        let step =
            DepthMap { width: w, height: h, values: (0..w * h).map(|i| if i % w < 4 { 1.0 } else { 2.0 }).collect() };
        let row: Vec<bool> = (w..2 * w).map(|p| static_surface(&step, p, 1.05)).collect();
        assert_eq!(row, [true, true, true, false, false, true, true, true]);
    }
}
