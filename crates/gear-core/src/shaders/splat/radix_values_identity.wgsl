// Radix scatter payload on the first pass of an index sort: the element's own position.
fn value_at(i: u32) -> u32 {
    return i;
}
