//! Multi-view pairs on synthetic multi-camera scenes with exact ground truth: the target is camera
//! t's real frames, the conditioning is camera s's frames through the real renderer and matches
//! the target on the masked pixels up to resampling, frames are matched by instant, choices are
//! deterministic by seed, and a corpus build fails a broken scene alone.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Command;

use datagen::geometry::covisibility::{CovisibilityConfig, target_visibility_mask};
use datagen::geometry::depth_mesh::{DepthMesh, MeshConfig};
use datagen::geometry::render::{render_novel_view, source_colour};
use datagen::io::multiview::{MultiViewScene, read_multiview};
use datagen::pairs::generator::PairsConfig;
use datagen::pairs::multiview::MultiViewConfig;
use datagen::pairs::scene::generate_scene_clips;
use datagen::synth::{CameraRig, SynthConfig, SynthScene, write_multiview};
use schemas::{ClipRecord, InputStatus, PairKind, TrajectoryKind};

const RIG: CameraRig = CameraRig { cameras: 3, spacing_deg: 8.0 };

fn synth(width: u32, height: u32, frames: u32) -> SynthConfig {
    SynthConfig { width, height, frames, ..SynthConfig::default() }
}

fn datagen() -> Command {
    Command::new(env!("CARGO_BIN_EXE_datagen"))
}

fn rgb(bytes: &[u8]) -> image::RgbImage {
    image::load_from_memory(bytes).unwrap().to_rgb8()
}

fn grey(bytes: &[u8]) -> image::GrayImage {
    image::load_from_memory(bytes).unwrap().to_luma8()
}

fn config(pairs: &[[&str; 2]], length: u32) -> PairsConfig {
    let mut config = PairsConfig::default();
    config.clip.length = length;
    config.clip.stride = length;
    config.multiview = MultiViewConfig {
        camera_pairs: pairs.iter().map(|[s, t]| [s.to_string(), t.to_string()]).collect(),
        ..MultiViewConfig::default()
    };
    config
}

fn multiview(records: &[ClipRecord]) -> Vec<&ClipRecord> {
    records.iter().filter(|r| r.pair_kind == PairKind::Multiview).collect()
}

// Measured on this scene (192 × 128, cameras 8° apart, pairs 0→1, 2→1, 1→0 over 3 frames;
// 193,886 masked pixels, the exact rule's masks): conditioning vs target mean |difference| 16.68
// levels per channel, max 173; 99.6 % of masked pixels show t's own surface, and there the ideal
// resampling (t's exact surface point projected into s, s's colour there by the render's colour
// rule) differs from t by 16.56 levels on average: that is the resampling error of the synthetic
// textures' high-contrast checks seen from two viewpoints, not the renderer's. The render differs
// from the ideal resampling by 0.05 levels on average, and 99.9 % of channels are within the
// resampling error + 4 levels. The same render compared with t shifted 2 px: 23.16 levels.

/// Largest mean absolute difference (levels, per channel, over masked pixels) between the
/// conditioning and the target: measured 16.68, of which 16.56 is the data's resampling error.
const MEAN_LEVELS: f64 = 20.0;
/// A render hit shows t's own surface when its depth in t is within this fraction of t's exact
/// depth (the same test as `multiview::one_cameras_render_into_another_matches_its_real_frame`).
const SAME_SURFACE: f64 = 0.01;
/// Least share of masked pixels that show t's own surface: measured 0.996 (the rest sit on
/// object edges, where s's mesh bridges what t sees past).
const SAME_SURFACE_SHARE: f64 = 0.98;
/// Largest mean difference between the render and the ideal resampling: measured 0.05 levels; a
/// sub-pixel misplacement of the render would add several levels on these textures.
const RENDER_MEAN_LEVELS: f64 = 0.5;
/// Tolerance beyond the resampling error, in levels: the bilinear colour's rounding (1 level)
/// plus the mesh's flat triangles between s's depth samples.
const RENDER_LEVELS: u8 = 4;
/// Least share of channels within the resampling error + [`RENDER_LEVELS`]: measured 0.999.
const WITHIN_SHARE: f64 = 0.998;
/// How much worse than the measured mean a conditioning misplaced by [`CONTROL_SHIFT`] is
/// required to be (measured 23.16 / 16.68 = 1.39): the mean bound above can tell a misplaced
/// render from a right one.
const CONTROL_FACTOR: f64 = 1.2;
/// Pixels the control comparison is shifted by.
const CONTROL_SHIFT: u32 = 2;

#[test]
fn the_target_is_camera_t_and_the_conditioning_matches_it_where_masked() {
    let dir = tempfile::tempdir().unwrap();
    let synth_config = synth(192, 128, 3);
    let rig = write_multiview(&synth_config, &RIG, &dir.path().join("rig"), |_| {}).unwrap();
    let scene = read_multiview(&rig).unwrap();
    let config = config(&[["cam00", "cam01"], ["cam02", "cam01"], ["cam01", "cam00"]], 3);
    let pairs = generate_scene_clips(&scene, "synth", &config, 1, 7, &mut |_| {}).unwrap();
    let records = multiview(&pairs.records);
    assert_eq!(records.len(), 3, "one 3-frame window per camera pair");
    assert_eq!(pairs.records.len() - records.len(), 3, "one monocular clip per camera with depth");

    let truth = SynthScene::new(&synth_config).unwrap();
    let (mut masked, mut total_error, mut max_error) = (0usize, 0u64, 0u8);
    let (mut same_surface, mut within, mut resampling_error, mut render_error) = (0usize, 0usize, 0u64, 0u64);
    let (mut controls, mut control_error) = (0usize, 0u64);
    for (record, (s, t)) in records.iter().zip([(0usize, 1usize), (2, 1), (1, 0)]) {
        let (source, target) = (&scene.cameras[s], &scene.cameras[t]);
        assert_eq!(
            (record.source_camera.as_deref(), record.target_camera.as_deref()),
            (Some(source.id.as_str()), Some(target.id.as_str()))
        );
        assert_eq!(record.trajectories.len(), 1);
        let trajectory = &record.trajectories[0];
        assert_eq!(trajectory.kind, TrajectoryKind::Camera);
        for frame in 0..3usize {
            // The target is camera t's frame, bit for bit, and the ray-traced ground truth.
            let target_frame = rgb(&record.frames[frame]);
            let pose = truth.rig_world_from_camera(frame as u32, &RIG, t as u32);
            let exact = truth.render_view(&truth.frame_geometry(frame as u32), &pose, &synth_config.intrinsics());
            assert!(target_frame == exact.rgb && target_frame == target.sequence.frames[frame], "{}", record.clip_id);
            let row_major = |m: &glam::DMat4| foundation::camera::mat4_to_row_major(m);
            assert_eq!(record.world_from_camera[frame], row_major(&pose));
            assert_eq!(
                trajectory.world_from_camera[frame],
                row_major(&source.sequence.cameras[frame].world_from_camera)
            );

            // The conditioning is the real renderer's output: s's frame through s's mesh into t.
            let condition = rgb(&trajectory.condition.as_ref().unwrap()[frame]);
            let mask = grey(&trajectory.covisible_mask[frame]);
            let mesh =
                DepthMesh::new(&source.sequence.depth[frame], &source.sequence.cameras[frame], &MeshConfig::default());
            let (render, holes) = render_novel_view(
                &mesh,
                &source.sequence.frames[frame],
                &source.sequence.cameras[frame],
                &target.sequence.cameras[frame],
            );
            assert!(condition == render, "{} frame {frame}: conditioning is the render", record.clip_id);
            // The target has depth: the mask is the exact rule's.
            assert_eq!(trajectory.mask_rule, schemas::MaskRule::Exact);
            let novel = target.sequence.cameras[frame];
            let exact = target_visibility_mask(
                &mesh,
                &source.sequence.cameras[frame],
                &target.sequence.depth[frame],
                &novel,
                &CovisibilityConfig::default(),
            );
            assert!(mask.pixels().map(|m| m.0[0] == 255).eq(exact), "{} frame {frame}: the exact mask", record.clip_id);
            let hits = mesh.view(&novel).surface_hits();
            let width = target_frame.width();
            let pixels = condition.pixels().zip(target_frame.pixels()).zip(mask.pixels()).zip(holes.pixels());
            for (p, (((c, g), m), h)) in pixels.enumerate() {
                if h.0[0] == 255 {
                    assert_eq!(c.0, [0, 0, 0], "holes are black");
                    continue;
                }
                if m.0[0] == 0 {
                    continue;
                }
                masked += 1;
                let errors: Vec<u8> = (0..3).map(|k| c.0[k].abs_diff(g.0[k])).collect();
                total_error += errors.iter().map(|&e| u64::from(e)).sum::<u64>();
                max_error = max_error.max(*errors.iter().max().unwrap());
                // Where the render shows the surface t really sees (its hit at t's exact depth),
                // the difference is resampling alone: a bilinear mix of s's pixels of that
                // surface, which t's 3 × 3 neighbourhood brackets.
                let (x, y) = (p as u32 % width, p as u32 / width);
                let distance = hits[p].expect("a pixel that is no hole is a hit");
                let point = novel.center() + novel.pixel_ray(f64::from(x), f64::from(y)).normalize() * distance;
                let (_, z) = novel.project(point).unwrap();
                let truth = f64::from(target.sequence.depth[frame].values[p]);
                if (z - truth).abs() > SAME_SURFACE * truth {
                    continue;
                }
                same_surface += 1;
                // The ideal resampled conditioning: t's exact surface point, projected into s,
                // s's colour there by the render's rule (bilinear between samples of one
                // surface, the footprint's pixel across a depth edge). Its difference from t's
                // pixel is the resampling error of the data; the render's difference from it is
                // the renderer's placement (its mesh is piecewise flat between s's samples).
                let exact = novel.unproject(f64::from(x), f64::from(y), truth);
                let (at, _) = source.sequence.cameras[frame].project(exact).unwrap();
                let ideal = source_colour(&mesh, &source.sequence.frames[frame], at).0;
                for k in 0..3 {
                    let resampling = ideal[k].abs_diff(g.0[k]);
                    resampling_error += u64::from(resampling);
                    render_error += u64::from(c.0[k].abs_diff(ideal[k]));
                    within += usize::from(errors[k] <= resampling.saturating_add(RENDER_LEVELS));
                }
                if x + CONTROL_SHIFT < width {
                    let shifted = target_frame.get_pixel(x + CONTROL_SHIFT, y).0;
                    control_error += (0..3).map(|k| u64::from(c.0[k].abs_diff(shifted[k]))).sum::<u64>();
                    controls += 1;
                }
            }
        }
        let kept = record.trajectories[0].covisible_fraction;
        assert!(kept > 0.5, "neighbouring cameras 8° apart share most of the view: {kept}");
    }
    let mean = total_error as f64 / (3 * masked) as f64;
    let channels = (3 * same_surface) as f64;
    let same_share = same_surface as f64 / masked as f64;
    let (resampling, render) = (resampling_error as f64 / channels, render_error as f64 / channels);
    let within_share = within as f64 / channels;
    let control = control_error as f64 / (3 * controls) as f64;
    println!(
        "multi-view conditioning vs target on {masked} masked pixels: mean |difference| {mean:.2} levels, max \
         {max_error}; {:.1} % show t's own surface; there the ideal resampling differs from t by {resampling:.2} \
         levels on average, the render from the ideal by {render:.2}, and {:.1} % of channels are within the \
         resampling error + {RENDER_LEVELS}; the render against t shifted {CONTROL_SHIFT} px: {control:.2}",
        100.0 * same_share,
        100.0 * within_share
    );
    assert!(mean < MEAN_LEVELS, "mean difference {mean} levels");
    assert!(same_share > SAME_SURFACE_SHARE, "{same_share} of masked pixels show t's own surface");
    assert!(render < RENDER_MEAN_LEVELS, "the render is {render} levels from the ideal resampling");
    assert!(within_share > WITHIN_SHARE, "{within_share} of channels within the resampling error");
    assert!(control > CONTROL_FACTOR * mean, "a 2-px misplacement ({control}) must be clearly worse than {mean}");
}

/// The scene of `rig` with camera `cam01` filming only the instants `kept`, and `cam02` without
/// depth (DyCheck's held-out cameras look like this).
fn partial_scene(rig: &Path, kept: &[usize]) -> MultiViewScene {
    let mut scene = read_multiview(rig).unwrap();
    let camera = &mut scene.cameras[1];
    let sequence = &mut camera.sequence;
    sequence.frames = kept.iter().map(|&k| sequence.frames[k].clone()).collect();
    sequence.depth = kept.iter().map(|&k| sequence.depth[k].clone()).collect();
    sequence.cameras = kept.iter().map(|&k| sequence.cameras[k]).collect();
    camera.time_ids = kept.to_vec();
    camera.timestamps = None;
    let blind = &mut scene.cameras[2];
    blind.has_depth = false;
    for depth in &mut blind.sequence.depth {
        depth.values.iter_mut().for_each(|d| *d = 0.0);
    }
    scene
}

#[test]
fn frames_are_matched_by_instant_and_cameras_without_depth_are_only_targets() {
    let dir = tempfile::tempdir().unwrap();
    let rig = write_multiview(&synth(64, 48, 4), &RIG, &dir.path().join("rig"), |_| {}).unwrap();
    let scene = partial_scene(&rig, &[0, 2, 3]);
    let pairs = generate_scene_clips(&scene, "synth", &config(&[], 8), 1, 0, &mut |_| {}).unwrap();
    let used: BTreeSet<(String, String)> = pairs.camera_pairs.iter().cloned().collect();
    let expected: BTreeSet<(String, String)> =
        [("cam00", "cam01"), ("cam00", "cam02"), ("cam01", "cam00"), ("cam01", "cam02")]
            .iter()
            .map(|(s, t)| (s.to_string(), t.to_string()))
            .collect();
    assert_eq!(used, expected, "every ordered pair whose source has depth");
    let monocular: Vec<&str> = pairs
        .records
        .iter()
        .filter(|r| r.pair_kind == PairKind::Monocular)
        .map(|r| r.source_camera.as_deref().unwrap())
        .collect();
    assert_eq!(monocular, ["cam00", "cam01"], "monocular pairs of the cameras with depth");

    let record = multiview(&pairs.records)
        .into_iter()
        .find(|r| r.source_camera.as_deref() == Some("cam00") && r.target_camera.as_deref() == Some("cam01"))
        .unwrap();
    assert_eq!(record.num_frames(), 3, "the three instants both film");
    let (source, target) = (&scene.cameras[0].sequence, &scene.cameras[1].sequence);
    for (k, instant) in [0usize, 2, 3].into_iter().enumerate() {
        assert!(rgb(&record.frames[k]) == target.frames[k]);
        let mesh = DepthMesh::new(&source.depth[instant], &source.cameras[instant], &MeshConfig::default());
        let (render, _) =
            render_novel_view(&mesh, &source.frames[instant], &source.cameras[instant], &target.cameras[k]);
        assert!(rgb(&record.trajectories[0].condition.as_ref().unwrap()[k]) == render, "instant {instant}");
    }
    let back = multiview(&pairs.records)
        .into_iter()
        .find(|r| r.source_camera.as_deref() == Some("cam01") && r.target_camera.as_deref() == Some("cam00"))
        .unwrap();
    assert_eq!(back.clip_start, 0);
    assert_eq!(back.world_from_camera.len(), 3, "cam00's frames at the instants cam01 films");

    // Naming a camera without depth as a source, or one the scene lacks, is an error naming the
    // key and the scene.
    for (pair, needle) in [(["cam02", "cam00"], "no depth"), (["cam00", "cam09"], "cam09")] {
        let error = generate_scene_clips(&scene, "synth", &config(&[pair], 8), 1, 0, &mut |_| {}).unwrap_err();
        let text = error.to_string();
        assert!(text.contains("multiview.camera_pairs[0]") && text.contains(needle) && text.contains("rig"), "{text}");
    }
}

#[test]
fn pairs_are_deterministic_by_seed_and_the_subset_follows_it() {
    let dir = tempfile::tempdir().unwrap();
    let rig = write_multiview(&synth(64, 48, 3), &RIG, &dir.path().join("rig"), |_| {}).unwrap();
    let scene = read_multiview(&rig).unwrap();
    let mut config = config(&[], 3);
    config.multiview.pairs_per_scene = 2;
    let run_with =
        |config: &PairsConfig, seed| generate_scene_clips(&scene, "synth", config, 1, seed, &mut |_| {}).unwrap();
    let run = |seed| run_with(&config, seed);
    let (a, b) = (run(5), run(5));
    assert_eq!(a.records, b.records, "same seed, same records");
    assert_eq!(a.camera_pairs.len(), 2);
    let subsets: BTreeSet<Vec<(String, String)>> = (0..8).map(|seed| run(seed).camera_pairs).collect();
    assert!(subsets.len() > 1, "the 2 of 6 camera pairs depend on the seed: {subsets:?}");

    // A cut-off drops the windows below it, and reports them.
    let mut strict = config.clone();
    strict.multiview.pairs_per_scene = 0;
    strict.multiview.min_covisible_fraction = 1.0;
    let strict = run_with(&strict, 5);
    assert!(multiview(&strict.records).is_empty());
    assert_eq!(strict.dropped.len(), 6, "every window of the 6 camera pairs is below 100 %");

    // `datagen pairs` on the folder writes the same records as the library, twice alike.
    let toml = dir.path().join("pairs.toml");
    std::fs::write(&toml, "[clip]\nlength = 3\n[multiview]\npairs_per_scene = 2\n").unwrap();
    let mut shards = Vec::new();
    for out in ["out1", "out2"] {
        let out = dir.path().join(out);
        let status = datagen()
            .args(["pairs", "--trajectories", "1", "--seed", "5", "--dataset", "synth", "--config"])
            .arg(&toml)
            .arg(&rig)
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        assert!(status.status.success(), "{}", String::from_utf8_lossy(&status.stderr));
        let text = String::from_utf8_lossy(&status.stdout);
        assert!(text.contains("3 monocular and 2 multi-view clips"), "{text}");
        shards.push(schemas::read_shard(&out.join("rig.parquet")).unwrap());
    }
    assert_eq!(shards[0], shards[1]);

    // The exports and the HTML report name the pair kind and the cameras.
    let (export, html) = (dir.path().join("export"), dir.path().join("report.html"));
    let inspect = datagen()
        .arg("inspect")
        .arg(dir.path().join("out1"))
        .arg("--export")
        .arg(&export)
        .arg("--report")
        .arg(&html)
        .output()
        .unwrap();
    assert!(inspect.status.success(), "{}", String::from_utf8_lossy(&inspect.stderr));
    let html = std::fs::read_to_string(&html).unwrap();
    assert!(html.contains("Pairs by pair kind: monocular 3, multiview 2"), "{html}");
    let multiview_record = shards[0].iter().find(|r| r.pair_kind == PairKind::Multiview).unwrap();
    let (source, target) =
        (multiview_record.source_camera.clone().unwrap(), multiview_record.target_camera.clone().unwrap());
    assert!(html.contains(&format!("{source}→{target}")), "{html}");
    let folder = export.join(format!("{}__t0", multiview_record.clip_id.replace('/', "__")));
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(folder.join("meta.json")).unwrap()).unwrap();
    assert_eq!(
        (meta["pair_kind"].as_str(), meta["source_camera"].as_str(), meta["target_camera"].as_str()),
        (Some("multiview"), Some(source.as_str()), Some(target.as_str()))
    );
    assert_eq!(meta["contact_sheet_columns"][0], format!("target {target}"));
    assert_eq!(meta["contact_sheet_columns"][2], format!("conditioning: from {source}"));
    let library: Vec<ClipRecord> =
        a.records.into_iter().map(|r| ClipRecord { source_path: rig.display().to_string(), ..r }).collect();
    let written: Vec<ClipRecord> =
        shards[0].iter().cloned().map(|r| ClipRecord { tool_version: library[0].tool_version.clone(), ..r }).collect();
    assert_eq!(written.len(), library.len());
    for (w, l) in written.iter().zip(&library) {
        assert_eq!((&w.clip_id, &w.frames, &w.trajectories), (&l.clip_id, &l.frames, &l.trajectories));
    }
}

#[test]
fn bad_multiview_keys_are_refused_naming_the_key() {
    let dir = tempfile::tempdir().unwrap();
    for (text, key, needle) in [
        ("[multiview]\ncamera_pairs = [[\"a\", \"a\"]]\n", "multiview.camera_pairs[0]", "both `a`"),
        ("[multiview]\ncamera_pairs = [[\"a\", \"b\"], [\"a\", \"b\"]]\n", "multiview.camera_pairs[1]", "twice"),
        ("[multiview]\nmin_covisible_fraction = 1.5\n", "multiview.min_covisible_fraction", "[0, 1]"),
    ] {
        let path = dir.path().join("pairs.toml");
        std::fs::write(&path, text).unwrap();
        let error = PairsConfig::from_toml_file(&path).unwrap_err().to_string();
        assert!(error.contains(key) && error.contains(needle) && error.contains("line"), "{text}: {error}");
    }
}

/// A scene of 2 frames in place of `scene`'s camera `camera`.
fn replace_camera(scene: &Path, camera: &str, with: &Path) {
    std::fs::remove_dir_all(scene.join(camera)).unwrap();
    let status = Command::new("cp").arg("-r").arg(with.join(camera)).arg(scene.join(camera)).status().unwrap();
    assert!(status.success());
}

#[test]
fn a_build_fails_a_broken_scene_alone_and_writes_nothing_for_it() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("scenes");
    let scene = |name: &str, frames: u32| -> PathBuf {
        write_multiview(&synth(48, 32, frames), &CameraRig { cameras: 2, spacing_deg: 8.0 }, &root.join(name), |_| {})
            .unwrap()
    };
    scene("good", 3);
    scene("also_good", 3);
    // Cameras with different frame counts.
    let short = scene("short", 3);
    let two = write_multiview(
        &synth(48, 32, 2),
        &CameraRig { cameras: 2, spacing_deg: 8.0 },
        &dir.path().join("two"),
        |_| {},
    )
    .unwrap();
    replace_camera(&short, "cam01", &two);
    // A camera file missing.
    let missing = scene("missing", 3);
    std::fs::remove_file(missing.join("cam01/cameras.json")).unwrap();

    let out = dir.path().join("corpus");
    let config = dir.path().join("corpus.toml");
    std::fs::write(
        &config,
        format!(
            "seed = 3\ntrajectories = 1\n[[sources]]\ndataset = \"multiview\"\nroot = \"{}\"\n\
             [output]\ndir = \"{}\"\n[pairs.clip]\nlength = 3\n[pairs.multiview]\nmin_covisible_fraction = 0.1\n",
            root.display(),
            out.display()
        ),
    )
    .unwrap();
    let build = datagen().arg("build").arg("--config").arg(&config).output().unwrap();
    assert!(build.status.success(), "{}", String::from_utf8_lossy(&build.stderr));
    let printed = String::from_utf8_lossy(&build.stdout);
    assert!(
        printed.contains("failed: multiview/short: ") && printed.contains("failed: multiview/missing: "),
        "the build lists the failed scenes with their reasons: {printed}"
    );
    let status = datagen::corpus::build::read_corpus_status(&out).unwrap();
    let expect = |key: &str, state: InputStatus, needles: &[&str]| {
        let record = &status[key];
        assert_eq!(record.status, state, "{key}: {}", record.reason);
        for needle in needles {
            assert!(record.reason.contains(needle), "{key}: `{}` should mention `{needle}`", record.reason);
        }
    };
    expect("multiview/good", InputStatus::Ok, &[]);
    expect("multiview/also_good", InputStatus::Ok, &[]);
    expect("multiview/short", InputStatus::Failed, &["cam01", "frames", "2 frames"]);
    expect("multiview/missing", InputStatus::Failed, &["cam01"]);

    let mut kinds = BTreeSet::new();
    let mut scenes = BTreeSet::new();
    for entry in std::fs::read_dir(&out).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "parquet") {
            for record in schemas::read_shard(&path).unwrap() {
                scenes.insert(record.clip_id.split('/').nth(1).unwrap().to_owned());
                kinds.insert((record.pair_kind, record.source_camera.clone(), record.target_camera.clone()));
            }
        }
    }
    assert_eq!(scenes, BTreeSet::from(["also_good".to_owned(), "good".to_owned()]), "nothing of the broken scenes");
    let some = |s: &str| Some(s.to_owned());
    assert_eq!(
        kinds,
        BTreeSet::from([
            (PairKind::Monocular, some("cam00"), some("cam00")),
            (PairKind::Monocular, some("cam01"), some("cam01")),
            (PairKind::Multiview, some("cam00"), some("cam01")),
            (PairKind::Multiview, some("cam01"), some("cam00")),
        ])
    );
    // The trajectory bank of the same corpus takes every camera's motion of the good scenes.
    let bank = datagen::corpus::harvest::collect_from_corpus(
        &datagen::corpus::build::BuildConfig::from_toml_file(&config).unwrap(),
    )
    .unwrap();
    assert_eq!(bank.windows, 4, "2 scenes × 2 cameras × 1 window");
    let failed: BTreeSet<&str> = bank.failed_inputs.iter().map(|(key, _)| key.as_str()).collect();
    assert_eq!(failed, BTreeSet::from(["multiview/missing", "multiview/short"]));

    let report = datagen().arg("inspect").arg(&out).output().unwrap();
    let text = String::from_utf8_lossy(&report.stdout);
    assert!(text.contains("2 ok, 0 skipped, 2 failed") && text.contains("4 monocular, 4 multiview"), "{text}");
    assert!(text.contains("multiview cam00→cam01"), "{text}");
}
