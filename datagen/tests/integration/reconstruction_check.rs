//! `datagen check`: exact synthetic reconstructions score ok on slow and fast camera paths; the
//! same scenes with perturbed poses, per-frame depth scales, a pose jump or each convention slip
//! users make (written in the tool's own format) score suspect with the reason naming it.

use std::path::{Path, PathBuf};
use std::process::Command;

use datagen::geometry::consistency::{CheckConfig, CheckReport, ProbeOutcome, Slip, check_folder_with};
use datagen::io::sequence::ReadOptions;
use datagen::synth::SynthConfig;
use glam::{DMat4, DQuat, DVec3, DVec4};

use crate::tool_layouts::{
    QuaternionOrder, Truth, write_colmap, write_colmap_ordered, write_depth_only_values, write_gen3c_w2c,
    write_vggt_extrinsics,
};

/// A scene whose camera sweeps ~25° over its 12 frames (seed 3), enough for both configured
/// frame gaps (1 and 5), written losslessly (a COLMAP workspace: PNG frames, float32 depth):
/// the tiny synthetic videos' H.264 frames are off by tens of levels at texture edges.
fn truth() -> Truth {
    Truth::of(SynthConfig { width: 96, height: 64, frames: 12, seed: 3, ..SynthConfig::default() })
}

/// The sweep of the slow path, degrees over the 12 frames: ~0.4° and ~0.04 m a frame, where
/// neighbouring frames barely tell conventions apart.
const SLOW_SWEEP_DEG: f64 = 4.0;

/// The seed-3 scene on a slow camera path.
fn slow_truth() -> Truth {
    Truth::of(SynthConfig {
        width: 96,
        height: 64,
        frames: 12,
        seed: 3,
        camera_sweep_deg: Some(SLOW_SWEEP_DEG),
        ..SynthConfig::default()
    })
}

/// Adds the moving objects' masks beside a tool's output (`masks/`, read in any layout), as a
/// user adds a segmenter's masks.
fn add_masks(truth: &Truth, seq: &Path) {
    std::fs::create_dir_all(seq.join("masks")).unwrap();
    for (i, mask) in truth.masks.iter().enumerate() {
        mask.save(seq.join(format!("masks/{i:05}.png"))).unwrap();
    }
}

/// The COLMAP workspace with the moving objects' masks beside it.
fn write_with_masks(truth: &Truth, dir: &Path, binary: bool) -> PathBuf {
    let seq = write_colmap(truth, dir, binary);
    add_masks(truth, &seq);
    seq
}

fn check_dir(seq: &Path) -> CheckReport {
    check_folder_with(seq, None, &ReadOptions::default(), &CheckConfig::default()).unwrap()
}

fn check(truth: &Truth, dir: &Path, name: &str) -> (PathBuf, CheckReport) {
    let seq = write_with_masks(truth, &dir.join(name), true);
    let report = check_dir(&seq);
    (seq, report)
}

#[test]
fn exact_reconstruction_is_ok_and_perturbations_are_suspect() {
    let dir = tempfile::tempdir().unwrap();
    let (_, exact) = check(&truth(), dir.path(), "exact");
    assert_eq!(exact.verdict, "ok", "{}", exact.to_text());
    assert!(exact.static_depth_consistency > 0.9, "{}", exact.to_text());
    assert!(exact.reasons.is_empty());
    assert!(exact.pairs.iter().all(|p| p.compared > 0 && p.share > 0.7), "{}", exact.to_text());
    assert!(exact.camera_path.length > 0.0 && exact.camera_path.jumps.is_empty());

    // Poses perturbed by ±2° about the vertical axis (~3 px), alternating per frame.
    let mut perturbed = truth();
    for (i, pose) in perturbed.world_from_camera.iter_mut().enumerate() {
        let sign = if i % 2 == 0 { 1.0 } else { -1.0 };
        *pose *= DMat4::from_quat(DQuat::from_rotation_y(sign * 2f64.to_radians()));
    }
    let (_, report) = check(&perturbed, dir.path(), "poses");
    assert_eq!(report.verdict, "suspect", "{}", report.to_text());
    assert!(report.static_depth_consistency < exact.static_depth_consistency - 0.2, "{}", report.to_text());
    assert!(report.reasons.iter().any(|r| r.contains("static depth consistency")), "{:?}", report.reasons);

    // Depth scaled per frame by ±15 %.
    let mut scaled = truth();
    for (i, depth) in scaled.depth.iter_mut().enumerate() {
        let scale = if i % 2 == 0 { 0.85 } else { 1.15 };
        depth.iter_mut().for_each(|d| *d *= scale);
    }
    let (_, report) = check(&scaled, dir.path(), "scaled");
    assert_eq!(report.verdict, "suspect", "{}", report.to_text());
    assert!(report.static_depth_consistency < 0.5, "{}", report.to_text());
}

#[test]
fn inverted_poses_are_named_as_a_convention_mix_up() {
    let dir = tempfile::tempdir().unwrap();
    let mut inverted = truth();
    for pose in &mut inverted.world_from_camera {
        *pose = pose.inverse();
    }
    let (_, report) = check(&inverted, dir.path(), "inverted");
    assert_eq!(report.verdict, "suspect", "{}", report.to_text());
    let probe = report.convention_probes.iter().find(|p| p.slip == Slip::CameraFromWorld).unwrap();
    assert_eq!(probe.outcome, ProbeOutcome::FitsBetter, "{}", report.to_text());
    assert!(report.reasons.iter().any(|r| r.contains("camera-from-world")), "{:?}", report.reasons);
}

#[test]
fn a_camera_jump_is_reported_with_its_frame() {
    let dir = tempfile::tempdir().unwrap();
    let mut jumped = truth();
    for pose in &mut jumped.world_from_camera[7..] {
        *pose = DMat4::from_translation(DVec3::new(3.0, 0.0, 0.0)) * *pose;
    }
    let (_, report) = check(&jumped, dir.path(), "jump");
    assert_eq!(report.camera_path.jumps, vec![7], "{}", report.to_text());
    assert!(report.reasons.iter().any(|r| r.contains("jumps at frame(s) [7]")), "{:?}", report.reasons);
}

#[test]
fn check_command_prints_json_with_verdict_reasons_and_consistency() {
    let dir = tempfile::tempdir().unwrap();
    let seq = write_with_masks(&truth(), &dir.path().join("cli"), false);
    let output =
        Command::new(env!("CARGO_BIN_EXE_datagen")).args(["check", seq.to_str().unwrap(), "--json"]).output().unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let json: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(json["verdict"], "ok");
    assert!(json["reasons"].as_array().unwrap().is_empty());
    let consistency = json["static_depth_consistency"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&consistency) && consistency > 0.9, "{consistency}");
    assert_eq!(json["layout"], "colmap");
    assert!(json["pairs"].as_array().unwrap().len() >= 2 * 11);

    let text = Command::new(env!("CARGO_BIN_EXE_datagen"))
        .args(["check", seq.to_str().unwrap(), "--layout", "colmap"])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&text.stdout);
    assert!(text.contains("static depth consistency") && text.contains("verdict: ok"), "{text}");
}

#[test]
fn build_skips_reconstructions_below_the_threshold_and_reports_the_distribution() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    write_with_masks(&truth(), &root.join("sequences/good"), true);
    let mut perturbed = truth();
    for (i, pose) in perturbed.world_from_camera.iter_mut().enumerate() {
        let sign = if i % 2 == 0 { 1.0 } else { -1.0 };
        *pose *= DMat4::from_quat(DQuat::from_rotation_y(sign * 2f64.to_radians()));
    }
    write_with_masks(&perturbed, &root.join("sequences/bad"), true);
    let out = root.join("corpus");
    let config = root.join("corpus.toml");
    std::fs::write(
        &config,
        format!(
            "[[sources]]\ndataset = \"sequences\"\nroot = \"{}\"\n\n[output]\ndir = \"{}\"\n\n[pairs.clip]\nlength = 5\nstride = 4\n\n\
             [check]\nmin_static_depth_consistency = 0.8\n",
            root.join("sequences").display(),
            out.display()
        ),
    )
    .unwrap();
    let output = Command::new(env!("CARGO_BIN_EXE_datagen"))
        .args(["build", "--config", config.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let status = datagen::corpus::build::read_corpus_status(&out).unwrap();
    assert_eq!(status["sequences/good"].status, schemas::InputStatus::Ok, "{}", status["sequences/good"].reason);
    let bad = &status["sequences/bad"];
    assert_eq!(bad.status, schemas::InputStatus::Skipped);
    assert!(bad.reason.contains("static_depth_consistency") && bad.reason.contains("below"), "{}", bad.reason);
    let scores = datagen::corpus::quality::read_scores(&out).unwrap();
    assert_eq!(scores.len(), 2);
    assert!(scores.iter().any(|&s| s >= 0.8) && scores.iter().any(|&s| s < 0.8), "{scores:?}");

    let report = root.join("report.html");
    let output = Command::new(env!("CARGO_BIN_EXE_datagen"))
        .args(["inspect", out.to_str().unwrap(), "--report", report.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let html = std::fs::read_to_string(&report).unwrap();
    assert!(html.contains("Reconstruction checks") && html.contains("2 inputs checked"), "report lacks the checks");
}

/// The Blender fixtures (exact depth and cameras of rendered scenes, MegaSAM's file layout): both
/// score ok as they are (0.88 and 0.98 when this test was written) and suspect with ±2° of pose
/// error (~0.64).
#[test]
fn blender_fixtures_are_ok_and_suspect_with_perturbed_poses() {
    use datagen::io::npy::{read_npy_f64, write_npy};
    let dir = tempfile::tempdir().unwrap();
    for scene in ["scene_101", "scene_102"] {
        let fixture = crate::sequence::fixtures().join(scene);
        let report = check_dir(&fixture);
        assert_eq!(report.verdict, "ok", "{}", report.to_text());

        let copy = dir.path().join(scene);
        std::fs::create_dir_all(copy.join("cam_info")).unwrap();
        std::fs::copy(fixture.join("gt_rgb.mp4"), copy.join("gt_rgb.mp4")).unwrap();
        for name in ["megasam_depth.npy", "megasam_intrinsics.npy"] {
            std::fs::copy(fixture.join("cam_info").join(name), copy.join("cam_info").join(name)).unwrap();
        }
        let poses = read_npy_f64(&fixture.join("cam_info/megasam_c2ws.npy")).unwrap();
        let perturbed: Vec<f64> = poses
            .data
            .chunks(16)
            .enumerate()
            .flat_map(|(i, pose)| {
                let sign = if i % 2 == 0 { 1.0 } else { -1.0 };
                let pose = foundation::camera::mat4_from_row_major(pose)
                    * DMat4::from_quat(DQuat::from_rotation_y(sign * 2f64.to_radians()));
                foundation::camera::mat4_to_row_major(&pose)
            })
            .collect();
        write_npy(&copy.join("cam_info/megasam_c2ws.npy"), &poses.shape, &perturbed).unwrap();
        let report = check_dir(&copy);
        assert_eq!(report.verdict, "suspect", "{}", report.to_text());
        assert!(report.static_depth_consistency < 0.75, "{}", report.to_text());
    }
}

/// Writes the `truth` scene in each tool format the slips below use, exactly.
fn write_exact(truth: &Truth, dir: &Path) -> Vec<PathBuf> {
    let camera_from_world: Vec<DMat4> = (0..truth.n()).map(|i| truth.camera_from_world(i)).collect();
    let vggt = write_vggt_extrinsics(truth, &dir.join("vggt"), &camera_from_world);
    let colmap = write_colmap(truth, &dir.join("colmap"), false);
    let depth_only = write_depth_only_values(truth, &dir.join("depth_only"), &truth.depth);
    let seqs = vec![vggt, colmap, depth_only];
    for seq in &seqs {
        add_masks(truth, seq);
    }
    seqs
}

#[test]
fn exact_reconstructions_are_ok_and_the_probes_decide_on_slow_and_fast_paths() {
    let dir = tempfile::tempdir().unwrap();
    for (name, truth) in [("fast", truth()), ("slow", slow_truth())] {
        for seq in write_exact(&truth, &dir.path().join(name)) {
            let report = check_dir(&seq);
            assert_eq!(report.verdict, "ok", "{name}: {}", report.to_text());
            // The pose and axis probes tell the conventions apart even on the slow path: the
            // right one is known, not merely not contradicted.
            for probe in &report.convention_probes {
                assert_ne!(probe.outcome, ProbeOutcome::FitsBetter, "{name}: {}", report.to_text());
                if matches!(probe.slip, Slip::CameraFromWorld | Slip::OpenGlAxes | Slip::QuaternionOrder) {
                    assert_eq!(probe.outcome, ProbeOutcome::Rejected, "{name}: {}", report.to_text());
                }
            }
        }
    }
}

/// Each slip applied to files in the tool's own format, on the slow and the fast path: suspect,
/// with the reason naming the slip (and no other convention named).
#[test]
fn convention_slips_are_suspect_and_named_on_slow_and_fast_paths() {
    let dir = tempfile::tempdir().unwrap();
    let flip = DMat4::from_diagonal(DVec4::new(1.0, -1.0, -1.0, 1.0));
    for (name, truth) in [("fast", truth()), ("slow", slow_truth())] {
        let root = dir.path().join(name);
        let camera_from_world: Vec<DMat4> = (0..truth.n()).map(|i| truth.camera_from_world(i)).collect();
        // VGGT's `extrinsic` holding camera-to-world matrices.
        let vggt = write_vggt_extrinsics(&truth, &root.join("vggt_c2w"), &truth.world_from_camera);
        // GEN3C's `w2c` in OpenGL camera axes (y up, z backwards).
        let opengl: Vec<DMat4> = camera_from_world.iter().map(|m| flip * *m).collect();
        let gen3c = write_gen3c_w2c(&truth, &root.join("gen3c_opengl"), &opengl);
        // COLMAP's qvec written x, y, z, w.
        let colmap = write_colmap_ordered(&truth, &root.join("colmap_xyzw"), true, QuaternionOrder::Xyzw);
        // Video Depth Anything's relative output (disparity, scale 3) declared as z-depth.
        let disparity: Vec<Vec<f32>> =
            truth.depth.iter().map(|d| d.iter().map(|&v| if v > 0.0 { 3.0 / v } else { 0.0 }).collect()).collect();
        let vda = write_depth_only_values(&truth, &root.join("vda_disparity"), &disparity);
        // Depth in millimetres with the poses in metres.
        let millimetres: Vec<Vec<f32>> = truth.depth.iter().map(|d| d.iter().map(|&v| 1000.0 * v).collect()).collect();
        let mm = write_depth_only_values(&truth, &root.join("millimetres"), &millimetres);
        for (seq, slip) in [
            (vggt, Slip::CameraFromWorld),
            (gen3c, Slip::OpenGlAxes),
            (colmap, Slip::QuaternionOrder),
            (vda, Slip::Disparity),
            (mm, Slip::Millimetres),
        ] {
            add_masks(&truth, &seq);
            let report = check_dir(&seq);
            let context = format!("{name} {}: {}", seq.display(), report.to_text());
            assert_eq!(report.verdict, "suspect", "{context}");
            let named: Vec<Slip> =
                Slip::ALL.into_iter().filter(|s| report.reasons.iter().any(|r| r.contains(s.describe()))).collect();
            assert_eq!(named, vec![slip], "{context}");
        }
    }
}

/// A 4° turn of every pose from frame 7 on (a re-initialised tracker) on the slow and the fast
/// path: the mean hides it, the stretch across frames 6 | 7 and the rotation steps do not.
#[test]
fn a_pose_jump_is_suspect_with_its_frames_on_slow_and_fast_paths() {
    let dir = tempfile::tempdir().unwrap();
    for (name, mut truth) in [("fast", truth()), ("slow", slow_truth())] {
        for pose in &mut truth.world_from_camera[7..] {
            *pose *= DMat4::from_quat(DQuat::from_rotation_y(4f64.to_radians()));
        }
        let (_, report) = check(&truth, dir.path(), name);
        assert_eq!(report.verdict, "suspect", "{name}: {}", report.to_text());
        let stretch = report.worst_stretch.as_ref().unwrap();
        assert_eq!((stretch.before, stretch.after), (6, 7), "{name}: {}", report.to_text());
        assert!(
            report.reasons.iter().any(|r| r.contains("a jump between frames 6 and 7")),
            "{name}: {:?}",
            report.reasons
        );
        assert_eq!(report.camera_path.rotation_jumps, vec![7], "{name}: {}", report.to_text());
        // The per-pair scores are kept: the pair across the jump is among the worst.
        let across = report.pairs.iter().find(|p| (p.from, p.to) == (6, 7)).unwrap();
        let before = report.pairs.iter().find(|p| (p.from, p.to) == (2, 3)).unwrap();
        assert!(across.share < before.share - 0.2, "{name}: {}", report.to_text());
    }
}

/// One frame's colours spoiled (as a video keyframe of another compression quality, or a blurred
/// frame, does): the pairs with that frame agree less, but the wider pairs across its boundaries
/// do not, so it is no jump.
#[test]
fn one_bad_frame_is_no_pose_jump() {
    let dir = tempfile::tempdir().unwrap();
    let mut truth = truth();
    for (i, value) in truth.frames[6].iter_mut().enumerate() {
        if i % 3 == 0 {
            *value = value.wrapping_add(64);
        }
    }
    let (_, report) = check(&truth, dir.path(), "bad_frame");
    let stretch = report.worst_stretch.as_ref().unwrap();
    assert!([5, 6].contains(&stretch.before) && stretch.consistency < 0.8, "{}", report.to_text());
    assert!(!report.reasons.iter().any(|r| r.contains("a jump between")), "{}", report.to_text());
}
