//! The geometry of one frame: the pinhole camera and its pose and K checks ([`camera`], which the
//! sequence readers in [`crate::io`] also use), the depth map lifted to a mesh, and the exact
//! co-visibility masks and novel-view renders computed against it; and the multi-frame
//! consistency check of a whole reconstruction ([`consistency`], `datagen check`).

pub mod camera;
pub mod consistency;
pub mod covisibility;
pub mod depth_mesh;
pub mod mesh_view;
pub mod ray_triangle;
pub mod render;
