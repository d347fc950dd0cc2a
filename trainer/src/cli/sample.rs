//! `trainer sample`: a novel-view video sampled from a checkpoint and a conditioning.

use std::path::PathBuf;

use clap::Args;

use super::common::{DeviceArgs, ModelArgs, SamplingArgs, progress_bar};
use crate::pipelines::sampling::{SampleReport, SampleRequest};

/// `trainer sample`'s flags.
#[derive(Debug, Args)]
pub struct SampleArgs {
    /// Checkpoint: a run's (RUN/checkpoints/step-N, full or LoRA), a transformer folder (the
    /// released CogNVS transformer) or a pipeline folder with transformer/.
    #[arg(long)]
    pub ckpt: PathBuf,
    /// Where the models come from besides the checkpoint.
    #[command(flatten)]
    pub model: ModelArgs,
    /// Conditioning: a `datagen render` folder, a folder of frames, or a video.
    #[arg(long)]
    pub cond: PathBuf,
    /// Output: a video (.mp4), or a folder of lossless PNG frames (any other path).
    #[arg(long)]
    pub out: PathBuf,
    /// Negative text embedding for guidance [default: the prompt's].
    #[arg(long)]
    pub negative_text_embedding: Option<PathBuf>,
    /// Denoising steps.
    #[arg(long, default_value_t = 50)]
    pub steps: usize,
    /// How each conditioning is sampled.
    #[command(flatten)]
    pub sampling: SamplingArgs,
    /// The compute device.
    #[command(flatten)]
    pub device: DeviceArgs,
}

impl SampleArgs {
    /// The library's request.
    pub fn request(self) -> crate::Result<SampleRequest> {
        let device = self.device.usable()?;
        let mut model = self.model.source(self.ckpt);
        model.negative_text_embedding = self.negative_text_embedding;
        Ok(SampleRequest {
            model,
            condition: self.cond,
            out: self.out,
            steps: self.steps,
            guidance: self.sampling.guidance,
            seed: self.sampling.seed,
            load: self.sampling.load(device),
            framing: self.sampling.framing(),
        })
    }
}

/// Resolves the models, refuses a sample that does not fit the device, and samples;
/// `on_step` hears each denoising step.
pub fn sample(request: &SampleRequest, on_step: &mut dyn FnMut(usize, usize)) -> crate::Result<SampleReport> {
    let paths = request.model.resolve()?;
    crate::training::plan::check_sampling_memory(&paths, request.load, &request.framing)?;
    crate::pipelines::sampling::sample(request, &paths, on_step)
}

/// Samples and prints what was resized, the memory peaks, the timings and the output.
pub fn run(args: SampleArgs) -> anyhow::Result<()> {
    let request = args.request()?;
    let bar = progress_bar(request.steps as u64, "denoising");
    let report = sample(&request, &mut |i, _| bar.set_position(i as u64))?;
    bar.finish_and_clear();
    if report.source_size != report.model_size {
        let ((w, h), (mw, mh)) = (report.source_size, report.model_size);
        let back =
            if request.framing.restore_size { format!(" and the result back to {w}x{h}") } else { String::new() };
        eprintln!(
            "note: resized the conditioning from {w}x{h} to the model's {mw}x{mh} ({:?}){back}",
            request.framing.resize
        );
    }
    if report.frames < report.source_frames.min(request.framing.frames) {
        eprintln!(
            "note: sampled the first {} of the conditioning's {} frames (1 + 8k frames decode back to as many)",
            report.frames, report.source_frames
        );
    }
    if let Some((allocated, reserved)) = report.cuda_peaks {
        let gib = |b: u64| b as f64 / (1u64 << 30) as f64;
        println!("cuda memory: peak allocated {:.2} GiB, peak reserved {:.2} GiB", gib(allocated), gib(reserved));
    }
    let t = &report.timings;
    println!("seconds: encode {:.2}, denoise {:.2}, decode {:.2}", t.encode, t.denoise, t.decode);
    println!(
        "wrote {} ({} frames, {}x{}; sampled at {}x{}) after {} steps in {:.1} s",
        request.out.display(),
        report.frames,
        report.size.0,
        report.size.1,
        report.model_size.0,
        report.model_size.1,
        request.steps,
        report.seconds
    );
    Ok(())
}
