//! Spatially varying stiffness maps over the rest rectangle (paper Fig. 1, 6, 10 (a)).

use serde::{Deserialize, Serialize};

/// How stiffness levels are laid out over the cloth.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Layout {
    /// Every spring or triangle gets the first level.
    Uniform,
    /// Equal vertical stripes across the width, one per level, in order.
    #[default]
    Stripes,
    /// Fig. 10 (a): the first level everywhere, two vertical stripes and a top band of the last
    /// level, and a central patch of the middle level.
    Patches,
}

/// A stiffness map: levels placed by a layout.
#[derive(Debug, Clone, PartialEq)]
pub struct StiffnessMap {
    /// The layout.
    pub layout: Layout,
    /// Stiffness levels (at least one).
    pub levels: Vec<f64>,
}

impl StiffnessMap {
    /// The level at the normalised rest point `(u, v) ∈ [0, 1]²` (u across the width, v up
    /// the height).
    pub fn at(&self, u: f64, v: f64) -> f64 {
        let n = self.levels.len();
        let last = self.levels[n - 1];
        match self.layout {
            Layout::Uniform => self.levels[0],
            Layout::Stripes => self.levels[((u * n as f64) as usize).min(n - 1)],
            Layout::Patches => {
                let inside = |x: f64, lo: f64, hi: f64| x >= lo && x < hi;
                if inside(u, 0.15, 0.3) || inside(u, 0.7, 0.85) || inside(v, 0.82, 0.94) {
                    last
                } else if inside(u, 0.4, 0.6) && inside(v, 0.35, 0.6) {
                    self.levels[n / 2]
                } else {
                    self.levels[0]
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stripes_and_patches_use_every_level() {
        let levels = vec![10.0, 50.0, 100.0];
        let stripes = StiffnessMap {
            layout: Layout::Stripes,
            levels: levels.clone(),
        };
        assert_eq!(
            [
                stripes.at(0.1, 0.5),
                stripes.at(0.5, 0.5),
                stripes.at(1.0, 0.5)
            ],
            [10.0, 50.0, 100.0]
        );
        let patches = StiffnessMap {
            layout: Layout::Patches,
            levels,
        };
        assert_eq!(patches.at(0.05, 0.05), 10.0);
        assert_eq!(patches.at(0.2, 0.5), 100.0);
        assert_eq!(patches.at(0.5, 0.9), 100.0);
        assert_eq!(patches.at(0.5, 0.5), 50.0);
    }
}
