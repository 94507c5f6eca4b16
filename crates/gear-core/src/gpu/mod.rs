//! GPU plumbing shared by every kernel: the process-wide device, compiled-pipeline cache,
//! buffer pool, and the helpers that upload, dispatch and read back.

mod buffers;
mod context;
mod dispatch;
mod pipelines;

pub use buffers::{BufferPool, PooledBuffer};
pub use context::{AdapterInfo, GpuContext, OptionalFeatures};
pub use dispatch::{workgroup_grid, MAX_WORKGROUPS_PER_DIM};
pub use pipelines::{PipelineCache, ShaderSpec};
