//! Flag groups several `datagen` commands share, defined once and flattened into each command's
//! arguments (`#[command(flatten)]`), so a flag reads and defaults the same everywhere.

use std::path::{Path, PathBuf};

use clap::Args;

use crate::io::layout::{FolderLayout, LayoutName, ReadOptions};
use crate::pairs::generator::PairsConfig;

/// Parses a `--layout` value: one name of the registry's one name set.
pub fn parse_layout(name: &str) -> Result<LayoutName, String> {
    name.parse()
}

/// How a folder is read: `--layout` and the tools' reading choices (`pairs`, `render`, `check`,
/// `view`).
#[derive(Debug, Clone, Args)]
pub struct ReadArgs {
    /// Layout of the folder: cog-nvs, megasam, generic, vipe, vggt, colmap, gen3c, depth-only
    /// (one camera) or dycheck, kubric4d, pardom4d (multi-camera scenes; generic also names a
    /// folder of camera sub-folders). A command that reads one sequence reads a scene's input
    /// camera [default: detected from its files; a folder matching several is an error listing
    /// them].
    #[arg(long, value_parser = parse_layout)]
    pub layout: Option<LayoutName>,
    /// VGGT output: drop depth whose depth_conf is below this percentile (0–100) of the
    /// sequence's confidences, as VGGT's viewers filter points (its demo's default is 50)
    /// [default: keep every finite depth].
    #[arg(long, value_name = "PERCENTILE")]
    pub vggt_conf_percentile: Option<f64>,
}

impl ReadArgs {
    /// The reading choices as the library takes them.
    pub fn options(&self) -> ReadOptions {
        ReadOptions { vggt_confidence_percentile: self.vggt_conf_percentile }
    }

    /// The one sequence a single-camera command reads from `dir` (a scene's input camera for a
    /// multi-camera layout), with the folder's layout.
    pub fn read_sequence(&self, dir: &Path) -> crate::Result<(crate::io::sequence::Sequence, FolderLayout)> {
        crate::io::layout::read_camera_sequence(dir, self.layout, &self.options())
    }
}

/// The pairs settings file, `--config` of `pairs` and `render`: [clip], [trajectory],
/// [covisibility], ... (defaults where absent).
pub fn pairs_config(path: Option<&PathBuf>) -> crate::Result<PairsConfig> {
    match path {
        Some(path) => PairsConfig::from_toml_file(path),
        None => Ok(PairsConfig::default()),
    }
}
