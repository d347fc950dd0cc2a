//! `trainer plan`: the memory plan of a training config, or of sampling with its models.

use std::path::PathBuf;

use clap::Args;

/// `trainer plan`'s flags.
#[derive(Debug, Args)]
pub struct PlanArgs {
    /// Training TOML (as for `pretrain --config`).
    #[arg(long)]
    pub config: PathBuf,
    /// Ranks [default: the launcher's WORLD_SIZE / SLURM_NTASKS, else the config's
    /// data.world_size].
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub world_size: Option<u64>,
    /// Device the plan is for (decides precision = "auto"): cpu, cuda or cuda:N; no device is
    /// needed to plan.
    #[arg(long, default_value = "cuda")]
    pub device: String,
    /// Plan sampling instead of training: the config's models and [data] frames and size, its
    /// precision, with VAE tiling unless --no-vae-tiling.
    #[arg(long)]
    pub sampling: bool,
    /// With --sampling: guidance against another prompt (a batch of two).
    #[arg(long, requires = "sampling")]
    pub guided: bool,
    /// With --sampling: without VAE tiling.
    #[arg(long, requires = "sampling")]
    pub no_vae_tiling: bool,
}

/// The plan the flags ask for, as text.
pub fn plan(args: &PlanArgs) -> crate::Result<String> {
    let config = crate::training::PretrainConfig::from_toml_file(&args.config)?;
    let device = crate::precision::parse_device(&args.device)?;
    if !args.sampling {
        let plan = crate::training::plan::plan_run(&config, args.world_size.map(|n| n as usize), device)?;
        return Ok(plan.to_string());
    }
    let (transformer, vae) = config.model.configs(true)?;
    let tiles = crate::models::cogvideox::autoencoder_kl_cogvideox::TilingConfig::for_config(&vae);
    let aligned = !args.no_vae_tiling && tiles.lands_on_latent_pixels(vae.spatial_compression_ratio());
    let d = &config.data;
    let plan = crate::training::plan::sampling_plan(
        &transformer,
        &vae,
        (d.frames as u64, u64::from(d.height), u64::from(d.width)),
        config.train.precision.kind(device),
        device,
        aligned.then_some(&tiles),
        args.guided,
    )?;
    Ok(plan.to_string())
}

/// Prints the plan.
pub fn run(args: PlanArgs) -> anyhow::Result<()> {
    println!("{}", plan(&args)?);
    Ok(())
}
