//! `datagen render`: a sequence rendered along a novel camera path, the inference-time
//! conditioning ([`crate::pairs::generator::render_sequence`]).

use std::path::PathBuf;

use clap::Args;

use crate::cli::flags::{ReadArgs, pairs_config};

/// Arguments of `datagen render`.
#[derive(Debug, Args)]
pub struct RenderArgs {
    /// The sequence folder (or a multi-camera scene's, whose input camera is rendered).
    pub seq_dir: PathBuf,
    /// How the folder is read.
    #[command(flatten)]
    pub read: ReadArgs,
    /// The novel camera path (.npy, .json or trajs/*.txt).
    #[arg(long)]
    pub trajectory: PathBuf,
    /// Output folder.
    #[arg(long)]
    pub out: PathBuf,
    /// TOML file with [covisibility] and [static_background] settings.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Fill the holes of each frame's render with the static background fused from all frames
    /// (points outside the dynamic-object masks, voxel-deduplicated).
    #[arg(long)]
    pub stack_background: bool,
}

/// Runs `datagen render`.
pub fn run(args: RenderArgs) -> anyhow::Result<()> {
    let config = pairs_config(args.config.as_ref())?;
    let (sequence, _) = args.read.read_sequence(&args.seq_dir)?;
    let summary = crate::pairs::generator::render_sequence(
        &sequence,
        &args.trajectory,
        &args.out,
        &config,
        args.stack_background,
    )?;
    println!("wrote {} frames to {} (render.mp4, frames/, holes/)", summary.frames, args.out.display());
    let pixels = (summary.frames as f64 * f64::from(sequence.size().0) * f64::from(sequence.size().1)).max(1.0);
    print!("  holes: {:.2} % of pixels", 100.0 * summary.holes as f64 / pixels);
    if args.stack_background {
        print!(
            ", {:.2} % after filling from the stacked background",
            100.0 * (summary.holes - summary.filled) as f64 / pixels
        );
    }
    println!();
    Ok(())
}
