//! One list entry evaluated at the eight pixels of a tile row, shared by the forward blend and
//! its backward (which must decide every pixel alike). Plain loops over `[f32; 8]` that the
//! compiler turns into SIMD; the exponential is a polynomial so that it vectorises too.

// Lane loops index several [f32; 8] arrays in step: the form the compiler vectorises.
#![allow(clippy::needless_range_loop)]

use super::lists::Entry;
use crate::splat::constants::{MAX_ALPHA, MIN_ALPHA};

/// Defines `fn $name(args) -> ret` calling `$body` (an `#[inline(always)]` function) compiled
/// for AVX2 where the CPU has it, else as compiled for the baseline target: eight-lane rows
/// become single instructions and floor/ceil inline. Per-lane IEEE results are the same either
/// way (no fused multiply-adds are formed), so outputs do not depend on the path taken.
macro_rules! with_avx2 {
    ($(#[$doc:meta])* fn $name:ident($($arg:ident: $ty:ty),*) -> $ret:ty = $body:path) => {
        $(#[$doc])*
        fn $name($($arg: $ty),*) -> $ret {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2")]
                fn wide($($arg: $ty),*) -> $ret {
                    $body($($arg),*)
                }
                if std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: the CPU supports AVX2.
                    return unsafe { wide($($arg),*) };
                }
            }
            $body($($arg),*)
        }
    };
}
pub(crate) use with_avx2;

pub(crate) const LANES: usize = 8;
pub(crate) type Lanes = [f32; LANES];
/// Per-lane conditions as all-ones-or-zero u32s, applied with bitwise operations: bool arrays
/// and per-lane branches would compile to scalar code per lane.
pub(crate) type Mask = [u32; LANES];

/// `[f(0), f(1), ...]` as `std::array::from_fn` builds it, but always inlined: from_fn's
/// element calls stay out-of-line calls, outside the AVX2 code and one per element.
#[inline(always)]
pub(crate) fn array<T: Copy + Default, const N: usize>(mut f: impl FnMut(usize) -> T) -> [T; N] {
    let mut out = [T::default(); N];
    for (i, o) in out.iter_mut().enumerate() {
        *o = f(i);
    }
    out
}

/// All ones where `condition` holds, else zero.
#[inline(always)]
pub(super) fn mask(condition: bool) -> u32 {
    u32::from(condition).wrapping_neg()
}

/// `value` where `mask` is all ones, +0 where it is zero.
#[inline(always)]
pub(super) fn masked(value: f32, mask: u32) -> f32 {
    f32::from_bits(value.to_bits() & mask)
}

/// `a` where `mask` is all ones, else `b`.
#[inline(always)]
pub(super) fn select(mask: u32, a: f32, b: f32) -> f32 {
    f32::from_bits((a.to_bits() & mask) | (b.to_bits() & !mask))
}

const LOG2E: f32 = std::f32::consts::LOG2_E;
/// ln 2 split so that n · LN2_HI is exact for the n that occur.
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
/// 1.5 · 2²³: adding and subtracting it rounds an f32 of magnitude < 2²² to an integer.
const ROUND: f32 = 12_582_912.0;

/// e^x to within a few f32 ulps for x in [-87, 88] (inputs are clamped to it): x = n ln 2 + r,
/// a degree-6 polynomial for e^r on |r| <= ln 2 / 2, and 2^n written into the exponent bits.
#[inline(always)]
pub(crate) fn exp(x: f32) -> f32 {
    let x = x.clamp(-87.0, 88.0);
    let shifted = x * LOG2E + ROUND;
    let n = shifted - ROUND;
    let r = x - n * LN2_HI - n * LN2_LO;
    let mut p = 1.987_569_2e-4f32;
    p = p * r + 1.398_199_9e-3;
    p = p * r + 8.333_452e-3;
    p = p * r + 4.166_579_6e-2;
    p = p * r + 0.166_666_65;
    p = p * r + 0.5;
    let e = p * r * r + r + 1.0;
    // `shifted` holds n in its low mantissa bits (1.5 · 2²³ + n, one unit per ulp), so 2^n's
    // exponent is those bits plus the bias, shifted into place: integer lane operations, where
    // `n as i32` (a saturating conversion) would be scalar code per lane.
    e * f32::from_bits(shifted.to_bits().wrapping_add(127) << 23)
}

/// A list entry at the eight pixels of a row.
pub(super) struct Evaluation {
    /// Pixel centres minus the mean.
    pub dx: Lanes,
    /// exp(-½ dᵀ conic d).
    pub gauss: Lanes,
    /// opacity · gauss, and alpha = that clamped to MAX_ALPHA.
    pub raw: Lanes,
    pub alpha: Lanes,
    /// The contract's per-pixel guards pass (all ones, else zero): power <= 0 and
    /// alpha >= MIN_ALPHA.
    pub passes: Mask,
}

/// Entry `s` at pixel centres x = `xs`, y = v + `dy` (as blend_common.wgsl's evaluate_quad).
#[inline(always)]
pub(super) fn evaluate(s: &Entry, xs: &Lanes, dy: f32) -> Evaluation {
    let mut e = Evaluation {
        dx: [0.0; LANES],
        gauss: [0.0; LANES],
        raw: [0.0; LANES],
        alpha: [0.0; LANES],
        passes: [0; LANES],
    };
    for i in 0..LANES {
        let dx = xs[i] - s.u;
        let power = -0.5 * (s.a * dx * dx + s.c * dy * dy) - s.b * dx * dy;
        let gauss = exp(power);
        let raw = s.opacity * gauss;
        let alpha = raw.min(MAX_ALPHA as f32);
        e.dx[i] = dx;
        e.gauss[i] = gauss;
        e.raw[i] = raw;
        e.alpha[i] = alpha;
        e.passes[i] = mask(power <= 0.0) & mask(alpha >= MIN_ALPHA as f32);
    }
    e
}

#[cfg(test)]
mod tests {
    /// The polynomial exp against f64 over the range the blend uses: relative error < 4e-7.
    #[test]
    fn exp_matches_f64() {
        let mut worst = 0.0f64;
        let steps = 200_000;
        for k in 0..=steps {
            let x = -87.0 + 87.5 * k as f32 / steps as f32;
            let want = f64::from(x).exp();
            let got = f64::from(super::exp(x));
            worst = worst.max((got - want).abs() / want);
        }
        assert!(worst < 4e-7, "exp relative error {worst:e}");
    }
}
