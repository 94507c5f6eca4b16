//! Connected components of occupied voxels (6- or 26-connectivity), labelled by size.
//!
//! Runs (see [`super::runs`]) of a line can only touch runs of the four earlier neighbouring
//! lines (two for 6-connectivity). They are found through a per-cell index of those lines
//! (or, where lines are too long to index and at slab seams, by a merge-like sweep) and
//! joined in a union-find whose root is always the smallest run index. Runs are in key order,
//! so each component's root is its first voxel in C order, which breaks ties between equal
//! sizes. The grid is cut into x slabs labelled in parallel, each in its own slice of the
//! union-find, then the slab seams are joined. Dense and sparse inputs share all of this; only
//! the run extraction and the output layout differ.

use rayon::prelude::*;

use super::runs::Runs;
use crate::error::{GearError, Result};

/// Which voxels are neighbours.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Connectivity {
    /// Shared faces only.
    Six,
    /// Shared faces, edges or corners.
    TwentySix,
}

impl Connectivity {
    /// From the neighbour count, 6 or 26.
    pub fn from_neighbours(n: i64) -> Result<Connectivity> {
        match n {
            6 => Ok(Connectivity::Six),
            26 => Ok(Connectivity::TwentySix),
            _ => Err(GearError::InvalidInput(format!(
                "connectivity: must be 6 or 26, got {n}"
            ))),
        }
    }

    /// Earlier lines a run can touch, as (dx, dy), and how far past its ends a touch reaches.
    fn neighbours(self) -> (&'static [(u64, i64)], u32) {
        match self {
            Connectivity::Six => (&[(1, 0), (0, -1)], 0),
            Connectivity::TwentySix => (&[(1, -1), (1, 0), (1, 1), (0, -1)], 1),
        }
    }
}

/// Labels (0 = empty, 1 = the largest component, ...) and the component sizes, largest first;
/// equal sizes are ordered by their first voxel in C order.
pub struct Components {
    pub labels: Vec<i32>,
    pub sizes: Vec<i64>,
}

/// Components of a dense occupancy (C order, `shape`); one label per cell.
pub fn components_dense(occ: &[bool], shape: [usize; 3], conn: Connectivity) -> Components {
    let [x, y, z] = shape;
    assert_eq!(occ.len(), x * y * z, "occupancy does not match its shape");
    let runs = Runs::from_dense(occ, shape);
    let (run_labels, sizes) = label_runs(&runs, shape, conn);

    let mut labels = vec![0i32; occ.len()];
    if y * z > 0 {
        labels
            .par_chunks_mut(y * z)
            .enumerate()
            .for_each(|(plane, out)| {
                let first = (plane * y) as u64;
                for li in runs.lines_between(first, first + y as u64) {
                    let offset = (runs.lines[li] - first) as usize * z;
                    let line_runs = runs.offsets[li]..runs.offsets[li + 1];
                    for (&(z0, z1), &label) in runs.spans[line_runs.clone()]
                        .iter()
                        .zip(&run_labels[line_runs])
                    {
                        out[offset + z0 as usize..offset + z1 as usize].fill(label);
                    }
                }
            });
    }
    Components { labels, sizes }
}

/// Components of a sparse occupancy (sorted, distinct keys in a grid of `shape`); one label
/// per key.
pub fn components_keys(keys: &[i64], shape: [usize; 3], conn: Connectivity) -> Components {
    let runs = Runs::from_keys(keys, shape);
    let (run_labels, sizes) = label_runs(&runs, shape, conn);
    let mut labels = Vec::with_capacity(keys.len());
    for (&(z0, z1), &label) in runs.spans.iter().zip(&run_labels) {
        labels.extend(std::iter::repeat_n(label, (z1 - z0) as usize));
    }
    Components { labels, sizes }
}

/// The label of every run and the component sizes, largest first.
fn label_runs(runs: &Runs, shape: [usize; 3], conn: Connectivity) -> (Vec<i32>, Vec<i64>) {
    let mut ids = join_runs(runs, shape, conn);
    // Component ids in root order, in place: a root (parent[i] == i) opens the next id, any
    // other run takes its root's id, already rewritten since roots come first (parent <= i).
    let mut count = 0u32;
    for i in 0..ids.len() {
        let p = ids[i] as usize;
        ids[i] = if p == i {
            count += 1;
            count - 1
        } else {
            ids[p]
        };
    }
    let mut size = vec![0i64; count as usize];
    for (&(z0, z1), &c) in runs.spans.iter().zip(&ids) {
        size[c as usize] += i64::from(z1 - z0);
    }
    // Ids are in first-voxel order, so (size descending, id) is the documented order.
    let mut order: Vec<(std::cmp::Reverse<i64>, u32)> = size
        .iter()
        .enumerate()
        .map(|(c, &n)| (std::cmp::Reverse(n), c as u32))
        .collect();
    order.par_sort_unstable();
    let mut label_of = vec![0i32; count as usize];
    for (rank, &(_, c)) in order.iter().enumerate() {
        label_of[c as usize] = rank as i32 + 1;
    }
    let labels = ids.par_iter().map(|&c| label_of[c as usize]).collect();
    let sizes = order.iter().map(|&(n, _)| n.0).collect();
    (labels, sizes)
}

/// The union-find forest over runs: following `parent` from any run reaches its component's
/// root, the component's smallest run index (`parent[i] <= i`).
fn join_runs(runs: &Runs, [x, y, z]: [usize; 3], conn: Connectivity) -> Vec<u32> {
    let mut parent = vec![0u32; runs.len()];
    // Slabs of whole x planes, as `lines` index ranges; each starts at plane `first_plane`.
    // A few slabs per thread, so a thread that gets descheduled on a busy machine can be
    // covered by the others; each seam costs only one plane of extra work.
    let slab_count = (4 * rayon::current_num_threads()).clamp(1, x.max(1));
    let slabs: Vec<(usize, std::ops::Range<usize>)> = (0..slab_count)
        .map(|s| {
            let (p0, p1) = (s * x / slab_count, (s + 1) * x / slab_count);
            (p0, runs.lines_between((p0 * y) as u64, (p1 * y) as u64))
        })
        .collect();

    // Inside each slab, in parallel: every neighbour line except the previous plane of the
    // slab's first plane. Each slab owns the parent entries of its runs, indexed locally.
    let mut rest = parent.as_mut_slice();
    let mut jobs = Vec::with_capacity(slabs.len());
    for (first_plane, lines) in &slabs {
        let base = runs.offsets[lines.start];
        let (mine, tail) = rest.split_at_mut(runs.offsets[lines.end] - base);
        rest = tail;
        jobs.push((*first_plane, lines.clone(), base, mine));
    }
    jobs.into_par_iter()
        .for_each(|(first_plane, lines, base, parent)| {
            for (i, p) in parent.iter_mut().enumerate() {
                *p = i as u32;
            }
            let mut index = LineIndex::fits(y, z).then(|| LineIndex::new(y, z));
            for li in lines {
                let first = |plane| plane > first_plane;
                join_line((runs, y, conn), li, first, index.as_ref(), base, parent);
                if let Some(index) = index.as_mut() {
                    index.record(runs, li);
                }
            }
            for p in parent.iter_mut() {
                *p += base as u32;
            }
        });
    // The seams: each slab's first plane against the last plane of the slab before it.
    for (first_plane, lines) in slabs.iter().skip(1) {
        let seam = runs.lines_between((first_plane * y) as u64, ((first_plane + 1) * y) as u64);
        for li in seam.start.max(lines.start)..seam.end.min(lines.end) {
            let seam = |plane| plane == *first_plane;
            join_line((runs, y, conn), li, seam, None, 0, &mut parent);
        }
    }
    parent
}

/// Joins the runs of `lines[li]` with those of its earlier neighbour lines; neighbours in the
/// previous plane only if `previous_plane_ok(this plane)`. With an `index` holding every
/// earlier line of this plane and the previous one, touching runs are looked up; otherwise
/// found by a sweep. `parent` holds runs from `base` on.
fn join_line(
    (runs, y, conn): (&Runs, usize, Connectivity),
    li: usize,
    previous_plane_ok: impl Fn(usize) -> bool,
    index: Option<&LineIndex>,
    base: usize,
    parent: &mut [u32],
) {
    let (neighbours, reach) = conn.neighbours();
    let line = runs.lines[li];
    let (lx, ly) = ((line / y as u64) as usize, (line % y as u64) as i64);
    let mine = runs.offsets[li]..runs.offsets[li + 1];
    for &(dx, dy) in neighbours {
        let ny = ly + dy;
        let wanted = if dx == 1 {
            previous_plane_ok(lx) && lx > 0
        } else {
            true
        };
        if !wanted || ny < 0 || ny >= y as i64 {
            continue;
        }
        let other = ((lx - dx as usize) * y) as u64 + ny as u64;
        let theirs = runs.of_line(other);
        if theirs.is_empty() {
            continue;
        }
        match index {
            Some(index) => {
                let first_after = index.line(other);
                join_indexed(runs, mine.clone(), theirs, first_after, reach, base, parent);
            }
            None => join_touching(runs, mine.clone(), theirs, reach, base, parent),
        }
    }
}

/// Like [`join_touching`], but finds the first run of `theirs` that can touch each run of
/// `mine` directly: `first_after[z]` is the first run of that line ending after cell `z`.
/// One data-dependent branch per run instead of one per sweep step.
fn join_indexed(
    runs: &Runs,
    mine: std::ops::Range<usize>,
    theirs: std::ops::Range<usize>,
    first_after: &[u32],
    reach: u32,
    base: usize,
    parent: &mut [u32],
) {
    for i in mine {
        let (a0, a1) = runs.spans[i];
        // Touching: b1 > a0 - reach (the lookup) and b0 < a1 + reach (the loop test).
        let mut t = first_after[a0.saturating_sub(reach) as usize] as usize;
        while t < theirs.end && runs.spans[t].0 < a1 + reach {
            union(parent, (i - base) as u32, (t - base) as u32);
            t += 1;
        }
    }
}

/// For the lines of two consecutive x planes, the first run ending after each cell; a
/// line's entry is written once its own runs have been joined and read by later lines.
struct LineIndex {
    first_after: Vec<u32>,
    y: usize,
    z: usize,
}

impl LineIndex {
    /// Whether two planes of `u32` per cell stay small (8 MiB) and lines short enough to
    /// index cell by cell.
    fn fits(y: usize, z: usize) -> bool {
        z <= 4096 && y.saturating_mul(z) <= 1 << 20
    }

    fn new(y: usize, z: usize) -> LineIndex {
        LineIndex {
            first_after: vec![0; 2 * y * z],
            y,
            z,
        }
    }

    fn slot(&self, line: u64) -> usize {
        let (x, y) = (
            (line / self.y as u64) as usize,
            (line % self.y as u64) as usize,
        );
        ((x % 2) * self.y + y) * self.z
    }

    fn line(&self, line: u64) -> &[u32] {
        let at = self.slot(line);
        &self.first_after[at..at + self.z]
    }

    /// Writes the entry of `lines[li]`, replacing that of the line two planes back.
    fn record(&mut self, runs: &Runs, li: usize) {
        let at = self.slot(runs.lines[li]);
        let cells = &mut self.first_after[at..at + self.z];
        let mut z = 0;
        for t in runs.offsets[li]..runs.offsets[li + 1] {
            let end = runs.spans[t].1 as usize;
            cells[z..end].fill(t as u32);
            z = end;
        }
        cells[z..].fill(runs.offsets[li + 1] as u32);
    }
}

/// Unions every run of `mine` with every run of `theirs` it touches (z ranges overlapping, or
/// for `reach = 1` also meeting diagonally). Both lists are sorted and disjoint, so one sweep
/// that advances whichever run ends first finds all touching pairs.
fn join_touching(
    runs: &Runs,
    mine: std::ops::Range<usize>,
    theirs: std::ops::Range<usize>,
    reach: u32,
    base: usize,
    parent: &mut [u32],
) {
    let (mut i, mut j) = (mine.start, theirs.start);
    while i < mine.end && j < theirs.end {
        let (a0, a1) = runs.spans[i];
        let (b0, b1) = runs.spans[j];
        if b0 < a1 + reach && a0 < b1 + reach {
            union(parent, (i - base) as u32, (j - base) as u32);
        }
        let mine_ends_first = a1 < b1;
        i += mine_ends_first as usize;
        j += !mine_ends_first as usize;
    }
}

/// Joins the trees of `x` and `y` under the smaller root (Rem's algorithm with splicing):
/// both paths are climbed together, each step re-pointing the node with the larger parent to
/// the smaller parent, until they meet or one reaches its root. Keeps `parent[i] <= i`.
fn union(parent: &mut [u32], mut x: u32, mut y: u32) {
    loop {
        let (px, py) = (parent[x as usize], parent[y as usize]);
        if px == py {
            return;
        }
        if px > py {
            parent[x as usize] = py;
            if x == px {
                return;
            }
            x = px;
        } else {
            parent[y as usize] = px;
            if y == py {
                return;
            }
            y = py;
        }
    }
}
