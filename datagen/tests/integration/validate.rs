//! `validate` finds stats mismatches, undecodable rasters and unreadable shards, and passes good ones.

use std::path::Path;

use datagen::corpus::validate::validate;
use datagen::io::depth_exr::encode_depth_exr;
use foundation::depth::DepthMap;
use schemas::{ClipRecord, ShardWriter, ShardWriterOptions, TrajectoryKind, TrajectoryRecord};

fn png<P: image::PixelWithColorType>(image: image::ImageBuffer<P, Vec<P::Subpixel>>) -> Vec<u8>
where
    [P::Subpixel]: image::EncodableLayout,
{
    let mut bytes = std::io::Cursor::new(Vec::new());
    image.write_to(&mut bytes, image::ImageFormat::Png).unwrap();
    bytes.into_inner()
}

pub fn record(id: &str) -> ClipRecord {
    let (w, h) = (6, 4);
    ClipRecord {
        clip_id: id.into(),
        source_id: id.into(),
        dataset: "test".into(),
        source_path: id.into(),
        clip_start: 0,
        fps: 24.0,
        width: w,
        height: h,
        seed: 1,
        tool_version: "test".into(),
        frames: vec![png(image::RgbImage::new(w, h)); 2],
        depth: vec![encode_depth_exr(&DepthMap { width: 6, height: 4, values: vec![2.0; 24] }).unwrap(); 2],
        intrinsics: vec![[1.0; 9]; 2],
        world_from_camera: vec![[0.0; 16]; 2],
        dynamic_mask: Some(vec![png(image::GrayImage::new(w, h)); 2]),
        trajectories: vec![TrajectoryRecord {
            index: 0,
            kind: TrajectoryKind::Sampled,
            pivot_distance: 1.0,
            azimuth_deg: vec![0.0; 4],
            elevation_deg: vec![0.0; 4],
            radius_frac: vec![0.0; 4],
            rejected_samples: 0,
            world_from_camera: vec![[0.0; 16]; 2],
            covisible_mask: vec![png(image::GrayImage::new(w, h)); 2],
            condition: None,
            covisible_fraction: 0.0,
            bank_entry: None,
            mask_rule: schemas::MaskRule::Exact,
        }],
        pair_kind: schemas::PairKind::Monocular,
        source_camera: None,
        target_camera: None,
    }
}

fn write(path: &Path, records: &[ClipRecord]) {
    let mut writer = ShardWriter::create(path, ShardWriterOptions::default()).unwrap();
    for r in records {
        writer.write(r).unwrap();
    }
    writer.finish().unwrap();
}

#[test]
fn good_corpus_has_no_problems_and_each_defect_is_named() {
    let dir = tempfile::tempdir().unwrap();
    write(&dir.path().join("shard-a.parquet"), &[record("a/0"), record("a/1")]);
    let report = validate(dir.path(), true).unwrap();
    assert_eq!((report.shards, report.clips), (1, 2));
    assert!(report.problems.is_empty(), "{:?}", report.problems);

    // A raster of the wrong size, found only by the deep check.
    let mut bad = record("b/0");
    bad.trajectories[0].covisible_mask[1] = png(image::GrayImage::new(3, 3));
    write(&dir.path().join("shard-b.parquet"), &[bad]);
    assert!(validate(dir.path(), false).unwrap().problems.is_empty());
    let deep = validate(dir.path(), true).unwrap();
    assert_eq!(deep.problems.len(), 1, "{:?}", deep.problems);
    assert!(
        deep.problems[0].message.contains("clip `b/0`")
            && deep.problems[0].message.contains("trajectories[0].covisible_mask[1]")
    );

    // Stats that disagree with the shard, and a truncated shard.
    let stats = schemas::stats_path(&dir.path().join("shard-a.parquet"));
    let text = std::fs::read_to_string(&stats).unwrap().replace("\"clips\": 2", "\"clips\": 3");
    std::fs::write(&stats, text).unwrap();
    let bytes = std::fs::read(dir.path().join("shard-b.parquet")).unwrap();
    std::fs::write(dir.path().join("shard-b.parquet"), &bytes[..bytes.len() / 3]).unwrap();
    let report = validate(dir.path(), false).unwrap();
    let messages: Vec<String> =
        report.problems.iter().map(|p| format!("{}: {}", p.path.display(), p.message)).collect();
    assert!(
        messages.iter().any(|m| m.contains("shard-a.parquet") && m.contains("`clips` says 3, shard has 2")),
        "{messages:?}"
    );
    assert!(messages.iter().any(|m| m.contains("shard-b.parquet")), "{messages:?}");
}
