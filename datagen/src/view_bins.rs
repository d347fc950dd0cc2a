//! Bins over a novel camera's image for the two per-view batches of DESIGN §4, the co-visibility
//! segments from the novel camera to every source point and the render rays through every novel
//! pixel: triangle bins ([`ViewBins`]) for rays one at a time, and bins of the source points
//! ([`PointBins`]) for the co-visibility batch, scanned from the triangles' side with the same
//! boxes and comparisons. All those rays leave the novel camera's centre, so a
//! triangle can only be hit by the rays whose image point falls inside the triangle's projection.
//! Each primitive's projected box (widened) is recorded once, in the bin of the novel pixel at its
//! top-left corner (a counting sort, linear in the primitives), together with the box and depth; a
//! ray scans the bins of the 2 × 2 pixels (`WINDOW`) up to and including its own, where
//! every box reaching its pixel is anchored. Boxes spanning more pixels in a direction are cut
//! into tiles of at most that many, each anchored alike, so that no box escapes the window. A
//! ray's candidates are then one contiguous run of the sorted array per row of the window, read
//! without indirection and nearly all culled by comparing box and depth before the exact f32
//! triangle test runs. (The earlier layout put each box's id into every bin it covers, about six
//! per box: three times the entries to sort, and a lookup per candidate.)
//!
//! Exactness: boxes are widened by [`MARGIN_PIXELS`], depths by [`DEPTH_SLACK`], and triangles
//! reaching close to or behind the camera's image plane (whose projection is unbounded or
//! numerically unstable) are tested by every ray, so answers equal a brute-force loop over every
//! triangle. Sub-pixel ray points are binned by their nearest pixel centre.

use glam::{DMat3, DMat4, DVec2, DVec3, Vec4};

use crate::pool::Pool;

/// Widening of every triangle's projected box. f32 corners and rays place a hit's projection
/// within ~1e-3 px of the exact one for triangles beyond the near limit; this leaves ×50.
pub const MARGIN_PIXELS: f64 = 0.05;

/// Relative widening of depth comparisons, far above f32 ray/triangle round-off (~1e-6).
pub const DEPTH_SLACK: f64 = 1e-4;

/// Primitives with a corner nearer the camera than this fraction of the nearest surface depth are
/// not binned but tested by every ray: close to the image plane, projection amplifies f32
/// round-off beyond the margin.
pub const NEAR_FRACTION: f64 = 0.1;

/// Pixels per side of the window a ray scans, and most pixels per side of one tile of a box.
/// At 2 a box of about a pixel (a quad seen at the source's scale) is mostly one tile, and a ray
/// scans about 7 entries on the benchmark clip; 3 × 3 (fewer tiles, more entries per scan) was no
/// faster in interleaved runs.
const WINDOW: usize = 2;

/// The bins of one novel view.
pub struct ViewBins {
    width: usize,
    /// (width, height) as f64, for the bin test of every ray.
    extent: DVec2,
    novel_from_world: DMat4,
    intrinsics: DMat3,
    /// The arrays, taken from [`POOL`] and given back on drop.
    buffers: BinBuffers,
}

/// A primitive as the bins see it: its widened projected box and nearest corner depth, read by
/// the rays of its bins (outside the box or ending before that depth: no exact test), kept in
/// the form the bins store ([`Entry`]), and where its box is anchored.
#[derive(Clone, Copy)]
pub struct Footprint {
    entry: Entry,
    anchor: u32,
}

/// [`Footprint::anchor`] of a primitive in no bin (outside the image).
const UNBINNED: u32 = u32::MAX;
/// [`Footprint::anchor`] of a primitive every ray is tested against (see [`NEAR_FRACTION`]).
const EVERYWHERE: u32 = u32::MAX - 1;
/// [`Footprint::anchor`] of a box cut into several tiles ([`Footprint::for_each_tile`]).
const TILED: u32 = u32::MAX - 2;

impl Footprint {
    /// A primitive no ray meets (none with that id, or its box is outside the image).
    pub const OUTSIDE: Self = Self { entry: Entry { bounds: [0.0; 4], nearest: 0.0 }, anchor: UNBINNED };
    /// A primitive every ray is tested against (see [`NEAR_FRACTION`]).
    const EVERYWHERE: Self = Self { entry: Entry { bounds: [0.0; 4], nearest: 0.0 }, anchor: EVERYWHERE };

    /// The footprint of a primitive whose corners, as (pixel x, pixel y, depth) in the novel
    /// camera, have the smallest (x, y, depth) `lo` and largest (x, y) `hi` ([`corner_range`],
    /// or shared by neighbours); `near` is [`ViewBins::near_limit`], `size` the image's.
    #[inline]
    pub fn of_range(lo: DVec3, hi: DVec2, near: f64, (width, height): (usize, usize)) -> Self {
        match Reach::of_range(lo, hi, near, (width, height)) {
            Reach::Everywhere => Self::EVERYWHERE,
            Reach::Outside => Self::OUTSIDE,
            Reach::Box { entry, range: [x0, x1, y0, y1] } => {
                let anchor = if x1 - x0 < WINDOW && y1 - y0 < WINDOW { (y0 * width + x0) as u32 } else { TILED };
                Self { entry, anchor }
            }
        }
    }

    /// Calls `visit` with the anchor pixels (row-major index) of the tiles of a [`TILED`] box
    /// (recomputing its pixel range from the f32 box: a hit lies far inside the box, so the
    /// rounding is harmless).
    fn for_each_tile(&self, size: (usize, usize), mut visit: impl FnMut(usize)) {
        let [x0, y0, x1, y1] = self.entry.bounds.map(f64::from);
        let Some([x0, x1, y0, y1]) = pixel_range(DVec2::new(x0, y0), DVec2::new(-x1, -y1), size) else { return };
        let mut y = y0;
        while y <= y1 {
            let mut x = x0;
            while x <= x1 {
                visit(y * size.0 + x);
                x += WINDOW;
            }
            y += WINDOW;
        }
    }
}

/// Where a primitive's rays can meet the image: what its [`Footprint`] records, with the pixel
/// ranges of its box for the point bins ([`PointBins`]).
pub enum Reach {
    /// Reaching close to the camera: tested by every ray (see [`NEAR_FRACTION`]).
    Everywhere,
    /// Its box misses the image.
    Outside,
    /// Binned.
    Box {
        /// Its widened box and nearest depth.
        entry: Entry,
        /// The inclusive pixel ranges [x0, x1, y0, y1] the box reaches.
        range: [usize; 4],
    },
}

impl Reach {
    /// The reach of a primitive whose corners, as (pixel x, pixel y, depth) in the novel camera,
    /// have the smallest (x, y, depth) `lo` and largest (x, y) `hi`; `near` is
    /// [`ViewBins::near_limit`], `size` the image's.
    #[inline]
    pub fn of_range(lo: DVec3, hi: DVec2, near: f64, size: (usize, usize)) -> Self {
        let (nearest, lo) = (lo.z, lo.truncate());
        if nearest.is_nan() || nearest <= near {
            return Self::Everywhere;
        }
        let (lo, hi) = (lo - MARGIN_PIXELS, hi + MARGIN_PIXELS);
        let Some(range) = pixel_range(lo, hi, size) else { return Self::Outside };
        let bounds = [lo.x as f32, lo.y as f32, -hi.x as f32, -hi.y as f32];
        Self::Box { entry: Entry { bounds, nearest: nearest as f32 }, range }
    }
}

/// The smaller of two values by one comparison: `x.min(y)` for values that are never NaN, without
/// the NaN handling that costs `f64::min` several instructions in the per-quad and per-corner
/// loops (with a NaN it returns `y`, so callers say why none reaches them).
#[inline]
pub fn smaller<T: PartialOrd>(x: T, y: T) -> T {
    if x < y { x } else { y }
}

/// The larger of two values by one comparison, as [`smaller`].
#[inline]
pub fn larger<T: PartialOrd>(x: T, y: T) -> T {
    if x > y { x } else { y }
}

/// The smallest (x, y, depth) and the largest (x, y) of `corners`, (pixel x, pixel y, depth) in
/// the novel camera: what [`Footprint::of_range`] and [`Reach::of_range`] take.
#[inline]
pub fn corner_range<'a>(corners: impl IntoIterator<Item = &'a DVec3>) -> (DVec3, DVec2) {
    // [`smaller`] and [`larger`]: the corners' depths are finite (projections of valid points),
    // and x or y can be NaN only for a corner at depth 0, whose primitive [`Reach::of_range`]
    // sends to every ray by its depth whatever its box.
    let (mut lo, mut hi) = (DVec3::INFINITY, DVec2::NEG_INFINITY);
    for c in corners {
        lo = DVec3::new(smaller(lo.x, c.x), smaller(lo.y, c.y), smaller(lo.z, c.z));
        hi = DVec2::new(larger(hi.x, c.x), larger(hi.y, c.y));
    }
    (lo, hi)
}

/// The inclusive pixel ranges [x0, x1, y0, y1] of an image of `size` that the box from `lo` to
/// `hi` (pixel coordinates) reaches; None when it misses the image.
#[inline]
fn pixel_range(lo: DVec2, hi: DVec2, (width, height): (usize, usize)) -> Option<[usize; 4]> {
    // Pixel k owns [k − 0.5, k + 0.5); truncation is floor once clamped at 0.
    if !(hi.x + 0.5 >= 0.0 && hi.y + 0.5 >= 0.0) {
        return None;
    }
    let (x0, y0) = (index_of((lo.x + 0.5).max(0.0)), index_of((lo.y + 0.5).max(0.0)));
    let x1 = index_of(hi.x + 0.5).min(width - 1);
    let y1 = index_of(hi.y + 0.5).min(height - 1);
    (x0 <= x1 && y0 <= y1).then_some([x0, x1, y0, y1])
}

/// Replaces each count by the sum of the counts up to and including it (the ends of the bins of
/// a counting sort), and gives the total. The sum runs in a register: a dependency through
/// memory per bin costs more.
fn running_sum(counts: &mut [u32]) -> u32 {
    let mut total = 0;
    for count in counts.iter_mut() {
        total += *count;
        *count = total;
    }
    total
}

/// The bin (x, y) of a point already projected into a novel camera whose image is `extent`
/// (width, height) pixels: `pixel` = K · (p / p.z) and `depth` = p.z for the point p in the
/// novel camera; None outside the image or behind the camera.
#[inline]
fn bin_of(pixel: DVec2, depth: f64, extent: DVec2) -> Option<[usize; 2]> {
    if depth.is_nan() || depth <= 0.0 {
        return None;
    }
    let (x, y) = (pixel.x + 0.5, pixel.y + 0.5);
    // Pixel k owns [k − 0.5, k + 0.5): truncation is floor for the non-negative values kept.
    let inside = x >= 0.0 && y >= 0.0 && x < extent.x && y < extent.y;
    inside.then_some([index_of(x), index_of(y)])
}

/// A non-negative coordinate truncated to an index, through i32: one conversion instruction and
/// a saturation check, where f64 → usize is an emulated unsigned conversion of about twice the
/// instructions (counted with callgrind, the conversions were a third of the footprint pass).
/// Values past i32::MAX, far outside any image, saturate there and are clamped or rejected alike.
#[inline]
fn index_of(coordinate: f64) -> usize {
    coordinate as i32 as usize
}

/// A primitive's box and depth as one anchored tile holds them, copied next to the id in the
/// sorted array so that a ray's scan reads one contiguous run. The box is (x0, y0, −x1, −y1): a
/// point (x, y) is inside when the box is ≤ (x, y, −x, −y), one SIMD comparison.
#[derive(Clone, Copy, Default)]
pub struct Entry {
    bounds: [f32; 4],
    nearest: f32,
}

impl Entry {
    /// Whether the pixel given as (x, y, −x, −y) is inside the box and the nearest corner is no
    /// deeper than `limit`; without a branch.
    #[inline]
    fn covers(&self, signed_pixel: Vec4, limit: f32) -> bool {
        Vec4::from_array(self.bounds).cmple(signed_pixel).all() & (self.nearest <= limit)
    }

    /// Whether a binned point is inside the box and at least as deep as its nearest corner.
    #[inline]
    fn holds(&self, point: &PointEntry) -> bool {
        self.covers(point.signed_pixel(), point.limit)
    }
}

/// An [`Entry`] in the sorted array, with its primitive's id.
#[derive(Clone, Copy, Default)]
struct Tile {
    entry: Entry,
    id: u32,
}

/// The arrays of one view's bins. They are the size of the image and of the mesh, tens of MB at
/// 480×720: allocating them anew per view had the kernel clear ~40 MB of fresh pages per view
/// (~10 % of `datagen pairs`' CPU), so they are kept in a pool and reused.
#[derive(Default)]
struct BinBuffers {
    /// Per primitive id.
    footprints: Vec<Footprint>,
    /// Per pixel (row-major) the tiles anchored there: `entries[starts[p]..starts[p + 1]]`.
    starts: Vec<u32>,
    entries: Vec<Tile>,
    /// Primitives every ray is tested against (see [`NEAR_FRACTION`]).
    everywhere: Vec<u32>,
    /// (anchor, id) of each tile of the [`TILED`] boxes, while sorting.
    tiles: Vec<[u32; 2]>,
}

/// Buffers of dropped views; at most as many as views were ever alive at once (one per thread).
static POOL: Pool<BinBuffers> = Pool::new();

impl Drop for ViewBins {
    fn drop(&mut self) {
        let buffers = std::mem::take(&mut self.buffers);
        POOL.give(buffers);
    }
}

impl ViewBins {
    /// The depth below which [`Reach::of_range`] has a primitive tested by every ray, for a scene
    /// whose smallest depth is `nearest_surface`.
    pub fn near_limit(nearest_surface: f64) -> f64 {
        nearest_surface * NEAR_FRACTION
    }

    /// Bins primitives `0..count` for a camera at `novel_from_world` with intrinsics K and image
    /// size. `fill` must write every primitive's [`Footprint`] ([`Footprint::of_range`],
    /// [`Footprint::OUTSIDE`] for none) into the slice it is given
    /// (index = id; it holds a previous view's values), in whatever order and parallelism suits
    /// the caller.
    pub fn new(
        count: usize,
        fill: impl FnOnce(&mut [Footprint]),
        novel_from_world: DMat4,
        intrinsics: DMat3,
        (width, height): (usize, usize),
    ) -> Self {
        let mut buffers = POOL.take();
        // Pooled arrays keep their length: `fill` and the scatter below overwrite every element,
        // so only growth initialises (writing 20 MB per view that is overwritten anyway costs).
        buffers.footprints.resize(count, Footprint::OUTSIDE);
        fill(&mut buffers.footprints);
        let BinBuffers { footprints, starts, entries, everywhere, tiles } = &mut buffers;
        // Counting sort by anchor: counts at `anchor + 1`, summed into each bin's end, then every
        // tile written at its bin's decremented end (in reverse, so ids ascend within a bin among
        // whole boxes and among tiles of cut ones), which leaves the ends at the starts.
        starts.clear();
        starts.resize(width * height + 1, 0);
        everywhere.clear();
        // The tiles of cut boxes, listed while counting so their ranges are computed once.
        tiles.clear();
        for (id, footprint) in footprints.iter().enumerate() {
            match footprint.anchor {
                UNBINNED => {}
                EVERYWHERE => everywhere.push(id as u32),
                TILED => footprint.for_each_tile((width, height), |anchor| {
                    starts[anchor + 1] += 1;
                    tiles.push([anchor as u32, id as u32]);
                }),
                anchor => starts[anchor as usize + 1] += 1,
            }
        }
        let total = running_sum(starts);
        entries.resize(total as usize, Tile::default());
        let mut place = |anchor: usize, entry: Entry, id: usize| {
            let slot = &mut starts[anchor + 1];
            *slot -= 1;
            entries[*slot as usize] = Tile { entry, id: id as u32 };
        };
        for (id, footprint) in footprints.iter().enumerate().rev() {
            if footprint.anchor < TILED {
                place(footprint.anchor as usize, footprint.entry, id);
            }
        }
        for &[anchor, id] in tiles.iter().rev() {
            place(anchor as usize, footprints[id as usize].entry, id as usize);
        }
        // Bin p's end, decremented once per entry of bin p, is now bin p's start: shift back.
        starts.copy_within(1.., 0);
        starts[width * height] = entries.len() as u32;
        let extent = DVec2::new(width as f64, height as f64);
        Self { width, extent, novel_from_world, intrinsics, buffers }
    }

    /// Where the rays towards `point` (world space) meet the image: pixel coordinates, and the
    /// point's depth (what [`Self::bin_of_projected`] bins).
    fn project(&self, point: DVec3) -> (DVec2, f64) {
        let in_novel = self.novel_from_world.transform_point3(point);
        (crate::camera::pixel_of(&self.intrinsics, in_novel), in_novel.z)
    }

    /// The bin (x, y) of a point already projected ([`bin_of`]).
    fn bin_of_projected(&self, pixel: DVec2, depth: f64) -> Option<[usize; 2]> {
        bin_of(pixel, depth, self.extent)
    }

    /// Calls `visit(id)` for the binned primitives whose box holds `pixel`, that reach nearer
    /// than `limit` and are not in `skip`, in the window of bin `[x, y]`, until it returns true;
    /// whether it did.
    fn any_candidate(
        &self,
        [x, y]: [usize; 2],
        pixel: DVec2,
        limit: f64,
        skip: [u32; 4],
        mut visit: impl FnMut(u32) -> bool,
    ) -> bool {
        let (px, py, limit) = (pixel.x as f32, pixel.y as f32, limit as f32);
        let point = Vec4::new(px, py, -px, -py);
        let BinBuffers { starts, entries, .. } = &self.buffers;
        let first_column = x.saturating_sub(WINDOW - 1);
        for row in y.saturating_sub(WINDOW - 1)..=y {
            let base = row * self.width;
            let run = &entries[starts[base + first_column] as usize..starts[base + x + 1] as usize];
            for &Tile { entry, id } in run {
                // Branch-free: which entries pass is unpredictable, and most are the query's own.
                let skipped = (id == skip[0]) | (id == skip[1]) | (id == skip[2]) | (id == skip[3]);
                if entry.covers(point, limit) & !skipped && visit(id) {
                    return true;
                }
            }
        }
        false
    }

    /// Calls `test(id, binned)` for each primitive that may cross the segment from the camera's
    /// centre to `point`, except binned ones in `skip`, until it returns true; whether it did.
    /// `binned` is false for the primitives tested by every ray (never skipped). None when `point`
    /// is outside the image or behind the camera (not binned).
    pub fn any_towards(&self, point: DVec3, skip: [u32; 4], test: impl FnMut(u32, bool) -> bool) -> Option<bool> {
        let (pixel, depth) = self.project(point);
        self.any_towards_projected(pixel, depth, skip, test)
    }

    /// [`Self::any_towards`] for a point already projected into the novel camera: `pixel` =
    /// K · (p / p.z) and `depth` = p.z, p the point in camera coordinates (`novel_from_world`
    /// applied), computed exactly so, which gives the same bin and answers.
    pub fn any_towards_projected(
        &self,
        pixel: DVec2,
        depth: f64,
        skip: [u32; 4],
        mut test: impl FnMut(u32, bool) -> bool,
    ) -> Option<bool> {
        let bin = self.bin_of_projected(pixel, depth)?;
        let limit = depth * (1.0 + DEPTH_SLACK);
        let binned = self.any_candidate(bin, pixel, limit, skip, |id| test(id, true));
        Some(binned || self.buffers.everywhere.iter().any(|&id| test(id, false)))
    }

    /// The nearest of `hit(id)` (a ray distance, +∞ for a miss) over the primitives that may
    /// cross the ray through `point`. None when `point` is not binned (see [`Self::any_towards`]).
    pub fn nearest_towards(&self, point: DVec3, hit: impl Fn(u32) -> f32) -> Option<f32> {
        let (pixel, depth) = self.project(point);
        let bin = self.bin_of_projected(pixel, depth)?;
        let mut nearest = f32::INFINITY;
        self.any_candidate(bin, pixel, f64::INFINITY, [u32::MAX; 4], |id| {
            nearest = nearest.min(hit(id));
            false
        });
        Some(self.buffers.everywhere.iter().map(|&id| hit(id)).fold(nearest, f32::min))
    }

    /// Number of bin entries (tiles), and of primitives tested by every ray.
    pub fn sizes(&self) -> (usize, usize) {
        (self.buffers.entries.len(), self.buffers.everywhere.len())
    }
}

/// The co-visibility queries of one view (points seen from the novel camera) binned by the
/// novel pixel they project to, the other way round from [`ViewBins`]: each primitive gathers
/// the points inside its box ([`PointBins::collect_inside`]; [`PointBins::any_inside`] asks
/// whether one passes a test), one contiguous run of the sorted array per pixel row of the box.
/// With one entry per point and no tiles (a box reaches a few bins), building and scanning them
/// is a fraction of the triangle bins' cost, and the pairs met are the same: a point is inside a
/// box here exactly when the box is a candidate of the point's ray there, the same f32
/// comparisons of the same values.
pub struct PointBins {
    width: usize,
    buffers: PointBuffers,
}

/// [`PointBins::all`] of a point that is no query.
pub const NO_QUERY: u32 = u32::MAX;
/// [`PointBins::all`] of a query outside the bins (see [`PointGrid::entry`]).
pub const UNBINNED_QUERY: u32 = u32::MAX - 1;

/// The image a [`PointBins`] covers: one bin per pixel.
#[derive(Clone, Copy)]
pub struct PointGrid {
    width: usize,
    height: usize,
    /// (width, height) as f64, for [`bin_of`].
    extent: DVec2,
}

impl PointGrid {
    /// The grid of an image of `size` (width, height) pixels.
    pub fn new((width, height): (usize, usize)) -> Self {
        Self { width, height, extent: DVec2::new(width as f64, height as f64) }
    }

    /// Point `id`'s bin (row-major pixel, [`NO_QUERY`] or [`UNBINNED_QUERY`]) and entry, for
    /// [`PointBins::new`]: `query` is its pixel coordinates K · (p / p.z) and depth p.z in the
    /// novel camera (None for no query). A query whose pixel rounds outside the bins (outside the
    /// image, or behind the camera) is [`UNBINNED_QUERY`]; its caller answers it another way.
    #[inline]
    pub fn entry(&self, id: usize, query: Option<(DVec2, f64)>) -> (u32, PointEntry) {
        let Some((pixel, depth)) = query else { return (NO_QUERY, PointEntry::default()) };
        let Some([x, y]) = bin_of(pixel, depth, self.extent) else { return (UNBINNED_QUERY, PointEntry::default()) };
        let bin = y * self.width + x;
        let (x, y) = (pixel.x as f32, pixel.y as f32);
        let limit = (depth * (1.0 + DEPTH_SLACK)) as f32;
        (bin as u32, PointEntry { pixel: [x, y], limit, id: id as u32 })
    }
}

/// A binned point as the primitives' scans read it: its pixel coordinates, the largest depth
/// a primitive may start at to count ([`DEPTH_SLACK`] included), and its id; 16 bytes, four to
/// a cache line (the sorting and the scans wait on memory more than they compute).
#[derive(Clone, Copy, Default)]
pub struct PointEntry {
    pixel: [f32; 2],
    limit: f32,
    id: u32,
}

impl PointEntry {
    /// Its pixel as (x, y, −x, −y): inside a box stored as [`Entry::bounds`] when the box is ≤
    /// it, one SIMD comparison.
    #[inline]
    fn signed_pixel(&self) -> Vec4 {
        let [x, y] = self.pixel;
        Vec4::new(x, y, -x, -y)
    }
}

/// The arrays of one view's point bins, pooled like [`BinBuffers`].
#[derive(Default)]
struct PointBuffers {
    /// Per point, the pixel (row-major) it is binned in, [`NO_QUERY`] or [`UNBINNED_QUERY`].
    bins: Vec<u32>,
    /// Per pixel the points binned there: `starts[p]..starts[p + 1]` of `points`.
    starts: Vec<u32>,
    points: Vec<PointEntry>,
    /// Per point its entry, while sorting.
    staged: Vec<PointEntry>,
}

static POINT_POOL: Pool<PointBuffers> = Pool::new();

impl Drop for PointBins {
    fn drop(&mut self) {
        let buffers = std::mem::take(&mut self.buffers);
        POINT_POOL.give(buffers);
    }
}

impl PointBins {
    /// Bins the points `0..count` on `grid`: `fill` must write each point's [`PointGrid::entry`]
    /// into the two slices it is given (index = id; they hold a previous view's values), in
    /// whatever order and parallelism suits the caller.
    pub fn new(count: usize, grid: &PointGrid, fill: impl FnOnce(&mut [u32], &mut [PointEntry])) -> Self {
        let (width, height) = (grid.width, grid.height);
        let mut buffers = POINT_POOL.take();
        let PointBuffers { bins, starts, points, staged } = &mut buffers;
        // Pooled arrays keep their length: `fill` overwrites every element.
        bins.resize(count, NO_QUERY);
        staged.resize(count, PointEntry::default());
        fill(bins, staged);
        // Counting sort by bin, as in `ViewBins::new`.
        starts.clear();
        starts.resize(width * height + 1, 0);
        for &bin in bins.iter() {
            if bin < UNBINNED_QUERY {
                starts[bin as usize + 1] += 1;
            }
        }
        let total = running_sum(starts);
        points.resize(total as usize, PointEntry::default());
        for (&bin, entry) in bins.iter().zip(staged.iter()).rev() {
            if bin < UNBINNED_QUERY {
                let slot = &mut starts[bin as usize + 1];
                *slot -= 1;
                points[*slot as usize] = *entry;
            }
        }
        starts.copy_within(1.., 0);
        starts[width * height] = points.len() as u32;
        Self { width, buffers }
    }

    /// Where each point is binned, by id: its pixel (row-major), [`NO_QUERY`] or
    /// [`UNBINNED_QUERY`].
    pub fn all(&self) -> &[u32] {
        &self.buffers.bins
    }

    /// The runs of binned points in the pixel ranges `range` ([x0, x1, y0, y1], inclusive), one
    /// per pixel row, top to bottom.
    #[inline]
    fn runs(&self, [x0, x1, y0, y1]: [usize; 4]) -> impl Iterator<Item = &[PointEntry]> {
        let PointBuffers { starts, points, .. } = &self.buffers;
        (y0..=y1).map(move |row| {
            let base = row * self.width;
            &points[starts[base + x0] as usize..starts[base + x1 + 1] as usize]
        })
    }

    /// Whether `test(id)` holds for a binned point inside the box of a primitive that
    /// [`Reach`]es the image as `entry` over the pixel ranges `range`, and at least as deep as its
    /// nearest corner; the points are tested in order until one passes.
    #[inline]
    pub fn any_inside(&self, entry: &Entry, range: [usize; 4], mut test: impl FnMut(u32) -> bool) -> bool {
        self.runs(range).any(|run| run.iter().any(|point| entry.holds(point) && test(point.id)))
    }

    /// Writes to the front of `out` the ids of the points [`Self::any_inside`] would test but
    /// those `skip` names, in the same order, and gives their number (`out` is scratch space,
    /// grown when a box holds more points than it has room for, never shrunk). No branch depends
    /// on a point: each id is written and the end moves past it only if it passes, since which of
    /// a box's few points pass is unpredictable (the callers visit the few that do afterwards).
    /// On the benchmark clip (medians of 9 interleaved one-thread runs), the quad tests of the
    /// co-visibility batch took 997 ms this way with a resize of `out` per row, against 1,039 ms
    /// with a branch per point, and 926 ms with the scratch space, for 2 % more instructions.
    #[inline]
    pub fn collect_inside(
        &self,
        entry: &Entry,
        range: [usize; 4],
        skip: impl Fn(u32) -> bool,
        out: &mut Vec<u32>,
    ) -> usize {
        let mut end = 0;
        for run in self.runs(range) {
            if out.len() < end + run.len() {
                out.resize(end + run.len(), 0);
            }
            for point in run {
                out[end] = point.id;
                end += usize::from(entry.holds(point) & !skip(point.id));
            }
        }
        end
    }
}

/// Whether the line through `a` and `b` (pixel coordinates) has `point` farther than
/// `margins` × [`MARGIN_PIXELS`] on one side and `other` on the other side or on the line. A
/// binned triangle with edge a–b and third corner `other` then cannot be hit by a ray through the
/// image point `point` (the margin argument of the module documentation, which makes the bins'
/// boxes exact, holds for any separating line).
pub fn line_separates(a: DVec2, b: DVec2, point: DVec2, other: DVec2, margins: f64) -> bool {
    let edge = b - a;
    let (point_side, other_side) = (edge.perp_dot(point - a), edge.perp_dot(other - a));
    // |edge|₁ ≥ |edge|₂: a conservative distance bound without a square root.
    let margin = margins * MARGIN_PIXELS * (edge.x.abs() + edge.y.abs());
    (point_side > margin && other_side <= 0.0) || (point_side < -margin && other_side >= 0.0)
}

/// Whether both triangles of a quad with corners `a`, `b`, `c`, `d` (0..3 in pixel coordinates,
/// see [`crate::depth_mesh`]), (a, b, c) and (b, d, c), turn counter-clockwise in the image's
/// axes (x right, y down: as they do in their source image) with every corner farther than
/// `margins` × [`MARGIN_PIXELS`] from the line of its opposite edge. Twice a triangle's area
/// over an edge's length is that corner's distance from the edge's line; the edges' 1-norms (at
/// least their lengths) make the test conservative without square roots. Both triangles thick
/// also means that their diagonal separates corners 0 and 3 ([`line_separates`] with the same
/// margins).
#[inline]
pub fn thick_quad(a: DVec2, b: DVec2, c: DVec2, d: DVec2, margins: f64) -> bool {
    let (ab, ac, bc, bd, cd) = (b - a, c - a, c - b, d - b, d - c);
    let norm = |e: DVec2| e.x.abs() + e.y.abs();
    // [`larger`]: a NaN corner makes the cross product of its triangle NaN, and that comparison
    // false, whichever norm the select keeps.
    let (diagonal, margin) = (norm(bc), margins * MARGIN_PIXELS);
    let first = ab.perp_dot(ac) > margin * larger(larger(norm(ab), norm(ac)), diagonal);
    let second = bd.perp_dot(bc) > margin * larger(larger(norm(bd), norm(cd)), diagonal);
    first & second
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
