//! Trajectory bank: collect → sample → pairs end to end (relative motion, skipped windows,
//! determinism, rejection, provenance), and bad banks and configs named by file and field.

use std::path::{Path, PathBuf};

use datagen::io::sequence::{Sequence, read_sequence};
use datagen::pairs::clip::ClipConfig;
use datagen::pairs::generator::{PairsConfig, TrajectoryRequest, generate_clips};
use datagen::pairs::trajectory::{NovelTrajectory, Sampler, TrajectoryConfig, sample_novel_trajectory};
use datagen::pairs::trajectory_bank::{CollectSummary, TrajectoryBank, collect_from_sequence};
use glam::{DMat4, DVec3};
use schemas::{BankEntry, TrajectoryKind};

/// A synthetic sequence of `frames` frames (its camera moves).
fn sequence(dir: &Path, frames: u32) -> Sequence {
    read_sequence(&crate::sequence::synth_sequence(dir, frames)).unwrap()
}

/// Collects the bank of `sequence` in windows of `length` frames and writes it to `dir/bank.parquet`.
fn bank_file(dir: &Path, sequence: &Sequence, length: u32) -> (PathBuf, CollectSummary) {
    let mut summary = CollectSummary::default();
    let clip = ClipConfig { length, stride: length, max_clips: 0 };
    collect_from_sequence(sequence, "synth", &clip, 1.0, &mut summary);
    let path = dir.join("bank.parquet");
    schemas::write_bank(&path, &summary.entries).unwrap();
    (path, summary)
}

fn bank_config(bank: &Path, sampler: Sampler, fraction: f64) -> PairsConfig {
    let mut config = PairsConfig::default();
    config.trajectory.sampler = sampler;
    config.trajectory.bank = Some(bank.to_owned());
    config.trajectory.bank_fraction = fraction;
    config
}

#[test]
fn collect_stores_motion_relative_to_the_first_camera_in_pivot_units_and_skips_static_windows() {
    let dir = tempfile::tempdir().unwrap();
    let mut sequence = sequence(dir.path(), 12);
    // Windows [0, 4) moving, [4, 8) static (every camera equals frame 4's), [8, 12) non-finite.
    let still = sequence.cameras[4].world_from_camera;
    for camera in &mut sequence.cameras[4..8] {
        camera.world_from_camera = still;
    }
    sequence.cameras[10].world_from_camera.w_axis.x = f64::NAN;
    let mut summary = CollectSummary::default();
    let clip = ClipConfig { length: 4, stride: 4, max_clips: 0 };
    collect_from_sequence(&sequence, "synth", &clip, 1.0, &mut summary);
    assert_eq!((summary.windows, summary.static_windows, summary.degenerate_windows), (3, 1, 1));
    assert_eq!(summary.entries.len(), 1);
    let entry = &summary.entries[0];
    assert_eq!(entry.entry_id, format!("synth/{}/0", sequence.source_id));
    assert_eq!((entry.window_start, entry.num_frames()), (0, 4));
    let pivot = datagen::pairs::clip::pivot_distance(&sequence.depth[0], &sequence.cameras[0], 1.0);
    assert!((entry.pivot_distance - pivot).abs() < 1e-12);
    assert!(foundation::camera::mat4_from_row_major(&entry.relative_pose[0]).abs_diff_eq(DMat4::IDENTITY, 1e-12));
    let first = sequence.cameras[0].world_from_camera;
    for (t, pose) in entry.relative_pose.iter().enumerate() {
        let expected = first.inverse() * sequence.cameras[t].world_from_camera;
        let pose = foundation::camera::mat4_from_row_major(pose);
        assert!((pose.w_axis.truncate() * pivot).abs_diff_eq(expected.w_axis.truncate(), 1e-9), "frame {t}");
        assert!(pose.x_axis.abs_diff_eq(expected.x_axis, 1e-9));
    }
    let steps: f64 =
        (1..4).map(|t| (sequence.cameras[t].center() - sequence.cameras[t - 1].center()).length() / pivot).sum();
    assert!((entry.path_length - steps).abs() < 1e-9 && entry.path_length > 0.0);
    let net = foundation::camera::mat4_from_row_major(&entry.relative_pose[3]).w_axis.truncate();
    assert!(DVec3::from_array(entry.net_translation).abs_diff_eq(net, 1e-12));
    assert!(!entry.dominant_direction.is_empty());
}

#[test]
fn bank_sampler_is_deterministic_records_its_entry_and_survives_the_shard() {
    let dir = tempfile::tempdir().unwrap();
    let sequence = sequence(dir.path(), 8);
    let (bank_path, summary) = bank_file(dir.path(), &sequence, 4);
    assert_eq!(summary.entries.len(), 2);
    let request = TrajectoryRequest { sampled: 3, explicit: Vec::new() };
    let config = bank_config(&bank_path, Sampler::Bank, 0.5);
    let records = generate_clips(&sequence, "synth", &config, &request, 11).unwrap();
    assert_eq!(records, generate_clips(&sequence, "synth", &config, &request, 11).unwrap(), "deterministic");
    let digest = blake3::hash(&std::fs::read(&bank_path).unwrap()).to_hex().to_string();
    let ids: Vec<&str> = summary.entries.iter().map(|e| e.entry_id.as_str()).collect();
    for trajectory in &records[0].trajectories {
        assert_eq!(trajectory.kind, TrajectoryKind::Bank);
        let drawn = trajectory.bank_entry.as_ref().expect("bank provenance");
        assert_eq!(ids[drawn.entry_row as usize], drawn.entry_id);
        assert_eq!(drawn.bank_digest, digest);
        assert!(drawn.roll_deg.abs() <= 180.0);
        assert!(trajectory.covisible_fraction > 0.0, "the composed path still sees the scene");
    }
    let other_seed = generate_clips(&sequence, "synth", &config, &request, 12).unwrap();
    assert_ne!(records[0].trajectories[0].world_from_camera, other_seed[0].trajectories[0].world_from_camera);
    // Provenance survives the shard.
    let (shard, _) = datagen::pairs::generator::write_shard(
        &dir.path().join("pairs"),
        "synth",
        &records,
        schemas::InputDigest { source_path: "synth".into(), content_hash: String::new() },
    )
    .unwrap();
    assert_eq!(schemas::read_shard(&shard).unwrap(), records);

    // `mixed` at 0 is exactly the spherical sampler; at 1 it is the bank sampler.
    let spherical = generate_clips(&sequence, "synth", &PairsConfig::default(), &request, 11).unwrap();
    let none = generate_clips(&sequence, "synth", &bank_config(&bank_path, Sampler::Mixed, 0.0), &request, 11).unwrap();
    assert_eq!(none, spherical);
    let all = generate_clips(&sequence, "synth", &bank_config(&bank_path, Sampler::Mixed, 1.0), &request, 11).unwrap();
    assert!(all[0].trajectories.iter().all(|t| t.kind == TrajectoryKind::Bank));
}

/// A bank of one entry: the camera pans right by 20° in place over `frames` frames.
fn pan_bank(dir: &Path, frames: usize) -> PathBuf {
    let relative_pose = (0..frames)
        .map(|t| {
            let angle = 20f64.to_radians() * t as f64 / (frames - 1) as f64;
            foundation::camera::mat4_to_row_major(&DMat4::from_rotation_y(angle))
        })
        .collect();
    let entry = BankEntry {
        entry_id: "synth/pan/0".into(),
        dataset: "synth".into(),
        video_id: "pan".into(),
        source_path: "/pan".into(),
        window_start: 0,
        fps: 24.0,
        pivot_distance: 1.0,
        relative_pose,
        total_rotation_deg: 20.0,
        path_length: 0.0,
        net_translation: [0.0; 3],
        dominant_direction: "pan right".into(),
    };
    let path = dir.join("pan.parquet");
    schemas::write_bank(&path, &[entry]).unwrap();
    path
}

#[test]
fn bank_motion_turns_about_the_pivot_mirrors_and_rolls() {
    let dir = tempfile::tempdir().unwrap();
    let sequence = sequence(dir.path(), 5);
    let bank = TrajectoryBank::load(&pan_bank(dir.path(), 9)).unwrap();
    let sources: Vec<DMat4> = sequence.cameras.iter().map(|c| c.world_from_camera).collect();
    let pivot = 3.0;
    let path = bank.compose(0, &sources, pivot, false, 0.0);
    assert!(path[0].abs_diff_eq(sources[0], 1e-9), "the motion starts at the source camera");
    for (t, (novel, source)) in path.iter().zip(&sources).enumerate() {
        // The pivot stays on the novel optical axis at distance R: a pan became an orbit.
        let pivot_point = source.transform_point3(DVec3::new(0.0, 0.0, pivot));
        let seen = novel.inverse().transform_point3(pivot_point);
        assert!(seen.x.abs() < 1e-9 && seen.y.abs() < 1e-9 && (seen.z - pivot).abs() < 1e-9, "frame {t}: {seen}");
    }
    // Resampled in time: the last clip frame has the entry's full 20° turn.
    let last = sources[4].inverse() * path[4];
    let centre = last.w_axis.truncate();
    let expected =
        DVec3::new(0.0, 0.0, pivot) - DMat4::from_rotation_y(20f64.to_radians()).transform_vector3(DVec3::Z) * pivot;
    assert!(centre.abs_diff_eq(expected, 1e-9), "{centre} vs {expected}");
    // Mirroring flips left/right; a half-turn roll flips left/right and up/down.
    let mirrored = (sources[4].inverse() * bank.compose(0, &sources, pivot, true, 0.0)[4]).w_axis.truncate();
    assert!(mirrored.abs_diff_eq(DVec3::new(-centre.x, centre.y, centre.z), 1e-9));
    let rolled = (sources[4].inverse() * bank.compose(0, &sources, pivot, false, 180.0)[4]).w_axis.truncate();
    assert!(rolled.abs_diff_eq(DVec3::new(-centre.x, -centre.y, centre.z), 1e-9));
}

#[test]
fn crossing_bank_candidates_are_rejected_and_redrawn() {
    let dir = tempfile::tempdir().unwrap();
    let sequence = sequence(dir.path(), 5);
    let bank = TrajectoryBank::load(&pan_bank(dir.path(), 5)).unwrap();
    let config =
        TrajectoryConfig { sampler: Sampler::Bank, bank: Some(dir.path().join("pan.parquet")), ..Default::default() };
    // A wall on the source camera's right: any path whose camera moves to +x crosses it.
    let cameras = &sequence.cameras;
    let right_wall =
        |i: usize, _: DVec3, to: DVec3| cameras[i].world_from_camera.inverse().transform_point3(to).x > 1e-6;
    let (mut rejected, mut accepted) = (0, 0);
    for index in 0..16 {
        let draw = || {
            sample_novel_trajectory(
                cameras,
                &sequence.depth[0],
                &config,
                Some(&bank),
                5,
                "clip",
                0,
                index,
                Some(&right_wall),
            )
            .unwrap()
        };
        let NovelTrajectory::Bank(trajectory) = draw() else { panic!("bank sampler") };
        assert_eq!(NovelTrajectory::Bank(trajectory.clone()), draw(), "deterministic");
        rejected += trajectory.rejected_samples;
        if trajectory.rejected_samples + 1 < config.max_attempts {
            accepted += 1;
            let crosses = trajectory
                .world_from_camera
                .iter()
                .enumerate()
                .any(|(i, p)| right_wall(i, DVec3::ZERO, p.w_axis.truncate()));
            assert!(!crosses, "accepted paths stay left of the wall");
        }
    }
    assert!(rejected > 0 && accepted > 0, "rejected {rejected}, accepted {accepted}");
}

#[test]
fn bad_banks_and_sampler_keys_are_named_by_file_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let first_line = |e: datagen::Error| e.to_string().lines().next().unwrap().to_owned();
    // Empty bank.
    let empty = dir.path().join("empty.parquet");
    schemas::write_bank(&empty, &[]).unwrap();
    let error = first_line(TrajectoryBank::load(&empty).unwrap_err());
    assert!(error.contains("empty.parquet") && error.contains("no entries"), "{error}");
    // Non-finite pose.
    let sequence = sequence(dir.path(), 4);
    let (_, mut summary) = bank_file(dir.path(), &sequence, 4);
    summary.entries[0].relative_pose[2][7] = f64::INFINITY;
    let bad = dir.path().join("bad.parquet");
    schemas::write_bank(&bad, &summary.entries).unwrap();
    let error = first_line(TrajectoryBank::load(&bad).unwrap_err());
    assert!(error.contains("bad.parquet") && error.contains("relative_pose") && error.contains("frame 2"), "{error}");
    // Another schema: a training-pair shard given as the bank, through `datagen pairs`' path.
    let records = generate_clips(
        &sequence,
        "synth",
        &PairsConfig::default(),
        &TrajectoryRequest { sampled: 1, explicit: vec![] },
        0,
    )
    .unwrap();
    let (shard, _) = datagen::pairs::generator::write_shard(
        &dir.path().join("pairs"),
        "synth",
        &records,
        schemas::InputDigest { source_path: "synth".into(), content_hash: String::new() },
    )
    .unwrap();
    let request = TrajectoryRequest { sampled: 1, explicit: Vec::new() };
    let error = first_line(
        generate_clips(&sequence, "synth", &bank_config(&shard, Sampler::Bank, 0.5), &request, 0).unwrap_err(),
    );
    assert!(
        error.contains("synth.parquet") && error.contains("cognvs.schema") && error.contains("cognvs.pairs"),
        "{error}"
    );
    // Config keys.
    for (text, key) in [
        ("[trajectory]\nsampler = \"mixed\"\nbank = \"b.parquet\"\nbank_fraction = 1.5\n", "trajectory.bank_fraction"),
        ("[trajectory]\nsampler = \"mixed\"\nbank = \"b.parquet\"\nbank_fraction = nan\n", "trajectory.bank_fraction"),
        ("[trajectory]\nsampler = \"bank\"\n", "trajectory.bank"),
        ("[trajectory]\nsampler = \"banks\"\n", "trajectory.sampler"),
        ("[trajectory]\nbank_roll_deg = -1\n", "trajectory.bank_roll_deg"),
    ] {
        let path = dir.path().join("pairs.toml");
        std::fs::write(&path, text).unwrap();
        let error = first_line(PairsConfig::from_toml_file(&path).unwrap_err());
        assert!(error.starts_with(&format!("{}: key `{key}`", path.display())), "{text:?}: {error}");
    }
}
