//! The `datagen` integration tests: one binary, a module per feature.

mod build;
mod corpus;
mod corpus_build;
mod depth_noise;
mod geometry;
mod inspect;
mod pairs;
mod sequence;
mod static_background;
mod synth;
mod validate;
