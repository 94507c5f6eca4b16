//! The backward of the CPU blend, without atomics: bands of tiles in parallel, each pixel row
//! replays its consumed list prefix back to front (T_i = T_{i+1} / (1 - alpha_i) from the
//! stored final T, as blend_backward.wgsl), and adds its eight pixels' contributions to the
//! gradient record of that (tile, entry) pair. Rows of a tile run in order on one thread, and
//! a pair belongs to one tile, so every record is summed in a fixed order whatever the thread
//! count; the per-Gaussian reduction over its pairs (mod.rs) is in a fixed order too.

// Lane loops index several [f32; 8] arrays in step: the form the compiler vectorises.
#![allow(clippy::needless_range_loop)]

use rayon::prelude::*;

use super::bins::split_lengths;
use super::blend::{PixelState, Row, Scene, TileList};
use super::lanes::{evaluate, Lanes, LANES};
use super::TILE;
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
}

impl Replay<'_> {
    pub fn stride(&self, channels: usize) -> usize {
        GEOMETRY + if self.features_grad { channels } else { 0 }
    }
}

/// The gradient record of every (tile, entry) pair, in tile-list order (pairs x stride).
pub(super) fn blend_backward(scene: &Scene, replay: &Replay) -> Vec<f32> {
    let bins = scene.bins;
    let stride = replay.stride(scene.channels);
    let mut records = vec![0.0f32; bins.pairs() * stride];
    let tiles_x = bins.tiles_x as usize;
    let band_pairs = (0..bins.tiles_y as usize).map(|b| {
        let (first, end) = (b * tiles_x, (b + 1) * tiles_x);
        (bins.tile_offsets[end] - bins.tile_offsets[first]) as usize * stride
    });
    split_lengths(&mut records, band_pairs)
        .into_par_iter()
        .enumerate()
        .for_each(|(b, band)| replay_band(scene, replay, b as u32, band));
    records
}

fn replay_band(scene: &Scene, replay: &Replay, band: u32, records: &mut [f32]) {
    let bins = scene.bins;
    let stride = replay.stride(scene.channels);
    let band_start = bins.tile_offsets[(band * bins.tiles_x) as usize] as usize;
    let mut list = TileList::new();
    let mut rows = RowBuffers::new(scene.channels);
    for tx in 0..bins.tiles_x {
        let tile = (band * bins.tiles_x + tx) as usize;
        let range = bins.range(tile);
        if range.is_empty() {
            continue;
        }
        list.gather(bins, tile, scene.features, scene.channels);
        let tile_records =
            &mut records[(range.start - band_start) * stride..(range.end - band_start) * stride];
        for r in 0..TILE {
            let y = band * TILE + r;
            if y >= scene.height {
                break;
            }
            let row = Row::new(tx * TILE, y, scene.width);
            let first = (y * scene.width + tx * TILE) as usize;
            replay_row(
                scene,
                replay,
                &list,
                range.start as u32,
                &row,
                first,
                &mut rows,
                tile_records,
            );
        }
    }
}

/// Per-channel lanes of a row, kept between rows to avoid allocations.
struct RowBuffers {
    grad_f: Vec<Lanes>,
    behind_f: Vec<Lanes>,
    sums: Vec<f32>,
}

impl RowBuffers {
    fn new(channels: usize) -> Self {
        RowBuffers {
            grad_f: vec![[0.0; LANES]; channels],
            behind_f: vec![[0.0; LANES]; channels],
            sums: vec![0.0; GEOMETRY + channels],
        }
    }
}

fn lane_sum(v: &Lanes) -> f32 {
    v.iter().sum()
}

/// Replays one pixel row (image index of its first pixel `first`) back to front, adding its
/// contributions to the tile's pair records.
#[allow(clippy::too_many_arguments)]
fn replay_row(
    scene: &Scene,
    replay: &Replay,
    list: &TileList,
    start: u32,
    row: &Row,
    first: usize,
    buffers: &mut RowBuffers,
    records: &mut [f32],
) {
    let channels = scene.channels;
    let stride = replay.stride(channels);
    let grads = replay.grads;
    // Lanes past the image edge consumed nothing and carry zero gradients.
    let mut final_t = [0.0f32; LANES];
    let mut consumed = [start; LANES];
    let mut grad_alpha = [0.0f32; LANES];
    let mut grad_depth = [0.0f32; LANES];
    for i in 0..row.len {
        let pix = first + i;
        final_t[i] = replay.state.final_t[pix];
        consumed[i] = replay.state.consumed[pix];
        grad_alpha[i] = grads.alpha[pix];
        if scene.depth {
            grad_depth[i] = grads.depth.map_or(0.0, |d| d[pix]);
        }
    }
    let last = *consumed.iter().max().unwrap();
    if last == start {
        return;
    }
    for c in 0..channels {
        for i in 0..LANES {
            buffers.grad_f[c][i] = if i < row.len {
                grads.features[(first + i) * channels + c]
            } else {
                0.0
            };
            buffers.behind_f[c][i] = final_t[i] * scene.background[c];
        }
    }
    let mut t = final_t;
    let mut behind_d = [0.0f32; LANES];
    let zero = [0.0f32; LANES];
    for k in (start..last).rev() {
        let j = (k - start) as usize;
        let s = &list.splats[j];
        let dy = row.cy - s.v;
        if !row.meets(s, dy) {
            continue;
        }
        let e = evaluate(s, &row.xs, dy);
        let hit: [bool; LANES] = std::array::from_fn(|i| k < consumed[i] && e.passes[i]);
        if !hit.iter().any(|&h| h) {
            continue;
        }
        let mut keep = zero;
        let mut t_i = zero;
        let mut w = zero;
        let mut grad_a = zero;
        for i in 0..LANES {
            keep[i] = 1.0 - e.alpha[i];
            t_i[i] = t[i] / keep[i];
            w[i] = e.alpha[i] * t_i[i];
            // dL/dalpha_i: own contribution T_i·f_i minus 1/(1-alpha_i) times what it hides.
            grad_a[i] = grad_alpha[i] * final_t[i] / keep[i];
        }
        let f = &list.features[j * channels..(j + 1) * channels];
        let sums = &mut buffers.sums;
        for (c, &fc) in f.iter().enumerate() {
            let (g, behind) = (&buffers.grad_f[c], &mut buffers.behind_f[c]);
            let mut contribution = zero;
            for i in 0..LANES {
                grad_a[i] += g[i] * (fc * t_i[i] - behind[i] / keep[i]);
                contribution[i] = if hit[i] { w[i] * g[i] } else { 0.0 };
                behind[i] = if hit[i] {
                    behind[i] + w[i] * fc
                } else {
                    behind[i]
                };
            }
            if replay.features_grad {
                sums[GEOMETRY + c] = lane_sum(&contribution);
            }
        }
        sums[6] = 0.0;
        if scene.depth {
            let mut contribution = zero;
            for i in 0..LANES {
                grad_a[i] += grad_depth[i] * (s.z * t_i[i] - behind_d[i] / keep[i]);
                contribution[i] = if hit[i] { w[i] * grad_depth[i] } else { 0.0 };
                behind_d[i] = if hit[i] {
                    behind_d[i] + w[i] * s.z
                } else {
                    behind_d[i]
                };
            }
            sums[6] = lane_sum(&contribution);
        }
        // The 0.999 clamp passes no gradient to opacity and power.
        let mut geometry = [zero; 6];
        for i in 0..LANES {
            if hit[i] && e.raw[i] <= MAX_ALPHA as f32 {
                let (dx, gp) = (e.dx[i], grad_a[i] * e.alpha[i]);
                geometry[0][i] = -0.5 * dx * dx * gp;
                geometry[1][i] = -dx * dy * gp;
                geometry[2][i] = -0.5 * dy * dy * gp;
                geometry[3][i] = (s.a * dx + s.b * dy) * gp;
                geometry[4][i] = (s.b * dx + s.c * dy) * gp;
                geometry[5][i] = grad_a[i] * e.gauss[i];
            }
            t[i] = if hit[i] { t_i[i] } else { t[i] };
        }
        for (q, g) in geometry.iter().enumerate() {
            sums[q] = lane_sum(g);
        }
        for (r, v) in records[j * stride..(j + 1) * stride]
            .iter_mut()
            .zip(&sums[..stride])
        {
            *r += v;
        }
    }
}
