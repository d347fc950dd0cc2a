//! The one error type of the `schemas` crate: every message names the shard file and the field.

use std::path::PathBuf;

/// Failures while writing, reading or validating a shard.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Creating, writing, renaming or reading a file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file involved.
        path: PathBuf,
        /// The operating-system error.
        source: std::io::Error,
    },
    /// The Parquet layer failed (corrupt file, truncated footer, write error).
    #[error("{path}: parquet: {source}")]
    Parquet {
        /// The shard file.
        path: PathBuf,
        /// The Parquet error.
        source: parquet::errors::ParquetError,
    },
    /// Building or reading Arrow arrays failed.
    #[error("{path}: arrow: {source}")]
    Arrow {
        /// The shard file.
        path: PathBuf,
        /// The Arrow error.
        source: arrow_schema::ArrowError,
    },
    /// The file is a Parquet file but not a shard of a schema version this code reads.
    #[error("{path}: field `{field}`: {reason}")]
    SchemaMismatch {
        /// The shard file.
        path: PathBuf,
        /// The column or metadata key at fault.
        field: String,
        /// What was expected and what was found.
        reason: String,
    },
    /// A record handed to the writer is internally inconsistent (a programming error upstream,
    /// reported instead of writing a shard that readers would reject).
    #[error("clip `{clip_id}`: field `{field}`: {reason}")]
    InvalidRecord {
        /// The record's clip id.
        clip_id: String,
        /// The field at fault.
        field: String,
        /// What is inconsistent.
        reason: String,
    },
    /// A stats marker file could not be parsed.
    #[error("{path}: {source}")]
    Json {
        /// The JSON file.
        path: PathBuf,
        /// The parse error.
        source: serde_json::Error,
    },
}

/// Result with this crate's error type.
pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    pub(crate) fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Self::Io { path: path.into(), source }
    }

    pub(crate) fn mismatch(path: impl Into<PathBuf>, field: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::SchemaMismatch { path: path.into(), field: field.into(), reason: reason.into() }
    }
}
