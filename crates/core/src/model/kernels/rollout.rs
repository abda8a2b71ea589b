//! The fused rollout-and-loss kernel: a whole batch of clips simulated (Eq. 5) and scored by
//! the force, impulse and position losses (Eqs. 7–10) in one call, with its adjoint.
//!
//! Per clip, with `T` frames of `n` substeps, frame step `F = n h`, free-particle mask `φ`:
//! - `f̄_j` = mean net force over frame `j` (the integrator's own forces);
//! - `L_f = Σ_j Σ_p φ |f̄_j − f̂_j|² / (B T P)`;
//! - `J = F Σ_j c_j f̄_j` with trapezoid weights `c_0 = c_{T−1} = ½`, else 1; the same `Ĵ` from
//!   `f̂`; `L_J = Σ_p φ |J − Ĵ|² / (B P)`;
//! - `L_x = Σ_{j=1..T} Σ_p φ |x_j − x̂_j|² / (B T P)`.
//!
//! The backward runs the adjoint of the semi-implicit Euler steps backwards in time, adding at
//! each frame the loss gradients `∂L/∂f̄_j` and `∂L/∂x_{j+1}`, and sums `∂L/∂k`, `∂L/∂b`. The
//! states it needs are either all kept from the forward pass (when they fit the memory budget)
//! or recomputed segment by segment from checkpoints stored every `⌈√T⌉` frames.

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

use num_traits::Float;
use rayon::prelude::*;

use super::HostGraph;
use super::cpu::{
    Lane, LaneGrads, LaneSprings, Springs, cast, interleave, run_backward, run_forces, wide,
};

/// One state `(x, v)` of a batch's lanes, owned.
type OwnedState<T, const L: usize> = (Vec<Lane<T, L>>, Vec<Lane<T, L>>);
/// One state `(x, v)` of a batch's lanes, borrowed.
type StateRef<'a, T, const L: usize> = (&'a [Lane<T, L>], &'a [Lane<T, L>]);

/// Constants of a rollout.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RolloutParams {
    /// Time between data frames, s.
    pub frame_dt: f64,
    /// Integration steps per frame.
    pub substeps: usize,
    /// Particle mass, kg.
    pub mass: f64,
    /// Rayleigh constant, N·s/m.
    pub rayleigh: f64,
    /// Gravity, m/s².
    pub gravity: [f64; 3],
    /// The springs' isotropic viscosity per unit stiffness, s
    /// ([`crate::sim::SimConfig::viscosity`]).
    pub viscosity: f64,
    /// The shear springs' stiffness in compression per unit `k`
    /// ([`crate::sim::SimConfig::shear_compression`]).
    pub shear_compression: f64,
    /// Memory the forward pass may keep for the backward, bytes; beyond it, states are
    /// checkpointed every `⌈√T⌉` frames and recomputed.
    pub state_budget: usize,
}

/// The host data of a batch: `B` clips of `T` frames over `P` particles.
#[derive(Clone, Copy)]
pub struct RolloutData<'a, T> {
    /// Initial positions `[B, P, 3]`.
    pub x0: &'a [T],
    /// Initial velocities `[B, P, 3]`.
    pub v0: &'a [T],
    /// 1 for pinned particles, `[B, P]`.
    pub pinned: &'a [T],
    /// Target positions at frames `0..=T`, `[B, T + 1, P, 3]` (pinned particles follow them).
    pub path: &'a [T],
    /// Target mean forces per frame, `[B, T, P, 3]`.
    pub target: &'a [T],
    /// Stiffness `[S]`.
    pub k: &'a [T],
    /// Damping `[S]`.
    pub b: &'a [T],
    /// Clips `B`.
    pub batch: usize,
    /// Frames `T`.
    pub frames: usize,
}

impl<T> RolloutData<'_, T> {
    fn check(&self, g: &HostGraph) {
        let (b, t, stride) = (self.batch, self.frames, g.particles * 3);
        assert!(b > 0 && t > 0, "a rollout needs clips and frames");
        assert!(self.x0.len() == b * stride && self.v0.len() == b * stride);
        assert!(self.pinned.len() == b * g.particles);
        assert!(self.path.len() == b * (t + 1) * stride && self.target.len() == b * t * stride);
        assert!(self.k.len() == g.num_params() && self.b.len() == g.num_params());
    }
}

/// What the forward pass keeps for the backward pass.
#[derive(Debug)]
pub struct Tape<T> {
    lanes: usize,
    segment: usize,
    stored_all: bool,
    chunks: Vec<ChunkTape<T>>,
}

#[derive(Debug)]
struct ChunkTape<T> {
    /// Stored states `(x, v)`, lanes flattened: every substep start and the end state when
    /// `stored_all`, else the start of every segment.
    states: Vec<(Vec<T>, Vec<T>)>,
    /// Mean force of every frame (only when `stored_all`).
    forces: Vec<Vec<T>>,
    /// `J − Ĵ`, lanes flattened.
    dj: Vec<T>,
}

/// Loss values `[L_f, L_J, L_x]` and the tape.
pub fn forward<T: Float + Send + Sync>(
    g: &HostGraph,
    data: RolloutData<T>,
    params: RolloutParams,
) -> ([f64; 3], Arc<Tape<T>>) {
    data.check(g);
    if std::mem::size_of::<T>() == 4 && wide() && data.batch >= 16 {
        forward_lanes::<T, 8>(g, data, params)
    } else {
        forward_lanes::<T, 4>(g, data, params)
    }
}

impl<T: Float + Send + Sync> Tape<T> {
    /// `(∂ℓ/∂k, ∂ℓ/∂b)` for `ℓ = w · [L_f, L_J, L_x]` of the rollout this tape recorded.
    pub fn backward(
        &self,
        g: &HostGraph,
        data: RolloutData<T>,
        params: RolloutParams,
        w: [f64; 3],
    ) -> (Vec<T>, Vec<T>) {
        data.check(g);
        match self.lanes {
            8 => backward_lanes::<T, 8>(g, data, params, self, w),
            _ => backward_lanes::<T, 4>(g, data, params, self, w),
        }
    }
}

/// Lane-wise constants and data views of one chunk of clips.
struct Chunk<'a, T, const L: usize> {
    sp: &'a Springs<'a, T>,
    data: RolloutData<'a, T>,
    first: usize,
    clips: usize,
    stride: usize,
    /// 1 for free particles, per particle and lane.
    free: Vec<Lane<T, L>>,
    h: T,
    hm: T,
    c: T,
    mg: [T; 3],
    inv_frame: T,
    substeps: usize,
}

impl<'a, T: Float + Send + Sync, const L: usize> Chunk<'a, T, L> {
    fn new(
        sp: &'a Springs<'a, T>,
        g: &HostGraph,
        data: RolloutData<'a, T>,
        params: RolloutParams,
        ch: usize,
    ) -> Self {
        let first = ch * L;
        let clips = L.min(data.batch - first);
        let free = (0..g.particles)
            .map(|p| {
                std::array::from_fn(|l| {
                    let clip = (first + l).min(data.batch - 1);
                    if data.pinned[clip * g.particles + p] > T::zero() {
                        T::zero()
                    } else {
                        T::one()
                    }
                })
            })
            .collect();
        let h = params.frame_dt / params.substeps as f64;
        Self {
            sp,
            data,
            first,
            clips,
            stride: g.particles * 3,
            free,
            h: cast(h),
            hm: cast(h / params.mass),
            c: cast(params.rayleigh),
            mg: params.gravity.map(|a| cast(a * params.mass)),
            inv_frame: cast(1.0 / params.frame_dt),
            substeps: params.substeps,
        }
    }

    /// Component `i` of frame `j` of `[B, frames, P, 3]` data, per lane.
    #[inline(always)]
    fn frame_value(&self, src: &[T], frames: usize, j: usize, i: usize) -> Lane<T, L> {
        std::array::from_fn(|l| {
            let clip = (self.first + l).min(self.data.batch - 1);
            src[(clip * frames + j) * self.stride + i]
        })
    }

    fn initial(&self) -> (Vec<Lane<T, L>>, Vec<Lane<T, L>>) {
        let (mut x, mut v) = (Vec::new(), Vec::new());
        interleave::<T, L>(
            self.data.x0,
            self.stride,
            self.first,
            self.data.batch,
            &mut x,
        );
        interleave::<T, L>(
            self.data.v0,
            self.stride,
            self.first,
            self.data.batch,
            &mut v,
        );
        (x, v)
    }

    /// Advances `(x, v)` over frame `j`; returns the frame's mean force. `record` receives the
    /// state at the start of every substep.
    fn advance(
        &self,
        j: usize,
        x: &mut [Lane<T, L>],
        v: &mut [Lane<T, L>],
        s: &mut [Lane<T, L>],
        mut record: impl FnMut(&[Lane<T, L>], &[Lane<T, L>]),
    ) -> Vec<Lane<T, L>> {
        let n = self.substeps;
        let frames = self.data.frames + 1;
        let mut fmean = vec![[T::zero(); L]; self.stride];
        let inv_n = T::one() / cast::<T>(n as f64);
        for sub in 0..n {
            record(x, v);
            s.fill([T::zero(); L]);
            // SAFETY: x, v, s hold 3P lanes; k, b hold S values (RolloutData::check).
            let springs = LaneSprings::new(self.sp, x, v, self.data.k, self.data.b);
            unsafe { run_forces(springs, s) };
            let t = cast::<T>((sub + 1) as f64 / n as f64);
            for i in 0..self.stride {
                let here = self.frame_value(self.data.path, frames, j, i);
                let next = self.frame_value(self.data.path, frames, j + 1, i);
                let free = self.free[i / 3];
                for l in 0..L {
                    let f = s[i][l] + self.mg[i % 3] - self.c * v[i][l];
                    fmean[i][l] = fmean[i][l] + f * inv_n;
                    let vn = v[i][l] + self.hm * f;
                    let xn = x[i][l] + self.h * vn;
                    let pin_x = if sub + 1 == n {
                        next[l]
                    } else {
                        here[l] * (T::one() - t) + next[l] * t
                    };
                    let pin_v = (next[l] - here[l]) * self.inv_frame;
                    let fr = free[l];
                    x[i][l] = fr * xn + (T::one() - fr) * pin_x;
                    v[i][l] = fr * vn + (T::one() - fr) * pin_v;
                }
            }
        }
        fmean
    }

    /// Trapezoid weight of frame `j`.
    fn trapezoid(&self, j: usize) -> T {
        let t = self.data.frames;
        let half = cast::<T>(0.5);
        let mut c = T::one();
        if j == 0 {
            c = c - half;
        }
        if j + 1 == t {
            c = c - half;
        }
        c
    }
}

fn flatten<T: Copy, const L: usize>(lanes: &[Lane<T, L>]) -> Vec<T> {
    lanes.iter().flatten().copied().collect()
}

fn unflatten<T: Copy, const L: usize>(flat: &[T]) -> &[Lane<T, L>] {
    flat.as_chunks::<L>().0
}

fn forward_lanes<T: Float + Send + Sync, const L: usize>(
    g: &HostGraph,
    data: RolloutData<T>,
    params: RolloutParams,
) -> ([f64; 3], Arc<Tape<T>>) {
    let sp = Springs::<T>::new(g).with_physics(params.viscosity, params.shear_compression);
    let (t, n, stride) = (data.frames, params.substeps.max(1), g.particles * 3);
    let params = RolloutParams {
        substeps: n,
        ..params
    };
    let chunks = data.batch.div_ceil(L);
    // Keeping every substep state and every frame force costs (2 T n + T) states per chunk.
    let keep_all = chunks * (2 * t * n + t + 2) * stride * L * std::mem::size_of::<T>();
    let stored_all = keep_all <= params.state_budget;
    let segment = if stored_all {
        1
    } else {
        (t as f64).sqrt().ceil() as usize
    };
    let results: Vec<([f64; 3], ChunkTape<T>)> = (0..chunks)
        .into_par_iter()
        .map(|ch| {
            let chunk = Chunk::<T, L>::new(&sp, g, data, params, ch);
            let (mut x, mut v) = chunk.initial();
            let mut s = vec![[T::zero(); L]; stride];
            let (mut j_sim, mut j_hat) =
                (vec![[T::zero(); L]; stride], vec![[T::zero(); L]; stride]);
            let (mut force_sum, mut pos_sum) = (0.0f64, 0.0f64);
            let mut tape = ChunkTape {
                states: Vec::new(),
                forces: Vec::new(),
                dj: Vec::new(),
            };
            let frame_dt = cast::<T>(params.frame_dt);
            for j in 0..t {
                if !stored_all && j % segment == 0 {
                    tape.states.push((flatten(&x), flatten(&v)));
                }
                let fmean = chunk.advance(j, &mut x, &mut v, &mut s, |xs, vs| {
                    if stored_all {
                        tape.states.push((flatten(xs), flatten(vs)));
                    }
                });
                let cj = chunk.trapezoid(j) * frame_dt;
                for i in 0..stride {
                    let target = chunk.frame_value(data.target, t, j, i);
                    let xhat = chunk.frame_value(data.path, t + 1, j + 1, i);
                    let free = chunk.free[i / 3];
                    for l in 0..chunk.clips {
                        let df = (fmean[i][l] - target[l]).to_f64().expect("float");
                        let dx = (x[i][l] - xhat[l]).to_f64().expect("float");
                        let fr = free[l].to_f64().expect("float");
                        force_sum += fr * df * df;
                        pos_sum += fr * dx * dx;
                    }
                    for l in 0..L {
                        j_sim[i][l] = j_sim[i][l] + cj * fmean[i][l];
                        j_hat[i][l] = j_hat[i][l] + cj * target[l];
                    }
                }
                if stored_all {
                    tape.forces.push(flatten(&fmean));
                }
            }
            if stored_all {
                tape.states.push((flatten(&x), flatten(&v)));
            }
            let mut impulse_sum = 0.0f64;
            let mut dj = vec![[T::zero(); L]; stride];
            for i in 0..stride {
                for l in 0..L {
                    dj[i][l] = j_sim[i][l] - j_hat[i][l];
                }
                for l in 0..chunk.clips {
                    let d = dj[i][l].to_f64().expect("float");
                    impulse_sum += chunk.free[i / 3][l].to_f64().expect("float") * d * d;
                }
            }
            tape.dj = flatten(&dj);
            ([force_sum, impulse_sum, pos_sum], tape)
        })
        .collect();
    let (b, p) = (data.batch as f64, g.particles as f64);
    let mut sums = [0.0; 3];
    let mut tapes = Vec::with_capacity(results.len());
    for (s, tape) in results {
        for i in 0..3 {
            sums[i] += s[i];
        }
        tapes.push(tape);
    }
    let losses = [
        sums[0] / (b * t as f64 * p),
        sums[1] / (b * p),
        sums[2] / (b * t as f64 * p),
    ];
    (
        losses,
        Arc::new(Tape {
            lanes: L,
            segment,
            stored_all,
            chunks: tapes,
        }),
    )
}

fn backward_lanes<T: Float + Send + Sync, const L: usize>(
    g: &HostGraph,
    data: RolloutData<T>,
    params: RolloutParams,
    tape: &Tape<T>,
    w: [f64; 3],
) -> (Vec<T>, Vec<T>) {
    let sp = Springs::<T>::new(g).with_physics(params.viscosity, params.shear_compression);
    let (t, n, stride) = (data.frames, params.substeps.max(1), g.particles * 3);
    let params = RolloutParams {
        substeps: n,
        ..params
    };
    let s_count = g.num_params();
    let (b, p) = (data.batch as f64, g.particles as f64);
    // ∂L_f/∂f̄ = 2 φ (f̄ − f̂)/(BTP); ∂L_J/∂f̄_j = 2 φ c_j F (J − Ĵ)/(BP); ∂L_x/∂x = 2 φ (x − x̂)/(BTP).
    let cf = cast::<T>(2.0 * w[0] / (b * t as f64 * p));
    let cj = cast::<T>(2.0 * w[1] / (b * p) * params.frame_dt);
    let cx = cast::<T>(2.0 * w[2] / (b * t as f64 * p));
    let partials: Vec<ChunkGradient<T>> = tape
        .chunks
        .par_iter()
        .enumerate()
        .map(|(ch, ctape)| {
            let chunk = Chunk::<T, L>::new(&sp, g, data, params, ch);
            let dj: &[Lane<T, L>] = unflatten(&ctape.dj);
            let mut lx = vec![[T::zero(); L]; stride];
            let mut lv = vec![[T::zero(); L]; stride];
            let mut s = vec![[T::zero(); L]; stride];
            let mut g_f = vec![[T::zero(); L]; stride];
            let mut acc_x = vec![[T::zero(); L]; stride];
            let mut acc_v = vec![[T::zero(); L]; stride];
            let mut pk = vec![T::zero(); 2 * s_count];
            let segments = if tape.stored_all {
                1
            } else {
                t.div_ceil(tape.segment)
            };
            for seg in (0..segments).rev() {
                let (j0, j1) = if tape.stored_all {
                    (0, t)
                } else {
                    (seg * tape.segment, ((seg + 1) * tape.segment).min(t))
                };
                // States at every substep start of the segment, the state after it, and the
                // frames' mean forces: from the tape, or recomputed from the checkpoint.
                let mut states: Vec<OwnedState<T, L>> = Vec::new();
                let mut forces: Vec<Vec<Lane<T, L>>> = Vec::new();
                let (states_ref, forces_ref): (Vec<StateRef<'_, T, L>>, Vec<&[Lane<T, L>]>) =
                    if tape.stored_all {
                        (
                            ctape
                                .states
                                .iter()
                                .map(|(x, v)| (unflatten::<T, L>(x), unflatten::<T, L>(v)))
                                .collect(),
                            ctape.forces.iter().map(|f| unflatten::<T, L>(f)).collect(),
                        )
                    } else {
                        let (x0, v0) = &ctape.states[seg];
                        let (mut x, mut v) = (
                            unflatten::<T, L>(x0).to_vec(),
                            unflatten::<T, L>(v0).to_vec(),
                        );
                        for j in j0..j1 {
                            let f = chunk.advance(j, &mut x, &mut v, &mut s, |xs, vs| {
                                states.push((xs.to_vec(), vs.to_vec()))
                            });
                            forces.push(f);
                        }
                        states.push((x, v));
                        (
                            states
                                .iter()
                                .map(|(x, v)| (x.as_slice(), v.as_slice()))
                                .collect(),
                            forces.iter().map(|f| f.as_slice()).collect(),
                        )
                    };
                for j in (j0..j1).rev() {
                    let local = j - j0;
                    // Position loss on the state after frame j.
                    let after = states_ref[(local + 1) * n].0;
                    let fmean = forces_ref[local];
                    let c = chunk.trapezoid(j);
                    for i in 0..stride {
                        let xhat = chunk.frame_value(data.path, t + 1, j + 1, i);
                        let target = chunk.frame_value(data.target, t, j, i);
                        let free = chunk.free[i / 3];
                        let mut gf = [T::zero(); L];
                        for l in 0..L {
                            let fr = if l < chunk.clips { free[l] } else { T::zero() };
                            lx[i][l] = lx[i][l] + cx * fr * (after[i][l] - xhat[l]);
                            gf[l] = fr * (cf * (fmean[i][l] - target[l]) + cj * c * dj[i][l]);
                        }
                        g_f[i] = gf;
                    }
                    let inv_n = T::one() / cast::<T>(n as f64);
                    for sub in (0..n).rev() {
                        let (xs, vs) = states_ref[local * n + sub];
                        // ḡx'' = φ λx, ḡv'' = φ λv + h ḡx'', G = ∂ℓ/∂f + h/m ḡv''.
                        let mut gsub = vec![[T::zero(); L]; stride];
                        for i in 0..stride {
                            let free = chunk.free[i / 3];
                            for l in 0..L {
                                let gxx = free[l] * lx[i][l];
                                let gvv = free[l] * lv[i][l] + chunk.h * gxx;
                                acc_x[i][l] = gxx;
                                acc_v[i][l] = gvv;
                                gsub[i][l] = g_f[i][l] * inv_n + chunk.hm * gvv;
                            }
                        }
                        let (pk_k, pk_b) = pk.split_at_mut(s_count);
                        // SAFETY: lane buffers hold 3P lanes; k, b, pk_k, pk_b hold S values.
                        let springs = LaneSprings::new(&sp, xs, vs, data.k, data.b);
                        let mut grads = LaneGrads {
                            x: &mut acc_x,
                            v: &mut acc_v,
                            k: pk_k,
                            b: pk_b,
                        };
                        unsafe { run_backward(springs, &gsub, &mut grads) };
                        for i in 0..stride {
                            for l in 0..L {
                                lx[i][l] = acc_x[i][l];
                                lv[i][l] = acc_v[i][l] - chunk.c * gsub[i][l];
                            }
                        }
                    }
                }
            }
            ChunkGradient {
                clips: chunk.clips,
                norm: pk
                    .iter()
                    .map(|v| v.to_f64().unwrap_or(f64::NAN).powi(2))
                    .sum::<f64>()
                    .sqrt(),
                values: pk,
            }
        })
        .collect();
    let kept = keep_chunks(&partials);
    let (clips, kept_clips) = (
        partials.iter().map(|c| c.clips).sum::<usize>(),
        partials
            .iter()
            .zip(&kept)
            .filter(|(_, k)| **k)
            .map(|(c, _)| c.clips)
            .sum::<usize>(),
    );
    DROPPED_CLIPS.fetch_add(clips - kept_clips, Ordering::Relaxed);
    // The mean over the clips kept: the loss weights above divide by all `B` clips.
    let scale = cast::<T>(clips as f64 / kept_clips.max(1) as f64);
    let (mut gk, mut gb) = (vec![T::zero(); s_count], vec![T::zero(); s_count]);
    for part in partials
        .iter()
        .zip(&kept)
        .filter(|(_, k)| **k)
        .map(|(c, _)| &c.values)
    {
        for s in 0..s_count {
            gk[s] = gk[s] + part[s] * scale;
            gb[s] = gb[s] + part[s_count + s] * scale;
        }
    }
    (gk, gb)
}

/// The parameter gradient of one chunk of clips.
struct ChunkGradient<T> {
    clips: usize,
    norm: f64,
    values: Vec<T>,
}

/// How far above the median chunk's gradient norm a chunk's may lie and still count.
pub(crate) const CHUNK_OUTLIER_RATIO: f64 = 100.0;

/// Clips left out of gradients since the last [`take_dropped_clips`].
static DROPPED_CLIPS: AtomicUsize = AtomicUsize::new(0);

/// The number of clips the backward left out since the last call (and resets it).
///
/// A clip's adjoint grows like the rollout's fastest instability (a compressed, buckling patch
/// of cloth grows at `√(k ε / m)`); over a long clip it overflows or dwarfs every other clip's.
/// Such chunks of clips, non-finite or more than [`CHUNK_OUTLIER_RATIO`] times the median
/// chunk's gradient norm, are left out of the step and the rest averaged.
pub(crate) fn take_dropped_clips() -> usize {
    DROPPED_CLIPS.swap(0, Ordering::Relaxed)
}

/// Which chunks count: finite, and within [`CHUNK_OUTLIER_RATIO`] of the median norm.
fn keep_chunks<T>(chunks: &[ChunkGradient<T>]) -> Vec<bool> {
    let mut finite: Vec<f64> = chunks
        .iter()
        .map(|c| c.norm)
        .filter(|n| n.is_finite())
        .collect();
    finite.sort_by(f64::total_cmp);
    let median = finite.get(finite.len() / 2).copied().unwrap_or(f64::NAN);
    if std::env::var_os("SPRINGTIME_DEBUG_CHUNKS").is_some() {
        let norms: Vec<String> = chunks.iter().map(|c| format!("{:.2e}", c.norm)).collect();
        eprintln!("chunk gradient norms: {}", norms.join(" "));
    }
    chunks
        .iter()
        .map(|c| c.norm.is_finite() && (c.norm <= CHUNK_OUTLIER_RATIO * median || median == 0.0))
        .collect()
}
