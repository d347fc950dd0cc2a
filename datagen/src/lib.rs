//! `datagen`: turns videos plus their 3D reconstructions into self-supervised CogNVS training
//! pairs (DESIGN §1, §4): sampled novel camera paths, exact co-visibility masks from depth-mesh
//! BVH occlusion tests, novel-view renders, and sharded Parquet output (`schemas`).
//!
//! Modules are named after the method's components; the `datagen` binary is a thin layer over them.

pub mod camera;
pub mod clip;
pub mod config_file;
pub mod contact_sheet;
pub mod corpus;
pub mod covisibility;
pub mod depth_exr;
pub mod depth_mesh;
pub mod depth_noise;
pub mod error;
pub mod inspect;
pub mod mesh_view;
pub mod npy;
pub mod pairs;
pub mod render;
pub mod report;
pub mod sequence;
pub mod static_background;
pub mod synth;
pub mod trajectory;
pub mod trajectory_bank;
pub mod video;

pub use error::{Error, Result};
