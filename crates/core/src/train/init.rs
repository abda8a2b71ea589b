//! Defaults derived from the data: gravity, Rayleigh damping, the initial uniform `k` and `b`,
//! and the number of substeps — every `"auto"` of a config, resolved when a run starts.
//!
//! Eq. 4 is linear in `k` and `b`, and the Rayleigh force `−c ẋ` is linear in `c`, so the
//! uniform network that best explains the data's forces is a small least-squares problem:
//! for free particles at interior frames `j` of a sample of clips,
//!
//! `m â_j − m g ≈ k Σ_s (|d| − l₀) d̂ + b Σ_s (w·d̂) d̂ − c v̂_j`,
//!
//! with `v̂_j = (x_{j+1} − x_{j−1}) / 2Δt` and `â_j = (x_{j+1} − 2x_j + x_{j−1}) / Δt²` from
//! positions alone (so files without velocities and at camera rate are handled alike). The
//! unknowns are kept non-negative. The resolved values go into the run's `config.toml`, so that
//! evaluation, simulation and export use the same physics.

use anyhow::{Result, bail};
use serde::Serialize;

use crate::cloth::Topology;
use crate::config::Config;
use crate::data::{ClipRef, ClipSet, Track};
use crate::settings::Auto;
use crate::sim::{GRAVITY, Stability};

/// The stability number `dt²ω² + 2·dt·γ` that `sim.substeps = "auto"` keeps the initial
/// surrogate below: a quarter of the limit, so training can raise `k` several-fold.
pub const AUTO_SUBSTEPS_TARGET: f64 = 1.0;
/// The stability number a fitted initial guess is clamped to when the substeps are fixed.
pub(crate) const INITIAL_CLAMP: f64 = 2.0;
/// At most this many clips are sampled for the fit.
const FIT_CLIPS: usize = 48;

/// The uniform spring network that best explains the data's forces.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct UniformFit {
    /// Stiffness, N/m.
    pub k: f64,
    /// Damping, N·s/m.
    pub b: f64,
    /// Rayleigh damping per particle, N·s/m (the given value when it was not fitted).
    pub c: f64,
    /// Whether `c` was fitted.
    pub fitted_c: bool,
    /// Particle-frame samples (free particles × frames) in the fit.
    pub samples: usize,
    /// Frames on either side of the acceleration's stencil that fitted best.
    pub stencil: usize,
    /// RMS of the target force `m â − m g`, N.
    pub target_rms: f64,
    /// RMS of the residual, N.
    pub residual_rms: f64,
}

impl UniformFit {
    /// The share of the target force's mean square that the fit explains.
    pub fn explained(&self) -> f64 {
        1.0 - (self.residual_rms / self.target_rms.max(f64::MIN_POSITIVE)).powi(2)
    }
}

/// Below this share of the target force explained, the fitted `k` is not trusted and
/// `model.k_init = "auto"` is found by a search over free rollouts instead
/// ([`search_stiffness`]).
pub(crate) const FIT_TRUST: f64 = 0.3;

/// Training rollouts the fallback search simulates.
const SEARCH_FILES: usize = 4;

/// Where `resolve` may simulate: the training files and a device (`None`: no search, as in
/// `data check`).
pub struct SearchContext<'a> {
    /// Training rollout files.
    pub files: &'a [std::path::PathBuf],
    /// Device for the rollouts.
    pub device: &'a burn::tensor::Device,
    /// How the search scores its candidates (`train.search_objective`).
    pub objective: crate::eval::Objective,
}

/// The uniform stiffness whose free rollouts best follow the training files (damping `b`,
/// Rayleigh `c`): `k = 2^i` N/m for `i = −3…13`, each at its own automatic substeps, the search
/// stopping three candidates past the best. Returns `(k, substeps, motion RMSE)`.
pub(crate) fn search_stiffness(
    clips: &ClipSet,
    gravity: [f64; 3],
    b: f64,
    c: f64,
    fixed_substeps: Option<usize>,
    ctx: &SearchContext,
) -> Result<(f64, usize, f64)> {
    let topo = &clips.topology;
    let mass = clips.particle_mass();
    let files: Vec<std::path::PathBuf> = ctx.files.iter().take(SEARCH_FILES).cloned().collect();
    let (cache, quiet) = (
        crate::eval::TrackCache::default(),
        crate::progress::Progress::quiet(),
    );
    let takes = crate::eval::Takes {
        topology: topo,
        files: &files,
        batch: 16,
        device: ctx.device,
        progress: &quiet,
        cache: Some(&cache),
        objective: ctx.objective,
    };
    let s = topo.num_springs();
    let mut best: Option<(f64, usize, f64)> = None;
    let mut worse = 0;
    for i in -3..=13 {
        let k = 2f64.powi(i);
        let frame_dt = clips.info.frame_dt;
        let stability = Stability::estimate(topo, &vec![k; s], &vec![b; s], mass, c, frame_dt);
        let number = |n: usize| stability.number_at(frame_dt / n as f64);
        let n = match fixed_substeps {
            Some(n) => n,
            None => stability
                .fewest_substeps(frame_dt, 1..=256, AUTO_SUBSTEPS_TARGET)
                .unwrap_or(256),
        };
        if number(n) >= 4.0 {
            break;
        }
        let physics = crate::sim::Physics {
            frame_dt: clips.info.frame_dt,
            substeps: n,
            mass,
            rayleigh: c,
            gravity,
            // The start's guess; the viscosity is searched (or given) at the run's map.
            viscosity: 0.0,
            shear_compression: 1.0,
        };
        let rmse =
            crate::eval::uniform::rollout_rmse(&physics, k, b, &takes).unwrap_or(f64::INFINITY);
        if best.is_none_or(|(_, _, r)| rmse < r) {
            best = Some((k, n, rmse));
            worse = 0;
        } else {
            worse += 1;
            if worse == 3 {
                break;
            }
        }
    }
    best.filter(|(_, _, r)| r.is_finite()).ok_or_else(|| {
        anyhow::anyhow!("no uniform stiffness between 1/8 and 8192 N/m gives a finite rollout")
    })
}

impl UniformFit {
    /// Fits `k`, `b` (and `c`, unless `rayleigh` gives it) to clips of `clips`, with particles
    /// of mass `mass` under `gravity`.
    pub fn fit(clips: &ClipSet, gravity: [f64; 3], rayleigh: Option<f64>) -> Result<Self> {
        let pool: Vec<ClipRef> = clips.all_clips();
        if pool.is_empty() {
            bail!("no clips to fit the initial stiffness to");
        }
        let stride = pool.len().div_ceil(FIT_CLIPS).max(1);
        let rows = StencilRows::new(clips, gravity, rayleigh);
        let stencils: Vec<usize> = STENCILS
            .iter()
            .copied()
            .filter(|&w| 2 * w < rows.t)
            .collect();
        let mut systems = vec![Normal::default(); stencils.len()];
        for clip in pool.iter().step_by(stride) {
            let track = clips.track(clip.rollout)?;
            let clip = ClipFrames {
                track: &track,
                offset: clip.offset,
                p: rows.p,
            };
            let frames = rows.columns(&clip);
            for (system, &w) in systems.iter_mut().zip(&stencils) {
                rows.add(system, w, &clip, &frames);
            }
        }
        let (solution, stencil) = best_stencil(&systems, &stencils, rows.unknowns)?;
        Ok(Self {
            k: solution.x[0],
            b: solution.x[1],
            c: rayleigh.unwrap_or(solution.x[2]),
            fitted_c: rayleigh.is_none(),
            samples: solution.samples,
            stencil,
            target_rms: solution.target_rms,
            residual_rms: solution.residual_rms,
        })
    }
}

/// The fit's solution of the stencil whose fit explains the largest share of the target force.
fn best_stencil(
    systems: &[Normal],
    stencils: &[usize],
    unknowns: usize,
) -> Result<(Solved, usize)> {
    systems
        .iter()
        .zip(stencils)
        .filter(|(s, _)| s.samples > 0)
        .map(|(s, &w)| (s.solve(unknowns), w))
        .inspect(|(s, w)| {
            if std::env::var_os("SPRINGTIME_DEBUG_FIT").is_some() {
                eprintln!(
                    "fit ±{w}: k {:.4e} b {:.4e} c {:.4e} explained {:.4} (target {:.3e})",
                    s.x[0],
                    s.x[1],
                    s.x[2],
                    s.explained(),
                    s.target_rms
                );
            }
        })
        .max_by(|a, b| a.0.explained().total_cmp(&b.0.explained()))
        .ok_or_else(|| {
            anyhow::anyhow!("the data has no free particle to fit the initial stiffness to")
        })
}

/// One clip's positions in double precision.
struct ClipFrames<'a> {
    track: &'a Track,
    offset: usize,
    p: usize,
}

impl ClipFrames<'_> {
    /// Particle `i` at frame `j` of the clip.
    fn x(&self, j: usize, i: usize) -> [f64; 3] {
        let o = ((self.offset + j) * self.p + i) * 3;
        let x = &self.track.positions[o..o + 3];
        [x[0] as f64, x[1] as f64, x[2] as f64]
    }
}

/// The rows of the uniform fit: each free particle's net force over a stencil against the
/// unit-`k`, unit-`b` and unit-Rayleigh forces averaged over the same frames.
struct StencilRows<'a> {
    topo: &'a Topology,
    neighbours: Vec<Vec<usize>>,
    p: usize,
    /// Steps per clip: a clip holds frames 0..=t.
    t: usize,
    mass: f64,
    dt: f64,
    gravity: [f64; 3],
    rayleigh: Option<f64>,
    unknowns: usize,
}

impl<'a> StencilRows<'a> {
    fn new(clips: &'a ClipSet, gravity: [f64; 3], rayleigh: Option<f64>) -> Self {
        let topo = &clips.topology;
        let p = topo.num_particles();
        let mut neighbours = vec![Vec::new(); p];
        for &[a, b] in &topo.springs {
            neighbours[a].push(b);
            neighbours[b].push(a);
        }
        Self {
            topo,
            neighbours,
            p,
            t: clips.steps,
            mass: clips.particle_mass(),
            dt: clips.info.frame_dt,
            gravity,
            rayleigh,
            unknowns: if rayleigh.is_some() { 2 } else { 3 },
        }
    }

    /// Unit columns and central-difference velocities at frames 1..t−1 of the clip.
    fn columns(&self, clip: &ClipFrames) -> Vec<Vec<[[f64; 3]; 3]>> {
        let (p, t, dt) = (self.p, self.t, self.dt);
        let mut cols = vec![[[0f64; 3]; 2]; p];
        let mut frames: Vec<Vec<[[f64; 3]; 3]>> = vec![Vec::new(); t + 1];
        for (j, slot) in frames.iter_mut().enumerate().take(t).skip(1) {
            let xs: Vec<[f64; 3]> = (0..p).map(|i| clip.x(j, i)).collect();
            let vs: Vec<[f64; 3]> = (0..p)
                .map(|i| {
                    let (a, c) = (clip.x(j - 1, i), clip.x(j + 1, i));
                    [0, 1, 2].map(|d| (c[d] - a[d]) / (2.0 * dt))
                })
                .collect();
            unit_columns(self.topo, &xs, &vs, &mut cols);
            *slot = (0..p)
                .map(|i| [0, 1, 2].map(|d| [cols[i][0][d], cols[i][1][d], -vs[i][d]]))
                .collect();
        }
        frames
    }

    /// Adds the clip's rows of stencil half-width `w` to `system`.
    fn add(&self, system: &mut Normal, w: usize, clip: &ClipFrames, frames: &[Vec<[[f64; 3]; 3]>]) {
        let (track, t) = (clip.track, self.t);
        // m (x_{j+w} − 2x_j + x_{j−w}) / (wΔt)² is the tent-weighted mean of the net
        // force over (j − w, j + w): weights (w − |i − j|)/w² on the frames between.
        let h2 = (w as f64 * self.dt).powi(2);
        // Frames j − w + 1 … j + w − 1 all lie in 1 … t − 1, where `frames` is filled.
        for j in w..=t - w {
            // With hidden particles, a row counts where the particle and its springs'
            // far ends are seen over the stencil and its velocities' frames.
            let window = (clip.offset + j).saturating_sub(w + 1)..=clip.offset + j + w + 1;
            let seen = |i: usize| track.seen_throughout(i, window.clone());
            let row_seen = |i: usize| {
                track.visible.is_none() || (seen(i) && self.neighbours[i].iter().all(|&e| seen(e)))
            };
            for i in (0..self.p).filter(|&i| !track.pinned[i] && row_seen(i)) {
                let (a, b, c) = (clip.x(j - w, i), clip.x(j, i), clip.x(j + w, i));
                for d in 0..3 {
                    let mut row = [0f64; 3];
                    for q in j + 1 - w..j + w {
                        let weight = (w - q.abs_diff(j)) as f64 / (w * w) as f64;
                        for (r, v) in row.iter_mut().zip(frames[q][i][d]) {
                            *r += weight * v;
                        }
                    }
                    let mut y = self.mass * ((c[d] - 2.0 * b[d] + a[d]) / h2 - self.gravity[d]);
                    if let Some(c) = self.rayleigh {
                        y -= c * row[2]; // the known Rayleigh force, −c v̄
                    }
                    system.add(&row, y, self.unknowns);
                }
                system.samples += 1;
            }
        }
    }
}

/// Stencil widths (frames) tried for the acceleration: the one whose fit explains the largest
/// share of the target force wins. At camera rate a stiff cloth rings faster than the frames
/// resolve; a wider stencil averages that ringing out of the target and the regressors alike.
const STENCILS: [usize; 5] = [1, 2, 4, 8, 16];

/// Accumulated normal equations of the fit.
#[derive(Debug, Clone, Default)]
struct Normal {
    a: [[f64; 3]; 3],
    rhs: [f64; 3],
    yy: f64,
    rows: usize,
    samples: usize,
}

/// A solved [`Normal`].
struct Solved {
    x: [f64; 3],
    samples: usize,
    target_rms: f64,
    residual_rms: f64,
}

impl Solved {
    /// The share of the target's mean square the fit explains.
    fn explained(&self) -> f64 {
        1.0 - (self.residual_rms / self.target_rms.max(f64::MIN_POSITIVE)).powi(2)
    }
}

impl Normal {
    fn add(&mut self, row: &[f64; 3], y: f64, unknowns: usize) {
        for r in 0..unknowns {
            self.rhs[r] += row[r] * y;
            for q in 0..unknowns {
                self.a[r][q] += row[r] * row[q];
            }
        }
        self.yy += y * y;
        self.rows += 1;
    }

    /// Non-negative least squares by elimination: the most negative unknown is dropped and the
    /// rest solved again (at most three unknowns).
    fn solve(&self, unknowns: usize) -> Solved {
        let mut active: Vec<usize> = (0..unknowns).collect();
        let x = loop {
            let x = solve(&self.a, &self.rhs, &active);
            match active
                .iter()
                .zip(&x)
                .filter(|(_, v)| **v < 0.0)
                .min_by(|a, b| a.1.total_cmp(b.1))
            {
                Some((&drop, _)) => active.retain(|&a| a != drop),
                None => {
                    let mut full = [0f64; 3];
                    for (&a, v) in active.iter().zip(&x) {
                        full[a] = *v;
                    }
                    break full;
                }
            }
        };
        // |y − Ax|² = yᵀy − 2xᵀAᵀy + xᵀAᵀAx.
        let mut res = self.yy;
        for r in 0..3 {
            res -= 2.0 * x[r] * self.rhs[r];
            for q in 0..3 {
                res += x[r] * self.a[r][q] * x[q];
            }
        }
        let n = self.rows.max(1) as f64;
        Solved {
            x,
            samples: self.samples,
            target_rms: (self.yy / n).sqrt(),
            residual_rms: (res.max(0.0) / n).sqrt(),
        }
    }
}

/// The forces of a spring `a`–`b` of rest length `l0` on `a` at unit stiffness and at unit
/// damping (Eq. 4): `(|d| − l₀) d̂` and `((v_b − v_a)·d̂) d̂`, `d = x_b − x_a`; `b` gets their
/// negatives.
pub(super) fn unit_spring_forces(
    xa: [f64; 3],
    xb: [f64; 3],
    va: [f64; 3],
    vb: [f64; 3],
    l0: f64,
) -> ([f64; 3], [f64; 3]) {
    let d = [0, 1, 2].map(|c| xb[c] - xa[c]);
    let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-12);
    let u = d.map(|c| c / len);
    let along = (0..3).map(|c| (vb[c] - va[c]) * u[c]).sum::<f64>();
    (u.map(|c| (len - l0) * c), u.map(|c| along * c))
}

/// Per particle, the force of unit uniform stiffness and of unit uniform damping (Eq. 4), per
/// unit of the mean mass (divided by the particle's relative mass, as the surrogate's).
fn unit_columns(topo: &Topology, x: &[[f64; 3]], v: &[[f64; 3]], out: &mut [[[f64; 3]; 2]]) {
    out.iter_mut().for_each(|c| *c = [[0.0; 3]; 2]);
    for (&[a, b], &l0) in topo.springs.iter().zip(&topo.rest_length) {
        let (fk, fb) = unit_spring_forces(x[a], x[b], v[a], v[b], l0);
        for c in 0..3 {
            out[a][0][c] += fk[c];
            out[b][0][c] -= fk[c];
            out[a][1][c] += fb[c];
            out[b][1][c] -= fb[c];
        }
    }
    if let Some(w) = &topo.mass_weight {
        for (o, w) in out.iter_mut().zip(w) {
            o.iter_mut().flatten().for_each(|f| *f /= w);
        }
    }
}

/// Solves the normal equations restricted to the unknowns `active` (Gaussian elimination).
fn solve(normal: &[[f64; 3]; 3], rhs: &[f64; 3], active: &[usize]) -> Vec<f64> {
    let n = active.len();
    let mut m: Vec<Vec<f64>> = active
        .iter()
        .map(|&r| {
            let mut row: Vec<f64> = active.iter().map(|&q| normal[r][q]).collect();
            row.push(rhs[r]);
            row
        })
        .collect();
    for col in 0..n {
        let pivot = (col..n)
            .max_by(|&a, &b| m[a][col].abs().total_cmp(&m[b][col].abs()))
            .expect("non-empty");
        m.swap(col, pivot);
        let p = m[col][col];
        if p.abs() < 1e-300 {
            continue;
        }
        for r in 0..n {
            if r != col {
                let f = m[r][col] / p;
                for c in col..=n {
                    m[r][c] -= f * m[col][c];
                }
            }
        }
    }
    (0..n)
        .map(|r| {
            if m[r][r].abs() < 1e-300 {
                0.0
            } else {
                m[r][n] / m[r][r]
            }
        })
        .collect()
}

/// What a run resolved from its data, written to `defaults.json` in the run.
#[derive(Debug, Clone, Serialize)]
pub struct Resolution {
    /// Gravity, m/s², and where it came from.
    pub gravity: [f64; 3],
    /// `"config"`, `"data"` or `"default"`.
    pub gravity_from: &'static str,
    /// Rayleigh damping per particle, N·s/m.
    pub rayleigh: f64,
    /// `"config"`, `"data"` or `"fit"`.
    pub rayleigh_from: &'static str,
    /// Initial uniform stiffness, N/m.
    pub k_init: f64,
    /// Initial uniform damping, N·s/m.
    pub b_init: f64,
    /// `"config"`, `"fit"` or `"fit, clamped for stability"`.
    pub init_from: String,
    /// Substeps per frame.
    pub substeps: usize,
    /// `"config"` or `"auto"`.
    pub substeps_from: &'static str,
    /// The stability number of the initial surrogate.
    pub stability_number: f64,
    /// The least-squares fit, when one was needed.
    pub fit: Option<UniformFit>,
}

impl Resolution {
    /// Whether the drag was fitted to the frames (neither the data nor the config states it).
    pub fn drag_fitted(&self) -> bool {
        self.rayleigh_from == "fit"
    }

    /// One line per resolved value, for the console.
    pub fn lines(&self) -> Vec<String> {
        let mut out = vec![
            format!(
                "gravity [{:.3}, {:.3}, {:.3}] m/s² ({})",
                self.gravity[0], self.gravity[1], self.gravity[2], self.gravity_from
            ),
            format!(
                "Rayleigh damping {:.4e} N·s/m per particle ({})",
                self.rayleigh, self.rayleigh_from
            ),
            format!(
                "initial k = {:.4} N/m, b = {:.4e} N·s/m ({})",
                self.k_init, self.b_init, self.init_from
            ),
            format!(
                "{} substep(s) per frame ({}): dt²ω² + 2·dt·γ = {:.3} at the start (stable below 4)",
                self.substeps, self.substeps_from, self.stability_number
            ),
        ];
        if let Some(f) = &self.fit {
            out.push(format!(
                "uniform fit over {} particle-frames (acceleration over ±{} frames): residual \
                 {:.3e} N of {:.3e} N RMS target force",
                f.samples, f.stencil, f.residual_rms, f.target_rms
            ));
        }
        out
    }
}

/// Resolves every `"auto"` of `config` from the training clips; returns the resolved config
/// (only numbers left) and what was chosen.
pub fn resolve(
    config: &Config,
    clips: &ClipSet,
    search: Option<&SearchContext>,
) -> Result<(Config, Resolution)> {
    let mut out = config.clone();
    let info = &clips.info;
    let mass = clips.particle_mass();
    let (gravity, gravity_from) = match (config.sim.gravity.value(), info.gravity) {
        (Some(g), _) => (g, "config"),
        (None, Some(g)) => (g, "data"),
        (None, None) => (GRAVITY, "default"),
    };
    let given_c = match config.sim.rayleigh.value() {
        Some(c) => Some((c, "config")),
        None => info.rayleigh_for(mass).map(|c| (c, "data")),
    };
    let need_fit = given_c.is_none()
        || (config.model.kind == crate::model::ModelKind::Springs
            && (config.model.k_init == Auto::Auto || config.model.b_init == Auto::Auto));
    let fit = if need_fit {
        Some(UniformFit::fit(clips, gravity, given_c.map(|c| c.0))?)
    } else {
        None
    };
    let (rayleigh, rayleigh_from) = match (given_c, &fit) {
        (Some(c), _) => c,
        (None, Some(f)) => (f.c, "fit"),
        (None, None) => unreachable!("fitted when not given"),
    };
    let stability = UniformStability {
        topology: &clips.topology,
        mass,
        rayleigh,
        frame_dt: info.frame_dt,
    };
    let start = Start::guess(config, clips, fit.as_ref(), gravity, rayleigh, search)?;
    let (substeps, substeps_from) = substeps_for(config, &start, &stability)?;
    let Start {
        mut k,
        mut b,
        mut from,
        ..
    } = start;
    // A fitted guess past the limit at fixed substeps is scaled into the stable region.
    let fitted = config.model.k_init == Auto::Auto || config.model.b_init == Auto::Auto;
    if fitted && stability.number(k, b, substeps) > INITIAL_CLAMP {
        let mut scale = 1.0;
        while stability.number(k * scale, b * scale, substeps) > INITIAL_CLAMP && scale > 1e-6 {
            scale *= 0.9;
        }
        if config.model.k_init == Auto::Auto {
            k *= scale;
        }
        if config.model.b_init == Auto::Auto {
            b *= scale;
        }
        from.push_str(&format!(", scaled by {scale:.3} to stay stable"));
    }
    out.data.clips.steps = Auto::Value(clips.steps);
    out.sim.gravity = Auto::Value(gravity);
    out.sim.rayleigh = Auto::Value(rayleigh);
    out.sim.substeps = Auto::Value(substeps);
    out.train.least_squares.noise = Auto::Value(
        config
            .train
            .least_squares
            .noise
            .value()
            .or(info.position_noise)
            .unwrap_or(0.0),
    );
    out.model.k_init = Auto::Value(k);
    out.model.b_init = Auto::Value(b);
    let resolution = Resolution {
        gravity,
        gravity_from,
        rayleigh,
        rayleigh_from,
        k_init: k,
        b_init: b,
        init_from: from,
        substeps,
        substeps_from,
        stability_number: stability.number(k, b, substeps),
        fit,
    };
    Ok((out, resolution))
}

/// The stability number of a uniform network on the data's grid at given substeps.
struct UniformStability<'a> {
    topology: &'a Topology,
    mass: f64,
    rayleigh: f64,
    frame_dt: f64,
}

impl UniformStability<'_> {
    /// The estimate of uniform `k`, `b` at one substep per frame (its `number_at` any step).
    fn of(&self, k: f64, b: f64) -> Stability {
        let s = self.topology.num_springs();
        Stability::estimate(
            self.topology,
            &vec![k; s],
            &vec![b; s],
            self.mass,
            self.rayleigh,
            self.frame_dt,
        )
    }

    fn number(&self, k: f64, b: f64, substeps: usize) -> f64 {
        self.of(k, b).number_at(self.frame_dt / substeps as f64)
    }
}

/// The uniform start before the stability clamp: `k` and `b` from the config or the fit (or a
/// search over free rollouts where the fit explains too little), where they came from, and the
/// substeps that search settled on.
struct Start {
    k: f64,
    b: f64,
    from: String,
    searched_substeps: Option<usize>,
}

impl Start {
    fn guess(
        config: &Config,
        clips: &ClipSet,
        fit: Option<&UniformFit>,
        gravity: [f64; 3],
        rayleigh: f64,
        search: Option<&SearchContext>,
    ) -> Result<Self> {
        let mut k = config
            .model
            .k_init
            .value()
            .or(fit.map(|f| f.k))
            .unwrap_or(1.0);
        let mut b = config
            .model
            .b_init
            .value()
            .or(fit.map(|f| f.b))
            .unwrap_or(0.0);
        let mut from = match (config.model.k_init, config.model.b_init) {
            (Auto::Value(_), Auto::Value(_)) => "config".to_string(),
            (Auto::Auto, Auto::Auto) => "fit".to_string(),
            _ => "config and fit".to_string(),
        };
        let mut searched_substeps = None;
        if let Some(f) = fit
            && f.explained() < FIT_TRUST
            && config.model.k_init == Auto::Auto
        {
            let Some(ctx) = search else {
                bail!(
                    "the uniform force fit explains only {:.1} % of the data's accelerations \
                     (frames too far apart for the motion's fastest parts, or a material unlike \
                     springs); `train` searches k over free rollouts instead",
                    100.0 * f.explained()
                );
            };
            let substeps = config.sim.substeps.value();
            let (k_best, n, rmse) = search_stiffness(clips, gravity, b, rayleigh, substeps, ctx)?;
            k = k_best;
            searched_substeps = Some(n);
            from = format!(
                "k from a search over free rollouts (motion RMSE {rmse:.3e} m on {} training \
                 rollouts): the force fit explains only {:.1} % of the accelerations",
                ctx.files.len().min(SEARCH_FILES),
                100.0 * f.explained()
            );
        }
        // A fitted damping of exactly zero stops training with NaN at the first step (seen on
        // tpcloth data; cause not isolated): keep at least 0.1 % of a spring's critical damping.
        let b_floor = 1e-3 * 2.0 * (k.max(0.0) * clips.particle_mass()).sqrt();
        if config.model.b_init == Auto::Auto && b < b_floor {
            b = b_floor;
        }
        if k <= 0.0 {
            bail!(
                "the data's forces fit no positive uniform stiffness (least squares gave k = \
                 {k:.4e} N/m); check `total_mass`, `frame_dt` and the units of `positions`, or \
                 set `model.k_init`"
            );
        }
        Ok(Self {
            k,
            b,
            from,
            searched_substeps,
        })
    }
}

/// The substeps per frame and where they came from: the config's, the search's, or the fewest
/// that keep the start's stability number within `AUTO_SUBSTEPS_TARGET`.
fn substeps_for(
    config: &Config,
    start: &Start,
    stability: &UniformStability,
) -> Result<(usize, &'static str)> {
    let (k, b) = (start.k, start.b);
    Ok(
        match (config.sim.substeps.value(), start.searched_substeps) {
            (Some(n), _) => (n, "config"),
            (None, Some(n)) => (n, "auto"),
            (None, None) => {
                let of = stability.of(k, b);
                let mut n = 1;
                while of.number_at(stability.frame_dt / n as f64) > AUTO_SUBSTEPS_TARGET {
                    n += 1;
                    if n > 10_000 {
                        bail!(
                            "sim.substeps = \"auto\": even 10000 substeps per {:.3e} s frame leave \
                         the initial surrogate unstable (k = {k:.4e}, b = {b:.4e}); set \
                         `sim.substeps`, `model.k_init` and `model.b_init`",
                            stability.frame_dt
                        );
                    }
                }
                (n, "auto")
            }
        },
    )
}
