//! The reconstruction check (`datagen check`): what a person reads before spending GPU hours on a
//! reconstruction. Pairs are only as good as the geometry under them (the CogNVS paper loses about
//! 3 dB PSNR on Kubric-4D when MegaSAM's reconstruction replaces the ground truth), and a wrong
//! convention (camera_from_world read as world_from_camera, OpenGL axes read as OpenCV) or a
//! per-frame depth scale gives masks that look plausible frame by frame and are wrong.
//!
//! The report holds the layout's declared convention and units, the camera path (length, steps,
//! jumps in position and in rotation), the valid-depth share, and the **multi-frame consistency
//! of static geometry**: static pixels (outside the dynamic masks, valid depth) of frame i are
//! lifted with frame i's depth and camera and projected into frame j; a point *agrees* when its z
//! in camera j is within [`CheckConfig::depth_tolerance`] of frame j's depth and its colour within
//! [`CheckConfig::colour_tolerance`] at one of the 2×2 pixels around its projection (depth alone
//! misses a pose error that slides points along a smooth wall; colour catches it). The share that
//! agrees is kept per frame pair (both directions, for the gaps of [`CheckConfig::frame_gaps`]) and
//! overall (`static_depth_consistency`), and per **stretch**: the pairs straddling each frame
//! boundary. A pose jump between two frames spoils only the few pairs across it, which the mean
//! hides; the worst stretch names the two frames.
//!
//! **Convention probes** ask whether the files fit another convention better: the poses inverted
//! (camera_from_world read as world_from_camera), OpenGL camera axes, a quaternion stored
//! x, y, z, w, depth that is disparity, depth in millimetres or centimetres. Neighbouring frames
//! cannot tell these apart on a slow camera path (every convention moves the pixels alike when
//! the camera barely moves), so the probes compare frame pairs across the whole path, at gaps
//! 1, 2, 4, ... up to the first-to-last frame, by the reprojection residual (bilinear colour and
//! depth at the landing, which resolves sub-pixel shifts), and judge each probe only on the pairs
//! where the two readings move the points apart ([`MIN_SHIFT_PX`]). A probe with no such pair, or
//! whose two readings fit alike there, is `undetermined`, never `ok`. The verdict is `ok`, or
//! `suspect` with the reasons, naming the probable slip.

use glam::{DMat3, DMat4, DQuat, DVec3};
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
            // VGGT's demo confidence filter (the 50th percentile, an option of its reader) alone
            // removes half of the pixels; below a quarter the masks would be mostly holes.
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

/// Median depth above which depth declared metric (metres) looks like centimetres or millimetres:
/// videos are filmed from a few metres, 200 m is a distant landscape.
const METRIC_MEDIAN_DEPTH_MAX: f64 = 200.0;

/// Camera steps shorter than this fraction of the median scene depth count as standing still when
/// looking for jumps (a tripod's jitter is not a path).
const STILL_STEP_FRACTION: f64 = 1e-3;

/// Rotation steps that deviate from the path's typical step by less than this many degrees are no
/// jump, whatever the median deviation: a tripod's or a stabilised camera's jitter.
const STILL_ROTATION_DEG: f64 = 0.05;

/// A stretch (the pairs across one frame boundary) is a jump when its consistency is below
/// `min_consistency` and this far below the median stretch's: one bad stretch in an otherwise
/// consistent video, not the general level of a mediocre one (which the overall score reports).
/// Measured on the synthetic scenes (tests/integration/reconstruction_check.rs): a 4° jump drops
/// its stretch ≥ 0.24 below the median, an exact or uniformly wrong (convention slip) video's
/// worst stretch lies within 0.08 of it.
const STRETCH_DROP: f64 = 0.15;

/// A stretch is only judged with at least this many compared points (a boundary whose straddling
/// pairs barely overlap says nothing).
const MIN_STRETCH_POINTS: u64 = 50;

/// A frame pair can tell a probe's two readings apart when they move its points this many pixels
/// apart on average (a point in view under one reading only counts [`SHIFT_CAP_PX`]): the
/// bilinear colour of textured images resolves half a pixel, while the 2×2 agreement test of
/// the consistency score does not.
pub const MIN_SHIFT_PX: f64 = 0.5;

/// The largest shift a point contributes to a pair's mean shift: beyond it the point is simply
/// elsewhere.
const SHIFT_CAP_PX: f64 = 10.0;

/// A frame pair needs this many judged points to inform a probe.
const MIN_INFORMATIVE_POINTS: u64 = 20;

/// A probe's reading must leave this much smaller a share of the files-as-read's reprojection
/// residual (on the pairs that can tell) to be reported as the slip, and the files as read this
/// much smaller a share of the reading's to reject it; in between it is undetermined. The right
/// reading leaves only sampling and compression noise, a wrong one adds its shift's colour and
/// depth errors (measured on the synthetic scenes of tests/integration/reconstruction_check.rs:
/// ≥ 35 % apart on the slow path, far more on the fast one).
const PROBE_MARGIN: f64 = 0.2;

/// Start frames per gap in the probes' frame pairs: evenly spread over the video, enough to
/// outvote one bad stretch, few enough that the probes cost about as much as the main pass.
const PROBE_STARTS_PER_GAP: usize = 4;

/// The disparity probe fits the unknown scale of `scale / disparity` over ± this many powers of 2
/// around the scale that keeps the median depth, then refines ([`fit_scale`]): affine-invariant
/// disparity (Video Depth Anything, DepthCrafter) has an arbitrary scale.
const DISPARITY_SCALE_OCTAVES: i32 = 8;

/// The disparity scale fit samples every this-many-th pixel of the check's stride in x and y: its
/// ~30 trial scales need the level of agreement, not its last digit (a sixteenth of the points).
const SCALE_FIT_STRIDE_FACTOR: usize = 4;

/// The scale of depth declared in the poses' units when it is in millimetres or centimetres.
const MILLIMETRES: f64 = 1e-3;
/// See [`MILLIMETRES`].
const CENTIMETRES: f64 = 1e-2;

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

/// The consistency of the frame pairs straddling one frame boundary.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Stretch {
    /// The last frame before the boundary.
    pub before: usize,
    /// The first frame after it.
    pub after: usize,
    /// Share of the compared points of the smallest-gap pairs across the boundary that agree.
    pub consistency: f64,
    /// Points those pairs compared.
    pub compared: u64,
    /// The same over the wider-gap pairs across the boundary that involve neither `before` nor
    /// `after` (None without such pairs): a jump spoils them too, while a single frame's fault
    /// (a video keyframe's other compression quality, a blurred frame) does not.
    pub wider: Option<f64>,
    /// The same over the wider-gap pairs that do not cross the boundary (None without such
    /// pairs): what `wider` is measured against.
    pub wider_elsewhere: Option<f64>,
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
    /// Largest step.
    pub max_step: f64,
    /// Total rotation along the path, degrees.
    pub rotation_deg: f64,
    /// Largest rotation between consecutive frames, degrees.
    pub max_rotation_step_deg: f64,
    /// Frames whose step from the previous frame is a jump in position.
    pub jumps: Vec<usize>,
    /// Frames whose rotation from the previous frame is a jump: it deviates from the path's
    /// typical (median) step by over `jump_factor` × the median deviation.
    pub rotation_jumps: Vec<usize>,
}

/// A way the files may be in another convention than their layout declares.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Slip {
    /// Every pose inverted: camera_from_world read as world_from_camera, or the reverse.
    CameraFromWorld,
    /// OpenGL camera axes (y up, z backwards) read as OpenCV's.
    OpenGlAxes,
    /// A rotation quaternion stored x, y, z, w, read as w, x, y, z (COLMAP's order).
    QuaternionOrder,
    /// Disparity (inverse depth, any scale) declared as z-depth.
    Disparity,
    /// Depth in millimetres where the poses are in metres.
    Millimetres,
    /// Depth in centimetres where the poses are in metres.
    Centimetres,
}

impl Slip {
    /// Every probe, in the order of the report.
    pub const ALL: [Self; 6] = [
        Self::CameraFromWorld,
        Self::OpenGlAxes,
        Self::QuaternionOrder,
        Self::Disparity,
        Self::Millimetres,
        Self::Centimetres,
    ];

    /// What the slip looks like, as a reason names it.
    pub fn describe(self) -> &'static str {
        match self {
            Self::CameraFromWorld => {
                "poses look camera-from-world (inverted: camera_from_world read as world_from_camera, or a camera-to-world \
                 matrix saved where camera_from_world is read)"
            }
            Self::OpenGlAxes => "axes look OpenGL (y up, z backwards) where OpenCV axes (y down, z forwards) are read",
            Self::QuaternionOrder => {
                "quaternion order: the rotations fit quaternions stored x, y, z, w and read as w, x, y, z"
            }
            Self::Disparity => "depth looks like disparity (inverse depth) declared as z-depth",
            Self::Millimetres => "depth looks millimetres (×0.001 fits the poses)",
            Self::Centimetres => "depth looks centimetres (×0.01 fits the poses)",
        }
    }

    /// The short name of the text report.
    fn label(self) -> &'static str {
        match self {
            Self::CameraFromWorld => "camera-from-world",
            Self::OpenGlAxes => "OpenGL axes",
            Self::QuaternionOrder => "quaternion order",
            Self::Disparity => "disparity",
            Self::Millimetres => "millimetres",
            Self::Centimetres => "centimetres",
        }
    }
}

/// What a probe found.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ProbeOutcome {
    /// The files as read fit clearly better than the slip.
    Rejected,
    /// The slip's reading fits clearly better: the files are probably in that convention.
    FitsBetter,
    /// This video cannot tell: no frame pair moves the points apart under the two readings, or
    /// both fit alike where they do.
    Undetermined,
}

/// One convention probe. Residuals are the mean reprojection residual of the static points the
/// two readings judge: 0 exact, 1 when colour and depth are off by their tolerances or more (a
/// point sent out of view counts 1).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ConventionProbe {
    /// The slip probed.
    pub slip: Slip,
    /// The finding.
    pub outcome: ProbeOutcome,
    /// The residual of the files as read, on the frame pairs that can tell (0 when none can).
    pub as_read: f64,
    /// The residual with the slip undone, on the same pairs.
    pub alternative: f64,
    /// The residual with the slip undone over every probe pair (how the probable slip is chosen
    /// among several readings that fit better).
    pub alternative_all_pairs: f64,
    /// The largest mean shift between the two readings' projections over the probe pairs, pixels.
    pub largest_shift_px: f64,
    /// Frame pairs that can tell the two readings apart, of `probe_pairs`.
    pub informative_pairs: usize,
    /// Frame pairs probed.
    pub probe_pairs: usize,
    /// The disparity probe's fitted scale (`depth = scale / value`).
    pub depth_scale: Option<f64>,
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
    /// What the check could not tell (undetermined probes); never makes the verdict suspect.
    pub notes: Vec<String>,
    /// Share of compared static points whose depth agrees across frames, 0–1.
    pub static_depth_consistency: f64,
    /// The frame boundary whose straddling pairs agree least (None with fewer than two frames).
    pub worst_stretch: Option<Stretch>,
    /// The median consistency across a frame boundary (None when no boundary has enough
    /// compared points): what the worst stretch is measured against.
    pub typical_stretch: Option<f64>,
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
    /// The convention probes, one per [`Slip`].
    pub convention_probes: Vec<ConventionProbe>,
    /// Per frame pair.
    pub pairs: Vec<PairConsistency>,
}

impl CheckReport {
    /// The score a corpus build filters on: the overall consistency, or the worst stretch's when
    /// lower (a jump in one stretch spoils the clips across it).
    pub fn score(&self) -> f64 {
        let stretch = self.worst_stretch.as_ref().filter(|s| s.compared >= MIN_STRETCH_POINTS);
        stretch.map_or(self.static_depth_consistency, |s| s.consistency.min(self.static_depth_consistency))
    }
}

/// OpenCV axes from OpenGL ones (and back): x kept, y and z negated.
fn opengl_flip() -> DMat4 {
    DMat4::from_diagonal(glam::DVec4::new(1.0, -1.0, -1.0, 1.0))
}

/// The pose a `world_from_camera` becomes when the quaternion of its camera_from_world rotation
/// was stored x, y, z, w and read as w, x, y, z: the read quaternion (w', x', y', z') holds the
/// file's (x, y, z, w), so the file meant (w, x, y, z) = (z', w', x', y').
fn quaternion_reordered(world_from_camera: &DMat4) -> DMat4 {
    let camera_from_world = world_from_camera.inverse();
    let read = DQuat::from_mat3(&DMat3::from_mat4(camera_from_world));
    let meant = DQuat::from_xyzw(read.w, read.x, read.y, read.z).normalize();
    DMat4::from_rotation_translation(meant, camera_from_world.w_axis.truncate()).inverse()
}

/// How the depth values are taken.
#[derive(Debug, Clone, Copy, PartialEq)]
enum DepthReading {
    /// As the files give them.
    AsRead,
    /// Multiplied by a scale.
    Scaled(f64),
    /// `scale / value`: the files hold disparity.
    Inverse(f64),
}

impl DepthReading {
    /// The z-depth of a stored value, `None` when invalid (not finite and positive).
    fn depth(self, value: f32) -> Option<f64> {
        let value = f64::from(value);
        if !is_valid_depth(value) {
            return None;
        }
        Some(match self {
            Self::AsRead => value,
            Self::Scaled(scale) => scale * value,
            Self::Inverse(scale) => scale / value,
        })
    }
}

/// One reading of the files: poses and depth.
struct Reading<'a> {
    sequence: &'a Sequence,
    poses: Vec<DMat4>,
    depth: DepthReading,
    stride: usize,
    depth_tolerance: f64,
    colour_tolerance: f64,
}

/// Where a lifted point lands in the other frame: exact pixel and z.
#[derive(Debug, Clone, Copy)]
struct Landing {
    x: f64,
    y: f64,
    z: f64,
}

/// A sampled static pixel of a frame with valid depth.
#[derive(Debug, Clone, Copy)]
struct Sample {
    u: usize,
    v: usize,
    index: usize,
}

/// The tallies of one frame pair under one reading.
#[derive(Debug, Clone, Copy, Default)]
struct Tally {
    /// Static points with valid depth lifted from the first frame.
    lifted: u64,
    /// Of those, points that landed on a valid static pixel of the other frame.
    compared: u64,
    /// Of those, points that agreed.
    agreeing: u64,
}

impl<'a> Reading<'a> {
    fn new(sequence: &'a Sequence, poses: Vec<DMat4>, depth: DepthReading, config: &CheckConfig) -> Self {
        Self {
            sequence,
            poses,
            depth,
            stride: config.pixel_stride as usize,
            depth_tolerance: config.depth_tolerance,
            colour_tolerance: config.colour_tolerance,
        }
    }

    /// The same files with other poses or depth.
    fn with(&self, poses: Vec<DMat4>, depth: DepthReading) -> Self {
        Self { sequence: self.sequence, poses, depth, ..*self }
    }

    /// The sampled static pixels of `frame` with valid depth.
    fn samples(&self, frame: usize) -> impl Iterator<Item = Sample> + '_ {
        let (width, height) = self.sequence.size();
        let (width, height) = (width as usize, height as usize);
        let depth = &self.sequence.depth[frame].values;
        (0..height).step_by(self.stride).flat_map(move |v| {
            (0..width).step_by(self.stride).filter_map(move |u| {
                let index = v * width + u;
                (is_valid_depth(f64::from(depth[index])) && is_static(self.sequence, frame, index)).then_some(Sample {
                    u,
                    v,
                    index,
                })
            })
        })
    }

    /// Camera `to` from camera `from`, under this reading's poses.
    fn relative(&self, from: usize, to: usize) -> DMat4 {
        self.poses[to].inverse() * self.poses[from]
    }

    /// Where `sample` of frame `from` lands in frame `to` (`to_from_from` from [`Self::relative`]),
    /// `None` when behind the camera or outside the frame.
    fn land(&self, sample: Sample, from: usize, to: usize, to_from_from: &DMat4) -> Option<Landing> {
        let d = self.depth.depth(self.sequence.depth[from].values[sample.index])?;
        let k_inverse = self.sequence.cameras[from].intrinsics.inverse();
        let in_from = d * (k_inverse * DVec3::new(sample.u as f64, sample.v as f64, 1.0));
        let in_to = to_from_from.transform_point3(in_from);
        if in_to.z.is_nan() || in_to.z <= 0.0 {
            return None;
        }
        let exact = pixel_of(&self.sequence.cameras[to].intrinsics, in_to);
        let (width, height) = self.sequence.size();
        let inside =
            exact.x >= -0.5 && exact.y >= -0.5 && exact.x < f64::from(width) - 0.5 && exact.y < f64::from(height) - 0.5;
        inside.then_some(Landing { x: exact.x, y: exact.y, z: in_to.z })
    }

    /// Whether the point of `sample` (frame `from`) agrees with frame `to` where it lands: `None`
    /// when none of the 2×2 pixels around the landing has valid static depth (not compared).
    fn agrees(&self, sample: Sample, from: usize, to: usize, landing: Landing) -> Option<bool> {
        let (width, height) = self.sequence.size();
        let (width, height) = (width as usize, height as usize);
        // The 2×2 pixels around the projection: the point agrees with the surface seen there
        // when one of them has its depth and colour (nearest-pixel lookups would count a
        // half-pixel rounding on a check edge or a grazing floor as a disagreement).
        let x0 = (landing.x.floor().max(0.0) as usize).min(width - 1);
        let y0 = (landing.y.floor().max(0.0) as usize).min(height - 1);
        let (x1, y1) = ((x0 + 1).min(width - 1), (y0 + 1).min(height - 1));
        let colour_from = &self.sequence.frames[from].as_raw()[sample.index * 3..][..3];
        let frame_to = self.sequence.frames[to].as_raw();
        let depth_to = &self.sequence.depth[to].values;
        let mut compared = false;
        let mut agrees = false;
        for (x, y) in [(x0, y0), (x1, y0), (x0, y1), (x1, y1)] {
            let target = y * width + x;
            let Some(seen) = self.depth.depth(depth_to[target]) else { continue };
            if !is_static(self.sequence, to, target) {
                continue;
            }
            compared = true;
            let colour_to = &frame_to[target * 3..][..3];
            let colour_difference = colour_from.iter().zip(colour_to).map(|(a, b)| a.abs_diff(*b)).max().unwrap_or(0);
            agrees |= (landing.z - seen).abs() <= self.depth_tolerance * seen
                && f64::from(colour_difference) <= self.colour_tolerance;
        }
        compared.then_some(agrees)
    }

    /// The tally of the pair `from` → `to`.
    fn tally(&self, from: usize, to: usize) -> Tally {
        let to_from_from = self.relative(from, to);
        let mut tally = Tally::default();
        for sample in self.samples(from) {
            tally.lifted += 1;
            let verdict = self.land(sample, from, to, &to_from_from).and_then(|l| self.agrees(sample, from, to, l));
            if let Some(agrees) = verdict {
                tally.compared += 1;
                tally.agreeing += u64::from(agrees);
            }
        }
        tally
    }

    /// The share of the points lifted over `pairs` that agree.
    fn agreeing_share(&self, pairs: &[(usize, usize)]) -> f64 {
        let (lifted, agreeing) = pairs
            .par_iter()
            .map(|&(from, to)| self.tally(from, to))
            .map(|t| (t.lifted, t.agreeing))
            .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
        share(agreeing, lifted)
    }
}

fn share(part: u64, whole: u64) -> f64 {
    if whole == 0 { 0.0 } else { part as f64 / whole as f64 }
}

/// How a reading explains one lifted point in the other frame.
#[derive(Debug, Clone, Copy)]
enum Explained {
    /// Outside the other frame or behind its camera.
    Away,
    /// Landed where the 2×2 pixels around it are not all valid static depth: not judged.
    Unjudged,
    /// Landed at `landing` with this residual: 0 exact, 1 at the tolerances.
    Residual(Landing, f64),
}

impl Reading<'_> {
    /// The reprojection residual of `sample` of frame `from` in frame `to`: the bilinear colour
    /// and depth of frame `to` at the landing against the point's colour and z, each over its
    /// tolerance and capped at 1, averaged.
    fn explain(&self, sample: Sample, from: usize, to: usize, to_from_from: &DMat4) -> Explained {
        let Some(landing) = self.land(sample, from, to, to_from_from) else { return Explained::Away };
        let (width, height) = self.sequence.size();
        let (width, height) = (width as usize, height as usize);
        if width < 2 || height < 2 {
            return Explained::Unjudged;
        }
        let x0 = (landing.x.floor().max(0.0) as usize).min(width - 2);
        let y0 = (landing.y.floor().max(0.0) as usize).min(height - 2);
        let (fx, fy) = ((landing.x - x0 as f64).clamp(0.0, 1.0), (landing.y - y0 as f64).clamp(0.0, 1.0));
        let frame_to = self.sequence.frames[to].as_raw();
        let depth_to = &self.sequence.depth[to].values;
        let mut colour = [0.0f64; 3];
        let mut depth = 0.0;
        for (x, y, weight) in [
            (x0, y0, (1.0 - fx) * (1.0 - fy)),
            (x0 + 1, y0, fx * (1.0 - fy)),
            (x0, y0 + 1, (1.0 - fx) * fy),
            (x0 + 1, y0 + 1, fx * fy),
        ] {
            let target = y * width + x;
            let Some(seen) = self.depth.depth(depth_to[target]) else { return Explained::Unjudged };
            if !is_static(self.sequence, to, target) {
                return Explained::Unjudged;
            }
            depth += weight * seen;
            for (c, value) in colour.iter_mut().zip(&frame_to[target * 3..][..3]) {
                *c += weight * f64::from(*value);
            }
        }
        let colour_from = &self.sequence.frames[from].as_raw()[sample.index * 3..][..3];
        let colour_error = colour_from.iter().zip(colour).map(|(a, b)| (f64::from(*a) - b).abs()).sum::<f64>() / 3.0;
        let depth_error = (landing.z - depth).abs() / depth;
        let capped = |error: f64, tolerance: f64| (error / tolerance).min(1.0);
        let residual = 0.5 * (capped(colour_error, self.colour_tolerance) + capped(depth_error, self.depth_tolerance));
        Explained::Residual(landing, residual)
    }
}

/// One frame pair read two ways: the points both readings judge (or one judges and the other
/// sends away), their residuals under each, and how far apart the readings put them.
#[derive(Debug, Clone, Copy, Default)]
struct PairContrast {
    judged: u64,
    residual_as_read: f64,
    residual_alternative: f64,
    shift_px: f64,
}

impl PairContrast {
    fn mean_shift(&self) -> f64 {
        if self.judged == 0 { 0.0 } else { self.shift_px / self.judged as f64 }
    }

    fn informative(&self) -> bool {
        self.judged >= MIN_INFORMATIVE_POINTS && self.mean_shift() >= MIN_SHIFT_PX
    }
}

fn contrast(as_read: &Reading, alternative: &Reading, from: usize, to: usize) -> PairContrast {
    let (read_motion, alternative_motion) = (as_read.relative(from, to), alternative.relative(from, to));
    let mut out = PairContrast::default();
    for sample in as_read.samples(from) {
        let a = as_read.explain(sample, from, to, &read_motion);
        let b = alternative.explain(sample, from, to, &alternative_motion);
        let (residual_a, residual_b, shift) = match (a, b) {
            (Explained::Residual(la, ra), Explained::Residual(lb, rb)) => {
                (ra, rb, (la.x - lb.x).hypot(la.y - lb.y).min(SHIFT_CAP_PX))
            }
            // In view and explained under one reading, away under the other: the other fails.
            (Explained::Residual(_, ra), Explained::Away) => (ra, 1.0, SHIFT_CAP_PX),
            (Explained::Away, Explained::Residual(_, rb)) => (1.0, rb, SHIFT_CAP_PX),
            _ => continue,
        };
        out.judged += 1;
        out.residual_as_read += residual_a;
        out.residual_alternative += residual_b;
        out.shift_px += shift;
    }
    out
}

/// The probes' frame pairs: gaps 1, 2, 4, ... and the first-to-last gap, each from up to
/// [`PROBE_STARTS_PER_GAP`] start frames spread over the video, both directions.
fn probe_pairs(n: usize) -> Vec<(usize, usize)> {
    let mut gaps: Vec<usize> = std::iter::successors(Some(1usize), |g| Some(g * 2)).take_while(|&g| g < n).collect();
    if n >= 2 && gaps.last() != Some(&(n - 1)) {
        gaps.push(n - 1);
    }
    let mut pairs = Vec::new();
    for gap in gaps {
        let starts = n - gap;
        let count = starts.min(PROBE_STARTS_PER_GAP);
        for k in 0..count {
            let start = if count == 1 { 0 } else { k * (starts - 1) / (count - 1) };
            pairs.push((start, start + gap));
            pairs.push((start + gap, start));
        }
    }
    pairs.sort_unstable();
    pairs.dedup();
    pairs
}

/// The scale maximising `fit` (a share of agreeing points): powers of 2 over
/// ± [`DISPARITY_SCALE_OCTAVES`] around `centre`, then quarter and sixteenth octaves around the
/// best, so the fitted scale is within 2^(1/32) (2 %) of the best, under the depth tolerance.
fn fit_scale(centre: f64, fit: impl Fn(f64) -> f64 + Sync) -> f64 {
    let mut best = centre;
    for (step, span) in [(1.0, DISPARITY_SCALE_OCTAVES), (0.25, 3), (1.0 / 16.0, 3)] {
        let candidates: Vec<f64> = (-span..=span).map(|k| best * (f64::from(k) * step).exp2()).collect();
        let scores: Vec<f64> = candidates.par_iter().map(|&s| fit(s)).collect();
        let winner = scores.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).map_or(0, |(i, _)| i);
        best = candidates[winner];
    }
    best
}

/// Runs one probe: `alternative` against `as_read` on `pairs`.
fn probe(slip: Slip, as_read: &Reading, alternative: &Reading, pairs: &[(usize, usize)]) -> ConventionProbe {
    let contrasts: Vec<PairContrast> =
        pairs.par_iter().map(|&(from, to)| contrast(as_read, alternative, from, to)).collect();
    let pooled = |items: &mut dyn Iterator<Item = &PairContrast>| {
        let (judged, read, other) = items
            .fold((0u64, 0.0, 0.0), |(n, a, b), c| (n + c.judged, a + c.residual_as_read, b + c.residual_alternative));
        if judged == 0 { (0.0, 0.0) } else { (read / judged as f64, other / judged as f64) }
    };
    let informative_pairs = contrasts.iter().filter(|c| c.informative()).count();
    let (read_residual, alternative_residual) = pooled(&mut contrasts.iter().filter(|c| c.informative()));
    let (_, alternative_all_pairs) = pooled(&mut contrasts.iter());
    let outcome = if informative_pairs == 0 {
        ProbeOutcome::Undetermined
    } else if alternative_residual <= (1.0 - PROBE_MARGIN) * read_residual {
        ProbeOutcome::FitsBetter
    } else if read_residual <= (1.0 - PROBE_MARGIN) * alternative_residual {
        ProbeOutcome::Rejected
    } else {
        ProbeOutcome::Undetermined
    };
    ConventionProbe {
        slip,
        outcome,
        as_read: read_residual,
        alternative: alternative_residual,
        alternative_all_pairs,
        largest_shift_px: contrasts.iter().map(PairContrast::mean_shift).fold(0.0, f64::max),
        informative_pairs,
        probe_pairs: pairs.len(),
        depth_scale: match alternative.depth {
            DepthReading::Inverse(scale) => Some(scale),
            _ => None,
        },
    }
}

/// Every convention probe of `as_read`.
fn convention_probes(as_read: &Reading, median_depth: f64) -> Vec<ConventionProbe> {
    let pairs = probe_pairs(as_read.sequence.len());
    let poses = &as_read.poses;
    Slip::ALL
        .into_iter()
        .map(|slip| {
            let alternative = match slip {
                Slip::CameraFromWorld => as_read.with(poses.iter().map(DMat4::inverse).collect(), DepthReading::AsRead),
                Slip::OpenGlAxes => {
                    as_read.with(poses.iter().map(|p| *p * opengl_flip()).collect(), DepthReading::AsRead)
                }
                Slip::QuaternionOrder => {
                    as_read.with(poses.iter().map(quaternion_reordered).collect(), DepthReading::AsRead)
                }
                Slip::Millimetres => as_read.with(poses.clone(), DepthReading::Scaled(MILLIMETRES)),
                Slip::Centimetres => as_read.with(poses.clone(), DepthReading::Scaled(CENTIMETRES)),
                Slip::Disparity => {
                    // Centre: the scale that keeps the median depth, `median² / median`.
                    let centre = if median_depth > 0.0 { median_depth * median_depth } else { 1.0 };
                    let scale = fit_scale(centre, |s| {
                        let mut candidate = as_read.with(poses.clone(), DepthReading::Inverse(s));
                        candidate.stride *= SCALE_FIT_STRIDE_FACTOR;
                        candidate.agreeing_share(&pairs)
                    });
                    as_read.with(poses.clone(), DepthReading::Inverse(scale))
                }
            };
            probe(slip, as_read, &alternative, &pairs)
        })
        .collect()
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
    let as_read = Reading::new(sequence, poses, DepthReading::AsRead, config);
    let pairs = consistency_pairs(&as_read, &config.frame_gaps);
    let static_depth_consistency = overall(&pairs);
    let stretches = stretches(&pairs, sequence.len());
    let judged: Vec<&Stretch> = stretches.iter().filter(|s| s.compared >= MIN_STRETCH_POINTS).collect();
    let typical_stretch = median_of(judged.iter().map(|s| s.consistency).collect());
    let worst_stretch = stretches.into_iter().min_by(|a, b| a.consistency.total_cmp(&b.consistency));
    let convention_probes = convention_probes(&as_read, median_depth);
    let camera_path = camera_path(sequence, median_depth, config);

    let mut reasons = Vec::new();
    let mut notes = Vec::new();
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
    // A jump: the worst stretch is low, clearly below the typical boundary, and the wider pairs
    // across it (without its two frames) confirm it against those elsewhere, when there are any.
    let confirmed = |stretch: &Stretch| match (stretch.wider, stretch.wider_elsewhere) {
        (Some(wider), Some(elsewhere)) => wider < elsewhere - STRETCH_DROP,
        _ => true,
    };
    if let (Some(stretch), Some(typical)) = (&worst_stretch, typical_stretch)
        && stretch.compared >= MIN_STRETCH_POINTS
        && stretch.consistency < config.min_consistency
        && stretch.consistency < typical - STRETCH_DROP
        && confirmed(stretch)
    {
        reasons.push(format!(
            "a jump between frames {} and {}: the frame pairs across it agree on {:.3} of their static points \
             ({typical:.3} across a typical boundary; a re-initialised or loop-closed pose, or a depth scale change)",
            stretch.before, stretch.after, stretch.consistency
        ));
    }
    // The probable slip: of the probes whose reading fits clearly better, the best fitting.
    let probable = convention_probes
        .iter()
        .filter(|p| p.outcome == ProbeOutcome::FitsBetter)
        .min_by(|a, b| a.alternative_all_pairs.total_cmp(&b.alternative_all_pairs));
    if let Some(probe) = probable {
        reasons.push(format!(
            "{}: the geometry fits that reading far better (reprojection residual {:.3} vs {:.3} as read, on the {} \
             frame pairs that can tell); the files are in another convention than the layout declares",
            probe.slip.describe(),
            probe.alternative,
            probe.as_read,
            probe.informative_pairs
        ));
    }
    for probe in convention_probes.iter().filter(|p| p.outcome == ProbeOutcome::Undetermined) {
        notes.push(format!(
            "{} probe undetermined: {}",
            probe.slip.label(),
            if probe.informative_pairs == 0 {
                "no frame pair moves the points far enough apart under the two readings (the camera moves too little)"
                    .to_owned()
            } else {
                format!(
                    "both readings fit alike (reprojection residual {:.3} vs {:.3} as read) on the {} frame pairs \
                     that can tell",
                    probe.alternative, probe.as_read, probe.informative_pairs
                )
            }
        ));
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
    if !camera_path.rotation_jumps.is_empty() {
        reasons.push(format!(
            "the camera turns abruptly at frame(s) {:?}: a rotation step off the path's typical step by over {}× the \
             median deviation (a re-initialised or loop-closed pose?)",
            camera_path.rotation_jumps, config.jump_factor
        ));
    }
    if metric && median_depth > METRIC_MEDIAN_DEPTH_MAX {
        reasons.push(format!(
            "median depth {median_depth:.1} for depth declared in metres: depth looks millimetres or centimetres"
        ));
    }
    CheckReport {
        sequence: sequence.source_id.clone(),
        layout: layout.to_owned(),
        conventions: conventions.to_owned(),
        verdict: if reasons.is_empty() { "ok" } else { "suspect" }.to_owned(),
        reasons,
        notes,
        static_depth_consistency,
        worst_stretch,
        typical_stretch,
        valid_depth_share,
        median_depth,
        frames: sequence.len(),
        width,
        height,
        camera_path,
        convention_probes,
        pairs,
    }
}

fn overall(pairs: &[PairConsistency]) -> f64 {
    let compared: u64 = pairs.iter().map(|p| p.compared).sum();
    let agreeing: u64 = pairs.iter().map(|p| p.agreeing).sum();
    share(agreeing, compared)
}

/// The stretch of every frame boundary with compared points: the pairs of the smallest configured
/// gap straddling it (`from` and `to` on either side), which localise a jump (wider pairs
/// straddle several boundaries and would smear it over its neighbours), and the wider ones that
/// confirm it ([`Stretch::wider`]).
fn stretches(pairs: &[PairConsistency], frames: usize) -> Vec<Stretch> {
    let gap = |p: &PairConsistency| p.from.abs_diff(p.to);
    let smallest = pairs.iter().map(gap).min().unwrap_or(1);
    let pooled = |selected: &mut dyn Iterator<Item = &PairConsistency>| {
        selected.fold((0, 0), |(c, a), p| (c + p.compared, a + p.agreeing))
    };
    (1..frames)
        .map(|after| {
            let before = after - 1;
            let across = |p: &&PairConsistency| p.from.min(p.to) < after && after <= p.from.max(p.to);
            let (compared, agreeing) = pooled(&mut pairs.iter().filter(across).filter(|p| gap(p) == smallest));
            let (wider_compared, wider_agreeing) = pooled(
                &mut pairs
                    .iter()
                    .filter(across)
                    .filter(|p| gap(p) > smallest && ![p.from, p.to].iter().any(|&f| f == before || f == after)),
            );
            let (elsewhere_compared, elsewhere_agreeing) =
                pooled(&mut pairs.iter().filter(|p| gap(p) > smallest && !across(p)));
            let judged = |agreeing, compared| (compared >= MIN_STRETCH_POINTS).then(|| share(agreeing, compared));
            Stretch {
                before,
                after,
                consistency: share(agreeing, compared),
                compared,
                wider: judged(wider_agreeing, wider_compared),
                wider_elsewhere: judged(elsewhere_agreeing, elsewhere_compared),
            }
        })
        .filter(|s| s.compared > 0)
        .collect()
}

/// The compared frame pairs (both directions for every configured gap), in parallel.
fn consistency_pairs(reading: &Reading, gaps: &[u32]) -> Vec<PairConsistency> {
    let n = reading.sequence.len();
    let mut jobs = Vec::new();
    for &gap in gaps {
        let gap = gap as usize;
        for i in 0..n.saturating_sub(gap) {
            jobs.push((i, i + gap));
            jobs.push((i + gap, i));
        }
    }
    jobs.sort_unstable();
    jobs.dedup();
    jobs.into_par_iter()
        .map(|(from, to)| {
            let tally = reading.tally(from, to);
            PairConsistency {
                from,
                to,
                compared: tally.compared,
                agreeing: tally.agreeing,
                share: share(tally.agreeing, tally.compared),
            }
        })
        .collect()
}

/// Valid depth: finite and positive (docs/ARCHITECTURE.md, Conventions).
fn is_valid_depth(depth: f64) -> bool {
    depth.is_finite() && depth > 0.0
}

fn is_static(sequence: &Sequence, frame: usize, index: usize) -> bool {
    sequence.dynamic_masks.as_ref().is_none_or(|masks| masks[frame].as_raw()[index] == 0)
}

/// The upper median of `values` (None when empty).
fn median_of(mut values: Vec<f64>) -> Option<f64> {
    let mid = values.len() / 2;
    (!values.is_empty()).then(|| *values.select_nth_unstable_by(mid, f64::total_cmp).1)
}

/// Indices (1-based: the frame a step ends at) of the steps over `factor` × the median step and
/// over `still`.
fn jumps(steps: &[f64], factor: f64, still: f64) -> Vec<usize> {
    let median = median_of(steps.to_vec()).unwrap_or(0.0);
    steps
        .iter()
        .enumerate()
        .filter(|&(_, &step)| step > still && step > factor * median.max(still))
        .map(|(i, _)| i + 1)
        .collect()
}

fn camera_path(sequence: &Sequence, median_depth: f64, config: &CheckConfig) -> CameraPath {
    let centres: Vec<DVec3> = sequence.cameras.iter().map(PinholeCamera::center).collect();
    let steps: Vec<f64> = centres.windows(2).map(|w| (w[1] - w[0]).length()).collect();
    // Each step's rotation as a rotation vector in the first camera's frame, degrees.
    let turns: Vec<DVec3> = sequence
        .cameras
        .windows(2)
        .map(|w| {
            let a = DQuat::from_mat3(&DMat3::from_mat4(w[0].world_from_camera));
            let b = DQuat::from_mat3(&DMat3::from_mat4(w[1].world_from_camera));
            (a.inverse() * b).normalize().to_scaled_axis() * 180.0 / std::f64::consts::PI
        })
        .collect();
    let rotation_steps: Vec<f64> = turns.iter().map(|t| t.length()).collect();
    // A jump in rotation is a step that turns unlike the path's typical step (a pan's steady
    // turn is no jump, a sudden extra degree on top of it is): each step's deviation from the
    // component-wise median step.
    let median = |values: Vec<f64>| median_of(values).unwrap_or(0.0);
    let typical_turn = DVec3::new(
        median(turns.iter().map(|t| t.x).collect()),
        median(turns.iter().map(|t| t.y).collect()),
        median(turns.iter().map(|t| t.z).collect()),
    );
    let turn_deviations: Vec<f64> = turns.iter().map(|t| (*t - typical_turn).length()).collect();
    let length: f64 = steps.iter().sum();
    let mean_step = if steps.is_empty() { 0.0 } else { length / steps.len() as f64 };
    CameraPath {
        length,
        length_in_median_depths: if median_depth > 0.0 { length / median_depth } else { 0.0 },
        mean_step,
        speed_per_second: (sequence.fps > 0.0).then_some(mean_step * sequence.fps),
        max_step: steps.iter().copied().fold(0.0, f64::max),
        rotation_deg: rotation_steps.iter().sum(),
        max_rotation_step_deg: rotation_steps.iter().copied().fold(0.0, f64::max),
        jumps: jumps(&steps, config.jump_factor, STILL_STEP_FRACTION * median_depth),
        rotation_jumps: jumps(&turn_deviations, config.jump_factor, STILL_ROTATION_DEG),
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
            "  camera path: length {:.4} ({:.2} median depths), mean step {:.4}{}, largest step {:.4}, rotation {:.1}° \
             (largest step {:.2}°), jumps {:?}, rotation jumps {:?}\n",
            path.length,
            path.length_in_median_depths,
            path.mean_step,
            path.speed_per_second.map(|s| format!(" ({s:.4}/s)")).unwrap_or_default(),
            path.max_step,
            path.rotation_deg,
            path.max_rotation_step_deg,
            path.jumps,
            path.rotation_jumps
        );
        out += &format!(
            "  static depth consistency: {:.3} over {} frame pairs\n",
            self.static_depth_consistency,
            self.pairs.len()
        );
        if let Some(stretch) = &self.worst_stretch {
            out += &format!(
                "    worst stretch: frames {} | {}: {:.3} of {} points across it agree ({} across a typical boundary; \
                 wider pairs across it {}, elsewhere {})\n",
                stretch.before,
                stretch.after,
                stretch.consistency,
                stretch.compared,
                number(self.typical_stretch),
                number(stretch.wider),
                number(stretch.wider_elsewhere)
            );
        }
        let mut worst: Vec<&PairConsistency> = self.pairs.iter().filter(|p| p.compared > 0).collect();
        worst.sort_by(|a, b| a.share.total_cmp(&b.share));
        for pair in worst.iter().take(WORST_PAIRS_SHOWN) {
            out += &format!(
                "    frames {} → {}: {:.3} of {} points agree\n",
                pair.from, pair.to, pair.share, pair.compared
            );
        }
        out += "  convention probes (reprojection residual as read vs with the slip undone, on the frame pairs that can tell):\n";
        for probe in &self.convention_probes {
            let outcome = match probe.outcome {
                ProbeOutcome::Rejected => "rejected",
                ProbeOutcome::FitsBetter => "FITS BETTER",
                ProbeOutcome::Undetermined => "undetermined",
            };
            out += &format!(
                "    {}: {outcome} ({:.3} vs {:.3}, {} of {} pairs can tell, shifts up to {:.1} px)\n",
                probe.slip.label(),
                probe.as_read,
                probe.alternative,
                probe.informative_pairs,
                probe.probe_pairs,
                probe.largest_shift_px
            );
        }
        out += &format!("verdict: {}\n", self.verdict);
        for reason in &self.reasons {
            out += &format!("  - {reason}\n");
        }
        for note in &self.notes {
            out += &format!("  note: {note}\n");
        }
        out
    }
}

/// A share for the text report, `-` when absent.
fn number(value: Option<f64>) -> String {
    value.map_or("-".to_owned(), |v| format!("{v:.3}"))
}

/// Frame pairs listed in the text report, worst first (the JSON has them all).
const WORST_PAIRS_SHOWN: usize = 3;

/// Reads the sequence folder `dir` (in `layout`, or the detected one) and checks it.
pub fn check_folder(
    dir: &std::path::Path,
    layout: Option<crate::io::sequence::LayoutName>,
    config: &CheckConfig,
) -> crate::error::Result<CheckReport> {
    check_folder_with(dir, layout, &crate::io::sequence::ReadOptions::default(), config)
}

/// [`check_folder`], reading the folder with `options`.
pub fn check_folder_with(
    dir: &std::path::Path,
    layout: Option<crate::io::sequence::LayoutName>,
    options: &crate::io::sequence::ReadOptions,
    config: &CheckConfig,
) -> crate::error::Result<CheckReport> {
    use crate::io::sequence::{Layout, detect_layout, layout_named, read_sequence_with};
    let layout = match layout {
        Some(name) => layout_named(dir, name)?,
        None => detect_layout(dir)?,
    };
    let sequence = read_sequence_with(dir, Some(layout.name()), options)?;
    let metric = matches!(layout, Layout::Vipe(_));
    Ok(check_sequence(&sequence, layout.name().as_str(), layout.conventions(), metric, config))
}
