//! The `datagen` integration tests: one binary, a module per feature.

mod build;
mod corpus;
mod corpus_build;
mod depth_noise;
mod geometry;
mod hostile_configs;
mod hostile_corpus;
mod hostile_files;
mod hostile_sequences;
mod inspect;
mod multiview;
mod multiview_datasets;
mod novel_view;
mod pairs;
mod pairs_golden;
mod reconstruction_check;
mod render;
mod report;
mod sequence;
mod static_background;
mod synth;
mod tool_layouts;
mod trajectory_bank;
mod validate;
mod view;
