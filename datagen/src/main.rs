//! The `datagen` command line: a thin layer that parses arguments and calls the library.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Args, Parser, Subcommand};
use datagen::config_file::Validate;
use datagen::corpus::build::{BuildConfig, Progress};
use datagen::corpus::partition::Worker;
use datagen::io::sequence::{LayoutName, ReadOptions};
use datagen::pairs::generator::PairsConfig;
use datagen::synth::{SynthConfig, write_sequence};
use schemas::InputStatus;

// Every frame allocates and drops tens of MB of meshes and bins; glibc returns such blocks to
// the kernel and faults them back in each time (a visible share of `pairs`' CPU), mimalloc reuses
// them. Its `no_thp` feature keeps it from asking for transparent huge pages: each fresh 2 MB page
// is cleared whole when first touched, also where only part of it is used (the encoders' growing
// output buffers). `scripts/bench_pairs_vs.sh` measures the peak RSS and wall time it saves.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

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
    /// Turn one sequence folder (cog-nvs, MegaSAM npz, generic, or a ViPE, VGGT, COLMAP, GEN3C or
    /// depth-only tool's output) into training pairs:
    /// one finished shard holding each clip once and one entry per trajectory.
    Pairs(PairsArgs),
    /// Check a reconstruction before spending GPU hours on it: the convention and units, the
    /// camera path (length, speed, jumps), the valid-depth share and the multi-frame consistency
    /// of static geometry, with a verdict `ok` or `suspect` and the reasons.
    Check(CheckArgs),
    /// Write a sequence (and the pairs of a shard made from it) as a recording for the Rerun
    /// viewer (`pip install rerun-sdk`, then `rerun FILE.rrd`): per frame the coloured point
    /// cloud, the source camera with its image, the novel trajectories as camera frusta and their
    /// co-visibility masks.
    View(ViewArgs),
    /// Render a sequence from a novel camera path: the inference-time conditioning
    /// (render.mp4, frames/%05d.png and holes/%05d.png, 255 = hole).
    Render(RenderArgs),
    /// Print statistics of a shard or corpus folder; with --export, write every pair as image
    /// folders, meta.json and a contact sheet (target | mask | cond | novel render).
    Inspect(InspectArgs),
    /// Build a corpus from dataset trees (SA-V, TAO, YouTube-VOS, DAVIS, sequence folders),
    /// resumably, on one machine or many (--num-workers/--worker-index or Slurm/Kubernetes).
    Build(BuildArgs),
    /// Check every shard of a folder against its stats marker and the schema.
    Validate(ValidateArgs),
    /// Write a small corpus of synthetic videos in every dataset layout (SA-V, TAO, YouTube-VOS,
    /// DAVIS, sequence folders) with reconstructions, annotations and a corpus.toml, to try or
    /// benchmark `datagen build`.
    SynthCorpus(SynthCorpusArgs),
    /// Trajectory banks: real camera motion harvested from reconstructions, for
    /// `[trajectory] sampler = "bank" | "mixed"`.
    Trajectories {
        #[command(subcommand)]
        command: TrajectoriesCommand,
    },
}

#[derive(Debug, Subcommand)]
enum TrajectoriesCommand {
    /// Harvest the source cameras' own motion over every clip window of a corpus (--config) or of
    /// one sequence folder into a trajectory bank (Parquet, schema in schemas/SCHEMA.md); static
    /// and degenerate windows are skipped and counted.
    Collect(CollectArgs),
    /// Print the distributions of trajectory parameters (azimuth/elevation span, radial change,
    /// path length) and of the co-visible fraction of one or more corpora side by side, and
    /// plot them as SVG histograms.
    Stats(StatsArgs),
}

#[derive(Debug, Args)]
struct CollectArgs {
    /// A sequence folder (instead of --config).
    seq_dir: Option<PathBuf>,
    /// Corpus TOML (as for `datagen build`): every video of its sources, windows from its
    /// [pairs.clip], R from its [pairs.trajectory] pivot_scale.
    #[arg(long, conflicts_with = "seq_dir")]
    config: Option<PathBuf>,
    /// For a sequence folder: its layout [default: detected from its files].
    #[arg(long, value_parser = parse_layout, requires = "seq_dir")]
    layout: Option<LayoutName>,
    /// For a sequence folder: TOML with [clip] and [trajectory] (as for `datagen pairs`).
    #[arg(long, requires = "seq_dir")]
    pairs_config: Option<PathBuf>,
    /// For a sequence folder: dataset name recorded with its entries.
    #[arg(long, default_value = "sequence")]
    dataset: String,
    /// The bank file to write.
    #[arg(long)]
    out: PathBuf,
}

#[derive(Debug, Args)]
struct StatsArgs {
    /// LABEL=DIR pairs: a corpus folder (or shard) and the name it gets in the table and plots.
    #[arg(required = true)]
    corpora: Vec<String>,
    /// Write one SVG histogram per quantity into this folder.
    #[arg(long)]
    plots: Option<PathBuf>,
}

#[derive(Debug, Args)]
struct SynthCorpusArgs {
    /// Root folder of the generated trees.
    #[arg(long)]
    out: PathBuf,
    /// Videos per dataset layout.
    #[arg(long, default_value_t = 2)]
    videos_per_layout: usize,
    /// Synth scene settings (TOML, as for `datagen synth --config`); default: 320x192, 25 frames.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Output folder written into the corpus.toml [default: <OUT>/corpus].
    #[arg(long)]
    corpus_out: Option<PathBuf>,
}

#[derive(Debug, Args)]
struct PairsArgs {
    /// The sequence folder, or a synchronised multi-camera scene folder (one sub-folder per
    /// camera): it gives each camera's monocular pairs and the multi-view pairs of the config's
    /// [multiview] table, in one shard.
    seq_dir: PathBuf,
    /// Layout of the folder (cog-nvs, megasam, generic, vipe, vggt, colmap, gen3c, depth-only)
    /// [default: detected from its files; a folder matching several is an error listing them].
    #[arg(long, value_parser = parse_layout)]
    layout: Option<LayoutName>,
    /// VGGT output: drop depth whose depth_conf is below this percentile (0–100) of the
    /// sequence's confidences, as VGGT's viewers filter points (its demo's default is 50)
    /// [default: keep every finite depth].
    #[arg(long, value_name = "PERCENTILE")]
    vggt_conf_percentile: Option<f64>,
    /// Output folder; the shard is written as <OUT>/<sequence name>.parquet.
    #[arg(long)]
    out: PathBuf,
    /// Number of sampled trajectories per clip [default: 2, or 0 when --trajectory is given].
    #[arg(long)]
    trajectories: Option<u32>,
    /// A trajectory file (.npy (N,4,4) world_from_camera, .json, or the public trajs/*.txt
    /// format); repeatable. Used alone unless --trajectories is also given.
    #[arg(long = "trajectory")]
    trajectory_files: Vec<PathBuf>,
    /// Seed of every random choice (combined with the sequence id, clip start and trajectory index).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// TOML file with [clip], [trajectory] and [covisibility] settings.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Dataset name stored with the pairs.
    #[arg(long, default_value = "sequence")]
    dataset: String,
    /// Print where the time went (decode, mesh build, rays, encode, write) to stderr.
    #[arg(long)]
    timings: bool,
    /// Add depth noise on dynamic objects (the config's [depth_noise] model); conditioning frames
    /// are then stored with the pairs.
    #[arg(long)]
    depth_noise: bool,
    /// A second, better depth source for measured depth noise: a folder of *.exr maps or an
    /// (N, H, W) .npy, one map per frame (implies --depth-noise).
    #[arg(long)]
    second_depth: Option<PathBuf>,
}

#[derive(Debug, Args)]
struct CheckArgs {
    /// The sequence folder.
    seq_dir: PathBuf,
    /// Layout of the folder [default: detected from its files].
    #[arg(long, value_parser = parse_layout)]
    layout: Option<LayoutName>,
    /// VGGT output: drop depth whose depth_conf is below this percentile (0–100) of the
    /// sequence's confidences, as VGGT's viewers filter points (its demo's default is 50)
    /// [default: keep every finite depth].
    #[arg(long, value_name = "PERCENTILE")]
    vggt_conf_percentile: Option<f64>,
    /// Print the report as JSON (verdict, reasons, static_depth_consistency, per-pair shares, ...).
    #[arg(long)]
    json: bool,
    /// TOML with the check's settings (depth_tolerance, min_consistency, min_valid_depth_share,
    /// frame_gaps, pixel_stride, jump_factor), as the [check] table of a corpus TOML.
    #[arg(long)]
    config: Option<PathBuf>,
}

#[derive(Debug, Args)]
struct ViewArgs {
    /// The sequence folder.
    seq_dir: PathBuf,
    /// Layout of the folder [default: detected from its files].
    #[arg(long, value_parser = parse_layout)]
    layout: Option<LayoutName>,
    /// A shard of pairs made from this sequence (`datagen pairs`): its novel trajectories and
    /// co-visibility masks go into the recording.
    #[arg(long)]
    pairs: Option<PathBuf>,
    /// The recording to write (.rrd).
    #[arg(long)]
    out: PathBuf,
    /// Python interpreter with rerun-sdk installed.
    #[arg(long, default_value = "python3")]
    python: PathBuf,
    /// The script writing the recording [default: scripts/rerun_view.py of this source tree].
    #[arg(long)]
    script: Option<PathBuf>,
    /// Every N-th pixel in x and y becomes a point of the cloud.
    #[arg(long, default_value_t = datagen::inspect::view::DEFAULT_POINT_STRIDE)]
    point_stride: u32,
}

#[derive(Debug, Args)]
struct RenderArgs {
    /// The sequence folder.
    seq_dir: PathBuf,
    /// Layout of the folder (cog-nvs, megasam, generic, vipe, vggt, colmap, gen3c, depth-only)
    /// [default: detected from its files; a folder matching several is an error listing them].
    #[arg(long, value_parser = parse_layout)]
    layout: Option<LayoutName>,
    /// The novel camera path (.npy, .json or trajs/*.txt).
    #[arg(long)]
    trajectory: PathBuf,
    /// Output folder.
    #[arg(long)]
    out: PathBuf,
    /// TOML file with [covisibility] and [static_background] settings.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Fill the holes of each frame's render with the static background fused from all frames
    /// (points outside the dynamic-object masks, voxel-deduplicated).
    #[arg(long)]
    stack_background: bool,
}

#[derive(Debug, Args)]
struct InspectArgs {
    /// A shard file or a folder of shards (a corpus).
    path: PathBuf,
    /// Write every pair under this folder.
    #[arg(long)]
    export: Option<PathBuf>,
    /// With --export: fill the holes of the contact sheet's novel renders from the static
    /// background stacked over each clip's frames.
    #[arg(long)]
    stack_background: bool,
    /// With --export: `pairs` (a folder per pair: PNGs, meta.json, contact sheet) or `cog-nvs`
    /// (a folder per clip as the public cog-nvs finetuning code reads it: gt_rgb.mp4 and
    /// train_render{k}.mp4, k from 1).
    #[arg(long, value_enum, default_value_t = LayoutArg::Pairs, requires = "export")]
    layout: LayoutArg,
    /// Write a self-contained HTML report (counts, failures by reason, histograms, thumbnails
    /// linked to the --export folders) to this file.
    #[arg(long)]
    report: Option<PathBuf>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum LayoutArg {
    Pairs,
    CogNvs,
}

#[derive(Debug, Args)]
struct BuildArgs {
    /// Corpus TOML: [[sources]], [output], [pairs] (see configs/corpus_example.toml).
    #[arg(long)]
    config: PathBuf,
    /// Override the output folder of the config.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Total number of workers [default: SLURM_ARRAY_TASK_COUNT, else 1].
    #[arg(long)]
    num_workers: Option<u32>,
    /// This worker's index [default: SLURM_ARRAY_TASK_ID or JOB_COMPLETION_INDEX, else 0].
    #[arg(long)]
    worker_index: Option<u32>,
    /// List what would be built, write nothing.
    #[arg(long)]
    dry_run: bool,
    /// Retry every input whose latest attempt failed, even if its files are unchanged (inputs
    /// whose files changed since they failed or were skipped are always retried).
    #[arg(long)]
    retry_failed: bool,
    /// Print where the time went (hashing, loading, mesh builds, rays, encoding, writing).
    #[arg(long)]
    timings: bool,
}

#[derive(Debug, Args)]
struct ValidateArgs {
    /// A shard file or a folder of shards.
    path: PathBuf,
    /// Also decode every PNG and EXR and check its size.
    #[arg(long)]
    deep: bool,
}

fn parse_layout(name: &str) -> Result<LayoutName, String> {
    name.parse()
}

fn pairs(args: PairsArgs) -> anyhow::Result<()> {
    let mut config = match &args.config {
        Some(path) => PairsConfig::from_toml_file(path)?,
        None => PairsConfig::default(),
    };
    config.depth_noise.enabled |= args.depth_noise || args.second_depth.is_some();
    if args.layout.is_none() && datagen::io::multiview_layout::detect_multiview_layout(&args.seq_dir).is_ok() {
        return multiview_pairs(&args, &config);
    }
    let job = datagen::pairs::job::PairsJob {
        seq_dir: args.seq_dir,
        layout: args.layout,
        read_options: ReadOptions { vggt_confidence_percentile: args.vggt_conf_percentile },
        out: args.out,
        trajectories: args.trajectories,
        trajectory_files: args.trajectory_files,
        seed: args.seed,
        config,
        dataset: args.dataset,
        second_depth: args.second_depth,
    };
    let report = datagen::pairs::job::make_pairs(&job)?;
    for note in &report.notes {
        eprintln!("note: {note}");
    }
    if args.timings {
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
    Ok(())
}

/// `datagen pairs` on a multi-camera scene folder: its monocular and multi-view pairs in one shard.
fn multiview_pairs(args: &PairsArgs, config: &PairsConfig) -> anyhow::Result<()> {
    if !args.trajectory_files.is_empty() || args.second_depth.is_some() {
        anyhow::bail!("--trajectory and --second-depth take one sequence folder, not a multi-camera scene");
    }
    let trajectories = args.trajectories.unwrap_or(datagen::pairs::generator::PAPER_TRAJECTORIES);
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template("{bar:30} {pos}/{len} cameras and camera pairs [{elapsed_precise}]")
            .expect("valid template"),
    );
    let started = std::time::Instant::now();
    let shard = datagen::pairs::scene::write_scene_pairs(
        &args.seq_dir,
        &args.out,
        &args.dataset,
        config,
        trajectories,
        args.seed,
        &mut |p| {
            bar.set_length(p.total as u64);
            bar.set_position(p.done as u64);
        },
    )?;
    bar.finish_and_clear();
    println!(
        "wrote {} ({} monocular and {} multi-view clips, {} pairs, {:.1} MB) in {:.2} s",
        shard.path.display(),
        shard.counts.0,
        shard.counts.1,
        shard.stats.pairs,
        shard.stats.bytes as f64 / 1e6,
        started.elapsed().as_secs_f64()
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
    Ok(())
}

fn check(args: CheckArgs) -> anyhow::Result<()> {
    let config = match &args.config {
        Some(path) => datagen::config_file::load_toml(path)?,
        None => datagen::geometry::consistency::CheckConfig::default(),
    };
    let options = ReadOptions { vggt_confidence_percentile: args.vggt_conf_percentile };
    let report = datagen::geometry::consistency::check_folder_with(&args.seq_dir, args.layout, &options, &config)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", report.to_text());
    }
    Ok(())
}

fn view(args: ViewArgs) -> anyhow::Result<()> {
    let sequence = datagen::io::sequence::read_sequence_as(&args.seq_dir, args.layout)?;
    let options = datagen::inspect::view::ViewOptions {
        python: args.python,
        script: args.script.unwrap_or_else(|| PathBuf::from(datagen::inspect::view::DEFAULT_SCRIPT)),
        point_stride: args.point_stride,
    };
    let summary = datagen::inspect::view::write_recording(&sequence, args.pairs.as_deref(), &args.out, &options)?;
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

fn render(args: RenderArgs) -> anyhow::Result<()> {
    let config = match &args.config {
        Some(path) => PairsConfig::from_toml_file(path)?,
        None => PairsConfig::default(),
    };
    let sequence = datagen::io::sequence::read_sequence_as(&args.seq_dir, args.layout)?;
    let summary = datagen::pairs::generator::render_sequence(
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

fn inspect(args: InspectArgs) -> anyhow::Result<()> {
    print!("{}", datagen::inspect::shards::report(&args.path)?);
    if let (Some(export), LayoutArg::CogNvs) = (&args.export, args.layout) {
        let folders = datagen::inspect::shards::export_cog_nvs(&args.path, export)?;
        println!("exported {} clips in the cog-nvs layout to {}", folders.len(), export.display());
    } else if let Some(export) = &args.export {
        let render = datagen::inspect::shards::ExportRender {
            covisibility: Default::default(),
            stacking: args.stack_background.then(Default::default),
        };
        let folders = datagen::inspect::shards::export(&args.path, export, Some(&render))?;
        println!("exported {} pairs to {}", folders.len(), export.display());
        if let Some(first) = folders.first() {
            println!("  look at: {}", first.join("contact_sheet.png").display());
        }
    }
    if let Some(out) = &args.report {
        let options = datagen::inspect::report::ReportOptions {
            export_dir: args.export.clone().filter(|_| args.layout == LayoutArg::Pairs),
            ..Default::default()
        };
        let summary = datagen::inspect::report::write_report(&args.path, out, &options)?;
        println!(
            "wrote {} ({} shards, {} clips, {} pairs, {} thumbnails, {} failed or skipped inputs)",
            out.display(),
            summary.shards,
            summary.clips,
            summary.pairs,
            summary.thumbnails,
            summary.failures
        );
    }
    Ok(())
}

fn trajectories(command: TrajectoriesCommand) -> anyhow::Result<()> {
    match command {
        TrajectoriesCommand::Collect(args) => {
            let summary = match (&args.config, &args.seq_dir) {
                (Some(config), _) => {
                    datagen::corpus::harvest::collect_from_corpus(&BuildConfig::from_toml_file(config)?)?
                }
                (None, Some(seq_dir)) => {
                    let config = match &args.pairs_config {
                        Some(path) => PairsConfig::from_toml_file(path)?,
                        None => PairsConfig::default(),
                    };
                    let sequence = datagen::io::sequence::read_sequence_as(seq_dir, args.layout)?;
                    let mut summary = datagen::pairs::trajectory_bank::CollectSummary::default();
                    datagen::pairs::trajectory_bank::collect_from_sequence(
                        &sequence,
                        &args.dataset,
                        &config.clip,
                        config.trajectory.pivot_scale,
                        &mut summary,
                    );
                    summary
                }
                (None, None) => anyhow::bail!("parameter `config`: give --config CORPUS.toml or a sequence folder"),
            };
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
        }
        TrajectoriesCommand::Stats(args) => {
            let corpora = args
                .corpora
                .iter()
                .map(|pair| match pair.split_once('=') {
                    Some((label, dir)) if !label.is_empty() => Ok((label.to_owned(), PathBuf::from(dir))),
                    _ => anyhow::bail!("parameter `corpora`: `{pair}` is not LABEL=DIR"),
                })
                .collect::<anyhow::Result<Vec<_>>>()?;
            print!("{}", datagen::inspect::report::compare_corpora(&corpora, args.plots.as_deref())?);
            if let Some(plots) = &args.plots {
                println!("plots in {}", plots.display());
            }
        }
    }
    Ok(())
}

/// Failed inputs `datagen build` lists with their reasons at the end (the status table and
/// `datagen inspect` have them all): a screenful.
const LISTED_FAILURES: usize = 20;

fn build(args: BuildArgs) -> anyhow::Result<()> {
    let mut config = BuildConfig::from_toml_file(&args.config)?;
    if let Some(out) = args.out {
        config.output.dir = out;
    }
    let worker = Worker::from_flags_or_env(args.num_workers, args.worker_index, |name| std::env::var(name).ok())?;
    if args.dry_run {
        let options = datagen::corpus::build::BuildOptions { retry_failed: args.retry_failed };
        let planned = datagen::corpus::build::plan(&config.sources, &config.output.dir, worker, options)?;
        for input in &planned {
            println!("{}\t{}", input.plan, input.key);
        }
        println!("worker {}/{}: {} inputs", worker.index, worker.count, planned.len());
        return Ok(());
    }
    let processor = datagen::corpus::input::SequenceProcessor::new(&config);
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template("{bar:30} {pos}/{len} inputs {msg} [{elapsed_precise}, eta {eta}]")
            .expect("valid template"),
    );
    let (mut pairs, mut failures) = (0u64, 0u64);
    let started = std::time::Instant::now();
    let options = datagen::corpus::build::BuildOptions { retry_failed: args.retry_failed };
    let summary = datagen::corpus::build::build_with_options(
        &config.sources,
        &config.output,
        worker,
        options,
        &processor,
        |event| match event {
            Progress::Start { pending } => bar.set_length(pending),
            Progress::Input { status, pairs: n } => {
                pairs += n;
                failures += u64::from(status == InputStatus::Failed);
                let rate = pairs as f64 / started.elapsed().as_secs_f64().max(1e-9);
                bar.set_message(format!("{pairs} pairs ({rate:.1}/s), {failures} failed"));
                bar.inc(1);
            }
        },
    )?;
    bar.finish_and_clear();
    for repair in &summary.repairs {
        println!("resume: {repair}");
    }
    println!(
        "worker {}/{}: {} ok, {} skipped, {} failed ({} already done); {} pairs in {} shards, {:.1} MB, {:.1} s",
        worker.index,
        worker.count,
        summary.ok,
        summary.skipped,
        summary.failed,
        summary.inputs_already_done,
        summary.pairs,
        summary.shards,
        summary.bytes as f64 / 1e6,
        summary.seconds
    );
    if summary.failed > 0 {
        let status = datagen::corpus::build::read_corpus_status(&config.output.dir)?;
        let failed: Vec<_> = status.values().filter(|r| r.status == InputStatus::Failed).collect();
        for record in failed.iter().take(LISTED_FAILURES) {
            println!("failed: {}: {}", record.input_key, record.reason);
        }
        if failed.len() > LISTED_FAILURES {
            println!(
                "... and {} more (datagen inspect {})",
                failed.len() - LISTED_FAILURES,
                config.output.dir.display()
            );
        }
    }
    if args.timings {
        let t = processor.timings();
        println!(
            "timings: {:.3} pairs/s, {:.2} MB/s written; wall {:.1} s = hash {:.1} s + process {:.1} s + write {:.1} s; \
             process: load (decode, reconstruction, masks) {:.1} s, per-frame phase {:.1} s wall [concurrent, \
             summed over frames, overlapping: mesh {:.1} s, rays {:.1} s, encode {:.1} s]",
            summary.pairs as f64 / summary.seconds.max(1e-9),
            summary.bytes as f64 / 1e6 / summary.seconds.max(1e-9),
            summary.seconds,
            summary.hash_seconds,
            summary.process_seconds,
            summary.write_seconds,
            t.load_seconds,
            t.pairs.masks_and_encode,
            t.pairs.mesh_build,
            t.pairs.ray_cpu,
            t.pairs.encode_cpu
        );
    }
    Ok(())
}

fn synth_corpus(args: SynthCorpusArgs) -> anyhow::Result<()> {
    let config = match &args.config {
        Some(path) => datagen::config_file::load_toml(path)?,
        None => SynthConfig::default(),
    };
    let out = args.corpus_out.unwrap_or_else(|| args.out.join("corpus"));
    let corpus = datagen::corpus::synthetic::write_synthetic_corpus(&args.out, &out, args.videos_per_layout, &config)?;
    println!(
        "wrote {} videos in each of 5 layouts under {}; build them with: datagen build --config {}",
        corpus.videos_per_layout,
        args.out.display(),
        corpus.config.display()
    );
    Ok(())
}

fn validate(args: ValidateArgs) -> anyhow::Result<()> {
    let report = datagen::corpus::validate::validate(&args.path, args.deep)?;
    for problem in &report.problems {
        println!("{}: {}", problem.path.display(), problem.message);
    }
    println!("{} shards, {} clips, {} problems", report.shards, report.clips, report.problems.len());
    if !report.problems.is_empty() {
        anyhow::bail!("validation found {} problems", report.problems.len());
    }
    Ok(())
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
    /// Number of thin static objects: poles and plates a few centimetres thick [default: 0].
    #[arg(long)]
    thin_objects: Option<u32>,
    /// Seed of every random choice [default: 0].
    #[arg(long)]
    seed: Option<u64>,
    /// Render the scene from this many synchronised cameras (2 to 64) instead of one: OUT/camNN/
    /// per camera in the generic layout (frames/, depth/*.exr, cameras.json with timestamps).
    #[arg(long)]
    cameras: Option<u32>,
    /// With --cameras: yaw between neighbouring cameras about the scene's centre, in degrees.
    #[arg(long, default_value_t = 10.0, requires = "cameras")]
    camera_spacing_deg: f64,
    /// With --cameras: the layout to write: generic (camNN/ sequence folders), dycheck (DyCheck
    /// iPhone: camera 0 moving with depth, the others static and held out) or kubric4d (Kubric-4D
    /// as GCD ships it; OUT's name is the scene id).
    #[arg(long, default_value = "generic", requires = "cameras")]
    format: datagen::synth_layouts::SynthFormat,
}

fn synth(args: SynthArgs) -> anyhow::Result<()> {
    let mut config = match &args.config {
        Some(path) => datagen::config_file::load_toml(path)?,
        None => SynthConfig::default(),
    };
    let overrides = [
        (args.width, &mut config.width),
        (args.height, &mut config.height),
        (args.frames, &mut config.frames),
        (args.moving_objects, &mut config.moving_objects),
        (args.static_objects, &mut config.static_objects),
        (args.thin_objects, &mut config.thin_objects),
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
    if let Some(cameras) = args.cameras {
        let rig = datagen::synth::CameraRig { cameras, spacing_deg: args.camera_spacing_deg };
        let progress = |done| bar.set_position(done as u64);
        datagen::synth_layouts::write_multiview_as(&config, &rig, args.format, &args.out, progress)?;
        bar.finish_and_clear();
        let layout = match args.format {
            datagen::synth_layouts::SynthFormat::Generic => "camNN/: frames/, depth/, cameras.json",
            datagen::synth_layouts::SynthFormat::Dycheck => {
                "DyCheck layout: camera/, rgb/, depth/, covisible/, splits/"
            }
            datagen::synth_layouts::SynthFormat::Kubric4d => "Kubric-4D layout: frames_p0_vN/, <scene>_p0_vN.json",
        };
        println!(
            "wrote a {}x{} scene of {} frames from {cameras} synchronised cameras to {} ({layout})",
            config.width,
            config.height,
            config.frames,
            args.out.display()
        );
        return Ok(());
    }
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
        Command::Pairs(args) => pairs(args),
        Command::Check(args) => check(args),
        Command::View(args) => view(args),
        Command::Render(args) => render(args),
        Command::Inspect(args) => inspect(args),
        Command::Build(args) => build(args),
        Command::Validate(args) => validate(args),
        Command::SynthCorpus(args) => synth_corpus(args),
        Command::Trajectories { command } => trajectories(command),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {error:#}");
            ExitCode::FAILURE
        }
    }
}
