//! Every training pair of one synchronised multi-camera scene: the monocular self-supervised
//! pairs of each camera with depth ([`crate::pairs::generator`], the camera's video as a
//! sequence) beside the multi-view pairs of the chosen camera pairs ([`crate::pairs::multiview`]),
//! and `datagen pairs` on a scene folder, which writes them as one shard.

use std::path::{Path, PathBuf};

use schemas::{ClipRecord, InputDigest, PairKind, ShardStats};

use crate::config_file::Validate;
use crate::error::{Error, Result};
use crate::io::multiview::{CameraView, MultiViewScene};
use crate::pairs::generator::{PairsConfig, TrajectoryRequest, generate_clips};
use crate::pairs::multiview::{DroppedPair, MultiViewPairsConfig, camera_pair_clips, camera_pairs};

/// The records one scene gives.
#[derive(Debug, Clone, Default)]
pub struct ScenePairs {
    /// Monocular records first (camera order), then multi-view ones (camera pair order).
    pub records: Vec<ClipRecord>,
    /// The camera pairs used, `(source, target)`, in order.
    pub camera_pairs: Vec<(String, String)>,
    /// Windows left out for their co-visible fraction.
    pub dropped: Vec<DroppedPair>,
}

/// One unit of work done for a scene (for progress bars): a camera's monocular pairs or a
/// camera pair's multi-view pairs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SceneProgress {
    /// Units done.
    pub done: usize,
    /// Units in all.
    pub total: usize,
}

/// Every record of `scene`: the monocular pairs of each camera with depth (when
/// `config.multiview.monocular`, `trajectories` sampled ones per clip) and the multi-view pairs
/// of the chosen camera pairs. `progress` hears of each camera and camera pair done.
pub fn generate_scene_clips(
    scene: &MultiViewScene,
    dataset: &str,
    config: &PairsConfig,
    trajectories: u32,
    seed: u64,
    progress: &mut dyn FnMut(SceneProgress),
) -> Result<ScenePairs> {
    config.validate()?;
    let pairs = camera_pairs(scene, &config.multiview, seed)?;
    let monocular: Vec<&CameraView> = if config.multiview.monocular && trajectories > 0 {
        scene.cameras.iter().filter(|c| c.has_depth).collect()
    } else {
        Vec::new()
    };
    let total = monocular.len() + pairs.len();
    let mut done = 0;
    let mut out = ScenePairs { camera_pairs: pairs.clone(), ..ScenePairs::default() };
    let multiview =
        MultiViewPairsConfig { clip: &config.clip, covisibility: &config.covisibility, multiview: &config.multiview };
    let request = TrajectoryRequest { sampled: trajectories, explicit: Vec::new() };
    for camera in monocular {
        // Seeds and clip ids derive from the source id: the scene's and the camera's, so two
        // scenes with the same camera names get different trajectories.
        let mut sequence = camera.sequence.clone();
        sequence.source_id = format!("{}/{}", scene.scene_id, camera.id);
        for mut record in generate_clips(&sequence, dataset, config, &request, seed)? {
            record.source_camera = Some(camera.id.clone());
            record.target_camera = Some(camera.id.clone());
            out.records.push(record);
        }
        done += 1;
        progress(SceneProgress { done, total });
    }
    for (source, target) in &pairs {
        let (source, target) = (scene.camera(source).expect("checked"), scene.camera(target).expect("checked"));
        let (records, dropped) = camera_pair_clips(scene, (source, target), dataset, &multiview, seed)?;
        out.records.extend(records);
        out.dropped.extend(dropped);
        done += 1;
        progress(SceneProgress { done, total });
    }
    Ok(out)
}

/// What [`write_scene_pairs`] wrote.
#[derive(Debug, Clone)]
pub struct SceneShard {
    /// The shard file.
    pub path: PathBuf,
    /// Its stats marker's content.
    pub stats: ShardStats,
    /// The scene's pairs (records moved into the shard are summarised here: camera pairs and
    /// dropped windows; `records` is empty).
    pub pairs: ScenePairs,
    /// Monocular and multi-view records written.
    pub counts: (usize, usize),
}

/// `datagen pairs` on a multi-camera folder: reads the scene, makes its monocular and multi-view
/// pairs and writes them as one shard `out/{scene id}.parquet`. Nothing is written when the scene
/// is refused.
pub fn write_scene_pairs(
    dir: &Path,
    out: &Path,
    dataset: &str,
    config: &PairsConfig,
    trajectories: u32,
    seed: u64,
    progress: &mut dyn FnMut(SceneProgress),
) -> Result<SceneShard> {
    write_scene_pairs_as(dir, None, out, dataset, config, trajectories, seed, progress)
}

/// [`write_scene_pairs`] with the scene read in `layout` (the detected one when `None`).
#[allow(clippy::too_many_arguments)] // write_scene_pairs' arguments and the layout
pub fn write_scene_pairs_as(
    dir: &Path,
    layout: Option<crate::io::layout::MultiViewLayoutName>,
    out: &Path,
    dataset: &str,
    config: &PairsConfig,
    trajectories: u32,
    seed: u64,
    progress: &mut dyn FnMut(SceneProgress),
) -> Result<SceneShard> {
    config.validate()?;
    let (scene, content_hash) =
        rayon::join(|| crate::io::layout::read_multiview_as(dir, layout), || foundation::hashing::hash_tree(dir));
    let scene = scene?;
    let input = InputDigest { source_path: dir.display().to_string(), content_hash: content_hash? };
    let mut pairs = generate_scene_clips(&scene, dataset, config, trajectories, seed, progress)?;
    if pairs.records.is_empty() {
        return Err(no_pairs(dir, config, &pairs));
    }
    let records = std::mem::take(&mut pairs.records);
    let multiview = records.iter().filter(|r| r.pair_kind == PairKind::Multiview).count();
    let counts = (records.len() - multiview, multiview);
    let (path, stats) = crate::pairs::generator::write_shard(out, &scene.scene_id, &records, input)?;
    Ok(SceneShard { path, stats, pairs, counts })
}

/// Why a scene gave no record: an empty shard is not a result.
fn no_pairs(dir: &Path, config: &PairsConfig, pairs: &ScenePairs) -> Error {
    let threshold = config.multiview.min_covisible_fraction;
    let reason = match pairs.dropped.iter().map(|d| d.covisible_fraction).max_by(f64::total_cmp) {
        Some(best) => format!(
            "no pairs: all {} windows of the camera pairs are below multiview.min_covisible_fraction {threshold} (the \
             best is {best:.4}), and no camera gave monocular pairs; lower the fraction or choose other camera_pairs",
            pairs.dropped.len()
        ),
        None => "no pairs: no camera pair has a window and no camera gave monocular pairs".to_string(),
    };
    Error::invalid(dir, "pairs", reason)
}
