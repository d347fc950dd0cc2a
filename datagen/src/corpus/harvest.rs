//! The trajectory bank of a whole corpus: every video a corpus config's sources crawl to is read
//! as the build reads it and cut into clip windows, and each window's camera motion becomes a bank
//! entry ([`crate::pairs::trajectory_bank::collect_from_sequence`]); a multi-camera scene gives
//! each camera's motion. `datagen trajectories collect
//! --config corpus.toml` runs it.

use super::build::BuildConfig;
use super::crawl::{FrameSource, crawl_all};
use super::input::load_entry_as;
use crate::error::Result;
use crate::io::layout::{LayoutName, read_multiview_as};
use crate::io::sequence::Sequence;
use crate::pairs::trajectory_bank::{CollectSummary, collect_from_sequence};

/// Harvests the bank of a whole corpus config (`datagen build`'s TOML): every video its sources
/// crawl to, cut into the windows of its `[pairs.clip]`, with its `[pairs.trajectory]`
/// `pivot_scale`. An input that cannot be read is recorded in `failed_inputs` and skipped.
pub fn collect_from_corpus(config: &BuildConfig) -> Result<CollectSummary> {
    let mut summary = CollectSummary::default();
    for entry in crawl_all(&config.sources)? {
        if let Some(reason) = &entry.crawl_error {
            summary.failed_inputs.push((entry.key(), reason.clone()));
            continue;
        }
        // A multi-camera scene gives every camera's own motion.
        let sequences = match &entry.frames {
            FrameSource::MultiView(dir) => {
                read_multiview_as(dir, config.layout.and_then(LayoutName::multiview)).map(|scene| {
                    let scene_id = &entry.video_id;
                    let cameras = scene.cameras.into_iter();
                    cameras.map(|c| Sequence { source_id: format!("{scene_id}/{}", c.id), ..c.sequence }).collect()
                })
            }
            _ => load_entry_as(&entry, config.layout).map(|sequence| vec![sequence]),
        };
        match sequences {
            Ok(sequences) => {
                for sequence in &sequences {
                    collect_from_sequence(
                        sequence,
                        entry.dataset.name(),
                        &config.pairs.clip,
                        config.pairs.trajectory.pivot_scale,
                        &mut summary,
                    );
                }
            }
            Err(error) => summary.failed_inputs.push((entry.key(), error.to_string())),
        }
    }
    Ok(summary)
}
