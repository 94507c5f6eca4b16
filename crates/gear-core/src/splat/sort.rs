//! Stable least-significant-digit radix sort of `(u32 key, u32 value)` pairs on the GPU,
//! sorting only the low `bits` bits of the keys.
//!
//! Each pass gives every thread a contiguous chunk of pairs: the thread counts its digits
//! (radix_count), one exclusive scan over the digit-major counts yields every (digit, thread)
//! its output slot, and the thread moves its pairs in order (radix_scatter). Serial work per
//! thread suits a software adapter (no barriers, no shared memory) and is stable by design.

use crate::error::Result;
use crate::gpu::{GpuContext, PooledBuffer};

use super::kernels::{self, dispatch, groups, storage, uniform, KernelParams, SortParams, SORT_WG};
use super::scan::encode_exclusive_scan;

/// Widest digit of one pass.
const MAX_DIGIT_BITS: u32 = 8;
/// Fewest pairs per thread (small inputs do not need more threads than this gives).
const MIN_CHUNK: u32 = 256;
/// Most threads per pass: bounds the counts array (threads x 2^digit bits) and its scan.
const MAX_THREADS: u32 = 2048;

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
    encode_passes(ctx, encoder, pairs.keys, Some(pairs.values), n, bits, keep)
}

/// Records a stable sort of `keys` by their low `bits` bits; the result's values are the
/// sorting permutation (each element's original position).
pub fn encode_index_sort(
    ctx: &'static GpuContext,
    encoder: &mut wgpu::CommandEncoder,
    keys: PooledBuffer,
    n: u32,
    bits: u32,
    keep: &mut Vec<PooledBuffer>,
) -> Result<Pairs> {
    if n <= 1 || bits == 0 {
        let identity: Vec<u32> = (0..n).collect();
        let values = ctx.upload(&identity)?;
        return Ok(Pairs { keys, values });
    }
    encode_passes(ctx, encoder, keys, None, n, bits, keep)
}

/// The passes of both sorts; `values: None` means "the identity" on the first pass.
fn encode_passes(
    ctx: &'static GpuContext,
    encoder: &mut wgpu::CommandEncoder,
    keys: PooledBuffer,
    values: Option<PooledBuffer>,
    n: u32,
    bits: u32,
    keep: &mut Vec<PooledBuffer>,
) -> Result<Pairs> {
    let passes = bits.div_ceil(MAX_DIGIT_BITS);
    let digit_bits = bits.div_ceil(passes);
    let chunk = n.div_ceil(MAX_THREADS).max(MIN_CHUNK);
    let threads = n.div_ceil(chunk);
    let hist = ctx.storage::<u32>((threads << digit_bits) as usize)?;
    let mut keys = keys;
    let mut spare_keys = ctx.storage::<u32>(n as usize)?;
    // Without input values the first pass generates them (the identity) and binds none;
    // later passes still need two full value buffers to ping-pong.
    let identity_first = values.is_none();
    let mut values = match values {
        Some(v) => v,
        None => ctx.storage::<u32>(n as usize)?,
    };
    let mut spare_values = ctx.storage::<u32>(n as usize)?;
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
                (0, storage(&keys)),
                (1, storage(&hist)),
                (SortParams::BINDING, params.as_entire_binding()),
            ],
            groups(threads, SORT_WG),
        );
        encode_exclusive_scan(ctx, encoder, &hist, threads << digit_bits, keep)?;
        let identity = identity_first && pass == 0;
        let mut bindings = vec![
            (0, storage(&keys)),
            (2, storage(&hist)),
            (3, storage(&spare_keys)),
            (4, storage(&spare_values)),
            (SortParams::BINDING, params.as_entire_binding()),
        ];
        if !identity {
            bindings.push((1, storage(&values)));
        }
        dispatch(
            ctx,
            encoder,
            &kernels::radix_scatter(digit_bits, identity),
            &bindings,
            groups(threads, SORT_WG),
        );
        std::mem::swap(&mut keys, &mut spare_keys);
        std::mem::swap(&mut values, &mut spare_values);
    }
    keep.extend([hist, spare_keys, spare_values]);
    Ok(Pairs { keys, values })
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
    fn index_sort_returns_the_stable_permutation() {
        let ctx = GpuContext::global().unwrap();
        for len in [1usize, 3, 40_000] {
            let keys: Vec<u32> = (0..len as u32)
                .map(|i| (i * 7919) % 1013 * 3_000_000)
                .collect();
            let mut encoder = ctx.device.create_command_encoder(&Default::default());
            let mut keep = Vec::new();
            let sorted = encode_index_sort(
                ctx,
                &mut encoder,
                ctx.upload(&keys).unwrap(),
                len as u32,
                32,
                &mut keep,
            )
            .unwrap();
            ctx.queue.submit(Some(encoder.finish()));
            let mut expected: Vec<u32> = (0..len as u32).collect();
            expected.sort_by_key(|&i| keys[i as usize]);
            assert_eq!(
                ctx.read::<u32>(&sorted.values, len).unwrap(),
                expected,
                "len {len}"
            );
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
