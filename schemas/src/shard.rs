//! Writing and reading shard files: a shard is one self-contained Parquet file of the
//! [`pair_schema`], written under a temporary name and renamed into place; it counts as finished
//! only once its stats marker (`<shard>.stats.json`), written last, exists.

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use arrow_schema::Schema;
use parquet::arrow::arrow_reader::{
    ParquetRecordBatchReader, ParquetRecordBatchReaderBuilder, RowSelection, RowSelector,
};
use parquet::arrow::arrow_writer::{ArrowColumnWriter, ArrowLeafColumn, ArrowRowGroupWriterFactory, compute_leaves};
use parquet::arrow::{ArrowSchemaConverter, ArrowWriter};
use parquet::basic::{Compression, LogicalType, Type as PhysicalType, ZstdLevel};
use parquet::file::metadata::KeyValue;
use parquet::file::properties::{EnabledStatistics, WriterProperties};
use parquet::file::writer::SerializedFileWriter;
use parquet::schema::types::ColumnPath;
use rayon::prelude::*;

use crate::arrow_convert::{batch_to_records, records_to_batch};
use crate::direct_file::DirectFile;
use crate::error::{Error, Result};
use crate::pairs::{
    ClipRecord, OLDEST_READABLE_SCHEMA_VERSION, PairKind, SCHEMA_NAME, SCHEMA_NAME_KEY, SCHEMA_VERSION,
    SCHEMA_VERSION_KEY, pair_schema, pair_schema_of_version,
};

/// Suffix of a shard's stats marker file, appended to the shard's file name.
pub const STATS_SUFFIX: &str = ".stats.json";
/// Marker in temporary file names; readers and listings skip such files.
pub const TEMP_MARKER: &str = ".tmp-";
/// Default row-group size target in bytes (uncompressed, as buffered by the writer). Large enough
/// for efficient scans, small enough that a reader holds one row group comfortably in memory.
pub const DEFAULT_ROW_GROUP_BYTES: usize = 64 << 20;
/// Zstandard level for the Parquet pages of the small columns (cameras, trajectories, ids).
const ZSTD_LEVEL: i32 = 1;
/// Rows decoded per Arrow batch when reading: one clip can be tens of megabytes.
const READ_BATCH_ROWS: usize = 4;

/// How a shard is written.
#[derive(Debug, Clone)]
pub struct ShardWriterOptions {
    /// Flush a row group once the buffered data reaches this many bytes.
    pub row_group_bytes: usize,
}

impl Default for ShardWriterOptions {
    fn default() -> Self {
        Self { row_group_bytes: DEFAULT_ROW_GROUP_BYTES }
    }
}

/// Content hash of one input that went into a shard, for provenance and resume checks.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct InputDigest {
    /// The input as the user named it (a sequence folder or a file).
    pub source_path: String,
    /// BLAKE3 hex digest of the input's files, in a stable order.
    pub content_hash: String,
}

/// The stats marker written beside a finished shard.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ShardStats {
    /// Schema name, [`SCHEMA_NAME`].
    pub schema: String,
    /// Schema version, [`SCHEMA_VERSION`].
    pub schema_version: u32,
    /// File name of the shard (no folder).
    pub shard: String,
    /// Number of clips (rows).
    pub clips: u64,
    /// Number of training pairs (trajectories over all clips).
    pub pairs: u64,
    /// Number of frames over all clips.
    pub frames: u64,
    /// Size of the shard file in bytes.
    pub bytes: u64,
    /// Number of Parquet row groups.
    pub row_groups: u64,
    /// Wall time from opening the writer to the rename, in seconds.
    pub write_seconds: f64,
    /// Inputs that went into the shard.
    pub inputs: Vec<InputDigest>,
}

/// Path of the stats marker of `shard`.
pub fn stats_path(shard: &Path) -> PathBuf {
    let mut name = shard.file_name().unwrap_or_default().to_os_string();
    name.push(STATS_SUFFIX);
    shard.with_file_name(name)
}

/// Whether `shard` is finished: the file and its stats marker both exist.
pub fn is_finished(shard: &Path) -> bool {
    shard.is_file() && stats_path(shard).is_file()
}

/// Reads the stats marker of a finished shard.
pub fn read_stats(shard: &Path) -> Result<ShardStats> {
    let path = stats_path(shard);
    let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
    serde_json::from_str(&text).map_err(|source| Error::Json { path, source })
}

/// Writes one shard atomically. Dropping the writer without [`ShardWriter::finish`] removes the
/// temporary file, so no partial shard is ever visible under the final name.
///
/// The Parquet columns of a row group are encoded in parallel (rayon), each by its own column
/// writer: a clip's frames and depth are tens of MB each, and one writer encoding them in turn was
/// most of the time `datagen pairs` spends writing.
pub struct ShardWriter {
    final_path: PathBuf,
    temp_path: PathBuf,
    /// The file, until [`ShardWriter::finish`].
    file: Option<SerializedFileWriter<DirectFile>>,
    columns: ArrowRowGroupWriterFactory,
    /// The column writers of the row group in progress, one per Parquet leaf column.
    row_group: Option<Vec<ArrowColumnWriter>>,
    row_groups: usize,
    options: ShardWriterOptions,
    clips: u64,
    pairs: u64,
    frames: u64,
    inputs: Vec<InputDigest>,
    started: Instant,
}

impl ShardWriter {
    /// Opens a writer whose output will appear at `final_path` when finished. The parent folder
    /// must exist.
    pub fn create(final_path: &Path, options: ShardWriterOptions) -> Result<Self> {
        let file_name = final_path.file_name().ok_or_else(|| {
            Error::io(final_path, std::io::Error::new(std::io::ErrorKind::InvalidInput, "shard path has no file name"))
        })?;
        let temp_name = format!(".{}{TEMP_MARKER}{}", file_name.to_string_lossy(), std::process::id());
        let temp_path = final_path.with_file_name(temp_name);
        let file = DirectFile::create(&temp_path).map_err(|e| Error::io(&temp_path, e))?;
        let schema = pair_schema();
        let mut properties = WriterProperties::builder()
            .set_compression(Compression::ZSTD(ZstdLevel::try_new(ZSTD_LEVEL).expect("valid zstd level")))
            .set_dictionary_enabled(false)
            .set_statistics_enabled(EnabledStatistics::Chunk)
            .set_max_row_group_row_count(Some(usize::MAX))
            .set_key_value_metadata(Some(vec![
                KeyValue::new(SCHEMA_NAME_KEY.to_owned(), SCHEMA_NAME.to_owned()),
                KeyValue::new(SCHEMA_VERSION_KEY.to_owned(), SCHEMA_VERSION.to_string()),
            ]));
        // Frames, depth and masks are PNG and EXR already: compressing them again gains under
        // 2 % of the file for a fifth of the write time.
        for column in binary_columns(&schema) {
            properties = properties.set_column_compression(column, Compression::UNCOMPRESSED);
        }
        // The Arrow writer sets up the file (the Arrow schema in its metadata) and hands over
        // its parts; rows are then written column by column (`write`).
        let (file, columns) = ArrowWriter::try_new(file, schema.into(), Some(properties.build()))
            .and_then(ArrowWriter::into_serialized_writer)
            .map_err(|source| Error::Parquet { path: temp_path.clone(), source })?;
        Ok(Self {
            final_path: final_path.to_owned(),
            temp_path,
            file: Some(file),
            columns,
            row_group: None,
            row_groups: 0,
            options,
            clips: 0,
            pairs: 0,
            frames: 0,
            inputs: Vec::new(),
            started: Instant::now(),
        })
    }

    fn parquet_error(&self, source: parquet::errors::ParquetError) -> Error {
        Error::Parquet { path: self.temp_path.clone(), source }
    }

    /// Appends one clip; flushes a row group when the buffered bytes reach the target.
    pub fn write(&mut self, record: &ClipRecord) -> Result<()> {
        let batch = records_to_batch(std::slice::from_ref(record))?;
        let leaves = batch
            .schema()
            .fields()
            .iter()
            .zip(batch.columns())
            .map(|(field, column)| compute_leaves(field, column))
            .collect::<parquet::errors::Result<Vec<_>>>()
            .map_err(|e| self.parquet_error(e))?;
        let writers = match self.row_group.take() {
            Some(writers) => writers,
            None => self.columns.create_column_writers(self.row_groups).map_err(|e| self.parquet_error(e))?,
        };
        let leaves: Vec<ArrowLeafColumn> = leaves.into_iter().flatten().collect();
        assert_eq!(leaves.len(), writers.len(), "one column writer per leaf of the pair schema");
        let writers = writers
            .into_par_iter()
            .zip(leaves)
            .map(|(mut writer, leaf)| writer.write(&leaf).map(|()| writer))
            .collect::<parquet::errors::Result<Vec<_>>>()
            .map_err(|e| self.parquet_error(e))?;
        let buffered: usize = writers.iter().map(ArrowColumnWriter::get_estimated_total_bytes).sum();
        self.row_group = Some(writers);
        if buffered >= self.options.row_group_bytes {
            self.flush_row_group()?;
        }
        self.clips += 1;
        self.pairs += record.trajectories.len() as u64;
        self.frames += record.num_frames() as u64;
        Ok(())
    }

    /// Closes the column writers of the row group in progress (in parallel) and appends their
    /// chunks to the file, in schema order.
    fn flush_row_group(&mut self) -> Result<()> {
        let Some(writers) = self.row_group.take() else { return Ok(()) };
        let chunks = writers
            .into_par_iter()
            .map(ArrowColumnWriter::close)
            .collect::<parquet::errors::Result<Vec<_>>>()
            .map_err(|e| self.parquet_error(e))?;
        let file = self.file.as_mut().expect("file open until finish");
        let append = |file: &mut SerializedFileWriter<DirectFile>| {
            let mut row_group = file.next_row_group()?;
            for chunk in chunks {
                chunk.append_to_row_group(&mut row_group)?;
            }
            row_group.close().map(drop)
        };
        append(file).map_err(|e| self.parquet_error(e))?;
        self.row_groups += 1;
        Ok(())
    }

    /// Records an input's content hash in the stats marker.
    pub fn add_input(&mut self, input: InputDigest) {
        self.inputs.push(input);
    }

    /// Closes the file, syncs it, renames it into place and writes the stats marker last.
    pub fn finish(mut self) -> Result<ShardStats> {
        let mut close = || -> Result<_> {
            self.flush_row_group()?;
            let mut file = self.file.take().expect("file open until finish");
            let metadata = file.finish().map_err(|e| self.parquet_error(e))?;
            // The last chunk, footer included, is still in the file's buffer: written and synced
            // here.
            let bytes = file.inner_mut().complete().map_err(|e| Error::io(&self.temp_path, e))?;
            std::fs::rename(&self.temp_path, &self.final_path).map_err(|e| Error::io(&self.final_path, e))?;
            Ok((metadata, bytes))
        };
        let (metadata, bytes) = close().inspect_err(|_| {
            // Disk full or similar while closing: never leave the partial file behind.
            let _ = std::fs::remove_file(&self.temp_path);
        })?;
        let stats = ShardStats {
            schema: SCHEMA_NAME.to_owned(),
            schema_version: SCHEMA_VERSION,
            shard: self.final_path.file_name().unwrap_or_default().to_string_lossy().into_owned(),
            clips: self.clips,
            pairs: self.pairs,
            frames: self.frames,
            bytes,
            row_groups: metadata.num_row_groups() as u64,
            write_seconds: self.started.elapsed().as_secs_f64(),
            inputs: std::mem::take(&mut self.inputs),
        };
        let marker =
            write_atomic(&stats_path(&self.final_path), &serde_json::to_vec_pretty(&stats).expect("stats serialise"));
        if let Err(error) = marker {
            // Without its marker the shard is unfinished: do not leave it looking like one.
            let _ = std::fs::remove_file(&self.final_path);
            return Err(error);
        }
        Ok(stats)
    }
}

impl Drop for ShardWriter {
    fn drop(&mut self) {
        if self.file.is_some() {
            // Unfinished: never leave the partial file behind. Nothing more can be done on error.
            let _ = std::fs::remove_file(&self.temp_path);
        }
    }
}

/// The Parquet leaf columns of `schema` holding raw bytes (not text).
fn binary_columns(schema: &Schema) -> Vec<ColumnPath> {
    let parquet = ArrowSchemaConverter::new().convert(schema).expect("the pair schema has a Parquet form");
    parquet
        .columns()
        .iter()
        .filter(|c| c.physical_type() == PhysicalType::BYTE_ARRAY && c.logical_type_ref() != Some(&LogicalType::String))
        .map(|c| c.path().clone())
        .collect()
}

/// Writes `bytes` to `path` through a temporary file in the same folder and a rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let temp = path.with_file_name(format!(
        ".{}{TEMP_MARKER}{}",
        path.file_name().unwrap_or_default().to_string_lossy(),
        std::process::id()
    ));
    let result = (|| {
        let mut file = File::create(&temp)?;
        file.write_all(bytes)?;
        file.sync_all()?;
        std::fs::rename(&temp, path)
    })();
    result.map_err(|e| {
        let _ = std::fs::remove_file(&temp);
        Error::io(path, e)
    })
}

/// Streams the clips of a shard, a few rows at a time.
pub struct ShardReader {
    path: PathBuf,
    batches: ParquetRecordBatchReader,
    pending: std::vec::IntoIter<ClipRecord>,
    num_rows: usize,
}

impl ShardReader {
    /// Opens `path`, checking that it is a pairs shard of the version this code reads.
    pub fn open(path: &Path) -> Result<Self> {
        let builder = open_checked(path)?;
        let parquet = |source| Error::Parquet { path: path.to_owned(), source };
        let num_rows = builder.metadata().file_metadata().num_rows() as usize;
        let batches = builder.with_batch_size(READ_BATCH_ROWS).build().map_err(parquet)?;
        Ok(Self { path: path.to_owned(), batches, pending: Vec::new().into_iter(), num_rows })
    }

    /// Number of clips in the shard, from its footer.
    pub fn num_rows(&self) -> usize {
        self.num_rows
    }
}

impl Iterator for ShardReader {
    type Item = Result<ClipRecord>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            if let Some(record) = self.pending.next() {
                return Some(Ok(record));
            }
            let batch = match self.batches.next()? {
                Ok(batch) => batch,
                Err(source) => return Some(Err(Error::Arrow { path: self.path.clone(), source })),
            };
            match batch_to_records(&batch, &self.path) {
                Ok(records) => self.pending = records.into_iter(),
                Err(error) => return Some(Err(error)),
            }
        }
    }
}

/// Opens a shard for reading after checking its schema name, version and columns.
fn open_checked(path: &Path) -> Result<ParquetRecordBatchReaderBuilder<File>> {
    let file = File::open(path).map_err(|e| Error::io(path, e))?;
    let parquet = |source| Error::Parquet { path: path.to_owned(), source };
    let builder = ParquetRecordBatchReaderBuilder::try_new(file).map_err(parquet)?;
    let key_values = builder.metadata().file_metadata().key_value_metadata().cloned().unwrap_or_default();
    let lookup = |key: &str| key_values.iter().find(|kv| kv.key == key).and_then(|kv| kv.value.clone());
    match lookup(SCHEMA_NAME_KEY) {
        Some(name) if name == SCHEMA_NAME => {}
        Some(name) => {
            return Err(Error::mismatch(path, SCHEMA_NAME_KEY, format!("expected `{SCHEMA_NAME}`, found `{name}`")));
        }
        None => return Err(Error::mismatch(path, SCHEMA_NAME_KEY, "missing: not a cognvs training-pair shard")),
    }
    let version = lookup(SCHEMA_VERSION_KEY).unwrap_or_default();
    let readable = OLDEST_READABLE_SCHEMA_VERSION..=SCHEMA_VERSION;
    let Some(version) = version.parse::<u32>().ok().filter(|v| readable.contains(v)) else {
        return Err(Error::mismatch(
            path,
            SCHEMA_VERSION_KEY,
            format!(
                "shard has version `{version}`, this reader reads versions {OLDEST_READABLE_SCHEMA_VERSION} to {SCHEMA_VERSION}"
            ),
        ));
    };
    check_columns(path, builder.schema(), &pair_schema_of_version(version))?;
    Ok(builder)
}

/// Every column of `expected` is in `found` with its data type (extra columns are allowed);
/// errors name the file and the column.
pub(crate) fn check_columns(path: &Path, found: &Schema, expected: &Schema) -> Result<()> {
    for field in expected.fields() {
        let column =
            found.field_with_name(field.name()).map_err(|_| Error::mismatch(path, field.name(), "column missing"))?;
        if !column.data_type().equals_datatype(field.data_type()) {
            return Err(Error::mismatch(
                path,
                field.name(),
                format!("expected type {}, found {}", field.data_type(), column.data_type()),
            ));
        }
    }
    Ok(())
}

/// Reads clip `row` (0-based) of a shard, decoding only the row group that holds it.
pub fn read_clip(path: &Path, row: usize) -> Result<ClipRecord> {
    let builder = open_checked(path)?;
    let parquet = |source| Error::Parquet { path: path.to_owned(), source };
    let mut first = 0usize;
    let mut group = None;
    for (g, meta) in builder.metadata().row_groups().iter().enumerate() {
        let rows = meta.num_rows() as usize;
        if row < first + rows {
            group = Some((g, row - first));
            break;
        }
        first += rows;
    }
    let (group, offset) = group
        .ok_or_else(|| Error::mismatch(path, "row", format!("row {row} is past the last clip ({first} clips)")))?;
    let selection = RowSelection::from(vec![RowSelector::skip(offset), RowSelector::select(1)]);
    let reader = builder
        .with_row_groups(vec![group])
        .with_row_selection(selection)
        .with_batch_size(1)
        .build()
        .map_err(parquet)?;
    for batch in reader {
        let batch = batch.map_err(|source| Error::Arrow { path: path.to_owned(), source })?;
        if let Some(record) = batch_to_records(&batch, path)?.into_iter().next() {
            return Ok(record);
        }
    }
    Err(Error::mismatch(path, "row", format!("row {row} could not be read")))
}

/// Number of clips in a shard, from its footer (the schema is checked too).
pub fn clip_count(path: &Path) -> Result<usize> {
    Ok(open_checked(path)?.metadata().file_metadata().num_rows() as usize)
}

/// The clip ids of a shard, in row order, reading only that column.
pub fn clip_ids(path: &Path) -> Result<Vec<String>> {
    string_column(path, "clip_id")?.ok_or_else(|| Error::mismatch(path, "clip_id", "column missing"))
}

/// The pair kind of every clip of a shard, in row order, reading only that column (shards before
/// v3 have none: all their clips are monocular).
pub fn pair_kinds(path: &Path) -> Result<Vec<PairKind>> {
    let Some(kinds) = string_column(path, "pair_kind")? else {
        return Ok(vec![PairKind::Monocular; clip_count(path)?]);
    };
    kinds
        .iter()
        .enumerate()
        .map(|(row, kind)| {
            PairKind::parse(kind)
                .ok_or_else(|| Error::mismatch(path, "pair_kind", format!("row {row}: unknown kind `{kind}`")))
        })
        .collect()
}

/// One string column of a shard, in row order, reading only that column; `None` if the shard
/// has no such column.
fn string_column(path: &Path, name: &str) -> Result<Option<Vec<String>>> {
    use arrow_array::Array as _;
    let builder = open_checked(path)?;
    let parquet = |source| Error::Parquet { path: path.to_owned(), source };
    let Ok(column) = builder.schema().index_of(name) else { return Ok(None) };
    let mask = parquet::arrow::ProjectionMask::roots(builder.parquet_schema(), [column]);
    let reader = builder.with_projection(mask).build().map_err(parquet)?;
    let mut values = Vec::new();
    for batch in reader {
        let batch = batch.map_err(|source| Error::Arrow { path: path.to_owned(), source })?;
        let strings = batch
            .column(0)
            .as_any()
            .downcast_ref::<arrow_array::StringArray>()
            .ok_or_else(|| Error::mismatch(path, name, "not a string column"))?;
        values.extend(strings.iter().map(|v| v.unwrap_or_default().to_string()));
    }
    Ok(Some(values))
}

/// Reads every clip of a shard.
pub fn read_shard(path: &Path) -> Result<Vec<ClipRecord>> {
    ShardReader::open(path)?.collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_the_encoded_image_columns_are_stored_uncompressed() {
        let columns: Vec<String> = binary_columns(&pair_schema()).iter().map(ColumnPath::string).collect();
        // Leaf names: the top-level column, or the trajectory field, of each byte list.
        let names: Vec<&str> =
            columns.iter().map(|c| c.trim_end_matches(".list.item").rsplit('.').next().unwrap()).collect();
        assert_eq!(names, ["frames", "depth", "dynamic_mask", "covisible_mask", "condition"], "{columns:?}");
    }

    /// A v1 shard of `records` (no `trajectories[].bank_entry`), written as a v1 writer did.
    fn write_v1(path: &Path, records: &[ClipRecord], version: &str) {
        write_old(path, records, 1, version)
    }

    /// A shard of `records` in the layout of schema version `layout` (the columns and trajectory
    /// fields that version has), labelled `version`, written as that version's writer did.
    fn write_old(path: &Path, records: &[ClipRecord], layout: u32, version: &str) {
        use arrow_array::cast::AsArray;
        use arrow_array::{Array, ArrayRef, ListArray, RecordBatch, StructArray};
        use std::sync::Arc;
        let batch = records_to_batch(records).unwrap();
        let index = batch.schema().index_of("trajectories").unwrap();
        let list = batch.column(index).as_list::<i32>();
        let structs = list.values().as_struct();
        let v1 = pair_schema_of_version(layout);
        let arrow_schema::DataType::List(item) = v1.field_with_name("trajectories").unwrap().data_type().clone() else {
            unreachable!()
        };
        let arrow_schema::DataType::Struct(fields) = item.data_type().clone() else { unreachable!() };
        let children: Vec<ArrayRef> = structs.columns()[..fields.len()].to_vec();
        let structs = StructArray::try_new(fields, children, None).unwrap();
        let list = ListArray::try_new(item, list.offsets().clone(), Arc::new(structs), list.nulls().cloned()).unwrap();
        let mut columns = batch.columns()[..v1.fields().len()].to_vec();
        columns[index] = Arc::new(list);
        let batch = RecordBatch::try_new(Arc::new(v1), columns).unwrap();
        let properties = WriterProperties::builder()
            .set_key_value_metadata(Some(vec![
                KeyValue::new(SCHEMA_NAME_KEY.to_owned(), SCHEMA_NAME.to_owned()),
                KeyValue::new(SCHEMA_VERSION_KEY.to_owned(), version.to_owned()),
            ]))
            .build();
        let mut writer = ArrowWriter::try_new(File::create(path).unwrap(), batch.schema(), Some(properties)).unwrap();
        writer.write(&batch).unwrap();
        writer.close().unwrap();
    }

    #[test]
    fn version_1_shards_still_read_and_unknown_versions_do_not() {
        let dir = tempfile::tempdir().unwrap();
        // A monocular pair with a sampled trajectory: the multi-view record's clip, version 1's
        // fields only.
        let multiview = multiview_record(crate::MaskRule::Exact);
        let record = ClipRecord {
            trajectories: vec![crate::TrajectoryRecord {
                kind: crate::TrajectoryKind::Sampled,
                pivot_distance: 2.0,
                azimuth_deg: vec![1.0; 4],
                elevation_deg: vec![2.0; 4],
                radius_frac: vec![0.1; 4],
                rejected_samples: 1,
                condition: None,
                ..multiview.trajectories[0].clone()
            }],
            pair_kind: PairKind::Monocular,
            source_camera: None,
            target_camera: None,
            ..multiview
        };
        let old = dir.path().join("v1.parquet");
        write_v1(&old, std::slice::from_ref(&record), "1");
        assert_eq!(read_shard(&old).unwrap(), vec![record.clone()]);
        assert_eq!(read_clip(&old, 0).unwrap(), record);
        let future = dir.path().join("v9.parquet");
        write_v1(&future, std::slice::from_ref(&record), "9");
        let error = read_shard(&future).err().unwrap().to_string();
        assert!(error.contains("v9.parquet") && error.contains(SCHEMA_VERSION_KEY) && error.contains("`9`"), "{error}");
    }

    /// A one-frame multi-view pair (cam0 to cam1) whose mask follows `mask_rule`, every field of
    /// the current layout set.
    fn multiview_record(mask_rule: crate::MaskRule) -> ClipRecord {
        ClipRecord {
            clip_id: "synth/a/0".into(),
            source_id: "a".into(),
            dataset: "synth".into(),
            source_path: "/a".into(),
            clip_start: 0,
            fps: 24.0,
            width: 2,
            height: 2,
            seed: 1,
            tool_version: "datagen 0.1.0".into(),
            frames: vec![vec![1, 2, 3]],
            depth: vec![vec![4]],
            intrinsics: vec![[1.0; 9]],
            world_from_camera: vec![[2.0; 16]],
            dynamic_mask: None,
            trajectories: vec![crate::TrajectoryRecord {
                index: 0,
                kind: crate::TrajectoryKind::Camera,
                pivot_distance: 0.0,
                azimuth_deg: Vec::new(),
                elevation_deg: Vec::new(),
                radius_frac: Vec::new(),
                rejected_samples: 0,
                world_from_camera: vec![[3.0; 16]],
                covisible_mask: vec![vec![5]],
                condition: Some(vec![vec![6]]),
                covisible_fraction: 0.5,
                bank_entry: None,
                mask_rule,
            }],
            pair_kind: PairKind::Multiview,
            source_camera: Some("cam0".into()),
            target_camera: Some("cam1".into()),
        }
    }

    #[test]
    fn an_unknown_mask_rule_is_an_error_naming_the_field() {
        use arrow_array::cast::AsArray;
        use arrow_array::{Array, ArrayRef, ListArray, RecordBatch, StringArray, StructArray};
        use std::sync::Arc;
        let dir = tempfile::tempdir().unwrap();
        let record = multiview_record(crate::MaskRule::Exact);
        // This version's layout with the rule's value replaced by one no version knows.
        let batch = records_to_batch(std::slice::from_ref(&record)).unwrap();
        let index = batch.schema().index_of("trajectories").unwrap();
        let list = batch.column(index).as_list::<i32>();
        let structs = list.values().as_struct();
        let mut children: Vec<ArrayRef> = structs.columns().to_vec();
        let rule = structs.column_names().iter().position(|name| *name == "mask_rule").unwrap();
        children[rule] = Arc::new(StringArray::from(vec!["guessed"]));
        let structs = StructArray::try_new(structs.fields().clone(), children, None).unwrap();
        let arrow_schema::DataType::List(item) = batch.schema().field(index).data_type().clone() else {
            unreachable!()
        };
        let list = ListArray::try_new(item, list.offsets().clone(), Arc::new(structs), list.nulls().cloned()).unwrap();
        let mut columns = batch.columns().to_vec();
        columns[index] = Arc::new(list);
        let batch = RecordBatch::try_new(batch.schema(), columns).unwrap();
        let path = dir.path().join("bad-rule.parquet");
        let properties = WriterProperties::builder()
            .set_key_value_metadata(Some(vec![
                KeyValue::new(SCHEMA_NAME_KEY.to_owned(), SCHEMA_NAME.to_owned()),
                KeyValue::new(SCHEMA_VERSION_KEY.to_owned(), SCHEMA_VERSION.to_string()),
            ]))
            .build();
        let mut writer = ArrowWriter::try_new(File::create(&path).unwrap(), batch.schema(), Some(properties)).unwrap();
        writer.write(&batch).unwrap();
        writer.close().unwrap();
        let error = read_shard(&path).err().unwrap().to_string();
        assert!(
            error.contains("bad-rule.parquet") && error.contains("trajectories.mask_rule") && error.contains("guessed"),
            "{error}"
        );
    }

    #[test]
    fn version_2_and_3_shards_read_with_the_rules_they_used() {
        let dir = tempfile::tempdir().unwrap();
        // Written with the v3 fields set: the v2 layout must drop them, and reading must not invent
        // them.
        let mut record = multiview_record(crate::MaskRule::Dataset);
        let current = dir.path().join("v3.parquet");
        let mut writer = ShardWriter::create(&current, ShardWriterOptions::default()).unwrap();
        writer.write(&record).unwrap();
        writer.finish().unwrap();
        assert_eq!(read_shard(&current).unwrap(), vec![record.clone()]);
        assert_eq!(pair_kinds(&current).unwrap(), [PairKind::Multiview]);

        // v3 kept the pair kind but not the mask rule: every multi-view mask was the render's
        // coverage.
        let v3 = dir.path().join("v3-layout.parquet");
        write_old(&v3, std::slice::from_ref(&record), 3, "3");
        let mut as_v3 = record.clone();
        as_v3.trajectories[0].mask_rule = crate::MaskRule::Coverage;
        assert_eq!(read_shard(&v3).unwrap(), vec![as_v3]);

        let old = dir.path().join("v2.parquet");
        write_old(&old, std::slice::from_ref(&record), 2, "2");
        record.trajectories[0].mask_rule = crate::MaskRule::Exact;
        record.pair_kind = PairKind::Monocular;
        record.source_camera = None;
        record.target_camera = None;
        assert_eq!(read_shard(&old).unwrap(), vec![record.clone()]);
        assert_eq!(read_clip(&old, 0).unwrap(), record);
        assert_eq!(pair_kinds(&old).unwrap(), [PairKind::Monocular]);
    }
}
