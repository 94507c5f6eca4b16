// Gradient accumulators for adapters with float32 atomics: a native atomicAdd.
// geometry: per Gaussian 8 values (conic a, b, c, u, v, opacity, z, unused).
// gradients: the packed output; features start at FEATURE_BASE (see blend_backward.wgsl).

@group(0) @binding(6) var<storage, read_write> geometry: array<atomic<f32>>;
@group(0) @binding(7) var<storage, read_write> gradients: array<atomic<f32>>;

fn add_geometry(i: u32, v: f32) {
    atomicAdd(&geometry[i], v);
}

fn add_gradient(i: u32, v: f32) {
    atomicAdd(&gradients[i], v);
}
