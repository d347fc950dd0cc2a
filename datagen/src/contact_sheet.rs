//! Contact sheets: a grid of frames (one row per sampled time, one column per kind of image) in
//! one PNG that a person can judge at a glance, plus colour maps for depth and object ids.

use std::path::Path;

use image::{GrayImage, Rgb, RgbImage};

use crate::error::{Error, Result};

/// Gap between tiles, in pixels, filled with [`GAP_COLOUR`].
const GAP: u32 = 4;
const GAP_COLOUR: Rgb<u8> = Rgb([32, 32, 32]);

/// Lays out `rows` (each a list of tiles, left to right) on a dark background and saves a PNG.
/// Tiles may differ in size; each column is as wide as its widest tile.
pub fn write_contact_sheet(path: &Path, rows: &[Vec<RgbImage>]) -> Result<()> {
    let sheet = contact_sheet(rows);
    sheet.save(path).map_err(|e| Error::Image { context: path.display().to_string(), reason: e.to_string() })
}

/// The contact sheet of `rows` as an image (see [`write_contact_sheet`]).
pub fn contact_sheet(rows: &[Vec<RgbImage>]) -> RgbImage {
    let columns = rows.iter().map(Vec::len).max().unwrap_or(0);
    let column_widths: Vec<u32> =
        (0..columns).map(|c| rows.iter().filter_map(|r| r.get(c)).map(RgbImage::width).max().unwrap_or(0)).collect();
    let row_heights: Vec<u32> = rows.iter().map(|r| r.iter().map(RgbImage::height).max().unwrap_or(0)).collect();
    let width = column_widths.iter().sum::<u32>() + GAP * (columns as u32 + 1);
    let height = row_heights.iter().sum::<u32>() + GAP * (rows.len() as u32 + 1);
    let mut sheet = RgbImage::from_pixel(width.max(1), height.max(1), GAP_COLOUR);
    let mut y = GAP;
    for (row, row_height) in rows.iter().zip(&row_heights) {
        let mut x = GAP;
        for (tile, column_width) in row.iter().zip(&column_widths) {
            image::imageops::replace(&mut sheet, tile, x as i64, y as i64);
            x += column_width + GAP;
        }
        y += row_height + GAP;
    }
    sheet
}

/// Depth as a colour image: near bright yellow to far dark blue (inverse depth, scaled to the
/// frame's valid range); invalid depth (≤ 0, NaN, inf) black.
pub fn colorize_depth(depth: &[f32], width: usize, height: usize) -> RgbImage {
    let valid = |d: f32| d.is_finite() && d > 0.0;
    let (lo, hi) = depth
        .iter()
        .filter(|&&d| valid(d))
        .fold((f32::INFINITY, 0.0f32), |(lo, hi), &d| (lo.min(1.0 / d), hi.max(1.0 / d)));
    let span = (hi - lo).max(f32::EPSILON);
    RgbImage::from_fn(width as u32, height as u32, |x, y| {
        let d = depth[y as usize * width + x as usize];
        if !valid(d) {
            return Rgb([0, 0, 0]);
        }
        let t = ((1.0 / d - lo) / span).clamp(0.0, 1.0);
        Rgb([(255.0 * t) as u8, (255.0 * (0.2 + 0.7 * t)) as u8, (255.0 * (0.6 - 0.5 * t)) as u8])
    })
}

/// Object ids as colours: 0 black, 255 (void) white, others a distinct hue each.
pub fn colorize_ids(ids: &GrayImage) -> RgbImage {
    RgbImage::from_fn(ids.width(), ids.height(), |x, y| match ids.get_pixel(x, y).0[0] {
        0 => Rgb([0, 0, 0]),
        255 => Rgb([255, 255, 255]),
        id => {
            // Golden-ratio hue steps keep neighbouring ids apart.
            let hue = (id as f32 * 0.618_034).fract() * 6.0;
            let f = hue.fract();
            let (r, g, b) = match hue as u32 {
                0 => (1.0, f, 0.0),
                1 => (1.0 - f, 1.0, 0.0),
                2 => (0.0, 1.0, f),
                3 => (0.0, 1.0 - f, 1.0),
                4 => (f, 0.0, 1.0),
                _ => (1.0, 0.0, 1.0 - f),
            };
            Rgb([(64.0 + 191.0 * r) as u8, (64.0 + 191.0 * g) as u8, (64.0 + 191.0 * b) as u8])
        }
    })
}

/// A binary mask (255 kept, 0 dropped) as a grey RGB image.
pub fn mask_to_rgb(mask: &GrayImage) -> RgbImage {
    RgbImage::from_fn(mask.width(), mask.height(), |x, y| {
        let v = mask.get_pixel(x, y).0[0];
        Rgb([v, v, v])
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_land_where_expected() {
        let red = RgbImage::from_pixel(3, 2, Rgb([255, 0, 0]));
        let blue = RgbImage::from_pixel(5, 4, Rgb([0, 0, 255]));
        let sheet = contact_sheet(&[vec![red.clone(), blue.clone()], vec![blue, red]]);
        assert_eq!(sheet.dimensions(), (GAP * 3 + 5 + 5, GAP * 3 + 4 + 4));
        assert_eq!(*sheet.get_pixel(GAP, GAP), Rgb([255, 0, 0]));
        assert_eq!(*sheet.get_pixel(GAP * 2 + 5, GAP), Rgb([0, 0, 255]));
        assert_eq!(*sheet.get_pixel(0, 0), GAP_COLOUR);
    }

    #[test]
    fn invalid_depth_is_black_and_near_is_brighter() {
        let image = colorize_depth(&[1.0, 10.0, f32::NAN, 0.0], 4, 1);
        assert_eq!(*image.get_pixel(2, 0), Rgb([0, 0, 0]));
        assert_eq!(*image.get_pixel(3, 0), Rgb([0, 0, 0]));
        assert!(image.get_pixel(0, 0).0[0] > image.get_pixel(1, 0).0[0]);
    }
}
