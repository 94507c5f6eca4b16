//! Morphological dilation by a cube of side `2r + 1`, clipped to the grid.
//!
//! The cube is separable: dilating along z, then y, then x by `r` gives the full cube, and
//! because the grid is convex, clipping after each axis loses nothing.

use rayon::prelude::*;

use crate::error::{GearError, Result};

/// Most keys (8 bytes each) a sparse dilation may produce in one axis pass: 1 GiB.
const MAX_SPARSE_KEYS: usize = 1 << 27;

/// Dense dilation of `occ` (C order, `shape`) by `radius` voxels. Along x and y each output
/// row ORs up to `2 * radius + 1` input rows, so the cost grows with the radius (meant for
/// the small radii of the coarse initialisation); along z it does not.
pub fn dilate_dense(occ: &[bool], shape: [usize; 3], radius: usize) -> Vec<bool> {
    let [x, y, z] = shape;
    assert_eq!(occ.len(), x * y * z, "occupancy does not match its shape");
    if radius == 0 || occ.is_empty() {
        return occ.to_vec();
    }
    let mut along_z = vec![false; occ.len()];
    along_z
        .par_chunks_mut(z)
        .zip(occ.par_chunks(z))
        .for_each(|(out, line)| dilate_line(line, out, radius));
    let mut along_y = vec![false; occ.len()];
    dilate_rows(&along_z, &mut along_y, y, z, radius);
    let mut along_x = along_z; // reuse the first buffer
    dilate_rows(&along_y, &mut along_x, x, y * z, radius);
    along_x
}

/// 1-D dilation of a contiguous line with a sliding count of the set cells in the window.
fn dilate_line(line: &[bool], out: &mut [bool], r: usize) {
    let n = line.len();
    let mut count: usize = line[..(r + 1).min(n)].iter().map(|&b| b as usize).sum();
    for i in 0..n {
        out[i] = count > 0;
        if i + r + 1 < n {
            count += line[i + r + 1] as usize;
        }
        if i >= r {
            count -= line[i - r] as usize;
        }
    }
}

/// Dilation along an outer axis: the array is `[.., len, row]` and output row `i` is the OR of
/// input rows `i - r ..= i + r` in the same block. Rows are contiguous, so the ORs vectorise.
fn dilate_rows(input: &[bool], out: &mut [bool], len: usize, row: usize, r: usize) {
    out.par_chunks_mut(row).enumerate().for_each(|(ri, dst)| {
        let (block, i) = (ri / len, ri % len);
        let base = block * len;
        let rows = i.saturating_sub(r)..(i + r + 1).min(len);
        dst.copy_from_slice(&input[(base + rows.start) * row..][..row]);
        for j in rows.skip(1) {
            for (d, &s) in dst.iter_mut().zip(&input[(base + j) * row..][..row]) {
                *d |= s;
            }
        }
    });
}

/// Sparse dilation of sorted keys in a grid of `shape` by `radius` voxels; sorted output.
///
/// Fails (naming `radius`) if an axis pass could emit more than 2^27 keys.
pub fn dilate_keys(keys: &[i64], shape: [usize; 3], radius: usize) -> Result<Vec<i64>> {
    let [_, y, z] = shape;
    let mut current = keys.to_vec();
    if radius == 0 {
        return Ok(current);
    }
    for (len, stride) in [(z, 1), (y, z), (shape[0], y * z)] {
        let r = radius.min(len.saturating_sub(1));
        let emitted = current.len().saturating_mul(2 * r + 1);
        if emitted > MAX_SPARSE_KEYS {
            return Err(GearError::InvalidInput(format!(
                "radius: dilating {} voxels by {radius} would produce up to {emitted} voxels, \
                 more than the {MAX_SPARSE_KEYS} a sparse grid may hold",
                current.len()
            )));
        }
        let (len, stride) = (len as i64, stride as i64);
        let mut next: Vec<i64> = current
            .par_iter()
            .flat_map_iter(|&key| {
                let c = (key / stride) % len;
                let lo = (c - r as i64).max(0);
                let hi = (c + r as i64).min(len - 1);
                (lo..=hi).map(move |d| key + (d - c) * stride)
            })
            .collect();
        next.par_sort_unstable();
        next.dedup();
        current = next;
    }
    Ok(current)
}
