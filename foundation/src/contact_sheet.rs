//! Contact sheets: a grid of frames (one row per sampled time, one column per kind of image) in
//! one PNG that a person can judge at a glance, plus colour maps for depth and object ids. A
//! labelled sheet also names its columns in a header and each row's frame index on its left,
//! drawn with a tiny built-in bitmap font (no font files, no text-rendering dependency).

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

/// Widths of the columns and heights of the rows of a sheet of `rows`.
fn layout(rows: &[Vec<RgbImage>]) -> (Vec<u32>, Vec<u32>) {
    let columns = rows.iter().map(Vec::len).max().unwrap_or(0);
    let column_widths: Vec<u32> =
        (0..columns).map(|c| rows.iter().filter_map(|r| r.get(c)).map(RgbImage::width).max().unwrap_or(0)).collect();
    let row_heights: Vec<u32> = rows.iter().map(|r| r.iter().map(RgbImage::height).max().unwrap_or(0)).collect();
    (column_widths, row_heights)
}

/// The contact sheet of `rows` as an image (see [`write_contact_sheet`]).
pub fn contact_sheet(rows: &[Vec<RgbImage>]) -> RgbImage {
    let (column_widths, row_heights) = layout(rows);
    let columns = column_widths.len();
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

/// Colour of header and row-label text.
const TEXT_COLOUR: Rgb<u8> = Rgb([240, 240, 240]);
/// Glyph cell of [`FONT`]: 5×7 pixels plus one column of spacing.
const GLYPH_WIDTH: u32 = 5;
const GLYPH_HEIGHT: u32 = 7;
const GLYPH_ADVANCE: u32 = GLYPH_WIDTH + 1;
/// Text is drawn at one font pixel per this many image pixels of the smallest row height
/// (at least 1): readable on 480×720 frames without dwarfing 64×48 test tiles.
const ROW_HEIGHT_PER_TEXT_SCALE: u32 = 120;
/// Largest text scale.
const MAX_TEXT_SCALE: u32 = 4;

/// A 5×7 bitmap font: digits, the capital letters and a few signs (rows top to bottom, bit 4 is
/// the leftmost pixel). Lower case is drawn as upper case; any other character as a hollow box.
const FONT: &[(char, [u8; 7])] = &[
    ('0', [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E]),
    ('1', [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E]),
    ('2', [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F]),
    ('3', [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E]),
    ('4', [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02]),
    ('5', [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E]),
    ('6', [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E]),
    ('7', [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08]),
    ('8', [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E]),
    ('9', [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C]),
    ('A', [0x0E, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11]),
    ('B', [0x1E, 0x11, 0x11, 0x1E, 0x11, 0x11, 0x1E]),
    ('C', [0x0E, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0E]),
    ('D', [0x1C, 0x12, 0x11, 0x11, 0x11, 0x12, 0x1C]),
    ('E', [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x1F]),
    ('F', [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x10]),
    ('G', [0x0E, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0F]),
    ('H', [0x11, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11]),
    ('I', [0x0E, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E]),
    ('J', [0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0C]),
    ('K', [0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11]),
    ('L', [0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1F]),
    ('M', [0x11, 0x1B, 0x15, 0x15, 0x11, 0x11, 0x11]),
    ('N', [0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11]),
    ('O', [0x0E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E]),
    ('P', [0x1E, 0x11, 0x11, 0x1E, 0x10, 0x10, 0x10]),
    ('Q', [0x0E, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0D]),
    ('R', [0x1E, 0x11, 0x11, 0x1E, 0x14, 0x12, 0x11]),
    ('S', [0x0F, 0x10, 0x10, 0x0E, 0x01, 0x01, 0x1E]),
    ('T', [0x1F, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04]),
    ('U', [0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E]),
    ('V', [0x11, 0x11, 0x11, 0x11, 0x11, 0x0A, 0x04]),
    ('W', [0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0A]),
    ('X', [0x11, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x11]),
    ('Y', [0x11, 0x11, 0x0A, 0x04, 0x04, 0x04, 0x04]),
    ('Z', [0x1F, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F]),
    (' ', [0x00; 7]),
    ('-', [0x00, 0x00, 0x00, 0x1F, 0x00, 0x00, 0x00]),
    ('.', [0x00, 0x00, 0x00, 0x00, 0x00, 0x0C, 0x0C]),
    (':', [0x00, 0x0C, 0x0C, 0x00, 0x0C, 0x0C, 0x00]),
    ('/', [0x01, 0x02, 0x02, 0x04, 0x08, 0x08, 0x10]),
    ('%', [0x19, 0x19, 0x02, 0x04, 0x08, 0x13, 0x13]),
];
/// Drawn for characters [`FONT`] lacks.
const UNKNOWN_GLYPH: [u8; 7] = [0x1F, 0x11, 0x11, 0x11, 0x11, 0x11, 0x1F];

fn glyph(c: char) -> [u8; 7] {
    let c = c.to_ascii_uppercase();
    FONT.iter().find(|(g, _)| *g == c).map_or(UNKNOWN_GLYPH, |(_, rows)| *rows)
}

/// Width in pixels of `text` drawn at `scale` by [`draw_text`].
pub fn text_width(text: &str, scale: u32) -> u32 {
    (text.chars().count() as u32 * GLYPH_ADVANCE).saturating_sub(1) * scale
}

/// Height in pixels of a line of text at `scale`.
pub fn text_height(scale: u32) -> u32 {
    GLYPH_HEIGHT * scale
}

/// Draws `text` with its top-left corner at (`x`, `y`), each font pixel a `scale`×`scale`
/// square; characters that would cross `max_x` (or the image's edge) are left out.
pub fn draw_text(image: &mut RgbImage, x: u32, y: u32, text: &str, scale: u32, max_x: u32, colour: Rgb<u8>) {
    let max_x = max_x.min(image.width());
    for (k, c) in text.chars().enumerate() {
        let left = x + k as u32 * GLYPH_ADVANCE * scale;
        if left + GLYPH_WIDTH * scale > max_x {
            break;
        }
        for (row, bits) in glyph(c).iter().enumerate() {
            for column in 0..GLYPH_WIDTH {
                if bits >> (GLYPH_WIDTH - 1 - column) & 1 == 0 {
                    continue;
                }
                for dy in 0..scale {
                    for dx in 0..scale {
                        let (px, py) = (left + column * scale + dx, y + row as u32 * scale + dy);
                        if px < image.width() && py < image.height() {
                            image.put_pixel(px, py, colour);
                        }
                    }
                }
            }
        }
    }
}

/// [`contact_sheet`] with a header band naming each column (`columns`, left to right) and each
/// row's label (`row_labels`, e.g. `FRAME 12`) in a band on its left.
pub fn labelled_contact_sheet(columns: &[&str], row_labels: &[String], rows: &[Vec<RgbImage>]) -> RgbImage {
    let grid = contact_sheet(rows);
    let (column_widths, row_heights) = layout(rows);
    let smallest_row = row_heights.iter().copied().min().unwrap_or(0);
    let scale = (smallest_row / ROW_HEIGHT_PER_TEXT_SCALE).clamp(1, MAX_TEXT_SCALE);
    let label_width = row_labels.iter().map(|l| text_width(l, scale)).max().unwrap_or(0);
    let left = if label_width > 0 { label_width + 2 * GAP } else { 0 };
    let top = text_height(scale) + 2 * GAP;
    let mut sheet = RgbImage::from_pixel(grid.width() + left, grid.height() + top, GAP_COLOUR);
    image::imageops::replace(&mut sheet, &grid, i64::from(left), i64::from(top));
    let mut x = left + GAP;
    for (name, width) in columns.iter().zip(&column_widths) {
        draw_text(&mut sheet, x, GAP, name, scale, x + width, TEXT_COLOUR);
        x += width + GAP;
    }
    let mut y = top + GAP;
    for (label, height) in row_labels.iter().zip(&row_heights) {
        draw_text(&mut sheet, GAP, y, label, scale, left, TEXT_COLOUR);
        y += height + GAP;
    }
    sheet
}

/// Saves [`labelled_contact_sheet`] as a PNG.
pub fn write_labelled_contact_sheet(
    path: &Path,
    columns: &[&str],
    row_labels: &[String],
    rows: &[Vec<RgbImage>],
) -> Result<()> {
    let sheet = labelled_contact_sheet(columns, row_labels, rows);
    sheet.save(path).map_err(|e| Error::Image { context: path.display().to_string(), reason: e.to_string() })
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
    fn labelled_sheet_names_columns_and_rows() {
        let tile = RgbImage::from_pixel(40, 30, Rgb([0, 0, 255]));
        let rows = vec![vec![tile.clone(), tile.clone()], vec![tile.clone(), tile]];
        let labels = ["FRAME 0".to_owned(), "FRAME 48".to_owned()];
        let sheet = labelled_contact_sheet(&["TARGET", "MASK"], &labels, &rows);
        let plain = contact_sheet(&rows);
        let left = text_width("FRAME 48", 1) + 2 * GAP;
        let top = text_height(1) + 2 * GAP;
        assert_eq!(sheet.dimensions(), (plain.width() + left, plain.height() + top));
        // The grid sits below the header and right of the labels, unchanged.
        assert_eq!(*sheet.get_pixel(left + GAP, top + GAP), Rgb([0, 0, 255]));
        let text_in = |x0: u32, x1: u32, y0: u32, y1: u32| {
            (y0..y1)
                .flat_map(|y| (x0..x1).map(move |x| (x, y)))
                .filter(|&(x, y)| *sheet.get_pixel(x, y) == TEXT_COLOUR)
                .count()
        };
        // Header text over each column, a label beside each row, and the labels differ.
        assert!(text_in(left, left + 40, 0, top) > 0 && text_in(left + 44, left + 84, 0, top) > 0);
        let row = |r: u32| top + GAP + r * (30 + GAP);
        assert!(text_in(0, left, row(0), row(0) + 7) > 0 && text_in(0, left, row(1), row(1) + 7) > 0);
        let crop = |y: u32| image::imageops::crop_imm(&sheet, 0, y, left, 7).to_image();
        assert_ne!(crop(row(0)), crop(row(1)), "frame indices are drawn");
        // Text never spills over into the next column.
        assert_eq!(text_width("CO-VISIBILITY MASK", 1), 18 * 6 - 1);
    }

    #[test]
    fn glyphs_differ_and_lower_case_is_upper_case() {
        let digits: Vec<[u8; 7]> = ('0'..='9').map(glyph).collect();
        for (i, a) in digits.iter().enumerate() {
            assert!(digits[i + 1..].iter().all(|b| a != b), "digit {i} is distinct");
        }
        assert_eq!(glyph('t'), glyph('T'));
        assert_eq!(glyph('~'), UNKNOWN_GLYPH);
    }

    #[test]
    fn invalid_depth_is_black_and_near_is_brighter() {
        let image = colorize_depth(&[1.0, 10.0, f32::NAN, 0.0], 4, 1);
        assert_eq!(*image.get_pixel(2, 0), Rgb([0, 0, 0]));
        assert_eq!(*image.get_pixel(3, 0), Rgb([0, 0, 0]));
        assert!(image.get_pixel(0, 0).0[0] > image.get_pixel(1, 0).0[0]);
    }
}
