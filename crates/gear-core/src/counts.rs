//! Loops over a count known only at run time, compiled for each common value: the
//! rasterizer's feature channels (stage 3's anchor renders three colours and a logit per
//! part) and the KNN consistency's part count. A constant count unrolls the per-count loops
//! of the hot paths into straight-line code; other counts take the generic instance.

/// Calls `$f::<C>(args)` with the count `$channels` as a compile-time constant C for the
/// common counts (1-13), else `$f::<0>(args)` (the count read at run time, see [`channels`]):
/// with a constant count the loops over it unroll into straight-line code.
macro_rules! with_channels {
    // `f(args)`, or `f::<T>(args)` for a function with generic parameters before the count.
    ($channels:expr, $f:ident $(::<$($g:ty),+>)? ($($arg:expr),* $(,)?)) => {
        match $channels {
            1 => $f::<$($($g,)+)? 1>($($arg),*),
            2 => $f::<$($($g,)+)? 2>($($arg),*),
            3 => $f::<$($($g,)+)? 3>($($arg),*),
            4 => $f::<$($($g,)+)? 4>($($arg),*),
            5 => $f::<$($($g,)+)? 5>($($arg),*),
            6 => $f::<$($($g,)+)? 6>($($arg),*),
            7 => $f::<$($($g,)+)? 7>($($arg),*),
            8 => $f::<$($($g,)+)? 8>($($arg),*),
            9 => $f::<$($($g,)+)? 9>($($arg),*),
            10 => $f::<$($($g,)+)? 10>($($arg),*),
            11 => $f::<$($($g,)+)? 11>($($arg),*),
            12 => $f::<$($($g,)+)? 12>($($arg),*),
            13 => $f::<$($($g,)+)? 13>($($arg),*),
            _ => $f::<$($($g,)+)? 0>($($arg),*),
        }
    };
}
pub(crate) use with_channels;

/// The count of a function specialised by [`with_channels!`]: `C`, or `runtime` for the
/// generic instance C = 0.
#[inline(always)]
pub(crate) fn channels<const C: usize>(runtime: usize) -> usize {
    debug_assert!(C == 0 || C == runtime);
    if C == 0 {
        runtime
    } else {
        C
    }
}
