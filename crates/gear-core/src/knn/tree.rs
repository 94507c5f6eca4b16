//! A balanced k-d tree stored as a complete binary tree in heap order (children of node `i` are
//! `2i + 1` and `2i + 2`), every leaf at the same depth.
//!
//! Each node splits its points at the median along the widest axis of their bounding box, so
//! the halves differ by at most one point and the whole tree is implied by the point count;
//! each node keeps the tight box of its points, which prunes better than split planes alone.
//! Points are stored reordered, leaf by leaf, with their original index alongside.

use rayon::prelude::*;

/// Points per leaf at most: small enough to prune well, large enough to amortise the descent.
const LEAF_SIZE: usize = 12;
/// Subtrees smaller than this are built on the current thread.
const PARALLEL_MIN: usize = 1 << 14;

/// A reference point and its index in the caller's array.
#[derive(Clone, Copy)]
pub(super) struct Entry {
    pub p: [f32; 3],
    pub id: u32,
}

/// The axis-aligned bounding box of a node's points.
#[derive(Clone, Copy)]
pub(super) struct Bounds {
    pub lo: [f32; 3],
    pub hi: [f32; 3],
}

impl Bounds {
    const EMPTY: Bounds = Bounds {
        lo: [f32::INFINITY; 3],
        hi: [f32::NEG_INFINITY; 3],
    };

    fn of(entries: &[Entry]) -> Bounds {
        entries.iter().fold(Bounds::EMPTY, |b, e| b.with(e.p))
    }

    fn with(self, p: [f32; 3]) -> Bounds {
        Bounds {
            lo: std::array::from_fn(|a| self.lo[a].min(p[a])),
            hi: std::array::from_fn(|a| self.hi[a].max(p[a])),
        }
    }

    fn union(self, o: Bounds) -> Bounds {
        Bounds {
            lo: std::array::from_fn(|a| self.lo[a].min(o.lo[a])),
            hi: std::array::from_fn(|a| self.hi[a].max(o.hi[a])),
        }
    }

    fn widest_axis(&self) -> usize {
        let ext: [f32; 3] = std::array::from_fn(|a| self.hi[a] - self.lo[a]);
        if ext[0] >= ext[1] && ext[0] >= ext[2] {
            0
        } else if ext[1] >= ext[2] {
            1
        } else {
            2
        }
    }

    /// Squared distance from `q` to the box (0 inside).
    #[inline]
    pub fn dist2(&self, q: [f32; 3]) -> f32 {
        let mut d2 = 0.0;
        for ((&lo, &hi), &c) in self.lo.iter().zip(&self.hi).zip(&q) {
            let d = (lo - c).max(c - hi).max(0.0);
            d2 += d * d;
        }
        d2
    }
}

pub(super) struct KdTree {
    pub(super) entries: Vec<Entry>,
    pub(super) bounds: Vec<Bounds>,
    /// `[start, end)` of each node in `entries`.
    pub(super) ranges: Vec<(u32, u32)>,
    /// Index of the first leaf; nodes from here on are leaves.
    pub(super) first_leaf: usize,
}

impl KdTree {
    /// Builds the tree over `points` (at most `u32::MAX` of them, all finite).
    pub fn build(points: &[[f32; 3]]) -> KdTree {
        assert!(
            points.len() < u32::MAX as usize,
            "too many points for a u32 index"
        );
        let mut depth = 0;
        while points.len().div_ceil(1 << depth) > LEAF_SIZE {
            depth += 1;
        }
        let node_count = (1usize << (depth + 1)) - 1;
        let first_leaf = (1usize << depth) - 1;

        let mut entries: Vec<Entry> = points
            .par_iter()
            .enumerate()
            .map(|(i, &p)| Entry { p, id: i as u32 })
            .collect();
        partition(&mut entries, depth);

        // Ranges follow the same halving rule as `partition`, top-down.
        let mut ranges = vec![(0u32, 0u32); node_count];
        ranges[0] = (0, points.len() as u32);
        for node in 0..first_leaf {
            let (s, e) = ranges[node];
            let mid = s + (e - s) / 2;
            ranges[2 * node + 1] = (s, mid);
            ranges[2 * node + 2] = (mid, e);
        }

        // Boxes bottom-up: leaves from their points, inner nodes as the union of children.
        let mut bounds = vec![Bounds::EMPTY; node_count];
        bounds[first_leaf..]
            .par_iter_mut()
            .zip(&ranges[first_leaf..])
            .for_each(|(b, &(s, e))| *b = Bounds::of(&entries[s as usize..e as usize]));
        for node in (0..first_leaf).rev() {
            bounds[node] = bounds[2 * node + 1].union(bounds[2 * node + 2]);
        }
        KdTree {
            entries,
            bounds,
            ranges,
            first_leaf,
        }
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }
}

/// Splits `entries` at its midpoint along the widest axis, then each half, `depth` levels deep.
fn partition(entries: &mut [Entry], depth: u32) {
    if depth == 0 || entries.len() < 2 {
        return;
    }
    let axis = Bounds::of(entries).widest_axis();
    let mid = entries.len() / 2;
    entries.select_nth_unstable_by(mid, |a, b| a.p[axis].total_cmp(&b.p[axis]));
    let (left, right) = entries.split_at_mut(mid);
    if left.len() + right.len() >= PARALLEL_MIN {
        rayon::join(
            || partition(left, depth - 1),
            || partition(right, depth - 1),
        );
    } else {
        partition(left, depth - 1);
        partition(right, depth - 1);
    }
}
