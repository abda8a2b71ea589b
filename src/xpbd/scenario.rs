//! The loading scenarios of paper 001 on a square swatch: the picture frame sheared at its
//! hinges (§4, Figs. 6, 8), a stretch between two clamped edges and a pull between two
//! opposite corners, a cantilever, and the swatch hanging from one edge with a weight on the
//! other, each under gravity. A scenario gives the clamps, the loads, the clamp
//! group whose reaction is measured, and a start (the clamps' shape with a small seeded
//! out-of-plane perturbation, which picks a wrinkle branch).

use rand::{Rng, SeedableRng, rngs::StdRng};
use serde::{Deserialize, Serialize};

use super::cloth::{Load, XpbdCloth};
use crate::cloth::triangles::V3;

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
        matches!(self, Scenario::Cantilever)
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
        let mut load = Load::gravity(cloth, g);
        let rest = cloth.rest();
        let id = |r: usize, c: usize| r * n + c;
        let mut groups = Vec::new();
        // The start's out-of-plane coordinate.
        let mut normal = 2;
        // Every vertex first follows the clamps' map; then the clamps are set.
        let map: Box<dyn Fn(V3) -> V3> = match *self {
            Scenario::FrameShear { angle_deg } => {
                let (s, c) = angle_deg.to_radians().sin_cos();
                for r in 0..n {
                    for q in 0..n {
                        if r == 0 || q == 0 || r == n - 1 || q == n - 1 {
                            let p = rest[id(r, q)];
                            load.clamped[id(r, q)] = Some([p[0] + p[1] * s, p[1] * c, 0.0]);
                        }
                    }
                }
                groups.push((0..n).map(|q| id(n - 1, q)).collect());
                Box::new(move |p: V3| [p[0] + p[1] * s, p[1] * c, 0.0])
            }
            Scenario::Stretch { strain, axis } => {
                // The held and the pulled edge, and the pull's coordinate.
                let (held, pulled, c): (Vec<usize>, Vec<usize>, usize) = match axis {
                    Axis::U => (
                        (0..n).map(|r| id(r, 0)).collect(),
                        (0..n).map(|r| id(r, n - 1)).collect(),
                        0,
                    ),
                    Axis::V => (
                        (0..n).map(|q| id(0, q)).collect(),
                        (0..n).map(|q| id(n - 1, q)).collect(),
                        1,
                    ),
                };
                for (&a, &b) in held.iter().zip(&pulled) {
                    load.clamped[a] = Some(rest[a]);
                    let mut p = rest[b];
                    p[c] += strain * size;
                    load.clamped[b] = Some(p);
                }
                groups.push(pulled);
                Box::new(move |p: V3| {
                    let mut q = p;
                    q[c] *= 1.0 + strain;
                    q
                })
            }
            Scenario::Cantilever => {
                let held: Vec<usize> = (0..2 * n).collect();
                for &i in &held {
                    load.clamped[i] = Some(rest[i]);
                }
                groups.push(held);
                Box::new(|p: V3| p)
            }
            Scenario::DiagonalPull { strain } => {
                let far = id(n - 1, n - 1);
                load.clamped[0] = Some(rest[0]);
                let p = rest[far];
                load.clamped[far] = Some([p[0] * (1.0 + strain), p[1] * (1.0 + strain), 0.0]);
                groups.push(vec![far]);
                Box::new(move |p: V3| [p[0] * (1.0 + strain), p[1] * (1.0 + strain), 0.0])
            }
            Scenario::HangingWeight { mass } => {
                let hang = move |p: V3| [p[0], 0.0, p[1] - size];
                let held: Vec<usize> = (0..n).map(|q| id(n - 1, q)).collect();
                for &i in &held {
                    load.clamped[i] = Some(hang(rest[i]));
                }
                for q in 0..n {
                    load.hang(id(0, q), mass / n as f64, g);
                }
                groups.push(held);
                normal = 1;
                Box::new(hang)
            }
        };
        let mut rng = StdRng::seed_from_u64(seed);
        let start = rest
            .iter()
            .enumerate()
            .map(|(i, &p)| match load.clamped[i] {
                Some(c) => c,
                None => {
                    let mut q = map(p);
                    q[normal] += noise * rng.random_range(-1.0..1.0);
                    q
                }
            })
            .collect();
        Setup {
            load,
            groups,
            start,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::xpbd::cloth::Solve;
    use crate::xpbd::equilibrium::polish;
    use crate::xpbd::material::Gamma;

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
