// Gradients to the coefficients and to the direction (through its normalisation), one thread
// per Gaussian; a clamped channel passes no gradient.

struct ShParams {
    n: u32,
}

@group(0) @binding(0) var<storage, read> dirs: array<f32>;
@group(0) @binding(1) var<storage, read> coeffs: array<f32>;
@group(0) @binding(2) var<storage, read> grad_rgb: array<f32>;
@group(0) @binding(3) var<uniform> params: ShParams;
@group(0) @binding(4) var<storage, read_write> grad_coeffs: array<f32>;
@group(0) @binding(5) var<storage, read_write> grad_dirs: array<f32>;

@compute @workgroup_size(WG)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = thread_index(gid, nwg, WG);
    if i >= params.n {
        return;
    }
    let unit = unit_of(load_dir(i));
    let y = basis(unit.u);
    let upstream = vec3<f32>(grad_rgb[3u * i], grad_rgb[3u * i + 1u], grad_rgb[3u * i + 2u]);
    let g = select(vec3<f32>(0.0), upstream, unclamped(i, y) > vec3<f32>(0.0));
    for (var j = 0u; j < K; j++) {
        let base = 3u * (i * K + j);
        grad_coeffs[base] = y[j] * g.x;
        grad_coeffs[base + 1u] = y[j] * g.y;
        grad_coeffs[base + 2u] = y[j] * g.z;
    }
    var grad_dir = vec3<f32>(0.0);
    if DEGREE >= 1u && unit.norm > 0.0 {
        let dy = basis_gradient(unit.u);
        var gu = vec3<f32>(0.0);
        for (var j = 1u; j < K; j++) {
            gu += dot(load_coeff(i, j), g) * dy[j];
        }
        // d(d / |d|)/dd = (I - u u^T) / |d|.
        grad_dir = (gu - dot(gu, unit.u) * unit.u) / unit.norm;
    }
    grad_dirs[3u * i] = grad_dir.x;
    grad_dirs[3u * i + 1u] = grad_dir.y;
    grad_dirs[3u * i + 2u] = grad_dir.z;
}
