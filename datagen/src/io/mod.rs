//! Reading and writing the files a sequence is made of: NumPy arrays, depth as OpenEXR (video and
//! image frames are `foundation`'s), dataset annotations (run-length encoded masks, palette PNGs, boxes), and whole
//! sequence folders in their layouts, including the outputs of the reconstruction tools in use
//! (ViPE, VGGT, COLMAP, GEN3C, depth-only tools), each converted at the door, and synchronised
//! multi-camera scenes: made of them, or as the benchmark datasets ship them (DyCheck, Kubric-4D,
//! ParallelDomain-4D). Every folder layout, single- or multi-camera, is named, recognised and
//! dispatched by one registry ([`layout`]).

pub mod annotations;
pub mod colmap;
pub mod depth_exr;
pub mod depth_only;
pub mod dycheck;
pub mod gen3c;
pub(crate) mod json_fields;
pub mod kubric4d;
pub mod layout;
pub mod multiview;
pub mod npy;
pub mod pardom4d;
pub mod reconstruction;
pub mod rle;
pub mod sequence;
pub mod tool_output;
pub mod vggt;
pub mod vipe;
