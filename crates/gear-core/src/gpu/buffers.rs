//! A pool of GPU buffers reused across calls, plus upload and readback.
//!
//! Training renders the same-sized images thousands of times; allocating fresh buffers each
//! call costs more than the kernels on a software adapter. Buffers are bucketed by usage and
//! power-of-two capacity, handed out as [`PooledBuffer`] and returned to the pool on drop.

use std::collections::HashMap;
use std::sync::Mutex;

use bytemuck::Pod;

use crate::error::{GearError, Result};

use super::GpuContext;

/// Smallest capacity handed out; also keeps zero-length arrays bindable.
const MIN_CAPACITY: u64 = 256;
/// Idle bytes the pool keeps; beyond this, returned buffers are freed.
const MAX_IDLE_BYTES: u64 = 1 << 30;

type Bucket = (u32, u64);

#[derive(Default)]
pub struct BufferPool {
    idle: Mutex<(HashMap<Bucket, Vec<wgpu::Buffer>>, u64)>,
}

/// A buffer on loan from the pool; `size` is what was asked for, the buffer may be larger.
pub struct PooledBuffer {
    pub buffer: wgpu::Buffer,
    pub size: u64,
    pool: &'static BufferPool,
}

impl Drop for PooledBuffer {
    fn drop(&mut self) {
        let key = (self.buffer.usage().bits(), self.buffer.size());
        let mut guard = self.pool.idle.lock().unwrap_or_else(|e| e.into_inner());
        if guard.1 + key.1 <= MAX_IDLE_BYTES {
            guard.1 += key.1;
            guard.0.entry(key).or_default().push(self.buffer.clone());
        }
    }
}

impl PooledBuffer {
    /// Binding covering exactly the requested size (at least 4 bytes, as WebGPU requires).
    pub fn binding(&self) -> wgpu::BindingResource<'_> {
        wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: &self.buffer,
            offset: 0,
            size: wgpu::BufferSize::new(self.size.max(4)),
        })
    }
}

impl GpuContext {
    /// A buffer of at least `size` bytes with `usage`, contents undefined.
    pub fn take_buffer(
        &'static self,
        size: u64,
        usage: wgpu::BufferUsages,
    ) -> Result<PooledBuffer> {
        let capacity = size.max(MIN_CAPACITY).next_power_of_two();
        if capacity > self.info.max_storage_binding_bytes.next_power_of_two()
            && usage.contains(wgpu::BufferUsages::STORAGE)
        {
            return Err(GearError::InvalidInput(format!(
                "a {size}-byte GPU buffer exceeds this adapter's storage binding limit of {} bytes",
                self.info.max_storage_binding_bytes
            )));
        }
        let key = (usage.bits(), capacity);
        let reused = {
            let mut guard = self.buffers.idle.lock().unwrap_or_else(|e| e.into_inner());
            let found = guard.0.get_mut(&key).and_then(Vec::pop);
            if found.is_some() {
                guard.1 -= capacity;
            }
            found
        };
        let buffer = reused.unwrap_or_else(|| {
            self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("gear-pool"),
                size: capacity,
                usage,
                mapped_at_creation: false,
            })
        });
        Ok(PooledBuffer {
            buffer,
            size,
            pool: &self.buffers,
        })
    }

    /// A storage buffer holding `data` (also usable as copy source/destination).
    pub fn upload<T: Pod>(&'static self, data: &[T]) -> Result<PooledBuffer> {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        let buf = self.take_buffer(bytes.len() as u64, storage_usage())?;
        if !bytes.is_empty() {
            self.queue.write_buffer(&buf.buffer, 0, bytes);
        }
        Ok(buf)
    }

    /// A storage buffer of `len` elements of `T`, contents undefined.
    pub fn storage<T: Pod>(&'static self, len: usize) -> Result<PooledBuffer> {
        self.take_buffer((len * std::mem::size_of::<T>()) as u64, storage_usage())
    }

    /// Fills `buf` with copies of `value` (used to poison outputs in tests, or to zero).
    pub fn fill<T: Pod>(&'static self, buf: &PooledBuffer, value: T) {
        let n = buf.size as usize / std::mem::size_of::<T>();
        if n > 0 {
            let data = vec![value; n];
            self.queue
                .write_buffer(&buf.buffer, 0, bytemuck::cast_slice(&data));
        }
    }

    /// Copies the first `len` elements of `buf` back to the host (waits for the GPU).
    pub fn read<T: Pod>(&'static self, buf: &PooledBuffer, len: usize) -> Result<Vec<T>> {
        let bytes = (len * std::mem::size_of::<T>()) as u64;
        if bytes == 0 {
            return Ok(Vec::new());
        }
        let staging = self.take_buffer(
            bytes,
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        )?;
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("read"),
            });
        encoder.copy_buffer_to_buffer(
            &buf.buffer,
            0,
            &staging.buffer,
            0,
            bytes.next_multiple_of(4),
        );
        self.queue.submit(Some(encoder.finish()));
        let slice = staging.buffer.slice(..bytes.next_multiple_of(4));
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.wait()?;
        rx.recv()
            .map_err(|_| GearError::Gpu("readback callback never ran".into()))?
            .map_err(|e| GearError::Gpu(format!("readback failed: {e}")))?;
        let out = {
            let view = slice.get_mapped_range();
            bytemuck::cast_slice::<u8, T>(&view[..bytes as usize]).to_vec()
        };
        staging.buffer.unmap();
        Ok(out)
    }
}

fn storage_usage() -> wgpu::BufferUsages {
    wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST
}
