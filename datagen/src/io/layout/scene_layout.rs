//! The multi-camera half of the layout registry, and the one entry every command reads a folder
//! through: for each multi-camera [`LayoutName`], how a scene folder in it is recognised and
//! which module reads it (the generic synchronised folder, [`crate::io::multiview`], and the
//! benchmark datasets' own layouts: DyCheck, Kubric-4D, ParallelDomain-4D), each converted at the
//! door into one [`MultiViewScene`]; and [`folder_layout`], which says whether a folder (with
//! the `--layout` the user gave, if any) is a sequence or a scene.
//!
//! A command that reads one sequence (`render`, `check`, `view`, `trajectories collect`) given a
//! multi-camera layout reads the scene's input camera, the one its evaluation split feeds a
//! method ([`read_camera_sequence`]): DyCheck's training camera, GCD's input view of Kubric-4D
//! and ParallelDomain-4D. A scene without one (the generic folder, a DyCheck scene without
//! splits) is refused naming the folder and the layout.

use std::path::Path;

use crate::error::{Error, Result};
use crate::io::layout::name::{LayoutName, MultiViewLayoutName};
use crate::io::layout::sequence_layout::{Layout, ReadOptions, detect_layout, layout_named};
use crate::io::multiview::{MultiViewScene, camera_folders, read_multiview};
use crate::io::sequence::{Sequence, read_sequence_in};

impl MultiViewLayoutName {
    /// The files that mark the layout, for messages.
    fn evidence(self) -> &'static str {
        match self {
            Self::Generic => "two or more camera sub-folders, each a sequence folder (generic)",
            Self::Dycheck => "dataset.json + metadata.json + camera/ (dycheck)",
            Self::Kubric4d => "<scene>_p0_v0.json + frames_p0_v0/ (kubric4d)",
            Self::Pardom4d => "rgb/ + depth/ + calibration/ (pardom4d)",
        }
    }

    /// Whether `dir` holds the layout's marking files.
    fn matches(self, dir: &Path) -> bool {
        match self {
            Self::Generic => camera_folders(dir).is_some(),
            Self::Dycheck => crate::io::dycheck::is_dycheck(dir),
            Self::Kubric4d => crate::io::kubric4d::is_kubric4d(dir),
            Self::Pardom4d => crate::io::pardom4d::is_pardom4d(dir),
        }
    }

    /// Reads the scene folder `dir` in this layout. DyCheck scenes are read at `extra.json`'s
    /// factor (call [`crate::io::dycheck::read_dycheck`] for another).
    fn read(self, dir: &Path) -> Result<MultiViewScene> {
        match self {
            Self::Generic => read_multiview(dir),
            Self::Dycheck => crate::io::dycheck::read_dycheck(dir, None),
            Self::Kubric4d => crate::io::kubric4d::read_kubric4d(dir),
            Self::Pardom4d => crate::io::pardom4d::read_pardom4d(dir),
        }
    }

    /// What the layout's files declare and how they were converted, as `datagen check` reports
    /// them for the input camera, and whether its depth is metric (metres).
    pub fn conventions(self) -> (&'static str, bool) {
        match self {
            Self::Generic => ("each camera folder's own layout's conventions", false),
            Self::Dycheck => (
                "OpenCV axes; orientation camera_from_world with the camera centre, inverted; principal point moved by -0.5; z-depth in the dataset's world units",
                false,
            ),
            Self::Kubric4d => (
                "Blender camera axes turned to OpenCV, Z-up world in metres; ray-length depth converted to metric z-depth",
                true,
            ),
            Self::Pardom4d => ("OpenCV axes; world_from_camera in the ego rig's frame; metric z-depth (metres)", true),
        }
    }
}

/// Detects the multi-camera layout of `dir` from its files; a folder matching none or several is
/// an error saying what was expected or what was found.
pub fn detect_multiview_layout(dir: &Path) -> Result<MultiViewLayoutName> {
    if !dir.is_dir() {
        return Err(Error::io(dir, std::io::Error::new(std::io::ErrorKind::NotFound, "scene folder not found")));
    }
    let found: Vec<MultiViewLayoutName> = MultiViewLayoutName::ALL.into_iter().filter(|l| l.matches(dir)).collect();
    match found.as_slice() {
        [one] => Ok(*one),
        [] => {
            let expected: Vec<&str> = MultiViewLayoutName::ALL.iter().map(|l| l.evidence()).collect();
            let reason = format!("not a multi-camera scene: expected {}", expected.join(", or "));
            Err(Error::invalid(dir, "layout", reason))
        }
        several => {
            let listed: Vec<&str> = several.iter().map(|l| l.evidence()).collect();
            let reason =
                format!("ambiguous: the folder holds the files of {}; name one with --layout", listed.join(" and "));
            Err(Error::invalid(dir, "layout", reason))
        }
    }
}

/// Reads the multi-camera scene in `dir` in layout `layout`, or the detected one when `None`,
/// converted to the toolkit's conventions. DyCheck scenes are read at `extra.json`'s factor
/// (call [`crate::io::dycheck::read_dycheck`] for another).
pub fn read_multiview_as(dir: &Path, layout: Option<MultiViewLayoutName>) -> Result<MultiViewScene> {
    let layout = match layout {
        Some(layout) => layout,
        None => detect_multiview_layout(dir)?,
    };
    layout.read(dir)
}

/// What a folder is, by the registry: one camera's sequence or a multi-camera scene.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum FolderLayout {
    /// A sequence folder in this single-camera layout.
    Sequence(Layout),
    /// A scene folder in this multi-camera layout.
    Scene(MultiViewLayoutName),
}

/// The layout of `dir`, named (`--layout`) or detected. Detected: a scene when a multi-camera
/// layout matches (as `datagen pairs` has always tried first), else the sequence layout that
/// matches. Named: the multi-camera names are scenes; `generic` is a scene where the folder holds
/// camera sub-folders and none of the generic sequence files, else a sequence; the other names
/// are sequences (their files checked as [`layout_named`] does).
pub fn folder_layout(dir: &Path, name: Option<LayoutName>) -> Result<FolderLayout> {
    let Some(name) = name else {
        if let Ok(scene) = detect_multiview_layout(dir) {
            return Ok(FolderLayout::Scene(scene));
        }
        return Ok(FolderLayout::Sequence(detect_layout(dir)?));
    };
    match name.multiview() {
        Some(MultiViewLayoutName::Generic) => {
            let scene = dir.is_dir()
                && !crate::io::layout::generic::recognised(dir)?
                && MultiViewLayoutName::Generic.matches(dir);
            if scene { Ok(FolderLayout::Scene(MultiViewLayoutName::Generic)) } else { sequence(dir, name) }
        }
        Some(scene) => Ok(FolderLayout::Scene(scene)),
        None => sequence(dir, name),
    }
}

fn sequence(dir: &Path, name: LayoutName) -> Result<FolderLayout> {
    Ok(FolderLayout::Sequence(layout_named(dir, name)?))
}

/// The one sequence a single-camera command reads from `dir` with the `--layout` it was given:
/// the sequence folder as [`crate::io::sequence::read_sequence_with`] reads it; for a multi-camera layout (named, or
/// `generic` on a folder of camera sub-folders), the scene's input camera, or an error naming
/// the folder and the layout where the scene defines none. Also returns the folder's layout.
pub fn read_camera_sequence(
    dir: &Path,
    name: Option<LayoutName>,
    options: &ReadOptions,
) -> Result<(Sequence, FolderLayout)> {
    // Undetected folders stay sequence folders: a single-camera command detects only those.
    let layout = match name {
        None => FolderLayout::Sequence(detect_layout(dir)?),
        Some(_) => folder_layout(dir, name)?,
    };
    let sequence = match &layout {
        FolderLayout::Sequence(found) => read_sequence_in(dir, found, options)?,
        FolderLayout::Scene(scene_layout) => input_camera(dir, *scene_layout)?,
    };
    Ok((sequence, layout))
}

/// The input camera's sequence of the scene `dir` in `layout` (see the module documentation).
fn input_camera(dir: &Path, layout: MultiViewLayoutName) -> Result<Sequence> {
    let refuse = |why: &str| {
        Error::invalid(
            dir,
            "layout",
            format!(
                "{layout} is a multi-camera layout and {why}: this command reads one camera; give the folder of the \
                 camera to read"
            ),
        )
    };
    let mut scene = layout.read(dir)?;
    let Some(split) = scene.split.take() else {
        return Err(refuse("the scene defines no input camera"));
    };
    let index = scene.cameras.iter().position(|c| c.id == split.input);
    let Some(camera) = index.map(|i| scene.cameras.swap_remove(i)) else {
        return Err(refuse(&format!("its input camera `{}` is missing", split.input)));
    };
    if !camera.has_depth {
        return Err(refuse(&format!("its input camera `{}` has no depth", split.input)));
    }
    Ok(camera.sequence)
}
