//! Novel camera paths (DESIGN §1, §4). The pivot distance R is the depth at the optical-centre
//! pixel of the clip's first frame (× a scale). Frame t's novel camera is the source camera of
//! frame t orbited about the point at distance R on *its own* optical axis by azimuth φ_t and
//! elevation θ_t, moved radially by Δr_t·R, and looking at that point: the source motion is kept
//! and the offset is smooth. φ, θ, Δr each have four control values (start and end uniform in the
//! configured range, two intermediate values between them) joined by a natural cubic spline (C2).
//!
//! Orientation: in source-camera coordinates (x right, y down, z forward) the novel camera is
//! rotated by `R_y(φ) · R_x(−θ)`, so positive elevation raises the camera and positive azimuth
//! moves it towards −x.
//!
//! Sampling is deterministic per (seed, source id, clip start, trajectory index). A candidate
//! whose camera, on any frame, reaches its position only by crossing the reconstructed surface
//! (under the floor, inside an object) is rejected and redrawn from the next attempt's seed.

use std::path::Path;

use glam::{DMat3, DMat4, DVec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::camera::{PinholeCamera, mat4_from_row_major};
use crate::depth_exr::DepthMap;
use crate::error::{Error, Result};

/// Ranges of the spherical offsets.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrajectoryConfig {
    /// Azimuth range ± this many degrees.
    pub azimuth_deg: f64,
    /// Elevation range ± this many degrees.
    pub elevation_deg: f64,
    /// Radial offset range ± this fraction of R.
    pub radius_frac: f64,
    /// R = this × the depth at the first frame's optical centre.
    pub pivot_scale: f64,
    /// Candidates drawn before giving up on rejection (the last one is then kept).
    pub max_attempts: u32,
}

impl Default for TrajectoryConfig {
    fn default() -> Self {
        Self::paper()
    }
}

impl TrajectoryConfig {
    /// The paper's ranges (CogNVS §3): elevation ±15°, azimuth ±30°, radius ±15 %.
    pub fn paper() -> Self {
        Self { azimuth_deg: 30.0, elevation_deg: 15.0, radius_frac: 0.15, pivot_scale: 1.0, max_attempts: 16 }
    }

    /// The public cog-nvs code's ranges: elevation ±10°, azimuth ±15°, radius ±10 %.
    pub fn public_code() -> Self {
        Self { azimuth_deg: 15.0, elevation_deg: 10.0, radius_frac: 0.10, ..Self::paper() }
    }
}

/// A sampled path with its parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct SampledTrajectory {
    /// Azimuth control values (degrees).
    pub azimuth_deg: [f64; 4],
    /// Elevation control values (degrees).
    pub elevation_deg: [f64; 4],
    /// Radial control values (fractions of R).
    pub radius_frac: [f64; 4],
    /// R.
    pub pivot_distance: f64,
    /// Per-frame novel camera poses.
    pub world_from_camera: Vec<DMat4>,
    /// Candidates rejected before this one.
    pub rejected_samples: u32,
}

/// Half-size of the window around the optical centre whose median valid depth gives R.
const PIVOT_WINDOW: i64 = 2;

/// R: the median valid depth in a small window around the first frame's principal point (the
/// whole frame's median if that window has none), × `scale`.
pub fn pivot_distance(depth: &DepthMap, camera: &PinholeCamera, scale: f64) -> f64 {
    let (cx, cy) = (camera.intrinsics.z_axis.x.round() as i64, camera.intrinsics.z_axis.y.round() as i64);
    let valid = |d: f32| d.is_finite() && d > 0.0;
    let mut window: Vec<f32> = Vec::new();
    for v in cy - PIVOT_WINDOW..=cy + PIVOT_WINDOW {
        for u in cx - PIVOT_WINDOW..=cx + PIVOT_WINDOW {
            if u >= 0 && v >= 0 && (u as usize) < depth.width && (v as usize) < depth.height {
                let d = depth.values[v as usize * depth.width + u as usize];
                if valid(d) {
                    window.push(d);
                }
            }
        }
    }
    if window.is_empty() {
        window = depth.values.iter().copied().filter(|&d| valid(d)).collect();
    }
    window.sort_by(f32::total_cmp);
    scale * f64::from(window.get(window.len() / 2).copied().unwrap_or(1.0))
}

/// The novel pose for one frame: `source` orbited about the point at `pivot` on its optical axis.
pub fn orbit(world_from_source: &DMat4, pivot: f64, azimuth_deg: f64, elevation_deg: f64, radius_frac: f64) -> DMat4 {
    let rotation =
        DMat3::from_rotation_y(azimuth_deg.to_radians()) * DMat3::from_rotation_x(-elevation_deg.to_radians());
    let direction = rotation * DVec3::Z;
    let center = DVec3::new(0.0, 0.0, pivot) - pivot * (1.0 + radius_frac) * direction;
    *world_from_source
        * DMat4::from_cols(
            rotation.x_axis.extend(0.0),
            rotation.y_axis.extend(0.0),
            rotation.z_axis.extend(0.0),
            center.extend(1.0),
        )
}

/// Natural cubic spline through four values at t = 0, 1/3, 2/3, 1, evaluated at `t` ∈ [0, 1].
pub fn natural_cubic(values: &[f64; 4], t: f64) -> f64 {
    let h = 1.0 / 3.0;
    let a = 6.0 / (h * h) * (values[0] - 2.0 * values[1] + values[2]);
    let b = 6.0 / (h * h) * (values[1] - 2.0 * values[2] + values[3]);
    let m = [0.0, (4.0 * a - b) / 15.0, (4.0 * b - a) / 15.0, 0.0];
    let t = t.clamp(0.0, 1.0);
    let i = ((t / h) as usize).min(2);
    let (x0, x1) = (i as f64 * h, (i + 1) as f64 * h);
    m[i] * (x1 - t).powi(3) / (6.0 * h)
        + m[i + 1] * (t - x0).powi(3) / (6.0 * h)
        + (values[i] / h - m[i] * h / 6.0) * (x1 - t)
        + (values[i + 1] / h - m[i + 1] * h / 6.0) * (t - x0)
}

/// The RNG of one candidate, from the run seed and stable ids only.
fn candidate_rng(seed: u64, source_id: &str, clip_start: u32, index: u32, attempt: u32) -> ChaCha8Rng {
    let mut hasher = blake3::Hasher::new();
    hasher.update(b"cognvs trajectory v1");
    hasher.update(&seed.to_le_bytes());
    hasher.update(&(source_id.len() as u64).to_le_bytes());
    hasher.update(source_id.as_bytes());
    hasher.update(&clip_start.to_le_bytes());
    hasher.update(&index.to_le_bytes());
    hasher.update(&attempt.to_le_bytes());
    ChaCha8Rng::from_seed(*hasher.finalize().as_bytes())
}

fn controls(rng: &mut ChaCha8Rng, range: f64) -> [f64; 4] {
    let mut draw = || if range > 0.0 { rng.random_range(-range..=range) } else { 0.0 };
    let (start, end) = (draw(), draw());
    let (mut u1, mut u2) = (rng.random::<f64>(), rng.random::<f64>());
    if u1 > u2 {
        std::mem::swap(&mut u1, &mut u2);
    }
    [start, start + (end - start) * u1, start + (end - start) * u2, end]
}

/// Per-frame poses of control values over `cameras`.
pub fn poses_from_controls(
    cameras: &[PinholeCamera],
    pivot: f64,
    azimuth: &[f64; 4],
    elevation: &[f64; 4],
    radius: &[f64; 4],
) -> Vec<DMat4> {
    let last = cameras.len().saturating_sub(1).max(1) as f64;
    cameras
        .iter()
        .enumerate()
        .map(|(i, camera)| {
            let t = i as f64 / last;
            orbit(
                &camera.world_from_camera,
                pivot,
                natural_cubic(azimuth, t),
                natural_cubic(elevation, t),
                natural_cubic(radius, t),
            )
        })
        .collect()
}

/// Points sampled along a camera path segment by [`crosses_depth_surface`].
const CROSSING_SAMPLES: usize = 256;

/// Whether the segment from `from` to `to` passes behind the surface seen in `depth` by
/// `camera` (some point of it projects inside the image with a z-depth beyond the depth there,
/// plus a 1 % margin): a camera that gets there has gone under the floor, into an object or into
/// space no view observed. A cheap height-field test that needs no mesh.
pub fn crosses_depth_surface(depth: &DepthMap, camera: &PinholeCamera, from: DVec3, to: DVec3) -> bool {
    (1..=CROSSING_SAMPLES).any(|k| {
        let point = from.lerp(to, k as f64 / CROSSING_SAMPLES as f64);
        let Some((pixel, z)) = camera.project(point) else { return false };
        if !camera.contains(pixel) {
            return false;
        }
        let (u, v) = (pixel.x.round() as usize, pixel.y.round() as usize);
        let surface = depth.values[v.min(depth.height - 1) * depth.width + u.min(depth.width - 1)];
        surface.is_finite() && surface > 0.0 && z > f64::from(surface) * 1.01
    })
}

/// Says whether, on frame `i`, the straight path between two camera centres crosses the surface.
pub type Crossing<'a> = &'a (dyn Fn(usize, DVec3, DVec3) -> bool + Sync);

/// Samples trajectory `index` of the clip starting at `clip_start` (see module docs).
#[allow(clippy::too_many_arguments)]
pub fn sample_trajectory(
    cameras: &[PinholeCamera],
    first_depth: &DepthMap,
    config: &TrajectoryConfig,
    seed: u64,
    source_id: &str,
    clip_start: u32,
    index: u32,
    crosses: Option<Crossing>,
) -> SampledTrajectory {
    let pivot = pivot_distance(first_depth, &cameras[0], config.pivot_scale);
    let attempts = config.max_attempts.max(1);
    let mut rejected = 0;
    loop {
        let mut rng = candidate_rng(seed, source_id, clip_start, index, rejected);
        let azimuth = controls(&mut rng, config.azimuth_deg);
        let elevation = controls(&mut rng, config.elevation_deg);
        let radius = controls(&mut rng, config.radius_frac);
        let poses = poses_from_controls(cameras, pivot, &azimuth, &elevation, &radius);
        let crossing = crosses.is_some_and(|crosses| {
            poses
                .iter()
                .zip(cameras)
                .enumerate()
                .any(|(i, (pose, camera))| crosses(i, camera.center(), pose.w_axis.truncate()))
        });
        if !crossing || rejected + 1 >= attempts {
            return SampledTrajectory {
                azimuth_deg: azimuth,
                elevation_deg: elevation,
                radius_frac: radius,
                pivot_distance: pivot,
                world_from_camera: poses,
                rejected_samples: rejected,
            };
        }
        rejected += 1;
    }
}

#[derive(Deserialize)]
#[serde(untagged)]
enum JsonPoses {
    Wrapped { world_from_camera: Vec<serde_json::Value> },
    Bare(Vec<serde_json::Value>),
}

fn json_matrix(value: &serde_json::Value) -> Option<Vec<f64>> {
    let flat: Vec<f64> = match value {
        serde_json::Value::Array(items) if items.iter().all(|i| i.is_array()) => items
            .iter()
            .flat_map(|row| row.as_array().into_iter().flatten().map(|v| v.as_f64()))
            .collect::<Option<_>>()?,
        serde_json::Value::Array(items) => items.iter().map(|v| v.as_f64()).collect::<Option<_>>()?,
        _ => return None,
    };
    (flat.len() == 16).then_some(flat)
}

/// Reads an explicit trajectory for a sequence of `frames` frames: `.npy` (N,4,4)
/// `world_from_camera`, `.json` (a list of N 4×4 matrices, nested or row-major flat, or
/// `{"world_from_camera": [...]}`), or the public `trajs/*.txt` format (three lines: azimuth
/// degrees, elevation degrees, radius fractions; resampled linearly to N frames and applied with
/// the orbit above).
pub fn read_trajectory_file(
    path: &Path,
    frames: usize,
    cameras: &[PinholeCamera],
    first_depth: &DepthMap,
) -> Result<Vec<DMat4>> {
    let extension = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
    let wrong_count = |found: usize| {
        Error::invalid(path, "world_from_camera", format!("{found} poses for a sequence of {frames} frames"))
    };
    let poses: Vec<DMat4> = match extension.as_str() {
        "npy" => {
            let array = crate::npy::read_npy_f64(path)?;
            array.expect_shape(path, "world_from_camera", &[None, Some(4), Some(4)])?;
            if array.shape[0] != frames {
                return Err(wrong_count(array.shape[0]));
            }
            array.data.chunks_exact(16).map(mat4_from_row_major).collect()
        }
        "json" => {
            let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
            let parsed: JsonPoses = serde_json::from_str(&text)
                .map_err(|e| Error::invalid(path, "world_from_camera", format!("invalid JSON: {e}")))?;
            let list = match parsed {
                JsonPoses::Wrapped { world_from_camera } => world_from_camera,
                JsonPoses::Bare(list) => list,
            };
            if list.len() != frames {
                return Err(wrong_count(list.len()));
            }
            list.iter()
                .enumerate()
                .map(|(i, m)| {
                    json_matrix(m).map(|v| mat4_from_row_major(&v)).ok_or_else(|| {
                        Error::invalid(
                            path,
                            format!("world_from_camera[{i}]"),
                            "expected a 4×4 matrix (nested rows or 16 values)",
                        )
                    })
                })
                .collect::<Result<_>>()?
        }
        "txt" => {
            let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
            let lines: Vec<Vec<f64>> = text
                .lines()
                .filter(|l| !l.trim().is_empty())
                .enumerate()
                .map(|(i, line)| {
                    line.split(|c: char| c.is_whitespace() || c == ',')
                        .filter(|s| !s.is_empty())
                        .map(|s| {
                            s.parse::<f64>().map_err(|_| {
                                Error::invalid(path, format!("line {}", i + 1), format!("`{s}` is not a number"))
                            })
                        })
                        .collect()
                })
                .collect::<Result<_>>()?;
            let names = ["azimuth", "elevation", "radius"];
            if lines.len() != 3 {
                return Err(Error::invalid(
                    path,
                    "lines",
                    format!("expected 3 lines (azimuth, elevation, radius), found {}", lines.len()),
                ));
            }
            if let Some(i) = lines.iter().position(Vec::is_empty) {
                return Err(Error::invalid(path, names[i], "no values"));
            }
            let pivot = pivot_distance(first_depth, &cameras[0], 1.0);
            let at = |values: &[f64], i: usize| {
                if values.len() == 1 || frames <= 1 {
                    return values[0];
                }
                let x = i as f64 / (frames - 1) as f64 * (values.len() - 1) as f64;
                let k = (x.floor() as usize).min(values.len() - 2);
                values[k] + (values[k + 1] - values[k]) * (x - k as f64)
            };
            (0..frames)
                .map(|i| {
                    orbit(&cameras[i].world_from_camera, pivot, at(&lines[0], i), at(&lines[1], i), at(&lines[2], i))
                })
                .collect()
        }
        other => return Err(Error::invalid(path, "extension", format!("`.{other}`: expected .npy, .json or .txt"))),
    };
    for (i, pose) in poses.iter().enumerate() {
        let rotation = DMat3::from_mat4(*pose);
        let rigid = (rotation.transpose() * rotation).abs_diff_eq(DMat3::IDENTITY, 1e-3)
            && (rotation.determinant() - 1.0).abs() < 1e-3;
        if !pose.is_finite() || !rigid {
            return Err(Error::invalid(path, format!("world_from_camera[{i}]"), "not a finite rigid transform"));
        }
    }
    Ok(poses)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spline_interpolates_controls_and_is_c2() {
        let values = [1.0, -2.0, 0.5, 3.0];
        for (k, &v) in values.iter().enumerate() {
            assert!((natural_cubic(&values, k as f64 / 3.0) - v).abs() < 1e-12);
        }
        // Continuous second derivative across the inner knots (finite differences).
        let second = |t: f64| {
            let h = 1e-4;
            (natural_cubic(&values, t + h) - 2.0 * natural_cubic(&values, t) + natural_cubic(&values, t - h)) / (h * h)
        };
        for knot in [1.0 / 3.0, 2.0 / 3.0] {
            assert!((second(knot - 1e-3) - second(knot + 1e-3)).abs() < 0.5, "C2 at {knot}");
        }
    }

    #[test]
    fn zero_offsets_give_the_source_camera_and_the_pivot_stays_in_view() {
        let source = DMat4::from_rotation_x(0.2) * DMat4::from_translation(DVec3::new(1.0, 2.0, 3.0));
        assert!(orbit(&source, 4.0, 0.0, 0.0, 0.0).abs_diff_eq(source, 1e-12));
        let novel = orbit(&source, 4.0, 20.0, 10.0, 0.1);
        let pivot = source.transform_point3(DVec3::new(0.0, 0.0, 4.0));
        let in_novel = novel.inverse().transform_point3(pivot);
        assert!(in_novel.x.abs() < 1e-9 && in_novel.y.abs() < 1e-9, "looks at the pivot: {in_novel}");
        assert!((in_novel.z - 4.4).abs() < 1e-9, "distance R(1 + Δr)");
        // Positive elevation raises the camera: its centre has negative y in source coordinates.
        let center = source.inverse().transform_point3(orbit(&source, 4.0, 0.0, 10.0, 0.0).w_axis.truncate());
        assert!(center.y < 0.0);
    }

    #[test]
    fn crossing_candidates_are_rejected_and_redrawn_deterministically() {
        let camera = PinholeCamera {
            width: 8,
            height: 6,
            intrinsics: DMat3::from_cols(
                DVec3::new(10.0, 0.0, 0.0),
                DVec3::new(0.0, 10.0, 0.0),
                DVec3::new(3.5, 2.5, 1.0),
            ),
            world_from_camera: DMat4::IDENTITY,
        };
        let cameras = vec![camera; 5];
        let depth = DepthMap { width: 8, height: 6, values: vec![4.0; 48] };
        // A "floor" just below the cameras (y down): any novel camera below it crosses it.
        let floor = |_: usize, a: DVec3, b: DVec3| a.y.max(b.y) > 0.05;
        let config = TrajectoryConfig::paper();
        let sample = |index| sample_trajectory(&cameras, &depth, &config, 9, "clip", 0, index, Some(&floor));
        let mut rejected = 0;
        for index in 0..20 {
            let trajectory = sample(index);
            rejected += trajectory.rejected_samples;
            assert_eq!(trajectory, sample(index), "deterministic");
            if trajectory.rejected_samples + 1 < config.max_attempts {
                assert!(
                    trajectory.world_from_camera.iter().all(|pose| pose.w_axis.y <= 0.05),
                    "accepted paths stay above the floor"
                );
            }
        }
        assert!(rejected > 0, "negative elevations go below the floor and must be redrawn");
    }
}
