//! The loading scenarios of paper 001 on a square swatch: the picture frame sheared at its
//! hinges (§4, Figs. 6, 8), a stretch between two clamped edges and a pull between two
//! opposite corners, a cantilever, the swatch hanging from one edge with a weight on the
//! other, and the swatch draped over a ledge (§5), each under gravity. A scenario gives the clamps, the loads, the clamp
//! group whose reaction is measured, and a start (the clamps' shape with a small seeded
//! out-of-plane perturbation, which picks a wrinkle branch).

use std::path::Path;

use anyhow::{Result, bail};
use rand::{Rng, SeedableRng, rngs::StdRng};
use serde::{Deserialize, Serialize};

use super::cloth::{Load, XpbdCloth};
use super::contact::StaticContact;
use springtime_core::cloth::triangles::V3;
use springtime_core::sim::contact::{Collider, ColliderConfig, ColliderKind};

/// One scenario of a config (`[[scenarios]]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Scenario {
    /// Every boundary vertex on a picture frame hinged at its corners, sheared by `angle_deg`:
    /// `(u, v) → (u + v sin θ, v cos θ)`. Reaction: the frame's top side.
    FrameShear {
        /// Shear angle, degrees.
        angle_deg: f64,
    },
    /// The edge `u = 0` held, the edge `u = L` moved out by `strain · L` (or the same along
    /// `v`). Reaction: the moved edge.
    Stretch {
        /// Engineering strain of the pull.
        strain: f64,
        /// The material axis pulled along: `"u"` (warp, default) or `"v"` (weft).
        #[serde(default)]
        axis: Axis,
    },
    /// A cantilever: the first two rows (`v = 0` and the next) held flat, the rest hanging
    /// under gravity. Its shape is set by bending mostly: the bending targets of the
    /// bending-first schedule. Reaction: the held rows.
    Cantilever,
    /// The corner `(0, 0)` held, the opposite corner moved out along the diagonal by
    /// `strain` times its length. Reaction: that corner.
    DiagonalPull {
        /// Engineering strain along the diagonal.
        strain: f64,
    },
    /// The swatch hanging in the `x–z` plane from its edge `v = L` (held at `z = 0`), a bar of
    /// `mass` kg hung along its free bottom edge and shared by its vertices, as the paper's
    /// captured swatches are stretched by weights (gravity along `−z`). Reaction: the held
    /// edge, which carries the cloth and the bar.
    HangingWeight {
        /// The bar's mass, kg.
        mass: f64,
    },
    /// The swatch over a horizontal ledge, as the paper's last two real-world targets (§5) and
    /// the cantilever bending test of textiles: its first two rows (`v = 0` and the next) held
    /// on the ledge's top as under a weight, the rest lying on the top, frictionless, and the
    /// last `overhang` of its length past the edge, bending over it under gravity. The ledge
    /// is a box whose top is `z = 0` and whose edge, rounded by `radius`, runs along `u` at
    /// `v = (1 − overhang) L`; the cloth touches it through the drapes' penalty layer
    /// (`thickness` δ, pressure `stiffness` κ per unit mass; see [`super::contact`]). The start
    /// lies on the top and hangs straight down past the edge. Reaction: the held rows.
    LedgeDrape {
        /// Fraction of the swatch's length past the edge.
        overhang: f64,
        /// Radius of the edge, m.
        #[serde(default = "default_ledge_radius")]
        radius: f64,
        /// Contact thickness δ, m.
        #[serde(default = "default_ledge_thickness")]
        thickness: f64,
        /// Contact pressure κ per unit mass, 1/s²: a vertex resting on the top sinks `g/κ`
        /// into the layer (1 % of the default δ).
        #[serde(default = "default_ledge_stiffness")]
        stiffness: f64,
    },
}

fn default_ledge_radius() -> f64 {
    0.005
}

fn default_ledge_thickness() -> f64 {
    0.001
}

fn default_ledge_stiffness() -> f64 {
    9.81 / (0.01 * default_ledge_thickness())
}

/// A material axis of the swatch.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Axis {
    /// Warp, along a grid row.
    #[default]
    U,
    /// Weft, along a grid column.
    V,
}

/// A scenario set up on a grid.
#[derive(Debug, Clone)]
pub struct Setup {
    /// Clamps and loads.
    pub load: Load,
    /// The clamp groups whose reactions are measured.
    pub groups: Vec<Vec<usize>>,
    /// Where the solve starts.
    pub start: Vec<V3>,
}

impl Scenario {
    /// Whether the scenario's shape is set by bending (the bending pass of the bending-first
    /// schedule) rather than by the membrane.
    pub fn is_bending(&self) -> bool {
        matches!(self, Scenario::Cantilever | Scenario::LedgeDrape { .. })
    }

    /// Checks the scenario's numbers; errors name the key.
    pub fn validate(&self) -> Result<()> {
        match *self {
            Scenario::HangingWeight { mass } if !(mass.is_finite() && mass >= 0.0) => {
                bail!("`scenarios.mass` of a hanging_weight must be a mass ≥ 0 (kg), is {mass}")
            }
            Scenario::LedgeDrape {
                overhang,
                radius,
                thickness,
                stiffness,
            } => {
                if !(overhang > 0.0 && overhang < 0.8) {
                    bail!(
                        "`scenarios.overhang` of a ledge_drape is the fraction of the swatch past \
                         the edge, in (0, 0.8) (the first two rows are held on the top), is \
                         {overhang}"
                    );
                }
                for (key, v) in [
                    ("radius", radius),
                    ("thickness", thickness),
                    ("stiffness", stiffness),
                ] {
                    if !(v.is_finite() && v > 0.0) {
                        bail!("`scenarios.{key}` of a ledge_drape must be positive, is {v}");
                    }
                }
            }
            _ => {}
        }
        Ok(())
    }

    /// The contact pressure κ per unit mass of the scenario's collider, 1/s² (none without).
    pub fn contact_stiffness(&self) -> Option<f64> {
        match *self {
            Scenario::LedgeDrape { stiffness, .. } => Some(stiffness),
            _ => None,
        }
    }

    /// A short name for files and tables.
    pub fn name(&self) -> String {
        match self {
            Scenario::FrameShear { angle_deg } => format!("frame_shear_{angle_deg}deg"),
            Scenario::Stretch { strain, axis } => format!(
                "stretch_{}_{strain}",
                match axis {
                    Axis::U => "u",
                    Axis::V => "v",
                }
            ),
            Scenario::DiagonalPull { strain } => format!("diagonal_pull_{strain}"),
            Scenario::HangingWeight { mass } => format!("hanging_weight_{mass}kg"),
            Scenario::Cantilever => "cantilever".into(),
            Scenario::LedgeDrape { overhang, .. } => format!("ledge_drape_{overhang}"),
        }
    }

    /// The clamps, loads and start on an `n × n` grid of side `size` under gravity `g`, with an
    /// out-of-plane perturbation of `noise` (m) seeded by `seed`.
    pub fn setup(
        &self,
        cloth: &XpbdCloth,
        n: usize,
        size: f64,
        g: V3,
        noise: f64,
        seed: u64,
    ) -> Setup {
        let grid = SetupGrid {
            n,
            size,
            gravity: g,
            noise,
            seed,
            refine: 1,
        };
        self.setup_refined(cloth, &grid)
    }

    /// [`setup`](Self::setup) on a grid `grid.refine` times finer than the template's
    /// (`grid.n` its vertices per side): the held strip of a cantilever or a ledge drape is the
    /// template's first two rows, `refine + 1` rows of this grid.
    pub(crate) fn setup_refined(&self, cloth: &XpbdCloth, grid: &SetupGrid) -> Setup {
        let mut clamps = Clamps::new(cloth, grid);
        // Every vertex first follows the clamps' map; then the clamps are set.
        let map = match *self {
            Scenario::FrameShear { angle_deg } => clamps.frame_shear(angle_deg),
            Scenario::Stretch { strain, axis } => clamps.stretch(strain, axis),
            Scenario::Cantilever => clamps.cantilever(),
            Scenario::DiagonalPull { strain } => clamps.diagonal_pull(strain),
            Scenario::HangingWeight { mass } => clamps.hanging_weight(mass),
            Scenario::LedgeDrape {
                overhang,
                radius,
                thickness,
                stiffness,
            } => clamps.ledge_drape(overhang, radius, thickness, stiffness),
        };
        clamps.start_from(map)
    }
}

/// Where a scenario is set up: its grid, gravity and the start's perturbation.
#[derive(Debug, Clone, Copy)]
pub(crate) struct SetupGrid {
    /// Vertices per side.
    pub n: usize,
    /// Side of the swatch, m.
    pub size: f64,
    /// Gravity, m/s².
    pub gravity: V3,
    /// The start's out-of-plane perturbation, m.
    pub noise: f64,
    /// The perturbation's seed.
    pub seed: u64,
    /// How many times finer than the template's the grid is.
    pub refine: usize,
}

/// Where every vertex of the start goes before its perturbation: the clamps' map.
type StartMap = Box<dyn Fn(V3) -> V3>;

/// A scenario's clamps, loads and measured groups being set on a grid, then its start.
struct Clamps<'a> {
    cloth: &'a XpbdCloth,
    grid: &'a SetupGrid,
    rest: Vec<V3>,
    load: Load,
    groups: Vec<Vec<usize>>,
    /// The start's out-of-plane coordinate.
    normal: usize,
    /// A ledge drape's edge: its start is perturbed away from the ledge only (up on the top,
    /// out past the edge), never into it.
    ledge_edge: Option<f64>,
}

impl<'a> Clamps<'a> {
    fn new(cloth: &'a XpbdCloth, grid: &'a SetupGrid) -> Self {
        Self {
            cloth,
            grid,
            rest: cloth.rest(),
            load: Load::gravity(cloth, grid.gravity),
            groups: Vec::new(),
            normal: 2,
            ledge_edge: None,
        }
    }

    /// Vertex `(r, c)` of the grid.
    fn id(&self, r: usize, c: usize) -> usize {
        r * self.grid.n + c
    }

    /// The held strip of a cantilever or a ledge drape: the template's first two rows.
    fn held_rows(&self) -> Vec<usize> {
        let held_rows = self.grid.refine.max(1) + 1;
        (0..held_rows * self.grid.n).collect()
    }

    fn frame_shear(&mut self, angle_deg: f64) -> StartMap {
        let n = self.grid.n;
        let (s, c) = angle_deg.to_radians().sin_cos();
        for r in 0..n {
            for q in 0..n {
                if r == 0 || q == 0 || r == n - 1 || q == n - 1 {
                    let i = self.id(r, q);
                    let p = self.rest[i];
                    self.load.clamped[i] = Some([p[0] + p[1] * s, p[1] * c, 0.0]);
                }
            }
        }
        self.groups
            .push((0..n).map(|q| self.id(n - 1, q)).collect());
        Box::new(move |p: V3| [p[0] + p[1] * s, p[1] * c, 0.0])
    }

    fn stretch(&mut self, strain: f64, axis: Axis) -> StartMap {
        let (n, size) = (self.grid.n, self.grid.size);
        // The held and the pulled edge, and the pull's coordinate.
        let (held, pulled, c): (Vec<usize>, Vec<usize>, usize) = match axis {
            Axis::U => (
                (0..n).map(|r| self.id(r, 0)).collect(),
                (0..n).map(|r| self.id(r, n - 1)).collect(),
                0,
            ),
            Axis::V => (
                (0..n).map(|q| self.id(0, q)).collect(),
                (0..n).map(|q| self.id(n - 1, q)).collect(),
                1,
            ),
        };
        for (&a, &b) in held.iter().zip(&pulled) {
            self.load.clamped[a] = Some(self.rest[a]);
            let mut p = self.rest[b];
            p[c] += strain * size;
            self.load.clamped[b] = Some(p);
        }
        self.groups.push(pulled);
        Box::new(move |p: V3| {
            let mut q = p;
            q[c] *= 1.0 + strain;
            q
        })
    }

    fn cantilever(&mut self) -> StartMap {
        let held = self.held_rows();
        for &i in &held {
            self.load.clamped[i] = Some(self.rest[i]);
        }
        self.groups.push(held);
        Box::new(|p: V3| p)
    }

    fn diagonal_pull(&mut self, strain: f64) -> StartMap {
        let n = self.grid.n;
        let far = self.id(n - 1, n - 1);
        self.load.clamped[0] = Some(self.rest[0]);
        let p = self.rest[far];
        self.load.clamped[far] = Some([p[0] * (1.0 + strain), p[1] * (1.0 + strain), 0.0]);
        self.groups.push(vec![far]);
        Box::new(move |p: V3| [p[0] * (1.0 + strain), p[1] * (1.0 + strain), 0.0])
    }

    fn hanging_weight(&mut self, mass: f64) -> StartMap {
        let (n, size) = (self.grid.n, self.grid.size);
        let hang = move |p: V3| [p[0], 0.0, p[1] - size];
        let held: Vec<usize> = (0..n).map(|q| self.id(n - 1, q)).collect();
        for &i in &held {
            self.load.clamped[i] = Some(hang(self.rest[i]));
        }
        for q in 0..n {
            self.load
                .hang(self.id(0, q), mass / n as f64, self.grid.gravity);
        }
        self.groups.push(held);
        self.normal = 1;
        Box::new(hang)
    }

    fn ledge_drape(
        &mut self,
        overhang: f64,
        radius: f64,
        thickness: f64,
        stiffness: f64,
    ) -> StartMap {
        let size = self.grid.size;
        let edge = (1.0 - overhang) * size;
        self.ledge_edge = Some(edge);
        let held = self.held_rows();
        for &i in &held {
            self.load.clamped[i] = Some([self.rest[i][0], self.rest[i][1], thickness]);
        }
        self.groups.push(held);
        self.load.contact = Some(StaticContact {
            collider: ledge(size, edge, radius),
            thickness,
            stiffness: (0..self.rest.len())
                .map(|i| (self.cloth.mass[i] + self.load.added_mass[i]) * stiffness)
                .collect(),
        });
        // On the top, then straight down past the edge, a layer's thickness out.
        Box::new(move |p: V3| {
            if p[1] <= edge {
                [p[0], p[1], thickness]
            } else {
                [p[0], edge + thickness, thickness - (p[1] - edge)]
            }
        })
    }

    /// The setup, its start every clamped vertex at its clamp and every other one at `map` of
    /// its rest position, perturbed out of plane by the seeded noise.
    fn start_from(self, map: StartMap) -> Setup {
        let mut rng = StdRng::seed_from_u64(self.grid.seed);
        let start = self
            .rest
            .iter()
            .enumerate()
            .map(|(i, &p)| match self.load.clamped[i] {
                Some(c) => c,
                None => {
                    let mut q = map(p);
                    let xi = self.grid.noise * rng.random_range(-1.0..1.0);
                    match self.ledge_edge {
                        Some(edge) if p[1] <= edge => q[2] += xi.abs(),
                        Some(_) => q[1] += xi.abs(),
                        None => q[self.normal] += xi,
                    }
                    q
                }
            })
            .collect();
        Setup {
            load: self.load,
            groups: self.groups,
            start,
        }
    }
}

/// A ledge for a swatch of side `size`: a box far larger than the swatch, its top at z = 0 and
/// its edge, rounded by `radius`, at v = `edge`.
fn ledge(size: f64, edge: f64, radius: f64) -> Collider {
    let half = 10.0 * size;
    ColliderConfig {
        kind: ColliderKind::RoundedBox,
        radius: Some(radius),
        half_height: None,
        half_extents: Some([half; 3]),
        mesh: None,
        scale: 1.0,
        translation: [0.5 * size, edge - half - radius, -half - radius],
        rotation_deg: [0.0; 3],
        friction: 0.0,
        path: Vec::new(),
    }
    .build(Path::new("."), "ledge")
    .expect("a validated ledge is a valid rounded box")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cloth::Solve;
    use crate::equilibrium::{polish, sensitivity};
    use crate::material::Gamma;
    use springtime_core::cloth::triangles::dot;

    const LEDGE: Scenario = Scenario::LedgeDrape {
        overhang: 0.4,
        radius: 0.005,
        thickness: 0.001,
        stiffness: 9.81e5,
    };

    /// A 7 × 7, 10 cm cotton-like swatch over [`LEDGE`] at bending stiffness `b` (J), solved
    /// from `start` (the scenario's own when `None`) and polished.
    fn ledge_drape(b: f64, start: Option<&[V3]>) -> (XpbdCloth, Gamma, Setup, Vec<V3>) {
        let (n, size) = (7, 0.1);
        let cloth = XpbdCloth::grid(n, n, size, size, 0.224).unwrap();
        let gamma = Gamma::from_engineering(100.0, 280.0, 40.0, 0.4, b);
        let setup = LEDGE.setup(&cloth, n, size, [0.0, 0.0, -9.81], 1e-4, 3);
        let solve = Solve {
            dt: 2e-4,
            steps: 5000,
            tolerance: 1e-9,
            ..Solve::default()
        };
        let from = start.unwrap_or(&setup.start);
        let mut x = cloth.solve(&gamma, &setup.load, from, &solve).unwrap().x;
        let residual = polish(&cloth, &gamma, &setup.load, &mut x, 50, 1e-12).unwrap();
        // Newton's line search on the potential stops near 1e-9 (rounding); differences of
        // 1 % in b are then exact to ~1e-6.
        assert!(residual < 1e-8, "residual {residual}");
        (cloth, gamma, setup, x)
    }

    #[test]
    fn a_ledge_drape_rests_on_the_top_and_bends_over_the_edge() {
        let (cloth, gamma, setup, x) = ledge_drape(5e-6, None);
        let contact = setup.load.contact.as_ref().unwrap();
        let (n, edge) = (7, 0.06);
        // The cloth rests in the layer and never reaches the ledge's surface.
        let deepest = contact.deepest(&x);
        assert!(deepest > 0.0 && deepest < 0.001, "deepest {deepest}");
        // Nothing reaches the box, and below the top's rounding every vertex is past the face.
        for p in &x {
            assert!(contact.collider.query(0.0, *p).distance > 0.0, "{p:?}");
            assert!(p[2] > -0.005 || p[1] > edge, "{p:?} is inside the ledge");
        }
        // Balance of the whole cloth: clamps, ledge and gravity.
        let weight: f64 = cloth.mass.iter().sum::<f64>() * 9.81;
        let clamps = cloth.reaction(&gamma, &setup.load, &x, &setup.groups[0]);
        let ledge = contact.force(&x);
        let sum = [0, 1, 2].map(|c| clamps[c] + ledge[c] - if c == 2 { weight } else { 0.0 });
        assert!(
            dot(sum, sum).sqrt() < 1e-9 * weight,
            "unbalanced by {sum:?}"
        );
        // A frictionless ledge carries every free vertex's weight (the held rows, flat on the
        // top, pass no vertical force), and pulls the clamps towards the edge.
        let free: f64 = (2 * n..n * n).map(|i| cloth.mass[i]).sum::<f64>() * 9.81;
        assert!((ledge[2] - free).abs() < 1e-3 * free, "{ledge:?} vs {free}");
        assert!(clamps[1] < 0.0 && ledge[1] > 0.0, "{clamps:?}");
        // The tip hangs below the top.
        let tip = x[n * n - 1];
        assert!(tip[2] < -0.02, "tip {tip:?}");
        // A stiffer cloth sticks out further past the edge.
        let (.., stiff) = ledge_drape(2e-5, None);
        assert!(
            stiff[n * n - 1][1] > tip[1] + 1e-3,
            "{:?} vs {tip:?}",
            stiff[n * n - 1]
        );
    }

    #[test]
    fn a_ledge_drapes_derivatives_follow_the_contact() {
        let b = 5e-6;
        let (cloth, gamma, setup, x) = ledge_drape(b, None);
        let sens = sensitivity(&cloth, &gamma, &setup.load, &x, &setup.groups).unwrap();
        // Central differences in b of equilibria polished from this one (the same branch).
        let h = 0.01 * b;
        let (.., up) = ledge_drape(b + h, Some(&x));
        let (.., down) = ledge_drape(b - h, Some(&x));
        let mut worst = 0.0f64;
        let mut scale = 0.0f64;
        for i in 0..x.len() {
            for c in 0..3 {
                let fd = (up[i][c] - down[i][c]) / (2.0 * h);
                worst = worst.max((fd - sens.dx[4][i][c]).abs());
                scale = scale.max(fd.abs());
            }
        }
        assert!(
            worst < 1e-3 * scale,
            "dx/db off by {worst:e} (scale {scale:e})"
        );
    }

    #[test]
    fn a_hanging_weight_is_carried_by_the_held_edge() {
        let (n, size) = (5, 0.1);
        let cloth = XpbdCloth::grid(n, n, size, size, 0.2).unwrap();
        let g = [0.0, 0.0, -9.81];
        let setup = Scenario::HangingWeight { mass: 0.05 }.setup(&cloth, n, size, g, 1e-4, 3);
        // The held edge is the top row at z = 0; the start hangs below it.
        for q in 0..n {
            let p = setup.load.clamped[(n - 1) * n + q].unwrap();
            assert_eq!((p[1], p[2]), (0.0, 0.0));
        }
        assert!((setup.start[0][2] + size).abs() < 1e-12);
        let gamma = Gamma::from_engineering(180.0, 500.0, 40.0, 0.3, 5e-6);
        let solve = Solve {
            dt: 2e-4,
            steps: 5000,
            tolerance: 1e-9,
            ..Solve::default()
        };
        let mut x = cloth
            .solve(&gamma, &setup.load, &setup.start, &solve)
            .unwrap()
            .x;
        let residual = polish(&cloth, &gamma, &setup.load, &mut x, 30, 1e-12).unwrap();
        assert!(residual < 1e-8, "residual {residual}");
        // Vertical balance: the held edge carries the cloth's weight and the bar's.
        let total = cloth.mass.iter().sum::<f64>() + 0.05;
        let r = cloth.reaction(&gamma, &setup.load, &x, &setup.groups[0]);
        assert!(
            (r[2].abs() - total * 9.81).abs() < 1e-6 * total * 9.81,
            "reaction {r:?} vs weight {}",
            total * 9.81
        );
        assert!(r[0].abs() < 1e-6 && r[1].abs() < 1e-6, "sideways {r:?}");
        // The weight stretches the swatch below its rest length.
        let drop = -x[0][2];
        assert!(
            drop > size,
            "the bottom edge hangs {drop} m below the held one"
        );
    }
}
