//! CPU kernels of the fused spring-force op: plain Rust over slices, clips in parallel.
//!
//! Layouts are row-major: states `[B, P, 3]`, per-spring values `[S]`. For spring
//! `s = (a, b)` with `d = x_b − x_a`, `w = v_b − v_a`, `L = |d|`:
//!
//! forward (Eq. 4, Eq. 2): `f_s = c_s d`, `c_s = k_s (1 − l0_s/L) + b_s (w·d)/L²`;
//! `F_a += f_s`, `F_b −= f_s`.
//!
//! backward, given `G = ∂ℓ/∂F` and `g = G_a − G_b = ∂ℓ/∂f_s`:
//! - `∂ℓ/∂k_s = Σ_clips (g·d)(1 − l0/L)`, `∂ℓ/∂b_s = Σ_clips (g·d)(w·d)/L²`;
//! - `∂ℓ/∂d = c g + (g·d) ∂c/∂d`, `∂c/∂d = k l0 d/L³ + b (w/L² − 2 (w·d) d/L⁴)`;
//! - `∂ℓ/∂w = (g·d) b d/L²`;
//! - `∂ℓ/∂x_b += ∂ℓ/∂d`, `∂ℓ/∂x_a −= ∂ℓ/∂d`, and the same for `v` with `∂ℓ/∂w`.

use num_traits::Float;
use rayon::prelude::*;

use super::HostGraph;

type V3<T> = [T; 3];

#[inline(always)]
fn sub<T: Float>(a: V3<T>, b: V3<T>) -> V3<T> {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[inline(always)]
fn dot<T: Float>(a: V3<T>, b: V3<T>) -> T {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Views a `[P·3]` slice as `P` points.
#[inline(always)]
fn points<T>(s: &[T]) -> &[V3<T>] {
    let (pts, rest) = s.as_chunks::<3>();
    debug_assert!(rest.is_empty());
    pts
}

#[inline(always)]
fn points_mut<T>(s: &mut [T]) -> &mut [V3<T>] {
    let (pts, rest) = s.as_chunks_mut::<3>();
    debug_assert!(rest.is_empty());
    pts
}

/// The springs with checked indices, so that the loops can skip bounds checks.
struct Springs<'a, T> {
    ends: &'a [(u32, u32)],
    l0: Vec<T>,
    particles: usize,
}

impl<'a, T: Float> Springs<'a, T> {
    fn new(g: &'a HostGraph) -> Self {
        Self {
            ends: &g.ends,
            l0: g.rest_length.iter().map(|&l| T::from(l).expect("float")).collect(),
            particles: g.particles,
        }
    }

    /// `(a, b, l0)` of spring `s`. Endpoints were checked against `particles` when the graph
    /// was built, and every state slice is checked to hold `particles` points.
    #[inline(always)]
    fn get(&self, s: usize) -> (usize, usize, T) {
        let (a, b) = self.ends[s];
        (a as usize, b as usize, self.l0[s])
    }
}

/// Spring forces `[B, P, 3]` into `out` (overwritten).
pub fn forces<T: Float + Send + Sync>(g: &HostGraph, x: &[T], v: &[T], k: &[T], b: &[T], out: &mut [T]) {
    let springs = Springs::<T>::new(g);
    let stride = g.particles * 3;
    assert!(x.len() == out.len() && v.len() == out.len() && out.len() % stride == 0);
    assert!(k.len() == g.ends.len() && b.len() == g.ends.len());
    out.par_chunks_mut(stride)
        .zip(x.par_chunks(stride).zip(v.par_chunks(stride)))
        .for_each(|(out, (x, v))| clip_forces(&springs, points(x), points(v), k, b, points_mut(out)));
}

fn clip_forces<T: Float>(sp: &Springs<T>, x: &[V3<T>], v: &[V3<T>], k: &[T], b: &[T], out: &mut [V3<T>]) {
    assert!(x.len() == sp.particles && v.len() == sp.particles && out.len() == sp.particles);
    out.fill([T::zero(); 3]);
    for s in 0..sp.ends.len() {
        let (ia, ib, l0) = sp.get(s);
        // SAFETY: ia, ib < particles (checked at graph construction) and every slice holds
        // `particles` points (asserted above).
        unsafe {
            let d = sub(*x.get_unchecked(ib), *x.get_unchecked(ia));
            let w = sub(*v.get_unchecked(ib), *v.get_unchecked(ia));
            let inv = T::one() / dot(d, d).sqrt();
            let c = *k.get_unchecked(s) * (T::one() - l0 * inv) + *b.get_unchecked(s) * dot(w, d) * inv * inv;
            let fa = out.get_unchecked_mut(ia);
            for i in 0..3 {
                fa[i] = fa[i] + c * d[i];
            }
            let fb = out.get_unchecked_mut(ib);
            for i in 0..3 {
                fb[i] = fb[i] - c * d[i];
            }
        }
    }
}

/// Gradients of the spring forces: `gx`, `gv` `[B, P, 3]` (overwritten) and `gk`, `gb` `[S]`
/// (overwritten, summed over clips), given `grad = ∂ℓ/∂F` `[B, P, 3]`.
#[allow(clippy::too_many_arguments)]
pub fn forces_backward<T: Float + Send + Sync>(
    g: &HostGraph,
    x: &[T],
    v: &[T],
    k: &[T],
    b: &[T],
    grad: &[T],
    gx: &mut [T],
    gv: &mut [T],
    gk: &mut [T],
    gb: &mut [T],
) {
    let springs = Springs::<T>::new(g);
    let stride = g.particles * 3;
    let s_count = g.ends.len();
    assert!(x.len() == gx.len() && v.len() == gx.len() && grad.len() == gx.len() && gv.len() == gx.len());
    assert!(gx.len() % stride == 0 && k.len() == s_count && b.len() == s_count);
    assert!(gk.len() == s_count && gb.len() == s_count);
    let partial = gx
        .par_chunks_mut(stride)
        .zip(gv.par_chunks_mut(stride))
        .zip(x.par_chunks(stride).zip(v.par_chunks(stride)).zip(grad.par_chunks(stride)))
        .fold(
            || vec![T::zero(); 2 * s_count],
            |mut acc, ((gx, gv), ((x, v), grad))| {
                let (pk, pb) = acc.split_at_mut(s_count);
                let states = (points(x), points(v), points(grad));
                clip_backward(&springs, states, k, b, points_mut(gx), points_mut(gv), pk, pb);
                acc
            },
        )
        .reduce(
            || vec![T::zero(); 2 * s_count],
            |mut a, b| {
                for (x, y) in a.iter_mut().zip(b) {
                    *x = *x + y;
                }
                a
            },
        );
    gk.copy_from_slice(&partial[..s_count]);
    gb.copy_from_slice(&partial[s_count..]);
}

type States<'a, T> = (&'a [V3<T>], &'a [V3<T>], &'a [V3<T>]);

#[allow(clippy::too_many_arguments)]
fn clip_backward<T: Float>(
    sp: &Springs<T>,
    (x, v, grad): States<T>,
    k: &[T],
    b: &[T],
    gx: &mut [V3<T>],
    gv: &mut [V3<T>],
    gk: &mut [T],
    gb: &mut [T],
) {
    let n = sp.particles;
    assert!(x.len() == n && v.len() == n && grad.len() == n && gx.len() == n && gv.len() == n);
    assert!(gk.len() == sp.ends.len() && gb.len() == sp.ends.len());
    gx.fill([T::zero(); 3]);
    gv.fill([T::zero(); 3]);
    let two = T::one() + T::one();
    for s in 0..sp.ends.len() {
        let (ia, ib, l0) = sp.get(s);
        // SAFETY: as in `clip_forces`; s < S = k.len() = b.len() = gk.len() = gb.len().
        unsafe {
            let d = sub(*x.get_unchecked(ib), *x.get_unchecked(ia));
            let w = sub(*v.get_unchecked(ib), *v.get_unchecked(ia));
            let gs = sub(*grad.get_unchecked(ia), *grad.get_unchecked(ib));
            let (ks, bs) = (*k.get_unchecked(s), *b.get_unchecked(s));
            let inv = T::one() / dot(d, d).sqrt();
            let inv2 = inv * inv;
            let wd = dot(w, d);
            let gd = dot(gs, d);
            let stretch = T::one() - l0 * inv;
            let c = ks * stretch + bs * wd * inv2;
            *gk.get_unchecked_mut(s) = *gk.get_unchecked(s) + gd * stretch;
            *gb.get_unchecked_mut(s) = *gb.get_unchecked(s) + gd * wd * inv2;
            let a1 = ks * l0 * inv2 * inv - two * bs * wd * inv2 * inv2;
            let a2 = bs * inv2;
            // ∂ℓ/∂d = c g + (g·d)(a1 d + a2 w); ∂ℓ/∂w = (g·d) a2 d.
            let dd = [0, 1, 2].map(|i| c * gs[i] + gd * (a1 * d[i] + a2 * w[i]));
            let dw = [0, 1, 2].map(|i| gd * a2 * d[i]);
            let gxb = gx.get_unchecked_mut(ib);
            for i in 0..3 {
                gxb[i] = gxb[i] + dd[i];
            }
            let gxa = gx.get_unchecked_mut(ia);
            for i in 0..3 {
                gxa[i] = gxa[i] - dd[i];
            }
            let gvb = gv.get_unchecked_mut(ib);
            for i in 0..3 {
                gvb[i] = gvb[i] + dw[i];
            }
            let gva = gv.get_unchecked_mut(ia);
            for i in 0..3 {
                gva[i] = gva[i] - dw[i];
            }
        }
    }
}
