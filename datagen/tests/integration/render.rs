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
/// map: quads of four valid samples whose depth ratio is within the cut) projected into the novel
/// image and rasterised there with 2D edge functions; the nearest triangle wins, by the depth of the
/// plane through its corners along the pixel's ray. Per pixel: Some(distance along the unit ray)
/// where a triangle holds the pixel centre by more than `SURE` px, None where none comes within
/// `SURE` px, and no verdict (skipped) in between.
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
    for v in 0..h.saturating_sub(1) {
        for u in 0..w.saturating_sub(1) {
            let d = [depth(u, v), depth(u + 1, v), depth(u, v + 1), depth(u + 1, v + 1)];
            if !d.iter().all(|&d| valid(d)) {
                continue;
            }
            let (near, far) = d.iter().fold((f32::INFINITY, 0.0f32), |(n, f), &d| (n.min(d), f.max(d)));
            if f64::from(far) > f64::from(near) * discontinuity_ratio {
                continue;
            }
            let c = [world(u, v), world(u + 1, v), world(u, v + 1), world(u + 1, v + 1)];
            consider([c[0], c[1], c[2]]);
            consider([c[1], c[3], c[2]]);
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
        let colour = bilinear(&frame.rgb, at);
        let got = image.get_pixel(x, y);
        let difference = (0..3).map(|k| (i32::from(got.0[k]) - i32::from(colour.0[k])).abs()).max().unwrap();
        assert!(difference <= 1, "{context}: ({x}, {y}) colour {got:?} vs {colour:?}");
    }
    (filled as f64 / hits.len() as f64, unsure)
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
