//! Dual numbers: a value and its derivatives with respect to `N` parameters, carried through
//! the same arithmetic (forward-mode differentiation). Implements [`Real`], so the element
//! maths of [`super::triangles`] (and the XPBD iterations built on it) runs on them unchanged.

use std::ops::{Add, Div, Mul, Neg, Sub};

use super::lanes::Real;

/// `v + Σ_k d_k ε_k` with `ε_k ε_l = 0`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Dual<const N: usize> {
    /// The value.
    pub v: f64,
    /// The derivatives of the value with respect to each parameter.
    pub d: [f64; N],
}

impl<const N: usize> Dual<N> {
    /// A constant (zero derivatives).
    pub fn constant(v: f64) -> Self {
        Self { v, d: [0.0; N] }
    }

    /// Parameter `k` at value `v` (derivative 1 with respect to itself).
    pub fn parameter(v: f64, k: usize) -> Self {
        let mut d = [0.0; N];
        d[k] = 1.0;
        Self { v, d }
    }

    /// `a·self + b·other` of the derivatives, with value `v` (the chain rule's common form).
    #[inline(always)]
    fn chain(v: f64, a: f64, x: Self, b: f64, y: Self) -> Self {
        Self {
            v,
            d: std::array::from_fn(|k| a * x.d[k] + b * y.d[k]),
        }
    }

    /// One argument's chain rule: value `v`, derivative `a` with respect to `x`.
    #[inline(always)]
    fn unary(v: f64, a: f64, x: Self) -> Self {
        Self {
            v,
            d: x.d.map(|d| a * d),
        }
    }
}

impl<const N: usize> Add for Dual<N> {
    type Output = Self;
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        Self::chain(self.v + o.v, 1.0, self, 1.0, o)
    }
}

impl<const N: usize> Sub for Dual<N> {
    type Output = Self;
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        Self::chain(self.v - o.v, 1.0, self, -1.0, o)
    }
}

impl<const N: usize> Mul for Dual<N> {
    type Output = Self;
    #[inline(always)]
    fn mul(self, o: Self) -> Self {
        Self::chain(self.v * o.v, o.v, self, self.v, o)
    }
}

impl<const N: usize> Div for Dual<N> {
    type Output = Self;
    #[inline(always)]
    fn div(self, o: Self) -> Self {
        let q = self.v / o.v;
        Self::chain(q, 1.0 / o.v, self, -q / o.v, o)
    }
}

impl<const N: usize> Neg for Dual<N> {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        Self::unary(-self.v, -1.0, self)
    }
}

impl<const N: usize> Real for Dual<N> {
    /// Comparisons compare values.
    type Mask = bool;
    fn splat(v: f64) -> Self {
        Self::constant(v)
    }
    fn sqrt(self) -> Self {
        let r = self.v.sqrt();
        Self::unary(r, 0.5 / r, self)
    }
    fn abs(self) -> Self {
        Self::unary(self.v.abs(), if self.v < 0.0 { -1.0 } else { 1.0 }, self)
    }
    /// `∂atan2(y, x) = (x dy − y dx) / (x² + y²)`.
    fn atan2(self, x: Self) -> Self {
        let r2 = x.v * x.v + self.v * self.v;
        Self::chain(self.v.atan2(x.v), x.v / r2, self, -self.v / r2, x)
    }
    fn gt(self, other: Self) -> bool {
        self.v > other.v
    }
    fn lt(self, other: Self) -> bool {
        self.v < other.v
    }
    fn eq(self, other: Self) -> bool {
        self.v == other.v
    }
    fn select(mask: bool, a: Self, b: Self) -> Self {
        if mask { a } else { b }
    }
    fn all(mask: bool) -> bool {
        mask
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A function of two parameters through every operation, against central differences.
    #[test]
    fn derivatives_equal_finite_differences() {
        fn f<R: Real>(a: R, b: R) -> R {
            let s = (a * a + b * b).sqrt();
            (a / s - b).abs() * a.atan2(b + R::splat(2.0)) - (-s)
        }
        let (a, b) = (0.7, -1.3);
        let out = f(Dual::<2>::parameter(a, 0), Dual::<2>::parameter(b, 1));
        assert_eq!(out.v, f(a, b));
        let h = 1e-6;
        let fd = [
            (f(a + h, b) - f(a - h, b)) / (2.0 * h),
            (f(a, b + h) - f(a, b - h)) / (2.0 * h),
        ];
        for k in 0..2 {
            assert!(
                (out.d[k] - fd[k]).abs() < 1e-8,
                "∂{k}: {} vs {}",
                out.d[k],
                fd[k]
            );
        }
    }
}
