//! Numbers of a fold equilibrium: the opening angle, the sag, and the shape error against a
//! finer mesh on the points the two grids share.

use anyhow::{Result, bail};

/// The fold's opening angle in degrees from the distance `d` between the two free corners:
/// a sheet folded about its pinned diagonal into two flat halves has `d = D sin(α/2)`, `D` the
/// sheet's diagonal (`2h`, `h = side/√2`), so a flat sheet gives 180° and two halves hanging
/// together 0°. Distances beyond `D` (stretching) count as flat.
pub fn opening_angle(x: &[[f64; 3]], free: [usize; 2], diagonal: f64) -> f64 {
    let [a, b] = free.map(|i| x[i]);
    let d = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
    2.0 * (d / diagonal).min(1.0).asin().to_degrees()
}

/// The mean drop of the free vertices below the mean height of the pinned ones, m.
pub fn sag(x: &[[f64; 3]], pinned: &[bool]) -> f64 {
    let mean = |pin: bool| {
        let z: Vec<f64> = x
            .iter()
            .zip(pinned)
            .filter(|(_, p)| **p == pin)
            .map(|(p, _)| p[2])
            .collect();
        z.iter().sum::<f64>() / z.len().max(1) as f64
    };
    mean(true) - mean(false)
}

/// Indices into a fine `fine × fine` vertex grid of the vertices of a coarse `coarse × coarse`
/// grid over the same square, row-major: coarse `(r, c)` is fine `(s r, s c)` with
/// `s = (fine − 1)/(coarse − 1)`. Fails unless the grids nest.
pub fn nested_indices(coarse: usize, fine: usize) -> Result<Vec<usize>> {
    if coarse < 2 || fine < coarse || !(fine - 1).is_multiple_of(coarse - 1) {
        bail!(
            "a {fine} × {fine} grid does not hold the vertices of a {coarse} × {coarse} grid \
             (needs fine − 1 to be a multiple of coarse − 1)"
        );
    }
    let s = (fine - 1) / (coarse - 1);
    Ok((0..coarse)
        .flat_map(|r| (0..coarse).map(move |c| s * r * fine + s * c))
        .collect())
}

/// Root-mean-square distance between `a[i]` and `b[at[i]]`, m.
pub fn shape_rmse(a: &[[f64; 3]], b: &[[f64; 3]], at: &[usize]) -> f64 {
    let sum: f64 = a
        .iter()
        .zip(at)
        .map(|(p, &j)| (0..3).map(|c| (p[c] - b[j][c]).powi(2)).sum::<f64>())
        .sum();
    (sum / a.len().max(1) as f64).sqrt()
}

/// The sheet's profile across the fold: the vertices on the free-corner diagonal of an
/// `n × n` grid (from one free corner to the other), as (horizontal distance from the pinned
/// diagonal's vertical plane, height) — a side view looking along the fold.
pub fn profile(
    x: &[[f64; 3]],
    n: usize,
    free: [(usize, usize); 2],
    pinned_axis: [f64; 2],
) -> Vec<(f64, f64)> {
    let [(r0, c0), (r1, c1)] = free;
    let norm = (pinned_axis[0].powi(2) + pinned_axis[1].powi(2)).sqrt();
    let across = [-pinned_axis[1] / norm, pinned_axis[0] / norm];
    (0..n)
        .map(|i| {
            let r = (r0 as f64 + (r1 as f64 - r0 as f64) * i as f64 / (n - 1) as f64).round();
            let c = (c0 as f64 + (c1 as f64 - c0 as f64) * i as f64 / (n - 1) as f64).round();
            let p = x[r as usize * n + c as usize];
            (p[0] * across[0] + p[1] * across[1], p[2])
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A unit square folded about its main diagonal so that the halves meet at `alpha`.
    fn folded(n: usize, alpha: f64) -> Vec<[f64; 3]> {
        // The fold line is the diagonal u = v; each point's signed distance from it is
        // s = (u − v)/√2. Points on the u > v side rotate down by (180° − α)/2, the others by
        // the same angle on their side, so the dihedral angle between the halves is α.
        let tilt = (std::f64::consts::PI - alpha) / 2.0;
        let axis = [1.0 / 2f64.sqrt(), 1.0 / 2f64.sqrt()];
        let across = [axis[1], -axis[0]];
        (0..n)
            .flat_map(|r| (0..n).map(move |c| (r, c)))
            .map(|(r, c)| {
                let (u, v) = (c as f64 / (n - 1) as f64, r as f64 / (n - 1) as f64);
                let along = u * axis[0] + v * axis[1];
                let s = u * across[0] + v * across[1];
                let (h, z) = (s.abs() * tilt.cos() * s.signum(), -s.abs() * tilt.sin());
                [
                    along * axis[0] + h * across[0],
                    along * axis[1] + h * across[1],
                    z,
                ]
            })
            .collect()
    }

    #[test]
    fn opening_angle_of_a_flat_sheet_and_of_a_hand_built_fold() {
        let n = 5;
        let free = [n - 1, (n - 1) * n]; // (0, n−1) and (n−1, 0)
        let diagonal = 2f64.sqrt();
        let flat = folded(n, std::f64::consts::PI);
        // (asin is steep at 1: rounding of the distance moves the angle by ~1e-6°.)
        assert!((opening_angle(&flat, free, diagonal) - 180.0).abs() < 1e-5);
        for alpha in [30.0f64, 90.0, 135.0] {
            let x = folded(n, alpha.to_radians());
            // The fold keeps every length on each half: the sheet is folded, not stretched.
            let d01 = |a: usize, b: usize| {
                (0..3)
                    .map(|c| (x[a][c] - x[b][c]).powi(2))
                    .sum::<f64>()
                    .sqrt()
            };
            assert!((d01(0, n * n - 1) - diagonal).abs() < 1e-12);
            let got = opening_angle(&x, free, diagonal);
            assert!((got - alpha).abs() < 1e-9, "{got} vs {alpha}");
        }
        // Two halves hanging together.
        let x = folded(n, 0.0);
        assert!(opening_angle(&x, free, diagonal).abs() < 1e-6);
    }

    #[test]
    fn fine_vertices_at_the_coarse_positions_are_found_exactly() {
        let (coarse, fine, side) = (16, 61, 1.5);
        let grid = |n: usize| -> Vec<[f64; 2]> {
            let h = side / (n - 1) as f64;
            (0..n)
                .flat_map(|r| (0..n).map(move |c| [c as f64 * h, r as f64 * h]))
                .collect()
        };
        let (gc, gf) = (grid(coarse), grid(fine));
        let at = nested_indices(coarse, fine).unwrap();
        assert_eq!(at.len(), coarse * coarse);
        assert_eq!(at[coarse + 1], 4 * fine + 4);
        for (p, &j) in gc.iter().zip(&at) {
            // Same point to rounding: coarse (i, j) is fine (4i, 4j).
            assert!((p[0] - gf[j][0]).abs() < 1e-12 && (p[1] - gf[j][1]).abs() < 1e-12);
        }
        assert!(nested_indices(16, 60).is_err());
        assert_eq!(
            nested_indices(16, 16).unwrap(),
            (0..256).collect::<Vec<_>>()
        );
        // A shape compared with itself at the shared points.
        let xf: Vec<[f64; 3]> = gf.iter().map(|p| [p[0], p[1], p[0] * p[1]]).collect();
        let xc: Vec<[f64; 3]> = at.iter().map(|&j| xf[j]).collect();
        assert_eq!(shape_rmse(&xc, &xf, &at), 0.0);
    }

    #[test]
    fn sag_is_the_mean_drop_below_the_pins() {
        let x = [[0.0, 0.0, 1.0], [0.0, 0.0, 0.5], [0.0, 0.0, -0.5]];
        assert!((sag(&x, &[true, false, false]) - 1.0).abs() < 1e-12);
    }
}
