//! The rasterizer's WGSL kernels as cached pipelines, and the one way they are dispatched.
//!
//! Every kernel is specialised in its source (see [`ShaderSpec`]): the contract constants
//! always, and `CHANNELS` / `WITH_DEPTH` where the kernel touches features or depth, so a
//! render without depth compiles no depth code.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use wgpu::util::DeviceExt;

use crate::gpu::{workgroup_grid, GpuContext, PooledBuffer, ShaderSpec};

use super::constants::{
    FAR, LOW_PASS, MAX_ALPHA, MIN_ALPHA, MIN_TRANSMITTANCE, NEAR, QUAT_EPS, ROW_LEVEL_MARGIN,
    ROW_SPAN_SLACK,
};

/// Side of the square pixel tiles the GPU kernels sort and blend by. The contract's 16
/// (constants::TILE) only decides which pixels are tested, never a result; on the software
/// adapter, where every pixel of a tile evaluates every Gaussian of the tile's list (divergent
/// branches are masked, not skipped), 8x8 tiles halved forward and backward time at 100k
/// Gaussians (256x256) against 16x16, and 4x4 gained nothing more (twice the pairs to sort).
/// The blend kernels give each thread one tile row as two vec4 quads, so it must be 8.
pub const GPU_TILE: u32 = 8;
const _: () = assert!(
    GPU_TILE == 8,
    "blend.wgsl and blend_backward.wgsl blend rows of 8"
);

/// Tiles per workgroup of the forward blend without subgroups (one thread per tile row):
/// enough threads for a real GPU's wave; on the software adapter each tile's rows fill one
/// SIMD vector. With subgroups a workgroup is one tile, so no subgroup spans two.
const TILE_GROUP: u32 = 8;

/// Tiles per workgroup of [`blend`].
pub fn blend_tile_group(subgroups: bool) -> u32 {
    if subgroups {
        1
    } else {
        TILE_GROUP
    }
}

/// 32-bit words of the counting blend's counters: quad evaluations, row-rule evaluations and
/// contributions, each as (low, high) words.
pub const BLEND_COUNTERS: usize = 6;
/// Binding of the counting blend's counters.
pub const BLEND_COUNTS_BINDING: u32 = 6;

/// Threads per workgroup of the scan's first level, and elements per thread.
pub const SCAN_WG: u32 = 256;
pub const SCAN_ITEMS: u32 = 4;
/// Threads per workgroup of the radix sort passes.
pub const SORT_WG: u32 = 64;
/// Threads per workgroup of the other 1D kernels.
pub const WG: u32 = 256;

/// One WGSL source from files of shaders/splat/ (names without `.wgsl`), in order after
/// grid.wgsl (indices in the folded dispatch grid, which every kernel needs): a file may use
/// what the ones before it declare.
macro_rules! splat_source {
    ($($file:literal),+ $(,)?) => {
        concat!(
            include_str!("../shaders/splat/grid.wgsl"),
            $(include_str!(concat!("../shaders/splat/", $file, ".wgsl"))),+
        )
    };
}

const PROJECT: &str = splat_source!("common", "level", "project_common", "project");
const PROJECT_BACKWARD: &str = splat_source!("common", "project_common", "project_backward");
/// Blend, its rows sharing loads over subgroups (needs the SUBGROUP feature) or not, without
/// or with its work counters.
const BLEND_SUBGROUP: &str = splat_source!(
    "common",
    "level",
    "tile_share_subgroup",
    "blend_common",
    "blend_counts_off",
    "blend"
);
const BLEND_ROWS: &str = splat_source!(
    "common",
    "level",
    "tile_share_rows",
    "blend_common",
    "blend_counts_off",
    "blend"
);
const BLEND_SUBGROUP_COUNTED: &str = splat_source!(
    "common",
    "level",
    "tile_share_subgroup",
    "blend_common",
    "blend_counts_on",
    "blend"
);
const BLEND_ROWS_COUNTED: &str = splat_source!(
    "common",
    "level",
    "tile_share_rows",
    "blend_common",
    "blend_counts_on",
    "blend"
);
/// Blend backward's accumulation (native f32 atomics or compare-and-swap), then how its rows
/// share loads and atomics (over a subgroup, or not at all).
const BLEND_BACKWARD_FLOAT_SUBGROUP: &str = splat_source!(
    "common",
    "level",
    "atomic_float",
    "tile_share_subgroup",
    "blend_common",
    "blend_backward",
);
const BLEND_BACKWARD_FLOAT_ROWS: &str = splat_source!(
    "common",
    "level",
    "atomic_float",
    "tile_share_rows",
    "blend_common",
    "blend_backward",
);
const BLEND_BACKWARD_CAS_SUBGROUP: &str = splat_source!(
    "common",
    "level",
    "atomic_cas",
    "tile_share_subgroup",
    "blend_common",
    "blend_backward",
);
const BLEND_BACKWARD_CAS_ROWS: &str = splat_source!(
    "common",
    "level",
    "atomic_cas",
    "tile_share_rows",
    "blend_common",
    "blend_backward",
);

/// A WGSL f32 literal.
fn f32_literal(v: f64) -> String {
    format!("{:?}f", v as f32)
}

/// `spec` plus every constant of the contract.
fn with_contract(spec: ShaderSpec) -> ShaderSpec {
    spec.with("NEAR", f32_literal(NEAR))
        .with("FAR", f32_literal(FAR))
        .with("LOW_PASS", f32_literal(LOW_PASS))
        .with("MIN_ALPHA", f32_literal(MIN_ALPHA))
        .with("MAX_ALPHA", f32_literal(MAX_ALPHA))
        .with("MIN_TRANSMITTANCE", f32_literal(MIN_TRANSMITTANCE))
        .with("QUAT_EPS", f32_literal(QUAT_EPS))
        .with("TILE", format!("{GPU_TILE}u"))
}

/// What a per-pixel kernel is compiled for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PixelVariant {
    pub channels: usize,
    pub depth: bool,
}

impl PixelVariant {
    fn apply(self, spec: ShaderSpec) -> ShaderSpec {
        with_contract(spec)
            .with("CHANNELS", format!("{}u", self.channels))
            .with("WITH_DEPTH", self.depth)
            .with("ROW_LEVEL_MARGIN", f32_literal(ROW_LEVEL_MARGIN))
            .with("ROW_SPAN_SLACK", f32_literal(ROW_SPAN_SLACK))
    }
}

pub fn project(variant: PixelVariant) -> ShaderSpec {
    let spec = variant.apply(ShaderSpec::new("splat_project", PROJECT, "main"));
    with_workgroup(spec, WG)
}

pub fn project_backward(variant: PixelVariant) -> ShaderSpec {
    let spec = ShaderSpec::new("splat_project_backward", PROJECT_BACKWARD, "main");
    with_workgroup(variant.apply(spec), WG)
}

/// The forward blend, its rows sharing loads over subgroups (needs the SUBGROUP feature) or
/// not; dispatched over `blend_tile_group(subgroups)` tiles per workgroup. With `counting`,
/// the variant that also counts its work into a buffer of [`BLEND_COUNTERS`] words at binding
/// [`BLEND_COUNTS_BINDING`] (blend_counts_on.wgsl); the normal variant calls empty functions
/// in their place (blend_counts_off.wgsl), which the shader compiler removes.
pub fn blend(variant: PixelVariant, subgroups: bool, counting: bool) -> ShaderSpec {
    let (name, source) = match (subgroups, counting) {
        (true, false) => ("splat_blend_sg", BLEND_SUBGROUP),
        (false, false) => ("splat_blend", BLEND_ROWS),
        (true, true) => ("splat_blend_sg_counted", BLEND_SUBGROUP_COUNTED),
        (false, true) => ("splat_blend_counted", BLEND_ROWS_COUNTED),
    };
    variant
        .apply(ShaderSpec::new(name, source, "main"))
        .with("TILE_GROUP", format!("{}u", blend_tile_group(subgroups)))
}

/// Blend backward accumulating with native f32 atomics or with a compare-and-swap loop, the
/// rows of a tile summed over subgroups first (needs the SUBGROUP feature) or not, adding
/// feature gradients only with `features_grad`.
pub fn blend_backward(
    variant: PixelVariant,
    float_atomics: bool,
    subgroups: bool,
    features_grad: bool,
) -> ShaderSpec {
    let (name, source) = match (float_atomics, subgroups) {
        (true, true) => ("splat_blend_backward_f32_sg", BLEND_BACKWARD_FLOAT_SUBGROUP),
        (true, false) => ("splat_blend_backward_f32", BLEND_BACKWARD_FLOAT_ROWS),
        (false, true) => ("splat_blend_backward_cas_sg", BLEND_BACKWARD_CAS_SUBGROUP),
        (false, false) => ("splat_blend_backward_cas", BLEND_BACKWARD_CAS_ROWS),
    };
    variant
        .apply(ShaderSpec::new(name, source, "main"))
        .with("FEATURE_GRADS", features_grad)
}

/// `spec` run by workgroups of `size` threads (the shader's `WG`).
fn with_workgroup(spec: ShaderSpec, size: u32) -> ShaderSpec {
    spec.with("WG", format!("{size}u"))
}

/// Scans blocks of `SCAN_WG * SCAN_ITEMS` elements, one per workgroup.
pub fn scan_block() -> ShaderSpec {
    let spec = ShaderSpec::new("splat_scan_block", splat_source!("scan_block"), "main");
    with_workgroup(spec, SCAN_WG).with("ITEMS", format!("{SCAN_ITEMS}u"))
}

/// Adds the scanned block totals back, one thread per element in workgroups of [`WG`].
pub fn scan_add() -> ShaderSpec {
    let spec = ShaderSpec::new("splat_scan_add", splat_source!("scan_add"), "main");
    with_workgroup(spec, WG).with("BLOCK", format!("{}u", SCAN_WG * SCAN_ITEMS))
}

pub fn radix_count(bits: u32) -> ShaderSpec {
    const SOURCE: &str = splat_source!("radix_common", "radix_count");
    let spec = ShaderSpec::new("splat_radix_count", SOURCE, "main");
    with_workgroup(spec, SORT_WG).with("BITS", format!("{bits}u"))
}

/// The scatter step; `identity_values` makes the payload each element's input position
/// (no values buffer is bound then).
pub fn radix_scatter(bits: u32, identity_values: bool) -> ShaderSpec {
    const FROM_BUFFER: &str = splat_source!("radix_common", "radix_values_buffer", "radix_scatter");
    const IDENTITY: &str = splat_source!("radix_common", "radix_values_identity", "radix_scatter");
    let (name, source) = if identity_values {
        ("splat_radix_scatter_identity", IDENTITY)
    } else {
        ("splat_radix_scatter", FROM_BUFFER)
    };
    with_workgroup(ShaderSpec::new(name, source, "main"), SORT_WG).with("BITS", format!("{bits}u"))
}

pub fn tile_counts() -> ShaderSpec {
    const SOURCE: &str = splat_source!("level", "tile_test", "tile_counts");
    let spec = ShaderSpec::new("splat_tile_counts", SOURCE, "main");
    with_workgroup(spec, WG)
        .with("TILE", format!("{GPU_TILE}u"))
        .with("MIN_ALPHA", f32_literal(MIN_ALPHA))
}

pub fn emit() -> ShaderSpec {
    const SOURCE: &str = splat_source!("level", "tile_test", "emit");
    let spec = ShaderSpec::new("splat_emit", SOURCE, "main");
    with_workgroup(spec, WG)
        .with("TILE", format!("{GPU_TILE}u"))
        .with("MIN_ALPHA", f32_literal(MIN_ALPHA))
}

pub fn tile_ranges() -> ShaderSpec {
    let spec = ShaderSpec::new("splat_tile_ranges", splat_source!("tile_ranges"), "main");
    with_workgroup(spec, WG)
}

/// A kernel's parameter uniform: its Rust layout, and the WGSL struct and group-0 binding the
/// shaders declare it as (the tests compare all three with each shader's reflection).
pub trait KernelParams: Pod {
    /// Name of the WGSL struct with the same layout.
    const WGSL_NAME: &'static str;
    /// Its `@binding` in group 0, in every shader that reads it.
    const BINDING: u32;
}

/// Gaussians counted by tile_counts, and the band's tile rows [tile_y0, tile_y1)
/// (`CountParams` in tile_counts.wgsl).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub struct CountParams {
    pub n: u32,
    pub tile_y0: u32,
    pub tile_y1: u32,
}

impl KernelParams for CountParams {
    const WGSL_NAME: &'static str = "CountParams";
    const BINDING: u32 = 3;
}

/// Gaussians emitting pairs, the tile grid's width and the band's tile rows
/// (`EmitParams` in emit.wgsl).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub struct EmitParams {
    pub n: u32,
    pub tiles_x: u32,
    pub tile_y0: u32,
    pub tile_y1: u32,
}

impl KernelParams for EmitParams {
    const WGSL_NAME: &'static str = "EmitParams";
    const BINDING: u32 = 5;
}

/// Sorted pairs whose tile runs tile_ranges finds (`RangeParams` in tile_ranges.wgsl).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub struct RangeParams {
    pub pairs: u32,
}

impl KernelParams for RangeParams {
    const WGSL_NAME: &'static str = "RangeParams";
    const BINDING: u32 = 2;
}

/// One radix pass, read by both its steps (`SortParams` in radix_common.wgsl).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub struct SortParams {
    pub n: u32,
    pub shift: u32,
    pub chunk: u32,
    pub threads: u32,
}

impl KernelParams for SortParams {
    const WGSL_NAME: &'static str = "SortParams";
    const BINDING: u32 = 5;
}

/// One scan level, read by both its steps (`ScanParams` in scan_block.wgsl, scan_add.wgsl).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub struct ScanParams {
    pub n: u32,
    pub blocks: u32,
}

impl KernelParams for ScanParams {
    const WGSL_NAME: &'static str = "ScanParams";
    const BINDING: u32 = 2;
}

/// A small uniform buffer holding `value`, zero-padded to a multiple of 16 bytes (the
/// granularity of uniform layouts).
pub fn uniform<T: KernelParams>(ctx: &GpuContext, value: &T) -> wgpu::Buffer {
    let mut contents = bytemuck::bytes_of(value).to_vec();
    contents.resize(contents.len().next_multiple_of(16), 0);
    ctx.device
        .create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(T::WGSL_NAME),
            contents: &contents,
            usage: wgpu::BufferUsages::UNIFORM,
        })
}

/// Records one dispatch of `spec` over `workgroups` workgroups (folded into 2D when needed),
/// binding `bindings` as `(binding number, resource)` in group 0.
pub fn dispatch(
    ctx: &GpuContext,
    encoder: &mut wgpu::CommandEncoder,
    spec: &ShaderSpec,
    bindings: &[(u32, wgpu::BindingResource<'_>)],
    workgroups: u32,
) {
    let pipeline: Arc<wgpu::ComputePipeline> = ctx.pipelines.get(&ctx.device, spec);
    let entries: Vec<wgpu::BindGroupEntry<'_>> = bindings
        .iter()
        .map(|(binding, resource)| wgpu::BindGroupEntry {
            binding: *binding,
            resource: resource.clone(),
        })
        .collect();
    let bind = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some(spec.name),
        layout: &pipeline.get_bind_group_layout(0),
        entries: &entries,
    });
    let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
        label: Some(spec.name),
        timestamp_writes: None,
    });
    pass.set_pipeline(&pipeline);
    pass.set_bind_group(0, &bind, &[]);
    let (x, y, z) = workgroup_grid(workgroups);
    pass.dispatch_workgroups(x, y, z);
}

/// Workgroups of `size` threads covering `threads` threads.
pub fn groups(threads: u32, size: u32) -> u32 {
    threads.div_ceil(size)
}

/// A binding of the requested part of `buf`, at least 32 bytes: empty arrays (N = 0, no
/// pairs) must still satisfy the minimum binding size of a vec4 array.
pub fn storage(buf: &PooledBuffer) -> wgpu::BindingResource<'_> {
    wgpu::BindingResource::Buffer(wgpu::BufferBinding {
        buffer: &buf.buffer,
        offset: 0,
        size: wgpu::BufferSize::new(buf.size.max(32)),
    })
}

#[cfg(test)]
mod tests {
    //! The host's declarations against the shaders' own: every kernel variant is compiled by
    //! naga (wgpu's shader compiler) and its parameter uniforms and workgroup size compared
    //! with the Rust structs, bindings and constants the dispatch code uses.

    use std::collections::HashSet;

    use super::super::constants::MAX_CHANNELS;
    use super::super::frame::Frame;
    use super::*;

    /// Every kernel variant the host can dispatch, with the threads per workgroup the host
    /// divides the work by (1D kernels) or lays tiles out for (blend kernels).
    fn every_kernel() -> Vec<(ShaderSpec, u32)> {
        let mut kernels = vec![
            (scan_block(), SCAN_WG),
            (scan_add(), WG),
            (tile_counts(), WG),
            (emit(), WG),
            (tile_ranges(), WG),
        ];
        for bits in [1, 8] {
            kernels.push((radix_count(bits), SORT_WG));
            for identity in [false, true] {
                kernels.push((radix_scatter(bits, identity), SORT_WG));
            }
        }
        for channels in [1, 3, MAX_CHANNELS] {
            for depth in [false, true] {
                let variant = PixelVariant { channels, depth };
                kernels.push((project(variant), WG));
                kernels.push((project_backward(variant), WG));
                for subgroups in [false, true] {
                    let rows = GPU_TILE * blend_tile_group(subgroups);
                    for counting in [false, true] {
                        kernels.push((blend(variant, subgroups, counting), rows));
                    }
                    for float_atomics in [false, true] {
                        for features_grad in [false, true] {
                            let spec =
                                blend_backward(variant, float_atomics, subgroups, features_grad);
                            kernels.push((spec, GPU_TILE));
                        }
                    }
                }
            }
        }
        kernels
    }

    /// `(WGSL struct name, binding, size in bytes)` of a parameter uniform as the host has it.
    fn host_params<T: KernelParams>() -> (&'static str, u32, u32) {
        (T::WGSL_NAME, T::BINDING, std::mem::size_of::<T>() as u32)
    }

    #[test]
    fn params_and_workgroup_sizes_match_the_shaders() {
        let declared = [
            host_params::<Frame>(),
            host_params::<CountParams>(),
            host_params::<EmitParams>(),
            host_params::<RangeParams>(),
            host_params::<SortParams>(),
            host_params::<ScanParams>(),
        ];
        let mut seen = HashSet::new();
        for (spec, threads) in every_kernel() {
            let label = format!("{} {:?}", spec.name, spec.constants);
            let module = naga::front::wgsl::parse_str(&spec.specialised_source())
                .unwrap_or_else(|e| panic!("{label}: {e}"));
            let mut layouter = naga::proc::Layouter::default();
            layouter.update(module.to_ctx()).unwrap();

            let mut bindings = HashSet::new();
            for (_, global) in module.global_variables.iter() {
                let Some(binding) = &global.binding else {
                    continue;
                };
                assert_eq!(binding.group, 0, "{label}");
                assert!(bindings.insert(binding.binding), "{label}: binding reused");
                if global.space != naga::AddressSpace::Uniform {
                    continue;
                }
                let name = module.types[global.ty].name.clone().unwrap_or_default();
                let (_, host_binding, host_size) = declared
                    .iter()
                    .find(|(wgsl_name, _, _)| *wgsl_name == name)
                    .unwrap_or_else(|| panic!("{label}: uniform {name} has no host struct"));
                assert_eq!(binding.binding, *host_binding, "{label}: binding of {name}");
                let size = layouter[global.ty].size;
                assert_eq!(size, *host_size, "{label}: size of {name}");
                seen.insert(name);
            }

            let entry = module
                .entry_points
                .iter()
                .find(|e| e.name == spec.entry)
                .unwrap_or_else(|| panic!("{label}: no entry point {}", spec.entry));
            assert_eq!(entry.workgroup_size, [threads, 1, 1], "{label}");
        }
        for (name, _, _) in declared {
            assert!(seen.contains(name), "no kernel reads {name}");
        }
    }
}
