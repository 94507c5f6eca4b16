//! Sum of an `f32` array on the GPU: the smallest real kernel, used to prove that device,
//! pipeline cache, buffer pool, dispatch folding and readback work end to end.

use crate::error::Result;
use crate::gpu::{workgroup_grid, GpuContext, ShaderSpec};

const WG: u32 = 256;
const ITEMS: u32 = 8;

/// Sum of `values`, reduced on the GPU in rounds of `WG * ITEMS` elements per workgroup.
pub fn sum_f32(values: &[f32]) -> Result<f32> {
    let ctx = GpuContext::global()?;
    if values.is_empty() {
        return Ok(0.0);
    }
    let spec = ShaderSpec::new(
        "reduce_sum",
        include_str!("shaders/reduce_sum.wgsl"),
        "main",
    )
    .with("WG", format!("{WG}u"))
    .with("ITEMS", format!("{ITEMS}u"));
    let pipeline = ctx.pipelines.get(&ctx.device, &spec);

    let mut current = ctx.upload(values)?;
    let mut len = values.len() as u32;
    // All rounds go in one submission; intermediate buffers stay alive until it is done.
    let mut keep_alive = Vec::new();
    let mut encoder = ctx
        .device
        .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("sum") });
    while len > 1 {
        let groups = len.div_ceil(WG * ITEMS);
        let partials = ctx.storage::<f32>(groups as usize)?;
        let params = uniform(ctx, &[len])?;
        let bind = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("sum"),
            layout: &pipeline.get_bind_group_layout(0),
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: current.binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: partials.binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: params.as_entire_binding(),
                },
            ],
        });
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&pipeline);
            pass.set_bind_group(0, &bind, &[]);
            let (x, y, z) = workgroup_grid(groups);
            pass.dispatch_workgroups(x, y, z);
        }
        keep_alive.push(std::mem::replace(&mut current, partials));
        len = groups;
    }
    ctx.queue.submit(Some(encoder.finish()));
    let out = ctx.read::<f32>(&current, 1)?;
    drop(keep_alive);
    Ok(out[0])
}

fn uniform(ctx: &GpuContext, data: &[u32]) -> Result<wgpu::Buffer> {
    use wgpu::util::DeviceExt;
    Ok(ctx
        .device
        .create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("params"),
            contents: bytemuck::cast_slice(data),
            usage: wgpu::BufferUsages::UNIFORM,
        }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cpu_sum(values: &[f32]) -> f64 {
        values.iter().map(|&v| f64::from(v)).sum()
    }

    #[test]
    fn matches_cpu_sum_across_round_boundaries() {
        // Lengths straddle one workgroup's span (2048) and force several rounds.
        for len in [1usize, 7, 2047, 2048, 2049, 100_003, 3_000_000] {
            let values: Vec<f32> = (0..len)
                .map(|i| ((i * 7919) % 1000) as f32 / 997.0 - 0.4)
                .collect();
            let gpu = f64::from(sum_f32(&values).unwrap());
            let cpu = cpu_sum(&values);
            let scale = values
                .iter()
                .map(|v| f64::from(v.abs()))
                .sum::<f64>()
                .max(1.0);
            assert!(
                (gpu - cpu).abs() <= 1e-5 * scale,
                "len {len}: gpu {gpu} cpu {cpu}"
            );
        }
    }

    #[test]
    fn empty_is_zero() {
        assert_eq!(sum_f32(&[]).unwrap(), 0.0);
    }
}
