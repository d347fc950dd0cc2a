//! Forward + backward step time of the CogVideoX transformer in this crate, the Rust half of
//! `scripts/bench_transformer.py` (which runs diffusers on the same config and inputs and reports
//! the ratio).
//!
//! `cargo run --release -p trainer --example bench_transformer -- CONFIG.json BATCH FRAMES HEIGHT
//! WIDTH TEXT_LEN STEPS WARMUP THREADS [cpu|cuda] [f32|bf16] [forward|train]`
//!
//! Prints one JSON line: per-step seconds (after warm-up), their median, and the process's peak
//! RSS (and peak CUDA memory on a GPU). Random weights and inputs: time does not depend on values.

use std::time::Instant;

use anyhow::{Context, Result, bail};
use trainer::diffusers_config::DiffusersConfig;
use trainer::models::cogvideox::cogvideox_transformer_3d::{
    self as transformer, CogVideoXTransformer3DModelConfig, TransformerInput,
};
use trainer::tch::{self, Device, Kind, Tensor};

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 9 {
        bail!(
            "usage: bench_transformer CONFIG BATCH FRAMES HEIGHT WIDTH TEXT_LEN STEPS WARMUP THREADS [cpu|cuda] [f32|bf16] [forward|train]"
        );
    }
    let config = CogVideoXTransformer3DModelConfig::from_json_file(&args[0])?;
    let num = |i: usize, name: &str| -> Result<i64> { args[i].parse().with_context(|| name.to_string()) };
    let (batch, frames, height, width, text_len) =
        (num(1, "BATCH")?, num(2, "FRAMES")?, num(3, "HEIGHT")?, num(4, "WIDTH")?, num(5, "TEXT_LEN")?);
    let (steps, warmup, threads) = (num(6, "STEPS")?, num(7, "WARMUP")?, num(8, "THREADS")?);
    let device = match args.get(9).map(String::as_str).unwrap_or("cpu") {
        "cuda" => Device::Cuda(0),
        _ => Device::Cpu,
    };
    let kind = match args.get(10).map(String::as_str).unwrap_or("f32") {
        "bf16" => Kind::BFloat16,
        _ => Kind::Float,
    };
    let train = args.get(11).map(String::as_str).unwrap_or("train") == "train";
    tch::set_num_threads(threads as i32);
    tch::manual_seed(0);
    let (vs, model) = transformer::build(&config, device, kind)?;
    let opts = (kind, device);
    let hidden = Tensor::randn([batch, frames, config.in_channels, height, width], opts);
    let text = Tensor::randn([batch, text_len, config.text_embed_dim], opts);
    let target = Tensor::randn([batch, frames, config.output_channels(), height, width], opts);
    let timestep = Tensor::full([batch], 500, (Kind::Int64, device));
    let rotary = model.rotary_for(frames, height, width, device)?;
    let input = TransformerInput {
        hidden_states: &hidden,
        encoder_hidden_states: &text,
        timestep: &timestep,
        ofs: None,
        image_rotary_emb: Some(&rotary),
    };
    let mut times = Vec::new();
    for step in 0..warmup + steps {
        let started = Instant::now();
        if train {
            let loss = (model.forward(&input, true)? - &target).square().mean(Kind::Float);
            loss.backward();
            for var in vs.trainable_variables() {
                let mut grad = var.grad();
                if grad.defined() {
                    let _ = grad.zero_();
                }
            }
        } else {
            let _ = tch::no_grad(|| model.forward(&input, false))?;
        }
        if let Device::Cuda(_) = device {
            tch::Cuda::synchronize(0);
        }
        if step >= warmup {
            times.push(started.elapsed().as_secs_f64());
        }
    }
    let mut sorted = times.clone();
    sorted.sort_by(f64::total_cmp);
    let median = sorted.get(sorted.len() / 2).copied().unwrap_or(f64::NAN);
    println!(
        "{}",
        serde_json::json!({
            "impl": "tch",
            "mode": if train { "train" } else { "forward" },
            "median_s": median,
            "step_s": times,
            "peak_rss_mb": peak_rss_mb(),
            "threads": tch::get_num_threads(),
        })
    );
    Ok(())
}

/// The process's peak resident set (`VmHWM`), in MB.
fn peak_rss_mb() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(f64::NAN, |kb| kb / 1024.0)
}
