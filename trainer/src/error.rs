//! The one error type of the `trainer` library. Messages name the file, config field or tensor at
//! fault with what was expected and what was found, so a bad checkpoint or input is fixable
//! without a debugger (and never surfaces as a panic deep inside libtorch).

use std::path::PathBuf;

/// Everything that can go wrong in the model, weights, data or training code.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file could not be read or written.
    #[error("{path}: {error}")]
    Io {
        /// The file involved.
        path: PathBuf,
        /// The operating-system error. In the message, and not exposed as the error's source,
        /// so that `{:#}` chains print it once.
        error: std::io::Error,
    },
    /// A configuration (diffusers `config.json`, scheduler config, training TOML) is invalid.
    #[error("{source_name}: field `{field}`: {reason}")]
    InvalidConfig {
        /// The config file or preset name.
        source_name: String,
        /// The offending field, spelled as in the file.
        field: String,
        /// What is wrong.
        reason: String,
    },
    /// A tensor has the wrong shape.
    #[error("tensor `{tensor}`: expected shape {expected}, got {actual:?}")]
    Shape {
        /// The tensor's name (argument or checkpoint key).
        tensor: String,
        /// The expected shape, in words or as a list.
        expected: String,
        /// The actual shape.
        actual: Vec<i64>,
    },
    /// A tensor has the wrong dtype or sits on the wrong device.
    #[error("tensor `{tensor}`: expected {expected}, got {actual}")]
    DtypeDevice {
        /// The tensor's name.
        tensor: String,
        /// The expected dtype/device.
        expected: String,
        /// The actual dtype/device.
        actual: String,
    },
    /// A checkpoint lacks a tensor the model needs.
    #[error("{path}: missing tensor `{tensor}` (expected shape {expected:?})")]
    MissingTensor {
        /// The checkpoint file or index.
        path: PathBuf,
        /// The checkpoint key.
        tensor: String,
        /// The shape the model expects.
        expected: Vec<i64>,
    },
    /// A checkpoint holds tensors the model does not have (e.g. weights of another config).
    #[error("{path}: {count} unexpected tensors, e.g. `{example}`")]
    UnexpectedTensors {
        /// The checkpoint file or index.
        path: PathBuf,
        /// How many.
        count: usize,
        /// One of them.
        example: String,
    },
    /// A tensor holds NaN or infinite values where only finite ones mean anything: a weight, a
    /// LoRA factor or a text embedding read from a file, or a sampled video.
    #[error("tensor `{tensor}`: {reason}")]
    NonFinite {
        /// The tensor's name and the file it came from (`encoder_hidden_states` in `prompt.safetensors`).
        tensor: String,
        /// How many values, where the first is, and what follows.
        reason: String,
    },
    /// An input file (a frame, a video, a shard folder) does not fit what it is used for.
    #[error("{path}: {what}: {reason}")]
    InvalidInput {
        /// The file or folder at fault.
        path: PathBuf,
        /// What in it (`frame size`, `frame count`).
        what: String,
        /// What was expected and found.
        reason: String,
    },
    /// A function argument is out of range or inconsistent.
    #[error("argument `{name}`: {reason}")]
    InvalidArgument {
        /// The argument or flag name.
        name: String,
        /// What is wrong.
        reason: String,
    },
    /// A launcher variable (torchrun, Slurm or set by hand) is missing or inconsistent.
    #[error("launcher variable `{variable}`: {reason}")]
    Launcher {
        /// The environment variable.
        variable: String,
        /// What is wrong.
        reason: String,
    },
    /// A multi-process job failed: a collective, the rendezvous, or ranks that disagree.
    #[error("rank {rank} of {world_size}: {what}: {reason}")]
    Distributed {
        /// This process's rank.
        rank: usize,
        /// Number of ranks.
        world_size: usize,
        /// The operation (`all-reduce #12 (gradients)`, `rendezvous`, `config check`).
        what: String,
        /// What happened, naming the ranks involved.
        reason: String,
    },
    /// A checkpoint could not be written (disk full, quota, I/O error). The run stops here: its
    /// earlier checkpoints are untouched and `--resume` continues from the newest of them.
    #[error(
        "checkpoint of step {step} could not be written: {reason}; the run stopped, earlier checkpoints are \
         untouched ({kept})"
    )]
    CheckpointWrite {
        /// The step whose checkpoint failed.
        step: u64,
        /// What failed, naming the file.
        reason: String,
        /// The newest complete checkpoint left, in words.
        kept: String,
    },
    /// A safetensors file is malformed.
    #[error("{path}: safetensors: {reason}")]
    Safetensors {
        /// The file.
        path: PathBuf,
        /// The parser's complaint.
        reason: String,
    },
    /// Reading or writing a shared file (video, frames, digest) failed.
    #[error(transparent)]
    Foundation(#[from] foundation::Error),
    /// A sequence could not be read or its pairs made (the `datagen` readers and generator).
    #[error(transparent)]
    Datagen(#[from] datagen::api::Error),
    /// A training shard or other `schemas` file could not be read or written.
    #[error(transparent)]
    Schemas(#[from] schemas::Error),
    /// libtorch reported an error.
    #[error(transparent)]
    Tch(#[from] tch::TchError),
}

/// Result with this crate's error type.
pub type Result<T, E = Error> = std::result::Result<T, E>;
