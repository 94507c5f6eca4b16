// The forward blend's work counters, compiled out (blend_counts_on.wgsl counts): the normal
// kernels call these and pay nothing.

fn count_row(e: Entry, span: vec2<f32>, tile: u32, row: TileRow, live: u32) {}

fn count_quad(first: u32, row_len: u32, blended: vec4<bool>) {}

fn flush_counts() {}
