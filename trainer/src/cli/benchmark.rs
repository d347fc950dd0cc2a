//! `trainer benchmark`: the paper's evaluation of a checkpoint on a dataset folder, or
//! `--compare` of two finished benchmarks.

use std::path::PathBuf;

use clap::{Args, ValueEnum};

use super::common::{DeviceArgs, EvalWeightArgs, parse_size};
use super::nvs::JobArgs;
use crate::benchmark::{self, Dataset, Progress, Reconstruction, Request, SplitOverride};

/// `trainer benchmark`'s flags.
#[derive(Debug, Args)]
pub struct BenchmarkArgs {
    /// Print the per-scene differences (B − A) of two finished benchmark folders and exit;
    /// refused when their protocols or scene lists differ.
    #[arg(long, num_args = 2, value_names = ["RUN_A", "RUN_B"], conflicts_with_all = ["dataset", "root", "init", "out"])]
    pub compare: Option<Vec<PathBuf>>,
    /// The dataset, which fixes the protocol (dycheck: DyCheck's, with masked metrics over its
    /// co-visibility masks; kubric4d, pardom4d: GCD's) and the paper's rows shown.
    #[arg(long, value_enum, required_unless_present = "compare")]
    pub dataset: Option<DatasetArg>,
    /// The dataset folder: one sub-folder per multi-camera scene.
    #[arg(long, required_unless_present = "compare")]
    pub root: Option<PathBuf>,
    /// Scenes to evaluate (folder names under --root) [default: every scene].
    #[arg(long, num_args = 1.., value_delimiter = ',')]
    pub scenes: Vec<String>,
    /// The scenes' layout: dycheck, kubric4d, pardom4d or generic (a sequence folder per camera)
    /// [default: detected per scene from its files].
    #[arg(long)]
    pub layout: Option<datagen::api::LayoutName>,
    /// What the source video is rendered from: `dataset` (the input camera's own depth and
    /// cameras) or a folder with one reconstruction per scene, DIR/<scene>/ (MegaSAM's, MoSca's
    /// exported, any layout datagen reads), scaled to the dataset's units by the median depth
    /// ratio.
    #[arg(long, default_value = "dataset")]
    pub reconstruction: String,
    /// The input camera, overriding the dataset's split (the generic layout has none: its first
    /// camera).
    #[arg(long)]
    pub input_camera: Option<String>,
    /// A held-out camera, overriding the dataset's split; repeatable (the generic layout's
    /// default: every camera but the input).
    #[arg(long = "held-out-camera")]
    pub held_out_cameras: Vec<String>,
    /// Checkpoint to evaluate (as `nvs --init`).
    #[arg(long, required_unless_present = "compare")]
    pub init: Option<PathBuf>,
    /// Output folder.
    #[arg(long, required_unless_present = "compare")]
    pub out: Option<PathBuf>,
    /// How the nvs job finetunes and samples.
    #[command(flatten)]
    pub job: JobArgs,
    /// Sampled trajectories per clip for the finetuning pairs [default: the paper's, 5 for
    /// DyCheck, 9 for Kubric-4D and ParDom-4D].
    #[arg(long = "finetune-trajectories")]
    pub finetune_trajectories: Option<u32>,
    /// Compute the metrics at WIDTHxHEIGHT instead of the protocol's size (the paper's numbers
    /// then do not compare; for quick checks).
    #[arg(long, value_parser = parse_size)]
    pub eval_size: Option<(u32, u32)>,
    /// The eval networks' weights.
    #[command(flatten)]
    pub weights: EvalWeightArgs,
    /// DyCheck: a folder of dycheck_<scene>_source_target_correspondence.txt files (the CogNVS
    /// evaluation bundle's dycheck/) selecting the held-out frames scored, as the official script
    /// selects them [default: every held-out frame the input camera's instants meet].
    #[arg(long)]
    pub correspondence: Option<PathBuf>,
    /// The compute device.
    #[command(flatten)]
    pub device: DeviceArgs,
}

/// `--dataset`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum DatasetArg {
    /// DyCheck iPhone (DyCheck protocol, masked metrics).
    Dycheck,
    /// Kubric-4D (GCD protocol).
    Kubric4d,
    /// ParallelDomain-4D (GCD protocol).
    Pardom4d,
}

impl DatasetArg {
    /// The library's dataset.
    pub fn dataset(self) -> Dataset {
        match self {
            Self::Dycheck => Dataset::Dycheck,
            Self::Kubric4d => Dataset::Kubric4d,
            Self::Pardom4d => Dataset::Pardom4d,
        }
    }
}

/// What the flags ask for.
#[derive(Debug)]
pub enum Asked {
    /// Compare two finished benchmark folders (A, B).
    Compare(PathBuf, PathBuf),
    /// Run (or continue) a benchmark.
    Run(Box<Request>),
}

impl BenchmarkArgs {
    /// The comparison or the library's request.
    pub fn asked(self) -> crate::Result<Asked> {
        if let Some([a, b]) = self.compare.as_deref() {
            return Ok(Asked::Compare(a.clone(), b.clone()));
        }
        // clap requires these without --compare; a program building the flags itself is told.
        let missing = |name: &str| crate::Error::InvalidArgument {
            name: name.to_string(),
            reason: "required unless --compare is given".to_string(),
        };
        let dataset = self.dataset.ok_or_else(|| missing("dataset"))?.dataset();
        let root = self.root.ok_or_else(|| missing("root"))?;
        let init = self.init.ok_or_else(|| missing("init"))?;
        let out = self.out.ok_or_else(|| missing("out"))?;
        let device = self.device.usable()?;
        let trajectories = self.finetune_trajectories.unwrap_or(dataset.finetune_trajectories());
        Ok(Asked::Run(Box::new(Request {
            dataset,
            root,
            scenes: self.scenes,
            layout: self.layout,
            split: SplitOverride { input: self.input_camera, held_out: self.held_out_cameras },
            reconstruction: match self.reconstruction.as_str() {
                "dataset" => Reconstruction::Dataset,
                dir => Reconstruction::Folder(PathBuf::from(dir)),
            },
            out,
            nvs: self.job.settings(init, trajectories, device),
            eval_size: self.eval_size,
            lpips: self.weights.lpips_weights,
            lpips_net: self.weights.lpips_net.net(),
            inception: self.weights.inception_weights,
            kid_subsets: self.weights.kid_subsets,
            kid_subset_size: self.weights.kid_subset_size,
            correspondence: self.correspondence,
        })))
    }
}

/// Runs (or continues) the benchmark with a line per event on stderr and prints the table, or
/// prints the comparison; true when a preemption stopped it.
pub fn run(args: BenchmarkArgs) -> anyhow::Result<bool> {
    let request = match args.asked()? {
        Asked::Compare(a, b) => {
            println!("{}", benchmark::report::comparison_markdown(&benchmark::compare(&a, &b)?));
            return Ok(false);
        }
        Asked::Run(request) => request,
    };
    let outcome = benchmark::run(&request, &mut |event| match event {
        Progress::Scene(name, i, n) => eprintln!("scene {}/{n}: {name}", i + 1),
        Progress::Skipped(name) => eprintln!("scene {name}: scored by an earlier run, skipped"),
        Progress::Failed(name, reason) => eprintln!("scene {name}: FAILED: {reason}"),
        Progress::Window(name, i, n, start) => eprintln!("scene {name}: window {}/{n} from frame {start}", i + 1),
        Progress::Done(name, line) => eprintln!(
            "scene {name}: {} frames, PSNR {}",
            line.frames,
            line.metrics.psnr.map_or("–".to_string(), |v| format!("{v:.3}"))
        ),
        Progress::Nvs(crate::pipelines::nvs::Progress::Phase(phase, len)) => eprintln!("  {phase} ({len})"),
        Progress::Nvs(crate::pipelines::nvs::Progress::Skipped(phase)) => {
            eprintln!("  {phase}: finished by an earlier run")
        }
        Progress::Nvs(_) => {}
    })?;
    let out = &request.out;
    let Some(report) = outcome.report else {
        eprintln!(
            "preempted: scored scenes are kept in {}; run the same command again to continue (exit status {})",
            out.display(),
            crate::training::preempt::EXIT_PREEMPTED
        );
        return Ok(true);
    };
    println!("{}", benchmark::report::markdown(&report));
    println!(
        "table: {}, JSON: {}",
        out.join(benchmark::REPORT_MD).display(),
        out.join(benchmark::REPORT_JSON).display()
    );
    Ok(false)
}
