//! Activation checkpointing (`[loop] gradient_checkpointing`): a checkpointed run repeats the
//! plain run's losses and weights, and the frozen VAE and text embedding hold no autograd state.

use std::path::{Path, PathBuf};
use std::process::Command;

use tch::Device;
use trainer::training::data::{DataPosition, ShardLoader};
use trainer::training::{CogNvsModel, LatentCache, PretrainConfig, read_metrics};

use super::parity::{assert_success, read_tensors, repo_root};
use super::pretrain::pairs;

/// Relative tolerance of the losses between the two runs: only the summation order of the
/// gradients differs (fp32).
const TOLERANCE: f64 = 1e-5;
/// Absolute tolerance of the final weights: AdamW divides by √v, so on parameters with tiny
/// gradients (norm biases) a last-bit difference in the gradient becomes a relative difference
/// of ~1e-5 in the update; 4 steps at lr 1e-3 move a weight by at most ~4e-3, of which 1e-6 is
/// a quarter per mille.
const WEIGHT_TOLERANCE: f64 = 1e-6;

/// The tiny preset for `steps` steps, without validation samples, checkpointed or not.
fn config(dir: &Path, steps: u64, checkpointing: bool) -> PathBuf {
    config_with(dir, steps, checkpointing, "")
}

/// [`config`] with `extra` TOML appended (after `[loop]`'s checkpointing line).
fn config_with(dir: &Path, steps: u64, checkpointing: bool, extra: &str) -> PathBuf {
    let text = std::fs::read_to_string(repo_root().join("configs/pretrain_tiny.toml"))
        .unwrap()
        .replace("steps = 20", &format!("steps = {steps}"))
        .replace("checkpoint_every = 10", &format!("checkpoint_every = {steps}"))
        .replace("validate_every = 10", "validate_every = 0");
    let text = format!("{text}\ngradient_checkpointing = {checkpointing}\n{extra}");
    let path = dir.join(format!("checkpointing_{checkpointing}_{}.toml", extra.len()));
    std::fs::write(&path, text).unwrap();
    path
}

/// The plain and the checkpointed run agree: `steps` losses within [`TOLERANCE`], and the
/// tensors of `file` in their last checkpoint (`what` they are) within [`WEIGHT_TOLERANCE`].
fn assert_runs_agree(plain: &Path, checkpointed: &Path, steps: u64, file: &str, what: &str) {
    let losses = |run: &Path| read_metrics(run).unwrap().iter().map(|m| m.loss).collect::<Vec<_>>();
    let (a, b) = (losses(plain), losses(checkpointed));
    assert_eq!(a.len(), steps as usize);
    for (step, (x, y)) in a.iter().zip(&b).enumerate() {
        assert!((x - y).abs() <= TOLERANCE * x.abs(), "step {}: loss {x} plain, {y} checkpointed", step + 1);
    }
    let tensors = |run: &Path| read_tensors(&run.join(format!("checkpoints/step-{steps:08}/{file}")));
    let (wa, wb) = (tensors(plain), tensors(checkpointed));
    assert!(!wa.is_empty() && wa.len() == wb.len());
    for (name, x) in &wa {
        let diff = (x - &wb[name]).abs().max().double_value(&[]);
        assert!(diff <= WEIGHT_TOLERANCE, "{name}: {what} differ by {diff}");
    }
}

fn pretrain(config: &Path, shards: &Path, out: &Path) {
    let output = Command::new(env!("CARGO_BIN_EXE_trainer"))
        .arg("pretrain")
        .arg("--config")
        .arg(config)
        .arg("--shards")
        .arg(shards)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap();
    assert_success(&output);
}

#[test]
fn checkpointed_run_repeats_the_plain_run() {
    let dir = tempfile::tempdir().unwrap();
    let shards = pairs(dir.path());
    let steps = 4;
    let (plain, checkpointed) = (dir.path().join("plain"), dir.path().join("checkpointed"));
    pretrain(&config(dir.path(), steps, false), &shards, &plain);
    pretrain(&config(dir.path(), steps, true), &shards, &checkpointed);
    let weights = "transformer/diffusion_pytorch_model.safetensors";
    assert_runs_agree(&plain, &checkpointed, steps, weights, "final weights");
}

/// LoRA with checkpointing: the frozen embeddings below the blocks have no graph, and the
/// adapters' gradients come from the recomputed blocks alone; the run repeats the plain LoRA run.
#[test]
fn checkpointed_lora_run_repeats_the_plain_lora_run() {
    let dir = tempfile::tempdir().unwrap();
    let shards = pairs(dir.path());
    let steps = 3;
    let lora = "[lora]\nrank = 4\nalpha = 2\n";
    let (plain, checkpointed) = (dir.path().join("plain"), dir.path().join("checkpointed"));
    pretrain(&config_with(dir.path(), steps, false, lora), &shards, &plain);
    pretrain(&config_with(dir.path(), steps, true, lora), &shards, &checkpointed);
    assert_runs_agree(&plain, &checkpointed, steps, trainer::loaders::lora::LORA_WEIGHTS_NAME, "adapters");
}

#[test]
fn frozen_vae_and_text_embedding_hold_no_autograd_state() {
    let dir = tempfile::tempdir().unwrap();
    let shards = pairs(dir.path());
    let config = PretrainConfig::from_toml_file(&config(dir.path(), 1, true)).unwrap();
    let model = CogNvsModel::load(&config.model, None, 0, Device::Cpu).unwrap();
    let mut loader = ShardLoader::open(&[shards], config.data.clone(), DataPosition::default()).unwrap();
    let batch = loader.next_batch().unwrap();
    let cache_dir = dir.path().join("latents");
    for cache in [None, Some(LatentCache::open(&cache_dir, &model.vae, &model.vae_vs, &config.data).unwrap())] {
        let value = model
            .loss_backward(
                &batch,
                (-3.0, 0.5),
                cache.as_ref(),
                1.0,
                trainer::training::Backward { checkpointing: true, on_stage: None },
                trainer::training::Draws::SINGLE,
            )
            .unwrap();
        assert!(value.is_finite());
        for (name, variable) in model.vae_vs.variables() {
            assert!(!variable.requires_grad() && !variable.grad().defined(), "VAE variable {name} holds a gradient");
        }
        assert!(!model.text.requires_grad() && !model.text.grad().defined(), "the text embedding holds a gradient");
        let trained = model.vs.trainable_variables();
        assert!(trained.iter().all(|v| v.grad().defined()), "every transformer variable receives a gradient");
    }
}
