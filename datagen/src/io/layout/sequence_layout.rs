//! The single-camera half of the layout registry: for each [`LayoutName`] of one camera, how a
//! folder in it is recognised (its marking files, with the evidence an error lists), what naming
//! it with `--layout` resolves to, and which module reads it. Detection asks every layout and
//! takes the one that matches; a folder matching several is an error listing them, one matching
//! none an error saying what each layout needs.

use std::path::{Path, PathBuf};

use crate::error::{Error, Result};
use crate::io::layout::name::LayoutName;
use crate::io::layout::{cog_nvs, depth_only, generic, megasam};
use crate::io::reconstruction::{Parts, Reconstruction, assemble_tool, tool_reconstruction};
use crate::io::vipe::VipeArtifact;

/// Which layout a folder is in, with the file that marks it where a folder could hold several.
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

    /// Reads the folder `dir` in this layout: frames, depth and cameras, checked and assembled.
    pub(crate) fn read(&self, dir: &Path, options: &ReadOptions) -> Result<Parts> {
        match self {
            Self::CogNvs => cog_nvs::read(dir),
            Self::MegaSam(npz) => megasam::read(npz),
            Self::Generic => generic::read(dir),
            Self::Vipe(artifact) => assemble_tool(crate::io::vipe::read_vipe(artifact)?),
            Self::Vggt(path) => assemble_tool(crate::io::vggt::read_vggt(path, options.vggt_confidence_percentile)?),
            Self::Colmap => assemble_tool(crate::io::colmap::read_colmap(dir)?),
            Self::Gen3c => assemble_tool(crate::io::gen3c::read_gen3c(dir)?),
            Self::DepthOnly(path) => depth_only::read(dir, path),
        }
    }

    /// The reconstruction alone of the folder `dir` in this layout, for frames decoded elsewhere.
    pub(crate) fn reconstruction(&self, dir: &Path) -> Result<Reconstruction> {
        Ok(match self {
            Self::CogNvs => cog_nvs::reconstruction(dir)?,
            Self::MegaSam(npz) => megasam::reconstruction(npz, false)?.1,
            Self::Generic => generic::reconstruction(dir)?,
            Self::Vipe(artifact) => tool_reconstruction(crate::io::vipe::read_vipe_reconstruction(artifact)?).1,
            Self::Vggt(path) => tool_reconstruction(crate::io::vggt::read_vggt(path, None)?).1,
            Self::Colmap => tool_reconstruction(crate::io::colmap::read_colmap_reconstruction(dir)?).1,
            Self::Gen3c => tool_reconstruction(crate::io::gen3c::read_gen3c_reconstruction(dir)?).1,
            Self::DepthOnly(path) => depth_only::reconstruction(dir, path)?,
        })
    }
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

/// A layout found in a folder with its evidence (what an ambiguity error lists).
type Found = Vec<(Layout, String)>;

/// The layouts detection asks, in the order an ambiguity error lists them. The first three,
/// [`EXCLUSIVE`], can share a folder (a cog-nvs folder keeping the MegaSAM archive it was made
/// from): among them the first that matches is the folder's, as it always was.
const DETECTION_ORDER: [LayoutName; 8] = [
    LayoutName::CogNvs,
    LayoutName::MegaSam,
    LayoutName::Generic,
    LayoutName::Vggt,
    LayoutName::Gen3c,
    LayoutName::Vipe,
    LayoutName::Colmap,
    LayoutName::DepthOnly,
];

/// The layouts of which a folder is in the first that matches, never ambiguous among them.
const EXCLUSIVE: [LayoutName; 3] = [LayoutName::CogNvs, LayoutName::MegaSam, LayoutName::Generic];

/// What each layout needs, for the error on a folder that matches none.
const EXPECTED_LAYOUTS: &str = "expected gt_rgb.mp4 + cam_info/ (cog-nvs), *_sgd_cvd_hr.npz (MegaSAM), frames/ + depth/ + cameras.json (generic), \
     rgb/ + pose/ + intrinsics/ + depth/ (ViPE), predictions.npz (VGGT), images/ + sparse/ + stereo/depth_maps/ (COLMAP), \
     rgb.mp4 + depth.npz + camera.npz (GEN3C) or a depth-only tool's .npz + cameras.json";

/// How the single-camera layout `name` is recognised in `dir`: what it found, with the evidence.
fn find(name: LayoutName, dir: &Path) -> Result<Found> {
    let file_name = |p: &Path| p.file_name().unwrap_or_default().to_string_lossy().into_owned();
    Ok(match name {
        LayoutName::CogNvs if cog_nvs::recognised(dir) => {
            vec![(Layout::CogNvs, "cog-nvs (gt_rgb.mp4 / cam_info/)".to_owned())]
        }
        LayoutName::MegaSam => megasam::archive(dir)?
            .map(|npz| {
                let evidence = format!("megasam ({})", file_name(&npz));
                (Layout::MegaSam(npz), evidence)
            })
            .into_iter()
            .collect(),
        LayoutName::Generic if generic::recognised(dir)? => {
            vec![(Layout::Generic, "generic (depth/*.exr or cameras.json)".to_owned())]
        }
        LayoutName::Vggt => {
            let predictions = dir.join(crate::io::vggt::PREDICTIONS_FILE);
            if predictions.is_file() {
                vec![(Layout::Vggt(predictions), "vggt (predictions.npz)".to_owned())]
            } else {
                vec![]
            }
        }
        LayoutName::Gen3c if dir.join(crate::io::gen3c::CAMERA_FILE).is_file() => {
            vec![(Layout::Gen3c, "gen3c (camera.npz)".to_owned())]
        }
        LayoutName::Vipe if dir.join("pose").is_dir() && dir.join("intrinsics").is_dir() => {
            crate::io::vipe::vipe_artifacts(dir)?
                .into_iter()
                .map(|artifact| {
                    let evidence = format!("vipe (pose/{}.npz)", artifact.name);
                    (Layout::Vipe(artifact), evidence)
                })
                .collect()
        }
        LayoutName::Colmap if crate::io::colmap::sparse_model_dir(dir).is_some() => {
            vec![(Layout::Colmap, "colmap (sparse model)".to_owned())]
        }
        LayoutName::DepthOnly => depth_only::archives(dir)?
            .into_iter()
            .map(|file| {
                let evidence = format!("depth-only ({} + cameras.json)", file_name(&file));
                (Layout::DepthOnly(file), evidence)
            })
            .collect(),
        _ => Vec::new(),
    })
}

/// What naming the single-camera layout `name` for `dir` resolves to: the layouts whose reader
/// checks the files themselves are taken as named; the ones that pick a file list every
/// candidate (several are refused by [`layout_named`]).
fn named(name: LayoutName, dir: &Path) -> Result<Found> {
    let taken = |layout| Ok(vec![(layout, String::new())]);
    match name {
        LayoutName::CogNvs => taken(Layout::CogNvs),
        LayoutName::Generic => taken(Layout::Generic),
        LayoutName::Colmap => taken(Layout::Colmap),
        LayoutName::Gen3c => taken(Layout::Gen3c),
        LayoutName::Vggt => taken(Layout::Vggt(dir.join(crate::io::vggt::PREDICTIONS_FILE))),
        LayoutName::MegaSam => {
            Ok(megasam::archive(dir)?.map(|p| (Layout::MegaSam(p), String::new())).into_iter().collect())
        }
        LayoutName::Vipe => Ok(crate::io::vipe::vipe_artifacts(dir)?
            .into_iter()
            .map(|a| {
                let name = a.name.clone();
                (Layout::Vipe(a), name)
            })
            .collect()),
        LayoutName::DepthOnly => Ok(crate::io::depth_only::depth_only_files(dir)?
            .into_iter()
            .map(|p| {
                let name = p.display().to_string();
                (Layout::DepthOnly(p), name)
            })
            .collect()),
        LayoutName::Dycheck | LayoutName::Kubric4d | LayoutName::Pardom4d => Err(Error::invalid(
            dir,
            "layout",
            format!(
                "{name} is a multi-camera layout, not a sequence folder's: read the scene (its input camera) instead"
            ),
        )),
    }
}

/// Every single-camera layout whose files are in `dir`, with the evidence.
fn layout_candidates(dir: &Path) -> Result<Found> {
    let mut found = Vec::new();
    let mut exclusive_found = false;
    for name in DETECTION_ORDER {
        let exclusive = EXCLUSIVE.contains(&name);
        if exclusive && exclusive_found {
            continue;
        }
        let matches = find(name, dir)?;
        exclusive_found |= exclusive && !matches.is_empty();
        found.extend(matches);
    }
    Ok(found)
}

/// Whether `dir` holds the files of any single-camera layout (one or several: an ambiguous
/// folder is still a sequence folder, whose reading then fails listing what was found).
pub fn has_layout_files(dir: &Path) -> bool {
    layout_candidates(dir).is_ok_and(|found| !found.is_empty())
}

/// Detects the single-camera layout of `dir` from its files; a folder matching none or several
/// is an error saying what was expected or listing what was found.
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
/// folder with several videos, or several depth-only archives, is still ambiguous). A
/// multi-camera layout is an error naming the folder and the layout.
pub fn layout_named(dir: &Path, name: LayoutName) -> Result<Layout> {
    if name == LayoutName::Vipe
        && let Some(artifact) = crate::io::vipe::vipe_artifact_of_file(dir)
    {
        return Ok(Layout::Vipe(artifact));
    }
    if !dir.is_dir() {
        return Err(Error::io(dir, std::io::Error::new(std::io::ErrorKind::NotFound, "sequence folder not found")));
    }
    let mut matching = named(name, dir)?;
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

/// The single-camera layout of `dir`: the named one, else the detected one.
pub fn layout_of(dir: &Path, name: Option<LayoutName>) -> Result<Layout> {
    match name {
        Some(name) => layout_named(dir, name),
        None => detect_layout(dir),
    }
}
