//! Self-supervised training pairs for one sequence: cut the video into clip
//! windows, give each clip N novel trajectories (sampled deterministically, or given by the
//! user), compute each frame's exact co-visibility mask from one depth mesh shared by all
//! trajectories, and pack clip + trajectories into shard records.

use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::DMat4;
use image::codecs::png::FilterType;
use image::{GrayImage, RgbImage};
use rayon::prelude::*;
use schemas::{
    ClipRecord, InputDigest, MaskRule, PairKind, ShardStats, ShardWriter, ShardWriterOptions, TrajectoryKind,
    TrajectoryRecord,
};
use serde::{Deserialize, Serialize};

use crate::config_file::{Checked, Validate, check_count};
use crate::error::{Error, Result};
use crate::geometry::covisibility::CovisibilityConfig;
use crate::io::depth_exr::encode_depth_exr;
use crate::io::sequence::Sequence;
use crate::pairs::clip::ClipConfig;
use crate::pairs::depth_noise::{DepthNoiseConfig, NoiseKey, SourceFrame};
use crate::pairs::encode::{mask_png, png};
use crate::pairs::static_background::{StackingConfig, StaticBackground};
use crate::pairs::trajectory::{NovelTrajectory, Sampler, TrajectoryConfig};
use crate::pairs::trajectory_bank::TrajectoryBank;
use foundation::camera::{PinholeCamera, mat3_to_row_major, mat4_to_row_major};

/// Paper value: the CogNVS paper pretrains with N = 2 trajectories per video.
pub const PAPER_TRAJECTORIES: u32 = 2;

/// Most trajectories per clip: every one adds a mask per frame to the clip's record, and the
/// CogNVS paper uses at most 9 (test-time finetuning on Kubric-4D and ParDom-4D); this bounds a
/// record's size, not the method.
pub const MAX_TRAJECTORIES: u32 = 256;

/// Everything `datagen pairs` can be configured with (a TOML file via `--config`). Every field
/// of every section has a documented valid range, checked when the file is loaded and by each
/// library function that takes a config ([`Validate`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(default, deny_unknown_fields)]
pub struct PairsConfig {
    /// Clip windows.
    pub clip: ClipConfig,
    /// Trajectory sampling ranges.
    pub trajectory: TrajectoryConfig,
    /// Occlusion-test settings.
    pub covisibility: CovisibilityConfig,
    /// Depth noise on dynamic objects (off by default).
    pub depth_noise: DepthNoiseConfig,
    /// Static-background stacking settings, used by `datagen render --stack-background`.
    pub static_background: StackingConfig,
    /// Multi-view pairs of multi-camera scenes (camera pairs, how many, least co-visible share).
    pub multiview: crate::pairs::multiview::MultiViewConfig,
}

impl PairsConfig {
    /// Reads a TOML config and checks every field; errors name the file and the key
    /// ([`crate::config_file::load_toml`]).
    pub fn from_toml_file(path: &Path) -> Result<Self> {
        crate::config_file::load_toml(path)
    }
}

impl Validate for PairsConfig {
    fn validate(&self) -> Checked {
        self.clip.validate().map_err(|e| e.under("clip"))?;
        self.trajectory.validate().map_err(|e| e.under("trajectory"))?;
        self.covisibility.validate().map_err(|e| e.under("covisibility"))?;
        self.depth_noise.validate().map_err(|e| e.under("depth_noise"))?;
        self.static_background.validate().map_err(|e| e.under("static_background"))?;
        self.multiview.validate().map_err(|e| e.under("multiview"))
    }
}

/// The trajectories a run uses: sampled ones and/or user-given per-frame poses for the whole
/// sequence (cut to each clip's window).
#[derive(Debug, Clone, Default)]
pub struct TrajectoryRequest {
    /// Number of sampled trajectories per clip.
    pub sampled: u32,
    /// User-given trajectories: (file, `world_from_camera` for every frame of the sequence).
    pub explicit: Vec<(PathBuf, Vec<DMat4>)>,
}

/// Which trajectories `datagen pairs` uses given its flags: explicit files alone unless
/// `--trajectories N` is also given; otherwise N (default 2) sampled ones.
pub fn trajectory_request(sequence: &Sequence, files: &[PathBuf], count: Option<u32>) -> Result<TrajectoryRequest> {
    if let Some(count) = count {
        check_count("trajectories", count, 0, MAX_TRAJECTORIES.into())?;
    }
    let explicit = files
        .iter()
        .map(|path| {
            let poses = crate::pairs::trajectory::read_trajectory_file(
                path,
                sequence.len(),
                &sequence.cameras,
                &sequence.depth[0],
            )?;
            Ok((path.clone(), poses))
        })
        .collect::<Result<Vec<_>>>()?;
    let sampled = match (count, explicit.is_empty()) {
        (Some(n), _) => n,
        (None, true) => PAPER_TRAJECTORIES,
        (None, false) => 0,
    };
    Ok(TrajectoryRequest { sampled, explicit })
}

/// `frame` with the pixels outside `mask` black: the conditioning without depth noise.
fn masked_frame(frame: &RgbImage, mask: &[bool]) -> RgbImage {
    let mut out = frame.clone();
    for (pixel, &keep) in out.pixels_mut().zip(mask) {
        if !keep {
            *pixel = image::Rgb([0, 0, 0]);
        }
    }
    out
}

/// One trajectory's data for one frame: mask PNG, co-visible pixel count, and under depth noise
/// the conditioning PNG with whether it differs from the frame × mask.
type EncodedMask = (Vec<u8>, usize, Option<(Vec<u8>, bool)>);

/// One frame of a clip, encoded: (frame PNG, depth EXR, dynamic-mask PNG, per trajectory its
/// [`EncodedMask`]).
type EncodedFrame = (Vec<u8>, Vec<u8>, Option<Vec<u8>>, Vec<EncodedMask>);

/// One novel path for one clip, before masks.
struct PlannedTrajectory {
    index: u32,
    kind: TrajectoryKind,
    pivot_distance: f64,
    controls: [Vec<f64>; 3],
    rejected: u32,
    poses: Vec<DMat4>,
    bank_entry: Option<schemas::BankProvenance>,
}

/// Where the time of [`generate_clips_timed`] went (for the benchmark's split).
#[derive(Debug, Clone, Copy, Default)]
pub struct PhaseTimes {
    /// CPU seconds, summed over threads, building the depth meshes and their BVHs.
    pub mesh_build: f64,
    /// Wall seconds of the per-frame phase: mesh builds, co-visibility rays, PNG/EXR encoding.
    pub masks_and_encode: f64,
    /// CPU seconds, summed over threads, spent casting co-visibility rays.
    pub ray_cpu: f64,
    /// CPU seconds, summed over threads, spent encoding frames, depth and masks.
    pub encode_cpu: f64,
}

impl PhaseTimes {
    /// Adds another run's times.
    pub fn add(&mut self, other: &Self) {
        self.mesh_build += other.mesh_build;
        self.masks_and_encode += other.masks_and_encode;
        self.ray_cpu += other.ray_cpu;
        self.encode_cpu += other.encode_cpu;
    }
}

/// Generates the records of every clip of `sequence`.
pub fn generate_clips(
    sequence: &Sequence,
    dataset: &str,
    config: &PairsConfig,
    request: &TrajectoryRequest,
    seed: u64,
) -> Result<Vec<ClipRecord>> {
    generate_clips_timed(sequence, dataset, config, request, seed).map(|(records, _)| records)
}

/// [`generate_clips`], also reporting where the time went.
pub fn generate_clips_timed(
    sequence: &Sequence,
    dataset: &str,
    config: &PairsConfig,
    request: &TrajectoryRequest,
    seed: u64,
) -> Result<(Vec<ClipRecord>, PhaseTimes)> {
    config.validate()?;
    check_count("trajectories", request.sampled, 0, MAX_TRAJECTORIES.into())?;
    let frames = sequence.len() as u32;
    // Only bank-sampled trajectories need it; explicit-only runs never open the file.
    let bank = if request.sampled > 0 { sampler_bank(&config.trajectory)? } else { None };
    let mut times = PhaseTimes::default();
    let mut records = Vec::new();
    for (start, length) in config.clip.windows(frames) {
        let (record, clip_times) =
            generate_clip(sequence, dataset, config, request, bank.as_deref(), seed, (start, length))?;
        records.push(record);
        times.add(&clip_times);
    }
    Ok((records, times))
}

/// The trajectory bank `config` samples from, if its sampler uses one (loaded once per file).
fn sampler_bank(config: &TrajectoryConfig) -> Result<Option<std::sync::Arc<TrajectoryBank>>> {
    match (config.sampler, &config.bank) {
        (Sampler::Spherical, _) => Ok(None),
        (_, Some(path)) => TrajectoryBank::load_cached(path).map(Some),
        (sampler, None) => Err(Error::parameter(
            "trajectory.bank",
            format!("sampler = \"{}\" needs a trajectory bank file", sampler.as_str()),
        )),
    }
}

fn generate_clip(
    sequence: &Sequence,
    dataset: &str,
    config: &PairsConfig,
    request: &TrajectoryRequest,
    bank: Option<&TrajectoryBank>,
    seed: u64,
    (start, length): (u32, u32),
) -> Result<(ClipRecord, PhaseTimes)> {
    let mut times = PhaseTimes::default();
    let range = start as usize..(start + length) as usize;
    let cameras = &sequence.cameras[range.clone()];
    let (width, height) = sequence.size();

    // Paths that reach their camera position by crossing the surface are rejected with a cheap
    // test against each frame's depth map, so no frame's mesh has to be kept for sampling.
    let crossing = |i: usize, a: glam::DVec3, b: glam::DVec3| {
        crate::pairs::trajectory::crosses_depth_surface(&sequence.depth[start as usize + i], &cameras[i], a, b)
    };

    let mut planned = Vec::new();
    for index in 0..request.sampled {
        let novel = crate::pairs::trajectory::sample_novel_trajectory(
            cameras,
            &sequence.depth[start as usize],
            &config.trajectory,
            bank,
            seed,
            &sequence.source_id,
            start,
            index,
            Some(&crossing),
        )?;
        planned.push(match novel {
            NovelTrajectory::Spherical(sampled) => PlannedTrajectory {
                index,
                kind: TrajectoryKind::Sampled,
                pivot_distance: sampled.pivot_distance,
                controls: [sampled.azimuth_deg.to_vec(), sampled.elevation_deg.to_vec(), sampled.radius_frac.to_vec()],
                rejected: sampled.rejected_samples,
                poses: sampled.world_from_camera,
                bank_entry: None,
            },
            NovelTrajectory::Bank(drawn) => PlannedTrajectory {
                index,
                kind: TrajectoryKind::Bank,
                pivot_distance: drawn.pivot_distance,
                controls: [Vec::new(), Vec::new(), Vec::new()],
                rejected: drawn.rejected_samples,
                poses: drawn.world_from_camera,
                bank_entry: bank.map(|bank| schemas::BankProvenance {
                    entry_id: drawn.entry_id,
                    entry_row: drawn.row as u32,
                    bank_digest: bank.digest.clone(),
                    mirrored: drawn.mirrored,
                    roll_deg: drawn.roll_deg,
                }),
            },
        });
    }
    for (offset, (_, poses)) in request.explicit.iter().enumerate() {
        planned.push(PlannedTrajectory {
            index: request.sampled + offset as u32,
            kind: TrajectoryKind::Explicit,
            pivot_distance: 0.0,
            controls: [Vec::new(), Vec::new(), Vec::new()],
            rejected: 0,
            poses: poses[range.clone()].to_vec(),
            bank_entry: None,
        });
    }

    // Per frame: build its mesh, one mask per trajectory from it, encode the clip's data once,
    // and drop the mesh (only the frames in flight hold one, which bounds memory).
    let phase = Instant::now();
    let per_frame: Vec<(EncodedFrame, f64, f64, f64)> = range
        .clone()
        .into_par_iter()
        .map(|i| -> Result<_> {
            let source = &sequence.cameras[i];
            let clock = Instant::now();
            let mesh =
                &crate::geometry::depth_mesh::DepthMesh::new(&sequence.depth[i], source, &config.covisibility.mesh);
            let mesh_seconds = clock.elapsed().as_secs_f64();
            let (mut ray_seconds, mut encode_seconds) = (0.0, 0.0);
            let dynamic = sequence.dynamic_masks.as_ref().map(|m| &m[i]);
            let noise = config.depth_noise.enabled.then_some(dynamic).flatten();
            let masks = planned
                .iter()
                .map(|t| {
                    let novel = PinholeCamera { world_from_camera: t.poses[i - start as usize], ..*source };
                    let clock = Instant::now();
                    let mut mask =
                        crate::geometry::covisibility::covisibility_mask(mesh, source, &novel, &config.covisibility);
                    ray_seconds += clock.elapsed().as_secs_f64();
                    let clock = Instant::now();
                    let condition = noise.map(|dynamic| {
                        let key = NoiseKey {
                            seed,
                            source_id: &sequence.source_id,
                            clip_start: start,
                            trajectory: t.index,
                            frame: i as u32,
                        };
                        let offsets = crate::pairs::depth_noise::offsets(
                            &config.depth_noise,
                            &sequence.depth[i],
                            sequence.second_depth.as_ref().map(|d| &d[i]),
                            config.covisibility.mesh.discontinuity_ratio,
                            &key,
                        );
                        let frame = SourceFrame {
                            frame: &sequence.frames[i],
                            depth: &sequence.depth[i],
                            dynamic,
                            camera: source,
                        };
                        let noisy =
                            crate::pairs::depth_noise::render_back(frame, |p| mesh.point(p), &mask, &offsets, &novel);
                        mask = noisy.mask;
                        let differs = noisy.condition != masked_frame(&sequence.frames[i], &mask);
                        (png(&noisy.condition, FilterType::Paeth), differs)
                    });
                    let kept = mask.iter().filter(|&&m| m).count();
                    let encoded = mask_png(&mask, width, height);
                    encode_seconds += clock.elapsed().as_secs_f64();
                    (encoded, kept, condition)
                })
                .collect();
            let clock = Instant::now();
            let frame = png(&sequence.frames[i], FilterType::Paeth);
            let depth = encode_depth_exr(&sequence.depth[i])?;
            let dynamic = dynamic.map(|mask| png(mask, FilterType::Up));
            encode_seconds += clock.elapsed().as_secs_f64();
            Ok(((frame, depth, dynamic, masks), mesh_seconds, ray_seconds, encode_seconds))
        })
        .collect::<Result<_>>()?;
    times.masks_and_encode += phase.elapsed().as_secs_f64();
    times.mesh_build += per_frame.iter().map(|f| f.1).sum::<f64>();
    times.ray_cpu += per_frame.iter().map(|f| f.2).sum::<f64>();
    times.encode_cpu += per_frame.iter().map(|f| f.3).sum::<f64>();
    // Moved, not copied, into the record's columns: copies would hold every encoded byte twice.
    let (mut frames, mut depth, mut dynamic_masks) = (Vec::new(), Vec::new(), Vec::new());
    let mut per_trajectory: Vec<Vec<EncodedMask>> = planned.iter().map(|_| Vec::new()).collect();
    for ((frame, depth_exr, dynamic, masks), ..) in per_frame {
        frames.push(frame);
        depth.push(depth_exr);
        dynamic_masks.extend(dynamic);
        for (column, mask) in per_trajectory.iter_mut().zip(masks) {
            column.push(mask);
        }
    }

    let pixels = (width as usize * height as usize * length as usize).max(1) as f64;
    let trajectories = planned
        .iter()
        .zip(per_trajectory)
        .map(|(plan, encoded)| TrajectoryRecord {
            index: plan.index,
            kind: plan.kind,
            bank_entry: plan.bank_entry.clone(),
            mask_rule: MaskRule::Exact,
            pivot_distance: plan.pivot_distance,
            azimuth_deg: plan.controls[0].clone(),
            elevation_deg: plan.controls[1].clone(),
            radius_frac: plan.controls[2].clone(),
            rejected_samples: plan.rejected,
            world_from_camera: plan.poses.iter().map(mat4_to_row_major).collect(),
            covisible_fraction: encoded.iter().map(|m| m.1).sum::<usize>() as f64 / pixels,
            // Stored only when depth noise changed some frame; otherwise it is frames × mask.
            condition: encoded
                .iter()
                .any(|m| m.2.as_ref().is_some_and(|c| c.1))
                .then(|| encoded.iter().map(|m| m.2.as_ref().expect("noise on").0.clone()).collect()),
            covisible_mask: encoded.into_iter().map(|m| m.0).collect(),
        })
        .collect();
    let clip_id = format!("{dataset}/{}/{start}", sequence.source_id);
    let record = ClipRecord {
        clip_id,
        source_id: sequence.source_id.clone(),
        dataset: dataset.to_owned(),
        source_path: sequence.path.display().to_string(),
        clip_start: start,
        fps: sequence.fps,
        width,
        height,
        seed,
        tool_version: format!("datagen {}", env!("CARGO_PKG_VERSION")),
        intrinsics: cameras.iter().map(|c| mat3_to_row_major(&c.intrinsics)).collect(),
        world_from_camera: cameras.iter().map(|c| mat4_to_row_major(&c.world_from_camera)).collect(),
        frames,
        depth,
        dynamic_mask: sequence.dynamic_masks.as_ref().map(|_| dynamic_masks),
        trajectories,
        pair_kind: PairKind::Monocular,
        source_camera: None,
        target_camera: None,
    };
    Ok((record, times))
}

/// Writes `records` as one finished shard `out/{name}.parquet` (temp name, rename, stats marker).
pub fn write_shard(
    out: &Path,
    name: &str,
    records: &[ClipRecord],
    input: InputDigest,
) -> Result<(PathBuf, ShardStats)> {
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let path = out.join(format!("{name}.parquet"));
    let mut writer = ShardWriter::create(&path, ShardWriterOptions::default())?;
    for record in records {
        writer.write(record)?;
    }
    writer.add_input(input);
    let stats = writer.finish()?;
    Ok((path, stats))
}

/// The novel-view render used by exports and `datagen render`: source frame + depth seen from
/// the novel camera, holes black.
pub fn render_novel(
    frame: &RgbImage,
    depth: &foundation::depth::DepthMap,
    source: &PinholeCamera,
    novel: &PinholeCamera,
    config: &CovisibilityConfig,
) -> RgbImage {
    let mesh = crate::geometry::depth_mesh::DepthMesh::new(depth, source, &config.mesh);
    crate::geometry::render::render_novel_view(&mesh, frame, source, novel).0
}

/// What [`render_sequence`] produced.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RenderSummary {
    /// Frames rendered.
    pub frames: usize,
    /// Hole pixels of the per-frame renders, over all frames.
    pub holes: usize,
    /// Of those, filled by the stacked static background.
    pub filled: usize,
}

/// `datagen render`: renders every frame of `sequence` from the trajectory in `trajectory_file`
/// into `out/frames/%05d.png`, `out/holes/%05d.png` (255 = hole) and `out/render.mp4`. With
/// `stacking`, holes are filled from the static background fused over the whole sequence.
pub fn render_sequence(
    sequence: &Sequence,
    trajectory_file: &Path,
    out: &Path,
    config: &PairsConfig,
    stacking: bool,
) -> Result<RenderSummary> {
    config.validate()?;
    let poses = crate::pairs::trajectory::read_trajectory_file(
        trajectory_file,
        sequence.len(),
        &sequence.cameras,
        &sequence.depth[0],
    )?;
    render_sequence_along(sequence, &poses, out, config, stacking)
}

/// [`render_sequence`] along `poses` (one `world_from_camera` per frame, read already).
pub fn render_sequence_along(
    sequence: &Sequence,
    poses: &[DMat4],
    out: &Path,
    config: &PairsConfig,
    stacking: bool,
) -> Result<RenderSummary> {
    config.validate()?;
    if poses.len() != sequence.len() {
        return Err(Error::parameter(
            "poses",
            format!("{} poses for a sequence of {} frames", poses.len(), sequence.len()),
        ));
    }
    for sub in ["frames", "holes"] {
        std::fs::create_dir_all(out.join(sub)).map_err(|e| Error::io(out.join(sub), e))?;
    }
    let ratio = config.covisibility.mesh.discontinuity_ratio;
    let background = stacking.then(|| StaticBackground::from_sequence(sequence, &config.static_background, ratio));
    let rendered: Vec<(RgbImage, usize, usize)> = (0..sequence.len())
        .into_par_iter()
        .map(|i| -> Result<_> {
            let novel = PinholeCamera { world_from_camera: poses[i], ..sequence.cameras[i] };
            let (mut image, mut holes) = render_frame(sequence, i, &novel, &config.covisibility);
            let hole_count = holes.pixels().filter(|p| p.0[0] != 0).count();
            let filled = background.as_ref().map_or(0, |b| b.fill_holes(&mut image, &mut holes, &novel));
            let save = |image: &dyn Fn(&Path) -> image::ImageResult<()>, path: PathBuf| {
                image(&path).map_err(|e| Error::Image { context: path.display().to_string(), reason: e.to_string() })
            };
            save(&|p| holes.save(p), out.join(format!("holes/{i:05}.png")))?;
            save(&|p| image.save(p), out.join(format!("frames/{i:05}.png")))?;
            Ok((image, hole_count, filled))
        })
        .collect::<Result<_>>()?;
    let (width, height) = sequence.size();
    let summary = RenderSummary {
        frames: rendered.len(),
        holes: rendered.iter().map(|r| r.1).sum(),
        filled: rendered.iter().map(|r| r.2).sum(),
    };
    let frames: Vec<RgbImage> = rendered.into_iter().map(|r| r.0).collect();
    if width % 2 == 0 && height % 2 == 0 {
        let fps = if sequence.fps > 0.0 { sequence.fps } else { DEFAULT_RENDER_FPS };
        foundation::video::encode_video(&out.join("render.mp4"), &frames, fps)?;
    }
    Ok(summary)
}

/// Frame `i` of `sequence` rendered from `novel` through its own depth mesh: image and holes.
pub fn render_frame(
    sequence: &Sequence,
    i: usize,
    novel: &PinholeCamera,
    config: &CovisibilityConfig,
) -> (RgbImage, GrayImage) {
    let source = &sequence.cameras[i];
    let mesh = crate::geometry::depth_mesh::DepthMesh::new(&sequence.depth[i], source, &config.mesh);
    crate::geometry::render::render_novel_view(&mesh, &sequence.frames[i], source, novel)
}

/// Frame rate of `render.mp4` when the input's is unknown (image-folder inputs).
const DEFAULT_RENDER_FPS: f64 = 24.0;
