//! Integration tests of the shard contract: round trips, the generated reference, atomic writing
//! and version checks.

use schemas::{ClipRecord, PairKind, ShardWriter, ShardWriterOptions, TrajectoryKind, TrajectoryRecord};

/// A small record with distinct, non-trivial values in every field.
fn sample_record(clip_start: u32, frames: usize, trajectories: usize) -> ClipRecord {
    let bytes = |tag: u8, i: usize| (0..(17 + i * 5)).map(|k| tag ^ (k as u8).wrapping_mul(31)).collect::<Vec<u8>>();
    let matrix16 = |i: usize, s: f64| std::array::from_fn(|k| s * (i as f64 + 1.0) + k as f64 * 0.125);
    ClipRecord {
        clip_id: format!("synth/scene/{clip_start}"),
        source_id: "scene".into(),
        dataset: "synth".into(),
        source_path: "/data/scene".into(),
        clip_start,
        fps: 24.0,
        width: 64,
        height: 48,
        seed: 0xDEAD_BEEF_0000_0001,
        tool_version: "datagen test".into(),
        frames: (0..frames).map(|i| bytes(1, i)).collect(),
        depth: (0..frames).map(|i| bytes(2, i)).collect(),
        intrinsics: (0..frames).map(|i| std::array::from_fn(|k| (i * 9 + k) as f64 * 0.5)).collect(),
        world_from_camera: (0..frames).map(|i| matrix16(i, 1.0)).collect(),
        dynamic_mask: clip_start.is_multiple_of(2).then(|| (0..frames).map(|i| bytes(3, i)).collect()),
        trajectories: (0..trajectories)
            .map(|t| TrajectoryRecord {
                index: t as u32,
                kind: match t {
                    2 => TrajectoryKind::Bank,
                    _ if t % 2 == 0 => TrajectoryKind::Sampled,
                    _ => TrajectoryKind::Explicit,
                },
                pivot_distance: 3.5 + t as f64,
                azimuth_deg: vec![1.0, -2.0, 3.0, t as f64],
                elevation_deg: vec![0.5; t],
                radius_frac: vec![],
                rejected_samples: t as u32 * 2,
                world_from_camera: (0..frames).map(|i| matrix16(i, -2.0 - t as f64)).collect(),
                covisible_mask: (0..frames).map(|i| bytes(4 + t as u8, i)).collect(),
                condition: (t == 1).then(|| (0..frames).map(|i| bytes(9, i)).collect()),
                covisible_fraction: 0.25 * t as f64,
                bank_entry: (t == 2).then(|| schemas::BankProvenance {
                    entry_id: format!("sav/v{clip_start}/48"),
                    entry_row: 3 + clip_start,
                    bank_digest: "ab".repeat(32),
                    mirrored: clip_start % 2 == 1,
                    roll_deg: -12.5,
                }),
                mask_rule: [schemas::MaskRule::Exact, schemas::MaskRule::Coverage, schemas::MaskRule::Dataset][t % 3],
            })
            .collect(),
        pair_kind: if clip_start % 3 == 1 { PairKind::Multiview } else { PairKind::Monocular },
        source_camera: (!clip_start.is_multiple_of(3)).then(|| format!("cam{clip_start}")),
        target_camera: (clip_start % 3 == 1).then(|| "cam_target".to_owned()),
    }
}

mod round_trip {
    //! Every field of every record survives write → read unchanged.
    use super::*;

    #[test]
    fn records_round_trip_through_parquet() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("shard-00000.parquet");
        let records: Vec<_> = (0..5).map(|i| sample_record(i * 7, 3 + i as usize, i as usize)).collect();
        let mut writer = ShardWriter::create(&path, ShardWriterOptions { row_group_bytes: 300 }).unwrap();
        for record in &records {
            writer.write(record).unwrap();
        }
        let stats = writer.finish().unwrap();
        assert_eq!(stats.clips, 5);
        assert_eq!(stats.pairs, (0..5).sum::<u64>());
        assert!(stats.row_groups > 1, "row groups are cut by bytes: {}", stats.row_groups);
        let read = schemas::read_shard(&path).unwrap();
        assert_eq!(read, records);
        assert_eq!(schemas::read_stats(&path).unwrap(), stats);
        // Random access reads only the row group holding the clip.
        assert_eq!(schemas::clip_count(&path).unwrap(), 5);
        for (row, record) in records.iter().enumerate() {
            assert_eq!(&schemas::read_clip(&path, row).unwrap(), record, "row {row}");
        }
        let err = schemas::read_clip(&path, 5).unwrap_err().to_string();
        assert!(err.contains("row 5") && err.contains("5 clips"), "{err}");
    }

    #[test]
    fn batch_conversion_round_trips() {
        let records = vec![sample_record(0, 2, 3), sample_record(1, 4, 0)];
        let batch = schemas::records_to_batch(&records).unwrap();
        assert_eq!(batch.num_rows(), 2);
        assert_eq!(schemas::batch_to_records(&batch, "mem".as_ref()).unwrap(), records);
    }

    #[test]
    fn inconsistent_record_is_rejected_naming_the_field() {
        let mut record = sample_record(0, 3, 2);
        record.trajectories[1].covisible_mask.pop();
        let error = schemas::records_to_batch(&[record]).unwrap_err().to_string();
        assert!(error.contains("trajectories[1].covisible_mask"), "{error}");
    }
}

mod reference_doc {
    //! `schemas/SCHEMA.md` is exactly what the code generates.

    #[test]
    fn schema_reference_is_in_sync() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("SCHEMA.md");
        let generated = schemas::reference_markdown();
        if std::env::var_os("UPDATE_SCHEMA_DOC").is_some() {
            std::fs::write(&path, &generated).unwrap();
        }
        let on_disk = std::fs::read_to_string(&path).unwrap_or_default();
        assert!(
            on_disk == generated,
            "{} is out of date: regenerate with UPDATE_SCHEMA_DOC=1 cargo test -p schemas",
            path.display()
        );
        for field in schemas::pair_schema().fields() {
            assert!(field.metadata().contains_key(schemas::DOC_KEY), "field {} undocumented", field.name());
        }
    }
}

mod atomic {
    //! Unfinished shards are never visible under their final name.
    use super::*;

    #[test]
    fn dropped_writer_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("shard.parquet");
        let mut writer = ShardWriter::create(&path, ShardWriterOptions::default()).unwrap();
        writer.write(&sample_record(0, 2, 1)).unwrap();
        drop(writer);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        assert!(!schemas::is_finished(&path));
    }

    #[test]
    fn finished_shard_has_stats_marker() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("shard.parquet");
        let mut writer = ShardWriter::create(&path, ShardWriterOptions::default()).unwrap();
        writer.write(&sample_record(0, 2, 1)).unwrap();
        writer.finish().unwrap();
        assert!(schemas::is_finished(&path));
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(names.len(), 2, "{names:?}");
    }
}

mod versions {
    //! Readers reject files that are not shards of this version, naming the file and key.
    use super::*;
    use std::sync::Arc;

    #[test]
    fn foreign_parquet_is_rejected() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("other.parquet");
        let batch = arrow_array::RecordBatch::try_from_iter([(
            "x",
            Arc::new(arrow_array::Int32Array::from(vec![1, 2])) as arrow_array::ArrayRef,
        )])
        .unwrap();
        let mut writer =
            parquet::arrow::ArrowWriter::try_new(std::fs::File::create(&path).unwrap(), batch.schema(), None).unwrap();
        writer.write(&batch).unwrap();
        writer.close().unwrap();
        let error = schemas::read_shard(&path).err().unwrap().to_string();
        assert!(error.contains("other.parquet") && error.contains(schemas::SCHEMA_NAME_KEY), "{error}");
    }

    #[test]
    fn truncated_shard_is_an_error_not_a_panic() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("shard.parquet");
        let mut writer = ShardWriter::create(&path, ShardWriterOptions::default()).unwrap();
        writer.write(&sample_record(0, 2, 1)).unwrap();
        writer.finish().unwrap();
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
        let error = schemas::read_shard(&path).err().unwrap().to_string();
        assert!(error.contains("shard.parquet"), "{error}");
    }
}

mod status_table {
    //! The per-input status table round-trips and is written atomically.
    use schemas::{InputStatus, StatusRecord};

    #[test]
    fn status_table_round_trips() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("status-w000.parquet");
        let records: Vec<StatusRecord> = [InputStatus::Ok, InputStatus::Skipped, InputStatus::Failed]
            .into_iter()
            .enumerate()
            .map(|(i, status)| StatusRecord {
                input_key: format!("sav/sav_{i:06}"),
                status,
                reason: if status == InputStatus::Ok { String::new() } else { format!("reason {i}") },
                clips: i as u32,
                pairs: 2 * i as u32,
                shard: if status == InputStatus::Ok { "shard-w000-000000.parquet".into() } else { String::new() },
                content_hash: format!("{i:064x}"),
                seconds: 0.5 * i as f64,
                worker_index: 1,
                worker_count: 2,
            })
            .collect();
        schemas::write_status_table(&path, &records).unwrap();
        assert_eq!(schemas::read_status_table(&path).unwrap(), records);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1, "no temporary file left");
    }
}
