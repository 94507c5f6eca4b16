//! Stage 1 and the binning of the CPU executor: project every Gaussian (in parallel) and
//! build each tile's list of the Gaussians whose 1/255 ellipse spans a pixel centre of one of
//! its rows, with the mask of those rows, in depth order (ties by index, as the GPU's stable
//! radix sort and the reference order them; the lists themselves: `lists`). Each entry
//! records its pair number, so the backward can reduce each Gaussian's per-pair gradients in
//! a fixed order.

// Lane loops index several [f32; 8] arrays in step: the form the compiler vectorises.
#![allow(clippy::needless_range_loop)]

use rayon::prelude::*;

use super::lanes::LANES as BLOCK;
use super::lanes::{array, mask, select, with_avx2, Lanes, LANES};
use super::lists::{Entry, Listed, Lists};
use super::project::{Prepared, Screen, View};
use super::spares::Spares;
use super::TILE;
use crate::splat::constants;
use crate::splat::types::{Camera, Gaussians};

/// The contract's widening of the row spans (shared with the wgpu kernels), in f32.
const LEVEL_MARGIN: f32 = constants::ROW_LEVEL_MARGIN as f32;
const SPAN_SLACK: f32 = constants::ROW_SPAN_SLACK as f32;
/// Pixel rows of slack above and below the ellipse's vertical extent; the rows inside it are
/// then tested one by one.
const ROW_SLACK: f32 = 1.0;

impl Entry {
    fn new(p: &Screen) -> Self {
        Entry {
            u: p.mean2d[0],
            v: p.mean2d[1],
            a: p.conic[0],
            b: p.conic[1],
            c: p.conic[2],
            opacity: p.opacity,
            z: p.z,
            rows: 0,
        }
    }
}

/// Where a Gaussian's ellipse lies, for binning: on a pixel row at dy = y - v the ellipse
/// dᵀ conic d <= level spans x in u + slope·dy ± sqrt((reach - dy²)·span), with reach =
/// level·Σ2D.c (widened), slope = Σ2D.b / Σ2D.c and span = det Σ2D / Σ2D.c². Written with Σ2D,
/// not the conic, so that long thin Gaussians suffer no cancellation.
#[derive(Debug, Clone, Copy)]
struct Footprint {
    u: f32,
    v: f32,
    reach: f32,
    slope: f32,
    span: f32,
}

impl Footprint {
    fn new(p: &Screen) -> Self {
        let level = p.level() * (1.0 + LEVEL_MARGIN) + LEVEL_MARGIN;
        Footprint {
            u: p.mean2d[0],
            v: p.mean2d[1],
            reach: level * p.cov[2],
            slope: p.cov[1] / p.cov[2],
            span: p.det / (p.cov[2] * p.cov[2]),
        }
    }

    /// The tile rows [first, last] holding an image row the ellipse may reach, or None.
    fn tile_rows(&self, height: u32) -> Option<(u32, u32)> {
        let extent = self.reach.sqrt() + ROW_SLACK;
        // NaN bounds widen to the image (f32::max and min drop a NaN operand).
        let first = (self.v - extent - 0.5).ceil().max(0.0);
        let last = (self.v + extent - 0.5).floor().min(height as f32 - 1.0);
        (first <= last).then_some((first as u32 / TILE, last as u32 / TILE))
    }

    /// The first and last pixel columns of each row of tile row `ty` whose centre the ellipse
    /// spans (first = +inf, last = -1 where none; rows below the image have none). One SIMD
    /// row, a lane per image row.
    #[inline(always)]
    fn columns(&self, ty: u32, width: u32, height: u32) -> (Lanes, Lanes) {
        let mut first = [0.0f32; LANES];
        let mut last = [0.0f32; LANES];
        let rows_inside = height.saturating_sub(ty * TILE);
        for r in 0..LANES {
            // Through i32: the same exact value, and a vector conversion (u32 has none).
            let dy = (ty * TILE + r as u32) as i32 as f32 + 0.5 - self.v;
            let room = self.reach - dy * dy;
            let half = (room.max(0.0) * self.span).sqrt() + SPAN_SLACK;
            let centre = self.u + self.slope * dy;
            let lo = (centre - half - 0.5).ceil().max(0.0);
            let hi = (centre + half - 0.5).floor().min(width as f32 - 1.0);
            // NaN room fails the compare: no columns.
            let meets = mask(room >= 0.0) & mask((r as u32) < rows_inside);
            first[r] = select(meets, lo, f32::INFINITY);
            last[r] = select(meets, hi, -1.0);
        }
        (first, last)
    }

    /// Appends to `out` every (tile, rows) pair: the tiles (in increasing order) with a row
    /// whose pixel centres the ellipse spans, and the mask of those rows.
    #[inline(always)]
    fn pairs(&self, grid: Grid, out: &mut Vec<[u32; 2]>) {
        let Some((ty0, ty1)) = self.tile_rows(grid.height) else {
            return;
        };
        let tile = TILE as f32;
        let bits: [u32; LANES] = array(|r| 1 << r);
        for ty in ty0..=ty1 {
            let (first, last) = self.columns(ty, grid.width, grid.height);
            let lo = first.iter().copied().fold(f32::INFINITY, f32::min);
            let hi = last.iter().copied().fold(-1.0, f32::max);
            if lo > hi {
                continue;
            }
            for tx in (lo / tile) as u32..=(hi / tile) as u32 {
                let (x0, x1) = (tx as f32 * tile, tx as f32 * tile + (tile - 1.0));
                let meets: [u32; LANES] =
                    array(|r| mask(first[r] <= x1) & mask(last[r] >= x0) & bits[r]);
                let rows = meets.iter().fold(0, |m, &b| m | b);
                if rows != 0 {
                    out.push([ty * grid.tiles_x + tx, rows]);
                }
            }
        }
    }
}

/// Every tile's list, where each pair went, and what the backward needs of each Gaussian.
pub(super) struct Bins {
    pub tiles_x: u32,
    pub tiles_y: u32,
    pub channels: usize,
    /// Tile t's list is `entries[tile_offsets[t]..tile_offsets[t + 1]]`, in depth order, and
    /// `entry_features` holds the features of each entry (entries x channels).
    pub tile_offsets: Vec<u32>,
    pub entries: Vec<Entry>,
    pub entry_features: Vec<f32>,
    /// Gaussian g's pairs are numbered `pair_offsets[g]..pair_offsets[g + 1]` (Gaussian-major,
    /// in increasing tile order), and list entry e is pair `entry_pairs[e]`: the backward
    /// writes each pair's gradient record at its pair number, so that a Gaussian's records are
    /// contiguous when they are summed.
    pub pair_offsets: Vec<u32>,
    pub entry_pairs: Vec<u32>,
    /// The prepared projections of Gaussians 8b..8b + 8 in block b.
    pub prepared: Vec<Prepared>,
    /// Gaussians.
    pub len: usize,
}

impl Bins {
    /// Entries in the tile lists.
    pub fn pairs(&self) -> usize {
        self.entries.len()
    }

    /// Pairs numbered: those of every Gaussian (more than the entries where some tiles'
    /// lists were left out, see [`bin_over`]).
    pub fn pair_count(&self) -> usize {
        self.pair_offsets[self.len] as usize
    }

    /// The tile lists, to read.
    pub fn listed(&self) -> Listed<'_> {
        Listed {
            offsets: &self.tile_offsets,
            entries: &self.entries,
            features: &self.entry_features,
            pairs: &self.entry_pairs,
        }
    }

    /// The list range of tile `t`.
    pub fn range(&self, t: usize) -> std::ops::Range<usize> {
        self.tile_offsets[t] as usize..self.tile_offsets[t + 1] as usize
    }

    /// The pair numbers of Gaussian `g`.
    pub fn pairs_of(&self, g: usize) -> std::ops::Range<usize> {
        self.pair_offsets[g] as usize..self.pair_offsets[g + 1] as usize
    }

    /// Frees the prepared projections (for lists kept only to be merged: [`bin_over`]).
    pub fn drop_projections(&mut self) {
        PREPARED.keep(std::mem::take(&mut self.prepared));
    }

    /// Bytes held by the lists and the per-Gaussian arrays.
    pub fn bytes(&self) -> usize {
        use std::mem::size_of;
        self.entries.len() * (size_of::<Entry>() + size_of::<u32>())
            + self.entry_features.len() * size_of::<f32>()
            + (self.tile_offsets.len() + self.pair_offsets.len()) * size_of::<u32>()
            + self.prepared.len() * size_of::<Prepared>()
    }
}

impl Drop for Bins {
    fn drop(&mut self) {
        Lists {
            entries: std::mem::take(&mut self.entries),
            features: std::mem::take(&mut self.entry_features),
            pairs: std::mem::take(&mut self.entry_pairs),
        }
        .keep();
        PREPARED.keep(std::mem::take(&mut self.prepared));
    }
}

// Buffers of earlier passes (see `spares`): binning's own scratch.
static PREPARED: Spares<Prepared> = Spares::new();
static SPLATS: Spares<Entry> = Spares::new();
static PAIRS: Spares<[u32; 2]> = Spares::new();

/// The image's tile grid and size, for binning.
#[derive(Clone, Copy)]
struct Grid {
    tiles_x: u32,
    width: u32,
    height: u32,
}

/// Per-Gaussian outputs of binning for a run of Gaussians.
struct Chunk<'a> {
    /// Blocks of eight Gaussians.
    prepared: &'a mut [Prepared],
    splats: &'a mut [Entry],
    /// Pairs of each Gaussian.
    counts: &'a mut [u32],
}

with_avx2!(
    /// Projects Gaussians `first..first + chunk.len()` and returns the pairs of those from
    /// `from` on, Gaussian by Gaussian.
    fn bin_chunk(gaussians: &Gaussians, first: usize, chunk: Chunk, view: &View, grid: Grid, from: usize) -> Vec<[u32; 2]> =
        bin_chunk_body
);

#[inline(always)]
fn bin_chunk_body(
    gaussians: &Gaussians,
    first: usize,
    chunk: Chunk,
    view: &View,
    grid: Grid,
    from: usize,
) -> Vec<[u32; 2]> {
    let mut pairs = Vec::with_capacity(2 * chunk.counts.len());
    let blocks = chunk
        .prepared
        .iter_mut()
        .zip(chunk.splats.chunks_mut(BLOCK))
        .zip(chunk.counts.chunks_mut(BLOCK));
    for (b, ((prepared, splats), counts)) in blocks.enumerate() {
        *prepared = Prepared::new(gaussians, first + b * BLOCK, view);
        let p = prepared.project(view);
        for (i, (splat, count)) in splats.iter_mut().zip(counts.iter_mut()).enumerate() {
            if p.valid[i] == 0 || first + b * BLOCK + i < from {
                continue;
            }
            let screen = p.screen(i);
            let before = pairs.len();
            Footprint::new(&screen).pairs(grid, &mut pairs);
            *count = (pairs.len() - before) as u32;
            *splat = Entry::new(&screen);
        }
    }
    pairs
}

/// What projecting Gaussians `from..` gives, in arrays over all the Gaussians (those before
/// `from` keep defaults, but for the prepared projections of `from`'s block of eight).
struct Projected {
    prepared: Vec<Prepared>,
    splats: Vec<Entry>,
    /// Pairs of each Gaussian.
    counts: Vec<u32>,
    /// (tile, rows) of Gaussians `from..`, Gaussian by Gaussian.
    pairs: Vec<[u32; 2]>,
}

/// Projects Gaussians `from..` in parallel and lists their pairs; call inside the executor's
/// thread pool.
fn project_from(gaussians: &Gaussians, view: &View, grid: Grid, from: usize) -> Projected {
    let n = gaussians.len();
    let mut prepared = PREPARED.take(n.div_ceil(BLOCK), Prepared::default());
    let mut splats = SPLATS.take(n, Entry::default());
    let mut counts = vec![0u32; n];
    // Chunks of Gaussians: few enough for little overhead, enough to balance the threads.
    let chunk = 128 * BLOCK;
    let skip = from / BLOCK * BLOCK;
    let chunk_pairs: Vec<Vec<[u32; 2]>> = prepared[skip / BLOCK..]
        .par_chunks_mut(chunk / BLOCK)
        .zip(splats[skip..].par_chunks_mut(chunk))
        .zip(counts[skip..].par_chunks_mut(chunk))
        .enumerate()
        .map(|(c, ((prepared, splats), counts))| {
            let out = Chunk {
                prepared,
                splats,
                counts,
            };
            bin_chunk(gaussians, skip + c * chunk, out, view, grid, from)
        })
        .collect();
    let mut pairs = PAIRS.take(0, [0, 0]);
    for chunk in &chunk_pairs {
        pairs.extend_from_slice(chunk);
    }
    Projected {
        prepared,
        splats,
        counts,
        pairs,
    }
}

/// Gaussian g's first pair number at [g], after `head` (the offsets of the Gaussians before
/// those counted in `counts[head.len() - 1..]`).
fn pair_offsets(head: &[u32], counts: &[u32]) -> Vec<u32> {
    let mut offsets = Vec::with_capacity(counts.len() + 1);
    offsets.extend_from_slice(head);
    for &count in &counts[head.len() - 1..] {
        offsets.push(offsets.last().unwrap() + count);
    }
    offsets
}

/// Tile t's list range at [t]..[t + 1], for lists of `pairs`.
fn tile_offsets(pairs: &[[u32; 2]], tile_count: usize) -> Vec<u32> {
    let mut offsets = vec![0u32; tile_count + 1];
    for &[t, _] in pairs {
        offsets[t as usize + 1] += 1;
    }
    for t in 0..tile_count {
        offsets[t + 1] += offsets[t];
    }
    offsets
}

impl Grid {
    fn new(camera: &Camera) -> Self {
        Grid {
            tiles_x: camera.width.div_ceil(TILE),
            width: camera.width,
            height: camera.height,
        }
    }

    fn tiles_y(&self) -> u32 {
        self.height.div_ceil(TILE)
    }

    fn tile_count(&self) -> usize {
        (self.tiles_x * self.tiles_y()) as usize
    }
}

/// Projects and bins `gaussians`; call inside the executor's thread pool.
///
/// Everything per Gaussian runs in index order (parallel, streaming through memory); only the
/// final scatter of the pairs into the tile lists walks the Gaussians in depth order.
pub(super) fn bin(gaussians: &Gaussians, camera: &Camera) -> Bins {
    let grid = Grid::new(camera);
    let channels = gaussians.channels;
    let projected = project_from(gaussians, &View::new(camera), grid, 0);
    let pair_offsets = pair_offsets(&[0], &projected.counts);
    let tile_offsets = tile_offsets(&projected.pairs, grid.tile_count());
    let mut lists = Lists::take(projected.pairs.len(), channels);
    let splats = (&projected.splats[..], &projected.pairs[..]);
    lists.fill(&tile_offsets, splats, &pair_offsets, gaussians, 0);
    lists.sort_by_depth(&tile_offsets, channels);
    Bins::assemble(grid, channels, lists, tile_offsets, pair_offsets, projected)
}

/// The bins of `gaussians` whose first `base.len` are the Gaussians `base` binned, seen by the
/// same camera: only the others are projected and binned, and only the tiles they reach get
/// lists (each the merge of `base`'s list and theirs, as [`bin`] orders it: by depth, ties
/// by index); the other tiles' lists are left empty. Also returns which tiles got lists.
/// The prepared projections of `base`'s Gaussians are not made (but for those sharing a
/// block of eight with the others): nothing may ask for their gradients.
pub(super) fn bin_over(base: &Bins, gaussians: &Gaussians, camera: &Camera) -> (Bins, Vec<bool>) {
    let grid = Grid::new(camera);
    let channels = gaussians.channels;
    let from = base.len;
    let projected = project_from(gaussians, &View::new(camera), grid, from);
    let pair_offsets = pair_offsets(&base.pair_offsets, &projected.counts);
    let tile_count = grid.tile_count();
    let own_offsets = tile_offsets(&projected.pairs, tile_count);
    let mut own = Lists::take(projected.pairs.len(), channels);
    let splats = (&projected.splats[..], &projected.pairs[..]);
    own.fill(&own_offsets, splats, &pair_offsets, gaussians, from);
    own.sort_by_depth(&own_offsets, channels);
    let touched: Vec<bool> = own_offsets.windows(2).map(|w| w[1] > w[0]).collect();
    let mut tile_offsets = vec![0u32; tile_count + 1];
    for t in 0..tile_count {
        let len = if touched[t] {
            base.range(t).len() as u32 + own_offsets[t + 1] - own_offsets[t]
        } else {
            0
        };
        tile_offsets[t + 1] = tile_offsets[t] + len;
    }
    let mut lists = Lists::take(tile_offsets[tile_count] as usize, channels);
    lists.merge(&tile_offsets, &base.listed(), &own, &own_offsets, channels);
    own.keep();
    let bins = Bins::assemble(grid, channels, lists, tile_offsets, pair_offsets, projected);
    (bins, touched)
}

impl Bins {
    /// The bins of `lists` (ranges `tile_offsets`, `channels` features per entry) and
    /// `projected`'s Gaussians, whose pairs start at `pair_offsets`; binning's scratch goes back
    /// to the kept buffers.
    fn assemble(
        grid: Grid,
        channels: usize,
        lists: Lists,
        tile_offsets: Vec<u32>,
        pair_offsets: Vec<u32>,
        projected: Projected,
    ) -> Self {
        SPLATS.keep(projected.splats);
        PAIRS.keep(projected.pairs);
        Bins {
            tiles_x: grid.tiles_x,
            tiles_y: grid.tiles_y(),
            channels,
            len: pair_offsets.len() - 1,
            tile_offsets,
            entries: lists.entries,
            entry_features: lists.features,
            pair_offsets,
            entry_pairs: lists.pairs,
            prepared: projected.prepared,
        }
    }
}
