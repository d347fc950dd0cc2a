//! `datagen inspect`: statistics of a shard or a whole corpus folder, and an export of each
//! training pair as image folders plus a contact sheet a person can judge at a glance
//! (target | mask | conditioning | novel-view render, with a header naming the columns and the
//! frame index on each row), or each clip as the public cog-nvs finetuning code reads a sequence
//! (`gt_rgb.mp4` + `train_render{k}.mp4`).

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use image::{GrayImage, Rgb, RgbImage};
use rayon::prelude::*;
use schemas::{ClipRecord, InputStatus, ShardReader, TrajectoryRecord};

use crate::error::{Error, Result};
use crate::geometry::covisibility::CovisibilityConfig;
use crate::io::sequence::Sequence;
use crate::pairs::static_background::{StackingConfig, StaticBackground};
use foundation::camera::{PinholeCamera, mat3_from_row_major, mat4_from_row_major};

/// Frames shown per pair on the contact sheet.
const SHEET_FRAMES: usize = 4;
/// The contact sheet's columns, left to right, as its header names them (the last only when the
/// novel view is rendered).
pub const SHEET_COLUMNS: [&str; 4] = ["target", "co-visibility mask", "conditioning", "novel render"];

/// Statistics of one trajectory (one training pair).
#[derive(Debug, Clone, serde::Serialize)]
pub struct PairStats {
    /// `{clip_id}/t{index}`.
    pub pair_id: String,
    /// Trajectory kind.
    pub kind: String,
    /// Pair kind: `monocular` or `multiview`.
    pub pair_kind: String,
    /// Source and target camera ids, for pairs of a multi-camera scene.
    pub cameras: Option<(String, String)>,
    /// Mean co-visible fraction over the clip's frames.
    pub covisible_fraction: f64,
    /// Rejected samples before this trajectory.
    pub rejected_samples: u32,
    /// Whether conditioning frames are stored (depth noise) rather than derived.
    pub stored_condition: bool,
}

/// Statistics of one shard.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ShardSummary {
    /// The shard file.
    pub path: PathBuf,
    /// File size in bytes.
    pub bytes: u64,
    /// Whether its stats marker exists.
    pub finished: bool,
    /// Per clip: id, dataset, frames, width, height and pairs.
    pub clips: Vec<(String, String, usize, u32, u32, Vec<PairStats>)>,
}

/// Finished and unfinished shard files under `path` (or `path` itself).
pub fn shard_paths(path: &Path) -> Result<Vec<PathBuf>> {
    if path.is_file() {
        return Ok(vec![path.to_owned()]);
    }
    let entries = std::fs::read_dir(path).map_err(|e| Error::io(path, e))?;
    let mut shards: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let name = p.file_name().unwrap_or_default().to_string_lossy();
            name.ends_with(".parquet") && !name.starts_with('.')
        })
        .collect();
    shards.sort();
    Ok(shards)
}

/// Reads one shard's statistics.
pub fn summarize_shard(path: &Path) -> Result<ShardSummary> {
    let bytes = std::fs::metadata(path).map_err(|e| Error::io(path, e))?.len();
    let mut clips = Vec::new();
    for record in ShardReader::open(path)? {
        let record = record?;
        let pairs = record.trajectories.iter().map(|t| pair_stats(&record, t)).collect();
        clips.push((
            record.clip_id.clone(),
            record.dataset.clone(),
            record.num_frames(),
            record.width,
            record.height,
            pairs,
        ));
    }
    Ok(ShardSummary { path: path.to_owned(), bytes, finished: schemas::is_finished(path), clips })
}

fn pair_stats(record: &ClipRecord, trajectory: &TrajectoryRecord) -> PairStats {
    PairStats {
        pair_id: pair_id(record, trajectory),
        kind: trajectory.kind.as_str().to_owned(),
        pair_kind: record.pair_kind.as_str().to_owned(),
        cameras: record.source_camera.clone().zip(record.target_camera.clone()),
        covisible_fraction: trajectory.covisible_fraction,
        rejected_samples: trajectory.rejected_samples,
        stored_condition: trajectory.condition.is_some(),
    }
}

/// A file-system friendly id of a pair: the clip id with `/` as `__`, then `__t{index}`.
pub fn pair_id(record: &ClipRecord, trajectory: &TrajectoryRecord) -> String {
    format!("{}__t{}", record.clip_id.replace('/', "__"), trajectory.index)
}

/// Human-readable report of shards, and for a corpus folder, of its status tables.
pub fn report(path: &Path) -> Result<String> {
    let mut out = String::new();
    let (mut total_clips, mut total_pairs, mut total_bytes) = (0usize, 0usize, 0u64);
    let mut per_dataset: BTreeMap<String, (usize, usize)> = BTreeMap::new();
    let mut per_kind: BTreeMap<String, usize> = BTreeMap::new();
    for shard in shard_paths(path)? {
        let summary = summarize_shard(&shard)?;
        let pairs: usize = summary.clips.iter().map(|c| c.5.len()).sum();
        let _ = writeln!(
            out,
            "{}: {} clips, {} pairs, {:.1} MB{}",
            shard.display(),
            summary.clips.len(),
            pairs,
            summary.bytes as f64 / 1e6,
            if summary.finished { "" } else { " (UNFINISHED: no stats marker)" }
        );
        for (clip_id, dataset, frames, width, height, pairs) in &summary.clips {
            let _ = writeln!(out, "  {clip_id}: {frames} frames {width}x{height}");
            for pair in pairs {
                let _ = writeln!(
                    out,
                    "    t{}: {}{}, {} trajectory, co-visible {:.1} %, {} rejected samples{}",
                    pair.pair_id.rsplit("__t").next().unwrap_or("?"),
                    pair.pair_kind,
                    pair.cameras.as_ref().map_or(String::new(), |(s, t)| format!(" {s}→{t}")),
                    pair.kind,
                    100.0 * pair.covisible_fraction,
                    pair.rejected_samples,
                    if pair.stored_condition { ", stored conditioning" } else { "" }
                );
            }
            let entry = per_dataset.entry(dataset.clone()).or_default();
            entry.0 += 1;
            entry.1 += pairs.len();
            for pair in pairs {
                *per_kind.entry(pair.pair_kind.clone()).or_default() += 1;
            }
        }
        total_clips += summary.clips.len();
        total_pairs += pairs;
        total_bytes += summary.bytes;
    }
    let _ = writeln!(out, "total: {total_clips} clips, {total_pairs} pairs, {:.1} MB", total_bytes as f64 / 1e6);
    for (dataset, (clips, pairs)) in &per_dataset {
        let _ = writeln!(out, "  {dataset}: {clips} clips, {pairs} pairs");
    }
    let kinds: Vec<String> = per_kind.iter().map(|(kind, n)| format!("{n} {kind}")).collect();
    let _ = writeln!(out, "pairs by kind: {}", if kinds.is_empty() { "none".to_owned() } else { kinds.join(", ") });
    if path.join("status").is_dir() {
        let status = crate::corpus::build::read_corpus_status(path)?;
        let count = |s: InputStatus| status.values().filter(|r| r.status == s).count();
        let _ = writeln!(
            out,
            "inputs: {} ok, {} skipped, {} failed",
            count(InputStatus::Ok),
            count(InputStatus::Skipped),
            count(InputStatus::Failed)
        );
        let mut reasons: BTreeMap<String, usize> = BTreeMap::new();
        for record in status.values().filter(|r| r.status != InputStatus::Ok) {
            *reasons.entry(format!("{}: {}", record.status.as_str(), reason_kind(&record.reason))).or_default() += 1;
        }
        for (reason, n) in reasons {
            let _ = writeln!(out, "  {n} × {reason}");
        }
    }
    Ok(out)
}

/// The part of a failure message that is the same across inputs (drops the leading path).
pub(crate) fn reason_kind(reason: &str) -> &str {
    reason.split_once(": ").map_or(reason, |(_, rest)| rest)
}

/// How the contact sheet's novel-render column is made.
#[derive(Debug, Clone, Default)]
pub struct ExportRender {
    /// The mesh settings of the render.
    pub covisibility: CovisibilityConfig,
    /// Fill the render's holes from the static background stacked over the clip's frames.
    pub stacking: Option<StackingConfig>,
}

/// Exports every pair of every shard under `path` into `out/<pair_id>/`: `target/%05d.png`,
/// `cond/%05d.png`, `mask/%05d.png` (255 co-visible, 0 hidden), `meta.json`,
/// `contact_sheet.png` (with a novel-render column when `render` is given). Returns the pair
/// folders.
pub fn export(path: &Path, out: &Path, render: Option<&ExportRender>) -> Result<Vec<PathBuf>> {
    let mut folders = Vec::new();
    for shard in shard_paths(path)? {
        for record in ShardReader::open(&shard)? {
            let record = record?;
            let renderer = match render {
                Some(options) => Some(ClipRenderer::new(&record, options)?),
                None => None,
            };
            for trajectory in &record.trajectories {
                folders.push(export_pair(&record, trajectory, out, renderer.as_ref())?);
            }
        }
    }
    Ok(folders)
}

/// Renders one clip's frames from novel cameras, with its stacked background if asked for.
struct ClipRenderer<'a> {
    sequence: Sequence,
    background: Option<StaticBackground>,
    options: &'a ExportRender,
}

impl<'a> ClipRenderer<'a> {
    fn new(record: &ClipRecord, options: &'a ExportRender) -> Result<Self> {
        let sequence = Sequence::from_clip(record)?;
        let ratio = options.covisibility.mesh.discontinuity_ratio;
        let background = options.stacking.as_ref().map(|s| StaticBackground::from_sequence(&sequence, s, ratio));
        Ok(Self { sequence, background, options })
    }

    fn render(&self, frame: usize, novel: &PinholeCamera) -> RgbImage {
        let (mut image, mut holes) =
            crate::pairs::generator::render_frame(&self.sequence, frame, novel, &self.options.covisibility);
        if let Some(background) = &self.background {
            background.fill_holes(&mut image, &mut holes, novel);
        }
        image
    }
}

fn decode_png(bytes: &[u8], context: &str) -> Result<image::DynamicImage> {
    image::load_from_memory_with_format(bytes, image::ImageFormat::Png)
        .map_err(|e| Error::Image { context: context.to_owned(), reason: e.to_string() })
}

fn save<P: image::PixelWithColorType>(image: &image::ImageBuffer<P, Vec<P::Subpixel>>, path: &Path) -> Result<()>
where
    [P::Subpixel]: image::EncodableLayout,
{
    image.save(path).map_err(|e| Error::Image { context: path.display().to_string(), reason: e.to_string() })
}

/// The conditioning frame: stored, or the target with hidden pixels black.
fn condition_frame(target: &RgbImage, mask: &GrayImage) -> RgbImage {
    RgbImage::from_fn(target.width(), target.height(), |x, y| {
        if mask.get_pixel(x, y).0[0] > 0 { *target.get_pixel(x, y) } else { Rgb([0, 0, 0]) }
    })
}

fn export_pair(
    record: &ClipRecord,
    trajectory: &TrajectoryRecord,
    out: &Path,
    render: Option<&ClipRenderer>,
) -> Result<PathBuf> {
    let folder = out.join(pair_id(record, trajectory));
    for sub in ["target", "cond", "mask"] {
        std::fs::create_dir_all(folder.join(sub)).map_err(|e| Error::io(folder.join(sub), e))?;
    }
    let frames = record.num_frames();
    let sheet_frames: Vec<usize> = {
        let mut picked: Vec<usize> =
            (0..SHEET_FRAMES).map(|k| k * frames.saturating_sub(1) / (SHEET_FRAMES - 1).max(1)).collect();
        picked.dedup();
        picked
    };
    let rows: Vec<Option<Vec<RgbImage>>> = (0..frames)
        .into_par_iter()
        .map(|i| -> Result<Option<Vec<RgbImage>>> {
            let target = decode_png(&record.frames[i], &format!("{}: frames[{i}]", record.clip_id))?.to_rgb8();
            let mask = decode_png(&trajectory.covisible_mask[i], &format!("{}: covisible_mask[{i}]", record.clip_id))?
                .to_luma8();
            let cond = match &trajectory.condition {
                Some(stored) => decode_png(&stored[i], &format!("{}: condition[{i}]", record.clip_id))?.to_rgb8(),
                None => condition_frame(&target, &mask),
            };
            save(&target, &folder.join(format!("target/{i:05}.png")))?;
            save(&cond, &folder.join(format!("cond/{i:05}.png")))?;
            save(&mask, &folder.join(format!("mask/{i:05}.png")))?;
            if !sheet_frames.contains(&i) {
                return Ok(None);
            }
            let mut row = vec![target.clone(), foundation::contact_sheet::mask_to_rgb(&mask), cond];
            if let Some(render) = render {
                row.push(render.render(i, &camera(record, &trajectory.world_from_camera[i], i)));
            }
            Ok(Some(row))
        })
        .collect::<Result<_>>()?;
    let sheet: Vec<Vec<RgbImage>> = rows.into_iter().flatten().collect();
    let columns = sheet_columns(record, render.is_some());
    let columns: Vec<&str> = columns.iter().map(String::as_str).collect();
    let labels: Vec<String> = sheet_frames.iter().map(|i| format!("frame {i}")).collect();
    foundation::contact_sheet::write_labelled_contact_sheet(
        &folder.join("contact_sheet.png"),
        &columns,
        &labels,
        &sheet,
    )?;
    let meta = serde_json::json!({
        "pair_id": pair_id(record, trajectory),
        "clip_id": record.clip_id,
        "source_id": record.source_id,
        "dataset": record.dataset,
        "source_path": record.source_path,
        "clip_start": record.clip_start,
        "frames": frames,
        "width": record.width,
        "height": record.height,
        "fps": record.fps,
        "seed": record.seed,
        "tool_version": record.tool_version,
        "pair_kind": record.pair_kind.as_str(),
        "source_camera": record.source_camera,
        "target_camera": record.target_camera,
        "intrinsics": record.intrinsics,
        "source_world_from_camera": record.world_from_camera,
        "trajectory": {
            "index": trajectory.index,
            "kind": trajectory.kind.as_str(),
            "pivot_distance": trajectory.pivot_distance,
            "azimuth_deg": trajectory.azimuth_deg,
            "elevation_deg": trajectory.elevation_deg,
            "radius_frac": trajectory.radius_frac,
            "rejected_samples": trajectory.rejected_samples,
            "covisible_fraction": trajectory.covisible_fraction,
            "world_from_camera": trajectory.world_from_camera,
        },
        "contact_sheet_columns": columns,
        "contact_sheet_frames": sheet_frames,
    });
    let meta_path = folder.join("meta.json");
    std::fs::write(&meta_path, serde_json::to_vec_pretty(&meta).expect("json"))
        .map_err(|e| Error::io(&meta_path, e))?;
    Ok(folder)
}

/// The contact sheet's column headers ([`SHEET_COLUMNS`]), naming for pairs of a multi-camera
/// scene the target camera and the pair kind or source camera (`target cam01`, `conditioning: from
/// cam00`), in the characters the sheet's font has; single-camera monocular pairs keep the plain
/// headers.
pub(crate) fn sheet_columns(record: &ClipRecord, with_render: bool) -> Vec<String> {
    let mut columns: Vec<String> =
        SHEET_COLUMNS[..if with_render { 4 } else { 3 }].iter().map(|c| c.to_string()).collect();
    if let Some(target) = &record.target_camera {
        columns[0] = format!("{} {target}", columns[0]);
    }
    match (record.pair_kind, &record.source_camera) {
        (schemas::PairKind::Multiview, Some(source)) => columns[2] = format!("{}: from {source}", columns[2]),
        (kind, _) if record.target_camera.is_some() => columns[2] = format!("{}: {}", columns[2], kind.as_str()),
        _ => {}
    }
    columns
}

fn camera(record: &ClipRecord, pose: &[f64; 16], frame: usize) -> PinholeCamera {
    PinholeCamera {
        width: record.width,
        height: record.height,
        intrinsics: mat3_from_row_major(&record.intrinsics[frame]),
        world_from_camera: mat4_from_row_major(pose),
    }
}

/// How `datagen inspect --export` lays out what it writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ExportLayout {
    /// One folder per pair: `target/`, `cond/`, `mask/` PNGs, `meta.json`, `contact_sheet.png`
    /// ([`export`]).
    #[default]
    Pairs,
    /// One folder per clip as the public cog-nvs finetuning code reads a sequence
    /// ([`export_cog_nvs`]).
    CogNvs,
}

/// Frame rate of the cog-nvs videos of a clip whose source rate is unknown (image-folder inputs):
/// the 24 fps of SA-V and of the public code's own renders.
pub const COG_NVS_DEFAULT_FPS: f64 = 24.0;

/// Name of the cog-nvs target video of a clip (the public code's `gt_rgb.mp4`).
pub const COG_NVS_TARGET: &str = "gt_rgb.mp4";

/// Name of the cog-nvs conditioning video of the clip's `k`-th trajectory (k from 1), the
/// public code's `train_render{k}.mp4`.
pub fn cog_nvs_render_name(k: usize) -> String {
    format!("train_render{k}.mp4")
}

/// Exports every clip of every shard under `path` into `out/<clip id, / as __>/` in the layout
/// the public cog-nvs finetuning code reads: `gt_rgb.mp4` (the clip's frames) and
/// `train_render{k}.mp4` for its k-th trajectory (k from 1; the masked conditioning, stored or
/// frames × mask), H.264 at the clip's frame rate ([`COG_NVS_DEFAULT_FPS`] when unknown), plus
/// `meta.json` mapping each k to its trajectory. Returns the clip folders. Clips of odd width
/// or height cannot be H.264 4:2:0 and are an error naming the clip.
pub fn export_cog_nvs(path: &Path, out: &Path) -> Result<Vec<PathBuf>> {
    let mut folders = Vec::new();
    for shard in shard_paths(path)? {
        for record in ShardReader::open(&shard)? {
            folders.push(export_clip_cog_nvs(&record?, out)?);
        }
    }
    Ok(folders)
}

fn export_clip_cog_nvs(record: &ClipRecord, out: &Path) -> Result<PathBuf> {
    let folder = out.join(record.clip_id.replace('/', "__"));
    std::fs::create_dir_all(&folder).map_err(|e| Error::io(&folder, e))?;
    let fps = if record.fps.is_finite() && record.fps > 0.0 { record.fps } else { COG_NVS_DEFAULT_FPS };
    let in_clip = |e: foundation::Error| match e {
        foundation::Error::InvalidParameter { name, reason } => {
            Error::invalid(&folder, name, format!("clip `{}`: {reason}", record.clip_id))
        }
        other => other.into(),
    };
    let targets: Vec<RgbImage> = (0..record.num_frames())
        .into_par_iter()
        .map(|i| Ok(decode_png(&record.frames[i], &format!("{}: frames[{i}]", record.clip_id))?.to_rgb8()))
        .collect::<Result<_>>()?;
    foundation::video::encode_video(&folder.join(COG_NVS_TARGET), &targets, fps).map_err(in_clip)?;
    let mut renders = Vec::new();
    for (position, trajectory) in record.trajectories.iter().enumerate() {
        let conditioning: Vec<RgbImage> = (0..record.num_frames())
            .into_par_iter()
            .map(|i| -> Result<RgbImage> {
                match &trajectory.condition {
                    Some(stored) => {
                        Ok(decode_png(&stored[i], &format!("{}: condition[{i}]", record.clip_id))?.to_rgb8())
                    }
                    None => {
                        let context = format!("{}: covisible_mask[{i}]", record.clip_id);
                        Ok(condition_frame(
                            &targets[i],
                            &decode_png(&trajectory.covisible_mask[i], &context)?.to_luma8(),
                        ))
                    }
                }
            })
            .collect::<Result<_>>()?;
        let name = cog_nvs_render_name(position + 1);
        foundation::video::encode_video(&folder.join(&name), &conditioning, fps).map_err(in_clip)?;
        renders.push(serde_json::json!({
            "file": name,
            "trajectory_index": trajectory.index,
            "kind": trajectory.kind.as_str(),
            "pair_kind": record.pair_kind.as_str(),
            "source_camera": record.source_camera,
            "target_camera": record.target_camera,
            "covisible_fraction": trajectory.covisible_fraction,
        }));
    }
    let meta = serde_json::json!({
        "clip_id": record.clip_id,
        "source_path": record.source_path,
        "fps": fps,
        "frames": record.num_frames(),
        "target": COG_NVS_TARGET,
        "renders": renders,
    });
    let meta_path = folder.join("meta.json");
    std::fs::write(&meta_path, serde_json::to_vec_pretty(&meta).expect("json"))
        .map_err(|e| Error::io(&meta_path, e))?;
    Ok(folder)
}
