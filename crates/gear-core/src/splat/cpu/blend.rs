//! The forward blend of the CPU executor: bands of TILE image rows in parallel; every pixel
//! row of a tile (eight pixels, one SIMD row) walks the tile's depth-ordered list front to back with the contract's guards. An entry is evaluated
//! only on the rows where binning found its 1/255 ellipse spanning a pixel centre, and the walk
//! stops once all eight pixels of every row have stopped.

// Lane loops index several [f32; 8] arrays in step: the form the compiler vectorises.
#![allow(clippy::needless_range_loop)]

use rayon::prelude::*;

use super::bins::Bins;
use super::lanes::{array, evaluate, mask, masked, select, with_avx2, Lanes, Mask, LANES};
use super::TILE;
use crate::counts::{channels, with_channels};
use crate::splat::constants::MIN_TRANSMITTANCE;

/// What the backward replays: per pixel the final transmittance and the end of the consumed
/// list prefix (an index into the tile lists); per list entry the rows of its tile where it
/// was blended into a pixel (bit r for row r). The backward visits only those rows: on any
/// other, every pixel either failed the entry's guards or had stopped blending, so its replay
/// would add nothing.
pub(super) struct PixelState {
    pub final_t: Vec<f32>,
    pub consumed: Vec<u32>,
    pub blended_rows: Vec<u8>,
}

/// Work counters of a forward blend.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct BlendCounts {
    /// Gaussian-pixel evaluations (eight per row that passed the row test, minus pixels past
    /// the image edge).
    pub evaluations: u64,
    /// Of those, the ones blended into their pixel.
    pub contributions: u64,
}

impl BlendCounts {
    fn add(self, other: Self) -> Self {
        BlendCounts {
            evaluations: self.evaluations + other.evaluations,
            contributions: self.contributions + other.contributions,
        }
    }
}

/// Where a pixel row of a tile lies.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Row {
    /// Pixels inside the image (0 for a row below it, else 1..=8).
    pub len: usize,
    /// Pixel-centre y and the pixel-centre x of the eight lanes.
    pub cy: f32,
    pub xs: Lanes,
}

impl Row {
    pub fn new(x0: u32, y: u32, width: u32, height: u32) -> Self {
        Row {
            len: if y < height {
                (width - x0).min(LANES as u32) as usize
            } else {
                0
            },
            cy: y as f32 + 0.5,
            xs: array(|i| x0 as f32 + 0.5 + i as f32),
        }
    }

    /// The TILE rows of tile (tx, ty).
    pub fn of_tile(tx: u32, ty: u32, width: u32, height: u32) -> [Row; TILE as usize] {
        array(|r| Row::new(tx * TILE, ty * TILE + r as u32, width, height))
    }
}

/// The output images of one band of rows (image-wide layouts, band slices).
struct BandImages<'a> {
    features: &'a mut [f32],
    alpha: &'a mut [f32],
    depth: &'a mut [f32],
    final_t: &'a mut [f32],
    consumed: &'a mut [u32],
    /// The band's list entries' blended rows (its tiles' lists are contiguous), the first of
    /// them entry `first_entry`.
    blended_rows: &'a mut [u8],
    first_entry: usize,
}

/// Inputs of the blend that every band shares.
pub(super) struct Scene<'a> {
    pub bins: &'a Bins,
    pub channels: usize,
    pub width: u32,
    pub height: u32,
    pub background: &'a [f32],
    pub depth: bool,
    /// The images of the tiles the blend does not walk, when some are given.
    pub base: Option<Base<'a>>,
}

/// A static layer's images, whose tiles stand in for the tiles no other Gaussian reaches.
pub(super) struct Base<'a> {
    /// H x W x C, blended over a background of -0 (so each value is exactly the blended sum:
    /// x + -0 = x for every x).
    pub colour: &'a [f32],
    pub final_t: &'a [f32],
    /// H x W (zeros without depth).
    pub depth: &'a [f32],
    /// The tiles to blend; the others take the layer's pixels.
    pub blend: &'a [bool],
}

/// Blends every tile; returns features (H x W x C), alpha, depth (H x W; zeros without depth),
/// the pixel state and the work counts. Call inside the executor's thread pool.
pub(super) fn blend(scene: &Scene) -> (Vec<f32>, Vec<f32>, Vec<f32>, PixelState, BlendCounts) {
    let (w, c) = (scene.width as usize, scene.channels);
    let pixels = w * scene.height as usize;
    let band = TILE as usize * w;
    // NaN until written, so that a pixel the blend missed cannot pass for a result.
    let mut features = vec![f32::NAN; pixels * c];
    let mut alpha = vec![f32::NAN; pixels];
    let mut depth = vec![f32::NAN; pixels];
    let mut final_t = vec![f32::NAN; pixels];
    let mut consumed = vec![0u32; pixels];
    let mut blended_rows = vec![0u8; scene.bins.pairs()];
    let band_rows = band_slices(scene.bins, &mut blended_rows);
    let counts = features
        .par_chunks_mut(band * c)
        .zip(alpha.par_chunks_mut(band))
        .zip(depth.par_chunks_mut(band))
        .zip(final_t.par_chunks_mut(band))
        .zip(consumed.par_chunks_mut(band))
        .zip(band_rows)
        .enumerate()
        .map(
            |(b, (((((features, alpha), depth), final_t), consumed), blended_rows))| {
                let images = BandImages {
                    features,
                    alpha,
                    depth,
                    final_t,
                    consumed,
                    blended_rows,
                    first_entry: scene.bins.range(b * scene.bins.tiles_x as usize).start,
                };
                blend_band(scene, b as u32, images)
            },
        )
        .reduce(BlendCounts::default, BlendCounts::add);
    let state = PixelState {
        final_t,
        consumed,
        blended_rows,
    };
    (features, alpha, depth, state, counts)
}

/// `per_entry` split into the entries of each band of tiles (a band's lists are contiguous).
fn band_slices<'a>(bins: &Bins, per_entry: &'a mut [u8]) -> Vec<&'a mut [u8]> {
    let mut rest = per_entry;
    let mut slices = Vec::with_capacity(bins.tiles_y as usize);
    for band in 0..bins.tiles_y as usize {
        let tiles = band * bins.tiles_x as usize..(band + 1) * bins.tiles_x as usize;
        let len = bins.range(tiles.end - 1).end - bins.range(tiles.start).start;
        let (head, tail) = std::mem::take(&mut rest).split_at_mut(len);
        slices.push(head);
        rest = tail;
    }
    slices
}

with_avx2!(
    /// Blends the tiles of one band of rows.
    fn blend_band(scene: &Scene, band: u32, out: BandImages) -> BlendCounts = blend_band_body
);

#[inline(always)]
fn blend_band_body(scene: &Scene, band: u32, mut out: BandImages) -> BlendCounts {
    let bins = scene.bins;
    let mut acc = vec![[0.0f32; LANES]; TILE as usize * scene.channels];
    let mut counts = BlendCounts::default();
    for tx in 0..bins.tiles_x {
        let tile = (band * bins.tiles_x + tx) as usize;
        let rows = Row::of_tile(tx, band, scene.width, scene.height);
        let range = bins.range(tile);
        if let Some(base) = scene.base.as_ref().filter(|base| !base.blend[tile]) {
            copy_tile(scene, base, &rows, band, tx, &mut out, range.start as u32);
            continue;
        }
        let tile_counts = with_channels!(
            scene.channels,
            blend_tile(scene, range, &rows, &mut acc, tx, &mut out)
        );
        counts = counts.add(tile_counts);
    }
    counts
}

/// Stores the pixels of tile (tx, band) from `base`, over the scene's background as
/// [`blend_tile`] stores its own: bit for bit what blending the layer's list would give. Their
/// consumed prefix is the tile's list start (its list is empty).
fn copy_tile(
    scene: &Scene,
    base: &Base,
    rows: &[Row; TILE as usize],
    band: u32,
    tx: u32,
    out: &mut BandImages,
    start: u32,
) {
    let (width, channels) = (scene.width as usize, scene.channels);
    let band_first = band as usize * TILE as usize * width;
    for (r, row) in rows.iter().enumerate() {
        let first = r * width + (tx * TILE) as usize;
        for pix in first..first + row.len {
            let t = base.final_t[band_first + pix];
            for c in 0..channels {
                out.features[pix * channels + c] =
                    base.colour[(band_first + pix) * channels + c] + t * scene.background[c];
            }
            out.alpha[pix] = 1.0 - t;
            out.depth[pix] = base.depth[band_first + pix];
            out.final_t[pix] = t;
            out.consumed[pix] = start;
        }
    }
}

/// A pixel row's blend state.
#[derive(Clone, Copy, Default)]
struct RowState {
    t: Lanes,
    depth: Lanes,
    consumed: [u32; LANES],
    /// Pixels still blending (all ones).
    open: Mask,
    /// Blended entries per pixel (for the counts).
    blended: [u32; LANES],
}

/// Blends one tile's list (entries `range`) front to back into its rows and stores their
/// pixels. The list is walked once for all rows; an entry visits only the rows its ellipse
/// spans that are still blending (a bit mask), so no row pays a branch for an entry that
/// misses it. `C` is the channel count if it is a compile-time constant ([`with_channels!`]).
#[inline(always)]
fn blend_tile<const C: usize>(
    scene: &Scene,
    range: std::ops::Range<usize>,
    rows: &[Row; TILE as usize],
    acc: &mut [Lanes],
    tx: u32,
    out: &mut BandImages,
) -> BlendCounts {
    let channels = channels::<C>(scene.channels);
    let start = range.start as u32;
    let entries = &scene.bins.entries[range.clone()];
    let features = &scene.bins.entry_features[range.start * channels..range.end * channels];
    let rows_blended = &mut out.blended_rows[range.start - out.first_entry..][..range.len()];
    let mut state: [RowState; TILE as usize] = array(|r| RowState {
        t: [1.0; LANES],
        depth: [0.0; LANES],
        consumed: [start; LANES],
        open: array(|i| mask(i < rows[r].len)),
        blended: [0; LANES],
    });
    // Rows with a pixel still blending.
    let mut live = rows
        .iter()
        .enumerate()
        .fold(0, |m, (r, row)| m | (u32::from(row.len > 0) << r));
    let mut evaluations = 0u64;
    acc.fill([0.0; LANES]);
    for (j, s) in entries.iter().enumerate() {
        if live == 0 {
            break;
        }
        let next_consumed = start + j as u32 + 1;
        let f = &features[j * channels..(j + 1) * channels];
        let mut visit = s.rows & live;
        while visit != 0 {
            let r = visit.trailing_zeros() as usize;
            visit &= visit - 1;
            let (row, st) = (&rows[r], &mut state[r]);
            evaluations += row.len as u64;
            let e = evaluate(s, &row.xs, row.cy - s.v);
            let mut w = [0.0f32; LANES];
            let mut blended: Mask = [0; LANES];
            for i in 0..LANES {
                let next = st.t[i] * (1.0 - e.alpha[i]);
                let hit = st.open[i] & e.passes[i];
                let stop = hit & mask(next < MIN_TRANSMITTANCE as f32);
                let blend = hit & !stop;
                st.open[i] &= !stop;
                st.blended[i] += blend & 1;
                blended[i] = blend;
                w[i] = masked(e.alpha[i] * st.t[i], blend);
                st.t[i] = select(blend, next, st.t[i]);
                st.consumed[i] = (next_consumed & blend) | (st.consumed[i] & !blend);
            }
            if st.open.iter().all(|&o| o == 0) {
                live &= !(1 << r);
            }
            if blended.iter().any(|&b| b != 0) {
                rows_blended[j] |= 1 << r;
            }
            for (a, &fc) in acc[r * channels..(r + 1) * channels].iter_mut().zip(f) {
                for i in 0..LANES {
                    a[i] += w[i] * fc;
                }
            }
            if scene.depth {
                // A whole-row copy: updated in place, the lanes would be scalar code.
                let mut depth = st.depth;
                for i in 0..LANES {
                    depth[i] += w[i] * s.z;
                }
                st.depth = depth;
            }
        }
    }
    let counts = BlendCounts {
        evaluations,
        contributions: state.iter().flat_map(|st| st.blended).map(u64::from).sum(),
    };
    for (r, (row, st)) in rows.iter().zip(&state).enumerate() {
        let first = r * scene.width as usize + (tx * TILE) as usize;
        for i in 0..row.len {
            let pix = first + i;
            for c in 0..channels {
                out.features[pix * channels + c] =
                    acc[r * channels + c][i] + st.t[i] * scene.background[c];
            }
            out.alpha[pix] = 1.0 - st.t[i];
            out.depth[pix] = st.depth[i];
            out.final_t[pix] = st.t[i];
            out.consumed[pix] = st.consumed[i];
        }
    }
    counts
}
