//! `datagen synth`: a seeded, analytic dynamic scene ray traced with obvhs, written as a sequence
//! folder in the cog-nvs layout ([`crate::io::sequence`]) with exact ground truth.
//!
//! The scene is a room (checkered floor, striped walls, open top) with static boxes and moving
//! spheres and boxes, seen by a moving camera. Everything is a triangle mesh, so the same geometry
//! that renders the frames answers exact visibility queries for any camera
//! ([`FrameGeometry::is_visible`], [`ground_truth_covisibility`]): the analytic counterpart of the
//! Blender fixtures. Shading is Lambertian with a fixed light, so a surface point has the same
//! colour from every viewpoint. [`write_multiview`] renders the same scene from a rig of
//! synchronised cameras (the multi-camera layout of [`crate::io::multiview`]).

use std::ops::Bound;
use std::path::{Path, PathBuf};
use std::time::Duration;

use glam::{DMat3, DMat4, DVec3, Vec3A};
use image::{GrayImage, RgbImage};
use obvhs::BvhBuildParams;
use obvhs::cwbvh::CwBvh;
use obvhs::cwbvh::builder::build_cwbvh_from_tris;
use obvhs::ray::{Ray, RayHit};
use obvhs::triangle::Triangle;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::config_file::{Checked, KeyError, Validate, check_count, check_float};
use crate::error::{Error, Result};

/// Parameters of a synthetic scene. Defaults give the quickstart's small scene. Every field is
/// checked ([`Validate`]) when a file is loaded, after command-line flags are applied, and by
/// [`SynthScene::new`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SynthConfig {
    /// Frame width in pixels. Valid: even (the video is H.264 4:2:0), 2 to [`MAX_SIDE`].
    pub width: u32,
    /// Frame height in pixels. Valid: even, 2 to [`MAX_SIDE`].
    pub height: u32,
    /// Number of frames. Valid: at least 1, and frames × width × height at most
    /// [`MAX_SCENE_PIXELS`].
    pub frames: u32,
    /// Frame rate of the written video. Valid: finite, in (0, [`MAX_FPS`]].
    pub fps: f64,
    /// Number of moving objects (alternating spheres and boxes); their mask ids are 1..=n.
    /// Valid: 0 to 254.
    pub moving_objects: u32,
    /// Number of static boxes standing on the floor. Valid: 0 to [`MAX_STATIC_OBJECTS`].
    pub static_objects: u32,
    /// Number of thin static objects standing on the floor: upright poles and plates
    /// [`THIN_SIDE`] thick (a pixel or two at the default size), the thin occluders of the
    /// visibility tests. Drawn after everything else, so a scene without them is unchanged.
    /// Valid: 0 to [`MAX_STATIC_OBJECTS`].
    pub thin_objects: u32,
    /// Seed of every random choice (object layout, colours, motion, camera path). Valid: any.
    pub seed: u64,
    /// Horizontal field of view in degrees. Valid: in (1, 170).
    pub fov_deg: f64,
    /// The camera's sweep around the scene over the whole video, degrees (signed: the direction);
    /// absent: drawn from the seed in ±[`MAX_RANDOM_SWEEP_DEG`]. A few degrees give the slow
    /// camera paths of real hand-held videos. Valid: [−[`MAX_SWEEP_DEG`], [`MAX_SWEEP_DEG`]].
    pub camera_sweep_deg: Option<f64>,
}

/// The largest sweep a seed draws, degrees.
pub const MAX_RANDOM_SWEEP_DEG: f64 = 25.0;
/// The largest sweep accepted, degrees: the camera stays on the room's near side of the look-at
/// point (its arc radius is at most 7 m, the back wall 6.5 m behind the look-at point).
pub const MAX_SWEEP_DEG: f64 = 90.0;

/// Widest and tallest frame: 8192 is the wide side of DCI 8K, the largest frame H.264's top
/// level (6.2) encodes; far above the CogNVS paper's 720×480.
pub const MAX_SIDE: u32 = 8192;
/// Most pixels of a whole scene (frames × width × height): the writer holds every frame's
/// colour, depth and ids (8 bytes a pixel) until the video is encoded, so this bounds it to
/// 4 GiB; the paper's clip size (49 × 720 × 480) is 1/30 of it.
pub const MAX_SCENE_PIXELS: u64 = 1 << 29;
/// Fastest frame rate: high-speed cameras' 1000 fps; above that it is a typo.
pub const MAX_FPS: f64 = 1000.0;
/// Most static boxes: they stand in a 5 m × 7 m play area, where a few hundred already fill
/// every spot; the cap bounds the scene's triangle count.
pub const MAX_STATIC_OBJECTS: u32 = 256;
/// Range of the thickness of thin objects, in world units (metres): 2 to 5 cm, one to three
/// pixels at the default size and distance (a focal length of 277 px, objects 4 to 9 m away).
pub const THIN_SIDE: (f64, f64) = (0.02, 0.05);

impl Default for SynthConfig {
    fn default() -> Self {
        Self {
            width: 320,
            height: 192,
            frames: 25,
            fps: 24.0,
            moving_objects: 3,
            static_objects: 3,
            thin_objects: 0,
            seed: 0,
            fov_deg: 60.0,
            camera_sweep_deg: None,
        }
    }
}

/// Most moving objects a mask can label (ids 1..=254; 255 is "void" in the mask convention).
const MAX_MOVING_OBJECTS: u32 = 254;

impl Validate for SynthConfig {
    /// Rejects impossible or unallocatable parameters, naming the key (the flag's name with
    /// `_` for `-`).
    fn validate(&self) -> Checked {
        for (key, value) in [("width", self.width), ("height", self.height)] {
            check_count(key, value, 2, MAX_SIDE.into())?;
            if !value.is_multiple_of(2) {
                return Err(KeyError::new(key, format!("must be even (H.264 4:2:0 video), got {value}")));
            }
        }
        check_count("frames", self.frames, 1, u64::MAX)?;
        let pixels = u64::from(self.frames) * u64::from(self.width) * u64::from(self.height);
        if pixels > MAX_SCENE_PIXELS {
            return Err(KeyError::new(
                "frames",
                format!(
                    "{} frames of {}x{} are {pixels} pixels, more than the {MAX_SCENE_PIXELS} a scene may hold \
                     in memory; use fewer frames or smaller ones",
                    self.frames, self.width, self.height
                ),
            ));
        }
        check_float("fps", self.fps, (Bound::Excluded(0.0), Bound::Included(MAX_FPS)))?;
        check_count("moving_objects", self.moving_objects, 0, MAX_MOVING_OBJECTS.into())?;
        check_count("static_objects", self.static_objects, 0, MAX_STATIC_OBJECTS.into())?;
        if let Some(sweep) = self.camera_sweep_deg {
            check_float("camera_sweep_deg", sweep, -MAX_SWEEP_DEG..=MAX_SWEEP_DEG)?;
        }
        check_count("thin_objects", self.thin_objects, 0, MAX_STATIC_OBJECTS.into())?;
        check_float("fov_deg", self.fov_deg, (Bound::Excluded(1.0), Bound::Excluded(170.0)))
    }
}

impl SynthConfig {
    /// Intrinsics K in pixels: square pixels, centred principal point at `W/2 − 0.5`.
    pub fn intrinsics(&self) -> DMat3 {
        let focal = 0.5 * self.width as f64 / (0.5 * self.fov_deg.to_radians()).tan();
        let (cx, cy) = (self.width as f64 / 2.0 - 0.5, self.height as f64 / 2.0 - 0.5);
        DMat3::from_cols(DVec3::new(focal, 0.0, 0.0), DVec3::new(0.0, focal, 0.0), DVec3::new(cx, cy, 1.0))
    }
}

/// Room extents (world units; y up): floor at y = 0, walls at x = ±ROOM_HALF_WIDTH and z = ROOM_BACK.
pub(crate) const ROOM_HALF_WIDTH: f64 = 5.0;
pub(crate) const ROOM_FRONT: f64 = -4.0;
pub(crate) const ROOM_BACK: f64 = 12.0;
pub(crate) const WALL_HEIGHT: f64 = 3.5;
/// Region of the floor where objects are placed and move.
const PLAY_X: (f64, f64) = (-2.5, 2.5);
const PLAY_Z: (f64, f64) = (3.0, 8.0);
/// The camera looks at this point while moving on an arc around it.
pub(crate) const LOOK_AT: DVec3 = DVec3::new(0.0, 0.6, 5.5);
const SPHERE_SEGMENTS: (usize, usize) = (32, 16);
/// Direction towards the light and the ambient term of the Lambertian shading.
const LIGHT_DIRECTION: DVec3 = DVec3::new(0.35, 0.85, -0.4);
const AMBIENT: f64 = 0.35;

#[derive(Debug, Clone, Copy, PartialEq)]
enum Shape {
    Sphere { radius: f64 },
    Cuboid { half: DVec3 },
}

/// A procedural texture: checks of two colours in the surface's local coordinates.
#[derive(Debug, Clone, Copy)]
struct Material {
    colours: [[f64; 3]; 2],
    check: f64,
}

impl Material {
    fn albedo(&self, local: DVec3) -> [f64; 3] {
        let cell = (local / self.check).floor();
        let parity = (cell.x + cell.y + cell.z).rem_euclid(2.0) as usize;
        let [r, g, b] = self.colours[parity];
        // A smooth shading ramp across each check gives texture inside it without aliasing.
        let stripe = 0.85 + 0.15 * ((local.x + local.y + local.z) * std::f64::consts::TAU / self.check).sin();
        [r * stripe, g * stripe, b * stripe]
    }
}

/// One object: its shape, texture and motion.
#[derive(Debug, Clone)]
struct Object {
    shape: Shape,
    material: Material,
    /// 0 for static geometry, else the moving-object id written to masks.
    mask_id: u8,
    start: DVec3,
    velocity: DVec3,
    spin: f64,
}

impl Object {
    /// `world_from_object` at time `seconds`: bouncing inside the play region, spinning about y.
    fn world_from_object(&self, seconds: f64) -> DMat4 {
        let bounce = |start: f64, speed: f64, (lo, hi): (f64, f64)| {
            let span = hi - lo;
            let phase = (start - lo + speed * seconds).rem_euclid(2.0 * span);
            lo + if phase <= span { phase } else { 2.0 * span - phase }
        };
        let position = DVec3::new(
            bounce(self.start.x, self.velocity.x, PLAY_X),
            self.start.y,
            bounce(self.start.z, self.velocity.z, PLAY_Z),
        );
        DMat4::from_translation(position) * DMat4::from_rotation_y(self.spin * seconds)
    }

    fn triangles_in_object(&self) -> Vec<[DVec3; 3]> {
        match self.shape {
            Shape::Sphere { radius } => sphere_triangles(radius),
            Shape::Cuboid { half } => cuboid_triangles(half),
        }
    }
}

fn cuboid_triangles(half: DVec3) -> Vec<[DVec3; 3]> {
    let corner = |i: usize| {
        DVec3::new(
            if i & 1 == 0 { -half.x } else { half.x },
            if i & 2 == 0 { -half.y } else { half.y },
            if i & 4 == 0 { -half.z } else { half.z },
        )
    };
    // Each face as four corner indices in order around it.
    const FACES: [[usize; 4]; 6] = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]];
    FACES
        .iter()
        .flat_map(|f| [[corner(f[0]), corner(f[1]), corner(f[2])], [corner(f[0]), corner(f[2]), corner(f[3])]])
        .collect()
}

fn sphere_triangles(radius: f64) -> Vec<[DVec3; 3]> {
    let (slices, stacks) = SPHERE_SEGMENTS;
    let point = |slice: usize, stack: usize| {
        let theta = std::f64::consts::PI * stack as f64 / stacks as f64;
        let phi = std::f64::consts::TAU * slice as f64 / slices as f64;
        radius * DVec3::new(theta.sin() * phi.cos(), theta.cos(), theta.sin() * phi.sin())
    };
    let mut triangles = Vec::with_capacity(slices * stacks * 2);
    for stack in 0..stacks {
        for slice in 0..slices {
            let (a, b) = (point(slice, stack), point(slice + 1, stack));
            let (c, d) = (point(slice, stack + 1), point(slice + 1, stack + 1));
            if stack > 0 {
                triangles.push([a, b, d]);
            }
            if stack + 1 < stacks {
                triangles.push([a, d, c]);
            }
        }
    }
    triangles
}

/// The scene: room, objects and camera path, all fixed by the config's seed.
#[derive(Debug, Clone)]
pub struct SynthScene {
    config: SynthConfig,
    room: Vec<([DVec3; 3], Material)>,
    objects: Vec<Object>,
    camera_sweep_deg: f64,
    camera_radius: f64,
    camera_height: f64,
}

/// Which surface a ray hit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfaceHit {
    /// Distance along the (unit) ray.
    pub distance: f64,
    /// Hit point in world coordinates.
    pub point_in_world: DVec3,
    /// Moving-object id (0 for the room and static objects).
    pub mask_id: u8,
    /// Shaded colour, linear in [0, 1].
    pub colour: [f64; 3],
}

/// The scene's triangles at one instant with a BVH over them.
pub struct FrameGeometry {
    triangles: Vec<Triangle>,
    /// Per triangle: index into the room list (`< room_len`) or object index + room_len.
    owners: Vec<u32>,
    room_len: u32,
    bvh: CwBvh,
    object_from_world: Vec<DMat4>,
    world_from_object: Vec<DMat4>,
}

impl SynthScene {
    /// Lays out the scene from `config`, after checking it ([`Validate`]).
    pub fn new(config: &SynthConfig) -> Result<Self> {
        config.validate()?;
        let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
        let colour = |rng: &mut ChaCha8Rng| {
            [rng.random_range(0.15..0.95), rng.random_range(0.15..0.95), rng.random_range(0.15..0.95)]
        };
        let material = |rng: &mut ChaCha8Rng, check: f64| Material { colours: [colour(rng), colour(rng)], check };

        let floor = material(&mut rng, 1.0);
        let walls = material(&mut rng, 1.2);
        let (x0, x1, z0, z1, h) = (-ROOM_HALF_WIDTH, ROOM_HALF_WIDTH, ROOM_FRONT, ROOM_BACK, WALL_HEIGHT);
        let quad = |a: DVec3, b: DVec3, c: DVec3, d: DVec3| [[a, b, c], [a, c, d]];
        let mut room = Vec::new();
        for triangle in
            quad(DVec3::new(x0, 0.0, z0), DVec3::new(x1, 0.0, z0), DVec3::new(x1, 0.0, z1), DVec3::new(x0, 0.0, z1))
        {
            room.push((triangle, floor));
        }
        let wall_quads = [
            quad(DVec3::new(x0, 0.0, z1), DVec3::new(x1, 0.0, z1), DVec3::new(x1, h, z1), DVec3::new(x0, h, z1)),
            quad(DVec3::new(x0, 0.0, z0), DVec3::new(x0, 0.0, z1), DVec3::new(x0, h, z1), DVec3::new(x0, h, z0)),
            quad(DVec3::new(x1, 0.0, z0), DVec3::new(x1, h, z0), DVec3::new(x1, h, z1), DVec3::new(x1, 0.0, z1)),
        ];
        for triangle in wall_quads.into_iter().flatten() {
            room.push((triangle, walls));
        }

        let mut objects = Vec::new();
        for _ in 0..config.static_objects {
            let half = DVec3::new(rng.random_range(0.2..0.6), rng.random_range(0.2..0.8), rng.random_range(0.2..0.6));
            let start =
                DVec3::new(rng.random_range(PLAY_X.0..PLAY_X.1), half.y, rng.random_range(PLAY_Z.0..PLAY_Z.1 + 2.0));
            let material = material(&mut rng, 0.3);
            objects.push(Object {
                shape: Shape::Cuboid { half },
                material,
                mask_id: 0,
                start,
                velocity: DVec3::ZERO,
                spin: 0.0,
            });
        }
        for index in 0..config.moving_objects {
            let shape = if index % 2 == 0 {
                Shape::Sphere { radius: rng.random_range(0.25..0.5) }
            } else {
                Shape::Cuboid { half: DVec3::splat(rng.random_range(0.2..0.4)) }
            };
            let height = match shape {
                Shape::Sphere { radius } => radius,
                Shape::Cuboid { half } => half.y,
            };
            let start = DVec3::new(rng.random_range(PLAY_X.0..PLAY_X.1), height, rng.random_range(PLAY_Z.0..PLAY_Z.1));
            let heading = rng.random_range(0.0..std::f64::consts::TAU);
            let speed = rng.random_range(0.8..1.8);
            let velocity = DVec3::new(heading.cos() * speed, 0.0, heading.sin() * speed);
            let material = material(&mut rng, 0.25);
            let spin = rng.random_range(-1.5..1.5);
            objects.push(Object { shape, material, mask_id: (index + 1) as u8, start, velocity, spin });
        }
        // The sweep is drawn even when the config sets it, so the rest of the scene stays the seed's.
        let (drawn_sweep_deg, camera_radius, camera_height) = (
            rng.random_range(-MAX_RANDOM_SWEEP_DEG..MAX_RANDOM_SWEEP_DEG),
            rng.random_range(5.5..7.0),
            rng.random_range(1.2..2.2),
        );
        let camera_sweep_deg = config.camera_sweep_deg.unwrap_or(drawn_sweep_deg);
        for index in 0..config.thin_objects {
            let thin = rng.random_range(THIN_SIDE.0..THIN_SIDE.1) / 2.0;
            let height = rng.random_range(0.4..1.2);
            // Alternately a pole (thin both ways) and a plate (thin across z, facing the room's
            // front, up to a metre wide).
            let width = if index % 2 == 0 { thin } else { rng.random_range(0.2..0.5) };
            let half = DVec3::new(width, height, thin);
            let start = DVec3::new(rng.random_range(PLAY_X.0..PLAY_X.1), height, rng.random_range(PLAY_Z.0..PLAY_Z.1));
            let material = material(&mut rng, 0.3);
            objects.push(Object {
                shape: Shape::Cuboid { half },
                material,
                mask_id: 0,
                start,
                velocity: DVec3::ZERO,
                spin: 0.0,
            });
        }
        Ok(Self { config: config.clone(), room, objects, camera_sweep_deg, camera_radius, camera_height })
    }

    /// The scene's configuration.
    pub fn config(&self) -> &SynthConfig {
        &self.config
    }

    /// Time of `frame` in seconds.
    pub fn seconds(&self, frame: u32) -> f64 {
        frame as f64 / self.config.fps
    }

    /// Source camera pose of `frame`: on an arc around the look-at point, OpenCV axes.
    pub fn world_from_camera(&self, frame: u32) -> DMat4 {
        let progress = if self.config.frames > 1 { frame as f64 / (self.config.frames - 1) as f64 } else { 0.0 };
        let angle = (self.camera_sweep_deg * (progress - 0.5)).to_radians();
        let eye = LOOK_AT
            + DVec3::new(
                self.camera_radius * angle.sin(),
                self.camera_height + 0.3 * progress,
                -self.camera_radius * angle.cos(),
            );
        look_at(eye, LOOK_AT)
    }

    /// The scene's triangles at `frame`, with a BVH.
    pub fn frame_geometry(&self, frame: u32) -> FrameGeometry {
        let seconds = self.seconds(frame);
        let world_from_object: Vec<DMat4> = self.objects.iter().map(|o| o.world_from_object(seconds)).collect();
        let mut triangles = Vec::new();
        let mut owners = Vec::new();
        let to_tri = |[a, b, c]: [DVec3; 3]| Triangle {
            v0: Vec3A::from(a.as_vec3()),
            v1: Vec3A::from(b.as_vec3()),
            v2: Vec3A::from(c.as_vec3()),
        };
        for (index, (triangle, _)) in self.room.iter().enumerate() {
            triangles.push(to_tri(*triangle));
            owners.push(index as u32);
        }
        let room_len = self.room.len() as u32;
        for (index, object) in self.objects.iter().enumerate() {
            let transform = world_from_object[index];
            for triangle in object.triangles_in_object() {
                triangles.push(to_tri(triangle.map(|p| transform.transform_point3(p))));
                owners.push(room_len + index as u32);
            }
        }
        let bvh = build_cwbvh_from_tris(&triangles, BvhBuildParams::medium_build(), &mut Duration::default());
        let object_from_world = world_from_object.iter().map(|m| m.inverse()).collect();
        FrameGeometry { triangles, owners, room_len, bvh, object_from_world, world_from_object }
    }

    /// Traces one ray at `frame`'s geometry and shades the hit.
    pub fn shade(&self, geometry: &FrameGeometry, origin: DVec3, direction: DVec3) -> Option<SurfaceHit> {
        let (distance, triangle) = geometry.first_hit(origin, direction, f64::INFINITY)?;
        let point_in_world = origin + direction * distance;
        let owner = geometry.owners[triangle];
        let (material, local, normal, mask_id) = if owner < geometry.room_len {
            let (_, material) = &self.room[owner as usize];
            (material, point_in_world, geometry.triangle_normal(triangle), 0)
        } else {
            let index = (owner - geometry.room_len) as usize;
            let object = &self.objects[index];
            let local = geometry.object_from_world[index].transform_point3(point_in_world);
            let normal = match object.shape {
                Shape::Sphere { .. } => geometry.world_from_object[index].transform_vector3(local).normalize(),
                Shape::Cuboid { .. } => geometry.triangle_normal(triangle),
            };
            (&object.material, local, normal, object.mask_id)
        };
        // Lambertian with a two-sided normal: the side facing the viewer is lit.
        let normal = if normal.dot(direction) > 0.0 { -normal } else { normal };
        let light = AMBIENT + (1.0 - AMBIENT) * normal.dot(LIGHT_DIRECTION.normalize()).max(0.0);
        let colour = material.albedo(local).map(|c| (c * light).clamp(0.0, 1.0));
        Some(SurfaceHit { distance, point_in_world, mask_id, colour })
    }

    /// Renders `frame` from its source camera.
    pub fn render_frame(&self, frame: u32) -> RenderedFrame {
        let geometry = self.frame_geometry(frame);
        self.render_view(&geometry, &self.world_from_camera(frame), &self.config.intrinsics())
    }

    /// Renders `geometry` from any camera with intrinsics `intrinsics` at the config's size.
    pub fn render_view(
        &self,
        geometry: &FrameGeometry,
        world_from_camera: &DMat4,
        intrinsics: &DMat3,
    ) -> RenderedFrame {
        let (width, height) = (self.config.width as usize, self.config.height as usize);
        let camera_from_pixel = intrinsics.inverse();
        let eye = world_from_camera.transform_point3(DVec3::ZERO);
        let pixels: Vec<(Option<SurfaceHit>, f64)> = (0..width * height)
            .into_par_iter()
            .map(|i| {
                let ray_in_camera = camera_from_pixel * DVec3::new((i % width) as f64, (i / width) as f64, 1.0);
                let direction = world_from_camera.transform_vector3(ray_in_camera).normalize();
                let hit = self.shade(geometry, eye, direction);
                // z-depth = distance × the unit ray's z component in camera space.
                let z_per_distance = 1.0 / ray_in_camera.length();
                (hit, z_per_distance)
            })
            .collect();
        let mut rgb = RgbImage::new(width as u32, height as u32);
        let mut ids = GrayImage::new(width as u32, height as u32);
        let mut depth = vec![0.0f32; width * height];
        let mut points_in_world = vec![None; width * height];
        for (i, (hit, z_per_distance)) in pixels.into_iter().enumerate() {
            let Some(hit) = hit else { continue };
            let (x, y) = ((i % width) as u32, (i / width) as u32);
            rgb.put_pixel(x, y, image::Rgb(hit.colour.map(|c| (c * 255.0).round() as u8)));
            ids.put_pixel(x, y, image::Luma([hit.mask_id]));
            depth[i] = (hit.distance * z_per_distance) as f32;
            points_in_world[i] = Some(hit.point_in_world);
        }
        RenderedFrame { rgb, mask_ids: ids, depth, points_in_world }
    }
}

/// One rendered view: colour, moving-object ids, z-depth (0 where no surface) and hit points.
#[derive(Debug, Clone)]
pub struct RenderedFrame {
    /// Shaded colour.
    pub rgb: RgbImage,
    /// Moving-object id per pixel (0 static or nothing).
    pub mask_ids: GrayImage,
    /// z-depth along the optical axis, row-major; 0 where the ray escapes (invalid depth).
    pub depth: Vec<f32>,
    /// Exact surface point per pixel, `None` where the ray escapes.
    pub points_in_world: Vec<Option<DVec3>>,
}

impl FrameGeometry {
    /// First intersection with any triangle closer than `max_distance`: (distance, triangle index).
    pub fn first_hit(&self, origin: DVec3, direction: DVec3, max_distance: f64) -> Option<(f64, usize)> {
        let ray = Ray::new(Vec3A::from(origin.as_vec3()), Vec3A::from(direction.as_vec3()), 0.0, max_distance as f32);
        let mut hit = RayHit::none();
        let found = self.bvh.ray_traverse(ray, &mut hit, |ray, id| {
            self.triangles[self.bvh.primitive_indices[id] as usize].intersect(ray)
        });
        found.then(|| (hit.t as f64, self.bvh.primitive_indices[hit.primitive_id as usize] as usize))
    }

    fn triangle_normal(&self, triangle: usize) -> DVec3 {
        self.triangles[triangle].compute_normal().as_dvec3().normalize()
    }

    /// Whether `point` (on a surface of this geometry) is visible from `eye`: nothing intersects
    /// the open segment between them, up to a relative epsilon at the point's end.
    pub fn is_visible(&self, point: DVec3, eye: DVec3) -> bool {
        let offset = point - eye;
        let distance = offset.length();
        self.first_hit(eye, offset / distance, distance * (1.0 - VISIBILITY_EPSILON)).is_none()
    }
}

/// Relative slack at the far end of a visibility segment so the surface a point lies on does not
/// occlude it (f32 BVH arithmetic on distances of ~10 units).
pub const VISIBILITY_EPSILON: f64 = 1e-4;

/// Camera pose looking from `eye` at `target` with world y up, OpenCV axes (x right, y down, z forward).
pub fn look_at(eye: DVec3, target: DVec3) -> DMat4 {
    let forward = (target - eye).normalize();
    let right = forward.cross(DVec3::Y).normalize();
    let down = forward.cross(right);
    DMat4::from_cols(right.extend(0.0), down.extend(0.0), forward.extend(0.0), eye.extend(1.0))
}

/// Exact co-visibility of `frame`'s source pixels from a novel camera: a pixel is co-visible iff
/// its surface point lies in front of the novel camera, projects inside its image, and is the
/// first surface along the novel camera's ray (ray cast in the true 3D scene). Row-major.
pub fn ground_truth_covisibility(
    scene: &SynthScene,
    frame: u32,
    source: &RenderedFrame,
    world_from_novel: &DMat4,
    novel_intrinsics: &DMat3,
) -> Vec<bool> {
    let geometry = scene.frame_geometry(frame);
    let novel_from_world = world_from_novel.inverse();
    let eye = world_from_novel.transform_point3(DVec3::ZERO);
    let (width, height) = (scene.config.width as f64, scene.config.height as f64);
    source
        .points_in_world
        .par_iter()
        .map(|point| {
            let Some(point) = *point else { return false };
            let in_novel = novel_from_world.transform_point3(point);
            if in_novel.z <= 0.0 {
                return false;
            }
            let pixel = foundation::camera::pixel_of(novel_intrinsics, in_novel);
            let inside = pixel.x > -0.5 && pixel.x < width - 0.5 && pixel.y > -0.5 && pixel.y < height - 0.5;
            inside && geometry.is_visible(point, eye)
        })
        .collect()
}

/// Where [`write_sequence`] put things.
#[derive(Debug, Clone)]
pub struct SynthOutput {
    /// The sequence folder.
    pub dir: PathBuf,
    /// The contact sheet: rows of sampled frames, columns rgb | depth | moving-object ids.
    pub contact_sheet: PathBuf,
}

/// Renders the scene and writes the sequence folder: `gt_rgb.mp4`, `frames/%05d.png`,
/// `cam_info/megasam_{depth,intrinsics,c2ws}.npy`, `masks/%05d.png` (moving-object ids),
/// `masks_ids.npy`, `meta.json` and `contact_sheet.png`.
pub fn write_sequence(config: &SynthConfig, out: &Path, mut progress: impl FnMut(u32)) -> Result<SynthOutput> {
    let scene = SynthScene::new(config)?;
    for sub in ["", "frames", "cam_info", "masks"] {
        let dir = out.join(sub);
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
    }
    let (width, height, frames) = (config.width as usize, config.height as usize, config.frames as usize);
    let mut rgb_frames = Vec::with_capacity(frames);
    let mut depth = Vec::with_capacity(frames * width * height);
    let mut ids = Vec::with_capacity(frames * width * height);
    let mut poses = Vec::with_capacity(frames * 16);
    let mut sheet_rows = Vec::new();
    for frame in 0..config.frames {
        let rendered = scene.render_frame(frame);
        let png = |sub: &str| out.join(sub).join(format!("{frame:05}.png"));
        save_png(&rendered.rgb, &png("frames"))?;
        save_png(&rendered.mask_ids, &png("masks"))?;
        depth.extend_from_slice(&rendered.depth);
        ids.extend_from_slice(rendered.mask_ids.as_raw());
        poses.extend(scene.world_from_camera(frame).transpose().to_cols_array().iter().map(|&v| v as f32));
        if sheet_frames(config.frames).contains(&frame) {
            sheet_rows.push(vec![
                rendered.rgb.clone(),
                foundation::contact_sheet::colorize_depth(&rendered.depth, width, height),
                foundation::contact_sheet::colorize_ids(&rendered.mask_ids),
            ]);
        }
        rgb_frames.push(rendered.rgb);
        progress(frame + 1);
    }
    let cam = out.join("cam_info");
    crate::io::npy::write_npy(&cam.join("megasam_depth.npy"), &[frames, height, width], &depth)?;
    let k: Vec<f32> = config.intrinsics().transpose().to_cols_array().iter().map(|&v| v as f32).collect();
    crate::io::npy::write_npy(&cam.join("megasam_intrinsics.npy"), &[3, 3], &k)?;
    crate::io::npy::write_npy(&cam.join("megasam_c2ws.npy"), &[frames, 4, 4], &poses)?;
    crate::io::npy::write_npy(&out.join("masks_ids.npy"), &[frames, height, width], &ids)?;
    foundation::video::encode_video(&out.join("gt_rgb.mp4"), &rgb_frames, config.fps)?;
    let meta = serde_json::json!({
        "generator": format!("datagen {}", env!("CARGO_PKG_VERSION")),
        "config": config,
        "conventions": "OpenCV camera axes; world_from_camera; pixel centres at integer coords; z-depth; depth 0 = no surface",
    });
    let meta_path = out.join("meta.json");
    std::fs::write(&meta_path, serde_json::to_vec_pretty(&meta).expect("json"))
        .map_err(|e| Error::io(&meta_path, e))?;
    let contact_sheet = out.join("contact_sheet.png");
    foundation::contact_sheet::write_contact_sheet(&contact_sheet, &sheet_rows)?;
    Ok(SynthOutput { dir: out.to_owned(), contact_sheet })
}

/// Synchronised cameras of a multi-camera scene ([`write_multiview`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraRig {
    /// Number of cameras. Valid: 2 to [`MAX_RIG_CAMERAS`].
    pub cameras: u32,
    /// Yaw between neighbouring cameras about the scene's look-at point, in degrees; the rig is
    /// centred on the source path. Valid: finite, in (0, [`MAX_RIG_SPACING_DEG`]].
    pub spacing_deg: f64,
}

/// Most cameras of a synthetic rig: more than the 16 of Kubric-4D, the largest public rig the
/// readers take.
pub const MAX_RIG_CAMERAS: u32 = 64;

/// Widest yaw between neighbouring synthetic cameras: beyond it neighbours share little of the
/// room.
pub const MAX_RIG_SPACING_DEG: f64 = 90.0;

impl CameraRig {
    /// Rejects a rig outside the documented ranges, naming the parameter.
    pub fn validate(&self) -> Result<()> {
        if !(2..=MAX_RIG_CAMERAS).contains(&self.cameras) {
            return Err(Error::parameter("cameras", format!("must be 2 to {MAX_RIG_CAMERAS}, got {}", self.cameras)));
        }
        if !(self.spacing_deg > 0.0 && self.spacing_deg <= MAX_RIG_SPACING_DEG) {
            let reason = format!("must be a finite number in (0, {MAX_RIG_SPACING_DEG}], got {}", self.spacing_deg);
            return Err(Error::parameter("camera_spacing_deg", reason));
        }
        Ok(())
    }
}

impl SynthScene {
    /// Pose of `camera` of `rig` at `frame`: the source path's pose turned about the look-at
    /// point's vertical axis by (camera − (cameras − 1) / 2) × spacing.
    pub fn rig_world_from_camera(&self, frame: u32, rig: &CameraRig, camera: u32) -> DMat4 {
        let yaw = (f64::from(camera) - f64::from(rig.cameras - 1) / 2.0) * rig.spacing_deg;
        let about_look_at = DMat4::from_translation(LOOK_AT)
            * DMat4::from_rotation_y(yaw.to_radians())
            * DMat4::from_translation(-LOOK_AT);
        about_look_at * self.world_from_camera(frame)
    }
}

/// Renders the scene from every camera of `rig` and writes a synchronised multi-camera folder:
/// `out/camNN/` per camera in the generic layout (`frames/%05d.png`, `depth/%05d.exr`,
/// `cameras.json` with `intrinsics`, `world_from_camera` and `timestamps` in seconds), one world
/// frame for all (see [`crate::io::multiview`]).
pub fn write_multiview(
    config: &SynthConfig,
    rig: &CameraRig,
    out: &Path,
    mut progress: impl FnMut(u32),
) -> Result<PathBuf> {
    rig.validate()?;
    let scene = SynthScene::new(config)?;
    let (width, height) = (config.width as usize, config.height as usize);
    let intrinsics = config.intrinsics();
    let folders: Vec<PathBuf> = (0..rig.cameras).map(|c| out.join(format!("cam{c:02}"))).collect();
    for folder in &folders {
        for sub in ["frames", "depth"] {
            let dir = folder.join(sub);
            std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        }
    }
    let mut poses = vec![Vec::new(); rig.cameras as usize];
    for frame in 0..config.frames {
        let geometry = scene.frame_geometry(frame);
        for (camera, folder) in folders.iter().enumerate() {
            let pose = scene.rig_world_from_camera(frame, rig, camera as u32);
            let rendered = scene.render_view(&geometry, &pose, &intrinsics);
            save_png(&rendered.rgb, &folder.join(format!("frames/{frame:05}.png")))?;
            let depth = foundation::depth::DepthMap { width, height, values: rendered.depth };
            let exr_path = folder.join(format!("depth/{frame:05}.exr"));
            let exr = crate::io::depth_exr::encode_depth_exr(&depth)?;
            std::fs::write(&exr_path, exr).map_err(|e| Error::io(&exr_path, e))?;
            poses[camera].push(foundation::camera::mat4_to_row_major(&pose).to_vec());
        }
        progress(frame + 1);
    }
    let timestamps: Vec<f64> = (0..config.frames).map(|f| scene.seconds(f)).collect();
    for (folder, poses) in folders.iter().zip(poses) {
        let cameras = serde_json::json!({
            "intrinsics": foundation::camera::mat3_to_row_major(&intrinsics).to_vec(),
            "world_from_camera": poses,
            "timestamps": timestamps,
        });
        let path = folder.join("cameras.json");
        std::fs::write(&path, serde_json::to_vec_pretty(&cameras).expect("json")).map_err(|e| Error::io(&path, e))?;
    }
    Ok(out.to_owned())
}

/// Up to four evenly spaced frames shown on the contact sheet.
fn sheet_frames(frames: u32) -> Vec<u32> {
    let mut picked: Vec<u32> = (0..4).map(|k| (k * (frames - 1) + 1) / 3).collect();
    picked.dedup();
    picked
}

pub(crate) fn save_png<P: image::PixelWithColorType>(
    image: &image::ImageBuffer<P, Vec<P::Subpixel>>,
    path: &Path,
) -> Result<()>
where
    [P::Subpixel]: image::EncodableLayout,
{
    image.save(path).map_err(|e| Error::Image { context: path.display().to_string(), reason: e.to_string() })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small() -> SynthConfig {
        SynthConfig { width: 64, height: 48, frames: 3, ..SynthConfig::default() }
    }

    #[test]
    fn look_at_is_a_rigid_opencv_frame() {
        let pose = look_at(DVec3::new(1.0, 2.0, -3.0), DVec3::new(0.0, 0.5, 4.0));
        let rotation = DMat3::from_mat4(pose);
        assert!((rotation.determinant() - 1.0).abs() < 1e-12);
        assert!((rotation * rotation.transpose()).abs_diff_eq(DMat3::IDENTITY, 1e-12));
        // Camera y (down) has a negative world-y component: the image is upright.
        assert!(rotation.y_axis.y < 0.0);
    }

    #[test]
    fn depth_is_z_depth_of_the_hit_point() {
        let scene = SynthScene::new(&small()).unwrap();
        let frame = scene.render_frame(1);
        let camera_from_world = scene.world_from_camera(1).inverse();
        let k = scene.config().intrinsics();
        let mut checked = 0;
        for (i, point) in frame.points_in_world.iter().enumerate() {
            let Some(point) = point else { continue };
            let in_camera = camera_from_world.transform_point3(*point);
            assert!((in_camera.z - frame.depth[i] as f64).abs() < 1e-4 * in_camera.z, "pixel {i}");
            let pixel = k * (in_camera / in_camera.z);
            assert!((pixel.x - (i % 64) as f64).abs() < 1e-3 && (pixel.y - (i / 64) as f64).abs() < 1e-3);
            checked += 1;
        }
        assert!(checked > 64 * 48 / 2, "most pixels see a surface");
    }

    #[test]
    fn same_seed_same_scene_other_seed_other_scene() {
        let a = SynthScene::new(&small()).unwrap().render_frame(2);
        let b = SynthScene::new(&small()).unwrap().render_frame(2);
        let c = SynthScene::new(&SynthConfig { seed: 7, ..small() }).unwrap().render_frame(2);
        assert_eq!(a.rgb, b.rgb);
        assert_eq!(a.depth, b.depth);
        assert_ne!(a.rgb, c.rgb);
    }

    #[test]
    fn moving_objects_appear_in_masks_and_move() {
        let config = SynthConfig { frames: 24, ..small() };
        let scene = SynthScene::new(&config).unwrap();
        let first = scene.render_frame(0).mask_ids;
        let last = scene.render_frame(23).mask_ids;
        assert!(first.pixels().any(|p| p.0[0] > 0));
        assert_ne!(first, last);
    }

    #[test]
    fn source_camera_sees_its_own_pixels() {
        let scene = SynthScene::new(&small()).unwrap();
        let frame = scene.render_frame(0);
        let covisible =
            ground_truth_covisibility(&scene, 0, &frame, &scene.world_from_camera(0), &scene.config().intrinsics());
        let valid = frame.points_in_world.iter().filter(|p| p.is_some()).count();
        let kept = covisible.iter().filter(|&&c| c).count();
        assert_eq!(kept, valid, "every surface pixel is visible from its own camera");
    }

    #[test]
    fn impossible_parameters_are_named() {
        for (config, name) in [
            (SynthConfig { frames: 0, ..small() }, "frames"),
            (SynthConfig { width: 0, ..small() }, "width"),
            (SynthConfig { height: 47, ..small() }, "height"),
            (SynthConfig { fps: 0.0, ..small() }, "fps"),
            (SynthConfig { width: 2_000_000, ..small() }, "width"),
            (SynthConfig { height: 4_000_000, ..small() }, "height"),
            (SynthConfig { width: 8192, height: 8192, frames: 100, ..small() }, "frames"),
            (SynthConfig { fps: f64::NAN, ..small() }, "fps"),
            (SynthConfig { static_objects: u32::MAX, ..small() }, "static_objects"),
            (SynthConfig { fov_deg: f64::INFINITY, ..small() }, "fov_deg"),
        ] {
            let error = SynthScene::new(&config).unwrap_err().to_string();
            assert!(error.contains(&format!("`{name}`")), "{error}");
        }
    }
}
