//! Peak-memory / speed probe for the real-size CogVideoX-5B VAE encoder on random weights.
//!
//! `cargo run -p trainer --example vae_encode_memory -- FRAMES HEIGHT WIDTH [tiled|untiled] [f32|bf16]`
//! then read the peak RSS with `/usr/bin/time -v`. Random weights: memory and time do not depend
//! on the values.

use std::time::Instant;

use anyhow::{Context, Result, bail};
use trainer::models::cogvideox::autoencoder_kl_cogvideox::{self as vae, AutoencoderKLCogVideoXConfig, TilingConfig};
use trainer::tch::{self, Device, Kind, Tensor};

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 3 {
        bail!("usage: vae_encode_memory FRAMES HEIGHT WIDTH [tiled|untiled] [f32|bf16]");
    }
    let frames: i64 = args[0].parse().context("FRAMES")?;
    let height: i64 = args[1].parse().context("HEIGHT")?;
    let width: i64 = args[2].parse().context("WIDTH")?;
    let tiled = args.get(3).map(String::as_str).unwrap_or("tiled") == "tiled";
    let kind = match args.get(4).map(String::as_str).unwrap_or("f32") {
        "bf16" => Kind::BFloat16,
        _ => Kind::Float,
    };
    let config = AutoencoderKLCogVideoXConfig::cogvideox_5b();
    let (_vs, mut model) = vae::build(&config, Device::Cpu, kind)?;
    if tiled {
        model.enable_tiling(TilingConfig::for_config(&config))?;
    }
    tch::manual_seed(0);
    let x = (Tensor::rand([1, 3, frames, height, width], (Kind::Float, Device::Cpu)) * 2.0 - 1.0).to_kind(kind);
    let start = Instant::now();
    let latent = tch::no_grad(|| model.encode(&x))?;
    println!(
        "encode {frames}x{height}x{width} ({}, {kind:?}, {} threads): latent {:?} in {:.1} s",
        if tiled { "tiled" } else { "untiled" },
        tch::get_num_threads(),
        latent.size(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}
