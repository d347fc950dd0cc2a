//! `datagen`: turns videos plus their 3D reconstructions into self-supervised CogNVS training
//! pairs: sampled novel camera paths, exact co-visibility masks from occlusion tests against each
//! frame's depth map lifted to a mesh, novel-view renders, and sharded Parquet output (`schemas`).
//!
//! The modules are grouped by layer, from the bottom: [`error`] and [`config_file`]; [`io`] (file
//! formats and sequence folders); [`geometry`] (cameras, depth meshes, co-visibility, rendering);
//! [`pairs`] (clips, trajectories, the pair generator); [`corpus`] (whole dataset trees);
//! [`inspect`] (looking at the shards). A module uses its own layer and those below, never one
//! above; [`synth`] is a tool beside them (synthetic scenes with exact answers, for tests and
//! benchmarks). The `datagen` binary is a thin layer over them.

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
