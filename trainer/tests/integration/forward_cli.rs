//! `trainer forward` end to end on the tiny goldens: transformer (sharded weights via the index),
//! VAE encoder and decoder match diffusers; bad inputs fail with the tensor named.

use std::collections::BTreeMap;
use std::path::Path;
use std::process::Output;

use trainer::tch::Tensor;

use super::parity::{assert_close, assert_success, read_tensors};

fn trainer(args: &[&dyn AsRef<std::ffi::OsStr>]) -> Output {
    let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_trainer"));
    cmd.arg("forward");
    for a in args {
        cmd.arg(a);
    }
    cmd.output().expect("run trainer")
}

/// `trainer forward --module transformer` with `extra` flags.
fn transformer(config: &Path, weights: &Path, inputs: &Path, out: &Path, extra: &[&str]) -> Output {
    let mut args: Vec<&dyn AsRef<std::ffi::OsStr>> = vec![
        &"--module",
        &"transformer",
        &"--config",
        &config,
        &"--weights",
        &weights,
        &"--inputs",
        &inputs,
        &"--out",
        &out,
    ];
    args.extend(extra.iter().map(|e| e as &dyn AsRef<std::ffi::OsStr>));
    trainer(&args)
}

fn write_inputs(path: &Path, io: &BTreeMap<String, Tensor>, pairs: &[(&str, &str)]) {
    let named: Vec<(&str, &Tensor)> = pairs.iter().map(|(name, key)| (*name, &io[*key])).collect();
    Tensor::write_safetensors(&named, path).unwrap();
}

#[test]
fn transformer_forward_matches_diffusers() {
    let goldens = super::transformer::goldens();
    let io = read_tensors(&goldens.join("transformer_io.safetensors"));
    let dir = tempfile::tempdir().unwrap();
    let inputs = dir.path().join("in.safetensors");
    let keys = [
        ("hidden_states", "cognvs.hidden_states"),
        ("encoder_hidden_states", "cognvs.encoder_hidden_states"),
        ("timestep", "cognvs.timestep"),
    ];
    write_inputs(&inputs, &io, &keys);
    let out = dir.path().join("out.safetensors");
    let model = goldens.join("cognvs_tiny_sharded");
    let index = model.join("diffusion_pytorch_model.safetensors.index.json");
    assert_success(&transformer(&model, &index, &inputs, &out, &[]));
    assert_close("trainer forward transformer", &read_tensors(&out)["sample"], &io["cognvs.sample"], 1e-4);

    let bf16 = dir.path().join("bf16.safetensors");
    assert_success(&transformer(&model, &index, &inputs, &bf16, &["--dtype", "bf16"]));
    assert_close("trainer forward transformer bf16", &read_tensors(&bf16)["sample"], &io["cognvs_bf16.sample"], 3e-2);
}

#[test]
fn vae_forward_matches_diffusers() {
    let goldens = super::vae::goldens();
    let io = read_tensors(&goldens.join("vae_io.safetensors"));
    let dir = tempfile::tempdir().unwrap();
    let vae = goldens.join("vae");
    let weights = vae.join("diffusion_pytorch_model.safetensors");
    let (enc_in, enc_out) = (dir.path().join("enc_in.safetensors"), dir.path().join("enc_out.safetensors"));
    write_inputs(&enc_in, &io, &[("sample", "encode.sample")]);
    assert_success(&trainer(&[
        &"--module",
        &"vae_encoder",
        &"--config",
        &vae,
        &"--weights",
        &weights,
        &"--inputs",
        &enc_in,
        &"--out",
        &enc_out,
    ]));
    assert_close("trainer forward vae_encoder", &read_tensors(&enc_out)["latent"], &io["encode.latent"], 1e-4);
    let (dec_in, dec_out) = (dir.path().join("dec_in.safetensors"), dir.path().join("dec_out.safetensors"));
    write_inputs(&dec_in, &io, &[("latent", "decode.latent")]);
    assert_success(&trainer(&[
        &"--module",
        &"vae_decoder",
        &"--config",
        &vae,
        &"--weights",
        &vae,
        &"--inputs",
        &dec_in,
        &"--out",
        &dec_out,
    ]));
    assert_close("trainer forward vae_decoder", &read_tensors(&dec_out)["sample"], &io["decode.sample"], 1e-4);
}

#[test]
fn bad_inputs_fail_naming_the_tensor() {
    let goldens = super::transformer::goldens();
    let io = read_tensors(&goldens.join("transformer_io.safetensors"));
    let dir = tempfile::tempdir().unwrap();
    let model = goldens.join("cognvs_tiny");
    let out = dir.path().join("out.safetensors");
    // No timestep.
    let inputs = dir.path().join("in.safetensors");
    write_inputs(
        &inputs,
        &io,
        &[("hidden_states", "cognvs.hidden_states"), ("encoder_hidden_states", "cognvs.encoder_hidden_states")],
    );
    let run = transformer(&model, &model, &inputs, &out, &[]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success() && stderr.contains("`timestep`"), "{stderr}");
    // Latents with the wrong channel count (the 2B case's 16 channels for the 32-channel model).
    write_inputs(
        &inputs,
        &io,
        &[
            ("hidden_states", "cogvideox2b.hidden_states"),
            ("encoder_hidden_states", "cogvideox2b.encoder_hidden_states"),
            ("timestep", "cogvideox2b.timestep"),
        ],
    );
    let run = transformer(&model, &model, &inputs, &out, &[]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        !run.status.success() && stderr.contains("hidden_states") && stderr.contains("[1, 3, 16, 6, 8]"),
        "{stderr}"
    );
    // A config that does not match the weights: named tensor, both shapes, before allocation.
    let other = goldens.join("cogvideox2b_tiny");
    let run = transformer(&other, &model, &inputs, &out, &[]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        !run.status.success()
            && stderr.contains("patch_embed.proj.weight")
            && stderr.contains("expected shape [32, 16, 2, 2]")
            && stderr.contains("got [32, 32, 2, 2]"),
        "{stderr}"
    );
    assert!(!out.exists(), "nothing is written on failure");
}
