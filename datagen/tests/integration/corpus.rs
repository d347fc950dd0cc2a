//! Corpus inputs checked against reference implementations: SA-V RLE strings made by pycocotools.

use std::path::Path;
use std::process::Command;

use datagen::io::annotations::{SAV_ANNOTATION_STRIDE, load_sav_annotation, sav_frame_masks};

fn venv_python() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../.venv/bin/python")
}

/// pycocotools encodes random masks into an SA-V-style annotation; our decoder must reproduce
/// every pixel of every annotated frame.
#[test]
fn sav_masklets_decode_exactly_like_pycocotools() {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("sav_000001_manual.json");
    let truth = dir.path().join("truth.npy");
    let script = r#"
import json, sys
import numpy as np
import pycocotools.mask as mask_util
rng = np.random.default_rng(5)
height, width, steps, objects = 37, 53, 4, 3
masklet, truth = [], np.zeros((steps, height, width), np.uint8)
for step in range(steps):
    frame = []
    for obj in range(objects):
        m = np.zeros((height, width), np.uint8)
        if not (step == 2 and obj == 1):  # one absent object: an empty RLE
            y, x = rng.integers(0, height - 10), rng.integers(0, width - 10)
            m[y:y + rng.integers(3, 10), x:x + rng.integers(3, 10)] = 1
            m |= (rng.random((height, width)) < 0.02).astype(np.uint8)
        rle = mask_util.encode(np.asfortranarray(m))
        frame.append({"size": rle["size"], "counts": rle["counts"].decode()})
        truth[step][(m == 1) & (truth[step] == 0)] = obj + 1
    masklet.append(frame)
json.dump({"video_frame_count": 16.0, "masklet": masklet, "masklet_id": list(range(objects))}, open(sys.argv[1], "w"))
np.save(sys.argv[2], truth)
"#;
    let output = Command::new(venv_python()).arg("-c").arg(script).arg(&json).arg(&truth).output().unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));

    let annotation = load_sav_annotation(&json).unwrap();
    let masks = sav_frame_masks(&annotation, 16, &json).unwrap();
    assert_eq!(masks.len(), 16);
    let truth = datagen::io::npy::read_npy_f64(&truth).unwrap();
    let frame_pixels = 37 * 53;
    for step in 0..4 {
        let expected: Vec<u8> =
            truth.data[step * frame_pixels..(step + 1) * frame_pixels].iter().map(|&v| v as u8).collect();
        assert_eq!(
            masks[step * SAV_ANNOTATION_STRIDE].as_raw(),
            &expected,
            "annotated frame {}",
            step * SAV_ANNOTATION_STRIDE
        );
    }
}

#[test]
fn corrupt_rle_names_the_file_and_masklet() {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("sav_000002_manual.json");
    std::fs::write(&json, r#"{"video_frame_count": 4, "masklet": [[{"size": [2, 2], "counts": "5\u007f"}]]}"#).unwrap();
    let annotation = load_sav_annotation(&json).unwrap();
    let error = sav_frame_masks(&annotation, 4, &json).unwrap_err().to_string();
    assert!(error.contains("sav_000002_manual.json") && error.contains("masklet[0][0]"), "{error}");
}
