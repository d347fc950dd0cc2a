//! Reading and writing the files a sequence is made of: NumPy arrays, depth as OpenEXR, video
//! through FFmpeg, dataset annotations (run-length encoded masks, palette PNGs, boxes), and whole
//! sequence folders in their three layouts, and synchronised multi-camera scenes made of them.

pub mod annotations;
pub mod depth_exr;
pub mod multiview;
pub mod npy;
pub mod rle;
pub mod sequence;
pub mod video;
