//! Multi-view training pairs from a synchronised multi-camera scene
//! ([`crate::io::multiview::MultiViewScene`]): for a source camera s and a target camera t, over
//! the instants both film, the target is t's real frames and the conditioning is s's frames
//! rendered into t through s's depth mesh ([`crate::geometry::render`], first surface hit, the
//! same renderer as `datagen render`). The mask says which target pixels s sees, by the first rule
//! that applies ([`MaskRule`], recorded per trajectory):
//!
//! - **exact**, where t has depth: a target pixel is kept when its own surface point (its depth
//!   lifted along its ray) is the first surface s sees along the ray to it, tested against s's
//!   depth mesh by the monocular co-visibility kernel itself
//!   ([`crate::geometry::covisibility::target_visibility_mask`]: the same mesh, skirts, epsilon and
//!   triangle test), and dropped when its surface turns its back to s;
//! - **dataset**, where t has no depth but the dataset ships co-visibility masks of t seen from s
//!   (DyCheck's `covisible/`, made for its held-out cameras against its input camera): those;
//! - **coverage** otherwise: the target pixels s's surface covers (the render's non-holes).
//!
//! This is the supervision the CogNVS paper names as missing ("does not take advantage of 3D/4D
//! datasets") and that GCD and ReCamMaster train on. The conditioning is the render whatever the
//! rule.
//!
//! Clip windows are cut as for monocular pairs ([`crate::pairs::clip::ClipConfig`]) over the
//! instants both cameras film, matched by `time_ids` (a camera may film a subset of the instants;
//! `clip_start` is the target's frame index of a window's first instant). Frames stay at the
//! target camera's resolution, like a monocular clip's. A camera without depth (`has_depth`
//! false) can be a target, never a source.
//!
//! Which camera pairs (all ordered pairs, or a list), how many per scene (a subset drawn by seed)
//! and the least co-visible fraction a pair must reach are the `[multiview]` table of the pairs
//! config ([`MultiViewConfig`]). [`crate::pairs::scene`] puts a scene's monocular and multi-view
//! pairs together.

use std::collections::{BTreeMap, BTreeSet};

use image::codecs::png::FilterType;
use image::{GrayImage, RgbImage};
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use schemas::{ClipRecord, MaskRule, PairKind, TrajectoryKind, TrajectoryRecord};
use serde::{Deserialize, Serialize};

use crate::config_file::{Checked, KeyError, Validate, check_float};
use crate::error::{Error, Result};
use crate::geometry::covisibility::{CovisibilityConfig, target_visibility_mask};
use crate::geometry::depth_mesh::DepthMesh;
use crate::io::depth_exr::encode_depth_exr;
use crate::io::multiview::{CameraView, MultiViewScene};
use crate::pairs::clip::ClipConfig;
use crate::pairs::encode::png;
use foundation::camera::{mat3_to_row_major, mat4_to_row_major};

/// Which multi-view pairs a multi-camera scene gives (the `[multiview]` table of a pairs config,
/// `[pairs.multiview]` of a corpus config).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MultiViewConfig {
    /// Ordered `[source, target]` camera id pairs, e.g. `[["cam00", "cam01"]]`; empty: every
    /// ordered pair of two cameras whose source has depth. Valid: two different non-empty ids,
    /// no pair twice; in a scene, ids of its cameras and a source with depth (checked per scene).
    pub camera_pairs: Vec<[String; 2]>,
    /// At most this many camera pairs per scene, drawn from the chosen ones by seed and scene id
    /// (0: all of them). Valid: any.
    pub pairs_per_scene: u32,
    /// Clip windows whose masks cover less than this fraction of the target's pixels are left
    /// out (0: keep every one). Valid: [0, 1].
    pub min_covisible_fraction: f64,
    /// Also write monocular self-supervised pairs of every camera with depth (the sampled
    /// trajectories of the run). Valid: any.
    pub monocular: bool,
}

impl Default for MultiViewConfig {
    fn default() -> Self {
        Self { camera_pairs: Vec::new(), pairs_per_scene: 0, min_covisible_fraction: 0.0, monocular: true }
    }
}

impl Validate for MultiViewConfig {
    fn validate(&self) -> Checked {
        let mut seen = BTreeSet::new();
        for (i, [source, target]) in self.camera_pairs.iter().enumerate() {
            let key = format!("camera_pairs[{i}]");
            if source.trim().is_empty() || target.trim().is_empty() {
                return Err(KeyError::new(key, "camera ids must be non-empty"));
            }
            if source == target {
                return Err(KeyError::new(key, format!("source and target are both `{source}`; name two cameras")));
            }
            if !seen.insert((source, target)) {
                return Err(KeyError::new(key, format!("[\"{source}\", \"{target}\"] is listed twice")));
            }
        }
        check_float("min_covisible_fraction", self.min_covisible_fraction, 0.0..=1.0)
    }
}

/// A multi-view clip window left out, and why.
#[derive(Debug, Clone, PartialEq)]
pub struct DroppedPair {
    /// Source camera id.
    pub source: String,
    /// Target camera id.
    pub target: String,
    /// The target's frame index where the window starts.
    pub clip_start: u32,
    /// Its co-visible fraction, below `min_covisible_fraction`.
    pub covisible_fraction: f64,
}

/// The `(source, target)` camera pairs of `scene` that `config` asks for, in order: the listed
/// ones (checked against the scene), or every ordered pair whose source has depth; then, with
/// `pairs_per_scene`, that many of them drawn by `seed` and the scene id (kept in that order).
pub fn camera_pairs(scene: &MultiViewScene, config: &MultiViewConfig, seed: u64) -> Result<Vec<(String, String)>> {
    config.validate().map_err(|e| e.under("multiview"))?;
    let mut pairs = Vec::new();
    if config.camera_pairs.is_empty() {
        for source in scene.cameras.iter().filter(|c| c.has_depth) {
            for target in scene.cameras.iter().filter(|c| c.id != source.id) {
                pairs.push((source.id.clone(), target.id.clone()));
            }
        }
    } else {
        let ids = || scene.cameras.iter().map(|c| format!("`{}`", c.id)).collect::<Vec<_>>().join(", ");
        for (i, [source, target]) in config.camera_pairs.iter().enumerate() {
            let field = format!("multiview.camera_pairs[{i}]");
            for id in [source, target] {
                if scene.camera(id).is_none() {
                    return Err(Error::invalid(
                        &scene.path,
                        field,
                        format!("the scene has no camera `{id}` (its cameras: {})", ids()),
                    ));
                }
            }
            if scene.camera(source).is_some_and(|c| !c.has_depth) {
                return Err(Error::invalid(
                    &scene.path,
                    field,
                    format!("camera `{source}` has no depth, so it cannot be a source (it can be a target)"),
                ));
            }
            pairs.push((source.clone(), target.clone()));
        }
    }
    let wanted = config.pairs_per_scene as usize;
    if wanted > 0 && wanted < pairs.len() {
        let mut order: Vec<usize> = (0..pairs.len()).collect();
        order.shuffle(&mut pair_rng(seed, &scene.scene_id));
        let mut kept: Vec<usize> = order[..wanted].to_vec();
        kept.sort_unstable();
        pairs = kept.into_iter().map(|i| pairs[i].clone()).collect();
    }
    Ok(pairs)
}

/// The generator of the camera-pair subset: BLAKE3 of a purpose tag, the seed and the scene id.
fn pair_rng(seed: u64, scene_id: &str) -> ChaCha8Rng {
    let mut hasher = blake3::Hasher::new();
    hasher.update(b"cognvs multiview camera pairs v1");
    hasher.update(&seed.to_le_bytes());
    hasher.update(scene_id.as_bytes());
    ChaCha8Rng::from_seed(*hasher.finalize().as_bytes())
}

/// The frames of `source` and `target` filming the same instants, as `(target frame, source
/// frame)` index pairs in the target's order.
pub fn shared_instants(source: &CameraView, target: &CameraView) -> Vec<(usize, usize)> {
    let by_instant: BTreeMap<usize, usize> = source.time_ids.iter().enumerate().map(|(k, &id)| (id, k)).collect();
    target.time_ids.iter().enumerate().filter_map(|(k, id)| by_instant.get(id).map(|&j| (k, j))).collect()
}

/// What multi-view pairs are made with: the clip windows, the source's depth mesh and the
/// visibility test against it, and the `[multiview]` table (borrowed from a
/// [`crate::pairs::generator::PairsConfig`]).
#[derive(Debug, Clone, Copy)]
pub struct MultiViewPairsConfig<'a> {
    /// How the shared instants are cut into clips.
    pub clip: &'a ClipConfig,
    /// How the source's depth becomes the mesh the render casts rays into, and the exact
    /// visibility test of target points against it (the monocular pairs' settings).
    pub covisibility: &'a CovisibilityConfig,
    /// Camera pairs, how many, least co-visible fraction.
    pub multiview: &'a MultiViewConfig,
}

/// The multi-view records of one camera pair: one per clip window of their shared instants,
/// except those below `min_covisible_fraction` (returned as dropped).
pub fn camera_pair_clips(
    scene: &MultiViewScene,
    (source, target): (&CameraView, &CameraView),
    dataset: &str,
    config: &MultiViewPairsConfig,
    seed: u64,
) -> Result<(Vec<ClipRecord>, Vec<DroppedPair>)> {
    if !source.has_depth {
        return Err(Error::invalid(
            &source.sequence.path,
            "depth",
            format!("camera `{}` has no depth, so it cannot be the source of a multi-view pair", source.id),
        ));
    }
    let shared = shared_instants(source, target);
    let (mut records, mut dropped) = (Vec::new(), Vec::new());
    if shared.is_empty() {
        return Ok((records, dropped));
    }
    for (start, length) in config.clip.windows(shared.len() as u32) {
        let window = &shared[start as usize..(start + length) as usize];
        let record = window_record(scene, (source, target), window, dataset, config, seed)?;
        let fraction = record.trajectories[0].covisible_fraction;
        if fraction < config.multiview.min_covisible_fraction {
            dropped.push(DroppedPair {
                source: source.id.clone(),
                target: target.id.clone(),
                clip_start: record.clip_start,
                covisible_fraction: fraction,
            });
        } else {
            records.push(record);
        }
    }
    Ok((records, dropped))
}

/// One frame of a multi-view window, encoded: (target frame PNG, target depth EXR, dynamic mask
/// PNG, conditioning PNG, mask PNG, co-visible pixels).
type EncodedFrame = (Vec<u8>, Vec<u8>, Option<Vec<u8>>, Vec<u8>, Vec<u8>, usize);

fn window_record(
    scene: &MultiViewScene,
    (source, target): (&CameraView, &CameraView),
    window: &[(usize, usize)],
    dataset: &str,
    config: &MultiViewPairsConfig,
    seed: u64,
) -> Result<ClipRecord> {
    let (s, t) = (&source.sequence, &target.sequence);
    let (width, height) = t.size();
    let mask_rule = mask_rule(scene, source, target);
    // Per frame, in parallel: s's mesh, its render into t and the mask, and t's data encoded; the
    // mesh is dropped when the frame is done, as in the monocular generator.
    let encoded: Vec<EncodedFrame> = window
        .par_iter()
        .map(|&(kt, ks)| -> Result<_> {
            let (condition, mask) = render_into_target((source, ks), (target, kt), mask_rule, config.covisibility);
            let kept = mask.pixels().filter(|p| p.0[0] != 0).count();
            let dynamic = t.dynamic_masks.as_ref().map(|m| png(&m[kt], FilterType::Up));
            Ok((
                png(&t.frames[kt], FilterType::Paeth),
                encode_depth_exr(&t.depth[kt])?,
                dynamic,
                png(&condition, FilterType::Paeth),
                png(&mask, FilterType::Up),
                kept,
            ))
        })
        .collect::<Result<_>>()?;
    let pixels = (width as usize * height as usize * window.len()).max(1) as f64;
    let covisible_fraction = encoded.iter().map(|e| e.5).sum::<usize>() as f64 / pixels;
    let (mut frames, mut depth, mut dynamic, mut condition, mut masks) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for (frame, depth_exr, dynamic_mask, conditioning, mask, _) in encoded {
        frames.push(frame);
        depth.push(depth_exr);
        dynamic.extend(dynamic_mask);
        condition.push(conditioning);
        masks.push(mask);
    }
    let clip_start = window[0].0 as u32;
    let trajectory = TrajectoryRecord {
        index: 0,
        kind: TrajectoryKind::Camera,
        pivot_distance: 0.0,
        azimuth_deg: Vec::new(),
        elevation_deg: Vec::new(),
        radius_frac: Vec::new(),
        rejected_samples: 0,
        world_from_camera: window.iter().map(|&(_, ks)| mat4_to_row_major(&s.cameras[ks].world_from_camera)).collect(),
        covisible_mask: masks,
        // Always stored: a render of another camera is not the target × mask.
        condition: Some(condition),
        covisible_fraction,
        bank_entry: None,
        mask_rule,
    };
    Ok(ClipRecord {
        clip_id: format!("{dataset}/{}/{}/from-{}/{clip_start}", scene.scene_id, target.id, source.id),
        source_id: format!("{}/{}", scene.scene_id, target.id),
        dataset: dataset.to_owned(),
        source_path: scene.path.display().to_string(),
        clip_start,
        fps: t.fps,
        width,
        height,
        seed,
        tool_version: format!("datagen {}", env!("CARGO_PKG_VERSION")),
        intrinsics: window.iter().map(|&(kt, _)| mat3_to_row_major(&t.cameras[kt].intrinsics)).collect(),
        world_from_camera: window.iter().map(|&(kt, _)| mat4_to_row_major(&t.cameras[kt].world_from_camera)).collect(),
        frames,
        depth,
        dynamic_mask: t.dynamic_masks.as_ref().map(|_| dynamic),
        trajectories: vec![trajectory],
        pair_kind: PairKind::Multiview,
        source_camera: Some(source.id.clone()),
        target_camera: Some(target.id.clone()),
    })
}

/// The rule that makes the masks of the pair `source` → `target` (module docs): exact where the
/// target has depth, the dataset's masks where it ships them for this source (DyCheck's are of
/// the held-out cameras against the input camera of its split), the render's coverage otherwise.
pub fn mask_rule(scene: &MultiViewScene, source: &CameraView, target: &CameraView) -> MaskRule {
    let shipped_for_source = scene.split.as_ref().is_some_and(|split| split.input == source.id);
    if target.has_depth {
        MaskRule::Exact
    } else if target.covisible.is_some() && shipped_for_source {
        MaskRule::Dataset
    } else {
        MaskRule::Coverage
    }
}

/// Frame `ks` of `source` rendered into camera `target` at its frame `kt`: the conditioning
/// (holes black) and the mask by `rule` (255 where s sees the target pixel, 0 elsewhere).
pub fn render_into_target(
    (source, ks): (&CameraView, usize),
    (target, kt): (&CameraView, usize),
    rule: MaskRule,
    config: &CovisibilityConfig,
) -> (RgbImage, GrayImage) {
    let (s, t) = (&source.sequence, &target.sequence);
    let mesh = DepthMesh::new(&s.depth[ks], &s.cameras[ks], &config.mesh);
    let (image, holes) =
        crate::geometry::render::render_novel_view(&mesh, &s.frames[ks], &s.cameras[ks], &t.cameras[kt]);
    let (width, height) = t.size();
    let binary = |kept: Vec<bool>| {
        let values = kept.into_iter().map(|kept| if kept { 255 } else { 0 }).collect();
        GrayImage::from_raw(width, height, values).expect("one value per target pixel")
    };
    let mask = match (rule, &target.covisible) {
        (MaskRule::Exact, _) => {
            binary(target_visibility_mask(&mesh, &s.cameras[ks], &t.depth[kt], &t.cameras[kt], config))
        }
        (MaskRule::Dataset, Some(shipped)) => binary(shipped[kt].pixels().map(|p| p.0[0] != 0).collect()),
        _ => binary(holes.pixels().map(|p| p.0[0] == 0).collect()),
    };
    (image, mask)
}
