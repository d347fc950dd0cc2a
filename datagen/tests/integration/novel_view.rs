//! The render batch of the image grids (every novel pixel's first surface hit) equals a loop over
//! every triangle, as the co-visibility batch does in `geometry`.

use datagen::geometry::depth_mesh::{DepthMesh, MeshConfig};
use datagen::geometry::mesh_view;
use datagen::synth::{SynthConfig, SynthScene, look_at};
use foundation::camera::PinholeCamera;
use foundation::depth::DepthMap;
use glam::{DMat3, DMat4, DVec3};

/// Asserts that every novel pixel's batch hit equals the brute-force one; gives how many pixels
/// hit a surface and how many quads reach every pixel (near or behind the image plane).
fn assert_hits_are_brute_force(mesh: &DepthMesh, novel: &PinholeCamera, context: &str) -> (usize, usize) {
    let view = mesh.view(novel);
    let hits = view.surface_hits();
    assert_eq!(hits.len(), (novel.width * novel.height) as usize, "{context}");
    let width = novel.width as usize;
    for (index, &hit) in hits.iter().enumerate() {
        let direction = novel.pixel_ray((index % width) as f64, (index / width) as f64).normalize();
        let brute = mesh.first_surface_hit_brute_force(novel.center(), direction);
        assert_eq!(hit, brute, "{context}: novel pixel {index}");
    }
    (hits.iter().flatten().count(), mesh_view::probe::bin_sizes(&view).expect("image grids").1)
}

/// Every mesh setting the render sees: the plain cut mesh and skirts (which it ignores).
fn meshes(depth: &DepthMap, source: &PinholeCamera) -> Vec<(f64, DepthMesh)> {
    [0.0, 0.05]
        .map(|thickness| {
            let config = MeshConfig { occluder_thickness: thickness, ..MeshConfig::default() };
            (thickness, DepthMesh::new(depth, source, &config))
        })
        .into()
}

/// Orbits left and right of the synthetic scene's frames, one above, and one just in front of the
/// surface looking along it.
#[test]
fn render_batch_equals_brute_force_on_synthetic_frames() {
    let config = SynthConfig { width: 64, height: 48, frames: 2, ..SynthConfig::default() };
    let scene = SynthScene::new(&config).unwrap();
    let mut hit = 0;
    for frame in 0..2u32 {
        let rendered = scene.render_frame(frame);
        let world_from_camera = scene.world_from_camera(frame);
        let source = PinholeCamera { width: 64, height: 48, intrinsics: config.intrinsics(), world_from_camera };
        let depth = DepthMap { width: 64, height: 48, values: rendered.depth.clone() };
        let surface = f64::from(rendered.depth[24 * 64 + 32]);
        let pivot = world_from_camera.transform_point3(DVec3::new(0.0, 0.0, surface));
        let orbit = |degrees: f64, lift: f64| {
            let eye = DMat3::from_rotation_y(degrees.to_radians()) * (source.center() - pivot);
            look_at(pivot + eye + DVec3::new(0.0, lift, 0.0), pivot)
        };
        let along = look_at(
            world_from_camera.transform_point3(DVec3::new(0.0, 0.0, 0.97 * surface)),
            world_from_camera.transform_point3(DVec3::new(3.0, 0.2, surface)),
        );
        for (thickness, mesh) in meshes(&depth, &source) {
            for (name, world_from_camera) in
                [("left", orbit(20.0, 0.0)), ("right", orbit(-25.0, 0.0)), ("above", orbit(5.0, 1.0)), ("along", along)]
            {
                let novel = PinholeCamera { world_from_camera, ..source };
                let context = format!("frame {frame} {name} skirt {thickness}");
                hit += assert_hits_are_brute_force(&mesh, &novel, &context).0;
            }
        }
    }
    assert!(hit > 1000, "the views must see the scene ({hit} pixels hit)");
}

/// A tilted plane with a square floating in front, seen from cameras so close to the plane that
/// the triangles in front of them are nearer than the near limit and visit every pixel (so they
/// are the first hits there), and from one turned away from the square.
#[test]
fn render_batch_equals_brute_force_next_to_the_surface() {
    let (width, height) = (48u32, 32u32);
    let intrinsics =
        DMat3::from_cols(DVec3::new(40.0, 0.0, 0.0), DVec3::new(0.0, 40.0, 0.0), DVec3::new(23.5, 15.5, 1.0));
    let source = PinholeCamera { width, height, intrinsics, world_from_camera: DMat4::IDENTITY };
    let depth_at = |u: f64, v: f64| {
        if (16.0..30.0).contains(&u) && (10.0..22.0).contains(&v) { 3.0 } else { 6.0 + 0.03 * u + 0.02 * v }
    };
    let values = (0..width * height).map(|i| depth_at(f64::from(i % width), f64::from(i / width)) as f32).collect();
    let depth = DepthMap { width: width as usize, height: height as usize, values };
    let (mut hit, mut everywhere) = (0, 0);
    for (thickness, mesh) in meshes(&depth, &source) {
        for (u, v, fraction, turn) in [(10.3, 5.4, 0.99, 0.0), (22.6, 14.2, 0.98, 0.0), (40.2, 25.7, 0.95, 30.0)] {
            let (eye, target) =
                (source.unproject(u, v, fraction * depth_at(u, v)), source.unproject(u, v, depth_at(u, v)));
            let target = eye + DMat3::from_rotation_y(f64::to_radians(turn)) * (target - eye);
            let novel = PinholeCamera { world_from_camera: look_at(eye, target), ..source };
            let (hits, quads) = assert_hits_are_brute_force(&mesh, &novel, &format!("at ({u}, {v}) skirt {thickness}"));
            (hit, everywhere) = (hit + hits, everywhere + quads);
        }
    }
    assert!(hit > 1000, "the views must see the plane ({hit} pixels hit)");
    assert!(everywhere > 0, "the triangles in front of the cameras must reach every pixel");
}
