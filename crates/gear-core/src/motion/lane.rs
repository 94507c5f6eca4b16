//! The numbers the deformation runs on: one Gaussian's values as a scalar (f32 or f64), or
//! eight Gaussians' values as one eight-lane f32 ([`F8`], one SIMD register in AVX2 code).
//! `quat.rs` and `blend.rs` are written once over [`Lane`]; per-Gaussian conditions are masks
//! and selects instead of branches, so each lane of an [`F8`] computes exactly the scalar f32
//! code's result (no fused multiply-adds are formed; the exponential is the same polynomial).

use std::ops::{Add, Div, Mul, Neg, Sub};

use num_traits::{Float, One, Zero};

use crate::splat::cpu::lanes::{self, array, Mask, LANES};
use crate::splat::cpu::wide::F8;

/// A number of [`Lane::WIDTH`] independent lanes, each one Gaussian's value.
pub trait Lane:
    Copy
    + Default
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
{
    /// The element type of a lane.
    type Scalar: Float + Default;
    /// A per-lane condition.
    type Mask: Copy;
    const WIDTH: usize;

    fn splat(v: Self::Scalar) -> Self;
    /// Lane i set to `f(i)`.
    fn from_fn(f: impl FnMut(usize) -> Self::Scalar) -> Self;
    fn lane(self, i: usize) -> Self::Scalar;
    fn sqrt(self) -> Self;
    fn exp(self) -> Self;
    fn max(self, o: Self) -> Self;
    fn gt(self, o: Self) -> Self::Mask;
    /// `a` on the lanes where `m` holds, else `b`.
    fn select(m: Self::Mask, a: Self, b: Self) -> Self;

    fn zero() -> Self {
        Self::splat(Self::Scalar::zero())
    }

    fn one() -> Self {
        Self::splat(Self::Scalar::one())
    }
}

/// A scalar is a lane of width one; `exp` is `$exp`.
macro_rules! scalar_lane {
    ($t:ty, $exp:path) => {
        impl Lane for $t {
            type Scalar = $t;
            type Mask = bool;
            const WIDTH: usize = 1;

            #[inline(always)]
            fn splat(v: $t) -> $t {
                v
            }

            #[inline(always)]
            fn from_fn(mut f: impl FnMut(usize) -> $t) -> $t {
                f(0)
            }

            #[inline(always)]
            fn lane(self, _: usize) -> $t {
                self
            }

            #[inline(always)]
            fn sqrt(self) -> $t {
                <$t>::sqrt(self)
            }

            #[inline(always)]
            fn exp(self) -> $t {
                $exp(self)
            }

            #[inline(always)]
            fn max(self, o: $t) -> $t {
                <$t>::max(self, o)
            }

            #[inline(always)]
            fn gt(self, o: $t) -> bool {
                self > o
            }

            #[inline(always)]
            fn select(m: bool, a: $t, b: $t) -> $t {
                if m {
                    a
                } else {
                    b
                }
            }
        }
    };
}

// f32 takes the polynomial exponential of the eight-lane code, so that a Gaussian computed
// alone (a chunk's tail) gets the bits it would get in a lane.
scalar_lane!(f32, lanes::exp);
scalar_lane!(f64, f64::exp);

impl Lane for F8 {
    type Scalar = f32;
    type Mask = Mask;
    const WIDTH: usize = LANES;

    #[inline(always)]
    fn splat(v: f32) -> F8 {
        F8::splat(v)
    }

    #[inline(always)]
    fn from_fn(f: impl FnMut(usize) -> f32) -> F8 {
        F8(array(f))
    }

    #[inline(always)]
    fn lane(self, i: usize) -> f32 {
        self.0[i]
    }

    #[inline(always)]
    fn sqrt(self) -> F8 {
        F8::sqrt(self)
    }

    #[inline(always)]
    fn exp(self) -> F8 {
        F8::exp(self)
    }

    #[inline(always)]
    fn max(self, o: F8) -> F8 {
        F8::max(self, o)
    }

    #[inline(always)]
    fn gt(self, o: F8) -> Mask {
        F8::gt(self, o)
    }

    #[inline(always)]
    fn select(m: Mask, a: F8, b: F8) -> F8 {
        a.select(m, b)
    }
}
