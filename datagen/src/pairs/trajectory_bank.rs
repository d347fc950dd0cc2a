//! The trajectory bank, the data of the sampler the CogNVS paper names as its generator's missing
//! piece ("sample from a set of real-world trajectories observed in the training set"). Collection
//! harvests the source cameras' own motion over each clip window of a reconstruction (a whole
//! corpus: [`crate::corpus::harvest`]): per frame the pose relative to the window's first camera,
//! translation in units of the window's pivot distance R ([`pivot_distance`]) so paths from scenes
//! of different scale compare, plus provenance and summary statistics. Static windows (no motion)
//! and degenerate ones (non-finite poses, no valid depth for R) are skipped and counted.
//!
//! Sampling ([`TrajectoryBank::compose`]) turns an entry's relative motion M_t into a novel path
//! for a clip: `world_from_novel_t = world_from_source_t · T(p) · C · M_t · C⁻¹ · T(−p)` with
//! `p = (0, 0, R)` the clip's pivot on the source camera's optical axis (so the motion's turns
//! become orbits about the pivot, as the spherical sampler's are, and keep the scene in view),
//! M_t's translation scaled by the clip's R, and C a left/right mirror and/or a rotation about
//! the viewing axis. The entry is resampled in time to the clip's length. Which entry, mirror and
//! roll a clip gets is drawn by [`crate::pairs::trajectory::sample_novel_trajectory`].

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock};

use glam::{DMat3, DMat4, DQuat, DVec3};
use schemas::BankEntry;

use crate::error::{Error, Result};
use crate::io::sequence::Sequence;
use crate::pairs::clip::{ClipConfig, pivot_distance};
use foundation::camera::{mat4_from_row_major, mat4_to_row_major};

/// A window whose camera turns less than this in total (degrees) and moves less than
/// [`MIN_PATH_LENGTH`] is static: below the frame-to-frame rotation noise of monocular SLAM
/// poses (MegaSAM-class systems report errors of a few tenths of a degree).
pub const MIN_ROTATION_DEG: f64 = 0.5;
/// A window whose camera centre travels less than this (in units of R) and turns less than
/// [`MIN_ROTATION_DEG`] is static: 1 % of the pivot distance moves the scene centre by about a
/// pixel per hundred of focal length, i.e. nothing a novel view would show.
pub const MIN_PATH_LENGTH: f64 = 0.01;

/// What [`collect_from_sequence`] and [`crate::corpus::harvest::collect_from_corpus`] found.
#[derive(Debug, Clone, Default)]
pub struct CollectSummary {
    /// The bank's entries, in input then window order.
    pub entries: Vec<BankEntry>,
    /// Windows looked at.
    pub windows: u64,
    /// Windows skipped as static (no motion).
    pub static_windows: u64,
    /// Windows skipped as degenerate (non-finite poses, fewer than 2 frames, no valid depth).
    pub degenerate_windows: u64,
    /// Inputs that could not be read: (input key, reason).
    pub failed_inputs: Vec<(String, String)>,
}

/// Rotation angle of `rotation` in degrees.
fn rotation_angle_deg(rotation: &DMat3) -> f64 {
    let cos = ((rotation.x_axis.x + rotation.y_axis.y + rotation.z_axis.z - 1.0) / 2.0).clamp(-1.0, 1.0);
    cos.acos().to_degrees()
}

fn upper_3x3(matrix: &DMat4) -> DMat3 {
    DMat3::from_cols(matrix.x_axis.truncate(), matrix.y_axis.truncate(), matrix.z_axis.truncate())
}

/// The dominant direction of a relative path (see [`BankEntry::dominant_direction`]).
fn dominant_direction(last: &DMat4) -> String {
    let net = last.w_axis.truncate();
    let (axis, angle) = DQuat::from_mat3(&upper_3x3(last)).to_axis_angle();
    // One radian of turn sweeps the pivot by R, as a translation of 1 (in units of R) does.
    let label = if angle > net.length() {
        let turn = axis * angle;
        let abs = turn.abs();
        if abs.z >= abs.x && abs.z >= abs.y {
            "roll"
        } else if abs.y >= abs.x {
            // A positive turn about +y (down) swings +z towards +x: the camera pans right.
            if turn.y > 0.0 { "pan right" } else { "pan left" }
        } else if turn.x > 0.0 {
            // A positive turn about +x swings +z towards −y (up).
            "tilt up"
        } else {
            "tilt down"
        }
    } else {
        let abs = net.abs();
        if abs.x >= abs.y && abs.x >= abs.z {
            if net.x > 0.0 { "right" } else { "left" }
        } else if abs.y >= abs.z {
            if net.y > 0.0 { "down" } else { "up" }
        } else if net.z > 0.0 {
            "forward"
        } else {
            "backward"
        }
    };
    label.to_owned()
}

/// Why a window is not a bank entry.
enum Skip {
    Static,
    Degenerate,
}

/// The bank entry of the window of `sequence` starting at `start` with `length` frames.
fn window_entry(
    sequence: &Sequence,
    dataset: &str,
    start: u32,
    length: u32,
    pivot_scale: f64,
) -> std::result::Result<BankEntry, Skip> {
    let range = start as usize..(start + length) as usize;
    let cameras = &sequence.cameras[range.clone()];
    let first_depth = &sequence.depth[start as usize];
    let has_depth = first_depth.values.iter().any(|d| d.is_finite() && *d > 0.0);
    if cameras.len() < 2 || !has_depth {
        return Err(Skip::Degenerate);
    }
    let pivot = pivot_distance(first_depth, &cameras[0], pivot_scale);
    let first_from_world = cameras[0].world_from_camera.inverse();
    let relative: Vec<DMat4> = cameras
        .iter()
        .map(|camera| {
            let mut pose = first_from_world * camera.world_from_camera;
            pose.w_axis = (pose.w_axis.truncate() / pivot).extend(1.0);
            pose
        })
        .collect();
    let finite = pivot.is_finite()
        && pivot > 0.0
        && relative.iter().all(|pose| mat4_to_row_major(pose).iter().all(|v| v.is_finite()));
    if !finite {
        return Err(Skip::Degenerate);
    }
    let (mut rotation, mut length_r) = (0.0, 0.0);
    for pair in relative.windows(2) {
        rotation += rotation_angle_deg(&(upper_3x3(&pair[0]).transpose() * upper_3x3(&pair[1])));
        length_r += (pair[1].w_axis.truncate() - pair[0].w_axis.truncate()).length();
    }
    if rotation < MIN_ROTATION_DEG && length_r < MIN_PATH_LENGTH {
        return Err(Skip::Static);
    }
    let last = relative.last().expect("at least two frames");
    let net = last.w_axis.truncate();
    Ok(BankEntry {
        entry_id: format!("{dataset}/{}/{start}", sequence.source_id),
        dataset: dataset.to_owned(),
        video_id: sequence.source_id.clone(),
        source_path: sequence.path.display().to_string(),
        window_start: start,
        fps: sequence.fps,
        pivot_distance: pivot,
        relative_pose: relative.iter().map(mat4_to_row_major).collect(),
        total_rotation_deg: rotation,
        path_length: length_r,
        net_translation: net.to_array(),
        dominant_direction: dominant_direction(last),
    })
}

/// The bank entries of one sequence folder (`datagen trajectories collect SEQ_DIR`): the
/// sequence read in `layout` (detected when `None`; a multi-camera layout gives its scene's input
/// camera) and harvested as [`collect_from_sequence`] does.
pub fn collect_from_folder(
    dir: &Path,
    layout: Option<crate::io::layout::LayoutName>,
    dataset: &str,
    clip: &ClipConfig,
    pivot_scale: f64,
) -> Result<CollectSummary> {
    let options = crate::io::layout::ReadOptions::default();
    let (sequence, _) = crate::io::layout::read_camera_sequence(dir, layout, &options)?;
    let mut summary = CollectSummary::default();
    collect_from_sequence(&sequence, dataset, clip, pivot_scale, &mut summary);
    Ok(summary)
}

/// Adds the bank entries of every clip window (`clip`) of `sequence` to `summary`; R is the
/// first frame's optical-centre depth × `pivot_scale`, as for sampled trajectories.
pub fn collect_from_sequence(
    sequence: &Sequence,
    dataset: &str,
    clip: &ClipConfig,
    pivot_scale: f64,
    summary: &mut CollectSummary,
) {
    for (start, length) in clip.windows(sequence.len() as u32) {
        summary.windows += 1;
        match window_entry(sequence, dataset, start, length, pivot_scale) {
            Ok(entry) => summary.entries.push(entry),
            Err(Skip::Static) => summary.static_windows += 1,
            Err(Skip::Degenerate) => summary.degenerate_windows += 1,
        }
    }
}

/// A loaded, checked trajectory bank.
#[derive(Debug)]
pub struct TrajectoryBank {
    /// The bank file.
    pub path: PathBuf,
    /// BLAKE3 hex digest of the file (recorded with every trajectory drawn from it).
    pub digest: String,
    /// The entries, in file order.
    pub entries: Vec<BankEntry>,
    motions: Vec<Vec<DMat4>>,
}

impl TrajectoryBank {
    /// Reads and checks the bank at `path`: its schema and version (`schemas::read_bank`), at
    /// least one entry, and every entry's poses finite with a rotation part that is a rotation.
    /// Errors name the file and the field (`relative_pose` of entry `id`).
    pub fn load(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        let digest = blake3::hash(&bytes).to_hex().to_string();
        let entries = schemas::read_bank(path)?;
        if entries.is_empty() {
            return Err(Error::invalid(path, "entry_id", "the trajectory bank has no entries"));
        }
        let mut motions = Vec::with_capacity(entries.len());
        for (row, entry) in entries.iter().enumerate() {
            let field = format!("relative_pose (row {row}, entry `{}`)", entry.entry_id);
            if entry.relative_pose.is_empty() {
                return Err(Error::invalid(path, field, "no poses"));
            }
            let mut poses = Vec::with_capacity(entry.relative_pose.len());
            for (frame, values) in entry.relative_pose.iter().enumerate() {
                if let Some(bad) = values.iter().find(|v| !v.is_finite()) {
                    return Err(Error::invalid(path, &field, format!("frame {frame}: non-finite value {bad}")));
                }
                let pose = mat4_from_row_major(values);
                let rotation = upper_3x3(&pose);
                if !(rotation.transpose() * rotation).abs_diff_eq(DMat3::IDENTITY, ROTATION_TOLERANCE)
                    || rotation.determinant() <= 0.0
                {
                    return Err(Error::invalid(path, &field, format!("frame {frame}: not a rigid motion")));
                }
                poses.push(pose);
            }
            motions.push(poses);
        }
        Ok(Self { path: path.to_owned(), digest, entries, motions })
    }

    /// [`TrajectoryBank::load`], once per file per process: a corpus build samples every input
    /// from the same bank. A file changed on disk (size or time) is read again.
    pub fn load_cached(path: &Path) -> Result<Arc<Self>> {
        type Cache = Mutex<HashMap<PathBuf, (Option<(u64, std::time::SystemTime)>, Arc<TrajectoryBank>)>>;
        static CACHE: OnceLock<Cache> = OnceLock::new();
        let stamp = std::fs::metadata(path).ok().and_then(|m| Some((m.len(), m.modified().ok()?)));
        let cache = CACHE.get_or_init(Mutex::default);
        if let Some((cached_stamp, bank)) = cache.lock().expect("bank cache").get(path)
            && stamp.is_some()
            && *cached_stamp == stamp
        {
            return Ok(bank.clone());
        }
        let bank = Arc::new(Self::load(path)?);
        cache.lock().expect("bank cache").insert(path.to_owned(), (stamp, bank.clone()));
        Ok(bank)
    }

    /// Number of entries.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether the bank has no entries (never true for a loaded bank).
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Entry `row`'s relative motion resampled to `frames` frames (linear in time: translation
    /// interpolated linearly, rotation by slerp).
    pub fn motion(&self, row: usize, frames: usize) -> Vec<DMat4> {
        let poses = &self.motions[row];
        let last = poses.len() - 1;
        (0..frames)
            .map(|t| {
                let x = if frames > 1 { t as f64 * last as f64 / (frames - 1) as f64 } else { 0.0 };
                let k = (x.floor() as usize).min(last.saturating_sub(1));
                let (a, b) = (&poses[k], &poses[(k + 1).min(last)]);
                let f = (x - k as f64).clamp(0.0, 1.0);
                let rotation = DQuat::from_mat3(&upper_3x3(a)).slerp(DQuat::from_mat3(&upper_3x3(b)), f);
                let translation = a.w_axis.truncate().lerp(b.w_axis.truncate(), f);
                DMat4::from_rotation_translation(rotation, translation)
            })
            .collect()
    }

    /// The novel path of a clip from entry `row` (see the module docs): `sources` are the clip's
    /// source poses, `pivot` its R; the motion is mirrored left/right when `mirrored`, then
    /// rotated by `roll_deg` about the viewing axis.
    pub fn compose(&self, row: usize, sources: &[DMat4], pivot: f64, mirrored: bool, roll_deg: f64) -> Vec<DMat4> {
        let mirror = if mirrored { DMat4::from_scale(DVec3::new(-1.0, 1.0, 1.0)) } else { DMat4::IDENTITY };
        let change = DMat4::from_rotation_z(roll_deg.to_radians()) * mirror;
        let change_inverse = mirror * DMat4::from_rotation_z(-roll_deg.to_radians());
        let to_pivot = DMat4::from_translation(DVec3::new(0.0, 0.0, pivot));
        let from_pivot = DMat4::from_translation(DVec3::new(0.0, 0.0, -pivot));
        self.motion(row, sources.len())
            .iter()
            .zip(sources)
            .map(|(motion, source)| {
                let mut scaled = *motion;
                scaled.w_axis = (motion.w_axis.truncate() * pivot).extend(1.0);
                *source * to_pivot * change * scaled * change_inverse * from_pivot
            })
            .collect()
    }
}

/// How far from orthonormal a bank pose's rotation may be (f64 poses composed from f32 or
/// f64 reconstructions are orthonormal to about 1e-6).
const ROTATION_TOLERANCE: f64 = 1e-3;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn directions_name_the_motion() {
        let moved = |v: DVec3| DMat4::from_translation(v);
        assert_eq!(dominant_direction(&moved(DVec3::new(0.3, 0.1, 0.0))), "right");
        assert_eq!(dominant_direction(&moved(DVec3::new(0.0, -0.3, 0.1))), "up");
        assert_eq!(dominant_direction(&moved(DVec3::new(0.0, 0.0, -0.5))), "backward");
        assert_eq!(dominant_direction(&DMat4::from_rotation_y(0.3)), "pan right");
        assert_eq!(dominant_direction(&DMat4::from_rotation_x(0.3)), "tilt up");
        assert_eq!(dominant_direction(&DMat4::from_rotation_z(-0.3)), "roll");
        // Positive turn about +y swings the optical axis towards +x (right), as the label says.
        assert!(DMat3::from_rotation_y(0.3).mul_vec3(DVec3::Z).x > 0.0);
    }
}
