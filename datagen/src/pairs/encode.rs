//! PNG encoding of the images a shard record holds (frames, conditionings, masks), shared by the
//! monocular and the multi-view pair generators.

use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{EncodableLayout, GrayImage, ImageEncoder};

/// PNG bytes of an image, fast deflate and one fixed filter instead of the default per-row choice
/// among all five: on the benchmark clip's frames and masks (png 0.18, fast deflate), Paeth encodes
/// colour frames faster than the adaptive choice and no larger, and Up encodes masks several times
/// faster for slightly larger files.
pub(crate) fn png<P: image::PixelWithColorType>(
    image: &image::ImageBuffer<P, Vec<P::Subpixel>>,
    filter: FilterType,
) -> Vec<u8>
where
    [P::Subpixel]: EncodableLayout,
{
    let mut bytes = Vec::new();
    PngEncoder::new_with_quality(&mut bytes, CompressionType::Fast, filter)
        .write_image(image.as_raw().as_bytes(), image.width(), image.height(), P::COLOR_TYPE)
        .expect("PNG encoding to memory");
    bytes
}

/// PNG of a co-visibility mask (255 = co-visible), row-major like the frame.
pub(crate) fn mask_png(mask: &[bool], width: u32, height: u32) -> Vec<u8> {
    let pixels = mask.iter().map(|&m| if m { 255 } else { 0 }).collect();
    png(&GrayImage::from_raw(width, height, pixels).expect("mask sized to the frame"), FilterType::Up)
}
