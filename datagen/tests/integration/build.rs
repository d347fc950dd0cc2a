//! The resumable corpus build with a deterministic stand-in processor: outcomes recorded,
//! resume skips finished inputs, crashes leave nothing visible, workers partition exactly.

use std::collections::BTreeSet;
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};

use datagen::corpus::build::{InputProcessor, Outcome, OutputConfig, build, read_corpus_status};
use datagen::corpus::crawl::{DatasetKind, SourceConfig, VideoEntry};
use datagen::corpus::partition::Worker;
use schemas::{ClipRecord, InputStatus, TrajectoryKind, TrajectoryRecord};

/// Clips derived from the input key only, so runs are comparable; fails on keys containing
/// "bad"; counts calls.
struct KeyProcessor {
    calls: AtomicUsize,
}

impl InputProcessor for KeyProcessor {
    fn process(&self, entry: &VideoEntry) -> datagen::Result<Outcome> {
        self.calls.fetch_add(1, Ordering::SeqCst);
        if entry.video_id.contains("bad") {
            return Err(datagen::Error::invalid(format!("{}/gt_rgb.mp4", entry.video_id), "video", "planted failure"));
        }
        let seed = blake3::hash(entry.key().as_bytes()).as_bytes()[0];
        let clip = |start: u32| ClipRecord {
            clip_id: format!("{}/{start}", entry.key()),
            source_id: entry.video_id.clone(),
            dataset: "sequences".into(),
            source_path: entry.key(),
            clip_start: start,
            fps: 24.0,
            width: 4,
            height: 2,
            seed: 0,
            tool_version: "test".into(),
            frames: (0..2).map(|f| noise(&entry.key(), f, 4000)).collect(),
            depth: vec![vec![seed ^ 1; 10]; 2],
            intrinsics: vec![[1.0; 9]; 2],
            world_from_camera: vec![[0.0; 16]; 2],
            dynamic_mask: None,
            trajectories: vec![TrajectoryRecord {
                index: 0,
                kind: TrajectoryKind::Sampled,
                pivot_distance: 1.0,
                azimuth_deg: vec![seed as f64],
                elevation_deg: vec![],
                radius_frac: vec![],
                rejected_samples: 0,
                world_from_camera: vec![[0.0; 16]; 2],
                covisible_mask: vec![vec![255; 5]; 2],
                condition: None,
                covisible_fraction: 1.0,
                bank_entry: None,
                mask_rule: schemas::MaskRule::Exact,
            }],
            pair_kind: schemas::PairKind::Monocular,
            source_camera: None,
            target_camera: None,
        };
        Ok(Outcome::Clips(vec![clip(0), clip(2)]))
    }
}

/// Incompressible bytes derived from `key` (so shard sizes are real, not zstd-collapsed).
fn noise(key: &str, stream: u8, len: usize) -> Vec<u8> {
    let mut bytes = vec![0u8; len];
    blake3::Hasher::new().update(key.as_bytes()).update(&[stream]).finalize_xof().fill(&mut bytes);
    bytes
}

fn corpus(root: &Path, names: &[&str]) -> Vec<SourceConfig> {
    for name in names {
        let dir = root.join(name);
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("gt_rgb.mp4"), name.as_bytes()).unwrap();
    }
    vec![SourceConfig {
        dataset: DatasetKind::Sequences,
        root: root.to_owned(),
        reconstructions: None,
        annotations: None,
        split: None,
        id_prefix: None,
    }]
}

fn output(dir: &Path) -> OutputConfig {
    // Small shards so a build spans several.
    OutputConfig { dir: dir.to_owned(), shard_bytes: 20_000, row_group_bytes: 1 << 20 }
}

/// (clip id, first frame byte) of every clip in finished shards.
fn clips_in(out: &Path) -> BTreeSet<(String, u8)> {
    let mut clips = BTreeSet::new();
    for entry in std::fs::read_dir(out).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        if name.starts_with("shard-") && name.ends_with(".parquet") {
            assert!(schemas::is_finished(&path), "{name} visible without stats");
            for clip in schemas::read_shard(&path).unwrap() {
                assert!(clips.insert((clip.clip_id.clone(), clip.frames[0][0])), "duplicate {}", clip.clip_id);
            }
        }
        assert!(!name.contains(".tmp-"), "temporary file left: {name}");
    }
    clips
}

#[test]
fn build_records_every_outcome_and_resume_redoes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let names = ["a", "b", "bad_one", "c", "d", "e"];
    let sources = corpus(&dir.path().join("in"), &names);
    let out = output(&dir.path().join("out"));
    let processor = KeyProcessor { calls: AtomicUsize::new(0) };
    let summary = build(&sources, &out, Worker::SOLE, &processor, |_| {}).unwrap();
    assert_eq!((summary.ok, summary.failed, summary.skipped), (5, 1, 0));
    assert!(summary.shards >= 2, "shards cut by size: {}", summary.shards);
    assert_eq!(clips_in(&out.dir).len(), 10);
    let status = read_corpus_status(&out.dir).unwrap();
    assert_eq!(status["sequences/bad_one"].status, InputStatus::Failed);
    assert!(
        status["sequences/bad_one"].reason.contains("bad_one/gt_rgb.mp4")
            && status["sequences/bad_one"].reason.contains("planted failure")
    );
    assert_eq!(status.values().filter(|s| s.status == InputStatus::Ok).count(), 5);
    assert!(out.dir.join("manifest-w0000of0001.json").is_file());

    let again = build(&sources, &out, Worker::SOLE, &processor, |_| {}).unwrap();
    assert_eq!((again.ok, again.failed, again.inputs_already_done), (0, 0, 6));
    assert_eq!(processor.calls.load(Ordering::SeqCst), 6, "nothing processed twice");
}

#[test]
fn crash_leftovers_are_cleaned_and_redone() {
    let dir = tempfile::tempdir().unwrap();
    let sources = corpus(&dir.path().join("in"), &["a", "b", "c", "d"]);
    let out = output(&dir.path().join("out"));
    let processor = KeyProcessor { calls: AtomicUsize::new(0) };
    build(&sources, &out, Worker::SOLE, &processor, |_| {}).unwrap();
    let complete = clips_in(&out.dir);

    // Simulate a kill between a shard's rename and its stats marker, plus a half-written temp file.
    let mut shards: Vec<_> = std::fs::read_dir(&out.dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "parquet"))
        .collect();
    shards.sort();
    let last = shards.last().unwrap();
    std::fs::remove_file(schemas::stats_path(last)).unwrap();
    std::fs::write(out.dir.join(".shard-w0000of0001-000099.parquet.tmp-4242"), b"partial").unwrap();
    for status in std::fs::read_dir(out.dir.join("status")).unwrap() {
        std::fs::remove_file(status.unwrap().path()).unwrap();
    }
    let resumed = build(&sources, &out, Worker::SOLE, &processor, |_| {}).unwrap();
    assert!(resumed.ok >= 1 && resumed.inputs_already_done >= 1, "{resumed:?}");
    assert_eq!(clips_in(&out.dir), complete, "same clips, none duplicated or lost");
}

#[test]
fn two_workers_together_equal_one() {
    let dir = tempfile::tempdir().unwrap();
    let names: Vec<String> = (0..12).map(|i| format!("video{i:02}")).collect();
    let names: Vec<&str> = names.iter().map(String::as_str).collect();
    let sources = corpus(&dir.path().join("in"), &names);
    let single = output(&dir.path().join("single"));
    let shared = output(&dir.path().join("shared"));
    let processor = KeyProcessor { calls: AtomicUsize::new(0) };
    build(&sources, &single, Worker::SOLE, &processor, |_| {}).unwrap();
    let a = build(&sources, &shared, Worker::new(2, 0).unwrap(), &processor, |_| {}).unwrap();
    let b = build(&sources, &shared, Worker::new(2, 1).unwrap(), &processor, |_| {}).unwrap();
    assert_eq!(a.inputs_owned + b.inputs_owned, 12);
    assert!(a.inputs_owned > 0 && b.inputs_owned > 0);
    assert_eq!(clips_in(&shared.dir), clips_in(&single.dir));
}

/// Mounts a tmpfs of `size` at `dir` (root only); `None` where mounting is not permitted.
fn mount_tmpfs(dir: &Path, size: &str) -> Option<()> {
    std::fs::create_dir_all(dir).unwrap();
    let status = std::process::Command::new("mount")
        .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
        .arg(dir)
        .status()
        .ok()?;
    status.success().then_some(())
}

#[test]
fn disk_full_is_a_clean_error_leaves_no_corrupt_shard_and_resumes() {
    let dir = tempfile::tempdir().unwrap();
    let names: Vec<String> = (0..8).map(|i| format!("video{i:02}")).collect();
    let names: Vec<&str> = names.iter().map(String::as_str).collect();
    let sources = corpus(&dir.path().join("in"), &names);
    let reference = output(&dir.path().join("reference"));
    let processor = KeyProcessor { calls: AtomicUsize::new(0) };
    build(&sources, &reference, Worker::SOLE, &processor, |_| {}).unwrap();

    let small = dir.path().join("small");
    if mount_tmpfs(&small, "48k").is_none() {
        eprintln!("skipped: mounting a tmpfs needs root (CI runs as root)");
        return;
    }
    let out = output(&small);
    let error = build(&sources, &out, Worker::SOLE, &processor, |_| {}).unwrap_err().to_string();
    let finished: Vec<_> =
        std::fs::read_dir(&small).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    let remount = std::process::Command::new("mount").args(["-o", "remount,size=16m"]).arg(&small).status().unwrap();
    assert!(remount.success());
    let resumed = build(&sources, &out, Worker::SOLE, &processor, |_| {});
    let clips = clips_in(&small);
    let _ = std::process::Command::new("umount").arg(&small).status();
    assert!(error.contains("No space left on device"), "{error}");
    assert!(error.contains(&small.display().to_string()), "error names the file: {error}");
    assert!(finished.iter().all(|n| !n.contains(".tmp-")), "no temporary file after the failure: {finished:?}");
    resumed.unwrap();
    assert_eq!(clips, clips_in(&reference.dir), "resumed corpus equals the uninterrupted one");
}
