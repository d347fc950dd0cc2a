//! `datagen build` end to end on generated SA-V and sequence-folder trees: planted bad inputs
//! are recorded and do not stop the run; kill -9 at several points then resume gives exactly the
//! pairs of an uninterrupted run; two workers together give the single-worker corpus.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Command;

use datagen::synth::{SynthConfig, write_sequence};
use schemas::InputStatus;

fn datagen() -> Command {
    Command::new(env!("CARGO_BIN_EXE_datagen"))
}

/// Column-major run lengths of a mask (the plain COCO RLE form SA-V tools also accept).
fn rle_runs(mask: &image::GrayImage, id: u8) -> Vec<u64> {
    let (w, h) = mask.dimensions();
    let mut runs = vec![0u64];
    let mut current = false;
    for x in 0..w {
        for y in 0..h {
            let on = mask.get_pixel(x, y).0[0] == id;
            if on != current {
                runs.push(0);
                current = on;
            }
            *runs.last_mut().unwrap() += 1;
        }
    }
    runs
}

/// An SA-V tree of `count` synthetic videos with reconstructions beside it, plus a tree of
/// sequence folders; returns (corpus config path, output dir).
fn make_corpus(root: &Path, count: usize) -> (PathBuf, PathBuf) {
    let sav = root.join("sav_train/sav_000");
    std::fs::create_dir_all(&sav).unwrap();
    for i in 0..count {
        let id = format!("sav_{i:06}");
        let scene = root.join("scenes").join(&id);
        let config = SynthConfig { width: 48, height: 32, frames: 9, seed: i as u64, ..SynthConfig::default() };
        write_sequence(&config, &scene, |_| {}).unwrap();
        std::fs::copy(scene.join("gt_rgb.mp4"), sav.join(format!("{id}.mp4"))).unwrap();
        let recon = root.join("recon").join(&id).join("cam_info");
        std::fs::create_dir_all(&recon).unwrap();
        for name in ["megasam_depth.npy", "megasam_intrinsics.npy", "megasam_c2ws.npy"] {
            std::fs::copy(scene.join("cam_info").join(name), recon.join(name)).unwrap();
        }
        // Masklets every 4th frame (SA-V's 6 fps of 24 fps), objects 1..=3.
        let masklet: Vec<Vec<serde_json::Value>> = (0..9)
            .step_by(4)
            .map(|frame| {
                let mask = image::open(scene.join(format!("masks/{frame:05}.png"))).unwrap().to_luma8();
                (1..=3).map(|id| serde_json::json!({"size": [32, 48], "counts": rle_runs(&mask, id)})).collect()
            })
            .collect();
        let json = serde_json::json!({"video_id": id, "video_frame_count": 9.0, "masklet": masklet});
        std::fs::write(sav.join(format!("{id}_manual.json")), json.to_string()).unwrap();
    }
    let config = root.join("corpus.toml");
    let out = root.join("corpus");
    std::fs::write(
        &config,
        format!(
            "seed = 5\ntrajectories = 2\n\n[[sources]]\ndataset = \"sav\"\nroot = \"{}\"\nreconstructions = \"{}/recon/{{video_id}}\"\n\n\
             [[sources]]\ndataset = \"sequences\"\nroot = \"{}/sequences\"\n\n[output]\ndir = \"{}\"\nshard_bytes = 150000\n\n[pairs.clip]\nlength = 5\nstride = 4\n",
            root.join("sav_train").display(),
            root.display(),
            root.display(),
            out.display()
        ),
    )
    .unwrap();
    std::fs::create_dir_all(root.join("sequences")).unwrap();
    (config, out)
}

/// (clip id, BLAKE3 of every encoded frame and mask) of every clip in finished shards.
fn corpus_content(out: &Path) -> BTreeSet<(String, String)> {
    let mut content = BTreeSet::new();
    for entry in std::fs::read_dir(out).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        assert!(!name.contains(".tmp-"), "temporary file visible: {name}");
        if name.starts_with("shard-") && name.ends_with(".parquet") {
            assert!(schemas::is_finished(&path), "{name} visible without its stats marker");
            for clip in schemas::read_shard(&path).unwrap() {
                let mut hasher = blake3::Hasher::new();
                for bytes in clip.frames.iter().chain(clip.trajectories.iter().flat_map(|t| t.covisible_mask.iter())) {
                    hasher.update(bytes);
                }
                assert!(
                    content.insert((clip.clip_id.clone(), hasher.finalize().to_hex().to_string())),
                    "duplicate {}",
                    clip.clip_id
                );
            }
        }
    }
    content
}

fn run_build(config: &Path, extra: &[&str]) {
    let output = datagen().arg("build").arg("--config").arg(config).args(extra).output().unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
}

#[test]
fn planted_bad_inputs_are_recorded_and_good_ones_produce_pairs() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let (config, out) = make_corpus(root, 7);
    let sav = root.join("sav_train/sav_000");
    // 1: truncated video.
    let video = sav.join("sav_000001.mp4");
    let bytes = std::fs::read(&video).unwrap();
    std::fs::write(&video, &bytes[..bytes.len() / 3]).unwrap();
    // 2: missing reconstruction.
    std::fs::remove_dir_all(root.join("recon/sav_000002")).unwrap();
    // 3: NaN-only depth.
    let depth = root.join("recon/sav_000003/cam_info/megasam_depth.npy");
    let values = datagen::io::npy::read_npy_f32(&depth).unwrap();
    datagen::io::npy::write_npy(&depth, &values.shape, &vec![f32::NAN; values.data.len()]).unwrap();
    // 4: frame-count mismatch.
    let depth = root.join("recon/sav_000004/cam_info/megasam_depth.npy");
    let values = datagen::io::npy::read_npy_f32(&depth).unwrap();
    datagen::io::npy::write_npy(&depth, &[7, 32, 48], &values.data[..7 * 32 * 48]).unwrap();
    // 5: corrupt RLE.
    std::fs::write(
        sav.join("sav_000005_manual.json"),
        r#"{"video_frame_count": 9, "masklet": [[{"size": [32, 48], "counts": "\u007f"}]]}"#,
    )
    .unwrap();
    // 6: a sequence folder with an unreadable mask PNG.
    let broken = root.join("sequences/broken");
    write_sequence(&SynthConfig { width: 48, height: 32, frames: 5, ..SynthConfig::default() }, &broken, |_| {})
        .unwrap();
    std::fs::write(broken.join("masks/00002.png"), b"not a png").unwrap();

    run_build(&config, &[]);
    let status = datagen::corpus::build::read_corpus_status(&out).unwrap();
    let expect = |key: &str, state: InputStatus, needle: &str| {
        let record = &status[key];
        assert_eq!(record.status, state, "{key}: {}", record.reason);
        assert!(record.reason.contains(needle), "{key}: `{}` should mention `{needle}`", record.reason);
    };
    expect("sav/sav_000001", InputStatus::Failed, "sav_000001.mp4");
    expect("sav/sav_000002", InputStatus::Skipped, "no reconstruction");
    expect("sav/sav_000003", InputStatus::Failed, "depth[0]");
    expect("sav/sav_000004", InputStatus::Failed, "megasam_depth.npy");
    expect("sav/sav_000005", InputStatus::Failed, "masklet[0][0]");
    expect("sequences/broken", InputStatus::Failed, "00002.png");
    let content = corpus_content(&out);
    let good: BTreeSet<&str> = content.iter().map(|(id, _)| id.split('/').nth(1).unwrap()).collect();
    assert_eq!(good, BTreeSet::from(["sav_000000", "sav_000006"]), "every good input produced pairs");
    assert_eq!(content.len(), 4, "9 frames, windows of 5 every 4: 2 clips per good video");

    let report = datagen().arg("inspect").arg(&out).output().unwrap();
    let text = String::from_utf8_lossy(&report.stdout);
    assert!(text.contains("2 ok, 1 skipped, 5 failed"), "{text}");
    let validate = datagen().arg("validate").arg(&out).arg("--deep").output().unwrap();
    assert!(validate.status.success(), "{}", String::from_utf8_lossy(&validate.stdout));
}

#[test]
fn kill_9_at_several_points_then_resume_equals_an_uninterrupted_run() {
    let dir = tempfile::tempdir().unwrap();
    let (config, out) = make_corpus(dir.path(), 6);
    run_build(&config, &[]);
    let reference = corpus_content(&out);
    assert_eq!(reference.len(), 12);

    // Kill points chosen by progress, not by wall time (this corpus builds in under 150 ms on a
    // fast machine): once during start-up, then each run right after it finishes a shard, while
    // the next one is being written.
    let killed_out = dir.path().join("killed");
    let finished_shards = || -> usize {
        let Ok(entries) = std::fs::read_dir(&killed_out) else { return 0 };
        entries.filter(|e| schemas::is_finished(&e.as_ref().unwrap().path())).count()
    };
    let mut kills = 0;
    for round in 0..5 {
        let before = finished_shards();
        let started = std::time::Instant::now();
        let mut child =
            datagen().arg("build").arg("--config").arg(&config).arg("--out").arg(&killed_out).spawn().unwrap();
        while child.try_wait().unwrap().is_none() {
            let due = if round == 0 { started.elapsed().as_millis() >= 5 } else { finished_shards() > before };
            if due {
                child.kill().unwrap(); // SIGKILL
                kills += 1;
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        child.wait().unwrap();
    }
    run_build(&config, &["--out", killed_out.to_str().unwrap()]);
    println!("killed {kills} runs before resuming");
    assert!(kills >= 2, "runs interrupted at several points");
    assert_eq!(corpus_content(&killed_out), reference);
}

#[test]
fn two_workers_equal_one_and_dry_run_lists_the_plan() {
    let dir = tempfile::tempdir().unwrap();
    let (config, out) = make_corpus(dir.path(), 4);
    let dry = datagen().arg("build").arg("--config").arg(&config).arg("--dry-run").output().unwrap();
    let text = String::from_utf8_lossy(&dry.stdout);
    assert!(text.contains("build\tsav/sav_000003") && text.contains("4 inputs"), "{text}");
    assert!(!out.exists(), "a dry run writes nothing");
    run_build(&config, &[]);
    let split = dir.path().join("split");
    for index in ["0", "1"] {
        let output = datagen()
            .args(["build", "--num-workers", "2", "--worker-index", index, "--config"])
            .arg(&config)
            .arg("--out")
            .arg(&split)
            .env_remove("SLURM_ARRAY_TASK_COUNT")
            .output()
            .unwrap();
        assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    }
    assert_eq!(corpus_content(&split), corpus_content(&out));
}

#[test]
fn synthetic_corpus_in_every_layout_builds_completely() {
    // `datagen synth-corpus` writes SA-V, TAO, YouTube-VOS, DAVIS and sequence trees in their own
    // formats (RLE masklets, sparse id PNGs, boxes); every video must become pairs.
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene.toml");
    std::fs::write(&scene, "width = 48\nheight = 32\nframes = 9\n").unwrap();
    let root = dir.path().join("trees");
    let made = datagen()
        .args(["synth-corpus", "--videos-per-layout", "1", "--out"])
        .arg(&root)
        .arg("--config")
        .arg(&scene)
        .output()
        .unwrap();
    assert!(made.status.success(), "{}", String::from_utf8_lossy(&made.stderr));
    let built = datagen().arg("build").arg("--config").arg(root.join("corpus.toml")).arg("--timings").output().unwrap();
    let stdout = String::from_utf8_lossy(&built.stdout);
    assert!(
        built.status.success() && stdout.contains("timings:"),
        "{stdout}{}",
        String::from_utf8_lossy(&built.stderr)
    );
    let status = datagen::corpus::build::read_corpus_status(&root.join("corpus")).unwrap();
    let keys: BTreeSet<&str> = status.keys().map(String::as_str).collect();
    assert_eq!(
        keys,
        BTreeSet::from([
            "davis/davis-0000",
            "sav/sav_000000",
            "sequences/seq_0000",
            "tao/train/SYN/tao0000",
            "ytvos/ytvos0000"
        ])
    );
    for (key, record) in &status {
        assert_eq!(record.status, InputStatus::Ok, "{key}: {}", record.reason);
        assert!(record.pairs >= 2, "{key}");
    }
    // Every layout's dynamic masks made it into the clips (boxes for TAO, RLE for SA-V, ...).
    for shard in std::fs::read_dir(root.join("corpus")).unwrap() {
        let path = shard.unwrap().path();
        if path.extension().is_some_and(|e| e == "parquet")
            && path.file_name().unwrap().to_string_lossy().starts_with("shard-")
        {
            for clip in schemas::read_shard(&path).unwrap() {
                let masks = clip.dynamic_mask.as_ref().unwrap_or_else(|| panic!("{}: no dynamic masks", clip.clip_id));
                let any = masks
                    .iter()
                    .any(|png| image::load_from_memory(png).unwrap().to_luma8().pixels().any(|p| p.0[0] != 0));
                assert!(any, "{}: dynamic masks are empty", clip.clip_id);
            }
        }
    }
}
