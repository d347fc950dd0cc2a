//! Reading one sequence folder (a video plus its reconstruction) in any of three layouts, into
//! frames, frame-resolution depth, per-frame cameras and optional dynamic masks:
//!
//! - **cog-nvs**: `gt_rgb.mp4` + `cam_info/megasam_depth.npy` (N,H,W), optional
//!   `cam_info/megasam_intrinsics.npy` (3,3) and `cam_info/megasam_c2ws.npy` (N,4,4). Depth at
//!   another resolution than the video is resampled (nearest, so depth edges stay sharp) and K
//!   scaled. Missing intrinsics: focal 500 px at the depth resolution, centred principal point;
//!   missing poses: identity (the public code's fallbacks).
//! - **MegaSAM native**: `*_sgd_cvd_hr.npz` with `images` (N,H,W,3) u8, `depths` (N,H,W),
//!   `intrinsic` (3,3) and `cam_c2w` (N,4,4).
//! - **generic**: `frames/*.png|jpg` (or the folder's one input video, [`frames_video`]), `depth/*.exr` (one
//!   float channel), `cameras.json`: `{"intrinsics": K or [K per frame], "world_from_camera":
//!   [4×4 per frame]}` with matrices as nested row lists or 9/16 row-major values.
//!
//! - the reconstruction tools' own outputs, read by their modules and converted at the door:
//!   **ViPE** ([`super::vipe`]), **VGGT** ([`super::vggt`]), **COLMAP** ([`super::colmap`]), the
//!   **GEN3C** per-video archive ([`super::gen3c`]) and **depth-only** tools (Video Depth
//!   Anything, DepthCrafter: [`super::depth_only`], with `cameras.json` for the cameras).
//!
//! The layout is detected from the files ([`detect_layout`]) or named ([`LayoutName`], the
//! `--layout` flag); a folder that matches several layouts is an error listing what was found.
//! Optional `masks/*.png` (palette or greyscale ids: 0 static, >0 object, 255 void) in any layout.
//! Every check failure names the file and the field.

use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4, DVec3};
use image::{GrayImage, RgbImage};
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::io::npy::{Axis, NdArray, NpzReader, read_npy_f32_planes, read_npy_f64, read_npy_f64_shaped};
use crate::io::tool_output::{ToolFrames, ToolOutput};
use crate::io::vipe::VipeArtifact;
use foundation::camera::{PinholeCamera, checked_intrinsics, checked_pose};
use foundation::depth::DepthMap;
use foundation::frames::read_frames;

/// Focal length in pixels (at the depth resolution) assumed when intrinsics are missing: the
/// public cog-nvs code's fallback.
pub const FALLBACK_FOCAL_PX: f64 = 500.0;

/// A video with its reconstruction, all at the video's resolution.
#[derive(Debug, Clone)]
pub struct Sequence {
    /// Id of the sequence (its folder name).
    pub source_id: String,
    /// The folder it was read from.
    pub path: PathBuf,
    /// Frame rate (0 if unknown).
    pub fps: f64,
    /// RGB frames.
    pub frames: Vec<RgbImage>,
    /// z-depth per frame at frame resolution.
    pub depth: Vec<DepthMap>,
    /// Camera per frame.
    pub cameras: Vec<PinholeCamera>,
    /// Dynamic-object id masks per frame, if the folder has them.
    pub dynamic_masks: Option<Vec<GrayImage>>,
    /// A second, more accurate depth per frame (LiDAR, a monocular estimator) for measured depth
    /// noise, if the user gave one ([`Sequence::load_second_depth`]).
    pub second_depth: Option<Vec<DepthMap>>,
}

impl Sequence {
    /// Reads a second depth source (a folder of `*.exr` or an `(N, H, W)` `.npy`, one map per
    /// frame), resampled to the frames' size.
    pub fn load_second_depth(&mut self, path: &Path) -> Result<()> {
        let (width, height) = self.size();
        self.second_depth = Some(read_depth_stack(path, self.len(), width, height)?);
        Ok(())
    }

    /// The sequence a stored clip was cut from, for its frames: decoded frames, depth and
    /// dynamic masks, and its cameras. Errors name the clip and the field.
    pub fn from_clip(record: &schemas::ClipRecord) -> Result<Self> {
        let id = &record.clip_id;
        let image = |bytes: &[u8], field: String| {
            image::load_from_memory_with_format(bytes, image::ImageFormat::Png)
                .map_err(|e| Error::Image { context: format!("{id}: {field}"), reason: e.to_string() })
        };
        let frames = record
            .frames
            .par_iter()
            .enumerate()
            .map(|(i, png)| Ok(image(png, format!("frames[{i}]"))?.to_rgb8()))
            .collect::<Result<Vec<_>>>()?;
        let depth = record
            .depth
            .par_iter()
            .enumerate()
            .map(|(i, exr)| {
                let (width, height) = (record.width as usize, record.height as usize);
                crate::io::depth_exr::decode_depth_exr_of_size(exr, &format!("{id}: depth[{i}]"), width, height)
            })
            .collect::<Result<Vec<_>>>()?;
        let dynamic_masks = match &record.dynamic_mask {
            Some(masks) => Some(
                masks
                    .par_iter()
                    .enumerate()
                    .map(|(i, png)| Ok(image(png, format!("dynamic_mask[{i}]"))?.to_luma8()))
                    .collect::<Result<Vec<_>>>()?,
            ),
            None => None,
        };
        // Stored cameras pass the same checks as read ones: a shard is user input too.
        let clip = Path::new(id);
        let cameras = record
            .intrinsics
            .iter()
            .zip(&record.world_from_camera)
            .enumerate()
            .map(|(i, (k, pose))| {
                Ok(PinholeCamera {
                    width: record.width,
                    height: record.height,
                    intrinsics: checked_intrinsics(clip, &format!("intrinsics[{i}]"), k)?,
                    world_from_camera: checked_pose(clip, &format!("world_from_camera[{i}]"), pose)?,
                })
            })
            .collect::<Result<_>>()?;
        Ok(Self {
            source_id: record.source_id.clone(),
            path: PathBuf::from(&record.source_path),
            fps: record.fps,
            frames,
            depth,
            cameras,
            dynamic_masks,
            second_depth: None,
        })
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// Whether the sequence has no frames (never true for a sequence returned by a reader).
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Frame width and height.
    pub fn size(&self) -> (u32, u32) {
        self.frames[0].dimensions()
    }
}

/// Which layout a folder is in.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Layout {
    /// `gt_rgb.mp4` + `cam_info/`.
    CogNvs,
    /// A `*_sgd_cvd_hr.npz`.
    MegaSam(PathBuf),
    /// `frames/` or a video, `depth/*.exr`, `cameras.json`.
    Generic,
    /// One video of ViPE's output folder.
    Vipe(VipeArtifact),
    /// VGGT's `predictions.npz`.
    Vggt(PathBuf),
    /// A COLMAP workspace: `images/`, `sparse/`, `stereo/depth_maps/`.
    Colmap,
    /// GEN3C's per-video archive: `rgb.mp4`, `depth.npz`, `mask.npz`, `camera.npz`.
    Gen3c,
    /// A depth-only tool's archive (this file) with `cameras.json` for the cameras.
    DepthOnly(PathBuf),
}

/// The layouts by the names the `--layout` flag takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LayoutName {
    /// `cog-nvs`
    CogNvs,
    /// `megasam`
    MegaSam,
    /// `generic`
    Generic,
    /// `vipe`
    Vipe,
    /// `vggt`
    Vggt,
    /// `colmap`
    Colmap,
    /// `gen3c`
    Gen3c,
    /// `depth-only`
    DepthOnly,
}

impl LayoutName {
    /// Every layout, in the order `--help` lists them.
    pub const ALL: [Self; 8] = [
        Self::CogNvs,
        Self::MegaSam,
        Self::Generic,
        Self::Vipe,
        Self::Vggt,
        Self::Colmap,
        Self::Gen3c,
        Self::DepthOnly,
    ];

    /// The name as the flag spells it.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::CogNvs => "cog-nvs",
            Self::MegaSam => "megasam",
            Self::Generic => "generic",
            Self::Vipe => "vipe",
            Self::Vggt => "vggt",
            Self::Colmap => "colmap",
            Self::Gen3c => "gen3c",
            Self::DepthOnly => "depth-only",
        }
    }
}

impl std::str::FromStr for LayoutName {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        Self::ALL.into_iter().find(|l| l.as_str() == s).ok_or_else(|| {
            let names: Vec<&str> = Self::ALL.iter().map(|l| l.as_str()).collect();
            format!("unknown layout `{s}`; one of: {}", names.join(", "))
        })
    }
}

impl Layout {
    /// The layout's name.
    pub fn name(&self) -> LayoutName {
        match self {
            Self::CogNvs => LayoutName::CogNvs,
            Self::MegaSam(_) => LayoutName::MegaSam,
            Self::Generic => LayoutName::Generic,
            Self::Vipe(_) => LayoutName::Vipe,
            Self::Vggt(_) => LayoutName::Vggt,
            Self::Colmap => LayoutName::Colmap,
            Self::Gen3c => LayoutName::Gen3c,
            Self::DepthOnly(_) => LayoutName::DepthOnly,
        }
    }

    /// What the layout's files declare and how they were converted: axes, pose direction, depth
    /// kind and units, as `datagen check` reports them.
    pub fn conventions(&self) -> &'static str {
        match self {
            Self::CogNvs | Self::MegaSam(_) => {
                "OpenCV axes; poses world_from_camera (MegaSAM cam_c2w), read as is; z-depth in MegaSAM's units (not metric)"
            }
            Self::Generic => {
                "OpenCV axes; poses world_from_camera (cameras.json), read as is; z-depth in the file's units"
            }
            Self::Vipe(_) => {
                "OpenCV axes; poses world_from_camera (ViPE cam2world), read as is; K from [fx, fy, cx, cy]; metric z-depth (metres)"
            }
            Self::Vggt(_) => {
                "OpenCV axes; extrinsic camera_from_world, inverted; z-depth in VGGT's normalised scene scale (not metric), all finite depth kept unless a depth_conf percentile is given"
            }
            Self::Colmap => {
                "OpenCV axes; qvec/tvec camera_from_world, inverted; pixel centres moved by -0.5; z-depth in the SfM model's units (not metric)"
            }
            Self::Gen3c => {
                "OpenCV axes; w2c camera_from_world, inverted; z-depth (near-metric), masked where mask.npz is false"
            }
            Self::DepthOnly(_) => {
                "OpenCV axes; poses world_from_camera from cameras.json (another tool); z-depth as declared by depth_kind"
            }
        }
    }
}

/// Whether the generic layout's files are in `dir`: `depth/*.exr`, or `cameras.json` with a
/// `depth/` folder or without a depth-only tool's archive beside it.
fn looks_generic(dir: &Path) -> Result<bool> {
    let depth = dir.join("depth");
    if depth.is_dir() && !with_extension(&depth, &["exr"])?.is_empty() {
        return Ok(true);
    }
    Ok(dir.join("cameras.json").is_file()
        && (depth.is_dir() || crate::io::depth_only::depth_only_files(dir)?.is_empty()))
}

/// Every layout whose files are in `dir`, with the evidence, for detection and its errors.
fn layout_candidates(dir: &Path) -> Result<Vec<(Layout, String)>> {
    let mut found = Vec::new();
    // The three original layouts keep their order of precedence among themselves.
    if dir.join("cam_info").is_dir() || dir.join("gt_rgb.mp4").is_file() {
        found.push((Layout::CogNvs, "cog-nvs (gt_rgb.mp4 / cam_info/)".to_owned()));
    } else if let Some(npz) = list(dir)?.into_iter().find(|p| p.to_string_lossy().ends_with("_sgd_cvd_hr.npz")) {
        let evidence = format!("megasam ({})", npz.file_name().unwrap_or_default().to_string_lossy());
        found.push((Layout::MegaSam(npz), evidence));
    } else if looks_generic(dir)? {
        found.push((Layout::Generic, "generic (depth/*.exr or cameras.json)".to_owned()));
    }
    let predictions = dir.join(crate::io::vggt::PREDICTIONS_FILE);
    if predictions.is_file() {
        found.push((Layout::Vggt(predictions), "vggt (predictions.npz)".to_owned()));
    }
    if dir.join(crate::io::gen3c::CAMERA_FILE).is_file() {
        found.push((Layout::Gen3c, "gen3c (camera.npz)".to_owned()));
    }
    if dir.join("pose").is_dir() && dir.join("intrinsics").is_dir() {
        for artifact in crate::io::vipe::vipe_artifacts(dir)? {
            let evidence = format!("vipe (pose/{}.npz)", artifact.name);
            found.push((Layout::Vipe(artifact), evidence));
        }
    }
    if crate::io::colmap::sparse_model_dir(dir).is_some() {
        found.push((Layout::Colmap, "colmap (sparse model)".to_owned()));
    }
    if dir.join("cameras.json").is_file() && !dir.join("depth").is_dir() {
        for file in crate::io::depth_only::depth_only_files(dir)? {
            let evidence =
                format!("depth-only ({} + cameras.json)", file.file_name().unwrap_or_default().to_string_lossy());
            found.push((Layout::DepthOnly(file), evidence));
        }
    }
    Ok(found)
}

/// Whether `dir` holds the files of any layout (one or several: an ambiguous folder is still a
/// sequence folder, whose reading then fails listing what was found).
pub fn has_layout_files(dir: &Path) -> bool {
    layout_candidates(dir).is_ok_and(|found| !found.is_empty())
}

/// What each layout needs, for the error on a folder that matches none.
const EXPECTED_LAYOUTS: &str = "expected gt_rgb.mp4 + cam_info/ (cog-nvs), *_sgd_cvd_hr.npz (MegaSAM), frames/ + depth/ + cameras.json (generic), \
     rgb/ + pose/ + intrinsics/ + depth/ (ViPE), predictions.npz (VGGT), images/ + sparse/ + stereo/depth_maps/ (COLMAP), \
     rgb.mp4 + depth.npz + camera.npz (GEN3C) or a depth-only tool's .npz + cameras.json";

/// Detects the layout of `dir` from its files; a folder matching none or several is an error
/// saying what was expected or listing what was found.
pub fn detect_layout(dir: &Path) -> Result<Layout> {
    if let Some(artifact) = crate::io::vipe::vipe_artifact_of_file(dir) {
        return Ok(Layout::Vipe(artifact));
    }
    if !dir.is_dir() {
        return Err(Error::io(dir, std::io::Error::new(std::io::ErrorKind::NotFound, "sequence folder not found")));
    }
    let mut found = layout_candidates(dir)?;
    match found.len() {
        0 => Err(Error::invalid(dir, "layout", format!("not a sequence folder: {EXPECTED_LAYOUTS}"))),
        1 => Ok(found.remove(0).0),
        _ => {
            let listed: Vec<String> = found.into_iter().map(|(_, evidence)| evidence).collect();
            Err(Error::invalid(
                dir,
                "layout",
                format!("ambiguous: the folder holds the files of {}; name one with --layout", listed.join(", ")),
            ))
        }
    }
}

/// The layout `name` of `dir`, when the user names it: its files must be there (a ViPE output
/// folder with several videos, or several depth-only archives, is still ambiguous).
pub fn layout_named(dir: &Path, name: LayoutName) -> Result<Layout> {
    if name == LayoutName::Vipe
        && let Some(artifact) = crate::io::vipe::vipe_artifact_of_file(dir)
    {
        return Ok(Layout::Vipe(artifact));
    }
    if !dir.is_dir() {
        return Err(Error::io(dir, std::io::Error::new(std::io::ErrorKind::NotFound, "sequence folder not found")));
    }
    let mut matching: Vec<(Layout, String)> = match name {
        LayoutName::CogNvs => vec![(Layout::CogNvs, String::new())],
        LayoutName::Generic => vec![(Layout::Generic, String::new())],
        LayoutName::Colmap => vec![(Layout::Colmap, String::new())],
        LayoutName::Gen3c => vec![(Layout::Gen3c, String::new())],
        LayoutName::Vggt => vec![(Layout::Vggt(dir.join(crate::io::vggt::PREDICTIONS_FILE)), String::new())],
        LayoutName::MegaSam => list(dir)?
            .into_iter()
            .filter(|p| p.to_string_lossy().ends_with("_sgd_cvd_hr.npz"))
            .take(1)
            .map(|p| (Layout::MegaSam(p), String::new()))
            .collect(),
        LayoutName::Vipe => crate::io::vipe::vipe_artifacts(dir)?
            .into_iter()
            .map(|a| {
                let name = a.name.clone();
                (Layout::Vipe(a), name)
            })
            .collect(),
        LayoutName::DepthOnly => crate::io::depth_only::depth_only_files(dir)?
            .into_iter()
            .map(|p| {
                let name = p.display().to_string();
                (Layout::DepthOnly(p), name)
            })
            .collect(),
    };
    match matching.len() {
        0 => Err(Error::invalid(dir, "layout", format!("no {} files found: {EXPECTED_LAYOUTS}", name.as_str()))),
        1 => Ok(matching.remove(0).0),
        _ => {
            let listed: Vec<String> = matching.into_iter().map(|(_, what)| what).collect();
            Err(Error::invalid(
                dir,
                "layout",
                format!(
                    "{} holds several {} outputs ({}): give one per folder",
                    dir.display(),
                    name.as_str(),
                    listed.join(", ")
                ),
            ))
        }
    }
}

fn list(dir: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    let mut paths: Vec<PathBuf> = entries.filter_map(|e| e.ok().map(|e| e.path())).collect();
    paths.sort();
    Ok(paths)
}

fn with_extension(dir: &Path, extensions: &[&str]) -> Result<Vec<PathBuf>> {
    Ok(list(dir)?
        .into_iter()
        .filter(|p| {
            p.extension().and_then(|e| e.to_str()).is_some_and(|e| extensions.iter().any(|x| e.eq_ignore_ascii_case(x)))
        })
        .collect())
}

/// Reads the sequence folder `dir` in whichever layout it is.
pub fn read_sequence(dir: &Path) -> Result<Sequence> {
    read_sequence_as(dir, None)
}

/// Reads the sequence folder `dir` in layout `layout`, or the detected one when `None`, with the
/// default [`ReadOptions`].
pub fn read_sequence_as(dir: &Path, layout: Option<LayoutName>) -> Result<Sequence> {
    read_sequence_with(dir, layout, &ReadOptions::default())
}

/// Choices a user makes about how a tool's output is read; the defaults keep everything the
/// tool gives.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ReadOptions {
    /// VGGT: drop depth whose `depth_conf` is below this percentile (0–100) of the sequence's
    /// confidences, as VGGT's demo viewers filter their point clouds (`--vggt-conf-percentile`;
    /// [`crate::io::vggt::confidence_threshold`]). `None`: every finite depth is kept.
    pub vggt_confidence_percentile: Option<f64>,
}

/// Reads the sequence folder `dir` in layout `layout` (or the detected one) with `options`.
pub fn read_sequence_with(dir: &Path, layout: Option<LayoutName>, options: &ReadOptions) -> Result<Sequence> {
    let layout = match layout {
        Some(name) => layout_named(dir, name)?,
        None => detect_layout(dir)?,
    };
    // A ViPE output folder holds its videos by name: the video's name is the sequence's id.
    let source_id = match &layout {
        Layout::Vipe(artifact) => artifact.name.clone(),
        _ => dir.file_name().unwrap_or_default().to_string_lossy().into_owned(),
    };
    let (fps, frames, depth_arrays, cameras) = match layout {
        Layout::CogNvs => read_cog_nvs(dir)?,
        Layout::MegaSam(npz) => read_megasam(&npz)?,
        Layout::Generic => read_generic(dir)?,
        Layout::Vipe(artifact) => assemble_tool(crate::io::vipe::read_vipe(&artifact)?)?,
        Layout::Vggt(path) => assemble_tool(crate::io::vggt::read_vggt(&path, options.vggt_confidence_percentile)?)?,
        Layout::Colmap => assemble_tool(crate::io::colmap::read_colmap(dir)?)?,
        Layout::Gen3c => assemble_tool(crate::io::gen3c::read_gen3c(dir)?)?,
        Layout::DepthOnly(path) => read_depth_only_folder(dir, &path)?,
    };
    let dynamic_masks = read_masks(dir, &frames)?;
    Ok(Sequence {
        source_id,
        path: dir.to_owned(),
        fps,
        frames,
        depth: depth_arrays,
        cameras,
        dynamic_masks,
        second_depth: None,
    })
}

type Parts = (f64, Vec<RgbImage>, Vec<DepthMap>, Vec<PinholeCamera>);

/// Depth maps at the reconstruction's resolution, one plane (row-major) per frame, in `f32`, the
/// precision they are kept in: no `f64` or whole-stack copy of a 49×480×720 stack (68 MB as f32).
#[derive(Debug, Clone, PartialEq)]
pub struct DepthStack {
    /// (frames, height, width) as the file declares it.
    pub shape: Vec<usize>,
    /// One map per frame.
    pub planes: Vec<Vec<f32>>,
}

impl DepthStack {
    fn from_array(array: NdArray<f32>) -> Self {
        Self { shape: array.shape.clone(), planes: array.into_planes() }
    }

    /// An `(N, H, W)` `.npy` stack, read plane by plane.
    fn read_npy(path: &Path) -> Result<Self> {
        let (shape, planes) = read_npy_f32_planes(path, &[Axis::Any, Axis::Pixels, Axis::Pixels])?;
        Ok(Self { shape, planes })
    }
}

/// The reconstruction part of a sequence: depth (N,H,W), optional K and poses, with their files.
struct Reconstruction {
    depth_path: PathBuf,
    depth: DepthStack,
    intrinsics: Option<(PathBuf, NdArray<f64>)>,
    poses: Option<(PathBuf, NdArray<f64>)>,
}

fn read_cog_nvs(dir: &Path) -> Result<Parts> {
    let video_path = dir.join("gt_rgb.mp4");
    // Decoding is mostly serial: read the reconstruction meanwhile.
    let (video, reconstruction) =
        rayon::join(|| foundation::video::decode_video(&video_path), || cog_nvs_reconstruction(dir));
    let video = video?;
    assemble(video.fps, video.frames, &video_path, reconstruction?)
}

/// Reads the reconstruction at `reconstruction` (a cog-nvs folder with `cam_info/`, a MegaSAM
/// `*_sgd_cvd_hr.npz` or a folder holding one, or a generic folder with `depth/` and
/// `cameras.json`) for frames decoded elsewhere (a dataset's video or JPEG folder).
pub fn read_with_frames(
    source_id: &str,
    reconstruction: &Path,
    fps: f64,
    frames: Vec<RgbImage>,
    frames_path: &Path,
) -> Result<Sequence> {
    let parts = if let Some(artifact) = crate::io::vipe::vipe_artifact_of_file(reconstruction) {
        tool_reconstruction(crate::io::vipe::read_vipe_reconstruction(&artifact)?).1
    } else if reconstruction.is_file() {
        megasam_reconstruction(reconstruction, false)?.1
    } else {
        match detect_layout(reconstruction)? {
            Layout::CogNvs => cog_nvs_reconstruction(reconstruction)?,
            Layout::MegaSam(npz) => megasam_reconstruction(&npz, false)?.1,
            Layout::Generic => generic_reconstruction(reconstruction)?,
            Layout::Vipe(artifact) => tool_reconstruction(crate::io::vipe::read_vipe_reconstruction(&artifact)?).1,
            Layout::Vggt(path) => tool_reconstruction(crate::io::vggt::read_vggt(&path, None)?).1,
            Layout::Colmap => tool_reconstruction(crate::io::colmap::read_colmap_reconstruction(reconstruction)?).1,
            Layout::Gen3c => tool_reconstruction(crate::io::gen3c::read_gen3c_reconstruction(reconstruction)?).1,
            Layout::DepthOnly(path) => depth_only_reconstruction(reconstruction, &path)?,
        }
    };
    let (fps, frames, depth, cameras) = assemble(fps, frames, frames_path, parts)?;
    let path = reconstruction.to_owned();
    Ok(Sequence {
        source_id: source_id.to_owned(),
        path,
        fps,
        frames,
        depth,
        cameras,
        dynamic_masks: None,
        second_depth: None,
    })
}

fn cog_nvs_reconstruction(dir: &Path) -> Result<Reconstruction> {
    let cam = dir.join("cam_info");
    let depth_path = cam.join("megasam_depth.npy");
    let depth = DepthStack::read_npy(&depth_path)?;
    let intrinsics_path = cam.join("megasam_intrinsics.npy");
    let intrinsics = if intrinsics_path.is_file() {
        let k = read_npy_f64_shaped(&intrinsics_path, &[Axis::Is(3), Axis::Is(3)])?;
        Some((intrinsics_path, k))
    } else {
        None
    };
    let poses_path = cam.join("megasam_c2ws.npy");
    let poses = if poses_path.is_file() { Some((poses_path.clone(), read_npy_f64(&poses_path)?)) } else { None };
    Ok(Reconstruction { depth_path, depth, intrinsics, poses })
}

/// The NumPy dtype (`<f4`, `|u1`, `|b1`, ...) of member `name` of the `.npz` at `path`, from the
/// member's header only; `None` if the archive has no such member.
fn npz_member_dtype(path: &Path, name: &str) -> Result<Option<String>> {
    let mut archive = NpzReader::open(path)?;
    if !archive.contains(name) {
        return Ok(None);
    }
    Ok(Some(archive.header(name, None)?.dtype))
}

/// MegaSAM stores `images` as uint8 0–255. A bool array is a mask, and a float array may hold 0–1
/// or 0–255 values: guessing would silently give black or saturated frames, so both are errors
/// (integer arrays are accepted when every value is in 0–255, checked when they are converted).
fn check_image_dtype(path: &Path, field: &str, dtype: &str) -> Result<()> {
    let kind = dtype.trim_start_matches(['<', '>', '|', '=']).chars().next();
    let reason = match kind {
        Some('b') => "is a boolean array (a mask?), not RGB images",
        Some('f') => {
            "is a float array: ambiguous (0–1 or 0–255?); store uint8 0–255, e.g. (images * 255).round().astype(np.uint8) for 0–1 values"
        }
        Some('u' | 'i') => return Ok(()),
        _ => "is not an integer array",
    };
    Err(Error::invalid(path, field, format!("dtype `{dtype}` {reason}")))
}

fn read_megasam(path: &Path) -> Result<Parts> {
    if let Some(dtype) = npz_member_dtype(path, "images")? {
        check_image_dtype(path, "images", &dtype)?;
    }
    let (images, reconstruction) = megasam_reconstruction(path, true)?;
    let images = images.ok_or_else(|| Error::array(path, Some("images.npy"), "missing from the archive"))?;
    let (n, h, w) = (images.shape[0], images.shape[1], images.shape[2]);
    if n == 0 || h == 0 || w == 0 {
        return Err(Error::invalid(path, "images", format!("zero-size frames: shape {:?}", images.shape)));
    }
    if let Some(i) = images.data.iter().position(|&v| !(0.0..=f32::from(u8::MAX)).contains(&v)) {
        return Err(Error::invalid(
            path,
            "images",
            format!("value {} in frame {} is outside 0–255 (RGB u8 expected)", images.data[i], i / (h * w * 3)),
        ));
    }
    let frames = images
        .data
        .chunks_exact(h * w * 3)
        .map(|frame| RgbImage::from_raw(w as u32, h as u32, frame.iter().map(|&v| v as u8).collect()).expect("sized"))
        .collect();
    // The MegaSAM depth is at the image resolution; `assemble` resamples if it is not.
    assemble(0.0, frames, path, reconstruction)
}

/// The arrays of a MegaSAM archive: the images (read only `with_images`: frames decoded
/// elsewhere replace them), and the reconstruction. Every member's header is checked against
/// the frame count of `images` first, so no member is inflated before its shape agrees with
/// its siblings'.
fn megasam_reconstruction(path: &Path, with_images: bool) -> Result<(Option<NdArray<f32>>, Reconstruction)> {
    let mut archive = NpzReader::open(path)?;
    let images_shape = archive.header("images", Some(&[Axis::Any, Axis::Pixels, Axis::Pixels, Axis::Is(3)]))?.shape;
    let images_spec: Vec<Axis> = images_shape.iter().map(|&n| Axis::Is(n)).collect();
    let frames = images_spec[0];
    let depth_spec = [frames, Axis::Pixels, Axis::Pixels];
    let intrinsic_spec = [Axis::Is(3), Axis::Is(3)];
    let poses_spec = [frames, Axis::Is(4), Axis::Is(4)];
    for (name, spec) in [("depths", &depth_spec[..]), ("intrinsic", &intrinsic_spec), ("cam_c2w", &poses_spec)] {
        archive.header(name, Some(spec))?;
    }
    // u8 values (other dtypes are refused first), exact in f32 at half the memory of f64.
    let images = if with_images { Some(archive.read_f32("images", &images_spec)?) } else { None };
    let depth = DepthStack::from_array(archive.read_f32("depths", &depth_spec)?);
    let intrinsic = archive.read_f64("intrinsic", &intrinsic_spec)?;
    let poses = archive.read_f64("cam_c2w", &poses_spec)?;
    let reconstruction = Reconstruction {
        depth_path: path.to_owned(),
        depth,
        intrinsics: Some((path.to_owned(), intrinsic)),
        poses: Some((path.to_owned(), poses)),
    };
    Ok((images, reconstruction))
}

/// The `intrinsics` of `cameras.json` as an `(3, 3)` (one K for all frames) or `(N, 3, 3)`
/// array. A single K is 9 numbers or 3 rows of 3; a per-frame list holds one such K per frame.
/// A list of 3 lists of 3 numbers is therefore one nested K, never 3 frames' K (a flat K has 9).
fn json_intrinsics(path: &Path, value: &serde_json::Value) -> Result<NdArray<f64>> {
    let field = "intrinsics";
    let single =
        |value| foundation::camera::json_matrix(value, 3, 3).map_err(|reason| Error::invalid(path, field, reason));
    let serde_json::Value::Array(items) = value else {
        return Err(single(value).unwrap_err());
    };
    let is_number_list =
        |v: &serde_json::Value| v.as_array().is_some_and(|r| r.iter().all(serde_json::Value::is_number));
    let one_k = items.iter().all(serde_json::Value::is_number)
        || (items.len() == 3 && items.iter().all(|r| is_number_list(r) && r.as_array().is_some_and(|r| r.len() == 3)));
    if one_k {
        return Ok(NdArray { shape: vec![3, 3], data: single(value)? });
    }
    let mut data = Vec::with_capacity(items.len() * 9);
    for (i, k) in items.iter().enumerate() {
        let values = foundation::camera::json_matrix(k, 3, 3)
            .map_err(|reason| Error::invalid(path, format!("{field}[{i}]"), reason))?;
        data.extend(values);
    }
    Ok(NdArray { shape: vec![items.len(), 3, 3], data })
}

/// The `world_from_camera` of `cameras.json`: one 4×4 pose per frame (nested rows or 16 values).
fn json_poses(path: &Path, value: &serde_json::Value) -> Result<NdArray<f64>> {
    let field = "world_from_camera";
    let Some(items) = value.as_array() else {
        return Err(Error::invalid(path, field, "expected a list of per-frame 4×4 matrices"));
    };
    let is_row = |v: &serde_json::Value| {
        v.as_array().is_some_and(|r| r.len() == 4 && r.iter().all(serde_json::Value::is_number))
    };
    if !items.is_empty()
        && (items.iter().all(serde_json::Value::is_number) || (items.len() == 4 && items.iter().all(is_row)))
    {
        return Err(Error::invalid(
            path,
            field,
            "a single matrix: expected a list of per-frame 4×4 matrices, one per frame",
        ));
    }
    let mut data = Vec::with_capacity(items.len() * 16);
    for (i, pose) in items.iter().enumerate() {
        let values = foundation::camera::json_matrix(pose, 4, 4)
            .map_err(|reason| Error::invalid(path, format!("{field}[{i}]"), reason))?;
        data.extend(values);
    }
    Ok(NdArray { shape: vec![items.len(), 4, 4], data })
}

/// The frames of `dir`: `frames/*.png|jpg`, else its one input video ([`frames_video`]).
fn read_frames_or_video(dir: &Path) -> Result<(f64, Vec<RgbImage>, PathBuf)> {
    let frames_dir = dir.join("frames");
    if frames_dir.is_dir() {
        let files = with_extension(&frames_dir, &["png", "jpg", "jpeg"])?;
        return Ok((0.0, read_frames(&files)?, frames_dir));
    }
    let video = frames_video(dir)?;
    let decoded = foundation::video::decode_video(&video)?;
    Ok((decoded.fps, decoded.frames, video))
}

/// Video file extensions a folder's frames may come in.
const VIDEO_EXTENSIONS: [&str; 5] = ["mp4", "mov", "mkv", "avi", "webm"];

/// Stem suffixes of the videos depth-only tools write *beside* their input, never frames:
/// DepthCrafter's `run.py` writes `NAME_depth.mp4` (the depth as grey video) and `NAME_vis.mp4`
/// (coloured); Video Depth Anything's `run.py` writes `NAME_vis.mp4` (Tencent/DepthCrafter and
/// DepthAnything/Video-Depth-Anything, `run.py`). `_depths` is Video Depth Anything's name for
/// its depth files, taken for a depth video too.
const TOOL_OUTPUT_VIDEO_SUFFIXES: [&str; 3] = ["_depth", "_depths", "_vis"];

/// Stem suffixes of the input video those tools save with their output, the frames their depth
/// belongs to (resized to the tool's working resolution): DepthCrafter's `NAME_input.mp4`, Video
/// Depth Anything's `NAME_src.mp4`.
const TOOL_INPUT_VIDEO_SUFFIXES: [&str; 2] = ["_input", "_src"];

/// The one video of `dir` that holds the frames. Videos a depth tool writes beside its input
/// (depth and visualisation videos, [`TOOL_OUTPUT_VIDEO_SUFFIXES`]) are never frames. Among the
/// rest, the tool's saved input `NAME_input`/`NAME_src` ([`TOOL_INPUT_VIDEO_SUFFIXES`]) wins over
/// the original `NAME` video it was made from: the depth belongs to the saved input's frames
/// (DepthCrafter's `--target-fps` drops frames, both tools resize). Any other choice between
/// several videos (or none) is an error naming them: a video is never picked by its sort order.
pub fn frames_video(dir: &Path) -> Result<PathBuf> {
    let videos = with_extension(dir, &VIDEO_EXTENSIONS)?;
    let stem = |p: &Path| p.file_stem().and_then(|s| s.to_str()).unwrap_or("").to_owned();
    let name = |p: &PathBuf| p.file_name().unwrap_or_default().to_string_lossy().into_owned();
    let (outputs, candidates): (Vec<PathBuf>, Vec<PathBuf>) =
        videos.into_iter().partition(|p| TOOL_OUTPUT_VIDEO_SUFFIXES.iter().any(|s| stem(p).ends_with(s)));
    let names = |paths: &[PathBuf]| paths.iter().map(name).collect::<Vec<_>>().join(", ");
    // The tool's saved input, when the other candidates are only the original it was made from.
    let original_of = |p: &Path| {
        let stem = stem(p);
        TOOL_INPUT_VIDEO_SUFFIXES.iter().find_map(|s| stem.strip_suffix(s).map(str::to_owned))
    };
    let tool_inputs: Vec<(&PathBuf, String)> =
        candidates.iter().filter_map(|p| original_of(p).map(|original| (p, original))).collect();
    if let [(input, original)] = tool_inputs.as_slice()
        && candidates.iter().all(|p| p == *input || stem(p) == *original)
    {
        return Ok((*input).clone());
    }
    match candidates.as_slice() {
        [one] => Ok(one.clone()),
        [] if outputs.is_empty() => Err(Error::invalid(dir, "frames", "no frames/ folder and no video file")),
        [] => Err(Error::invalid(
            dir,
            "frames",
            format!(
                "no input video: {} are a depth tool's depth or visualisation videos (names ending in {}), not frames; \
                 add the tool's input video (DepthCrafter's NAME_input.mp4, Video Depth Anything's NAME_src.mp4) or frames/",
                names(&outputs),
                TOOL_OUTPUT_VIDEO_SUFFIXES.join(", ")
            ),
        )),
        several => Err(Error::invalid(
            dir,
            "frames",
            format!(
                "ambiguous: several videos could be the frames ({}){}; keep only the one the depth was computed from \
                 (DepthCrafter's NAME_input.mp4, Video Depth Anything's NAME_src.mp4) or put the frames in frames/",
                names(several),
                if outputs.is_empty() {
                    String::new()
                } else {
                    format!(" besides the tool outputs {}", names(&outputs))
                }
            ),
        )),
    }
}

fn read_generic(dir: &Path) -> Result<Parts> {
    // Decoding is mostly serial: read the reconstruction meanwhile.
    let (frames, reconstruction) = rayon::join(|| read_frames_or_video(dir), || generic_reconstruction(dir));
    let (fps, frames, frames_source) = frames?;
    assemble(fps, frames, &frames_source, reconstruction?)
}

fn generic_reconstruction(dir: &Path) -> Result<Reconstruction> {
    let depth_dir = dir.join("depth");
    let depth = read_exr_folder(&depth_dir)?;
    let (cameras_path, _, intrinsics, poses) = read_cameras_json(dir)?;
    let intrinsics = Some((cameras_path.clone(), intrinsics));
    Ok(Reconstruction { depth_path: depth_dir, depth, intrinsics, poses: Some((cameras_path, poses)) })
}

/// A tool's output as the parts [`assemble`] checks: its frames (if it has them) and the
/// reconstruction, with K moved from the size it is given at to the depth maps' size.
fn tool_reconstruction(output: ToolOutput) -> (Option<ToolFrames>, Reconstruction) {
    let ToolOutput {
        frames,
        depth_path,
        depth_size: (width, height),
        depth,
        intrinsics_path,
        intrinsics_size,
        intrinsics,
        poses_path,
        world_from_camera,
    } = output;
    let n = depth.len();
    let k_at_depth: Vec<f64> = intrinsics
        .iter()
        .flat_map(|k| {
            let camera = PinholeCamera {
                width: intrinsics_size.0,
                height: intrinsics_size.1,
                intrinsics: foundation::camera::mat3_from_row_major(k),
                world_from_camera: DMat4::IDENTITY,
            };
            let at_depth = if intrinsics_size == (width as u32, height as u32) {
                camera
            } else {
                camera.resized(width as u32, height as u32)
            };
            foundation::camera::mat3_to_row_major(&at_depth.intrinsics)
        })
        .collect();
    let reconstruction = Reconstruction {
        depth_path,
        depth: DepthStack { shape: vec![n, height, width], planes: depth },
        intrinsics: Some((intrinsics_path, NdArray { shape: vec![intrinsics.len(), 3, 3], data: k_at_depth })),
        poses: Some((
            poses_path,
            NdArray { shape: vec![world_from_camera.len(), 4, 4], data: world_from_camera.concat() },
        )),
    };
    (frames, reconstruction)
}

/// A tool's output that holds its frames, checked and assembled like any layout.
fn assemble_tool(output: ToolOutput) -> Result<Parts> {
    let (frames, reconstruction) = tool_reconstruction(output);
    let frames = frames.expect("the tools' full readers decode their frames");
    assemble(frames.fps, frames.frames, &frames.path, reconstruction)
}

/// A depth-only tool's archive `depth_path` with the cameras of `cameras.json` in `dir`.
fn depth_only_reconstruction(dir: &Path, depth_path: &Path) -> Result<Reconstruction> {
    let cameras_file = dir.join("cameras.json");
    if !cameras_file.is_file() {
        return Err(Error::invalid(
            &cameras_file,
            "cameras",
            format!(
                "missing: {} holds depth only; depth-only tools give no cameras and none are invented: \
                 add cameras.json with `intrinsics` and `world_from_camera` from another tool",
                depth_path.display()
            ),
        ));
    }
    let (cameras_path, cameras, intrinsics, poses) = read_cameras_json(dir)?;
    crate::io::depth_only::check_depth_kind(&cameras_path, &cameras, depth_path)?;
    let (shape, planes) = crate::io::depth_only::read_depth_only(depth_path)?;
    Ok(Reconstruction {
        depth_path: depth_path.to_owned(),
        depth: DepthStack { shape, planes },
        intrinsics: Some((cameras_path.clone(), intrinsics)),
        poses: Some((cameras_path, poses)),
    })
}

fn read_depth_only_folder(dir: &Path, depth_path: &Path) -> Result<Parts> {
    let (frames, reconstruction) =
        rayon::join(|| read_frames_or_video(dir), || depth_only_reconstruction(dir, depth_path));
    let (fps, frames, frames_source) = frames?;
    assemble(fps, frames, &frames_source, reconstruction?)
}

/// `cameras.json` of `dir`: its path, the parsed document, and its `intrinsics` and
/// `world_from_camera` arrays.
fn read_cameras_json(dir: &Path) -> Result<(PathBuf, serde_json::Value, NdArray<f64>, NdArray<f64>)> {
    let cameras_path = dir.join("cameras.json");
    let text = std::fs::read_to_string(&cameras_path).map_err(|e| Error::io(&cameras_path, e))?;
    let cameras: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| Error::invalid(&cameras_path, "cameras", format!("invalid JSON: {e}")))?;
    if !cameras.is_object() {
        return Err(Error::invalid(
            &cameras_path,
            "cameras",
            "expected an object with `intrinsics` and `world_from_camera`",
        ));
    }
    let key = |name: &str| {
        cameras.get(name).ok_or_else(|| {
            Error::invalid(&cameras_path, name, "missing: cameras.json needs `intrinsics` and `world_from_camera`")
        })
    };
    let intrinsics = json_intrinsics(&cameras_path, key("intrinsics")?)?;
    let poses = json_poses(&cameras_path, key("world_from_camera")?)?;
    Ok((cameras_path, cameras, intrinsics, poses))
}

/// Checks counts and values across the parts and builds frame-resolution depth and cameras.
fn assemble(fps: f64, frames: Vec<RgbImage>, frames_path: &Path, reconstruction: Reconstruction) -> Result<Parts> {
    let Reconstruction { depth_path, depth, intrinsics, poses } = reconstruction;
    let depth_path = depth_path.as_path();
    let n = frames.len();
    let (width, height) = frames.first().map(RgbImage::dimensions).unwrap_or((0, 0));
    if n == 0 || width == 0 || height == 0 {
        return Err(Error::invalid(frames_path, "frames", "no frames or zero-size frames"));
    }
    if let Some(i) = frames.iter().position(|f| f.dimensions() != (width, height)) {
        let (found_w, found_h) = frames[i].dimensions();
        return Err(Error::invalid(
            frames_path,
            format!("frames[{i}]"),
            format!("size {found_w}x{found_h} differs from frame 0's {width}x{height}"),
        ));
    }
    if depth.shape.len() != 3 || depth.shape[0] != n {
        return Err(Error::invalid(
            depth_path,
            "depth",
            format!(
                "shape {:?} does not hold one (H, W) map per frame: {} has {n} frames",
                depth.shape,
                frames_path.display()
            ),
        ));
    }
    let (depth_h, depth_w) = (depth.shape[1], depth.shape[2]);
    if depth_h == 0 || depth_w == 0 {
        return Err(Error::invalid(depth_path, "depth", "zero-size depth maps"));
    }
    check_depth_orientation(depth_path, "depth", depth_w, depth_h, width, height)?;

    // Intrinsics at the depth resolution (the reconstruction's), then scaled to the frames.
    let at_depth_resolution = |k: DMat3| PinholeCamera {
        width: depth_w as u32,
        height: depth_h as u32,
        intrinsics: k,
        world_from_camera: DMat4::IDENTITY,
    };
    let intrinsics_per_frame: Vec<DMat3> = match &intrinsics {
        None => vec![
            DMat3::from_cols(
                DVec3::new(FALLBACK_FOCAL_PX, 0.0, 0.0),
                DVec3::new(0.0, FALLBACK_FOCAL_PX, 0.0),
                DVec3::new(depth_w as f64 / 2.0 - 0.5, depth_h as f64 / 2.0 - 0.5, 1.0),
            );
            n
        ],
        Some((path, k)) if k.shape == [3, 3] => vec![checked_intrinsics(path, "intrinsics", &k.data)?; n],
        Some((path, k)) if k.shape.len() == 3 && k.shape[1..] == [3, 3] => {
            if k.shape[0] != n {
                return Err(Error::invalid(path, "intrinsics", format!("{} matrices for {n} frames", k.shape[0])));
            }
            k.data
                .chunks_exact(9)
                .enumerate()
                .map(|(i, v)| checked_intrinsics(path, &format!("intrinsics[{i}]"), v))
                .collect::<foundation::Result<_>>()?
        }
        Some((path, k)) => {
            return Err(Error::invalid(
                path,
                "intrinsics",
                format!("expected shape (3, 3) or (N, 3, 3), found {:?}", k.shape),
            ));
        }
    };
    let poses_per_frame: Vec<DMat4> = match &poses {
        None => vec![DMat4::IDENTITY; n],
        Some((path, p)) => {
            if p.shape.len() != 3 || p.shape[1..] != [4, 4] {
                return Err(Error::invalid(
                    path,
                    "world_from_camera",
                    format!("expected shape (N, 4, 4), found {:?}", p.shape),
                ));
            }
            if p.shape[0] != n {
                return Err(Error::invalid(path, "world_from_camera", format!("{} poses for {n} frames", p.shape[0])));
            }
            p.data
                .chunks_exact(16)
                .enumerate()
                .map(|(i, v)| checked_pose(path, &format!("world_from_camera[{i}]"), v))
                .collect::<foundation::Result<_>>()?
        }
    };
    let cameras: Vec<PinholeCamera> = intrinsics_per_frame
        .iter()
        .zip(&poses_per_frame)
        .map(|(k, pose)| PinholeCamera { world_from_camera: *pose, ..at_depth_resolution(*k).resized(width, height) })
        .collect();

    let depth_maps = resample_stack(depth, width as usize, height as usize);
    if let Some(i) = depth_maps.iter().position(|d| !d.values.iter().any(|&v| v.is_finite() && v > 0.0)) {
        return Err(Error::invalid(depth_path, format!("depth[{i}]"), "every value is invalid (≤ 0, NaN or inf)"));
    }
    Ok((fps, frames, depth_maps, cameras))
}

/// Relative tolerance when comparing a depth map's aspect ratio with the frames': depth computed
/// at a reduced size rounds each side to a multiple of 8 or so (480×854 → 288×512 differs by
/// 0.1 %), far below the gap between a non-square aspect and its transpose.
const ASPECT_TOLERANCE: f64 = 0.01;

/// Depth at another resolution than the frames is legal (it is resampled, K scaled per axis), but
/// depth whose aspect ratio is the frames' transposed (and not also the frames' own, as for
/// near-square frames) was stored as (N, W, H): resampling it would silently stretch a rotated
/// depth map over the frames, so it is an error naming both shapes.
fn check_depth_orientation(
    path: &Path,
    field: &str,
    depth_w: usize,
    depth_h: usize,
    width: u32,
    height: u32,
) -> Result<()> {
    let aspect = |w: f64, h: f64| w / h;
    let frames_aspect = aspect(f64::from(width), f64::from(height));
    let close = |a: f64| (a / frames_aspect - 1.0).abs() <= ASPECT_TOLERANCE;
    let (depth_w, depth_h) = (depth_w as f64, depth_h as f64);
    if close(aspect(depth_h, depth_w)) && !close(aspect(depth_w, depth_h)) {
        return Err(Error::invalid(
            path,
            field,
            format!(
                "depth maps are {depth_h}x{depth_w} (H×W) but the frames are {height}x{width} (H×W): the depth looks \
                 stored transposed as (N, W, H); save it as (N, H, W) (e.g. depth.transpose(0, 2, 1))"
            ),
        ));
    }
    Ok(())
}

/// A folder of per-frame `*.exr` depth maps (sorted by name) as an `[N, H, W]` array; every map
/// must have the first one's size.
pub fn read_exr_folder(depth_dir: &Path) -> Result<DepthStack> {
    let depth_files = with_extension(depth_dir, &["exr"])?;
    let contents =
        depth_files.par_iter().map(|p| std::fs::read(p).map_err(|e| Error::io(p, e))).collect::<Result<Vec<_>>>()?;
    let context = |i: usize| depth_files[i].display().to_string();
    // Every header first: a map declaring another size fails before any is decoded.
    let sizes = contents
        .par_iter()
        .enumerate()
        .map(|(i, bytes)| crate::io::depth_exr::depth_exr_size(bytes, &context(i)))
        .collect::<Result<Vec<_>>>()?;
    let Some(&(w, h)) = sizes.first() else {
        return Err(Error::invalid(depth_dir, "depth", "no .exr files"));
    };
    if let Some(i) = sizes.iter().position(|&size| size != (w, h)) {
        let (found_w, found_h) = sizes[i];
        return Err(Error::invalid(
            &depth_files[i],
            "depth",
            format!("{found_w}x{found_h} differs from the first map's {w}x{h}"),
        ));
    }
    let depth_maps = contents
        .par_iter()
        .enumerate()
        .map(|(i, bytes)| crate::io::depth_exr::decode_depth_exr_of_size(bytes, &context(i), w, h))
        .collect::<Result<Vec<_>>>()?;
    Ok(DepthStack { shape: vec![depth_maps.len(), h, w], planes: depth_maps.into_iter().map(|m| m.values).collect() })
}

/// Per-frame depth maps from a folder of `*.exr` files or an `(N, H, W)` `.npy` array, resampled
/// (nearest) to `width × height`; there must be exactly `frames` of them.
pub fn read_depth_stack(path: &Path, frames: usize, width: u32, height: u32) -> Result<Vec<DepthMap>> {
    let stack = if path.is_dir() { read_exr_folder(path)? } else { DepthStack::read_npy(path)? };
    let (n, h, w) = (stack.shape[0], stack.shape[1], stack.shape[2]);
    if n != frames {
        return Err(Error::invalid(path, "depth", format!("{n} depth maps for {frames} frames")));
    }
    if h == 0 || w == 0 {
        return Err(Error::invalid(path, "depth", "zero-size depth maps"));
    }
    check_depth_orientation(path, "depth", w, h, width, height)?;
    Ok(resample_stack(stack, width as usize, height as usize))
}

/// Every map of a checked stack at `width × height`: moved as they are when they already have
/// that size, else resampled ([`resample_nearest`]).
fn resample_stack(stack: DepthStack, width: usize, height: usize) -> Vec<DepthMap> {
    let (h, w) = (stack.shape[1], stack.shape[2]);
    if (w, h) == (width, height) {
        return stack.planes.into_iter().map(|values| DepthMap { width, height, values }).collect();
    }
    stack.planes.par_iter().map(|map| resample_nearest(map, w, h, width, height)).collect()
}

/// Nearest-neighbour resampling with pixel centres at integer coordinates (no blending across
/// depth edges, which would invent surfaces between foreground and background).
pub fn resample_nearest(values: &[f32], width: usize, height: usize, to_width: usize, to_height: usize) -> DepthMap {
    let map = |to: usize, to_size: usize, size: usize| {
        (((to as f64 + 0.5) * size as f64 / to_size as f64 - 0.5).round().max(0.0) as usize).min(size - 1)
    };
    // The source column of each output column, computed once (not once per pixel).
    let columns: Vec<usize> = (0..to_width).map(|u| map(u, to_width, width)).collect();
    let mut out = Vec::with_capacity(to_width * to_height);
    for v in 0..to_height {
        let row = &values[map(v, to_height, height) * width..][..width];
        out.extend(columns.iter().map(|&u| row[u]));
    }
    DepthMap { width: to_width, height: to_height, values: out }
}

fn read_masks(dir: &Path, frames: &[RgbImage]) -> Result<Option<Vec<GrayImage>>> {
    let masks_dir = dir.join("masks");
    if !masks_dir.is_dir() {
        return Ok(None);
    }
    let files = with_extension(&masks_dir, &["png"])?;
    if files.len() != frames.len() {
        return Err(Error::invalid(&masks_dir, "masks", format!("{} masks for {} frames", files.len(), frames.len())));
    }
    let (width, height) = frames[0].dimensions();
    files
        .par_iter()
        .map(|path| {
            let mask = crate::io::annotations::read_id_png(path)?;
            Ok(if mask.dimensions() == (width, height) {
                mask
            } else {
                image::imageops::resize(&mask, width, height, image::imageops::FilterType::Nearest)
            })
        })
        .collect::<Result<Vec<_>>>()
        .map(Some)
}
