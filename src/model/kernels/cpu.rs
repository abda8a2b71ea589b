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

/// Spring forces `[B, P, 3]` into `out` (overwritten).
pub fn forces<T: Float + Send + Sync>(
    g: &HostGraph,
    x: &[T],
    v: &[T],
    k: &[T],
    b: &[T],
    out: &mut [T],
) {
    let stride = g.particles * 3;
    let l0: Vec<T> = g
        .rest_length
        .iter()
        .map(|&l| T::from(l).expect("float"))
        .collect();
    out.par_chunks_mut(stride)
        .zip(x.par_chunks(stride).zip(v.par_chunks(stride)))
        .for_each(|(out, (x, v))| clip_forces(g, &l0, x, v, k, b, out));
}

#[inline]
fn sub3<T: Float>(p: &[T], a: usize, b: usize) -> [T; 3] {
    [
        p[3 * b] - p[3 * a],
        p[3 * b + 1] - p[3 * a + 1],
        p[3 * b + 2] - p[3 * a + 2],
    ]
}

#[inline]
fn dot3<T: Float>(a: [T; 3], b: [T; 3]) -> T {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn clip_forces<T: Float>(
    g: &HostGraph,
    l0: &[T],
    x: &[T],
    v: &[T],
    k: &[T],
    b: &[T],
    out: &mut [T],
) {
    out.fill(T::zero());
    for s in 0..g.ia.len() {
        let (ia, ib) = (g.ia[s] as usize, g.ib[s] as usize);
        let d = sub3(x, ia, ib);
        let w = sub3(v, ia, ib);
        let inv = T::one() / dot3(d, d).sqrt();
        let c = k[s] * (T::one() - l0[s] * inv) + b[s] * dot3(w, d) * inv * inv;
        for i in 0..3 {
            let f = c * d[i];
            out[3 * ia + i] = out[3 * ia + i] + f;
            out[3 * ib + i] = out[3 * ib + i] - f;
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
    let stride = g.particles * 3;
    let s_count = g.ia.len();
    let l0: Vec<T> = g
        .rest_length
        .iter()
        .map(|&l| T::from(l).expect("float"))
        .collect();
    let partial = gx
        .par_chunks_mut(stride)
        .zip(gv.par_chunks_mut(stride))
        .zip(
            x.par_chunks(stride)
                .zip(v.par_chunks(stride))
                .zip(grad.par_chunks(stride)),
        )
        .fold(
            || vec![T::zero(); 2 * s_count],
            |mut acc, ((gx, gv), ((x, v), grad))| {
                let (pk, pb) = acc.split_at_mut(s_count);
                clip_backward(g, &l0, x, v, k, b, grad, gx, gv, pk, pb);
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

#[allow(clippy::too_many_arguments)]
fn clip_backward<T: Float>(
    g: &HostGraph,
    l0: &[T],
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
    gx.fill(T::zero());
    gv.fill(T::zero());
    let two = T::one() + T::one();
    for s in 0..g.ia.len() {
        let (ia, ib) = (g.ia[s] as usize, g.ib[s] as usize);
        let d = sub3(x, ia, ib);
        let w = sub3(v, ia, ib);
        let gs = [
            grad[3 * ia] - grad[3 * ib],
            grad[3 * ia + 1] - grad[3 * ib + 1],
            grad[3 * ia + 2] - grad[3 * ib + 2],
        ];
        let inv = T::one() / dot3(d, d).sqrt();
        let inv2 = inv * inv;
        let wd = dot3(w, d);
        let gd = dot3(gs, d);
        let stretch = T::one() - l0[s] * inv;
        let c = k[s] * stretch + b[s] * wd * inv2;
        gk[s] = gk[s] + gd * stretch;
        gb[s] = gb[s] + gd * wd * inv2;
        let a1 = k[s] * l0[s] * inv2 * inv - two * b[s] * wd * inv2 * inv2;
        let a2 = b[s] * inv2;
        for i in 0..3 {
            // ∂ℓ/∂d_i = c g_i + (g·d)(a1 d_i + a2 w_i); ∂ℓ/∂w_i = (g·d) a2 d_i.
            let dd = c * gs[i] + gd * (a1 * d[i] + a2 * w[i]);
            let dw = gd * a2 * d[i];
            gx[3 * ib + i] = gx[3 * ib + i] + dd;
            gx[3 * ia + i] = gx[3 * ia + i] - dd;
            gv[3 * ib + i] = gv[3 * ib + i] + dw;
            gv[3 * ia + i] = gv[3 * ia + i] - dw;
        }
    }
}
