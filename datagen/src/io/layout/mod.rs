//! The layout registry: every folder layout the toolkit reads, single-camera (a video and its
//! reconstruction) and multi-camera (a synchronised scene), under one name set ([`LayoutName`],
//! the `--layout` flag of every command that reads a folder). One file per layout the toolkit
//! defines here (`cog_nvs`, `megasam`, `generic`, `depth_only`: how it is recognised and read);
//! the tools' and datasets' formats keep their readers beside this folder (`io::vipe`,
//! `io::vggt`, `io::colmap`, `io::gen3c`, `io::dycheck`, `io::kubric4d`, `io::pardom4d`,
//! `io::multiview`). [`sequence_layout`] recognises and dispatches the single-camera layouts,
//! [`scene_layout`] the multi-camera ones and says which a folder is ([`folder_layout`]).

pub mod cog_nvs;
pub mod depth_only;
pub mod generic;
pub mod megasam;
pub mod name;
pub mod scene_layout;
pub mod sequence_layout;

pub use name::{Cameras, LayoutName, MultiViewLayoutName};
pub use scene_layout::{FolderLayout, detect_multiview_layout, folder_layout, read_camera_sequence, read_multiview_as};
pub use sequence_layout::{Layout, ReadOptions, detect_layout, has_layout_files, layout_named, layout_of};
