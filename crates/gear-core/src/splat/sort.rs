//! Stable least-significant-digit radix sort of `(u32 key, u32 value)` pairs on the GPU,
//! sorting only the low `bits` bits of the keys.
//!
//! Each pass gives every thread a contiguous chunk of pairs: the thread counts its digits
//! (radix_count), one exclusive scan over the digit-major counts yields every (digit, thread)
//! its output slot, and the thread moves its pairs in order (radix_scatter). Serial work per
//! thread suits a software adapter (no barriers, no shared memory) and is stable by design.

use bytemuck::{Pod, Zeroable};

use crate::error::Result;
use crate::gpu::{GpuContext, PooledBuffer};

use super::kernels::{self, dispatch, groups, storage, uniform, SORT_WG};
use super::scan::encode_exclusive_scan;

/// Widest digit of one pass.
const MAX_DIGIT_BITS: u32 = 8;
/// Fewest pairs per thread (small inputs do not need more threads than this gives).
const MIN_CHUNK: u32 = 256;
/// Most threads per pass: bounds the counts array (threads x 2^digit bits) and its scan.
const MAX_THREADS: u32 = 2048;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct SortParams {
    n: u32,
    shift: u32,
    chunk: u32,
    threads: u32,
}

/// Pairs to sort: `keys` and `values` hold `n` elements each.
pub struct Pairs {
    pub keys: PooledBuffer,
    pub values: PooledBuffer,
}

/// Records a stable sort of `pairs` by the low `bits` bits of the keys and returns the buffers
/// that hold the result (the inputs are used as ping-pong space). Temporaries go to `keep`.
pub fn encode_radix_sort(
    ctx: &'static GpuContext,
    encoder: &mut wgpu::CommandEncoder,
    pairs: Pairs,
    n: u32,
    bits: u32,
    keep: &mut Vec<PooledBuffer>,
) -> Result<Pairs> {
    if n <= 1 || bits == 0 {
        return Ok(pairs);
    }
    let passes = bits.div_ceil(MAX_DIGIT_BITS);
    let digit_bits = bits.div_ceil(passes);
    let chunk = n.div_ceil(MAX_THREADS).max(MIN_CHUNK);
    let threads = n.div_ceil(chunk);
    let hist = ctx.storage::<u32>((threads << digit_bits) as usize)?;
    let mut current = pairs;
    let mut spare = Pairs {
        keys: ctx.storage::<u32>(n as usize)?,
        values: ctx.storage::<u32>(n as usize)?,
    };
    for pass in 0..passes {
        let params = uniform(
            ctx,
            &SortParams {
                n,
                shift: pass * digit_bits,
                chunk,
                threads,
            },
        );
        dispatch(
            ctx,
            encoder,
            &kernels::radix_count(digit_bits),
            &[
                (0, storage(&current.keys)),
                (1, storage(&hist)),
                (2, params.as_entire_binding()),
            ],
            groups(threads, SORT_WG),
        );
        encode_exclusive_scan(ctx, encoder, &hist, threads << digit_bits, keep)?;
        dispatch(
            ctx,
            encoder,
            &kernels::radix_scatter(digit_bits),
            &[
                (0, storage(&current.keys)),
                (1, storage(&current.values)),
                (2, storage(&hist)),
                (3, storage(&spare.keys)),
                (4, storage(&spare.values)),
                (5, params.as_entire_binding()),
            ],
            groups(threads, SORT_WG),
        );
        std::mem::swap(&mut current, &mut spare);
    }
    keep.extend([hist, spare.keys, spare.values]);
    Ok(current)
}

/// Bits needed to represent every value below `count` (0 when count <= 1).
pub fn bits_for(count: u32) -> u32 {
    u32::BITS - count.saturating_sub(1).leading_zeros()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gpu_sort(keys: &[u32], bits: u32) -> (Vec<u32>, Vec<u32>) {
        let ctx = GpuContext::global().unwrap();
        let values: Vec<u32> = (0..keys.len() as u32).collect();
        let pairs = Pairs {
            keys: ctx.upload(keys).unwrap(),
            values: ctx.upload(&values).unwrap(),
        };
        let mut keep = Vec::new();
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        let sorted =
            encode_radix_sort(ctx, &mut encoder, pairs, keys.len() as u32, bits, &mut keep)
                .unwrap();
        ctx.queue.submit(Some(encoder.finish()));
        (
            ctx.read::<u32>(&sorted.keys, keys.len()).unwrap(),
            ctx.read::<u32>(&sorted.values, keys.len()).unwrap(),
        )
    }

    #[test]
    fn sorts_stably_by_the_requested_bits() {
        for (len, bits) in [(2usize, 1u32), (1000, 5), (5000, 12), (300_000, 32)] {
            let mask = if bits == 32 {
                u32::MAX
            } else {
                (1 << bits) - 1
            };
            // Few distinct keys, so stability is exercised; high bits above `bits` are noise
            // that must be ignored... except with 32 bits, where every bit counts.
            let keys: Vec<u32> = (0..len as u64)
                .map(|i| ((i * 2_654_435_761) % 4_294_967_291) as u32)
                .map(|k| if bits == 32 { k % 977 * 4_000_000 } else { k })
                .collect();
            let (got_keys, got_values) = gpu_sort(&keys, bits);
            let mut expected: Vec<u32> = (0..len as u32).collect();
            expected.sort_by_key(|&i| keys[i as usize] & mask); // std sort is stable
            assert_eq!(got_values, expected, "len {len} bits {bits}");
            let expected_keys: Vec<u32> = expected.iter().map(|&i| keys[i as usize]).collect();
            assert_eq!(got_keys, expected_keys);
        }
    }

    #[test]
    fn bits_cover_the_range() {
        assert_eq!(bits_for(0), 0);
        assert_eq!(bits_for(1), 0);
        assert_eq!(bits_for(2), 1);
        assert_eq!(bits_for(256), 8);
        assert_eq!(bits_for(257), 9);
    }
}
