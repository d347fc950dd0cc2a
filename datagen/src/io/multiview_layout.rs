//! Multi-camera scenes in every layout this toolkit reads, by name or detected: the generic
//! synchronised folder ([`crate::io::multiview`]) and the benchmark datasets' own layouts
//! (DyCheck, Kubric-4D, ParallelDomain-4D), each converted at the door into one
//! [`MultiViewScene`].

use std::path::Path;

use crate::error::{Error, Result};
use crate::io::multiview::{MultiViewScene, camera_folders, read_multiview};

/// The multi-camera layouts by the names a `--layout` flag takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MultiViewLayoutName {
    /// `generic`: one sub-folder per camera, each a sequence folder ([`read_multiview`]).
    Generic,
    /// `dycheck`: DyCheck iPhone / Nerfies ([`crate::io::dycheck`]).
    Dycheck,
    /// `kubric4d`: Kubric-4D as GCD ships it ([`crate::io::kubric4d`]).
    Kubric4d,
    /// `pardom4d`: ParallelDomain-4D as GCD reads it ([`crate::io::pardom4d`]).
    Pardom4d,
}

impl MultiViewLayoutName {
    /// Every layout, in the order `--help` lists them.
    pub const ALL: [Self; 4] = [Self::Generic, Self::Dycheck, Self::Kubric4d, Self::Pardom4d];

    /// The name as the flag spells it.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Generic => "generic",
            Self::Dycheck => "dycheck",
            Self::Kubric4d => "kubric4d",
            Self::Pardom4d => "pardom4d",
        }
    }

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
}

impl std::fmt::Display for MultiViewLayoutName {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for MultiViewLayoutName {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        Self::ALL.into_iter().find(|l| l.as_str() == s).ok_or_else(|| {
            let names: Vec<&str> = Self::ALL.iter().map(|l| l.as_str()).collect();
            format!("unknown multi-camera layout `{s}`; one of: {}", names.join(", "))
        })
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
    match layout {
        MultiViewLayoutName::Generic => read_multiview(dir),
        MultiViewLayoutName::Dycheck => crate::io::dycheck::read_dycheck(dir, None),
        MultiViewLayoutName::Kubric4d => crate::io::kubric4d::read_kubric4d(dir),
        MultiViewLayoutName::Pardom4d => crate::io::pardom4d::read_pardom4d(dir),
    }
}
