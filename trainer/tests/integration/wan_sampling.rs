//! Sampling novel views with a Wan model: `trainer nvs` end to end on the CPU with a tiny random
//! Wan pipeline folder (`transformer/`, `vae/`, `scheduler/`) and a text embedding, and the
//! family dispatch of `pipelines::sampling` adding nothing to `pipeline_wan::generate` called
//! directly with the same seed, render and hole mask.

use std::path::{Path, PathBuf};

use trainer::models::backbone::{TextShape, Transformer, TransformerConfig, Vae, VaeConfig};
use trainer::models::wan::autoencoder_kl_wan::AutoencoderKLWanConfig;
use trainer::models::wan::transformer_wan::WanTransformer3DModelConfig;
use trainer::models::weights;
use trainer::pipelines::sampling::{Framing, LoadOptions, Pipeline};
use trainer::precision::Precision;
use trainer::schedulers::scheduling_unipc_multistep::UniPCMultistepSchedulerConfig;
use trainer::tch::{self, Device, Kind, Tensor};

use super::parity::assert_success;

/// A tiny random Wan CogNVS pipeline folder at `dir` (diffusers' layout: `transformer/`,
/// `vae/`, `scheduler/`) and a random text embedding file of the transformer's text shape.
fn wan_pipeline_folder(dir: &Path) -> PathBuf {
    tch::manual_seed(11);
    let config = WanTransformer3DModelConfig::tiny_cognvs();
    let (vs, _, model) =
        Transformer::build(&TransformerConfig::Wan(config.clone()), None, Device::Cpu, Kind::Float).unwrap();
    model
        .save(vs.variables().into_iter().collect(), &dir.join("transformer"), weights::DEFAULT_MAX_SHARD_BYTES)
        .unwrap();
    let (vae_vs, vae) = Vae::build(&VaeConfig::Wan(AutoencoderKLWanConfig::tiny()), Device::Cpu, Kind::Float).unwrap();
    vae.save(&vae_vs, &dir.join("vae"), weights::DEFAULT_MAX_SHARD_BYTES).unwrap();
    std::fs::create_dir_all(dir.join("scheduler")).unwrap();
    let mut scheduler = serde_json::to_value(UniPCMultistepSchedulerConfig::wan_480p()).unwrap();
    scheduler["_class_name"] = "UniPCMultistepScheduler".into();
    std::fs::write(dir.join("scheduler/scheduler_config.json"), scheduler.to_string()).unwrap();
    let text = Tensor::randn(config.text_shape(), (Kind::Float, Device::Cpu));
    let embedding = dir.join("prompt.safetensors");
    Tensor::write_safetensors(&[("encoder_hidden_states", text)], &embedding).unwrap();
    embedding
}

/// A render folder as `datagen render` writes it: `frames/` and `holes/` (255 a hole), a hole
/// band moving across the frames.
fn render_folder(dir: &Path, frames: u32, (width, height): (u32, u32)) {
    std::fs::create_dir_all(dir.join("frames")).unwrap();
    std::fs::create_dir_all(dir.join("holes")).unwrap();
    for f in 0..frames {
        let hole = |x: u32| x >= 4 * f && x < 4 * f + 6;
        let image = image::RgbImage::from_fn(width, height, |x, y| {
            if hole(x) { image::Rgb([0, 0, 0]) } else { image::Rgb([(x * 7 + f) as u8, (y * 5) as u8, 90]) }
        });
        image.save(dir.join(format!("frames/{f:05}.png"))).unwrap();
        let holes = image::GrayImage::from_fn(width, height, |x, _| image::Luma([if hole(x) { 255 } else { 0 }]));
        holes.save(dir.join(format!("holes/{f:05}.png"))).unwrap();
    }
}

/// The dispatch route (`Pipeline::load` + `sample`, what `trainer sample` and `nvs` run) gives
/// exactly the frames of `pipeline_wan::generate` called on the same models, seed, render and
/// hole mask (the mask built here from `holes/` independently).
#[test]
fn wan_sampling_route_equals_pipeline_wan_directly() {
    let dir = tempfile::tempdir().unwrap();
    let embedding = wan_pipeline_folder(&dir.path().join("pipeline"));
    let render = dir.path().join("render");
    let (frames, size, steps, seed) = (5, (32, 24), 2, 9);
    render_folder(&render, frames, size);
    let source = trainer::loaders::ModelSource {
        checkpoint: dir.path().join("pipeline"),
        base_model: Some(dir.path().join("pipeline")),
        vae: None,
        lora: None,
        text_embedding: Some(embedding),
        negative_text_embedding: None,
        zero_text_embedding: false,
    };
    let paths = source.resolve().unwrap();
    let options = LoadOptions { device: Device::Cpu, precision: Precision::Fp32, vae_tiling: false };
    let framing = Framing { frames: frames as usize, size: Some(size), restore_size: false, ..Framing::default() };
    let pipeline = Pipeline::load(&paths, options).unwrap();
    assert!(matches!(pipeline, Pipeline::Wan(_)), "the family comes from the folder's config.json");
    let routed = pipeline.sample(&render, &framing, steps, 6.0, seed, Device::Cpu, &mut |_, _| {}).unwrap();

    // The same, by hand.
    use trainer::models::wan::{autoencoder_kl_wan as wan_vae, transformer_wan as wan_transformer};
    use trainer::pipelines::pipeline_wan::{self, WanCondition, WanExperts, WanSampling};
    let config: WanTransformer3DModelConfig = trainer::diffusers_config::read(&paths.transformer).unwrap();
    let (vs, transformer) = wan_transformer::build(&config, Device::Cpu, Kind::Float).unwrap();
    wan_transformer::load(&vs, &paths.transformer).unwrap();
    let vae_config: AutoencoderKLWanConfig = trainer::diffusers_config::read(&paths.vae).unwrap();
    let (vae_vs, vae) = wan_vae::build(&vae_config, Device::Cpu, Kind::Float).unwrap();
    weights::load(&vae_vs, &paths.vae).unwrap();
    let scheduler = UniPCMultistepSchedulerConfig::wan_480p();
    let text = trainer::loaders::load_text_embedding(paths.text_embedding.as_deref(), &config, Device::Cpu).unwrap();
    let read = |sub: &str| {
        let mut files: Vec<PathBuf> = std::fs::read_dir(render.join(sub)).unwrap().map(|e| e.unwrap().path()).collect();
        files.sort();
        foundation::frames::read_frames(&files).unwrap()
    };
    let video =
        trainer::pipelines::video_processor::frames_to_video(&read("frames"), Kind::Float, Device::Cpu).unwrap();
    let known: Vec<f32> =
        read("holes").iter().flat_map(|h| h.pixels().map(|p| f32::from(p.0[0] == 0)).collect::<Vec<_>>()).collect();
    let mask = Tensor::from_slice(&known).view([1, 1, frames as i64, size.1 as i64, size.0 as i64]);
    tch::manual_seed(seed as i64);
    let direct = pipeline_wan::generate(
        WanExperts { transformer: &transformer, transformer_2: None, boundary_ratio: None },
        &vae,
        &scheduler,
        &text,
        None,
        Some(WanCondition { video: &video, mask: &mask, image_embeds: None }),
        &WanSampling {
            frames: frames as i64,
            height: size.1 as i64,
            width: size.0 as i64,
            steps,
            // The negative embedding is the prompt's: guidance gives the conditional prediction.
            guidance_scale: 1.0,
            guidance_scale_2: None,
            expand_timesteps: false,
        },
    )
    .unwrap();
    let direct = trainer::pipelines::sampling::to_frames(&direct).unwrap();
    assert_eq!(routed.frames.len(), frames as usize);
    assert!(routed.frames == direct, "the routed sample must equal pipeline_wan's for the same seed and inputs");
    // The hole mask matters: without holes the same render samples other frames.
    let no_holes = dir.path().join("no_holes");
    render_folder(&no_holes, frames, size);
    for f in 0..frames {
        image::GrayImage::new(size.0, size.1).save(no_holes.join(format!("holes/{f:05}.png"))).unwrap();
    }
    let other = pipeline.sample(&no_holes, &framing, steps, 6.0, seed, Device::Cpu, &mut |_, _| {}).unwrap();
    assert!(other.frames != routed.frames, "the mask must reach the model");
}

/// `trainer nvs --init <Wan pipeline folder>`: the sequence rendered along a trajectory and the
/// render sampled by the Wan model into the novel-view video and frames.
#[test]
fn nvs_samples_novel_views_with_a_wan_pipeline_folder() {
    let dir = tempfile::tempdir().unwrap();
    let folder = dir.path().join("wan");
    let embedding = wan_pipeline_folder(&folder);
    let sequence = dir.path().join("video");
    let scene = datagen::synth::SynthConfig { width: 80, height: 64, frames: 5, seed: 3, ..Default::default() };
    datagen::synth::write_sequence(&scene, &sequence, |_| {}).unwrap();
    let trajectories = super::nvs::trajectories(dir.path(), &sequence);
    let out = dir.path().join("out");
    let mut args: Vec<std::ffi::OsString> = vec!["--init".into(), folder.clone().into()];
    args.extend(["--sequence".into(), sequence.clone().into(), "--trajectory".into(), trajectories[0].clone().into()]);
    args.extend(["--out".into(), out.clone().into(), "--text-embedding".into(), embedding.into()]);
    for s in ["--steps", "0", "--sample-steps", "2", "--frames", "5", "--size", "80x64"] {
        args.push(s.into());
    }
    let output = super::nvs::nvs(&args).output().unwrap();
    assert_success(&output);
    let record: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("nvs.json")).unwrap()).unwrap();
    assert_eq!(record["complete"], true);
    let video = foundation::video::decode_video(&out.join("orbit.mp4")).unwrap();
    assert_eq!((video.frames.len(), video.frames[0].dimensions()), (5, (80, 64)));
    assert_eq!(std::fs::read_dir(out.join("orbit")).unwrap().count(), 5);
    assert!(out.join("renders/orbit/holes/00000.png").is_file());
}
