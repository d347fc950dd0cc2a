//! Corpus building (DESIGN §3, §5): crawling dataset trees, turning their annotations into
//! dynamic-object masks, and splitting the inputs across workers.

pub mod build;
pub mod crawl;
pub mod harvest;
pub mod input;
pub mod partition;
pub mod synthetic;
pub mod validate;
