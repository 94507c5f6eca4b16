// rgb = max(sum_j coeffs_j Y_j(dir / |dir|) + 0.5, 0), one thread per Gaussian.

struct ShParams {
    n: u32,
}

@group(0) @binding(0) var<storage, read> dirs: array<f32>;
@group(0) @binding(1) var<storage, read> coeffs: array<f32>;
@group(0) @binding(2) var<storage, read_write> rgb: array<f32>;
@group(0) @binding(3) var<uniform> params: ShParams;

@compute @workgroup_size(WG)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = thread_index(gid, nwg, WG);
    if i >= params.n {
        return;
    }
    let y = basis(unit_of(load_dir(i)).u);
    let c = max(unclamped(i, y), vec3<f32>(0.0));
    rgb[3u * i] = c.x;
    rgb[3u * i + 1u] = c.y;
    rgb[3u * i + 2u] = c.z;
}
