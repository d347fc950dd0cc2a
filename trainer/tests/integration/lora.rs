//! LoRA training (`[lora]`): only adapters train and hold optimizer state, checkpoints hold
//! `pytorch_lora_weights.safetensors` in diffusers' layout, a resumed run repeats the
//! uninterrupted one, the file loads in diffusers (peft) with our outputs, `merge-lora`
//! round-trips, and mismatched files or configs fail naming the key and both shapes.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use tch::{Device, Kind, Tensor};
use trainer::loaders::lora::LORA_WEIGHTS_NAME;
use trainer::models::cogvideox::cogvideox_transformer_3d::{
    self as transformer, CogVideoXTransformer3DModelConfig, TransformerInput,
};
use trainer::models::lora::LoraConfig;
use trainer::training::read_metrics;

use super::parity::{errors, read_tensors, repo_root, run_python};
use super::pretrain::pairs;

/// Rank and alpha of the test adapters: alpha ≠ rank, so a scale that is lost on the way to
/// diffusers shows.
const RANK: i64 = 4;
const ALPHA: f64 = 2.0;
/// Largest error relative to the reference's magnitude between our LoRA transformer and
/// diffusers + peft on the same files (fp32).
const PARITY: f64 = 1e-5;

fn config(dir: &Path, name: &str, steps: u64, lora: &str) -> PathBuf {
    let text = std::fs::read_to_string(repo_root().join("configs/pretrain_tiny.toml"))
        .unwrap()
        .replace("steps = 20", &format!("steps = {steps}"))
        .replace("checkpoint_every = 10", "checkpoint_every = 2")
        .replace("validate_every = 10", "validate_every = 0");
    let path = dir.join(format!("{name}.toml"));
    std::fs::write(&path, format!("{text}\n{lora}\n")).unwrap();
    path
}

fn lora_section() -> String {
    format!("[lora]\nrank = {RANK}\nalpha = {ALPHA}\n")
}

fn trainer(args: &[&std::ffi::OsStr]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_trainer")).args(args).output().unwrap()
}

fn pretrain(config: &Path, shards: &Path, out: &Path, resume: bool) -> std::process::Output {
    let mut args: Vec<&std::ffi::OsStr> = vec![
        "pretrain".as_ref(),
        "--config".as_ref(),
        config.as_os_str(),
        "--shards".as_ref(),
        shards.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ];
    if resume {
        args.push("--resume".as_ref());
    }
    trainer(&args)
}

fn ok(output: &std::process::Output) {
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
}

/// Random inputs of the tiny transformer: 3 latent frames, batch 1.
fn inputs(path: &Path) -> BTreeMap<String, Tensor> {
    let c = CogVideoXTransformer3DModelConfig::tiny();
    tch::manual_seed(7);
    let opts = (Kind::Float, Device::Cpu);
    let named = [
        ("hidden_states", Tensor::randn([1, 3, c.in_channels, c.sample_height, c.sample_width], opts)),
        ("encoder_hidden_states", Tensor::randn([1, c.max_text_seq_length, c.text_embed_dim], opts)),
        ("timestep", Tensor::from_slice(&[321i64])),
    ];
    Tensor::write_safetensors(&named.iter().map(|(n, t)| (*n, t)).collect::<Vec<_>>(), path).unwrap();
    named.into_iter().map(|(n, t)| (n.to_string(), t)).collect()
}

fn forward(model: &transformer::CogVideoXTransformer3DModel, x: &BTreeMap<String, Tensor>) -> Tensor {
    let input = TransformerInput {
        hidden_states: &x["hidden_states"],
        encoder_hidden_states: &x["encoder_hidden_states"],
        timestep: &x["timestep"],
        ofs: None,
        image_rotary_emb: None,
    };
    tch::no_grad(|| model.forward(&input, false)).unwrap()
}

#[test]
fn lora_run_trains_adapters_only_saves_diffusers_layout_and_resumes_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let shards = pairs(dir.path());
    let full = dir.path().join("full");
    ok(&pretrain(&config(dir.path(), "full", 4, &lora_section()), &shards, &full, false));
    let step4 = full.join("checkpoints/step-00000004");
    assert!(!step4.join("transformer").exists(), "a LoRA checkpoint holds no full transformer");
    let file = read_tensors(&step4.join(LORA_WEIGHTS_NAME));
    let c = CogVideoXTransformer3DModelConfig::tiny();
    let inner = c.inner_dim();
    let mut expected = Vec::new();
    for block in 0..c.num_layers {
        for module in ["to_q", "to_k", "to_v", "to_out.0"] {
            let key = format!("transformer.transformer_blocks.{block}.attn1.{module}");
            expected.push((format!("{key}.lora_A.weight"), vec![RANK, inner]));
            expected.push((format!("{key}.lora_B.weight"), vec![inner, RANK]));
        }
    }
    expected.sort();
    let found: Vec<(String, Vec<i64>)> = file.iter().map(|(k, t)| (k.clone(), t.size())).collect();
    assert_eq!(found, expected, "keys and shapes of the diffusers LoRA layout");
    let b = &file["transformer.transformer_blocks.0.attn1.to_q.lora_B.weight"];
    assert!(b.abs().max().double_value(&[]) > 0.0, "the adapters trained");
    // Only the adapters have optimizer state.
    let optimizer = read_tensors(&step4.join("optimizer.safetensors"));
    let moments = optimizer.keys().filter(|k| k.starts_with("exp_avg.")).count();
    assert_eq!(moments, expected.len());
    assert!(full.join("base_transformer/config.json").is_file(), "a preset base is kept once for the adapters");

    // Interrupted at step 2, resumed to 4: the same losses and adapters, bit for bit.
    let parts = dir.path().join("parts");
    ok(&pretrain(&config(dir.path(), "parts2", 2, &lora_section()), &shards, &parts, false));
    ok(&pretrain(&config(dir.path(), "parts4", 4, &lora_section()), &shards, &parts, true));
    let losses = |run: &Path| read_metrics(run).unwrap().iter().map(|m| m.loss).collect::<Vec<_>>();
    assert_eq!(losses(&parts), losses(&full));
    let resumed = read_tensors(&parts.join("checkpoints/step-00000004").join(LORA_WEIGHTS_NAME));
    for (name, t) in &file {
        assert!(t.equal(&resumed[name]), "{name} differs after resume");
    }

    // A LoRA checkpoint samples and merges on its own: its run kept the base.
    let merged = dir.path().join("merged");
    ok(&trainer(&[
        "merge-lora".as_ref(),
        "--base".as_ref(),
        step4.as_os_str(),
        "--lora".as_ref(),
        step4.join(LORA_WEIGHTS_NAME).as_os_str(),
        "--out".as_ref(),
        merged.as_os_str(),
    ]));
    assert!(merged.join("config.json").is_file());
    ok(&trainer(&[
        "sample".as_ref(),
        "--ckpt".as_ref(),
        step4.as_os_str(),
        "--cond".as_ref(),
        dir.path().join("seq/gt_rgb.mp4").as_os_str(),
        "--out".as_ref(),
        dir.path().join("novel.mp4").as_os_str(),
        "--steps".as_ref(),
        "1".as_ref(),
    ]));
    assert!(dir.path().join("novel.mp4").is_file());

    // Resuming a LoRA run with a full-model config is refused.
    let refused = pretrain(&config(dir.path(), "nolora", 6, ""), &shards, &parts, true);
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success() && stderr.contains("LoRA checkpoint"), "{stderr}");
}

#[test]
fn lora_file_loads_in_diffusers_with_our_outputs_and_merge_round_trips() {
    let dir = tempfile::tempdir().unwrap();
    let c = CogVideoXTransformer3DModelConfig::tiny();
    let base = dir.path().join("base");
    let lora = LoraConfig { rank: RANK, alpha: ALPHA, ..LoraConfig::default() };
    tch::manual_seed(3);
    let (vs, lora_vs, model) = transformer::build_with_lora(&c, &lora, Device::Cpu, Kind::Float).unwrap();
    trainer::models::weights::save(
        &vs,
        &c,
        transformer::CLASS_NAME,
        &base,
        trainer::models::weights::DEFAULT_MAX_SHARD_BYTES,
    )
    .unwrap();
    // Adapters far from their zero start, so that a lost scale or a dropped layer shows.
    tch::no_grad(|| {
        for (_, mut variable) in lora_vs.variables() {
            let noise = variable.randn_like() * 0.2;
            variable.copy_(&noise);
        }
    });
    let file = dir.path().join(LORA_WEIGHTS_NAME);
    trainer::loaders::lora::save(&lora_vs, &BTreeMap::new(), lora.scale(), &file).unwrap();
    let x = inputs(&dir.path().join("inputs.safetensors"));
    let ours = forward(&model, &x);

    // diffusers + peft on the same base folder and our LoRA file.
    let reference = dir.path().join("diffusers.safetensors");
    run_python(
        "goldens_transformer.py",
        &[
            "--reload".as_ref(),
            base.as_os_str(),
            dir.path().join("inputs.safetensors").as_os_str(),
            reference.as_os_str(),
            file.as_os_str(),
        ],
    );
    let reference = &read_tensors(&reference)["sample"];
    let (abs, rel) = errors(&ours, reference);
    println!("LoRA vs diffusers+peft: max abs {abs:.3e}, relative {rel:.3e}");
    assert!(rel <= PARITY, "LoRA output differs from diffusers+peft: {abs} abs, {rel} relative");
    let (base_vs, base_model) = transformer::build(&c, Device::Cpu, Kind::Float).unwrap();
    trainer::models::weights::load(&base_vs, &base).unwrap();
    let base_only = forward(&base_model, &x);
    let (_, changed) = errors(&base_only, reference);
    assert!(changed > 1e-2, "the adapter must change the output (by {changed} here)");

    // merge-lora writes a full transformer computing the same.
    let merged = dir.path().join("merged");
    ok(&trainer(&[
        "merge-lora".as_ref(),
        "--base".as_ref(),
        base.as_os_str(),
        "--lora".as_ref(),
        file.as_os_str(),
        "--out".as_ref(),
        merged.as_os_str(),
    ]));
    let (merged_vs, merged_model) = transformer::build(&c, Device::Cpu, Kind::Float).unwrap();
    trainer::models::weights::load(&merged_vs, &merged).unwrap();
    let (abs, rel) = errors(&forward(&merged_model, &x), reference);
    println!("merged vs diffusers+peft: max abs {abs:.3e}, relative {rel:.3e}");
    assert!(rel <= PARITY, "merged transformer differs: {abs} abs, {rel} relative");
}

#[test]
fn mismatched_lora_files_and_configs_fail_naming_key_and_shapes() {
    let dir = tempfile::tempdir().unwrap();
    let c = CogVideoXTransformer3DModelConfig::tiny();
    let base = dir.path().join("base");
    let (vs, _) = transformer::build(&c, Device::Cpu, Kind::Float).unwrap();
    trainer::models::weights::save(
        &vs,
        &c,
        transformer::CLASS_NAME,
        &base,
        trainer::models::weights::DEFAULT_MAX_SHARD_BYTES,
    )
    .unwrap();
    let inner = c.inner_dim();
    let write = |name: &str, tensors: &[(&str, Tensor)]| {
        let path = dir.path().join(name);
        Tensor::write_safetensors(&tensors.iter().map(|(n, t)| (*n, t)).collect::<Vec<_>>(), &path).unwrap();
        path
    };
    let merge = |lora: &Path, out: &str| {
        let out = dir.path().join(out);
        let output = trainer(&[
            "merge-lora".as_ref(),
            "--base".as_ref(),
            base.as_os_str(),
            "--lora".as_ref(),
            lora.as_os_str(),
            "--out".as_ref(),
            out.as_os_str(),
        ]);
        assert!(!output.status.success());
        assert!(!out.exists(), "nothing is written for a bad LoRA file");
        String::from_utf8_lossy(&output.stderr).into_owned()
    };
    let key = "transformer.transformer_blocks.0.attn1.to_q";
    let a = |r: i64, i: i64| Tensor::zeros([r, i], (Kind::Float, Device::Cpu));
    let wide = write(
        "wide.safetensors",
        &[(&format!("{key}.lora_A.weight"), a(4, inner + 8)), (&format!("{key}.lora_B.weight"), a(inner, 4))],
    );
    let err = merge(&wide, "o1");
    assert!(
        err.contains("lora_A") && err.contains(&format!("{}", inner + 8)) && err.contains(&format!("{inner}")),
        "{err}"
    );
    let ranks = write(
        "ranks.safetensors",
        &[(&format!("{key}.lora_A.weight"), a(4, inner)), (&format!("{key}.lora_B.weight"), a(inner, 3))],
    );
    assert!(merge(&ranks, "o2").contains("ranks differ"));
    let foreign = write(
        "foreign.safetensors",
        &[("transformer.nowhere.lora_A.weight", a(4, inner)), ("transformer.nowhere.lora_B.weight", a(inner, 4))],
    );
    assert!(merge(&foreign, "o3").contains("no linear layer `nowhere`"));
    let half = write("half.safetensors", &[(&format!("{key}.lora_A.weight"), a(4, inner))]);
    assert!(merge(&half, "o4").contains("only one of lora_A and lora_B"));

    // Configs: bad fields and targets that match nothing fail before a run folder exists.
    let shards = dir.path().join("no-shards-needed");
    for (section, field) in [
        ("[lora]\nrank = 0\n", "lora.rank"),
        ("[lora]\nalpha = -1.0\n", "lora.alpha"),
        ("[lora]\ntarget_modules = [\"to_x\"]\n", "lora.target_modules"),
        ("[lora]\nrank = 100000\n", "lora.rank"),
    ] {
        let out = dir.path().join("run");
        let output = pretrain(&config(dir.path(), "bad", 2, section), &shards, &out, false);
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success() && stderr.contains(field), "{section}: {stderr}");
        assert!(!out.exists(), "{section}: nothing is written");
    }
}
