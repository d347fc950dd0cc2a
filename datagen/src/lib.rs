//! `datagen`: turns videos plus their 3D reconstructions into self-supervised CogNVS training
//! pairs: sampled novel camera paths, exact co-visibility masks from occlusion tests against each
//! frame's depth map lifted to a mesh, novel-view renders, and sharded Parquet output (`schemas`).
//!
//! The modules are grouped by layer, from the bottom, on the `foundation` crate (cameras, depth
//! maps, video and frames): [`error`] and [`config_file`]; [`io`] (file formats, the layout
//! registry, sequence folders and multi-camera scenes); [`geometry`] (depth meshes,
//! co-visibility, rendering); [`pairs`] (clips, trajectories, the pair generator); [`synth`]
//! (synthetic scenes with exact answers, for tests and benchmarks); [`corpus`] (whole dataset
//! trees); [`inspect`] (looking at the shards); [`api`], the one door for other crates (the
//! trainer) to what they use of these; [`cli`] (the commands: their arguments, the
//! requests they make, what they print). A module uses its own layer and those below, never one
//! above (`docs/ARCHITECTURE.md` states the layers; `scripts/check_module_cycles.py` checks
//! them). The `datagen` binary only parses the arguments and runs a [`cli`] command.

pub mod api;
pub mod cli;
pub mod config_file;
pub mod corpus;
pub mod error;
pub mod geometry;
pub mod inspect;
pub mod io;
pub mod pairs;
pub mod synth;
pub mod synth_layouts;

pub use error::{Error, Result};
