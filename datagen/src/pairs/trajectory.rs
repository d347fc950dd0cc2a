//! Novel camera paths. The pivot distance R ([`pivot_distance`]) is the depth at the optical-centre
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
//! With `sampler = "bank"` (or `"mixed"`), a trajectory is instead a real camera motion from a
//! trajectory bank composed with the source path about the pivot ([`super::trajectory_bank`]),
//! randomly mirrored left/right and rotated about the viewing axis.
//!
//! Sampling is deterministic per (seed, source id, clip start, trajectory index). A candidate
//! whose camera, on any frame, reaches its position only by crossing the reconstructed surface
//! (under the floor, inside an object) is rejected and redrawn from the next attempt's seed.

use std::ops::Bound;
use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4, DVec3};
use rand::distr::uniform::SampleRange;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::config_file::{Checked, KeyError, Validate, check_count, check_float};
use crate::error::{Error, Result};
use crate::pairs::clip::pivot_distance;
use foundation::camera::{PinholeCamera, checked_pose};
use foundation::depth::DepthMap;

/// Ranges of the spherical offsets. Every field is checked when a config is loaded and when
/// [`sample_trajectory`] is called ([`Validate`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrajectoryConfig {
    /// Azimuth range ± this many degrees. Valid: finite, in [0, 180] (a half turn each way
    /// reaches every azimuth).
    pub azimuth_deg: f64,
    /// Elevation range ± this many degrees. Valid: finite, in [0, 90] (past 90° the camera
    /// turns over the pivot).
    pub elevation_deg: f64,
    /// Radial offset range ± this fraction of R. Valid: finite, in [0, 1) (at −1 the camera
    /// would sit on the pivot).
    pub radius_frac: f64,
    /// R = this × the depth at the first frame's optical centre. Valid: finite, > 0.
    pub pivot_scale: f64,
    /// Candidates drawn before giving up on rejection (the last one is then kept). Valid: 1 to
    /// [`MAX_ATTEMPTS`].
    pub max_attempts: u32,
    /// Which sampler draws trajectories: `spherical` (the paper's offsets; the default), `bank`
    /// (real camera motion from `bank`) or `mixed` (from the bank with probability
    /// `bank_fraction`, else spherical). Valid: one of those three.
    pub sampler: Sampler,
    /// The trajectory bank file (`datagen trajectories collect`), relative to the working
    /// directory. Valid: set whenever `sampler` is not `spherical`.
    pub bank: Option<PathBuf>,
    /// Under `mixed`, the probability that a trajectory is drawn from the bank. Valid: finite,
    /// in [0, 1].
    pub bank_fraction: f64,
    /// A bank motion is rotated about the viewing axis by an angle uniform in ± this many
    /// degrees (180: any rotation). Valid: finite, in [0, 180].
    pub bank_roll_deg: f64,
}

/// Which trajectory sampler a run uses (`[trajectory] sampler`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Sampler {
    /// Spherical offsets about the pivot (the paper's sampler).
    #[default]
    Spherical,
    /// Real camera motion from a trajectory bank.
    Bank,
    /// Bank with probability `bank_fraction`, otherwise spherical.
    Mixed,
}

impl Sampler {
    /// The name as written in a config.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Spherical => "spherical",
            Self::Bank => "bank",
            Self::Mixed => "mixed",
        }
    }
}

/// Default `bank_fraction`: half of the trajectories from the bank under `mixed`.
pub const DEFAULT_BANK_FRACTION: f64 = 0.5;
/// Default `bank_roll_deg`: any rotation about the viewing axis (the "random rotation").
pub const DEFAULT_BANK_ROLL_DEG: f64 = 180.0;

/// Most candidates per trajectory: each costs a surface-crossing test on every frame, and a
/// path that crossed the surface a thousand times in a row will not be found by more draws.
pub const MAX_ATTEMPTS: u32 = 1000;

impl Validate for TrajectoryConfig {
    fn validate(&self) -> Checked {
        check_float("azimuth_deg", self.azimuth_deg, 0.0..=180.0)?;
        check_float("elevation_deg", self.elevation_deg, 0.0..=90.0)?;
        check_float("radius_frac", self.radius_frac, 0.0..1.0)?;
        check_float("pivot_scale", self.pivot_scale, (Bound::Excluded(0.0), Bound::Unbounded))?;
        check_count("max_attempts", self.max_attempts, 1, MAX_ATTEMPTS.into())?;
        check_float("bank_fraction", self.bank_fraction, 0.0..=1.0)?;
        check_float("bank_roll_deg", self.bank_roll_deg, 0.0..=180.0)?;
        if self.sampler != Sampler::Spherical && self.bank.is_none() {
            return Err(KeyError::new(
                "bank",
                format!(
                    "sampler = \"{}\" needs `bank` = a trajectory bank file (make one with `datagen trajectories collect`)",
                    self.sampler.as_str()
                ),
            ));
        }
        Ok(())
    }
}

impl Default for TrajectoryConfig {
    fn default() -> Self {
        Self::paper()
    }
}

impl TrajectoryConfig {
    /// The paper's ranges (CogNVS §3): elevation ±15°, azimuth ±30°, radius ±15 %.
    pub fn paper() -> Self {
        Self {
            azimuth_deg: 30.0,
            elevation_deg: 15.0,
            radius_frac: 0.15,
            pivot_scale: 1.0,
            max_attempts: 16,
            sampler: Sampler::Spherical,
            bank: None,
            bank_fraction: DEFAULT_BANK_FRACTION,
            bank_roll_deg: DEFAULT_BANK_ROLL_DEG,
        }
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
    tagged_rng(b"cognvs trajectory v1", seed, source_id, clip_start, index, attempt)
}

/// An RNG for one purpose (`tag`) from the run seed and stable ids only.
fn tagged_rng(tag: &[u8], seed: u64, source_id: &str, clip_start: u32, index: u32, attempt: u32) -> ChaCha8Rng {
    let mut hasher = blake3::Hasher::new();
    hasher.update(tag);
    hasher.update(&seed.to_le_bytes());
    hasher.update(&(source_id.len() as u64).to_le_bytes());
    hasher.update(source_id.as_bytes());
    hasher.update(&clip_start.to_le_bytes());
    hasher.update(&index.to_le_bytes());
    hasher.update(&attempt.to_le_bytes());
    ChaCha8Rng::from_seed(*hasher.finalize().as_bytes())
}

/// Four control values in ±`range`; `key` names the range's config key should it be unusable
/// (the config is validated first, so this is only a second line of defence).
fn controls(rng: &mut ChaCha8Rng, range: f64, key: &str) -> Result<[f64; 4], KeyError> {
    // The same stream as `random_range`, without its unwrap; a zero range draws nothing.
    let mut draw = || -> Result<f64, KeyError> {
        if range > 0.0 {
            (-range..=range)
                .sample_single(&mut *rng)
                .map_err(|e| KeyError::new(key, format!("cannot draw from ±{range}: {e}")))
        } else {
            Ok(0.0)
        }
    };
    let (start, end) = (draw()?, draw()?);
    let (mut u1, mut u2) = (rng.random::<f64>(), rng.random::<f64>());
    if u1 > u2 {
        std::mem::swap(&mut u1, &mut u2);
    }
    Ok([start, start + (end - start) * u1, start + (end - start) * u2, end])
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

/// Whether any frame's move from its source camera to the candidate novel pose crosses the
/// surface (the rejection test of every sampler); never, without a test.
fn path_crosses(crosses: Option<Crossing>, poses: &[DMat4], cameras: &[PinholeCamera]) -> bool {
    crosses.is_some_and(|crosses| {
        poses
            .iter()
            .zip(cameras)
            .enumerate()
            .any(|(i, (pose, camera))| crosses(i, camera.center(), pose.w_axis.truncate()))
    })
}

/// Samples trajectory `index` of the clip starting at `clip_start` (see module docs). Fails,
/// naming the key (`trajectory.azimuth_deg`), when `config` is out of its documented ranges.
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
) -> Result<SampledTrajectory> {
    let in_config = |e: KeyError| Error::from(e.under("trajectory"));
    config.validate().map_err(in_config)?;
    let Some(first_camera) = cameras.first() else {
        return Err(Error::parameter("cameras", "a trajectory needs at least one frame"));
    };
    let pivot = pivot_distance(first_depth, first_camera, config.pivot_scale);
    let attempts = config.max_attempts.max(1);
    let mut rejected = 0;
    loop {
        let mut rng = candidate_rng(seed, source_id, clip_start, index, rejected);
        let azimuth = controls(&mut rng, config.azimuth_deg, "azimuth_deg").map_err(in_config)?;
        let elevation = controls(&mut rng, config.elevation_deg, "elevation_deg").map_err(in_config)?;
        let radius = controls(&mut rng, config.radius_frac, "radius_frac").map_err(in_config)?;
        let poses = poses_from_controls(cameras, pivot, &azimuth, &elevation, &radius);
        let crossing = path_crosses(crosses, &poses, cameras);
        if !crossing || rejected + 1 >= attempts {
            return Ok(SampledTrajectory {
                azimuth_deg: azimuth,
                elevation_deg: elevation,
                radius_frac: radius,
                pivot_distance: pivot,
                world_from_camera: poses,
                rejected_samples: rejected,
            });
        }
        rejected += 1;
    }
}

/// A path drawn from a trajectory bank entry.
#[derive(Debug, Clone, PartialEq)]
pub struct BankTrajectory {
    /// The entry's row in the bank.
    pub row: usize,
    /// The entry's id.
    pub entry_id: String,
    /// Whether the motion was mirrored left/right.
    pub mirrored: bool,
    /// Rotation of the motion about the viewing axis, in degrees.
    pub roll_deg: f64,
    /// R.
    pub pivot_distance: f64,
    /// Per-frame novel camera poses.
    pub world_from_camera: Vec<DMat4>,
    /// Candidates rejected before this one.
    pub rejected_samples: u32,
}

/// A novel path from whichever sampler the config names.
#[derive(Debug, Clone, PartialEq)]
pub enum NovelTrajectory {
    /// From spherical offsets ([`sample_trajectory`]).
    Spherical(SampledTrajectory),
    /// From a bank entry.
    Bank(BankTrajectory),
}

impl NovelTrajectory {
    /// Per-frame novel camera poses.
    pub fn world_from_camera(&self) -> &[DMat4] {
        match self {
            Self::Spherical(t) => &t.world_from_camera,
            Self::Bank(t) => &t.world_from_camera,
        }
    }
}

/// Samples trajectory `index` of the clip starting at `clip_start` with `config.sampler`:
/// spherical as [`sample_trajectory`]; `bank` from `bank` (loaded from `config.bank`); `mixed`
/// from the bank for a fraction `bank_fraction` of trajectories (chosen per trajectory, from the
/// same stable ids). Bank candidates that cross the surface are rejected and redrawn exactly as
/// spherical ones. Fails naming the key when `config` is out of range or a bank is needed and
/// `bank` is `None`.
#[allow(clippy::too_many_arguments)]
pub fn sample_novel_trajectory(
    cameras: &[PinholeCamera],
    first_depth: &DepthMap,
    config: &TrajectoryConfig,
    bank: Option<&crate::pairs::trajectory_bank::TrajectoryBank>,
    seed: u64,
    source_id: &str,
    clip_start: u32,
    index: u32,
    crosses: Option<Crossing>,
) -> Result<NovelTrajectory> {
    let in_config = |e: KeyError| Error::from(e.under("trajectory"));
    config.validate().map_err(in_config)?;
    let from_bank = match config.sampler {
        Sampler::Spherical => false,
        Sampler::Bank => true,
        Sampler::Mixed => {
            let mut rng = tagged_rng(b"cognvs sampler choice v1", seed, source_id, clip_start, index, 0);
            rng.random::<f64>() < config.bank_fraction
        }
    };
    if !from_bank {
        let sampled = sample_trajectory(cameras, first_depth, config, seed, source_id, clip_start, index, crosses)?;
        return Ok(NovelTrajectory::Spherical(sampled));
    }
    let Some(bank) = bank.filter(|b| !b.is_empty()) else {
        return Err(Error::parameter("trajectory.bank", "the bank sampler needs a loaded, non-empty trajectory bank"));
    };
    let Some(first_camera) = cameras.first() else {
        return Err(Error::parameter("cameras", "a trajectory needs at least one frame"));
    };
    let pivot = pivot_distance(first_depth, first_camera, config.pivot_scale);
    let sources: Vec<DMat4> = cameras.iter().map(|c| c.world_from_camera).collect();
    let attempts = config.max_attempts.max(1);
    let mut rejected = 0;
    loop {
        let mut rng = tagged_rng(b"cognvs bank trajectory v1", seed, source_id, clip_start, index, rejected);
        let row = (0..bank.len())
            .sample_single(&mut rng)
            .map_err(|e| Error::parameter("trajectory.bank", format!("cannot draw an entry: {e}")))?;
        let mirrored = rng.random::<bool>();
        let roll = config.bank_roll_deg;
        let roll_deg = if roll > 0.0 {
            (-roll..=roll)
                .sample_single(&mut rng)
                .map_err(|e| in_config(KeyError::new("bank_roll_deg", e.to_string())))?
        } else {
            0.0
        };
        let poses = bank.compose(row, &sources, pivot, mirrored, roll_deg);
        let crossing = path_crosses(crosses, &poses, cameras);
        if !crossing || rejected + 1 >= attempts {
            return Ok(NovelTrajectory::Bank(BankTrajectory {
                row,
                entry_id: bank.entries[row].entry_id.clone(),
                mirrored,
                roll_deg,
                pivot_distance: pivot,
                world_from_camera: poses,
                rejected_samples: rejected,
            }));
        }
        rejected += 1;
    }
}

/// Shape parameters of a novel path relative to its source path, comparable across samplers:
/// per frame the novel camera centre is expressed in the source camera's coordinates as azimuth
/// φ, elevation θ and radial offset Δr about the pivot at distance R on the optical axis (the
/// inverse of [`orbit`]'s placement).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct PathParameters {
    /// max φ − min φ over frames, degrees.
    pub azimuth_span_deg: f64,
    /// max θ − min θ over frames, degrees.
    pub elevation_span_deg: f64,
    /// max Δr − min Δr over frames, in units of R.
    pub radial_change: f64,
    /// Length of the novel centre's path relative to the source camera, in units of R.
    pub path_length: f64,
}

/// [`PathParameters`] of `novel` (per-frame `world_from_camera`) against `sources` about a pivot
/// at distance `pivot`; `None` without frames or with R ≤ 0 (explicit paths store no R).
pub fn path_parameters(sources: &[DMat4], novel: &[DMat4], pivot: f64) -> Option<PathParameters> {
    if sources.is_empty() || sources.len() != novel.len() || !(pivot.is_finite() && pivot > 0.0) {
        return None;
    }
    let centre = DVec3::new(0.0, 0.0, pivot);
    let offsets: Vec<DVec3> =
        sources.iter().zip(novel).map(|(s, n)| s.inverse().transform_point3(n.w_axis.truncate())).collect();
    let (mut azimuth, mut elevation, mut radial) = (Vec::new(), Vec::new(), Vec::new());
    for offset in &offsets {
        // orbit() puts the centre at pivot − R(1 + Δr)·d with d = (sin φ cos θ, sin θ, cos φ cos θ).
        let towards_pivot = centre - *offset;
        let distance = towards_pivot.length();
        let d = towards_pivot / distance.max(f64::MIN_POSITIVE);
        elevation.push(d.y.clamp(-1.0, 1.0).asin().to_degrees());
        azimuth.push(d.x.atan2(d.z).to_degrees());
        radial.push(distance / pivot - 1.0);
    }
    let span = |v: &[f64]| {
        v.iter().copied().fold(f64::NEG_INFINITY, f64::max) - v.iter().copied().fold(f64::INFINITY, f64::min)
    };
    let path_length = offsets.windows(2).map(|w| (w[1] - w[0]).length()).sum::<f64>() / pivot;
    Some(PathParameters {
        azimuth_span_deg: span(&azimuth),
        elevation_span_deg: span(&elevation),
        radial_change: span(&radial),
        path_length,
    })
}

#[derive(Deserialize)]
#[serde(untagged)]
enum JsonPoses {
    Wrapped { world_from_camera: Vec<serde_json::Value> },
    Bare(Vec<serde_json::Value>),
}

/// One pose of a JSON trajectory: a 4×4 matrix as nested rows or 16 row-major values
/// ([`foundation::camera::json_matrix`]), checked by [`checked_pose`].
fn json_matrix(path: &Path, index: usize, value: &serde_json::Value) -> Result<DMat4> {
    let field = format!("world_from_camera[{index}]");
    let values = foundation::camera::json_matrix(value, 4, 4).map_err(|reason| Error::invalid(path, &field, reason))?;
    Ok(checked_pose(path, &field, &values)?)
}

/// The three lines of a public `trajs/*.txt` file, in order.
const TXT_LINES: [&str; 3] = ["azimuth", "elevation", "radius"];

/// Parses a `trajs/*.txt` file: three non-blank lines of numbers (whitespace- or comma-separated),
/// azimuth degrees, elevation degrees, radius fractions of R. Every error names the line (as
/// numbered in the file) and its field; values must be finite and radii > −1 (at −1 the camera
/// sits on the pivot it looks at).
fn read_txt_offsets(path: &Path) -> Result<[Vec<f64>; 3]> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let lines: Vec<(usize, &str)> =
        text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()).map(|(i, l)| (i + 1, l)).collect();
    if lines.len() != TXT_LINES.len() {
        return Err(Error::invalid(
            path,
            "lines",
            format!("expected 3 lines (azimuth, elevation, radius), found {} non-blank lines", lines.len()),
        ));
    }
    let mut offsets: [Vec<f64>; 3] = Default::default();
    for ((values, &(number, line)), name) in offsets.iter_mut().zip(&lines).zip(TXT_LINES) {
        for (k, token) in line.split(|c: char| c.is_whitespace() || c == ',').filter(|s| !s.is_empty()).enumerate() {
            let invalid =
                |reason: String| Error::invalid(path, name, format!("line {number}, value {}: {reason}", k + 1));
            let value = token.parse::<f64>().map_err(|_| invalid(format!("`{token}` is not a number")))?;
            if !value.is_finite() {
                return Err(invalid(format!("`{token}` is not a finite number")));
            }
            if name == "radius" && value <= -1.0 {
                return Err(invalid(format!(
                    "{value} ≤ −1 puts the camera on or past the pivot it orbits (radius values are fractions of R)"
                )));
            }
            values.push(value);
        }
        if values.is_empty() {
            return Err(Error::invalid(path, name, format!("line {number}: no values")));
        }
    }
    Ok(offsets)
}

/// Reads an explicit trajectory for a sequence of `frames` frames: `.npy` (N,4,4)
/// `world_from_camera`, `.json` (a list of N 4×4 matrices, nested or row-major flat, or
/// `{"world_from_camera": [...]}`), or the public `trajs/*.txt` format (three lines: azimuth
/// degrees, elevation degrees, radius fractions; resampled linearly to N frames and applied with
/// the orbit above). Every pose passes [`checked_pose`], the check sequence poses get.
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
    if cameras.len() != frames || frames == 0 {
        return Err(Error::parameter("frames", format!("{} cameras for a sequence of {frames} frames", cameras.len())));
    }
    let poses: Vec<DMat4> = match extension.as_str() {
        "npy" => {
            // The shape is checked from the header, before the values are read.
            use crate::io::npy::Axis;
            let array = crate::io::npy::read_npy_f64_shaped(path, &[Axis::Any, Axis::Is(4), Axis::Is(4)])?;
            if array.shape[0] != frames {
                return Err(wrong_count(array.shape[0]));
            }
            array
                .data
                .chunks_exact(16)
                .enumerate()
                .map(|(i, v)| checked_pose(path, &format!("world_from_camera[{i}]"), v))
                .collect::<foundation::Result<_>>()?
        }
        "json" => {
            let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
            let parsed: JsonPoses = serde_json::from_str(&text).map_err(|e| {
                Error::invalid(
                    path,
                    "world_from_camera",
                    format!("expected a list of 4×4 matrices or {{\"world_from_camera\": [...]}}: {e}"),
                )
            })?;
            let list = match parsed {
                JsonPoses::Wrapped { world_from_camera } => world_from_camera,
                JsonPoses::Bare(list) => list,
            };
            if list.len() != frames {
                return Err(wrong_count(list.len()));
            }
            list.iter().enumerate().map(|(i, m)| json_matrix(path, i, m)).collect::<Result<_>>()?
        }
        "txt" => {
            let [azimuth, elevation, radius] = read_txt_offsets(path)?;
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
                    let pose =
                        orbit(&cameras[i].world_from_camera, pivot, at(&azimuth, i), at(&elevation, i), at(&radius, i));
                    checked_pose(
                        path,
                        &format!("world_from_camera[{i}]"),
                        &foundation::camera::mat4_to_row_major(&pose),
                    )
                })
                .collect::<foundation::Result<_>>()?
        }
        other => return Err(Error::invalid(path, "extension", format!("`.{other}`: expected .npy, .json or .txt"))),
    };
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
        let sample = |index| sample_trajectory(&cameras, &depth, &config, 9, "clip", 0, index, Some(&floor)).unwrap();
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
