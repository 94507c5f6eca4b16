//! The CPU executor's tile lists: entries in per-tile ranges of three parallel arrays (what
//! the blend reads of each Gaussian, its features, its pair number), scattered to their tiles
//! in Gaussian order (a counting sort by tile, whose reads all stream), then sorted by depth
//! or merged with lists made before (a static layer's), in parallel over the tiles.

use rayon::prelude::*;

use super::spares::Spares;
use crate::splat::types::Gaussians;

/// A list entry: what the blend reads of a Gaussian (the contract's evaluation: mean, conic,
/// opacity, depth) and the rows of the tile that its ellipse spans.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Entry {
    pub u: f32,
    pub v: f32,
    /// Conic a, b, c.
    pub a: f32,
    pub b: f32,
    pub c: f32,
    pub opacity: f32,
    pub z: f32,
    /// Bit r set where the ellipse spans a pixel centre of the tile's row r (inside the image).
    pub rows: u32,
}

// Buffers of earlier passes (see `spares`): the lists.
static ENTRIES: Spares<Entry> = Spares::new();
static ENTRY_FEATURES: Spares<f32> = Spares::new();
static ENTRY_PAIRS: Spares<u32> = Spares::new();

/// The tile lists under construction: entry e of every array belongs to the same pair.
pub(super) struct Lists {
    pub entries: Vec<Entry>,
    /// Entries x channels.
    pub features: Vec<f32>,
    /// The pair number of each entry.
    pub pairs: Vec<u32>,
}

/// Tile lists made before (a static layer's), to read: tile t's entries are
/// `offsets[t]..offsets[t + 1]`.
pub(super) struct Listed<'a> {
    pub offsets: &'a [u32],
    pub entries: &'a [Entry],
    pub features: &'a [f32],
    pub pairs: &'a [u32],
}

impl Lists {
    /// Lists for `pairs` entries of `channels` features, in kept buffers.
    pub fn take(pairs: usize, channels: usize) -> Self {
        Lists {
            entries: ENTRIES.take(pairs, Entry::default()),
            features: ENTRY_FEATURES.take(pairs * channels, 0.0),
            pairs: ENTRY_PAIRS.take(pairs, 0),
        }
    }

    /// Returns the buffers to the kept ones.
    pub fn keep(self) {
        ENTRIES.keep(self.entries);
        ENTRY_FEATURES.keep(self.features);
        ENTRY_PAIRS.keep(self.pairs);
    }

    /// Scatters the pairs of Gaussians `from..` to their tiles walking the Gaussians in index
    /// order, so that every read streams through memory (a walk in depth order gathers each
    /// Gaussian from a random place, and cost most of the binning). Each list comes out in
    /// index order. `projected`: each Gaussian's entry (rows aside), and the (tile, rows)
    /// pairs of Gaussians `from..`, Gaussian by Gaussian.
    pub fn fill(
        &mut self,
        tile_offsets: &[u32],
        projected: (&[Entry], &[[u32; 2]]),
        pair_offsets: &[u32],
        gaussians: &Gaussians,
        from: usize,
    ) {
        let (splats, own_pairs) = projected;
        let channels = gaussians.channels;
        // `own_pairs` starts at Gaussian `from`'s first pair.
        let first_pair = pair_offsets[from] as usize;
        let mut cursor = tile_offsets[..tile_offsets.len() - 1].to_vec();
        for (g, splat) in splats.iter().enumerate().skip(from) {
            let features = &gaussians.features[g * channels..(g + 1) * channels];
            for pair in pair_offsets[g] as usize..pair_offsets[g + 1] as usize {
                let [t, rows] = own_pairs[pair - first_pair];
                let e = cursor[t as usize] as usize;
                cursor[t as usize] += 1;
                self.entries[e] = Entry { rows, ..*splat };
                self.pairs[e] = pair as u32;
                self.features[e * channels..(e + 1) * channels].copy_from_slice(features);
            }
        }
    }

    /// Fills each tile's list (ranges `tile_offsets`, empty or as long as both) with the
    /// merge of `base`'s list and `own`'s (ranges `own_offsets`), both in depth order: by
    /// depth, `base`'s entries first on ties (their Gaussians come first); `channels`
    /// features per entry. In parallel over the tiles.
    pub fn merge(
        &mut self,
        tile_offsets: &[u32],
        base: &Listed,
        own: &Lists,
        own_offsets: &[u32],
        channels: usize,
    ) {
        self.by_tile(tile_offsets, channels)
            .into_par_iter()
            .enumerate()
            .filter(|(_, tile)| !tile.entries.is_empty())
            .for_each(|(t, tile)| {
                let TileList {
                    entries,
                    features,
                    pairs,
                } = tile;
                let from_base = base.offsets[t] as usize..base.offsets[t + 1] as usize;
                let from_own = own_offsets[t] as usize..own_offsets[t + 1] as usize;
                let (mut b, mut o) = (from_base.start, from_own.start);
                for e in 0..entries.len() {
                    let take_base = o == from_own.end
                        || (b < from_base.end
                            && base.entries[b].z.to_bits() <= own.entries[o].z.to_bits());
                    let (list, k) = if take_base {
                        b += 1;
                        ((base.entries, base.features, base.pairs), b - 1)
                    } else {
                        o += 1;
                        ((&own.entries[..], &own.features[..], &own.pairs[..]), o - 1)
                    };
                    entries[e] = list.0[k];
                    pairs[e] = list.2[k];
                    features[e * channels..(e + 1) * channels]
                        .copy_from_slice(&list.1[k * channels..(k + 1) * channels]);
                }
            });
    }

    /// Sorts every tile's list (in index order) by depth, in parallel over the tiles; ties
    /// keep index order, as in the GPU's stable sort and the reference. z > 0, so its bits
    /// order like the floats.
    pub fn sort_by_depth(&mut self, tile_offsets: &[u32], channels: usize) {
        self.by_tile(tile_offsets, channels)
            .into_par_iter()
            .for_each_init(TileScratch::default, |scratch, tile| {
                scratch.sort(tile, channels)
            });
    }

    /// Each tile's part of the lists (ranges `tile_offsets`), to work on the tiles in parallel.
    fn by_tile(&mut self, tile_offsets: &[u32], channels: usize) -> Vec<TileList<'_>> {
        let lengths: Vec<usize> = tile_offsets
            .windows(2)
            .map(|w| (w[1] - w[0]) as usize)
            .collect();
        let entries = split_by_lengths(&mut self.entries, &lengths, 1);
        let features = split_by_lengths(&mut self.features, &lengths, channels);
        let pairs = split_by_lengths(&mut self.pairs, &lengths, 1);
        entries
            .into_iter()
            .zip(features)
            .zip(pairs)
            .map(|((entries, features), pairs)| TileList {
                entries,
                features,
                pairs,
            })
            .collect()
    }
}

/// One tile's part of the lists.
struct TileList<'a> {
    entries: &'a mut [Entry],
    features: &'a mut [f32],
    pairs: &'a mut [u32],
}

/// One thread's copies of a tile's list while it is permuted.
#[derive(Default)]
struct TileScratch {
    keys: Vec<u64>,
    entries: Vec<Entry>,
    features: Vec<f32>,
    pairs: Vec<u32>,
}

impl TileScratch {
    fn sort(&mut self, tile: TileList, channels: usize) {
        let TileList {
            entries,
            features,
            pairs,
        } = tile;
        self.keys.clear();
        self.keys.extend(
            entries
                .iter()
                .enumerate()
                .map(|(i, e)| (u64::from(e.z.to_bits()) << 32) | i as u64),
        );
        if self.keys.windows(2).all(|w| w[0] <= w[1]) {
            return;
        }
        self.keys.sort_unstable();
        self.entries.clear();
        self.entries.extend_from_slice(entries);
        self.features.clear();
        self.features.extend_from_slice(features);
        self.pairs.clear();
        self.pairs.extend_from_slice(pairs);
        for (to, &key) in self.keys.iter().enumerate() {
            let from = key as u32 as usize;
            entries[to] = self.entries[from];
            pairs[to] = self.pairs[from];
            features[to * channels..(to + 1) * channels]
                .copy_from_slice(&self.features[from * channels..(from + 1) * channels]);
        }
    }
}

/// `slice` cut into consecutive pieces of `lengths[i] * stride` elements.
fn split_by_lengths<'a, T>(
    mut slice: &'a mut [T],
    lengths: &[usize],
    stride: usize,
) -> Vec<&'a mut [T]> {
    let mut pieces = Vec::with_capacity(lengths.len());
    for &length in lengths {
        let (piece, rest) = slice.split_at_mut(length * stride);
        pieces.push(piece);
        slice = rest;
    }
    pieces
}
