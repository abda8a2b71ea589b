//! CPU kernels of the fused ops: plain Rust over slices, SIMD across clips.
//!
//! Tensors arrive row-major, states `[B, P, 3]` and per-spring values `[S]`. Each kernel
//! works on chunks of `L` clips re-laid out as `[P·3][L]` ("lanes"), so that one pass over the
//! springs computes `L` clips at once in SIMD registers (L = 8 with AVX2, 4 otherwise); chunks
//! run in parallel. For spring `s = (a, b)` with `d = x_b − x_a`, `w = v_b − v_a`, `L = |d|`:
//!
//! forward (Eq. 4, Eq. 2): `f_s = c_s d + ν_s w`, `c_s = k_s (1 − l0_s/L) + b_s (w·d)/L²`,
//! `ν_s = β k_s` (the step's isotropic viscosity `β`, 0 for the plain forces op);
//! `F_a += f_s`, `F_b −= f_s`. A shear spring shorter than at rest (`L < l0`) has `k_s κ` in
//! place of `k_s` in `c_s` and in the backward (the step's `shear_compression` `κ`, 1 for the
//! plain forces op); `ν_s` keeps `k_s`.
//!
//! backward, given `G = ∂ℓ/∂F` and `g = G_a − G_b = ∂ℓ/∂f_s`:
//! - `∂ℓ/∂k_s = Σ_clips (g·d)(1 − l0/L) + β g·w`, `∂ℓ/∂b_s = Σ_clips (g·d)(w·d)/L²`;
//! - `∂ℓ/∂d = c g + (g·d) ∂c/∂d`, `∂c/∂d = k l0 d/L³ + b (w/L² − 2 (w·d) d/L⁴)`;
//! - `∂ℓ/∂w = (g·d) b d/L² + ν_s g`;
//! - `∂ℓ/∂x_b += ∂ℓ/∂d`, `∂ℓ/∂x_a −= ∂ℓ/∂d`, and the same for `v` with `∂ℓ/∂w`.
//!
//! The fused step adds semi-implicit Euler (Eq. 5) and the pins:
//! `f = S(x, v) + m g − c v`, `v'' = v + h/m f`, `x'' = x + h v''`, then pinned particles take
//! their prescribed `x̂`, `v̂`. Its backward, given `(∂ℓ/∂x', ∂ℓ/∂v', ∂ℓ/∂f)`:
//! `ḡx'' = free ∂ℓ/∂x'`, `ḡv'' = free ∂ℓ/∂v' + h ḡx''`, `G = ∂ℓ/∂f + h/m ḡv''`, then
//! `∂ℓ/∂x = ḡx'' + S_xᵀ G`, `∂ℓ/∂v = ḡv'' − c G + S_vᵀ G`, and `∂ℓ/∂k`, `∂ℓ/∂b` from `G`.

use num_traits::Float;
use rayon::prelude::*;

use super::HostGraph;

/// Constants of one integration step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepParams {
    /// Step `h`, s.
    pub h: f64,
    /// Particle mass `m`, kg.
    pub mass: f64,
    /// Rayleigh constant `c`, N·s/m.
    pub rayleigh: f64,
    /// Gravity, m/s².
    pub gravity: [f64; 3],
    /// The springs' isotropic viscosity per unit stiffness `β`, s
    /// ([`crate::sim::SimConfig::viscosity`]).
    pub viscosity: f64,
    /// The shear springs' stiffness in compression per unit `k`
    /// ([`crate::sim::SimConfig::shear_compression`]; 1: linear springs).
    pub shear_compression: f64,
}

/// The springs with checked indices, so that the loops can skip bounds checks.
pub(super) struct Springs<'a, T> {
    ends: &'a [(u32, u32)],
    /// Curvature elements `(i, j, l)`, whose `κ` follow the springs' `k` (their `b` entries unused).
    triples: &'a [(u32, u32, u32)],
    l0: Vec<T>,
    /// Per-particle factor on the spring forces ([`HostGraph::with_force_scale`]).
    scale: Option<Vec<T>>,
    /// Isotropic viscosity per unit stiffness `β` ([`Springs::with_viscosity`]; 0: none).
    visc: T,
    /// Each spring's stiffness in compression per unit `k` ([`Springs::with_compression`]):
    /// empty where every spring is linear.
    comp: Vec<T>,
    /// The graph's shear springs.
    shear: &'a [bool],
}

impl<'a, T: Float> Springs<'a, T> {
    pub(super) fn new(g: &'a HostGraph) -> Self {
        Self {
            ends: &g.ends,
            triples: &g.triples,
            l0: g
                .rest_length
                .iter()
                .map(|&l| T::from(l).expect("float"))
                .collect(),
            scale: g
                .force_scale
                .as_ref()
                .map(|s| s.iter().map(|&v| T::from(v).expect("float")).collect()),
            visc: T::zero(),
            comp: Vec::new(),
            shear: &g.shear,
        }
    }

    /// The same springs with the isotropic viscosity `β k_s (v_b − v_a)` of a step's physics.
    pub(super) fn with_viscosity(mut self, viscosity: f64) -> Self {
        self.visc = T::from(viscosity).expect("float");
        self
    }

    /// The same springs with the shear springs pushing with `shear_compression · k_s` when
    /// shorter than at rest (a step's physics; 1: linear springs).
    pub(super) fn with_compression(mut self, shear_compression: f64) -> Self {
        self.comp = if shear_compression == 1.0 || self.shear.is_empty() {
            Vec::new()
        } else {
            let soft = T::from(shear_compression).expect("float");
            self.shear
                .iter()
                .map(|&s| if s { soft } else { T::one() })
                .collect()
        };
        self
    }

    /// A step's physics on these springs: the viscosity `β` and the shear springs' stiffness in
    /// compression per unit `k`.
    pub(super) fn with_physics(self, viscosity: f64, shear_compression: f64) -> Self {
        self.with_viscosity(viscosity)
            .with_compression(shear_compression)
    }

    /// Spring `s`'s stiffness in compression per unit `k` (1 unless softened).
    #[inline(always)]
    fn compression(&self, s: usize) -> T {
        self.comp.get(s).copied().unwrap_or_else(T::one)
    }
}

pub(super) type Lane<T, const L: usize> = [T; L];

/// What the spring forces read: positions and velocities `[B, P, 3]` and one `k`, `b` per
/// spring (then per curvature element).
#[derive(Clone, Copy)]
pub struct Inputs<'a, T> {
    /// Positions.
    pub x: &'a [T],
    /// Velocities.
    pub v: &'a [T],
    /// Stiffness.
    pub k: &'a [T],
    /// Damping.
    pub b: &'a [T],
}

/// What the backward kernels write (overwritten): `∂ℓ/∂x`, `∂ℓ/∂v` `[B, P, 3]` and `∂ℓ/∂k`,
/// `∂ℓ/∂b` `[S]` summed over clips.
pub struct Grads<'a, T> {
    /// `∂ℓ/∂x`.
    pub x: &'a mut [T],
    /// `∂ℓ/∂v`.
    pub v: &'a mut [T],
    /// `∂ℓ/∂k`.
    pub k: &'a mut [T],
    /// `∂ℓ/∂b`.
    pub b: &'a mut [T],
}

impl<T> Inputs<'_, T> {
    /// Panics unless `x`, `v` hold `n` values, whole clips of `g` (at least one), and `k`, `b`
    /// one per parameter of `g`.
    fn check(&self, g: &HostGraph, n: usize) {
        assert!(self.x.len() == n && self.v.len() == n);
        assert!(n.is_multiple_of(g.particles * 3) && n > 0);
        assert!(self.k.len() == g.num_params() && self.b.len() == g.num_params());
    }
}

impl<T> Grads<'_, T> {
    /// Panics unless `x`, `v` hold `n` values and `k`, `b` one per parameter of `g`.
    fn check(&self, g: &HostGraph, n: usize) {
        assert!(self.x.len() == n && self.v.len() == n);
        assert!(self.k.len() == g.num_params() && self.b.len() == g.num_params());
    }
}

/// One chunk of `L` clips as the kernels read it: the springs, the states as lanes `[P·3][L]`
/// and the per-spring `k`, `b`.
#[derive(Clone, Copy)]
pub(super) struct LaneSprings<'a, T, const L: usize> {
    pub(super) sp: &'a Springs<'a, T>,
    pub(super) x: &'a [Lane<T, L>],
    pub(super) v: &'a [Lane<T, L>],
    pub(super) k: &'a [T],
    pub(super) b: &'a [T],
}

impl<'a, T, const L: usize> LaneSprings<'a, T, L> {
    pub(super) fn new(
        sp: &'a Springs<'a, T>,
        x: &'a [Lane<T, L>],
        v: &'a [Lane<T, L>],
        k: &'a [T],
        b: &'a [T],
    ) -> Self {
        Self { sp, x, v, k, b }
    }
}

/// What the backward of one chunk adds to: `∂ℓ/∂x`, `∂ℓ/∂v` as lanes and the lane sums of
/// `∂ℓ/∂k`, `∂ℓ/∂b`.
pub(super) struct LaneGrads<'a, T, const L: usize> {
    pub(super) x: &'a mut [Lane<T, L>],
    pub(super) v: &'a mut [Lane<T, L>],
    pub(super) k: &'a mut [T],
    pub(super) b: &'a mut [T],
}

/// `[B, P·3]` rows of clips `first..first + L` as `[P·3][L]` (clips past the batch repeat the
/// last one, and their results are dropped).
pub(super) fn interleave<T: Copy, const L: usize>(
    src: &[T],
    stride: usize,
    first: usize,
    batch: usize,
    dst: &mut Vec<Lane<T, L>>,
) {
    dst.clear();
    dst.reserve(stride);
    let rows: [&[T]; L] = std::array::from_fn(|l| {
        let c = (first + l).min(batch - 1);
        &src[c * stride..(c + 1) * stride]
    });
    for i in 0..stride {
        dst.push(std::array::from_fn(|l| rows[l][i]));
    }
}

/// Writes the valid lanes of `[P·3][L]` back to `[n, P·3]` rows.
pub(super) fn deinterleave<T: Copy, const L: usize>(
    src: &[Lane<T, L>],
    stride: usize,
    dst: &mut [T],
) {
    for (l, row) in dst.chunks_mut(stride).enumerate() {
        for (i, out) in row.iter_mut().enumerate() {
            *out = src[i][l];
        }
    }
}

/// One spring of a chunk: its stiffness, damping and rest length, and per lane
/// `d = x_b − x_a`, `w = v_b − v_a`.
struct SpringLanes<T, const L: usize> {
    ks: T,
    bs: T,
    l0: T,
    d: [Lane<T, L>; 3],
    w: [Lane<T, L>; 3],
}

/// Spring `s` of the chunk `c`, whose ends' first lane rows are `a` and `bb`.
///
/// # Safety
/// `s` is one of `c`'s springs and `a`, `bb` its ends' rows (`3 ·` particle), within the
/// lengths [`chunk_forces`] asks for.
#[inline(always)]
unsafe fn spring_lanes<T: Float, const L: usize>(
    c: &LaneSprings<T, L>,
    s: usize,
    (a, bb): (usize, usize),
) -> SpringLanes<T, L> {
    // SAFETY: the caller's contract.
    unsafe {
        let (ks, bs, l0) = (
            *c.k.get_unchecked(s),
            *c.b.get_unchecked(s),
            *c.sp.l0.get_unchecked(s),
        );
        let mut d = [[T::zero(); L]; 3];
        let mut w = [[T::zero(); L]; 3];
        for i in 0..3 {
            let (xa, xb) = (c.x.get_unchecked(a + i), c.x.get_unchecked(bb + i));
            let (va, vb) = (c.v.get_unchecked(a + i), c.v.get_unchecked(bb + i));
            for l in 0..L {
                d[i][l] = xb[l] - xa[l];
                w[i][l] = vb[l] - va[l];
            }
        }
        SpringLanes { ks, bs, l0, d, w }
    }
}

/// Accumulates the spring forces of one chunk into `out` (`[P·3][L]`); `SOFT`: whether some
/// springs are softer in compression ([`Springs::with_compression`]; `false` builds the loop
/// without that test, the springs all linear).
///
/// # Safety
/// `x`, `v` and `out` hold `3 · sp.particles` lanes, `k` and `b` one value per spring.
#[inline(always)]
unsafe fn chunk_forces<T: Float, const L: usize, const SOFT: bool>(
    c: LaneSprings<T, L>,
    out: &mut [Lane<T, L>],
) {
    for (s, &(a, bb)) in c.sp.ends.iter().enumerate() {
        let (a, bb) = (3 * a as usize, 3 * bb as usize);
        // SAFETY: endpoints < particles (HostGraph::new) and the caller's length contract.
        unsafe {
            let SpringLanes { ks, bs, l0, d, w } = spring_lanes(&c, s, (a, bb));
            let nu = c.sp.visc * ks;
            let soft = if SOFT { c.sp.compression(s) } else { T::one() };
            let mut coef = [T::zero(); L];
            for l in 0..L {
                let len2 = d[0][l] * d[0][l] + d[1][l] * d[1][l] + d[2][l] * d[2][l];
                let wd = w[0][l] * d[0][l] + w[1][l] * d[1][l] + w[2][l] * d[2][l];
                let inv = T::one() / len2.sqrt();
                let stretch = T::one() - l0 * inv;
                let kl = if SOFT && stretch < T::zero() {
                    ks * soft
                } else {
                    ks
                };
                coef[l] = kl * stretch + bs * wd * inv * inv;
            }
            for c in 0..3 {
                let mut f = [T::zero(); L];
                for l in 0..L {
                    f[l] = coef[l] * d[c][l];
                }
                if nu != T::zero() {
                    for l in 0..L {
                        f[l] = f[l] + nu * w[c][l];
                    }
                }
                scatter_pair(out, (a + c, bb + c), &f);
            }
        }
    }
}

/// Back-propagates `gf` (`[P·3][L]`) through the spring forces of one chunk: adds `S_xᵀ gf`
/// to `gx`, `S_vᵀ gf` to `gv`, and the lane sums of `∂ℓ/∂k`, `∂ℓ/∂b` to `gk`, `gb`.
///
/// # Safety
/// As [`chunk_forces`], and `gk`, `gb` hold one value per spring.
#[inline(always)]
unsafe fn chunk_backward<T: Float, const L: usize, const SOFT: bool>(
    c: LaneSprings<T, L>,
    gf: &[Lane<T, L>],
    g: &mut LaneGrads<T, L>,
) {
    let (gx, gv, gk, gb) = (&mut *g.x, &mut *g.v, &mut *g.k, &mut *g.b);
    let two = T::one() + T::one();
    for (s, &(a, bb)) in c.sp.ends.iter().enumerate() {
        let (a, bb) = (3 * a as usize, 3 * bb as usize);
        // SAFETY: as in `chunk_forces`.
        unsafe {
            let SpringLanes { ks, bs, l0, d, w } = spring_lanes(&c, s, (a, bb));
            let nu = c.sp.visc * ks;
            let soft = if SOFT { c.sp.compression(s) } else { T::one() };
            let mut g = [[T::zero(); L]; 3];
            for c in 0..3 {
                let (ga, gbb) = (gf.get_unchecked(a + c), gf.get_unchecked(bb + c));
                for l in 0..L {
                    g[c][l] = ga[l] - gbb[l];
                }
            }
            let (mut coef, mut gd, mut a1, mut a2) = (
                [T::zero(); L],
                [T::zero(); L],
                [T::zero(); L],
                [T::zero(); L],
            );
            let (mut dk, mut db) = (T::zero(), T::zero());
            for l in 0..L {
                let len2 = d[0][l] * d[0][l] + d[1][l] * d[1][l] + d[2][l] * d[2][l];
                let wd = w[0][l] * d[0][l] + w[1][l] * d[1][l] + w[2][l] * d[2][l];
                let gdl = g[0][l] * d[0][l] + g[1][l] * d[1][l] + g[2][l] * d[2][l];
                let inv = T::one() / len2.sqrt();
                let inv2 = inv * inv;
                let stretch = T::one() - l0 * inv;
                // A softened spring in compression: k_s · soft in place of k_s.
                let f = if SOFT && stretch < T::zero() {
                    soft
                } else {
                    T::one()
                };
                let kl = if SOFT { ks * f } else { ks };
                coef[l] = kl * stretch + bs * wd * inv2;
                gd[l] = gdl;
                dk = dk
                    + if SOFT {
                        gdl * stretch * f
                    } else {
                        gdl * stretch
                    };
                db = db + gdl * wd * inv2;
                a1[l] = kl * l0 * inv2 * inv - two * bs * wd * inv2 * inv2;
                a2[l] = bs * inv2;
                if nu != T::zero() {
                    let gw = g[0][l] * w[0][l] + g[1][l] * w[1][l] + g[2][l] * w[2][l];
                    dk = dk + c.sp.visc * gw;
                }
            }
            *gk.get_unchecked_mut(s) = *gk.get_unchecked(s) + dk;
            *gb.get_unchecked_mut(s) = *gb.get_unchecked(s) + db;
            for c in 0..3 {
                // ∂ℓ/∂d = c g + (g·d)(a1 d + a2 w); ∂ℓ/∂w = (g·d) a2 d + ν g.
                let mut dd = [T::zero(); L];
                let mut dw = [T::zero(); L];
                for l in 0..L {
                    dd[l] = coef[l] * g[c][l] + gd[l] * (a1[l] * d[c][l] + a2[l] * w[c][l]);
                    dw[l] = gd[l] * a2[l] * d[c][l];
                }
                if nu != T::zero() {
                    for l in 0..L {
                        dw[l] = dw[l] + nu * g[c][l];
                    }
                }
                scatter_pair(gx, (bb + c, a + c), &dd);
                scatter_pair(gv, (bb + c, a + c), &dw);
            }
        }
    }
}

/// Adds `d` to lane row `plus` and subtracts it from row `minus`: a spring's equal and
/// opposite pair.
///
/// # Safety
/// Both rows exist.
#[inline(always)]
unsafe fn scatter_pair<T: Float, const L: usize>(
    rows: &mut [Lane<T, L>],
    (plus, minus): (usize, usize),
    d: &Lane<T, L>,
) {
    // SAFETY: the caller's contract.
    let p = unsafe { rows.get_unchecked_mut(plus) };
    for l in 0..L {
        p[l] = p[l] + d[l];
    }
    // SAFETY: as above.
    let m = unsafe { rows.get_unchecked_mut(minus) };
    for l in 0..L {
        m[l] = m[l] - d[l];
    }
}

/// `a_i − 2a_j + a_l` of the lane rows `i`, `j`, `l` (component offsets included).
///
/// # Safety
/// The three rows exist.
#[inline(always)]
unsafe fn second_difference<T: Float, const L: usize>(
    a: &[Lane<T, L>],
    (i, j, l): (usize, usize, usize),
) -> Lane<T, L> {
    let two = T::one() + T::one();
    // SAFETY: forwarded contract.
    let (ai, aj, al) = unsafe { (a.get_unchecked(i), a.get_unchecked(j), a.get_unchecked(l)) };
    std::array::from_fn(|q| ai[q] - two * aj[q] + al[q])
}

/// Adds `s · (w, −2w, w)` to the lane rows `i`, `j`, `l`: the transpose of
/// [`second_difference`].
///
/// # Safety
/// The three rows exist.
#[inline(always)]
unsafe fn add_second_difference_transpose<T: Float, const L: usize>(
    acc: &mut [Lane<T, L>],
    (i, j, l): (usize, usize, usize),
    w: &Lane<T, L>,
    s: T,
) {
    let minus_two_s = -(s + s);
    for (row, f) in [(i, s), (j, minus_two_s), (l, s)] {
        // SAFETY: forwarded contract.
        let a = unsafe { acc.get_unchecked_mut(row) };
        for q in 0..L {
            a[q] = a[q] + f * w[q];
        }
    }
}

/// Accumulates the curvature elements' forces of one chunk into `out`: with `e = x_i − 2x_j +
/// x_l` and `f = κ e` (`κ` the element's entry of `k` after the springs'), `−f` on `i` and `l`
/// and `2f` on `j`. The elements have no damping: their entries of `b` (which keep `k` and `b`
/// paired, one entry per spring and per element) are neither read nor given a gradient.
///
/// # Safety
/// As [`chunk_forces`], and `k` holds one value per spring and per element.
#[inline(always)]
unsafe fn chunk_curvature<T: Float, const L: usize>(
    sp: &Springs<T>,
    x: &[Lane<T, L>],
    k: &[T],
    out: &mut [Lane<T, L>],
) {
    let offset = sp.ends.len();
    for (t, &(i, j, l)) in sp.triples.iter().enumerate() {
        let rows = (3 * i as usize, 3 * j as usize, 3 * l as usize);
        // SAFETY: element indices < particles (HostGraph::with_curvature) and the caller's
        // length contract.
        unsafe {
            let kt = *k.get_unchecked(offset + t);
            for c in 0..3 {
                let rows = (rows.0 + c, rows.1 + c, rows.2 + c);
                let e = second_difference(x, rows);
                let f: Lane<T, L> = std::array::from_fn(|q| kt * e[q]);
                add_second_difference_transpose(out, rows, &f, -T::one());
            }
        }
    }
}

/// Back-propagates `gf` through the curvature elements' forces of one chunk (see
/// [`chunk_curvature`]): with `q = −(g_i − 2g_j + g_l)`, `∂ℓ/∂e = κ q` and `∂ℓ/∂κ = e·q`
/// (summed over the lanes).
///
/// # Safety
/// As [`chunk_curvature`], and `gk` holds one value per spring and per element.
#[inline(always)]
unsafe fn chunk_curvature_backward<T: Float, const L: usize>(
    sp: &Springs<T>,
    x: &[Lane<T, L>],
    k: &[T],
    gf: &[Lane<T, L>],
    gx: &mut [Lane<T, L>],
    gk: &mut [T],
) {
    let offset = sp.ends.len();
    for (t, &(i, j, l)) in sp.triples.iter().enumerate() {
        let rows = (3 * i as usize, 3 * j as usize, 3 * l as usize);
        // SAFETY: as in `chunk_curvature`.
        unsafe {
            let kt = *k.get_unchecked(offset + t);
            let mut dk = T::zero();
            for c in 0..3 {
                let rows = (rows.0 + c, rows.1 + c, rows.2 + c);
                let g = second_difference(gf, rows);
                let q: Lane<T, L> = std::array::from_fn(|p| -g[p]);
                let e = second_difference(x, rows);
                for p in 0..L {
                    dk = dk + e[p] * q[p];
                }
                add_second_difference_transpose(gx, rows, &q, kt);
            }
            *gk.get_unchecked_mut(offset + t) = *gk.get_unchecked(offset + t) + dk;
        }
    }
}

/// Whether the 8-lane AVX2 kernels may run.
pub(super) fn wide() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Clips a chunk of the narrow kernels holds (the wide ones, 8 with AVX2, take 16 clips or more).
pub const NARROW_LANES: usize = 4;

macro_rules! dispatch_lanes {
    ($batch:expr, $t:ty, $f:ident, ($($arg:expr),*)) => {{
        // 8 lanes with AVX2 when there are enough clips to keep both cores busy.
        if std::mem::size_of::<$t>() == 4 && wide() && $batch >= 16 {
            $f::<$t, 8>($($arg),*)
        } else {
            $f::<$t, NARROW_LANES>($($arg),*)
        }
    }};
}

/// [`chunk_forces`] compiled with AVX2 (used for 8 lanes, after `wide()` said yes).
///
/// # Safety
/// As [`chunk_forces`], and the CPU supports AVX2.
#[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2"))]
unsafe fn chunk_forces_wide<T: Float, const L: usize, const SOFT: bool>(
    c: LaneSprings<T, L>,
    out: &mut [Lane<T, L>],
) {
    // SAFETY: forwarded contract.
    unsafe { chunk_forces::<T, L, SOFT>(c, out) }
}

/// [`chunk_backward`] compiled with AVX2.
///
/// # Safety
/// As [`chunk_backward`], and the CPU supports AVX2.
#[cfg_attr(target_arch = "x86_64", target_feature(enable = "avx2"))]
unsafe fn chunk_backward_wide<T: Float, const L: usize, const SOFT: bool>(
    c: LaneSprings<T, L>,
    gf: &[Lane<T, L>],
    g: &mut LaneGrads<T, L>,
) {
    // SAFETY: forwarded contract.
    unsafe { chunk_backward::<T, L, SOFT>(c, gf, g) }
}

/// Spring forces of one chunk, with the AVX2 build of the loop for 8 lanes.
///
/// # Safety
/// As [`chunk_forces`]; `L == 8` only after `wide()` returned true.
pub(super) unsafe fn run_forces<T: Float, const L: usize>(
    c: LaneSprings<T, L>,
    out: &mut [Lane<T, L>],
) {
    // SAFETY: forwarded contract; 8 lanes are only dispatched on AVX2 machines.
    unsafe {
        match (L == 8, c.sp.comp.is_empty()) {
            (true, true) => chunk_forces_wide::<T, L, false>(c, out),
            (true, false) => chunk_forces_wide::<T, L, true>(c, out),
            (false, true) => chunk_forces::<T, L, false>(c, out),
            (false, false) => chunk_forces::<T, L, true>(c, out),
        }
        if !c.sp.triples.is_empty() {
            chunk_curvature(c.sp, c.x, c.k, out)
        }
    }
    if let Some(scale) = &c.sp.scale {
        for (i, f) in out.iter_mut().enumerate() {
            let s = scale[i / 3];
            f.iter_mut().for_each(|f| *f = *f * s);
        }
    }
}

/// Spring backward of one chunk, with the AVX2 build of the loop for 8 lanes.
///
/// # Safety
/// As [`chunk_backward`]; `L == 8` only after `wide()` returned true.
pub(super) unsafe fn run_backward<T: Float, const L: usize>(
    c: LaneSprings<T, L>,
    gf: &[Lane<T, L>],
    g: &mut LaneGrads<T, L>,
) {
    // The scale multiplies the forces, so it multiplies their upstream gradient.
    let scaled: Vec<Lane<T, L>>;
    let gf = match &c.sp.scale {
        Some(scale) => {
            scaled = gf
                .iter()
                .enumerate()
                .map(|(i, g)| g.map(|g| g * scale[i / 3]))
                .collect();
            &scaled[..]
        }
        None => gf,
    };
    // SAFETY: forwarded contract; 8 lanes are only dispatched on AVX2 machines.
    unsafe {
        match (L == 8, c.sp.comp.is_empty()) {
            (true, true) => chunk_backward_wide::<T, L, false>(c, gf, g),
            (true, false) => chunk_backward_wide::<T, L, true>(c, gf, g),
            (false, true) => chunk_backward::<T, L, false>(c, gf, g),
            (false, false) => chunk_backward::<T, L, true>(c, gf, g),
        }
        if !c.sp.triples.is_empty() {
            chunk_curvature_backward(c.sp, c.x, c.k, gf, g.x, g.k)
        }
    }
}

/// Spring forces `[B, P, 3]` into `out` (overwritten).
pub fn forces<T: Float + Send + Sync>(g: &HostGraph, s: Inputs<T>, out: &mut [T]) {
    s.check(g, out.len());
    let batch = out.len() / (g.particles * 3);
    dispatch_lanes!(batch, T, forces_lanes, (g, s, out))
}

#[inline(always)]
fn forces_lanes<T: Float + Send + Sync, const L: usize>(
    g: &HostGraph,
    s: Inputs<T>,
    out: &mut [T],
) {
    let Inputs { x, v, k, b } = s;
    let sp = Springs::<T>::new(g);
    let stride = g.particles * 3;
    let batch = out.len() / stride;
    out.par_chunks_mut(L * stride)
        .enumerate()
        .for_each(|(ch, out)| {
            let (mut xs, mut vs) = (Vec::new(), Vec::new());
            interleave::<T, L>(x, stride, ch * L, batch, &mut xs);
            interleave::<T, L>(v, stride, ch * L, batch, &mut vs);
            let mut acc = vec![[T::zero(); L]; stride];
            // SAFETY: every lane buffer holds `stride` = 3P lanes; k, b hold S values (asserted).
            let chunk = LaneSprings::new(&sp, &xs, &vs, k, b);
            unsafe { run_forces(chunk, &mut acc) };
            deinterleave(&acc, stride, out);
        });
}

/// Gradients of the spring forces: `gx`, `gv` `[B, P, 3]` (overwritten) and `gk`, `gb` `[S]`
/// (overwritten, summed over clips), given `grad = ∂ℓ/∂F` `[B, P, 3]`.
pub fn forces_backward<T: Float + Send + Sync>(
    g: &HostGraph,
    s: Inputs<T>,
    grad: &[T],
    grads: Grads<T>,
) {
    let n = grad.len();
    s.check(g, n);
    grads.check(g, n);
    let stride = g.particles * 3;
    let no_step = None;
    dispatch_lanes!(n / stride, T, backward_lanes, (g, s, no_step, grad, grads))
}

/// Step inputs that are data, not parameters: pin flags `[B, P]` (1 = pinned) and the pinned
/// particles' prescribed positions and velocities `[B, P, 3]`.
#[derive(Clone, Copy)]
pub struct Pins<'a, T> {
    /// 1 for pinned particles, `[B, P]`.
    pub pinned: &'a [T],
    /// Prescribed positions `[B, P, 3]`.
    pub x: &'a [T],
    /// Prescribed velocities `[B, P, 3]`.
    pub v: &'a [T],
}

/// One fused semi-implicit Euler step: writes `x'`, `v'` and the net force `f` `[B, P, 3]`.
pub fn step<T: Float + Send + Sync>(
    g: &HostGraph,
    s: Inputs<T>,
    pins: Pins<T>,
    params: StepParams,
    out: &mut [T],
) {
    let (stride, n) = (g.particles * 3, s.x.len());
    s.check(g, n);
    assert!(pins.x.len() == n && pins.v.len() == n && pins.pinned.len() * 3 == n);
    assert!(out.len() == 3 * n);
    dispatch_lanes!(n / stride, T, step_lanes, (g, s, pins, params, out))
}

pub(super) fn cast<T: Float>(v: f64) -> T {
    T::from(v).expect("float")
}

/// [`StepParams`] in the kernels' float type: the semi-implicit Euler update of one coordinate,
/// written once so that [`step`] and [`frame`] round alike.
#[derive(Clone, Copy)]
struct StepConsts<T> {
    h: T,
    /// `h / m`.
    hm: T,
    /// The Rayleigh constant.
    c: T,
    /// Gravity's force per coordinate, `m g`.
    mg: [T; 3],
}

impl<T: Float> StepConsts<T> {
    fn new(params: &StepParams) -> Self {
        Self {
            h: cast(params.h),
            hm: cast(params.h / params.mass),
            c: cast(params.rayleigh),
            mg: params.gravity.map(|a| cast(a * params.mass)),
        }
    }

    /// Coordinate `d` of a free particle with spring force `f` at `(x, v)`: the net force
    /// `f + m g − c v`, then `v' = v + h/m · net`, `x' = x + h v'`. Returns `(net, x', v')`.
    #[inline(always)]
    fn update(&self, d: usize, f: T, x: T, v: T) -> (T, T, T) {
        let net = f + self.mg[d] - self.c * v;
        let vn = v + self.hm * net;
        (net, x + self.h * vn, vn)
    }
}

#[inline(always)]
fn step_lanes<T: Float + Send + Sync, const L: usize>(
    g: &HostGraph,
    s: Inputs<T>,
    pins: Pins<T>,
    params: StepParams,
    out: &mut [T],
) {
    let Inputs { x, v, k, b } = s;
    let sp = Springs::<T>::new(g).with_physics(params.viscosity, params.shear_compression);
    let stride = g.particles * 3;
    let n = x.len();
    let batch = n / stride;
    let consts = StepConsts::<T>::new(&params);
    let (ox, rest) = out.split_at_mut(n);
    let (ov, of) = rest.split_at_mut(n);
    ox.par_chunks_mut(L * stride)
        .zip(
            ov.par_chunks_mut(L * stride)
                .zip(of.par_chunks_mut(L * stride)),
        )
        .enumerate()
        .for_each(|(ch, (ox, (ov, of)))| {
            let (mut xs, mut vs) = (Vec::new(), Vec::new());
            interleave::<T, L>(x, stride, ch * L, batch, &mut xs);
            interleave::<T, L>(v, stride, ch * L, batch, &mut vs);
            let mut f = vec![[T::zero(); L]; stride];
            // SAFETY: lane buffers hold 3P lanes; k, b hold S values (asserted by `step`).
            let chunk = LaneSprings::new(&sp, &xs, &vs, k, b);
            unsafe { run_forces(chunk, &mut f) };
            // Per clip of the chunk, per particle: its pin read once, its three coordinates
            // integrated from the lanes (no index arithmetic per coordinate).
            let rows = ox
                .chunks_exact_mut(stride)
                .zip(ov.chunks_exact_mut(stride))
                .zip(of.chunks_exact_mut(stride));
            for (l, ((ox, ov), of)) in rows.enumerate() {
                let clip = ch * L + l;
                let row = clip * stride..(clip + 1) * stride;
                let pinned = &pins.pinned[clip * g.particles..(clip + 1) * g.particles];
                let (px, pv) = (&pins.x[row.clone()], &pins.v[row]);
                for (p, &pin) in pinned.iter().enumerate() {
                    let pinned = pin > T::zero();
                    for d in 0..3 {
                        let i = 3 * p + d;
                        let (net, xn, vn) = consts.update(d, f[i][l], xs[i][l], vs[i][l]);
                        of[i] = net;
                        (ox[i], ov[i]) = if pinned { (px[i], pv[i]) } else { (xn, vn) };
                    }
                }
            }
        });
}

/// The pins of a whole frame: pin flags `[B, P]` (1 = pinned) and the frame's first and last
/// positions `[B, P, 3]`, between which the pinned particles move at a constant velocity.
#[derive(Clone, Copy)]
pub struct FramePins<'a, T> {
    /// 1 for pinned particles, `[B, P]`.
    pub pinned: &'a [T],
    /// Positions at the frame's start.
    pub here: &'a [T],
    /// Positions at the frame's end.
    pub next: &'a [T],
}

/// One data frame of `frame_dt` in `substeps` fused steps of [`step`] (each of
/// `params.h = frame_dt / substeps`), the clips kept as lanes from the first substep to the last:
/// writes `x'`, `v'` `[B, P, 3]` stacked into `out` `[2, B, P, 3]`.
///
/// The pinned particles follow `crate::sim::step_frame` to the bit: after substep `s` of `n`
/// at `here · (1 − t) + next · t`, `t = s / n`, each factor rounded to `T` as a tensor's scalar
/// is, and at `next` after the last; their velocity `(next − here) / frame_dt`.
pub fn frame<T: Float + Send + Sync>(
    g: &HostGraph,
    s: Inputs<T>,
    pins: FramePins<T>,
    params: StepParams,
    (substeps, frame_dt): (usize, f64),
    out: &mut [T],
) {
    let (stride, n) = (g.particles * 3, s.x.len());
    s.check(g, n);
    assert!(pins.here.len() == n && pins.next.len() == n && pins.pinned.len() * 3 == n);
    assert!(out.len() == 2 * n && substeps > 0);
    let span = (substeps, frame_dt);
    dispatch_lanes!(n / stride, T, frame_lanes, (g, s, pins, params, span, out))
}

#[inline(always)]
fn frame_lanes<T: Float + Send + Sync, const L: usize>(
    g: &HostGraph,
    s: Inputs<T>,
    pins: FramePins<T>,
    params: StepParams,
    (substeps, frame_dt): (usize, f64),
    out: &mut [T],
) {
    let Inputs { x, v, k, b } = s;
    let sp = Springs::<T>::new(g).with_physics(params.viscosity, params.shear_compression);
    let (particles, stride) = (g.particles, g.particles * 3);
    let n = x.len();
    let batch = n / stride;
    let consts = StepConsts::<T>::new(&params);
    let inv_frame = cast::<T>(1.0 / frame_dt);
    // The pins' weights on `here` and `next` after each substep but the last.
    let weights: Vec<(T, T)> = (1..substeps)
        .map(|s| {
            let t = s as f64 / substeps as f64;
            (cast::<T>(1.0 - t), cast::<T>(t))
        })
        .collect();
    let (ox, ov) = out.split_at_mut(n);
    ox.par_chunks_mut(L * stride)
        .zip(ov.par_chunks_mut(L * stride))
        .enumerate()
        .for_each(|(ch, (ox, ov))| {
            let lanes = |src: &[T]| {
                let mut dst = Vec::new();
                interleave::<T, L>(src, stride, ch * L, batch, &mut dst);
                dst
            };
            let (mut xs, mut vs) = (lanes(x), lanes(v));
            let (here, next) = (lanes(pins.here), lanes(pins.next));
            // The pinned (particle, lane) pairs: every lane integrates every particle without a
            // branch, then these are set to their path.
            let pinned: Vec<(usize, usize)> = (0..particles)
                .flat_map(|p| (0..L).map(move |l| (p, l)))
                .filter(|&(p, l)| {
                    let clip = (ch * L + l).min(batch - 1);
                    pins.pinned[clip * particles + p] > T::zero()
                })
                .collect();
            let mut f = vec![[T::zero(); L]; stride];
            for sub in 0..substeps {
                f.fill([T::zero(); L]);
                // SAFETY: lane buffers hold 3P lanes; k, b hold S values (asserted by `frame`).
                let chunk = LaneSprings::new(&sp, &xs, &vs, k, b);
                unsafe { run_forces(chunk, &mut f) };
                let particles = xs
                    .chunks_exact_mut(3)
                    .zip(vs.chunks_exact_mut(3))
                    .zip(f.chunks_exact(3));
                for ((x3, v3), f3) in particles {
                    for (d, ((x, v), f)) in x3.iter_mut().zip(v3).zip(f3).enumerate() {
                        for l in 0..L {
                            (_, x[l], v[l]) = consts.update(d, f[l], x[l], v[l]);
                        }
                    }
                }
                let weight = weights.get(sub).copied();
                for &(p, l) in &pinned {
                    for i in 3 * p..3 * p + 3 {
                        let (from, to) = (here[i][l], next[i][l]);
                        xs[i][l] = match weight {
                            Some((w_from, w_to)) => from * w_from + to * w_to,
                            None => to,
                        };
                        vs[i][l] = (to - from) * inv_frame;
                    }
                }
            }
            deinterleave(&xs, stride, ox);
            deinterleave(&vs, stride, ov);
        });
}

/// Gradients of [`step`]: given `gout = (∂ℓ/∂x', ∂ℓ/∂v', ∂ℓ/∂f)` stacked `[3, B, P, 3]`, writes
/// `∂ℓ/∂x`, `∂ℓ/∂v` `[B, P, 3]` and `∂ℓ/∂k`, `∂ℓ/∂b` `[S]`.
pub(crate) fn step_backward<T: Float + Send + Sync>(
    g: &HostGraph,
    s: Inputs<T>,
    pinned: &[T],
    params: StepParams,
    gout: &[T],
    grads: Grads<T>,
) {
    let (stride, n) = (g.particles * 3, s.x.len());
    s.check(g, n);
    grads.check(g, n);
    assert!(pinned.len() * 3 == n && gout.len() == 3 * n);
    let step = Some((pinned, params));
    dispatch_lanes!(n / stride, T, backward_lanes, (g, s, step, gout, grads))
}

type StepInfo<'a, T> = Option<(&'a [T], StepParams)>;

/// The backward of the spring forces (`step = None`, `grad` = `∂ℓ/∂F` `[B, P, 3]`) or of a
/// whole step (`step = Some((pinned, params))`, `grad` = `[3, B, P, 3]`).
#[inline(always)]
fn backward_lanes<T: Float + Send + Sync, const L: usize>(
    g: &HostGraph,
    s: Inputs<T>,
    step: StepInfo<T>,
    grad: &[T],
    grads: Grads<T>,
) {
    let Inputs { x, v, k, b } = s;
    let (gx, gv, gk, gb) = (grads.x, grads.v, grads.k, grads.b);
    let sp = match step {
        Some((_, p)) => Springs::<T>::new(g).with_physics(p.viscosity, p.shear_compression),
        None => Springs::<T>::new(g),
    };
    let stride = g.particles * 3;
    let n = x.len();
    let batch = n / stride;
    let s_count = g.num_params();
    let partials: Vec<Vec<T>> = gx
        .par_chunks_mut(L * stride)
        .zip(gv.par_chunks_mut(L * stride))
        .enumerate()
        .map(|(ch, (gx, gv))| {
            let (mut xs, mut vs, mut gfs) = (Vec::new(), Vec::new(), Vec::new());
            interleave::<T, L>(x, stride, ch * L, batch, &mut xs);
            interleave::<T, L>(v, stride, ch * L, batch, &mut vs);
            let clips = gx.len() / stride;
            let mut acc_x = vec![[T::zero(); L]; stride];
            let mut acc_v = vec![[T::zero(); L]; stride];
            match step {
                None => interleave::<T, L>(grad, stride, ch * L, batch, &mut gfs),
                Some((pinned, params)) => {
                    // ḡx'' = free ∂ℓ/∂x', ḡv'' = free ∂ℓ/∂v' + h ḡx'', G = ∂ℓ/∂f + h/m ḡv''.
                    let (h, hm) = (cast::<T>(params.h), cast::<T>(params.h / params.mass));
                    let (gxo, rest) = grad.split_at(n);
                    let (gvo, gfo) = rest.split_at(n);
                    gfs.resize(stride, [T::zero(); L]);
                    for l in 0..clips {
                        let clip = ch * L + l;
                        let row = clip * stride;
                        for i in 0..stride {
                            let free = pinned[clip * g.particles + i / 3] <= T::zero();
                            let (gxx, gvv) = if free {
                                let gxx = gxo[row + i];
                                (gxx, gvo[row + i] + h * gxx)
                            } else {
                                (T::zero(), T::zero())
                            };
                            gfs[i][l] = gfo[row + i] + hm * gvv;
                            acc_x[i][l] = gxx;
                            acc_v[i][l] = gvv;
                        }
                    }
                }
            }
            let mut pk = vec![T::zero(); 2 * s_count];
            let (pk_k, pk_b) = pk.split_at_mut(s_count);
            if clips < L {
                // Padding lanes repeat the last clip: zero their upstream gradient.
                for lane in gfs.iter_mut() {
                    for value in lane.iter_mut().skip(clips) {
                        *value = T::zero();
                    }
                }
            }
            // SAFETY: lane buffers hold 3P lanes; k, b, pk_k, pk_b hold S values.
            let chunk = LaneSprings::new(&sp, &xs, &vs, k, b);
            let mut g = LaneGrads {
                x: &mut acc_x,
                v: &mut acc_v,
                k: pk_k,
                b: pk_b,
            };
            unsafe { run_backward(chunk, &gfs, &mut g) };
            if let Some((_, params)) = step {
                // ∂ℓ/∂v gets −c G from the Rayleigh force.
                let c = cast::<T>(params.rayleigh);
                for i in 0..stride {
                    for l in 0..L {
                        acc_v[i][l] = acc_v[i][l] - c * gfs[i][l];
                    }
                }
            }
            deinterleave(&acc_x, stride, gx);
            deinterleave(&acc_v, stride, gv);
            pk
        })
        .collect();
    gk.fill(T::zero());
    gb.fill(T::zero());
    for p in partials {
        for s in 0..s_count {
            gk[s] = gk[s] + p[s];
            gb[s] = gb[s] + p[s_count + s];
        }
    }
}
