//! The XPBD cloth of paper 001 (§3.3, Eqs. 1–6), f64: orthotropic Green-strain triangle blocks
//! (three rows solved together) and dihedral hinges, stepped quasi-statically from a given start
//! to equilibrium under clamps and loads, with the equilibrium residual and the clamps'
//! reactions as its measures. The triangulation, hinges and element maths are the FEM source's
//! ([`springtime_core::cloth::triangles`]).

use anyhow::{Result, bail};
use serde::{Deserialize, Serialize};

use super::contact::StaticContact;
use super::equilibrium::Sensitivity;
use super::material::Gamma;
use springtime_core::cloth::dual::Dual;
use springtime_core::cloth::lanes::Real;
use springtime_core::cloth::triangles::{self, Hinge, RestTriangle, V3, add_to, dot, scale, sub};

/// How the constraints are swept in one iteration.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum Sweep {
    /// Each block's correction is applied before the next block is solved.
    GaussSeidel,
    /// Every block is solved at the same positions; every block's multiplier increment and
    /// correction are scaled by `omega` and the corrections summed. (Averaging the corrections
    /// per vertex instead, as PBD does, leaves the multipliers out of step with the positions:
    /// its rest state is another one, 0.3 % off in sag on a hanging sheet.) Stable for
    /// `omega` below about one over the blocks that share a vertex.
    Jacobi {
        /// Relaxation of every block's increment.
        omega: f64,
    },
}

/// The solve to equilibrium: `steps` XPBD steps of `dt` (Macklin et al. 2016, Alg. 1) with the
/// velocity damped by `damping` per step (dynamic relaxation: `damping = 1` resets it, the
/// overdamped quasi-static stepping, which creeps; a little damping settles in a few
/// oscillation periods), `iterations` constraint sweeps per step.
///
/// XPBD's rest state departs from the true equilibrium `∇U = f` by `O(dt² |f_i| / m_i)`
/// relative to an edge (its update drops the primal residual): weights hang as masses
/// ([`Load::hang`]) so that `|f_i| / m_i` stays near `g`, and [`Equilibrium::residual`] reports
/// what is left.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default = "Solve::auto")]
pub struct Solve {
    /// Step, s (0 in a config: chosen by the estimator).
    pub dt: f64,
    /// Steps at most.
    pub steps: usize,
    /// Constraint sweeps per step.
    pub iterations: usize,
    /// Gauss–Seidel or Jacobi.
    pub sweep: Sweep,
    /// Fraction of the velocity removed each step, in (0, 1].
    pub damping: f64,
    /// Stop once the relative equilibrium residual is below this (checked every 50 steps;
    /// 0 = run every step).
    pub tolerance: f64,
    /// Gauss–Seidel only (ours; plain XPBD resets the multipliers every step): carry each
    /// step's multipliers `λ` into the next and start it from `x + h v + h²W f + W ∇Cᵀλ`. With
    /// them reset, a step's few sweeps leave the constraints unconverged and the rest state
    /// short of the equilibrium (a relative residual of 0.16 after 10 sweeps on a hanging
    /// 5 × 5 sheet, 4e-4 after 50); carried, the equilibrium `∇U = f` is itself a fixed point
    /// whatever the sweep count. It needs steps with `dt² k / m` of order 1 or less for the
    /// stiffest element (`k ≈ C·A/ℓ²`): at larger steps the carried multipliers overshoot and
    /// the solve diverges (measured: a hanging 5 × 5 sheet of 2.5 cm cells at 10 ms).
    pub warm_start: bool,
}

impl Solve {
    /// The defaults with the step left to the caller (`dt = 0`; the estimator picks it from
    /// the stiffest element): what a config's `[solve]` starts from.
    pub fn auto() -> Self {
        Self {
            dt: 0.0,
            ..Self::default()
        }
    }
}

impl Default for Solve {
    fn default() -> Self {
        Self {
            dt: 1e-3,
            steps: 20_000,
            iterations: 10,
            sweep: Sweep::GaussSeidel,
            damping: 0.02,
            tolerance: 1e-4,
            warm_start: true,
        }
    }
}

/// Boundary conditions: clamped vertices held at given positions, external forces, the
/// masses of hanging weights and a collider the cloth rests on.
#[derive(Debug, Clone)]
pub struct Load {
    /// The prescribed position of each clamped vertex (`None`: free).
    pub clamped: Vec<Option<V3>>,
    /// External force on each vertex (gravity on its mass plus any weights), N.
    pub force: Vec<V3>,
    /// Mass hung on each vertex (weights), kg: it moves with the vertex.
    pub added_mass: Vec<f64>,
    /// A rigid body under the cloth (a ledge), whose penalty layer is part of the potential.
    pub contact: Option<StaticContact>,
}

impl Load {
    /// Gravity `g` on the cloth, nothing clamped.
    pub fn gravity(cloth: &XpbdCloth, g: V3) -> Self {
        Self {
            clamped: vec![None; cloth.len()],
            force: cloth.mass.iter().map(|&m| scale(g, m)).collect(),
            added_mass: vec![0.0; cloth.len()],
            contact: None,
        }
    }

    /// No force, nothing clamped.
    pub fn none(n: usize) -> Self {
        Self {
            clamped: vec![None; n],
            force: vec![[0.0; 3]; n],
            added_mass: vec![0.0; n],
            contact: None,
        }
    }

    /// Hangs `mass` (kg) on vertex `i` under gravity `g`.
    pub fn hang(&mut self, i: usize, mass: f64, g: V3) {
        self.added_mass[i] += mass;
        add_to(&mut self.force[i], scale(g, mass));
    }

    /// The relative equilibrium residual `‖∇U − f‖ / ‖f‖` over the free vertices, given the
    /// gradient `grad` of any cloth model's energy plus the contact's ([`Self::add_contact`]).
    pub fn residual(&self, grad: &[V3]) -> f64 {
        let (mut r2, mut f2) = (0.0, 0.0);
        for i in 0..grad.len() {
            if self.clamped[i].is_none() {
                let d = sub(grad[i], self.force[i]);
                r2 += dot(d, d);
                f2 += dot(self.force[i], self.force[i]);
            }
        }
        (r2 / f2.max(f64::MIN_POSITIVE)).sqrt()
    }

    /// The force the clamps of `group` exert on the cloth: `Σ (∇U − f)` over its vertices
    /// (`grad` as in [`Self::residual`]).
    pub fn reaction(&self, grad: &[V3], group: &[usize]) -> V3 {
        let mut r = [0.0; 3];
        for &i in group {
            add_to(&mut r, sub(grad[i], self.force[i]));
        }
        r
    }

    /// `grad += ∇E_c(x)`, the contact's part of the potential's gradient (nothing without a
    /// collider).
    pub fn add_contact(&self, x: &[V3], grad: &mut [V3]) {
        if let Some(c) = &self.contact {
            c.add_gradient(x, grad);
        }
    }

    /// The contact's penalty energy at `x`, J (0 without a collider).
    pub fn contact_energy(&self, x: &[V3]) -> f64 {
        self.contact.as_ref().map_or(0.0, |c| c.energy(x))
    }
}

/// A cloth at equilibrium.
#[derive(Debug, Clone, PartialEq)]
pub struct Equilibrium {
    /// Positions.
    pub x: Vec<V3>,
    /// `‖∇U + ∇E_c − f‖ / ‖f‖` over the free vertices' coordinates (`E_c`: the load's contact).
    pub residual: f64,
    /// Steps taken.
    pub steps: usize,
}

/// The XPBD cloth over a triangle mesh of its flat rest shape.
#[derive(Debug, Clone)]
pub struct XpbdCloth {
    /// Rest coordinates (u along the warp, v along the weft), m.
    pub rest_uv: Vec<[f64; 2]>,
    /// The triangles' rest frames.
    pub triangles: Vec<RestTriangle>,
    /// Interior edges.
    pub hinges: Vec<Hinge>,
    /// Lumped vertex masses (a third of each triangle's), kg.
    pub mass: Vec<f64>,
}

impl XpbdCloth {
    /// A cloth over `triangles` of `rest_uv` with areal density `density` (kg/m²).
    pub fn new(rest_uv: Vec<[f64; 2]>, triangles: &[[usize; 3]], density: f64) -> Result<Self> {
        let mut mass = vec![0.0; rest_uv.len()];
        let mut rest = Vec::with_capacity(triangles.len());
        for (i, &t) in triangles.iter().enumerate() {
            if t.iter().any(|&v| v >= rest_uv.len()) {
                bail!(
                    "triangle {i} {t:?} names a vertex beyond the {} given",
                    rest_uv.len()
                );
            }
            let Some(r) = RestTriangle::new(&rest_uv, t) else {
                bail!("triangle {i} {t:?} is degenerate (zero rest area)");
            };
            for &v in &t {
                mass[v] += density * r.area / 3.0;
            }
            rest.push(r);
        }
        Ok(Self {
            hinges: triangles::hinges(triangles),
            rest_uv,
            triangles: rest,
            mass,
        })
    }

    /// An `nx × ny` grid over a `width × height` rectangle (row-major, `u` along a row),
    /// triangulated like the FEM source's alternating grid.
    pub fn grid(nx: usize, ny: usize, width: f64, height: f64, density: f64) -> Result<Self> {
        if nx < 2 || ny < 2 {
            bail!("an XPBD grid needs at least 2 × 2 vertices, not {nx} × {ny}");
        }
        let uv = (0..ny)
            .flat_map(|r| {
                (0..nx).map(move |c| {
                    [
                        width * c as f64 / (nx - 1) as f64,
                        height * r as f64 / (ny - 1) as f64,
                    ]
                })
            })
            .collect();
        let tris = springtime_core::source::fem::grid_triangles(
            nx,
            ny,
            springtime_core::source::Diagonal::Alternating,
        );
        Self::new(uv, &tris, density)
    }

    /// Number of vertices.
    pub fn len(&self) -> usize {
        self.rest_uv.len()
    }

    /// Whether the cloth has no vertices.
    pub fn is_empty(&self) -> bool {
        self.rest_uv.is_empty()
    }

    /// The flat rest positions (z = 0).
    pub fn rest(&self) -> Vec<V3> {
        self.rest_uv.iter().map(|p| [p[0], p[1], 0.0]).collect()
    }

    /// Elastic energy (membrane and bending), J.
    pub fn energy(&self, gamma: &Gamma, x: &[V3]) -> f64 {
        self.element_energies(gamma, x).iter().sum()
    }

    /// Every element's energy, J: each triangle's membrane energy, then each hinge's bending
    /// energy (paper 001 Eq. 9's `U_triangle`, `U_bend`).
    pub fn element_energies(&self, gamma: &Gamma, x: &[V3]) -> Vec<f64> {
        let membrane = self
            .triangles
            .iter()
            .map(|t| t.area * gamma.membrane_density(strain(t, x).0));
        let bending = self
            .hinges
            .iter()
            .map(|h| 0.5 * gamma.b * triangles::dihedral(h, x).0.powi(2));
        membrane.chain(bending).collect()
    }

    /// Every element's strain (the constraints `C` of the XPBD blocks): each triangle's Voigt
    /// Green strain `(ε_uu, ε_vv, 2ε_uv)`, then each hinge's signed dihedral angle, rad.
    pub fn element_strains(&self, x: &[V3]) -> Vec<f64> {
        let membrane = self.triangles.iter().flat_map(|t| strain(t, x).0);
        let bending = self.hinges.iter().map(|h| triangles::dihedral(h, x).0);
        membrane.chain(bending).collect()
    }

    /// `∇U(x)`, written into `out`.
    pub fn gradient(&self, gamma: &Gamma, x: &[V3], out: &mut [V3]) {
        self.gradient_of(gamma.to_array(), x, out);
    }

    /// [`gradient`](Self::gradient) in any [`Scalar`], γ as `[C00, C11, C01, C22, b]`.
    fn gradient_of<R: Scalar>(&self, gamma: [R; 5], x: &[[R; 3]], out: &mut [[R; 3]]) {
        out.fill([R::splat(0.0); 3]);
        let [c00, c11, c01, c22, b] = gamma;
        for t in &self.triangles {
            let (e, g) = strain_of(t, x);
            let s = [c00 * e[0] + c01 * e[1], c01 * e[0] + c11 * e[1], c22 * e[2]];
            let area = R::splat(t.area);
            for (k, &v) in t.v.iter().enumerate() {
                for (row, &sr) in s.iter().enumerate() {
                    add_to(&mut out[v], scale(g[row][k], area * sr));
                }
            }
        }
        for h in &self.hinges {
            let (theta, g) = triangles::dihedral_of([x[h.a], x[h.b], x[h.c], x[h.d]]);
            for (v, gv) in [h.c, h.d, h.a, h.b].into_iter().zip(g) {
                add_to(&mut out[v], scale(gv, b * theta));
            }
        }
    }

    /// `∇U(x) + ∇E_c(x)`: the gradient of the elastic energy and of `load`'s contact, the
    /// part of the potential's gradient that is not the constant force (written into `out`).
    pub fn net_gradient(&self, gamma: &Gamma, load: &Load, x: &[V3], out: &mut [V3]) {
        self.gradient(gamma, x, out);
        load.add_contact(x, out);
    }

    /// The relative equilibrium residual `‖∇U + ∇E_c − f‖ / ‖f‖` over the free vertices.
    pub fn residual(&self, gamma: &Gamma, load: &Load, x: &[V3]) -> f64 {
        let mut g = vec![[0.0; 3]; x.len()];
        self.net_gradient(gamma, load, x, &mut g);
        load.residual(&g)
    }

    /// The force the clamps of `group` exert on the cloth: `Σ (∇U + ∇E_c − f)` over its
    /// vertices.
    pub fn reaction(&self, gamma: &Gamma, load: &Load, x: &[V3], group: &[usize]) -> V3 {
        let mut g = vec![[0.0; 3]; x.len()];
        self.net_gradient(gamma, load, x, &mut g);
        load.reaction(&g, group)
    }

    /// Steps from `start` (at rest) to equilibrium (see [`Solve`]).
    pub fn solve(
        &self,
        gamma: &Gamma,
        load: &Load,
        start: &[V3],
        cfg: &Solve,
    ) -> Result<Equilibrium> {
        let (x, steps) = self.iterate(gamma.to_array(), load, start.to_vec(), cfg)?;
        Ok(Equilibrium {
            residual: self.residual(gamma, load, &x),
            x,
            steps,
        })
    }

    /// [`solve`](Self::solve) with the derivatives of every iterate with respect to γ
    /// accumulated beside it in forward mode (dual numbers through the same iterations, as
    /// paper 001 §3.3.2 does): the equilibrium, `dx/dγ_k` per vertex (zero on clamped ones) and
    /// `dR_G/dγ_k` of the reactions of the clamp `groups`. At a converged equilibrium they
    /// equal the implicit-function derivatives ([`super::equilibrium::sensitivity`]); before
    /// it, they are the iterate's own.
    pub fn solve_with_derivatives(
        &self,
        gamma: &Gamma,
        load: &Load,
        start: &[V3],
        cfg: &Solve,
        groups: &[Vec<usize>],
    ) -> Result<(Equilibrium, Sensitivity)> {
        if load.contact.is_some() {
            bail!(
                "forward-mode derivatives do not follow contact (the ledge's penalty is applied \
                 at the positions' values): use the implicit ones (`fit.derivatives = \
                 \"implicit\"`)"
            );
        }
        let g = gamma.to_array();
        let params: [Dual<5>; 5] = std::array::from_fn(|k| Dual::parameter(g[k], k));
        let start = start.iter().map(|p| p.map(Dual::constant)).collect();
        let (xd, steps) = self.iterate(params, load, start, cfg)?;
        let mut grad = vec![[Dual::constant(0.0); 3]; xd.len()];
        self.gradient_of(params, &xd, &mut grad);
        let reactions = groups
            .iter()
            .map(|group| {
                let mut r = [Dual::<5>::constant(0.0); 3];
                for &i in group {
                    add_to(&mut r, grad[i]);
                }
                std::array::from_fn(|k| r.map(|c| c.d[k]))
            })
            .collect();
        let x: Vec<V3> = xd.iter().map(|p| p.map(|c| c.v)).collect();
        let dx = std::array::from_fn(|k| xd.iter().map(|p| p.map(|c| c.d[k])).collect());
        Ok((
            Equilibrium {
                residual: self.residual(gamma, load, &x),
                x,
                steps,
            },
            Sensitivity { dx, reactions },
        ))
    }

    /// The XPBD steps of [`solve`](Self::solve) in any [`Scalar`]: γ as
    /// `[C00, C11, C01, C22, b]`; the positions and the steps taken.
    fn iterate<R: Scalar>(
        &self,
        gamma: [R; 5],
        load: &Load,
        start: Vec<[R; 3]>,
        cfg: &Solve,
    ) -> Result<(Vec<[R; 3]>, usize)> {
        let n = self.len();
        let contact = load.contact.as_ref().map_or(n, |c| c.stiffness.len());
        if start.len() != n
            || load.clamped.len() != n
            || load.force.len() != n
            || load.added_mass.len() != n
            || contact != n
        {
            bail!(
                "the start ({}), clamps ({}), forces ({}), hung masses ({}) and contact \
                 stiffnesses ({contact}) must each have one entry per vertex ({n})",
                start.len(),
                load.clamped.len(),
                load.force.len(),
                load.added_mass.len()
            );
        }
        if !(cfg.damping > 0.0 && cfg.damping <= 1.0 && cfg.dt > 0.0) {
            bail!(
                "the solve needs dt > 0 and damping in (0, 1], not {} and {}",
                cfg.dt,
                cfg.damping
            );
        }
        let w: Vec<R> = (0..n)
            .map(|i| {
                let m = self.mass[i] + load.added_mass[i];
                R::splat(if load.clamped[i].is_some() || m <= 0.0 {
                    0.0
                } else {
                    1.0 / m
                })
            })
            .collect();
        let (h, h2) = (R::splat(cfg.dt), R::splat(cfg.dt * cfg.dt));
        let stiffness = [
            [gamma[0], gamma[2], R::splat(0.0)],
            [gamma[2], gamma[1], R::splat(0.0)],
            [R::splat(0.0), R::splat(0.0), gamma[3]],
        ];
        let mut x = start;
        let zero3 = [R::splat(0.0); 3];
        let mut v = vec![zero3; n];
        let mut lambda_t = vec![zero3; self.triangles.len()];
        let mut lambda_h = vec![R::splat(0.0); self.hinges.len()];
        let mut dx = vec![zero3; n];
        let (jacobi, relax) = match cfg.sweep {
            Sweep::GaussSeidel => (false, 1.0),
            Sweep::Jacobi { omega } => (true, omega),
        };
        let warm = cfg.warm_start;
        let keep = R::splat((1.0 - cfg.damping) / cfg.dt);
        if let Some(c) = &load.contact {
            // The contact force is explicit: stable while `h² m_i κ / m_i` is well below 1.
            let worst = (0..n)
                .filter(|&i| load.clamped[i].is_none())
                .map(|i| c.stiffness[i] / (self.mass[i] + load.added_mass[i]))
                .fold(0.0, f64::max);
            if cfg.dt * cfg.dt * worst > 0.5 {
                bail!(
                    "the XPBD step dt = {} s is too long for the contact's stiffness κ = {worst:.3e}/s² \
                     (dt² κ must stay below 0.5): lower `solve.dt` or the scenario's `stiffness`",
                    cfg.dt
                );
            }
        }
        let mut steps = 0;
        while steps < cfg.steps {
            let prev = x.clone();
            let mut push: Vec<[R; 3]> = load
                .force
                .iter()
                .map(|f| scale(f.map(R::splat), h2))
                .collect();
            if let Some(c) = &load.contact {
                // At the values: the forward-mode derivatives refuse contact.
                for (i, p) in push.iter_mut().enumerate() {
                    let g = c.vertex_gradient(i, x[i].map(R::value));
                    add_to(p, scale(g.map(R::splat), -h2));
                }
            }
            if warm {
                self.add_impulses(&x, &lambda_t, &lambda_h, &mut push);
            } else {
                lambda_t.fill(zero3);
                lambda_h.fill(R::splat(0.0));
            }
            for i in 0..n {
                x[i] = match load.clamped[i] {
                    Some(p) => p.map(R::splat),
                    None => [0, 1, 2].map(|c| x[i][c] + h * v[i][c] + w[i] * push[i][c]),
                };
            }
            for _ in 0..cfg.iterations {
                if jacobi {
                    dx.fill(zero3);
                }
                for (t, lam) in self.triangles.iter().zip(lambda_t.iter_mut()) {
                    let corr = membrane_block(t, &x, &w, &stiffness, h2, relax, lam);
                    apply(&t.v, &corr, &mut x, &mut dx, jacobi);
                }
                for (hg, lam) in self.hinges.iter().zip(lambda_h.iter_mut()) {
                    let corr = hinge_block(hg, &x, &w, gamma[4], h2, relax, lam);
                    apply(&[hg.c, hg.d, hg.a, hg.b], &corr, &mut x, &mut dx, jacobi);
                }
                if jacobi {
                    for i in 0..n {
                        add_to(&mut x[i], dx[i]);
                    }
                }
            }
            for i in 0..n {
                v[i] = scale(sub(x[i], prev[i]), keep);
            }
            steps += 1;
            if !x.iter().flatten().all(|c| c.value().is_finite()) {
                bail!(
                    "the XPBD solve diverged at step {steps} (dt = {} s)",
                    cfg.dt
                );
            }
            if cfg.tolerance > 0.0 && steps % 50 == 0 {
                let values: Vec<V3> = x.iter().map(|p| p.map(R::value)).collect();
                let gamma = Gamma::from_array(gamma.map(R::value));
                if self.residual(&gamma, load, &values) < cfg.tolerance {
                    break;
                }
            }
        }
        Ok((x, steps))
    }

    /// `out += ∇Cᵀλ` over every block: the constraints' impulses (`h²` times their forces).
    fn add_impulses<R: Scalar>(&self, x: &[[R; 3]], lt: &[[R; 3]], lh: &[R], out: &mut [[R; 3]]) {
        for (t, lam) in self.triangles.iter().zip(lt) {
            let (_, g) = strain_of(t, x);
            for (k, &v) in t.v.iter().enumerate() {
                for row in 0..3 {
                    add_to(&mut out[v], scale(g[row][k], lam[row]));
                }
            }
        }
        for (h, &lam) in self.hinges.iter().zip(lh) {
            let (_, g) = triangles::dihedral_of([x[h.a], x[h.b], x[h.c], x[h.d]]);
            for (v, gv) in [h.c, h.d, h.a, h.b].into_iter().zip(g) {
                add_to(&mut out[v], scale(gv, lam));
            }
        }
    }
}

/// The number types the XPBD iterations run in: `f64`, and [`Dual`] numbers carrying the
/// derivatives with respect to γ.
pub trait Scalar: Real<Mask = bool> {
    /// The value (without derivatives).
    fn value(self) -> f64;
    /// `y` with `a y = rhs`, `a` 3 × 3 (zero if `a` is singular).
    fn solve3(a: [[Self; 3]; 3], rhs: [Self; 3]) -> [Self; 3];
}

/// The LU factors of a 3 × 3 matrix, `None` if singular.
fn lu3(a: [[f64; 3]; 3]) -> nalgebra::LU<f64, nalgebra::U3, nalgebra::U3> {
    nalgebra::Matrix3::from_fn(|r, c| a[r][c]).lu()
}

impl Scalar for f64 {
    fn value(self) -> f64 {
        self
    }
    fn solve3(a: [[f64; 3]; 3], rhs: [f64; 3]) -> [f64; 3] {
        lu3(a)
            .solve(&nalgebra::Vector3::from(rhs))
            .unwrap_or_else(nalgebra::Vector3::zeros)
            .into()
    }
}

impl<const N: usize> Scalar for Dual<N> {
    fn value(self) -> f64 {
        self.v
    }
    /// The value's system, then per parameter `a ẏ = ṙ − ȧ y` with the same factors.
    fn solve3(a: [[Self; 3]; 3], rhs: [Self; 3]) -> [Self; 3] {
        let lu = lu3(a.map(|row| row.map(|e| e.v)));
        let solve = |r: [f64; 3]| lu.solve(&nalgebra::Vector3::from(r));
        let Some(y) = solve(rhs.map(|e| e.v)) else {
            return [Dual::constant(0.0); 3];
        };
        let mut out: [Self; 3] = std::array::from_fn(|r| Dual::constant(y[r]));
        for k in 0..N {
            let r: [f64; 3] = std::array::from_fn(|i| {
                rhs[i].d[k] - (0..3).map(|j| a[i][j].d[k] * y[j]).sum::<f64>()
            });
            let dy = solve(r).unwrap_or_else(nalgebra::Vector3::zeros);
            for i in 0..3 {
                out[i].d[k] = dy[i];
            }
        }
        out
    }
}

/// `Σ_{i<n} f(i)`, in order.
fn sum<R: Real>(n: usize, f: impl Fn(usize) -> R) -> R {
    (0..n).fold(R::splat(-0.0), |acc, i| acc + f(i))
}

/// A triangle's Voigt Green strain `(ε_uu, ε_vv, 2ε_uv)` and its gradient: `g[row][k]` is the
/// gradient of row `row` with respect to the triangle's vertex `k`.
pub fn strain(t: &RestTriangle, x: &[V3]) -> ([f64; 3], [[V3; 3]; 3]) {
    strain_of(t, x)
}

/// [`strain`] in any number type.
#[allow(clippy::type_complexity)]
fn strain_of<R: Real>(t: &RestTriangle, x: &[[R; 3]]) -> ([R; 3], [[[R; 3]; 3]; 3]) {
    let m = t.dm_inv.map(|row| row.map(R::splat));
    let f = triangles::deformation([x[t.v[0]], x[t.v[1]], x[t.v[2]]], m);
    let e = triangles::green(f);
    let fu = [f[0][0], f[1][0], f[2][0]];
    let fv = [f[0][1], f[1][1], f[2][1]];
    let (a, b, c, d) = (m[0][0], m[0][1], m[1][0], m[1][1]);
    let lin =
        |p: [R; 3], q: [R; 3], s: R, r: R| -> [R; 3] { [0, 1, 2].map(|i| s * p[i] + r * q[i]) };
    let uu1 = scale(fu, a);
    let uu2 = scale(fu, c);
    let vv1 = scale(fv, b);
    let vv2 = scale(fv, d);
    let uv1 = lin(fv, fu, a, b);
    let uv2 = lin(fv, fu, c, d);
    let neg = |p: [R; 3], q: [R; 3]| -> [R; 3] { [0, 1, 2].map(|i| -(p[i] + q[i])) };
    (
        [e[0][0], e[1][1], R::splat(2.0) * e[0][1]],
        [
            [neg(uu1, uu2), uu1, uu2],
            [neg(vv1, vv2), vv1, vv2],
            [neg(uv1, uv2), uv1, uv2],
        ],
    )
}

/// One membrane block: solves `(h² A K S + I) Δλ = −h² A K C − λ` (the compliance form
/// multiplied through by `h² A K`, valid for a singular `K`), adds `relax · Δλ` to `λ` and
/// returns the corrections `relax · w_k G_kᵀ Δλ` of the three vertices.
fn membrane_block<R: Scalar>(
    t: &RestTriangle,
    x: &[[R; 3]],
    w: &[R],
    k: &[[R; 3]; 3],
    h2: R,
    relax: f64,
    lambda: &mut [R; 3],
) -> [[R; 3]; 3] {
    let (c, g) = strain_of(t, x);
    let wk = t.v.map(|v| w[v]);
    let s: [[R; 3]; 3] =
        std::array::from_fn(|r| std::array::from_fn(|q| sum(3, |j| wk[j] * dot(g[r][j], g[q][j]))));
    let ha = h2 * R::splat(t.area);
    let ak: [[R; 3]; 3] = k.map(|row| row.map(|v| ha * v));
    let a: [[R; 3]; 3] = std::array::from_fn(|r| {
        std::array::from_fn(|q| {
            sum(3, |m| ak[r][m] * s[m][q]) + R::splat(if r == q { 1.0 } else { 0.0 })
        })
    });
    let rhs: [R; 3] = std::array::from_fn(|r| -sum(3, |m| ak[r][m] * c[m]) - lambda[r]);
    // The system is I plus a positive semi-definite product: never singular in practice.
    let dl = R::solve3(a, rhs).map(|d| R::splat(relax) * d);
    for r in 0..3 {
        lambda[r] = lambda[r] + dl[r];
    }
    std::array::from_fn(|j| {
        let mut d = [R::splat(0.0); 3];
        for r in 0..3 {
            add_to(&mut d, scale(g[r][j], wk[j] * dl[r]));
        }
        d
    })
}

/// One hinge: `Δλ = −(b h² θ + λ) / (b h² Σ w |∇θ|² + 1)`, scaled by `relax`; corrections of
/// `(c, d, a, b)`.
fn hinge_block<R: Scalar>(
    h: &Hinge,
    x: &[[R; 3]],
    w: &[R],
    b: R,
    h2: R,
    relax: f64,
    lambda: &mut R,
) -> [[R; 3]; 4] {
    let (theta, g) = triangles::dihedral_of([x[h.a], x[h.b], x[h.c], x[h.d]]);
    let wk = [h.c, h.d, h.a, h.b].map(|v| w[v]);
    let denom = b * h2 * sum(4, |k| wk[k] * dot(g[k], g[k])) + R::splat(1.0);
    let dl = R::splat(-relax) * (b * h2 * theta + *lambda) / denom;
    *lambda = *lambda + dl;
    std::array::from_fn(|k| scale(g[k], wk[k] * dl))
}

/// Applies a block's corrections now (Gauss–Seidel) or gathers them (Jacobi).
fn apply<R: Real>(v: &[usize], corr: &[[R; 3]], x: &mut [[R; 3]], dx: &mut [[R; 3]], jacobi: bool) {
    for (&i, d) in v.iter().zip(corr) {
        if jacobi {
            add_to(&mut dx[i], *d);
        } else {
            add_to(&mut x[i], *d);
        }
    }
}

/// `x` rotated about the y axis by the rotation `(cos, sin)` and then moved by (1, −2, 0.5): a
/// rigid motion, for the tests of what does not see one.
#[cfg(test)]
pub(crate) fn rigidly_moved(x: &[V3], (c, s): (f64, f64)) -> Vec<V3> {
    x.iter()
        .map(|p| {
            [
                c * p[0] - s * p[2] + 1.0,
                p[1] - 2.0,
                s * p[0] + c * p[2] + 0.5,
            ]
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use springtime_core::source::Diagonal;
    use springtime_core::source::fem::{FemCloth, FemMaterial, Membrane, grid_triangles};

    fn wavy(cloth: &XpbdCloth, amp: f64) -> Vec<V3> {
        cloth
            .rest_uv
            .iter()
            .map(|p| {
                [
                    p[0] * 1.03 + amp * (3.0 * p[1]).sin(),
                    p[1] * 0.98 + amp * (2.0 * p[0]).cos(),
                    amp * (5.0 * p[0] + 4.0 * p[1]).sin(),
                ]
            })
            .collect()
    }

    #[test]
    fn green_strain_is_zero_under_rigid_motion() {
        let cloth = XpbdCloth::grid(4, 3, 0.3, 0.2, 0.2).unwrap();
        let x = rigidly_moved(&cloth.rest(), (0.6f64.cos(), 0.6f64.sin()));
        let g = Gamma::isotropic(100.0, 0.3, 1e-3);
        for t in &cloth.triangles {
            let (e, _) = strain(t, &x);
            assert!(e.iter().all(|v| v.abs() < 1e-14), "{e:?}");
        }
        assert!(cloth.energy(&g, &x).abs() < 1e-24);
    }

    #[test]
    fn constraint_and_hinge_jacobians_equal_finite_differences() {
        let cloth = XpbdCloth::grid(3, 3, 0.2, 0.2, 0.2).unwrap();
        let eps = 1e-7;
        for x in [cloth.rest(), wavy(&cloth, 0.02)] {
            for t in &cloth.triangles {
                let (_, g) = strain(t, &x);
                for (k, &v) in t.v.iter().enumerate() {
                    for c in 0..3 {
                        let (mut up, mut dn) = (x.clone(), x.clone());
                        up[v][c] += eps;
                        dn[v][c] -= eps;
                        let (eu, ed) = (strain(t, &up).0, strain(t, &dn).0);
                        for row in 0..3 {
                            let fd = (eu[row] - ed[row]) / (2.0 * eps);
                            assert!(
                                (fd - g[row][k][c]).abs() < 1e-6,
                                "row {row}: {fd} vs {}",
                                g[row][k][c]
                            );
                        }
                    }
                }
            }
            // Hinges, the flat rest state included (θ = 0 and a finite gradient).
            for h in &cloth.hinges {
                let (_, g) = triangles::dihedral(h, &x);
                for (k, v) in [h.c, h.d, h.a, h.b].into_iter().enumerate() {
                    for c in 0..3 {
                        let (mut up, mut dn) = (x.clone(), x.clone());
                        up[v][c] += eps;
                        dn[v][c] -= eps;
                        let fd = (triangles::dihedral(h, &up).0 - triangles::dihedral(h, &dn).0)
                            / (2.0 * eps);
                        assert!(
                            (fd - g[k][c]).abs() < 1e-5 * (1.0 + fd.abs()),
                            "{fd} vs {}",
                            g[k][c]
                        );
                    }
                }
            }
        }
        // The energy gradient too.
        let gamma = Gamma::from_engineering(181.0, 507.0, 40.0, 0.4, 5e-6);
        let x = wavy(&cloth, 0.02);
        let mut g = vec![[0.0; 3]; x.len()];
        cloth.gradient(&gamma, &x, &mut g);
        for v in 0..x.len() {
            for c in 0..3 {
                let (mut up, mut dn) = (x.clone(), x.clone());
                up[v][c] += eps;
                dn[v][c] -= eps;
                let fd = (cloth.energy(&gamma, &up) - cloth.energy(&gamma, &dn)) / (2.0 * eps);
                assert!(
                    (fd - g[v][c]).abs() < 1e-6 * (1.0 + fd.abs()),
                    "{fd} vs {}",
                    g[v][c]
                );
            }
        }
    }

    #[test]
    fn the_orthotropic_membrane_with_isotropic_parameters_is_the_fem_sources_stvk() {
        let (n, size, youngs, nu) = (5, 0.4, 250.0, 0.3);
        let cloth = XpbdCloth::grid(n, n, size, size, 0.2).unwrap();
        let fem = FemCloth::new(
            cloth.rest_uv.clone(),
            &grid_triangles(n, n, Diagonal::Alternating),
            &vec![youngs; 2 * (n - 1) * (n - 1)],
            FemMaterial {
                poisson: nu,
                bending: 0.0,
                strain_damping: 0.0,
                membrane: Membrane::Stvk,
                areal_density: 0.2,
                rayleigh: 0.0,
                gravity: [0.0; 3],
            },
        );
        let gamma = Gamma::isotropic(youngs, nu, 0.0);
        for amp in [0.0, 0.01, 0.05] {
            let x = wavy(&cloth, amp);
            let (a, b) = (cloth.energy(&gamma, &x), fem.membrane_energy(&x));
            assert!((a - b).abs() <= 1e-12 * b.abs().max(1e-12), "{a} vs {b}");
        }
        assert_eq!(cloth.mass, fem.masses());
    }

    #[test]
    fn a_hanging_strip_under_a_weight_stretches_as_its_closed_form() {
        // A 2 cm × 10 cm strip clamped along its top edge, a 100 g weight hung on its bottom
        // edge (gravity on the weight only): away from the ends the weft stretch s solves
        // W / w₀ = E_v ε (1 + s), with ε = ½((1 + s)² − 1) the Green strain and
        // E_v = C11 − C01²/C00 the uniaxial modulus (the lateral contraction is free).
        let (nx, ny, w0, len) = (3, 21, 0.02, 0.1);
        let cloth = XpbdCloth::grid(nx, ny, w0, len, 0.2).unwrap();
        let gamma = Gamma::from_engineering(180.0, 500.0, 40.0, 0.3, 0.0);
        let (mass, g) = (0.1, [0.0, -9.81, 0.0]);
        let rest = cloth.rest();
        let mut load = Load::none(cloth.len());
        for c in 0..nx {
            // Clamped along v = len; the weight hangs from the edge v = 0 (gravity along −v).
            load.clamped[(ny - 1) * nx + c] = Some(rest[(ny - 1) * nx + c]);
            load.hang(c, mass * if c == 0 || c == nx - 1 { 0.25 } else { 0.5 }, g);
        }
        // Light vertices (3 mg) on stiff edges: the carried multipliers need h²k/m ≲ 1.
        let solve = Solve {
            dt: 1e-4,
            steps: 200_000,
            iterations: 10,
            sweep: Sweep::GaussSeidel,
            damping: 0.02,
            tolerance: 1e-8,
            warm_start: true,
        };
        let eq = cloth.solve(&gamma, &load, &rest, &solve).unwrap();
        assert!(
            eq.residual < 1e-3,
            "residual {} after {} steps",
            eq.residual,
            eq.steps
        );
        // The stretch of the middle third, along the centre line.
        let at = |r: usize| eq.x[r * nx + 1][1];
        let (r0, r1) = (ny / 3, 2 * ny / 3);
        let stretch = (at(r1) - at(r0)) / (len * (r1 - r0) as f64 / (ny - 1) as f64) - 1.0;
        let e_v = gamma.engineering()[1];
        let target = mass * 9.81 / w0;
        let (mut lo, mut hi) = (0.0f64, 1.0f64);
        for _ in 0..100 {
            let s = 0.5 * (lo + hi);
            let eps = 0.5 * ((1.0 + s).powi(2) - 1.0);
            if e_v * eps * (1.0 + s) < target {
                lo = s
            } else {
                hi = s
            }
        }
        assert!(lo > 0.05, "a real stretch: {lo}");
        assert!(
            (stretch - lo).abs() < 0.02 * lo,
            "stretch {stretch} vs closed form {lo}"
        );
    }

    #[test]
    fn gauss_seidel_and_jacobi_reach_the_equilibrium_that_plain_xpbd_falls_short_of() {
        let cloth = XpbdCloth::grid(5, 5, 0.1, 0.1, 0.2).unwrap();
        let gamma = Gamma::from_engineering(180.0, 500.0, 40.0, 0.3, 5e-5);
        let rest = cloth.rest();
        let mut load = Load::gravity(&cloth, [0.0, 0.0, -9.81]);
        for c in 0..5 {
            load.clamped[c] = Some(rest[c]);
        }
        let base = Solve {
            dt: 1e-3,
            steps: 3000,
            iterations: 10,
            sweep: Sweep::GaussSeidel,
            damping: 0.02,
            tolerance: 0.0,
            warm_start: true,
        };
        let gs = cloth.solve(&gamma, &load, &rest, &base).unwrap();
        let jacobi = Solve {
            sweep: Sweep::Jacobi { omega: 0.25 },
            ..base
        };
        let jc = cloth.solve(&gamma, &load, &rest, &jacobi).unwrap();
        let plain = Solve {
            warm_start: false,
            ..base
        };
        let pl = cloth.solve(&gamma, &load, &rest, &plain).unwrap();
        let sag = |x: &[V3]| x.iter().map(|p| p[2]).fold(0.0, f64::min);
        assert!(sag(&gs.x) < -0.05, "the sheet hangs: sag {}", sag(&gs.x));
        assert!(
            gs.residual < 1e-8 && jc.residual < 1e-8,
            "{} {}",
            gs.residual,
            jc.residual
        );
        let d =
            gs.x.iter()
                .zip(&jc.x)
                .map(|(a, b)| dot(sub(*a, *b), sub(*a, *b)).sqrt())
                .fold(0.0, f64::max);
        assert!(d < 1e-9, "GS and Jacobi differ by {d} m");
        // Plain XPBD (multipliers reset every step) stops short with the same sweeps.
        assert!(pl.residual > 1e-2, "plain XPBD residual {}", pl.residual);
    }
}
