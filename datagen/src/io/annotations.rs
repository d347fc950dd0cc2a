//! Dynamic-object masks from dataset annotations: SA-V RLE masklets, YouTube-VOS and
//! DAVIS palette PNGs, TAO boxes. All become per-frame id masks: 0 static, 1..=254 object, 255 void.
//!
//! Annotations are sparse in time (SA-V every 4th frame, YouTube-VOS train every 5th, TAO every
//! 30th). A frame between two annotated frames gets the **union** of their masks (the earlier
//! frame's id wins where both have one): a moving object lies, roughly, within the union of where
//! it was just before and just after, and treating slightly too much as dynamic (depth noise on
//! a few static pixels) is the safe error. Frames after the last annotation repeat it; frames
//! before the first take it too. TAO boxes are interpolated linearly per track instead.

use std::path::Path;

use image::GrayImage;
use serde::Deserialize;

use super::rle::CocoRle;
use crate::error::{Error, Result};

/// Largest object id a mask can hold; 255 means void.
pub const MAX_OBJECT_ID: u8 = 254;
/// Void label in the mask convention.
pub const VOID: u8 = 255;

/// Reads a mask PNG as ids: palette indices for indexed PNGs (YouTube-VOS, DAVIS), grey values for
/// greyscale ones. Any other colour type is an error naming the file.
pub fn read_id_png(path: &Path) -> Result<GrayImage> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
    decoder.set_transformations(png::Transformations::IDENTITY);
    let bad = |reason: String| Error::invalid(path, "mask", reason);
    let mut reader = decoder.read_info().map_err(|e| bad(format!("unreadable PNG: {e}")))?;
    let mut buffer = vec![0; reader.output_buffer_size().ok_or_else(|| bad("PNG too large".into()))?];
    let info = reader.next_frame(&mut buffer).map_err(|e| bad(format!("unreadable PNG: {e}")))?;
    let (width, height) = (info.width as usize, info.height as usize);
    let bits = match (info.color_type, info.bit_depth) {
        (png::ColorType::Indexed | png::ColorType::Grayscale, depth) => depth as usize,
        (other, depth) => {
            return Err(bad(format!("expected an indexed or greyscale PNG, found {other:?} {depth:?}-bit")));
        }
    };
    if bits == 16 {
        return Err(bad("16-bit greyscale masks are not supported; ids are 8-bit".into()));
    }
    let per_byte = 8 / bits;
    let mask = ((1u16 << bits) - 1) as u8;
    let mut ids = Vec::with_capacity(width * height);
    for row in buffer.chunks(info.line_size).take(height) {
        if bits == 8 {
            // One id per byte (most masks): the row as it is, without the per-pixel unpacking.
            ids.extend_from_slice(&row[..width]);
            continue;
        }
        for x in 0..width {
            let byte = row[x / per_byte];
            let shift = 8 - bits * (x % per_byte + 1);
            ids.push((byte >> shift) & mask);
        }
    }
    Ok(GrayImage::from_raw(width as u32, height as u32, ids).expect("sized above"))
}

/// Fills the masks of unannotated frames from their annotated neighbours (see module docs).
/// `annotated[i]` is the mask of frame `i` if it has one. Returns `None` if no frame has one.
pub fn fill_between_annotations(annotated: Vec<Option<GrayImage>>) -> Option<Vec<GrayImage>> {
    let known: Vec<usize> = annotated.iter().enumerate().filter_map(|(i, m)| m.as_ref().map(|_| i)).collect();
    let (&first, &last) = (known.first()?, known.last()?);
    let mut filled = Vec::with_capacity(annotated.len());
    for frame in 0..annotated.len() {
        let mask = if let Some(mask) = &annotated[frame] {
            mask.clone()
        } else if frame < first {
            annotated[first].clone().expect("known")
        } else if frame > last {
            annotated[last].clone().expect("known")
        } else {
            let before = known[known.partition_point(|&k| k < frame) - 1];
            let after = known[known.partition_point(|&k| k < frame)];
            let (a, b) = (annotated[before].as_ref().expect("known"), annotated[after].as_ref().expect("known"));
            let mut union = a.clone();
            for (out, &other) in union.iter_mut().zip(b.as_raw()) {
                if *out == 0 {
                    *out = other;
                }
            }
            union
        };
        filled.push(mask);
    }
    Some(filled)
}

/// The fields of an SA-V `{id}_manual.json` / `{id}_auto.json` file that mask generation uses.
#[derive(Debug, Clone, Deserialize)]
pub struct SavAnnotation {
    /// Number of frames of the 24 fps video.
    pub video_frame_count: f64,
    /// Per annotated frame (every [`SAV_ANNOTATION_STRIDE`]-th video frame), per masklet, its RLE.
    pub masklet: Vec<Vec<CocoRle>>,
}

/// SA-V annotates every 4th frame of its 24 fps videos (6 fps masklets).
pub const SAV_ANNOTATION_STRIDE: usize = 4;

/// Loads an SA-V annotation file.
pub fn load_sav_annotation(path: &Path) -> Result<SavAnnotation> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    serde_json::from_str(&text)
        .map_err(|e| Error::invalid(path, "masklet", format!("invalid SA-V annotation JSON: {e}")))
}

/// Per-frame id masks for `frame_count` video frames from an SA-V annotation: masklet `k` gets id
/// `k + 1` (capped at [`MAX_OBJECT_ID`]); empty RLEs (object absent) add nothing.
pub fn sav_frame_masks(annotation: &SavAnnotation, frame_count: usize, path: &Path) -> Result<Vec<GrayImage>> {
    let mut annotated: Vec<Option<GrayImage>> = vec![None; frame_count];
    for (step, objects) in annotation.masklet.iter().enumerate() {
        let frame = step * SAV_ANNOTATION_STRIDE;
        if frame >= frame_count {
            break;
        }
        let mut ids: Option<GrayImage> = None;
        for (object, rle) in objects.iter().enumerate() {
            let [height, width] = rle.size;
            let decoded =
                rle.decode().map_err(|e| Error::invalid(path, format!("masklet[{step}][{object}]"), e.to_string()))?;
            let ids = ids.get_or_insert_with(|| GrayImage::new(width as u32, height as u32));
            if ids.dimensions() != (width as u32, height as u32) {
                return Err(Error::invalid(
                    path,
                    format!("masklet[{step}][{object}].size"),
                    "differs from other masklets",
                ));
            }
            let id = (object + 1).min(MAX_OBJECT_ID as usize) as u8;
            for (pixel, on) in ids.iter_mut().zip(decoded) {
                if on && *pixel == 0 {
                    *pixel = id;
                }
            }
        }
        annotated[frame] = ids;
    }
    fill_between_annotations(annotated)
        .ok_or_else(|| Error::invalid(path, "masklet", "no annotated frame within the video"))
}

/// An axis-aligned box `[x, y, w, h]` in pixels on an annotated frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackBox {
    /// Video frame index the box is annotated on.
    pub frame: usize,
    /// Track id (objects keep it across frames).
    pub track: u64,
    /// `[x, y, width, height]`, top-left origin.
    pub bbox: [f64; 4],
}

/// Per-frame box masks: each track's box is interpolated linearly between its annotated frames
/// and held constant outside them; ids are assigned per track in order of first appearance.
pub fn box_frame_masks(boxes: &[TrackBox], frame_count: usize, width: u32, height: u32) -> Vec<GrayImage> {
    let mut tracks: Vec<u64> = Vec::new();
    for b in boxes {
        if !tracks.contains(&b.track) {
            tracks.push(b.track);
        }
    }
    let mut masks = vec![GrayImage::new(width, height); frame_count];
    for (index, track) in tracks.iter().enumerate() {
        let id = (index + 1).min(MAX_OBJECT_ID as usize) as u8;
        let mut keys: Vec<&TrackBox> = boxes.iter().filter(|b| b.track == *track).collect();
        keys.sort_by_key(|b| b.frame);
        for (frame, mask) in masks.iter_mut().enumerate() {
            let after = keys.partition_point(|b| b.frame < frame);
            let bbox = match (after.checked_sub(1).map(|i| keys[i]), keys.get(after)) {
                (Some(a), Some(b)) if b.frame != a.frame => {
                    let t = (frame - a.frame) as f64 / (b.frame - a.frame) as f64;
                    std::array::from_fn(|k| a.bbox[k] + t * (b.bbox[k] - a.bbox[k]))
                }
                (_, Some(b)) => b.bbox,
                (Some(a), None) => a.bbox,
                (None, None) => continue,
            };
            let [x, y, w, h] = bbox;
            // Pixel centres at integer coordinates: pixel (u, v) is inside if its centre is.
            let (u0, u1) = ((x - 0.5).ceil().max(0.0) as u32, ((x + w - 0.5).floor().min(width as f64 - 1.0)) as i64);
            let (v0, v1) = ((y - 0.5).ceil().max(0.0) as u32, ((y + h - 0.5).floor().min(height as f64 - 1.0)) as i64);
            for v in v0 as i64..=v1 {
                for u in u0 as i64..=u1 {
                    let pixel = mask.get_pixel_mut(u as u32, v as u32);
                    if pixel.0[0] == 0 {
                        pixel.0[0] = id;
                    }
                }
            }
        }
    }
    masks
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mask(values: &[u8]) -> GrayImage {
        GrayImage::from_raw(values.len() as u32, 1, values.to_vec()).unwrap()
    }

    #[test]
    fn unannotated_frames_take_the_union_of_their_neighbours() {
        let filled =
            fill_between_annotations(vec![None, Some(mask(&[1, 0, 0])), None, None, Some(mask(&[0, 0, 2])), None])
                .unwrap();
        let rows: Vec<Vec<u8>> = filled.iter().map(|m| m.as_raw().clone()).collect();
        assert_eq!(
            rows,
            vec![vec![1, 0, 0], vec![1, 0, 0], vec![1, 0, 2], vec![1, 0, 2], vec![0, 0, 2], vec![0, 0, 2]]
        );
        assert!(fill_between_annotations(vec![None, None]).is_none());
    }

    #[test]
    fn boxes_interpolate_between_annotations() {
        let boxes = [
            TrackBox { frame: 0, track: 7, bbox: [0.0, 0.0, 2.0, 1.0] },
            TrackBox { frame: 4, track: 7, bbox: [4.0, 0.0, 2.0, 1.0] },
        ];
        let masks = box_frame_masks(&boxes, 6, 8, 2);
        let row = |m: &GrayImage| m.as_raw()[..8].to_vec();
        assert_eq!(row(&masks[0]), vec![1, 1, 0, 0, 0, 0, 0, 0]);
        assert_eq!(row(&masks[2]), vec![0, 0, 1, 1, 0, 0, 0, 0]);
        assert_eq!(row(&masks[5]), vec![0, 0, 0, 0, 1, 1, 0, 0]);
        assert!(masks[3].as_raw()[8..].iter().all(|&v| v == 0), "second row outside the 1-pixel-high box");
    }

    #[test]
    fn palette_png_indices_are_read_unexpanded() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("00000.png");
        let file = std::fs::File::create(&path).unwrap();
        let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), 4, 2);
        encoder.set_color(png::ColorType::Indexed);
        encoder.set_depth(png::BitDepth::Eight);
        let mut palette = vec![0u8; 256 * 3];
        palette[255 * 3] = 200;
        encoder.set_palette(palette);
        let mut writer = encoder.write_header().unwrap();
        writer.write_image_data(&[0, 1, 2, 255, 3, 0, 0, 1]).unwrap();
        drop(writer);
        assert_eq!(read_id_png(&path).unwrap().as_raw(), &vec![0, 1, 2, 255, 3, 0, 0, 1]);
        std::fs::write(&path, b"not a png").unwrap();
        assert!(read_id_png(&path).unwrap_err().to_string().contains("00000.png"));
    }

    #[test]
    fn packed_palette_and_grey_pngs_unpack_to_one_id_per_pixel() {
        let dir = tempfile::tempdir().unwrap();
        // 5 pixels a row: the rows end inside a byte, as DAVIS's 2-bit and 4-bit masks can.
        let ids = [[0u8, 1, 2, 3, 1], [3, 3, 0, 2, 1]];
        for (color, depth, bits) in [
            (png::ColorType::Indexed, png::BitDepth::Two, 2),
            (png::ColorType::Grayscale, png::BitDepth::Four, 4),
            (png::ColorType::Grayscale, png::BitDepth::One, 1),
        ] {
            let path = dir.path().join(format!("{bits}.png"));
            let mut encoder = png::Encoder::new(std::fs::File::create(&path).unwrap(), 5, 2);
            encoder.set_color(color);
            encoder.set_depth(depth);
            if color == png::ColorType::Indexed {
                encoder.set_palette(vec![0u8; 4 * 3]);
            }
            let per_byte = 8 / bits;
            let packed: Vec<u8> = ids
                .iter()
                .flat_map(|row| {
                    row.chunks(per_byte).map(move |pixels| {
                        let mask = (1u8 << bits) - 1;
                        pixels.iter().enumerate().fold(0u8, |byte, (k, &id)| byte | (id & mask) << (8 - bits * (k + 1)))
                    })
                })
                .collect();
            encoder.write_header().unwrap().write_image_data(&packed).unwrap();
            let expected: Vec<u8> = ids.as_flattened().iter().map(|&id| id & ((1 << bits) - 1)).collect();
            assert_eq!(read_id_png(&path).unwrap().as_raw(), &expected, "{bits}-bit");
        }
    }
}
