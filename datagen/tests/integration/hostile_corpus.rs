//! Hostile corpus builds: clashing ids, a malformed split file, a template
//! typo, fixed inputs retried, a second build on a locked folder, planted orphans, empty folders.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicUsize, Ordering};

use datagen::corpus::build::{
    BuildConfig, BuildOptions, InputProcessor, Outcome, OutputConfig, build, build_with_options, lock_output,
    read_corpus_status,
};
use datagen::corpus::crawl::{DatasetKind, FrameSource, SourceConfig, VideoEntry, crawl};
use datagen::corpus::partition::Worker;
use datagen::corpus::validate::validate;
use schemas::InputStatus;

fn datagen() -> Command {
    Command::new(env!("CARGO_BIN_EXE_datagen"))
}

/// A stand-in for the real processor: one small valid clip per input, named after its key, or a
/// failure when the input's first file starts with `bad`. Counts calls.
#[derive(Default)]
struct FileProcessor {
    calls: AtomicUsize,
}

impl InputProcessor for FileProcessor {
    fn process(&self, entry: &VideoEntry) -> datagen::Result<Outcome> {
        self.calls.fetch_add(1, Ordering::SeqCst);
        let path = match &entry.frames {
            FrameSource::Sequence(dir) | FrameSource::MultiView(dir) => dir.join("gt_rgb.mp4"),
            FrameSource::Images(paths) => paths[0].clone(),
            FrameSource::Video(path) => path.clone(),
        };
        let bytes = std::fs::read(&path).map_err(|e| datagen::Error::io(&path, e))?;
        if bytes.starts_with(b"bad") {
            return Err(datagen::Error::invalid(&path, "video", "planted failure"));
        }
        let mut clip = super::validate::record(&format!("{}/0", entry.key()));
        clip.source_id = entry.video_id.clone();
        clip.source_path = entry.key();
        Ok(Outcome::Clips(vec![clip]))
    }
}

impl FileProcessor {
    fn calls(&self) -> usize {
        self.calls.load(Ordering::SeqCst)
    }
}

/// Sequence folders `names` under `root` whose `gt_rgb.mp4` holds `content(name)`.
fn sequences(root: &Path, names: &[&str], content: impl Fn(&str) -> String) -> SourceConfig {
    for name in names {
        std::fs::create_dir_all(root.join(name)).unwrap();
        std::fs::write(root.join(name).join("gt_rgb.mp4"), content(name)).unwrap();
    }
    source(DatasetKind::Sequences, root)
}

fn source(dataset: DatasetKind, root: &Path) -> SourceConfig {
    SourceConfig {
        dataset,
        root: root.to_owned(),
        reconstructions: None,
        annotations: None,
        split: None,
        id_prefix: None,
    }
}

fn output(dir: &Path) -> OutputConfig {
    // One shard per input, so a build leaves several to plant orphans in.
    OutputConfig { dir: dir.to_owned(), shard_bytes: 1, row_group_bytes: 1 << 20 }
}

/// Clip ids of every finished shard, asserting none is listed twice.
fn clip_ids(out: &Path) -> BTreeSet<String> {
    let mut ids = BTreeSet::new();
    for entry in std::fs::read_dir(out).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        if name.starts_with("shard-") && name.ends_with(".parquet") && schemas::is_finished(&path) {
            for clip in schemas::read_shard(&path).unwrap() {
                assert!(ids.insert(clip.clip_id.clone()), "clip {} written twice", clip.clip_id);
            }
        }
    }
    ids
}

#[test]
fn two_sources_with_the_same_video_id_are_an_error_at_start_naming_both() {
    let dir = tempfile::tempdir().unwrap();
    let first = sequences(&dir.path().join("tree_a"), &["scene", "only_a"], |n| format!("a {n}"));
    let second = sequences(&dir.path().join("tree_b"), &["scene"], |n| format!("b {n}"));
    let out = output(&dir.path().join("out"));
    let processor = FileProcessor::default();
    let error =
        build(&[first.clone(), second.clone()], &out, Worker::SOLE, &processor, |_| {}).unwrap_err().to_string();
    let first_line = error.lines().next().unwrap();
    for needle in ["sequences/scene", "sources[1]", "sources[0]", "tree_a", "tree_b", "id_prefix"] {
        assert!(first_line.contains(needle), "`{first_line}` should name `{needle}`");
    }
    assert_eq!(processor.calls(), 0, "refused before building anything");
    assert!(!out.dir.exists(), "nothing written");

    // An explicit prefix tells the two apart: both videos built, under distinct keys and clip ids.
    let second = SourceConfig { id_prefix: Some("mirror".into()), ..second };
    build(&[first, second], &out, Worker::SOLE, &processor, |_| {}).unwrap();
    let status = read_corpus_status(&out.dir).unwrap();
    let keys: Vec<&str> = status.keys().map(String::as_str).collect();
    assert_eq!(keys, ["sequences/mirror/scene", "sequences/only_a", "sequences/scene"]);
    assert!(status.values().all(|r| r.status == InputStatus::Ok));
    assert_eq!(clip_ids(&out.dir).len(), 3);
}

/// A TAO split under `root`: frame folders `frames/{split}/SYN/{video}` and, unless `json` is
/// given, a valid `annotations/{split}.json` listing them.
fn tao_split(root: &Path, split: &str, videos: &[&str], json: Option<&str>) -> SourceConfig {
    let mut listed = Vec::new();
    let mut images = Vec::new();
    for (i, video) in videos.iter().enumerate() {
        let name = format!("{split}/SYN/{video}");
        let folder = root.join("frames").join(&name);
        std::fs::create_dir_all(&folder).unwrap();
        std::fs::write(folder.join("frame0001.jpg"), format!("frames of {name}")).unwrap();
        std::fs::create_dir_all(root.join("recon").join(video)).unwrap();
        listed.push(serde_json::json!({"id": i + 1, "name": name, "width": 6, "height": 4}));
        images
            .push(serde_json::json!({"id": 100 + i, "video_id": i + 1, "file_name": format!("{name}/frame0001.jpg")}));
    }
    let text = json
        .map(str::to_owned)
        .unwrap_or_else(|| serde_json::json!({"videos": listed, "images": images, "annotations": []}).to_string());
    std::fs::create_dir_all(root.join("annotations")).unwrap();
    std::fs::write(root.join("annotations").join(format!("{split}.json")), text).unwrap();
    SourceConfig {
        split: Some(split.into()),
        reconstructions: Some("{root}/recon/{name}".into()),
        ..source(DatasetKind::Tao, root)
    }
}

#[test]
fn a_malformed_split_annotation_fails_its_videos_and_the_rest_builds() {
    let dir = tempfile::tempdir().unwrap();
    let tao = dir.path().join("tao");
    let train = tao_split(&tao, "train", &["t1", "t2"], None);
    let validation = tao_split(&tao, "validation", &["v1"], Some(r#"{"videos": [{"id": 1, "name": "#));
    let seqs = sequences(&dir.path().join("seqs"), &["s1"], |n| n.to_owned());
    let out = output(&dir.path().join("out"));
    let sources = [train.clone(), validation.clone(), seqs];
    let processor = FileProcessor::default();
    let summary = build(&sources, &out, Worker::SOLE, &processor, |_| {}).unwrap();
    assert_eq!((summary.ok, summary.failed), (3, 1));
    let status = read_corpus_status(&out.dir).unwrap();
    let broken = &status["tao/validation/SYN/v1"];
    assert_eq!(broken.status, InputStatus::Failed);
    assert!(broken.reason.contains("annotations/validation.json"), "{}", broken.reason);
    for key in ["tao/train/SYN/t1", "tao/train/SYN/t2", "sequences/s1"] {
        assert_eq!(status[key].status, InputStatus::Ok, "{key}: {}", status[key].reason);
    }

    // Fixing the file changes the content hash of the videos that depend on it: they are retried.
    tao_split(&tao, "validation", &["v1"], None);
    let summary = build(&sources, &out, Worker::SOLE, &processor, |_| {}).unwrap();
    assert_eq!((summary.ok, summary.failed, summary.inputs_already_done), (1, 0, 3));
    assert_eq!(read_corpus_status(&out.dir).unwrap()["tao/validation/SYN/v1"].status, InputStatus::Ok);
}

#[test]
fn an_unknown_placeholder_in_a_reconstruction_template_is_rejected_at_load() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("corpus.toml");
    std::fs::write(
        &config,
        "[[sources]]\ndataset = \"sav\"\nroot = \"/data/sav\"\nreconstructions = \"/data/recon/{vidoe_id}\"\n\n\
         [output]\ndir = \"/data/out\"\n",
    )
    .unwrap();
    let error = BuildConfig::from_toml_file(&config).unwrap_err().to_string();
    let first_line = error.lines().next().unwrap();
    for needle in ["corpus.toml", "sources[0].reconstructions", "{vidoe_id}", "{video_id}", "{root}", "{name}"] {
        assert!(first_line.contains(needle), "`{first_line}` should name `{needle}`");
    }
    // Unbalanced braces, and a library caller bypassing the file, are caught the same way.
    std::fs::write(&config, std::fs::read_to_string(&config).unwrap().replace("{vidoe_id}", "{video_id")).unwrap();
    assert!(BuildConfig::from_toml_file(&config).unwrap_err().to_string().contains("sources[0].reconstructions"));
    let mut typo = source(DatasetKind::Sav, dir.path());
    typo.reconstructions = Some("{root}/{vido_id}".into());
    assert!(crawl(&typo).unwrap_err().to_string().contains("{vido_id}"));
}

#[test]
fn a_failed_input_is_retried_when_its_files_change_or_with_retry_failed() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("seqs");
    let seqs = sequences(&root, &["good", "fixed_later", "still_bad"], |n| {
        if n == "good" { "fine".into() } else { format!("bad {n}") }
    });
    let out = output(&dir.path().join("out"));
    let sources = [seqs];
    let processor = FileProcessor::default();
    let summary = build(&sources, &out, Worker::SOLE, &processor, |_| {}).unwrap();
    assert_eq!((summary.ok, summary.failed, processor.calls()), (1, 2, 3));
    let summary = build(&sources, &out, Worker::SOLE, &processor, |_| {}).unwrap();
    assert_eq!((summary.inputs_already_done, processor.calls()), (3, 3), "unchanged failures are not redone");

    std::fs::write(root.join("fixed_later/gt_rgb.mp4"), "fixed").unwrap();
    let summary = build(&sources, &out, Worker::SOLE, &processor, |_| {}).unwrap();
    assert_eq!((summary.ok, summary.failed, processor.calls()), (1, 0, 4), "the changed input alone is retried");
    let status = read_corpus_status(&out.dir).unwrap();
    assert_eq!(status["sequences/fixed_later"].status, InputStatus::Ok);

    // The CLI offers the forced retry; a dry run shows it.
    let config = sequences_config(dir.path(), &root, &out.dir);
    let dry =
        datagen().arg("build").arg("--config").arg(&config).args(["--dry-run", "--retry-failed"]).output().unwrap();
    let text = String::from_utf8_lossy(&dry.stdout);
    assert!(dry.status.success(), "{}", String::from_utf8_lossy(&dry.stderr));
    assert!(
        text.contains("retry: --retry-failed\tsequences/still_bad") && text.contains("done\tsequences/good"),
        "{text}"
    );

    let options = BuildOptions { retry_failed: true };
    let summary = build_with_options(&sources, &out, Worker::SOLE, options, &processor, |_| {}).unwrap();
    assert_eq!((summary.failed, summary.inputs_already_done, processor.calls()), (1, 2, 5));
    assert_eq!(read_corpus_status(&out.dir).unwrap()["sequences/still_bad"].status, InputStatus::Failed);
}

#[test]
fn a_second_build_on_a_locked_folder_and_worker_refuses_to_start() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("seqs");
    let seqs = sequences(&root, &["a", "b"], |n| n.to_owned());
    let out = output(&dir.path().join("out"));
    std::fs::create_dir_all(&out.dir).unwrap();
    let config = sequences_config(dir.path(), &root, &out.dir);

    let held = lock_output(&out.dir, Worker::SOLE).unwrap();
    // A planted temporary file of the running build must survive the refused one.
    let temp = out.dir.join(".shard-w0000of0001-000000.parquet.tmp-1");
    std::fs::write(&temp, b"being written").unwrap();
    let second = datagen().arg("build").arg("--config").arg(&config).output().unwrap();
    let stderr = String::from_utf8_lossy(&second.stderr);
    assert!(!second.status.success(), "a second build on a locked folder must refuse: {stderr}");
    let first_line = stderr.lines().next().unwrap_or_default();
    for needle in ["build-w0000of0001.lock", "another `datagen build`", &format!("pid {}", std::process::id())] {
        assert!(first_line.contains(needle), "`{first_line}` should name `{needle}`");
    }
    assert!(temp.is_file(), "the refused build touched the running one's files");
    assert!(
        !std::fs::read_dir(&out.dir).unwrap().any(|e| e.unwrap().file_name().to_string_lossy().starts_with("shard-"))
    );

    // A build with another worker count overlaps this one's inputs: refused too; another index
    // of one partition runs alongside.
    let overlapping = lock_output(&out.dir, Worker::new(2, 0).unwrap()).unwrap_err().to_string();
    assert!(overlapping.contains("--num-workers 1"), "{overlapping}");
    drop(held);
    let first_half = lock_output(&out.dir, Worker::new(2, 0).unwrap()).unwrap();
    lock_output(&out.dir, Worker::new(2, 1).unwrap()).unwrap();
    drop(first_half);

    // Released: the build runs, and cleans up the temporary file left behind.
    let processor = FileProcessor::default();
    let summary = build(&[seqs], &out, Worker::SOLE, &processor, |_| {}).unwrap();
    assert_eq!(summary.ok, 2);
    assert!(!temp.exists());
}

fn shards(out: &Path) -> Vec<PathBuf> {
    let mut shards: Vec<PathBuf> = std::fs::read_dir(out)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "parquet"))
        .collect();
    shards.sort();
    shards
}

#[test]
fn resume_repairs_planted_orphans_and_the_result_validates() {
    let dir = tempfile::tempdir().unwrap();
    let seqs = sequences(&dir.path().join("seqs"), &["a", "b", "c", "d"], |n| n.to_owned());
    let out = output(&dir.path().join("out"));
    let processor = FileProcessor::default();
    build(std::slice::from_ref(&seqs), &out, Worker::SOLE, &processor, |_| {}).unwrap();
    let complete = clip_ids(&out.dir);
    let shards = shards(&out.dir);
    assert_eq!(shards.len(), 4, "one shard per input");

    // A stats marker without its shard (status still says ok there).
    std::fs::remove_file(&shards[0]).unwrap();
    // A shard without its marker.
    std::fs::remove_file(schemas::shard::stats_path(&shards[1])).unwrap();
    // A shard and marker gone entirely: only the status row says ok.
    std::fs::remove_file(&shards[2]).unwrap();
    std::fs::remove_file(schemas::shard::stats_path(&shards[2])).unwrap();
    // A temporary file of an interrupted run.
    std::fs::write(out.dir.join(".shard-w0000of0001-000009.parquet.tmp-4242"), b"partial").unwrap();

    let report = validate(&out.dir, false).unwrap();
    let messages: Vec<String> =
        report.problems.iter().map(|p| format!("{}: {}", p.path.display(), p.message)).collect();
    let marker = schemas::shard::stats_path(&shards[0]).display().to_string();
    assert!(messages.iter().any(|m| m.starts_with(&marker) && m.contains("without its shard")), "{messages:?}");
    let gone = shards[2].display().to_string();
    assert!(messages.iter().any(|m| m.starts_with(&gone) && m.contains("status says input")), "{messages:?}");

    let summary = build(std::slice::from_ref(&seqs), &out, Worker::SOLE, &processor, |_| {}).unwrap();
    assert_eq!((summary.ok, summary.inputs_already_done), (3, 1), "{:?}", summary.repairs);
    let repairs = summary.repairs.join("\n");
    for needle in ["stats marker whose shard is gone", "never marked finished", "temporary file", "status says ok"] {
        assert!(repairs.contains(needle), "repairs should mention `{needle}`:\n{repairs}");
    }
    assert_eq!(clip_ids(&out.dir), complete, "every clip back, none twice");
    let report = validate(&out.dir, true).unwrap();
    assert!(report.problems.is_empty(), "{:?}", report.problems);
    assert!(!std::fs::read_dir(&out.dir).unwrap().any(|e| e.unwrap().file_name().to_string_lossy().contains(".tmp-")));
}

#[test]
fn validate_fails_on_an_empty_folder_and_on_a_marker_without_its_shard() {
    let dir = tempfile::tempdir().unwrap();
    let empty = dir.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let run = datagen().arg("validate").arg(&empty).output().unwrap();
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(!run.status.success(), "an empty folder is not a valid corpus: {stdout}");
    assert!(stdout.contains(&format!("{}: no shards", empty.display())), "{stdout}");

    let corpus = dir.path().join("corpus");
    std::fs::create_dir_all(&corpus).unwrap();
    let shard = corpus.join("shard-a.parquet");
    let mut writer = schemas::ShardWriter::create(&shard, schemas::ShardWriterOptions::default()).unwrap();
    writer.write(&super::validate::record("a/0")).unwrap();
    writer.finish().unwrap();
    let kept = corpus.join("shard-b.parquet");
    std::fs::copy(&shard, &kept).unwrap();
    std::fs::copy(schemas::shard::stats_path(&shard), schemas::shard::stats_path(&kept)).unwrap();
    std::fs::remove_file(&shard).unwrap();
    let run = datagen().arg("validate").arg(&corpus).output().unwrap();
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(!run.status.success(), "a marker without its shard is a problem: {stdout}");
    let marker = schemas::shard::stats_path(&shard);
    assert!(stdout.contains(&format!("{}: stats marker without its shard", marker.display())), "{stdout}");
}

/// A corpus TOML building the sequence folders under `root` into `out`, written in `dir`.
fn sequences_config(dir: &Path, root: &Path, out: &Path) -> PathBuf {
    let config = dir.join("corpus.toml");
    let text = format!(
        "[[sources]]\ndataset = \"sequences\"\nroot = \"{}\"\n\n[output]\ndir = \"{}\"\n",
        root.display(),
        out.display()
    );
    std::fs::write(&config, text).unwrap();
    config
}
