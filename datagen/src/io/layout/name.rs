//! The one name set of the `--layout` flag, shared by every command that reads a folder: the
//! single-camera layouts (a video and its reconstruction) and the multi-camera ones (a
//! synchronised scene), each name saying which it is.

/// Whether a layout holds one camera's sequence or a synchronised multi-camera scene.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Cameras {
    /// One video with its reconstruction ([`crate::io::sequence::Sequence`]).
    One,
    /// A synchronised scene of several cameras ([`crate::io::multiview::MultiViewScene`]).
    Several,
}

/// Every layout by the name the `--layout` flag takes (and a corpus TOML's `layout` key).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum LayoutName {
    /// `cog-nvs`: `gt_rgb.mp4` + `cam_info/` ([`super::cog_nvs`]).
    CogNvs,
    /// `megasam`: a `*_sgd_cvd_hr.npz` ([`super::megasam`]).
    MegaSam,
    /// `generic`: the toolkit's own layout, a sequence folder (`frames/` or a video,
    /// `depth/*.exr`, `cameras.json`: [`super::generic`]) or a scene folder with one sequence
    /// folder per camera ([`crate::io::multiview`]); the folder's files say which.
    Generic,
    /// `vipe`: one video of ViPE's output folder ([`crate::io::vipe`]).
    Vipe,
    /// `vggt`: VGGT's `predictions.npz` ([`crate::io::vggt`]).
    Vggt,
    /// `colmap`: a COLMAP workspace ([`crate::io::colmap`]).
    Colmap,
    /// `gen3c`: GEN3C's per-video archive ([`crate::io::gen3c`]).
    Gen3c,
    /// `depth-only`: a depth-only tool's archive with `cameras.json` ([`crate::io::depth_only`]).
    DepthOnly,
    /// `dycheck`: DyCheck iPhone / Nerfies scenes ([`crate::io::dycheck`]).
    Dycheck,
    /// `kubric4d`: Kubric-4D as GCD ships it ([`crate::io::kubric4d`]).
    Kubric4d,
    /// `pardom4d`: ParallelDomain-4D as GCD reads it ([`crate::io::pardom4d`]).
    Pardom4d,
}

impl LayoutName {
    /// Every layout, in the order `--help` lists them: single-camera ones first.
    pub const ALL: [Self; 11] = [
        Self::CogNvs,
        Self::MegaSam,
        Self::Generic,
        Self::Vipe,
        Self::Vggt,
        Self::Colmap,
        Self::Gen3c,
        Self::DepthOnly,
        Self::Dycheck,
        Self::Kubric4d,
        Self::Pardom4d,
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
            Self::Dycheck => "dycheck",
            Self::Kubric4d => "kubric4d",
            Self::Pardom4d => "pardom4d",
        }
    }

    /// What a folder in this layout holds. `generic` holds either: it is listed with
    /// [`Cameras::One`], and also read as a scene where a folder holds camera sub-folders.
    pub fn cameras(self) -> Cameras {
        match self {
            Self::Dycheck | Self::Kubric4d | Self::Pardom4d => Cameras::Several,
            _ => Cameras::One,
        }
    }
}

impl std::fmt::Display for LayoutName {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
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

impl TryFrom<String> for LayoutName {
    type Error = String;

    fn try_from(name: String) -> std::result::Result<Self, String> {
        name.parse()
    }
}

impl From<LayoutName> for String {
    fn from(name: LayoutName) -> Self {
        name.as_str().to_owned()
    }
}

/// The multi-camera layouts, by the names a `--layout` flag takes: the [`LayoutName`]s a scene
/// folder can be in (`generic` among them).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum MultiViewLayoutName {
    /// `generic`: one sub-folder per camera, each a sequence folder ([`crate::io::multiview`]).
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
        LayoutName::from(self).as_str()
    }
}

impl From<MultiViewLayoutName> for LayoutName {
    fn from(name: MultiViewLayoutName) -> Self {
        match name {
            MultiViewLayoutName::Generic => Self::Generic,
            MultiViewLayoutName::Dycheck => Self::Dycheck,
            MultiViewLayoutName::Kubric4d => Self::Kubric4d,
            MultiViewLayoutName::Pardom4d => Self::Pardom4d,
        }
    }
}

impl LayoutName {
    /// The multi-camera layout of this name, if a scene folder can be in it.
    pub fn multiview(self) -> Option<MultiViewLayoutName> {
        MultiViewLayoutName::ALL.into_iter().find(|m| LayoutName::from(*m) == self)
    }

    /// This name if a sequence folder can be in it (every name but the datasets' scene layouts).
    pub fn sequence(self) -> Option<Self> {
        (self.cameras() == Cameras::One).then_some(self)
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
