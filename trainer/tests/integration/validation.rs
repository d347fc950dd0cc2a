//! Held-out validation while training: videos held out of the training shards are never in a
//! training batch, none of their clips, validation shards that are also training shards are refused, and a run
//! logs PSNR, SSIM and LPIPS (whole frames and co-visible pixels) of a fixed set of held-out
//! pairs to `metrics.jsonl` and TensorBoard; on 2 ranks the pairs are shared out and the means
//! are those of 1 rank.

use std::path::{Path, PathBuf};

use trainer::training::data::{DataConfig, DataPosition, ShardLoader};
use trainer::training::validation::{ValidationMetrics, is_held_out, split_training_clips};
use trainer::training::{PretrainConfig, read_metrics, read_validation};

use super::distributed::{config, pretrain_args, read_events, torchrun};
use super::parity::assert_success;

/// Pairs of a second synthetic video (2 clips), for `[validation] shards`.
fn validation_shards(dir: &Path) -> PathBuf {
    super::pretrain::video_pairs(&dir.join("held-out"), "heldout", 13, 9, 1)
}

/// The smallest fraction (in steps of 0.05) that holds out exactly one of the videos of `ids`.
fn fraction_holding_out_one_video(ids: &[String]) -> f64 {
    let video = |id: &String| id.rsplit_once('/').unwrap().0.to_string();
    (1..20)
        .map(|k| f64::from(k) * 0.05)
        .find(|&f| {
            let held: std::collections::BTreeSet<String> =
                ids.iter().filter(|id| is_held_out(id, f)).map(video).collect();
            held.len() == 1
        })
        .expect("some fraction holds out exactly one video")
}

/// `pretrain_args` with a second shard folder after the first.
fn pretrain_args_two(config: &Path, shards: [&Path; 2], out: &Path) -> Vec<std::ffi::OsString> {
    let mut args = pretrain_args(config, shards[0], out, false);
    let at = args.iter().position(|a| a == "--shards").unwrap() + 2;
    args.insert(at, shards[1].into());
    args
}

fn validation_config(dir: &Path, name: &str, section: &str) -> PathBuf {
    let path = config(dir, name, 4, 0, super::distributed::LR);
    let text = std::fs::read_to_string(&path)
        .unwrap()
        .replace("validate_every = 3", "validate_every = 2")
        .replace("validation_steps = 1", "validation_steps = 2");
    std::fs::write(&path, format!("{text}\n{section}")).unwrap();
    path
}

#[test]
fn held_out_videos_are_never_trained_on_and_a_run_measures_them() {
    let dir = tempfile::tempdir().unwrap();
    // Two training videos: 3 clips of dataset `synth`, 2 of dataset `second`.
    let shards = super::pretrain::pairs(dir.path());
    let second = super::pretrain::video_pairs(&dir.path().join("second"), "second", 13, 7, 1);
    let held_out_shards = validation_shards(dir.path());
    let ids: Vec<String> =
        [&shards, &second].iter().flat_map(|s| schemas::clip_ids(&s.join("seq.parquet")).unwrap()).collect();
    assert_eq!(ids.len(), 5);
    let fraction = fraction_holding_out_one_video(&ids);
    let held_ids: Vec<&String> = ids.iter().filter(|id| is_held_out(id, fraction)).collect();
    let held_video = held_ids[0].rsplit_once('/').unwrap().0;
    assert!(held_ids.len() >= 2, "a video is held out with all its clips: {held_ids:?}");
    let lpips = super::eval_parity::goldens().join("lpips_alex.safetensors");
    let section = format!(
        "[validation]\nshards = [{:?}]\nholdout_fraction = {fraction}\npairs = 3\nlpips_weights = {:?}\n",
        held_out_shards.display().to_string(),
        lpips.display().to_string()
    );
    let config_path = validation_config(dir.path(), "validated", &section);

    // The training clips leave the held-out one out, over whole epochs of batches.
    let config = PretrainConfig::from_toml_file(&config_path).unwrap();
    let training_shards = [shards.clone(), second.clone()];
    let (training, held) = split_training_clips(&config, &training_shards).unwrap();
    let trained = ids.len() - held_ids.len();
    assert_eq!((training.len(), held.as_ref().map(|h| h.len())), (trained, Some(held_ids.len() + 2)));
    let data = DataConfig { batch_size: 1, ..config.data.clone() };
    let mut loader = ShardLoader::new(std::sync::Arc::new(training), data, DataPosition::default()).unwrap();
    for _ in 0..3 * trained {
        let batch = loader.next_batch().unwrap();
        assert!(!batch.provenance[0].starts_with(&format!("{held_video}/")), "{held_video} was trained on");
    }
    // Validation shards that are training shards would be trained on: refused.
    let mut overlapping = config.clone();
    overlapping.validation.as_mut().unwrap().shards = vec![shards.clone()];
    let refused = split_training_clips(&overlapping, &training_shards).unwrap_err().to_string();
    assert!(refused.contains("validation.shards") && refused.contains("training shard"), "{refused}");

    // One rank: a validation line at steps 2 and 4, every metric present and in range.
    let run = dir.path().join("one");
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_trainer"))
        .args(pretrain_args_two(&config_path, [&shards, &second], &run))
        .output()
        .unwrap();
    assert_success(&output);
    let err = String::from_utf8_lossy(&output.stderr);
    let counts = format!("training on {trained} clips; {} held out for validation", held_ids.len() + 2);
    assert!(err.contains(&counts), "{err}");
    let measured = read_validation(&run).unwrap();
    assert_eq!(measured.iter().map(|(step, _)| *step).collect::<Vec<_>>(), vec![2, 4]);
    for (step, m) in &measured {
        println!("validation at step {step}: {m:?}");
        assert_eq!(m.pairs, 3);
        let all = [m.psnr, m.ssim, m.psnr_covisible, m.ssim_covisible, m.lpips, m.lpips_covisible];
        assert!(all.iter().all(|v| v.is_some_and(f64::is_finite)), "{m:?}");
        assert!((-1.0..=1.0).contains(&m.ssim.unwrap()) && m.lpips.unwrap() > 0.0, "{m:?}");
    }
    assert_eq!(read_metrics(&run).unwrap().len(), 4, "step lines read past the validation lines");
    assert!(run.join("samples/step-00000004/contact_sheet.png").is_file());

    // TensorBoard holds the same values (tensorboard's own reader).
    let read = read_events(&run, dir.path());
    for (tag, value) in [
        ("validation/psnr", (|m: &ValidationMetrics| m.psnr) as fn(&ValidationMetrics) -> Option<f64>),
        ("validation/ssim_covisible", |m| m.ssim_covisible),
        ("validation/lpips_covisible", |m| m.lpips_covisible),
    ] {
        let series = read["scalars"][tag].as_array().unwrap_or_else(|| panic!("{tag} missing: {read}"));
        assert_eq!(series.len(), measured.len(), "{tag}");
        for (event, (step, m)) in series.iter().zip(&measured) {
            assert_eq!(event[0].as_u64().unwrap(), *step);
            assert_eq!(event[1].as_f64().unwrap() as f32, value(m).unwrap() as f32, "{tag}");
        }
    }

    // Two ranks share the pairs (rank 0 two, rank 1 one) and report the means over all three:
    // those of one rank, up to the weights' fp32 reduction-order differences.
    let ranks = dir.path().join("two");
    assert_success(&torchrun(2, &pretrain_args_two(&config_path, [&shards, &second], &ranks), 29581).output().unwrap());
    let shared = read_validation(&ranks).unwrap();
    assert_eq!(shared.len(), measured.len());
    for ((step, a), (_, b)) in shared.iter().zip(&measured) {
        println!("2 ranks at step {step}: {a:?}");
        assert_eq!(a.pairs, 3);
        for (x, y) in [(a.psnr, b.psnr), (a.ssim_covisible, b.ssim_covisible), (a.lpips, b.lpips)] {
            let (x, y) = (x.unwrap(), y.unwrap());
            assert!((x - y).abs() <= 1e-5 * y.abs(), "step {step}: {x} vs {y}");
        }
    }
}
