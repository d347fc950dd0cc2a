//! The benchmark datasets' multi-camera layouts: `datagen synth --format dycheck|kubric4d` writes
//! the synthetic scene in DyCheck's and Kubric-4D's own conventions, the readers give back the
//! exact cameras (toolkit conventions), frames, depth and masks, detection picks the layout, and
//! broken scenes are refused naming the file and field.

use std::path::{Path, PathBuf};

use datagen::io::dycheck::{read_dycheck, read_dycheck_with_info};
use datagen::io::kubric4d::read_kubric4d;
use datagen::io::layout::{MultiViewLayoutName, detect_multiview_layout, read_multiview_as};
use datagen::synth::{CameraRig, SynthConfig, SynthScene, ground_truth_covisibility, write_multiview};
use datagen::synth_layouts::{dycheck_frames, dycheck_world_from_camera, write_dycheck, write_kubric4d};
use foundation::camera::PinholeCamera;
use glam::{DMat3, DMat4, DVec3};

const RIG: CameraRig = CameraRig { cameras: 3, spacing_deg: 8.0 };

fn config() -> SynthConfig {
    SynthConfig { width: 64, height: 48, frames: 3, ..SynthConfig::default() }
}

fn dycheck_scene(dir: &Path) -> PathBuf {
    write_dycheck(&config(), &RIG, &dir.join("dycheck"), |_| {}).unwrap()
}

/// Mean of each 2 × 2 block, rounded (DyCheck's 2x frames).
fn half(image: &image::RgbImage) -> image::RgbImage {
    image::RgbImage::from_fn(image.width() / 2, image.height() / 2, |x, y| {
        let p = |k: u32| image.get_pixel(2 * x + k % 2, 2 * y + k / 2).0;
        image::Rgb([0, 1, 2].map(|c| ((0..4).map(|k| u32::from(p(k)[c])).sum::<u32>() + 2).div_euclid(4) as u8))
    })
}

#[test]
fn a_dycheck_scene_reads_back_exactly_at_full_resolution() {
    let dir = tempfile::tempdir().unwrap();
    let path = dycheck_scene(dir.path());
    let (scene, info) = read_dycheck_with_info(&path, Some(1)).unwrap();
    assert_eq!((info.factor, info.fps), (1, Some(24.0)));
    let ids: Vec<&str> = scene.cameras.iter().map(|c| c.id.as_str()).collect();
    assert_eq!(ids, ["0", "1", "2"]);
    let split = scene.split.clone().unwrap();
    assert_eq!((split.input.as_str(), split.held_out.clone()), ("0", vec!["1".to_owned(), "2".to_owned()]));
    let synth = SynthScene::new(&config()).unwrap();
    let k = config().intrinsics();
    for (c, camera) in scene.cameras.iter().enumerate() {
        let c = c as u32;
        let frames = dycheck_frames(&config(), c);
        let time_ids: Vec<usize> = frames.iter().map(|&t| t as usize).collect();
        assert_eq!(camera.time_ids, time_ids, "camera {c}");
        assert_eq!(camera.time_ids, if c == 0 { vec![0, 1, 2] } else { vec![0, 2] }, "held-out cameras skip frame 1");
        assert_eq!(camera.timestamps.clone().unwrap(), frames.iter().map(|&t| t as f64 / 24.0).collect::<Vec<_>>());
        assert_eq!(camera.has_depth, c == 0);
        assert_eq!(camera.covisible.is_some(), c != 0);
        for (k_frame, &t) in frames.iter().enumerate() {
            let pose = dycheck_world_from_camera(&synth, &RIG, c, t);
            let read = camera.sequence.cameras[k_frame];
            assert_eq!(read.world_from_camera, pose, "camera {c} frame {t}");
            assert_eq!(read.intrinsics, k, "K in pixels, centres at integers");
            let truth = synth.render_view(&synth.frame_geometry(t), &pose, &k);
            assert!(camera.sequence.frames[k_frame] == truth.rgb, "camera {c} frame {t}");
            let depth = &camera.sequence.depth[k_frame].values;
            if c == 0 {
                assert_eq!(depth, &truth.depth, "frame {t}");
            } else {
                assert!(depth.iter().all(|&d| d == 0.0), "held-out cameras ship no depth");
                let input_pose = dycheck_world_from_camera(&synth, &RIG, 0, t);
                let covisible = ground_truth_covisibility(&synth, t, &truth, &input_pose, &k);
                let mask = &camera.covisible.as_ref().unwrap()[k_frame];
                let read: Vec<bool> = mask.pixels().map(|p| p.0[0] != 0).collect();
                assert_eq!(read, covisible, "camera {c} frame {t}");
                let share = covisible.iter().filter(|&&v| v).count() as f64 / covisible.len() as f64;
                assert!(share > 0.2 && share < 1.0, "a mask with both kinds of pixels: {share}");
            }
        }
    }
}

#[test]
fn a_dycheck_scene_reads_at_its_benchmark_factor_with_area_averaged_depth() {
    let dir = tempfile::tempdir().unwrap();
    let path = dycheck_scene(dir.path());
    let scene = read_dycheck(&path, None).unwrap();
    let synth = SynthScene::new(&config()).unwrap();
    let full =
        PinholeCamera { width: 64, height: 48, intrinsics: config().intrinsics(), world_from_camera: DMat4::IDENTITY };
    let input = &scene.cameras[0];
    for t in 0..3u32 {
        let read = input.sequence.cameras[t as usize];
        assert_eq!((read.width, read.height), (32, 24), "extra.json factor 2");
        assert_eq!(read.intrinsics, full.resized(32, 24).intrinsics);
        let pose = dycheck_world_from_camera(&synth, &RIG, 0, t);
        let truth = synth.render_view(&synth.frame_geometry(t), &pose, &config().intrinsics());
        assert!(input.sequence.frames[t as usize] == half(&truth.rgb), "frame {t}");
        let depth = &input.sequence.depth[t as usize].values;
        for (i, &d) in depth.iter().enumerate() {
            let (x, y) = (i % 32, i / 32);
            let block: Vec<f32> = (0..4).map(|k| truth.depth[(2 * y + k / 2) * 64 + 2 * x + k % 2]).collect();
            let want = if block.iter().all(|&v| v > 0.0) { block.iter().sum::<f32>() / 4.0 } else { 0.0 };
            assert!((d - want).abs() <= 1e-6 * want, "pixel {i}: {d} vs {want}");
        }
    }
    // Without depth/2x the reader area-averages depth/1x to the same values.
    std::fs::remove_dir_all(path.join("depth/2x")).unwrap();
    let from_full = read_dycheck(&path, None).unwrap();
    for t in 0..3 {
        assert_eq!(from_full.cameras[0].sequence.depth[t].values, input.sequence.depth[t].values);
    }
}

/// The Nerfies layout DyCheck extends: no `extra.json` (factor 1, no frame rate) and no
/// `splits/` (the split comes from `dataset.json`'s `train_ids` / `val_ids`).
#[test]
fn a_nerfies_layout_scene_reads_without_extra_or_splits() {
    let dir = tempfile::tempdir().unwrap();
    let path = dycheck_scene(dir.path());
    std::fs::remove_file(path.join("extra.json")).unwrap();
    std::fs::remove_dir_all(path.join("splits")).unwrap();
    let (scene, info) = read_dycheck_with_info(&path, None).unwrap();
    assert_eq!((info.factor, info.fps, info.bbox), (1, None, None));
    assert_eq!(scene.cameras[0].sequence.size(), (64, 48));
    assert!(scene.cameras.iter().all(|c| c.timestamps.is_none()));
    let split = scene.split.unwrap();
    assert_eq!((split.input.as_str(), split.held_out.len()), ("0", 2));
    assert_eq!(scene.cameras[2].time_ids, vec![0, 2]);
    // Training items on two cameras leave no single input camera: no split, every frame kept.
    edit_json(&path.join("dataset.json"), &|j| {
        j["train_ids"].as_array_mut().unwrap().push(serde_json::json!("1_00000"));
        j["num_exemplars"] = serde_json::json!(4);
    });
    let scene = read_dycheck(&path, None).unwrap();
    assert!(scene.split.is_none());
}

/// Kubric's Z-up world from the synthetic scene's y-up one: (x, y, z) ↦ (x, −z, y).
fn kubric_from_synth() -> DMat4 {
    DMat4::from_mat3(DMat3::from_cols(DVec3::X, DVec3::Z, -DVec3::Y))
}

#[test]
fn a_kubric4d_scene_reads_back_in_opencv_axes_with_z_depth() {
    let dir = tempfile::tempdir().unwrap();
    let rig = CameraRig { cameras: 5, spacing_deg: 6.0 };
    let path = write_kubric4d(&config(), &rig, &dir.path().join("scn00042"), |_| {}).unwrap();
    assert!(path.join("scn00042_p0_v4.json").is_file() && path.join("frames_p0_v4/depth_00002.tiff").is_file());
    let scene = read_kubric4d(&path).unwrap();
    assert_eq!(scene.cameras.len(), 5);
    let split = scene.split.clone().unwrap();
    assert_eq!((split.input.as_str(), split.held_out.len()), ("4", 4), "GCD's input view 4");
    let synth = SynthScene::new(&config()).unwrap();
    let k = config().intrinsics();
    let (mut worst_pose, mut worst_k, mut worst_depth) = (0.0f64, 0.0f64, 0.0f64);
    for (v, camera) in scene.cameras.iter().enumerate() {
        assert_eq!(camera.id, v.to_string());
        assert_eq!(camera.time_ids, vec![0, 1, 2]);
        for t in 0..3u32 {
            let pose = synth.rig_world_from_camera(t, &rig, v as u32);
            let read = camera.sequence.cameras[t as usize];
            let expected = kubric_from_synth() * pose;
            let error = (read.world_from_camera - expected).to_cols_array().iter().fold(0.0f64, |m, e| m.max(e.abs()));
            worst_pose = worst_pose.max(error);
            let k_error = (read.intrinsics - k).to_cols_array().iter().fold(0.0f64, |m, e| m.max(e.abs()));
            worst_k = worst_k.max(k_error);
            let truth = synth.render_view(&synth.frame_geometry(t), &pose, &k);
            assert!(camera.sequence.frames[t as usize] == truth.rgb, "view {v} frame {t}");
            assert!(camera.sequence.dynamic_masks.as_ref().unwrap()[t as usize] == truth.mask_ids);
            for (d, z) in camera.sequence.depth[t as usize].values.iter().zip(&truth.depth) {
                worst_depth = worst_depth.max(f64::from((d - z).abs() / z.max(1e-6)));
            }
        }
    }
    eprintln!("Kubric-4D round trip: pose {worst_pose:.1e}, K {worst_k:.1e}, z-depth {worst_depth:.1e} relative");
    assert!(worst_pose < 1e-12, "poses: {worst_pose}");
    assert!(worst_k < 1e-12, "K: {worst_k}");
    // float32 ray lengths divided back by the ray's length: a few float32 ulps.
    assert!(worst_depth < 1e-6, "depth: {worst_depth}");
    // A point the source sees projects into the read camera where the truth says.
    let read = scene.cameras[1].sequence.cameras[0];
    let depth = f64::from(scene.cameras[1].sequence.depth[0].values[30 * 64 + 40]);
    assert!(depth > 0.0);
    let point = read.unproject(40.0, 30.0, depth);
    let in_synth = kubric_from_synth().inverse().transform_point3(point);
    let (pixel, _) =
        PinholeCamera { world_from_camera: synth.rig_world_from_camera(0, &rig, 1), ..read }.project(in_synth).unwrap();
    assert!((pixel.x - 40.0).abs() < 1e-6 && (pixel.y - 30.0).abs() < 1e-6, "{pixel}");
}

#[test]
fn the_layout_is_detected_from_the_files() {
    let dir = tempfile::tempdir().unwrap();
    let dycheck = dycheck_scene(dir.path());
    let kubric = write_kubric4d(&config(), &RIG, &dir.path().join("scn00001"), |_| {}).unwrap();
    let generic = write_multiview(&config(), &RIG, &dir.path().join("generic"), |_| {}).unwrap();
    assert_eq!(detect_multiview_layout(&dycheck).unwrap(), MultiViewLayoutName::Dycheck);
    assert_eq!(detect_multiview_layout(&kubric).unwrap(), MultiViewLayoutName::Kubric4d);
    assert_eq!(detect_multiview_layout(&generic).unwrap(), MultiViewLayoutName::Generic);
    assert_eq!(read_multiview_as(&dycheck, None).unwrap().cameras[0].sequence.size(), (32, 24));
    assert_eq!(read_multiview_as(&kubric, None).unwrap().cameras.len(), 3);
    assert_eq!(read_multiview_as(&generic, Some(MultiViewLayoutName::Generic)).unwrap().cameras.len(), 3);
    let names: Vec<MultiViewLayoutName> =
        ["generic", "dycheck", "kubric4d", "pardom4d"].iter().map(|s| s.parse().unwrap()).collect();
    assert_eq!(names, MultiViewLayoutName::ALL);
    let empty = dir.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let text = detect_multiview_layout(&empty).unwrap_err().to_string();
    assert!(text.contains("dataset.json") && text.contains("frames_p0_v0"), "{text}");
    // A layout named by the user that the folder is not in fails on its files.
    assert!(read_multiview_as(&generic, Some(MultiViewLayoutName::Dycheck)).is_err());
}

fn copy(from: &Path, to: &Path) -> PathBuf {
    assert!(std::process::Command::new("cp").arg("-r").arg(from).arg(to).status().unwrap().success());
    to.to_owned()
}

fn edit_json(path: &Path, change: &dyn Fn(&mut serde_json::Value)) {
    let mut json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    change(&mut json);
    std::fs::write(path, json.to_string()).unwrap();
}

fn dycheck_refusal(dir: &Path) -> String {
    format!("{:#}", anyhow::Error::from(read_dycheck(dir, Some(1)).unwrap_err()))
}

#[test]
fn broken_dycheck_scenes_are_refused_naming_the_file_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let good = dycheck_scene(dir.path());
    let case = |name: &str| copy(&good, &dir.path().join(name));

    // A camera file missing, or unreadable.
    let missing = case("missing");
    std::fs::remove_file(missing.join("camera/0_00001.json")).unwrap();
    assert!(dycheck_refusal(&missing).contains("camera/0_00001.json"));
    let garbled = case("garbled");
    std::fs::write(garbled.join("camera/1_00002.json"), "{ not json").unwrap();
    let text = dycheck_refusal(&garbled);
    assert!(text.contains("camera/1_00002.json") && text.contains("invalid JSON"), "{text}");

    // Distortion, skew; a non-rigid orientation; a non-finite position.
    let camera = |dir: &Path| dir.join("camera/0_00000.json");
    let edits: [(&str, &str, serde_json::Value); 5] = [
        ("radial", "radial_distortion", serde_json::json!([0.05, 0.0, 0.0])),
        ("tangential", "tangential_distortion", serde_json::json!([0.0, 0.01])),
        ("skew", "skew", serde_json::json!(0.5)),
        ("position", "position", serde_json::json!([null, 0.0, 0.0])),
        ("focal", "focal_length", serde_json::json!(-3.0)),
    ];
    for (name, field, value) in edits {
        let bad = case(name);
        edit_json(&camera(&bad), &|j| j[field] = value.clone());
        let text = dycheck_refusal(&bad);
        assert!(text.contains("camera/0_00000.json") && text.contains(&format!("`{field}")), "{name}: {text}");
    }
    let scaled = case("scaled");
    edit_json(&camera(&scaled), &|j| {
        for r in 0..3 {
            for c in 0..3 {
                let v = j["orientation"][r][c].as_f64().unwrap();
                j["orientation"][r][c] = serde_json::json!(2.0 * v);
            }
        }
    });
    let text = dycheck_refusal(&scaled);
    assert!(text.contains("`orientation`") && text.contains("not a rigid transform"), "{text}");
    // The old key `tangential` is read as dycheck reads it, distortion included.
    let old_key = case("old_key");
    edit_json(&camera(&old_key), &|j| {
        j.as_object_mut().unwrap().remove("tangential_distortion");
        j["tangential"] = serde_json::json!([0.02, 0.0]);
    });
    let text = dycheck_refusal(&old_key);
    assert!(text.contains("`tangential`") && text.contains("p1 = 0.02"), "{text}");

    // A depth map of another resolution.
    let small = case("small_depth");
    datagen::io::npy::write_npy(&small.join("depth/1x/0_00002.npy"), &[24, 32, 1], &vec![1.0f32; 24 * 32]).unwrap();
    let text = dycheck_refusal(&small);
    assert!(text.contains("depth/1x/0_00002.npy") && text.contains("(48, 64, 1)"), "{text}");

    // A split naming a camera that does not exist, or disagreeing with metadata.json.
    let ghost = case("ghost");
    edit_json(&ghost.join("splits/val.json"), &|j| j["camera_ids"][1] = serde_json::json!(7));
    let text = dycheck_refusal(&ghost);
    assert!(text.contains("splits/val.json") && text.contains("camera_ids[1]") && text.contains("camera 7"), "{text}");
    let shifted = case("shifted");
    edit_json(&shifted.join("splits/train.json"), &|j| j["time_ids"][2] = serde_json::json!(5));
    let text = dycheck_refusal(&shifted);
    assert!(text.contains("splits/train.json") && text.contains("time_ids[2]"), "{text}");

    // A held-out frame at an instant the input camera does not film (unsynchronised cameras).
    let unsynchronised = case("unsynchronised");
    std::fs::remove_dir_all(unsynchronised.join("splits")).unwrap();
    edit_json(&unsynchronised.join("metadata.json"), &|j| j["2_00002"]["warp_id"] = serde_json::json!(9));
    let text = dycheck_refusal(&unsynchronised);
    assert!(text.contains("metadata.json") && text.contains("2_00002.warp_id"), "{text}");
    // Two frames of one camera at one instant.
    let twice = case("twice");
    std::fs::remove_dir_all(twice.join("splits")).unwrap();
    edit_json(&twice.join("metadata.json"), &|j| j["0_00001"]["warp_id"] = serde_json::json!(0));
    let text = dycheck_refusal(&twice);
    assert!(text.contains("metadata.json") && text.contains("warp_id") && text.contains("twice"), "{text}");

    // A frame whose size disagrees with its camera's image_size; a factor the scene lacks.
    let wrong_size = case("wrong_size");
    edit_json(&camera(&wrong_size), &|j| j["image_size"] = serde_json::json!([80, 48]));
    let text = dycheck_refusal(&wrong_size);
    assert!(text.contains("rgb/1x/0_00000.png") && text.contains("image_size"), "{text}");
    let text = format!("{:#}", anyhow::Error::from(read_dycheck(&good, Some(4)).unwrap_err()));
    assert!(text.contains("factor") && text.contains("4x"), "{text}");
}

fn kubric_refusal(dir: &Path) -> String {
    format!("{:#}", anyhow::Error::from(read_kubric4d(dir).unwrap_err()))
}

#[test]
fn broken_kubric4d_scenes_are_refused_naming_the_file_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let good = write_kubric4d(&config(), &RIG, &dir.path().join("scn00007"), |_| {}).unwrap();
    let case = |name: &str| {
        let parent = dir.path().join(name);
        std::fs::create_dir_all(&parent).unwrap();
        copy(&good, &parent.join("scn00007"))
    };
    let metadata = |dir: &Path, v: u32| dir.join(format!("scn00007_p0_v{v}.json"));

    // Views whose frame counts or frame rates disagree.
    let short = case("short");
    edit_json(&metadata(&short, 1), &|j| {
        j["scene"]["num_frames"] = serde_json::json!(2);
        for key in ["positions", "quaternions"] {
            j["camera"][key].as_array_mut().unwrap().pop();
        }
    });
    let text = kubric_refusal(&short);
    assert!(text.contains("scn00007_p0_v1.json") && text.contains("scene.num_frames"), "{text}");
    let fast = case("fast");
    edit_json(&metadata(&fast, 2), &|j| j["scene"]["frame_rate"] = serde_json::json!(30.0));
    let text = kubric_refusal(&fast);
    assert!(text.contains("scn00007_p0_v2.json") && text.contains("scene.frame_rate"), "{text}");

    // A metadata file missing or unreadable; a frame missing.
    let missing = case("missing");
    std::fs::remove_file(metadata(&missing, 2)).unwrap();
    assert!(kubric_refusal(&missing).contains("scn00007_p0_v2.json"));
    let garbled = case("garbled");
    std::fs::write(metadata(&garbled, 0), "[1, 2").unwrap();
    assert!(kubric_refusal(&garbled).contains("invalid JSON"));
    let no_frame = case("no_frame");
    std::fs::remove_file(no_frame.join("frames_p0_v1/depth_00001.tiff")).unwrap();
    assert!(kubric_refusal(&no_frame).contains("frames_p0_v1/depth_00001.tiff"));

    // Depth of another resolution.
    let small = case("small");
    datagen::synth_layouts::write_tiff(&small.join("frames_p0_v0/depth_00000.tiff"), 32, 24, &vec![1.0; 32 * 24])
        .unwrap();
    let text = kubric_refusal(&small);
    assert!(text.contains("depth_00000.tiff") && text.contains("32x24"), "{text}");

    // A quaternion that is not a rotation, a non-finite position, a K with skew.
    let scaled = case("scaled");
    edit_json(&metadata(&scaled, 1), &|j| j["camera"]["quaternions"][2] = serde_json::json!([2.0, 0.0, 0.0, 0.0]));
    let text = kubric_refusal(&scaled);
    assert!(text.contains("camera.quaternions[2]") && text.contains("unit quaternion"), "{text}");
    let nan = case("nan");
    edit_json(&metadata(&nan, 1), &|j| j["camera"]["positions"][0][1] = serde_json::Value::Null);
    let text = kubric_refusal(&nan);
    assert!(text.contains("camera.positions[0][1]") && text.contains("finite"), "{text}");
    let skew = case("skew");
    edit_json(&metadata(&skew, 0), &|j| j["camera"]["K"][0][1] = serde_json::json!(0.1));
    let text = kubric_refusal(&skew);
    assert!(text.contains("camera.K") && text.contains("skew"), "{text}");
    let focal = case("focal");
    edit_json(&metadata(&focal, 0), &|j| j["camera"]["focal_length"] = serde_json::json!(50.0));
    let text = kubric_refusal(&focal);
    assert!(text.contains("camera.focal_length"), "{text}");
}

const PARDOM_VIEWS: [&str; 3] = ["camera0", "yaw-0", "yaw-60"];

/// A ParallelDomain-4D scene as GCD reads it, rendered from static rig cameras (PD's cameras
/// are fixed on the ego rig): view i at the rig's pose of frame 0.
fn pardom_scene(dir: &Path) -> PathBuf {
    let out = dir.join("scene_000042");
    let synth = SynthScene::new(&config()).unwrap();
    let k = config().intrinsics();
    let (mut intrinsics, mut extrinsics) = (Vec::new(), Vec::new());
    for (i, view) in PARDOM_VIEWS.iter().enumerate() {
        let pose = synth.rig_world_from_camera(0, &RIG, i as u32);
        for t in 0..3u32 {
            let truth = synth.render_view(&synth.frame_geometry(t), &pose, &k);
            let ts = t * 10 + 5;
            for sub in ["rgb", "depth"] {
                std::fs::create_dir_all(out.join(sub).join(view)).unwrap();
            }
            truth.rgb.save(out.join(format!("rgb/{view}/{ts:018}.png"))).unwrap();
            crate::tool_layouts::write_npz(
                &out.join(format!("depth/{view}/{ts:018}.npz")),
                vec![("data", vec![48, 64], crate::tool_layouts::Values::F32(truth.depth))],
            );
        }
        let q = glam::DQuat::from_mat3(&DMat3::from_mat4(pose));
        let p = pose.w_axis;
        intrinsics.push(serde_json::json!({"fx": k.x_axis.x, "fy": k.y_axis.y, "cx": k.z_axis.x, "cy": k.z_axis.y}));
        extrinsics.push(serde_json::json!({
            "rotation": {"qw": q.w, "qx": q.x, "qy": q.y, "qz": q.z},
            "translation": {"x": p.x, "y": p.y, "z": p.z},
        }));
    }
    // The LiDAR entry PD lists beside the cameras: no images, skipped.
    intrinsics.push(serde_json::json!({"fx": 0.0, "fy": 0.0, "cx": 0.0, "cy": 0.0}));
    extrinsics.push(extrinsics[0].clone());
    let names: Vec<&str> = PARDOM_VIEWS.iter().copied().chain(["velodyne"]).collect();
    std::fs::create_dir_all(out.join("calibration")).unwrap();
    let calibration = serde_json::json!({"names": names, "intrinsics": intrinsics, "extrinsics": extrinsics});
    std::fs::write(out.join("calibration/abc123.json"), calibration.to_string()).unwrap();
    out
}

#[test]
fn a_pardom4d_scene_reads_back_and_drops_instants_a_view_lacks() {
    let dir = tempfile::tempdir().unwrap();
    let path = pardom_scene(dir.path());
    assert_eq!(detect_multiview_layout(&path).unwrap(), MultiViewLayoutName::Pardom4d);
    let scene = read_multiview_as(&path, None).unwrap();
    let split = scene.split.clone().unwrap();
    assert_eq!((split.input.as_str(), split.held_out.len()), ("yaw-0", 2), "GCD's input ego camera");
    let synth = SynthScene::new(&config()).unwrap();
    let k = config().intrinsics();
    for (i, camera) in scene.cameras.iter().enumerate() {
        assert_eq!(camera.id, PARDOM_VIEWS[i]);
        assert_eq!(camera.time_ids, vec![0, 1, 2]);
        let pose = synth.rig_world_from_camera(0, &RIG, i as u32);
        for t in 0..3u32 {
            let read = camera.sequence.cameras[t as usize];
            let error = (read.world_from_camera - pose).to_cols_array().iter().fold(0.0f64, |m, e| m.max(e.abs()));
            assert!(error < 1e-12, "view {i}: {error}");
            assert_eq!(read.intrinsics, k);
            let truth = synth.render_view(&synth.frame_geometry(t), &pose, &k);
            assert!(camera.sequence.frames[t as usize] == truth.rgb);
            assert_eq!(camera.sequence.depth[t as usize].values, truth.depth);
        }
    }
    // A frame missing from one view is dropped from all, as GCD skips it.
    std::fs::remove_file(path.join(format!("rgb/yaw-60/{:018}.png", 15))).unwrap();
    let scene = read_multiview_as(&path, Some(MultiViewLayoutName::Pardom4d)).unwrap();
    assert!(scene.cameras.iter().all(|c| c.time_ids == [0, 2] && c.sequence.len() == 2));
    assert_eq!(scene.cameras[0].timestamps.clone().unwrap(), vec![0.0, 0.2]);
}

#[test]
fn undocumented_pardom4d_variants_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let good = pardom_scene(dir.path());
    let refusal = |path: &Path| {
        let error = read_multiview_as(path, Some(MultiViewLayoutName::Pardom4d)).unwrap_err();
        format!("{:#}", anyhow::Error::from(error))
    };
    let two = copy(&good, &dir.path().join("two"));
    std::fs::copy(two.join("calibration/abc123.json"), two.join("calibration/def456.json")).unwrap();
    assert!(refusal(&two).contains("found 2"));
    let odd = copy(&good, &dir.path().join("odd"));
    std::fs::copy(odd.join(format!("rgb/yaw-0/{:018}.png", 5)), odd.join(format!("rgb/yaw-0/{:018}.png", 7))).unwrap();
    let text = refusal(&odd);
    assert!(text.contains("000000000000000007.png") && text.contains("timestamp"), "{text}");
    let keys = copy(&good, &dir.path().join("keys"));
    edit_json(&keys.join("calibration/abc123.json"), &|j| {
        let rotation = j["extrinsics"][1]["rotation"].take();
        j["extrinsics"][1] = serde_json::json!({"orientation": rotation});
    });
    let text = refusal(&keys);
    assert!(text.contains("extrinsics[1].rotation") && text.contains("not documented"), "{text}");
    let scaled = copy(&good, &dir.path().join("scaled"));
    edit_json(&scaled.join("calibration/abc123.json"), &|j| {
        j["extrinsics"][2]["rotation"]["qw"] = serde_json::json!(3.0)
    });
    let text = refusal(&scaled);
    assert!(text.contains("extrinsics[2].rotation") && text.contains("unit quaternion"), "{text}");
    let unknown = copy(&good, &dir.path().join("unknown"));
    copy(&unknown.join("rgb/yaw-60"), &unknown.join("rgb/yaw-120"));
    copy(&unknown.join("depth/yaw-60"), &unknown.join("depth/yaw-120"));
    let text = refusal(&unknown);
    assert!(text.contains("yaw-120") && text.contains("names"), "{text}");
}

/// `datagen synth --cameras N --format F` writes a scene the reader detects as F.
#[test]
fn the_synth_command_writes_each_format() {
    let dir = tempfile::tempdir().unwrap();
    for (format, name, layout) in [
        ("dycheck", "dy", MultiViewLayoutName::Dycheck),
        ("kubric4d", "scn00005", MultiViewLayoutName::Kubric4d),
        ("generic", "rig", MultiViewLayoutName::Generic),
    ] {
        let out = dir.path().join(name);
        let status = std::process::Command::new(env!("CARGO_BIN_EXE_datagen"))
            .args(["synth", "--width", "32", "--height", "24", "--frames", "2", "--cameras", "2", "--format", format])
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        assert!(status.status.success(), "{format}: {}", String::from_utf8_lossy(&status.stderr));
        assert_eq!(detect_multiview_layout(&out).unwrap(), layout);
        assert_eq!(read_multiview_as(&out, None).unwrap().cameras.len(), 2, "{format}");
    }
    let refused = std::process::Command::new(env!("CARGO_BIN_EXE_datagen"))
        .args(["synth", "--cameras", "2", "--format", "colmap", "--out"])
        .arg(dir.path().join("x"))
        .output()
        .unwrap();
    assert!(!refused.status.success());
    assert!(String::from_utf8_lossy(&refused.stderr).contains("generic, dycheck, kubric4d"));
}
