//! `datagen check`: the reconstruction check of one sequence ([`crate::geometry::consistency`]).

use std::path::PathBuf;

use clap::Args;

use crate::cli::flags::ReadArgs;
use crate::geometry::consistency::{CheckConfig, CheckReport, check_folder_with, check_sequence};
use crate::io::layout::{FolderLayout, folder_layout, read_camera_sequence};

/// Arguments of `datagen check`.
#[derive(Debug, Args)]
pub struct CheckArgs {
    /// The sequence folder (or a multi-camera scene's, whose input camera is checked).
    pub seq_dir: PathBuf,
    /// How the folder is read.
    #[command(flatten)]
    pub read: ReadArgs,
    /// Print the report as JSON (verdict, reasons, static_depth_consistency, per-pair shares, ...).
    #[arg(long)]
    pub json: bool,
    /// TOML with the check's settings (depth_tolerance, min_consistency, min_valid_depth_share,
    /// frame_gaps, pixel_stride, jump_factor), as the [check] table of a corpus TOML.
    #[arg(long)]
    pub config: Option<PathBuf>,
}

impl CheckArgs {
    /// The check's report on the folder: a sequence folder as [`check_folder_with`] reads it, a
    /// scene (a multi-camera `--layout`) by its input camera.
    pub fn report(&self) -> anyhow::Result<CheckReport> {
        let config = match &self.config {
            Some(path) => crate::config_file::load_toml(path)?,
            None => CheckConfig::default(),
        };
        if let Some(name) = self.read.layout.filter(|name| name.multiview().is_some())
            && let FolderLayout::Scene(scene) = folder_layout(&self.seq_dir, Some(name))?
        {
            let (sequence, _) = read_camera_sequence(&self.seq_dir, Some(name), &self.read.options())?;
            let (conventions, metric) = scene.conventions();
            return Ok(check_sequence(&sequence, scene.as_str(), conventions, metric, &config));
        }
        Ok(check_folder_with(&self.seq_dir, self.read.layout, &self.read.options(), &config)?)
    }
}

/// Runs `datagen check`.
pub fn run(args: CheckArgs) -> anyhow::Result<()> {
    let report = args.report()?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", report.to_text());
    }
    Ok(())
}
