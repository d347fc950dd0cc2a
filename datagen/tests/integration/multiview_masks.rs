//! Multi-view masks against exact visibility: on synthetic multi-camera scenes with thin poles and
//! plates, objects occluding each other both ways and targets that see sides of objects the source
//! sees from behind, written in the generic and Kubric-4D layouts and read back by their readers,
//! the masks of targets with depth are made by the exact rule and match the ray-traced visibility
//! as closely as the monocular kernel does; DyCheck's held-out targets take the dataset's masks
//! where it ships them, the render's coverage where not; the conditioning is the render whatever
//! the rule.

use std::path::Path;

use datagen::geometry::covisibility::{CovisibilityConfig, covisibility_mask};
use datagen::geometry::depth_mesh::{DepthMesh, MeshConfig};
use datagen::geometry::render::render_novel_view;
use datagen::io::layout::read_multiview_as;
use datagen::io::multiview::MultiViewScene;
use datagen::pairs::generator::PairsConfig;
use datagen::pairs::scene::generate_scene_clips;
use datagen::synth::{CameraRig, SynthConfig, SynthScene, ground_truth_covisibility};
use datagen::synth_layouts::{SynthFormat, write_dycheck, write_multiview_as};
use schemas::{ClipRecord, MaskRule, PairKind};

/// Least IoU of a scene's kept pixels with the exact visibility: the monocular kernel's accuracy
/// on the hidden Blender scenes (IoU 0.9953), which the issue asks multi-view masks to reach.
const MIN_IOU: f64 = 0.995;
/// Most target pixels kept that the source does not see, as a share of all target pixels: the
/// monocular kernel's 0.19 % on the same scenes, rounded up.
const MAX_FALSE_KEEP: f64 = 0.002;

/// Kept pixels against the truth, summed over masks.
#[derive(Debug, Default, Clone, Copy)]
struct Tally {
    both: usize,
    false_keep: usize,
    false_drop: usize,
    pixels: usize,
}

impl Tally {
    fn add(&mut self, kept: impl IntoIterator<Item = bool>, truth: &[bool]) {
        for (kept, &truth) in kept.into_iter().zip(truth) {
            self.pixels += 1;
            match (kept, truth) {
                (true, true) => self.both += 1,
                (true, false) => self.false_keep += 1,
                (false, true) => self.false_drop += 1,
                (false, false) => {}
            }
        }
    }

    fn iou(&self) -> f64 {
        self.both as f64 / (self.both + self.false_keep + self.false_drop).max(1) as f64
    }

    fn false_keep_share(&self) -> f64 {
        self.false_keep as f64 / self.pixels.max(1) as f64
    }

    fn false_drop_share(&self) -> f64 {
        self.false_drop as f64 / self.pixels.max(1) as f64
    }

    fn line(&self) -> String {
        format!(
            "IoU {:.4}, kept but hidden {:.3} %, seen but dropped {:.3} % of {} pixels",
            self.iou(),
            100.0 * self.false_keep_share(),
            100.0 * self.false_drop_share(),
            self.pixels
        )
    }
}

fn grey(bytes: &[u8]) -> image::GrayImage {
    image::load_from_memory(bytes).unwrap().to_luma8()
}

fn rgb(bytes: &[u8]) -> image::RgbImage {
    image::load_from_memory(bytes).unwrap().to_rgb8()
}

/// Every ordered camera pair's multi-view pairs of `scene`, one clip of all its frames each.
fn multiview_records(scene: &MultiViewScene, frames: u32) -> Vec<ClipRecord> {
    let mut config = PairsConfig::default();
    config.clip.length = frames;
    config.clip.stride = frames;
    config.multiview.monocular = false;
    let pairs = generate_scene_clips(scene, "synth", &config, 0, 7, &mut |_| {}).unwrap();
    pairs.records.into_iter().filter(|r| r.pair_kind == PairKind::Multiview).collect()
}

/// A scene of the visibility tests: thin objects among the boxes and balls.
fn synth(seed: u64, frames: u32) -> SynthConfig {
    SynthConfig { width: 320, height: 192, frames, thin_objects: 8, static_objects: 4, seed, ..SynthConfig::default() }
}

/// The masks of every multi-view pair of the scene `config` filmed by `rig` in `format`, and the
/// render's coverage of the same pairs, against the ray-traced visibility of each target pixel's
/// surface point from the source camera; checks that the records hold the render as their
/// conditioning and name the exact rule.
fn measure(config: &SynthConfig, rig: &CameraRig, format: SynthFormat, dir: &Path) -> [Tally; 3] {
    let path =
        write_multiview_as(config, rig, format, &dir.join(format!("{format:?}-{}", config.seed)), |_| {}).unwrap();
    let scene = read_multiview_as(&path, None).unwrap();
    let records = multiview_records(&scene, config.frames);
    let cameras = rig.cameras as usize;
    assert_eq!(records.len(), cameras * (cameras - 1), "every ordered pair of cameras with depth");
    let truth = SynthScene::new(config).unwrap();
    let k = config.intrinsics();
    let index = |id: &Option<String>| scene.cameras.iter().position(|c| Some(&c.id) == id.as_ref()).unwrap();
    let (mut exact, mut coverage, mut monocular) = (Tally::default(), Tally::default(), Tally::default());
    for record in &records {
        let (s, t) = (index(&record.source_camera), index(&record.target_camera));
        let trajectory = &record.trajectories[0];
        assert_eq!(trajectory.mask_rule, MaskRule::Exact, "{}: the target has depth", record.clip_id);
        let (source, target) = (&scene.cameras[s].sequence, &scene.cameras[t].sequence);
        for frame in 0..config.frames {
            let f = frame as usize;
            let geometry = truth.frame_geometry(frame);
            let target_view = truth.render_view(&geometry, &truth.rig_world_from_camera(frame, rig, t as u32), &k);
            let seen = ground_truth_covisibility(
                &truth,
                frame,
                &target_view,
                &truth.rig_world_from_camera(frame, rig, s as u32),
                &k,
            );
            let mask = grey(&trajectory.covisible_mask[f]);
            exact.add(mask.pixels().map(|p| p.0[0] == 255), &seen);
            // The monocular kernel on the same two cameras (the source's pixels seen by the
            // target): the accuracy the issue asks the multi-view masks to reach.
            let source_view = truth.render_view(&geometry, &truth.rig_world_from_camera(frame, rig, s as u32), &k);
            let seen_by_target = ground_truth_covisibility(
                &truth,
                frame,
                &source_view,
                &truth.rig_world_from_camera(frame, rig, t as u32),
                &k,
            );
            // The conditioning is the render, whatever made the mask.
            let mesh = DepthMesh::new(&source.depth[f], &source.cameras[f], &MeshConfig::default());
            let config = CovisibilityConfig::default();
            monocular.add(covisibility_mask(&mesh, &source.cameras[f], &target.cameras[f], &config), &seen_by_target);
            let (render, holes) = render_novel_view(&mesh, &source.frames[f], &source.cameras[f], &target.cameras[f]);
            assert!(rgb(&trajectory.condition.as_ref().unwrap()[f]) == render, "{} frame {f}", record.clip_id);
            coverage.add(holes.pixels().map(|p| p.0[0] == 0), &seen);
        }
    }
    [exact, coverage, monocular]
}

#[test]
fn masks_of_targets_with_depth_match_exact_visibility() {
    let dir = tempfile::tempdir().unwrap();
    // Neighbouring cameras 12° apart: occlusion edges both ways, poles and plates a few pixels
    // wide, at a size near the paper's 720 × 480, where the masks must be as accurate as the
    // monocular kernel is on the Blender scenes.
    let near = SynthConfig { width: 640, height: 384, ..synth(3, 1) };
    let [exact, coverage, monocular] =
        measure(&near, &CameraRig { cameras: 3, spacing_deg: 12.0 }, SynthFormat::Generic, dir.path());
    println!(
        "cameras 12° apart, 640×384, generic: exact rule {}; render coverage {}; the monocular kernel on the same \
         cameras {}",
        exact.line(),
        coverage.line(),
        monocular.line()
    );
    assert!(exact.iou() >= MIN_IOU && exact.false_keep_share() <= MAX_FALSE_KEEP, "{}", exact.line());
    // Cameras 30° apart, read from Kubric-4D's layout: the outer two, 60° apart, each see sides
    // of the objects that the other sees from behind. Smaller frames; there the masks must be at
    // least as accurate as the monocular kernel's on the same cameras (the source's pixels seen
    // by the target), pair for pair summed.
    let wide = synth(4, 1);
    let [exact, coverage, monocular] =
        measure(&wide, &CameraRig { cameras: 3, spacing_deg: 30.0 }, SynthFormat::Kubric4d, dir.path());
    println!(
        "cameras 30° apart, 320×192, Kubric-4D: exact rule {}; render coverage {}; the monocular kernel on the same \
         cameras {}",
        exact.line(),
        coverage.line(),
        monocular.line()
    );
    assert!(exact.iou() >= monocular.iou(), "{} against the monocular kernel's {}", exact.line(), monocular.line());
    assert!(exact.false_keep_share() <= monocular.false_keep_share(), "{}", exact.line());
}

#[test]
fn dycheck_held_out_targets_take_the_shipped_masks_where_present_and_the_coverage_elsewhere() {
    let dir = tempfile::tempdir().unwrap();
    let config = SynthConfig { width: 96, height: 64, frames: 3, thin_objects: 2, ..SynthConfig::default() };
    let rig = CameraRig { cameras: 3, spacing_deg: 10.0 };
    let path = write_dycheck(&config, &rig, &dir.path().join("dycheck"), |_| {}).unwrap();
    let scene = read_multiview_as(&path, None).unwrap();
    let input = scene.split.as_ref().unwrap().input.clone();
    let records = multiview_records(&scene, 2);
    assert!(!records.is_empty());
    for record in &records {
        assert_eq!(record.source_camera.as_ref(), Some(&input), "only the input camera has depth");
        let target = scene.camera(record.target_camera.as_ref().unwrap()).unwrap();
        let trajectory = &record.trajectories[0];
        assert_eq!(trajectory.mask_rule, MaskRule::Dataset, "{}", record.clip_id);
        let shipped = target.covisible.as_ref().unwrap();
        let start = record.clip_start as usize;
        for (k, mask) in trajectory.covisible_mask.iter().enumerate() {
            let expected: Vec<u8> = shipped[start + k].pixels().map(|p| if p.0[0] != 0 { 255 } else { 0 }).collect();
            assert_eq!(grey(mask).into_raw(), expected, "{} frame {k}", record.clip_id);
        }
    }
    // Without shipped masks the held-out targets fall back to the render's coverage.
    std::fs::remove_dir_all(path.join("covisible")).unwrap();
    let scene = read_multiview_as(&path, None).unwrap();
    for record in multiview_records(&scene, 2) {
        let trajectory = &record.trajectories[0];
        assert_eq!(trajectory.mask_rule, MaskRule::Coverage, "{}", record.clip_id);
        let condition = rgb(&trajectory.condition.as_ref().unwrap()[0]);
        let mask = grey(&trajectory.covisible_mask[0]);
        for (c, m) in condition.pixels().zip(mask.pixels()) {
            if m.0[0] == 0 {
                assert_eq!(c.0, [0, 0, 0], "{}: coverage keeps exactly the render's non-holes", record.clip_id);
            }
        }
    }
}
