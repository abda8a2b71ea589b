//! The phase-free shape descriptor of paper 001 (Eq. 9, `s_FFT`): the magnitude of the 2-D
//! discrete Fourier transform of the grid's vertex positions, per coordinate, orthonormally
//! scaled, without the mean (DC) bin. Magnitudes drop the phase, so a wrinkle pattern shifted
//! along the grid (another equilibrium of the same material) has the same descriptor, while a
//! change of amplitude or wavelength changes it. Any grid size (a dense DFT, not a radix-2 FFT).
//! Beside it, the paper's other three descriptors: the positions, the per-element energies and
//! the per-element strains.

use burn::tensor::{Tensor, TensorData};
use serde::{Deserialize, Serialize};

use super::cloth::XpbdCloth;
use super::material::Gamma;
use springtime_core::cloth::triangles::V3;

/// A shape descriptor of paper 001, Eq. 9.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Descriptor {
    /// `s_FFT`: the phase-free DFT magnitudes of the grid positions.
    Fft,
    /// `s_pos`: the positions themselves.
    Positions,
    /// `s_energy`: every triangle's membrane and every hinge's bending energy (depends on γ).
    Energy,
    /// `s_strain`: every triangle's Green strain and every hinge's angle.
    Strain,
}

impl Descriptor {
    /// All four, in the paper's order of Eq. 9.
    pub const ALL: [Descriptor; 4] = [
        Descriptor::Positions,
        Descriptor::Energy,
        Descriptor::Strain,
        Descriptor::Fft,
    ];

    /// The name in configs and files.
    pub fn name(self) -> &'static str {
        match self {
            Descriptor::Fft => "fft",
            Descriptor::Positions => "positions",
            Descriptor::Energy => "energy",
            Descriptor::Strain => "strain",
        }
    }

    /// Whether it depends on γ besides the positions (then a target's descriptor changes with
    /// the estimate, as the paper notes of `s_energy`).
    pub fn depends_on_gamma(self) -> bool {
        matches!(self, Descriptor::Energy)
    }

    /// The descriptor of positions `x` of `cloth`, an `nx × ny` row-major grid, at `gamma`.
    pub fn of(self, cloth: &XpbdCloth, nx: usize, ny: usize, gamma: &Gamma, x: &[V3]) -> Vec<f64> {
        match self {
            Descriptor::Fft => fft_descriptor(x, nx, ny),
            Descriptor::Positions => x.iter().flatten().copied().collect(),
            Descriptor::Energy => cloth.element_energies(gamma, x),
            Descriptor::Strain => cloth.element_strains(x),
        }
    }
}

/// `|DFT₂(x_c)[k, l]| / √(nx·ny)` for every coordinate `c` and frequency `(k, l) ≠ (0, 0)` of
/// positions on an `nx × ny` row-major grid (row `r`, column `c` at `r·nx + c`); `nx·ny − 1`
/// values per coordinate, x's first.
pub fn fft_descriptor(x: &[V3], nx: usize, ny: usize) -> Vec<f64> {
    assert_eq!(x.len(), nx * ny, "positions must fill the {nx} × {ny} grid");
    let tw = |n: usize| -> Vec<(f64, f64)> {
        (0..n)
            .map(|j| {
                let a = -2.0 * std::f64::consts::PI * j as f64 / n as f64;
                (a.cos(), a.sin())
            })
            .collect()
    };
    let (wx, wy) = (tw(nx), tw(ny));
    let norm = 1.0 / ((nx * ny) as f64).sqrt();
    let mut out = Vec::with_capacity(3 * (nx * ny - 1));
    for c in 0..3 {
        // Along rows first: R[r][l] = Σ_col x[r][col] e^{−2πi l col / nx}.
        let mut rows = vec![(0.0, 0.0); nx * ny];
        for r in 0..ny {
            for l in 0..nx {
                let (mut re, mut im) = (0.0, 0.0);
                for col in 0..nx {
                    let (cs, sn) = wx[(l * col) % nx];
                    let v = x[r * nx + col][c];
                    re += v * cs;
                    im += v * sn;
                }
                rows[r * nx + l] = (re, im);
            }
        }
        for (k, l) in frequencies(nx, ny) {
            let (mut re, mut im) = (0.0, 0.0);
            for r in 0..ny {
                let (cs, sn) = wy[(k * r) % ny];
                let (a, b) = rows[r * nx + l];
                re += a * cs - b * sn;
                im += a * sn + b * cs;
            }
            out.push(norm * (re * re + im * im).sqrt());
        }
    }
    out
}

/// The descriptor's frequencies `(k, l)` of an `nx × ny` grid in its order: every one but the
/// mean (DC) bin `(0, 0)`, `k` (along the columns) major.
fn frequencies(nx: usize, ny: usize) -> impl Iterator<Item = (usize, usize)> {
    (0..ny)
        .flat_map(move |k| (0..nx).map(move |l| (k, l)))
        .skip(1)
}

/// [`fft_descriptor`] as Burn tensor ops (differentiable): positions `[nx·ny, 3]` → `[3(nx·ny − 1)]`,
/// the DFT along rows and then columns as products with cosine and sine matrices (any grid size;
/// a `√(· + 1e-24)` keeps the magnitude's gradient finite at an empty bin).
pub fn fft_descriptor_tensor(x: Tensor<2>, nx: usize, ny: usize) -> Tensor<1> {
    let device = x.device();
    let [rows, _] = x.dims();
    assert_eq!(rows, nx * ny, "positions must fill the {nx} × {ny} grid");
    let twiddles = |n: usize, f: fn(f64) -> f64| {
        let v: Vec<f32> = (0..n * n)
            .map(|i| {
                f(-2.0 * std::f64::consts::PI * ((i / n) * (i % n) % n) as f64 / n as f64) as f32
            })
            .collect();
        Tensor::<2>::from_data(TensorData::new(v, [n, n]), &device)
    };
    // Symmetric: W[a][b] depends on a·b only.
    let (cx, sx, cy, sy) = (
        twiddles(nx, f64::cos),
        twiddles(nx, f64::sin),
        twiddles(ny, f64::cos),
        twiddles(ny, f64::sin),
    );
    let norm = 1.0 / ((nx * ny) as f64).sqrt();
    let parts: Vec<Tensor<1>> = (0..3)
        .map(|c| {
            let xc = x.clone().slice([0..rows, c..c + 1]).reshape([ny, nx]);
            let (re, im) = (xc.clone().matmul(cx.clone()), xc.matmul(sx.clone()));
            let f_re = cy.clone().matmul(re.clone()) - sy.clone().matmul(im.clone());
            let f_im = sy.clone().matmul(re) + cy.clone().matmul(im);
            let mag = (f_re.powi_scalar(2) + f_im.powi_scalar(2))
                .add_scalar(1e-24)
                .sqrt()
                * norm;
            mag.reshape([nx * ny]).narrow(0, 1, nx * ny - 1)
        })
        .collect();
    Tensor::cat(parts, 0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn field(nx: usize, ny: usize, shift: (usize, usize)) -> Vec<V3> {
        // Periodic wrinkles: exact circular-shift invariance holds for periodic fields.
        (0..ny)
            .flat_map(|r| {
                (0..nx).map(move |c| {
                    let (rr, cc) = ((r + shift.0) % ny, (c + shift.1) % nx);
                    let (u, v) = (cc as f64 / nx as f64, rr as f64 / ny as f64);
                    let t = std::f64::consts::TAU;
                    [
                        0.3 * (t * 2.0 * u).sin() + 0.1 * (t * v).cos(),
                        0.2 * (t * (u + 3.0 * v)).cos(),
                        0.05 * (t * 3.0 * u).sin() * (t * 2.0 * v).cos() + 0.01 * cc as f64,
                    ]
                })
            })
            .collect()
    }

    #[test]
    fn the_dft_descriptor_matches_a_naive_dft_and_is_invariant_to_translation_and_shift() {
        let (nx, ny) = (7, 5);
        let x = field(nx, ny, (0, 0));
        let d = fft_descriptor(&x, nx, ny);
        assert_eq!(d.len(), 3 * (nx * ny - 1));
        // A naive 2-D DFT.
        let mut naive = Vec::new();
        for c in 0..3 {
            for (k, l) in frequencies(nx, ny) {
                let (mut re, mut im) = (0.0, 0.0);
                for r in 0..ny {
                    for q in 0..nx {
                        let a = -std::f64::consts::TAU
                            * (k as f64 * r as f64 / ny as f64 + l as f64 * q as f64 / nx as f64);
                        re += x[r * nx + q][c] * a.cos();
                        im += x[r * nx + q][c] * a.sin();
                    }
                }
                naive.push((re * re + im * im).sqrt() / ((nx * ny) as f64).sqrt());
            }
        }
        for (a, b) in d.iter().zip(&naive) {
            assert!((a - b).abs() < 1e-12, "{a} vs {b}");
        }
        // Translation: exactly invariant (the DC bin is left out).
        let moved: Vec<V3> = x
            .iter()
            .map(|p| [p[0] + 1.5, p[1] - 0.25, p[2] + 3.0])
            .collect();
        for (a, b) in d.iter().zip(fft_descriptor(&moved, nx, ny)) {
            assert!((a - b).abs() < 1e-12);
        }
        // A circular shift of the grid (the same wrinkles elsewhere): exactly invariant.
        let shifted = field(nx, ny, (2, 3));
        for (a, b) in d.iter().zip(fft_descriptor(&shifted, nx, ny)) {
            assert!((a - b).abs() < 1e-12, "{a} vs {b}");
        }
        // A larger amplitude is not.
        let taller: Vec<V3> = x.iter().map(|p| [p[0], p[1], 2.0 * p[2]]).collect();
        let diff: f64 = d
            .iter()
            .zip(fft_descriptor(&taller, nx, ny))
            .map(|(a, b)| (a - b).abs())
            .sum();
        assert!(diff > 0.05, "{diff}");
    }

    #[test]
    fn the_element_descriptors_ignore_rigid_motion_and_energy_is_linear_in_gamma() {
        let n = 4;
        let cloth = XpbdCloth::grid(n, n, 0.1, 0.1, 0.2).unwrap();
        let gamma = Gamma::from_engineering(100.0, 280.0, 40.0, 0.4, 5e-6);
        // At rest every strain and energy is zero.
        let rest = cloth.rest();
        for d in [Descriptor::Energy, Descriptor::Strain] {
            let s = d.of(&cloth, n, n, &gamma, &rest);
            assert_eq!(
                s.len(),
                cloth.triangles.len() * if d == Descriptor::Strain { 3 } else { 1 }
                    + cloth.hinges.len()
            );
            assert!(s.iter().all(|v| v.abs() < 1e-15), "{d:?} at rest: {s:?}");
        }
        // A deformed, bent state, then the same rotated about an axis and moved.
        let x: Vec<V3> = rest
            .iter()
            .map(|p| {
                [
                    1.05 * p[0] + 0.2 * p[1],
                    0.97 * p[1],
                    0.3 * (p[0] * 40.0).sin() * p[1],
                ]
            })
            .collect();
        let moved = crate::cloth::rigidly_moved(&x, (0.8, 0.6));
        for d in [Descriptor::Energy, Descriptor::Strain] {
            let (a, b) = (
                d.of(&cloth, n, n, &gamma, &x),
                d.of(&cloth, n, n, &gamma, &moved),
            );
            assert!(
                a.iter().any(|v| v.abs() > 1e-6),
                "{d:?} sees the deformation"
            );
            for (p, q) in a.iter().zip(&b) {
                assert!((p - q).abs() < 1e-12 * (1.0 + p.abs()), "{d:?}: {p} vs {q}");
            }
        }
        // The energies are linear in γ and sum to the cloth's energy.
        let doubled = Gamma::from_array(gamma.to_array().map(|v| 2.0 * v));
        let e1 = Descriptor::Energy.of(&cloth, n, n, &gamma, &x);
        let e2 = Descriptor::Energy.of(&cloth, n, n, &doubled, &x);
        for (p, q) in e1.iter().zip(&e2) {
            assert!((2.0 * p - q).abs() < 1e-12 * q.abs().max(1e-30));
        }
        let total: f64 = e1.iter().sum();
        assert!((total - cloth.energy(&gamma, &x)).abs() < 1e-12 * total);
        // The strains do not depend on γ; the positions are the positions.
        assert_eq!(
            Descriptor::Strain.of(&cloth, n, n, &gamma, &x),
            Descriptor::Strain.of(&cloth, n, n, &doubled, &x)
        );
        assert_eq!(
            Descriptor::Positions.of(&cloth, n, n, &gamma, &x)[3..6],
            x[1]
        );
    }
}
