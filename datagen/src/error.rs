//! The one error type of the `datagen` library. Every message names the file and, where there is
//! one, the field or parameter at fault, so a user can fix the input without reading code.

use std::path::PathBuf;

/// Everything that can go wrong while reading inputs, generating pairs or writing outputs.
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
    /// A NumPy array (a `.npy` file or a member of an `.npz` archive) is unreadable, or is not
    /// what its header, the archive's directory or the arrays beside it say it is.
    #[error("{path}: {}{reason}", member_prefix(.member.as_deref()))]
    InvalidArray {
        /// The `.npy` or `.npz` file.
        path: PathBuf,
        /// The `.npz` member (`depths.npy`); `None` for a `.npy` file, which is the array.
        member: Option<String>,
        /// What is wrong, in words a user can act on.
        reason: String,
    },
    /// A command-line or configuration parameter has an impossible value.
    #[error("parameter `{name}`: {reason}")]
    InvalidParameter {
        /// The parameter as the user spells it.
        name: String,
        /// Why it is rejected.
        reason: String,
    },
    /// A config file (TOML) does not parse, or holds a value outside its documented range.
    #[error("{path}: key `{key}`: {reason}")]
    Config {
        /// The config file.
        path: PathBuf,
        /// The key as written in TOML, with its tables (`trajectory.azimuth_deg`,
        /// `sources[1].root`).
        key: String,
        /// What is wrong, with the value and its line.
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
    /// Encoding or decoding an image (PNG, JPEG, EXR) failed.
    #[error("{context}: image: {reason}")]
    Image {
        /// What was being encoded or decoded (a file or a field).
        context: String,
        /// The codec's complaint.
        reason: String,
    },
    /// Writing or reading a shard failed at the schema layer.
    #[error(transparent)]
    Schema(#[from] schemas::Error),
    /// Reading or writing a shared file (camera, video, frames, digest) failed.
    #[error(transparent)]
    Foundation(#[from] foundation::Error),
}

/// Result with the library's error type.
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

    /// An [`Error::InvalidArray`] for the `.npy` at `path`, or its `.npz` member `member`.
    pub fn array(path: impl Into<PathBuf>, member: Option<&str>, reason: impl Into<String>) -> Self {
        Self::InvalidArray { path: path.into(), member: member.map(str::to_owned), reason: reason.into() }
    }

    /// An [`Error::InvalidParameter`] for parameter `name`.
    pub fn parameter(name: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::InvalidParameter { name: name.into(), reason: reason.into() }
    }
}

/// `member `NAME`: ` for an [`Error::InvalidArray`] in an archive, nothing for a plain `.npy`.
fn member_prefix(member: Option<&str>) -> String {
    member.map(|m| format!("member `{m}`: ")).unwrap_or_default()
}
