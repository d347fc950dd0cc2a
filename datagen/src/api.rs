//! The one door into `datagen` for other crates (the trainer): read a sequence folder or a
//! multi-camera scene (by layout name or detected), make a sequence's training pairs (the
//! `datagen pairs` job), read a trajectory file and render a sequence along it (`datagen render`),
//! DyCheck's correspondence files and the depth EXR codec, with the types these take and return
//! and [`Error`]. Everything here is a name for what the modules below already do, so the trainer
//! and the `datagen` binary run the same code; `scripts/check_module_cycles.py` (from
//! `docs/ARCHITECTURE.md`'s layer block) refuses a trainer path into `datagen` that is not under
//! `datagen::api`.

use std::borrow::Cow;
use std::path::Path;

pub use glam::DMat4;
pub use schemas::InputDigest;

pub use crate::error::{Error, Result};
pub use crate::io::depth_exr::encode_depth_exr;
pub use crate::io::dycheck::{FrameCorrespondence, correspondence_file_name, read_correspondence};
pub use crate::io::layout::{LayoutName, ReadOptions};
pub use crate::io::multiview::{CameraView, MultiViewScene};
pub use crate::io::sequence::Sequence;
pub use crate::pairs::clip::ClipConfig;
pub use crate::pairs::generator::{PairsConfig, RenderSummary};
pub use crate::pairs::job::{PairsJob, PairsReport, make_pairs};

/// Reads one camera's sequence from `dir` in layout `layout` (None: a sequence folder, detected
/// from its files), as `datagen render --layout` reads it: a scene layout (DyCheck, ...) gives
/// the scene's input camera, or an error naming the folder and the layout where it has none.
pub fn read_sequence(dir: &Path, layout: Option<LayoutName>) -> Result<Sequence> {
    Ok(crate::io::layout::read_camera_sequence(dir, layout, &ReadOptions::default())?.0)
}

/// Reads the multi-camera scene in `dir` in layout `layout` (None: detected from its files); a
/// single-camera layout name is refused, naming the folder.
pub fn read_multiview(dir: &Path, layout: Option<LayoutName>) -> Result<MultiViewScene> {
    let layout = layout
        .map(|name| {
            name.multiview().ok_or_else(|| Error::InvalidInput {
                path: dir.to_path_buf(),
                field: "layout".to_string(),
                reason: format!("`{name}` is a single-camera layout; a multi-camera scene is needed here"),
            })
        })
        .transpose()?;
    crate::io::layout::read_multiview_as(dir, layout)
}

/// The `world_from_camera` pose of every frame of `sequence` along the trajectory file `path`
/// (`.npy`, `.json` or the public `trajs/*.txt`; see
/// [`crate::pairs::trajectory::read_trajectory_file`]).
pub fn read_trajectory(path: &Path, sequence: &Sequence) -> Result<Vec<DMat4>> {
    crate::pairs::trajectory::read_trajectory_file(path, sequence.len(), &sequence.cameras, &sequence.depth[0])
}

/// [`make_pairs`] on a sequence the caller has read already (`input` names the folder and its
/// content hash for the shard's stats marker): the same pairs and shard, without reading again.
pub fn make_pairs_of(job: &PairsJob, sequence: &Sequence, input: InputDigest) -> Result<PairsReport> {
    crate::pairs::job::make_pairs_from(job, Cow::Borrowed(sequence), input)
}

/// `datagen render` along poses read already ([`read_trajectory`]): every frame of `sequence`
/// seen from `poses` into `out/frames/`, `out/holes/` and `out/render.mp4`, holes filled from the
/// stacked static background with `stacking`.
pub use crate::pairs::generator::render_sequence_along as render_sequence;
