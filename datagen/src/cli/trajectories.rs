//! `datagen trajectories`: harvesting a trajectory bank ([`crate::pairs::trajectory_bank`],
//! [`crate::corpus::harvest`]) and comparing the trajectory distributions of corpora.

use std::path::PathBuf;

use clap::{Args, Subcommand};

use crate::cli::flags::{pairs_config, parse_layout};
use crate::corpus::build::BuildConfig;
use crate::io::layout::LayoutName;
use crate::pairs::trajectory_bank::CollectSummary;

/// The `datagen trajectories` commands.
#[derive(Debug, Subcommand)]
pub enum TrajectoriesCommand {
    /// Harvest the source cameras' own motion over every clip window of a corpus (--config) or of
    /// one sequence folder into a trajectory bank (Parquet, schema in schemas/SCHEMA.md); static
    /// and degenerate windows are skipped and counted.
    Collect(CollectArgs),
    /// Print the distributions of trajectory parameters (azimuth/elevation span, radial change,
    /// path length) and of the co-visible fraction of one or more corpora side by side, and
    /// plot them as SVG histograms.
    Stats(StatsArgs),
}

/// Arguments of `datagen trajectories collect`.
#[derive(Debug, Args)]
pub struct CollectArgs {
    /// A sequence folder (instead of --config).
    pub seq_dir: Option<PathBuf>,
    /// Corpus TOML (as for `datagen build`): every video of its sources, windows from its
    /// [pairs.clip], R from its [pairs.trajectory] pivot_scale.
    #[arg(long, conflicts_with = "seq_dir")]
    pub config: Option<PathBuf>,
    /// For a sequence folder: its layout, as `--layout` of `datagen pairs` (a multi-camera
    /// layout gives the scene's input camera) [default: detected from its files]. Not the shared
    /// flag group: it requires the folder, which --config replaces.
    #[arg(long, value_parser = parse_layout, requires = "seq_dir")]
    pub layout: Option<LayoutName>,
    /// For a sequence folder: TOML with [clip] and [trajectory] (as for `datagen pairs`).
    #[arg(long, requires = "seq_dir")]
    pub pairs_config: Option<PathBuf>,
    /// For a sequence folder: dataset name recorded with its entries.
    #[arg(long, default_value = "sequence")]
    pub dataset: String,
    /// The bank file to write.
    #[arg(long)]
    pub out: PathBuf,
}

impl CollectArgs {
    /// The harvest these arguments ask for: a corpus's or one folder's.
    pub fn collect(&self) -> anyhow::Result<CollectSummary> {
        Ok(match (&self.config, &self.seq_dir) {
            (Some(config), _) => crate::corpus::harvest::collect_from_corpus(&BuildConfig::from_toml_file(config)?)?,
            (None, Some(seq_dir)) => {
                let config = pairs_config(self.pairs_config.as_ref())?;
                crate::pairs::trajectory_bank::collect_from_folder(
                    seq_dir,
                    self.layout,
                    &self.dataset,
                    &config.clip,
                    config.trajectory.pivot_scale,
                )?
            }
            (None, None) => anyhow::bail!("parameter `config`: give --config CORPUS.toml or a sequence folder"),
        })
    }
}

/// Arguments of `datagen trajectories stats`.
#[derive(Debug, Args)]
pub struct StatsArgs {
    /// LABEL=DIR pairs: a corpus folder (or shard) and the name it gets in the table and plots.
    #[arg(required = true)]
    pub corpora: Vec<String>,
    /// Write one SVG histogram per quantity into this folder.
    #[arg(long)]
    pub plots: Option<PathBuf>,
}

impl StatsArgs {
    /// The corpora as (label, folder).
    pub fn corpora(&self) -> anyhow::Result<Vec<(String, PathBuf)>> {
        self.corpora
            .iter()
            .map(|pair| match pair.split_once('=') {
                Some((label, dir)) if !label.is_empty() => Ok((label.to_owned(), PathBuf::from(dir))),
                _ => anyhow::bail!("parameter `corpora`: `{pair}` is not LABEL=DIR"),
            })
            .collect()
    }
}

/// Runs a `datagen trajectories` command.
pub fn run(command: TrajectoriesCommand) -> anyhow::Result<()> {
    match command {
        TrajectoriesCommand::Collect(args) => collect(&args),
        TrajectoriesCommand::Stats(args) => {
            print!("{}", crate::inspect::report::compare_corpora(&args.corpora()?, args.plots.as_deref())?);
            if let Some(plots) = &args.plots {
                println!("plots in {}", plots.display());
            }
            Ok(())
        }
    }
}

fn collect(args: &CollectArgs) -> anyhow::Result<()> {
    let summary = args.collect()?;
    for (input, reason) in &summary.failed_inputs {
        println!("failed: {input}: {reason}");
    }
    if summary.entries.is_empty() {
        anyhow::bail!(
            "{}: no moving windows found ({} windows: {} static, {} degenerate); no bank written",
            args.out.display(),
            summary.windows,
            summary.static_windows,
            summary.degenerate_windows
        );
    }
    schemas::write_bank(&args.out, &summary.entries)?;
    println!(
        "wrote {}: {} entries from {} windows ({} static and {} degenerate skipped, {} inputs failed)",
        args.out.display(),
        summary.entries.len(),
        summary.windows,
        summary.static_windows,
        summary.degenerate_windows,
        summary.failed_inputs.len()
    );
    Ok(())
}
