//! `datagen validate`: checks every shard of a corpus folder against its stats marker and the
//! schema, and (deep mode) decodes every image and depth map, reporting each problem with the
//! shard, clip and field it concerns.

use std::path::{Path, PathBuf};

use schemas::ShardReader;

use crate::error::{Error, Result};

/// One problem found.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Problem {
    /// The shard (or other file) concerned.
    pub path: PathBuf,
    /// What is wrong, naming the clip and field where there is one.
    pub message: String,
}

/// What validation looked at and found.
#[derive(Debug, Clone, Default)]
pub struct ValidationReport {
    /// Shards checked.
    pub shards: u64,
    /// Clips read.
    pub clips: u64,
    /// Problems, in shard order.
    pub problems: Vec<Problem>,
}

/// Validates every `shard-*.parquet` (or any `*.parquet` outside `status/`) under `dir`, or the
/// single shard `dir` names. `deep` also decodes every PNG and EXR and checks its size.
///
/// A folder is also checked as a corpus: holding no shard at all is a problem (an unbuilt or
/// wrong folder, not an empty success), and so is every stats marker whose shard is gone and
/// every input whose latest status row says ok in a shard that is not there (finished).
pub fn validate(dir: &Path, deep: bool) -> Result<ValidationReport> {
    let shards = shard_files(dir)?;
    let mut report = ValidationReport::default();
    if dir.is_dir() {
        check_corpus_folder(dir, shards.is_empty(), &mut report.problems)?;
    }
    for shard in shards {
        report.shards += 1;
        let mut problem = |message: String| report.problems.push(Problem { path: shard.clone(), message });
        let stats = match schemas::read_stats(&shard) {
            Ok(stats) => Some(stats),
            Err(error) => {
                problem(format!("no readable stats marker ({error}): unfinished shard"));
                None
            }
        };
        let reader = match ShardReader::open(&shard) {
            Ok(reader) => reader,
            Err(error) => {
                problem(error.to_string());
                continue;
            }
        };
        let (mut clips, mut pairs, mut frames) = (0u64, 0u64, 0u64);
        for record in reader {
            let record = match record {
                Ok(record) => record,
                Err(error) => {
                    problem(error.to_string());
                    break;
                }
            };
            clips += 1;
            pairs += record.trajectories.len() as u64;
            frames += record.num_frames() as u64;
            if deep {
                for message in check_clip_content(&record) {
                    problem(format!("clip `{}`: {message}", record.clip_id));
                }
            }
        }
        report.clips += clips;
        if let Some(stats) = stats {
            let size = std::fs::metadata(&shard).map(|m| m.len()).unwrap_or(0);
            let checks = [
                ("clips", stats.clips, clips),
                ("pairs", stats.pairs, pairs),
                ("frames", stats.frames, frames),
                ("bytes", stats.bytes, size),
            ];
            for (field, expected, found) in checks {
                if expected != found {
                    problem(format!("stats field `{field}` says {expected}, shard has {found}"));
                }
            }
        }
    }
    Ok(report)
}

/// The folder-level problems: no shards, orphan stats markers, ok status rows without a shard.
fn check_corpus_folder(dir: &Path, no_shards: bool, problems: &mut Vec<Problem>) -> Result<()> {
    if no_shards {
        problems.push(Problem {
            path: dir.to_owned(),
            message: "no shards (*.parquet) in this folder: nothing was built here, or this is not a corpus".into(),
        });
    }
    let markers = crate::corpus::crawl::sorted_dir(dir)?.into_iter().filter(|p| {
        let name = p.file_name().unwrap_or_default().to_string_lossy();
        name.ends_with(schemas::shard::STATS_SUFFIX) && !name.contains(schemas::shard::TEMP_MARKER)
    });
    for marker in markers {
        let name = marker.file_name().unwrap_or_default().to_string_lossy().into_owned();
        let shard = name.trim_end_matches(schemas::shard::STATS_SUFFIX);
        if !dir.join(shard).is_file() {
            problems.push(Problem {
                path: marker,
                message: format!(
                    "stats marker without its shard `{shard}` (lost or deleted); `datagen build` on this folder \
                     removes the marker and rebuilds its inputs"
                ),
            });
        }
    }
    if dir.join("status").is_dir() {
        match crate::corpus::build::read_corpus_status(dir) {
            Ok(latest) => {
                for record in latest.values().filter(|r| r.status == schemas::InputStatus::Ok) {
                    let shard = dir.join(&record.shard);
                    if !schemas::is_finished(&shard) {
                        problems.push(Problem {
                            path: shard,
                            message: format!(
                                "status says input `{}` is ok in this shard, which is missing or has no stats \
                                 marker; `datagen build` on this folder rebuilds it",
                                record.input_key
                            ),
                        });
                    }
                }
            }
            Err(error) => problems.push(Problem { path: dir.join("status"), message: error.to_string() }),
        }
    }
    Ok(())
}

fn shard_files(dir: &Path) -> Result<Vec<PathBuf>> {
    if dir.is_file() {
        return Ok(vec![dir.to_owned()]);
    }
    let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    let mut shards: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let name = p.file_name().unwrap_or_default().to_string_lossy();
            name.ends_with(".parquet") && !name.starts_with('.') && !name.contains(schemas::shard::TEMP_MARKER)
        })
        .collect();
    shards.sort();
    Ok(shards)
}

/// Decodes every encoded raster of a clip and checks its size and kind.
fn check_clip_content(record: &schemas::ClipRecord) -> Vec<String> {
    let (width, height) = (record.width, record.height);
    let mut problems = Vec::new();
    let mut check_png = |field: String, bytes: &[u8], grey: bool| match image::load_from_memory_with_format(
        bytes,
        image::ImageFormat::Png,
    ) {
        Ok(image) if image.width() != width || image.height() != height => {
            problems.push(format!("{field}: {}x{} image in a {width}x{height} clip", image.width(), image.height()))
        }
        Ok(image) if grey && image.color() != image::ColorType::L8 => {
            problems.push(format!("{field}: expected 8-bit greyscale, found {:?}", image.color()))
        }
        Ok(_) => {}
        Err(error) => problems.push(format!("{field}: undecodable PNG: {error}")),
    };
    for (i, frame) in record.frames.iter().enumerate() {
        check_png(format!("frames[{i}]"), frame, false);
    }
    for (i, mask) in record.dynamic_mask.iter().flatten().enumerate() {
        check_png(format!("dynamic_mask[{i}]"), mask, true);
    }
    for trajectory in &record.trajectories {
        for (i, mask) in trajectory.covisible_mask.iter().enumerate() {
            check_png(format!("trajectories[{}].covisible_mask[{i}]", trajectory.index), mask, true);
        }
        for (i, frame) in trajectory.condition.iter().flatten().enumerate() {
            check_png(format!("trajectories[{}].condition[{i}]", trajectory.index), frame, false);
        }
    }
    for (i, depth) in record.depth.iter().enumerate() {
        // The header's size is compared with the clip's before any pixel is decoded.
        let context = format!("depth[{i}]");
        if let Err(error) =
            crate::io::depth_exr::decode_depth_exr_of_size(depth, &context, width as usize, height as usize)
        {
            problems.push(error.to_string());
        }
    }
    problems
}
