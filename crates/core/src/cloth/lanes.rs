//! Arithmetic written once for a single `f64` and for eight of them at a time.
//!
//! [`Real`] is the number type of the triangle-mesh maths in [`super::triangles`] and of the
//! FEM source's elements: with `f64` it is the scalar code (energies, Hessians, the XPBD
//! estimator), with [`Lanes`] the same expressions evaluate eight triangles or hinges at once,
//! which the compiler turns into SIMD instructions (AVX-512, AVX2 or SSE2, whichever the CPU
//! has). Branches are [`Real::select`]s so that every lane runs the same instructions. Both
//! types perform the same IEEE operations in the same order, so a lane's result is the scalar
//! result bit for bit, except `atan2`: `f64` uses the C library's, [`Lanes`] a vectorisable
//! rational approximation ([`atan2_rational`], within 2 ulp of it).

use std::ops::{Add, BitOr, Div, Mul, Neg, Sub};

/// `lanewise!(|l| e)` is `[e with l = 0, …, e with l = 7]`, written out: closures and
/// `std::array::from_fn` are not always inlined into the SIMD-compiled loops, and then every
/// operation copies its lanes through memory.
macro_rules! lanewise {
    (|$l:ident| $e:expr) => {
        [
            { let $l = 0usize; $e },
            { let $l = 1usize; $e },
            { let $l = 2usize; $e },
            { let $l = 3usize; $e },
            { let $l = 4usize; $e },
            { let $l = 5usize; $e },
            { let $l = 6usize; $e },
            { let $l = 7usize; $e },
        ]
    };
}
pub(crate) use lanewise;

/// `each3!(|i| e)` is `[e with i = 0, 1, 2]`, written out (see [`lanewise`]).
macro_rules! each3 {
    (|$i:ident| $e:expr) => {
        [{ let $i = 0usize; $e }, { let $i = 1usize; $e }, { let $i = 2usize; $e }]
    };
}
pub(crate) use each3;

/// Lanes of a [`Lanes`].
pub(crate) const LANES: usize = 8;

/// A real number type: `f64` or eight `f64` lanes.
pub trait Real:
    Copy
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
{
    /// The outcome of a comparison, per lane.
    type Mask: Copy + BitOr<Output = Self::Mask>;
    /// Every lane `v`.
    fn splat(v: f64) -> Self;
    /// Square root.
    fn sqrt(self) -> Self;
    /// Absolute value.
    fn abs(self) -> Self;
    /// The angle of `(x, self)`, in `[−π, π]`.
    fn atan2(self, x: Self) -> Self;
    /// `self > other`.
    fn gt(self, other: Self) -> Self::Mask;
    /// `self < other`.
    fn lt(self, other: Self) -> Self::Mask;
    /// `self == other`.
    fn eq(self, other: Self) -> Self::Mask;
    /// `a` where `mask` holds, else `b`.
    fn select(mask: Self::Mask, a: Self, b: Self) -> Self;
    /// Whether `mask` holds in every lane (to skip computing a rarely needed alternative).
    fn all(mask: Self::Mask) -> bool;
}

impl Real for f64 {
    type Mask = bool;
    #[inline(always)]
    fn splat(v: f64) -> Self {
        v
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        f64::sqrt(self)
    }
    #[inline(always)]
    fn abs(self) -> Self {
        f64::abs(self)
    }
    #[inline(always)]
    fn atan2(self, x: Self) -> Self {
        f64::atan2(self, x)
    }
    #[inline(always)]
    fn gt(self, other: Self) -> bool {
        self > other
    }
    #[inline(always)]
    fn lt(self, other: Self) -> bool {
        self < other
    }
    #[inline(always)]
    fn eq(self, other: Self) -> bool {
        self == other
    }
    #[inline(always)]
    fn select(mask: bool, a: Self, b: Self) -> Self {
        if mask { a } else { b }
    }
    #[inline(always)]
    fn all(mask: bool) -> bool {
        mask
    }
}

/// Eight `f64`s operated on together (aligned to a cache line, as a 512-bit register).
#[derive(Debug, Clone, Copy, PartialEq)]
#[repr(C, align(64))]
pub struct Lanes(pub [f64; LANES]);

/// A comparison's outcome per lane: all bits set where it holds (the form SIMD compares
/// produce and blends consume).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(C, align(64))]
pub struct Mask(pub [u64; LANES]);

impl BitOr for Mask {
    type Output = Self;
    #[inline(always)]
    fn bitor(self, o: Self) -> Self {
        Mask(lanewise!(|l| self.0[l] | o.0[l]))
    }
}

macro_rules! lanewise_op {
    ($tr:ident, $f:ident, $op:tt) => {
        impl $tr for Lanes {
            type Output = Self;
            #[inline(always)]
            fn $f(self, o: Self) -> Self {
                Self(lanewise!(|l| self.0[l] $op o.0[l]))
            }
        }
    };
}
lanewise_op!(Add, add, +);
lanewise_op!(Sub, sub, -);
lanewise_op!(Mul, mul, *);
lanewise_op!(Div, div, /);

impl Neg for Lanes {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        Self(lanewise!(|l| -self.0[l]))
    }
}

impl Real for Lanes {
    type Mask = Mask;
    #[inline(always)]
    fn splat(v: f64) -> Self {
        Self([v; LANES])
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        Self(lanewise!(|l| self.0[l].sqrt()))
    }
    #[inline(always)]
    fn abs(self) -> Self {
        Self(lanewise!(|l| self.0[l].abs()))
    }
    #[inline(always)]
    fn atan2(self, x: Self) -> Self {
        atan2_rational(self, x)
    }
    #[inline(always)]
    fn gt(self, o: Self) -> Mask {
        Mask(lanewise!(|l| if self.0[l] > o.0[l] { u64::MAX } else { 0 }))
    }
    #[inline(always)]
    fn lt(self, o: Self) -> Mask {
        Mask(lanewise!(|l| if self.0[l] < o.0[l] { u64::MAX } else { 0 }))
    }
    #[inline(always)]
    fn eq(self, o: Self) -> Mask {
        Mask(lanewise!(|l| if self.0[l] == o.0[l] {
            u64::MAX
        } else {
            0
        }))
    }
    #[inline(always)]
    fn select(mask: Mask, a: Self, b: Self) -> Self {
        Self(lanewise!(|l| f64::from_bits(
            (a.0[l].to_bits() & mask.0[l]) | (b.0[l].to_bits() & !mask.0[l])
        )))
    }
    #[inline(always)]
    fn all(mask: Mask) -> bool {
        mask.0.iter().fold(u64::MAX, |acc, &m| acc & m) == u64::MAX
    }
}

/// `atan2(y, x)` without a library call, so that it vectorises: the argument is reduced to
/// `t = min(|x|, |y|) / max(|x|, |y|)` in `[0, 1]`, and above 0.66 by `atan t = π/4 +
/// atan((t − 1)/(t + 1))` to `|r| ≤ 0.21` (formed as `(min − max)/(min + max)`: one division), where `atan r = r + r³ P(r²)/Q(r²)` with the
/// degree-4/5 rational of Cephes' `atan` (relative error about 1e-16); the quadrant follows
/// from the signs. `atan2(0, 0) = 0`.
#[inline(always)]
pub fn atan2_rational<R: Real>(y: R, x: R) -> R {
    const P: [f64; 5] = [
        -8.750_608_600_031_904e-1,
        -1.615_753_718_733_365e1,
        -7.500_855_792_314_705e1,
        -1.228_866_684_490_136_2e2,
        -6.485_021_904_942_025e1,
    ];
    const Q: [f64; 5] = [
        2.485_846_490_142_306_3e1,
        1.650_270_098_316_988_6e2,
        4.328_810_604_912_903e2,
        4.853_903_996_359_137e2,
        1.945_506_571_482_614e2,
    ];
    /// The part of π/2 below `FRAC_PI_2`'s last bit.
    const MOREBITS: f64 = 6.123_233_995_736_766e-17;
    let zero = R::splat(0.0);
    let (ay, ax) = (y.abs(), x.abs());
    let steep = ay.gt(ax);
    let hi = R::select(steep, ay, ax);
    let lo = R::select(steep, ax, ay);
    // `hi` is 0 only at the origin; a lane there divides by 1 and is zeroed at the end.
    let origin = hi.eq(zero);
    let hi = R::select(origin, R::splat(1.0), hi);
    // t = lo / hi, and above 0.66 r = (t − 1)/(t + 1) = (lo − hi)/(lo + hi): one division.
    let big = lo.gt(R::splat(0.66) * hi);
    let r = R::select(big, lo - hi, lo) / R::select(big, lo + hi, hi);
    let z = r * r;
    let p = (((R::splat(P[0]) * z + R::splat(P[1])) * z + R::splat(P[2])) * z + R::splat(P[3])) * z
        + R::splat(P[4]);
    let q = ((((z + R::splat(Q[0])) * z + R::splat(Q[1])) * z + R::splat(Q[2])) * z
        + R::splat(Q[3]))
        * z
        + R::splat(Q[4]);
    let kernel = r + r * z * p / q;
    let a = R::select(
        big,
        R::splat(std::f64::consts::FRAC_PI_4) + (kernel + R::splat(0.5 * MOREBITS)),
        kernel,
    );
    let a = R::select(
        steep,
        R::splat(std::f64::consts::FRAC_PI_2) - a + R::splat(MOREBITS),
        a,
    );
    let a = R::select(
        x.lt(zero),
        R::splat(std::f64::consts::PI) - a + R::splat(2.0 * MOREBITS),
        a,
    );
    let a = R::select(y.lt(zero), -a, a);
    R::select(origin, zero, a)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Distance in units in the last place.
    fn ulps(a: f64, b: f64) -> f64 {
        if a == b {
            return 0.0;
        }
        let spacing = f64::EPSILON * a.abs().max(b.abs()).max(f64::MIN_POSITIVE);
        (a - b).abs() / spacing
    }

    #[test]
    fn rational_atan2_is_within_two_ulp_of_the_library_in_every_quadrant() {
        let mut worst: f64 = 0.0;
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut uniform = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        for i in 0..200_000 {
            // Angles everywhere, magnitudes over many decades, and the branch edges.
            let (y, x) = match i % 4 {
                0 => {
                    let a = (uniform() * 2.0 - 1.0) * std::f64::consts::PI;
                    let r = 10f64.powf(uniform() * 12.0 - 6.0);
                    (r * a.sin(), r * a.cos())
                }
                1 => (uniform() * 0.02 - 0.01, 1.0),
                2 => (0.66 + (uniform() - 0.5) * 1e-9, 1.0),
                _ => (
                    1.0 + (uniform() - 0.5) * 1e-9,
                    -(1.0 + (uniform() - 0.5) * 1e-9),
                ),
            };
            let lanes = Lanes::splat(y).atan2(Lanes::splat(x));
            let exact = y.atan2(x);
            worst = worst.max(ulps(lanes.0[3], exact));
            assert_eq!(
                atan2_rational(y, x),
                lanes.0[0],
                "one formula for f64 and lanes"
            );
        }
        assert!(worst <= 2.0, "worst error {worst} ulp");
        for (y, x) in [(0.0, 0.0), (0.0, 1.0), (0.0, -1.0), (1.0, 0.0), (-1.0, 0.0)] {
            let got = atan2_rational(y, x);
            assert!(ulps(got, y.atan2(x)) <= 2.0, "atan2({y}, {x}) = {got}");
        }
    }

    #[test]
    fn lanes_are_independent_and_select_per_lane() {
        let a = Lanes(std::array::from_fn(|l| l as f64 - 3.5));
        let b = Lanes::splat(0.0);
        let m = a.gt(b);
        let s = Lanes::select(m, a.sqrt(), -a);
        for l in 0..LANES {
            let v = a.0[l];
            assert_eq!(s.0[l], if v > 0.0 { v.sqrt() } else { -v });
        }
        assert_eq!((a * a / a - a).abs(), Lanes::splat(0.0));
    }
}
