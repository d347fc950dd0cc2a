//! Hostile inputs to `trainer`: every bad config value, shard folder, safetensors
//! file, dtype, config.json, frame size or count fails with one error naming the file and the
//! key or tensor, before any model work and without writing anything; diffusers-accepted VAE
//! configs and off-size conditionings are computed as diffusers / the training loader do.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use image::{Rgb, RgbImage};
use trainer::autoencoder_kl_cogvideox::AutoencoderKLCogVideoXConfig;
use trainer::cogvideox_transformer_3d::CogVideoXTransformer3DModelConfig;
use trainer::diffusers_config::DiffusersConfig;
use trainer::tch::{Device, Kind, Tensor};
use trainer::training::PretrainConfig;
use trainer::weights;

use super::parity::{assert_close, python, read_tensors, repo_root};

fn run(args: &[&dyn AsRef<std::ffi::OsStr>]) -> Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_trainer"));
    for a in args {
        cmd.arg(a);
    }
    cmd.output().expect("run trainer")
}

fn stderr(output: &Output) -> String {
    String::from_utf8_lossy(&output.stderr).into_owned()
}

/// Asserts a non-zero exit whose first error line contains every one of `needles`.
/// `trainer forward --module vae_encoder` with the VAE folder as config and weights.
fn encode(vae_dir: &Path, inputs: &Path, out: &Path) -> Output {
    run(&[
        &"forward",
        &"--module",
        &"vae_encoder",
        &"--config",
        &vae_dir,
        &"--weights",
        &vae_dir,
        &"--inputs",
        &inputs,
        &"--out",
        &out,
    ])
}

fn fails_with(output: &Output, needles: &[&str]) {
    let text = stderr(output);
    let first = text.lines().find(|l| l.starts_with("Error: ")).unwrap_or_default();
    assert!(!output.status.success(), "expected failure, got success: {text}");
    for needle in needles {
        assert!(first.contains(needle), "`{needle}` not in the error's first line:\n{text}");
    }
}

/// The tiny training TOML with `from` replaced by `to`.
fn tiny_toml(dir: &Path, name: &str, from: &str, to: &str) -> PathBuf {
    let text = std::fs::read_to_string(repo_root().join("configs/pretrain_tiny.toml")).unwrap();
    assert!(text.contains(from), "`{from}` not in configs/pretrain_tiny.toml");
    let path = dir.join(format!("{name}.toml"));
    std::fs::write(&path, text.replacen(from, to, 1)).unwrap();
    path
}

#[test]
fn training_toml_values_out_of_range_name_key_and_value() {
    let dir = tempfile::tempdir().unwrap();
    let cases: &[(&str, &str, &str, &[&str])] = &[
        ("lr = 1e-3", "lr = nan", "optim.lr", &["NaN"]),
        ("lr = 1e-3", "lr = -1e-3", "optim.lr", &["-0.001"]),
        ("lr = 1e-3", "lr = inf", "optim.lr", &["inf"]),
        ("beta1 = 0.9", "beta1 = 1.0", "optim.beta1", &["1 must be in [0, 1)"]),
        ("beta2 = 0.95", "beta2 = -0.1", "optim.beta2", &["-0.1"]),
        ("weight_decay = 1e-4", "weight_decay = -1.0", "optim.weight_decay", &["-1"]),
        ("weight_decay = 1e-4", "weight_decay = 1e-4\neps = 0.0", "optim.eps", &["0 must be finite and > 0"]),
        ("max_grad_norm = 1.0", "max_grad_norm = nan", "optim.max_grad_norm", &["NaN"]),
        ("max_grad_norm = 1.0", "max_grad_norm = -1.0", "optim.max_grad_norm", &["-1"]),
        ("schedule = \"constant\"", "schedule = \"linear\"", "optim.schedule", &["`linear`"]),
        ("grad_accumulation = 1", "grad_accumulation = 0", "optim.grad_accumulation", &["0"]),
        ("steps = 20", "steps = 0", "loop.steps", &["0"]),
        ("keep_last = 2", "keep_last = 0", "loop.keep_last", &["0"]),
        (
            "seed = 0\ncheckpoint_every",
            "seed = 0\ncondition_noise_log_std = -0.5\ncheckpoint_every",
            "loop.condition_noise_log_std",
            &["-0.5"],
        ),
        (
            "seed = 0\ncheckpoint_every",
            "seed = 0\ncondition_noise_log_mean = nan\ncheckpoint_every",
            "loop.condition_noise_log_mean",
            &["NaN"],
        ),
        ("validation_steps = 10", "validation_steps = 0", "loop.validation_steps", &["0"]),
        ("validation_steps = 10", "validation_steps = 5000", "loop.validation_steps", &["5000", "1000"]),
        ("frames = 9", "frames = 10", "data.frames", &["10", "4k + 1"]),
        ("frames = 9", "frames = 0", "data.frames", &["0"]),
        ("frames = 9", "frames = 100001", "data.frames", &["100001"]),
        ("height = 64", "height = 72", "data.height", &["72", "multiple of 16"]),
        ("width = 80", "width = 160", "data.width", &["160", "80 pixels"]),
        ("height = 64", "height = 4000000", "data.height", &["4000000"]),
        ("batch_size = 1", "batch_size = 0", "data.batch_size", &["0"]),
        ("seed = 0\n\n[optim]", "seed = 0\nrank = 2\n\n[optim]", "data.rank", &["2", "world_size 1"]),
        ("seed = 0\n\n[optim]", "seed = 0\nprefetch_batches = 0\n\n[optim]", "data.prefetch_batches", &["0"]),
        ("transformer = \"tiny\"", "transformer = \"huge\"", "model.transformer", &["huge"]),
        ("vae = \"tiny\"", "vae = \"/no/such/vae\"", "model.vae", &["/no/such/vae"]),
        (
            "# text_embedding = \"empty_prompt_t5.safetensors\"",
            "text_embedding = \"/nonexistent/prompt.safetensors\"",
            "model.text_embedding",
            &["/nonexistent/prompt.safetensors"],
        ),
    ];
    for (i, (from, to, key, values)) in cases.iter().enumerate() {
        let path = tiny_toml(dir.path(), &format!("case{i}"), from, to);
        let err = PretrainConfig::from_toml_file(&path).expect_err(to).to_string();
        let first = err.lines().next().unwrap();
        assert!(first.contains(&format!("`{key}`")), "{to}: key `{key}` not in: {err}");
        assert!(first.contains(&path.display().to_string()), "{to}: file not named: {err}");
        for v in *values {
            assert!(first.contains(v), "{to}: `{v}` not in: {err}");
        }
    }
    // The unchanged file is valid.
    PretrainConfig::from_toml_file(&tiny_toml(dir.path(), "ok", "steps = 20", "steps = 20")).unwrap();
}

#[test]
fn training_toml_parse_errors_name_file_and_key_on_the_first_line() {
    let dir = tempfile::tempdir().unwrap();
    for (from, to, key) in [
        ("lr = 1e-3", "lr = \"fast\"", "optim.lr"),
        ("steps = 20", "steps = -3", "loop.steps"),
        ("lr = 1e-3", "lr = 1e-3\nlrr = 1", "optim.lrr"),
        ("frames = 9", "", "data.frames"),
        ("height = 64", "height = 64.5", "data.height"),
    ] {
        let path = tiny_toml(dir.path(), "parse", from, to);
        let err = PretrainConfig::from_toml_file(&path).expect_err(to).to_string();
        let first = err.lines().next().unwrap();
        assert!(
            first.contains(&path.display().to_string()) && first.contains(&format!("`{key}`")),
            "{to:?}: first line must name the file and `{key}`: {err}"
        );
        assert!(first.contains("line "), "{to:?}: the line number: {err}");
    }
}

#[test]
fn pretrain_cli_refuses_a_bad_config_before_writing_anything() {
    let dir = tempfile::tempdir().unwrap();
    let config = tiny_toml(dir.path(), "nan", "lr = 1e-3", "lr = nan");
    let shards = dir.path().join("shards");
    std::fs::create_dir_all(&shards).unwrap();
    let out = dir.path().join("run");
    let output = run(&[&"pretrain", &"--config", &config, &"--shards", &shards, &"--out", &out]);
    fails_with(&output, &["optim.lr", "NaN", &config.display().to_string()]);
    assert!(!out.exists(), "nothing is written");
    // --steps 0 is refused by the flag parser.
    let good = tiny_toml(dir.path(), "good", "steps = 20", "steps = 20");
    let output = run(&[&"pretrain", &"--config", &good, &"--shards", &shards, &"--out", &out, &"--steps", &"0"]);
    assert!(!output.status.success() && stderr(&output).contains("--steps"), "{}", stderr(&output));
    assert!(!out.exists(), "nothing is written");
}

#[test]
fn empty_and_foreign_shard_folders_are_named_errors() {
    let dir = tempfile::tempdir().unwrap();
    let config = tiny_toml(dir.path(), "ok", "steps = 20", "steps = 20");
    let out = dir.path().join("run");
    let pretrain = |shards: &Path| run(&[&"pretrain", &"--config", &config, &"--shards", &shards, &"--out", &out]);

    let empty = dir.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    fails_with(&pretrain(&empty), &[&empty.display().to_string(), "no *.parquet shards"]);

    // A Parquet file of another schema: skipped-as-unfinished without a stats marker (named),
    // read and refused with one.
    let foreign = dir.path().join("foreign");
    std::fs::create_dir_all(&foreign).unwrap();
    let table = foreign.join("other.parquet");
    let status = Command::new(python())
        .arg("-c")
        .arg("import sys, pyarrow as pa, pyarrow.parquet as pq; pq.write_table(pa.table({'x': [1, 2]}), sys.argv[1])")
        .arg(&table)
        .status()
        .unwrap();
    assert!(status.success());
    fails_with(&pretrain(&foreign), &[&foreign.display().to_string(), "other.parquet", "stats marker"]);
    std::fs::write(schemas::shard::stats_path(&table), "{}").unwrap();
    fails_with(&pretrain(&foreign), &[&table.display().to_string()]);
    fails_with(&pretrain(&table), &[&table.display().to_string()]);
    assert!(!out.exists(), "nothing is written");
}

/// A tiny checkpoint (random transformer and VAE) in the layout `trainer sample` reads.
fn tiny_checkpoint(dir: &Path) -> PathBuf {
    let ckpt = dir.join("ckpt");
    let config = CogVideoXTransformer3DModelConfig::tiny();
    super::parity::save_tiny_models(&config, &ckpt.join("transformer"), &ckpt.join("vae"));
    ckpt
}

/// `count` PNG frames of `width × height` (a gradient) in `dir`, `sizes` overriding some.
fn frames(dir: &Path, count: usize, (width, height): (u32, u32), sizes: &[(usize, (u32, u32))]) -> PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    for i in 0..count {
        let (w, h) = sizes.iter().find(|(k, _)| *k == i).map_or((width, height), |(_, s)| *s);
        let img = RgbImage::from_fn(w, h, |x, y| Rgb([(x * 3) as u8, (y * 5) as u8, (i * 20) as u8]));
        img.save(dir.join(format!("{i:05}.png"))).unwrap();
    }
    dir.to_path_buf()
}

fn sample(ckpt: &Path, cond: &Path, out: &Path) -> Output {
    run(&[&"sample", &"--ckpt", &ckpt, &"--cond", &cond, &"--out", &out, &"--steps", &"1"])
}

#[test]
fn sample_resizes_an_off_size_conditioning_to_the_model_and_back_and_says_so() {
    let dir = tempfile::tempdir().unwrap();
    let ckpt = tiny_checkpoint(dir.path());
    // 96 x 64: the tiny model's learned positional table needs 80 x 64. As the public demo, the
    // frames are stretched to it with an area average and the result resized back.
    let cond = frames(&dir.path().join("cond"), 9, (96, 64), &[]);
    let out = dir.path().join("out.mp4");
    let output = sample(&ckpt, &cond, &out);
    let text = stderr(&output);
    assert!(output.status.success(), "{text}");
    assert!(text.contains("resized") && text.contains("96x64") && text.contains("80x64"), "{text}");
    let video = datagen::io::video::decode_video(&out).unwrap();
    assert_eq!((video.frames.len(), video.frames[0].dimensions()), (9, (96, 64)));
    // The training loader's cover-crop, kept at the model's size, on request.
    let cropped = dir.path().join("cropped");
    let output = run(&[
        &"sample",
        &"--ckpt",
        &ckpt,
        &"--cond",
        &cond,
        &"--out",
        &cropped,
        &"--steps",
        &"1",
        &"--resize",
        &"crop",
        &"--keep-model-size",
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    assert_eq!(std::fs::read_dir(&cropped).unwrap().count(), 9);
    assert_eq!(image::image_dimensions(cropped.join("00000.png")).unwrap(), (80, 64));
}

#[test]
fn sample_refuses_mixed_sizes_and_bad_frame_counts_before_model_work() {
    let dir = tempfile::tempdir().unwrap();
    let ckpt = tiny_checkpoint(dir.path());
    let out = dir.path().join("out.mp4");
    let mixed = frames(&dir.path().join("mixed"), 9, (80, 64), &[(4, (96, 64))]);
    fails_with(&sample(&ckpt, &mixed, &out), &["00004.png", "96x64", "00000.png", "80x64"]);
    let short = frames(&dir.path().join("short"), 8, (80, 64), &[]);
    let output = run(&[&"sample", &"--ckpt", &ckpt, &"--cond", &short, &"--out", &out, &"--frames", &"8"]);
    fails_with(&output, &["frames", "8 is not 1 + 4k"]);
    let empty = dir.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    fails_with(&sample(&ckpt, &empty, &out), &[&empty.display().to_string(), "frames"]);
    // A truncated text embedding and an integer one are named errors.
    let text = dir.path().join("text.safetensors");
    Tensor::write_safetensors(&[("encoder_hidden_states", &Tensor::zeros([8, 16], (Kind::Int64, Device::Cpu)))], &text)
        .unwrap();
    let cond = frames(&dir.path().join("cond"), 9, (80, 64), &[]);
    let output = run(&[&"sample", &"--ckpt", &ckpt, &"--cond", &cond, &"--out", &out, &"--text-embedding", &text]);
    fails_with(&output, &["encoder_hidden_states", &text.display().to_string(), "Int64"]);
    truncate(&text, 16);
    let output = run(&[&"sample", &"--ckpt", &ckpt, &"--cond", &cond, &"--out", &out, &"--text-embedding", &text]);
    fails_with(&output, &[&text.display().to_string(), "encoder_hidden_states", "truncated"]);
    assert!(!out.exists(), "nothing is written");
}

fn truncate(path: &Path, by: u64) {
    let file = std::fs::OpenOptions::new().write(true).open(path).unwrap();
    let len = file.metadata().unwrap().len();
    file.set_len(len - by).unwrap();
}

#[test]
fn truncated_safetensors_name_the_file_and_tensor_before_reading() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("t.safetensors");
    let a = Tensor::zeros([4, 4], (Kind::Float, Device::Cpu));
    let b = Tensor::ones([2, 3], (Kind::Float, Device::Cpu));
    Tensor::write_safetensors(&[("a", &a), ("b", &b)], &path).unwrap();
    assert_eq!(weights::read_header(&path).unwrap().len(), 2);
    truncate(&path, 8);
    let err = weights::read_header(&path).unwrap_err().to_string();
    assert!(err.contains(&path.display().to_string()) && err.contains("`b`") && err.contains("truncated"), "{err}");
    let err = weights::read_safetensors(&path).unwrap_err().to_string();
    assert!(err.contains("`b`"), "{err}");
    // A header length beyond the file.
    std::fs::write(&path, 1_000_000u64.to_le_bytes()).unwrap();
    let err = weights::read_header(&path).unwrap_err().to_string();
    assert!(err.contains(&path.display().to_string()) && err.contains("header length"), "{err}");

    // The CLI: truncated VAE weights fail before the model is built; nothing is written.
    let ckpt = tiny_checkpoint(dir.path());
    let vae_dir = ckpt.join("vae");
    let inputs = dir.path().join("in.safetensors");
    let sample = Tensor::zeros([1, 3, 1, 16, 16], (Kind::Float, Device::Cpu));
    Tensor::write_safetensors(&[("sample", &sample)], &inputs).unwrap();
    let weights_file = vae_dir.join(weights::WEIGHTS_NAME);
    truncate(&weights_file, 1000);
    let out = dir.path().join("out.safetensors");
    fails_with(&encode(&vae_dir, &inputs, &out), &[&weights_file.display().to_string(), "truncated"]);
    // Truncated inputs name the input file and tensor.
    truncate(&inputs, 100);
    fails_with(&encode(&vae_dir, &inputs, &out), &[&inputs.display().to_string(), "`sample`", "truncated"]);
    assert!(!out.exists(), "nothing is written");
}

#[test]
fn integer_inputs_where_floats_are_expected_name_tensor_and_dtype() {
    let dir = tempfile::tempdir().unwrap();
    let ckpt = tiny_checkpoint(dir.path());
    let vae_dir = ckpt.join("vae");
    let inputs = dir.path().join("in.safetensors");
    Tensor::write_safetensors(&[("sample", &Tensor::zeros([1, 3, 1, 16, 16], (Kind::Int64, Device::Cpu)))], &inputs)
        .unwrap();
    let out = dir.path().join("out.safetensors");
    let output = encode(&vae_dir, &inputs, &out);
    fails_with(&output, &["`sample`", &inputs.display().to_string(), "Int64"]);
    assert!(!out.exists());
    // An integer text embedding (library).
    let text = dir.path().join("text.safetensors");
    Tensor::write_safetensors(&[("encoder_hidden_states", &Tensor::zeros([8, 16], (Kind::Int, Device::Cpu)))], &text)
        .unwrap();
    let err =
        trainer::loaders::load_text_embedding(Some(&text), &CogVideoXTransformer3DModelConfig::tiny(), Device::Cpu)
            .unwrap_err()
            .to_string();
    assert!(err.contains("encoder_hidden_states") && err.contains("Int"), "{err}");
}

#[test]
fn config_json_of_wrong_types_names_file_and_key() {
    let dir = tempfile::tempdir().unwrap();
    let ckpt = tiny_checkpoint(dir.path());
    let vae_config = ckpt.join("vae/config.json");
    let original = std::fs::read_to_string(&vae_config).unwrap();
    let mut json: serde_json::Value = serde_json::from_str(&original).unwrap();
    for (key, value) in [
        ("block_out_channels", serde_json::json!("wide")),
        ("layers_per_block", serde_json::json!(1.5)),
        ("scaling_factor", serde_json::json!([0.7])),
        ("temporal_compression_ratio", serde_json::json!(0)),
    ] {
        let saved = json[key].clone();
        json[key] = value;
        std::fs::write(&vae_config, serde_json::to_string_pretty(&json).unwrap()).unwrap();
        let err = AutoencoderKLCogVideoXConfig::from_json_file(&vae_config).unwrap_err().to_string();
        assert!(
            err.lines().next().unwrap().contains(&vae_config.display().to_string())
                && err.contains(&format!("`{key}`")),
            "{key}: {err}"
        );
        json[key] = saved;
    }
    // Through the CLI: one error, exit non-zero, nothing written.
    json["block_out_channels"] = serde_json::json!("wide");
    std::fs::write(&vae_config, serde_json::to_string_pretty(&json).unwrap()).unwrap();
    let inputs = dir.path().join("in.safetensors");
    Tensor::write_safetensors(&[("sample", &Tensor::zeros([1, 3, 1, 16, 16], (Kind::Float, Device::Cpu)))], &inputs)
        .unwrap();
    let (vae_dir, out) = (ckpt.join("vae"), dir.path().join("out.safetensors"));
    let output = encode(&vae_dir, &inputs, &out);
    fails_with(&output, &[&vae_config.display().to_string(), "`block_out_channels`", "\"wide\""]);
    assert!(!out.exists());
    // The transformer's config.json and a run's config.json (nested keys named as a path).
    let transformer_config = ckpt.join("transformer/config.json");
    let mut json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&transformer_config).unwrap()).unwrap();
    json["num_layers"] = serde_json::json!("two");
    std::fs::write(&transformer_config, serde_json::to_string_pretty(&json).unwrap()).unwrap();
    let err = CogVideoXTransformer3DModelConfig::from_json_file(&transformer_config).unwrap_err().to_string();
    assert!(err.contains(&transformer_config.display().to_string()) && err.contains("`num_layers`"), "{err}");
    let run_config = dir.path().join("config.json");
    let toml = PretrainConfig::from_toml_file(&tiny_toml(dir.path(), "ok", "steps = 20", "steps = 20")).unwrap();
    let mut json = serde_json::to_value(&toml).unwrap();
    json["optim"]["lr"] = serde_json::json!("fast");
    std::fs::write(&run_config, serde_json::to_string_pretty(&json).unwrap()).unwrap();
    let err = PretrainConfig::from_json_file(&run_config).unwrap_err().to_string();
    assert!(err.contains(&run_config.display().to_string()) && err.contains("`optim.lr`"), "{err}");
}

#[test]
fn eval_of_videos_of_different_sizes_names_both_files_and_sizes() {
    let dir = tempfile::tempdir().unwrap();
    let pred = frames(&dir.path().join("pred"), 3, (16, 16), &[]);
    let target = frames(&dir.path().join("target"), 3, (24, 16), &[]);
    let out = dir.path().join("metrics.json");
    let eval = |pred: &Path, target: &Path| run(&[&"eval", &"--pred", &pred, &"--target", &target, &"--out", &out]);
    fails_with(
        &eval(&pred, &target),
        &[
            &pred.join("00000.png").display().to_string(),
            "16x16",
            &target.join("00000.png").display().to_string(),
            "24x16",
        ],
    );
    // Frames of different sizes within one input.
    let mixed = frames(&dir.path().join("mixed"), 3, (16, 16), &[(2, (16, 24))]);
    fails_with(&eval(&pred, &mixed), &["00002.png", "16x24", "00000.png", "16x16"]);
    assert!(!out.exists(), "nothing is written");
}

#[test]
fn vae_with_fewer_levels_than_its_temporal_ratio_runs_as_in_diffusers() {
    let goldens = super::vae::goldens();
    let model = goldens.join("vae_two_level");
    let config = AutoencoderKLCogVideoXConfig::from_json_file(&model).unwrap();
    assert_eq!((config.temporal_compression_ratio, config.effective_temporal_compression_ratio()), (4.0, 2));
    let io = read_tensors(&goldens.join("vae_two_level_io.safetensors"));
    let dir = tempfile::tempdir().unwrap();
    for (module, input, key, produced) in
        [("vae_encoder", "sample", "encode", "latent"), ("vae_decoder", "latent", "decode", "sample")]
    {
        let inputs = dir.path().join(format!("{module}_in.safetensors"));
        Tensor::write_safetensors(&[(input, &io[&format!("{key}.{input}")])], &inputs).unwrap();
        let out = dir.path().join(format!("{module}_out.safetensors"));
        let output = run(&[
            &"forward",
            &"--module",
            &module,
            &"--config",
            &model,
            &"--weights",
            &model,
            &"--inputs",
            &inputs,
            &"--out",
            &out,
        ]);
        let text = stderr(&output);
        assert!(output.status.success(), "{text}");
        assert!(text.contains("warning") && text.contains("temporal_compression_ratio 4"), "{text}");
        let name = format!("two-level VAE {module} (ratio 4 with 2 levels)");
        assert_close(&name, &read_tensors(&out)[produced], &io[&format!("{key}.{produced}")], 1e-4);
    }
}

#[test]
fn pretrain_steps_flag_overrides_loop_steps() {
    let dir = tempfile::tempdir().unwrap();
    let shards = super::pretrain::pairs(dir.path());
    let config = tiny_toml(dir.path(), "ok", "steps = 20", "steps = 20");
    let out = dir.path().join("run");
    let output = run(&[&"pretrain", &"--config", &config, &"--shards", &shards, &"--out", &out, &"--steps", &"1"]);
    assert!(output.status.success(), "{}", stderr(&output));
    assert_eq!(trainer::training::read_metrics(&out).unwrap().len(), 1);
    assert!(out.join("checkpoints/step-00000001/transformer/config.json").is_file());
}
