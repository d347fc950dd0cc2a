//! `schemas`: the contract between `datagen` and `trainer`. It defines the Arrow
//! schema of a training-pair shard, its Rust record types, atomic shard writing with a stats
//! marker, and reading with schema-version checks. The field-by-field reference in
//! `schemas/SCHEMA.md` is generated from the schema by [`reference_markdown`] and kept in sync by a
//! test.

mod arrow_convert;
pub mod direct_file;
pub mod error;
pub mod pairs;
pub mod shard;
pub mod status;
pub mod trajectory_bank;

pub use arrow_convert::{batch_to_records, records_to_batch};
pub use error::{Error, Result};
pub use pairs::{
    BankProvenance, ClipRecord, DOC_KEY, MaskRule, OLDEST_READABLE_SCHEMA_VERSION, PairKind, SCHEMA_NAME,
    SCHEMA_NAME_KEY, SCHEMA_VERSION, SCHEMA_VERSION_KEY, TrajectoryKind, TrajectoryRecord, pair_schema,
};
pub use shard::{
    InputDigest, ShardReader, ShardStats, ShardWriter, ShardWriterOptions, clip_count, clip_ids, is_finished,
    pair_kinds, read_clip, read_shard, read_stats, stats_path, write_atomic,
};
pub use status::{InputStatus, StatusRecord, read_status_table, status_schema, write_status_table};
pub use trajectory_bank::{BANK_SCHEMA_NAME, BANK_SCHEMA_VERSION, BankEntry, bank_schema, read_bank, write_bank};

use arrow_schema::{DataType, Field};

/// The field-by-field reference of the shard schema as Markdown (the content of `SCHEMA.md`).
pub fn reference_markdown() -> String {
    let schema = pair_schema();
    let mut out = format!(
        "# Training-pair shard schema `{SCHEMA_NAME}` v{SCHEMA_VERSION}\n\n\
         Generated from `schemas/src/pairs.rs` by `schemas::reference_markdown()`; a test keeps this file in\n\
         sync (regenerate with `UPDATE_SCHEMA_DOC=1 cargo test -p schemas`).\n\n\
         A shard is one Parquet file, one row per source clip. The Parquet key-value metadata holds\n\
         `{SCHEMA_NAME_KEY}` = `{SCHEMA_NAME}` and `{SCHEMA_VERSION_KEY}` = `{SCHEMA_VERSION}`. A shard is finished only\n\
         when its stats marker `<shard>.stats.json` exists; files whose name contains `.tmp-` are\n\
         unfinished and must be ignored. Matrices are row-major; per-frame lists all have `num_frames`\n\
         entries. Each field's text is also in the Arrow field metadata under `{DOC_KEY}`.\n\n\
         | column | type | nullable | meaning |\n|---|---|---|---|\n"
    );
    for field in schema.fields() {
        push_field(&mut out, "", field);
    }
    out.push_str(&format!(
        "\nShards of versions {OLDEST_READABLE_SCHEMA_VERSION} to {SCHEMA_VERSION} are read; columns added since a shard's\n\
         version read as null (v2 added `trajectories[].bank_entry` and the kind `bank`; v3 added `pair_kind`,\n\
         `source_camera`, `target_camera` and the trajectory kind `camera`, and older shards read as monocular\n\
         pairs of single-camera inputs).\n\n\
         # Trajectory bank schema `{BANK_SCHEMA_NAME}` v{BANK_SCHEMA_VERSION}\n\n\
         Generated from `schemas/src/trajectory_bank.rs`. Written by `datagen trajectories collect`, read by the\n\
         `bank` and `mixed` trajectory samplers. One Parquet file, one row per clip window of a source video's\n\
         own camera path; the key-value metadata holds `{SCHEMA_NAME_KEY}` = `{BANK_SCHEMA_NAME}` and\n\
         `{SCHEMA_VERSION_KEY}` = `{BANK_SCHEMA_VERSION}`. Translations are in units of the window's pivot distance R\n\
         (the depth at the first frame's principal point × `pivot_scale`), so paths from scenes of different\n\
         scale compare. Static windows (no motion) and degenerate ones (non-finite poses, no valid depth) are\n\
         not stored.\n\n\
         | column | type | nullable | meaning |\n|---|---|---|---|\n"
    ));
    for field in bank_schema().fields() {
        push_field(&mut out, "", field);
    }
    out
}

fn push_field(out: &mut String, prefix: &str, field: &Field) {
    let name = format!("{prefix}{}", field.name());
    let text = field.metadata().get(DOC_KEY).map(String::as_str).unwrap_or("");
    out.push_str(&format!(
        "| `{name}` | `{}` | {} | {text} |\n",
        type_name(field.data_type()),
        if field.is_nullable() { "yes" } else { "no" }
    ));
    if let DataType::List(item) = field.data_type()
        && let DataType::Struct(children) = item.data_type()
    {
        for child in children {
            push_field(out, &format!("{name}[]."), child);
        }
    }
    if let DataType::Struct(children) = field.data_type() {
        for child in children {
            push_field(out, &format!("{name}."), child);
        }
    }
}

fn type_name(data_type: &DataType) -> String {
    match data_type {
        DataType::List(item) => format!("list<{}>", type_name(item.data_type())),
        DataType::FixedSizeList(item, n) => format!("fixed_size_list<{}, {n}>", type_name(item.data_type())),
        DataType::Struct(_) => "struct".to_owned(),
        DataType::LargeBinary => "large_binary".to_owned(),
        DataType::Utf8 => "string".to_owned(),
        other => other.to_string().to_lowercase(),
    }
}
