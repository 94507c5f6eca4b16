//! The backward of the CPU blend, without atomics: bands of tiles in parallel, each pixel row
//! replays its consumed list prefix back to front (T_i = T_{i+1} / (1 - alpha_i) from the
//! stored final T, as blend_backward.wgsl), and adds its eight pixels' contributions to the
//! gradient record of that (tile, entry) pair. Rows of a tile run in order on one thread, and
//! a pair belongs to one tile, so every record is summed in a fixed order whatever the thread
//! count; the per-Gaussian reduction over its pairs (mod.rs) is in a fixed order too.

// Lane loops index several [f32; 8] arrays in step: the form the compiler vectorises.
#![allow(clippy::needless_range_loop)]

use rayon::prelude::*;

use super::blend::{PixelState, Row, Scene};
use super::lanes::{array, evaluate, mask, masked, select, with_avx2, Lanes, Mask, LANES};
use super::lists::Entry;
use super::spares::Spares;
use super::TILE;
use crate::counts::{channels, with_channels};
use crate::splat::constants::MAX_ALPHA;
use crate::splat::types::OutputGradients;

/// Values of a pair record before its feature gradients: conic a, b, c, mean u, v, opacity, z.
pub(super) const GEOMETRY: usize = 7;

/// Per-pixel inputs of the backward.
pub(super) struct Replay<'a> {
    pub state: &'a PixelState,
    pub grads: &'a OutputGradients<'a, f32>,
    /// Also sum the feature gradients (records then hold GEOMETRY + C values, else GEOMETRY).
    pub features_grad: bool,
    /// Pairs numbered below this belong to held Gaussians (no gradients wanted): they are
    /// replayed for the transmittance and what lies behind, but get no record.
    pub first_pair: u32,
}

impl Replay<'_> {
    pub fn stride(&self, channels: usize) -> usize {
        GEOMETRY + if self.features_grad { channels } else { 0 }
    }
}

/// The gradient records of pairs `first..first + pairs` (pairs x stride, by pair number:
/// Gaussian-major), written by the band threads at once.
struct Records {
    values: *mut f32,
    stride: usize,
    first: usize,
    pairs: usize,
}

// SAFETY: every pair belongs to one list entry, every entry to one tile and every tile to one
// band, so the threads write disjoint records (`write` is the only access), each once.
unsafe impl Sync for Records {}

impl Records {
    /// Writes the lane sums of `sums` as the record of pair `pair`.
    #[inline(always)]
    fn write(&self, pair: usize, sums: &[Lanes]) {
        let at = pair - self.first;
        assert!(pair >= self.first && at < self.pairs && sums.len() >= self.stride);
        // SAFETY: in bounds (checked above); no other thread touches this record.
        let record = unsafe {
            std::slice::from_raw_parts_mut(self.values.add(at * self.stride), self.stride)
        };
        for (out, v) in record.iter_mut().zip(sums) {
            *out = lane_sum(v);
        }
    }
}

/// Record buffers of earlier backwards (see `spares`); the caller keeps each one here when it
/// has reduced it.
pub(super) static RECORDS: Spares<f32> = Spares::new();

/// The gradient record of every pair from `replay.first_pair` on, by pair number (pairs x
/// stride, record 0 that of `first_pair`), so that each Gaussian's records are contiguous;
/// records of pairs no pixel blended are zero.
pub(super) fn blend_backward(scene: &Scene, replay: &Replay) -> Vec<f32> {
    let bins = scene.bins;
    let stride = replay.stride(scene.channels);
    let first = replay.first_pair as usize;
    let pairs = bins.pair_count() - first;
    let mut values = RECORDS.take(pairs * stride, 0.0);
    let records = Records {
        values: values.as_mut_ptr(),
        stride,
        first,
        pairs,
    };
    (0..bins.tiles_y)
        .into_par_iter()
        .for_each(|band| replay_band(scene, replay, band, &records));
    values
}

with_avx2!(
    /// Replays the tiles of one band of rows into their pair records.
    fn replay_band(scene: &Scene, replay: &Replay, band: u32, records: &Records) -> () =
        replay_band_body
);

#[inline(always)]
fn replay_band_body(scene: &Scene, replay: &Replay, band: u32, records: &Records) {
    let bins = scene.bins;
    let mut buffers = TileBuffers::new(scene.channels);
    for tx in 0..bins.tiles_x {
        let tile = (band * bins.tiles_x + tx) as usize;
        let range = bins.range(tile);
        if range.is_empty() {
            continue;
        }
        let rows = Row::of_tile(tx, band, scene.width, scene.height);
        with_channels!(
            scene.channels,
            replay_tile(scene, replay, range, &rows, tx, &mut buffers, records)
        );
    }
}

/// A pixel row's replay state.
#[derive(Clone, Copy, Default)]
struct RowState {
    /// T after the entries replayed so far (T_{i+1} for the next one, i).
    t: Lanes,
    final_t: Lanes,
    consumed: [u32; LANES],
    /// The row's longest consumed prefix end.
    last: u32,
    grad_alpha: Lanes,
    grad_depth: Lanes,
    /// Σ_{j>i} w_j z_j.
    behind_d: Lanes,
}

/// Per-channel lanes of a tile's rows (row r, channel c at r·C + c), reused between tiles.
struct TileBuffers {
    grad_f: Vec<Lanes>,
    /// Σ_{j>i} w_j f_j + T_final · background.
    behind_f: Vec<Lanes>,
    /// The current entry's contributions summed over the rows, per lane (record layout).
    sums: Vec<Lanes>,
}

impl TileBuffers {
    fn new(channels: usize) -> Self {
        let lanes = TILE as usize * channels;
        TileBuffers {
            grad_f: vec![[0.0; LANES]; lanes],
            behind_f: vec![[0.0; LANES]; lanes],
            sums: vec![[0.0; LANES]; GEOMETRY + channels],
        }
    }
}

/// The eight lanes summed as a fixed tree (vectorises; the same order every time).
fn lane_sum(v: &Lanes) -> f32 {
    ((v[0] + v[4]) + (v[2] + v[6])) + ((v[1] + v[5]) + (v[3] + v[7]))
}

/// Loads a row's pixel state and image gradients (lanes past the image edge consumed nothing
/// and carry zero gradients).
#[inline(always)]
fn load_row(
    scene: &Scene,
    replay: &Replay,
    row: &Row,
    r: usize,
    first: usize,
    start: u32,
    buffers: &mut TileBuffers,
) -> RowState {
    let channels = scene.channels;
    let grads = replay.grads;
    let mut st = RowState {
        consumed: [start; LANES],
        ..RowState::default()
    };
    for i in 0..row.len {
        let pix = first + i;
        st.final_t[i] = replay.state.final_t[pix];
        st.consumed[i] = replay.state.consumed[pix];
        st.grad_alpha[i] = grads.alpha[pix];
        if scene.depth {
            st.grad_depth[i] = grads.depth.map_or(0.0, |d| d[pix]);
        }
    }
    st.t = st.final_t;
    st.last = *st.consumed.iter().max().unwrap();
    for c in 0..channels {
        let (g, behind) = (
            &mut buffers.grad_f[r * channels + c],
            &mut buffers.behind_f[r * channels + c],
        );
        for i in 0..LANES {
            g[i] = if i < row.len {
                grads.features[(first + i) * channels + c]
            } else {
                0.0
            };
            behind[i] = st.final_t[i] * scene.background[c];
        }
    }
    st
}

/// Replays a tile's list (entries `range`) back to front for all its rows at once (from the
/// longest consumed prefix; an entry visits only the rows where the forward blended it and
/// that hold it in their prefix), adding each row's contributions to the entry's record, rows
/// in increasing order; entries of held Gaussians only advance the rows' state, and only
/// behind the frontmost entry that wants gradients. `C` is the channel count if it is a
/// compile-time constant ([`with_channels!`]).
#[inline(always)]
fn replay_tile<const C: usize>(
    scene: &Scene,
    replay: &Replay,
    range: std::ops::Range<usize>,
    rows: &[Row; TILE as usize],
    tx: u32,
    buffers: &mut TileBuffers,
    records: &Records,
) {
    let bins = scene.bins;
    let channels = channels::<C>(scene.channels);
    // Entries in front of the frontmost one that wants gradients change nothing it sees:
    // the replay stops there, and a tile of held Gaussians alone is not replayed at all.
    let Some(front) = range
        .clone()
        .find(|&k| bins.entry_pairs[k] >= replay.first_pair)
    else {
        return;
    };
    let start = range.start as u32;
    let mut state: [RowState; TILE as usize] = array(|r| {
        let first = ((rows[r].cy - 0.5) as u32 * scene.width + tx * TILE) as usize;
        if rows[r].len == 0 {
            RowState {
                consumed: [start; LANES],
                last: start,
                ..RowState::default()
            }
        } else {
            load_row(scene, replay, &rows[r], r, first, start, buffers)
        }
    });
    let ends: [u32; TILE as usize] = array(|r| state[r].last);
    let last = ends.iter().copied().max().unwrap();
    // Rows by decreasing prefix end: those whose consumed prefix holds entry k (end > k) are
    // a leading run of this order that grows as k falls.
    let mut by_end: [usize; TILE as usize] = array(|r| r);
    by_end.sort_unstable_by_key(|&r| std::cmp::Reverse(ends[r]));
    let (mut held, mut holding) = (0, 0u32);
    for k in (front as u32..last).rev() {
        while held < by_end.len() && ends[by_end[held]] > k {
            holding |= 1 << by_end[held];
            held += 1;
        }
        let visit = u32::from(replay.state.blended_rows[k as usize]) & holding;
        if visit == 0 {
            continue;
        }
        let entry = EntryReplay {
            k,
            s: &bins.entries[k as usize],
            f: &bins.entry_features[k as usize * channels..(k as usize + 1) * channels],
            visit,
        };
        let pair = bins.entry_pairs[k as usize];
        if pair < replay.first_pair {
            replay_entry::<C, false>(scene, replay, &entry, rows, &mut state, buffers);
        } else if replay_entry::<C, true>(scene, replay, &entry, rows, &mut state, buffers) {
            // Each pair's record is written once, its rows summed lane-wise in row order first.
            records.write(pair as usize, &buffers.sums);
        }
    }
}

/// A list entry being replayed: its index, evaluation data and features, and the rows of the
/// tile to visit (blended by the forward and holding it in their consumed prefix).
struct EntryReplay<'a> {
    k: u32,
    s: &'a Entry,
    f: &'a [f32],
    visit: u32,
}

/// Replays one entry on the rows it visits: each row's transmittance and what lies behind
/// advance past it, and with `GRADS` its contributions are summed lane-wise into
/// `buffers.sums` (its record; returns whether any pixel blended it). Without `GRADS` (a held
/// Gaussian) only the state the entries in front of it need is updated.
#[inline(always)]
fn replay_entry<const C: usize, const GRADS: bool>(
    scene: &Scene,
    replay: &Replay,
    entry: &EntryReplay,
    rows: &[Row; TILE as usize],
    state: &mut [RowState; TILE as usize],
    buffers: &mut TileBuffers,
) -> bool {
    let channels = channels::<C>(scene.channels);
    let stride = replay.stride(channels);
    let (k, s, f) = (entry.k, entry.s, entry.f);
    let zero = [0.0f32; LANES];
    let mut touched = false;
    let mut visit = entry.visit;
    while visit != 0 {
        let r = visit.trailing_zeros() as usize;
        visit &= visit - 1;
        let (row, st) = (&rows[r], &mut state[r]);
        let dy = row.cy - s.v;
        let e = evaluate(s, &row.xs, dy);
        let hit: Mask = array(|i| mask(k < st.consumed[i]) & e.passes[i]);
        if !hit.iter().any(|&h| h != 0) {
            continue;
        }
        if GRADS && !touched {
            buffers.sums[..stride].fill(zero);
        }
        touched = true;
        let mut inv_keep = zero;
        let mut t_i = zero;
        let mut w = zero;
        let mut grad_a = zero;
        for i in 0..LANES {
            // One division per lane; the terms below multiply by its reciprocal.
            inv_keep[i] = 1.0 / (1.0 - e.alpha[i]);
            t_i[i] = st.t[i] * inv_keep[i];
            w[i] = e.alpha[i] * t_i[i];
            if GRADS {
                // dL/dalpha_i: own contribution T_i·f_i minus 1/(1-alpha_i) times what it hides.
                grad_a[i] = st.grad_alpha[i] * st.final_t[i] * inv_keep[i];
            }
        }
        // The blended lanes' weights, zero elsewhere: the sums below multiply by them
        // instead of branching per lane, which keeps them vector adds.
        let w_hit: Lanes = array(|i| masked(w[i], hit[i]));
        let sums = &mut buffers.sums;
        for (c, &fc) in f.iter().enumerate() {
            // Whole-row copies and one loop per update: the form the compiler keeps in
            // vector registers.
            let g = buffers.grad_f[r * channels + c];
            let mut behind = buffers.behind_f[r * channels + c];
            if GRADS {
                for i in 0..LANES {
                    grad_a[i] += g[i] * (fc * t_i[i] - behind[i] * inv_keep[i]);
                }
            }
            for i in 0..LANES {
                behind[i] += w_hit[i] * fc;
            }
            buffers.behind_f[r * channels + c] = behind;
            if GRADS && replay.features_grad {
                let mut sum = sums[GEOMETRY + c];
                for i in 0..LANES {
                    sum[i] += w_hit[i] * g[i];
                }
                sums[GEOMETRY + c] = sum;
            }
        }
        if scene.depth {
            // Local copies, as for the features above.
            let (g, mut behind, mut sum) = (st.grad_depth, st.behind_d, sums[6]);
            if GRADS {
                for i in 0..LANES {
                    grad_a[i] += g[i] * (s.z * t_i[i] - behind[i] * inv_keep[i]);
                }
                for i in 0..LANES {
                    sum[i] += w_hit[i] * g[i];
                }
                sums[6] = sum;
            }
            for i in 0..LANES {
                behind[i] += w_hit[i] * s.z;
            }
            st.behind_d = behind;
        }
        if GRADS {
            // The 0.999 clamp passes no gradient to opacity and power: dL/dalpha is zeroed on
            // clamped and unblended lanes first (every factor below is finite, so their terms
            // are zeros), then the terms are summed over the lanes term by term (not lane by
            // lane), so that each sum is one vector add.
            let unclamped: Mask = array(|i| hit[i] & mask(e.raw[i] <= MAX_ALPHA as f32));
            let grad_a: Lanes = array(|i| masked(grad_a[i], unclamped[i]));
            let gp: Lanes = array(|i| grad_a[i] * e.alpha[i]);
            let dx = &e.dx;
            let terms: [Lanes; 6] = [
                array(|i| -0.5 * dx[i] * dx[i] * gp[i]),
                array(|i| -dx[i] * dy * gp[i]),
                array(|i| -0.5 * dy * dy * gp[i]),
                array(|i| (s.a * dx[i] + s.b * dy) * gp[i]),
                array(|i| (s.b * dx[i] + s.c * dy) * gp[i]),
                array(|i| grad_a[i] * e.gauss[i]),
            ];
            // A fixed-size view, so the adds compile to whole-row vector adds.
            let geometry: &mut [Lanes; 6] = (&mut sums[..6]).try_into().unwrap();
            for (sum, term) in geometry.iter_mut().zip(&terms) {
                for i in 0..LANES {
                    sum[i] += term[i];
                }
            }
        }
        for i in 0..LANES {
            st.t[i] = select(hit[i], t_i[i], st.t[i]);
        }
    }
    touched
}
