//! Conversion between [`ClipRecord`]s and Arrow record batches of the [`pair_schema`].

use std::path::Path;
use std::sync::Arc;

use arrow_array::builder::LargeBinaryBuilder;
use arrow_array::cast::AsArray;
use arrow_array::types::{Float64Type, UInt32Type, UInt64Type};
use arrow_array::{
    Array, ArrayRef, BooleanArray, FixedSizeListArray, Float64Array, ListArray, RecordBatch, StringArray, StructArray,
    UInt32Array, UInt64Array,
};
use arrow_buffer::{NullBuffer, OffsetBuffer};
use arrow_schema::{DataType, FieldRef, SchemaRef};

use crate::error::{Error, Result};
use crate::pairs::{
    BankProvenance, ClipRecord, MaskRule, PairKind, TrajectoryKind, TrajectoryRecord, bank_provenance_fields,
    pair_schema, trajectory_fields,
};

/// The item field of a list data type (the schema defines it; this just reads it back).
fn item_field(data_type: &DataType) -> FieldRef {
    match data_type {
        DataType::List(item) => item.clone(),
        other => unreachable!("schema field is a list, got {other}"),
    }
}

fn offsets<I: IntoIterator<Item = usize>>(lengths: I) -> OffsetBuffer<i32> {
    OffsetBuffer::from_lengths(lengths)
}

/// `list<large_binary>` from per-row byte lists; a `None` row is null.
fn bytes_list(data_type: &DataType, rows: &[Option<&[Vec<u8>]>]) -> Result<ListArray, arrow_schema::ArrowError> {
    // Sized up front: the frames of a clip are tens of megabytes, copied once.
    let items = || rows.iter().flatten().flat_map(|row| row.iter());
    let mut values = LargeBinaryBuilder::with_capacity(items().count(), items().map(Vec::len).sum());
    items().for_each(|item| values.append_value(item));
    let values = values.finish();
    let nulls = rows.iter().any(Option::is_none).then(|| NullBuffer::from_iter(rows.iter().map(Option::is_some)));
    let lengths = rows.iter().map(|row| row.map_or(0, <[Vec<u8>]>::len));
    ListArray::try_new(item_field(data_type), offsets(lengths), Arc::new(values), nulls)
}

/// `list<fixed_size_list<float64, N>>` from per-row matrix lists.
pub(crate) fn matrix_list<const N: usize>(
    data_type: &DataType,
    rows: &[&[[f64; N]]],
) -> Result<ListArray, arrow_schema::ArrowError> {
    let item = item_field(data_type);
    let DataType::FixedSizeList(scalar, size) = item.data_type() else {
        unreachable!("matrix column items are fixed-size lists")
    };
    let flat = Float64Array::from_iter_values(rows.iter().flat_map(|row| row.iter().flatten().copied()));
    let matrices = FixedSizeListArray::try_new(scalar.clone(), *size, Arc::new(flat), None)?;
    ListArray::try_new(item, offsets(rows.iter().map(|row| row.len())), Arc::new(matrices), None)
}

/// `list<float64>` from per-row value lists.
fn f64_list(data_type: &DataType, rows: &[&[f64]]) -> Result<ListArray, arrow_schema::ArrowError> {
    let flat = Float64Array::from_iter_values(rows.iter().flat_map(|row| row.iter().copied()));
    ListArray::try_new(item_field(data_type), offsets(rows.iter().map(|row| row.len())), Arc::new(flat), None)
}

/// Checks that every per-frame list of a record has one entry per frame.
pub(crate) fn check_record(record: &ClipRecord) -> Result<()> {
    let n = record.frames.len();
    let bad = |field: &str, len: usize| Error::InvalidRecord {
        clip_id: record.clip_id.clone(),
        field: field.to_owned(),
        reason: format!("{len} entries for {n} frames"),
    };
    let lengths = [
        ("depth", record.depth.len()),
        ("intrinsics", record.intrinsics.len()),
        ("world_from_camera", record.world_from_camera.len()),
        ("dynamic_mask", record.dynamic_mask.as_ref().map_or(n, Vec::len)),
    ];
    for (field, len) in lengths {
        if len != n {
            return Err(bad(field, len));
        }
    }
    for (t, trajectory) in record.trajectories.iter().enumerate() {
        let lengths = [
            ("world_from_camera", trajectory.world_from_camera.len()),
            ("covisible_mask", trajectory.covisible_mask.len()),
            ("condition", trajectory.condition.as_ref().map_or(n, Vec::len)),
        ];
        for (field, len) in lengths {
            if len != n {
                return Err(bad(&format!("trajectories[{t}].{field}"), len));
            }
        }
    }
    Ok(())
}

/// Builds one record batch (one row per record) of the [`pair_schema`].
pub fn records_to_batch(records: &[ClipRecord]) -> Result<RecordBatch> {
    for record in records {
        check_record(record)?;
    }
    let schema: SchemaRef = Arc::new(pair_schema());
    let arrow_err = |source| Error::Arrow { path: "<in memory>".into(), source };
    let dt = |name: &str| schema.field_with_name(name).expect("field defined by pair_schema").data_type().clone();
    let strings =
        |f: fn(&ClipRecord) -> &str| Arc::new(StringArray::from_iter_values(records.iter().map(f))) as ArrayRef;
    let u32s = |f: fn(&ClipRecord) -> u32| Arc::new(UInt32Array::from_iter_values(records.iter().map(f))) as ArrayRef;
    let f64s = |f: fn(&ClipRecord) -> f64| Arc::new(Float64Array::from_iter_values(records.iter().map(f))) as ArrayRef;

    let frames: Vec<_> = records.iter().map(|r| Some(r.frames.as_slice())).collect();
    let depth: Vec<_> = records.iter().map(|r| Some(r.depth.as_slice())).collect();
    let masks: Vec<_> = records.iter().map(|r| r.dynamic_mask.as_deref()).collect();
    let intrinsics: Vec<_> = records.iter().map(|r| r.intrinsics.as_slice()).collect();
    let poses: Vec<_> = records.iter().map(|r| r.world_from_camera.as_slice()).collect();

    let columns: Vec<ArrayRef> = vec![
        strings(|r| &r.clip_id),
        strings(|r| &r.source_id),
        strings(|r| &r.dataset),
        strings(|r| &r.source_path),
        u32s(|r| r.clip_start),
        u32s(|r| r.frames.len() as u32),
        f64s(|r| r.fps),
        u32s(|r| r.width),
        u32s(|r| r.height),
        Arc::new(UInt64Array::from_iter_values(records.iter().map(|r| r.seed))),
        strings(|r| &r.tool_version),
        Arc::new(bytes_list(&dt("frames"), &frames).map_err(arrow_err)?),
        Arc::new(bytes_list(&dt("depth"), &depth).map_err(arrow_err)?),
        Arc::new(matrix_list(&dt("intrinsics"), &intrinsics).map_err(arrow_err)?),
        Arc::new(matrix_list(&dt("world_from_camera"), &poses).map_err(arrow_err)?),
        Arc::new(bytes_list(&dt("dynamic_mask"), &masks).map_err(arrow_err)?),
        Arc::new(trajectories_column(&dt("trajectories"), records).map_err(arrow_err)?),
        strings(|r| r.pair_kind.as_str()),
        Arc::new(StringArray::from_iter(records.iter().map(|r| r.source_camera.as_deref()))),
        Arc::new(StringArray::from_iter(records.iter().map(|r| r.target_camera.as_deref()))),
    ];
    RecordBatch::try_new(schema, columns).map_err(arrow_err)
}

fn trajectories_column(data_type: &DataType, records: &[ClipRecord]) -> Result<ListArray, arrow_schema::ArrowError> {
    let all: Vec<&TrajectoryRecord> = records.iter().flat_map(|r| &r.trajectories).collect();
    let fields = trajectory_fields();
    let dt = |name: &str| fields.find(name).expect("trajectory field").1.data_type().clone();
    let azimuth: Vec<_> = all.iter().map(|t| t.azimuth_deg.as_slice()).collect();
    let elevation: Vec<_> = all.iter().map(|t| t.elevation_deg.as_slice()).collect();
    let radius: Vec<_> = all.iter().map(|t| t.radius_frac.as_slice()).collect();
    let poses: Vec<_> = all.iter().map(|t| t.world_from_camera.as_slice()).collect();
    let masks: Vec<_> = all.iter().map(|t| Some(t.covisible_mask.as_slice())).collect();
    let condition: Vec<_> = all.iter().map(|t| t.condition.as_deref()).collect();
    let columns: Vec<ArrayRef> = vec![
        Arc::new(UInt32Array::from_iter_values(all.iter().map(|t| t.index))),
        Arc::new(StringArray::from_iter_values(all.iter().map(|t| t.kind.as_str()))),
        Arc::new(Float64Array::from_iter_values(all.iter().map(|t| t.pivot_distance))),
        Arc::new(f64_list(&dt("azimuth_deg"), &azimuth)?),
        Arc::new(f64_list(&dt("elevation_deg"), &elevation)?),
        Arc::new(f64_list(&dt("radius_frac"), &radius)?),
        Arc::new(UInt32Array::from_iter_values(all.iter().map(|t| t.rejected_samples))),
        Arc::new(matrix_list(&dt("world_from_camera"), &poses)?),
        Arc::new(bytes_list(&dt("covisible_mask"), &masks)?),
        Arc::new(bytes_list(&dt("condition"), &condition)?),
        Arc::new(Float64Array::from_iter_values(all.iter().map(|t| t.covisible_fraction))),
        Arc::new(bank_entry_column(&all)?),
        Arc::new(StringArray::from_iter_values(all.iter().map(|t| t.mask_rule.as_str()))),
    ];
    let structs = StructArray::try_new(fields, columns, None)?;
    ListArray::try_new(
        item_field(data_type),
        offsets(records.iter().map(|r| r.trajectories.len())),
        Arc::new(structs),
        None,
    )
}

/// The nullable `bank_entry` struct column: one element per trajectory, null unless drawn from a bank.
fn bank_entry_column(all: &[&TrajectoryRecord]) -> Result<StructArray, arrow_schema::ArrowError> {
    // Null rows still need a value in each child; they hold defaults nobody reads.
    let entries: Vec<Option<&BankProvenance>> = all.iter().map(|t| t.bank_entry.as_ref()).collect();
    let nulls = entries.iter().any(Option::is_none).then(|| NullBuffer::from_iter(entries.iter().map(Option::is_some)));
    let columns: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from_iter_values(entries.iter().map(|e| e.map_or("", |e| e.entry_id.as_str())))),
        Arc::new(UInt32Array::from_iter_values(entries.iter().map(|e| e.map_or(0, |e| e.entry_row)))),
        Arc::new(StringArray::from_iter_values(entries.iter().map(|e| e.map_or("", |e| e.bank_digest.as_str())))),
        Arc::new(BooleanArray::from_iter(entries.iter().map(|e| Some(e.is_some_and(|e| e.mirrored))))),
        Arc::new(Float64Array::from_iter_values(entries.iter().map(|e| e.map_or(0.0, |e| e.roll_deg)))),
    ];
    StructArray::try_new(bank_provenance_fields(), columns, nulls)
}

/// Reads a batch of the [`pair_schema`] back into records. `path` names the file in errors.
pub fn batch_to_records(batch: &RecordBatch, path: &Path) -> Result<Vec<ClipRecord>> {
    let columns = Columns { batch, path };
    let clip_id = columns.strings("clip_id")?;
    let source_id = columns.strings("source_id")?;
    let dataset = columns.strings("dataset")?;
    let source_path = columns.strings("source_path")?;
    let clip_start = columns.primitive::<UInt32Type>("clip_start")?;
    let num_frames = columns.primitive::<UInt32Type>("num_frames")?;
    let fps = columns.primitive::<Float64Type>("fps")?;
    let width = columns.primitive::<UInt32Type>("width")?;
    let height = columns.primitive::<UInt32Type>("height")?;
    let seed = columns.primitive::<UInt64Type>("seed")?;
    let tool_version = columns.strings("tool_version")?;
    let frames = columns.list("frames")?;
    let depth = columns.list("depth")?;
    let intrinsics = columns.list("intrinsics")?;
    let poses = columns.list("world_from_camera")?;
    let masks = columns.list("dynamic_mask")?;
    let trajectories = columns.list("trajectories")?;
    // Absent before v3: every clip then reads as monocular, from a single-camera input.
    let pair_kind = columns.optional_strings("pair_kind")?;
    let source_camera = columns.optional_strings("source_camera")?;
    let target_camera = columns.optional_strings("target_camera")?;
    let camera =
        |column: Option<&StringArray>, row: usize| column.filter(|c| !c.is_null(row)).map(|c| c.value(row).to_owned());

    let mut records = Vec::with_capacity(batch.num_rows());
    for row in 0..batch.num_rows() {
        let pair_kind = match pair_kind {
            Some(kinds) => PairKind::parse(kinds.value(row)).ok_or_else(|| {
                Error::mismatch(path, "pair_kind", format!("row {row}: unknown kind `{}`", kinds.value(row)))
            })?,
            None => PairKind::Monocular,
        };
        let record = ClipRecord {
            clip_id: clip_id.value(row).to_owned(),
            source_id: source_id.value(row).to_owned(),
            dataset: dataset.value(row).to_owned(),
            source_path: source_path.value(row).to_owned(),
            clip_start: clip_start.value(row),
            fps: fps.value(row),
            width: width.value(row),
            height: height.value(row),
            seed: seed.value(row),
            tool_version: tool_version.value(row).to_owned(),
            frames: read_bytes(&frames.value(row), path, "frames")?,
            depth: read_bytes(&depth.value(row), path, "depth")?,
            intrinsics: read_matrices(&intrinsics.value(row), path, "intrinsics")?,
            world_from_camera: read_matrices(&poses.value(row), path, "world_from_camera")?,
            dynamic_mask: if masks.is_null(row) {
                None
            } else {
                Some(read_bytes(&masks.value(row), path, "dynamic_mask")?)
            },
            trajectories: read_trajectories(&trajectories.value(row), path, MaskRule::before_v4(pair_kind))?,
            pair_kind,
            source_camera: camera(source_camera, row),
            target_camera: camera(target_camera, row),
        };
        if record.frames.len() != num_frames.value(row) as usize {
            return Err(Error::mismatch(
                path,
                "num_frames",
                format!("row {row} says {} frames but holds {}", num_frames.value(row), record.frames.len()),
            ));
        }
        check_record(&record).map_err(|e| Error::mismatch(path, "frames", e.to_string()))?;
        records.push(record);
    }
    Ok(records)
}

/// Typed access to the columns of a batch, with errors naming the file and column.
struct Columns<'a> {
    batch: &'a RecordBatch,
    path: &'a Path,
}

impl<'a> Columns<'a> {
    fn column(&self, name: &str) -> Result<&'a ArrayRef> {
        self.batch.column_by_name(name).ok_or_else(|| Error::mismatch(self.path, name, "column missing"))
    }

    fn strings(&self, name: &str) -> Result<&'a StringArray> {
        let column = self.column(name)?;
        column.as_string_opt::<i32>().ok_or_else(|| self.wrong_type(name, column))
    }

    /// A string column that older schema versions lack (`None` when absent).
    fn optional_strings(&self, name: &str) -> Result<Option<&'a StringArray>> {
        match self.batch.column_by_name(name) {
            Some(column) => column.as_string_opt::<i32>().map(Some).ok_or_else(|| self.wrong_type(name, column)),
            None => Ok(None),
        }
    }

    fn primitive<T: arrow_array::ArrowPrimitiveType>(&self, name: &str) -> Result<&'a arrow_array::PrimitiveArray<T>> {
        let column = self.column(name)?;
        column.as_primitive_opt::<T>().ok_or_else(|| self.wrong_type(name, column))
    }

    fn list(&self, name: &str) -> Result<&'a ListArray> {
        let column = self.column(name)?;
        column.as_list_opt::<i32>().ok_or_else(|| self.wrong_type(name, column))
    }

    fn wrong_type(&self, name: &str, column: &ArrayRef) -> Error {
        let expected = pair_schema().field_with_name(name).map(|f| f.data_type().to_string()).unwrap_or_default();
        Error::mismatch(self.path, name, format!("expected type {expected}, found {}", column.data_type()))
    }
}

fn read_bytes(values: &ArrayRef, path: &Path, field: &str) -> Result<Vec<Vec<u8>>> {
    let values = values.as_binary_opt::<i64>().ok_or_else(|| {
        Error::mismatch(path, field, format!("expected large_binary items, found {}", values.data_type()))
    })?;
    Ok(values.iter().map(|v| v.unwrap_or_default().to_vec()).collect())
}

fn read_f64s(values: &ArrayRef, path: &Path, field: &str) -> Result<Vec<f64>> {
    let values = values
        .as_primitive_opt::<Float64Type>()
        .ok_or_else(|| Error::mismatch(path, field, format!("expected float64 items, found {}", values.data_type())))?;
    Ok(values.values().to_vec())
}

pub(crate) fn read_matrices<const N: usize>(values: &ArrayRef, path: &Path, field: &str) -> Result<Vec<[f64; N]>> {
    let matrices = values.as_fixed_size_list_opt().filter(|m| m.value_length() as usize == N).ok_or_else(|| {
        Error::mismatch(path, field, format!("expected fixed_size_list<float64, {N}>, found {}", values.data_type()))
    })?;
    (0..matrices.len())
        .map(|j| {
            let values = read_f64s(&matrices.value(j), path, field)?;
            Ok(values.try_into().expect("fixed-size list of N"))
        })
        .collect()
}

/// The trajectories of one row; `older_rule` is the mask rule of shards that do not record it.
fn read_trajectories(values: &ArrayRef, path: &Path, older_rule: MaskRule) -> Result<Vec<TrajectoryRecord>> {
    let field = "trajectories";
    let structs = values
        .as_struct_opt()
        .ok_or_else(|| Error::mismatch(path, field, format!("expected struct items, found {}", values.data_type())))?;
    let column = |name: &str| {
        structs.column_by_name(name).ok_or_else(|| Error::mismatch(path, format!("{field}.{name}"), "column missing"))
    };
    let typed = |name: &str| Error::mismatch(path, format!("{field}.{name}"), "wrong type");
    let index = column("index")?.as_primitive_opt::<UInt32Type>().ok_or_else(|| typed("index"))?;
    let kind = column("kind")?.as_string_opt::<i32>().ok_or_else(|| typed("kind"))?;
    let pivot = column("pivot_distance")?.as_primitive_opt::<Float64Type>().ok_or_else(|| typed("pivot_distance"))?;
    let azimuth = column("azimuth_deg")?.as_list_opt::<i32>().ok_or_else(|| typed("azimuth_deg"))?;
    let elevation = column("elevation_deg")?.as_list_opt::<i32>().ok_or_else(|| typed("elevation_deg"))?;
    let radius = column("radius_frac")?.as_list_opt::<i32>().ok_or_else(|| typed("radius_frac"))?;
    let rejected =
        column("rejected_samples")?.as_primitive_opt::<UInt32Type>().ok_or_else(|| typed("rejected_samples"))?;
    let poses = column("world_from_camera")?.as_list_opt::<i32>().ok_or_else(|| typed("world_from_camera"))?;
    let masks = column("covisible_mask")?.as_list_opt::<i32>().ok_or_else(|| typed("covisible_mask"))?;
    let condition = column("condition")?.as_list_opt::<i32>().ok_or_else(|| typed("condition"))?;
    let fraction =
        column("covisible_fraction")?.as_primitive_opt::<Float64Type>().ok_or_else(|| typed("covisible_fraction"))?;
    // Absent in v1 shards: every trajectory then reads as not drawn from a bank.
    let bank = match structs.column_by_name("bank_entry") {
        Some(column) => Some(BankColumns::new(column, path)?),
        None => None,
    };
    // Absent before v4: the rule is then the one every pair of the kind used.
    let mask_rule = match structs.column_by_name("mask_rule") {
        Some(column) => Some(column.as_string_opt::<i32>().ok_or_else(|| typed("mask_rule"))?),
        None => None,
    };
    (0..structs.len())
        .map(|i| {
            Ok(TrajectoryRecord {
                index: index.value(i),
                kind: TrajectoryKind::parse(kind.value(i)).ok_or_else(|| {
                    Error::mismatch(path, "trajectories.kind", format!("unknown kind `{}`", kind.value(i)))
                })?,
                pivot_distance: pivot.value(i),
                azimuth_deg: read_f64s(&azimuth.value(i), path, "trajectories.azimuth_deg")?,
                elevation_deg: read_f64s(&elevation.value(i), path, "trajectories.elevation_deg")?,
                radius_frac: read_f64s(&radius.value(i), path, "trajectories.radius_frac")?,
                rejected_samples: rejected.value(i),
                world_from_camera: read_matrices(&poses.value(i), path, "trajectories.world_from_camera")?,
                covisible_mask: read_bytes(&masks.value(i), path, "trajectories.covisible_mask")?,
                condition: if condition.is_null(i) {
                    None
                } else {
                    Some(read_bytes(&condition.value(i), path, "trajectories.condition")?)
                },
                covisible_fraction: fraction.value(i),
                bank_entry: bank.as_ref().and_then(|b| b.get(i)),
                mask_rule: match mask_rule {
                    Some(rules) => MaskRule::parse(rules.value(i)).ok_or_else(|| {
                        Error::mismatch(path, "trajectories.mask_rule", format!("unknown rule `{}`", rules.value(i)))
                    })?,
                    None => older_rule,
                },
            })
        })
        .collect()
}

/// Typed children of the `trajectories.bank_entry` struct column.
struct BankColumns<'a> {
    column: &'a StructArray,
    entry_id: &'a StringArray,
    entry_row: &'a UInt32Array,
    bank_digest: &'a StringArray,
    mirrored: &'a BooleanArray,
    roll_deg: &'a Float64Array,
}

impl<'a> BankColumns<'a> {
    fn new(column: &'a ArrayRef, path: &Path) -> Result<Self> {
        let typed =
            |name: &str| Error::mismatch(path, format!("trajectories.bank_entry.{name}"), "missing or wrong type");
        let column = column.as_struct_opt().ok_or_else(|| typed(""))?;
        let child = |name: &str| column.column_by_name(name).ok_or_else(|| typed(name));
        Ok(Self {
            column,
            entry_id: child("entry_id")?.as_string_opt::<i32>().ok_or_else(|| typed("entry_id"))?,
            entry_row: child("entry_row")?.as_primitive_opt::<UInt32Type>().ok_or_else(|| typed("entry_row"))?,
            bank_digest: child("bank_digest")?.as_string_opt::<i32>().ok_or_else(|| typed("bank_digest"))?,
            mirrored: child("mirrored")?.as_boolean_opt().ok_or_else(|| typed("mirrored"))?,
            roll_deg: child("roll_deg")?.as_primitive_opt::<Float64Type>().ok_or_else(|| typed("roll_deg"))?,
        })
    }

    fn get(&self, i: usize) -> Option<BankProvenance> {
        (!self.column.is_null(i)).then(|| BankProvenance {
            entry_id: self.entry_id.value(i).to_owned(),
            entry_row: self.entry_row.value(i),
            bank_digest: self.bank_digest.value(i).to_owned(),
            mirrored: self.mirrored.value(i),
            roll_deg: self.roll_deg.value(i),
        })
    }
}
