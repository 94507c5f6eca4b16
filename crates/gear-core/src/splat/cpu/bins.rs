//! Stage 1 and the binning of the CPU executor: project every Gaussian (in parallel), sort the
//! survivors by depth (ties by index, as the GPU's stable radix sort and the reference do), and
//! build each tile's depth-ordered list of the Gaussians whose 1/255 ellipse reaches it (the
//! test of tile_test.wgsl). A counting sort by tile id over the (tile, Gaussian) pairs in depth
//! order keeps every list in depth order and records where each pair landed, so the backward
//! can reduce each Gaussian's per-pair gradients in a fixed order.

use rayon::prelude::*;

use super::lanes::with_avx2;
use super::project::{project, Projection, View};
use super::TILE;
use crate::splat::types::{Camera, Gaussians};

/// The relative and absolute margins by which the blend's row test widens the 1/255 level:
/// f32 rounding of the per-pixel quadratic must never make a pixel pass that the row test
/// dropped (the per-pixel test still decides exactly).
const LEVEL_MARGIN: f32 = 1e-3;
/// Pixels of slack on each side of a row's span.
const SPAN_SLACK: f32 = 1e-2;

/// What the blend reads of a Gaussian: the contract's evaluation (mean, conic, opacity,
/// depth) and the row test's constants.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Splat {
    pub u: f32,
    pub v: f32,
    /// Conic a, b, c.
    pub a: f32,
    pub b: f32,
    pub c: f32,
    pub opacity: f32,
    pub z: f32,
    /// On a pixel row at dy = y - v the ellipse dᵀ conic d <= level spans x in
    /// u + slope·dy ± sqrt((reach - dy²)·span): reach = level·Σ2D.c (widened), slope =
    /// Σ2D.b / Σ2D.c, span = det Σ2D / Σ2D.c². Written with Σ2D, not the conic, so that long
    /// thin Gaussians suffer no cancellation.
    pub reach: f32,
    pub slope: f32,
    pub span: f32,
}

impl Splat {
    fn new(p: &Projection) -> Self {
        let level = p.level() * (1.0 + LEVEL_MARGIN) + LEVEL_MARGIN;
        Splat {
            u: p.mean2d.x,
            v: p.mean2d.y,
            a: p.conic.x,
            b: p.conic.y,
            c: p.conic.z,
            opacity: p.opacity,
            z: p.t.z,
            reach: level * p.cov.z,
            slope: p.cov.y / p.cov.z,
            span: p.det / (p.cov.z * p.cov.z),
        }
    }

    /// Bit r set where the Gaussian can reach a pixel of tile row r (pixel-centre y = `y0` +
    /// r) whose pixel centres span [x_lo, x_hi]: a few flops and compares per row, before any
    /// exp, for all TILE rows at once (one SIMD row, no branch).
    #[inline(always)]
    pub fn row_mask(&self, y0: f32, x_lo: f32, x_hi: f32) -> u32 {
        let meets: [bool; TILE as usize] = std::array::from_fn(|r| {
            let dy = (y0 + r as f32) - self.v;
            let room = self.reach - dy * dy;
            let half = (room.max(0.0) * self.span).sqrt() + SPAN_SLACK;
            let centre = self.u + self.slope * dy;
            // NaN (a culled or degenerate entry) fails every compare.
            room >= 0.0 && centre + half >= x_lo && centre - half <= x_hi
        });
        meets
            .iter()
            .enumerate()
            .fold(0, |mask, (r, &m)| mask | (u32::from(m) << r))
    }
}

/// Minimum of a q² + 2 b q t + c t² over t in [lo, hi] for fixed q (c > 0).
fn edge_minimum(q: f32, a: f32, b: f32, c: f32, lo: f32, hi: f32) -> f32 {
    let t = (-b * q / c).max(lo).min(hi);
    a * q * q + 2.0 * b * q * t + c * t * t
}

/// Whether the 1/255 ellipse of `s` (level `level`) reaches a pixel centre of tile (tx, ty),
/// with tile_test.wgsl's margin for f32 rounding.
#[inline(always)]
fn meets_tile(s: &Splat, level: f32, tx: u32, ty: u32) -> bool {
    let tile = TILE as f32;
    let (ux, uy) = (s.u, s.v);
    let (cx, cy) = (tx as f32 * tile, ty as f32 * tile);
    let lo = [cx + 0.5 - ux, cy + 0.5 - uy];
    let hi = [cx + tile - 0.5 - ux, cy + tile - 0.5 - uy];
    let (a, b, c) = (s.a, s.b, s.c);
    let mut least = 0.0f32;
    if lo[0] > 0.0 || lo[1] > 0.0 || hi[0] < 0.0 || hi[1] < 0.0 {
        least = edge_minimum(lo[0], a, b, c, lo[1], hi[1])
            .min(edge_minimum(hi[0], a, b, c, lo[1], hi[1]))
            .min(
                edge_minimum(lo[1], c, b, a, lo[0], hi[0])
                    .min(edge_minimum(hi[1], c, b, a, lo[0], hi[0])),
            );
    }
    let reach = [lo[0].abs().max(hi[0].abs()), lo[1].abs().max(hi[1].abs())];
    let terms =
        a * reach[0] * reach[0] + 2.0 * b.abs() * reach[0] * reach[1] + c * reach[1] * reach[1];
    let position = ux.abs() + uy.abs() + cx + cy + 2.0 * tile;
    let margin = 1e-5 * (terms + 16.0 * position) + 1e-3;
    // NaN counts as reaching, as in tile_test.wgsl.
    least.partial_cmp(&(level + margin)) != Some(std::cmp::Ordering::Greater)
}

/// Tiles [x0, x1) x [y0, y1) holding a pixel centre in the Gaussian's per-axis 1/255 box
/// (project.wgsl), or None.
#[inline(always)]
fn tile_rect(p: &Projection, level: f32, tiles: [u32; 2]) -> Option<[u32; 4]> {
    let extent = [
        (level * p.cov.x).sqrt() + 1.0,
        (level * p.cov.z).sqrt() + 1.0,
    ];
    let centre = [p.mean2d.x, p.mean2d.y];
    let tile = TILE as f32;
    let mut rect = [0u32; 4];
    for axis in 0..2 {
        let (lo, hi) = (centre[axis] - extent[axis], centre[axis] + extent[axis]);
        if !(lo.is_finite() && hi.is_finite()) {
            return None;
        }
        let first = (((lo - 0.5).ceil() + 0.5) / tile).floor();
        let last = (((hi - 0.5).floor() + 0.5) / tile).floor();
        let end = tiles[axis] as f32 - 1.0;
        if last < first || last < 0.0 || first > end {
            return None;
        }
        rect[axis] = first.max(0.0) as u32;
        rect[axis + 2] = last.min(end) as u32 + 1;
    }
    Some(rect)
}

/// Every tile's list, and where each pair went.
pub(super) struct Bins {
    pub tiles_x: u32,
    pub tiles_y: u32,
    /// Blend data of every Gaussian (by index; zero for culled ones).
    pub splats: Vec<Splat>,
    /// Tile t's list is `entries[tile_offsets[t]..tile_offsets[t + 1]]` (Gaussian indices in
    /// depth order).
    pub tile_offsets: Vec<u32>,
    pub entries: Vec<u32>,
    /// Gaussian g's pairs are numbered `pair_offsets[g]..pair_offsets[g + 1]` (Gaussian-major,
    /// in increasing tile order), and the list entry at `entries[e]` is pair `entry_pairs[e]`:
    /// the backward writes each pair's gradient record at its pair number, so that a
    /// Gaussian's records are contiguous when they are summed.
    pub pair_offsets: Vec<u32>,
    pub entry_pairs: Vec<u32>,
}

impl Bins {
    pub fn pairs(&self) -> usize {
        self.entries.len()
    }

    /// The list range of tile `t`.
    pub fn range(&self, t: usize) -> std::ops::Range<usize> {
        self.tile_offsets[t] as usize..self.tile_offsets[t + 1] as usize
    }

    /// The pair numbers of Gaussian `g`.
    pub fn pairs_of(&self, g: usize) -> std::ops::Range<usize> {
        self.pair_offsets[g] as usize..self.pair_offsets[g + 1] as usize
    }
}

/// Splits `values` into consecutive pieces of the given lengths.
fn split_lengths<T>(mut values: &mut [T], lengths: impl Iterator<Item = usize>) -> Vec<&mut [T]> {
    let mut pieces = Vec::new();
    for len in lengths {
        let (head, tail) = values.split_at_mut(len);
        pieces.push(head);
        values = tail;
    }
    pieces
}

/// What binning keeps of a projected Gaussian: its blend data, and what the tile test needs.
#[derive(Debug, Clone, Copy, Default)]
struct Binned {
    splat: Splat,
    /// The unwidened 1/255 level, and the tile rectangle (x0, y0, x1, y1).
    level: f32,
    rect: [u32; 4],
    /// Tiles of the rectangle the ellipse meets (0 when culled).
    count: u32,
    /// Which tiles of the rectangle (row-major bits) it meets, for rectangles of up to 64
    /// tiles (larger ones are tested again when their pairs are written).
    met: u64,
}

impl Binned {
    /// The tiles of its rectangle, row-major.
    fn rect_tiles(&self) -> impl Iterator<Item = (u32, u32)> {
        let r = self.rect;
        (r[1]..r[3]).flat_map(move |ty| (r[0]..r[2]).map(move |tx| (tx, ty)))
    }

    fn area(&self) -> u32 {
        (self.rect[2] - self.rect[0]) * (self.rect[3] - self.rect[1])
    }

    /// Runs the tile test (tile_test.wgsl) on the rectangle; a one-tile rectangle needs none
    /// (the blend tests pixels).
    fn test_tiles(&mut self) {
        if self.area() == 1 {
            (self.count, self.met) = (1, 1);
        } else if self.area() <= 64 {
            self.met = 0;
            for (bit, (tx, ty)) in self.rect_tiles().enumerate() {
                if meets_tile(&self.splat, self.level, tx, ty) {
                    self.met |= 1 << bit;
                }
            }
            self.count = self.met.count_ones();
        } else {
            let met = self
                .rect_tiles()
                .filter(|&(tx, ty)| meets_tile(&self.splat, self.level, tx, ty));
            self.count = met.count() as u32;
        }
    }

    /// The tiles it meets, row-major.
    fn tiles(&self) -> impl Iterator<Item = (u32, u32)> + '_ {
        let small = self.area() <= 64;
        self.rect_tiles()
            .enumerate()
            .filter_map(move |(bit, (tx, ty))| {
                let met = if small {
                    self.met & (1 << bit) != 0
                } else {
                    meets_tile(&self.splat, self.level, tx, ty)
                };
                met.then_some((tx, ty))
            })
    }
}

with_avx2!(
    /// Gaussian `i` projected and tested against the tiles of its rectangle.
    fn bin_one(gaussians: &Gaussians, i: usize, view: &View, tiles: [u32; 2]) -> Binned =
        bin_one_body
);

#[inline(always)]
fn bin_one_body(gaussians: &Gaussians, i: usize, view: &View, tiles: [u32; 2]) -> Binned {
    let Some(p) = project(gaussians, i, view) else {
        return Binned::default();
    };
    let level = p.level();
    let Some(rect) = tile_rect(&p, level, tiles) else {
        return Binned::default();
    };
    let mut b = Binned {
        splat: Splat::new(&p),
        level,
        rect,
        count: 0,
        met: 0,
    };
    b.test_tiles();
    b
}

/// Projects and bins `gaussians`; call inside the executor's thread pool.
///
/// Everything per Gaussian runs in index order (parallel, streaming through memory); only the
/// final scatter of the pairs into the tile lists walks the Gaussians in depth order.
pub(super) fn bin(gaussians: &Gaussians, camera: &Camera) -> Bins {
    let view = View::new(camera);
    let tiles = [camera.width.div_ceil(TILE), camera.height.div_ceil(TILE)];
    let n = gaussians.len();
    let binned: Vec<Binned> = (0..n)
        .into_par_iter()
        .map(|i| bin_one(gaussians, i, &view, tiles))
        .collect();

    // The tiles of each Gaussian, in index order.
    let mut pair_offsets = vec![0u32; n + 1];
    for (i, b) in binned.iter().enumerate() {
        pair_offsets[i + 1] = pair_offsets[i] + b.count;
    }
    let mut tile_ids = vec![0u32; pair_offsets[n] as usize];
    split_lengths(&mut tile_ids, binned.iter().map(|b| b.count as usize))
        .into_par_iter()
        .zip(binned.par_iter())
        .for_each(|(out, b)| {
            for (slot, (tx, ty)) in out.iter_mut().zip(b.tiles()) {
                *slot = ty * tiles[0] + tx;
            }
        });

    // Depth order of the Gaussians with pairs; z > 0, so its bits order like the floats, and
    // the index breaks ties.
    let mut by_depth: Vec<u64> = binned
        .iter()
        .enumerate()
        .filter(|(_, b)| b.count > 0)
        .map(|(i, b)| (u64::from(b.splat.z.to_bits()) << 32) | i as u64)
        .collect();
    by_depth.par_sort_unstable();

    // Counting sort of the pairs by tile, fed in depth order, so every list is in depth order.
    let tile_count = (tiles[0] * tiles[1]) as usize;
    let mut tile_offsets = vec![0u32; tile_count + 1];
    for &t in &tile_ids {
        tile_offsets[t as usize + 1] += 1;
    }
    for t in 0..tile_count {
        tile_offsets[t + 1] += tile_offsets[t];
    }
    let mut cursor = tile_offsets[..tile_count].to_vec();
    let mut entries = vec![0u32; tile_ids.len()];
    let mut entry_pairs = vec![0u32; tile_ids.len()];
    for &key in &by_depth {
        let g = key as u32;
        let pairs = pair_offsets[g as usize] as usize..pair_offsets[g as usize + 1] as usize;
        for pair in pairs {
            let t = tile_ids[pair] as usize;
            entries[cursor[t] as usize] = g;
            entry_pairs[cursor[t] as usize] = pair as u32;
            cursor[t] += 1;
        }
    }
    Bins {
        tiles_x: tiles[0],
        tiles_y: tiles[1],
        splats: binned.iter().map(|b| b.splat).collect(),
        tile_offsets,
        entries,
        pair_offsets,
        entry_pairs,
    }
}
