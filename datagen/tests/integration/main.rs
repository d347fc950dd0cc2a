//! The `datagen` integration tests: one binary, a module per feature.

mod build;
mod corpus;
mod sequence;
mod synth;
mod validate;
