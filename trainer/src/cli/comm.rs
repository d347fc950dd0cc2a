//! `trainer comm-check` and `trainer comm-cost`: the launcher's multi-process setup, checked and
//! measured.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

/// `trainer comm-check`'s flags.
#[derive(Debug, Args)]
pub struct CommCheckArgs {
    /// Size of the all-reduce bandwidth test in MiB (fp32).
    #[arg(long, default_value_t = 64)]
    pub mib: usize,
    /// All-reduces timed.
    #[arg(long, default_value_t = 5)]
    pub iterations: usize,
    /// Compute device: cpu (Gloo) or cuda (NCCL, the GPU chosen by LOCAL_RANK).
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Seconds any collective may wait.
    #[arg(long, default_value_t = 60.0)]
    pub timeout: f64,
}

/// `trainer comm-cost`'s flags.
#[derive(Debug, Args)]
pub struct CommCostArgs {
    /// Training TOML (as for `pretrain --config`; its [distributed] zero_stage and
    /// noop_collectives are overridden per variant).
    #[arg(long)]
    pub config: PathBuf,
    /// Timed steps per variant and round (after one warm-up step).
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u64).range(1..))]
    pub steps: u64,
    /// Rounds over the four variants.
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u64).range(1..))]
    pub rounds: u64,
    /// Compute device: cpu (Gloo) or cuda (NCCL, the GPU chosen by LOCAL_RANK).
    #[arg(long, default_value = "cpu")]
    pub device: String,
}

/// Checks the collectives and prints rank 0's lines.
pub fn run_check(args: CommCheckArgs) -> anyhow::Result<()> {
    let device = crate::precision::usable_device(&args.device)?;
    crate::distributed::comm_check::run_launched(device, args.timeout, args.mib as u64, args.iterations, |line| {
        println!("{line}")
    })?;
    Ok(())
}

/// Measures the exchange's cost and prints rank 0's JSON line.
pub fn run_cost(args: CommCostArgs) -> anyhow::Result<()> {
    let config = crate::training::PretrainConfig::from_toml_file(&args.config)?;
    // A launcher's world size of 1 still gets a process group: the exchange on one GPU.
    let launch = crate::distributed::Launch::from_env_any_size()?;
    let device = crate::precision::usable_device(&args.device)?;
    let (device, pg) = crate::distributed::join(launch, device, config.distributed.timeout_seconds)?;
    let Some(pg) = pg else {
        anyhow::bail!("no launcher variables (torchrun, srun, RANK/WORLD_SIZE): run it under a launcher");
    };
    let cost = crate::training::comm_cost(&config, device, &pg, args.steps as usize, args.rounds as usize)
        .with_context(|| format!("comm-cost with {}", args.config.display()))?;
    if pg.rank == 0 {
        println!("{}", serde_json::to_string(&cost)?);
    }
    Ok(())
}
