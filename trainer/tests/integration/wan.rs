//! Wan parity with diffusers: `WanTransformer3DModel` (T2V, Wan2.2 per-token timesteps, I2V image
//! cross-attention, FLF2V's image positional table) on tiny random models, diffusers' own model
//! folders loaded and ours written back in the same layout, the exact names and shapes of the
//! released Wan checkpoints, and the flow-matching schedulers Wan samples with
//! (`UniPCMultistepScheduler`, `FlowMatchEulerDiscreteScheduler`) step for step, and
//! `AutoencoderKLWan` (Wan2.1's, Wan2.2's residual patchified one) encoding and decoding; whole
//! sampling runs equal to `WanPipeline` and `WanImageToVideoPipeline` for a seed, the CogNVS
//! render + mask conditioning reducing to them (I2V checkpoint; T2V widened with zeros), and the
//! jobs that do not run Wan yet refusing it by family (training: `wan_training.rs`).
//!
//! Reference values come from `scripts/goldens_wan.py` (diffusers with a fixed seed), run into a
//! temporary folder once per test binary.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::OnceLock;

use trainer::diffusers_config::DiffusersConfig;
use trainer::models::wan::autoencoder_kl_wan::{self as vae, AutoencoderKLWanConfig};
use trainer::models::wan::transformer_wan::{
    self as transformer, WanTransformer3DModel, WanTransformer3DModelConfig, WanTransformerInput,
};
use trainer::models::weights;
use trainer::schedulers::scheduling_flow_match_euler_discrete::{
    FlowMatchEulerDiscreteScheduler, FlowMatchEulerDiscreteSchedulerConfig,
};
use trainer::schedulers::scheduling_unipc_multistep::{UniPCMultistepScheduler, UniPCMultistepSchedulerConfig};
use trainer::tch::{self, Device, Kind, Tensor, nn};

use super::parity::{assert_close, assert_success, read_tensors, run_script};

/// Output of `scripts/goldens_wan.py`, generated once per test binary.
pub(super) fn goldens() -> &'static Path {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    DIR.get_or_init(|| run_script("goldens_wan.py")).path()
}

/// The inputs and diffusers' outputs (tensors are not `Sync`: each test reads its own copy).
fn transformer_io() -> BTreeMap<String, Tensor> {
    read_tensors(&goldens().join("transformer_io.safetensors"))
}

/// A model built from a golden folder's config.json with its weights loaded (names and shapes
/// checked both ways by `transformer::load`).
fn load_model(dir: &Path) -> (nn::VarStore, WanTransformer3DModel) {
    let config = WanTransformer3DModelConfig::from_json_file(dir).unwrap();
    let (vs, model) = transformer::build(&config, Device::Cpu, Kind::Float).unwrap();
    transformer::load(&vs, dir).unwrap();
    (vs, model)
}

fn forward(model: &WanTransformer3DModel, io: &BTreeMap<String, Tensor>, case: &str) -> Tensor {
    let image = io.get(&format!("{case}.encoder_hidden_states_image"));
    let input = WanTransformerInput {
        hidden_states: &io[&format!("{case}.hidden_states")],
        timestep: &io[&format!("{case}.timestep")],
        encoder_hidden_states: &io[&format!("{case}.encoder_hidden_states")],
        encoder_hidden_states_image: image,
    };
    tch::no_grad(|| model.forward(&input)).unwrap()
}

#[test]
fn tiny_presets_equal_the_golden_configs() {
    for (folder, preset) in [
        ("transformer_t2v", WanTransformer3DModelConfig::tiny_t2v()),
        ("transformer_i2v", WanTransformer3DModelConfig::tiny_i2v()),
    ] {
        let config = WanTransformer3DModelConfig::from_json_file(goldens().join(folder)).unwrap();
        assert_eq!(
            WanTransformer3DModelConfig { extra: Default::default(), ..config },
            preset,
            "{folder}: the script's config and the Rust preset must agree"
        );
    }
}

/// Relative tolerance of an fp32 forward against diffusers' fp32 output (the same ops; room for
/// another reduction order).
const FORWARD_TOL: f64 = 1e-4;

/// Runs each `(case, label)` of `transformer_io.safetensors` through the model of golden folder
/// `folder` and compares it with diffusers' output of that case.
fn assert_forwards_match(folder: &str, cases: &[(&str, &str)]) {
    let (_vs, model) = load_model(&goldens().join(folder));
    let io = transformer_io();
    for (case, label) in cases {
        assert_close(label, &forward(&model, &io, case), &io[&format!("{case}.sample")], FORWARD_TOL);
    }
}

#[test]
fn text_to_video_forward_matches_diffusers() {
    assert_forwards_match(
        "transformer_t2v",
        &[
            ("t2v", "wan transformer t2v (batch 2, 3x6x8 latents)"),
            // Wan2.2 TI2V: one timestep per token, the first frame's tokens at 0.
            ("ti2v", "wan transformer per-token timesteps"),
        ],
    );
    assert_forwards_match(
        "transformer_variant",
        &[("variant", "wan transformer without cross-attention norm, 2x2x2 patches")],
    );
}

#[test]
fn image_to_video_forward_matches_diffusers() {
    assert_forwards_match("transformer_i2v", &[("i2v", "wan transformer i2v (image cross-attention)")]);
    assert_forwards_match("transformer_flf2v", &[("flf2v", "wan transformer flf2v (image positional table)")]);
}

/// In bf16 the fp32-kept modules stay fp32 as in diffusers' `from_pretrained(torch_dtype=bf16)`,
/// and the result tracks diffusers' bf16 and fp32 outputs.
#[test]
fn bf16_forward_tracks_diffusers_bf16() {
    let io = transformer_io();
    let dir = goldens().join("transformer_i2v");
    let config = WanTransformer3DModelConfig::from_json_file(&dir).unwrap();
    let (vs, model) = transformer::build(&config, Device::Cpu, Kind::BFloat16).unwrap();
    transformer::load(&vs, &dir).unwrap();
    let variables = vs.variables();
    assert_eq!(variables["blocks.0.scale_shift_table"].kind(), Kind::Float);
    assert_eq!(variables["condition_embedder.time_embedder.linear_1.weight"].kind(), Kind::Float);
    assert_eq!(variables["condition_embedder.image_embedder.norm1.weight"].kind(), Kind::Float);
    assert_eq!(variables["blocks.0.attn1.to_q.weight"].kind(), Kind::BFloat16);
    let bf16 = |name: &str| io[&format!("i2v.{name}")].to_kind(Kind::BFloat16);
    let (x, text, image) = (bf16("hidden_states"), bf16("encoder_hidden_states"), bf16("encoder_hidden_states_image"));
    let input = WanTransformerInput {
        hidden_states: &x,
        timestep: &io["i2v.timestep"],
        encoder_hidden_states: &text,
        encoder_hidden_states_image: Some(&image),
    };
    let out = tch::no_grad(|| model.forward(&input)).unwrap();
    assert_eq!(out.kind(), Kind::BFloat16);
    // The same ops in the same dtypes (bit-exact on the CPU); the tolerance leaves room for another
    // reduction order.
    assert_close("wan transformer bf16 vs diffusers bf16", &out, &io["i2v_bf16.sample"], 1e-2);
    assert_close("wan transformer bf16 vs diffusers fp32", &out, &io["i2v.sample"], 5e-2);
}

/// Our save of a loaded model is diffusers' folder again: the same config.json values and
/// tensor names and shapes, and the model read back computes the same output bit for bit.
#[test]
fn saved_folders_equal_diffusers_layout() {
    let dir = goldens().join("transformer_i2v");
    let (vs, model) = load_model(&dir);
    let out = tempfile::tempdir().unwrap();
    weights::save(&vs, model.config(), transformer::CLASS_NAME, out.path(), weights::DEFAULT_MAX_SHARD_BYTES).unwrap();
    let read = |path: &Path| -> serde_json::Map<String, serde_json::Value> {
        let mut json: serde_json::Map<String, serde_json::Value> =
            serde_json::from_str(&std::fs::read_to_string(path.join("config.json")).unwrap()).unwrap();
        json.remove("_diffusers_version");
        json
    };
    assert_eq!(read(out.path()), read(&dir), "config.json");
    let shapes = |path: &Path| -> BTreeMap<String, Vec<i64>> {
        weights::read_checkpoint_info(path).unwrap().into_iter().map(|(k, v)| (k, v.shape)).collect()
    };
    assert_eq!(shapes(out.path()), shapes(&dir), "tensor names and shapes");
    let (_vs, reloaded) = load_model(out.path());
    let io = transformer_io();
    assert!(forward(&reloaded, &io, "i2v").equal(&forward(&model, &io, "i2v")));
}

/// A checkpoint with the `norm_added_q` weights early I2V conversions wrote loads (diffusers skips
/// them too) and computes the same; any other extra tensor is still refused, named.
#[test]
fn stale_norm_added_q_weights_are_skipped_and_nothing_else() {
    let golden = goldens().join("transformer_i2v");
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(golden.join("config.json"), dir.path().join("config.json")).unwrap();
    let mut tensors = read_tensors(&golden.join("diffusion_pytorch_model.safetensors"));
    tensors.insert("blocks.0.attn2.norm_added_q.weight".to_string(), Tensor::ones([32], (Kind::Float, Device::Cpu)));
    let file = dir.path().join("diffusion_pytorch_model.safetensors");
    let write = |tensors: &BTreeMap<String, Tensor>| {
        let named: Vec<(&str, &Tensor)> = tensors.iter().map(|(k, v)| (k.as_str(), v)).collect();
        Tensor::write_safetensors(&named, &file).unwrap();
    };
    write(&tensors);
    let io = transformer_io();
    let (_vs, model) = load_model(dir.path());
    assert_close("wan i2v with norm_added_q in the checkpoint", &forward(&model, &io, "i2v"), &io["i2v.sample"], 0.0);

    tensors.insert("blocks.0.attn2.mystery.weight".to_string(), Tensor::ones([32], (Kind::Float, Device::Cpu)));
    write(&tensors);
    let (vs, _model) = transformer::build(model.config(), Device::Cpu, Kind::Float).unwrap();
    let err = transformer::load(&vs, dir.path()).unwrap_err().to_string();
    assert!(err.contains("blocks.0.attn2.mystery.weight") && err.contains("unexpected"), "{err}");
}

/// The module tree of each released model has exactly the checkpoint's names and shapes (diffusers
/// built on the meta device by the golden script).
#[test]
fn presets_have_the_released_checkpoints_names_and_shapes() {
    let text = std::fs::read_to_string(goldens().join("transformer_shapes.json")).unwrap();
    let all: BTreeMap<String, BTreeMap<String, Vec<i64>>> = serde_json::from_str(&text).unwrap();
    assert_eq!(all.len(), 3);
    for (preset, expected) in all {
        let config = WanTransformer3DModelConfig::preset(&preset).unwrap();
        assert_eq!(transformer::variable_shapes(&config).unwrap(), expected, "{preset}");
    }
}

/// A scheduler case of the golden script, stepped the way it is in diffusers.
enum Sampler {
    UniPC(Box<UniPCMultistepScheduler>),
    Euler(FlowMatchEulerDiscreteScheduler),
}

impl Sampler {
    fn timesteps(&self) -> Tensor {
        match self {
            Sampler::UniPC(s) => Tensor::from_slice(s.timesteps()),
            Sampler::Euler(s) => Tensor::from_slice(s.timesteps()),
        }
    }

    fn sigmas(&self) -> Tensor {
        match self {
            Sampler::UniPC(s) => Tensor::from_slice(s.sigmas()),
            Sampler::Euler(s) => Tensor::from_slice(s.sigmas()),
        }
    }

    fn noisy(&self, x0: &Tensor, noise: &Tensor, timesteps: &Tensor) -> Tensor {
        match self {
            Sampler::UniPC(s) => s.add_noise(x0, noise, timesteps).unwrap(),
            Sampler::Euler(s) => s.scale_noise(x0, timesteps, noise).unwrap(),
        }
    }

    fn step(&mut self, i: usize, output: &Tensor, sample: &Tensor, noise: Option<&Tensor>) -> Tensor {
        match self {
            Sampler::UniPC(s) => {
                let t = s.timesteps()[i];
                s.step(output, t, sample).unwrap()
            }
            Sampler::Euler(s) => {
                let t = s.timesteps()[i];
                s.step(output, t, sample, noise).unwrap()
            }
        }
    }
}

/// The `wan_480p` preset is the script's copy of the released scheduler config, as diffusers
/// writes it back.
#[test]
fn unipc_wan_preset_equals_the_golden_config() {
    let config = UniPCMultistepSchedulerConfig::from_json_file(goldens().join("scheduler_unipc_wan")).unwrap();
    assert_eq!(
        UniPCMultistepSchedulerConfig { extra: Default::default(), ..config },
        UniPCMultistepSchedulerConfig::wan_480p()
    );
}

/// Every scheduler case: its schedule, the forward process and a whole sampling loop on random
/// "model outputs" equal diffusers' step for step (fp32; the solver's coefficients are fp32 in
/// both, the order conditions solved in fp64 here and in fp32 LAPACK there).
#[test]
fn flow_schedulers_match_diffusers_step_for_step() {
    let io = read_tensors(&goldens().join("scheduler_io.safetensors"));
    let cases = [
        "unipc_wan",
        "unipc_order3",
        "unipc_epsilon",
        "euler_shift",
        "euler_dynamic",
        "euler_inverted",
        "euler_stochastic",
    ];
    for case in cases {
        let dir = goldens().join(format!("scheduler_{case}"));
        let steps = io[&format!("{case}.steps")].int64_value(&[0]) as usize;
        let mu = io.get(&format!("{case}.mu")).map(|t| t.double_value(&[0]));
        let mut sampler = if case.starts_with("unipc") {
            let config = UniPCMultistepSchedulerConfig::from_json_file(&dir).unwrap();
            let mut s = UniPCMultistepScheduler::new(&config).unwrap();
            s.set_timesteps(steps, mu).unwrap();
            Sampler::UniPC(Box::new(s))
        } else {
            let config = FlowMatchEulerDiscreteSchedulerConfig::from_json_file(&dir).unwrap();
            let mut s = FlowMatchEulerDiscreteScheduler::new(&config).unwrap();
            s.set_timesteps(steps, mu).unwrap();
            Sampler::Euler(s)
        };
        let expected_timesteps = &io[&format!("{case}.timesteps")];
        if expected_timesteps.kind() == Kind::Int64 {
            assert!(sampler.timesteps().equal(expected_timesteps), "{case}: timesteps {:?}", sampler.timesteps());
        } else {
            assert_close(&format!("{case} timesteps"), &sampler.timesteps(), expected_timesteps, 1e-6);
        }
        assert_close(&format!("{case} sigmas"), &sampler.sigmas(), &io[&format!("{case}.sigmas")], 1e-6);
        let noisy = sampler.noisy(
            &io[&format!("{case}.original_samples")],
            &io[&format!("{case}.noise")],
            &io[&format!("{case}.noise_timesteps")],
        );
        assert_close(&format!("{case} forward process"), &noisy, &io[&format!("{case}.noisy_samples")], 1e-6);

        let mut sample = io[&format!("{case}.initial_sample")].shallow_clone();
        for i in 0..steps {
            let output = &io[&format!("{case}.{i}.model_output")];
            let noise = io.get(&format!("{case}.{i}.step_noise"));
            sample = sampler.step(i, output, &sample, noise);
            let expected = &io[&format!("{case}.{i}.prev_sample")];
            assert_close(&format!("{case} step {i}"), &sample, expected, 1e-5);
        }
    }
}

#[test]
fn vae_tiny_presets_equal_the_golden_configs() {
    for (folder, preset) in
        [("vae_wan21", AutoencoderKLWanConfig::tiny()), ("vae_wan22", AutoencoderKLWanConfig::tiny_residual())]
    {
        let config = AutoencoderKLWanConfig::from_json_file(goldens().join(folder)).unwrap();
        assert_eq!(AutoencoderKLWanConfig { extra: Default::default(), ..config }, preset, "{folder}");
    }
}

/// Encode (posterior mean and log-variance, 9 frames in chunks of 1 + 4 + 4 with the causal
/// caches carried), decode (3 latent frames one at a time) and the pipelines' latent
/// normalisation equal diffusers' for Wan2.1's VAE (also with a spatial-only first level) and
/// Wan2.2's residual, patchified one.
#[test]
fn vae_encode_and_decode_match_diffusers() {
    let io = read_tensors(&goldens().join("vae_io.safetensors"));
    for name in ["wan21", "wan22", "wan21_2d"] {
        let dir = goldens().join(format!("vae_{name}"));
        let config = AutoencoderKLWanConfig::from_json_file(&dir).unwrap();
        let (vs, model) = vae::build(&config, Device::Cpu, Kind::Float).unwrap();
        weights::load(&vs, &dir).unwrap();
        let posterior = tch::no_grad(|| model.encode_posterior(&io[&format!("{name}.encode.sample")])).unwrap();
        assert_close(&format!("vae {name} encode mean"), &posterior.mean, &io[&format!("{name}.encode.mean")], 1e-5);
        assert_close(
            &format!("vae {name} encode logvar"),
            &posterior.logvar,
            &io[&format!("{name}.encode.logvar")],
            1e-5,
        );
        let sample = tch::no_grad(|| model.decode(&io[&format!("{name}.decode.latent")])).unwrap();
        assert_close(&format!("vae {name} decode"), &sample, &io[&format!("{name}.decode.sample")], 1e-5);
        let normalized = model.normalize_latents(&posterior.mean).unwrap();
        assert_close(&format!("vae {name} normalize"), &normalized, &io[&format!("{name}.normalized")], 1e-6);
        let denormalized = model.denormalize_latents(&io[&format!("{name}.decode.latent")]).unwrap();
        assert_close(&format!("vae {name} denormalize"), &denormalized, &io[&format!("{name}.denormalized")], 1e-6);
    }
}

/// The module trees of the released VAEs have exactly their checkpoints' names and shapes.
#[test]
fn vae_presets_have_the_released_checkpoints_names_and_shapes() {
    let text = std::fs::read_to_string(goldens().join("vae_shapes.json")).unwrap();
    let all: BTreeMap<String, BTreeMap<String, Vec<i64>>> = serde_json::from_str(&text).unwrap();
    let wan22 = AutoencoderKLWanConfig {
        base_dim: 160,
        decoder_base_dim: Some(256),
        z_dim: 48,
        is_residual: true,
        in_channels: 12,
        out_channels: 12,
        patch_size: Some(2),
        scale_factor_spatial: Some(16),
        latents_mean: vec![0.0; 48],
        latents_std: vec![1.0; 48],
        ..AutoencoderKLWanConfig::wan21()
    };
    assert_eq!(vae::variable_shapes(&AutoencoderKLWanConfig::wan21()).unwrap(), all["wan2.1"], "wan2.1");
    assert_eq!(vae::variable_shapes(&wan22).unwrap(), all["wan2.2"], "wan2.2");
}

/// `trainer forward` with `args`, its output checked for success.
fn trainer_forward(args: &[&std::ffi::OsStr]) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_trainer")).arg("forward").args(args).output().expect("run trainer")
}

/// `trainer forward` picks the Wan family from the config's `_class_name` and reads inputs under
/// diffusers' argument names (the I2V transformer with its image tokens; Wan2.2's VAE encoder);
/// a class it does not run is refused, naming the field.
#[test]
fn trainer_forward_runs_wan_configs() {
    let io = transformer_io();
    let dir = tempfile::tempdir().unwrap();
    let inputs = dir.path().join("in.safetensors");
    let names = ["hidden_states", "timestep", "encoder_hidden_states", "encoder_hidden_states_image"];
    let named: Vec<(&str, &Tensor)> = names.iter().map(|n| (*n, &io[&format!("i2v.{n}")])).collect();
    Tensor::write_safetensors(&named, &inputs).unwrap();
    let out = dir.path().join("out.safetensors");
    let model = goldens().join("transformer_i2v");
    let run = |module: &str, model: &Path, inputs: &Path| {
        trainer_forward(&[
            "--module".as_ref(),
            module.as_ref(),
            "--config".as_ref(),
            model.as_os_str(),
            "--weights".as_ref(),
            model.as_os_str(),
            "--inputs".as_ref(),
            inputs.as_os_str(),
            "--out".as_ref(),
            out.as_os_str(),
        ])
    };
    assert_success(&run("transformer", &model, &inputs));
    assert_close("trainer forward wan i2v", &read_tensors(&out)["sample"], &io["i2v.sample"], FORWARD_TOL);

    let vae_io = read_tensors(&goldens().join("vae_io.safetensors"));
    let vae_inputs = dir.path().join("vae_in.safetensors");
    Tensor::write_safetensors(&[("sample", &vae_io["wan22.encode.sample"])], &vae_inputs).unwrap();
    assert_success(&run("vae_encoder", &goldens().join("vae_wan22"), &vae_inputs));
    assert_close(
        "trainer forward wan2.2 vae encoder",
        &read_tensors(&out)["latent"],
        &vae_io["wan22.encode.mean"],
        1e-5,
    );

    let output = run("vae_encoder", &model, &vae_inputs);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        !output.status.success() && stderr.contains("_class_name") && stderr.contains("AutoencoderKLWan"),
        "{stderr}"
    );
}

/// Sampling picks the family from the folders' `_class_name`: the CogVideoX pipeline's reader
/// refuses a Wan model by name before anything is parsed as CogVideoX's, and sampling and
/// training refuse a mix of families.
#[test]
fn sampling_and_training_pick_wan_folders_by_family() {
    let root = tempfile::tempdir().unwrap();
    let folder = |name: &str, class: &str| {
        let dir = root.path().join(name);
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("config.json"), format!(r#"{{"_class_name": "{class}"}}"#)).unwrap();
        dir
    };
    let wan_transformer = folder("transformer", transformer::CLASS_NAME);
    let wan_vae = folder("vae", vae::CLASS_NAME);
    let paths = trainer::loaders::ModelPaths {
        transformer: wan_transformer.clone(),
        adapters: Vec::new(),
        vae: wan_vae.clone(),
        scheduler: None,
        text_embedding: None,
        negative_text_embedding: None,
        zero_text_embedding: false,
    };
    let e = trainer::pipelines::sampling::CheckedModels::read(&paths, Device::Cpu).unwrap_err().to_string();
    assert!(e.contains("is a Wan model; the CogVideoX pipeline reads CogVideoX"), "{e}");
    assert!(e.contains(&wan_transformer.display().to_string()), "{e}");
    let cog_vae = folder("cog_vae", "AutoencoderKLCogVideoX");
    let mixed = trainer::loaders::ModelPaths { vae: cog_vae, ..paths.clone() };
    let e = trainer::pipelines::sampling::Checked::read(&mixed, Device::Cpu).unwrap_err().to_string();
    assert!(e.contains("is a CogVideoX VAE; the transformer") && e.contains("is a Wan model"), "{e}");
    let model = trainer::training::ModelConfig {
        transformer: "tiny".to_string(),
        vae: wan_vae.display().to_string(),
        text_embedding: None,
        zero_text_embedding: false,
        scheduler: None,
        transformer_lora: None,
    };
    // Training runs Wan, but one family at a time: a CogVideoX transformer with a Wan VAE is refused.
    let e = model.model_configs(false).unwrap_err().to_string();
    assert!(e.contains("is a Wan VAE but the transformer tiny is a CogVideoX model") && e.contains("vae"), "{e}");
}

/// `WanPipeline`'s videos for a seed (`output_type="np"`, [0, 1]) from ours, within one grey
/// level: classifier-free guidance, Wan2.2's two experts switching at `boundary_ratio` with their
/// own guidance scale, TI2V's per-token timesteps, and no guidance.
#[test]
fn wan_pipeline_samples_equal_diffusers_for_the_same_seed() {
    use trainer::pipelines::pipeline_wan::{self, WanExperts, WanSampling};
    let io = read_tensors(&goldens().join("pipeline_io.safetensors"));
    let (_vs, model) = load_model(&goldens().join("transformer_t2v"));
    let (_vs_2, model_2) = load_model(&goldens().join("pipeline_transformer_2"));
    let vae_dir = goldens().join("vae_wan21");
    let (vae_vs, vae_model) =
        vae::build(&AutoencoderKLWanConfig::from_json_file(&vae_dir).unwrap(), Device::Cpu, Kind::Float).unwrap();
    weights::load(&vae_vs, &vae_dir).unwrap();
    let scheduler = UniPCMultistepSchedulerConfig::from_json_file(goldens().join("pipeline_scheduler")).unwrap();
    let shape: Vec<i64> = Vec::try_from(&io["shape"]).unwrap();
    let [frames, height, width, steps, seed] = shape[..] else { panic!("shape holds 5 values") };
    // (case, guidance_scale, guidance_scale_2, boundary_ratio, expand_timesteps): the script's.
    let cases = [
        ("cfg", 3.0, None, None, false),
        ("two_experts", 3.0, Some(1.5), Some(0.8), false),
        ("expand_timesteps", 2.0, None, None, true),
        ("no_guidance", 1.0, None, None, false),
    ];
    let grey = |a: &Tensor, b: &Tensor| a.f_sub(b).unwrap().abs().max().double_value(&[]) * 255.0;
    for (case, guidance_scale, guidance_scale_2, boundary_ratio, expand_timesteps) in cases {
        let experts =
            WanExperts { transformer: &model, transformer_2: boundary_ratio.map(|_| &model_2), boundary_ratio };
        let sampling = WanSampling {
            frames,
            height,
            width,
            steps: steps as usize,
            guidance_scale,
            guidance_scale_2,
            expand_timesteps,
        };
        tch::manual_seed(seed);
        let video = pipeline_wan::generate(
            experts,
            &vae_model,
            &scheduler,
            &io["prompt_embeds"],
            Some(&io["negative_prompt_embeds"]),
            None,
            &sampling,
        )
        .unwrap();
        let frames_np = (video / 2.0 + 0.5).clamp(0.0, 1.0).permute([0, 2, 3, 4, 1]);
        let expected = &io[&format!("{case}.video")];
        let error = grey(&frames_np, expected);
        println!("wan pipeline {case}: max error {error:.3e} grey levels");
        assert!(error <= 1.0, "{case}: {error} grey levels from WanPipeline");
    }
    // Each case exercises its branch: the second expert and guidance change the video.
    for (a, b) in [("cfg", "two_experts"), ("cfg", "no_guidance")] {
        let apart = grey(&io[&format!("{a}.video")], &io[&format!("{b}.video")]);
        assert!(apart > 1.0, "{a} and {b} are {apart} grey levels apart: the case tests nothing");
    }
}

/// The CogNVS conditioning on an image-to-video checkpoint reduces to `WanImageToVideoPipeline`:
/// a render that is the image followed by zeros, with a mask marking only the first frame, gives
/// the pipeline's video for that image within one grey level (Wan2.1 I2V: CLIP tokens too). A
/// mask that also marks a later frame known changes the video.
#[test]
fn cognvs_condition_of_first_frame_equals_wan_image_to_video_pipeline() {
    use trainer::pipelines::pipeline_wan::{self, WanCondition, WanExperts, WanSampling};
    let io = read_tensors(&goldens().join("pipeline_io.safetensors"));
    let (_vs, model) = load_model(&goldens().join("transformer_i2v"));
    let vae_dir = goldens().join("vae_wan21");
    let (vae_vs, vae_model) =
        vae::build(&AutoencoderKLWanConfig::from_json_file(&vae_dir).unwrap(), Device::Cpu, Kind::Float).unwrap();
    weights::load(&vae_vs, &vae_dir).unwrap();
    let scheduler = UniPCMultistepSchedulerConfig::from_json_file(goldens().join("pipeline_scheduler")).unwrap();
    let shape: Vec<i64> = Vec::try_from(&io["shape"]).unwrap();
    let [frames, height, width, steps, seed] = shape[..] else { panic!("shape holds 5 values") };
    let image = io["i2v.image"].unsqueeze(2);
    let render =
        Tensor::cat(&[&image, &Tensor::zeros([1, 3, frames - 1, height, width], (Kind::Float, Device::Cpu))], 2);
    let mask = Tensor::zeros([1, 1, frames, height, width], (Kind::Float, Device::Cpu));
    let _ = mask.narrow(2, 0, 1).fill_(1.0);
    let sampling = WanSampling {
        frames,
        height,
        width,
        steps: steps as usize,
        guidance_scale: 3.0,
        guidance_scale_2: None,
        expand_timesteps: false,
    };
    let experts = WanExperts { transformer: &model, transformer_2: None, boundary_ratio: None };
    let sample = |mask: &Tensor| {
        tch::manual_seed(seed);
        let condition = WanCondition { video: &render, mask, image_embeds: Some(&io["i2v.image_embeds"]) };
        let video = pipeline_wan::generate(
            experts,
            &vae_model,
            &scheduler,
            &io["i2v.prompt_embeds"],
            Some(&io["i2v.negative_prompt_embeds"]),
            Some(condition),
            &sampling,
        )
        .unwrap();
        (video / 2.0 + 0.5).clamp(0.0, 1.0).permute([0, 2, 3, 4, 1])
    };
    let grey = |a: &Tensor, b: &Tensor| a.f_sub(b).unwrap().abs().max().double_value(&[]) * 255.0;
    let error = grey(&sample(&mask), &io["i2v.video"]);
    println!("wan i2v pipeline from the CogNVS condition: max error {error:.3e} grey levels");
    assert!(error <= 1.0, "{error} grey levels from WanImageToVideoPipeline");
    let _ = mask.narrow(2, frames - 1, 1).fill_(1.0);
    let apart = grey(&sample(&mask), &io["i2v.video"]);
    assert!(apart > 1.0, "marking the last frame known moved the video only {apart} grey levels");
}

/// The CogNVS conditioning on a text-to-video checkpoint: the patch embedding widened with zero
/// weights for the mask and condition channels leaves the untrained model equal to `WanPipeline`
/// (within one grey level), whatever the render and mask; a non-zero weight there changes the
/// video, so the condition does reach the model.
#[test]
fn t2v_widened_for_the_cognvs_condition_equals_wan_pipeline() {
    use trainer::pipelines::pipeline_wan::{self, WanCondition, WanExperts, WanSampling};
    let io = read_tensors(&goldens().join("pipeline_io.safetensors"));
    let dir = goldens().join("transformer_t2v");
    let config = WanTransformer3DModelConfig::from_json_file(&dir).unwrap();
    let (vs, _) = load_model(&dir);
    let vae_dir = goldens().join("vae_wan21");
    let vae_config = AutoencoderKLWanConfig::from_json_file(&vae_dir).unwrap();
    let (vae_vs, vae_model) = vae::build(&vae_config, Device::Cpu, Kind::Float).unwrap();
    weights::load(&vae_vs, &vae_dir).unwrap();
    let temporal = vae_config.scale_factor_temporal.unwrap();
    // Noisy latents, then t mask channels and z_dim condition latents.
    let wide = config.in_channels + temporal + vae_config.z_dim;
    let (wide_vs, model) = transformer::widen_in_channels(&vs, &config, wide).unwrap();
    let scheduler = UniPCMultistepSchedulerConfig::from_json_file(goldens().join("pipeline_scheduler")).unwrap();
    let shape: Vec<i64> = Vec::try_from(&io["shape"]).unwrap();
    let [frames, height, width, steps, seed] = shape[..] else { panic!("shape holds 5 values") };
    tch::manual_seed(7);
    let render = Tensor::rand([1, 3, frames, height, width], (Kind::Float, Device::Cpu)) * 2.0 - 1.0;
    // Random holes, and a first frame known whole (so the mask channels are not all zero).
    let mask = Tensor::rand([1, 1, frames, height, width], (Kind::Float, Device::Cpu)).gt(0.5).to_kind(Kind::Float);
    let _ = mask.narrow(2, 0, 1).fill_(1.0);
    let sampling = WanSampling {
        frames,
        height,
        width,
        steps: steps as usize,
        guidance_scale: 3.0,
        guidance_scale_2: None,
        expand_timesteps: false,
    };
    let sample = || {
        tch::manual_seed(seed);
        let video = pipeline_wan::generate(
            WanExperts { transformer: &model, transformer_2: None, boundary_ratio: None },
            &vae_model,
            &scheduler,
            &io["prompt_embeds"],
            Some(&io["negative_prompt_embeds"]),
            Some(WanCondition { video: &render, mask: &mask, image_embeds: None }),
            &sampling,
        )
        .unwrap();
        (video / 2.0 + 0.5).clamp(0.0, 1.0).permute([0, 2, 3, 4, 1])
    };
    let grey = |a: &Tensor, b: &Tensor| a.f_sub(b).unwrap().abs().max().double_value(&[]) * 255.0;
    let error = grey(&sample(), &io["cfg.video"]);
    println!("wan t2v widened for the CogNVS condition: max error {error:.3e} grey levels from WanPipeline");
    assert!(error <= 1.0, "{error} grey levels from WanPipeline");
    let weight = &wide_vs.variables()[transformer::PATCH_EMBEDDING_WEIGHT];
    tch::no_grad(|| {
        // Random, not constant: a constant over the features is removed by the blocks' LayerNorms.
        let mut condition_weights = weight.narrow(1, config.in_channels, wide - config.in_channels);
        condition_weights.copy_(&(condition_weights.randn_like() * 0.1));
    });
    let apart = grey(&sample(), &io["cfg.video"]);
    assert!(apart > 1.0, "non-zero condition weights moved the video only {apart} grey levels");
}

/// Arguments the Wan sampler cannot honour are refused by name, before anything is drawn.
#[test]
fn wan_sampling_refuses_what_it_cannot_honour() {
    use trainer::pipelines::pipeline_wan::{self, WanCondition, WanExperts, WanSampling};
    let (_vs, model) = transformer::build(&WanTransformer3DModelConfig::tiny_t2v(), Device::Cpu, Kind::Float).unwrap();
    let (_vae_vs, vae_model) = vae::build(&AutoencoderKLWanConfig::tiny(), Device::Cpu, Kind::Float).unwrap();
    let scheduler = UniPCMultistepSchedulerConfig::wan_480p();
    let text = Tensor::zeros([1, 7, model.config().text_dim], (Kind::Float, Device::Cpu));
    let base = WanSampling {
        frames: 5,
        height: 16,
        width: 16,
        steps: 2,
        guidance_scale: 1.0,
        guidance_scale_2: None,
        expand_timesteps: false,
    };
    let one = WanExperts { transformer: &model, transformer_2: None, boundary_ratio: None };
    let video = Tensor::zeros([1, 3, 5, 16, 16], (Kind::Float, Device::Cpu));
    let mask = Tensor::zeros([1, 1, 5, 16, 16], (Kind::Float, Device::Cpu));
    let condition = WanCondition { video: &video, mask: &mask, image_embeds: None };
    let refusal = |experts, negative, condition, sampling: WanSampling| {
        pipeline_wan::generate(experts, &vae_model, &scheduler, &text, negative, condition, &sampling)
            .unwrap_err()
            .to_string()
    };
    let cases = [
        (one, None, None, WanSampling { frames: 6, ..base }, "frames"),
        (one, None, None, WanSampling { height: 12, ..base }, "size"),
        (one, None, None, WanSampling { guidance_scale: 2.0, ..base }, "negative"),
        (WanExperts { boundary_ratio: Some(0.9), ..one }, None, None, base, "boundary_ratio"),
        (one, None, Some(condition), WanSampling { expand_timesteps: true, ..base }, "expand_timesteps"),
        // Condition channels on a transformer without room for them.
        (one, None, Some(condition), base, "condition"),
    ];
    for (experts, negative, condition, sampling, flag) in cases {
        let e = refusal(experts, negative, condition, sampling);
        assert!(e.contains(flag), "{flag}: {e}");
    }
}
