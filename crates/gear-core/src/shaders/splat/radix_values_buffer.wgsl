// Radix scatter payload: the values carried by the previous pass.
@group(0) @binding(1) var<storage, read> values_in: array<u32>;

fn value_at(i: u32) -> u32 {
    return values_in[i];
}
