//! The `datagen` command line as a library: one file per command, each holding its clap
//! arguments, their conversion into the library's request, and the run that prints what the
//! command prints; shared flag groups in [`flags`]. The binary (`main.rs`) only parses and maps
//! the result to an exit code, so a test or another program calls exactly what a command calls.

pub mod build;
pub mod check;
pub mod flags;
pub mod inspect;
pub mod pairs;
pub mod render;
pub mod synth;
pub mod synth_corpus;
pub mod trajectories;
pub mod validate;
pub mod view;

use clap::{Parser, Subcommand};

/// Self-supervised CogNVS training pairs from videos and their 3D reconstructions.
#[derive(Debug, Parser)]
#[command(name = "datagen", version, about, long_about = None)]
pub struct Cli {
    /// The command to run.
    #[command(subcommand)]
    pub command: Command,
}

/// Every `datagen` command.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Generate a synthetic dynamic scene (ray traced, exact ground truth) as a sequence folder in
    /// the cog-nvs layout: gt_rgb.mp4, cam_info/megasam_*.npy, masks/, plus a contact sheet.
    Synth(synth::SynthArgs),
    /// Turn one sequence folder (cog-nvs, MegaSAM npz, generic, or a ViPE, VGGT, COLMAP, GEN3C or
    /// depth-only tool's output) into training pairs:
    /// one finished shard holding each clip once and one entry per trajectory.
    Pairs(pairs::PairsArgs),
    /// Check a reconstruction before spending GPU hours on it: the convention and units, the
    /// camera path (length, speed, jumps), the valid-depth share and the multi-frame consistency
    /// of static geometry, with a verdict `ok` or `suspect` and the reasons.
    Check(check::CheckArgs),
    /// Write a sequence (and the pairs of a shard made from it) as a recording for the Rerun
    /// viewer (`pip install rerun-sdk`, then `rerun FILE.rrd`): per frame the coloured point
    /// cloud, the source camera with its image, the novel trajectories as camera frusta and their
    /// co-visibility masks.
    View(view::ViewArgs),
    /// Render a sequence from a novel camera path: the inference-time conditioning
    /// (render.mp4, frames/%05d.png and holes/%05d.png, 255 = hole).
    Render(render::RenderArgs),
    /// Print statistics of a shard or corpus folder; with --export, write every pair as image
    /// folders, meta.json and a contact sheet (target | mask | cond | novel render).
    Inspect(inspect::InspectArgs),
    /// Build a corpus from dataset trees (SA-V, TAO, YouTube-VOS, DAVIS, sequence folders),
    /// resumably, on one machine or many (--num-workers/--worker-index or Slurm/Kubernetes).
    Build(build::BuildArgs),
    /// Check every shard of a folder against its stats marker and the schema.
    Validate(validate::ValidateArgs),
    /// Write a small corpus of synthetic videos in every dataset layout (SA-V, TAO, YouTube-VOS,
    /// DAVIS, sequence folders) with reconstructions, annotations and a corpus.toml, to try or
    /// benchmark `datagen build`.
    SynthCorpus(synth_corpus::SynthCorpusArgs),
    /// Trajectory banks: real camera motion harvested from reconstructions, for
    /// `[trajectory] sampler = "bank" | "mixed"`.
    Trajectories {
        /// The trajectories command to run.
        #[command(subcommand)]
        command: trajectories::TrajectoriesCommand,
    },
}

impl Command {
    /// Runs the command, printing what it prints.
    pub fn run(self) -> anyhow::Result<()> {
        match self {
            Self::Synth(args) => synth::run(args),
            Self::Pairs(args) => pairs::run(args),
            Self::Check(args) => check::run(args),
            Self::View(args) => view::run(args),
            Self::Render(args) => render::run(args),
            Self::Inspect(args) => inspect::run(args),
            Self::Build(args) => build::run(args),
            Self::Validate(args) => validate::run(args),
            Self::SynthCorpus(args) => synth_corpus::run(args),
            Self::Trajectories { command } => trajectories::run(command),
        }
    }
}
