//! Novel-view rendering: one ray per novel pixel into the frame's depth mesh (skirts ignored, the
//! footprint fragments of its valid pixels included), the source colour at the first hit by
//! bilinear interpolation within a surface quad, the footprint's own pixel's colour on a fragment;
//! no hit is a hole (black in the image, 255 in the hole mask). This is the conditioning at
//! inference time.

use glam::DVec2;
use image::{GrayImage, Rgb, RgbImage};
use rayon::prelude::*;

use crate::geometry::depth_mesh::DepthMesh;
use foundation::camera::PinholeCamera;

/// Bilinear colour of `image` at pixel coordinates (centres at integers), clamped to the edges.
pub fn bilinear(image: &RgbImage, at: DVec2) -> Rgb<u8> {
    let (w, h) = (image.width() as f64, image.height() as f64);
    let x = at.x.clamp(0.0, w - 1.0);
    let y = at.y.clamp(0.0, h - 1.0);
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let (x1, y1) = ((x0 + 1.0).min(w - 1.0), (y0 + 1.0).min(h - 1.0));
    let p = |x: f64, y: f64| image.get_pixel(x as u32, y as u32).0.map(f64::from);
    let (a, b, c, d) = (p(x0, y0), p(x1, y0), p(x0, y1), p(x1, y1));
    Rgb(std::array::from_fn(|k| {
        let top = a[k] + (b[k] - a[k]) * fx;
        let bottom = c[k] + (d[k] - c[k]) * fx;
        (top + (bottom - top) * fy).round().clamp(0.0, 255.0) as u8
    }))
}

/// The colour of the source image at `at` (pixel coordinates), where a render ray met the mesh's
/// surface: bilinear inside a surface quad, whose four samples are one surface; elsewhere (a
/// footprint fragment, [`DepthMesh::fragments`]) the colour of the pixel whose footprint holds
/// `at`, so that no colour bleeds across a depth edge.
pub fn source_colour(mesh: &DepthMesh, image: &RgbImage, at: DVec2) -> Rgb<u8> {
    if mesh.joined_at(at) {
        return bilinear(image, at);
    }
    let x = at.x.round().clamp(0.0, f64::from(image.width()) - 1.0);
    let y = at.y.round().clamp(0.0, f64::from(image.height()) - 1.0);
    *image.get_pixel(x as u32, y as u32)
}

/// Renders `frame` (seen by `source`, lifted by `mesh`) from `novel`: the image and its hole mask.
pub fn render_novel_view(
    mesh: &DepthMesh,
    frame: &RgbImage,
    source: &PinholeCamera,
    novel: &PinholeCamera,
) -> (RgbImage, GrayImage) {
    let (width, height) = (novel.width as usize, novel.height as usize);
    let eye = novel.center();
    let hits = mesh.view(novel).surface_hits();
    let colours: Vec<Option<Rgb<u8>>> = (0..width * height)
        .into_par_iter()
        .map(|i| {
            let direction = novel.pixel_ray((i % width) as f64, (i / width) as f64).normalize();
            let (pixel, _) = source.project(eye + direction * hits[i]?)?;
            Some(source_colour(mesh, frame, pixel))
        })
        .collect();
    let mut image = RgbImage::new(width as u32, height as u32);
    let mut holes = GrayImage::new(width as u32, height as u32);
    for (i, colour) in colours.into_iter().enumerate() {
        let (x, y) = ((i % width) as u32, (i / width) as u32);
        match colour {
            Some(colour) => image.put_pixel(x, y, colour),
            None => holes.put_pixel(x, y, image::Luma([255])),
        }
    }
    (image, holes)
}
