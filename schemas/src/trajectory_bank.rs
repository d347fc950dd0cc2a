//! The trajectory bank table: real camera motion harvested from the source
//! cameras of a corpus, one Parquet row per clip window, for the data-driven trajectory sampler.
//! Each row holds, per frame, the pose relative to the window's first camera with translation in
//! units of the window's pivot distance R (so paths from scenes of any scale compare), its
//! provenance and summary statistics. The file carries [`BANK_SCHEMA_NAME`] and
//! [`BANK_SCHEMA_VERSION`] in its key-value metadata; readers reject anything else, naming the
//! file and the key or column.

use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

use arrow_array::cast::AsArray;
use arrow_array::types::{Float64Type, UInt32Type};
use arrow_array::{ArrayRef, FixedSizeListArray, Float64Array, RecordBatch, StringArray, UInt32Array};
use arrow_schema::{DataType, Field, Schema};
use parquet::arrow::ArrowWriter;
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use parquet::file::metadata::KeyValue;
use parquet::file::properties::WriterProperties;

use crate::arrow_convert::{matrix_list, read_matrices};
use crate::error::{Error, Result};
use crate::pairs::{DOC_KEY, SCHEMA_NAME_KEY, SCHEMA_VERSION_KEY, per_frame_matrix};
use crate::shard::{check_columns, write_atomic};

/// Value of [`SCHEMA_NAME_KEY`] for trajectory banks.
pub const BANK_SCHEMA_NAME: &str = "cognvs.trajectory_bank";
/// The bank schema version this code writes and reads. Bump on any change a reader could notice.
pub const BANK_SCHEMA_VERSION: u32 = 1;

/// One clip window's camera motion.
#[derive(Debug, Clone, PartialEq)]
pub struct BankEntry {
    /// Unique id within the bank: `{dataset}/{video_id}/{window_start}`.
    pub entry_id: String,
    /// Dataset of the source video.
    pub dataset: String,
    /// Id of the source video within its dataset.
    pub video_id: String,
    /// Path of the input sequence the motion was read from.
    pub source_path: String,
    /// Index of the window's first frame in the source video.
    pub window_start: u32,
    /// Frame rate of the source video (0 if unknown).
    pub fps: f64,
    /// The window's pivot distance R in the reconstruction's depth units (the unit of the
    /// translations below).
    pub pivot_distance: f64,
    /// Per frame, `first_from_camera`: the camera's pose in the window's first camera's
    /// coordinates, row-major 4×4, OpenCV axes, translation divided by R. Frame 0 is identity.
    pub relative_pose: Vec<[f64; 16]>,
    /// Sum of the rotation angles between consecutive frames, in degrees.
    pub total_rotation_deg: f64,
    /// Length of the camera centre's path, in units of R.
    pub path_length: f64,
    /// Last camera centre in the first camera's coordinates, in units of R.
    pub net_translation: [f64; 3],
    /// The motion's dominant direction in the first camera's frame: `right`, `left`, `down`,
    /// `up`, `forward` or `backward` (largest component of the net translation), or for a
    /// camera that mostly turns in place `pan right`, `pan left`, `tilt down`, `tilt up`,
    /// `roll`.
    pub dominant_direction: String,
}

impl BankEntry {
    /// Number of frames of the window.
    pub fn num_frames(&self) -> usize {
        self.relative_pose.len()
    }
}

fn doc(field: Field, text: &str) -> Field {
    field.with_metadata(HashMap::from([(DOC_KEY.to_owned(), text.to_owned())]))
}

/// The Arrow schema of a trajectory bank, with its name and version in the metadata.
pub fn bank_schema() -> Schema {
    let vector3 = DataType::FixedSizeList(Arc::new(Field::new("item", DataType::Float64, false)), 3);
    Schema::new(vec![
        doc(
            Field::new("entry_id", DataType::Utf8, false),
            "Unique id of the entry: `{dataset}/{video_id}/{window_start}`; trajectories sampled from it record it.",
        ),
        doc(Field::new("dataset", DataType::Utf8, false), "Dataset of the source video."),
        doc(Field::new("video_id", DataType::Utf8, false), "Id of the source video within its dataset."),
        doc(Field::new("source_path", DataType::Utf8, false), "Path of the input sequence the motion was read from."),
        doc(
            Field::new("window_start", DataType::UInt32, false),
            "Index of the window's first frame in the source video (frames numbered from 0).",
        ),
        doc(
            Field::new("num_frames", DataType::UInt32, false),
            "Frames of the window; `relative_pose` has this many entries.",
        ),
        doc(Field::new("fps", DataType::Float64, false), "Frame rate of the source video (0 if unknown)."),
        doc(
            Field::new("pivot_distance", DataType::Float64, false),
            "The window's pivot distance R (depth at the first frame's optical centre × pivot_scale), in the reconstruction's depth units.",
        ),
        doc(
            Field::new("relative_pose", per_frame_matrix(16), false),
            "Per-frame `first_from_camera`: the pose relative to the window's first camera, row-major 4×4, OpenCV axes, translation in units of R; frame 0 is identity.",
        ),
        doc(
            Field::new("total_rotation_deg", DataType::Float64, false),
            "Sum of the rotation angles between consecutive frames, in degrees.",
        ),
        doc(Field::new("path_length", DataType::Float64, false), "Length of the camera centre's path, in units of R."),
        doc(
            Field::new("net_translation", vector3, false),
            "Last camera centre in the first camera's coordinates (x right, y down, z forward), in units of R.",
        ),
        doc(
            Field::new("dominant_direction", DataType::Utf8, false),
            "`right`, `left`, `down`, `up`, `forward`, `backward` (largest net translation component) or, for a camera turning in place, `pan right`, `pan left`, `tilt down`, `tilt up`, `roll`.",
        ),
    ])
    .with_metadata(HashMap::from([
        (SCHEMA_NAME_KEY.to_owned(), BANK_SCHEMA_NAME.to_owned()),
        (SCHEMA_VERSION_KEY.to_owned(), BANK_SCHEMA_VERSION.to_string()),
    ]))
}

fn batch(entries: &[BankEntry]) -> Result<RecordBatch> {
    let schema = Arc::new(bank_schema());
    let arrow_err = |source| Error::Arrow { path: "<in memory>".into(), source };
    let strings =
        |f: fn(&BankEntry) -> &str| Arc::new(StringArray::from_iter_values(entries.iter().map(f))) as ArrayRef;
    let f64s = |f: fn(&BankEntry) -> f64| Arc::new(Float64Array::from_iter_values(entries.iter().map(f))) as ArrayRef;
    let poses: Vec<&[[f64; 16]]> = entries.iter().map(|e| e.relative_pose.as_slice()).collect();
    let pose_type = schema.field_with_name("relative_pose").expect("defined above").data_type().clone();
    let net = Float64Array::from_iter_values(entries.iter().flat_map(|e| e.net_translation));
    let net =
        FixedSizeListArray::try_new(Arc::new(Field::new("item", DataType::Float64, false)), 3, Arc::new(net), None)
            .map_err(arrow_err)?;
    let columns: Vec<ArrayRef> = vec![
        strings(|e| &e.entry_id),
        strings(|e| &e.dataset),
        strings(|e| &e.video_id),
        strings(|e| &e.source_path),
        Arc::new(UInt32Array::from_iter_values(entries.iter().map(|e| e.window_start))),
        Arc::new(UInt32Array::from_iter_values(entries.iter().map(|e| e.relative_pose.len() as u32))),
        f64s(|e| e.fps),
        f64s(|e| e.pivot_distance),
        Arc::new(matrix_list(&pose_type, &poses).map_err(arrow_err)?),
        f64s(|e| e.total_rotation_deg),
        f64s(|e| e.path_length),
        Arc::new(net),
        strings(|e| &e.dominant_direction),
    ];
    RecordBatch::try_new(schema, columns).map_err(arrow_err)
}

/// Writes `entries` as a bank at `path` (temporary name + rename, so a bank is never half there).
pub fn write_bank(path: &Path, entries: &[BankEntry]) -> Result<()> {
    let batch = batch(entries)?;
    let properties = WriterProperties::builder()
        .set_key_value_metadata(Some(vec![
            KeyValue::new(SCHEMA_NAME_KEY.to_owned(), BANK_SCHEMA_NAME.to_owned()),
            KeyValue::new(SCHEMA_VERSION_KEY.to_owned(), BANK_SCHEMA_VERSION.to_string()),
        ]))
        .build();
    let parquet = |source| Error::Parquet { path: path.to_owned(), source };
    let mut bytes = Vec::new();
    let mut writer = ArrowWriter::try_new(&mut bytes, batch.schema(), Some(properties)).map_err(parquet)?;
    writer.write(&batch).map_err(parquet)?;
    writer.close().map_err(parquet)?;
    write_atomic(path, &bytes)
}

/// Reads a bank, checking its schema name, version and every column's type; errors name the
/// file and the key or column.
pub fn read_bank(path: &Path) -> Result<Vec<BankEntry>> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let parquet = |source| Error::Parquet { path: path.to_owned(), source };
    let builder = ParquetRecordBatchReaderBuilder::try_new(file).map_err(parquet)?;
    let key_values = builder.metadata().file_metadata().key_value_metadata().cloned().unwrap_or_default();
    let lookup = |key: &str| key_values.iter().find(|kv| kv.key == key).and_then(|kv| kv.value.clone());
    match lookup(SCHEMA_NAME_KEY) {
        Some(name) if name == BANK_SCHEMA_NAME => {}
        Some(name) => {
            return Err(Error::mismatch(
                path,
                SCHEMA_NAME_KEY,
                format!("expected `{BANK_SCHEMA_NAME}` (a trajectory bank), found `{name}`"),
            ));
        }
        None => return Err(Error::mismatch(path, SCHEMA_NAME_KEY, "missing: not a cognvs trajectory bank")),
    }
    let version = lookup(SCHEMA_VERSION_KEY).unwrap_or_default();
    if version != BANK_SCHEMA_VERSION.to_string() {
        return Err(Error::mismatch(
            path,
            SCHEMA_VERSION_KEY,
            format!("bank has version `{version}`, this reader reads version {BANK_SCHEMA_VERSION}"),
        ));
    }
    check_columns(path, builder.schema(), &bank_schema())?;
    let mut entries = Vec::new();
    for batch in builder.build().map_err(parquet)? {
        let batch = batch.map_err(|source| Error::Arrow { path: path.to_owned(), source })?;
        entries.extend(entries_of(&batch, path)?);
    }
    Ok(entries)
}

fn entries_of(batch: &RecordBatch, path: &Path) -> Result<Vec<BankEntry>> {
    // Types were checked against the schema before reading, so these casts hold.
    let column = |name: &str| batch.column_by_name(name).ok_or_else(|| Error::mismatch(path, name, "column missing"));
    let strings = |name: &str| -> Result<StringArray> {
        Ok(column(name)?.as_string_opt::<i32>().ok_or_else(|| Error::mismatch(path, name, "wrong type"))?.clone())
    };
    let u32s = |name: &str| -> Result<UInt32Array> {
        Ok(column(name)?
            .as_primitive_opt::<UInt32Type>()
            .ok_or_else(|| Error::mismatch(path, name, "wrong type"))?
            .clone())
    };
    let f64s = |name: &str| -> Result<Float64Array> {
        Ok(column(name)?
            .as_primitive_opt::<Float64Type>()
            .ok_or_else(|| Error::mismatch(path, name, "wrong type"))?
            .clone())
    };
    let (entry_id, dataset, video_id, source_path) =
        (strings("entry_id")?, strings("dataset")?, strings("video_id")?, strings("source_path")?);
    let (window_start, num_frames) = (u32s("window_start")?, u32s("num_frames")?);
    let (fps, pivot, rotation, length) =
        (f64s("fps")?, f64s("pivot_distance")?, f64s("total_rotation_deg")?, f64s("path_length")?);
    let direction = strings("dominant_direction")?;
    let poses = column("relative_pose")?
        .as_list_opt::<i32>()
        .ok_or_else(|| Error::mismatch(path, "relative_pose", "wrong type"))?
        .clone();
    let net = column("net_translation")?
        .as_fixed_size_list_opt()
        .ok_or_else(|| Error::mismatch(path, "net_translation", "wrong type"))?
        .clone();
    (0..batch.num_rows())
        .map(|row| {
            let relative_pose = read_matrices::<16>(&poses.value(row), path, "relative_pose")?;
            if relative_pose.len() != num_frames.value(row) as usize {
                return Err(Error::mismatch(
                    path,
                    "relative_pose",
                    format!(
                        "entry `{}` says {} frames but holds {} poses",
                        entry_id.value(row),
                        num_frames.value(row),
                        relative_pose.len()
                    ),
                ));
            }
            let net_values = net.value(row);
            let net_values = net_values
                .as_primitive_opt::<Float64Type>()
                .ok_or_else(|| Error::mismatch(path, "net_translation", "wrong type"))?;
            Ok(BankEntry {
                entry_id: entry_id.value(row).to_owned(),
                dataset: dataset.value(row).to_owned(),
                video_id: video_id.value(row).to_owned(),
                source_path: source_path.value(row).to_owned(),
                window_start: window_start.value(row),
                fps: fps.value(row),
                pivot_distance: pivot.value(row),
                relative_pose,
                total_rotation_deg: rotation.value(row),
                path_length: length.value(row),
                net_translation: [net_values.value(0), net_values.value(1), net_values.value(2)],
                dominant_direction: direction.value(row).to_owned(),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(i: u32) -> BankEntry {
        let mut poses = vec![[0.0; 16]; 3 + i as usize];
        for (k, pose) in poses.iter_mut().enumerate() {
            for d in 0..4 {
                pose[d * 5] = 1.0;
            }
            pose[3] = 0.01 * k as f64 * f64::from(i + 1);
        }
        BankEntry {
            entry_id: format!("synth/v{i}/{}", 7 * i),
            dataset: "synth".into(),
            video_id: format!("v{i}"),
            source_path: format!("/data/v{i}"),
            window_start: 7 * i,
            fps: 24.0,
            pivot_distance: 2.5 + f64::from(i),
            relative_pose: poses,
            total_rotation_deg: 0.0,
            path_length: 0.02 * f64::from(i + 1),
            net_translation: [0.02, -0.5, 1.25],
            dominant_direction: "right".into(),
        }
    }

    #[test]
    fn bank_round_trips_with_name_and_version() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bank.parquet");
        let entries: Vec<BankEntry> = (0..4).map(entry).collect();
        write_bank(&path, &entries).unwrap();
        assert_eq!(read_bank(&path).unwrap(), entries);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1, "no temporary file left");
        for field in bank_schema().fields() {
            assert!(field.metadata().contains_key(DOC_KEY), "field {} undocumented", field.name());
        }
    }

    /// The bank batch of `entries` written with schema name `name` and version `version`.
    fn write_with(path: &Path, entries: &[BankEntry], name: &str, version: &str) {
        let batch = batch(entries).unwrap();
        let properties = WriterProperties::builder()
            .set_key_value_metadata(Some(vec![
                KeyValue::new(SCHEMA_NAME_KEY.to_owned(), name.to_owned()),
                KeyValue::new(SCHEMA_VERSION_KEY.to_owned(), version.to_owned()),
            ]))
            .build();
        let file = std::fs::File::create(path).unwrap();
        let mut writer = ArrowWriter::try_new(file, batch.schema(), Some(properties)).unwrap();
        writer.write(&batch).unwrap();
        writer.close().unwrap();
    }

    #[test]
    fn other_tables_and_versions_are_rejected_naming_file_and_key() {
        let dir = tempfile::tempdir().unwrap();
        let status = dir.path().join("status.parquet");
        crate::status::write_status_table(&status, &[]).unwrap();
        let error = read_bank(&status).unwrap_err().to_string();
        assert!(error.contains("status.parquet") && error.contains("`cognvs.schema`: missing"), "{error}");
        let shard = dir.path().join("shard.parquet");
        write_with(&shard, &[entry(0)], crate::SCHEMA_NAME, "2");
        let error = read_bank(&shard).unwrap_err().to_string();
        assert!(error.contains("shard.parquet") && error.contains("found `cognvs.pairs`"), "{error}");
        let future = dir.path().join("future.parquet");
        write_with(&future, &[entry(0)], BANK_SCHEMA_NAME, "99");
        let error = read_bank(&future).unwrap_err().to_string();
        assert!(
            error.contains("future.parquet") && error.contains("cognvs.schema_version") && error.contains("`99`"),
            "{error}"
        );
    }
}
