//! A depth map lifted to a triangle mesh in world space, and the reference answers to ray queries
//! against it.
//!
//! Two triangles per 2×2 pixel quad, with vertices at the surface points of the pixel centres. A
//! quad with invalid depth at a corner has no triangles, nor has one spanning a depth
//! discontinuity (max/min of its depths above `discontinuity_ratio`), which would otherwise be a
//! "rubber sheet" joining foreground and background. Optionally such a quad becomes an *occluder
//! skirt* instead: its corners are pulled along their pixel rays to at most
//! `(1 + occluder_thickness)` × its nearest depth, so that the unobserved space just behind a
//! foreground edge is solid for a limited depth. Skirts block visibility segments but are never
//! rendered. Thickness 0 is the plain cut mesh; a very large one approaches the uncut mesh.
//!
//! Every co-visibility segment ends in obvhs's f32 ray/triangle test on these triangles; every
//! render ray in the watertight f64 test of [`super::ray_triangle`], which also counts the mesh's
//! vertices as surface. The mesh itself answers single rays from anywhere: through an obvhs BVH
//! when built with [`Accelerator::Cwbvh`], else by testing every triangle. The production path,
//! the rays leaving one novel camera in a batch, is [`super::mesh_view::MeshView`]; it must equal
//! those answers exactly (integration tests).

use std::sync::OnceLock;
use std::time::Duration;

use glam::{DMat3, DVec3, Vec3A};
use obvhs::BvhBuildParams;
use obvhs::cwbvh::CwBvh;
use obvhs::cwbvh::builder::build_cwbvh_from_tris;
use obvhs::ray::{Ray, RayHit};
use obvhs::triangle::Triangle;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::config_file::{Checked, Validate, check_float};
use crate::geometry::ray_triangle::RenderRay;
use foundation::camera::PinholeCamera;
use foundation::depth::DepthMap;

/// How the mesh is cut and how unobserved space is treated.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MeshConfig {
    /// A quad whose max/min depth exceeds this spans a discontinuity (the fixtures' README
    /// baseline uses 1.05). Valid: finite, ≥ 1 (max/min of positive depths is never below 1;
    /// 1 cuts every quad that is not fronto-parallel).
    pub discontinuity_ratio: f64,
    /// Depth of the occluder skirt behind foreground edges, relative to the edge's depth
    /// (0: plain cut mesh, gaps behind every edge). Keep it small (≤ 1): skirts reaching far
    /// behind the scene make degenerate triangles. Valid: finite, in [0, [`MAX_OCCLUDER_THICKNESS`]].
    pub occluder_thickness: f64,
    /// The ray-query structure. Both give the same answers (the brute-force test checks each).
    /// Valid: `image-grids` or `cwbvh`.
    pub accelerator: Accelerator,
}

/// Thickest skirt accepted: 100 × the edge's depth already reaches behind any scene a depth
/// map can hold (depths in one frame rarely span two orders of magnitude); more only breeds
/// degenerate triangles.
pub const MAX_OCCLUDER_THICKNESS: f64 = 100.0;

impl Validate for MeshConfig {
    fn validate(&self) -> Checked {
        check_float("discontinuity_ratio", self.discontinuity_ratio, 1.0..)?;
        check_float("occluder_thickness", self.occluder_thickness, 0.0..=MAX_OCCLUDER_THICKNESS)
    }
}

impl Default for MeshConfig {
    fn default() -> Self {
        Self {
            discontinuity_ratio: 1.05,
            occluder_thickness: DEFAULT_OCCLUDER_THICKNESS,
            accelerator: Accelerator::default(),
        }
    }
}

/// Default skirt depth, chosen on the Blender fixtures (the `occluder_thickness` integration
/// test prints the sweep): 5 % cuts scene_101's false-keep from 1.00 % to 0.61 % and *raises*
/// IoU (0.985 → 0.987); thicker skirts lower false-keep further but cost more IoU than they gain.
pub const DEFAULT_OCCLUDER_THICKNESS: f64 = 0.05;

/// The structure that answers ray queries against a frame's mesh.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Accelerator {
    /// Nothing built per frame: the batches of rays leaving a novel camera are scanned on its pixel
    /// grid ([`super::mesh_view::MeshView`]); a single ray from elsewhere tests every triangle.
    #[default]
    ImageGrids,
    /// An obvhs compressed-wide BVH over all triangles (SAH build per frame) answers every ray
    /// one at a time: the independent reference the image grids are compared with.
    Cwbvh,
}

/// What the quad whose corner 0 is a pixel holds (corners 0 = (u, v), 1 = (u+1, v), 2 = (u, v+1),
/// 3 = (u+1, v+1); triangles as in [`SPLIT`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Quad {
    /// No triangles: a corner has invalid depth, it spans a discontinuity without a skirt, or the
    /// pixel is in the last column or row.
    Empty,
    /// Two triangles joining its corners' surface points.
    Surface,
    /// An occluder skirt, whose two triangles are `skirts[index]`.
    Skirt(u32),
}

/// Most pixels a side of a depth map, so that a pixel's column and row fit in 16 bits (the
/// readers stop at [`crate::io::npy::MAX_SIDE_PX`]).
pub const MAX_SIDE: usize = u16::MAX as usize;

/// The two triangles of a quad, as corner indices (see [`Quad`]).
pub(crate) const SPLIT: [[usize; 3]; 2] = [[0, 1, 2], [1, 3, 2]];

/// A pixel's eight neighbours, as offsets.
const NEIGHBOURS: [(isize, isize); 8] = [(-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)];

/// Where a point from another camera lies against a mesh's surface ([`DepthMesh::footprint_of`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Footprint {
    /// It is the surface of this pixel (row-major index): the pixel's triangles never hide it.
    Own(u32),
    /// It lies behind the pixel's sample where no triangle says what is between the samples: the
    /// pixel's surface hides it.
    Behind,
    /// Neither (in front of the pixel's surface, behind it where triangles are, or outside the
    /// image or its valid depth): the triangles decide.
    Elsewhere,
}

/// The four quarters of a pixel's footprint, as the signs of their directions in (x, y).
const QUARTERS: [(isize, isize); 4] = [(-1, -1), (1, -1), (-1, 1), (1, 1)];

/// A footprint fragment's side in pixels: half a pixel, from the pixel's centre to the edge of
/// its footprint (pixel k covers [k − 0.5, k + 0.5)).
const FRAGMENT_SIDE: f64 = 0.5;

/// Finite and positive: `depth > 0.0 && depth < f32::INFINITY` (false for NaN) by one integer
/// comparison, for the per-pixel passes. The bit patterns of the positive finite floats are
/// exactly 1..=0x7f7f_ffff; zero wraps to the top, and negative values, infinities and NaNs all
/// lie above.
fn valid(depth: f32) -> bool {
    depth.to_bits().wrapping_sub(1) < 0x7f7f_ffff
}

/// The mesh of one frame.
pub struct DepthMesh {
    width: usize,
    height: usize,
    /// The depth map it was lifted from (its footprint fragments are lifted at these depths).
    depth: Vec<f32>,
    /// The camera it was lifted from, and its K inverted.
    camera: PinholeCamera,
    camera_from_pixel: DMat3,
    /// Two depths within this ratio are one surface (`MeshConfig::discontinuity_ratio`).
    discontinuity_ratio: f64,
    /// Every footprint fragment, listed once for the single-ray queries that test them all.
    all_fragments: OnceLock<Vec<[DVec3; 4]>>,
    /// World-space surface point of each pixel (row-major), NaN where depth is invalid (24 bytes
    /// a pixel, where an `Option` takes 32: the per-view passes read them all). The triangles'
    /// corners are these points in f32.
    points: Vec<DVec3>,
    /// Per pixel, the quad whose corner 0 it is; quads are named by that pixel throughout.
    quads: Vec<Quad>,
    skirts: Vec<[Triangle; 2]>,
    /// The smallest valid depth.
    nearest_depth: f64,
    /// Built for [`Accelerator::Cwbvh`] only.
    bvh: Option<MeshBvh>,
}

/// The obvhs BVH over a mesh's triangles, with the quad of each triangle pair.
struct MeshBvh {
    bvh: CwBvh,
    triangles: Vec<Triangle>,
    quad_of: Vec<u32>,
}

impl DepthMesh {
    /// Lifts `depth` seen by `camera` into a mesh (and builds its BVH if `config` asks for one).
    pub fn new(depth: &DepthMap, camera: &PinholeCamera, config: &MeshConfig) -> Self {
        let (width, height) = (depth.width, depth.height);
        assert!(width.max(height) <= MAX_SIDE, "depth maps are read up to {MAX_SIDE} px a side");
        let center = camera.center();
        // `camera.pixel_ray` with K inverted once.
        let camera_from_pixel = camera.intrinsics.inverse();
        let ray = |u: usize, v: usize| {
            camera.world_from_camera.transform_vector3(camera_from_pixel * DVec3::new(u as f64, v as f64, 1.0))
        };
        let row = width.max(1);
        let mut points = vec![DVec3::NAN; width * height];
        let nearest_depth = points
            .par_chunks_mut(row)
            .enumerate()
            .map(|(v, points)| {
                let mut nearest = f64::INFINITY;
                for (u, (point, &d)) in points.iter_mut().zip(&depth.values[v * width..(v + 1) * width]).enumerate() {
                    if valid(d) {
                        *point = center + f64::from(d) * ray(u, v);
                        nearest = nearest.min(f64::from(d));
                    }
                }
                nearest
            })
            .reduce(|| f64::INFINITY, f64::min);
        // Each row of quads classified on its own, with its skirts (by column) kept aside and
        // numbered afterwards in row order.
        let mut quads = vec![Quad::Empty; width * height];
        let skirts_by_row: Vec<Vec<(usize, [Triangle; 2])>> = quads
            .par_chunks_mut(row)
            .enumerate()
            .take(height.saturating_sub(1))
            .map(|(v, kinds)| {
                let mut skirts = Vec::new();
                let (upper, lower) =
                    (&depth.values[v * width..(v + 1) * width], &depth.values[(v + 1) * width..(v + 2) * width]);
                // Per pixel column of the two rows: whether both depths are valid, and the smaller
                // and larger one (each column serves the quads on both sides).
                let column =
                    |u: usize| (valid(upper[u]) & valid(lower[u]), upper[u].min(lower[u]), upper[u].max(lower[u]));
                let mut left = column(0);
                for u in 0..width.saturating_sub(1) {
                    let right = column(u + 1);
                    let ((left_valid, left_near, left_far), (right_valid, right_near, right_far)) = (left, right);
                    left = right;
                    if !(left_valid & right_valid) {
                        continue;
                    }
                    let (near, far) = (f64::from(left_near.min(right_near)), f64::from(left_far.max(right_far)));
                    if far <= near * config.discontinuity_ratio {
                        kinds[u] = Quad::Surface;
                    } else if config.occluder_thickness > 0.0 {
                        let limit = near * (1.0 + config.occluder_thickness);
                        let corner =
                            |(u, v, d): (usize, usize, f32)| (center + f64::from(d).min(limit) * ray(u, v)).as_vec3a();
                        let (d0, d1, d2, d3) = (upper[u], upper[u + 1], lower[u], lower[u + 1]);
                        skirts.push((
                            u,
                            split([(u, v, d0), (u + 1, v, d1), (u, v + 1, d2), (u + 1, v + 1, d3)].map(corner)),
                        ));
                    }
                }
                skirts
            })
            .collect();
        let mut skirts = Vec::new();
        for (v, row_skirts) in skirts_by_row.into_iter().enumerate() {
            for (u, triangles) in row_skirts {
                quads[v * width + u] = Quad::Skirt(skirts.len() as u32);
                skirts.push(triangles);
            }
        }
        let depth = depth.values.clone();
        let camera = *camera;
        let mut mesh = Self {
            width,
            height,
            depth,
            camera,
            camera_from_pixel,
            points,
            quads,
            skirts,
            nearest_depth,
            bvh: None,
            discontinuity_ratio: config.discontinuity_ratio,
            all_fragments: OnceLock::new(),
        };
        if config.accelerator == Accelerator::Cwbvh {
            mesh.bvh = Some(mesh.build_bvh());
        }
        mesh
    }

    /// The obvhs BVH over every triangle.
    fn build_bvh(&self) -> MeshBvh {
        let (mut triangles, mut quad_of) = (Vec::new(), Vec::new());
        for quad in 0..self.quads.len() {
            if self.quads[quad] != Quad::Empty {
                triangles.extend(self.triangles(quad));
                quad_of.push(quad as u32);
            }
        }
        let bvh = build_cwbvh_from_tris(&triangles, BvhBuildParams::fast_build(), &mut Duration::default());
        MeshBvh { bvh, triangles, quad_of }
    }

    /// Image width the mesh was lifted from.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Image height the mesh was lifted from.
    pub fn height(&self) -> usize {
        self.height
    }

    /// The surface point of pixel `index` (row-major), if its depth is valid.
    pub fn point(&self, index: usize) -> Option<DVec3> {
        let point = self.points[index];
        (!point.x.is_nan()).then_some(point)
    }

    /// The quad whose corner 0 is pixel `quad`.
    pub(crate) fn quad(&self, quad: usize) -> Quad {
        self.quads[quad]
    }

    /// The smallest valid depth of the frame.
    pub(crate) fn nearest_depth(&self) -> f64 {
        self.nearest_depth
    }

    /// The two triangles of a quad that has triangles (see [`SPLIT`]).
    pub(crate) fn triangles(&self, quad: usize) -> [Triangle; 2] {
        match self.quads[quad] {
            Quad::Skirt(index) => self.skirts[index as usize],
            _ => split(corner_indices(quad, self.width).map(|p| self.points[p].as_vec3a())),
        }
    }

    /// Whether triangle `half` of `quad` has pixel `exclude` as a corner.
    fn has_corner(&self, quad: usize, half: usize, exclude: Option<usize>) -> bool {
        let corners = corner_indices(quad, self.width);
        exclude.is_some_and(|p| SPLIT[half].iter().any(|&k| corners[k] == p))
    }

    /// Whether a triangle of `quad` (skirts included, those with pixel `exclude` as a corner not)
    /// crosses the segment `ray` before its end.
    pub(crate) fn blocks_segment(&self, quad: usize, ray: &Ray, exclude: Option<usize>) -> bool {
        if self.quads[quad] == Quad::Empty {
            return false;
        }
        let [first, second] = self.triangles(quad);
        (!self.has_corner(quad, 0, exclude) && first.intersect(ray) < ray.tmax)
            || (!self.has_corner(quad, 1, exclude) && second.intersect(ray) < ray.tmax)
    }

    /// The *footprint fragments* of pixel `p`: the quarters of its footprint (the square of
    /// side 1 about its centre in the source image) that no surface quad covers, because the quad
    /// on that side is cut at a depth discontinuity, has a corner without valid depth, or lies
    /// beyond the image's border. Each is the quarter lifted at the pixel's own depth (corners in
    /// [`Quad`] order, corner 0 the pixel's point); none for a pixel without valid depth.
    ///
    /// Why: seen from the source camera's centre, the surface quads and the fragments together
    /// cover the footprint of every valid pixel, so a camera turned about that centre, which
    /// reveals nothing new, sees no crack where the cut mesh has one. Fragments are rendered
    /// ([`RenderRay::triangle_hit`] on their [`SPLIT`] triangles) and never block a visibility
    /// segment.
    pub(crate) fn fragments(&self, p: usize) -> impl Iterator<Item = [DVec3; 4]> + '_ {
        let (u, v) = (p % self.width.max(1), p / self.width.max(1));
        let point = self.point(p);
        QUARTERS.into_iter().filter_map(move |(sx, sy)| {
            let point = point?;
            // The quad on that side, if the image has one there: its corner 0 is the pixel or the
            // neighbour before it on each axis.
            let neighbour = (u.checked_add_signed(sx), v.checked_add_signed(sy));
            if let (Some(nu), Some(nv)) = neighbour
                && nu < self.width
                && nv < self.height
                && self.quads[nv.min(v) * self.width + nu.min(u)] == Quad::Surface
            {
                return None;
            }
            let depth = f64::from(self.depth[p]);
            let center = self.camera.center();
            let lift = |x: f64, y: f64| {
                center
                    + depth
                        * self
                            .camera
                            .world_from_camera
                            .transform_vector3(self.camera_from_pixel * DVec3::new(x, y, 1.0))
            };
            let (x0, y0) = (u as f64, v as f64);
            let (x1, y1) = (x0 + sx as f64 * FRAGMENT_SIDE, y0 + sy as f64 * FRAGMENT_SIDE);
            Some([point, lift(x1, y0), lift(x0, y1), lift(x1, y1)])
        })
    }

    /// Where a point (from another camera's depth) meets this mesh's surface, as the mesh's own
    /// camera sees it: the pixel whose footprint holds the point's image, and whether the point is
    /// that pixel's surface ([`Footprint`]). The surface of a pixel spans the depths its sample's
    /// plane takes over the footprint, widened by `epsilon` (relative) for round-off: a point at
    /// such a depth is the surface the pixel samples, whatever the flat triangles between the
    /// samples say (a concave crease, the bend of a curved surface, or a cut quad beside a
    /// foreground edge, half of which is the background's).
    ///
    /// The plane is known from the eight neighbours on the same surface (depths within
    /// `discontinuity_ratio`; none: the pixel's own depth), in inverse depth, which is affine in
    /// the image on a plane: over the footprint it ranges between the values halfway to the
    /// neighbours in inverse depth (the harmonic mean of the two depths; the arithmetic mean
    /// overshoots on the near side, leaving out the near part of a slanted pixel's own surface).
    /// Exact on planes; on curved surfaces and creases it spans the chords to the neighbours.
    pub fn footprint_of(&self, point: DVec3, epsilon: f64) -> Footprint {
        let Some((at, z)) = self.camera.project(point) else { return Footprint::Elsewhere };
        let (u, v) = (at.x.round(), at.y.round());
        if !(u >= 0.0 && v >= 0.0 && u < self.width as f64 && v < self.height as f64) {
            return Footprint::Elsewhere;
        }
        let (u, v) = (u as usize, v as usize);
        let p = v * self.width + u;
        let depth = self.depth[p];
        if !valid(depth) {
            return Footprint::Elsewhere;
        }
        let own = f64::from(depth);
        // The extremes of inverse depth over the footprint: its own, or halfway to a neighbour.
        let (mut nearest, mut farthest) = (1.0 / own, 1.0 / own);
        for (du, dv) in NEIGHBOURS {
            let (Some(nu), Some(nv)) = (u.checked_add_signed(du), v.checked_add_signed(dv)) else { continue };
            if nu >= self.width || nv >= self.height || !valid(self.depth[nv * self.width + nu]) {
                continue;
            }
            let neighbour = f64::from(self.depth[nv * self.width + nu]);
            if own.max(neighbour) <= own.min(neighbour) * self.discontinuity_ratio {
                let halfway = (1.0 / own + 1.0 / neighbour) / 2.0;
                nearest = nearest.max(halfway);
                farthest = farthest.min(halfway);
            }
        }
        let (low, high) = (1.0 / nearest, 1.0 / farthest);
        if z < low * (1.0 - epsilon) {
            Footprint::Elsewhere
        } else if z <= high * (1.0 + epsilon) {
            Footprint::Own(p as u32)
        } else if self.quarter_is_bare(p, at) {
            Footprint::Behind
        } else {
            Footprint::Elsewhere
        }
    }

    /// Whether the surface at pixel `p`'s point shows `eye` its back: `eye` lies behind the plane
    /// of every surface triangle having `p` as a corner (by more than `epsilon` of its distance,
    /// for round-off), on the side away from the mesh's own camera, which sees their front.
    /// False where `p` has no surface triangle (no valid depth, or every quad around it cut):
    /// there the samples say nothing of the surface's orientation.
    ///
    /// Why: an opaque surface seen from behind is not the surface seen from the front. From
    /// `eye`, the ray to the point arrives through the surface's other side (a closed object's
    /// body, or the far face of a sheet), so what the mesh's camera sees there is not visible
    /// from `eye`, however close the points are.
    pub fn faces_away_from(&self, p: usize, eye: DVec3, epsilon: f64) -> bool {
        let Some(point) = self.point(p) else { return false };
        let (u, v) = (p % self.width, p / self.width);
        let center = self.camera.center();
        let mut any = false;
        // The quads having `p` as a corner: those whose corner 0 is `p` or the pixel before it on
        // each axis; in each, the triangles having `p`'s corner.
        for (du, dv) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
            let (Some(qu), Some(qv)) = (u.checked_sub(du), v.checked_sub(dv)) else { continue };
            let quad = qv * self.width + qu;
            if self.quads[quad] != Quad::Surface {
                continue;
            }
            let corners = corner_indices(quad, self.width);
            let corner = du + 2 * dv;
            for triangle in SPLIT.iter().filter(|triangle| triangle.contains(&corner)) {
                let [a, b, c] = triangle.map(|k| self.points[corners[k]]);
                let normal = (b - a).cross(c - a);
                let (front, seen) = (normal.dot(center - point), normal.dot(eye - point));
                let behind = front * seen < 0.0 && seen.abs() > epsilon * normal.length() * (eye - point).length();
                if !behind {
                    return false;
                }
                any = true;
            }
        }
        any
    }

    /// Whether the quarter of pixel `p`'s footprint that holds the image point `at` has no
    /// triangles under it (the quad on that side has none, or the image ends there), so that only
    /// the pixel's own sample says what is there.
    fn quarter_is_bare(&self, p: usize, at: glam::DVec2) -> bool {
        let (u, v) = (p % self.width, p / self.width);
        let (sx, sy) = (if at.x < u as f64 { -1 } else { 1 }, if at.y < v as f64 { -1 } else { 1 });
        match (u.checked_add_signed(sx), v.checked_add_signed(sy)) {
            (Some(nu), Some(nv)) if nu < self.width && nv < self.height => {
                self.quads[nv.min(v) * self.width + nu.min(u)] == Quad::Empty
            }
            _ => true,
        }
    }

    /// Whether the source image point `at` (pixel coordinates) lies in a surface quad, whose four
    /// samples are one surface (on its closed border included).
    pub fn joined_at(&self, at: glam::DVec2) -> bool {
        let (u, v) = (at.x.floor(), at.y.floor());
        if !(u >= 0.0 && v >= 0.0 && u + 1.0 < self.width as f64 && v + 1.0 < self.height as f64) {
            return false;
        }
        self.quads[v as usize * self.width + u as usize] == Quad::Surface
    }

    /// The nearest hit of `ray` on a fragment's closed triangles (see [`Self::fragments`]).
    pub(crate) fn fragment_hit(fragment: &[DVec3; 4], ray: &RenderRay) -> Option<f64> {
        let [first, second] = SPLIT.map(|[a, b, c]| ray.triangle_hit([fragment[a], fragment[b], fragment[c]]));
        nearest(first, second)
    }

    /// The nearest fragment that `ray` hits, testing every one.
    fn fragment_hit_brute_force(&self, ray: &RenderRay) -> Option<f64> {
        let all = self.all_fragments.get_or_init(|| (0..self.points.len()).flat_map(|p| self.fragments(p)).collect());
        all.iter().map(|fragment| Self::fragment_hit(fragment, ray)).fold(None, nearest)
    }

    /// The nearest hit distance of `ray` on a surface quad's closed triangles
    /// ([`RenderRay::triangle_hit`]); None for a miss, a skirt or an empty quad.
    pub(crate) fn surface_hit(&self, quad: usize, ray: &RenderRay) -> Option<f64> {
        if self.quads[quad] != Quad::Surface {
            return None;
        }
        let corners = corner_indices(quad, self.width).map(|p| self.points[p]);
        let [first, second] = SPLIT.map(|[a, b, c]| ray.triangle_hit([corners[a], corners[b], corners[c]]));
        nearest(first, second)
    }

    /// Whether any triangle (skirts included) other than those with pixel `exclude` as a corner
    /// crosses the segment from `from` to `to`, shortened by `epsilon` (relative) at `to`.
    pub fn segment_blocked(&self, from: DVec3, to: DVec3, exclude: Option<u32>, epsilon: f64) -> bool {
        let Some(MeshBvh { bvh, triangles, quad_of }) = &self.bvh else {
            return self.segment_blocked_brute_force(from, to, exclude, epsilon);
        };
        let Some(ray) = segment_ray(from, to, epsilon) else { return false };
        let exclude = exclude.map(|p| p as usize);
        let mut state = bvh.new_ray_traversal(Ray::new(ray.origin, ray.direction, ray.tmin, ray.tmax));
        bvh.ray_traverse_dynamic(&mut state, &mut RayHit::none(), |ray, id| {
            let triangle = bvh.primitive_indices[id] as usize;
            if self.has_corner(quad_of[triangle / 2] as usize, triangle % 2, exclude) {
                return f32::INFINITY;
            }
            triangles[triangle].intersect(ray)
        })
    }

    /// The first surface hit of the ray from `origin` along the unit `direction` (skirts ignored;
    /// triangles and vertices as in [`super::ray_triangle`], footprint fragments as in
    /// [`Self::fragments`]): its distance.
    pub fn first_surface_hit(&self, origin: DVec3, direction: DVec3) -> Option<f64> {
        let ray = RenderRay::new(origin, direction);
        let fragments = self.fragment_hit_brute_force(&ray);
        nearest(nearest(self.first_triangle_hit(&ray), self.vertex_hit_brute_force(&ray)), fragments)
    }

    /// The nearest surface triangle that `ray` hits: through the BVH if the mesh has one, else
    /// testing every triangle.
    pub(crate) fn first_triangle_hit(&self, ray: &RenderRay) -> Option<f64> {
        let Some(MeshBvh { bvh, quad_of, .. }) = &self.bvh else {
            return (0..self.quads.len()).map(|quad| self.surface_hit(quad, ray)).fold(None, nearest);
        };
        // The BVH finds the candidate triangles in f32; each is tested in f64, and the traversal
        // prunes with the f32 distance rounded up, so it never drops a nearer candidate.
        let (origin, direction) = (ray.origin().as_vec3a(), ray.direction().as_vec3a());
        let mut found = None;
        bvh.ray_traverse(Ray::new_inf(origin, direction), &mut RayHit::none(), |_, id| {
            let quad = quad_of[bvh.primitive_indices[id] as usize / 2] as usize;
            let Some(t) = self.surface_hit(quad, ray) else { return f32::INFINITY };
            found = nearest(found, Some(t));
            (t as f32).next_up()
        });
        found
    }

    /// [`Self::segment_blocked`] by testing every triangle.
    pub fn segment_blocked_brute_force(&self, from: DVec3, to: DVec3, exclude: Option<u32>, epsilon: f64) -> bool {
        let Some(ray) = segment_ray(from, to, epsilon) else { return false };
        (0..self.quads.len()).any(|quad| self.blocks_segment(quad, &ray, exclude.map(|p| p as usize)))
    }

    /// [`Self::first_surface_hit`] by testing every triangle and vertex.
    pub fn first_surface_hit_brute_force(&self, origin: DVec3, direction: DVec3) -> Option<f64> {
        let ray = RenderRay::new(origin, direction);
        let triangles = (0..self.quads.len()).map(|quad| self.surface_hit(quad, &ray)).fold(None, nearest);
        nearest(nearest(triangles, self.vertex_hit_brute_force(&ray)), self.fragment_hit_brute_force(&ray))
    }

    /// The nearest vertex that `ray` hits ([`RenderRay::vertex_hit`]), testing every one.
    fn vertex_hit_brute_force(&self, ray: &RenderRay) -> Option<f64> {
        (0..self.points.len()).filter_map(|p| ray.vertex_hit(self.point(p)?)).fold(None, |a, b| nearest(a, Some(b)))
    }

    /// Whether the mesh was built with a BVH ([`Accelerator::Cwbvh`]), which then answers every ray.
    pub(crate) fn has_bvh(&self) -> bool {
        self.bvh.is_some()
    }
}

/// The nearer of two hit distances.
pub(crate) fn nearest(a: Option<f64>, b: Option<f64>) -> Option<f64> {
    match (a, b) {
        (Some(a), Some(b)) => Some(a.min(b)),
        (a, b) => a.or(b),
    }
}

/// The two triangles of a quad with corners 0..3 (see [`SPLIT`]).
fn split(corners: [Vec3A; 4]) -> [Triangle; 2] {
    SPLIT.map(|[a, b, c]| Triangle { v0: corners[a], v1: corners[b], v2: corners[c] })
}

/// Pixel indices of the corners of the quad whose corner 0 is pixel `quad` (see [`Quad`]).
pub(crate) fn corner_indices(quad: usize, width: usize) -> [usize; 4] {
    [quad, quad + 1, quad + width, quad + width + 1]
}

/// The f32 ray of a visibility segment: from `from` towards `to`, ending `epsilon` (relative)
/// short of it. None for a zero-length segment. For triangle tests only: without the inverse
/// direction (three divisions) that only the BVH's box tests read ([`Ray::new`] adds it).
pub(crate) fn segment_ray(from: DVec3, to: DVec3, epsilon: f64) -> Option<Ray> {
    let offset = to - from;
    let length = offset.length();
    (length > 0.0).then(|| Ray {
        origin: from.as_vec3a(),
        direction: (offset / length).as_vec3a(),
        inv_direction: Vec3A::ZERO,
        tmin: 0.0,
        tmax: (length * (1.0 - epsilon)) as f32,
    })
}

#[cfg(test)]
mod tests {
    use glam::{DMat3, DMat4, DVec3};
    use rand::{Rng, SeedableRng};

    use super::{DepthMesh, Footprint, MeshConfig, valid};
    use foundation::camera::PinholeCamera;
    use foundation::depth::DepthMap;

    #[test]
    fn a_slanted_planes_own_surface_reaches_the_footprints_near_border() {
        // A plane x = (z − 5) / 0.8 seen from the origin: its depth 5 / (1 − 0.8 x/z) grows 4 % a
        // pixel to the right (one surface at the default cut of 5 %).
        let (width, height, focal) = (16, 12, 20.0);
        let camera = PinholeCamera {
            width,
            height,
            intrinsics: DMat3::from_cols(
                DVec3::new(focal, 0.0, 0.0),
                DVec3::new(0.0, focal, 0.0),
                DVec3::new(7.5, 5.5, 1.0),
            ),
            world_from_camera: DMat4::IDENTITY,
        };
        let depth_at = |x: f64| 5.0 / (1.0 - 0.8 * (x - 7.5) / focal);
        let values = (0..width * height).map(|i| depth_at(f64::from(i % width)) as f32).collect();
        let mesh = DepthMesh::new(
            &DepthMap { width: width as usize, height: height as usize, values },
            &camera,
            &MeshConfig::default(),
        );
        // Just inside pixel (8, 6)'s footprint on its near side, where the plane's depth is the
        // harmonic mean of the two samples' (the arithmetic mean lies 4e-4 farther, beyond the
        // epsilon).
        let x = 7.5 + 1e-3;
        let point = camera.unproject(x, 6.0, depth_at(x));
        assert_eq!(mesh.footprint_of(point, 1e-4), Footprint::Own(6 * width + 8));
        // In front of it by more than the epsilon, it is not that surface.
        let nearer = camera.unproject(x, 6.0, depth_at(x) * (1.0 - 1e-3));
        assert_eq!(mesh.footprint_of(nearer, 1e-4), Footprint::Elsewhere);
    }

    #[test]
    fn valid_depth_by_bits_equals_the_comparisons() {
        let by_comparison = |d: f32| d > 0.0 && d < f32::INFINITY;
        let special = [
            0.0,
            -0.0,
            f32::MIN_POSITIVE,
            -f32::MIN_POSITIVE,
            f32::from_bits(1),
            f32::from_bits(0x8000_0001),
            f32::MAX,
            f32::MIN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            -f32::NAN,
            f32::from_bits(0x7f80_0001),
            f32::from_bits(0xffff_ffff),
            1.0,
            -1.0,
        ];
        for d in special {
            assert_eq!(valid(d), by_comparison(d), "{d:?} ({:#x})", d.to_bits());
        }
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for _ in 0..1_000_000 {
            let d = f32::from_bits(rng.random());
            assert_eq!(valid(d), by_comparison(d), "{d:?} ({:#x})", d.to_bits());
        }
    }
}
