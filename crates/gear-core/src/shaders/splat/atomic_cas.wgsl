// Gradient accumulators for adapters without float32 atomics: f32 bits in atomic<u32>, added
// with a compare-and-swap loop. Same layout as atomic_float.wgsl.

@group(0) @binding(6) var<storage, read_write> geometry: array<atomic<u32>>;
@group(0) @binding(7) var<storage, read_write> gradients: array<atomic<u32>>;

fn add_geometry(i: u32, v: f32) {
    var old = atomicLoad(&geometry[i]);
    loop {
        let r = atomicCompareExchangeWeak(&geometry[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if r.exchanged {
            break;
        }
        old = r.old_value;
    }
}

fn add_gradient(i: u32, v: f32) {
    var old = atomicLoad(&gradients[i]);
    loop {
        let r = atomicCompareExchangeWeak(&gradients[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if r.exchanged {
            break;
        }
        old = r.old_value;
    }
}
