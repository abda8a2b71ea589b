//! The estimated parameters γ = (C00, C11, C01, C22, b) (paper 001, Eqs. 5–7): the orthotropic
//! StVK membrane in Voigt form with engineering shear and one dihedral bending stiffness, in SI
//! (N/m, J) and the paper's CGS units (dyn/cm, erg).

use serde::{Deserialize, Serialize};

/// The orthotropic membrane and bending parameters of a fabric, SI.
///
/// A triangle's membrane energy is `½ A [C00 ε_uu² + 2 C01 ε_uu ε_vv + C11 ε_vv² + C22 (2ε_uv)²]`
/// (Green strain along the warp `u` and weft `v`), a hinge's bending energy `½ b θ²`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Gamma {
    /// Warp stiffness, N/m.
    #[serde(rename = "C00")]
    pub c00: f64,
    /// Weft stiffness, N/m.
    #[serde(rename = "C11")]
    pub c11: f64,
    /// Warp–weft coupling, N/m.
    #[serde(rename = "C01")]
    pub c01: f64,
    /// Shear stiffness, N/m.
    #[serde(rename = "C22")]
    pub c22: f64,
    /// Bending stiffness per hinge, J.
    pub b: f64,
}

/// The names of γ's components, in [`Gamma::to_array`] order.
pub const NAMES: [&str; 5] = ["C00", "C11", "C01", "C22", "b"];

/// N/m → dyn/cm.
pub const DYN_PER_CM: f64 = 1e3;
/// J → erg.
pub const ERG: f64 = 1e7;

impl Gamma {
    /// From engineering constants (paper Eq. 6): Young's moduli `e_u`, `e_v` and shear modulus
    /// `mu` (N/m), Poisson ratio `nu_uv` (`ν_vu = ν_uv E_v / E_u` by symmetry), bending `b` (J).
    pub fn from_engineering(e_u: f64, e_v: f64, mu: f64, nu_uv: f64, b: f64) -> Self {
        let nu_vu = nu_uv * e_v / e_u;
        let d = 1.0 - nu_uv * nu_vu;
        Self {
            c00: e_u / d,
            c11: e_v / d,
            c01: nu_vu * e_u / d,
            c22: mu,
            b,
        }
    }

    /// An isotropic membrane of Young's modulus `youngs` (N/m) and Poisson ratio `nu`, plane
    /// stress: the StVK membrane of the FEM source with the same constants.
    pub fn isotropic(youngs: f64, nu: f64, b: f64) -> Self {
        let c = youngs / (1.0 - nu * nu);
        Self {
            c00: c,
            c11: c,
            c01: nu * c,
            c22: youngs / (2.0 * (1.0 + nu)),
            b,
        }
    }

    /// `(E_u, E_v, μ, ν_uv)`: the inverse of [`Gamma::from_engineering`].
    pub fn engineering(&self) -> [f64; 4] {
        let d = 1.0 - self.c01 * self.c01 / (self.c00 * self.c11);
        [self.c00 * d, self.c11 * d, self.c22, self.c01 / self.c11]
    }

    /// `ν_uv = C01 / C11`, the Poisson ratio the paper's penalty keeps at most 0.5.
    pub fn poisson(&self) -> f64 {
        self.c01 / self.c11
    }

    /// `[C00, C11, C01, C22, b]`.
    pub fn to_array(&self) -> [f64; 5] {
        [self.c00, self.c11, self.c01, self.c22, self.b]
    }

    /// From `[C00, C11, C01, C22, b]`.
    pub fn from_array(a: [f64; 5]) -> Self {
        Self {
            c00: a[0],
            c11: a[1],
            c01: a[2],
            c22: a[3],
            b: a[4],
        }
    }

    /// The same parameters in the paper's CGS units: C in dyn/cm, b in erg.
    pub fn to_cgs(&self) -> [f64; 5] {
        let a = self.to_array();
        [
            a[0] * DYN_PER_CM,
            a[1] * DYN_PER_CM,
            a[2] * DYN_PER_CM,
            a[3] * DYN_PER_CM,
            a[4] * ERG,
        ]
    }

    /// From the paper's CGS units.
    pub fn from_cgs(a: [f64; 5]) -> Self {
        Self::from_array([
            a[0] / DYN_PER_CM,
            a[1] / DYN_PER_CM,
            a[2] / DYN_PER_CM,
            a[3] / DYN_PER_CM,
            a[4] / ERG,
        ])
    }

    /// The membrane's energy density per unit rest area at Voigt strain `e = (ε_uu, ε_vv, 2ε_uv)`.
    #[inline]
    pub fn membrane_density(&self, e: [f64; 3]) -> f64 {
        0.5 * (self.c00 * e[0] * e[0]
            + 2.0 * self.c01 * e[0] * e[1]
            + self.c11 * e[1] * e[1]
            + self.c22 * e[2] * e[2])
    }

    /// The stress `K e` of Voigt strain `e`.
    #[inline]
    pub fn stress(&self, e: [f64; 3]) -> [f64; 3] {
        [
            self.c00 * e[0] + self.c01 * e[1],
            self.c01 * e[0] + self.c11 * e[1],
            self.c22 * e[2],
        ]
    }

    /// The membrane stiffness `K` (3 × 3, Voigt).
    pub fn stiffness(&self) -> [[f64; 3]; 3] {
        [
            [self.c00, self.c01, 0.0],
            [self.c01, self.c11, 0.0],
            [0.0, 0.0, self.c22],
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_papers_cotton_converts_as_its_table_1() {
        // Table 1: E_u 1.0e5, E_v 2.8e5, μ 4.0e4 dyn/cm, ν 0.4, b 50 erg.
        let g = Gamma::from_engineering(1.0e5, 2.8e5, 4.0e4, 0.4, 50.0);
        assert!((g.c00 - 1.8116e5).abs() / 1.8116e5 < 1e-4, "{g:?}");
        assert!((g.c01 - 2.0290e5).abs() / 2.0290e5 < 1e-4, "{g:?}");
        let back = g.engineering();
        for (a, b) in back.iter().zip([1.0e5, 2.8e5, 4.0e4, 0.4]) {
            assert!((a - b).abs() < 1e-9 * b, "{back:?}");
        }
        let si = Gamma::from_cgs(g.to_array());
        assert!((si.c00 - 181.16).abs() < 0.01 && (si.b - 5e-6).abs() < 1e-12);
        for (a, b) in si.to_cgs().iter().zip(g.to_array()) {
            assert!((a - b).abs() <= 1e-12 * b.abs(), "{a} vs {b}");
        }
    }
}
