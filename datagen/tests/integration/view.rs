//! `datagen view`: a sequence and its pairs become a Rerun recording (through
//! scripts/rerun_view.py), which the Rerun SDK opens with the expected entities and counts; a
//! failing run leaves no file.

use std::path::{Path, PathBuf};
use std::process::Command;

use crate::sequence::synth_sequence;

fn venv_python() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../.venv/bin/python")
}

/// Rows per (entity path, component prefix) of a recording, read with the Rerun SDK.
const SUMMARY: &str = r#"
import json, sys
from collections import Counter
from rerun.chunk import RrdReader
rows = Counter()
for chunk in RrdReader(sys.argv[1]).stream():
    names = chunk.to_record_batch().schema.names
    archetypes = sorted({n.split(":")[0] for n in names if ":" in n})
    for archetype in archetypes:
        rows[f"{chunk.entity_path}|{archetype}"] += chunk.num_rows
print(json.dumps(rows))
"#;

#[test]
fn recording_of_a_sequence_and_its_pairs_opens_in_the_rerun_sdk() {
    let dir = tempfile::tempdir().unwrap();
    let seq = synth_sequence(dir.path(), 5);
    let pairs = dir.path().join("pairs");
    let made = Command::new(env!("CARGO_BIN_EXE_datagen"))
        .args(["pairs", seq.to_str().unwrap(), "--out", pairs.to_str().unwrap(), "--trajectories", "2"])
        .output()
        .unwrap();
    assert!(made.status.success(), "{}", String::from_utf8_lossy(&made.stderr));
    let shard = pairs.join("synth.parquet");
    let out = dir.path().join("synth.rrd");
    let python = venv_python();
    let viewed = Command::new(env!("CARGO_BIN_EXE_datagen"))
        .args(["view", seq.to_str().unwrap(), "--pairs", shard.to_str().unwrap(), "--out", out.to_str().unwrap()])
        .arg("--python")
        .arg(&python)
        .output()
        .unwrap();
    assert!(viewed.status.success(), "{}", String::from_utf8_lossy(&viewed.stderr));
    assert!(String::from_utf8_lossy(&viewed.stdout).contains("2 novel trajectories"));
    assert!(!out.with_extension("rrd.parts").exists() && !out.with_extension("rrd.tmp").exists());

    let summary = Command::new(&python).arg("-c").arg(SUMMARY).arg(&out).output().unwrap();
    assert!(summary.status.success(), "{}", String::from_utf8_lossy(&summary.stderr));
    let rows: serde_json::Value = serde_json::from_slice(&summary.stdout).unwrap();
    let count = |key: &str| rows[key].as_u64().unwrap_or(0);
    for key in
        ["/world/points|Points3D", "/world/source|Transform3D", "/world/source|Pinhole", "/world/source/image|Image"]
    {
        assert_eq!(count(key), 5, "{key}: {rows}");
    }
    let novel: Vec<&String> = rows
        .as_object()
        .unwrap()
        .keys()
        .filter(|k| k.starts_with("/world/novel/") && k.ends_with("|Pinhole"))
        .collect();
    assert_eq!(novel.len(), 2, "{rows}");
    for key in novel {
        assert_eq!(count(key), 5, "one frustum per clip frame: {key}");
    }
    let masks = rows.as_object().unwrap().iter().filter(|(k, _)| k.starts_with("/world/source/covisibility/")).count();
    assert_eq!(masks, 2, "{rows}");
}

#[test]
fn a_failing_script_leaves_no_recording() {
    let dir = tempfile::tempdir().unwrap();
    let seq = synth_sequence(dir.path(), 2);
    let script = dir.path().join("broken.py");
    std::fs::write(&script, "import sys\nopen(sys.argv[2], 'w').write('partial')\nsys.exit('no rerun here')\n")
        .unwrap();
    let out = dir.path().join("x.rrd");
    let output = Command::new(env!("CARGO_BIN_EXE_datagen"))
        .args(["view", seq.to_str().unwrap(), "--out", out.to_str().unwrap(), "--script", script.to_str().unwrap()])
        .arg("--python")
        .arg(venv_python())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("no rerun here") && stderr.contains("rerun-sdk"), "{stderr}");
    let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().filter_map(|e| e.ok()).map(|e| e.file_name()).collect();
    assert!(!out.exists() && left.iter().all(|n| !n.to_string_lossy().starts_with("x.rrd")), "{left:?}");
}
