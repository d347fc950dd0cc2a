//! A depth map lifted to a triangle mesh in world space, and the structures that answer ray
//! queries against it exactly (DESIGN §4): two triangles per 2×2 pixel quad, vertices at pixel centres; triangles touching invalid depth
//! are dropped, and so are those spanning a depth discontinuity (max/min depth of the quad above a
//! ratio), which would otherwise be "rubber sheets" joining foreground and background.
//!
//! Optionally, a discontinuity quad becomes an *occluder skirt* instead of a gap: its vertices
//! are pulled along their pixel rays to at most `(1 + occluder_thickness)` × the quad's nearest
//! depth, modelling the unobserved space just behind a foreground edge as solid for a limited
//! depth. Skirts block visibility rays but are never rendered. Thickness 0 is the plain cut mesh;
//! a very large thickness approaches the uncut mesh.
//!
//! Queries run the obvhs ray/triangle test on the f32 triangles; what differs is how candidates
//! are found (`accelerator`). The default exploits that the mesh is a regular grid seen from one
//! camera: nothing generic is built per frame, a depth pyramid over the source image serves single
//! rays ([`crate::depth_pyramid`]) and per-view bins serve the batches of rays leaving a novel
//! camera ([`crate::view_bins`]): triangle bins for the render rays, and for the co-visibility
//! segments the source points binned instead, tested by the quads of the blocks that may hide
//! anything ([`MeshView::covisibility`]). The obvhs CWBVH over all triangles is the alternative.
//! Every path equals a brute-force loop over all triangles (integration tests).

use std::sync::OnceLock;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use glam::{DMat4, DVec2, DVec3, Vec3A};
use obvhs::BvhBuildParams;
use obvhs::cwbvh::CwBvh;
use obvhs::cwbvh::builder::build_cwbvh_from_tris;
use obvhs::ray::{Ray, RayHit};
use obvhs::triangle::Triangle;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::camera::PinholeCamera;
use crate::config_file::{Checked, Validate, check_float};
use crate::depth_exr::DepthMap;
use crate::depth_pyramid::DepthPyramid;
use crate::pool::Pool;
use crate::view_bins::{self, ViewBins};

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
    /// Structures built on the image grids, in milliseconds: a quadtree with per-node depth
    /// ranges over the source image ([`DepthPyramid`]) for single rays, and triangle bins over
    /// each novel image ([`ViewBins`]) for the batches of rays leaving one novel camera.
    #[default]
    ImageGrids,
    /// A generic obvhs compressed-wide BVH over the triangles (SAH build per frame); kept as the
    /// reference the pyramid is compared with.
    Cwbvh,
}

/// Finite and positive: `depth > 0.0 && depth < f32::INFINITY` (false for NaN) by one integer
/// comparison. The bit patterns of the positive finite floats are exactly 1..=0x7f7f_ffff; zero
/// wraps to the top, and negative values, infinities and NaNs all lie above.
#[inline]
fn valid(depth: f32) -> bool {
    depth.to_bits().wrapping_sub(1) < 0x7f7f_ffff
}

/// The two triangles of a quad, as corner indices 0 = (u, v), 1 = (u+1, v), 2 = (u, v+1),
/// 3 = (u+1, v+1).
const SPLIT: [[usize; 3]; 2] = [[0, 1, 2], [1, 3, 2]];

/// [`DepthMesh::points`] of a pixel without a point (invalid depth); a valid point is finite.
const NO_POINT: DVec3 = DVec3::NAN;

/// A stored point as an `Option`: None for [`NO_POINT`].
#[inline]
fn stored_point(point: DVec3) -> Option<DVec3> {
    (!point.x.is_nan()).then_some(point)
}

/// A quad with no triangles (a corner has invalid depth, or it spans an edge without a skirt).
const NO_TRIANGLES: u32 = u32::MAX;
/// A surface quad, whose triangles join its corners' surface points.
const SURFACE: u32 = u32::MAX - 1;

/// The ray-query structure of one mesh.
enum Acceleration {
    /// The source-image pyramid, built on the first single-ray query (the per-view batches use
    /// [`ViewBins`] and never need it).
    ImageGrids(Box<LazyPyramid>),
    /// The BVH and, per BVH triangle pair (surface quads first, then skirts), its quad.
    Cwbvh { bvh: CwBvh, triangles: Vec<Triangle>, quad_of: Vec<u32> },
}

/// A [`DepthPyramid`] built on first use, from the camera the mesh was lifted with.
struct LazyPyramid {
    pyramid: OnceLock<DepthPyramid>,
    camera: PinholeCamera,
}

/// Per row of quads: its number of surface quads, and its skirts by column.
type QuadRow = (usize, Vec<(usize, [Triangle; 2])>);

/// The per-pixel arrays of a [`DepthMesh`]: the size of the image, so reused across frames
/// ([`MESH_POOL`]) rather than allocated anew, for the same reason as the per-view arrays.
#[derive(Default)]
struct MeshArrays {
    points: Vec<DVec3>,
    vertices: Vec<Vec3A>,
    quads: Vec<u32>,
    columns: Vec<u32>,
}

/// Arrays of dropped meshes; at most as many as meshes were ever alive at once.
static MESH_POOL: Pool<MeshArrays> = Pool::new();

impl Drop for DepthMesh {
    fn drop(&mut self) {
        let arrays = MeshArrays {
            points: std::mem::take(&mut self.points),
            vertices: std::mem::take(&mut self.vertices),
            quads: std::mem::take(&mut self.quads),
            columns: std::mem::take(&mut self.columns),
        };
        MESH_POOL.give(arrays);
    }
}

/// The mesh of one frame and its ray-query structure.
pub struct DepthMesh {
    width: usize,
    height: usize,
    /// World-space surface point of each pixel ([`NO_POINT`] where depth is invalid: 24 bytes a
    /// pixel where an `Option` takes 32, and the per-view pass over them waits on memory).
    points: Vec<DVec3>,
    /// The same points in f32, the triangles' corners (zero where depth is invalid).
    vertices: Vec<Vec3A>,
    /// Per pixel, the quad whose corner 0 it is (see [`SPLIT`]; none in the last column and row):
    /// [`NO_TRIANGLES`], [`SURFACE`], or the index of its occluder-skirt triangles in `skirts`.
    /// Quads are named by that pixel throughout.
    quads: Vec<u32>,
    /// Per pixel, its column: `p % width` without a division, for the per-point tests of the
    /// co-visibility batch ([`MeshView::good_blocks`]).
    columns: Vec<u32>,
    skirts: Vec<[Triangle; 2]>,
    surface_quads: usize,
    /// The smallest valid depth.
    nearest_depth: f64,
    acceleration: Acceleration,
}

impl DepthMesh {
    /// Lifts `depth` seen by `camera` into a mesh and builds its ray-query structure.
    pub fn new(depth: &DepthMap, camera: &PinholeCamera, config: &MeshConfig) -> Self {
        let (width, height) = (depth.width, depth.height);
        let center = camera.center();
        // `camera.pixel_ray` with K inverted once.
        let camera_from_pixel = camera.intrinsics.inverse();
        // Column and row as u32, whose conversion to f64 is one instruction (usize's is not).
        let ray = |u: u32, v: u32| {
            let in_camera = camera_from_pixel * DVec3::new(f64::from(u), f64::from(v), 1.0);
            camera.world_from_camera.transform_vector3(in_camera)
        };
        let pixel_ray = |p: usize| ray((p % width) as u32, (p / width) as u32);
        // Rays are recomputed where needed (the same arithmetic each time), not stored: an array
        // of them is 8 MB a frame at 480×720 for one pass over the pixels and the rare skirts.
        let MeshArrays { mut points, mut vertices, mut quads, mut columns } = MESH_POOL.take();
        // Points, their f32 copies and the nearest depth in one pass by rows (every element is
        // written; pooled arrays of the right length are not cleared first).
        points.resize(depth.values.len(), NO_POINT);
        vertices.resize(depth.values.len(), Vec3A::ZERO);
        let row = width.max(1);
        let nearest_depth = points
            .par_chunks_mut(row)
            .zip(vertices.par_chunks_mut(row))
            .zip(depth.values.par_chunks(row))
            .enumerate()
            .map(|(v, ((points, vertices), depths))| {
                let mut nearest = f64::INFINITY;
                for (u, ((point, vertex), &d)) in points.iter_mut().zip(vertices.iter_mut()).zip(depths).enumerate() {
                    if valid(d) {
                        *point = center + f64::from(d) * ray(u as u32, v as u32);
                        *vertex = to_vec3a(*point);
                        nearest = nearest.min(f64::from(d));
                    } else {
                        (*point, *vertex) = (NO_POINT, Vec3A::ZERO);
                    }
                }
                nearest
            })
            .reduce(|| f64::INFINITY, f64::min);
        // Per row of quads, written in place: each quad's kind, with the skirt triangles of the
        // row collected aside (numbered in row order below).
        quads.resize(width * height, NO_TRIANGLES);
        let rows: Vec<QuadRow> = quads
            .par_chunks_mut(width.max(1))
            .enumerate()
            .map(|(v, kinds)| {
                let (mut surface, mut skirts) = (0, Vec::new());
                kinds.fill(NO_TRIANGLES);
                if v + 1 == height {
                    return (0, skirts);
                }
                let (upper, lower) =
                    (&depth.values[v * width..(v + 1) * width], &depth.values[(v + 1) * width..(v + 2) * width]);
                // Per pixel column, whether both of its depths are valid and their smaller and
                // larger one: each column serves the quads on both sides, so it is read once.
                // Valid depths are never NaN, so plain selects give min and max (and an invalid
                // column's values are never used).
                let (smaller, larger) = (view_bins::smaller, view_bins::larger);
                let column = |(&a, &b): (&f32, &f32)| (valid(a) & valid(b), smaller(a, b), larger(a, b));
                let mut left = column((&upper[0], &lower[0]));
                let quads = kinds.iter_mut().zip(upper[1..].iter().zip(&lower[1..])).enumerate();
                for (u, (kind, right)) in quads {
                    let right = column(right);
                    let (left_valid, left_near, left_far) = std::mem::replace(&mut left, right);
                    // Not short-circuited: nearly every quad is valid, and the branches cost more.
                    if !(left_valid & right.0) {
                        continue;
                    }
                    let near = smaller(left_near, right.1) as f64;
                    let far = larger(left_far, right.2) as f64;
                    if far <= near * config.discontinuity_ratio {
                        *kind = SURFACE;
                        surface += 1;
                    } else if config.occluder_thickness > 0.0 {
                        let limit = near * (1.0 + config.occluder_thickness);
                        let index = corner_indices(v * width + u, width);
                        let d = [upper[u], upper[u + 1], lower[u], lower[u + 1]];
                        let skirt = SPLIT
                            .map(|tri| triangle(tri.map(|k| center + (d[k] as f64).min(limit) * pixel_ray(index[k]))));
                        skirts.push((u, skirt));
                    }
                }
                (surface, skirts)
            })
            .collect();
        let mut skirts = Vec::new();
        let mut surface_quads = 0;
        for (v, (surface, row_skirts)) in rows.into_iter().enumerate() {
            surface_quads += surface;
            for (u, skirt) in row_skirts {
                quads[v * width + u] = skirts.len() as u32;
                skirts.push(skirt);
            }
        }
        let acceleration =
            Acceleration::ImageGrids(Box::new(LazyPyramid { pyramid: OnceLock::new(), camera: *camera }));
        columns.resize(width * height, 0);
        columns.par_chunks_mut(width.max(1)).for_each(|row| {
            for (u, column) in row.iter_mut().enumerate() {
                *column = u as u32;
            }
        });
        let mut mesh = Self {
            width,
            height,
            points,
            vertices,
            quads,
            columns,
            skirts,
            surface_quads,
            nearest_depth,
            acceleration,
        };
        if config.accelerator == Accelerator::Cwbvh {
            mesh.acceleration = mesh.cwbvh();
        }
        mesh
    }

    /// The quadtree over the quads, from each quad's source-camera depth range.
    fn depth_pyramid(&self, camera: &PinholeCamera) -> DepthPyramid {
        let camera_from_world = camera.camera_from_world();
        let depth_of = |p: Vec3A| camera_from_world.transform_point3(p.as_dvec3()).z as f32;
        let corner_depths: Vec<f32> = self.vertices.par_iter().map(|&p| depth_of(p)).collect();
        let (quad_width, quad_height) = (self.width.saturating_sub(1), self.height.saturating_sub(1));
        let ranges = (0..quad_width * quad_height)
            .into_par_iter()
            .map(|q| {
                let quad = q + q / quad_width;
                match self.quads[quad] {
                    NO_TRIANGLES => [f32::INFINITY, f32::NEG_INFINITY],
                    SURFACE => {
                        let d = corner_indices(quad, self.width).map(|i| corner_depths[i]);
                        [d.into_iter().fold(f32::INFINITY, f32::min), d.into_iter().fold(f32::NEG_INFINITY, f32::max)]
                    }
                    skirt => {
                        let d = self.skirts[skirt as usize].map(|t| [t.v0, t.v1, t.v2].map(depth_of));
                        let d = d.as_flattened();
                        [
                            d.iter().copied().fold(f32::INFINITY, f32::min),
                            d.iter().copied().fold(f32::NEG_INFINITY, f32::max),
                        ]
                    }
                }
            })
            .collect();
        DepthPyramid::new(quad_width, quad_height, ranges, camera_from_world, camera.intrinsics)
    }

    /// The obvhs BVH over every triangle (surface first, then skirts).
    fn cwbvh(&self) -> Acceleration {
        let (mut triangles, mut quad_of) = (Vec::new(), Vec::new());
        for want_skirts in [false, true] {
            for quad in 0..self.quads.len() {
                if let Some((skirt, pair)) = self.quad_triangles(quad)
                    && skirt == want_skirts
                {
                    triangles.extend(pair);
                    quad_of.push(quad as u32);
                }
            }
        }
        let bvh = build_cwbvh_from_tris(&triangles, BvhBuildParams::fast_build(), &mut Duration::default());
        Acceleration::Cwbvh { bvh, triangles, quad_of }
    }

    /// A quad's two triangles and whether they are a skirt; None for a quad without triangles.
    fn quad_triangles(&self, quad: usize) -> Option<(bool, [Triangle; 2])> {
        match self.quads[quad] {
            NO_TRIANGLES => None,
            SURFACE => {
                let corners = corner_indices(quad, self.width).map(|i| self.vertices[i]);
                Some((false, SPLIT.map(|t| Triangle { v0: corners[t[0]], v1: corners[t[1]], v2: corners[t[2]] })))
            }
            skirt => Some((true, self.skirts[skirt as usize])),
        }
    }

    /// Whether triangle `half` of `quad` has pixel `exclude` as a corner.
    fn has_corner(&self, quad: usize, half: usize, exclude: Option<u32>) -> bool {
        exclude.is_some_and(|p| {
            let corners = corner_indices(quad, self.width);
            SPLIT[half].iter().any(|&k| corners[k] == p as usize)
        })
    }

    /// The hit distance of `ray` on each of a quad's two triangles, +∞ for a miss; a quad without
    /// triangles, a skirt unless `skirts`, and triangles with pixel `exclude` as a corner never hit.
    #[inline]
    fn quad_hits(&self, quad: usize, ray: &Ray, skirts: bool, exclude: Option<u32>) -> impl Iterator<Item = f32> {
        let kind = self.quads[quad];
        let none = kind == NO_TRIANGLES || (kind != SURFACE && !skirts);
        let corners = corner_indices(quad, self.width);
        SPLIT.iter().enumerate().take(if none { 0 } else { 2 }).map(move |(half, split)| {
            if exclude.is_some_and(|p| split.iter().any(|&k| corners[k] == p as usize)) {
                return f32::INFINITY;
            }
            let triangle = if kind == SURFACE {
                let [a, b, c] = split.map(|k| self.vertices[corners[k]]);
                Triangle { v0: a, v1: b, v2: c }
            } else {
                self.skirts[kind as usize][half]
            };
            triangle.intersect(ray)
        })
    }

    /// The nearest hit distance of `ray` on a quad's triangles ([`Self::quad_hits`]).
    fn hit_quad(&self, quad: usize, ray: &Ray, skirts: bool, exclude: Option<u32>) -> f32 {
        self.quad_hits(quad, ray, skirts, exclude).fold(f32::INFINITY, f32::min)
    }

    /// Whether a quad's triangles (skirts included, those with pixel `exclude` as a corner not)
    /// cross the segment `ray` before its end: `hit_quad(..) < ray.tmax`, without testing the
    /// second triangle when the first already does.
    fn blocks_segment(&self, quad: usize, ray: &Ray, exclude: Option<u32>) -> bool {
        self.quad_hits(quad, ray, true, exclude).any(|t| t < ray.tmax)
    }

    /// The mesh seen from a novel camera, for the batches of rays leaving its centre. With the
    /// image-grid accelerator this projects and bins every point for the co-visibility batch
    /// (`projection`); the triangle bins of single queries are built on their first use.
    pub fn view(&self, novel: &PinholeCamera) -> MeshView<'_> {
        let novel_from_world = novel.camera_from_world();
        let projection =
            matches!(self.acceleration, Acceleration::ImageGrids(_)).then(|| self.projection(&novel_from_world, novel));
        MeshView { mesh: self, novel: *novel, novel_from_world, eye: novel.center(), projection }
    }

    /// The per-view arrays of the image-grid accelerator: every point projected into `novel`,
    /// the points binned by the novel pixel they project to, and the integral image of the
    /// quads that cannot be part of a good block ([`MeshView::good_blocks`]). They come from
    /// one pass over bands of pixel rows ([`Self::project_band`]): separate passes over the
    /// 8 MB of projections at 480×720 waited on memory for most of their time.
    fn projection(&self, novel_from_world: &DMat4, novel: &PinholeCamera) -> Projection {
        let (width, height) = (self.width, self.height);
        let setup = BandSetup {
            novel_from_world,
            novel,
            grid: view_bins::PointGrid::new((novel.width as usize, novel.height as usize)),
            near: ViewBins::near_limit(self.nearest_depth),
        };
        let mut points = VIEW_POOL.take();
        let mut bad = BAD_POOL.take();
        // Every element is written below; only growth initialises.
        points.resize(self.points.len(), DVec3::ZERO);
        bad.resize((width + 1) * (height + 1), 0);
        // Row 0 of the integral image; each band writes its rows' sums along the row.
        bad[..width + 1].fill(0);
        let band = QUAD_ROWS_PER_BAND * width.max(1);
        let point_bins = view_bins::PointBins::new(self.points.len(), &setup.grid, |bins, entries| {
            let bands = points
                .par_chunks_mut(band)
                .zip(bins.par_chunks_mut(band).zip(entries.par_chunks_mut(band)))
                .zip(bad[width + 1..].par_chunks_mut(QUAD_ROWS_PER_BAND * (width + 1)));
            bands.enumerate().for_each(|(index, ((projected, binned), sums))| {
                self.project_band(index * QUAD_ROWS_PER_BAND, &setup, projected, binned, sums);
            });
        });
        // Summed down the columns.
        for v in 1..=height {
            let (above, rows) = bad[(v - 1) * (width + 1)..].split_at_mut(width + 1);
            for (sum, &above) in rows[..width + 1].iter_mut().zip(above.iter()) {
                *sum += above;
            }
        }
        Projection { points, bad, point_bins, quad_bins: OnceLock::new() }
    }

    /// [`Self::projection`] of the band of pixel rows from `first_row`: projects its points into
    /// `projected`, gives each its [`view_bins::PointGrid::entry`] in `bins` and `entries`, and
    /// writes into `sums` (width + 1 per row) the rows of the integral image of bad quads summed
    /// along each row ([`bad_quads`]), all while the band's projections are in cache.
    fn project_band(
        &self,
        first_row: usize,
        setup: &BandSetup,
        projected: &mut [DVec3],
        (bins, entries): (&mut [u32], &mut [view_bins::PointEntry]),
        sums: &mut [u32],
    ) {
        let width = self.width;
        let first = first_row * width;
        setup.project(projected, &self.points[first..first + projected.len()]);
        let binned = projected.iter().zip(bins.iter_mut().zip(entries.iter_mut())).enumerate();
        for (offset, (&q, (bin, entry))) in binned {
            (*bin, *entry) = setup.grid.entry(first + offset, query_of(q));
        }
        let mut next_row = Vec::new();
        for (r, sums) in sums.chunks_mut(width + 1).enumerate() {
            let v = first_row + r;
            let lower = match projected.get((r + 1) * width..(r + 2) * width) {
                Some(lower) => Some(lower),
                None if v + 1 < self.height => {
                    // The band's last quad row: its lower corners begin the next band, projected
                    // here too (the same arithmetic, so the same values).
                    next_row.resize(width, DVec3::ZERO);
                    setup.project(&mut next_row, &self.points[(v + 1) * width..(v + 2) * width]);
                    Some(&next_row[..])
                }
                None => None,
            };
            let upper = &projected[r * width..(r + 1) * width];
            sums[0] = 0;
            bad_quads(upper, lower, &self.quads[v * width..(v + 1) * width], setup.near, &mut sums[1..]);
        }
    }

    /// Calls `emit(offset, quad, separates)` for each quad `first + offset` of a band of whole
    /// quad rows ending before `end`: `quad` the smallest (x, y, depth) and largest (x, y) of its
    /// corners as (pixel x, pixel y, depth) in the novel camera (None without triangles), one
    /// range per quad (its two triangles share most of their footprint), and `separates` whether
    /// the quad is a surface quad whose diagonal separates corners 0 and 3 in the image
    /// ([`Projection::quad_bins`]). `projected` holds the projections of the band's corner pixels
    /// (its rows and the next) and `novel` is the camera, for the skirts' corners. The f64 points
    /// stand for their f32 triangle corners: they differ by f32 rounding, ~1e-4 px at the scale
    /// of any depth map, inside [`view_bins::MARGIN_PIXELS`].
    #[inline]
    fn band_quads(
        &self,
        (first, end): (usize, usize),
        (u0, u1): (usize, usize),
        projected: &[DVec3],
        (novel, novel_from_world): (&PinholeCamera, &DMat4),
        mut emit: impl FnMut(usize, Option<(DVec3, DVec2)>, bool),
    ) {
        let width = self.width;
        // Per vertex column of a quad row, the smallest (x, y, depth) and largest (x, y) of its two
        // corners: each column serves the quads on both sides.
        let mut columns: Vec<(DVec3, DVec2)> = Vec::with_capacity(u1 + 1 - u0);
        let vertex_end = (u1 + 1).min(width);
        for (row, quads) in self.quads[first..end].chunks(width).enumerate() {
            let upper = &projected[row * width..(row + 1) * width];
            // The image's last row has no quads (nor a row below).
            let lower = projected.get((row + 1) * width..(row + 2) * width).unwrap_or(&[]);
            columns.clear();
            let pairs = upper[u0..vertex_end].iter().zip(lower.get(u0..vertex_end).unwrap_or(&[]));
            columns.extend(pairs.map(|(a, b)| (a.min(*b), a.truncate().max(b.truncate()))));
            for (u, &kind) in quads.iter().enumerate().take(u1).skip(u0) {
                let offset = row * width + u;
                match kind {
                    NO_TRIANGLES => emit(offset, None, false),
                    SURFACE => {
                        let [c0, c1, c2, c3] = [upper[u], upper[u + 1], lower[u], lower[u + 1]];
                        // Twice the margin covers the f32 rounding of the corners' positions.
                        let (a, b, c, d) = (c0.truncate(), c1.truncate(), c2.truncate(), c3.truncate());
                        let separates = [c0, c1, c2, c3].iter().all(|p| p.z > 0.0)
                            && view_bins::line_separates(b, c, a, d, 2.0)
                            && view_bins::line_separates(b, c, d, a, 2.0);
                        let ((lo_left, hi_left), (lo_right, hi_right)) = (columns[u - u0], columns[u + 1 - u0]);
                        emit(offset, Some((lo_left.min(lo_right), hi_left.max(hi_right))), separates);
                    }
                    skirt => {
                        let [a, b] = self.skirts[skirt as usize];
                        // Corners 0..3 of the quad, pulled onto the skirt (see SPLIT).
                        let corners = [a.v0, a.v1, a.v2, b.v1].map(|v| project(novel_from_world, novel, v.as_dvec3()));
                        emit(offset, Some(view_bins::corner_range(&corners)), false);
                    }
                }
            }
        }
    }

    /// The surface point of pixel `index` (row-major), if its depth is valid.
    pub fn point(&self, index: usize) -> Option<DVec3> {
        stored_point(self.points[index])
    }

    /// Image width the mesh was lifted from.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Number of surface and skirt triangles.
    pub fn triangle_counts(&self) -> (usize, usize) {
        (2 * self.surface_quads, 2 * self.skirts.len())
    }

    /// Whether any triangle (skirts included) other than those with pixel `exclude` as a corner
    /// crosses the segment from `from` to `to`, shortened by `epsilon` (relative) at `to`.
    pub fn segment_blocked(&self, from: DVec3, to: DVec3, exclude: Option<u32>, epsilon: f64) -> bool {
        let Some(ray) = segment_ray(from, to, epsilon) else { return false };
        match &self.acceleration {
            Acceleration::ImageGrids(lazy) => {
                let pyramid = lazy.pyramid.get_or_init(|| self.depth_pyramid(&lazy.camera));
                // Hits at exactly the segment's end do not count, as in the BVH's traversal.
                let hit = |u, v| {
                    let t = self.hit_quad(v * self.width + u, &ray, true, exclude);
                    if t < ray.tmax { t } else { f32::INFINITY }
                };
                pyramid
                    .traverse(world_of(ray.origin), world_of(ray.direction), f64::from(ray.tmax), true, hit)
                    .is_some()
            }
            Acceleration::Cwbvh { bvh, triangles, quad_of } => {
                let mut state = bvh.new_ray_traversal(ray);
                let mut hit = RayHit::none();
                bvh.ray_traverse_dynamic(&mut state, &mut hit, |ray, id| {
                    let triangle = bvh.primitive_indices[id] as usize;
                    if self.has_corner(quad_of[triangle / 2] as usize, triangle % 2, exclude) {
                        return f32::INFINITY;
                    }
                    triangles[triangle].intersect(ray)
                })
            }
        }
    }

    /// The first surface triangle (skirts ignored) hit by the ray: distance along the unit
    /// `direction`.
    pub fn first_surface_hit(&self, origin: DVec3, direction: DVec3) -> Option<f64> {
        let ray = Ray::new_inf(to_vec3a(origin), to_vec3a(direction));
        match &self.acceleration {
            Acceleration::ImageGrids(lazy) => {
                let pyramid = lazy.pyramid.get_or_init(|| self.depth_pyramid(&lazy.camera));
                let hit = |u, v| self.hit_quad(v * self.width + u, &ray, false, None);
                pyramid
                    .traverse(world_of(ray.origin), world_of(ray.direction), f64::INFINITY, false, hit)
                    .map(f64::from)
            }
            Acceleration::Cwbvh { bvh, triangles, .. } => {
                let surface_triangles = 2 * self.surface_quads;
                let mut hit = RayHit::none();
                let found = bvh.ray_traverse(ray, &mut hit, |ray, id| {
                    let triangle = bvh.primitive_indices[id] as usize;
                    if triangle >= surface_triangles { f32::INFINITY } else { triangles[triangle].intersect(ray) }
                });
                found.then_some(f64::from(hit.t))
            }
        }
    }

    /// Brute-force version of [`DepthMesh::segment_blocked`] over every triangle, for tests.
    pub fn segment_blocked_brute_force(&self, from: DVec3, to: DVec3, exclude: Option<u32>, epsilon: f64) -> bool {
        let Some(ray) = segment_ray(from, to, epsilon) else { return false };
        (0..self.quads.len()).any(|quad| self.blocks_segment(quad, &ray, exclude))
    }

    /// Brute-force version of [`DepthMesh::first_surface_hit`] over every triangle, for tests.
    pub fn first_surface_hit_brute_force(&self, origin: DVec3, direction: DVec3) -> Option<f64> {
        let ray = Ray::new_inf(to_vec3a(origin), to_vec3a(direction));
        let nearest =
            (0..self.quads.len()).map(|quad| self.hit_quad(quad, &ray, false, None)).fold(f32::INFINITY, f32::min);
        nearest.is_finite().then_some(f64::from(nearest))
    }
}

/// What [`DepthMesh::project_band`] needs of the view.
struct BandSetup<'a> {
    novel_from_world: &'a DMat4,
    novel: &'a PinholeCamera,
    grid: view_bins::PointGrid,
    /// [`ViewBins::near_limit`] of the mesh.
    near: f64,
}

impl BandSetup<'_> {
    /// `points` projected into `projected` ([`project`]; depth NaN without a point).
    fn project(&self, projected: &mut [DVec3], points: &[DVec3]) {
        for (projected, &point) in projected.iter_mut().zip(points) {
            *projected = stored_point(point)
                .map_or(DVec3::new(0.0, 0.0, f64::NAN), |p| project(self.novel_from_world, self.novel, p));
        }
    }
}

/// A projected point (pixel x, pixel y, depth; depth NaN for none) as a co-visibility query:
/// its pixel coordinates and depth, if it has a point. [`view_bins::PointBins`] bins those in
/// front of the camera and inside its image; the others, answered one by one
/// ([`MeshView::covisible_single`]), are not co-visible without a segment test.
#[inline]
fn query_of(q: DVec3) -> Option<(DVec2, f64)> {
    (!q.z.is_nan()).then_some((q.truncate(), q.z))
}

/// Per quad of one row, with corners `upper` and `lower` (projected; None below the last
/// row), 1 unless it is a surface quad beyond the `near` limit whose two triangles are thick
/// ([`view_bins::thick_quad`]), summed along the row into `sums` (one per pixel column; the
/// last column has no quad and counts as bad).
fn bad_quads(upper: &[DVec3], lower: Option<&[DVec3]>, kinds: &[u32], near: f64, sums: &mut [u32]) {
    let Some(lower) = lower else {
        for (u, sum) in sums.iter_mut().enumerate() {
            *sum = u as u32 + 1;
        }
        return;
    };
    let (Some(&first_upper), Some(&first_lower)) = (upper.first(), lower.first()) else { return };
    // Each quad's right corners are the next one's left corners: loaded once.
    let mut left = (first_upper, first_lower);
    let mut running = 0;
    let quads = sums.iter_mut().zip(kinds).zip(upper[1..].iter().zip(&lower[1..]));
    for ((sum, &kind), (&c1, &c3)) in quads {
        let (c0, c2) = std::mem::replace(&mut left, (c1, c3));
        // Surface quads have four valid points: no NaN depth, so plain selects suffice.
        let smaller = view_bins::smaller;
        let good = kind == SURFACE
            && smaller(smaller(c0.z, c1.z), smaller(c2.z, c3.z)) > near
            && view_bins::thick_quad(c0.truncate(), c1.truncate(), c2.truncate(), c3.truncate(), 2.0);
        running += u32::from(!good);
        *sum = running;
    }
    // The last column: no quad.
    if let Some(last) = sums.last_mut() {
        *last = running + 1;
    }
}

/// Pixel indices of the corners of the quad whose corner 0 is pixel `quad` (see [`SPLIT`]).
fn corner_indices(quad: usize, width: usize) -> [usize; 4] {
    [quad, quad + 1, quad + width, quad + width + 1]
}

/// The f32 ray of a visibility segment: from `from` towards `to`, ending `epsilon` (relative)
/// short of it. None for a zero-length segment.
fn segment_ray(from: DVec3, to: DVec3, epsilon: f64) -> Option<Ray> {
    let offset = to - from;
    let length = offset.length();
    (length > 0.0).then(|| Ray::new(to_vec3a(from), to_vec3a(offset / length), 0.0, (length * (1.0 - epsilon)) as f32))
}

/// [`segment_ray`] for triangle tests only: the same origin, direction and range, without the
/// inverse direction (three divisions per ray) that only box tests read.
fn segment_ray_for_triangles(from: DVec3, to: DVec3, epsilon: f64) -> Option<Ray> {
    let offset = to - from;
    let length = offset.length();
    (length > 0.0).then(|| Ray {
        origin: to_vec3a(from),
        direction: to_vec3a(offset / length),
        inv_direction: Vec3A::ZERO,
        tmin: 0.0,
        tmax: (length * (1.0 - epsilon)) as f32,
    })
}

/// A depth mesh seen from one novel camera ([`DepthMesh::view`]): the same answers as the mesh's
/// own queries from the camera's centre, faster for whole images of rays.
pub struct MeshView<'a> {
    mesh: &'a DepthMesh,
    novel: PinholeCamera,
    novel_from_world: DMat4,
    eye: DVec3,
    /// None with the BVH accelerator, which serves every ray alike.
    projection: Option<Projection>,
}

/// The per-view structures of the image-grid accelerator.
struct Projection {
    /// Per pixel, its surface point in the novel camera as (pixel x, pixel y, depth): `pixel_of`
    /// and the depth of `novel_from_world` applied to [`DepthMesh::point`], computed once per
    /// view for the bins and the co-visibility queries alike; depth NaN where there is no point.
    points: Vec<DVec3>,
    /// The integral image of the quads that no good block may hold ([`MeshView::good_blocks`]):
    /// `bad[(v + 1)(width + 1) + u + 1]` counts those in quad rows ..=v and columns ..=u.
    bad: Vec<u32>,
    /// The points binned by the novel pixel they project to, for the co-visibility batch.
    point_bins: view_bins::PointBins,
    /// The triangle bins, for single segments and the render rays, built on first use (the
    /// co-visibility batch, [`MeshView::covisibility`], bins the points instead).
    quad_bins: OnceLock<QuadBins>,
}

/// The triangle bins of a view, and what its segment queries need with them.
struct QuadBins {
    bins: ViewBins,
    /// Per surface quad (by its corner-0 pixel): whether, in the novel image, the diagonal shared
    /// by its two triangles separates corners 0 and 3 beyond the bins' margin. Then neither corner
    /// can be hidden by the quad's triangle opposite it ([`view_bins::line_separates`]). A source
    /// point's own four quads always reach its bin and its two opposite triangles would otherwise
    /// be most of the exact tests.
    diagonal_separates: Vec<bool>,
}

/// The per-pixel arrays of dropped views ([`Projection::points`], the co-visibility batch's
/// flags), reused for the same reason as the bins' ([`view_bins`]): fresh image-sized
/// allocations per view cost the kernel's page clearing.
static VIEW_POOL: Pool<Vec<DVec3>> = Pool::new();
static BAD_POOL: Pool<Vec<u32>> = Pool::new();
static FLAG_POOL: Pool<(Vec<AtomicBool>, Vec<bool>)> = Pool::new();

/// Quad rows per parallel task of the passes over a view's quads.
const QUAD_ROWS_PER_BAND: usize = 16;

/// Quads per side of the blocks whose quads the co-visibility batch can skip
/// ([`MeshView::good_blocks`]).
const BLOCK: usize = 8;

/// Quads per side of a quarter of a block, tested on its own where the whole block is not good.
const QUARTER: usize = BLOCK / 2;

/// [`MeshView::good_blocks`] of a block whose four quarters are good.
const ALL_QUARTERS: u8 = 0b1111;

/// Most rings of quads around a block that must be regular too ([`MeshView::good_blocks`]):
/// points of the block's neighbours fall inside its box wherever the novel view turns or shears
/// it, and those of the rings' inner vertices do not count. Near a bad quad fewer rings (at least
/// one, which makes every vertex of the block inner) often still suffice. On the clip of
/// `scripts/bench_pairs_vs.sh`, up to 6 rings instead of always 4 skip 89.0 % of the quarters
/// instead of 86.8 % and test 17 % fewer quads; more than 6 change almost nothing there.
const RINGS: usize = 6;

impl Drop for Projection {
    fn drop(&mut self) {
        VIEW_POOL.give(std::mem::take(&mut self.points));
        BAD_POOL.give(std::mem::take(&mut self.bad));
    }
}

/// Pixel coordinates and depth of world point `p` in the novel camera (pixel coordinates are
/// meaningless for depth ≤ 0, which neither bins nor queries use).
#[inline]
fn project(novel_from_world: &DMat4, novel: &PinholeCamera, p: DVec3) -> DVec3 {
    let in_novel = novel_from_world.transform_point3(p);
    crate::camera::pixel_of(&novel.intrinsics, in_novel).extend(in_novel.z)
}

impl MeshView<'_> {
    /// The image's size and [`ViewBins::near_limit`] for the mesh.
    fn bin_settings(&self) -> ((usize, usize), f64) {
        ((self.novel.width as usize, self.novel.height as usize), ViewBins::near_limit(self.mesh.nearest_depth))
    }

    /// Quads per band of the passes over the quads, run in parallel (whole quad rows).
    fn band(&self) -> usize {
        (QUAD_ROWS_PER_BAND * self.mesh.width).max(1)
    }

    /// [`DepthMesh::band_quads`] for the band of quads `range`.
    fn band_quads(
        &self,
        projection: &Projection,
        range: (usize, usize),
        columns: (usize, usize),
        emit: impl FnMut(usize, Option<(DVec3, DVec2)>, bool),
    ) {
        let corners = &projection.points[range.0..(range.1 + self.mesh.width).min(projection.points.len())];
        self.mesh.band_quads(range, columns, corners, (&self.novel, &self.novel_from_world), emit);
    }

    fn quad_bins<'p>(&self, projection: &'p Projection) -> &'p QuadBins {
        projection.quad_bins.get_or_init(|| {
            let ((size, near), band) = (self.bin_settings(), self.band());
            let mut diagonal_separates = vec![false; self.mesh.quads.len()];
            let fill = |footprints: &mut [view_bins::Footprint]| {
                footprints.par_chunks_mut(band).zip(diagonal_separates.par_chunks_mut(band)).enumerate().for_each(
                    |(index, (footprints, separates))| {
                        let range = (index * band, index * band + footprints.len());
                        self.band_quads(projection, range, (0, self.mesh.width), |offset, quad, separating| {
                            separates[offset] = separating;
                            footprints[offset] = quad.map_or(view_bins::Footprint::OUTSIDE, |(lo, hi)| {
                                view_bins::Footprint::of_range(lo, hi, near, size)
                            });
                        });
                    },
                );
            };
            let bins = ViewBins::new(self.mesh.quads.len(), fill, self.novel_from_world, self.novel.intrinsics, size);
            QuadBins { bins, diagonal_separates }
        })
    }
}

impl MeshView<'_> {
    /// Pixel `index`'s surface point in the novel camera: its pixel coordinates K · (p / p.z) and
    /// depth p.z, p = `novel.camera_from_world()` applied to [`DepthMesh::point`], as computed
    /// there (None without a point, or with the BVH accelerator).
    pub fn projected(&self, index: usize) -> Option<(DVec2, f64)> {
        query_of(*self.projection.as_ref()?.points.get(index)?)
    }

    /// Bin entries and unbinned primitives of the per-view triangle bins (None with the BVH).
    pub fn bin_sizes(&self) -> Option<(usize, usize)> {
        self.projection.as_ref().map(|p| self.quad_bins(p).bins.sizes())
    }

    /// Co-visibility from the view's camera of every source pixel (row-major): whether its
    /// surface point lies in front of the camera, projects inside its image, and the segment to
    /// it is not blocked ([`DepthMesh::segment_blocked`], the pixel's own triangles excluded).
    /// The image-grid accelerator answers the whole image at once: the queries are binned by the
    /// pixel they project to ([`view_bins::PointBins`]) and every quad tests the points inside
    /// its box, the same candidate pairs as the triangle bins give each segment; the quads
    /// tested by every ray and a pixel's own two quads with a non-separating diagonal are tested
    /// per pixel afterwards, as in [`Self::segment_blocked`].
    pub fn covisibility(&self, epsilon: f64) -> Vec<bool> {
        let mesh = self.mesh;
        let pixels = mesh.points.len();
        let row = mesh.width.max(1);
        let mut mask = vec![false; pixels];
        let Some(projection) = &self.projection else {
            mask.par_chunks_mut(row).enumerate().for_each(|(v, out)| {
                for (u, keep) in out.iter_mut().enumerate() {
                    *keep = self.covisible_single(v * row + u, epsilon);
                }
            });
            return mask;
        };
        let (size, near) = self.bin_settings();
        let bins = &projection.point_bins;
        let (mut blocked, mut separates) = FLAG_POOL.take();
        blocked.resize_with(pixels, || AtomicBool::new(false));
        // Plain stores through `&mut` (a memset), not one atomic store per flag.
        blocked.iter_mut().for_each(|flag| *flag.get_mut() = false);
        // The quads of good quarters keep `true`: thick triangles separate at their shared
        // diagonal (`view_bins::thick_quad`). The others' flags are written as they are tested.
        // One fill of the whole array, not a few bytes per row of each of ~20 000 quarters.
        separates.clear();
        separates.resize(mesh.quads.len(), true);
        let ray_to = |p: usize| mesh.point(p).and_then(|point| segment_ray_for_triangles(self.eye, point, epsilon));
        let width = mesh.width as u32;
        let blocks = self.good_blocks(projection, near, size);
        // A quad of a block that is not skipped, with the smallest (x, y, depth) and largest (x, y)
        // of its corners, against the binned points inside its box but its own four corners; a
        // quad reaching close to the camera is left to the per-pixel pass (`everywhere`).
        let test_quad = |quad: u32, (lo, hi): (DVec3, DVec2), everywhere: &mut Vec<u32>, candidates: &mut Vec<u32>| {
            let reach = view_bins::Reach::of_range(lo, hi, near, size);
            match reach {
                view_bins::Reach::Everywhere => everywhere.push(quad),
                view_bins::Reach::Outside => {}
                view_bins::Reach::Box { entry, range } => {
                    // The quad's own corners (most of the points inside its box) are left out.
                    let own = |p: u32| {
                        let corner = p.wrapping_sub(quad);
                        (corner <= 1) | (corner.wrapping_sub(width) <= 1)
                    };
                    let found = bins.collect_inside(&entry, range, own, candidates);
                    for &p in &candidates[..found] {
                        if blocked[p as usize].load(Ordering::Relaxed) {
                            continue;
                        }
                        let hits =
                            ray_to(p as usize).is_some_and(|ray| mesh.blocks_segment(quad as usize, &ray, Some(p)));
                        if hits {
                            blocked[p as usize].store(true, Ordering::Relaxed);
                        }
                    }
                }
            }
        };
        let block_rows = (BLOCK * mesh.width).max(1);
        let everywhere: Vec<u32> = separates
            .par_chunks_mut(block_rows)
            .zip(blocks.par_chunks(mesh.width.div_ceil(BLOCK).max(1)))
            .enumerate()
            .flat_map_iter(|(index, (separates, good))| {
                // The quads tested by every ray, and the candidates of one quad at a time.
                let (mut everywhere, mut candidates) = (Vec::new(), Vec::new());
                let band_start = index * block_rows;
                let band_rows = separates.len() / mesh.width.max(1);
                // Per quarter of each block of the band that is not good: its pixel columns, and its
                // quads as a range of indices into the band's (whole rows).
                let quarters = (0..good.len()).flat_map(|column| (0..4).map(move |quarter| (column, quarter)));
                for (column, quarter) in quarters.filter(|&(column, quarter)| good[column] & (1 << quarter) == 0) {
                    let first_column = column * BLOCK + quarter % 2 * QUARTER;
                    let columns = (first_column.min(mesh.width), (first_column + QUARTER).min(mesh.width));
                    let first_row = quarter / 2 * QUARTER;
                    let rows = (first_row.min(band_rows), (first_row + QUARTER).min(band_rows));
                    if columns.0 == columns.1 || rows.0 == rows.1 {
                        continue;
                    }
                    let (first, end) = (rows.0 * mesh.width, rows.1 * mesh.width);
                    let quads = (band_start + first, band_start + end);
                    self.band_quads(projection, quads, columns, |offset, corners, separating| {
                        separates[first + offset] = separating;
                        if let Some(corners) = corners {
                            test_quad((quads.0 + offset) as u32, corners, &mut everywhere, &mut candidates);
                        }
                    });
                }
                everywhere
            })
            .collect();
        let nothing_everywhere = everywhere.is_empty();
        mask.par_chunks_mut(row).enumerate().for_each(|(v, out)| {
            // The row's slices of the per-pixel arrays, read in step (no index checks per pixel).
            let start = v * row;
            let end = start + out.len();
            let pixels = bins.all()[start..end].iter().zip(&blocked[start..end]).zip(&separates[start..end]);
            for (u, (keep, ((&bin, blocked), &separating))) in out.iter_mut().zip(pixels).enumerate() {
                let p = start + u;
                *keep = match bin {
                    view_bins::NO_QUERY => false,
                    view_bins::UNBINNED_QUERY => self.covisible_single(p, epsilon),
                    _ if blocked.load(Ordering::Relaxed) => false,
                    // Most pixels: nothing tested by every ray, and both diagonals separating.
                    _ if nothing_everywhere
                        && separating
                        && p.checked_sub(row + 1).is_none_or(|quad| separates[quad]) =>
                    {
                        true
                    }
                    _ => {
                        // As in `segment_blocked_with`: the quads tested by every ray but the two
                        // with `p` in both triangles, and the two with `p` as corner 0 or 3
                        // unless their diagonal separates it from the other triangle.
                        let p32 = p as u32;
                        let both = [p32.wrapping_sub(1), p32.wrapping_sub(width)];
                        let one = [p32, p32.wrapping_sub(width + 1)];
                        let mut ray = None;
                        let mut blocks = |quad: u32| {
                            ray.get_or_insert_with(|| ray_to(p))
                                .is_some_and(|ray| mesh.blocks_segment(quad as usize, &ray, Some(p32)))
                        };
                        let blocked = everywhere.iter().any(|&quad| !both.contains(&quad) && blocks(quad))
                            || one
                                .iter()
                                .any(|&quad| separates.get(quad as usize).is_some_and(|&s| !s) && blocks(quad));
                        !blocked
                    }
                };
            }
        });
        FLAG_POOL.give((blocked, separates));
        mask
    }

    /// Per block of [`BLOCK`] × [`BLOCK`] quads (row-major by block), which of its quarters
    /// (bit `q` for quarter column `q % 2` and row `q / 2`, [`QUARTER`] quads a side) are good:
    /// no quad of a good block can hide any point from the novel camera but its own corners, so
    /// that the batch skips its quads. Every quarter of a good block is good; a block that is not
    /// good may still have good quarters. A block (of either size) is good when it and up to
    /// [`RINGS`] rings of quads around it (the most without a bad quad, at least one) form a
    /// rectangle of surface quads whose triangles all keep their orientation in the novel image,
    /// each vertex farther than twice [`view_bins::MARGIN_PIXELS`] from its opposite edge
    /// ([`view_bins::thick_quad`]), all beyond the bins' near limit, and the block's box (widened
    /// as the bins widen every box) holds no binned point as deep as the block's nearest corner but
    /// the rectangle's inner vertices.
    ///
    /// Why: both cameras then see every triangle of the rectangle from the same side. Two points
    /// of the surface on one ray from the novel camera lie in one epipolar plane, whose cut
    /// through the rectangle (convex, without holes) is one chain of triangle pieces along which
    /// the direction seen from the novel camera turns monotonically, as it does from the source
    /// camera: no such ray meets the rectangle's surface twice, so its projection is one-to-one.
    /// An inner vertex's triangles then cover a disk around its image point, of radius at least
    /// their smallest height (over twice the margin), that no other triangle of the rectangle
    /// reaches: the margin argument of [`view_bins`] keeps every f32 ray to it clear of them. A
    /// quad can hide only points inside its box, which is inside the block's: those of the
    /// rectangle it cannot hide, and there are no others.
    fn good_blocks(&self, projection: &Projection, near: f64, size: (usize, usize)) -> Vec<u8> {
        let mesh = self.mesh;
        let (width, height) = (mesh.width, mesh.height);
        let points = &projection.points;
        let (bad, bins) = (&projection.bad, &projection.point_bins);
        let bad_in = |(u0, u1): (usize, usize), (v0, v1): (usize, usize)| {
            let at = |u: usize, v: usize| bad[v * (width + 1) + u];
            at(u1, v1) + at(u0, v0) - at(u0, v1) - at(u1, v0)
        };
        // The quads of the image are columns and rows ..width − 1 and ..height − 1.
        let (quad_columns, quad_rows) = (width.saturating_sub(1), height.saturating_sub(1));
        // Whether the square of `side` quads from quad (bu, bv) is good.
        let good = |bu: usize, bv: usize, side: usize| {
            let (u1, v1) = ((bu + side).min(quad_columns), (bv + side).min(quad_rows));
            if bu >= u1 || bv >= v1 {
                return false;
            }
            // The widest rectangle of at most RINGS rings without a bad quad: a wider one accepts
            // every point a narrower one does (its inner vertices include theirs).
            let rectangle = |rings: usize| {
                let widen =
                    |(start, end): (usize, usize), last: usize| (start.saturating_sub(rings), (end + rings).min(last));
                (widen((bu, u1), quad_columns), widen((bv, v1), quad_rows))
            };
            let Some((ring_u, ring_v)) = (1..=RINGS).rev().map(rectangle).find(|&(u, v)| bad_in(u, v) == 0) else {
                return false;
            };
            let (lo, hi) = view_bins::corner_range((bv..=v1).flat_map(|v| &points[v * width + bu..=v * width + u1]));
            match view_bins::Reach::of_range(lo, hi, near, size) {
                view_bins::Reach::Everywhere => false,
                view_bins::Reach::Outside => true,
                view_bins::Reach::Box { entry, range } => {
                    // The rectangle's inner vertices, whose star of triangles is whole: by the
                    // column and where the row starts, both ranges checked without a division.
                    let (columns, rows) = (ring_u.0 + 1..ring_u.1, (ring_v.0 + 1) * width..ring_v.1 * width);
                    !bins.any_inside(&entry, range, |p| {
                        let u = mesh.columns[p as usize] as usize;
                        !columns.contains(&u) || !rows.contains(&(p as usize - u))
                    })
                }
            }
        };
        let (across, down) = (width.div_ceil(BLOCK).max(1), height.div_ceil(BLOCK).max(1));
        (0..across * down)
            .into_par_iter()
            .map(|block| {
                let (bu, bv) = (block % across * BLOCK, block / across * BLOCK);
                if good(bu, bv, BLOCK) {
                    return ALL_QUARTERS;
                }
                // Near whatever spoils the block, a quarter's smaller ring and box often avoid it.
                (0..4).filter(|&q| good(bu + q % 2 * QUARTER, bv + q / 2 * QUARTER, QUARTER)).map(|q| 1 << q).sum()
            })
            .collect()
    }

    /// How many quarter blocks of quads the co-visibility batch skips ([`Self::good_blocks`]),
    /// and of how many (None with the BVH accelerator); for tests and benchmarks.
    pub fn skipped_quad_blocks(&self) -> Option<(usize, usize)> {
        let projection = self.projection.as_ref()?;
        let (size, near) = self.bin_settings();
        let blocks = self.good_blocks(projection, near, size);
        Some((blocks.iter().map(|quarters| quarters.count_ones() as usize).sum(), 4 * blocks.len()))
    }

    /// Co-visibility of pixel `p` by a single segment query (the points the batch does not bin,
    /// and every point with the BVH accelerator).
    fn covisible_single(&self, p: usize, epsilon: f64) -> bool {
        let Some(point) = self.mesh.point(p) else { return false };
        let (pixel, depth) = self.projected(p).unwrap_or_else(|| {
            let q = project(&self.novel_from_world, &self.novel, point);
            (q.truncate(), q.z)
        });
        depth > 0.0
            && self.novel.contains(pixel)
            && !self.segment_blocked_projected(point, (pixel, depth), Some(p as u32), epsilon)
    }

    /// [`DepthMesh::segment_blocked`] from the camera's centre to `to`.
    pub fn segment_blocked(&self, to: DVec3, exclude: Option<u32>, epsilon: f64) -> bool {
        self.segment_blocked_with(to, None, exclude, epsilon)
    }

    /// [`Self::segment_blocked`] for a point already projected into the novel camera: `pixel` =
    /// K · (p / p.z) and `depth` = p.z, p = `novel.camera_from_world()` applied to `to`, computed
    /// exactly so (then the answer is the same; the point is not projected a second time).
    pub fn segment_blocked_projected(
        &self,
        to: DVec3,
        projected: (DVec2, f64),
        exclude: Option<u32>,
        epsilon: f64,
    ) -> bool {
        self.segment_blocked_with(to, Some(projected), exclude, epsilon)
    }

    /// The query of [`Self::segment_blocked`], with `to`'s projection when the caller has it.
    fn segment_blocked_with(
        &self,
        to: DVec3,
        projected: Option<(DVec2, f64)>,
        exclude: Option<u32>,
        epsilon: f64,
    ) -> bool {
        let fallback = || self.mesh.segment_blocked(self.eye, to, exclude, epsilon);
        let Some(projection) = &self.projection else { return fallback() };
        let quad_bins = self.quad_bins(projection);
        // The four quads around the excluded pixel reach its bin for every view. It is corner 1
        // or 2 of two of them and in both their triangles; corner 0 or 3 of the other two and in
        // one triangle, the other one missed if their diagonal separates them.
        let width = self.mesh.width as u32;
        let (both, one) = match exclude {
            Some(p) => ([p.wrapping_sub(1), p.wrapping_sub(width)], [p, p.wrapping_sub(width + 1)]),
            None => ([u32::MAX; 2], [u32::MAX; 2]),
        };
        // Most queries reach no exact test (their own quads are skipped), so the ray is made at
        // the first. A zero-length segment (None) is never blocked; its point is at the camera's
        // centre, which the bins never bin, so the fallback gives that answer.
        let mut ray = None;
        let mut blocks = |quad: u32| {
            ray.get_or_insert_with(|| segment_ray_for_triangles(self.eye, to, epsilon))
                .is_some_and(|ray| self.mesh.blocks_segment(quad as usize, &ray, exclude))
        };
        // The bin scan skips all four; unbinned ones are tested but for `both`; binned `one`
        // quads whose diagonal does not separate are tested here (a quad that is no candidate is
        // missed by the exact test too).
        let skip = [both[0], both[1], one[0], one[1]];
        let scan = |quad: u32, binned: bool| (binned || !both.contains(&quad)) && blocks(quad);
        let answer = match projected {
            Some((pixel, depth)) => quad_bins.bins.any_towards_projected(pixel, depth, skip, scan),
            None => quad_bins.bins.any_towards(to, skip, scan),
        };
        let Some(blocked) = answer else { return fallback() };
        blocked
            || one.iter().any(|&quad| {
                quad_bins.diagonal_separates.get(quad as usize).is_some_and(|&separates| !separates) && blocks(quad)
            })
    }

    /// [`DepthMesh::first_surface_hit`] from the camera's centre along the unit `direction`.
    pub fn first_surface_hit(&self, direction: DVec3) -> Option<f64> {
        let fallback = || self.mesh.first_surface_hit(self.eye, direction);
        let Some(projection) = &self.projection else { return fallback() };
        let ray = Ray::new_inf(to_vec3a(self.eye), to_vec3a(direction));
        let hit = |quad: u32| self.mesh.hit_quad(quad as usize, &ray, false, None);
        let nearest = self.quad_bins(projection).bins.nearest_towards(self.eye + direction, hit);
        match nearest {
            Some(t) => t.is_finite().then_some(f64::from(t)),
            None => fallback(),
        }
    }
}

fn world_of(v: Vec3A) -> DVec3 {
    v.as_dvec3()
}

fn to_vec3a(v: DVec3) -> Vec3A {
    Vec3A::new(v.x as f32, v.y as f32, v.z as f32)
}

fn triangle(p: [DVec3; 3]) -> Triangle {
    Triangle { v0: to_vec3a(p[0]), v1: to_vec3a(p[1]), v2: to_vec3a(p[2]) }
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};

    use super::valid;

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
