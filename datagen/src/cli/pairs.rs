//! `datagen pairs`: one sequence folder into a shard of training pairs ([`crate::pairs::job`]),
//! or a multi-camera scene folder into its monocular and multi-view pairs in one shard
//! ([`crate::pairs::scene`]).

use std::path::PathBuf;

use clap::Args;

use crate::cli::flags::{ReadArgs, pairs_config};
use crate::io::layout::{FolderLayout, MultiViewLayoutName, detect_multiview_layout, folder_layout};
use crate::pairs::generator::PairsConfig;
use crate::pairs::job::{PairsJob, PairsReport};
use crate::pairs::scene::SceneShard;

/// Arguments of `datagen pairs`.
#[derive(Debug, Args)]
pub struct PairsArgs {
    /// The sequence folder, or a synchronised multi-camera scene folder (one sub-folder per
    /// camera, or a dataset's scene: see --layout): it gives each camera's monocular pairs and the
    /// multi-view pairs of the config's [multiview] table, in one shard.
    pub seq_dir: PathBuf,
    /// How the folder is read.
    #[command(flatten)]
    pub read: ReadArgs,
    /// Output folder; the shard is written as <OUT>/<sequence name>.parquet.
    #[arg(long)]
    pub out: PathBuf,
    /// Number of sampled trajectories per clip [default: 2, or 0 when --trajectory is given].
    #[arg(long)]
    pub trajectories: Option<u32>,
    /// A trajectory file (.npy (N,4,4) world_from_camera, .json, or the public trajs/*.txt
    /// format); repeatable. Used alone unless --trajectories is also given.
    #[arg(long = "trajectory")]
    pub trajectory_files: Vec<PathBuf>,
    /// Seed of every random choice (combined with the sequence id, clip start and trajectory index).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// TOML file with [clip], [trajectory] and [covisibility] settings.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Dataset name stored with the pairs.
    #[arg(long, default_value = "sequence")]
    pub dataset: String,
    /// Print where the time went (decode, mesh build, rays, encode, write) to stderr.
    #[arg(long)]
    pub timings: bool,
    /// Add depth noise on dynamic objects (the config's [depth_noise] model); conditioning frames
    /// are then stored with the pairs.
    #[arg(long)]
    pub depth_noise: bool,
    /// A second, better depth source for measured depth noise: a folder of *.exr maps or an
    /// (N, H, W) .npy, one map per frame (implies --depth-noise).
    #[arg(long)]
    pub second_depth: Option<PathBuf>,
}

/// What `datagen pairs` does with a folder.
#[derive(Debug)]
pub enum PairsRequest {
    /// One sequence folder.
    Sequence(PairsJob),
    /// A multi-camera scene folder in this layout.
    Scene(SceneRequest),
}

/// `datagen pairs` on a scene folder.
#[derive(Debug)]
pub struct SceneRequest {
    /// The scene folder.
    pub dir: PathBuf,
    /// Its layout.
    pub layout: MultiViewLayoutName,
    /// The output folder.
    pub out: PathBuf,
    /// The dataset name stored with the pairs.
    pub dataset: String,
    /// The pairs settings.
    pub config: PairsConfig,
    /// Sampled trajectories per monocular clip.
    pub trajectories: u32,
    /// The seed.
    pub seed: u64,
}

impl PairsArgs {
    /// The library request these arguments make: a scene when the folder is one (detected, or a
    /// multi-camera `--layout`), else the sequence folder's pairs job.
    pub fn request(self) -> anyhow::Result<PairsRequest> {
        let mut config = pairs_config(self.config.as_ref())?;
        config.depth_noise.enabled |= self.depth_noise || self.second_depth.is_some();
        let scene = match self.read.layout {
            None => detect_multiview_layout(&self.seq_dir).ok(),
            Some(name) if name.multiview().is_some() => match folder_layout(&self.seq_dir, Some(name))? {
                FolderLayout::Scene(layout) => Some(layout),
                FolderLayout::Sequence(_) => None,
            },
            Some(_) => None,
        };
        if let Some(layout) = scene {
            if !self.trajectory_files.is_empty() || self.second_depth.is_some() {
                anyhow::bail!("--trajectory and --second-depth take one sequence folder, not a multi-camera scene");
            }
            return Ok(PairsRequest::Scene(SceneRequest {
                dir: self.seq_dir,
                layout,
                out: self.out,
                dataset: self.dataset,
                config,
                trajectories: self.trajectories.unwrap_or(crate::pairs::generator::PAPER_TRAJECTORIES),
                seed: self.seed,
            }));
        }
        Ok(PairsRequest::Sequence(PairsJob {
            seq_dir: self.seq_dir,
            layout: self.read.layout,
            read_options: self.read.options(),
            out: self.out,
            trajectories: self.trajectories,
            trajectory_files: self.trajectory_files,
            seed: self.seed,
            config,
            dataset: self.dataset,
            second_depth: self.second_depth,
        }))
    }
}

/// Runs `datagen pairs`.
pub fn run(args: PairsArgs) -> anyhow::Result<()> {
    let timings = args.timings;
    match args.request()? {
        PairsRequest::Sequence(job) => print_report(&crate::pairs::job::make_pairs(&job)?, timings),
        PairsRequest::Scene(request) => {
            let started = std::time::Instant::now();
            let shard = write_scene(&request)?;
            print_scene(&shard, started.elapsed().as_secs_f64());
        }
    }
    Ok(())
}

/// Writes the scene's shard, with a progress bar over its cameras and camera pairs.
pub fn write_scene(request: &SceneRequest) -> crate::Result<SceneShard> {
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template("{bar:30} {pos}/{len} cameras and camera pairs [{elapsed_precise}]")
            .expect("valid template"),
    );
    let shard = crate::pairs::scene::write_scene_pairs_as(
        &request.dir,
        Some(request.layout),
        &request.out,
        &request.dataset,
        &request.config,
        request.trajectories,
        request.seed,
        &mut |p| {
            bar.set_length(p.total as u64);
            bar.set_position(p.done as u64);
        },
    );
    bar.finish_and_clear();
    shard
}

fn print_report(report: &PairsReport, timings: bool) {
    for note in &report.notes {
        eprintln!("note: {note}");
    }
    if timings {
        let phases = &report.phases;
        eprintln!(
            "timings (wall s; phases in brackets run concurrently and overlap): [read+decode, hash] \
             {:.3} s, per-frame phase {:.3} s [summed over frames: mesh build {:.3} s, \
             view bins + rays {:.3} s, encode {:.3} s], shard write {:.3} s",
            report.read_seconds,
            phases.masks_and_encode,
            phases.mesh_build,
            phases.ray_cpu,
            phases.encode_cpu,
            report.write_seconds
        );
    }
    let stats = &report.stats;
    println!(
        "wrote {} ({} clips, {} pairs, {} frames, {:.1} MB) in {:.2} s",
        report.path.display(),
        stats.clips,
        stats.pairs,
        stats.frames,
        stats.bytes as f64 / 1e6,
        report.seconds
    );
    for t in &report.trajectories {
        println!(
            "  {} t{}: co-visible {:.1} %, {} rejected samples",
            t.clip_id,
            t.index,
            100.0 * t.covisible_fraction,
            t.rejected_samples
        );
    }
}

fn print_scene(shard: &SceneShard, seconds: f64) {
    println!(
        "wrote {} ({} monocular and {} multi-view clips, {} pairs, {:.1} MB) in {:.2} s",
        shard.path.display(),
        shard.counts.0,
        shard.counts.1,
        shard.stats.pairs,
        shard.stats.bytes as f64 / 1e6,
        seconds
    );
    let used: Vec<String> = shard.pairs.camera_pairs.iter().map(|(s, t)| format!("{s}→{t}")).collect();
    println!("  camera pairs: {}", used.join(", "));
    for dropped in &shard.pairs.dropped {
        println!(
            "  left out {}→{} from frame {}: co-visible {:.1} % < multiview.min_covisible_fraction",
            dropped.source,
            dropped.target,
            dropped.clip_start,
            100.0 * dropped.covisible_fraction
        );
    }
}
