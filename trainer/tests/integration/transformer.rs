//! Transformer parity with diffusers (learned + rotary and sin-cos positions, fp32 and bf16),
//! single-file and sharded checkpoints both ways, the exact 1025 names of the released CogNVS
//! checkpoint, and named errors for mismatched weights.
//!
//! Reference values come from `scripts/goldens_transformer.py` (diffusers'
//! `CogVideoXTransformer3DModel` with a fixed seed), run into a temporary folder once per binary.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::sync::OnceLock;

use trainer::diffusers_config::DiffusersConfig;
use trainer::models::cogvideox::cogvideox_transformer_3d::{
    self as transformer, CogVideoXTransformer3DModel, CogVideoXTransformer3DModelConfig, TransformerInput,
};
use trainer::models::weights;
use trainer::tch::{self, Device, Kind, Tensor, nn};

use super::parity::{assert_close, read_tensors, repo_root, run_python, run_script};

/// Output of `scripts/goldens_transformer.py`, generated once per test binary.
pub fn goldens() -> &'static Path {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    DIR.get_or_init(|| run_script("goldens_transformer.py")).path()
}

/// A model built from a golden folder's config.json with its weights loaded (names and shapes
/// checked both ways by `weights::load`).
fn load_model(dir: &Path, kind: Kind) -> (nn::VarStore, CogVideoXTransformer3DModel) {
    let config = CogVideoXTransformer3DModelConfig::from_json_file(dir).unwrap();
    let (mut vs, model) = transformer::build(&config, Device::Cpu, Kind::Float).unwrap();
    weights::load(&vs, dir).unwrap();
    vs.set_kind(kind);
    (vs, model)
}

fn forward(model: &CogVideoXTransformer3DModel, io: &BTreeMap<String, Tensor>, case: &str, kind: Kind) -> Tensor {
    let hidden = io[&format!("{case}.hidden_states")].to_kind(kind);
    let text = io[&format!("{case}.encoder_hidden_states")].to_kind(kind);
    let input = TransformerInput {
        hidden_states: &hidden,
        encoder_hidden_states: &text,
        timestep: &io[&format!("{case}.timestep")],
        ofs: None,
        image_rotary_emb: None,
    };
    tch::no_grad(|| model.forward(&input, false)).unwrap()
}

#[test]
fn tiny_preset_equals_the_golden_config() {
    let config = CogVideoXTransformer3DModelConfig::from_json_file(goldens().join("cognvs_tiny")).unwrap();
    assert_eq!(
        CogVideoXTransformer3DModelConfig { extra: Default::default(), ..config },
        CogVideoXTransformer3DModelConfig::tiny(),
        "the script's TINY_COGNVS and the Rust `tiny` preset must agree"
    );
}

#[test]
fn forward_matches_diffusers_with_learned_and_rotary_positions() {
    let (_vs, model) = load_model(&goldens().join("cognvs_tiny"), Kind::Float);
    let io = read_tensors(&goldens().join("transformer_io.safetensors"));
    let out = forward(&model, &io, "cognvs", Kind::Float);
    assert_close("transformer cognvs-tiny (batch 2, stored positional table)", &out, &io["cognvs.sample"], 1e-4);
    // A frame count other than the stored table's: diffusers computes a sin-cos table instead.
    let out = forward(&model, &io, "cognvs_f2", Kind::Float);
    assert_close("transformer cognvs-tiny (2 latent frames, computed table)", &out, &io["cognvs_f2.sample"], 1e-4);
}

#[test]
fn forward_matches_diffusers_with_sincos_positions() {
    let (_vs, model) = load_model(&goldens().join("cogvideox2b_tiny"), Kind::Float);
    let io = read_tensors(&goldens().join("transformer_io.safetensors"));
    let out = forward(&model, &io, "cogvideox2b", Kind::Float);
    assert_close(
        "transformer cogvideox-2b-tiny (sin-cos positions, 6x8 latents)",
        &out,
        &io["cogvideox2b.sample"],
        1e-4,
    );
}

#[test]
fn bf16_matches_diffusers_bf16() {
    let (_vs, model) = load_model(&goldens().join("cognvs_tiny"), Kind::BFloat16);
    let io = read_tensors(&goldens().join("transformer_io.safetensors"));
    let out = forward(&model, &io, "cognvs", Kind::BFloat16);
    assert_eq!(out.kind(), Kind::BFloat16);
    // Both sides round to 8 mantissa bits at every op, in different orders.
    assert_close("transformer bf16 vs diffusers bf16", &out, &io["cognvs_bf16.sample"], 3e-2);
    assert_close("transformer bf16 vs diffusers fp32", &out, &io["cognvs.sample"], 5e-2);
}

#[test]
fn sharded_checkpoint_loads_the_same_weights() {
    let (single, _) = load_model(&goldens().join("cognvs_tiny"), Kind::Float);
    let (sharded, _) = load_model(&goldens().join("cognvs_tiny_sharded"), Kind::Float);
    let (a, b) = (single.variables(), sharded.variables());
    assert_eq!(a.len(), b.len());
    for (name, tensor) in &a {
        assert!(tensor.equal(&b[name]), "{name} differs between the single-file and sharded checkpoints");
    }
}

#[test]
fn saved_checkpoints_load_in_diffusers_and_compute_the_same() {
    // A model with our own random initialisation, saved by us (single file and sharded), loaded by
    // diffusers' from_pretrained and run there on the same inputs.
    tch::manual_seed(11);
    let config = CogVideoXTransformer3DModelConfig::tiny();
    let (vs, model) = transformer::build(&config, Device::Cpu, Kind::Float).unwrap();
    let io = read_tensors(&goldens().join("transformer_io.safetensors"));
    let ours = forward(&model, &io, "cognvs", Kind::Float);
    let dir = tempfile::tempdir().unwrap();
    let inputs = dir.path().join("inputs.safetensors");
    let named: Vec<(&str, &Tensor)> = ["hidden_states", "encoder_hidden_states", "timestep"]
        .iter()
        .map(|n| (*n, &io[&format!("cognvs.{n}")]))
        .collect();
    Tensor::write_safetensors(&named, &inputs).unwrap();
    let cases = [("single", weights::DEFAULT_MAX_SHARD_BYTES), ("sharded", 50_000)];
    // Both folders saved first, then run by diffusers in one Python process.
    let mut reload_args: Vec<std::ffi::OsString> = vec!["--reload-each".into(), inputs.into_os_string()];
    for (name, shard_bytes) in cases {
        let folder = dir.path().join(name);
        weights::save(&vs, &config, transformer::CLASS_NAME, &folder, shard_bytes).unwrap();
        assert_eq!(folder.join(weights::WEIGHTS_INDEX_NAME).exists(), name == "sharded");
        reload_args.extend([folder.into_os_string(), dir.path().join(format!("{name}_out.safetensors")).into()]);
    }
    let reload_args: Vec<&std::ffi::OsStr> = reload_args.iter().map(|a| a.as_os_str()).collect();
    run_python("goldens_transformer.py", &reload_args);
    for (name, _) in cases {
        let folder = dir.path().join(name);
        let theirs = read_tensors(&dir.path().join(format!("{name}_out.safetensors")));
        assert_close(&format!("our {name} checkpoint run by diffusers"), &ours, &theirs["sample"], 1e-4);
        // And back: our loader reads our own output.
        let (again, _) = load_model(&folder, Kind::Float);
        assert_eq!(again.len(), vs.len());
    }
}

#[test]
fn cognvs_5b_module_tree_has_exactly_the_reference_names() {
    let shapes = transformer::variable_shapes(&CogVideoXTransformer3DModelConfig::cognvs_5b()).unwrap();
    let keys_file = repo_root().join("trainer/tests/reference/cognvs_transformer_keys.txt");
    let text = std::fs::read_to_string(&keys_file).unwrap_or_else(|e| panic!("{}: {e}", keys_file.display()));
    let reference: BTreeSet<&str> = text.lines().map(str::trim).filter(|l| !l.is_empty()).collect();
    assert_eq!(reference.len(), 1025);
    let ours: BTreeSet<&str> = shapes.keys().map(String::as_str).collect();
    let missing: Vec<_> = reference.difference(&ours).collect();
    let extra: Vec<_> = ours.difference(&reference).collect();
    assert!(missing.is_empty() && extra.is_empty(), "missing {missing:?}, extra {extra:?}");
    // Shapes equal those of diffusers' model built on the meta device with the same config.
    let json = std::fs::read_to_string(goldens().join("cognvs_5b_shapes.json")).unwrap();
    let theirs: BTreeMap<String, Vec<i64>> = serde_json::from_str(&json).unwrap();
    assert_eq!(shapes, theirs);
    let params: i64 = shapes.values().map(|s| s.iter().product::<i64>()).sum();
    println!("cognvs-5b: {} tensors, {params} values", shapes.len());
}

#[test]
fn cognvs_5b_preset_equals_the_reference_config() {
    let path = repo_root().join("trainer/tests/reference/cognvs_transformer_config.json");
    let config = CogVideoXTransformer3DModelConfig::from_json_file(&path).unwrap();
    assert!(config.unknown_keys().is_empty(), "{:?}", config.unknown_keys());
    assert_eq!(
        CogVideoXTransformer3DModelConfig { extra: Default::default(), ..config },
        CogVideoXTransformer3DModelConfig::cognvs_5b()
    );
}

#[test]
fn mismatched_weights_are_named_errors() {
    // Weights of another config (wider heads): the first differing tensor, both shapes.
    let wider =
        CogVideoXTransformer3DModelConfig { attention_head_dim: 24, ..CogVideoXTransformer3DModelConfig::tiny() };
    let (vs, _) = transformer::build(&wider, Device::Cpu, Kind::Float).unwrap();
    let err = weights::load(&vs, &goldens().join("cognvs_tiny")).unwrap_err().to_string();
    assert!(err.contains("expected shape [48") && err.contains("got [32"), "{err}");
    // CogVideoX-2B-style weights (16 input channels, no stored table) for a CogNVS config.
    let (vs, _) = transformer::build(&CogVideoXTransformer3DModelConfig::tiny(), Device::Cpu, Kind::Float).unwrap();
    let err = weights::load(&vs, &goldens().join("cogvideox2b_tiny")).unwrap_err().to_string();
    assert!(err.contains("cogvideox2b_tiny"), "{err}");
    assert!(err.contains("patch_embed.pos_embedding") || err.contains("patch_embed.proj.weight"), "{err}");
    // Checked from the headers alone, before any allocation: the 5B shapes against tiny weights.
    let shapes = transformer::variable_shapes(&CogVideoXTransformer3DModelConfig::cognvs_5b()).unwrap();
    let found = weights::read_checkpoint_info(&goldens().join("cognvs_tiny")).unwrap();
    let err = weights::check_against(&shapes, &found, &goldens().join("cognvs_tiny")).unwrap_err().to_string();
    assert!(err.contains("expected shape [") && err.contains("got ["), "{err}");
}
