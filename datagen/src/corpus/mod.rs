//! Corpus building: finding the videos of dataset trees ([`crawl`]), reading each with its
//! reconstruction and annotation masks ([`input`]), splitting the inputs across workers
//! ([`partition`]), the resumable build ([`build`]) with its reconstruction filter ([`quality`]),
//! checking its output ([`validate`]), synthetic
//! corpora in every layout ([`synthetic`]), and the trajectory bank of a whole corpus
//! ([`harvest`]).

pub mod build;
pub mod crawl;
pub mod harvest;
pub mod input;
pub mod partition;
pub mod quality;
pub mod synthetic;
pub mod validate;
