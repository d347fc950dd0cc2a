//! Training pairs for one sequence: clip windows and their pivot distance ([`clip`]), the
//! trajectory bank of real camera motion ([`trajectory_bank`]), novel camera paths drawn from the
//! spherical or the bank sampler ([`trajectory`]), depth noise on dynamic objects
//! ([`depth_noise`]), the fused static background ([`static_background`]), and the pair generator
//! that turns a sequence into shard records and renders it along a path ([`generator`]);
//! `datagen pairs` as one call ([`job`]); and multi-view pairs of synchronised multi-camera
//! scenes, one real camera rendered into another ([`multiview`]), made with a scene's monocular
//! pairs by [`scene`].

pub mod clip;
pub mod depth_noise;
mod encode;
pub mod generator;
pub mod job;
pub mod multiview;
pub mod scene;
pub mod static_background;
pub mod trajectory;
pub mod trajectory_bank;
