//! Runs that produce nothing exit non-zero with the reason (multi-view pairs all below the
//! co-visibility cut-off, an interpreter that writes no recording), and written videos do not
//! depend on the CPUs the process may use or on what its heap held before.

use std::path::Path;
use std::process::Command;

use datagen::synth::{CameraRig, SynthConfig, write_multiview};

fn datagen() -> Command {
    Command::new(env!("CARGO_BIN_EXE_datagen"))
}

fn small() -> SynthConfig {
    SynthConfig { width: 32, height: 24, frames: 3, ..SynthConfig::default() }
}

#[test]
fn multiview_pairs_all_below_the_cut_off_fail_without_a_shard() {
    let dir = tempfile::tempdir().unwrap();
    let scene = write_multiview(&small(), &CameraRig { cameras: 2, spacing_deg: 8.0 }, &dir.path().join("rig"), |_| {})
        .unwrap();
    let toml = dir.path().join("pairs.toml");
    std::fs::write(&toml, "[clip]\nlength = 3\n[multiview]\nmonocular = false\nmin_covisible_fraction = 1.0\n")
        .unwrap();
    let out = dir.path().join("out");
    let run = datagen()
        .args(["pairs", "--trajectories", "1", "--dataset", "synth", "--config"])
        .arg(&toml)
        .arg(&scene)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success(), "an empty shard is no result: {stderr}");
    assert!(stderr.contains("no pairs") && stderr.contains("min_covisible_fraction"), "{stderr}");
    assert!(!out.join("rig.parquet").exists(), "no empty shard is written");
}

#[test]
fn an_interpreter_that_writes_no_recording_is_named_with_its_output() {
    let dir = tempfile::tempdir().unwrap();
    let sequence = dir.path().join("seq");
    datagen::synth::write_sequence(&small(), &sequence, |_| {}).unwrap();
    // `echo` exits 0, prints its arguments and writes nothing: as `/bin/true`, with output to show.
    let out = dir.path().join("v.rrd");
    let run = datagen().arg("view").arg(&sequence).args(["--python", "echo", "--out"]).arg(&out).output().unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success(), "{stderr}");
    for needle in ["python", "echo", "wrote no recording", "v.rrd", "rerun_view.py"] {
        assert!(stderr.contains(needle), "`{stderr}` should contain `{needle}`");
    }
    assert!(!out.exists());
}

/// `datagen synth` (which encodes `gt_rgb.mp4`) into `out`, on the CPUs `cpus` allows (all: None),
/// with glibc's `MALLOC_PERTURB_` set to `perturb` (None: unset, a fresh heap's zero pages).
fn synth_video(out: &Path, cpus: Option<&str>, perturb: Option<&str>) -> Vec<u8> {
    let mut command = match cpus {
        Some(list) => {
            let mut c = Command::new("taskset");
            c.args(["-c", list, env!("CARGO_BIN_EXE_datagen")]);
            c
        }
        None => datagen(),
    };
    match perturb {
        Some(byte) => command.env("MALLOC_PERTURB_", byte),
        None => command.env_remove("MALLOC_PERTURB_"),
    };
    let run = command.args(["synth", "--width", "64", "--height", "48", "--frames", "9", "--out"]).arg(out).output();
    let run = run.unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    std::fs::read(out.join("gt_rgb.mp4")).unwrap()
}

#[test]
fn encoded_video_bytes_do_not_depend_on_the_cpus_the_process_may_use() {
    // x264 picks its thread count from the CPUs the process may run on unless told, and its
    // bitstream depends on that count: the same job on one CPU and on all would differ.
    if !Command::new("taskset").args(["-c", "0", "true"]).status().is_ok_and(|s| s.success()) {
        eprintln!("taskset (util-linux) is missing or may not set the CPUs here: nothing to compare");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let all = synth_video(&dir.path().join("all"), None, None);
    let one = synth_video(&dir.path().join("one"), Some("0"), None);
    assert!(all == one, "gt_rgb.mp4 differs between one CPU and all ({} vs {} bytes)", one.len(), all.len());
}

#[test]
fn encoded_video_bytes_do_not_depend_on_what_the_heap_held() {
    // glibc fills each block malloc returns with the complement of MALLOC_PERTURB_'s byte and each
    // freed block with the byte: memory an encoder reads before writing then holds other values,
    // as it does in a long-running process (a resumed trainer job) against a fresh one. x264's
    // AVX-512 code let such memory reach the P/B frames.
    let dir = tempfile::tempdir().unwrap();
    let fresh = synth_video(&dir.path().join("fresh"), None, None);
    for byte in ["85", "170"] {
        let dirty = synth_video(&dir.path().join(byte), None, Some(byte));
        assert!(
            dirty == fresh,
            "gt_rgb.mp4 differs under MALLOC_PERTURB_={byte} ({} vs {} bytes)",
            dirty.len(),
            fresh.len()
        );
    }
}
