//! A sequence (a video plus its reconstruction: frames, frame-resolution depth, per-frame cameras
//! and optional dynamic masks), and reading one from a folder in any single-camera layout of the
//! registry ([`crate::io::layout`]: cog-nvs, MegaSAM, generic, and the reconstruction tools'
//! outputs ViPE, VGGT, COLMAP, GEN3C and depth-only), each checked and assembled alike
//! ([`crate::io::reconstruction`]).
//!
//! The layout is detected from the files ([`detect_layout`]) or named ([`LayoutName`], the
//! `--layout` flag); a folder that matches several is an error listing what was found. A
//! multi-camera layout is not a sequence folder's: [`crate::io::layout::read_camera_sequence`]
//! reads a scene's input camera. Optional `masks/*.png` (palette or greyscale ids: 0 static, >0
//! object, 255 void) in any layout. Every check failure names the file and the field.

use std::path::{Path, PathBuf};

use image::{GrayImage, RgbImage};
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::io::reconstruction::{assemble, with_extension};
use foundation::camera::{PinholeCamera, checked_intrinsics, checked_pose};
use foundation::depth::DepthMap;

// Where these lived before the registry split them out; kept so callers' paths stay valid.
pub use crate::io::layout::generic::frames_video;
pub use crate::io::layout::{Layout, LayoutName, ReadOptions, detect_layout, has_layout_files, layout_named};
pub use crate::io::reconstruction::{
    DepthStack, FALLBACK_FOCAL_PX, read_depth_stack, read_exr_folder, resample_nearest,
};

/// A video with its reconstruction, all at the video's resolution.
#[derive(Debug, Clone)]
pub struct Sequence {
    /// Id of the sequence (its folder name).
    pub source_id: String,
    /// The folder it was read from.
    pub path: PathBuf,
    /// Frame rate (0 if unknown).
    pub fps: f64,
    /// RGB frames.
    pub frames: Vec<RgbImage>,
    /// z-depth per frame at frame resolution.
    pub depth: Vec<DepthMap>,
    /// Camera per frame.
    pub cameras: Vec<PinholeCamera>,
    /// Dynamic-object id masks per frame, if the folder has them.
    pub dynamic_masks: Option<Vec<GrayImage>>,
    /// A second, more accurate depth per frame (LiDAR, a monocular estimator) for measured depth
    /// noise, if the user gave one ([`Sequence::load_second_depth`]).
    pub second_depth: Option<Vec<DepthMap>>,
}

impl Sequence {
    /// Reads a second depth source (a folder of `*.exr` or an `(N, H, W)` `.npy`, one map per
    /// frame), resampled to the frames' size.
    pub fn load_second_depth(&mut self, path: &Path) -> Result<()> {
        let (width, height) = self.size();
        self.second_depth = Some(read_depth_stack(path, self.len(), width, height)?);
        Ok(())
    }

    /// The sequence a stored clip was cut from, for its frames: decoded frames, depth and
    /// dynamic masks, and its cameras. Errors name the clip and the field.
    pub fn from_clip(record: &schemas::ClipRecord) -> Result<Self> {
        let id = &record.clip_id;
        let image = |bytes: &[u8], field: String| {
            image::load_from_memory_with_format(bytes, image::ImageFormat::Png)
                .map_err(|e| Error::Image { context: format!("{id}: {field}"), reason: e.to_string() })
        };
        let frames = record
            .frames
            .par_iter()
            .enumerate()
            .map(|(i, png)| Ok(image(png, format!("frames[{i}]"))?.to_rgb8()))
            .collect::<Result<Vec<_>>>()?;
        let depth = record
            .depth
            .par_iter()
            .enumerate()
            .map(|(i, exr)| {
                let (width, height) = (record.width as usize, record.height as usize);
                crate::io::depth_exr::decode_depth_exr_of_size(exr, &format!("{id}: depth[{i}]"), width, height)
            })
            .collect::<Result<Vec<_>>>()?;
        let dynamic_masks = match &record.dynamic_mask {
            Some(masks) => Some(
                masks
                    .par_iter()
                    .enumerate()
                    .map(|(i, png)| Ok(image(png, format!("dynamic_mask[{i}]"))?.to_luma8()))
                    .collect::<Result<Vec<_>>>()?,
            ),
            None => None,
        };
        // Stored cameras pass the same checks as read ones: a shard is user input too.
        let clip = Path::new(id);
        let cameras = record
            .intrinsics
            .iter()
            .zip(&record.world_from_camera)
            .enumerate()
            .map(|(i, (k, pose))| {
                Ok(PinholeCamera {
                    width: record.width,
                    height: record.height,
                    intrinsics: checked_intrinsics(clip, &format!("intrinsics[{i}]"), k)?,
                    world_from_camera: checked_pose(clip, &format!("world_from_camera[{i}]"), pose)?,
                })
            })
            .collect::<Result<_>>()?;
        Ok(Self {
            source_id: record.source_id.clone(),
            path: PathBuf::from(&record.source_path),
            fps: record.fps,
            frames,
            depth,
            cameras,
            dynamic_masks,
            second_depth: None,
        })
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// Whether the sequence has no frames (never true for a sequence returned by a reader).
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Frame width and height.
    pub fn size(&self) -> (u32, u32) {
        self.frames[0].dimensions()
    }
}

/// Reads the sequence folder `dir` in whichever layout it is.
pub fn read_sequence(dir: &Path) -> Result<Sequence> {
    read_sequence_as(dir, None)
}

/// Reads the sequence folder `dir` in layout `layout`, or the detected one when `None`, with the
/// default [`ReadOptions`].
pub fn read_sequence_as(dir: &Path, layout: Option<LayoutName>) -> Result<Sequence> {
    read_sequence_with(dir, layout, &ReadOptions::default())
}

/// Reads the sequence folder `dir` in layout `layout` (or the detected one) with `options`.
pub fn read_sequence_with(dir: &Path, layout: Option<LayoutName>, options: &ReadOptions) -> Result<Sequence> {
    read_sequence_in(dir, &crate::io::layout::layout_of(dir, layout)?, options)
}

/// Reads the sequence folder `dir` in the layout `layout` found in it, with `options`.
pub fn read_sequence_in(dir: &Path, layout: &Layout, options: &ReadOptions) -> Result<Sequence> {
    // A ViPE output folder holds its videos by name: the video's name is the sequence's id.
    let source_id = match layout {
        Layout::Vipe(artifact) => artifact.name.clone(),
        _ => dir.file_name().unwrap_or_default().to_string_lossy().into_owned(),
    };
    let (fps, frames, depth, cameras) = layout.read(dir, options)?;
    let dynamic_masks = read_masks(dir, &frames)?;
    Ok(Sequence { source_id, path: dir.to_owned(), fps, frames, depth, cameras, dynamic_masks, second_depth: None })
}

/// Reads the reconstruction at `reconstruction` (a folder in any single-camera layout, a MegaSAM
/// `*_sgd_cvd_hr.npz`, or a file of a ViPE output naming its video) for frames decoded elsewhere
/// (a dataset's video or JPEG folder).
pub fn read_with_frames(
    source_id: &str,
    reconstruction: &Path,
    fps: f64,
    frames: Vec<RgbImage>,
    frames_path: &Path,
) -> Result<Sequence> {
    read_with_frames_as(source_id, reconstruction, None, fps, frames, frames_path)
}

/// [`read_with_frames`] with the reconstruction read in `layout` (detected when `None`).
pub fn read_with_frames_as(
    source_id: &str,
    reconstruction: &Path,
    layout: Option<LayoutName>,
    fps: f64,
    frames: Vec<RgbImage>,
    frames_path: &Path,
) -> Result<Sequence> {
    // A file is a ViPE output's (naming its video) or else a MegaSAM archive.
    let layout = if reconstruction.is_file() && crate::io::vipe::vipe_artifact_of_file(reconstruction).is_none() {
        Layout::MegaSam(reconstruction.to_owned())
    } else {
        crate::io::layout::layout_of(reconstruction, layout)?
    };
    let parts = layout.reconstruction(reconstruction)?;
    let (fps, frames, depth, cameras) = assemble(fps, frames, frames_path, parts)?;
    let path = reconstruction.to_owned();
    Ok(Sequence {
        source_id: source_id.to_owned(),
        path,
        fps,
        frames,
        depth,
        cameras,
        dynamic_masks: None,
        second_depth: None,
    })
}

fn read_masks(dir: &Path, frames: &[RgbImage]) -> Result<Option<Vec<GrayImage>>> {
    let masks_dir = dir.join("masks");
    if !masks_dir.is_dir() {
        return Ok(None);
    }
    let files = with_extension(&masks_dir, &["png"])?;
    if files.len() != frames.len() {
        return Err(Error::invalid(&masks_dir, "masks", format!("{} masks for {} frames", files.len(), frames.len())));
    }
    let (width, height) = frames[0].dimensions();
    files
        .par_iter()
        .map(|path| {
            let mask = crate::io::annotations::read_id_png(path)?;
            Ok(if mask.dimensions() == (width, height) {
                mask
            } else {
                image::imageops::resize(&mask, width, height, image::imageops::FilterType::Nearest)
            })
        })
        .collect::<Result<Vec<_>>>()
        .map(Some)
}
