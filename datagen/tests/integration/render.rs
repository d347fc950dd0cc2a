//! The novel-view render at and near the source pose: along its own camera a frame renders back
//! to itself (holes exactly where the depth is invalid), and near it the render fills the pixels
//! that an independent image-space rasteriser fills, with the same colours.

use datagen::geometry::depth_mesh::{DepthMesh, MeshConfig};
use datagen::geometry::render::{bilinear, render_novel_view};
use datagen::io::sequence::read_sequence;
use datagen::synth::{SynthConfig, SynthScene};
use foundation::camera::PinholeCamera;
use foundation::depth::DepthMap;
use glam::{DMat3, DMat4, DVec2, DVec3};
use image::RgbImage;

/// A source frame: colours, depth and camera.
struct Frame {
    rgb: RgbImage,
    depth: DepthMap,
    camera: PinholeCamera,
}

/// Frame 0 of a synthetic scene at `width` × `height`, its depth made invalid (NaN, 0 or −1 in
/// turn) on a scattered fifth of the pixels and on a block, so that the mesh has holes, borders,
/// isolated samples and one-pixel strips.
fn synth_frame(width: u32, height: u32, invalid: bool) -> Frame {
    // The scene is rendered at the next even size (its video needs one) and cropped from the top
    // left, which keeps K.
    let config =
        SynthConfig { width: width + width % 2, height: height + height % 2, frames: 1, ..SynthConfig::default() };
    let scene = SynthScene::new(&config).unwrap();
    let rendered = scene.render_frame(0);
    let full_width = config.width as usize;
    let (w, h) = (width as usize, height as usize);
    let rgb = image::imageops::crop_imm(&rendered.rgb, 0, 0, width, height).to_image();
    let mut values: Vec<f32> = (0..w * h).map(|i| rendered.depth[(i / w) * full_width + i % w]).collect();
    if invalid {
        for (i, value) in values.iter_mut().enumerate() {
            let (u, v) = (i % w, i / w);
            let scattered = (i * 7919 + 13) % 5 == 0;
            let block = (w / 3..w / 2).contains(&u) && (h / 3..).contains(&v);
            if scattered || block {
                *value = [f32::NAN, 0.0, -1.0][i % 3];
            }
        }
    }
    let camera =
        PinholeCamera { width, height, intrinsics: config.intrinsics(), world_from_camera: scene.world_from_camera(0) };
    Frame { rgb, depth: DepthMap { width: w, height: h, values }, camera }
}

/// Frame `index` of a Blender fixture (exact depth).
fn fixture_frame(scene: &str, index: usize) -> Frame {
    let sequence = read_sequence(&crate::sequence::fixtures().join(scene)).unwrap();
    Frame { rgb: sequence.frames[index].clone(), depth: sequence.depth[index].clone(), camera: sequence.cameras[index] }
}

fn valid(depth: f32) -> bool {
    depth.is_finite() && depth > 0.0
}

/// Renders `frame` along its own camera and checks that the holes are exactly its invalid-depth
/// pixels and every other pixel is its own colour; gives the hole share.
fn assert_renders_back(frame: &Frame, config: &MeshConfig, context: &str) -> f64 {
    let mesh = DepthMesh::new(&frame.depth, &frame.camera, config);
    let (image, holes) = render_novel_view(&mesh, &frame.rgb, &frame.camera, &frame.camera);
    let width = frame.depth.width;
    let mut hole_count = 0;
    for (i, &depth) in frame.depth.values.iter().enumerate() {
        let (x, y) = ((i % width) as u32, (i / width) as u32);
        let hole = holes.get_pixel(x, y).0[0] == 255;
        assert_eq!(hole, !valid(depth), "{context}: pixel ({x}, {y}) depth {depth}: hole {hole}");
        if hole {
            hole_count += 1;
        } else {
            assert_eq!(image.get_pixel(x, y), frame.rgb.get_pixel(x, y), "{context}: colour of ({x}, {y})");
        }
    }
    hole_count as f64 / frame.depth.values.len() as f64
}

/// Every mesh setting: the plain cut mesh, skirts, and the image-grid and BVH paths.
fn mesh_configs() -> Vec<MeshConfig> {
    let cwbvh = MeshConfig { accelerator: datagen::geometry::depth_mesh::Accelerator::Cwbvh, ..MeshConfig::default() };
    vec![MeshConfig::default(), MeshConfig { occluder_thickness: 0.0, ..MeshConfig::default() }, cwbvh]
}

#[test]
fn a_synthetic_frame_renders_back_to_itself_at_every_size() {
    // Even and odd sizes, one-pixel strips both ways, a single pixel.
    for (width, height) in [(320, 240), (80, 64), (37, 23), (1, 17), (17, 1), (2, 9), (1, 1)] {
        for invalid in [false, true] {
            let frame = synth_frame(width, height, invalid);
            for config in mesh_configs() {
                let context = format!("{width}×{height} invalid {invalid} {config:?}");
                let holes = assert_renders_back(&frame, &config, &context);
                assert!(holes < 1.0 || width * height == 1, "{context}: the frame must show some surface");
            }
        }
    }
}

#[test]
fn blender_fixtures_render_back_to_themselves() {
    for (scene, index) in [("scene_101", 0), ("scene_101", 8), ("scene_102", 4)] {
        let frame = fixture_frame(scene, index);
        for config in mesh_configs().into_iter().take(2) {
            assert_renders_back(&frame, &config, &format!("{scene} frame {index} {config:?}"));
        }
    }
}

/// An independent reference for the render: every triangle of the mesh (rebuilt here from the depth
/// map: quads of four valid samples whose depth ratio is within the cut, and the footprint
/// fragments, each valid pixel's quarter-pixel squares at its own depth toward every side where no
/// such quad is) projected into the novel image and rasterised there with 2D edge functions; the
/// nearest triangle wins, by the depth of the plane through its corners along the pixel's ray. Per
/// pixel: Some(distance along the unit ray) where a triangle holds the pixel centre by more than
/// `SURE` px, None where none comes within `SURE` px, and no verdict (skipped) in between.
struct Reference {
    nearest: Vec<Option<f64>>,
    unsure: Vec<bool>,
}

/// Distance (novel pixels) from a triangle's edge under which the reference gives no verdict.
const SURE: f64 = 1e-6;

fn reference_render(frame: &Frame, novel: &PinholeCamera, discontinuity_ratio: f64) -> Reference {
    let (w, h) = (frame.depth.width, frame.depth.height);
    let (nw, nh) = (novel.width as usize, novel.height as usize);
    let depth = |u: usize, v: usize| frame.depth.values[v * w + u];
    let world = |u: usize, v: usize| frame.camera.unproject(u as f64, v as f64, f64::from(depth(u, v)));
    let novel_from_world = novel.camera_from_world();
    let eye = novel.center();
    let mut nearest: Vec<Option<f64>> = vec![None; nw * nh];
    let mut unsure = vec![false; nw * nh];
    let mut consider = |corners: [DVec3; 3]| {
        let in_novel = corners.map(|c| novel_from_world.transform_point3(c));
        if in_novel.iter().any(|c| c.z <= 0.0) {
            return;
        }
        let image = in_novel.map(|c| {
            let k = novel.intrinsics;
            DVec2::new(k.x_axis.x * c.x / c.z + k.z_axis.x, k.y_axis.y * c.y / c.z + k.z_axis.y)
        });
        let area = (image[1] - image[0]).perp_dot(image[2] - image[0]);
        if area.abs() < 1e-12 {
            return;
        }
        // Signed distances of a pixel centre from the three edges, positive inside.
        let inside = |p: DVec2| {
            (0..3)
                .map(|k| {
                    let (a, b) = (image[k], image[(k + 1) % 3]);
                    area.signum() * (b - a).perp_dot(p - a) / (b - a).length()
                })
                .fold(f64::INFINITY, f64::min)
        };
        // The pixel centres inside the triangle's box, clamped to the image.
        let lo = image.iter().fold(DVec2::INFINITY, |m, p| m.min(*p)).ceil().max(DVec2::ZERO);
        let hi = image
            .iter()
            .fold(DVec2::NEG_INFINITY, |m, p| m.max(*p))
            .floor()
            .min(DVec2::new(nw as f64 - 1.0, nh as f64 - 1.0));
        if lo.x > hi.x || lo.y > hi.y {
            return;
        }
        let normal = (corners[1] - corners[0]).cross(corners[2] - corners[0]);
        for y in lo.y as usize..=hi.y as usize {
            for x in lo.x as usize..=hi.x as usize {
                let distance = inside(DVec2::new(x as f64, y as f64));
                let i = y * nw + x;
                if distance.abs() <= SURE {
                    unsure[i] = true;
                } else if distance > 0.0 {
                    let ray = novel.pixel_ray(x as f64, y as f64).normalize();
                    let t = normal.dot(corners[0] - eye) / normal.dot(ray);
                    nearest[i] = Some(nearest[i].map_or(t, |n: f64| n.min(t)));
                }
            }
        }
    };
    let joined = |u: usize, v: usize| {
        let d = [depth(u, v), depth(u + 1, v), depth(u, v + 1), depth(u + 1, v + 1)];
        let (near, far) = d.iter().fold((f32::INFINITY, 0.0f32), |(n, f), &d| (n.min(d), f.max(d)));
        d.iter().all(|&d| valid(d)) && f64::from(far) <= f64::from(near) * discontinuity_ratio
    };
    for v in 0..h.saturating_sub(1) {
        for u in 0..w.saturating_sub(1) {
            if joined(u, v) {
                let c = [world(u, v), world(u + 1, v), world(u, v + 1), world(u + 1, v + 1)];
                consider([c[0], c[1], c[2]]);
                consider([c[1], c[3], c[2]]);
            }
        }
    }
    for v in 0..h {
        for u in 0..w {
            if !valid(depth(u, v)) {
                continue;
            }
            for (sx, sy) in [(-1i64, -1i64), (1, -1), (-1, 1), (1, 1)] {
                let (nu, nv) = (u as i64 + sx, v as i64 + sy);
                let inside = nu >= 0 && nv >= 0 && (nu as usize) < w && (nv as usize) < h;
                if inside && joined((nu as usize).min(u), (nv as usize).min(v)) {
                    continue;
                }
                let at = |x: f64, y: f64| frame.camera.unproject(x, y, f64::from(depth(u, v)));
                let (x0, y0) = (u as f64, v as f64);
                let (x1, y1) = (x0 + 0.5 * sx as f64, y0 + 0.5 * sy as f64);
                let c = [at(x0, y0), at(x1, y0), at(x0, y1), at(x1, y1)];
                consider([c[0], c[1], c[2]]);
                consider([c[1], c[3], c[2]]);
            }
        }
    }
    Reference { nearest, unsure }
}

/// Renders `frame` from `novel` and compares with the reference: the same pixels filled wherever
/// the reference is sure, at the same distance, with the same colour within one level; gives the
/// filled share and how many pixels the reference left unsure.
fn assert_matches_reference(frame: &Frame, novel: &PinholeCamera, context: &str) -> (f64, usize) {
    let config = MeshConfig::default();
    let mesh = DepthMesh::new(&frame.depth, &frame.camera, &config);
    let (image, holes) = render_novel_view(&mesh, &frame.rgb, &frame.camera, novel);
    let hits = mesh.view(novel).surface_hits();
    let reference = reference_render(frame, novel, config.discontinuity_ratio);
    let width = novel.width as usize;
    let (mut filled, mut unsure) = (0, 0);
    for (i, hit) in hits.iter().enumerate() {
        let (x, y) = ((i % width) as u32, (i / width) as u32);
        if reference.unsure[i] {
            unsure += 1;
            continue;
        }
        let hole = holes.get_pixel(x, y).0[0] == 255;
        assert_eq!(hole, reference.nearest[i].is_none(), "{context}: pixel ({x}, {y})");
        let Some(expected) = reference.nearest[i] else { continue };
        filled += 1;
        let t = hit.unwrap();
        assert!((t - expected).abs() <= 1e-6 * expected, "{context}: ({x}, {y}) distance {t} vs {expected}");
        let point = novel.center() + novel.pixel_ray(f64::from(x), f64::from(y)).normalize() * expected;
        let (at, _) = frame.camera.project(point).unwrap();
        let colour = expected_colour(frame, at, config.discontinuity_ratio);
        let got = image.get_pixel(x, y);
        let difference = (0..3).map(|k| (i32::from(got.0[k]) - i32::from(colour.0[k])).abs()).max().unwrap();
        assert!(difference <= 1, "{context}: ({x}, {y}) colour {got:?} vs {colour:?}");
    }
    (filled as f64 / hits.len() as f64, unsure)
}

/// The colour a render shows where its ray meets the surface at source image point `at`: bilinear
/// between the four samples around it when they are one surface (valid, depth ratio within
/// `discontinuity_ratio`), else the colour of the pixel whose footprint holds `at`.
fn expected_colour(frame: &Frame, at: DVec2, discontinuity_ratio: f64) -> image::Rgb<u8> {
    let (w, h) = (frame.depth.width, frame.depth.height);
    let (u, v) = (at.x.floor(), at.y.floor());
    if u >= 0.0 && v >= 0.0 && u + 1.0 < w as f64 && v + 1.0 < h as f64 {
        let (u, v) = (u as usize, v as usize);
        let d = [(u, v), (u + 1, v), (u, v + 1), (u + 1, v + 1)].map(|(u, v)| frame.depth.values[v * w + u]);
        let (near, far) = d.iter().fold((f32::INFINITY, 0.0f32), |(n, f), &d| (n.min(d), f.max(d)));
        if d.iter().all(|&d| valid(d)) && f64::from(far) <= f64::from(near) * discontinuity_ratio {
            return bilinear(&frame.rgb, at);
        }
    }
    let (x, y) = (at.x.round().clamp(0.0, w as f64 - 1.0), at.y.round().clamp(0.0, h as f64 - 1.0));
    *frame.rgb.get_pixel(x as u32, y as u32)
}

/// The camera turned by `degrees` about its vertical axis, or orbited that much about the point at
/// `pivot` depth on its optical axis.
fn turned(camera: &PinholeCamera, degrees: f64, orbit_at: Option<f64>) -> PinholeCamera {
    let rotation = DMat4::from_mat3(DMat3::from_rotation_y(degrees.to_radians()));
    let world_from_camera = match orbit_at {
        None => camera.world_from_camera * rotation,
        Some(depth) => {
            let to_pivot = DMat4::from_translation(DVec3::new(0.0, 0.0, depth));
            camera.world_from_camera * to_pivot * rotation * to_pivot.inverse()
        }
    };
    PinholeCamera { world_from_camera, ..*camera }
}

#[test]
fn near_the_source_pose_the_render_fills_what_an_independent_rasteriser_fills() {
    let frames = [
        ("synth 80×64", synth_frame(80, 64, false)),
        ("synth 37×23 with invalid depth", synth_frame(37, 23, true)),
        ("scene_101", fixture_frame("scene_101", 5)),
    ];
    for (name, frame) in &frames {
        let pivot = f64::from(frame.depth.values[frame.depth.values.len() / 2]);
        for degrees in [0.01, 0.1, 1.0] {
            for orbit in [None, Some(pivot)] {
                let novel = turned(&frame.camera, degrees, orbit);
                let context = format!("{name} turned {degrees}° orbit {orbit:?}");
                let (filled, unsure) = assert_matches_reference(frame, &novel, &context);
                let pixels = (novel.width * novel.height) as usize;
                assert!(unsure * 1000 < pixels, "{context}: {unsure} pixels without a verdict");
                assert!(filled > 0.0, "{context}: nothing filled");
            }
        }
    }
}

/// The camera turned by `degrees` about the axis `axis` through its centre.
fn rotated(camera: &PinholeCamera, axis: DVec3, degrees: f64) -> PinholeCamera {
    let rotation = DMat4::from_mat3(DMat3::from_axis_angle(axis.normalize(), degrees.to_radians()));
    PinholeCamera { world_from_camera: camera.world_from_camera * rotation, ..*camera }
}

/// Distance (source pixels) from a footprint's border under which the rotation reference gives no
/// verdict: a ray there may land in either neighbour's footprint by round-off.
const FOOTPRINT_SURE: f64 = 1e-6;

/// A turn about the source camera's centre reveals nothing new: every novel ray lands at a point
/// of the source image, and the render must show the source there (the source image warped by the
/// turn's homography: bilinearly between samples of one surface, else the nearest pixel) unless the pixel whose footprint holds that point has no valid
/// depth or the point is outside the source image. The reference is that warp, computed here from
/// the cameras alone (no mesh). Gives the share of novel pixels that are holes although the
/// source has a surface there.
fn assert_turn_reveals_nothing(frame: &Frame, novel: &PinholeCamera, context: &str) -> f64 {
    let mesh = DepthMesh::new(&frame.depth, &frame.camera, &MeshConfig::default());
    let (image, holes) = render_novel_view(&mesh, &frame.rgb, &frame.camera, novel);
    let (w, h) = (frame.depth.width, frame.depth.height);
    let source_from_novel = frame.camera.camera_from_world() * novel.world_from_camera;
    let (nw, nh) = (novel.width as usize, novel.height as usize);
    let (mut cracks, mut unsure) = (0, 0);
    for i in 0..nw * nh {
        let (x, y) = ((i % nw) as u32, (i / nw) as u32);
        let ray = source_from_novel
            .transform_vector3(novel.intrinsics.inverse() * DVec3::new(f64::from(x), f64::from(y), 1.0));
        let k = frame.camera.intrinsics;
        let at = DVec2::new(k.x_axis.x * ray.x / ray.z + k.z_axis.x, k.y_axis.y * ray.y / ray.z + k.z_axis.y);
        let border = |c: f64| ((c + 0.5) - (c + 0.5).round()).abs() < FOOTPRINT_SURE;
        if border(at.x) || border(at.y) {
            unsure += 1;
            continue;
        }
        let inside = ray.z > 0.0 && at.x > -0.5 && at.y > -0.5 && at.x < w as f64 - 0.5 && at.y < h as f64 - 0.5;
        let surface = inside && valid(frame.depth.values[at.y.round() as usize * w + at.x.round() as usize]);
        let hole = holes.get_pixel(x, y).0[0] == 255;
        if hole && surface {
            cracks += 1;
            continue;
        }
        assert_eq!(hole, !surface, "{context}: pixel ({x}, {y}) lands at {at} in the source");
        if surface {
            let expected = expected_colour(frame, at, MeshConfig::default().discontinuity_ratio);
            let got = image.get_pixel(x, y);
            let difference = (0..3).map(|c| (i32::from(got.0[c]) - i32::from(expected.0[c])).abs()).max().unwrap();
            assert!(difference <= 1, "{context}: ({x}, {y}) colour {got:?} vs the warp's {expected:?}");
        }
    }
    assert!(unsure * 1000 < nw * nh, "{context}: {unsure} pixels without a verdict");
    cracks as f64 / (nw * nh) as f64
}

#[test]
fn turned_about_its_centre_the_render_has_holes_only_where_the_source_has_no_surface() {
    let frames = [
        ("synth 80×64", synth_frame(80, 64, false)),
        ("synth 37×23 with invalid depth", synth_frame(37, 23, true)),
        ("scene_101", fixture_frame("scene_101", 5)),
        ("scene_102", fixture_frame("scene_102", 4)),
    ];
    let mut failures = Vec::new();
    for (name, frame) in &frames {
        for degrees in [0.01, 0.1, 1.0] {
            for axis in [DVec3::Y, DVec3::new(1.0, 2.0, 0.5)] {
                let context = format!("{name} turned {degrees}° about {axis}");
                let cracks = assert_turn_reveals_nothing(frame, &rotated(&frame.camera, axis, degrees), &context);
                println!("{context}: {:.3} % holes where the source has a surface", 100.0 * cracks);
                if cracks > 0.0 {
                    failures.push(context);
                }
            }
        }
    }
    assert!(failures.is_empty(), "cracks: {failures:?}");
}

#[test]
fn datagen_render_along_the_sequences_own_poses_gives_its_frames_back() {
    let dir = tempfile::tempdir().unwrap();
    let sequence_dir = crate::sequence::synth_sequence(dir.path(), 3);
    let sequence = read_sequence(&sequence_dir).unwrap();
    let own_poses = sequence_dir.join("cam_info/megasam_c2ws.npy");
    let config = datagen::pairs::generator::PairsConfig::default();
    let out = dir.path().join("render");
    let summary = datagen::pairs::generator::render_sequence(&sequence, &own_poses, &out, &config, false).unwrap();
    let invalid = sequence.depth.iter().flat_map(|d| &d.values).filter(|&&d| !valid(d)).count();
    assert_eq!((summary.frames, summary.holes), (3, invalid), "holes exactly where the depth is invalid");
    for (i, source) in sequence.frames.iter().enumerate() {
        let frame = image::open(out.join(format!("frames/{i:05}.png"))).unwrap().to_rgb8();
        for (p, &depth) in sequence.depth[i].values.iter().enumerate() {
            let (x, y) = ((p % frame.width() as usize) as u32, (p / frame.width() as usize) as u32);
            let expected = if valid(depth) { *source.get_pixel(x, y) } else { image::Rgb([0; 3]) };
            assert_eq!(*frame.get_pixel(x, y), expected, "frame {i} pixel ({x}, {y})");
        }
    }
}

/// Depth noise moves points along the novel camera's rays; from the source camera those are the
/// source rays, so whatever the offsets, the render back into the source is the source itself on
/// every kept pixel, and covers exactly them.
#[test]
fn depth_noise_rendered_back_at_the_source_pose_is_the_source() {
    use datagen::pairs::depth_noise::{SourceFrame, render_back};
    use rand::{Rng, SeedableRng};
    for (width, height, invalid) in [(80, 64, false), (37, 23, true)] {
        let frame = synth_frame(width, height, invalid);
        let mesh = DepthMesh::new(&frame.depth, &frame.camera, &MeshConfig::default());
        let dynamic = image::GrayImage::from_pixel(width, height, image::Luma([1]));
        let kept: Vec<bool> = frame.depth.values.iter().map(|&d| valid(d)).collect();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let offsets: Vec<f64> =
            frame.depth.values.iter().map(|&d| f64::from(d) * rng.random_range(-0.05..0.05)).collect();
        let source = SourceFrame { frame: &frame.rgb, depth: &frame.depth, dynamic: &dynamic, camera: &frame.camera };
        let back = render_back(source, |p| mesh.point(p), &kept, &offsets, &frame.camera);
        assert_eq!(back.mask, kept, "{width}×{height}");
        for (i, &keep) in kept.iter().enumerate() {
            let (x, y) = ((i % width as usize) as u32, (i / width as usize) as u32);
            if keep {
                assert_eq!(back.condition.get_pixel(x, y), frame.rgb.get_pixel(x, y), "({x}, {y})");
            }
        }
    }
}

/// The co-visibility masks do not share the render's fault: near the source pose they equal masks
/// computed with the watertight test of `ray_triangle` (a segment is blocked when it crosses a
/// closed triangle not having its end as a corner), on the plain cut mesh, by brute force.
#[test]
fn near_the_source_pose_masks_equal_a_watertight_reference() {
    use datagen::geometry::covisibility::{CovisibilityConfig, covisibility_mask};
    use datagen::geometry::ray_triangle::RenderRay;
    let config = CovisibilityConfig {
        mesh: MeshConfig { occluder_thickness: 0.0, ..MeshConfig::default() },
        ..CovisibilityConfig::default()
    };
    let mut compared = 0;
    for frame in [synth_frame(48, 36, false), synth_frame(37, 23, true)] {
        let mesh = DepthMesh::new(&frame.depth, &frame.camera, &config.mesh);
        let (w, h) = (frame.depth.width, frame.depth.height);
        let depth = |u: usize, v: usize| frame.depth.values[v * w + u];
        let mut triangles = Vec::new();
        for v in 0..h - 1 {
            for u in 0..w - 1 {
                let corners = [(u, v), (u + 1, v), (u, v + 1), (u + 1, v + 1)];
                let d = corners.map(|(u, v)| depth(u, v));
                let (near, far) = d.iter().fold((f32::INFINITY, 0.0f32), |(n, f), &d| (n.min(d), f.max(d)));
                if d.iter().all(|&d| valid(d)) && f64::from(far) <= f64::from(near) * config.mesh.discontinuity_ratio {
                    let index = corners.map(|(u, v)| v * w + u);
                    triangles.push([index[0], index[1], index[2]]);
                    triangles.push([index[1], index[3], index[2]]);
                }
            }
        }
        let pivot = f64::from(depth(w / 2, h / 2));
        for degrees in [0.0, 0.01, 0.1, 1.0, 5.0] {
            for orbit in [None, Some(pivot)] {
                let novel = turned(&frame.camera, degrees, orbit);
                let mask = covisibility_mask(&mesh, &frame.camera, &novel, &config);
                let eye = novel.center();
                for (p, &covisible) in mask.iter().enumerate() {
                    let Some(point) = mesh.point(p) else {
                        assert!(!covisible);
                        continue;
                    };
                    let seen = novel.project(point).is_some_and(|(pixel, _)| novel.contains(pixel));
                    let length = (point - eye).length();
                    let ray = RenderRay::new(eye, (point - eye) / length);
                    let blocked = triangles.iter().any(|t| {
                        !t.contains(&p)
                            && ray
                                .triangle_hit(t.map(|q| mesh.point(q).unwrap()))
                                .is_some_and(|hit| hit < length * (1.0 - config.epsilon))
                    });
                    assert_eq!(covisible, seen && !blocked, "turned {degrees}° orbit {orbit:?}: pixel {p}");
                    compared += 1;
                }
            }
        }
    }
    assert!(compared > 10_000);
}
