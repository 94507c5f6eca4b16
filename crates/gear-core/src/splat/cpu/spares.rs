//! Buffers a pass is done with, kept for the next pass. A forward and backward at 90k
//! Gaussians allocate ~20 MB of lists and records; fresh pages from the kernel cost a page
//! fault and a zeroing each, which measured as much as the binning's own work. Refilling a
//! kept buffer costs one pass of stores. A few buffers per kind are kept (enough for the
//! several views a training step renders before its backward); the memory stays with the
//! process, bounded by those few buffers of the largest pass seen.

use std::sync::Mutex;

/// Buffers kept per kind.
const KEPT: usize = 4;

/// Spare vectors of one element type.
pub(super) struct Spares<T> {
    kept: Mutex<Vec<Vec<T>>>,
}

impl<T: Copy> Spares<T> {
    pub const fn new() -> Self {
        Spares {
            kept: Mutex::new(Vec::new()),
        }
    }

    /// `len` copies of `value`, in the smallest kept buffer that holds them (else the
    /// largest, which grows, else a new one).
    pub fn take(&self, len: usize, value: T) -> Vec<T> {
        let found = {
            let mut kept = self.kept.lock().unwrap_or_else(|e| e.into_inner());
            let fits = (0..kept.len())
                .filter(|&i| kept[i].capacity() >= len)
                .min_by_key(|&i| kept[i].capacity());
            let largest = (0..kept.len()).max_by_key(|&i| kept[i].capacity());
            fits.or(largest).map(|i| kept.swap_remove(i))
        };
        match found {
            Some(mut buffer) => {
                buffer.clear();
                buffer.resize(len, value);
                buffer
            }
            None => vec![value; len],
        }
    }

    /// Keeps `buffer` for a later [`Spares::take`] (in place of a smaller one when full).
    pub fn keep(&self, buffer: Vec<T>) {
        if buffer.capacity() == 0 {
            return;
        }
        let mut kept = self.kept.lock().unwrap_or_else(|e| e.into_inner());
        if kept.len() < KEPT {
            kept.push(buffer);
        } else if let Some(i) = (0..kept.len()).min_by_key(|&i| kept[i].capacity()) {
            if kept[i].capacity() < buffer.capacity() {
                kept[i] = buffer;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::Spares;

    /// A kept buffer is reused (same allocation) and refilled whatever it held.
    #[test]
    fn reuses_and_refills() {
        let spares = Spares::<u32>::new();
        let mut first = spares.take(1000, 7);
        assert!(first.iter().all(|&v| v == 7));
        first.iter_mut().for_each(|v| *v = 1);
        let address = first.as_ptr();
        spares.keep(first);
        let again = spares.take(600, 0);
        assert_eq!(again.as_ptr(), address);
        assert_eq!(again.len(), 600);
        assert!(again.iter().all(|&v| v == 0));
    }

    /// The smallest buffer that fits is taken; a full store drops its smallest for a larger.
    #[test]
    fn picks_the_smallest_fit_and_bounds_the_store() {
        let spares = Spares::<u8>::new();
        for size in [10, 400, 200, 50] {
            spares.keep(Vec::with_capacity(size));
        }
        assert!(spares.take(150, 0).capacity() >= 200);
        assert!(spares.take(150, 0).capacity() >= 400);
        spares.keep(Vec::with_capacity(5));
        spares.keep(Vec::with_capacity(1000));
        spares.keep(Vec::with_capacity(900));
        let kept = spares.kept.lock().unwrap();
        let mut capacities: Vec<usize> = kept.iter().map(|b| b.capacity()).collect();
        capacities.sort();
        assert_eq!(capacities.len(), super::KEPT);
        assert!(
            capacities[0] >= 10 && capacities[2] >= 900,
            "{capacities:?}"
        );
    }
}
