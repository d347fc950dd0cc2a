//! The `trainer` command line as a library: one file per command holding its argument struct and
//! its conversion into the library's request, and [`common`] for the flag groups several commands
//! share (device, released-model flags, sampling and dtype, eval weights). `main.rs` only parses,
//! dispatches through [`run`] and maps the end to an exit status, so a test or another program
//! parses and runs exactly what a command runs ([`parse_from`], [`run`]).

pub mod benchmark;
pub mod comm;
pub mod common;
pub mod eval;
pub mod finetune;
pub mod forward;
pub mod merge_lora;
pub mod nvs;
pub mod plan;
pub mod pretrain;
pub mod sample;

use clap::{Parser, Subcommand};

/// CogNVS video-to-video diffusion in tch: the CogVideoX transformer, VAE and schedulers,
/// weight-compatible with diffusers.
#[derive(Debug, Parser)]
#[command(name = "trainer", version, about, long_about = None)]
pub struct Cli {
    /// The command.
    #[command(subcommand)]
    pub command: Command,
}

/// The commands (each documented in its file).
// Parsed once per process: boxing the larger argument structs would save nothing worth their noise.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Run one component on tensors from a safetensors file and write its output: for checking
    /// this port or a checkpoint against diffusers. The config's `_class_name` picks CogVideoX or
    /// Wan. Inputs and outputs use diffusers' argument names: CogVideoX transformer
    /// `hidden_states` [B,F,C,H,W], `encoder_hidden_states` [B,S,D], `timestep` [B] → `sample`;
    /// Wan transformer `hidden_states` [B,C,F,H,W], `timestep`, `encoder_hidden_states` and for
    /// image-to-video `encoder_hidden_states_image` → `sample`; vae_encoder `sample`
    /// [B,3,F,H,W] → `latent` (posterior mean, unscaled); vae_decoder `latent` → `sample`.
    /// Outputs are written as fp32.
    Forward(forward::ForwardArgs),
    /// Compare predictions with targets: PSNR and SSIM (scikit-image conventions), LPIPS (the
    /// lpips package) and FID/KID (clean-fid) from weight files you convert once with
    /// scripts/convert_eval_weights.py, masked mPSNR/mSSIM/mLPIPS with --mask. One video pair
    /// (video files or frame folders; JSON as before), or folders of videos matched by name
    /// (a Markdown table and JSON, per video and mean, FID/KID over all frames).
    Eval(eval::EvalArgs),
    /// Pretrain the transformer on training-pair shards (datagen pairs/build output): v-prediction
    /// with the CogVideoX-5B schedule, AdamW, checkpoints in the diffusers layout plus optimizer
    /// and data position; --resume continues the run exactly.
    Pretrain(pretrain::PretrainArgs),
    /// Sample a novel-view video from a checkpoint and a conditioning render (datagen render
    /// output, a frame folder or a video): DPM sampler, classifier-free guidance, mp4 out.
    Sample(sample::SampleArgs),
    /// Test-time finetuning: build the video's own self-supervised pairs in-process (datagen
    /// library) and finetune a checkpoint on them.
    Finetune(finetune::FinetuneArgs),
    /// The whole novel-view job on one video: test-time finetune a checkpoint (the released
    /// CogNVS one, or a run's) on the video's own pairs, render the video from each --trajectory,
    /// sample every render with one load of the finetuned model, and write OUT/<name>.mp4, PNG
    /// frames, a contact sheet (source | render | result) and OUT/nvs.json (settings, seeds,
    /// digests). Run again with the same arguments after a kill, it continues from the last
    /// finished phase.
    Nvs(nvs::NvsArgs),
    /// The paper's evaluation of a checkpoint on a dataset folder in one command: per scene, the
    /// split's input camera is the source, each held-out camera's poses a trajectory, `nvs`
    /// (finetuning with the paper's settings unless --steps 0) samples the novel views, and
    /// PSNR/SSIM/LPIPS (DyCheck: also over its co-visibility masks) and pooled FID/KID are
    /// computed at the protocol's size. Writes OUT/report.{md,json} with the paper's CogNVS rows
    /// beside ours; rerun with the same arguments it continues, skipping scored scenes.
    /// --compare RUN_A RUN_B prints the per-scene differences of two benchmark folders.
    Benchmark(benchmark::BenchmarkArgs),
    /// Merge a LoRA file into a base transformer and write the full diffusers transformer folder
    /// (config.json + diffusion_pytorch_model.safetensors).
    MergeLora(merge_lora::MergeLoraArgs),
    /// Print the memory plan of a training config per device: parameters, gradients, master
    /// weights, optimizer state, activations with and without checkpointing (per block and in
    /// all), VAE encode/decode peaks and the predicted peak, for the config's precision, LoRA
    /// and ZeRO settings. `pretrain` and `finetune` print the same plan and, on CUDA, refuse a
    /// run that does not fit the device's free memory.
    Plan(plan::PlanArgs),
    /// Check the multi-process setup the launcher gives (torchrun, srun, RANK/WORLD_SIZE): every
    /// collective the trainer uses, verified against values computed locally, then all-reduce
    /// bandwidth. Prints one line per check on rank 0; exits non-zero on any mismatch.
    CommCheck(comm::CommCheckArgs),
    /// How much of a data-parallel training step the gradient and weight exchange costs: the
    /// config's model trains on random clips, ZeRO-0 and ZeRO-2 each with real collectives and
    /// with local no-ops, interleaved in rounds; prints one JSON line (rank 0) with each
    /// variant's median step time and the exposed share of each stage. Run it under the launcher
    /// (torchrun, srun, RANK/WORLD_SIZE), at any world size, 1 included.
    CommCost(comm::CommCostArgs),
}

/// How a command ended when it did not fail.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Ended {
    /// It did all it was asked.
    Done,
    /// A preemption signal stopped it after a complete checkpoint or phase: the same command
    /// continues it (exit status [`crate::training::preempt::EXIT_PREEMPTED`]).
    Preempted,
}

impl Ended {
    fn of(preempted: bool) -> Self {
        if preempted { Self::Preempted } else { Self::Done }
    }
}

impl Command {
    /// Whether the command is a training run, whose exit status tells a preemption and a
    /// checkpoint that could not be written apart (README, "Long runs").
    pub fn is_training_run(&self) -> bool {
        matches!(self, Self::Pretrain(_) | Self::Finetune(_) | Self::Nvs(_) | Self::Benchmark(_))
    }
}

/// The command line as clap builds it, with every value argument taking values that look like
/// negative numbers (`--seed -1`): the value then reaches the flag's parser, whose refusal names
/// the flag, instead of being read as an unknown flag `-1`.
pub fn command_line() -> clap::Command {
    use clap::CommandFactory;
    Cli::command().mut_subcommands(|sub| {
        sub.mut_args(|arg| if arg.get_action().takes_values() { arg.allow_negative_numbers(true) } else { arg })
    })
}

/// Parses `args` (the program name first) as the `trainer` binary does.
pub fn parse_from<I, T>(args: I) -> Result<Cli, clap::Error>
where
    I: IntoIterator<Item = T>,
    T: Into<std::ffi::OsString> + Clone,
{
    use clap::FromArgMatches;
    Cli::from_arg_matches(&command_line().try_get_matches_from(args)?)
}

/// Runs one command as the `trainer` binary does, output and progress included.
pub fn run(command: Command) -> anyhow::Result<Ended> {
    let done = |result: anyhow::Result<()>| result.map(|()| Ended::Done);
    match command {
        Command::Forward(args) => done(forward::run(args)),
        Command::Eval(args) => done(eval::run(args)),
        Command::Pretrain(args) => pretrain::run(args).map(Ended::of),
        Command::Sample(args) => done(sample::run(args)),
        Command::Finetune(args) => finetune::run(args).map(Ended::of),
        Command::Nvs(args) => nvs::run(args).map(Ended::of),
        Command::Benchmark(args) => benchmark::run(args).map(Ended::of),
        Command::Plan(args) => done(plan::run(args)),
        Command::CommCheck(args) => done(comm::run_check(args)),
        Command::CommCost(args) => done(comm::run_cost(args)),
        Command::MergeLora(args) => done(merge_lora::run(args)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `trainer` with `args`, parsed as the binary parses them.
    fn parse(args: &[&str]) -> Result<Command, clap::Error> {
        parse_from(std::iter::once("trainer").chain(args.iter().copied())).map(|cli| cli.command)
    }

    const NVS: [&str; 9] = ["nvs", "--init", "ckpt", "--sequence", "seq", "--trajectory", "orbit.npy", "--out", "out"];

    #[test]
    fn nvs_and_finetune_take_the_layout_names_of_datagen_pairs() {
        for layout in datagen::api::LayoutName::ALL {
            let Command::Nvs(args) = parse(&[&NVS[..], &["--layout", layout.as_str()]].concat()).unwrap() else {
                panic!("nvs parses as nvs")
            };
            assert_eq!(args.request().unwrap().layout, Some(layout));
            let finetune =
                ["finetune", "--init", "ckpt", "--sequence", "seq", "--out", "o", "--layout", layout.as_str()];
            let Command::Finetune(args) = parse(&finetune).unwrap() else { panic!("finetune parses as finetune") };
            assert_eq!(args.request().layout, Some(layout));
        }
        let Command::Nvs(args) = parse(&NVS).unwrap() else { panic!("nvs parses as nvs") };
        assert_eq!(args.request().unwrap().layout, None, "detected unless named");
        let refused = parse(&[&NVS[..], &["--layout", "cognvs"]].concat()).unwrap_err().to_string();
        assert!(refused.contains("--layout") && refused.contains("cog-nvs"), "{refused}");
    }

    #[test]
    fn benchmark_runs_each_window_with_the_settings_nvs_would_take_from_the_same_flags() {
        let job = ["--steps", "7", "--config", "ft.toml", "--vae", "vae", "--sample-steps", "3", "--guidance", "2.5"];
        let more = ["--seed", "9", "--frames", "13", "--resize", "crop", "--size", "64x32", "--fps", "12"];
        let nvs = [&NVS[..], &job, &more, &["--finetune-trajectories", "9", "--stack-background", "on"]].concat();
        let Command::Nvs(nvs) = parse(&nvs).unwrap() else { panic!("nvs parses as nvs") };
        let bench = ["benchmark", "--dataset", "kubric4d", "--root", "root", "--init", "ckpt", "--out", "bench"];
        let bench = [&bench[..], &job, &more, &["--stack-background", "on"]].concat();
        let Command::Benchmark(bench) = parse(&bench).unwrap() else { panic!("benchmark parses as benchmark") };
        let benchmark::Asked::Run(request) = bench.asked().unwrap() else { panic!("a run, not a comparison") };
        // Kubric-4D's paper default of 9 finetuning trajectories equals nvs's explicit 9.
        assert_eq!(request.nvs.record(), nvs.request().unwrap().settings.record());
    }

    #[test]
    fn the_commands_that_write_checkpoints_are_the_training_runs() {
        let plan = parse(&["plan", "--config", "c.toml"]).unwrap();
        assert!(parse(&NVS).unwrap().is_training_run() && !plan.is_training_run());
    }
}
