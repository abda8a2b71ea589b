//! The fold scenarios (paper §4.4, Fig. 2): a square sheet released flat and at rest, pinned
//! at the neighbourhoods of two diagonally opposite corners, settles under gravity and
//! Rayleigh damping. The equilibrium is found by damped dynamics with the system's own
//! explicit step ([`settle`]); it does not depend on the damping used to reach it.

use anyhow::{Result, bail};
use serde::{Deserialize, Serialize};

use crate::source::{ClothSim, Diagonal};

/// Two corners of a grid as `(row, col)`.
pub type Corners = [(usize, usize); 2];

/// Which diagonal of the sheet is pinned, relative to the mesh's cell diagonals.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FoldCase {
    /// `fold_aligned`: the pinned corners lie on the diagonal that the cells' cuts follow, so
    /// the fold runs along mesh edges.
    Aligned,
    /// `fold_misaligned`: the other pair of corners; the fold cuts across the triangles.
    Misaligned,
}

impl FoldCase {
    /// Both cases, aligned first.
    pub const ALL: [FoldCase; 2] = [FoldCase::Aligned, FoldCase::Misaligned];

    /// `aligned` or `misaligned`.
    pub fn name(self) -> &'static str {
        match self {
            FoldCase::Aligned => "aligned",
            FoldCase::Misaligned => "misaligned",
        }
    }

    /// The pinned corners of an `nx × ny` grid cut along `diagonal`, as `(row, col)`, and the
    /// free corners. A main-diagonal mesh has its cuts along `(0, 0)–(n−1, n−1)`; an
    /// anti-diagonal mesh along `(0, n−1)–(n−1, 0)`. Alternating cuts have no aligned diagonal.
    pub fn corners(self, nx: usize, ny: usize, diagonal: Diagonal) -> Result<(Corners, Corners)> {
        let main = [(0, 0), (ny - 1, nx - 1)];
        let anti = [(0, nx - 1), (ny - 1, 0)];
        let aligned_is_main = match diagonal {
            Diagonal::Main => true,
            Diagonal::Anti => false,
            Diagonal::Alternating => {
                bail!("a mesh with alternating diagonals has no aligned fold (source.fem.diagonal)")
            }
        };
        Ok(if aligned_is_main == (self == FoldCase::Aligned) {
            (main, anti)
        } else {
            (anti, main)
        })
    }
}

/// Vertices of a grid (`rest_uv` row-major, `nx` per row) within `radius` of the given
/// corners in the rest rectangle: pins of one physical size at every resolution.
pub fn corner_pins(rest_uv: &[[f64; 2]], nx: usize, corners: &Corners, radius: f64) -> Vec<bool> {
    let r2 = radius * radius * (1.0 + 1e-9) + 1e-18;
    let centres = corners.map(|(r, c)| rest_uv[r * nx + c]);
    rest_uv
        .iter()
        .map(|p| {
            centres
                .iter()
                .any(|q| (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) <= r2)
        })
        .collect()
}

/// How an equilibrium is found: damped dynamics until the fastest free vertex is slower than
/// `tolerance` for `hold` seconds, or `max_seconds` have passed (the `[fold.settle]` section).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SettleConfig {
    /// Rayleigh damping per unit mass, 1/s: the constant `c` of `−c v` is this times the mean
    /// vertex mass, so every resolution is damped alike.
    pub damping_rate: f64,
    /// Strain-rate damping `β` used while settling, s (the material's own β limits the
    /// explicit step of fine meshes as `β ω²`; the equilibrium does not depend on it).
    pub strain_damping: f64,
    /// Velocity tolerance, m/s.
    pub tolerance: f64,
    /// How long the tolerance must hold, s.
    pub hold: f64,
    /// Step cap, in simulated seconds.
    pub max_seconds: f64,
    /// The step as a fraction of the largest stable step of the stability guard.
    pub dt_fraction: f64,
    /// Largest step, s.
    pub max_dt: f64,
}

impl Default for SettleConfig {
    fn default() -> Self {
        Self {
            damping_rate: 4.0,
            strain_damping: 0.0,
            tolerance: 1e-3,
            hold: 0.25,
            max_seconds: 30.0,
            dt_fraction: 0.8,
            max_dt: 1e-3,
        }
    }
}

impl SettleConfig {
    /// Checks ranges; errors name the key.
    pub fn validate(&self) -> Result<()> {
        for (key, v) in [
            ("damping_rate", self.damping_rate),
            ("tolerance", self.tolerance),
            ("max_seconds", self.max_seconds),
            ("max_dt", self.max_dt),
        ] {
            if !(v > 0.0 && v.is_finite()) {
                bail!("`fold.settle.{key}` must be positive, is {v}");
            }
        }
        if !(self.hold >= 0.0) || !(self.strain_damping >= 0.0) {
            bail!("`fold.settle.hold` and `fold.settle.strain_damping` must be non-negative");
        }
        if !(self.dt_fraction > 0.0 && self.dt_fraction < 1.0) {
            bail!(
                "`fold.settle.dt_fraction` must lie in (0, 1), is {}",
                self.dt_fraction
            );
        }
        Ok(())
    }
}

/// A settled state.
#[derive(Debug, Clone)]
pub struct Equilibrium {
    /// Positions, m.
    pub x: Vec<[f64; 3]>,
    /// Simulated time, s.
    pub seconds: f64,
    /// Steps taken.
    pub steps: usize,
    /// The step used, s.
    pub dt: f64,
    /// Fastest free vertex at the end, m/s.
    pub max_speed: f64,
    /// Whether the tolerance was met (else the cap stopped it).
    pub converged: bool,
}

/// The step [`settle`] takes for `sim`: `dt_fraction` of the guard's largest stable step,
/// at most `max_dt`.
pub fn settle_dt(sim: &dyn ClothSim, cfg: &SettleConfig) -> f64 {
    (cfg.dt_fraction * sim.stability(cfg.max_dt).max_stable_dt()).min(cfg.max_dt)
}

/// Damped dynamics from `x0` at rest until the equilibrium (see [`SettleConfig`]); `on_time`
/// gets the simulated time now and then. Fails when the simulation diverges.
pub fn settle(
    sim: &dyn ClothSim,
    x0: Vec<[f64; 3]>,
    pinned: &[bool],
    dt: f64,
    cfg: &SettleConfig,
    mut on_time: impl FnMut(f64),
) -> Result<Equilibrium> {
    let n = x0.len();
    let mut x = x0;
    let mut v = vec![[0.0f64; 3]; n];
    let mut scratch = Vec::new();
    // Check the speed every ~5 ms of simulated time.
    let every = ((5e-3 / dt).round() as usize).max(1);
    let max_steps = (cfg.max_seconds / dt).ceil() as usize;
    let mut held = 0.0;
    let mut step = 0;
    let mut max_speed = f64::INFINITY;
    let mut converged = false;
    while step < max_steps {
        for _ in 0..every {
            sim.step(&mut x, &mut v, pinned, dt, None, &mut scratch);
        }
        step += every;
        max_speed = v
            .iter()
            .zip(pinned)
            .filter(|(_, p)| !**p)
            .map(|(w, _)| (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt())
            .fold(0.0, f64::max);
        if !max_speed.is_finite() || x.iter().flatten().any(|c| !c.is_finite()) {
            bail!(
                "the fold diverged at t = {:.3} s (dt = {dt:.3e} s): {}",
                step as f64 * dt,
                sim.stability(dt).describe()
            );
        }
        if max_speed < cfg.tolerance {
            held += every as f64 * dt;
            if held >= cfg.hold {
                converged = true;
                break;
            }
        } else {
            held = 0.0;
        }
        if step % (every * 200) == 0 {
            on_time(step as f64 * dt);
        }
    }
    Ok(Equilibrium {
        x,
        seconds: step as f64 * dt,
        steps: step,
        dt,
        max_speed,
        converged,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::{FemCloth, FemConfig, Layout, SourceConfig, SourceKind};

    fn sheet(n: usize, rayleigh: f64) -> (SourceConfig, FemCloth) {
        let cfg = SourceConfig {
            kind: SourceKind::Fem,
            nx: n,
            ny: n,
            width: 1.0,
            height: 1.0,
            areal_density: 0.2,
            stiffness_levels: vec![300.0],
            layout: Layout::Uniform,
            rayleigh,
            fem: FemConfig {
                bending: 0.002,
                strain_damping: 0.0,
                ..FemConfig::default()
            },
            ..SourceConfig::default()
        };
        let fem = FemCloth::from_config(&cfg);
        (cfg, fem)
    }

    #[test]
    fn fold_scenarios_pin_the_right_corners_with_one_physical_radius() {
        // Main cuts run (0, 0)–(n−1, n−1): that diagonal is the aligned one.
        let (al, al_free) = FoldCase::Aligned.corners(5, 5, Diagonal::Main).unwrap();
        let (mis, mis_free) = FoldCase::Misaligned.corners(5, 5, Diagonal::Main).unwrap();
        assert_eq!(al, [(0, 0), (4, 4)]);
        assert_eq!(al_free, [(0, 4), (4, 0)]);
        assert_eq!(mis, [(0, 4), (4, 0)]);
        assert_eq!(mis_free, al);
        // An anti-diagonal mesh swaps them; alternating cuts have no aligned fold.
        assert_eq!(
            FoldCase::Aligned.corners(5, 5, Diagonal::Anti).unwrap().0,
            mis
        );
        assert!(
            FoldCase::Aligned
                .corners(5, 5, Diagonal::Alternating)
                .is_err()
        );
        // The same physical neighbourhood at two resolutions: every pinned vertex lies within
        // the radius of a pinned corner, and the fine mesh pins more vertices.
        let radius = 0.3;
        let mut counts = Vec::new();
        for n in [6, 16] {
            let (_, fem) = sheet(n, 0.0);
            let uv = fem.rest_uv();
            for case in FoldCase::ALL {
                let (corners, free) = case.corners(n, n, Diagonal::Main).unwrap();
                let pins = corner_pins(uv, n, &corners, radius);
                for (r, c) in corners {
                    assert!(
                        pins[r * n + c],
                        "corner ({r}, {c}) of {n} × {n} is not pinned"
                    );
                }
                for (r, c) in free {
                    assert!(!pins[r * n + c], "free corner ({r}, {c}) is pinned");
                }
                for (i, p) in uv.iter().enumerate() {
                    let near = corners.iter().any(|&(r, c)| {
                        let q = uv[r * n + c];
                        (p[0] - q[0]).hypot(p[1] - q[1]) <= radius + 1e-12
                    });
                    assert_eq!(pins[i], near, "vertex {i} of {n} × {n}");
                }
                counts.push(pins.iter().filter(|p| **p).count());
            }
        }
        // 6 × 6 (0.2 m spacing): corner + two neighbours + the diagonal one (0.28 m), twice.
        assert_eq!(counts[0], 8);
        assert!(counts[2] > 4 * counts[0], "{counts:?}");
    }

    #[test]
    fn equilibrium_is_reached_and_does_not_depend_on_the_damping() {
        let n = 6;
        let settle_with = |rate: f64| {
            let (cfg, _) = sheet(n, 0.0);
            let mass = cfg.areal_density / (n * n) as f64;
            let (_, fem) = sheet(n, rate * mass);
            let cfg = SettleConfig {
                damping_rate: rate,
                tolerance: 1e-4,
                hold: 0.1,
                max_seconds: 20.0,
                ..SettleConfig::default()
            };
            let (corners, _) = FoldCase::Misaligned.corners(n, n, Diagonal::Main).unwrap();
            let pins = corner_pins(fem.rest_uv(), n, &corners, 0.1);
            let dt = settle_dt(&fem, &cfg);
            settle(
                &fem,
                crate::cloth::flat(fem.rest_uv(), 1.0, 1.0),
                &pins,
                dt,
                &cfg,
                |_| {},
            )
            .unwrap()
        };
        let (slow, fast) = (settle_with(3.0), settle_with(12.0));
        for eq in [&slow, &fast] {
            assert!(eq.converged && eq.max_speed < 1e-4, "{:?}", eq.max_speed);
            // Gravity did something: the free corners hang well below the pins.
            assert!(eq.x.iter().map(|p| p[2]).fold(0.0, f64::min) < -0.2);
        }
        // Different paths (the damping differs by 4×), one equilibrium.
        assert!(slow.seconds != fast.seconds);
        let at: Vec<usize> = (0..n * n).collect();
        let gap = crate::fold::metrics::shape_rmse(&slow.x, &fast.x, &at);
        assert!(gap < 1e-3, "equilibria differ by {gap} m");
        // Stopped early the state is not an equilibrium: the test can fail.
        let (_, fem) = sheet(n, 0.0);
        let cfg = SettleConfig {
            max_seconds: 0.05,
            ..SettleConfig::default()
        };
        let (corners, _) = FoldCase::Misaligned.corners(n, n, Diagonal::Main).unwrap();
        let pins = corner_pins(fem.rest_uv(), n, &corners, 0.1);
        let early = settle(
            &fem,
            crate::cloth::flat(fem.rest_uv(), 1.0, 1.0),
            &pins,
            1e-3,
            &cfg,
            |_| {},
        )
        .unwrap();
        assert!(!early.converged);
        assert!(crate::fold::metrics::shape_rmse(&early.x, &slow.x, &at) > 1e-2);
    }
}
