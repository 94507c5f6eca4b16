//! Exclusive prefix sum of a `u32` GPU buffer, in place, recorded into an encoder.
//!
//! Level one scans blocks of `SCAN_WG * SCAN_ITEMS` elements and collects block totals; the
//! totals are scanned the same way (recursively) and added back.

use crate::error::Result;
use crate::gpu::{GpuContext, PooledBuffer};

use super::kernels::{
    self, dispatch, groups, storage, uniform, KernelParams, ScanParams, SCAN_ITEMS, SCAN_WG, WG,
};

/// Records an exclusive scan of the first `n` elements of `data`. Temporaries are pushed to
/// `keep` and must outlive the submission of `encoder`.
pub fn encode_exclusive_scan(
    ctx: &'static GpuContext,
    encoder: &mut wgpu::CommandEncoder,
    data: &PooledBuffer,
    n: u32,
    keep: &mut Vec<PooledBuffer>,
) -> Result<()> {
    if n == 0 {
        return Ok(());
    }
    let blocks = n.div_ceil(SCAN_WG * SCAN_ITEMS);
    let block_sums = ctx.storage::<u32>(blocks as usize)?;
    let params = uniform(ctx, &ScanParams { n, blocks });
    dispatch(
        ctx,
        encoder,
        &kernels::scan_block(),
        &[
            (0, storage(data)),
            (1, storage(&block_sums)),
            (ScanParams::BINDING, params.as_entire_binding()),
        ],
        blocks,
    );
    if blocks > 1 {
        encode_exclusive_scan(ctx, encoder, &block_sums, blocks, keep)?;
        dispatch(
            ctx,
            encoder,
            &kernels::scan_add(),
            &[
                (0, storage(data)),
                (1, storage(&block_sums)),
                (ScanParams::BINDING, params.as_entire_binding()),
            ],
            groups(n, WG),
        );
    }
    keep.push(block_sums);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gpu_scan(values: &[u32]) -> Vec<u32> {
        let ctx = GpuContext::global().unwrap();
        let data = ctx.upload(values).unwrap();
        let mut keep = Vec::new();
        let mut encoder = ctx.device.create_command_encoder(&Default::default());
        encode_exclusive_scan(ctx, &mut encoder, &data, values.len() as u32, &mut keep).unwrap();
        ctx.queue.submit(Some(encoder.finish()));
        ctx.read::<u32>(&data, values.len()).unwrap()
    }

    #[test]
    fn matches_a_serial_scan_across_levels() {
        // Lengths straddle one block (1024) and force a second and third level.
        for len in [1usize, 5, 1023, 1024, 1025, 70_001, 1_100_000] {
            let values: Vec<u32> = (0..len)
                .map(|i| ((i * 2_654_435_761) >> 7) as u32 % 9)
                .collect();
            let mut expected = Vec::with_capacity(len);
            let mut running = 0u32;
            for v in &values {
                expected.push(running);
                running += v;
            }
            assert_eq!(gpu_scan(&values), expected, "length {len}");
        }
    }
}
