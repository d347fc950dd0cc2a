//! `trainer eval`: predictions scored against targets, one pair, folders of videos or the
//! paper's evaluation bundle.

use std::path::PathBuf;

use clap::{Args, ValueEnum};

use super::common::{EvalWeightArgs, write_optional};
use crate::eval::metrics::VideoMetrics;
use crate::eval::score::{self, ScoreReport};
use crate::eval::{inception, lpips};

/// `trainer eval`'s flags.
#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Predicted video: a video file or a folder of PNG/JPEG frames (or a folder of such videos).
    #[arg(long, required_unless_present = "bundle", conflicts_with = "bundle")]
    pub pred: Option<PathBuf>,
    /// Target video: a video file or a folder of PNG/JPEG frames (or a folder of such videos).
    #[arg(long, required_unless_present = "bundle", conflicts_with = "bundle")]
    pub target: Option<PathBuf>,
    /// Score one method of the paper's evaluation bundle as the official eval_metrics.py does:
    /// ROOT/<dataset>/<method>/*<scene>_<method>[_cam<k>].mp4 against target_gt[_1x]/, DyCheck
    /// frames selected by ROOT/dycheck/dycheck_<scene>_source_target_correspondence.txt.
    #[arg(long, requires_all = ["dataset", "method"], conflicts_with_all = ["mask", "protocol", "top_k"])]
    pub bundle: Option<PathBuf>,
    /// The bundle's dataset folder.
    #[arg(long, value_enum, requires = "bundle")]
    pub dataset: Option<BundleDatasetArg>,
    /// The bundle's method (its folder and file-name key: cognvs, gcd, trajcrafter, megasam_render,
    /// shape_of_motion, mosca, gt_render).
    #[arg(long, requires = "bundle")]
    pub method: Option<String>,
    /// DyCheck's resolution in the bundle: 720p (target_gt_1x/, 960x720) or 360p (target_gt/, 480x360).
    #[arg(long, value_enum, default_value = "720p", requires = "bundle")]
    pub dycheck_resolution: DycheckResolutionArg,
    /// Folder of per-frame mask PNGs (non-zero = co-visible), e.g. an export's mask/ folder;
    /// for folders of videos, a folder with one such folder per video name.
    #[arg(long)]
    pub mask: Option<PathBuf>,
    /// Also write the JSON to this file.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Resize predictions and targets to the protocol's size first (cv2.resize, as the official
    /// script; masks nearest): gcd 384x576, dycheck 960x720, dycheck360 480x360 (HxW). Without
    /// it, sizes must agree.
    #[arg(long, value_enum)]
    pub protocol: Option<ProtocolArg>,
    /// Each prediction PRED/NAME/ holds K samples; the best by PSNR (mPSNR with masks) is scored.
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub top_k: Option<u64>,
    /// Metrics beyond PSNR/SSIM (comma-separated: lpips, fid, kid) [default: those whose
    /// weights are given].
    #[arg(long, value_delimiter = ',')]
    pub metrics: Vec<MetricArg>,
    /// The eval networks' weights.
    #[command(flatten)]
    pub weights: EvalWeightArgs,
    /// Seed of KID's subsets.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Also write the Markdown table to this file.
    #[arg(long)]
    pub markdown: Option<PathBuf>,
    /// Compute device of the networks: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    pub device: String,
}

/// `--protocol`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ProtocolArg {
    /// Kubric-4D / ParallelDomain-4D (GCD): 384x576.
    Gcd,
    /// DyCheck iPhone at 720p: 960x720.
    Dycheck,
    /// DyCheck iPhone at 360p: 480x360.
    Dycheck360,
}

/// `--dataset` of a bundle.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum BundleDatasetArg {
    /// kubric_4d/ (GCD protocol).
    #[value(name = "kubric_4d")]
    Kubric4d,
    /// pardom_4d/ (GCD protocol).
    #[value(name = "pardom_4d")]
    Pardom4d,
    /// dycheck/.
    Dycheck,
}

/// `--dycheck-resolution`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum DycheckResolutionArg {
    /// 480x360 (HxW), targets in target_gt/.
    #[value(name = "360p")]
    P360,
    /// 960x720 (HxW), targets in target_gt_1x/.
    #[value(name = "720p")]
    P720,
}

/// `--metrics`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum MetricArg {
    /// LPIPS (needs --lpips-weights).
    Lpips,
    /// FID (needs --inception-weights).
    Fid,
    /// KID (needs --inception-weights).
    Kid,
}

/// What `trainer eval` computed.
#[derive(Debug)]
pub enum Evaluated {
    /// One pair without networks, protocol or top-k: its metrics (the JSON as before).
    Pair(VideoMetrics),
    /// Folders of videos or a bundle: the table.
    Table(ScoreReport),
}

impl EvalArgs {
    fn wants(&self, metric: MetricArg) -> bool {
        self.metrics.contains(&metric)
    }

    /// The bundle asked for, if any.
    fn bundle(&self) -> Option<score::Bundle> {
        match (&self.bundle, self.dataset, &self.method) {
            (Some(root), Some(dataset), Some(method)) => Some(score::Bundle {
                root: root.clone(),
                dataset: match dataset {
                    BundleDatasetArg::Kubric4d => score::BundleDataset::Kubric4d,
                    BundleDatasetArg::Pardom4d => score::BundleDataset::Pardom4d,
                    BundleDatasetArg::Dycheck => score::BundleDataset::Dycheck,
                },
                method: method.clone(),
                dycheck_720p: self.dycheck_resolution == DycheckResolutionArg::P720,
            }),
            _ => None,
        }
    }
}

/// Scores what the flags name; `progress` hears (videos done, of videos) for tables.
pub fn evaluate(args: &EvalArgs, progress: impl FnMut(usize, usize)) -> anyhow::Result<Evaluated> {
    let bundle = args.bundle();
    // clap requires --pred and --target without --bundle.
    let (pred, target) = (args.pred.clone().unwrap_or_default(), args.target.clone().unwrap_or_default());
    // One pair: a video file, or a folder holding frames itself (not videos).
    let single =
        bundle.is_none() && (pred.is_file() || crate::eval::metrics::read_frames(&pred).is_ok_and(|f| !f.is_empty()));
    let weights = &args.weights;
    let networks = weights.lpips_weights.is_some() || weights.inception_weights.is_some() || !args.metrics.is_empty();
    if single && !networks && args.protocol.is_none() && args.top_k.is_none() {
        return Ok(Evaluated::Pair(crate::eval::metrics::evaluate(&pred, &target, args.mask.as_deref())?));
    }
    if args.wants(MetricArg::Lpips) && weights.lpips_weights.is_none() {
        anyhow::bail!("--metrics lpips needs --lpips-weights FILE: {}", lpips::HOW_TO_GET);
    }
    if (args.wants(MetricArg::Fid) || args.wants(MetricArg::Kid)) && weights.inception_weights.is_none() {
        anyhow::bail!("--metrics fid/kid needs --inception-weights FILE: {}", inception::HOW_TO_GET);
    }
    let all = args.metrics.is_empty();
    let fid_requested = all || args.wants(MetricArg::Fid) || args.wants(MetricArg::Kid);
    let (bundle_protocol, bundle_pairs, bundle_notes) = match &bundle {
        Some(b) => {
            let (protocol, pairs, notes) = score::bundle_pairs(b)?;
            (Some(protocol), Some(pairs), notes)
        }
        None => (None, None, Vec::new()),
    };
    let request = score::ScoreRequest {
        pred,
        target,
        mask: args.mask.clone(),
        single,
        protocol: bundle_protocol.or(args.protocol.map(|p| match p {
            ProtocolArg::Gcd => score::Protocol::Gcd,
            ProtocolArg::Dycheck => score::Protocol::Dycheck,
            ProtocolArg::Dycheck360 => score::Protocol::Dycheck360,
        })),
        top_k: args.top_k.map(|k| k as usize),
        lpips: weights.lpips_weights.clone().filter(|_| all || args.wants(MetricArg::Lpips)),
        lpips_net: weights.lpips_net.net(),
        inception: weights.inception_weights.clone().filter(|_| fid_requested),
        kid: all || args.wants(MetricArg::Kid),
        kid_subsets: weights.kid_subsets,
        kid_subset_size: weights.kid_subset_size,
        seed: args.seed,
        device: crate::precision::usable_device(&args.device)?,
    };
    let mut report = match &bundle_pairs {
        Some(pairs) => score::run_pairs(&request, pairs, progress)?,
        None => score::run(&request, progress)?,
    };
    report.notes.splice(0..0, bundle_notes);
    Ok(Evaluated::Table(report))
}

/// Scores and prints (and writes) the JSON, with the table for folders and bundles.
pub fn run(args: EvalArgs) -> anyhow::Result<()> {
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template("{bar:30} {pos}/{len} videos [{elapsed_precise}, eta {eta}]")
            .expect("valid template"),
    );
    let evaluated = evaluate(&args, |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })?;
    bar.finish_and_clear();
    match evaluated {
        Evaluated::Pair(result) => {
            let json = serde_json::to_string_pretty(&result)?;
            write_optional(&args.out, &json)?;
            println!("{json}");
        }
        Evaluated::Table(report) => {
            let json = serde_json::to_string_pretty(&report)?;
            let table = score::markdown(&report);
            write_optional(&args.out, &json)?;
            write_optional(&args.markdown, &table)?;
            println!("{table}\n{json}");
        }
    }
    Ok(())
}
