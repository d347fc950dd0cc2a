//! Depth noise on dynamic objects, for training robustness: reconstructions of moving
//! objects are the least accurate part of a video's geometry, and at inference the conditioning
//! render shows the resulting smearing at object edges. Training pairs imitate it.
//!
//! For one frame and one novel camera, every co-visible dynamic-object pixel's surface point is
//! moved along the *novel* camera's ray through it by an offset δ, so the novel camera sees the
//! same picture, and the moved points are rendered back into the source camera (nearest pixel,
//! nearest point wins). Static pixels stay where they are. The conditioning frame is that
//! render; its mask is the set of pixels it covers. Offsets come from
//!
//! - **measured** depth error, when a second (better) depth source is given for the video:
//!   δ = second depth − reconstruction depth at the pixel (0 where either is invalid); or
//! - a **parametric** model: δ = σ · n, with σ = depth · (`relative_sigma` + `edge_relative_sigma`
//!   · exp(−distance to the nearest depth edge / `edge_width_px`)) and n a smooth Gaussian field
//!   (unit-variance values on a grid of `correlation_px` spacing, bilinearly interpolated), clamped
//!   to ±`max_sigmas` · σ. Depth edges are the discontinuities of the co-visibility mesh (depth
//!   ratio above `discontinuity_ratio` between 4-neighbours, or invalid depth).
//!
//! The field is seeded by (run seed, source id, clip start, trajectory index, frame), so pairs
//! are reproducible and trajectories of one clip get independent noise.

use std::path::{Path, PathBuf};

use glam::DVec2;
use image::{GrayImage, Rgb, RgbImage};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::config_file::{Checked, Validate, check_count, check_float, check_placeholders};
use crate::error::Result;
use crate::io::sequence::Sequence;
use foundation::camera::PinholeCamera;
use foundation::depth::DepthMap;

/// Parametric noise settings and the optional second depth source.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DepthNoiseConfig {
    /// Off by default: pairs are then exactly the noise-free ones.
    pub enabled: bool,
    /// σ away from depth edges, as a fraction of depth. Valid: finite, in [0, 1] (σ equal to
    /// the depth already throws points behind the camera).
    pub relative_sigma: f64,
    /// Extra σ at depth edges, as a fraction of depth, decaying with distance from the edge.
    /// Valid: finite, in [0, 1].
    pub edge_relative_sigma: f64,
    /// Decay length of the edge term, in pixels (0: no edge term). Valid: finite, ≥ 0.
    pub edge_width_px: f64,
    /// Grid spacing of the smooth noise field, in pixels (larger: smoother, blob-like smears).
    /// Valid: at least 1.
    pub correlation_px: u32,
    /// Offsets are clamped to ± this many σ. Valid: finite, in [0, [`MAX_SIGMAS`]].
    pub max_sigmas: f64,
    /// A second depth source per video, as a path template with `{dataset}`, `{video_id}` and
    /// `{name}` (the sequence folder's or video's name): a folder of `*.exr` maps or an
    /// `(N, H, W)` `.npy`, one map per frame, any resolution (resampled). Videos whose path does
    /// not exist use the parametric model. Valid: non-empty, no other `{placeholder}`.
    pub second_depth: Option<String>,
}

/// Widest clamp: a unit Gaussian exceeds 10 σ with probability ~1e-23, so a larger clamp
/// never binds and is a typo.
pub const MAX_SIGMAS: f64 = 10.0;

/// The placeholders of `second_depth`.
const SECOND_DEPTH_PLACEHOLDERS: [&str; 3] = ["dataset", "video_id", "name"];

impl Validate for DepthNoiseConfig {
    fn validate(&self) -> Checked {
        check_float("relative_sigma", self.relative_sigma, 0.0..=1.0)?;
        check_float("edge_relative_sigma", self.edge_relative_sigma, 0.0..=1.0)?;
        check_float("edge_width_px", self.edge_width_px, 0.0..)?;
        check_count("correlation_px", self.correlation_px, 1, u64::MAX)?;
        check_float("max_sigmas", self.max_sigmas, 0.0..=MAX_SIGMAS)?;
        if let Some(template) = &self.second_depth {
            check_placeholders("second_depth", template, &SECOND_DEPTH_PLACEHOLDERS)?;
        }
        Ok(())
    }
}

impl Default for DepthNoiseConfig {
    fn default() -> Self {
        Self {
            enabled: false,
            relative_sigma: 0.01,
            edge_relative_sigma: 0.04,
            edge_width_px: 3.0,
            correlation_px: 8,
            max_sigmas: 3.0,
            second_depth: None,
        }
    }
}

impl DepthNoiseConfig {
    /// The second-depth path of one video, if configured and present.
    pub fn second_depth_path(&self, dataset: &str, video_id: &str) -> Option<PathBuf> {
        let template = self.second_depth.as_ref()?;
        let name = video_id.rsplit('/').next().unwrap_or(video_id);
        let path = PathBuf::from(
            template.replace("{dataset}", dataset).replace("{video_id}", video_id).replace("{name}", name),
        );
        path.exists().then_some(path)
    }

    /// With depth noise on, reads `sequence`'s second depth for measured noise: from `explicit`
    /// (a path the user gave), else from the configured template's path for (`dataset`,
    /// `video_id`) if it exists. Nothing with depth noise off.
    pub fn load_second_depth(
        &self,
        sequence: &mut Sequence,
        explicit: Option<&Path>,
        dataset: &str,
        video_id: &str,
    ) -> Result<()> {
        if !self.enabled {
            return Ok(());
        }
        match explicit.map(Path::to_path_buf).or_else(|| self.second_depth_path(dataset, video_id)) {
            Some(path) => sequence.load_second_depth(&path),
            None => Ok(()),
        }
    }
}

/// The per-pixel offsets (along the novel ray, in depth units) of one frame: measured from a
/// second depth map, or drawn from the parametric model.
pub fn offsets(
    config: &DepthNoiseConfig,
    depth: &DepthMap,
    second_depth: Option<&DepthMap>,
    discontinuity_ratio: f64,
    rng_key: &NoiseKey,
) -> Vec<f64> {
    let valid = |d: f32| d.is_finite() && d > 0.0;
    if let Some(second) = second_depth {
        return depth
            .values
            .iter()
            .zip(&second.values)
            .map(|(&a, &b)| if valid(a) && valid(b) { f64::from(b) - f64::from(a) } else { 0.0 })
            .collect();
    }
    let distance = edge_distance(depth, discontinuity_ratio);
    let field = smooth_gaussian_field(depth.width, depth.height, config.correlation_px.max(1), &mut rng_key.rng());
    depth
        .values
        .iter()
        .zip(distance.iter().zip(&field))
        .map(|(&d, (&dist, &n))| {
            if !valid(d) {
                return 0.0;
            }
            let edge = if config.edge_width_px > 0.0 { (-dist / config.edge_width_px).exp() } else { 0.0 };
            let sigma = f64::from(d) * (config.relative_sigma + config.edge_relative_sigma * edge);
            (sigma * n).clamp(-config.max_sigmas * sigma, config.max_sigmas * sigma)
        })
        .collect()
}

/// The stable ids that seed one frame's noise field.
#[derive(Debug, Clone)]
pub struct NoiseKey<'a> {
    /// Run seed.
    pub seed: u64,
    /// Source video id.
    pub source_id: &'a str,
    /// First frame of the clip.
    pub clip_start: u32,
    /// Trajectory index within the clip.
    pub trajectory: u32,
    /// Frame index within the video.
    pub frame: u32,
}

impl NoiseKey<'_> {
    fn rng(&self) -> ChaCha8Rng {
        let mut hasher = blake3::Hasher::new();
        hasher.update(b"cognvs depth noise v1");
        hasher.update(&self.seed.to_le_bytes());
        hasher.update(&(self.source_id.len() as u64).to_le_bytes());
        hasher.update(self.source_id.as_bytes());
        for v in [self.clip_start, self.trajectory, self.frame] {
            hasher.update(&v.to_le_bytes());
        }
        ChaCha8Rng::from_seed(*hasher.finalize().as_bytes())
    }
}

/// Distance in pixels (chamfer 1/√2) from each pixel to the nearest depth-edge pixel.
fn edge_distance(depth: &DepthMap, ratio: f64) -> Vec<f64> {
    let (w, h) = (depth.width, depth.height);
    let d = |x: usize, y: usize| f64::from(depth.values[y * w + x]);
    let is_edge = |x: usize, y: usize| {
        let a = d(x, y);
        if !(a.is_finite() && a > 0.0) {
            return true;
        }
        let neighbours = [(x.wrapping_sub(1), y), (x + 1, y), (x, y.wrapping_sub(1)), (x, y + 1)];
        neighbours.into_iter().filter(|&(u, v)| u < w && v < h).any(|(u, v)| {
            let b = d(u, v);
            !(b.is_finite() && b > 0.0) || a.max(b) / a.min(b) > ratio
        })
    };
    let mut dist: Vec<f64> = (0..w * h).map(|i| if is_edge(i % w, i / w) { 0.0 } else { f64::INFINITY }).collect();
    let diagonal = std::f64::consts::SQRT_2;
    for y in 0..h {
        for x in 0..w {
            let mut best = dist[y * w + x];
            if x > 0 {
                best = best.min(dist[y * w + x - 1] + 1.0);
            }
            if y > 0 {
                best = best.min(dist[(y - 1) * w + x] + 1.0);
                if x > 0 {
                    best = best.min(dist[(y - 1) * w + x - 1] + diagonal);
                }
                if x + 1 < w {
                    best = best.min(dist[(y - 1) * w + x + 1] + diagonal);
                }
            }
            dist[y * w + x] = best;
        }
    }
    for y in (0..h).rev() {
        for x in (0..w).rev() {
            let mut best = dist[y * w + x];
            if x + 1 < w {
                best = best.min(dist[y * w + x + 1] + 1.0);
            }
            if y + 1 < h {
                best = best.min(dist[(y + 1) * w + x] + 1.0);
                if x + 1 < w {
                    best = best.min(dist[(y + 1) * w + x + 1] + diagonal);
                }
                if x > 0 {
                    best = best.min(dist[(y + 1) * w + x - 1] + diagonal);
                }
            }
            dist[y * w + x] = best;
        }
    }
    dist
}

/// Standard normal values on a grid of `spacing` pixels covering the image, bilinearly
/// interpolated at every pixel.
fn smooth_gaussian_field(width: usize, height: usize, spacing: u32, rng: &mut ChaCha8Rng) -> Vec<f64> {
    let spacing = spacing as usize;
    let (gw, gh) = (width.div_ceil(spacing) + 1, height.div_ceil(spacing) + 1);
    let mut normal = || {
        // Box–Muller; 1 − u keeps the logarithm finite.
        let (u1, u2): (f64, f64) = (1.0 - rng.random::<f64>(), rng.random());
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    };
    let grid: Vec<f64> = (0..gw * gh).map(|_| normal()).collect();
    let mut field = Vec::with_capacity(width * height);
    for y in 0..height {
        let gy = y as f64 / spacing as f64;
        let (y0, fy) = (gy.floor() as usize, gy.fract());
        for x in 0..width {
            let gx = x as f64 / spacing as f64;
            let (x0, fx) = (gx.floor() as usize, gx.fract());
            let g = |u: usize, v: usize| grid[v * gw + u];
            let top = g(x0, y0) * (1.0 - fx) + g(x0 + 1, y0) * fx;
            let bottom = g(x0, y0 + 1) * (1.0 - fx) + g(x0 + 1, y0 + 1) * fx;
            field.push(top * (1.0 - fy) + bottom * fy);
        }
    }
    field
}

/// A frame's conditioning under depth noise and its mask (true: covered).
#[derive(Debug, Clone)]
pub struct NoisyCondition {
    /// The render of the moved co-visible points into the source camera (uncovered pixels black).
    pub condition: RgbImage,
    /// Which pixels the render covers.
    pub mask: Vec<bool>,
}

/// One source frame as [`render_back`] needs it.
#[derive(Debug, Clone, Copy)]
pub struct SourceFrame<'a> {
    /// Its colours.
    pub frame: &'a RgbImage,
    /// Its depth.
    pub depth: &'a DepthMap,
    /// Its dynamic-object mask (non-zero: dynamic).
    pub dynamic: &'a GrayImage,
    /// Its camera.
    pub camera: &'a PinholeCamera,
}

/// Moves the co-visible dynamic points along the novel rays by `offsets` and renders all
/// co-visible points back into the source camera (see the module docs). `points` gives each
/// pixel's world-space surface point.
pub fn render_back(
    source: SourceFrame,
    points: impl Fn(usize) -> Option<glam::DVec3>,
    covisible: &[bool],
    offsets: &[f64],
    novel: &PinholeCamera,
) -> NoisyCondition {
    let SourceFrame { frame, depth, dynamic, camera: source } = source;
    let (w, h) = (depth.width, depth.height);
    let eye = novel.center();
    let mut nearest = vec![f64::INFINITY; w * h];
    let mut colour = vec![Rgb([0u8; 3]); w * h];
    for p in (0..w * h).filter(|&p| covisible[p]) {
        let moved = dynamic.as_raw()[p] != 0 && offsets[p] != 0.0;
        let (target, z) = if moved {
            let Some(point) = points(p) else { continue };
            let moved_point = point + (point - eye).normalize() * offsets[p];
            let Some((pixel, z)) = source.project(moved_point) else { continue };
            let DVec2 { x, y } = pixel.round();
            if !(x >= 0.0 && y >= 0.0 && (x as usize) < w && (y as usize) < h) {
                continue;
            }
            (y as usize * w + x as usize, z)
        } else {
            (p, f64::from(depth.values[p]))
        };
        if z < nearest[target] {
            nearest[target] = z;
            colour[target] = *frame.get_pixel((p % w) as u32, (p / w) as u32);
        }
    }
    let mut condition = RgbImage::new(w as u32, h as u32);
    for (i, c) in colour.iter().enumerate() {
        if nearest[i].is_finite() {
            condition.put_pixel((i % w) as u32, (i / w) as u32, *c);
        }
    }
    NoisyCondition { condition, mask: nearest.iter().map(|z| z.is_finite()).collect() }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn edge_distance_grows_away_from_a_step() {
        // Left half at depth 1, right half at depth 2: the edge is the two middle columns.
        let (w, h) = (12, 3);
        let values = (0..w * h).map(|i| if i % w < w / 2 { 1.0 } else { 2.0 }).collect();
        let dist = edge_distance(&DepthMap { width: w, height: h, values }, 1.05);
        let row: Vec<f64> = dist[w..2 * w].to_vec();
        assert_eq!(row, vec![5.0, 4.0, 3.0, 2.0, 1.0, 0.0, 0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
    }

    #[test]
    fn field_is_deterministic_per_key_and_differs_between_keys() {
        let key = |trajectory| NoiseKey { seed: 1, source_id: "v", clip_start: 0, trajectory, frame: 3 };
        let a = smooth_gaussian_field(20, 10, 4, &mut key(0).rng());
        let b = smooth_gaussian_field(20, 10, 4, &mut key(0).rng());
        let c = smooth_gaussian_field(20, 10, 4, &mut key(1).rng());
        assert_eq!(a, b);
        assert_ne!(a, c);
        // Grid nodes carry the drawn values; neighbours between them are interpolated (smooth).
        let max_step = a.chunks(20).flat_map(|row| row.windows(2).map(|p| (p[1] - p[0]).abs())).fold(0.0, f64::max);
        assert!(max_step < 3.0, "{max_step}");
    }
}
