//! Frames as image files: a list of PNG or JPEG files decoded as one video's RGB frames.

use std::path::PathBuf;

use image::RgbImage;
use rayon::prelude::*;

use crate::error::{Error, Result};

/// Decodes image files (PNG, JPEG) as RGB frames, in parallel, in the given order.
/// Every frame must have the first one's size: the error names the first file that differs and
/// both sizes (checked from the image headers, before anything is decoded). Shared by the generic
/// layout's `frames/` and the corpus image datasets (DAVIS, YouTube-VOS, TAO).
pub fn read_frames(paths: &[PathBuf]) -> Result<Vec<RgbImage>> {
    let sizes = paths
        .par_iter()
        .map(|p| image::image_dimensions(p).map_err(|e| Error::invalid(p, "frame", format!("unreadable image: {e}"))))
        .collect::<Result<Vec<_>>>()?;
    if let (Some(first), Some(&(width, height))) = (paths.first(), sizes.first())
        && let Some(i) = sizes.iter().position(|&size| size != (width, height))
    {
        let (found_w, found_h) = sizes[i];
        return Err(Error::invalid(
            &paths[i],
            "frame",
            format!(
                "size {found_w}x{found_h} differs from the first frame's {width}x{height} ({}): every frame of a sequence must have one size",
                first.display()
            ),
        ));
    }
    paths
        .par_iter()
        .map(|p| {
            image::open(p)
                .map(|i| i.to_rgb8())
                .map_err(|e| Error::invalid(p, "frame", format!("unreadable image: {e}")))
        })
        .collect()
}
