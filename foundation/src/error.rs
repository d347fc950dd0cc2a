//! The one error type of the `foundation` crate: what reading and writing the shared files can
//! go wrong with, each message naming the file and, where there is one, the field.

use std::path::PathBuf;

/// Everything that can go wrong in the shared foundations.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file could not be opened, read, created or renamed.
    #[error("{path}: {error}")]
    Io {
        /// The file or folder involved.
        path: PathBuf,
        /// The operating-system error. Part of the message and deliberately not the error's
        /// `source()`: a chain printed whole (anyhow's `{:#}`) would say it twice.
        error: std::io::Error,
    },
    /// An input file exists but its content is wrong: bad shape, bad value, truncated data.
    #[error("{path}: field `{field}`: {reason}")]
    InvalidInput {
        /// The file at fault.
        path: PathBuf,
        /// The array, key or column within it.
        field: String,
        /// What is wrong, in words a user can act on.
        reason: String,
    },
    /// A parameter has an impossible value.
    #[error("parameter `{name}`: {reason}")]
    InvalidParameter {
        /// The parameter as the user spells it.
        name: String,
        /// Why it is rejected.
        reason: String,
    },
    /// FFmpeg failed to open, decode or encode a video.
    #[error("{path}: video: {reason}")]
    Video {
        /// The video file.
        path: PathBuf,
        /// FFmpeg's complaint, with context.
        reason: String,
    },
    /// Encoding or decoding an image failed.
    #[error("{context}: image: {reason}")]
    Image {
        /// What was being encoded or decoded (a file or a field).
        context: String,
        /// The codec's complaint.
        reason: String,
    },
}

/// Result with the crate's error type.
pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    /// An [`Error::Io`] for `path`.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Self::Io { path: path.into(), error: source }
    }

    /// An [`Error::InvalidInput`] for `field` of `path`.
    pub fn invalid(path: impl Into<PathBuf>, field: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::InvalidInput { path: path.into(), field: field.into(), reason: reason.into() }
    }

    /// An [`Error::InvalidParameter`] for parameter `name`.
    pub fn parameter(name: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::InvalidParameter { name: name.into(), reason: reason.into() }
    }
}
