//! Symmetric banded systems, solved by Cholesky (positive definite) or by LU with partial
//! pivoting (indefinite) in `O(n · bw²)` instead of the dense `O(n³)`. A grid cloth's vertices
//! in row order couple only within a few rows, so its Hessians are banded: the FEM source's
//! Newton steps (`source::implicit`) and the XPBD equilibrium's polish and derivatives
//! (`xpbd::equilibrium`) both solve them here.

use anyhow::{Result, bail};

/// A symmetric banded matrix, stored as its lower band.
#[derive(Debug, Clone)]
pub struct BandMatrix {
    n: usize,
    bw: usize,
    /// Row `i` holds columns `i − bw ..= i` at `i · (bw + 1) + (j + bw − i)`.
    data: Vec<f64>,
}

/// A [`BandMatrix`]'s Cholesky factor `L` (`A = L Lᵀ`), for any number of right-hand sides.
#[derive(Debug, Clone)]
pub struct BandCholesky(BandMatrix);

/// A [`BandMatrix`]'s LU factorisation with partial pivoting (`P A = L U`; LINPACK's banded
/// elimination: the row interchanges keep `L` within `bw` sub-diagonals and widen `U` to
/// `2 bw` super-diagonals), for symmetric matrices that are not positive definite.
#[derive(Debug, Clone)]
pub struct BandLu {
    n: usize,
    bw: usize,
    /// Row `i` holds columns `i − bw ..= i + 2 bw` at `i · (3 bw + 1) + (j + bw − i)`.
    data: Vec<f64>,
    /// The row swapped with row `k` at step `k`.
    pivots: Vec<usize>,
}

impl BandMatrix {
    /// The `n × n` zero matrix with half-bandwidth `bw`.
    pub fn zeros(n: usize, bw: usize) -> Self {
        Self {
            n,
            bw,
            data: vec![0.0; n * (bw + 1)],
        }
    }

    #[inline]
    fn at(&self, i: usize, j: usize) -> usize {
        i * (self.bw + 1) + (j + self.bw - i)
    }

    /// Adds `v` to entry `(i, j)`, `j ≤ i ≤ j + bw`.
    pub fn add(&mut self, i: usize, j: usize, v: f64) {
        debug_assert!(j <= i && i - j <= self.bw);
        let k = self.at(i, j);
        self.data[k] += v;
    }

    /// Its Cholesky factor. Fails when the matrix is not positive definite.
    pub fn factor(mut self) -> Result<BandCholesky> {
        let (n, bw) = (self.n, self.bw);
        for i in 0..n {
            let lo = i.saturating_sub(bw);
            for j in lo..=i {
                let mut s = self.data[self.at(i, j)];
                for k in lo.max(j.saturating_sub(bw))..j {
                    s -= self.data[self.at(i, k)] * self.data[self.at(j, k)];
                }
                if i == j {
                    if !(s > 0.0) {
                        bail!("the Newton system is not positive definite (pivot {i} of {n})");
                    }
                    let k = self.at(i, i);
                    self.data[k] = s.sqrt();
                } else {
                    let k = self.at(i, j);
                    self.data[k] = s / self.data[self.at(j, j)];
                }
            }
        }
        Ok(BandCholesky(self))
    }

    /// Its LU factorisation with partial pivoting (the full symmetric matrix, both halves of
    /// the band). Fails when the matrix is singular.
    pub fn lu(&self) -> Result<BandLu> {
        let (n, bw) = (self.n, self.bw);
        let at = |i: usize, j: usize| BandLu::at(bw, i, j);
        let mut data = vec![0.0; n * (3 * bw + 1)];
        for i in 0..n {
            for j in i.saturating_sub(bw)..=i {
                let v = self.data[self.at(i, j)];
                data[at(i, j)] = v;
                data[at(j, i)] = v;
            }
        }
        let mut pivots = vec![0; n];
        for k in 0..n {
            let last = (k + bw).min(n - 1);
            let p = (k..=last)
                .max_by(|&a, &b| data[at(a, k)].abs().total_cmp(&data[at(b, k)].abs()))
                .unwrap_or(k);
            let pivot = data[at(p, k)];
            if pivot == 0.0 || !pivot.is_finite() {
                bail!("the Newton system is singular (column {k} of {n})");
            }
            pivots[k] = p;
            let right = (k + 2 * bw).min(n - 1);
            if p != k {
                for c in k..=right {
                    data.swap(at(k, c), at(p, c));
                }
            }
            for r in k + 1..=last {
                let l = data[at(r, k)] / pivot;
                data[at(r, k)] = l;
                if l != 0.0 {
                    for c in k + 1..=right {
                        data[at(r, c)] -= l * data[at(k, c)];
                    }
                }
            }
        }
        Ok(BandLu {
            n,
            bw,
            data,
            pivots,
        })
    }

    /// Solves `A x = b` in place (`b` becomes `x`), consuming `A`. Fails when `A` is not
    /// positive definite.
    pub fn solve(self, b: &mut [f64]) -> Result<()> {
        self.factor()?.solve(b);
        Ok(())
    }
}

impl BandCholesky {
    /// Solves `A x = b` in place (`b` becomes `x`) by forward and back substitution.
    pub fn solve(&self, b: &mut [f64]) {
        let l = &self.0;
        let (n, bw) = (l.n, l.bw);
        assert_eq!(
            b.len(),
            n,
            "right-hand side of length {} for order {n}",
            b.len()
        );
        for i in 0..n {
            let mut s = b[i];
            for k in i.saturating_sub(bw)..i {
                s -= l.data[l.at(i, k)] * b[k];
            }
            b[i] = s / l.data[l.at(i, i)];
        }
        for i in (0..n).rev() {
            let mut s = b[i];
            for k in i + 1..(i + bw + 1).min(n) {
                s -= l.data[l.at(k, i)] * b[k];
            }
            b[i] = s / l.data[l.at(i, i)];
        }
    }
}

impl BandLu {
    /// Where entry `(i, j)` lies in `data` for half-bandwidth `bw`.
    #[inline]
    fn at(bw: usize, i: usize, j: usize) -> usize {
        i * (3 * bw + 1) + (j + bw - i)
    }

    /// Solves `A x = b` in place (`b` becomes `x`).
    pub fn solve(&self, b: &mut [f64]) {
        let (n, bw) = (self.n, self.bw);
        assert_eq!(
            b.len(),
            n,
            "right-hand side of length {} for order {n}",
            b.len()
        );
        let at = |i: usize, j: usize| Self::at(bw, i, j);
        for k in 0..n {
            b.swap(k, self.pivots[k]);
            for r in k + 1..=(k + bw).min(n - 1) {
                b[r] -= self.data[at(r, k)] * b[k];
            }
        }
        for i in (0..n).rev() {
            let mut s = b[i];
            for c in i + 1..=(i + 2 * bw).min(n - 1) {
                s -= self.data[at(i, c)] * b[c];
            }
            b[i] = s / self.data[at(i, i)];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{DMatrix, DVector};

    /// A diagonally dominant banded matrix, banded and dense.
    fn example(n: usize, bw: usize) -> (BandMatrix, DMatrix<f64>) {
        let mut band = BandMatrix::zeros(n, bw);
        let mut dense = DMatrix::<f64>::zeros(n, n);
        for i in 0..n {
            for j in i.saturating_sub(bw)..=i {
                let v = if i == j {
                    10.0 + i as f64
                } else {
                    ((i * 7 + j * 3) % 5) as f64 * 0.3 - 0.6
                };
                band.add(i, j, v);
                dense[(i, j)] = v;
                dense[(j, i)] = v;
            }
        }
        (band, dense)
    }

    #[test]
    fn banded_cholesky_matches_a_dense_solve_for_several_right_hand_sides() {
        let (band, dense) = example(12, 3);
        let factor = band.factor().unwrap();
        let chol = dense.cholesky().unwrap();
        for shift in [0.0, 1.3] {
            let b: Vec<f64> = (0..12).map(|i| (i as f64 + shift).sin()).collect();
            let mut x = b.clone();
            factor.solve(&mut x);
            let exact = chol.solve(&DVector::from_vec(b));
            for i in 0..12 {
                assert!(
                    (x[i] - exact[i]).abs() < 1e-12,
                    "{i}: {} vs {}",
                    x[i],
                    exact[i]
                );
            }
        }
    }

    #[test]
    fn banded_lu_solves_an_indefinite_matrix_as_a_dense_lu_does() {
        // Negative and zero diagonal entries: Cholesky refuses it, pivoting is needed.
        let (n, bw) = (15, 4);
        let mut band = BandMatrix::zeros(n, bw);
        let mut dense = DMatrix::<f64>::zeros(n, n);
        for i in 0..n {
            for j in i.saturating_sub(bw)..=i {
                let v = if i == j {
                    [2.0, -3.0, 0.0][i % 3]
                } else {
                    ((i * 5 + j * 11) % 7) as f64 * 0.4 - 1.1
                };
                band.add(i, j, v);
                dense[(i, j)] = v;
                dense[(j, i)] = v;
            }
        }
        let lu = band.lu().unwrap();
        assert!(band.factor().is_err());
        let b: Vec<f64> = (0..n).map(|i| (0.3 * i as f64).cos()).collect();
        let mut x = b.clone();
        lu.solve(&mut x);
        let exact = dense
            .clone()
            .lu()
            .solve(&DVector::from_vec(b.clone()))
            .unwrap();
        let residual = &dense * DVector::from_vec(x.clone()) - DVector::from_vec(b);
        assert!(residual.amax() < 1e-12, "residual {}", residual.amax());
        for i in 0..n {
            assert!(
                (x[i] - exact[i]).abs() < 1e-10 * exact.amax(),
                "{i}: {} vs {}",
                x[i],
                exact[i]
            );
        }
        let mut singular = BandMatrix::zeros(3, 1);
        singular.add(1, 1, 1.0);
        assert!(singular.lu().unwrap_err().to_string().contains("singular"));
    }

    #[test]
    fn an_indefinite_matrix_is_refused() {
        let mut a = BandMatrix::zeros(2, 1);
        a.add(0, 0, 1.0);
        a.add(1, 0, 2.0);
        a.add(1, 1, 1.0);
        let err = a.factor().unwrap_err().to_string();
        assert!(err.contains("not positive definite"), "{err}");
    }
}
