//! `datagen build`: a corpus from dataset trees, resumable, on one machine or many
//! ([`crate::corpus::build`]).

use std::path::PathBuf;

use clap::Args;
use schemas::InputStatus;

use crate::cli::flags::parse_layout;
use crate::corpus::build::{BuildConfig, BuildOptions, Progress};
use crate::corpus::partition::Worker;
use crate::io::layout::LayoutName;

/// Failed inputs `datagen build` lists with their reasons at the end (the status table and
/// `datagen inspect` have them all): a screenful.
const LISTED_FAILURES: usize = 20;

/// Arguments of `datagen build`.
#[derive(Debug, Args)]
pub struct BuildArgs {
    /// Corpus TOML: [[sources]], [output], [pairs] (see configs/corpus_example.toml).
    #[arg(long)]
    pub config: PathBuf,
    /// Override the output folder of the config.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Total number of workers [default: SLURM_ARRAY_TASK_COUNT, else 1].
    #[arg(long)]
    pub num_workers: Option<u32>,
    /// This worker's index [default: SLURM_ARRAY_TASK_ID or JOB_COMPLETION_INDEX, else 0].
    #[arg(long)]
    pub worker_index: Option<u32>,
    /// List what would be built, write nothing.
    #[arg(long)]
    pub dry_run: bool,
    /// Retry every input whose latest attempt failed, even if its files are unchanged (inputs
    /// whose files changed since they failed or were skipped are always retried).
    #[arg(long)]
    pub retry_failed: bool,
    /// Print where the time went (hashing, loading, mesh builds, rays, encoding, writing).
    #[arg(long)]
    pub timings: bool,
    /// The layout of every input's folder, as --layout of `datagen pairs` (overrides the
    /// config's `layout`): a single-camera name for sequence folders and reconstructions, a
    /// multi-camera one for scene folders; inputs of the other kind keep detection [default:
    /// the config's, else detected from the files].
    #[arg(long, value_parser = parse_layout)]
    pub layout: Option<LayoutName>,
}

impl BuildArgs {
    /// The corpus settings (the config file with `--out` and `--layout` on top), this worker and
    /// the options.
    pub fn request(&self) -> anyhow::Result<(BuildConfig, Worker, BuildOptions)> {
        let mut config = BuildConfig::from_toml_file(&self.config)?;
        if let Some(out) = &self.out {
            config.output.dir = out.clone();
        }
        if self.layout.is_some() {
            config.layout = self.layout;
        }
        let worker = Worker::from_flags_or_env(self.num_workers, self.worker_index, |name| std::env::var(name).ok())?;
        Ok((config, worker, BuildOptions { retry_failed: self.retry_failed }))
    }
}

/// Runs `datagen build`.
pub fn run(args: BuildArgs) -> anyhow::Result<()> {
    let (config, worker, options) = args.request()?;
    if args.dry_run {
        let planned = crate::corpus::build::plan(&config.sources, &config.output.dir, worker, options)?;
        for input in &planned {
            println!("{}\t{}", input.plan, input.key);
        }
        println!("worker {}/{}: {} inputs", worker.index, worker.count, planned.len());
        return Ok(());
    }
    let processor = crate::corpus::input::SequenceProcessor::new(&config);
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template("{bar:30} {pos}/{len} inputs {msg} [{elapsed_precise}, eta {eta}]")
            .expect("valid template"),
    );
    let (mut pairs, mut failures) = (0u64, 0u64);
    let started = std::time::Instant::now();
    let summary = crate::corpus::build::build_with_options(
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
        let status = crate::corpus::build::read_corpus_status(&config.output.dir)?;
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
