//! `datagen view`: a sequence and its pairs as a Rerun recording ([`crate::inspect::view`]).

use std::path::PathBuf;

use clap::Args;

use crate::cli::flags::ReadArgs;
use crate::inspect::view::{DEFAULT_POINT_STRIDE, DEFAULT_SCRIPT, ViewOptions};

/// Arguments of `datagen view`.
#[derive(Debug, Args)]
pub struct ViewArgs {
    /// The sequence folder (or a multi-camera scene's, whose input camera is shown).
    pub seq_dir: PathBuf,
    /// How the folder is read.
    #[command(flatten)]
    pub read: ReadArgs,
    /// A shard of pairs made from this sequence (`datagen pairs`): its novel trajectories and
    /// co-visibility masks go into the recording.
    #[arg(long)]
    pub pairs: Option<PathBuf>,
    /// The recording to write (.rrd).
    #[arg(long)]
    pub out: PathBuf,
    /// Python interpreter with rerun-sdk installed.
    #[arg(long, default_value = "python3")]
    pub python: PathBuf,
    /// The script writing the recording [default: scripts/rerun_view.py of this source tree].
    #[arg(long)]
    pub script: Option<PathBuf>,
    /// Every N-th pixel in x and y becomes a point of the cloud.
    #[arg(long, default_value_t = DEFAULT_POINT_STRIDE)]
    pub point_stride: u32,
}

/// Runs `datagen view`.
pub fn run(args: ViewArgs) -> anyhow::Result<()> {
    let (sequence, _) = args.read.read_sequence(&args.seq_dir)?;
    let options = ViewOptions {
        python: args.python,
        script: args.script.unwrap_or_else(|| PathBuf::from(DEFAULT_SCRIPT)),
        point_stride: args.point_stride,
    };
    let summary = crate::inspect::view::write_recording(&sequence, args.pairs.as_deref(), &args.out, &options)?;
    println!(
        "wrote {} ({} frames, {} points, {} novel trajectories); open it with `rerun {}`",
        args.out.display(),
        summary.frames,
        summary.points,
        summary.trajectories,
        args.out.display()
    );
    Ok(())
}
