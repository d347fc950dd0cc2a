//! A depth mesh seen from one novel camera: the production path of the two batches of rays that
//! leave the camera's centre, the co-visibility segments to every source point
//! ([`MeshView::covisibility`]) and the render rays through every novel pixel
//! ([`MeshView::surface_hits`]).
//!
//! A triangle can only meet a ray leaving the camera whose image point falls inside the
//! triangle's projection. So both batches are scanned from the quads' side on the novel image's
//! pixel grid: each quad visits the pixels its projected box covers, and there tests exactly the
//! source points that project into the box and lie behind its nearest corner (co-visibility:
//! the points are binned by the pixel they project to, `PointBins`), or the ray through each
//! pixel centre in the box (render). A quad reaching close to or behind the camera's image
//! plane, whose projection is unbounded or unstable, visits every pixel. The co-visibility batch
//! also skips the blocks of quads that can provably hide nothing (`Batch::good`).
//!
//! Exactness: for a triangle beyond [`NEAR_FRACTION`] of the nearest depth, f32 corners and rays
//! place a hit within ~1e-3 px of the exact projection; boxes are widened by [`MARGIN_PIXELS`]
//! and depth comparisons by [`DEPTH_SLACK`], so every pair left out is one the f32 triangle test
//! misses, and answers equal a loop over every triangle (integration tests).

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use glam::{DMat4, DVec2, DVec3, Vec4};
use rayon::prelude::*;

use crate::geometry::depth_mesh::{DepthMesh, MAX_SIDE, Quad, corner_indices, segment_ray};
use crate::geometry::ray_triangle::RenderRay;
use foundation::camera::{PinholeCamera, pixel_of};

/// Widening of every quad's projected box, in pixels: ×50 the f32 error of a hit's projection.
pub const MARGIN_PIXELS: f64 = 0.05;

/// Relative widening of depth comparisons, far above f32 ray/triangle round-off (~1e-6).
pub const DEPTH_SLACK: f64 = 1e-4;

/// Quads with a corner nearer the camera than this fraction of the frame's nearest depth visit
/// every pixel: close to the image plane, projection amplifies f32 round-off beyond the margin.
pub const NEAR_FRACTION: f64 = 0.1;

/// Quads per side of the blocks that the co-visibility batch skips when they hide nothing, and of
/// their quarters, tested on their own where a block is not skipped.
const BLOCK: usize = 8;
const QUARTER: usize = BLOCK / 2;

/// Most rings of regular quads around a block that [`Batch::good`] looks at: the wider the
/// rectangle, the more points of the block's neighbours, which fall inside its box wherever the
/// novel view turns or shears it, are its inner vertices; near an irregular quad, fewer rings (at
/// least one) are used.
const RINGS: usize = 6;

/// Pixel rows per task of the pass that makes a view's [`Grids`]: the quads of a band are
/// classified while its projections are in cache.
const BAND_ROWS: usize = 16;

/// A depth mesh seen from a novel camera ([`DepthMesh::view`]).
pub struct MeshView<'a> {
    mesh: &'a DepthMesh,
    novel: PinholeCamera,
    novel_from_world: DMat4,
    eye: DVec3,
    /// The depth below which a quad visits every pixel ([`NEAR_FRACTION`]).
    near: f64,
    /// What the batches read; None when the mesh has a BVH, which then answers every ray.
    grids: Option<Grids>,
}

/// The source points and quads as the novel camera sees them ([`MeshView::grids`]).
struct Grids {
    /// Per source pixel, its surface point as (pixel x, pixel y, depth) in the novel camera (zero
    /// without a point).
    projected: Vec<DVec3>,
    /// Per source pixel, the novel pixel its point is seen at: in front of the camera and inside
    /// its image, binned by the nearest pixel centre; None for the others and pixels without one.
    seen_at: Vec<Option<u32>>,
    /// The integral image of the quads that are not *regular*, surface quads beyond the near limit
    /// whose triangles turn counter-clockwise in the novel image, as in the source image, each
    /// corner farther than twice [`MARGIN_PIXELS`] from its opposite edge ([`thick_quad`]): at
    /// (v, u), how many are in quad columns ..u of quad rows ..v (v up to the image's height).
    irregular: Vec<u32>,
    /// The source image's width (quad columns + 1).
    width: usize,
}

/// Where a quad's rays can meet the novel image.
enum Reach {
    /// Close to or behind the image plane: anywhere.
    Everywhere,
    /// Its box misses the image.
    Outside,
    Box(QuadBox),
}

/// A quad's projected box widened by [`MARGIN_PIXELS`] as (x0, y0, −x1, −y1), its nearest
/// corner's depth, and the pixels [x0, x1, y0, y1] (inclusive) it covers.
struct QuadBox {
    bounds: Vec4,
    nearest: f32,
    pixels: [usize; 4],
}

impl QuadBox {
    /// Whether `point` projects inside the box and lies at or behind its nearest corner: the box
    /// is ≤ (x, y, −x, −y) in one SIMD comparison (and no branch: which of a box's points pass is
    /// unpredictable).
    fn holds(&self, point: &BinnedPoint) -> bool {
        self.bounds.cmple(Vec4::new(point.x, point.y, -point.x, -point.y)).all() & (self.nearest <= point.limit)
    }
}

/// A source point in view, as the quads' scans read it: where it projects, the depth up to which
/// a quad's nearest corner counts ([`DEPTH_SLACK`] included), and its source pixel (16 bits a
/// coordinate: [`crate::geometry::depth_mesh::MAX_SIDE`]).
#[derive(Clone, Copy, Default)]
struct BinnedPoint {
    x: f32,
    y: f32,
    limit: f32,
    column: u16,
    row: u16,
}

/// The source points in view sorted by the novel pixel they are seen at (a counting sort), so
/// that the points in a box are one contiguous run per pixel row.
struct PointBins {
    width: usize,
    /// Per novel pixel p, its points are `points[starts[p]..starts[p + 1]]`.
    starts: Vec<u32>,
    points: Vec<BinnedPoint>,
}

impl PointBins {
    /// Bins points on a novel image of `size`: per point (row-major on a grid `width` wide: the
    /// source image's for the mesh's vertices), its projection and the novel pixel it is seen at.
    fn new(
        projected: &[DVec3],
        seen_at: &[Option<u32>],
        width: usize,
        (novel_width, novel_height): (usize, usize),
    ) -> Self {
        // A counting sort: each pixel's count summed into its bin's end, then every point written
        // at its bin's decremented end (in reverse), which leaves each end at its bin's start.
        let pixels = novel_width * novel_height;
        let mut starts = vec![0u32; pixels + 1];
        for &pixel in seen_at.iter().flatten() {
            starts[pixel as usize] += 1;
        }
        let mut sum = 0;
        for end in &mut starts {
            sum += *end;
            *end = sum;
        }
        let mut points = vec![BinnedPoint::default(); starts[pixels] as usize];
        let rows = seen_at.chunks(width.max(1)).zip(projected.chunks(width.max(1))).enumerate();
        for (row, (seen_at, projected)) in rows.rev() {
            for (column, (seen_at, q)) in seen_at.iter().zip(projected).enumerate().rev() {
                if let Some(pixel) = seen_at {
                    let end = &mut starts[*pixel as usize];
                    *end -= 1;
                    let limit = (q.z * (1.0 + DEPTH_SLACK)) as f32;
                    let (column, row) = (column as u16, row as u16);
                    points[*end as usize] = BinnedPoint { x: q.x as f32, y: q.y as f32, limit, column, row };
                }
            }
        }
        Self { width: novel_width, starts, points }
    }

    /// The binned points of pixel row `row`, columns `x0..=x1`.
    fn run(&self, row: usize, x0: usize, x1: usize) -> &[BinnedPoint] {
        &self.points[self.starts[row * self.width + x0] as usize..self.starts[row * self.width + x1 + 1] as usize]
    }

    /// Writes to the front of `out` the source pixels of the binned points that `quad_box` holds
    /// and `keep` accepts, and gives their number (`out` is scratch space that only grows).
    /// Without a branch per point: which of a box's few points pass is unpredictable, so each is
    /// written and the end moves past it only if it passes.
    fn gather(
        &self,
        quad_box: &QuadBox,
        keep: impl Fn(usize) -> bool,
        source_width: usize,
        out: &mut Vec<usize>,
    ) -> usize {
        let [x0, x1, y0, y1] = quad_box.pixels;
        let mut end = 0;
        for row in y0..=y1 {
            let run = self.run(row, x0, x1);
            if out.len() < end + run.len() {
                out.resize(end + run.len(), 0);
            }
            for point in run {
                let p = usize::from(point.row) * source_width + usize::from(point.column);
                out[end] = p;
                end += usize::from(quad_box.holds(point) & keep(p));
            }
        }
        end
    }

    /// Whether `quad_box` holds a binned point for which `test` is true (`test` is cheap: it runs
    /// on every point in the box, without a branch on whether the box holds it).
    fn any_inside(&self, quad_box: &QuadBox, test: impl Fn(&BinnedPoint) -> bool) -> bool {
        let [x0, x1, y0, y1] = quad_box.pixels;
        (y0..=y1).any(|row| self.run(row, x0, x1).iter().any(|point| quad_box.holds(point) & test(point)))
    }
}

impl Grids {
    /// How many quads in quad columns `u0..u1` of quad rows `v0..v1` are not regular.
    fn irregular_within(&self, (u0, u1): (usize, usize), (v0, v1): (usize, usize)) -> u32 {
        let at = |u: usize, v: usize| self.irregular[v * self.width + u];
        at(u1, v1) + at(u0, v0) - at(u0, v1) - at(u1, v0)
    }
}

/// A rectangle of quads: quad columns `u0..u1` and rows `v0..v1`.
type Rect = ((usize, usize), (usize, usize));

/// The non-empty quarters of a block.
fn quarters(((u0, u1), (v0, v1)): Rect) -> Vec<Rect> {
    let split = |(start, end): (usize, usize)| [(start, (start + QUARTER).min(end)), ((start + QUARTER).min(end), end)];
    let (columns, rows) = (split((u0, u1)), split((v0, v1)));
    let all = rows.iter().flat_map(|&rows| columns.map(|columns| (columns, rows)));
    all.filter(|((u0, u1), (v0, v1))| u0 < u1 && v0 < v1).collect()
}

impl DepthMesh {
    /// The mesh seen from a novel camera, for the batches of rays leaving its centre (defined
    /// here, beside what it builds, so that the mesh does not depend on its views).
    pub fn view(&self, novel: &PinholeCamera) -> MeshView<'_> {
        let (novel_from_world, eye, near) =
            (novel.camera_from_world(), novel.center(), self.nearest_depth() * NEAR_FRACTION);
        let mut view = MeshView { mesh: self, novel: *novel, novel_from_world, eye, near, grids: None };
        // With a BVH nothing is prepared: it answers every ray.
        if !self.has_bvh() {
            view.grids = Some(view.grids());
        }
        view
    }
}

impl MeshView<'_> {
    /// The view's [`Grids`], in one pass over bands of [`BAND_ROWS`] pixel rows (in parallel):
    /// a band's points projected and binned, then its quads counted into the rows of the
    /// integral image, summed down the columns afterwards.
    fn grids(&self) -> Grids {
        let (width, height) = (self.mesh.width(), self.mesh.height());
        let project_row = |v: usize, projected: &mut [DVec3], seen_at: &mut [Option<u32>]| {
            for (u, (q, seen_at)) in projected.iter_mut().zip(seen_at).enumerate() {
                let Some(point) = self.mesh.point(v * width + u) else { continue };
                *q = self.project(point);
                *seen_at = self.seen_at(*q);
            }
        };
        let (mut projected, mut seen_at) = (vec![DVec3::ZERO; width * height], vec![None; width * height]);
        let mut sums = vec![0u32; width * (height + 1)];
        let band = BAND_ROWS * width.max(1);
        let bands =
            projected.par_chunks_mut(band).zip(seen_at.par_chunks_mut(band)).zip(sums[width..].par_chunks_mut(band));
        bands.enumerate().for_each(|(index, ((projected, seen_at), sums))| {
            let first = index * BAND_ROWS;
            for (r, (projected, seen_at)) in projected.chunks_mut(width).zip(seen_at.chunks_mut(width)).enumerate() {
                project_row(first + r, projected, seen_at);
            }
            // The band's last quad row reaches the next band's first row, projected again here
            // (the same arithmetic, so the same values).
            let rows = projected.len() / width.max(1);
            let mut next = vec![DVec3::ZERO; if first + rows < height { width } else { 0 }];
            project_row(first + rows, &mut next, &mut vec![None; width]);
            for (r, sums) in sums.chunks_mut(width).enumerate().take_while(|(r, _)| first + r + 1 < height) {
                let upper = &projected[r * width..(r + 1) * width];
                let lower = if r + 1 < rows { &projected[(r + 1) * width..(r + 2) * width] } else { &next };
                let mut irregular = 0;
                for u in 0..width - 1 {
                    let c = [upper[u], upper[u + 1], lower[u], lower[u + 1]];
                    let regular = self.mesh.quad((first + r) * width + u) == Quad::Surface
                        && c.iter().all(|c| c.z > self.near)
                        && thick_quad(c.map(DVec3::truncate), 2.0);
                    irregular += u32::from(!regular);
                    sums[u + 1] = irregular;
                }
            }
        });
        for v in 1..=height {
            let (above, row) = sums[(v - 1) * width..(v + 1) * width].split_at_mut(width);
            row.iter_mut().zip(above.iter()).for_each(|(sum, above)| *sum += above);
        }
        Grids { projected, seen_at, irregular: sums, width }
    }

    /// World point `point` as (pixel x, pixel y, depth) in the novel camera (pixel coordinates
    /// are meaningless for depth ≤ 0).
    fn project(&self, point: DVec3) -> DVec3 {
        let in_novel = self.novel_from_world.transform_point3(point);
        pixel_of(&self.novel.intrinsics, in_novel).extend(in_novel.z)
    }

    /// The novel pixel at which a point projected to `q` ([`Self::project`]) is seen: in front of
    /// the camera and inside its image, binned by the nearest pixel centre; None otherwise.
    fn seen_at(&self, q: DVec3) -> Option<u32> {
        let (novel_width, novel_height) = (self.novel.width as usize, self.novel.height as usize);
        (q.z > 0.0 && self.novel.contains(q.truncate())).then(|| {
            // Clamped: rounding must not move a point out of the image.
            let (x, y) = (pixel_index(q.x + 0.5), pixel_index(q.y + 0.5));
            (y.min(novel_height - 1) * novel_width + x.min(novel_width - 1)) as u32
        })
    }

    /// [`DepthMesh::segment_blocked`] from the camera's centre to `to`.
    pub fn segment_blocked(&self, to: DVec3, exclude: Option<u32>, epsilon: f64) -> bool {
        self.mesh.segment_blocked(self.eye, to, exclude, epsilon)
    }

    /// [`DepthMesh::first_surface_hit`] from the camera's centre along the unit `direction`.
    pub fn first_surface_hit(&self, direction: DVec3) -> Option<f64> {
        self.mesh.first_surface_hit(self.eye, direction)
    }

    /// Where the rays can meet a quad ([`Self::reach`] of its corners, a skirt's as pulled onto
    /// the skirt); None for a quad without triangles.
    fn quad_reach(&self, grids: &Grids, quad: usize) -> Option<Reach> {
        let corners = match self.mesh.quad(quad) {
            Quad::Empty => return None,
            Quad::Surface => corner_indices(quad, self.mesh.width()).map(|p| grids.projected[p]),
            Quad::Skirt(_) => {
                let [a, b] = self.mesh.triangles(quad);
                [a.v0, a.v1, a.v2, b.v1].map(|v| self.project(v.as_dvec3()))
            }
        };
        Some(self.reach(&corners))
    }

    /// Where rays can meet anything inside the hull of `corners` (pixel x, pixel y, depth).
    fn reach<'c>(&self, corners: impl IntoIterator<Item = &'c DVec3>) -> Reach {
        // Plain comparisons (no NaN handling): the corners of quads with triangles are finite.
        let (mut lo, mut hi) = (DVec3::INFINITY, DVec2::NEG_INFINITY);
        for c in corners {
            lo = DVec3::select(c.cmplt(lo), *c, lo);
            hi = DVec2::select(c.truncate().cmpgt(hi), c.truncate(), hi);
        }
        let nearest = lo.z;
        if nearest <= self.near {
            return Reach::Everywhere;
        }
        let (lo, hi) = (lo.truncate() - MARGIN_PIXELS, hi + MARGIN_PIXELS);
        // Pixel k owns [k − 0.5, k + 0.5).
        if !(hi.x + 0.5 >= 0.0 && hi.y + 0.5 >= 0.0) {
            return Reach::Outside;
        }
        let (width, height) = (self.novel.width as usize, self.novel.height as usize);
        let (x0, y0) = (pixel_index((lo.x + 0.5).max(0.0)), pixel_index((lo.y + 0.5).max(0.0)));
        let (x1, y1) = (pixel_index(hi.x + 0.5).min(width - 1), pixel_index(hi.y + 0.5).min(height - 1));
        if x0 > x1 || y0 > y1 {
            return Reach::Outside;
        }
        let bounds = Vec4::new(lo.x as f32, lo.y as f32, -hi.x as f32, -hi.y as f32);
        Reach::Box(QuadBox { bounds, nearest: nearest as f32, pixels: [x0, x1, y0, y1] })
    }

    /// Whether the diagonal shared by a surface quad's two triangles separates corners 0 and 3 in
    /// the novel image, beyond twice [`MARGIN_PIXELS`]: then neither can be hidden by the
    /// triangle opposite it ([`line_separates`]).
    fn diagonal_separates(&self, grids: &Grids, quad: usize) -> bool {
        if self.mesh.quad(quad) != Quad::Surface {
            return false;
        }
        let c = corner_indices(quad, self.mesh.width()).map(|p| grids.projected[p]);
        let [a, b, c0, d] = c.map(DVec3::truncate);
        c.iter().all(|c| c.z > 0.0) && line_separates(b, c0, a, d, 2.0) && line_separates(b, c0, d, a, 2.0)
    }

    /// Columns and rows of quads (the pixels but the last column and row).
    fn quad_grid(&self) -> (usize, usize) {
        (self.mesh.width().saturating_sub(1), self.mesh.height().saturating_sub(1))
    }

    /// The blocks of [`BLOCK`] × [`BLOCK`] quads, row-major.
    fn blocks(&self) -> impl IndexedParallelIterator<Item = Rect> {
        let (columns, rows) = self.quad_grid();
        let across = columns.div_ceil(BLOCK);
        (0..across * rows.div_ceil(BLOCK)).into_par_iter().map(move |block| {
            let (u0, v0) = (block % across * BLOCK, block / across * BLOCK);
            ((u0, (u0 + BLOCK).min(columns)), (v0, (v0 + BLOCK).min(rows)))
        })
    }

    /// Co-visibility from the view's camera of every source pixel (row-major): whether its
    /// surface point lies in front of the camera, projects inside its image, and the segment to
    /// it is not blocked ([`DepthMesh::segment_blocked`], the pixel's own triangles excluded).
    pub fn covisibility(&self, epsilon: f64) -> Vec<bool> {
        self.visibility(None, epsilon)
    }

    /// Visibility from the view's camera of points that are not the mesh's vertices (another
    /// camera's surface points, row-major on a grid `width` wide, None where it has none), each
    /// with the source pixel whose surface it is, if any ([`DepthMesh::footprint_of`]): whether
    /// each lies in front of the camera, projects inside its image, and the segment to it crosses
    /// no triangle of the mesh ([`DepthMesh::segment_blocked`]) but those having that pixel as a
    /// corner, its own surface, as a vertex's own triangles never hide the vertex. The same batch
    /// and the same exactness as [`Self::covisibility`].
    pub fn visibility_of(&self, points: &[Option<(DVec3, Option<u32>)>], width: usize, epsilon: f64) -> Vec<bool> {
        assert!(width.max(points.len() / width.max(1)) <= MAX_SIDE, "point grids are read up to {MAX_SIDE} px a side");
        self.visibility(Some(Foreign { points, width }), epsilon)
    }

    /// [`Self::covisibility`] of the mesh's vertices (`foreign` None) or [`Self::visibility_of`]
    /// the `foreign` points.
    fn visibility(&self, foreign: Option<Foreign<'_>>, epsilon: f64) -> Vec<bool> {
        let mesh = self.mesh;
        let Some(grids) = &self.grids else {
            let count = foreign.as_ref().map_or(mesh.width() * mesh.height(), |f| f.points.len());
            return (0..count)
                .into_par_iter()
                .map(|p| {
                    let point = match &foreign {
                        None => mesh.point(p).map(|point| (point, Some(p as u32))),
                        Some(foreign) => foreign.points[p],
                    };
                    let Some((point, own)) = point else { return false };
                    let q = self.project(point);
                    q.z > 0.0 && self.novel.contains(q.truncate()) && !self.segment_blocked(point, own, epsilon)
                })
                .collect();
        };
        let batch = Batch::new(self, grids, foreign, epsilon);
        let everywhere: Vec<usize> = self.blocks().flat_map_iter(|block| batch.scan_block(block)).collect();
        let seen_at = batch.seen_at();
        let visible = |p: usize| {
            seen_at[p].is_some()
                && !batch.blocked[p].load(Ordering::Relaxed)
                && !everywhere.iter().any(|&quad| batch.may_hide(quad, p) && batch.hides(quad, p))
        };
        (0..seen_at.len()).into_par_iter().map(visible).collect()
    }

    /// The first surface hit of the ray through every novel pixel (row-major): its distance along
    /// the unit direction `novel.pixel_ray(x, y).normalize()`, None where it hits nothing. Hits
    /// are those of [`super::ray_triangle`]: closed surface triangles, the mesh's vertices and
    /// its footprint fragments ([`DepthMesh::fragments`]).
    pub fn surface_hits(&self) -> Vec<Option<f64>> {
        let (width, height) = (self.novel.width as usize, self.novel.height as usize);
        let rays: Vec<RenderRay> = (0..width * height)
            .into_par_iter()
            .map(|i| {
                let direction = self.novel.pixel_ray((i % width) as f64, (i / width) as f64).normalize();
                RenderRay::new(self.eye, direction)
            })
            .collect();
        // Per pixel the nearest distance so far, as f64 bits: positive floats order as their bits.
        let nearest: Vec<AtomicU64> = (0..width * height).map(|_| AtomicU64::new(f64::INFINITY.to_bits())).collect();
        let record = |i: usize, t: Option<f64>| {
            if let Some(t) = t {
                nearest[i].fetch_min(t.to_bits(), Ordering::Relaxed);
            }
        };
        match &self.grids {
            None => rays.par_iter().enumerate().for_each(|(i, ray)| record(i, self.mesh.first_triangle_hit(ray))),
            Some(grids) => {
                let quads = (0..grids.projected.len()).into_par_iter().filter(|&q| self.mesh.quad(q) == Quad::Surface);
                quads.for_each(|quad| {
                    let [x0, x1, y0, y1] = match self.quad_reach(grids, quad) {
                        Some(Reach::Box(quad_box)) => quad_box.pixels,
                        Some(Reach::Everywhere) => [0, width - 1, 0, height - 1],
                        Some(Reach::Outside) | None => return,
                    };
                    for i in (y0..=y1).flat_map(|y| y * width + x0..=y * width + x1) {
                        record(i, self.mesh.surface_hit(quad, &rays[i]));
                    }
                });
            }
        }
        // A vertex can only be hit by the ray of the pixel centre nearest its image point (the
        // tolerance is far below half a pixel).
        (0..self.mesh.width() * self.mesh.height()).into_par_iter().for_each(|p| {
            let Some(point) = self.mesh.point(p) else { return };
            let q = self.project(point);
            let (x, y) = (q.x.round(), q.y.round());
            if q.z > 0.0 && x >= 0.0 && y >= 0.0 && x < width as f64 && y < height as f64 {
                let i = y as usize * width + x as usize;
                record(i, rays[i].vertex_hit(point));
            }
        });
        // The footprint fragments, each tested against the rays in its box as a quad is.
        (0..self.mesh.width() * self.mesh.height()).into_par_iter().for_each(|p| {
            for fragment in self.mesh.fragments(p) {
                let corners = fragment.map(|corner| self.project(corner));
                let [x0, x1, y0, y1] = match self.reach(&corners) {
                    Reach::Box(quad_box) => quad_box.pixels,
                    Reach::Everywhere => [0, width - 1, 0, height - 1],
                    Reach::Outside => continue,
                };
                for i in (y0..=y1).flat_map(|y| y * width + x0..=y * width + x1) {
                    record(i, DepthMesh::fragment_hit(&fragment, &rays[i]));
                }
            }
        });
        nearest.into_iter().map(|t| Some(f64::from_bits(t.into_inner())).filter(|t| t.is_finite())).collect()
    }
}

/// Points that a visibility batch tests other than the mesh's vertices ([`MeshView::visibility_of`]).
struct Foreign<'p> {
    /// Row-major on a grid `width` wide, with the pixel whose triangles never hide it; None
    /// where there is no point.
    points: &'p [Option<(DVec3, Option<u32>)>],
    width: usize,
}

/// The foreign points as the novel camera sees them.
struct SeenForeign<'p> {
    points: &'p [Option<(DVec3, Option<u32>)>],
    width: usize,
    /// Per point, the novel pixel it is seen at (as [`Grids::seen_at`]).
    seen_at: Vec<Option<u32>>,
}

/// One visibility batch of a view: the mesh's own vertices ([`MeshView::covisibility`]) or
/// foreign points ([`MeshView::visibility_of`]).
struct Batch<'v, 'm> {
    view: &'v MeshView<'m>,
    grids: &'v Grids,
    /// None: the points tested are the mesh's vertices, each excluding its own triangles.
    foreign: Option<SeenForeign<'v>>,
    bins: PointBins,
    /// Per point tested, whether a quad was found to hide it.
    blocked: Vec<AtomicBool>,
    epsilon: f64,
}

impl<'v, 'm> Batch<'v, 'm> {
    fn new(view: &'v MeshView<'m>, grids: &'v Grids, foreign: Option<Foreign<'v>>, epsilon: f64) -> Self {
        let novel_size = (view.novel.width as usize, view.novel.height as usize);
        let (foreign, bins) = match foreign {
            None => (None, PointBins::new(&grids.projected, &grids.seen_at, view.mesh.width(), novel_size)),
            Some(Foreign { points, width }) => {
                let projected: Vec<DVec3> = points
                    .par_iter()
                    .map(|point| point.map_or(DVec3::ZERO, |(point, _)| view.project(point)))
                    .collect();
                let seen_at: Vec<Option<u32>> =
                    points.par_iter().zip(&projected).map(|(point, &q)| point.and_then(|_| view.seen_at(q))).collect();
                let bins = PointBins::new(&projected, &seen_at, width, novel_size);
                (Some(SeenForeign { points, width, seen_at }), bins)
            }
        };
        let count = foreign.as_ref().map_or(grids.seen_at.len(), |f| f.seen_at.len());
        let blocked = (0..count).map(|_| AtomicBool::new(false)).collect();
        Self { view, grids, foreign, bins, blocked, epsilon }
    }

    /// Per point tested, the novel pixel it is seen at.
    fn seen_at(&self) -> &[Option<u32>] {
        self.foreign.as_ref().map_or(&self.grids.seen_at, |f| &f.seen_at)
    }

    /// Tests the quads of `block` against the points in their boxes, but those of the block, or
    /// of its quarters, that are good; gives the quads that reach everywhere.
    fn scan_block(&self, block: Rect) -> Vec<usize> {
        let mut everywhere = Vec::new();
        if !self.good(block) {
            for quarter in quarters(block).into_iter().filter(|&quarter| !self.good(quarter)) {
                self.scan(quarter, &mut everywhere);
            }
        }
        everywhere
    }

    /// Whether no quad of `rect` can hide any binned point but its own corners, so that the batch
    /// skips them. It is *good* when it and up to [`RINGS`] rings of quads around it (the most
    /// without an irregular one, at least one) form a rectangle of regular quads
    /// (see [`Grids::irregular`]), and its box holds no binned point at or behind its nearest
    /// corner but the rectangle's inner vertices.
    ///
    /// Why: both cameras then see every triangle of the rectangle from the same side. Two points
    /// of the surface on one ray from the novel camera lie in one epipolar plane, whose cut
    /// through the rectangle (convex, without holes) is one chain of triangle pieces along which
    /// the direction seen from the novel camera turns monotonically, as it does from the source
    /// camera: no such ray meets the rectangle's surface twice, so its projection is one-to-one.
    /// An inner vertex's triangles then cover a disk around its image point, of radius at least
    /// their smallest height (over twice the margin), that no other triangle of the rectangle
    /// reaches: the margin argument of the module documentation keeps every f32 ray to the vertex
    /// clear of them. A quad can hide only points inside its box, which is inside `rect`'s:
    /// those of the rectangle it cannot hide, and there are no others.
    fn good(&self, ((u0, u1), (v0, v1)): Rect) -> bool {
        let (view, width) = (self.view, self.view.mesh.width());
        let (columns, rows) = view.quad_grid();
        let widen = |(start, end): (usize, usize), rings: usize, last: usize| {
            (start.saturating_sub(rings), (end + rings).min(last))
        };
        let rectangles = (1..=RINGS).rev().map(|rings| (widen((u0, u1), rings, columns), widen((v0, v1), rings, rows)));
        let Some(((r0, r1), (s0, s1))) = rectangles.into_iter().find(|&(u, v)| self.grids.irregular_within(u, v) == 0)
        else {
            return false;
        };
        // The vertices of `rect`: columns u0..=u1 of rows v0..=v1.
        let corners = (v0..=v1).flat_map(|v| &self.grids.projected[v * width + u0..=v * width + u1]);
        match view.reach(corners) {
            Reach::Everywhere => false,
            Reach::Outside => true,
            // Foreign points are no vertex of the mesh: any of them in the box may be hidden.
            Reach::Box(quad_box) if self.foreign.is_some() => !self.bins.any_inside(&quad_box, |_| true),
            Reach::Box(quad_box) => !self.bins.any_inside(&quad_box, |point| {
                // Not an inner vertex: its column outside r0 + 1..r1 or its row outside s0 + 1..s1
                // (each by one comparison: below the start wraps to the top).
                let (u, v) = (usize::from(point.column), usize::from(point.row));
                (u.wrapping_sub(r0 + 1) >= r1 - (r0 + 1)) | (v.wrapping_sub(s0 + 1) >= s1 - (s0 + 1))
            }),
        }
    }

    /// Tests each quad of `rect` against the binned points in its box, marking those it hides;
    /// the quads that reach everywhere are added to `everywhere` instead.
    fn scan(&self, ((u0, u1), (v0, v1)): Rect, everywhere: &mut Vec<usize>) {
        let (view, width) = (self.view, self.view.mesh.width());
        let mut candidates = Vec::new();
        for quad in (v0..v1).flat_map(|v| v * width + u0..v * width + u1) {
            match view.quad_reach(self.grids, quad) {
                Some(Reach::Everywhere) => everywhere.push(quad),
                Some(Reach::Outside) | None => {}
                Some(Reach::Box(quad_box)) => {
                    let Some(foreign) = &self.foreign else {
                        // Its own corners are most of the points in its box: see `may_hide`.
                        let found = self.bins.gather(&quad_box, |p| !is_corner(quad, p, width), width, &mut candidates);
                        for &p in &candidates[..found] {
                            self.test(quad, p);
                        }
                        if !view.diagonal_separates(self.grids, quad) {
                            self.test(quad, quad);
                            self.test(quad, quad + width + 1);
                        }
                        continue;
                    };
                    let found = self.bins.gather(&quad_box, |_| true, foreign.width, &mut candidates);
                    for &p in &candidates[..found] {
                        self.test(quad, p);
                    }
                }
            }
        }
    }

    /// Marks point `p` blocked if a triangle of `quad` (without `p` as a corner, for a vertex)
    /// crosses the segment to it.
    fn test(&self, quad: usize, p: usize) {
        if !self.blocked[p].load(Ordering::Relaxed) && self.hides(quad, p) {
            self.blocked[p].store(true, Ordering::Relaxed);
        }
    }

    /// Whether `quad` may hide the point of pixel `p`, so that it is tested: unless `p` is a
    /// corner (the point's own surface never hides it). Corners 1 and 2 are in both triangles;
    /// corners 0 and 3 are in one, and the other cannot hide them when the quad's diagonal
    /// separates them from it ([`MeshView::diagonal_separates`]). Any quad may hide a foreign
    /// point.
    fn may_hide(&self, quad: usize, p: usize) -> bool {
        let width = self.view.mesh.width();
        self.foreign.is_some()
            || !is_corner(quad, p, width)
            || ((p == quad || p == quad + width + 1) && !self.view.diagonal_separates(self.grids, quad))
    }

    /// Whether a triangle of `quad` crosses the segment to point `p` (for a vertex, a triangle
    /// without `p` as a corner).
    fn hides(&self, quad: usize, p: usize) -> bool {
        let mesh = self.view.mesh;
        let (point, own) = match &self.foreign {
            None => (mesh.point(p).expect("corners and binned points have one"), Some(p)),
            Some(foreign) => {
                let (point, own) = foreign.points[p].expect("binned points have one");
                (point, own.map(|own| own as usize))
            }
        };
        segment_ray(self.view.eye, point, self.epsilon).is_some_and(|ray| mesh.blocks_segment(quad, &ray, own))
    }
}

/// Whether pixel `p` is a corner of the quad whose corner 0 is pixel `quad` (without a branch:
/// most of the points in a quad's box are its corners, in no predictable order).
fn is_corner(quad: usize, p: usize, width: usize) -> bool {
    let offset = p.wrapping_sub(quad);
    (offset <= 1) | (offset.wrapping_sub(width) <= 1)
}

/// A non-negative pixel coordinate truncated to an index (through i32: one instruction, where
/// f64 → usize is emulated; values far outside any image saturate and are clamped or rejected).
fn pixel_index(coordinate: f64) -> usize {
    coordinate as i32 as usize
}

/// Whether the line through `a` and `b` (pixel coordinates) has `point` farther than
/// `margins` × [`MARGIN_PIXELS`] on one side and `other` on the other side or on the line. A
/// triangle with edge a–b and third corner `other` then cannot be hit by a ray through the image
/// point `point` (the margin argument of the module documentation holds for any separating line).
fn line_separates(a: DVec2, b: DVec2, point: DVec2, other: DVec2, margins: f64) -> bool {
    let edge = b - a;
    let (point_side, other_side) = (edge.perp_dot(point - a), edge.perp_dot(other - a));
    // |edge|₁ ≥ |edge|₂: a conservative distance bound without a square root.
    let margin = margins * MARGIN_PIXELS * (edge.x.abs() + edge.y.abs());
    (point_side > margin && other_side <= 0.0) || (point_side < -margin && other_side >= 0.0)
}

/// Whether both triangles of a quad with corners `a`, `b`, `c`, `d` (pixel coordinates; see
/// [`Quad`]), (a, b, c) and (b, d, c), turn counter-clockwise in the image's axes (x right, y
/// down: as they do in their source image) with every corner farther than `margins` ×
/// [`MARGIN_PIXELS`] from the line of its opposite edge. Twice a triangle's area over an edge's
/// length is that corner's distance from the edge's line; the edges' 1-norms (at least their
/// lengths) make the test conservative without square roots. Both triangles thick also means that
/// their diagonal separates corners 0 and 3 ([`line_separates`] with the same margins).
fn thick_quad([a, b, c, d]: [DVec2; 4], margins: f64) -> bool {
    let (ab, ac, bc, bd, cd) = (b - a, c - a, c - b, d - b, d - c);
    let margin = margins * MARGIN_PIXELS;
    // Twice the area above the margin times each edge's 1-norm (without a branch).
    let thick = |area: f64, edges: [DVec2; 3]| {
        edges.iter().fold(true, |all, e| all & (area > margin * (e.x.abs() + e.y.abs())))
    };
    thick(ab.perp_dot(ac), [ab, ac, bc]) & thick(bd.perp_dot(bc), [bd, cd, bc])
}

/// Counters of the image-grid path's internals, for tests and benchmarks only (not part of the
/// kernel's API: they rebuild what a batch builds, to count it).
#[doc(hidden)]
pub mod probe {
    use super::*;

    /// Quarter blocks of quads the co-visibility batch skips (`Batch::good`), and all quarter
    /// blocks (None with the BVH); for tests and benchmarks.
    pub fn skipped_quad_blocks(view: &MeshView<'_>) -> Option<(usize, usize)> {
        let batch = Batch::new(view, view.grids.as_ref()?, None, 0.0);
        let count = |block: Rect| {
            let (whole, quarters) = (batch.good(block), quarters(block));
            (quarters.iter().filter(|&&quarter| whole || batch.good(quarter)).count(), quarters.len())
        };
        Some(view.blocks().map(count).reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1)))
    }

    /// How many (quad, pixel) pairs the boxes of the quads with triangles cover, and how many
    /// quads reach every pixel (None with the BVH); for tests and benchmarks.
    pub fn bin_sizes(view: &MeshView<'_>) -> Option<(usize, usize)> {
        let grids = view.grids.as_ref()?;
        let (mut pairs, mut everywhere) = (0, 0);
        for quad in 0..grids.projected.len() {
            match view.quad_reach(grids, quad) {
                Some(Reach::Box(QuadBox { pixels: [x0, x1, y0, y1], .. })) => pairs += (x1 + 1 - x0) * (y1 + 1 - y0),
                Some(Reach::Everywhere) => everywhere += 1,
                Some(Reach::Outside) | None => {}
            }
        }
        Some((pairs, everywhere))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_line_separates_only_beyond_the_margin_and_with_the_triangle_on_the_other_side() {
        let (a, b) = (DVec2::new(0.0, 0.0), DVec2::new(1.0, 1.0));
        let (left, right) = (DVec2::new(0.0, 1.0), DVec2::new(1.0, 0.0));
        assert!(line_separates(a, b, left, right, 1.0));
        assert!(line_separates(a, b, right, left, 1.0));
        // Third corner on the line: the triangle is degenerate but still on one side.
        assert!(line_separates(a, b, left, DVec2::new(2.0, 2.0), 1.0));
        // Both on the same side: no separation.
        assert!(!line_separates(a, b, left, DVec2::new(0.2, 0.9), 1.0));
        // Within the margin of the line (0.05 px; the bound uses |edge|₁ = 2, so ≈ 0.07 px).
        let close = DVec2::new(0.5, 0.5) + DVec2::new(-1.0, 1.0).normalize() * 0.06;
        assert!(!line_separates(a, b, close, right, 1.0));
        let far = DVec2::new(0.5, 0.5) + DVec2::new(-1.0, 1.0).normalize() * 0.08;
        assert!(line_separates(a, b, far, right, 1.0));
        // A zero-length edge separates nothing.
        assert!(!line_separates(a, a, left, right, 1.0));
    }
}
