//! Set operations on sparse occupancy (sorted, distinct keys), by linear merges.
//! Dense occupancy needs none: elementwise `&`, `|`, `& !` on the cells do the same.

use std::cmp::Ordering;

/// Keys in both `a` and `b`.
pub fn intersection(a: &[i64], b: &[i64]) -> Vec<i64> {
    merge(a, b, false, true, false)
}

/// Keys in `a` but not in `b`.
pub fn difference(a: &[i64], b: &[i64]) -> Vec<i64> {
    merge(a, b, true, false, false)
}

/// Keys in `a` or `b`.
pub fn union(a: &[i64], b: &[i64]) -> Vec<i64> {
    merge(a, b, true, true, true)
}

/// Walks both sorted lists once, keeping keys only in `a`, in both, or only in `b` as asked.
fn merge(a: &[i64], b: &[i64], only_a: bool, both: bool, only_b: bool) -> Vec<i64> {
    let mut out = Vec::with_capacity(if only_a || only_b {
        a.len() + b.len()
    } else {
        a.len().min(b.len())
    });
    let (mut i, mut j) = (0, 0);
    while i < a.len() && j < b.len() {
        match a[i].cmp(&b[j]) {
            Ordering::Less => {
                if only_a {
                    out.push(a[i]);
                }
                i += 1;
            }
            Ordering::Greater => {
                if only_b {
                    out.push(b[j]);
                }
                j += 1;
            }
            Ordering::Equal => {
                if both {
                    out.push(a[i]);
                }
                i += 1;
                j += 1;
            }
        }
    }
    if only_a {
        out.extend_from_slice(&a[i..]);
    }
    if only_b {
        out.extend_from_slice(&b[j..]);
    }
    out
}
