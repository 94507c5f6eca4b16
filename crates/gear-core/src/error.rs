//! The one error type of gear-core; the Python binding maps each variant to a Python exception.

use thiserror::Error;

#[derive(Debug, Error)]
pub enum GearError {
    /// No usable GPU adapter (not even a software one) could be found.
    #[error("{0}")]
    NoAdapter(String),
    /// The device failed while running work (out of memory, lost device, validation).
    #[error("GPU error: {0}")]
    Gpu(String),
    /// The caller passed something the kernels cannot work with.
    #[error("{0}")]
    InvalidInput(String),
}

pub type Result<T> = std::result::Result<T, GearError>;

/// A [`GearError::InvalidInput`] with `message`.
pub(crate) fn invalid(message: String) -> GearError {
    GearError::InvalidInput(message)
}

/// An error naming the first non-finite value of `values` (`what`: the array, for the
/// message); a non-finite input is a bug upstream, reported rather than spread as NaNs.
pub(crate) fn check_finite<T: Copy + Into<f64>>(what: &str, values: &[T]) -> Result<()> {
    match values.iter().position(|&v| !v.into().is_finite()) {
        None => Ok(()),
        Some(i) => Err(GearError::InvalidInput(format!(
            "{what} has a non-finite value at flat index {i}"
        ))),
    }
}
