//! The per-input status table of a corpus build: one row per input and attempt, with
//! `ok`, `skipped` or `failed` and the reason, as a Parquet file that pyarrow and DuckDB read
//! directly. Written atomically (temporary name + rename), like shards.

use std::collections::HashMap;
use std::fs::File;
use std::path::Path;
use std::sync::Arc;

use arrow_array::cast::AsArray;
use arrow_array::types::{Float64Type, UInt32Type};
use arrow_array::{Array, ArrayRef, Float64Array, RecordBatch, StringArray, UInt32Array};
use arrow_schema::{DataType, Field, Schema};
use parquet::arrow::ArrowWriter;
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;

use crate::error::{Error, Result};
use crate::pairs::{DOC_KEY, SCHEMA_NAME_KEY, SCHEMA_VERSION_KEY};
use crate::shard::TEMP_MARKER;

/// Value of the schema-name key for status tables.
pub const STATUS_SCHEMA_NAME: &str = "cognvs.status";
/// Version of the status table schema.
pub const STATUS_SCHEMA_VERSION: u32 = 1;

/// Outcome of one input.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum InputStatus {
    /// Pairs were generated and are in a finished shard.
    Ok,
    /// Deliberately not processed (no reconstruction, too short, ...).
    Skipped,
    /// Processing failed; the reason says why.
    Failed,
}

impl InputStatus {
    /// The string stored in the `status` column.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Ok => "ok",
            Self::Skipped => "skipped",
            Self::Failed => "failed",
        }
    }

    fn parse(value: &str) -> Option<Self> {
        [Self::Ok, Self::Skipped, Self::Failed].into_iter().find(|s| s.as_str() == value)
    }
}

/// One row of the status table.
#[derive(Debug, Clone, PartialEq)]
pub struct StatusRecord {
    /// Stable input key, `{dataset}/{video_id}`.
    pub input_key: String,
    /// Outcome.
    pub status: InputStatus,
    /// Why it was skipped or failed (empty when ok).
    pub reason: String,
    /// Clips written.
    pub clips: u32,
    /// Training pairs written.
    pub pairs: u32,
    /// File name of the shard holding its pairs (empty unless ok).
    pub shard: String,
    /// BLAKE3 of the input's files (empty if they could not be read).
    pub content_hash: String,
    /// Processing wall time in seconds.
    pub seconds: f64,
    /// Index of the worker that processed it.
    pub worker_index: u32,
    /// Number of workers of the run.
    pub worker_count: u32,
}

fn doc(field: Field, text: &str) -> Field {
    field.with_metadata(HashMap::from([(DOC_KEY.to_owned(), text.to_owned())]))
}

/// The Arrow schema of a status table.
pub fn status_schema() -> Schema {
    Schema::new(vec![
        doc(Field::new("input_key", DataType::Utf8, false), "Stable input key `{dataset}/{video_id}`."),
        doc(Field::new("status", DataType::Utf8, false), "`ok`, `skipped` or `failed`."),
        doc(
            Field::new("reason", DataType::Utf8, false),
            "Why the input was skipped or failed, naming the file and field; empty when ok.",
        ),
        doc(Field::new("clips", DataType::UInt32, false), "Clips written for the input."),
        doc(Field::new("pairs", DataType::UInt32, false), "Training pairs written for the input."),
        doc(
            Field::new("shard", DataType::Utf8, false),
            "File name of the shard holding the input's pairs; empty unless ok.",
        ),
        doc(Field::new("content_hash", DataType::Utf8, false), "BLAKE3 of the input's files; empty if unreadable."),
        doc(Field::new("seconds", DataType::Float64, false), "Processing wall time in seconds."),
        doc(Field::new("worker_index", DataType::UInt32, false), "Index of the worker that processed the input."),
        doc(Field::new("worker_count", DataType::UInt32, false), "Number of workers of the run."),
    ])
    .with_metadata(HashMap::from([
        (SCHEMA_NAME_KEY.to_owned(), STATUS_SCHEMA_NAME.to_owned()),
        (SCHEMA_VERSION_KEY.to_owned(), STATUS_SCHEMA_VERSION.to_string()),
    ]))
}

/// Writes `records` as a status table at `path` (temporary name + rename).
pub fn write_status_table(path: &Path, records: &[StatusRecord]) -> Result<()> {
    let schema = Arc::new(status_schema());
    let strings =
        |f: fn(&StatusRecord) -> &str| Arc::new(StringArray::from_iter_values(records.iter().map(f))) as ArrayRef;
    let u32s = |f: fn(&StatusRecord) -> u32| Arc::new(UInt32Array::from_iter_values(records.iter().map(f))) as ArrayRef;
    let columns = vec![
        strings(|r| &r.input_key),
        strings(|r| r.status.as_str()),
        strings(|r| &r.reason),
        u32s(|r| r.clips),
        u32s(|r| r.pairs),
        strings(|r| &r.shard),
        strings(|r| &r.content_hash),
        Arc::new(Float64Array::from_iter_values(records.iter().map(|r| r.seconds))) as ArrayRef,
        u32s(|r| r.worker_index),
        u32s(|r| r.worker_count),
    ];
    let batch = RecordBatch::try_new(schema.clone(), columns)
        .map_err(|source| Error::Arrow { path: path.to_owned(), source })?;
    let temp = path.with_file_name(format!(
        ".{}{TEMP_MARKER}{}",
        path.file_name().unwrap_or_default().to_string_lossy(),
        std::process::id()
    ));
    let write = || -> Result<()> {
        let file = File::create(&temp).map_err(|e| Error::io(&temp, e))?;
        let parquet = |source| Error::Parquet { path: temp.clone(), source };
        let mut writer = ArrowWriter::try_new(file, schema, None).map_err(parquet)?;
        writer.write(&batch).map_err(parquet)?;
        writer.close().map_err(parquet)?;
        File::open(&temp).and_then(|f| f.sync_all()).map_err(|e| Error::io(&temp, e))?;
        std::fs::rename(&temp, path).map_err(|e| Error::io(path, e))
    };
    write().inspect_err(|_| {
        let _ = std::fs::remove_file(&temp);
    })
}

/// Reads a status table.
pub fn read_status_table(path: &Path) -> Result<Vec<StatusRecord>> {
    let file = File::open(path).map_err(|e| Error::io(path, e))?;
    let parquet = |source| Error::Parquet { path: path.to_owned(), source };
    let reader = ParquetRecordBatchReaderBuilder::try_new(file).map_err(parquet)?.build().map_err(parquet)?;
    let mut records = Vec::new();
    for batch in reader {
        let batch = batch.map_err(|source| Error::Arrow { path: path.to_owned(), source })?;
        let column =
            |name: &str| batch.column_by_name(name).ok_or_else(|| Error::mismatch(path, name, "column missing"));
        let typed = |name: &str| Error::mismatch(path, name, "wrong type");
        let string = |name: &'static str| -> Result<StringArray> {
            column(name)?.as_string_opt::<i32>().cloned().ok_or_else(|| typed(name))
        };
        let u32s = |name: &'static str| -> Result<UInt32Array> {
            column(name)?.as_primitive_opt::<UInt32Type>().cloned().ok_or_else(|| typed(name))
        };
        let (key, status, reason, shard, hash) =
            (string("input_key")?, string("status")?, string("reason")?, string("shard")?, string("content_hash")?);
        let (clips, pairs, index, count) =
            (u32s("clips")?, u32s("pairs")?, u32s("worker_index")?, u32s("worker_count")?);
        let seconds = column("seconds")?.as_primitive_opt::<Float64Type>().cloned().ok_or_else(|| typed("seconds"))?;
        for row in 0..batch.num_rows() {
            records.push(StatusRecord {
                input_key: key.value(row).to_owned(),
                status: InputStatus::parse(status.value(row)).ok_or_else(|| {
                    Error::mismatch(path, "status", format!("unknown status `{}`", status.value(row)))
                })?,
                reason: reason.value(row).to_owned(),
                clips: clips.value(row),
                pairs: pairs.value(row),
                shard: shard.value(row).to_owned(),
                content_hash: hash.value(row).to_owned(),
                seconds: seconds.value(row),
                worker_index: index.value(row),
                worker_count: count.value(row),
            });
        }
        debug_assert!(key.len() == batch.num_rows());
    }
    Ok(records)
}
