//! Hostile inputs to `trainer`: every bad config value, shard folder, safetensors
//! file, dtype, config.json, frame size or count fails with one error naming the file and the
//! key or tensor, before any model work and without writing anything; diffusers-accepted VAE
//! configs and off-size conditionings are computed as diffusers / the training loader do. On the
//! user path (`trainer nvs`, text embeddings, released-model folders, checkpoints, held-out
//! validation): output names that leave or clash with OUT, non-finite tensors and samples,
//! scheduler and transformer configs out of range, checkpoint records reaching beyond their
//! folder, signals at start-up, and flags refused by the parser.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use image::{Rgb, RgbImage};
use trainer::diffusers_config::DiffusersConfig;
use trainer::models::cogvideox::autoencoder_kl_cogvideox::AutoencoderKLCogVideoXConfig;
use trainer::models::cogvideox::cogvideox_transformer_3d::CogVideoXTransformer3DModelConfig;
use trainer::models::weights;
use trainer::tch::{Device, Kind, Tensor};
use trainer::training::PretrainConfig;

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
        ("\n\n[optim]", "\nrank = 2\n\n[optim]", "data.rank", &["2", "world_size 1"]),
        ("\n\n[optim]", "\nprefetch_batches = 0\n\n[optim]", "data.prefetch_batches", &["0"]),
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
fn pretrain_refuses_a_non_finite_text_embedding_before_writing_anything() {
    let dir = tempfile::tempdir().unwrap();
    let text = text_embedding_with(&dir.path().join("nan_text.safetensors"), f64::NAN);
    let config = tiny_toml(
        dir.path(),
        "nan_text",
        "# text_embedding = \"empty_prompt_t5.safetensors\"",
        &format!("text_embedding = {:?}", text.display().to_string()),
    );
    let shards = dir.path().join("shards");
    std::fs::create_dir_all(&shards).unwrap();
    let out = dir.path().join("run");
    let output = run(&[&"pretrain", &"--config", &config, &"--shards", &shards, &"--out", &out]);
    fails_with(&output, &["encoder_hidden_states", &text.display().to_string(), "not finite"]);
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
    let video = foundation::video::decode_video(&out).unwrap();
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

// ------------------------------------------------------------------------------------------------
// The user path: `trainer nvs`, text embeddings, released-model folders, verified checkpoints,
// held-out validation. Every refusal names the flag or the file and field, and comes before
// anything is written.
// ------------------------------------------------------------------------------------------------

/// A `trainer nvs` job on the tiny released layout: the models, a 13-frame video, its two
/// trajectories (`orbit.txt`, `shift.json`) and the arguments of a valid job without finetuning.
struct NvsJob {
    dir: tempfile::TempDir,
    transformer: PathBuf,
    base: PathBuf,
    toml: PathBuf,
    sequence: PathBuf,
    trajectories: Vec<PathBuf>,
}

impl NvsJob {
    fn new() -> Self {
        let dir = tempfile::tempdir().unwrap();
        let (transformer, base, toml) = super::nvs::released_layout(dir.path());
        let sequence = dir.path().join("video");
        let scene = datagen::synth::SynthConfig { width: 80, height: 64, frames: 13, seed: 3, ..Default::default() };
        datagen::synth::write_sequence(&scene, &sequence, |_| {}).unwrap();
        let trajectories = super::nvs::trajectories(dir.path(), &sequence);
        Self { dir, transformer, base, toml, sequence, trajectories }
    }

    fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    /// The arguments of the valid job into `out` with `trajectories`, with `extra`'s flag and
    /// value pairs replacing the valid job's value of the same flag or added.
    fn args(
        &self,
        out: &Path,
        trajectories: &[PathBuf],
        extra: &[&dyn AsRef<std::ffi::OsStr>],
    ) -> Vec<std::ffi::OsString> {
        let mut a: Vec<std::ffi::OsString> = vec!["--init".into(), self.transformer.clone().into()];
        a.extend(["--base-model".into(), self.base.clone().into(), "--sequence".into(), self.sequence.clone().into()]);
        for p in trajectories {
            a.extend(["--trajectory".into(), p.clone().into()]);
        }
        a.extend(["--out".into(), out.into()]);
        for s in ["--steps", "0", "--sample-steps", "1", "--frames", "9"] {
            a.push(s.into());
        }
        for pair in extra.chunks(2) {
            let (flag, value) = (pair[0].as_ref().to_os_string(), pair[1].as_ref().to_os_string());
            match a.iter().position(|x| *x == flag) {
                Some(i) => a[i + 1] = value,
                None => a.extend([flag, value]),
            }
        }
        a
    }

    fn run(&self, out: &Path, trajectories: &[PathBuf], extra: &[&dyn AsRef<std::ffi::OsStr>]) -> Output {
        super::nvs::nvs(&self.args(out, trajectories, extra)).output().unwrap()
    }
}

/// Command-line flags and values of a case.
type Flags<'a> = Vec<&'a dyn AsRef<std::ffi::OsStr>>;
/// Config fields and their values of a case.
type Fields<'a> = &'a [(&'a str, i64)];
/// Files a checkpoint record lists: name, bytes, BLAKE3.
type Listed<'a> = Vec<(&'a str, u64, String)>;

/// A copy of `from` named `name` beside it.
fn copy_as(from: &Path, name: &str) -> PathBuf {
    let to = from.with_file_name(name);
    std::fs::copy(from, &to).unwrap();
    to
}

#[test]
fn nvs_refuses_output_names_that_leave_out_or_clash_before_any_work() {
    let job = NvsJob::new();
    let orbit = &job.trajectories[0];
    // A file beside OUT that a `..` name would overwrite.
    let out = job.path("jobs/out");
    std::fs::create_dir_all(job.path("jobs")).unwrap();
    std::fs::write(job.path("jobs/keep.txt"), "mine").unwrap();
    let dots = copy_as(orbit, "...txt");
    let dot = copy_as(orbit, "..txt");
    let mut cases: Vec<(Vec<PathBuf>, &str)> = vec![(vec![dots.clone()], "`..`"), (vec![dot], "`.`")];
    for reserved in ["nvs.json", "nvs.json.tmp", "trainer.lock", "renders", "finetune"] {
        cases.push((vec![copy_as(orbit, &format!("{reserved}.txt"))], reserved));
    }
    // Two trajectories whose outputs are the same entry of OUT.
    let a = copy_as(orbit, "a.txt");
    cases.push((vec![a.clone(), copy_as(orbit, "a_sheet.png.txt")], "a_sheet.png"));
    cases.push((vec![a.clone(), copy_as(orbit, "a.mp4.txt")], "a.mp4"));
    cases.push((vec![a.clone(), copy_as(&job.trajectories[1], "a.json")], "`a`"));
    cases.push((vec![copy_as(orbit, &format!("{}.txt", "n".repeat(250)))], "255 bytes"));
    for (trajectories, needle) in &cases {
        let output = job.run(&out, trajectories, &[]);
        let named = trajectories.last().unwrap().display().to_string();
        fails_with(&output, &["trajectory", "--trajectory", &named, needle]);
        assert!(!out.exists(), "{named}: nothing is written");
    }
    assert_eq!(std::fs::read_to_string(job.path("jobs/keep.txt")).unwrap(), "mine");
    // A plain name beside them runs (the neighbour that must pass): `a` alone.
    let output = job.run(&out, &[a], &[]);
    assert!(output.status.success(), "{}", stderr(&output));
    assert!(out.join("a.mp4").is_file() && out.join("a/00000.png").is_file());
}

/// A text embedding `[8, 16]` (the tiny transformer's text shape) with `value` at one element.
fn text_embedding_with(path: &Path, value: f64) -> PathBuf {
    let tensor = Tensor::randn([8, 16], (Kind::Float, Device::Cpu));
    let _ = tensor.get(3).get(5).fill_(value);
    Tensor::write_safetensors(&[("encoder_hidden_states", &tensor)], path).unwrap();
    path.to_path_buf()
}

/// The scheduler folder of `base` with `key` set to `value`, as a new base model folder
/// (`scheduler/` only: the VAE is given with --vae).
fn base_with_scheduler(job: &NvsJob, name: &str, key: &str, value: serde_json::Value) -> PathBuf {
    let base = job.path(name);
    std::fs::create_dir_all(base.join("scheduler")).unwrap();
    let file = job.base.join("scheduler/scheduler_config.json");
    let mut json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(file).unwrap()).unwrap();
    json[key] = value;
    std::fs::write(base.join("scheduler/scheduler_config.json"), json.to_string()).unwrap();
    base
}

#[test]
fn nvs_checks_every_argument_and_model_before_its_first_write() {
    let job = NvsJob::new();
    let out = job.path("out");
    let nan_text = text_embedding_with(&job.path("nan_text.safetensors"), f64::NAN);
    let inf_text = text_embedding_with(&job.path("inf_text.safetensors"), f64::INFINITY);
    let lora = job.path("lora.safetensors");
    let a = Tensor::randn([2, 32], (Kind::Float, Device::Cpu));
    let b = Tensor::randn([32, 2], (Kind::Float, Device::Cpu));
    let _ = b.get(1).get(1).fill_(f64::NEG_INFINITY);
    Tensor::write_safetensors(
        &[
            ("transformer.transformer_blocks.0.attn1.to_q.lora_A.weight", &a),
            ("transformer.transformer_blocks.0.attn1.to_q.lora_B.weight", &b),
        ],
        &lora,
    )
    .unwrap();
    let vae = job.base.join("vae");
    let huge =
        base_with_scheduler(&job, "huge_timesteps", "num_train_timesteps", serde_json::json!(1_000_000_000_000i64));
    let beta = base_with_scheduler(&job, "beta_end", "beta_end", serde_json::json!(5.0));
    let spacing = base_with_scheduler(&job, "spacing", "timestep_spacing", serde_json::json!("sideways"));
    let huge_file = huge.join("scheduler/scheduler_config.json").display().to_string();
    let beta_file = beta.join("scheduler/scheduler_config.json").display().to_string();
    let bad_toml = job.path("bad.toml");
    std::fs::write(&bad_toml, std::fs::read_to_string(&job.toml).unwrap().replace("lr = 1e-3", "lr = nan")).unwrap();
    let bad_toml_name = bad_toml.display().to_string();
    let mistyped = job.path("released/transformr");
    let mistyped_name = mistyped.display().to_string();
    let nan_name = nan_text.display().to_string();
    let inf_name = inf_text.display().to_string();
    let lora_name = lora.display().to_string();
    let cases: Vec<(Flags, Vec<&str>)> = vec![
        (vec![&"--init", &mistyped], vec![&mistyped_name]),
        (vec![&"--config", &bad_toml], vec![&bad_toml_name, "optim.lr"]),
        (vec![&"--sample-steps", &"0"], vec!["steps", "0"]),
        (vec![&"--sample-steps", &"1001"], vec!["steps", "1001", "1000"]),
        (vec![&"--frames", &"8"], vec!["frames", "8"]),
        // 1 + 4k, and beyond what any size computed from it can hold: refused, not a panic.
        (vec![&"--frames", &"18446744073709551613"], vec!["frames", "18446744073709551613", "1025"]),
        (vec![&"--guidance", &"nan"], vec!["guidance", "NaN"]),
        (vec![&"--fps", &"0"], vec!["fps", "0"]),
        (vec![&"--fps", &"-1"], vec!["fps", "-1"]),
        (vec![&"--size", &"96x64"], vec!["size", "80x64"]),
        (vec![&"--text-embedding", &nan_text], vec![&nan_name, "encoder_hidden_states", "not finite"]),
        (vec![&"--text-embedding", &inf_text], vec![&inf_name, "encoder_hidden_states", "not finite"]),
        (vec![&"--lora", &lora], vec![&lora_name, "lora_B", "not finite"]),
        (vec![&"--base-model", &huge, &"--vae", &vae], vec![&huge_file, "num_train_timesteps", "1000000000000"]),
        (vec![&"--base-model", &beta, &"--vae", &vae], vec![&beta_file, "beta_end", "5"]),
        (vec![&"--base-model", &spacing, &"--vae", &vae], vec!["timestep_spacing", "sideways"]),
        (
            vec![&"--steps", &"2", &"--config", &job.toml, &"--finetune-trajectories", &"0"],
            vec!["finetune-trajectories"],
        ),
    ];
    for (extra, needles) in &cases {
        let output = job.run(&out, &job.trajectories, extra);
        fails_with(&output, needles);
        assert!(!out.exists(), "{needles:?}: nothing is written");
    }
    // Values the flag parser refuses, naming the flag (exit status 2).
    for (flag, value) in [("--seed", "-1"), ("--steps", "-2"), ("--finetune-trajectories", "-1"), ("--size", "0x0")] {
        let output = job.run(&out, &job.trajectories, &[&flag, &value]);
        let text = stderr(&output);
        assert_eq!(output.status.code(), Some(2), "{text}");
        assert!(text.contains(flag) && text.contains(value) && !text.contains("unexpected argument"), "{text}");
        assert!(!out.exists(), "{flag}: nothing is written");
    }
    // An OUT that is a file is named, and kept.
    let file = job.path("a_file");
    std::fs::write(&file, "mine").unwrap();
    fails_with(&job.run(&file, &job.trajectories, &[]), &["out", &file.display().to_string(), "not a folder"]);
    assert_eq!(std::fs::read_to_string(&file).unwrap(), "mine");
    // A new job refuses to replace what a folder without nvs.json holds.
    let used = job.path("used");
    std::fs::create_dir_all(&used).unwrap();
    std::fs::write(used.join("orbit.mp4"), "mine").unwrap();
    fails_with(&job.run(&used, &job.trajectories, &[]), &["out", "orbit.mp4", "nvs.json"]);
    assert_eq!(std::fs::read_to_string(used.join("orbit.mp4")).unwrap(), "mine");
    assert_eq!(std::fs::read_dir(&used).unwrap().count(), 1, "nothing is written");
    // The corrected command on the same OUT is a new job, not "a job with other settings".
    let output = job.run(&out, &job.trajectories, &[]);
    assert!(output.status.success(), "{}", stderr(&output));
    let record: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("nvs.json")).unwrap()).unwrap();
    assert_eq!(record["complete"], true);
}

#[test]
fn non_finite_weights_are_refused_at_load_and_a_non_finite_sample_is_never_written() {
    let dir = tempfile::tempdir().unwrap();
    let ckpt = tiny_checkpoint(dir.path());
    let cond = frames(&dir.path().join("cond"), 9, (80, 64), &[]);
    let out = dir.path().join("out.mp4");
    let weights_file = ckpt.join("transformer").join(weights::WEIGHTS_NAME);
    let pristine = std::fs::read(&weights_file).unwrap();
    // One NaN in one transformer weight: named, with its file, before any sampling.
    let tensors = read_tensors(&weights_file);
    let name = "transformer_blocks.1.ff.net.0.proj.weight";
    let _ = tensors[name].get(0).get(0).fill_(f64::NAN);
    let list: Vec<(String, Tensor)> = tensors.into_iter().collect();
    Tensor::write_safetensors(&list, &weights_file).unwrap();
    let output = sample(&ckpt, &cond, &out);
    fails_with(&output, &[name, &weights_file.display().to_string(), "1 of", "not finite"]);
    assert!(!out.exists(), "nothing is written");
    std::fs::write(&weights_file, &pristine).unwrap();

    // Finite weights that overflow: the VAE's last layer scaled to f32's edge makes the decoded
    // video inf − inf = NaN. The sample is an error, never a video.
    let vae_file = ckpt.join("vae").join(weights::WEIGHTS_NAME);
    let mut tensors = read_tensors(&vae_file);
    let key = tensors.keys().find(|k| k.starts_with("decoder.conv_out") && k.ends_with("weight")).unwrap().clone();
    let scaled = tensors[&key].sign() * 3e38;
    tensors.insert(key, scaled);
    let list: Vec<(String, Tensor)> = tensors.into_iter().collect();
    Tensor::write_safetensors(&list, &vae_file).unwrap();
    let output = sample(&ckpt, &cond, &out);
    fails_with(&output, &["sampled video", "not finite", "nothing is written"]);
    assert!(!out.exists(), "nothing is written");

    // Library: the text embedding and a LoRA file name the file and tensor.
    let text = text_embedding_with(&dir.path().join("text.safetensors"), f64::NAN);
    let config = CogVideoXTransformer3DModelConfig::tiny();
    let err = trainer::loaders::load_text_embedding(Some(&text), &config, Device::Cpu).unwrap_err().to_string();
    assert!(err.contains("encoder_hidden_states") && err.contains(&text.display().to_string()), "{err}");
    assert!(err.contains("1 of 128 values are not finite") && err.contains("flat index 53"), "{err}");
    let finite = text_embedding_with(&dir.path().join("finite.safetensors"), 1e30);
    let _ = trainer::loaders::load_text_embedding(Some(&finite), &config, Device::Cpu).unwrap();
}

#[test]
fn scheduler_configs_outside_their_ranges_name_file_and_field() {
    use trainer::schedulers::CogVideoXSchedulerConfig;
    let valid = serde_json::to_value(CogVideoXSchedulerConfig::cogvideox_5b()).unwrap();
    let cases: &[(&str, serde_json::Value, &str)] = &[
        ("num_train_timesteps", serde_json::json!(1_000_000_000_000i64), "1000000000000"),
        ("num_train_timesteps", serde_json::json!(0), "0"),
        ("num_train_timesteps", serde_json::json!(1), "two"),
        ("beta_end", serde_json::json!(5.0), "5"),
        ("beta_end", serde_json::json!(1.0), "(0, 1)"),
        ("beta_start", serde_json::json!(0.0), "(0, 1)"),
        ("beta_start", serde_json::json!(-0.1), "-0.1"),
        ("beta_start", serde_json::json!(0.5), "0.012"),
        ("beta_schedule", serde_json::json!("cubic"), "cubic"),
        ("trained_betas", serde_json::json!([0.5, 1.5]), "num_train_timesteps"),
        ("snr_shift_scale", serde_json::json!(0.0), "0"),
        ("steps_offset", serde_json::json!(1000), "1000"),
        ("steps_offset", serde_json::json!(-1), "-1"),
        ("prediction_type", serde_json::json!("noise"), "noise"),
        ("timestep_spacing", serde_json::json!("sideways"), "sideways"),
        ("clip_sample_range", serde_json::json!(-1.0), "-1"),
    ];
    for (key, value, needle) in cases {
        let mut json = valid.clone();
        json[*key] = value.clone();
        let err = CogVideoXSchedulerConfig::from_json_str(&json.to_string(), "sched.json").unwrap_err().to_string();
        let expected = if *key == "beta_start" && *needle == "0.012" { "beta_end" } else { key };
        assert!(err.contains("sched.json") && err.contains(&format!("`{expected}`")), "{key}: {err}");
        assert!(err.contains(needle), "{key} = {value}: `{needle}` not in {err}");
    }
    // Trained βs of the right length but one out of range.
    let mut json = valid.clone();
    json["num_train_timesteps"] = serde_json::json!(3);
    json["rescale_betas_zero_snr"] = serde_json::json!(false);
    json["trained_betas"] = serde_json::json!([0.1, 1.5, 0.2]);
    let err = CogVideoXSchedulerConfig::from_json_str(&json.to_string(), "sched.json").unwrap_err().to_string();
    assert!(err.contains("`trained_betas`") && err.contains("value 1") && err.contains("1.5"), "{err}");
    json["trained_betas"] = serde_json::json!([0.1, 0.15, 0.2]);
    CogVideoXSchedulerConfig::from_json_str(&json.to_string(), "sched.json").unwrap();

    // `trainer sample` reads it before any model work; a training config when it is loaded.
    let dir = tempfile::tempdir().unwrap();
    let ckpt = tiny_checkpoint(dir.path());
    std::fs::create_dir_all(ckpt.join("scheduler")).unwrap();
    let file = ckpt.join("scheduler/scheduler_config.json");
    let mut json = valid.clone();
    json["num_train_timesteps"] = serde_json::json!(1_000_000_000_000i64);
    std::fs::write(&file, json.to_string()).unwrap();
    let cond = frames(&dir.path().join("cond"), 9, (80, 64), &[]);
    let out = dir.path().join("out.mp4");
    fails_with(&sample(&ckpt, &cond, &out), &[&file.display().to_string(), "num_train_timesteps"]);
    assert!(!out.exists());
    let toml = tiny_toml(
        dir.path(),
        "sched",
        "vae = \"tiny\"",
        &format!("vae = \"tiny\"\nscheduler = {:?}", ckpt.join("scheduler")),
    );
    let err = PretrainConfig::from_toml_file(&toml).unwrap_err().to_string();
    assert!(err.contains(&file.display().to_string()) && err.contains("`num_train_timesteps`"), "{err}");
}

#[test]
fn seed_and_other_negative_values_are_refused_naming_the_flag() {
    let dir = tempfile::tempdir().unwrap();
    let ckpt = tiny_checkpoint(dir.path());
    let cond = frames(&dir.path().join("cond"), 9, (80, 64), &[]);
    let out = dir.path().join("out.mp4");
    for (flag, value) in [("--seed", "-1"), ("--steps", "-3"), ("--frames", "-9")] {
        let output = run(&[&"sample", &"--ckpt", &ckpt, &"--cond", &cond, &"--out", &out, &flag, &value]);
        let text = stderr(&output);
        assert_eq!(output.status.code(), Some(2), "{text}");
        assert!(text.contains(flag) && text.contains(value) && !text.contains("unexpected argument"), "{text}");
    }
    assert!(!out.exists());
}

#[test]
fn transformer_configs_whose_sizes_overflow_name_the_config_and_fields() {
    let dir = tempfile::tempdir().unwrap();
    let ckpt = tiny_checkpoint(dir.path());
    let config_path = ckpt.join("transformer/config.json");
    let original: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&config_path).unwrap()).unwrap();
    let cases: &[(Fields, &[&str])] = &[
        (
            &[("num_attention_heads", 1 << 32), ("attention_head_dim", 1 << 32)],
            &["num_attention_heads", "attention_head_dim"],
        ),
        (
            &[("num_attention_heads", 4096), ("attention_head_dim", 4096)],
            &["num_attention_heads", "attention_head_dim"],
        ),
        (&[("num_layers", i64::MAX)], &["num_layers"]),
        (
            &[("sample_frames", 1 << 19), ("sample_height", 1 << 19), ("sample_width", 1 << 19)],
            &["sample_frames", "positional table"],
        ),
    ];
    let cond = frames(&dir.path().join("cond"), 9, (80, 64), &[]);
    let out = dir.path().join("out.mp4");
    for (fields, needles) in cases {
        let mut json = original.clone();
        for (key, value) in *fields {
            json[*key] = serde_json::json!(value);
        }
        std::fs::write(&config_path, json.to_string()).unwrap();
        let err = CogVideoXTransformer3DModelConfig::from_json_file(&config_path).unwrap_err().to_string();
        assert!(err.contains(&config_path.display().to_string()), "{fields:?}: {err}");
        for needle in *needles {
            assert!(err.contains(needle), "{fields:?}: `{needle}` not in {err}");
        }
        let output = sample(&ckpt, &cond, &out);
        fails_with(&output, &[&config_path.display().to_string(), needles[0]]);
        assert!(!stderr(&output).contains("libtorch") && !out.exists(), "{}", stderr(&output));
    }
}

#[test]
fn an_impossible_held_out_split_names_the_config_file() {
    let dir = tempfile::tempdir().unwrap();
    let shards = super::pretrain::pairs(dir.path());
    let config =
        tiny_toml(dir.path(), "split", "[loop]", "[validation]\nholdout_fraction = 1e-12\npairs = 1\n\n[loop]");
    let out = dir.path().join("run");
    let output = run(&[&"pretrain", &"--config", &config, &"--shards", &shards, &"--out", &out]);
    fails_with(&output, &[&config.display().to_string(), "validation.holdout_fraction", "holds out none"]);
    assert!(!out.exists(), "nothing is written");
}

/// Writes `run/checkpoints/<folder>/` with `files` (name → content) and a `state.json` of
/// `step` listing `listed` (name → the bytes and digest it claims).
fn checkpoint_folder(
    run: &Path,
    folder: &str,
    step: u64,
    files: &[(&str, &[u8])],
    listed: &[(&str, u64, String)],
) -> PathBuf {
    use trainer::training::{FileRecord, TrainState};
    let dir = run.join("checkpoints").join(folder);
    std::fs::create_dir_all(&dir).unwrap();
    for (name, bytes) in files {
        std::fs::write(dir.join(name), bytes).unwrap();
    }
    let state = TrainState {
        step,
        data_position: Default::default(),
        seed: 0,
        layout: None,
        files: listed
            .iter()
            .map(|(name, bytes, blake3)| (name.to_string(), FileRecord { bytes: *bytes, blake3: blake3.clone() }))
            .collect(),
    };
    std::fs::write(dir.join("state.json"), serde_json::to_string(&state).unwrap()).unwrap();
    dir
}

fn digest(bytes: &[u8]) -> String {
    blake3::hash(bytes).to_hex().to_string()
}

#[test]
fn checkpoint_records_name_only_regular_files_of_their_folder_and_their_own_step() {
    use trainer::training::checkpoint::{newest_intact, read_state};
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let weights: &[u8] = b"weights";
    // The intact one the resume falls back to.
    let intact = checkpoint_folder(&run, "step-00000001", 1, &[("w.bin", weights)], &[("w.bin", 7, digest(weights))]);
    std::fs::write(dir.path().join("outside.bin"), weights).unwrap();
    // Newer ones, each damaged by its record alone: a device, paths out of the folder, a link
    // to a device and one to a file outside, and a step that is not the folder's.
    let cases: Vec<(&str, Listed, u64, &str)> = vec![
        ("step-00000002", vec![("/dev/zero", 0, digest(b""))], 2, "/dev/zero"),
        ("step-00000003", vec![("../../../outside.bin", 7, digest(weights))], 3, "outside.bin"),
        ("step-00000004", vec![("sub/../../step-00000001/w.bin", 7, digest(weights))], 4, "w.bin"),
        ("step-00000005", vec![("zero", 0, digest(b""))], 5, "not a regular file"),
        ("step-00000006", vec![("outside", 7, digest(weights))], 6, "not a regular file"),
        ("step-00000007", vec![("w.bin", 7, digest(weights))], 9, "step-00000007"),
    ];
    for (folder, listed, step, _) in &cases {
        let files: &[(&str, &[u8])] = if listed[0].0 == "w.bin" { &[("w.bin", weights)] } else { &[] };
        checkpoint_folder(&run, folder, *step, files, listed);
    }
    std::os::unix::fs::symlink("/dev/zero", run.join("checkpoints/step-00000005/zero")).unwrap();
    std::os::unix::fs::symlink(dir.path().join("outside.bin"), run.join("checkpoints/step-00000006/outside")).unwrap();
    for (folder, _, _, needle) in &cases {
        let folder = run.join("checkpoints").join(folder);
        let problems = match read_state(&folder) {
            Err(e) => vec![e.to_string()],
            Ok(state) => trainer::training::checkpoint::check_files(&folder, &state, true, (0, 1)),
        };
        assert!(problems.iter().any(|p| p.contains(needle)), "{}: {problems:?}", folder.display());
    }
    // The resume skips them all (without reading a device) for the intact one.
    let (sender, receiver) = std::sync::mpsc::channel();
    let watched = run.clone();
    std::thread::spawn(move || sender.send(newest_intact(&watched, None).map(|found| found.map(|(d, s)| (d, s.step)))));
    let found = receiver.recv_timeout(std::time::Duration::from_secs(60)).expect("the resume check hangs").unwrap();
    assert_eq!(found, Some((intact, 1)));
}

#[test]
fn a_signal_while_nothing_checkpointable_runs_ends_the_process_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let shards = super::pretrain::pairs(dir.path());
    let config = tiny_toml(dir.path(), "ok", "steps = 20", "steps = 20");
    let run = dir.path().join("run");
    // A checkpoint whose one listed file takes a while to hash: a large sparse file (its digest
    // is wrong, so the resume would fail after hashing it, exit 1).
    let folder = run.join("checkpoints/step-00000001");
    checkpoint_folder(&run, "step-00000001", 1, &[], &[("big.bin", 32 << 30, digest(b"not it"))]);
    let big = std::fs::File::create(folder.join("big.bin")).unwrap();
    big.set_len(32 << 30).unwrap();
    let mut job = Command::new(env!("CARGO_BIN_EXE_trainer"))
        .args(["pretrain".as_ref(), "--config".as_ref(), config.as_os_str(), "--shards".as_ref(), shards.as_os_str()])
        .args(["--out".as_ref(), run.as_os_str(), "--resume".as_ref()])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // Signalled once the resume check reads the file.
    let fd_dir = PathBuf::from(format!("/proc/{}/fd", job.id()));
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
    let reading = || {
        std::fs::read_dir(&fd_dir)
            .into_iter()
            .flatten()
            .flatten()
            .any(|e| std::fs::read_link(e.path()).is_ok_and(|target| target.ends_with("big.bin")))
    };
    while !reading() {
        assert!(job.try_wait().unwrap().is_none(), "the job ended before reading the checkpoint");
        assert!(std::time::Instant::now() < deadline, "the resume check never read the file");
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    let signalled = std::time::Instant::now();
    Command::new("kill").args(["-TERM", &job.id().to_string()]).status().unwrap();
    let status = job.wait().unwrap();
    let took = signalled.elapsed();
    // 128 + SIGTERM, from the handler: not the preemption path, and not after the hash.
    assert_eq!(status.code(), Some(143), "{status:?}");
    assert!(took < std::time::Duration::from_secs(5), "the signal waited {took:?} for the hash");
}

/// A benchmark ROOT whose one scene is unreadable (its second camera's cameras.json cut), with
/// the tiny released models: `(dir, root, transformer, base)`.
fn unreadable_benchmark_root() -> (tempfile::TempDir, PathBuf, PathBuf, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let (transformer, base, _) = super::nvs::released_layout(dir.path());
    let root = dir.path().join("root");
    let config = datagen::synth::SynthConfig { width: 80, height: 64, frames: 5, ..Default::default() };
    let rig = datagen::synth::CameraRig { cameras: 2, spacing_deg: 10.0 };
    datagen::synth::write_multiview(&config, &rig, &root.join("broken"), |_| {}).unwrap();
    let cameras = root.join("broken/cam01/cameras.json");
    let text = std::fs::read_to_string(&cameras).unwrap();
    std::fs::write(&cameras, &text[..text.len() / 2]).unwrap();
    (dir, root, transformer, base)
}

#[test]
fn benchmark_refuses_bad_flags_before_recording_and_fails_when_nothing_is_scored() {
    let (dir, root, transformer, base) = unreadable_benchmark_root();
    let out = dir.path().join("run");
    let benchmark = |extra: &[&str]| {
        let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_trainer"));
        cmd.args(["benchmark", "--dataset", "kubric4d", "--steps", "0", "--sample-steps", "1", "--frames", "5"]);
        cmd.arg("--root").arg(&root).arg("--init").arg(&transformer).arg("--base-model").arg(&base);
        cmd.arg("--out").arg(&out).args(extra);
        cmd.output().unwrap()
    };
    // A size of no pixels is refused by the parser, naming the flag, before OUT exists.
    let refused = benchmark(&["--eval-size", "0x0"]);
    let text = stderr(&refused);
    assert_eq!(refused.status.code(), Some(2), "{text}");
    assert!(text.contains("--eval-size") && text.contains("0x0"), "{text}");
    assert!(!out.exists(), "a refused flag leaves no record behind");

    // Every scene failing is a failure with each scene's reason, not "0/1 scenes" and exit 0.
    let failed = benchmark(&["--eval-size", "80x64"]);
    let text = stderr(&failed);
    assert!(!failed.status.success(), "{text}");
    assert!(
        text.contains("no scene could be scored") && text.contains("broken: ") && text.contains("cameras.json"),
        "{text}"
    );

    // Other settings are refused naming each change once.
    let changed = benchmark(&["--eval-size", "80x64", "--seed", "7"]);
    let text = stderr(&changed);
    assert!(!changed.status.success() && text.contains("other settings"), "{text}");
    assert_eq!(text.matches("seed: 42 → 7").count(), 1, "{text}");
}
