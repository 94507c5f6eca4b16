//! The executor's thread pool: built once per process with `GEAR_THREADS` threads (default:
//! every core), so that no render pays for thread start-up.

use std::sync::OnceLock;

use rayon::{ThreadPool, ThreadPoolBuilder};

use crate::error::{GearError, Result};

/// The thread count `GEAR_THREADS` asks for (unset or empty: the number of cores).
pub fn thread_count() -> Result<usize> {
    match std::env::var("GEAR_THREADS") {
        Ok(v) if !v.trim().is_empty() => match v.trim().parse::<usize>() {
            Ok(n) if n > 0 => Ok(n),
            _ => Err(GearError::InvalidInput(format!(
                "GEAR_THREADS must be a positive integer, got '{v}'"
            ))),
        },
        _ => Ok(std::thread::available_parallelism().map_or(1, |n| n.get())),
    }
}

/// A pool of `threads` threads.
pub fn build_pool(threads: usize) -> Result<ThreadPool> {
    ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(|i| format!("gear-cpu-{i}"))
        .build()
        .map_err(|e| GearError::InvalidInput(format!("cannot start {threads} threads: {e}")))
}

/// The process-wide pool ([`thread_count`] threads), built on first use.
pub fn global_pool() -> Result<&'static ThreadPool> {
    static POOL: OnceLock<std::result::Result<ThreadPool, String>> = OnceLock::new();
    POOL.get_or_init(|| {
        thread_count()
            .and_then(build_pool)
            .map_err(|e| e.to_string())
    })
    .as_ref()
    .map_err(|e| GearError::InvalidInput(e.clone()))
}
