//! Synchronised multi-camera scenes: `datagen synth --cameras` writes them in the generic
//! multi-camera layout with exact ground truth, the reader gives back every camera's frames,
//! depth and poses, one camera's render into another matches that camera's real frames where it
//! fills them, and broken scenes are refused naming the file and field.

use std::path::{Path, PathBuf};

use datagen::geometry::depth_mesh::{DepthMesh, MeshConfig};
use datagen::geometry::render::render_novel_view;
use datagen::io::multiview::read_multiview;
use datagen::synth::{CameraRig, SynthConfig, SynthScene, write_multiview};
use foundation::camera::PinholeCamera;

const RIG: CameraRig = CameraRig { cameras: 3, spacing_deg: 8.0 };

fn config(frames: u32) -> SynthConfig {
    SynthConfig { width: 96, height: 64, frames, ..SynthConfig::default() }
}

fn scene(dir: &Path, frames: u32) -> PathBuf {
    write_multiview(&config(frames), &RIG, &dir.join("rig"), |_| {}).unwrap()
}

#[test]
fn a_synthetic_rig_reads_back_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let read = read_multiview(&scene(dir.path(), 3)).unwrap();
    let ids: Vec<&str> = read.cameras.iter().map(|c| c.id.as_str()).collect();
    assert_eq!((ids, read.frames()), (vec!["cam00", "cam01", "cam02"], 3));
    let synth = SynthScene::new(&config(3)).unwrap();
    for frame in 0..3u32 {
        let geometry = synth.frame_geometry(frame);
        for (c, camera) in read.cameras.iter().enumerate() {
            let pose = synth.rig_world_from_camera(frame, &RIG, c as u32);
            let truth = synth.render_view(&geometry, &pose, &config(3).intrinsics());
            let f = frame as usize;
            assert!(camera.sequence.frames[f] == truth.rgb, "{} frame {frame}", camera.id);
            assert_eq!(camera.sequence.depth[f].values, truth.depth, "{} frame {frame}", camera.id);
            assert_eq!(camera.sequence.cameras[f].world_from_camera, pose, "{} frame {frame}", camera.id);
            assert_eq!(camera.sequence.cameras[f].intrinsics, config(3).intrinsics());
        }
    }
    let seconds = read.cameras[1].timestamps.clone().unwrap();
    assert_eq!(seconds, vec![0.0, 1.0 / 24.0, 2.0 / 24.0]);
}

/// The core of a multi-view pair: camera s's frame rendered into camera t fills most of t's
/// image for neighbouring cameras, the surface it shows there is the one t really sees (the
/// render's depth equals t's exact depth), and on those pixels its colours are t's real ones up
/// to the render's bilinear resampling of s's pixels.
#[test]
fn one_cameras_render_into_another_matches_its_real_frame() {
    let dir = tempfile::tempdir().unwrap();
    let config = SynthConfig { width: 192, height: 128, frames: 2, ..SynthConfig::default() };
    let rig = write_multiview(&config, &RIG, &dir.path().join("rig"), |_| {}).unwrap();
    let read = read_multiview(&rig).unwrap();
    let width = config.width as usize;
    let (mut pixels, mut filled, mut same_surface, mut compared) = (0usize, 0usize, 0usize, 0usize);
    let (mut close, mut total_error) = (0usize, 0u64);
    for frame in 0..2 {
        for (s, t) in [(0, 1), (1, 0), (1, 2), (0, 2)] {
            let (source, target) = (&read.cameras[s].sequence, &read.cameras[t].sequence);
            let mesh = DepthMesh::new(&source.depth[frame], &source.cameras[frame], &MeshConfig::default());
            let novel: PinholeCamera = target.cameras[frame];
            let (render, _) = render_novel_view(&mesh, &source.frames[frame], &source.cameras[frame], &novel);
            let hits = mesh.view(&novel).surface_hits();
            for (p, hit) in hits.iter().enumerate() {
                pixels += 1;
                let Some(distance) = hit else { continue };
                filled += 1;
                let (x, y) = ((p % width) as f64, (p / width) as f64);
                let point = novel.center() + novel.pixel_ray(x, y).normalize() * distance;
                let (_, z) = novel.project(point).unwrap();
                let truth = f64::from(target.depth[frame].values[p]);
                if (z - truth).abs() > 0.01 * truth {
                    continue;
                }
                same_surface += 1;
                let (a, b) =
                    (render.get_pixel(x as u32, y as u32).0, target.frames[frame].get_pixel(x as u32, y as u32).0);
                // Colours are compared where t's image is smooth (its 3 × 3 neighbourhood within
                // SMOOTH levels): across the synthetic textures' sharp check edges a resampled
                // colour and a point sample differ by the edge's contrast.
                if !smooth(&target.frames[frame], x as u32, y as u32) {
                    continue;
                }
                compared += 1;
                let error = (0..3).map(|k| a[k].abs_diff(b[k])).max().unwrap();
                total_error += u64::from(error);
                close += usize::from(error <= 8);
            }
        }
    }
    let filled_share = filled as f64 / pixels as f64;
    let same_share = same_surface as f64 / filled as f64;
    let (close_share, mean_error) = (close as f64 / compared as f64, total_error as f64 / compared as f64);
    println!(
        "render s→t at 192×128, 8° apart: {:.1} % of t filled, {:.1} % of those on t's own surface; on the {compared} smooth ones {:.1} % within 8 levels, mean max-channel error {mean_error:.2}",
        100.0 * filled_share,
        100.0 * same_share,
        100.0 * close_share
    );
    assert!(filled_share > 0.6, "neighbouring cameras see most of each other's surface: {filled_share}");
    assert!(same_share > 0.9, "the render shows what t sees: {same_share}");
    assert!(compared > 2000, "enough smooth pixels to compare: {compared}");
    assert!(close_share > 0.8 && mean_error < 10.0, "colours: {close_share} within 8 levels, mean {mean_error}");
}

/// Most difference (any channel) between a pixel and its 3 × 3 neighbours for it to count as smooth.
const SMOOTH: u8 = 10;

fn smooth(image: &image::RgbImage, x: u32, y: u32) -> bool {
    let centre = image.get_pixel(x, y).0;
    let (x0, y0) = (x.saturating_sub(1), y.saturating_sub(1));
    let (x1, y1) = ((x + 1).min(image.width() - 1), (y + 1).min(image.height() - 1));
    (y0..=y1).all(|v| (x0..=x1).all(|u| (0..3).all(|k| image.get_pixel(u, v).0[k].abs_diff(centre[k]) <= SMOOTH)))
}

fn refusal(dir: &Path) -> String {
    format!("{:#}", anyhow::Error::from(read_multiview(dir).unwrap_err()))
}

#[test]
fn broken_rigs_are_refused_naming_the_camera_file_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let good = scene(dir.path(), 3);
    let copy = |name: &str| {
        let to = dir.path().join(name);
        std::process::Command::new("cp").arg("-r").arg(&good).arg(&to).status().unwrap();
        to
    };
    let edit_json = |path: PathBuf, change: &dyn Fn(&mut serde_json::Value)| {
        let mut json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
        change(&mut json);
        std::fs::write(&path, json.to_string()).unwrap();
    };

    // A camera with fewer frames than the others.
    let short = copy("short");
    let other = write_multiview(&config(2), &RIG, &dir.path().join("two"), |_| {}).unwrap();
    std::fs::remove_dir_all(short.join("cam02")).unwrap();
    std::process::Command::new("cp").arg("-r").arg(other.join("cam02")).arg(short.join("cam02")).status().unwrap();
    let text = refusal(&short);
    assert!(text.contains("cam02") && text.contains("frames") && text.contains("2 frames"), "{text}");

    // Timestamps that disagree, that are missing from one camera, that are not finite.
    let late = copy("late");
    edit_json(late.join("cam01/cameras.json"), &|j| j["timestamps"][2] = serde_json::json!(0.1));
    let text = refusal(&late);
    assert!(text.contains("cam01/cameras.json") && text.contains("timestamps[2]"), "{text}");
    let partial = copy("partial");
    edit_json(partial.join("cam02/cameras.json"), &|j| {
        j.as_object_mut().unwrap().remove("timestamps");
    });
    let text = refusal(&partial);
    assert!(text.contains("cam02/cameras.json") && text.contains("timestamps"), "{text}");
    let backwards = copy("backwards");
    edit_json(backwards.join("cam00/cameras.json"), &|j| j["timestamps"][1] = serde_json::json!(-1.0));
    let text = refusal(&backwards);
    assert!(text.contains("cam00/cameras.json") && text.contains("timestamps[1]"), "{text}");

    // A camera whose cameras.json is missing, or unreadable.
    let missing = copy("missing");
    std::fs::remove_file(missing.join("cam01/cameras.json")).unwrap();
    let text = refusal(&missing);
    assert!(text.contains("cam01"), "{text}");
    let garbled = copy("garbled");
    std::fs::write(garbled.join("cam01/cameras.json"), "{ not json").unwrap();
    let text = refusal(&garbled);
    assert!(text.contains("cam01/cameras.json"), "{text}");

    // A pose that is not rigid, one that is not finite.
    for (name, value) in [("scaled", serde_json::json!(2.0)), ("nan", serde_json::json!("nan"))] {
        let bad = copy(name);
        edit_json(bad.join("cam02/cameras.json"), &|j| j["world_from_camera"][1][0] = value.clone());
        let text = refusal(&bad);
        assert!(text.contains("cam02/cameras.json") && text.contains("world_from_camera"), "{name}: {text}");
    }

    // One camera is not a rig.
    let single = dir.path().join("single");
    std::fs::create_dir_all(&single).unwrap();
    std::process::Command::new("cp").arg("-r").arg(good.join("cam00")).arg(single.join("cam00")).status().unwrap();
    assert!(refusal(&single).contains("multi-camera"));
}
