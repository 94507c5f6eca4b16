//! Connected components of occupied voxels (6- or 26-connectivity), labelled by size.
//!
//! Occupied cells are first grouped into runs: maximal stretches along z of one `(x, y)` line.
//! Runs of a line can only touch runs of the four earlier neighbouring lines (two for
//! 6-connectivity), found by a merge-like sweep, and are joined in a union-find whose root is
//! always the smallest run index. Runs are in key order, so each component's root is its first
//! voxel in C order, which breaks ties between equal sizes. Dense and sparse inputs share all
//! of this; only the run extraction and the output layout differ.

use rayon::prelude::*;

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
                let lines = runs.lines.partition_point(|&l| l < first)
                    ..runs.lines.partition_point(|&l| l < first + y as u64);
                for li in lines {
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
    let runs = Runs::from_keys(keys, shape[2]);
    let (run_labels, sizes) = label_runs(&runs, shape, conn);
    let mut labels = Vec::with_capacity(keys.len());
    for (ri, &(z0, z1)) in runs.spans.iter().enumerate() {
        labels.extend(std::iter::repeat_n(run_labels[ri], (z1 - z0) as usize));
    }
    Components { labels, sizes }
}

/// A line and its runs.
type LineSpans = (u64, Vec<(u32, u32)>);

/// Occupied runs grouped by line; a line is `x * Y + y`, listed only if it has runs.
struct Runs {
    /// Non-empty lines, increasing.
    lines: Vec<u64>,
    /// Runs of `lines[i]` are `spans[offsets[i]..offsets[i + 1]]`.
    offsets: Vec<usize>,
    /// `[z0, z1)` of each run, in key order.
    spans: Vec<(u32, u32)>,
}

impl Runs {
    fn from_dense(occ: &[bool], [_, y, z]: [usize; 3]) -> Runs {
        if y * z == 0 {
            return Runs::from_parts(Vec::new());
        }
        // Planes in parallel, each giving (line, spans) pairs, then concatenated in order.
        let planes: Vec<Vec<LineSpans>> = occ
            .par_chunks(y * z)
            .enumerate()
            .map(|(plane, cells)| {
                cells
                    .chunks(z)
                    .enumerate()
                    .filter_map(|(j, line)| {
                        let spans = line_spans(line);
                        (!spans.is_empty()).then(|| ((plane * y + j) as u64, spans))
                    })
                    .collect()
            })
            .collect();
        Runs::from_parts(planes.into_iter().flatten().collect())
    }

    fn from_keys(keys: &[i64], z: usize) -> Runs {
        let z = z as i64;
        let mut lines = Vec::new();
        let mut offsets = vec![0];
        let mut spans: Vec<(u32, u32)> = Vec::new();
        let mut prev = i64::MIN;
        for &key in keys {
            let (line, k) = ((key / z) as u64, (key % z) as u32);
            if key == prev + 1 && lines.last() == Some(&line) {
                spans.last_mut().expect("a run is open").1 = k + 1;
            } else {
                if lines.last() != Some(&line) {
                    if !lines.is_empty() {
                        offsets.push(spans.len());
                    }
                    lines.push(line);
                }
                spans.push((k, k + 1));
            }
            prev = key;
        }
        offsets.push(spans.len());
        if lines.is_empty() {
            offsets.truncate(1);
        }
        Runs {
            lines,
            offsets,
            spans,
        }
    }

    fn from_parts(parts: Vec<LineSpans>) -> Runs {
        let mut lines = Vec::with_capacity(parts.len());
        let mut offsets = Vec::with_capacity(parts.len() + 1);
        offsets.push(0);
        let mut spans = Vec::with_capacity(parts.iter().map(|(_, s)| s.len()).sum());
        for (line, s) in parts {
            lines.push(line);
            spans.extend_from_slice(&s);
            offsets.push(spans.len());
        }
        Runs {
            lines,
            offsets,
            spans,
        }
    }

    /// Run index range of line `line`, empty if the line has no runs.
    fn of_line(&self, line: u64, before: usize) -> std::ops::Range<usize> {
        match self.lines[..before].binary_search(&line) {
            Ok(li) => self.offsets[li]..self.offsets[li + 1],
            Err(_) => 0..0,
        }
    }
}

/// Maximal runs of `true` in one line.
fn line_spans(line: &[bool]) -> Vec<(u32, u32)> {
    let mut spans = Vec::new();
    let mut k = 0;
    while k < line.len() {
        match line[k..].iter().position(|&b| b) {
            None => break,
            Some(off) => {
                let start = k + off;
                let len = line[start..]
                    .iter()
                    .position(|&b| !b)
                    .unwrap_or(line.len() - start);
                spans.push((start as u32, (start + len) as u32));
                k = start + len;
            }
        }
    }
    spans
}

/// The label of every run and the component sizes, largest first.
fn label_runs(runs: &Runs, [_, y, _]: [usize; 3], conn: Connectivity) -> (Vec<i32>, Vec<i64>) {
    let y = y as u64;
    // Earlier lines a run can touch, as (dx, dy), and how far along z a touch may reach.
    let (neighbours, reach): (&[(u64, i64)], u32) = match conn {
        Connectivity::Six => (&[(1, 0), (0, -1)], 0),
        Connectivity::TwentySix => (&[(1, -1), (1, 0), (1, 1), (0, -1)], 1),
    };
    let mut parent: Vec<u32> = (0..runs.spans.len() as u32).collect();
    for (li, &line) in runs.lines.iter().enumerate() {
        let (lx, ly) = (line / y, line % y);
        let mine = runs.offsets[li]..runs.offsets[li + 1];
        for &(dx, dy) in neighbours {
            let ny = ly as i64 + dy;
            if dx > lx || ny < 0 || ny >= y as i64 {
                continue;
            }
            let theirs = runs.of_line((lx - dx) * y + ny as u64, li);
            join_touching(runs, mine.clone(), theirs, reach, &mut parent);
        }
    }

    // Roots are the smallest index of their tree, so one forward pass flattens every tree.
    for i in 0..parent.len() {
        parent[i] = parent[parent[i] as usize];
    }
    let mut size = vec![0i64; parent.len()];
    for (i, &(z0, z1)) in runs.spans.iter().enumerate() {
        size[parent[i] as usize] += i64::from(z1 - z0);
    }
    let mut roots: Vec<u32> = (0..parent.len() as u32)
        .filter(|&i| parent[i as usize] == i)
        .collect();
    roots.sort_by_key(|&r| (std::cmp::Reverse(size[r as usize]), r));
    let mut root_label = vec![0i32; parent.len()];
    for (rank, &r) in roots.iter().enumerate() {
        root_label[r as usize] = rank as i32 + 1;
    }
    let labels = parent.iter().map(|&p| root_label[p as usize]).collect();
    let sizes = roots.iter().map(|&r| size[r as usize]).collect();
    (labels, sizes)
}

/// Unions every run of `mine` with every run of `theirs` it touches (z ranges overlapping, or
/// for `reach = 1` also meeting diagonally). Both lists are sorted and disjoint, so one sweep
/// that advances whichever run ends first finds all touching pairs.
fn join_touching(
    runs: &Runs,
    mine: std::ops::Range<usize>,
    theirs: std::ops::Range<usize>,
    reach: u32,
    parent: &mut [u32],
) {
    let (mut i, mut j) = (mine.start, theirs.start);
    while i < mine.end && j < theirs.end {
        let (a0, a1) = runs.spans[i];
        let (b0, b1) = runs.spans[j];
        if b0 < a1 + reach && a0 < b1 + reach {
            union(parent, i as u32, j as u32);
        }
        if a1 < b1 {
            i += 1;
        } else {
            j += 1;
        }
    }
}

fn find(parent: &mut [u32], mut i: u32) -> u32 {
    while parent[i as usize] != i {
        let grand = parent[parent[i as usize] as usize];
        parent[i as usize] = grand;
        i = grand;
    }
    i
}

/// Joins two trees under the smaller root, keeping `parent[i] <= i` everywhere.
fn union(parent: &mut [u32], a: u32, b: u32) {
    let (ra, rb) = (find(parent, a), find(parent, b));
    if ra < rb {
        parent[rb as usize] = ra;
    } else if rb < ra {
        parent[ra as usize] = rb;
    }
}
