//! The reconstruction check (`datagen check`): what a person reads before spending GPU hours on a
//! reconstruction. Pairs are only as good as the geometry under them (the CogNVS paper loses about
//! 3 dB PSNR on Kubric-4D when MegaSAM's reconstruction replaces the ground truth), and a wrong
//! convention (camera_from_world read as world_from_camera, OpenGL axes read as OpenCV) or a
//! per-frame depth scale gives masks that look plausible frame by frame and are wrong.
//!
//! The report holds the layout's declared convention and units, the camera path (length, mean and
//! largest step, jumps), the valid-depth share, and the **multi-frame consistency of static
//! geometry**: static pixels (outside the dynamic masks, valid depth) of frame i are lifted with
//! frame i's depth and camera and projected into frame j; a point *agrees* when its z in camera j
//! is within [`CheckConfig::depth_tolerance`] of frame j's depth and its colour within
//! [`CheckConfig::colour_tolerance`] at one of the 2×2 pixels around its projection (depth alone
//! misses a pose error that slides points along a smooth wall; colour catches it). The share
//! that agrees, per frame pair (both directions, for the gaps of [`CheckConfig::frame_gaps`]) and
//! overall, is `static_depth_consistency`: near 1 for a consistent reconstruction (true
//! occlusions between the two views keep it a little below), far lower for perturbed poses or
//! per-frame depth scales. The same measure with the poses inverted and with OpenGL axes probes the
//! convention: when one of those fits clearly better than the poses as read, the files are in
//! another convention than their layout declares. The verdict is `ok`, or `suspect` with the
//! reasons.

use glam::{DMat4, DVec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::config_file::{Checked, KeyError, Validate, check_count, check_float};
use crate::io::sequence::Sequence;
use foundation::camera::{PinholeCamera, pixel_of};

/// Settings of the check (`[check]` of a corpus TOML, or defaults).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CheckConfig {
    /// Relative depth difference within which a reprojected static point agrees with the other
    /// frame's depth. Valid: (0, 1).
    pub depth_tolerance: f64,
    /// Largest difference of any RGB channel (0–255) between a static point's colour in the two
    /// frames for it to agree: a surface point keeps its colour across nearby frames, while a
    /// point moved by a wrong pose lands on other texture even where a smooth wall's depth still
    /// matches. Valid: [0, 255].
    pub colour_tolerance: f64,
    /// Verdict `suspect` below this static depth consistency. Valid: [0, 1].
    pub min_consistency: f64,
    /// Verdict `suspect` below this share of valid depth pixels. Valid: [0, 1].
    pub min_valid_depth_share: f64,
    /// Frame gaps compared (1: consecutive frames). Valid: 1 to 1000 each, at least one.
    pub frame_gaps: Vec<u32>,
    /// Every `pixel_stride`-th pixel in x and y is checked. Valid: 1 to 64.
    pub pixel_stride: u32,
    /// A camera step longer than `jump_factor` × the median step is a jump. Valid: > 1.
    pub jump_factor: f64,
}

impl Default for CheckConfig {
    fn default() -> Self {
        Self {
            // A few per cent: consistent video depth (MegaSAM, ViPE) agrees across neighbouring
            // frames to about this, while a 10 % per-frame scale error or a degree of rotation error
            // over a room-sized scene does not.
            depth_tolerance: 0.05,
            // Video compression and auto-exposure move a static point's colour by a few levels
            // between neighbouring frames; a texture edge by far more.
            colour_tolerance: 40.0,
            // Measured on the synthetic scenes (tests/integration/reconstruction_check.rs): an
            // exact reconstruction of a camera sweeping 25° over 12 frames scores 0.90 (aliased
            // point-sampled textures and occlusions cost the rest), the same with ±2° of pose
            // error or ±15 % per-frame depth scale below 0.7.
            min_consistency: 0.8,
            // VGGT's confidence masking alone removes half of the pixels; below a quarter the
            // masks would be mostly holes.
            min_valid_depth_share: 0.25,
            frame_gaps: vec![1, 5],
            pixel_stride: 4,
            jump_factor: 5.0,
        }
    }
}

impl Validate for CheckConfig {
    fn validate(&self) -> Checked {
        check_float("depth_tolerance", self.depth_tolerance, f64::MIN_POSITIVE..1.0)?;
        check_float("colour_tolerance", self.colour_tolerance, 0.0..=f64::from(u8::MAX))?;
        check_float("min_consistency", self.min_consistency, 0.0..=1.0)?;
        check_float("min_valid_depth_share", self.min_valid_depth_share, 0.0..=1.0)?;
        if self.frame_gaps.is_empty() {
            return Err(KeyError::new("frame_gaps", "needs at least one gap"));
        }
        for gap in &self.frame_gaps {
            check_count("frame_gaps", *gap, 1, MAX_FRAME_GAP)?;
        }
        check_count("pixel_stride", self.pixel_stride, 1, MAX_PIXEL_STRIDE)?;
        check_float("jump_factor", self.jump_factor, 1.0 + f64::EPSILON..)
    }
}

/// Largest frame gap accepted: far beyond any clip (49 frames).
const MAX_FRAME_GAP: u64 = 1000;
/// Largest pixel stride accepted: 64 px leaves ~80 samples in a 480×720 frame.
const MAX_PIXEL_STRIDE: u64 = 64;

/// A convention probe must beat the poses as read by this much (and pass `min_consistency`) to be
/// reported: clear of the noise between the scores of the same poses (a near-static camera scores
/// alike in every convention), while the exact and the inverted poses of a 25° sweep differ by
/// ~0.09.
const PROBE_MARGIN: f64 = 0.05;

/// Median depth above which depth declared metric (metres) looks like centimetres or millimetres:
/// videos are filmed from a few metres, 200 m is a distant landscape.
const METRIC_MEDIAN_DEPTH_MAX: f64 = 200.0;

/// Camera steps shorter than this fraction of the median scene depth count as standing still when
/// looking for jumps (a tripod's jitter is not a path).
const STILL_STEP_FRACTION: f64 = 1e-3;

/// One compared frame pair.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PairConsistency {
    /// The frame whose pixels are lifted.
    pub from: usize,
    /// The frame they are projected into.
    pub to: usize,
    /// Points that landed on a valid static pixel of `to`.
    pub compared: u64,
    /// Of those, points whose depth agreed.
    pub agreeing: u64,
    /// `agreeing / compared` (0 when nothing was compared).
    pub share: f64,
}

/// The camera path.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraPath {
    /// Sum of the camera centres' steps (scene units).
    pub length: f64,
    /// `length` over the median scene depth: unit-free.
    pub length_in_median_depths: f64,
    /// Mean step per frame (scene units).
    pub mean_step: f64,
    /// Mean step per second, when the frame rate is known.
    pub speed_per_second: Option<f64>,
    /// Largest step, and the frame it ends at.
    pub max_step: f64,
    /// Total rotation along the path, degrees.
    pub rotation_deg: f64,
    /// Frames whose step from the previous frame is a jump.
    pub jumps: Vec<usize>,
}

/// Consistency of the same geometry with the poses read in other conventions.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ConventionProbe {
    /// The poses as read.
    pub as_read: f64,
    /// Each pose inverted (camera_from_world taken for world_from_camera, or the reverse).
    pub inverted: f64,
    /// OpenGL camera axes (y up, z backwards) taken for OpenCV's.
    pub opengl_axes: f64,
}

/// The whole report; its JSON is what `datagen check --json` prints.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckReport {
    /// The sequence id.
    pub sequence: String,
    /// The layout it was read in.
    pub layout: String,
    /// What the layout's files declare, and how they were converted.
    pub conventions: String,
    /// `ok` or `suspect`.
    pub verdict: String,
    /// Why it is suspect (empty when ok).
    pub reasons: Vec<String>,
    /// Share of compared static points whose depth agrees across frames, 0–1.
    pub static_depth_consistency: f64,
    /// Share of pixels with valid depth, 0–1.
    pub valid_depth_share: f64,
    /// Median valid depth (the reconstruction's units).
    pub median_depth: f64,
    /// Frames, width, height.
    pub frames: usize,
    /// See `frames`.
    pub width: u32,
    /// See `frames`.
    pub height: u32,
    /// The camera path.
    pub camera_path: CameraPath,
    /// The convention probe.
    pub convention_probe: ConventionProbe,
    /// Per frame pair.
    pub pairs: Vec<PairConsistency>,
}

/// OpenCV axes from OpenGL ones (and back): x kept, y and z negated.
fn opengl_flip() -> DMat4 {
    DMat4::from_diagonal(glam::DVec4::new(1.0, -1.0, -1.0, 1.0))
}

/// Checks `sequence`, read in a layout described by `layout` and `conventions`; `metric` says
/// whether the layout declares metric depth (for the units check).
pub fn check_sequence(
    sequence: &Sequence,
    layout: &str,
    conventions: &str,
    metric: bool,
    config: &CheckConfig,
) -> CheckReport {
    let (width, height) = sequence.size();
    let total_pixels = (sequence.len() * width as usize * height as usize).max(1);
    let mut valid: Vec<f32> =
        sequence.depth.iter().flat_map(|d| d.values.iter().copied().filter(|v| v.is_finite() && *v > 0.0)).collect();
    let valid_depth_share = valid.len() as f64 / total_pixels as f64;
    let median_depth = if valid.is_empty() {
        0.0
    } else {
        let mid = valid.len() / 2;
        f64::from(*valid.select_nth_unstable_by(mid, f32::total_cmp).1)
    };
    drop(valid);

    let poses: Vec<DMat4> = sequence.cameras.iter().map(|c| c.world_from_camera).collect();
    let pairs = consistency_pairs(sequence, &poses, config);
    let static_depth_consistency = overall(&pairs);
    let probe = |transform: &dyn Fn(&DMat4) -> DMat4| {
        let poses: Vec<DMat4> = poses.iter().map(transform).collect();
        overall(&consistency_pairs(sequence, &poses, config))
    };
    let convention_probe = ConventionProbe {
        as_read: static_depth_consistency,
        inverted: probe(&|p| p.inverse()),
        opengl_axes: probe(&|p| *p * opengl_flip()),
    };
    let camera_path = camera_path(sequence, median_depth, config);

    let mut reasons = Vec::new();
    if pairs.iter().all(|p| p.compared == 0) {
        reasons
            .push("no static points could be compared between frames (a single frame, or no valid depth)".to_owned());
    } else if static_depth_consistency < config.min_consistency {
        reasons.push(format!(
            "static depth consistency {static_depth_consistency:.3} is below {:.3}: reprojected static points disagree \
             with the other frames' depth (wrong poses, per-frame depth scale, or a convention mix-up)",
            config.min_consistency
        ));
    }
    for (name, score) in [
        ("inverted poses (camera_from_world read as world_from_camera)", convention_probe.inverted),
        ("OpenGL camera axes (y up, z backwards)", convention_probe.opengl_axes),
    ] {
        if score >= config.min_consistency && score > static_depth_consistency + PROBE_MARGIN {
            reasons.push(format!(
                "the geometry fits {name} far better ({score:.3} vs {static_depth_consistency:.3} as read): the files are \
                 in another convention than the layout declares"
            ));
        }
    }
    if valid_depth_share < config.min_valid_depth_share {
        reasons.push(format!(
            "only {:.1} % of the pixels have valid depth (below {:.1} %)",
            100.0 * valid_depth_share,
            100.0 * config.min_valid_depth_share
        ));
    }
    if !camera_path.jumps.is_empty() {
        reasons.push(format!(
            "the camera jumps at frame(s) {:?}: a step over {}× the median step (lost tracking, or frames out of order)",
            camera_path.jumps, config.jump_factor
        ));
    }
    if metric && median_depth > METRIC_MEDIAN_DEPTH_MAX {
        reasons
            .push(format!("median depth {median_depth:.1} for depth declared in metres: centimetres or millimetres?"));
    }
    CheckReport {
        sequence: sequence.source_id.clone(),
        layout: layout.to_owned(),
        conventions: conventions.to_owned(),
        verdict: if reasons.is_empty() { "ok" } else { "suspect" }.to_owned(),
        reasons,
        static_depth_consistency,
        valid_depth_share,
        median_depth,
        frames: sequence.len(),
        width,
        height,
        camera_path,
        convention_probe,
        pairs,
    }
}

fn overall(pairs: &[PairConsistency]) -> f64 {
    let compared: u64 = pairs.iter().map(|p| p.compared).sum();
    let agreeing: u64 = pairs.iter().map(|p| p.agreeing).sum();
    if compared == 0 { 0.0 } else { agreeing as f64 / compared as f64 }
}

/// The compared frame pairs (both directions for every configured gap), in parallel.
fn consistency_pairs(sequence: &Sequence, poses: &[DMat4], config: &CheckConfig) -> Vec<PairConsistency> {
    let n = sequence.len();
    let mut jobs = Vec::new();
    for &gap in &config.frame_gaps {
        let gap = gap as usize;
        for i in 0..n.saturating_sub(gap) {
            jobs.push((i, i + gap));
            jobs.push((i + gap, i));
        }
    }
    jobs.sort_unstable();
    jobs.dedup();
    jobs.into_par_iter().map(|(from, to)| pair_consistency(sequence, poses, from, to, config)).collect()
}

/// Valid depth: finite and positive (docs/ARCHITECTURE.md, Conventions).
fn is_valid_depth(depth: f64) -> bool {
    depth.is_finite() && depth > 0.0
}

fn is_static(sequence: &Sequence, frame: usize, index: usize) -> bool {
    sequence.dynamic_masks.as_ref().is_none_or(|masks| masks[frame].as_raw()[index] == 0)
}

fn pair_consistency(
    sequence: &Sequence,
    poses: &[DMat4],
    from: usize,
    to: usize,
    config: &CheckConfig,
) -> PairConsistency {
    let source = PinholeCamera { world_from_camera: poses[from], ..sequence.cameras[from] };
    let target_from_world = poses[to].inverse();
    let target_k = sequence.cameras[to].intrinsics;
    let (width, height) = (source.width as usize, source.height as usize);
    let depth_from = &sequence.depth[from].values;
    let depth_to = &sequence.depth[to].values;
    let (frame_from, frame_to) = (&sequence.frames[from], &sequence.frames[to]);
    let stride = config.pixel_stride as usize;
    let (mut compared, mut agreeing) = (0u64, 0u64);
    for v in (0..height).step_by(stride) {
        for u in (0..width).step_by(stride) {
            let index = v * width + u;
            let d = depth_from[index];
            if !is_valid_depth(f64::from(d)) || !is_static(sequence, from, index) {
                continue;
            }
            let point = source.unproject(u as f64, v as f64, f64::from(d));
            let in_target: DVec3 = target_from_world.transform_point3(point);
            if in_target.z.is_nan() || in_target.z <= 0.0 {
                continue;
            }
            let exact = pixel_of(&target_k, in_target);
            if exact.x < -0.5 || exact.y < -0.5 || exact.x >= width as f64 - 0.5 || exact.y >= height as f64 - 0.5 {
                continue;
            }
            // The 2×2 pixels around the projection: the point agrees with the surface seen
            // there when one of them has its depth and colour (nearest-pixel lookups would
            // count a half-pixel rounding on a check edge or a grazing floor as a disagreement).
            let x0 = (exact.x.floor().max(0.0) as usize).min(width - 1);
            let y0 = (exact.y.floor().max(0.0) as usize).min(height - 1);
            let neighbours = [
                (x0, y0),
                ((x0 + 1).min(width - 1), y0),
                (x0, (y0 + 1).min(height - 1)),
                ((x0 + 1).min(width - 1), (y0 + 1).min(height - 1)),
            ];
            let colour_from = &frame_from.as_raw()[index * 3..][..3];
            let mut any_valid = false;
            let mut agrees = false;
            for (x, y) in neighbours {
                let target_index = y * width + x;
                let seen = f64::from(depth_to[target_index]);
                if !is_valid_depth(seen) || !is_static(sequence, to, target_index) {
                    continue;
                }
                any_valid = true;
                let colour_to = &frame_to.as_raw()[target_index * 3..][..3];
                let colour_difference =
                    colour_from.iter().zip(colour_to).map(|(a, b)| a.abs_diff(*b)).max().unwrap_or(0);
                agrees |= (in_target.z - seen).abs() <= config.depth_tolerance * seen
                    && f64::from(colour_difference) <= config.colour_tolerance;
            }
            if any_valid {
                compared += 1;
                agreeing += u64::from(agrees);
            }
        }
    }
    let share = if compared == 0 { 0.0 } else { agreeing as f64 / compared as f64 };
    PairConsistency { from, to, compared, agreeing, share }
}

fn camera_path(sequence: &Sequence, median_depth: f64, config: &CheckConfig) -> CameraPath {
    let centres: Vec<DVec3> = sequence.cameras.iter().map(PinholeCamera::center).collect();
    let steps: Vec<f64> = centres.windows(2).map(|w| (w[1] - w[0]).length()).collect();
    let rotation_deg: f64 = sequence
        .cameras
        .windows(2)
        .map(|w| {
            let a = glam::DQuat::from_mat4(&w[0].world_from_camera);
            let b = glam::DQuat::from_mat4(&w[1].world_from_camera);
            a.angle_between(b).to_degrees()
        })
        .sum();
    let length: f64 = steps.iter().sum();
    let mut sorted = steps.clone();
    sorted.sort_by(f64::total_cmp);
    let median_step = sorted.get(sorted.len() / 2).copied().unwrap_or(0.0);
    let still = STILL_STEP_FRACTION * median_depth;
    let jumps = steps
        .iter()
        .enumerate()
        .filter(|&(_, &step)| step > still && step > config.jump_factor * median_step.max(still))
        .map(|(i, _)| i + 1)
        .collect();
    let mean_step = if steps.is_empty() { 0.0 } else { length / steps.len() as f64 };
    CameraPath {
        length,
        length_in_median_depths: if median_depth > 0.0 { length / median_depth } else { 0.0 },
        mean_step,
        speed_per_second: (sequence.fps > 0.0).then_some(mean_step * sequence.fps),
        max_step: sorted.last().copied().unwrap_or(0.0),
        rotation_deg,
        jumps,
    }
}

impl CheckReport {
    /// The report as a person reads it.
    pub fn to_text(&self) -> String {
        let mut out = String::new();
        let path = &self.camera_path;
        out += &format!(
            "{}: {} frames, {}x{}, layout {}\n",
            self.sequence, self.frames, self.width, self.height, self.layout
        );
        out += &format!("  conventions: {}\n", self.conventions);
        out += &format!(
            "  depth: {:.1} % valid, median {:.4} (the reconstruction's units)\n",
            100.0 * self.valid_depth_share,
            self.median_depth
        );
        out += &format!(
            "  camera path: length {:.4} ({:.2} median depths), mean step {:.4}{}, largest step {:.4}, rotation {:.1}°, jumps {:?}\n",
            path.length,
            path.length_in_median_depths,
            path.mean_step,
            path.speed_per_second.map(|s| format!(" ({s:.4}/s)")).unwrap_or_default(),
            path.max_step,
            path.rotation_deg,
            path.jumps
        );
        out += &format!(
            "  static depth consistency: {:.3} over {} frame pairs (poses inverted: {:.3}, OpenGL axes: {:.3})\n",
            self.static_depth_consistency,
            self.pairs.len(),
            self.convention_probe.inverted,
            self.convention_probe.opengl_axes
        );
        let mut worst: Vec<&PairConsistency> = self.pairs.iter().filter(|p| p.compared > 0).collect();
        worst.sort_by(|a, b| a.share.total_cmp(&b.share));
        for pair in worst.iter().take(WORST_PAIRS_SHOWN) {
            out += &format!(
                "    frames {} → {}: {:.3} of {} points agree\n",
                pair.from, pair.to, pair.share, pair.compared
            );
        }
        out += &format!("verdict: {}\n", self.verdict);
        for reason in &self.reasons {
            out += &format!("  - {reason}\n");
        }
        out
    }
}

/// Frame pairs listed in the text report, worst first (the JSON has them all).
const WORST_PAIRS_SHOWN: usize = 3;

/// Reads the sequence folder `dir` (in `layout`, or the detected one) and checks it.
pub fn check_folder(
    dir: &std::path::Path,
    layout: Option<crate::io::sequence::LayoutName>,
    config: &CheckConfig,
) -> crate::error::Result<CheckReport> {
    use crate::io::sequence::{Layout, detect_layout, layout_named, read_sequence_as};
    let layout = match layout {
        Some(name) => layout_named(dir, name)?,
        None => detect_layout(dir)?,
    };
    let sequence = read_sequence_as(dir, Some(layout.name()))?;
    let metric = matches!(layout, Layout::Vipe(_));
    Ok(check_sequence(&sequence, layout.name().as_str(), layout.conventions(), metric, config))
}
