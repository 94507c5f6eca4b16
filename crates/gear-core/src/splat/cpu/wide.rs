//! Eight f32 lanes as a number: the per-Gaussian stage runs eight Gaussians at once with the
//! same expressions as scalar code. Every operation is a plain loop over the lanes, which the
//! compiler turns into one SIMD instruction where it is inlined into AVX2 code (see
//! `with_avx2!`); no fused multiply-adds are formed, so each lane's result is the IEEE result
//! of the scalar expression.

// Lane loops index several [f32; 8] arrays in step: the form the compiler vectorises.
#![allow(clippy::needless_range_loop)]

use std::ops::{Add, Div, Mul, Neg, Sub};

use super::lanes::{self, array, mask, Lanes, Mask, LANES};

#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct F8(pub Lanes);

impl F8 {
    #[inline(always)]
    pub fn splat(v: f32) -> Self {
        F8([v; LANES])
    }

    #[inline(always)]
    fn map(self, f: impl Fn(f32) -> f32) -> Self {
        F8(array(|i| f(self.0[i])))
    }

    #[inline(always)]
    fn zip(self, o: Self, f: impl Fn(f32, f32) -> f32) -> Self {
        F8(array(|i| f(self.0[i], o.0[i])))
    }

    #[inline(always)]
    fn test(self, o: Self, f: impl Fn(f32, f32) -> bool) -> Mask {
        array(|i| mask(f(self.0[i], o.0[i])))
    }

    #[inline(always)]
    pub fn sqrt(self) -> Self {
        self.map(f32::sqrt)
    }

    #[inline(always)]
    pub fn abs(self) -> Self {
        self.map(f32::abs)
    }

    /// e^x per lane (the polynomial of [`lanes::exp`]).
    #[inline(always)]
    pub fn exp(self) -> Self {
        self.map(lanes::exp)
    }

    #[inline(always)]
    pub fn min(self, o: Self) -> Self {
        self.zip(o, f32::min)
    }

    #[inline(always)]
    pub fn max(self, o: Self) -> Self {
        self.zip(o, f32::max)
    }

    #[inline(always)]
    pub fn ge(self, o: Self) -> Mask {
        self.test(o, |a, b| a >= b)
    }

    #[inline(always)]
    pub fn le(self, o: Self) -> Mask {
        self.test(o, |a, b| a <= b)
    }

    #[inline(always)]
    pub fn gt(self, o: Self) -> Mask {
        self.test(o, |a, b| a > b)
    }

    /// All ones where the lane is finite.
    #[inline(always)]
    pub fn finite(self) -> Mask {
        // NaN fails the compare.
        self.abs().le(F8::splat(f32::MAX))
    }

    /// `self` where `m` is all ones, else `other`.
    #[inline(always)]
    pub fn select(self, m: Mask, other: Self) -> Self {
        F8(array(|i| lanes::select(m[i], self.0[i], other.0[i])))
    }
}

macro_rules! binary {
    ($trait:ident, $method:ident, $op:tt) => {
        impl $trait for F8 {
            type Output = F8;
            #[inline(always)]
            fn $method(self, o: F8) -> F8 {
                self.zip(o, |a, b| a $op b)
            }
        }
        impl $trait<f32> for F8 {
            type Output = F8;
            #[inline(always)]
            fn $method(self, o: f32) -> F8 {
                self.map(|a| a $op o)
            }
        }
        impl $trait<F8> for f32 {
            type Output = F8;
            #[inline(always)]
            fn $method(self, o: F8) -> F8 {
                o.map(|b| self $op b)
            }
        }
    };
}
binary!(Add, add, +);
binary!(Sub, sub, -);
binary!(Mul, mul, *);
binary!(Div, div, /);

impl Neg for F8 {
    type Output = F8;
    #[inline(always)]
    fn neg(self) -> F8 {
        self.map(|a| -a)
    }
}

/// Lane-wise and of masks.
#[inline(always)]
pub(super) fn and(a: Mask, b: Mask) -> Mask {
    array(|i| a[i] & b[i])
}

/// Three-vectors of lanes.
pub(super) type V3 = [F8; 3];

#[inline(always)]
pub(super) fn dot(a: &V3, b: &V3) -> F8 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline(always)]
pub(super) fn cross(a: &V3, b: &V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[cfg(test)]
mod tests {
    use super::F8;

    #[test]
    fn finite_marks_only_finite_lanes() {
        let v = F8([
            0.0,
            -1.0,
            f32::MAX,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            1e-40,
            3.0,
        ]);
        let want = [true, true, true, false, false, false, true, true];
        assert_eq!(v.finite(), want.map(super::mask));
    }
}
