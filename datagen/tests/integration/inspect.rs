//! `inspect`: statistics of a shard and the per-pair export (folders, masks, meta, contact sheet).

use datagen::inspect::shards::{export, report};
use schemas::{ClipRecord, ShardWriter, ShardWriterOptions};

fn shard_with_one_clip(dir: &std::path::Path) -> (std::path::PathBuf, ClipRecord) {
    let record = crate::validate::record("synth/scene/0");
    let path = dir.join("scene.parquet");
    let mut writer = ShardWriter::create(&path, ShardWriterOptions::default()).unwrap();
    writer.write(&record).unwrap();
    writer.finish().unwrap();
    (path, record)
}

#[test]
fn report_lists_clips_and_pairs() {
    let dir = tempfile::tempdir().unwrap();
    let (path, _) = shard_with_one_clip(dir.path());
    let text = report(&path).unwrap();
    assert!(text.contains("1 clips, 1 pairs"), "{text}");
    assert!(text.contains("synth/scene/0: 2 frames 6x4"), "{text}");
    assert!(text.contains("co-visible 0.0 %"), "{text}");
}

#[test]
fn export_writes_every_frame_mask_meta_and_sheet() {
    let dir = tempfile::tempdir().unwrap();
    let (path, record) = shard_with_one_clip(dir.path());
    let out = dir.path().join("export");
    let folders = export(&path, &out, None).unwrap();
    assert_eq!(folders, vec![out.join("synth__scene__0__t0")]);
    let pair = &folders[0];
    for sub in ["target", "cond", "mask"] {
        for i in 0..2 {
            assert!(pair.join(format!("{sub}/{i:05}.png")).is_file(), "{sub}/{i:05}.png");
        }
    }
    let mask = image::open(pair.join("mask/00001.png")).unwrap().to_luma8();
    assert_eq!(mask.dimensions(), (record.width, record.height));
    let meta: serde_json::Value = serde_json::from_slice(&std::fs::read(pair.join("meta.json")).unwrap()).unwrap();
    assert_eq!(meta["clip_id"], "synth/scene/0");
    assert_eq!(meta["trajectory"]["kind"], "sampled");
    assert!(image::open(pair.join("contact_sheet.png")).unwrap().width() > 3 * record.width);
}

#[test]
fn clips_decode_back_to_their_sequence_and_export_renders_with_stacking() {
    let dir = tempfile::tempdir().unwrap();
    let seq_dir = crate::sequence::synth_sequence(dir.path(), 6);
    let sequence = datagen::io::sequence::read_sequence(&seq_dir).unwrap();
    let request = datagen::pairs::generator::TrajectoryRequest { sampled: 1, explicit: Vec::new() };
    let config = datagen::pairs::generator::PairsConfig::default();
    let records = datagen::pairs::generator::generate_clips(&sequence, "synth", &config, &request, 3).unwrap();
    // Lossless round trip: PNG frames and masks, EXR depth, cameras.
    let decoded = datagen::io::sequence::Sequence::from_clip(&records[0]).unwrap();
    assert_eq!(decoded.frames, sequence.frames);
    assert_eq!(decoded.dynamic_masks, sequence.dynamic_masks);
    for (a, b) in decoded.depth.iter().zip(&sequence.depth) {
        assert_eq!(a.values, b.values);
    }
    for (a, b) in decoded.cameras.iter().zip(&sequence.cameras) {
        assert!(
            a.world_from_camera.abs_diff_eq(b.world_from_camera, 1e-12)
                && a.intrinsics.abs_diff_eq(b.intrinsics, 1e-12)
        );
    }
    let (shard, _) = datagen::pairs::generator::write_shard(
        &dir.path().join("pairs"),
        "synth",
        &records,
        schemas::InputDigest { source_path: "synth".into(), content_hash: String::new() },
    )
    .unwrap();
    let options = datagen::inspect::shards::ExportRender { stacking: Some(Default::default()), ..Default::default() };
    let folders = export(&shard, &dir.path().join("export"), Some(&options)).unwrap();
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(folders[0].join("meta.json")).unwrap()).unwrap();
    assert_eq!(meta["contact_sheet_columns"].as_array().unwrap().len(), 4);
    let sheet = image::open(folders[0].join("contact_sheet.png")).unwrap();
    assert!(sheet.width() >= 4 * sequence.size().0);
}
