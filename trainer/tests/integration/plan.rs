//! The memory plan (`trainer plan`): parameter counts equal the built models', LoRA, ZeRO-2 and
//! checkpointing shrink what they should, the 5B presets plan to fit next to the published
//! anchors, the test-time finetuning presets fit the GPUs they are for, sampling the 5B model
//! fits a 24 GB GPU, and a plan over the free memory or a bad `--world-size` is refused with one
//! message.

use std::path::Path;
use std::process::Command;

use tch::{Device, Kind};
use trainer::models::cogvideox::cogvideox_transformer_3d::{self as transformer, CogVideoXTransformer3DModelConfig};
use trainer::models::lora::LoraConfig;
use trainer::training::PretrainConfig;
use trainer::training::plan::{MemoryPlan, PlanOptions, fits, plan};

use super::parity::repo_root;

/// Published per-GPU memory of CogVideoX-5B at 49×480×720 with gradient checkpointing (the
/// CogVideo finetune README, cogvideox-factory and finetrainers docs):
/// LoRA rank 128 about 20–24 GB on one GPU; full SFT about 42 GB per GPU under ZeRO-2 on 8.
const LORA_ANCHOR_GB: (f64, f64) = (20.0, 24.0);
const FULL_ZERO2_ANCHOR_GB: f64 = 42.0;
/// How far a 5B plan may sit from its anchor: the anchors are diffusers/DeepSpeed runs (their own
/// allocator slack, fused kernels and load paths), ours is this trainer; a quarter either way
/// still catches a unit or a factor-of-N mistake.
const ANCHOR_TOLERANCE: f64 = 0.25;
/// The single-GPU target: a 24–48 GB card.
const ONE_GPU_BYTES: u64 = 48_000_000_000;
/// An 80 GB card (the ZeRO-2 anchors' A100/H100).
const EIGHTY_GB: u64 = 80_000_000_000;

fn preset(name: &str) -> PretrainConfig {
    let path = repo_root().join("configs").join(name);
    PretrainConfig::from_toml_file(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn plan_of(config: &PretrainConfig, world_size: usize, device: Device) -> MemoryPlan {
    plan(config, &PlanOptions { world_size, device }).unwrap()
}

fn tiny() -> PretrainConfig {
    preset("pretrain_tiny.toml")
}

#[test]
fn parameter_counts_equal_the_built_models() {
    let mut config = tiny();
    let c = CogVideoXTransformer3DModelConfig::tiny();
    let (vs, _) = transformer::build(&c, Device::Cpu, Kind::Float).unwrap();
    let count = |vs: &tch::nn::VarStore| vs.variables().values().map(|t| t.numel() as u64).sum::<u64>();
    let full = plan_of(&config, 1, Device::Cpu);
    assert_eq!(full.transformer_parameters, count(&vs));
    assert_eq!(full.trainable_parameters, count(&vs));
    let lora = LoraConfig { rank: 4, ..LoraConfig::default() };
    let (_, lora_vs, _) = transformer::build_with_lora(&c, &lora, Device::Cpu, Kind::Float).unwrap();
    config.lora = Some(lora);
    let adapted = plan_of(&config, 1, Device::Cpu);
    assert_eq!(adapted.trainable_parameters, count(&lora_vs));
    let (vae_vs, _) = trainer::models::cogvideox::autoencoder_kl_cogvideox::build(
        &config.model.configs(false).unwrap().1,
        Device::Cpu,
        Kind::Float,
    )
    .unwrap();
    assert_eq!(adapted.vae_parameters, count(&vae_vs));
}

#[test]
fn a_multiview_share_leaves_the_plan_as_it_is() {
    // Both pair kinds decode to the same target, conditioning and mask tensors.
    let monocular = plan_of(&tiny(), 2, Device::Cpu);
    for share in [0.0, 0.5, 1.0] {
        let mut config = tiny();
        config.data.multiview_share = Some(share);
        assert_eq!(plan_of(&config, 2, Device::Cpu), monocular, "share {share}");
    }
}

#[test]
fn lora_zero2_and_checkpointing_shrink_what_they_should() {
    let full = preset("finetune_5b_full.toml");
    let one = plan_of(&full, 1, Device::Cuda(0));
    let eight = plan_of(&full, 8, Device::Cuda(0));
    let row = |p: &MemoryPlan, what: &str| p.persistent.iter().find(|r| r.what == what).unwrap().bytes;
    // ZeRO-2: moments and master weights 1/8 per rank; working weights full on every rank.
    assert_eq!(row(&one, "optimizer state").div_ceil(8), row(&eight, "optimizer state"));
    assert_eq!(row(&one, "master weights").div_ceil(8), row(&eight, "master weights"));
    assert_eq!(row(&one, "transformer weights"), row(&eight, "transformer weights"));
    // bf16: two bytes per working weight; AdamW: two fp32 moments per trainable parameter.
    assert_eq!(row(&one, "transformer weights"), 2 * one.transformer_parameters);
    assert_eq!(row(&one, "optimizer state"), 8 * one.trainable_parameters);
    // Checkpointing keeps one block's graph instead of 42.
    let a = &eight.activations;
    assert!(a.checkpointing && a.with_checkpointing * 5 < a.without_checkpointing, "{a:?}");
    let lora = plan_of(&preset("finetune_5b_lora_1gpu.toml"), 1, Device::Cuda(0));
    assert!(lora.trainable_parameters * 20 < lora.transformer_parameters);
    assert!(lora.activations.block_units < a.block_units);
}

#[test]
fn five_b_presets_fit_next_to_the_published_anchors() {
    let gb = |bytes: u64| bytes as f64 / 1e9;
    let lora = plan_of(&preset("finetune_5b_lora_1gpu.toml"), 1, Device::Cuda(0));
    assert!(lora.total <= ONE_GPU_BYTES, "LoRA on one GPU plans {:.1} GB:\n{lora}", gb(lora.total));
    let (low, high) = LORA_ANCHOR_GB;
    let lora_gb = gb(lora.total);
    assert!(
        lora_gb >= low * (1.0 - ANCHOR_TOLERANCE) && lora_gb <= high * (1.0 + ANCHOR_TOLERANCE),
        "LoRA plan {lora_gb:.1} GB vs the published {low}-{high} GB:\n{lora}"
    );
    for name in ["finetune_5b_full.toml", "pretrain_cognvs_5b.toml"] {
        let full = plan_of(&preset(name), 8, Device::Cuda(0));
        let full_gb = gb(full.total);
        assert!(full.total <= EIGHTY_GB, "{name} plans {full_gb:.1} GB per rank:\n{full}");
        assert!(
            (full_gb - FULL_ZERO2_ANCHOR_GB).abs() <= FULL_ZERO2_ANCHOR_GB * ANCHOR_TOLERANCE,
            "{name}: {full_gb:.1} GB per rank vs the published {FULL_ZERO2_ANCHOR_GB} GB:\n{full}"
        );
    }
}

#[test]
fn a_plan_over_the_free_memory_is_refused_with_one_message() {
    let config = preset("finetune_5b_full.toml");
    let one = plan_of(&config, 1, Device::Cuda(0));
    let free = 40_000_000_000;
    let err = fits(&one, free, EIGHTY_GB, "configs/finetune_5b_full.toml").unwrap_err().to_string();
    assert!(err.starts_with("configs/finetune_5b_full.toml: field `(memory plan)`"), "{err}");
    assert!(err.contains("nothing was written") && err.contains("[lora]"), "{err}");
    assert!(fits(&one, one.total * 2, EIGHTY_GB, "x").is_ok());
}

#[test]
fn plan_cli_prints_the_rows_and_rejects_bad_arguments() {
    let bin = env!("CARGO_BIN_EXE_trainer");
    let preset = repo_root().join("configs/finetune_5b_lora_1gpu.toml");
    let out = Command::new(bin).args(["plan", "--config"]).arg(&preset).args(["--world-size", "1"]).output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    for row in [
        "transformer weights",
        "gradients",
        "master weights",
        "optimizer state",
        "activations, per block",
        "activations without checkpointing",
        "activations with checkpointing",
        "VAE encode peak",
        "VAE decode peak",
        "total (predicted peak)",
    ] {
        assert!(text.contains(row), "no `{row}` row in\n{text}");
    }
    for (args, needle) in [(vec!["--world-size", "0"], "world-size"), (vec!["--device", "tpu"], "tpu")] {
        let out = Command::new(bin).args(["plan", "--config"]).arg(&preset).args(&args).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && err.contains(needle), "{args:?}: {err}");
    }
    let missing = Path::new("/nonexistent/plan.toml");
    let out = Command::new(bin).args(["plan", "--config"]).arg(missing).output().unwrap();
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("/nonexistent/plan.toml"));
}

#[test]
fn test_time_finetuning_presets_fit_where_they_are_meant_to_run() {
    /// An H200's 141 GB.
    const H200: u64 = 141_000_000_000;
    for (name, world, capacity) in [
        ("finetune_5b_lora_1gpu.toml", 1, ONE_GPU_BYTES),
        ("finetune_5b_full_1gpu.toml", 1, H200),
        ("finetune_5b_full.toml", 8, ONE_GPU_BYTES),
    ] {
        let config = preset(name);
        // The paper's test-time finetuning: 200 steps, lr 2e-5, AdamW β = (0.9, 0.95).
        let o = &config.optim;
        assert_eq!((config.train.steps, o.lr, o.beta1, o.beta2), (200, 2e-5, 0.9, 0.95), "{name}");
        let plan = plan_of(&config, world, Device::Cuda(0));
        assert!(plan.total <= capacity, "{name} on {world} rank(s) plans {} B > {capacity}:\n{plan}", plan.total);
    }
}

#[test]
fn sampling_the_5b_model_in_bf16_fits_a_24_gb_gpu_with_tiles() {
    let config = preset("finetune_5b_lora_1gpu.toml");
    let (transformer, vae) = config.model.configs(false).unwrap();
    let tiles = trainer::models::cogvideox::autoencoder_kl_cogvideox::TilingConfig::for_config(&vae);
    assert!(tiles.lands_on_latent_pixels(vae.spatial_compression_ratio()));
    let plan = |tiling, guided| {
        trainer::training::plan::sampling_plan(
            &transformer,
            &vae,
            (49, 480, 720),
            Kind::BFloat16,
            Device::Cuda(0),
            tiling,
            guided,
        )
        .unwrap()
    };
    let (tiled, whole, guided) = (plan(Some(&tiles), false), plan(None, false), plan(Some(&tiles), true));
    assert!(tiled.total < 24_000_000_000, "{tiled}");
    assert!(tiled.vae_decode_peak < whole.vae_decode_peak, "tiles lower the decode peak");
    assert_eq!(guided.denoise_peak, 2 * tiled.denoise_peak, "guidance is a batch of two");
    assert_eq!(tiled.persistent[0].bytes, 2 * count_of(&transformer), "bf16 weights");
}

fn count_of(config: &CogVideoXTransformer3DModelConfig) -> u64 {
    trainer::models::cogvideox::cogvideox_transformer_3d::variable_shapes(config)
        .unwrap()
        .values()
        .map(|s| s.iter().map(|&d| d as u64).product::<u64>())
        .sum()
}

/// The Wan test-time finetuning presets: file, its model folder under `configs/wan/` (the
/// released diffusers configs' shapes) and the memory of the GPU it is for.
const WAN_PRESETS: [(&str, &str, u64); 3] = [
    ("finetune_wan21_1.3b_lora_24gb.toml", "Wan2.1-T2V-1.3B", 24_000_000_000),
    ("finetune_wan21_i2v_14b_lora_80gb.toml", "Wan2.1-I2V-14B-480P", EIGHTY_GB),
    ("finetune_wan22_ti2v_5b_lora_1gpu.toml", "Wan2.2-TI2V-5B", ONE_GPU_BYTES),
];

#[test]
fn wan_presets_are_the_released_shapes_and_fit_their_gpus_as_the_readme_states() {
    use trainer::diffusers_config::DiffusersConfig;
    use trainer::models::wan::autoencoder_kl_wan::AutoencoderKLWanConfig;
    use trainer::models::wan::transformer_wan::WanTransformer3DModelConfig;
    let readme = std::fs::read_to_string(repo_root().join("README.md")).unwrap();
    for (name, folder, capacity) in WAN_PRESETS {
        let config = preset(name);
        let (mut transformer, mut vae) = config.model.wan_configs().unwrap().expect("a Wan preset");
        let dir = repo_root().join("configs/wan").join(folder);
        let mut released = WanTransformer3DModelConfig::from_json_file(dir.join("transformer")).unwrap();
        let mut released_vae = AutoencoderKLWanConfig::from_json_file(dir.join("vae")).unwrap();
        for extra in [&mut transformer.extra, &mut released.extra, &mut vae.extra, &mut released_vae.extra] {
            extra.clear();
        }
        // A text-to-video (or TI2V) release is trained widened for the CogNVS condition channels;
        // everything else is the release's.
        let condition = vae.z_dim + trainer::models::wan::transformer_wan::COGNVS_MASK_CHANNELS;
        if released.in_channels != transformer.in_channels {
            assert_eq!(transformer.in_channels, released.output_channels() + condition, "{name}");
            released = released.for_cognvs();
        }
        assert_eq!(transformer, released, "{name}: the preset's transformer is {folder}'s");
        assert_eq!(vae, released_vae, "{name}: the preset's VAE is {folder}'s");

        let plan = plan_of(&config, 1, Device::Cuda(0));
        assert!(plan.total <= capacity, "{name} plans {} B > {capacity}:\n{plan}", plan.total);
        assert!(plan.trainable_parameters * 20 < plan.transformer_parameters, "{name}: LoRA trains adapters only");
        assert!(plan.activations.checkpointing, "{name}");
        // The README's table states each preset's predicted peak as `trainer plan` prints it.
        let row = readme.lines().find(|l| l.contains(&format!("`configs/{name}`"))).unwrap_or_else(|| {
            panic!("README.md has no row for configs/{name}");
        });
        let peak = trainer::training::plan::human_bytes(plan.total);
        assert!(row.contains(&peak), "README row for {name} must state {peak}:\n{row}\n{plan}");
    }
}

/// A tiny Wan training config: `transformer` and `vae` presets and `lora` appended to the tiny
/// CogVideoX preset's settings.
fn tiny_wan(dir: &Path, transformer: &str, lora: &str) -> PretrainConfig {
    let text = std::fs::read_to_string(repo_root().join("configs/pretrain_tiny.toml"))
        .unwrap()
        .replace("transformer = \"tiny\"", &format!("transformer = \"{transformer}\""));
    // Validation samples CogVideoX models only so far: a Wan run validates nothing.
    let validate =
        text.lines().find(|l| l.starts_with("validate_every")).expect("pretrain_tiny.toml sets validate_every");
    let text = text.replace(validate, "validate_every = 0");
    let path = dir.join(format!("{transformer}.toml"));
    std::fs::write(&path, format!("{text}\n{lora}\n")).unwrap();
    PretrainConfig::from_toml_file(&path).unwrap()
}

#[test]
fn wan_parameter_counts_equal_the_built_models_and_lora_shrinks_what_it_should() {
    use trainer::models::wan::autoencoder_kl_wan::{self as wan_vae, AutoencoderKLWanConfig};
    use trainer::models::wan::transformer_wan::{self as wan, WanTransformer3DModelConfig};
    let dir = tempfile::tempdir().unwrap();
    let count = |vs: &tch::nn::VarStore| vs.variables().values().map(|t| t.numel() as u64).sum::<u64>();
    let c = WanTransformer3DModelConfig::tiny_i2v();
    let full = plan_of(&tiny_wan(dir.path(), "tiny-i2v", ""), 1, Device::Cpu);
    let (vs, _) = wan::build(&c, Device::Cpu, Kind::Float).unwrap();
    assert_eq!(full.transformer_parameters, count(&vs));
    assert_eq!(full.trainable_parameters, count(&vs));
    let (vae_vs, _) = wan_vae::build(&AutoencoderKLWanConfig::tiny(), Device::Cpu, Kind::Float).unwrap();
    assert_eq!(full.vae_parameters, count(&vae_vs));

    let section = "[lora]\nrank = 4\ntarget_modules = [\"to_q\", \"to_k\", \"to_v\", \"to_out.0\", \"add_k_proj\", \"add_v_proj\"]";
    let config = tiny_wan(dir.path(), "tiny-i2v", section);
    let adapted = plan_of(&config, 1, Device::Cpu);
    let (_, lora_vs, _) = wan::build_with_lora(&c, config.lora.as_ref().unwrap(), Device::Cpu, Kind::Float).unwrap();
    assert_eq!(adapted.trainable_parameters, count(&lora_vs));
    assert_eq!(adapted.transformer_parameters, full.transformer_parameters);
    // Frozen modulation, norms and feed-forward: fewer saved tensors per block, a frozen head.
    assert!(adapted.activations.per_block_bytes < full.activations.per_block_bytes);
    assert!(adapted.activations.without_checkpointing < full.activations.without_checkpointing);
    // Text and image tokens enter through cross-attention: the unit is the video tokens alone.
    assert_eq!(adapted.shape.unit_tokens, adapted.shape.video_tokens);

    // A target the Wan blocks do not have is refused naming the field.
    let path = dir.path().join("bad.toml");
    let text = std::fs::read_to_string(dir.path().join("tiny-i2v.toml")).unwrap().replace("add_v_proj", "to_x");
    std::fs::write(&path, text).unwrap();
    let err = PretrainConfig::from_toml_file(&path).unwrap_err().to_string();
    assert!(err.contains("lora.target_modules") && err.contains("to_x"), "{err}");
}

#[test]
fn plan_cli_plans_a_wan_preset_with_its_image_tokens() {
    let preset = repo_root().join("configs/finetune_wan21_i2v_14b_lora_80gb.toml");
    let out = Command::new(env!("CARGO_BIN_EXE_trainer"))
        .args(["plan", "--config"])
        .arg(&preset)
        .args(["--world-size", "1", "--device", "cuda"])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    for row in [
        "image embedding (frozen)",
        "512 text tokens of width 5120, 40 blocks",
        "activations with checkpointing",
        "total",
    ] {
        assert!(text.contains(row), "no `{row}` in\n{text}");
    }
}
