//! Occupied voxels grouped into runs: maximal stretches along z of one line `x * Y + y`.
//! Runs are the unit of connected-component labelling; a random grid at 30% occupancy has
//! about a fifth as many runs as cells, a solid object far fewer.

use rayon::prelude::*;

pub(super) struct Runs {
    /// Non-empty lines, increasing.
    pub lines: Vec<u64>,
    /// Runs of `lines[i]` are `spans[offsets[i]..offsets[i + 1]]`.
    pub offsets: Vec<usize>,
    /// `[z0, z1)` of each run, in key order.
    pub spans: Vec<(u32, u32)>,
    /// Direct lookup, when cheap enough: the runs of line id `L` (empty or not) are
    /// `spans[table[L]..table[L + 1]]`, one entry per line of the grid plus one.
    table: Option<Vec<u32>>,
}

/// The runs of one x plane, with offsets local to the plane.
struct PlaneRuns {
    lines: Vec<u64>,
    ends: Vec<usize>,
    spans: Vec<(u32, u32)>,
}

impl Runs {
    /// Runs of a dense occupancy (C order, `shape`); planes are scanned in parallel.
    pub fn from_dense(occ: &[bool], [x, y, z]: [usize; 3]) -> Runs {
        let bytes = as_bytes(occ);
        let planes: Vec<PlaneRuns> = if y * z == 0 {
            Vec::new()
        } else {
            bytes
                .par_chunks(y * z)
                .enumerate()
                .map(|(plane, cells)| {
                    let mut runs = PlaneRuns {
                        lines: Vec::new(),
                        ends: Vec::new(),
                        spans: Vec::new(),
                    };
                    for (j, line) in cells.chunks(z).enumerate() {
                        let before = runs.spans.len();
                        push_spans(line, &mut runs.spans);
                        if runs.spans.len() > before {
                            runs.lines.push((plane * y + j) as u64);
                            runs.ends.push(runs.spans.len());
                        }
                    }
                    runs
                })
                .collect()
        };
        let mut runs = Runs {
            lines: Vec::with_capacity(planes.iter().map(|p| p.lines.len()).sum()),
            offsets: vec![0],
            spans: Vec::with_capacity(planes.iter().map(|p| p.spans.len()).sum()),
            table: None,
        };
        for plane in planes {
            let base = runs.spans.len();
            runs.lines.extend_from_slice(&plane.lines);
            runs.offsets.extend(plane.ends.iter().map(|e| base + e));
            runs.spans.extend_from_slice(&plane.spans);
        }
        runs.with_table(x * y)
    }

    /// Runs of a sparse occupancy (sorted, distinct keys) in a grid of `shape`.
    pub fn from_keys(keys: &[i64], [x, y, z]: [usize; 3]) -> Runs {
        let z = z as i64;
        let mut runs = Runs {
            lines: Vec::new(),
            offsets: vec![0],
            spans: Vec::new(),
            table: None,
        };
        let mut prev = i64::MIN;
        for &key in keys {
            let (line, k) = ((key / z) as u64, (key % z) as u32);
            let same_line = runs.lines.last() == Some(&line);
            if same_line && key == prev + 1 {
                runs.spans.last_mut().expect("the line has a run").1 = k + 1;
            } else {
                if !same_line {
                    if !runs.lines.is_empty() {
                        runs.offsets.push(runs.spans.len());
                    }
                    runs.lines.push(line);
                }
                runs.spans.push((k, k + 1));
            }
            prev = key;
        }
        if !runs.lines.is_empty() {
            runs.offsets.push(runs.spans.len());
        }
        runs.with_table(x.saturating_mul(y))
    }

    fn with_table(mut self, line_count: usize) -> Runs {
        assert!(
            self.spans.len() < u32::MAX as usize,
            "too many runs for u32 indices"
        );
        // A direct table when it costs at most a few words per run; else binary search.
        if line_count <= 4 * self.spans.len() + 4096 {
            let mut table = Vec::with_capacity(line_count + 1);
            for (li, &line) in self.lines.iter().enumerate() {
                table.resize(line as usize + 1, self.offsets[li] as u32);
            }
            table.resize(line_count + 1, self.spans.len() as u32);
            self.table = Some(table);
        }
        self
    }

    pub fn len(&self) -> usize {
        self.spans.len()
    }

    /// Run index range of line `line` (empty if the line has no runs).
    #[inline]
    pub fn of_line(&self, line: u64) -> std::ops::Range<usize> {
        match &self.table {
            Some(t) => t[line as usize] as usize..t[line as usize + 1] as usize,
            None => match self.lines.binary_search(&line) {
                Ok(li) => self.offsets[li]..self.offsets[li + 1],
                Err(_) => 0..0,
            },
        }
    }

    /// Range of `lines` indices whose line id lies in `[first, end)`.
    pub fn lines_between(&self, first: u64, end: u64) -> std::ops::Range<usize> {
        self.lines.partition_point(|&l| l < first)..self.lines.partition_point(|&l| l < end)
    }
}

/// Appends the maximal runs of set bytes in `line`, 64 cells at a time as a bit mask.
fn push_spans(line: &[u8], spans: &mut Vec<(u32, u32)>) {
    let mut open: Option<usize> = None;
    for (block, cells) in line.chunks(64).enumerate() {
        let (offset, width) = (block * 64, cells.len() as u32);
        let mask = occupied_bits(cells);
        let mut pos = 0u32;
        while pos < width {
            let from = u64::MAX << pos;
            match open {
                None => {
                    let ones = mask & from;
                    if ones == 0 {
                        break;
                    }
                    pos = ones.trailing_zeros();
                    open = Some(offset + pos as usize);
                }
                Some(start) => {
                    let end = (!mask & from).trailing_zeros().min(width);
                    if end == width {
                        break; // the run goes on into the next block
                    }
                    spans.push((start as u32, offset as u32 + end));
                    open = None;
                    pos = end;
                }
            }
        }
    }
    if let Some(start) = open {
        spans.push((start as u32, line.len() as u32));
    }
}

/// Bit `i` set iff `cells[i]` is non-zero (at most 64 cells of 0/1 bytes).
#[inline]
fn occupied_bits(cells: &[u8]) -> u64 {
    let mut mask = 0u64;
    for (w, bytes) in cells.chunks(8).enumerate() {
        let mut word = [0u8; 8];
        word[..bytes.len()].copy_from_slice(bytes);
        // Each 0/1 byte i of the little-endian word lands on bit 56 + i of the product.
        let gathered = u64::from_le_bytes(word).wrapping_mul(0x0102_0408_1020_4080) >> 56;
        mask |= gathered << (8 * w);
    }
    mask
}

fn as_bytes(occ: &[bool]) -> &[u8] {
    // SAFETY: `bool` is one byte holding 0 or 1, always a valid `u8`; same length and lifetime.
    unsafe { std::slice::from_raw_parts(occ.as_ptr().cast(), occ.len()) }
}
