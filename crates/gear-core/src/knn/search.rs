//! Queries against a [`KdTree`]: a depth-first walk, nearest child first, that skips every box
//! no closer than the current k-th neighbour. With strict pruning a cluster of identical points
//! costs one leaf visit, not a scan of the cluster.

use rayon::prelude::*;

use super::tree::{Entry, KdTree};

/// Queries handed to one rayon task: enough to amortise the task, small enough to balance.
const CHUNK: usize = 512;

/// k neighbours per query, row-major `[queries, k]`, nearest first.
pub struct Neighbours {
    pub k: usize,
    /// Index of each neighbour in the reference points.
    pub indices: Vec<i64>,
    /// Euclidean distance of each neighbour.
    pub distances: Vec<f32>,
}

impl Neighbours {
    pub(super) fn empty(k: usize) -> Neighbours {
        Neighbours {
            k,
            indices: Vec::new(),
            distances: Vec::new(),
        }
    }

    pub fn len(&self) -> usize {
        self.indices.len() / self.k
    }

    pub fn is_empty(&self) -> bool {
        self.indices.is_empty()
    }
}

/// Neighbours of every reference point, excluding its own index. Queries run in tree order
/// (leaf by leaf), the most cache-friendly order there is.
pub(super) fn self_neighbours(tree: &KdTree, k: usize) -> Neighbours {
    run(
        tree.len(),
        k,
        |pos| {
            let e = tree.entries[pos];
            (e.p, e.id, e.id as usize)
        },
        tree,
    )
}

/// Neighbours of each of `queries`, processed in Morton (Z-curve) order for locality (a set
/// of one task's size in its own order: sorting it would cost more than it saves).
pub(super) fn query_neighbours(tree: &KdTree, queries: &[[f32; 3]], k: usize) -> Neighbours {
    if queries.len() <= CHUNK {
        return run(queries.len(), k, |pos| (queries[pos], u32::MAX, pos), tree);
    }
    let order = morton_order(queries);
    run(
        queries.len(),
        k,
        |pos| {
            let row = order[pos] as usize;
            (queries[row], u32::MAX, row)
        },
        tree,
    )
}

/// Answers `count` queries; `query(pos)` gives the point, the reference id to skip, and the
/// output row of the `pos`-th query in processing order.
fn run(
    count: usize,
    k: usize,
    query: impl Fn(usize) -> ([f32; 3], u32, usize) + Sync,
    tree: &KdTree,
) -> Neighbours {
    let mut indices = vec![0i64; count * k];
    let mut distances = vec![0f32; count * k];
    let rows = RowWriter {
        indices: indices.as_mut_ptr(),
        distances: distances.as_mut_ptr(),
        k,
    };
    let task = |chunk: usize| {
        let mut best = Best::new(k);
        for pos in chunk * CHUNK..((chunk + 1) * CHUNK).min(count) {
            let (q, skip, row) = query(pos);
            best.clear();
            visit(tree, 0, q, skip, &mut best);
            // SAFETY: `row` is a permutation of 0..count over all positions, so every row is
            // written by exactly one task, and it lies inside the buffers.
            unsafe { rows.write(row, &best) };
        }
    };
    let chunks = count.div_ceil(CHUNK);
    if chunks == 1 {
        // One task: handing it to the pool and waiting costs more than a small query set.
        task(0);
    } else {
        (0..chunks).into_par_iter().for_each(task);
    }
    Neighbours {
        k,
        indices,
        distances,
    }
}

fn visit(tree: &KdTree, node: usize, q: [f32; 3], skip: u32, best: &mut Best) {
    if node >= tree.first_leaf {
        let (s, e) = tree.ranges[node];
        for &Entry { p, id } in &tree.entries[s as usize..e as usize] {
            let d2 = dist2(p, q);
            if d2 < best.worst && id != skip {
                best.push(d2, id);
            }
        }
        return;
    }
    let (l, r) = (2 * node + 1, 2 * node + 2);
    let (dl, dr) = (tree.bounds[l].dist2(q), tree.bounds[r].dist2(q));
    let ((near, dn), (far, df)) = if dl <= dr {
        ((l, dl), (r, dr))
    } else {
        ((r, dr), (l, dl))
    };
    if dn < best.worst {
        visit(tree, near, q, skip, best);
    }
    if df < best.worst {
        visit(tree, far, q, skip, best);
    }
}

#[inline]
fn dist2(a: [f32; 3], b: [f32; 3]) -> f32 {
    let (dx, dy, dz) = (a[0] - b[0], a[1] - b[1], a[2] - b[2]);
    dx * dx + dy * dy + dz * dz
}

/// The k best candidates so far, sorted by squared distance (binary search and a block move
/// per insertion: cheap for the small k this serves, tolerable for large k).
struct Best {
    d2: Vec<f32>,
    ids: Vec<u32>,
    len: usize,
    /// Squared distance a candidate must beat: the k-th best, or infinity until k are found.
    worst: f32,
}

impl Best {
    fn new(k: usize) -> Best {
        Best {
            d2: vec![0.0; k],
            ids: vec![0; k],
            len: 0,
            worst: f32::INFINITY,
        }
    }

    fn clear(&mut self) {
        self.len = 0;
        self.worst = f32::INFINITY;
    }

    /// Inserts a candidate known to beat `worst`, dropping the k-th if the list is full.
    fn push(&mut self, d2: f32, id: u32) {
        let k = self.d2.len();
        let at = self.d2[..self.len].partition_point(|&d| d <= d2);
        let last = self.len.min(k - 1); // the slot the shifted tail ends in
        self.d2.copy_within(at..last, at + 1);
        self.ids.copy_within(at..last, at + 1);
        self.d2[at] = d2;
        self.ids[at] = id;
        self.len = (self.len + 1).min(k);
        if self.len == k {
            self.worst = self.d2[k - 1];
        }
    }
}

/// Raw output rows shared by the query tasks; each row has exactly one writer.
struct RowWriter {
    indices: *mut i64,
    distances: *mut f32,
    k: usize,
}

// SAFETY: tasks write disjoint rows (see `run`); the buffers outlive the parallel loop.
unsafe impl Sync for RowWriter {}

impl RowWriter {
    /// # Safety
    /// `row` must be in bounds and written by no other thread.
    unsafe fn write(&self, row: usize, best: &Best) {
        let base = row * self.k;
        for j in 0..self.k {
            *self.indices.add(base + j) = best.ids[j] as i64;
            *self.distances.add(base + j) = best.d2[j].sqrt();
        }
    }
}

/// Query indices sorted along a Z-order curve over the queries' bounding box (10 bits/axis).
fn morton_order(queries: &[[f32; 3]]) -> Vec<u32> {
    let (lo, hi) = queries.iter().fold(
        ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]),
        |(lo, hi), p| {
            (
                std::array::from_fn(|a| lo[a].min(p[a])),
                std::array::from_fn(|a| hi[a].max(p[a])),
            )
        },
    );
    let scale: [f32; 3] = std::array::from_fn(|a| {
        let ext = hi[a] - lo[a];
        if ext > 0.0 {
            1023.0 / ext
        } else {
            0.0
        }
    });
    let mut keyed: Vec<(u32, u32)> = queries
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            let cell = |a: usize| ((p[a] - lo[a]) * scale[a]) as u32;
            (
                spread_bits(cell(0)) | spread_bits(cell(1)) << 1 | spread_bits(cell(2)) << 2,
                i as u32,
            )
        })
        .collect();
    keyed.par_sort_unstable();
    keyed.into_iter().map(|(_, i)| i).collect()
}

/// Spreads the low 10 bits of `v` to every third bit.
fn spread_bits(v: u32) -> u32 {
    let mut x = v & 0x3ff;
    x = (x | (x << 16)) & 0x0300_00ff;
    x = (x | (x << 8)) & 0x0300_f00f;
    x = (x | (x << 4)) & 0x030c_30c3;
    (x | (x << 2)) & 0x0924_9249
}
