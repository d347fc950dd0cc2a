//! End-to-end tests that cross crates: `datagen` output → `schemas` shards → readers outside this
//! code (pyarrow, DuckDB and Hugging Face `datasets` from the project venv).

use std::path::{Path, PathBuf};
use std::process::Command;

/// The project venv's Python (created by `scripts/setup.sh`).
fn venv_python() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../.venv/bin/python")
}

fn png_bytes<P: image::PixelWithColorType>(image: &image::ImageBuffer<P, Vec<P::Subpixel>>) -> Vec<u8>
where
    [P::Subpixel]: image::EncodableLayout,
{
    let mut bytes = std::io::Cursor::new(Vec::new());
    image.write_to(&mut bytes, image::ImageFormat::Png).unwrap();
    bytes.into_inner()
}

mod shards_in_python {
    //! A shard built from a synthetic scene opens unchanged in pyarrow, DuckDB and HF `datasets`.
    use super::*;
    use datagen::io::depth_exr::encode_depth_exr;
    use datagen::synth::{SynthConfig, SynthScene};
    use foundation::depth::DepthMap;
    use schemas::{ClipRecord, ShardWriter, ShardWriterOptions, TrajectoryKind, TrajectoryRecord};

    fn synth_record(frames: u32) -> ClipRecord {
        let config = SynthConfig { width: 48, height: 32, frames, ..SynthConfig::default() };
        let scene = SynthScene::new(&config).unwrap();
        let rendered: Vec<_> = (0..frames).map(|f| scene.render_frame(f)).collect();
        let row_major = |m: glam::DMat4| m.transpose().to_cols_array();
        let k = config.intrinsics().transpose().to_cols_array();
        ClipRecord {
            clip_id: "synth/scene0/0".into(),
            source_id: "scene0".into(),
            dataset: "synth".into(),
            source_path: "generated".into(),
            clip_start: 0,
            fps: config.fps,
            width: config.width,
            height: config.height,
            seed: config.seed,
            tool_version: "e2e test".into(),
            frames: rendered.iter().map(|r| png_bytes(&r.rgb)).collect(),
            depth: rendered
                .iter()
                .map(|r| encode_depth_exr(&DepthMap { width: 48, height: 32, values: r.depth.clone() }).unwrap())
                .collect(),
            intrinsics: vec![k; frames as usize],
            world_from_camera: (0..frames).map(|f| row_major(scene.world_from_camera(f))).collect(),
            dynamic_mask: Some(rendered.iter().map(|r| png_bytes(&r.mask_ids)).collect()),
            trajectories: vec![TrajectoryRecord {
                index: 0,
                kind: TrajectoryKind::Explicit,
                pivot_distance: 5.0,
                azimuth_deg: vec![],
                elevation_deg: vec![],
                radius_frac: vec![],
                rejected_samples: 0,
                world_from_camera: (0..frames).map(|f| row_major(scene.world_from_camera(f))).collect(),
                covisible_mask: rendered.iter().map(|r| png_bytes(&r.mask_ids)).collect(),
                condition: None,
                covisible_fraction: 1.0,
                bank_entry: None,
                mask_rule: schemas::MaskRule::Exact,
            }],
            pair_kind: schemas::PairKind::Monocular,
            source_camera: None,
            target_camera: None,
        }
    }

    #[test]
    fn pyarrow_duckdb_and_hf_datasets_read_a_shard() {
        let dir = tempfile::tempdir().unwrap();
        let shard = dir.path().join("shard-000000.parquet");
        let record = synth_record(3);
        let mut writer = ShardWriter::create(&shard, ShardWriterOptions::default()).unwrap();
        writer.write(&record).unwrap();
        writer.finish().unwrap();

        let script = r#"
import io, json, sys
import numpy as np
import pyarrow.parquet as pq
import duckdb
import datasets
path = sys.argv[1]
table = pq.read_table(path)
meta = pq.read_metadata(path).metadata
row = table.to_pylist()[0]
traj = row["trajectories"][0]
k = np.array(row["intrinsics"][0]).reshape(3, 3)
pose = np.array(row["world_from_camera"][1]).reshape(4, 4)
out = {
    "version": meta[b"cognvs.schema_version"].decode(),
    "rows": table.num_rows,
    "num_frames": row["num_frames"],
    "png": all(f[:8] == b"\x89PNG\r\n\x1a\n" for f in row["frames"]),
    "exr": all(d[:4] == b"\x76\x2f\x31\x01" for d in row["depth"]),
    "cx": float(k[0, 2]),
    "pose_det": float(np.linalg.det(pose[:3, :3])),
    "traj_kind": traj["kind"],
    "traj_frames": len(traj["covisible_mask"]),
    "condition_is_null": traj["condition"] is None,
    "doc": table.schema.field("frames").metadata[b"doc"].decode()[:10],
    "duckdb_frames": duckdb.sql(f"select sum(len(frames)) from read_parquet('{path}')").fetchall()[0][0],
    "duckdb_pairs": duckdb.sql(f"select count(*) from (select unnest(trajectories) from read_parquet('{path}'))").fetchall()[0][0],
}
hf = datasets.Dataset.from_parquet(path, cache_dir=sys.argv[2])
hf_row = hf[0]
out["hf_rows"] = hf.num_rows
out["hf_pairs"] = len(hf_row["trajectories"])
out["hf_frames_equal"] = hf_row["frames"] == row["frames"]
print(json.dumps(out))
"#;
        let output = Command::new(venv_python())
            .arg("-c")
            .arg(script)
            .arg(&shard)
            .arg(dir.path().join("hf-cache"))
            .env("HF_DATASETS_OFFLINE", "1")
            .output()
            .expect("run the venv python");
        assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
        let read: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
        assert_eq!(read["version"], schemas::SCHEMA_VERSION.to_string());
        assert_eq!(read["rows"], 1);
        assert_eq!(read["num_frames"], 3);
        assert_eq!(read["png"], true);
        assert_eq!(read["exr"], true);
        assert_eq!(read["cx"], 48.0 / 2.0 - 0.5);
        assert!((read["pose_det"].as_f64().unwrap() - 1.0).abs() < 1e-9);
        assert_eq!(read["traj_kind"], "explicit");
        assert_eq!(read["traj_frames"], 3);
        assert_eq!(read["condition_is_null"], true);
        assert_eq!(read["doc"], "Per-frame ");
        assert_eq!(read["duckdb_frames"], 3);
        assert_eq!(read["duckdb_pairs"], 1);
        assert_eq!(read["hf_rows"], 1);
        assert_eq!(read["hf_pairs"], 1);
        assert_eq!(read["hf_frames_equal"], true);
    }

    #[test]
    fn depth_survives_the_shard_bit_exactly() {
        let dir = tempfile::tempdir().unwrap();
        let shard = dir.path().join("s.parquet");
        let record = synth_record(2);
        let mut writer = ShardWriter::create(&shard, ShardWriterOptions::default()).unwrap();
        writer.write(&record).unwrap();
        writer.finish().unwrap();
        let read = schemas::read_shard(&shard).unwrap().remove(0);
        let depth = datagen::io::depth_exr::decode_depth_exr(&read.depth[1], "shard depth[1]").unwrap();
        let scene =
            SynthScene::new(&SynthConfig { width: 48, height: 32, frames: 2, ..SynthConfig::default() }).unwrap();
        assert_eq!(depth.values, scene.render_frame(1).depth);
    }
}
