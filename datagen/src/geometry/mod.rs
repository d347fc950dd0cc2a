//! The geometry of one frame (on `foundation`'s pinhole camera and depth map): the depth map
//! lifted to a mesh, and the exact
//! co-visibility masks and novel-view renders computed against it; and the multi-frame
//! consistency check of a whole reconstruction ([`consistency`], `datagen check`).

pub mod consistency;
pub mod covisibility;
pub mod depth_mesh;
pub mod mesh_view;
pub mod ray_triangle;
pub mod render;
