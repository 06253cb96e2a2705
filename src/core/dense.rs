//! Dense symmetric positive definite systems held as a packed lower triangle, solved by
//! an `L D Lᵀ` factorisation (Golub & Van Loan, "Matrix Computations", 4th ed., §4.1):
//! the exact coarsest-level solve of the lattice multigrid
//! ([`super::multigrid::Sweeps::exact_coarsest`]).
//!
//! Row `r`, column `c ≤ r` of a matrix is element [`packed`]`(r, c)` of a slice. The
//! system `A x = b` (`A` of `m` rows) is given bordered by its right-hand side, as the
//! lower triangle of `[[A, ·], [bᵀ, ·]]` (`m + 1` rows, `b` in the last): eliminating
//! the bordered matrix factorises `A` and carries out the forward substitution in the
//! same steps, so that only the backward substitution is left. [`solve_bordered`] works
//! in `f32`, each entry's updates in the order the GPU's kernels take them (they
//! eliminate a node's three columns a step, or keep the factor of `A` and carry the
//! border row through it in each solve, with the same updates in the same order), so
//! that the two agree to rounding.
//!
//! ```
//! use bevy_tissue::core::dense::{packed, packed_len, solve_bordered};
//! // A = [[4, 2], [2, 3]], b = [2, 5].
//! let mut a = vec![0.0f32; packed_len(3)];
//! a[packed(0, 0)] = 4.0;
//! a[packed(1, 0)] = 2.0;
//! a[packed(1, 1)] = 3.0;
//! a[packed(2, 0)] = 2.0;
//! a[packed(2, 1)] = 5.0;
//! let x = solve_bordered(&mut a, 2).unwrap();
//! // x = A⁻¹ b = [-0.5, 2].
//! assert!((x[0] + 0.5).abs() < 1e-6 && (x[1] - 2.0).abs() < 1e-6);
//! ```

/// Where row `r`, column `c` (`c ≤ r`) of a packed lower triangle is.
pub fn packed(r: usize, c: usize) -> usize {
    r * (r + 1) / 2 + c
}

/// Length of the packed lower triangle of a matrix of `rows` rows.
pub const fn packed_len(rows: usize) -> usize {
    rows * (rows + 1) / 2
}

/// Solves `A x = b` for the symmetric `A` of `m` rows whose lower triangle, bordered by
/// `b` as row `m`, `a` holds (packed, at least [`packed_len`]`(m + 1)` long). The
/// elimination is in place: afterwards column `k` of `a` below the diagonal holds
/// `l_ik d_k` and the diagonal `d_k` (`A = L D Lᵀ`, `L` unit lower), row `m` holds
/// `L⁻¹ b`. Each step `k` updates the rows and columns past `k` by
/// `a_ij −= a_ik (a_jk / d_k)`; the backward substitution then takes `x_k` from the
/// last row up. `None` where a pivot is not positive (`A` is not numerically positive
/// definite, or holds a NaN) or `a` is too short.
pub fn solve_bordered(a: &mut [f32], m: usize) -> Option<Vec<f32>> {
    if a.len() < packed_len(m + 1) {
        return None;
    }
    let mut ok = true;
    for k in 0..m {
        let d = a[packed(k, k)];
        ok &= d > 0.0;
        let inv = if d > 0.0 { 1.0 / d } else { 0.0 };
        for i in k + 1..=m {
            let aik = a[packed(i, k)];
            for j in k + 1..=i {
                a[packed(i, j)] -= aik * (a[packed(j, k)] * inv);
            }
        }
    }
    if !ok {
        return None;
    }
    let own: Vec<f32> = (0..m).map(|i| 1.0 / a[packed(i, i)]).collect();
    let mut y: Vec<f32> = (0..m).map(|i| a[packed(m, i)] * own[i]).collect();
    for k in (0..m).rev() {
        let xk = y[k];
        for i in 0..k {
            y[i] -= a[packed(k, i)] * own[i] * xk;
        }
    }
    Some(y)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A random symmetric positive definite matrix (`Bᵀ B + m I`), dense row-major.
    fn spd(m: usize, seed: u64) -> Vec<f64> {
        let mut s = seed;
        let mut rand = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 33) as f64 / (1u64 << 31) as f64) - 0.5
        };
        let b: Vec<f64> = (0..m * m).map(|_| rand()).collect();
        let mut a = vec![0.0; m * m];
        for i in 0..m {
            for j in 0..m {
                a[i * m + j] = (0..m).map(|k| b[k * m + i] * b[k * m + j]).sum::<f64>();
            }
            a[i * m + i] += m as f64 * 0.1;
        }
        a
    }

    /// `dense` (row-major, `m` rows) bordered by `b`, packed.
    fn bordered(dense: &[f64], b: &[f32], m: usize) -> Vec<f32> {
        let mut a = vec![0.0f32; packed_len(m + 1)];
        for r in 0..m {
            for c in 0..=r {
                a[packed(r, c)] = dense[r * m + c] as f32;
            }
            a[packed(m, r)] = b[r];
        }
        a
    }

    /// The solve of a random positive definite system matches the residual of the dense
    /// matrix (checked in f64), at the sizes the multigrid uses.
    #[test]
    fn solves_random_positive_definite_systems() {
        for (m, seed) in [(1, 1), (3, 2), (27, 3), (84, 4)] {
            let dense = spd(m, seed);
            let b: Vec<f32> = (0..m).map(|i| (i as f32 * 0.37 + 1.0).sin()).collect();
            let mut a = bordered(&dense, &b, m);
            let x = solve_bordered(&mut a, m).unwrap_or_else(|| panic!("m = {m}"));
            let scale = b.iter().map(|v| v.abs() as f64).fold(0.0, f64::max);
            for r in 0..m {
                let ax: f64 = (0..m).map(|c| dense[r * m + c] * x[c] as f64).sum();
                assert!(
                    (ax - b[r] as f64).abs() < 1e-4 * scale,
                    "m = {m}, row {r}: {ax} vs {}",
                    b[r]
                );
            }
        }
    }

    /// The factor reproduces the matrix: `L D Lᵀ = A` (with `a_ik = l_ik d_k` below the
    /// diagonal and `d_k` on it), and the last row is `L⁻¹ b`.
    #[test]
    fn the_factor_times_its_transpose_is_the_matrix() {
        let m = 12;
        let dense = spd(m, 7);
        let b: Vec<f32> = (0..m).map(|i| i as f32 - 4.0).collect();
        let mut a = bordered(&dense, &b, m);
        assert!(solve_bordered(&mut a, m).is_some());
        let d = |k: usize| a[packed(k, k)] as f64;
        for r in 0..m {
            for c in 0..=r {
                let ldl: f64 = (0..c)
                    .map(|k| a[packed(r, k)] as f64 * a[packed(c, k)] as f64 / d(k))
                    .sum::<f64>()
                    + a[packed(r, c)] as f64;
                assert!((ldl - dense[r * m + c]).abs() < 1e-4 * dense[r * m + r].abs());
            }
        }
        // L z = b with L unit lower (l_rk = a_rk / d_k).
        for r in 0..m {
            let lz: f64 = (0..r)
                .map(|k| a[packed(r, k)] as f64 / d(k) * a[packed(m, k)] as f64)
                .sum::<f64>()
                + a[packed(m, r)] as f64;
            assert!((lz - b[r] as f64).abs() < 1e-4, "row {r}: {lz}");
        }
    }

    /// Indefinite, singular or NaN matrices and a too-short slice are refused.
    #[test]
    fn refuses_what_is_not_positive_definite() {
        // [[1, 2], [2, 1]]: eigenvalues 3 and −1 (b = [1, 1]).
        let mut indefinite = vec![1.0f32, 2.0, 1.0, 1.0, 1.0, 0.0];
        assert!(solve_bordered(&mut indefinite, 2).is_none());
        let mut singular = vec![1.0f32, 1.0, 1.0, 1.0, 1.0, 0.0];
        assert!(solve_bordered(&mut singular, 2).is_none());
        let mut nan = vec![1.0f32, f32::NAN, 1.0, 1.0, 1.0, 0.0];
        assert!(solve_bordered(&mut nan, 2).is_none());
        let mut short = vec![1.0f32, 0.0, 1.0];
        assert!(solve_bordered(&mut short, 2).is_none());
        let mut empty = vec![0.0f32];
        assert_eq!(solve_bordered(&mut empty, 0), Some(Vec::new()));
    }
}
