//! LoRA on Wan in diffusers' Wan key layout: our adapter files load in `WanPipeline.
//! load_lora_weights` (diffusers + peft) with our outputs, for text-to-video and for
//! image-to-video with the image cross-attention's `add_k_proj` / `add_v_proj`; the files a
//! diffusers trainer saves (peft metadata with alpha ≠ r, rsLoRA) load in ours; `merge-lora` merges
//! into a Wan base; and with LoRA on only the adapters get gradients.
//!
//! Reference values come from one run of `scripts/goldens_wan_lora.py` over every case.

use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;

use trainer::loaders::lora::{LORA_WEIGHTS_NAME, LoraFile};
use trainer::models::lora::LoraConfig;
use trainer::models::wan::transformer_wan::{
    self as transformer, WanTransformer3DModel, WanTransformer3DModelConfig, WanTransformerInput,
};
use trainer::models::weights;
use trainer::tch::{self, Device, Kind, Tensor};

use super::parity::{assert_close, assert_success, errors, read_tensors, run_python};

/// Rank and alpha of the test adapters: alpha ≠ rank, so that a scale lost on the way shows.
const RANK: i64 = 4;
const ALPHA: f64 = 2.0;
/// Largest error relative to the reference's magnitude between our LoRA transformer and
/// diffusers + peft on the same files (fp32), as for the CogVideoX LoRA.
const PARITY: f64 = 1e-5;
/// Smallest relative change an adapter must make to the output, so that parity is not reached
/// by an adapter that was dropped.
const MIN_CHANGE: f64 = 1e-2;
/// Standard deviation of our random adapter weights (far from `B`'s zero start).
const ADAPTER_STD: f64 = 0.2;

/// One model structure the LoRA round trip runs on.
struct Case {
    name: &'static str,
    config: WanTransformer3DModelConfig,
    /// Targets of our adapter.
    targets: Vec<String>,
    /// Whether diffusers' adapter uses rsLoRA's `alpha / √r`.
    rslora: bool,
}

fn cases() -> Vec<Case> {
    let t2v = WanTransformer3DModelConfig::tiny_t2v();
    let i2v = WanTransformer3DModelConfig::tiny_i2v();
    // T2V: the default attention targets plus the feed-forward, so every linear kind is covered.
    let mut t2v_targets = transformer::lora_target_modules(&t2v);
    t2v_targets.extend(["ffn.net.0.proj", "ffn.net.2"].map(String::from));
    vec![
        Case { name: "t2v", targets: t2v_targets, config: t2v, rslora: false },
        Case { name: "i2v", targets: transformer::lora_target_modules(&i2v), config: i2v, rslora: true },
    ]
}

/// Random inputs of a tiny model: 2 latent frames of 4 × 6, text (512 tokens beside image ones).
fn inputs(c: &WanTransformer3DModelConfig) -> BTreeMap<String, Tensor> {
    let opts = (Kind::Float, Device::Cpu);
    let text_len = if c.image_dim.is_some() { transformer::TEXT_CONTEXT_LENGTH } else { 7 };
    let mut named = BTreeMap::from([
        ("hidden_states".to_string(), Tensor::randn([1, c.in_channels, 2, 4, 6], opts)),
        ("timestep".to_string(), Tensor::from_slice(&[321.0f32])),
        ("encoder_hidden_states".to_string(), Tensor::randn([1, text_len, c.text_dim], opts)),
    ]);
    if let Some(image_dim) = c.image_dim {
        named.insert("encoder_hidden_states_image".to_string(), Tensor::randn([1, 5, image_dim], opts));
    }
    named
}

fn forward(model: &WanTransformer3DModel, x: &BTreeMap<String, Tensor>) -> Tensor {
    let input = WanTransformerInput {
        hidden_states: &x["hidden_states"],
        timestep: &x["timestep"],
        encoder_hidden_states: &x["encoder_hidden_states"],
        encoder_hidden_states_image: x.get("encoder_hidden_states_image"),
    };
    tch::no_grad(|| model.forward(&input)).unwrap()
}

fn load_base(config: &WanTransformer3DModelConfig, dir: &Path) -> WanTransformer3DModel {
    let (vs, model) = transformer::build(config, Device::Cpu, Kind::Float).unwrap();
    transformer::load(&vs, dir).unwrap();
    model
}

fn keys_and_shapes(path: &Path) -> Vec<(String, Vec<i64>)> {
    read_tensors(path).into_iter().map(|(k, t)| (k, t.size())).collect()
}

#[test]
fn wan_lora_files_round_trip_through_diffusers_and_peft() {
    let dir = tempfile::tempdir().unwrap();
    let mut ours = BTreeMap::new();
    for (i, case) in cases().iter().enumerate() {
        let work = dir.path().join(case.name);
        let lora = LoraConfig { rank: RANK, alpha: ALPHA, target_modules: case.targets.clone(), ..Default::default() };
        tch::manual_seed(11 + i as i64);
        let (vs, lora_vs, model) = transformer::build_with_lora(&case.config, &lora, Device::Cpu, Kind::Float).unwrap();
        weights::save(&vs, &case.config, transformer::CLASS_NAME, &work.join("base"), weights::DEFAULT_MAX_SHARD_BYTES)
            .unwrap();
        tch::no_grad(|| {
            for (_, mut variable) in lora_vs.variables() {
                let noise = variable.randn_like() * ADAPTER_STD;
                variable.copy_(&noise);
            }
        });
        trainer::loaders::lora::save(&lora_vs, &BTreeMap::new(), lora.scale(), &work.join(LORA_WEIGHTS_NAME)).unwrap();
        let x = inputs(&case.config);
        let named: Vec<(&str, &Tensor)> = x.iter().map(|(k, t)| (k.as_str(), t)).collect();
        Tensor::write_safetensors(&named, work.join("inputs.safetensors")).unwrap();
        let settings = serde_json::json!({
            "r": RANK, "lora_alpha": ALPHA, "target_modules": case.targets, "use_rslora": case.rslora,
        });
        std::fs::write(work.join("lora.json"), settings.to_string()).unwrap();
        ours.insert(case.name, (forward(&model, &x), x));
    }
    let mut args = vec![dir.path().as_os_str()];
    args.extend(cases().iter().map(|c| std::ffi::OsStr::new(c.name)));
    run_python("goldens_wan_lora.py", &args);

    for case in cases() {
        let work = dir.path().join(case.name);
        let (our_output, x) = &ours[case.name];
        let reference = read_tensors(&work.join("outputs.safetensors"));
        let name = case.name;
        // Our file in diffusers: the same output as our adapters.
        assert_close(&format!("{name} LoRA vs diffusers+peft"), our_output, &reference["ours"], PARITY);
        let (_, changed) = errors(&reference["base"], &reference["ours"]);
        assert!(changed > MIN_CHANGE, "{name}: the adapter must change the output (by {changed} here)");
        // The same keys and shapes as the file diffusers saves for the same targets.
        let diffusers_file = work.join("diffusers_lora").join(LORA_WEIGHTS_NAME);
        assert_eq!(keys_and_shapes(&work.join(LORA_WEIGHTS_NAME)), keys_and_shapes(&diffusers_file), "{name} keys");
        if case.config.added_kv_proj_dim.is_some() {
            let key = "transformer.blocks.0.attn2.add_k_proj.lora_A.weight";
            assert!(read_tensors(&diffusers_file).contains_key(key), "{name}: no {key}");
        }

        // diffusers' file (peft metadata: alpha ≠ r, rsLoRA for I2V) merged into our base.
        let (vs, model) = transformer::build(&case.config, Device::Cpu, Kind::Float).unwrap();
        transformer::load(&vs, &work.join("base")).unwrap();
        LoraFile::read(&diffusers_file).unwrap().merge_into(&vs, &diffusers_file).unwrap();
        assert_close(
            &format!("{name} diffusers' LoRA in ours"),
            &forward(&model, x),
            &reference["diffusers_lora"],
            PARITY,
        );

        // `trainer merge-lora` on a Wan base: a full Wan transformer computing the same.
        let merged = work.join("merged");
        let output = Command::new(env!("CARGO_BIN_EXE_trainer"))
            .arg("merge-lora")
            .arg("--base")
            .arg(work.join("base"))
            .arg("--lora")
            .arg(work.join(LORA_WEIGHTS_NAME))
            .arg("--out")
            .arg(&merged)
            .output()
            .unwrap();
        assert_success(&output);
        assert_close(
            &format!("{name} merged"),
            &forward(&load_base(&case.config, &merged), x),
            &reference["ours"],
            PARITY,
        );
    }
}

#[test]
fn with_lora_only_the_adapters_get_gradients() {
    let c = WanTransformer3DModelConfig::tiny_i2v();
    let lora = LoraConfig {
        rank: RANK,
        alpha: ALPHA,
        target_modules: transformer::lora_target_modules(&c),
        ..Default::default()
    };
    tch::manual_seed(5);
    let (vs, lora_vs, model) = transformer::build_with_lora(&c, &lora, Device::Cpu, Kind::Float).unwrap();
    // Adapters on every attention projection of both blocks, the image ones included.
    let adapted: Vec<String> =
        lora_vs.variables().into_keys().filter_map(|k| k.strip_suffix(".lora_A.weight").map(String::from)).collect();
    assert_eq!(adapted.len() as i64, c.num_layers * (4 + 4 + 2), "{adapted:?}");
    assert!(adapted.iter().any(|m| m == "blocks.1.attn2.add_v_proj"));
    // `B` starts at zero (a fresh adapter leaves the model as it is); move it so `A` gets a gradient.
    tch::no_grad(|| {
        for (name, mut variable) in lora_vs.variables() {
            if name.ends_with("lora_B.weight") {
                let noise = variable.randn_like() * ADAPTER_STD;
                variable.copy_(&noise);
            }
        }
    });
    let x = inputs(&c);
    let input = WanTransformerInput {
        hidden_states: &x["hidden_states"],
        timestep: &x["timestep"],
        encoder_hidden_states: &x["encoder_hidden_states"],
        encoder_hidden_states_image: x.get("encoder_hidden_states_image"),
    };
    model.forward(&input).unwrap().square().mean(Kind::Float).backward();
    for (name, variable) in lora_vs.variables() {
        let grad = variable.grad();
        assert!(grad.defined() && grad.abs().max().double_value(&[]) > 0.0, "{name} has no gradient");
    }
    for (name, variable) in vs.variables() {
        assert!(!variable.requires_grad() && !variable.grad().defined(), "base variable {name} trains");
    }
}

#[test]
fn wan_lora_targets_that_match_nothing_are_named() {
    let t2v = WanTransformer3DModelConfig::tiny_t2v();
    let image_only = LoraConfig { target_modules: vec!["add_k_proj".to_string()], rank: RANK, ..Default::default() };
    let err = transformer::lora_shapes(&t2v, &image_only).unwrap_err().to_string();
    assert!(
        err.contains("lora.target_modules") && err.contains("add_k_proj") && err.contains("ffn.net.0.proj"),
        "{err}"
    );
    let too_wide = LoraConfig { rank: 1000, ..Default::default() };
    let err = transformer::lora_shapes(&t2v, &too_wide).unwrap_err().to_string();
    assert!(err.contains("lora.rank") && err.contains("1000"), "{err}");
    // Adapter sizes: r·(in + out) per adapted layer, 4 per attention × 2 attentions × 2 blocks.
    let sizes = transformer::lora_shapes(&t2v, &LoraConfig { rank: RANK, ..Default::default() }).unwrap();
    let dim = t2v.inner_dim() as u64;
    assert_eq!(sizes.len(), 16);
    assert!(sizes.iter().all(|(_, n)| *n == RANK as u64 * 2 * dim), "{sizes:?}");
}
