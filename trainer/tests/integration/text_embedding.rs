//! The text input: `scripts/encode_prompt.py` writes what diffusers' CogVideoX prompt encoder
//! computes (on a tiny T5 and a tokenizer trained at test time) and refuses incomplete or
//! mismatched model folders, and a transformer of the released models' T5-XXL text shape refuses
//! to sample or train on zeros unless asked.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

use trainer::models::cogvideox::cogvideox_transformer_3d::CogVideoXTransformer3DModelConfig;
use trainer::tch::{Device, Kind, Tensor};

use super::parity::{assert_success, python, read_tensors, repo_root, run_script};

/// Output of `scripts/goldens_text_embedding.py` (the tiny text stack and its reference
/// embeddings), generated once per test binary; read only, tests write beside it.
fn text_stack() -> &'static Path {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    DIR.get_or_init(|| run_script("goldens_text_embedding.py")).path()
}

fn encode_prompt(model: &Path, prompt: &str, dtype: &str, out: &Path) {
    let output = Command::new(python())
        .arg(repo_root().join("scripts/encode_prompt.py"))
        .arg("--model")
        .arg(model)
        .args(["--prompt", prompt, "--dtype", dtype, "--device", "cpu", "--out"])
        .arg(out)
        .output()
        .unwrap();
    assert_success(&output);
}

#[test]
fn encode_prompt_equals_the_cogvideox_prompt_encoder() {
    let dir = tempfile::tempdir().unwrap();
    let model = text_stack();
    let prompts: Vec<String> =
        serde_json::from_str(&std::fs::read_to_string(model.join("prompts.json")).unwrap()).unwrap();
    let reference = read_tensors(&model.join("reference.safetensors"));
    // The empty prompt (CogNVS's), a short one, and one truncated at 226 tokens.
    for (i, prompt) in prompts.iter().enumerate() {
        let out = dir.path().join(format!("prompt_{i}.safetensors"));
        encode_prompt(model, prompt, "fp32", &out);
        let ours = &read_tensors(&out)["encoder_hidden_states"];
        let theirs = &reference[&format!("prompt_{i}")];
        assert_eq!(ours.size(), [226, 32]);
        assert!(ours.equal(theirs), "prompt {i}: {:?}", (ours - theirs).abs().max());
        if i == 0 {
            // Not zeros: the end-of-sequence token and padding run through T5.
            assert!(ours.abs().sum(Kind::Double).double_value(&[]) > 1.0);
            // The file is what the trainer reads for a transformer of this text shape.
            let config = CogVideoXTransformer3DModelConfig {
                max_text_seq_length: 226,
                text_embed_dim: 32,
                ..CogVideoXTransformer3DModelConfig::tiny()
            };
            let loaded = trainer::loaders::load_text_embedding(Some(&out), &config, Device::Cpu).unwrap();
            assert!(loaded.squeeze_dim(0).equal(theirs));
        }
    }
    // bf16, as the public pipeline encodes on the GPU: within bf16 rounding of the f32 result.
    let bf16 = dir.path().join("bf16.safetensors");
    encode_prompt(model, "", "bf16", &bf16);
    let ours = read_tensors(&bf16)["encoder_hidden_states"].to_kind(Kind::Float);
    let (abs, rel) = super::parity::errors(&ours, &reference["prompt_0"]);
    assert!(rel < 0.05, "bf16 encoding: max abs {abs}, rel {rel}");
}

/// `encode_prompt.py` with the text encoder and tokenizer folders given apart.
fn encode_with(encoder: &Path, tokenizer: &Path, out: &Path) -> Output {
    Command::new(python())
        .arg(repo_root().join("scripts/encode_prompt.py"))
        .arg("--text-encoder")
        .arg(encoder)
        .arg("--tokenizer")
        .arg(tokenizer)
        .args(["--prompt", "a dog runs", "--dtype", "fp32", "--device", "cpu", "--out"])
        .arg(out)
        .output()
        .unwrap()
}

/// Copies the files of folder `from` into a new folder `to`.
fn copy_folder(from: &Path, to: &Path) -> PathBuf {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        std::fs::copy(entry.path(), to.join(entry.file_name())).unwrap();
    }
    to.to_path_buf()
}

#[test]
fn encode_prompt_refuses_incomplete_or_mismatched_folders_naming_what_is_missing() {
    let dir = tempfile::tempdir().unwrap();
    let model = text_stack();
    let (encoder, tokenizer) = (model.join("text_encoder"), model.join("tokenizer"));
    let out = dir.path().join("out.safetensors");
    // The complete pair encodes.
    assert_success(&encode_with(&encoder, &tokenizer, &out));
    std::fs::remove_file(&out).unwrap();

    let empty = dir.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    // A tokenizer folder without its vocabulary (it loads as one that knows no word).
    let no_vocabulary = copy_folder(&tokenizer, &dir.path().join("no_vocabulary"));
    std::fs::remove_file(no_vocabulary.join("spiece.model")).unwrap();
    // Another tokenizer's size: 100 extra ids make 140 tokens for the encoder's 40 rows.
    let other = copy_folder(&tokenizer, &dir.path().join("other_tokenizer"));
    std::fs::write(
        other.join("tokenizer_config.json"),
        r#"{"tokenizer_class": "T5Tokenizer", "model_max_length": 226, "extra_ids": 100}"#,
    )
    .unwrap();
    // An encoder without weights, of another model type, and with a weight missing.
    let no_weights = copy_folder(&encoder, &dir.path().join("no_weights"));
    std::fs::remove_file(no_weights.join("model.safetensors")).unwrap();
    let not_t5 = copy_folder(&encoder, &dir.path().join("not_t5"));
    let mut config: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(not_t5.join("config.json")).unwrap()).unwrap();
    config["model_type"] = "bert".into();
    std::fs::write(not_t5.join("config.json"), config.to_string()).unwrap();
    let partial = copy_folder(&encoder, &dir.path().join("partial"));
    let mut tensors = read_tensors(&partial.join("model.safetensors"));
    let dropped = tensors.keys().find(|k| k.contains("block.1.")).unwrap().clone();
    tensors.remove(&dropped);
    let kept: Vec<(String, Tensor)> = tensors.into_iter().collect();
    Tensor::write_safetensors(&kept, partial.join("model.safetensors")).unwrap();

    let cases: [(&Path, &Path, &[&str]); 7] = [
        (&encoder, &empty, &["tokenizer folder", "empty", "spiece.model"]),
        (&encoder, &no_vocabulary, &["no_vocabulary", "no vocabulary", "spiece.model"]),
        (&encoder, &other, &["other_tokenizer", "140 tokens", "vocab_size 40"]),
        (&empty, &tokenizer, &["text encoder folder", "empty", "config.json"]),
        (&no_weights, &tokenizer, &["no_weights", "no weights", "model.safetensors"]),
        (&not_t5, &tokenizer, &["not_t5/config.json", "model_type", "bert"]),
        (&partial, &tokenizer, &["partial", "weights missing", &dropped]),
    ];
    for (encoder, tokenizer, needles) in cases {
        let output = encode_with(encoder, tokenizer, &out);
        let text = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success(), "{} + {} was accepted: {text}", encoder.display(), tokenizer.display());
        for needle in needles {
            assert!(text.contains(needle), "`{needle}` not in:\n{text}");
        }
        assert!(!out.exists(), "nothing is written");
    }
}

/// A transformer folder of the released text shape (226 × 4096) but tiny otherwise, with a tiny
/// VAE beside it (`DIR/transformer`, `DIR/vae`).
fn t5_xxl_shaped_checkpoint(dir: &Path) -> PathBuf {
    let ckpt = dir.join("ckpt");
    let config = CogVideoXTransformer3DModelConfig {
        max_text_seq_length: 226,
        text_embed_dim: 4096,
        ..CogVideoXTransformer3DModelConfig::tiny()
    };
    super::parity::save_tiny_models(&config, &ckpt.join("transformer"), &ckpt.join("vae"));
    ckpt
}

fn trainer(args: &[&dyn AsRef<std::ffi::OsStr>]) -> Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_trainer"));
    for a in args {
        cmd.arg(a);
    }
    cmd.output().unwrap()
}

fn refused_naming_the_fix(output: &Output) {
    let text = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success(), "zeros were accepted: {text}");
    for needle in ["T5-XXL", "226 × 4096", "--text-embedding", "scripts/encode_prompt.py", "--zero-text-embedding"] {
        assert!(text.contains(needle), "`{needle}` not in:\n{text}");
    }
}

#[test]
fn a_t5_xxl_shaped_transformer_refuses_zero_text_unless_asked() {
    let dir = tempfile::tempdir().unwrap();
    let ckpt = t5_xxl_shaped_checkpoint(dir.path());
    let cond = dir.path().join("cond");
    std::fs::create_dir_all(&cond).unwrap();
    for i in 0..9 {
        image::RgbImage::from_fn(80, 64, |x, y| image::Rgb([x as u8 * 3, y as u8 * 4, i * 20]))
            .save(cond.join(format!("{i:05}.png")))
            .unwrap();
    }
    let out = dir.path().join("out");
    let sample = |extra: &[&dyn AsRef<std::ffi::OsStr>]| {
        let mut args: Vec<&dyn AsRef<std::ffi::OsStr>> =
            vec![&"sample", &"--ckpt", &ckpt, &"--cond", &cond, &"--out", &out, &"--steps", &"1", &"--frames", &"9"];
        args.extend_from_slice(extra);
        trainer(&args)
    };
    refused_naming_the_fix(&sample(&[]));
    assert!(!out.exists(), "nothing is written");
    assert_success(&sample(&[&"--zero-text-embedding"]));
    // With an embedding of the right shape it samples (and a wrong shape is a named error).
    let text = dir.path().join("text.safetensors");
    Tensor::write_safetensors(
        &[("encoder_hidden_states", &Tensor::randn([226, 4096], (Kind::Float, Device::Cpu)))],
        &text,
    )
    .unwrap();
    assert_success(&sample(&[&"--text-embedding", &text]));

    // Training refuses too, before anything is written, and accepts the explicit switch.
    let config = dir.path().join("train.toml");
    let write_config = |extra: &str| {
        std::fs::write(
            &config,
            format!(
                "[model]\ntransformer = \"{}\"\nvae = \"{}\"\n{extra}\n[data]\nframes = 9\nheight = 64\nwidth = 80\n\
                 batch_size = 1\nseed = 0\n[loop]\nsteps = 1\n",
                ckpt.join("transformer").display(),
                ckpt.join("vae").display()
            ),
        )
        .unwrap()
    };
    write_config("");
    let shards = dir.path().join("no_shards_needed_before_the_check");
    std::fs::create_dir_all(&shards).unwrap();
    let run = dir.path().join("run");
    let pretrain = trainer(&[&"pretrain", &"--config", &config, &"--shards", &shards, &"--out", &run]);
    refused_naming_the_fix(&pretrain);
    assert!(!run.exists(), "nothing is written");
    write_config("zero_text_embedding = true");
    let pretrain = trainer(&[&"pretrain", &"--config", &config, &"--shards", &shards, &"--out", &run]);
    let text = String::from_utf8_lossy(&pretrain.stderr);
    assert!(!text.contains("T5-XXL"), "the switch lets the run past the check: {text}");
}
