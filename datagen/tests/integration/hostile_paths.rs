//! Names read from files that would leave their folder (DyCheck ids, COLMAP image names,
//! ParallelDomain view names), links in crawled trees (`loop -> .`) and a camera listed twice
//! through a link: each refused naming the file and entry, or walked once.

use std::os::unix::fs::symlink;
use std::path::{Path, PathBuf};

use datagen::corpus::crawl::{DatasetKind, SourceConfig, crawl};
use datagen::io::dycheck::read_dycheck;
use datagen::io::multiview::read_multiview;
use datagen::io::sequence::read_sequence;
use datagen::synth::{CameraRig, SynthConfig, write_multiview, write_sequence};
use datagen::synth_layouts::write_dycheck;

use super::tool_layouts::{Truth, write_colmap};

const RIG: CameraRig = CameraRig { cameras: 2, spacing_deg: 8.0 };

fn small(frames: u32) -> SynthConfig {
    SynthConfig { width: 32, height: 24, frames, ..SynthConfig::default() }
}

fn assert_names(error: &str, needles: &[&str]) {
    for needle in needles {
        assert!(error.contains(needle), "`{error}` should contain `{needle}`");
    }
}

/// Replaces `from` by `to` in every text file under `dir` (the DyCheck JSON files).
fn rename_in_files(dir: &Path, from: &str, to: &str) {
    for entry in walkdir(dir) {
        if entry.extension().is_some_and(|e| e == "json") {
            let text = std::fs::read_to_string(&entry).unwrap();
            std::fs::write(&entry, text.replace(from, to)).unwrap();
        }
    }
}

fn walkdir(dir: &Path) -> Vec<PathBuf> {
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() { files.extend(walkdir(&path)) } else { files.push(path) }
    }
    files
}

#[test]
fn a_dycheck_item_id_climbing_out_of_the_scene_is_refused_naming_file_and_entry() {
    let dir = tempfile::tempdir().unwrap();
    let scene = write_dycheck(&small(2), &RIG, &dir.path().join("scene"), |_| {}).unwrap();
    // The id, in dataset.json, metadata.json and the splits alike, climbs out of the scene; its
    // files are planted where the joined paths would lead, so only the name check stops it.
    let escaped = "../../x/0_00001";
    for (folder, ext) in [("camera", "json"), ("rgb/1x", "png"), ("depth/1x", "npy")] {
        let from = scene.join(folder).join(format!("0_00001.{ext}"));
        if from.is_file() {
            let to = scene.join(folder).join(format!("{escaped}.{ext}"));
            std::fs::create_dir_all(to.parent().unwrap()).unwrap();
            std::fs::copy(&from, &to).unwrap();
        }
    }
    rename_in_files(&scene, "\"0_00001\"", &format!("\"{escaped}\""));
    let error = read_dycheck(&scene, Some(1)).unwrap_err().to_string();
    assert_names(&error, &["dataset.json", "ids[", escaped, "climbs out"]);
    // An absolute id is refused the same way.
    rename_in_files(&scene, &format!("\"{escaped}\""), "\"/tmp/0_00001\"");
    let error = read_dycheck(&scene, Some(1)).unwrap_err().to_string();
    assert_names(&error, &["dataset.json", "ids[", "/tmp/0_00001", "absolute"]);
}

#[test]
fn colmap_image_names_leaving_the_workspace_are_refused_in_text_and_binary_models() {
    let truth = Truth::new(2);
    let dir = tempfile::tempdir().unwrap();
    let text = write_colmap(&truth, &dir.path().join("text"), false);
    let images = text.join("sparse/0/images.txt");
    let model = std::fs::read_to_string(&images).unwrap();
    std::fs::write(&images, model.replace("frame_001.png", "../../frame_001.png")).unwrap();
    let error = read_sequence(&text).unwrap_err().to_string();
    assert_names(&error, &["images.txt", "line ", "../../frame_001.png", "climbs out"]);

    let binary = write_colmap(&truth, &dir.path().join("binary"), true);
    let images = binary.join("sparse/0/images.bin");
    let model = std::fs::read(&images).unwrap();
    let at = model.windows(14).position(|w| w == b"frame_001.png\0").unwrap();
    let mut lying = model[..at].to_vec();
    lying.extend(b"/etc/frame_001.png\0");
    lying.extend(&model[at + 14..]);
    std::fs::write(&images, lying).unwrap();
    let error = read_sequence(&binary).unwrap_err().to_string();
    assert_names(&error, &["images.bin", "image[1]", "/etc/frame_001.png", "absolute"]);
}

#[test]
fn colmap_camera_sizes_that_wrap_when_narrowed_are_refused() {
    // 2^32 + 64 narrows to the frames' real width, 64: it must be refused, not read as 64.
    let huge = (1u64 << 32) + 64;
    let truth = Truth::new(2);
    let dir = tempfile::tempdir().unwrap();
    let text = write_colmap(&truth, &dir.path().join("text"), false);
    let cameras = text.join("sparse/0/cameras.txt");
    let model = std::fs::read_to_string(&cameras).unwrap();
    std::fs::write(&cameras, model.replace("PINHOLE 64 48", &format!("PINHOLE {huge} 48"))).unwrap();
    let error = read_sequence(&text).unwrap_err().to_string();
    assert_names(&error, &["cameras.txt", "line 2", &huge.to_string(), "outside"]);
    // A fractional id or size is not truncated either.
    std::fs::write(&cameras, model.replace("PINHOLE 64 48", "PINHOLE 64.5 48")).unwrap();
    assert_names(&read_sequence(&text).unwrap_err().to_string(), &["cameras.txt", "line 2", "64.5"]);

    let binary = write_colmap(&truth, &dir.path().join("binary"), true);
    let cameras = binary.join("sparse/0/cameras.bin");
    let mut model = std::fs::read(&cameras).unwrap();
    // num_cameras (8), camera_id and model_id (4 each), then the width.
    model[16..24].copy_from_slice(&huge.to_le_bytes());
    std::fs::write(&cameras, model).unwrap();
    let error = read_sequence(&binary).unwrap_err().to_string();
    assert_names(&error, &["cameras.bin", "camera[0]", &huge.to_string(), "outside"]);
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

#[test]
fn crawls_follow_each_real_folder_once_through_links_that_loop() {
    let dir = tempfile::tempdir().unwrap();
    // A multi-view root with one scene, a link to itself and a second loop further down.
    let root = dir.path().join("multiview");
    write_multiview(&small(2), &RIG, &root.join("scene"), |_| {}).unwrap();
    symlink(".", root.join("loop")).unwrap();
    std::fs::create_dir_all(root.join("deeper")).unwrap();
    symlink("..", root.join("deeper/up")).unwrap();
    let keys: Vec<String> = crawl(&source(DatasetKind::Multiview, &root)).unwrap().iter().map(|e| e.key()).collect();
    assert_eq!(keys, ["multiview/scene"], "one scene, listed once under its own name");

    // A sequence tree with the same loops, and a second name for a sequence (a sibling link).
    let root = dir.path().join("sequences");
    write_sequence(&small(2), &root.join("clip"), |_| {}).unwrap();
    symlink(".", root.join("loop")).unwrap();
    symlink("clip", root.join("alias")).unwrap();
    let keys: Vec<String> = crawl(&source(DatasetKind::Sequences, &root)).unwrap().iter().map(|e| e.key()).collect();
    assert_eq!(keys, ["sequences/clip"], "the real folder keeps its name; its link is not a second video");
}

#[test]
fn a_camera_folder_linked_to_another_camera_is_refused_naming_both() {
    let dir = tempfile::tempdir().unwrap();
    let scene = write_multiview(&small(2), &RIG, &dir.path().join("scene"), |_| {}).unwrap();
    read_multiview(&scene).unwrap();
    symlink("cam00", scene.join("cam02")).unwrap();
    let error = read_multiview(&scene).unwrap_err().to_string();
    assert_names(&error, &["cameras", "`cam00`", "`cam02`", "same folder"]);
}
