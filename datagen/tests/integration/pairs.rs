//! `datagen pairs` / `render` end to end: fixture accuracy through the command with the
//! ground-truth trajectories, determinism, trajectory selection, clip windows, bad input.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use crate::sequence::{fixtures, synth_sequence};

fn datagen(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_datagen")).args(args).output().unwrap()
}

fn s(path: &Path) -> &str {
    path.to_str().unwrap()
}

fn mask_bits(png: &[u8]) -> Vec<bool> {
    image::load_from_memory(png).unwrap().to_luma8().pixels().map(|p| p.0[0] > 127).collect()
}

#[test]
fn fixtures_through_pairs_with_ground_truth_trajectories() {
    for (scene, min_iou, max_false_keep) in [("scene_101", 0.975, 0.012), ("scene_102", 0.99, 0.004)] {
        let dir = tempfile::tempdir().unwrap();
        let seq = fixtures().join(scene);
        let (t0, t1) = (seq.join("gt/novel_0_c2ws.npy"), seq.join("gt/novel_1_c2ws.npy"));
        let output =
            datagen(&["pairs", s(&seq), "--out", s(dir.path()), "--trajectory", s(&t0), "--trajectory", s(&t1)]);
        assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
        let record = schemas::read_shard(&dir.path().join(format!("{scene}.parquet"))).unwrap().remove(0);
        assert_eq!(record.trajectories.len(), 2, "explicit trajectories only");
        let (mut tp, mut fp, mut fn_, mut all) = (0u64, 0u64, 0u64, 0u64);
        for (k, trajectory) in record.trajectories.iter().enumerate() {
            let truth = datagen::io::npy::read_npy_f64(&seq.join(format!("gt/covis_{k}.npy"))).unwrap();
            let plane = truth.data.len() / record.num_frames();
            for (frame, png) in trajectory.covisible_mask.iter().enumerate() {
                for (p, &t) in mask_bits(png).into_iter().zip(&truth.data[frame * plane..(frame + 1) * plane]) {
                    let t = t > 0.5;
                    tp += u64::from(p && t);
                    fp += u64::from(p && !t);
                    fn_ += u64::from(!p && t);
                    all += 1;
                }
            }
        }
        let iou = tp as f64 / (tp + fp + fn_) as f64;
        let (false_keep, false_drop) = (fp as f64 / all as f64, fn_ as f64 / all as f64);
        println!(
            "{scene} via pairs: IoU {iou:.4}, false-keep {:.3} %, false-drop {:.3} %",
            100.0 * false_keep,
            100.0 * false_drop
        );
        assert!(iou >= min_iou && false_keep <= max_false_keep, "{scene}: IoU {iou}, false-keep {false_keep}");
    }
}

/// Rejected samples (novel camera paths crossing the surface) with the paper's ranges.
#[test]
fn trajectory_rejections_on_the_fixtures_are_reported() {
    for scene in ["scene_101", "scene_102"] {
        let sequence = datagen::io::sequence::read_sequence(&fixtures().join(scene)).unwrap();
        let crossing = |i: usize, a: glam::DVec3, b: glam::DVec3| {
            datagen::pairs::trajectory::crosses_depth_surface(&sequence.depth[i], &sequence.cameras[i], a, b)
        };
        let trajectory_config = datagen::pairs::trajectory::TrajectoryConfig::paper();
        let (mut rejected, samples) = (0, 40);
        for index in 0..samples {
            let sampled = datagen::pairs::trajectory::sample_trajectory(
                &sequence.cameras,
                &sequence.depth[0],
                &trajectory_config,
                0,
                scene,
                0,
                index,
                Some(&crossing),
            )
            .unwrap();
            rejected += sampled.rejected_samples;
            let last = sampled.world_from_camera.len() - 1;
            let final_camera = sampled.world_from_camera[last].w_axis.truncate();
            assert!(
                !crossing(last, sequence.cameras[last].center(), final_camera)
                    || sampled.rejected_samples + 1 >= trajectory_config.max_attempts
            );
        }
        println!(
            "{scene}: {rejected} of {} drawn candidates rejected ({:.1} %)",
            rejected + samples,
            100.0 * rejected as f64 / (rejected + samples) as f64
        );
    }
}

fn shard_bytes(dir: &Path) -> Vec<u8> {
    std::fs::read(dir.join("synth.parquet")).unwrap()
}

#[test]
fn pairs_are_deterministic_and_trajectory_flags_select_as_documented() {
    let dir = tempfile::tempdir().unwrap();
    let seq = synth_sequence(dir.path(), 5);
    let run = |name: &str, extra: &[&str]| -> PathBuf {
        let out = dir.path().join(name);
        let mut args = vec!["pairs", s(&seq), "--out", s(&out)];
        args.extend_from_slice(extra);
        let output = datagen(&args);
        assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
        out
    };
    let a = run("a", &["--seed", "3"]);
    let b = run("b", &["--seed", "3"]);
    let c = run("c", &["--seed", "4"]);
    assert_eq!(shard_bytes(&a), shard_bytes(&b), "same seed, byte-identical shard");
    let read = |dir: &Path| schemas::read_shard(&dir.join("synth.parquet")).unwrap().remove(0);
    let (ra, rc) = (read(&a), read(&c));
    assert_eq!(ra.trajectories.len(), 2, "default: 2 sampled trajectories");
    assert_ne!(ra.trajectories[0].azimuth_deg, rc.trajectories[0].azimuth_deg, "other seed, other path");
    assert_ne!(ra.trajectories[0].azimuth_deg, ra.trajectories[1].azimuth_deg, "trajectories differ");

    // An explicit trajectory alone, then together with --trajectories 1.
    let poses: Vec<f64> = ra.trajectories[1].world_from_camera.iter().flatten().copied().collect();
    let file = dir.path().join("t.npy");
    datagen::io::npy::write_npy(&file, &[5, 4, 4], &poses).unwrap();
    let explicit = read(&run("d", &["--trajectory", s(&file)]));
    assert_eq!(explicit.trajectories.len(), 1);
    assert_eq!(explicit.trajectories[0].kind, schemas::TrajectoryKind::Explicit);
    assert_eq!(explicit.trajectories[0].covisible_mask, ra.trajectories[1].covisible_mask, "same cameras, same masks");
    let both = read(&run("e", &["--trajectory", s(&file), "--trajectories", "1", "--seed", "3"]));
    assert_eq!(both.trajectories.len(), 2);
    assert_eq!(both.trajectories[0].azimuth_deg, ra.trajectories[0].azimuth_deg);
}

#[test]
fn long_videos_are_cut_into_windows() {
    let dir = tempfile::tempdir().unwrap();
    let seq = synth_sequence(dir.path(), 12);
    let config = dir.path().join("pairs.toml");
    std::fs::write(&config, "[clip]\nlength = 5\nstride = 5\n").unwrap();
    let out = dir.path().join("out");
    let output = datagen(&["pairs", s(&seq), "--out", s(&out), "--config", s(&config), "--trajectories", "1"]);
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let records = schemas::read_shard(&out.join("synth.parquet")).unwrap();
    let starts: Vec<u32> = records.iter().map(|r| r.clip_start).collect();
    assert_eq!(starts, vec![0, 5]);
    assert!(records.iter().all(|r| r.num_frames() == 5));
}

#[test]
fn render_writes_video_frames_and_holes() {
    let dir = tempfile::tempdir().unwrap();
    let seq = synth_sequence(dir.path(), 3);
    // The source poses shifted sideways by 0.3 in world x.
    let source = datagen::io::npy::read_npy_f64(&seq.join("cam_info/megasam_c2ws.npy")).unwrap();
    let shifted: Vec<f64> =
        source.data.iter().enumerate().map(|(i, &v)| if i % 16 == 3 { v + 0.3 } else { v }).collect();
    let file = dir.path().join("traj.npy");
    datagen::io::npy::write_npy(&file, &[3, 4, 4], &shifted).unwrap();
    let out = dir.path().join("render");
    let output = datagen(&["render", s(&seq), "--trajectory", s(&file), "--out", s(&out)]);
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    assert_eq!(foundation::video::decode_video(&out.join("render.mp4")).unwrap().frames.len(), 3);
    let holes = image::open(out.join("holes/00001.png")).unwrap().to_luma8();
    let hole_fraction = holes.pixels().filter(|p| p.0[0] == 255).count() as f64 / (64.0 * 48.0);
    assert!(hole_fraction > 0.0 && hole_fraction < 0.5, "a sideways step opens some holes: {hole_fraction}");
    let frame = image::open(out.join("frames/00001.png")).unwrap().to_rgb8();
    assert!(frame.pixels().zip(holes.pixels()).all(|(c, h)| h.0[0] == 0 || c.0 == [0, 0, 0]), "holes are black");
}

/// Runs `pairs` on a broken copy and checks the failure: non-zero exit, one message naming the
/// file and field, nothing in the output folder.
fn fails_cleanly(seq: &Path, out: &Path, extra: &[&str], needles: &[&str]) {
    let mut args = vec!["pairs", s(seq), "--out", s(out)];
    args.extend_from_slice(extra);
    let output = datagen(&args);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success(), "{needles:?}: must fail");
    for needle in needles {
        assert!(stderr.contains(needle), "`{stderr}` should name `{needle}`");
    }
    let leftovers: Vec<_> =
        std::fs::read_dir(out).map(|d| d.map(|e| e.unwrap().file_name()).collect()).unwrap_or_default();
    assert!(leftovers.is_empty(), "nothing written for bad input: {leftovers:?}");
}

#[test]
fn bad_input_exits_non_zero_naming_file_and_field_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let good = synth_sequence(dir.path(), 3);
    let out = dir.path().join("out");
    let copy = |name: &str| -> PathBuf {
        let target = dir.path().join(name);
        let status = Command::new("cp").arg("-r").arg(&good).arg(&target).status().unwrap();
        assert!(status.success());
        target
    };
    let npy = |seq: &Path, name: &str| seq.join("cam_info").join(name);

    let seq = copy("no_video");
    std::fs::remove_file(seq.join("gt_rgb.mp4")).unwrap();
    fails_cleanly(&seq, &out, &[], &["gt_rgb.mp4"]);

    let seq = copy("no_depth");
    std::fs::remove_file(npy(&seq, "megasam_depth.npy")).unwrap();
    fails_cleanly(&seq, &out, &[], &["megasam_depth.npy"]);

    let seq = copy("truncated");
    let bytes = std::fs::read(npy(&seq, "megasam_c2ws.npy")).unwrap();
    std::fs::write(npy(&seq, "megasam_c2ws.npy"), &bytes[..bytes.len() - 20]).unwrap();
    fails_cleanly(&seq, &out, &[], &["megasam_c2ws.npy", "megasam_c2ws"]);

    let seq = copy("count_mismatch");
    let poses = datagen::io::npy::read_npy_f64(&npy(&seq, "megasam_c2ws.npy")).unwrap();
    datagen::io::npy::write_npy(&npy(&seq, "megasam_c2ws.npy"), &[2, 4, 4], &poses.data[..32]).unwrap();
    fails_cleanly(&seq, &out, &[], &["megasam_c2ws.npy", "world_from_camera", "2 poses for 3 frames"]);

    let seq = copy("nan_pose");
    let mut bad = poses.data.clone();
    bad[5] = f64::NAN;
    datagen::io::npy::write_npy(&npy(&seq, "megasam_c2ws.npy"), &[3, 4, 4], &bad).unwrap();
    fails_cleanly(&seq, &out, &[], &["megasam_c2ws.npy", "world_from_camera[0]"]);

    let seq = copy("dead_depth");
    let depth = datagen::io::npy::read_npy_f32(&npy(&seq, "megasam_depth.npy")).unwrap();
    datagen::io::npy::write_npy(&npy(&seq, "megasam_depth.npy"), &depth.shape, &vec![f32::NAN; depth.data.len()])
        .unwrap();
    fails_cleanly(&seq, &out, &[], &["megasam_depth.npy", "depth[0]"]);

    let seq = copy("zero_size");
    datagen::io::npy::write_npy(&npy(&seq, "megasam_depth.npy"), &[3, 0, 64], &Vec::<f32>::new()).unwrap();
    fails_cleanly(&seq, &out, &[], &["megasam_depth.npy", "zero-size"]);

    let trajectory = dir.path().join("short.npy");
    datagen::io::npy::write_npy(&trajectory, &[2, 4, 4], &poses.data[..32]).unwrap();
    fails_cleanly(
        &good,
        &out,
        &["--trajectory", s(&trajectory)],
        &["short.npy", "world_from_camera", "2 poses for a sequence of 3 frames"],
    );
}
