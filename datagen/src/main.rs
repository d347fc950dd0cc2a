//! The `datagen` command line: a thin layer that parses arguments and calls the library.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::{Args, Parser, Subcommand};
use datagen::synth::{SynthConfig, write_sequence};

/// Self-supervised CogNVS training pairs from videos and their 3D reconstructions.
#[derive(Debug, Parser)]
#[command(name = "datagen", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Generate a synthetic dynamic scene (ray traced, exact ground truth) as a sequence folder in
    /// the cog-nvs layout: gt_rgb.mp4, cam_info/megasam_*.npy, masks/, plus a contact sheet.
    Synth(SynthArgs),
}

#[derive(Debug, Args)]
struct SynthArgs {
    /// Output sequence folder (created if missing).
    #[arg(long, default_value = "out/synth")]
    out: PathBuf,
    /// TOML file with any of the fields below (flags given on the command line win).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Frame width in pixels (even) [default: 320].
    #[arg(long)]
    width: Option<u32>,
    /// Frame height in pixels (even) [default: 192].
    #[arg(long)]
    height: Option<u32>,
    /// Number of frames [default: 25].
    #[arg(long)]
    frames: Option<u32>,
    /// Frame rate of the written video [default: 24].
    #[arg(long)]
    fps: Option<f64>,
    /// Number of moving objects (spheres and boxes) [default: 3].
    #[arg(long)]
    moving_objects: Option<u32>,
    /// Number of static boxes [default: 3].
    #[arg(long)]
    static_objects: Option<u32>,
    /// Seed of every random choice [default: 0].
    #[arg(long)]
    seed: Option<u64>,
}

fn synth(args: SynthArgs) -> anyhow::Result<()> {
    let mut config = match &args.config {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
            toml::from_str(&text).with_context(|| format!("{}: invalid synth config", path.display()))?
        }
        None => SynthConfig::default(),
    };
    let overrides = [
        (args.width, &mut config.width),
        (args.height, &mut config.height),
        (args.frames, &mut config.frames),
        (args.moving_objects, &mut config.moving_objects),
        (args.static_objects, &mut config.static_objects),
    ];
    for (value, field) in overrides {
        if let Some(value) = value {
            *field = value;
        }
    }
    config.fps = args.fps.unwrap_or(config.fps);
    config.seed = args.seed.unwrap_or(config.seed);
    config.validate()?;

    let bar = indicatif::ProgressBar::new(config.frames as u64).with_style(
        indicatif::ProgressStyle::with_template("rendering {bar:30} {pos}/{len} frames [{elapsed_precise}, eta {eta}]")
            .expect("valid template"),
    );
    let output = write_sequence(&config, &args.out, |done| bar.set_position(done as u64))?;
    bar.finish_and_clear();
    println!(
        "wrote a {}x{} scene of {} frames to {}\n  video:  {}\n  cameras and depth: {}\n  moving-object masks: {}\n  look at: {}",
        config.width,
        config.height,
        config.frames,
        output.dir.display(),
        output.dir.join("gt_rgb.mp4").display(),
        output.dir.join("cam_info").display(),
        output.dir.join("masks").display(),
        output.contact_sheet.display(),
    );
    Ok(())
}

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(error) if error.use_stderr() => {
            // One line naming the parameter; `--help` has the rest.
            let message = error.to_string();
            eprintln!("{}", message.lines().next().unwrap_or("error: invalid arguments"));
            return ExitCode::from(2);
        }
        Err(error) => {
            let _ = error.print();
            return ExitCode::SUCCESS;
        }
    };
    let result = match cli.command {
        Command::Synth(args) => synth(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {error:#}");
            ExitCode::FAILURE
        }
    }
}
