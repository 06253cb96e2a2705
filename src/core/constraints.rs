//! Constraint math as pure functions (`init_*` computes rest data, `solve_*` computes a
//! correction), kept apart from the arrays that own the data, in the manner of Bender's
//! PositionBasedDynamics. Both the Gauss–Seidel and the Jacobi solver, and the GPU
//! kernels' CPU twins, call these.
//!
//! **Clusters as generalised tetrahedra.** A cluster is a particle and its K nearest rest
//! neighbours. With rest centre of mass `X_cm`, `q_j = X_j − X_cm`,
//! `A_qq = Σ m_j q_j q_jᵀ` and `b_j = m_j A_qq⁻¹ q_j`, the cluster's deformation gradient is
//! `F = Σ_j (p_j − x_cm) b_jᵀ = A_pq A_qq⁻¹` with `A_pq = Σ m_j (p_j − x_cm) q_jᵀ`
//! (Müller et al. 2005, "Meshless deformations based on shape matching", eq. 7;
//! Müller et al. 2022, "Physically based shape matching").
//!
//! **Corrections as affine maps.** Every cluster solve here returns a [`ClusterCorrection`]
//! `(M, t, a)`; member `j` moves by `Δx_j = M X_j + t − a p_j` (`X_j` its rest position).
//! Shape matching gives `M = aR`, `t = a (x_cm − R X_cm)`; XPBD gives `a = 0`. So a Jacobi pass is: one gather per cluster
//! (`A_pq`), a 3×3 solve, then one gather per particle over the clusters that contain it
//! — no scatter, no atomics, deterministic on every thread count and on the GPU.

use glam::{Mat3, Quat, Vec3};

/// Rest data of one cluster (SPEC §2).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClusterRest {
    /// Rest centre of mass `X_cm`, m.
    pub com: Vec3,
    /// `A_qq⁻¹` (m⁻²·kg⁻¹), regularised for flat clusters.
    pub aqq_inv: Mat3,
    /// Total mass of the members, kg.
    pub mass: f32,
}

/// Computes a cluster's rest data from its members' rest positions and masses.
///
/// `A_qq = Σ m_j q_j q_jᵀ` is inverted in f64 as a pseudo-inverse, so a coplanar or
/// collinear cluster gets a finite `A_qq⁻¹` instead of NaN.
pub fn init_cluster(members: &[u32], rest: &[Vec3], mass: &[f32]) -> ClusterRest {
    let mut m_sum = 0.0f64;
    let mut com = glam::DVec3::ZERO;
    for &j in members {
        let m = mass[j as usize] as f64;
        m_sum += m;
        com += rest[j as usize].as_dvec3() * m;
    }
    let com = com / m_sum.max(f64::MIN_POSITIVE);
    let mut aqq = glam::DMat3::ZERO;
    for &j in members {
        let q = rest[j as usize].as_dvec3() - com;
        aqq += outer_d(q * mass[j as usize] as f64, q);
    }
    ClusterRest {
        com: com.as_vec3(),
        aqq_inv: pseudo_inverse_sym(&aqq, 1e-6).as_mat3(),
        mass: m_sum as f32,
    }
}

/// Pseudo-inverse of a symmetric positive semi-definite 3×3 matrix: eigenvalues below
/// `rel_eps` times the largest are treated as zero (a flat cluster gets no stiffness
/// across its plane instead of an infinite one). Exact inverse otherwise.
pub fn pseudo_inverse_sym(a: &glam::DMat3, rel_eps: f64) -> glam::DMat3 {
    let (vals, vecs) = sym_eigen(a);
    let max = vals.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let mut out = glam::DMat3::ZERO;
    for k in 0..3 {
        if max > 0.0 && vals[k] > rel_eps * max {
            let v = vecs.col(k);
            out += outer_d(v / vals[k], v);
        }
    }
    out
}

/// Eigenvalues and eigenvectors (columns) of a symmetric 3×3 matrix by cyclic Jacobi
/// rotations.
pub fn sym_eigen(a: &glam::DMat3) -> ([f64; 3], glam::DMat3) {
    let mut m = a.to_cols_array_2d(); // m[col][row]
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for _sweep in 0..32 {
        let off = m[1][0].powi(2) + m[2][0].powi(2) + m[2][1].powi(2);
        if off < 1e-30 * (m[0][0].powi(2) + m[1][1].powi(2) + m[2][2].powi(2)) || off == 0.0 {
            break;
        }
        for (p, q) in [(0usize, 1usize), (0, 2), (1, 2)] {
            let apq = m[q][p];
            if apq == 0.0 {
                continue;
            }
            let theta = (m[q][q] - m[p][p]) / (2.0 * apq);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let t = if theta == 0.0 { 1.0 } else { t };
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            for k in 0..3 {
                let (mkp, mkq) = (m[p][k], m[q][k]);
                m[p][k] = c * mkp - s * mkq;
                m[q][k] = s * mkp + c * mkq;
            }
            for k in 0..3 {
                let (mpk, mqk) = (m[k][p], m[k][q]);
                m[k][p] = c * mpk - s * mqk;
                m[k][q] = s * mpk + c * mqk;
            }
            for k in 0..3 {
                let (vkp, vkq) = (v[p][k], v[q][k]);
                v[p][k] = c * vkp - s * vkq;
                v[q][k] = s * vkp + c * vkq;
            }
        }
    }
    (
        [m[0][0], m[1][1], m[2][2]],
        glam::DMat3::from_cols_array_2d(&v),
    )
}

fn outer_d(a: glam::DVec3, b: glam::DVec3) -> glam::DMat3 {
    glam::DMat3::from_cols(a * b.x, a * b.y, a * b.z)
}

/// `a bᵀ`.
#[inline(always)]
pub fn outer(a: Vec3, b: Vec3) -> Mat3 {
    Mat3::from_cols(a * b.x, a * b.y, a * b.z)
}

/// Frobenius inner product `<A, B> = tr(AᵀB)`.
#[inline(always)]
pub fn frob(a: &Mat3, b: &Mat3) -> f32 {
    a.x_axis.dot(b.x_axis) + a.y_axis.dot(b.y_axis) + a.z_axis.dot(b.z_axis)
}

/// Current centre of mass `x_cm` and `A_pq = Σ m_j (p_j − x_cm) q_jᵀ` of a cluster.
///
/// Positions are taken relative to `p[members[0]]` before summing, which keeps f32
/// cancellation at the size of the cluster rather than of the world.
#[inline]
pub fn cluster_moments(
    members: &[u32],
    p: &[Vec3],
    rest: &[Vec3],
    mass: &[f32],
    rest_data: &ClusterRest,
) -> (Vec3, Mat3) {
    let origin = p[members[0] as usize];
    let mut mp = Vec3::ZERO;
    let mut a = Mat3::ZERO;
    let mut mq = Vec3::ZERO;
    for &j in members {
        let j = j as usize;
        let m = mass[j];
        let d = p[j] - origin;
        let q = rest[j] - rest_data.com;
        mp += d * m;
        mq += q * m;
        a += outer(d * m, q);
    }
    let c_rel = mp / rest_data.mass;
    // Σ m (p − x_cm) qᵀ = Σ m p qᵀ − x_cm (Σ m q)ᵀ; the second term is zero up to rounding.
    a -= outer(c_rel, mq);
    (origin + c_rel, a)
}

/// A cluster's correction as an affine map of the rest position: member `j` moves by
/// `Δx_j = m X_j + t − a p_j`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClusterCorrection {
    /// Linear part applied to the rest position `X_j` (dimensionless).
    pub m: Mat3,
    /// Translation, m.
    pub t: Vec3,
    /// Weight of the current position (dimensionless, in [0, 1]).
    pub a: f32,
}

impl ClusterCorrection {
    /// No correction.
    pub const ZERO: Self = Self {
        m: Mat3::ZERO,
        t: Vec3::ZERO,
        a: 0.0,
    };

    /// The displacement of a member with rest position `x_rest` and current position `p`.
    #[inline(always)]
    pub fn apply(&self, x_rest: Vec3, p: Vec3) -> Vec3 {
        self.m * x_rest + self.t - self.a * p
    }
}

/// Rotational part of `a` by the iterative method of Müller et al. 2016 ("A robust
/// method to extract the rotational part of deformations"), warm-started from `q`;
/// returns a proper rotation even for flat or inverted `a`. Updates `q` in place.
pub fn extract_rotation(a: &Mat3, q: &mut Quat, iterations: u32) {
    for _ in 0..iterations {
        let r = Mat3::from_quat(*q);
        let num = r.x_axis.cross(a.x_axis) + r.y_axis.cross(a.y_axis) + r.z_axis.cross(a.z_axis);
        let den = (r.x_axis.dot(a.x_axis) + r.y_axis.dot(a.y_axis) + r.z_axis.dot(a.z_axis)).abs()
            + 1.0e-9;
        let omega = num / den;
        let w = omega.length();
        if !(w >= 1.0e-9) {
            break; // converged (also stops on NaN)
        }
        *q = (Quat::from_axis_angle(omega / w, w) * *q).normalize();
    }
}

/// Per-iteration stiffness that gives stiffness `k` after `iterations` iterations:
/// `k' = 1 − (1 − k)^(1/n)` (Müller et al. 2006, "Position based dynamics", §3.3).
pub fn iteration_stiffness(k: f32, iterations: u32) -> f32 {
    1.0 - (1.0 - k.clamp(0.0, 1.0)).powf(1.0 / iterations.max(1) as f32)
}

/// Shape matching (Müller et al. 2005, eq. 6): goal `g_j = x_cm + R q_j` with
/// `R = polar(A_pq)`, correction `Δx_j = α (g_j − p_j)` with `α = k' · weight`
/// (`weight` = 1 for Gauss–Seidel, the cluster's Jacobi weight otherwise).
pub fn solve_shape_matching(
    c: Vec3,
    apq: &Mat3,
    rest: &ClusterRest,
    rot: &mut Quat,
    alpha: f32,
    rotation_iterations: u32,
) -> ClusterCorrection {
    extract_rotation(apq, rot, rotation_iterations);
    let r = Mat3::from_quat(*rot);
    ClusterCorrection {
        m: r * alpha,
        t: (c - r * rest.com) * alpha,
        a: alpha,
    }
}

/// Lamé parameters `(μ, λ)` in Pa of Young's modulus `e` (Pa) and Poisson ratio `nu`.
pub fn lame(e: f32, nu: f32) -> (f32, f32) {
    let mu = e / (2.0 * (1.0 + nu));
    let lambda = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu));
    (mu, lambda)
}

/// Parameters of the stable neo-Hookean constraints of one material.
///
/// Energy density (Macklin & Müller 2021, "A constraint-based formulation of stable
/// neo-Hookean materials", eq. 9 without the log term):
/// `Ψ = μ/2 (tr FᵀF − 3) + λ'/2 (det F − γ)²`, `γ = 1 + μ/λ'`, as two constraints
/// `C_D = ‖F‖_F` (compliance `1/(μV)`) and `C_H = det F − γ` (compliance `1/(λ'V)`).
/// Linearising gives `Ψ ≈ μ‖ε‖² + (λ' − μ)/2 (tr ε)²`, so `λ' = λ + μ` makes the small-strain
/// response that of linear elasticity with the given E and ν.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NeoHookean {
    /// Shear modulus μ, Pa.
    pub mu: f32,
    /// Hydrostatic stiffness λ' = λ + μ, Pa.
    pub lambda: f32,
    /// Rest determinant target γ = 1 + μ/λ'.
    pub gamma: f32,
}

impl NeoHookean {
    /// From Young's modulus (Pa) and Poisson ratio.
    pub fn new(youngs_modulus: f32, poisson_ratio: f32) -> Self {
        let (mu, lambda) = lame(youngs_modulus, poisson_ratio);
        let lambda = lambda + mu;
        Self {
            mu,
            lambda,
            gamma: 1.0 + mu / lambda,
        }
    }
}

/// Cofactor matrix `cof F = det(F) F⁻ᵀ` (columns `f2×f3, f3×f1, f1×f2`) = `∂ det F / ∂F`.
#[inline]
pub fn cofactor(f: &Mat3) -> Mat3 {
    Mat3::from_cols(
        f.y_axis.cross(f.z_axis),
        f.z_axis.cross(f.x_axis),
        f.x_axis.cross(f.y_axis),
    )
}

/// One XPBD iteration of the coupled stable neo-Hookean constraints of a cluster
/// (Macklin & Müller 2021, solved as a 2×2 block as their §5 suggests; multipliers kept
/// across the iterations of a substep as in Macklin et al. 2016, "XPBD").
///
/// * `f` — the cluster's deformation gradient `A_pq A_qq⁻¹`;
/// * `volume` — the cluster's share of the body's rest volume, m³;
/// * `h2` — substep length squared, s²;
/// * `scale` — 1 for Gauss–Seidel; for Jacobi the cluster weight times the relaxation
///   (`ω/s_c`). Both the applied correction and the multiplier increments are scaled by
///   it, so `C + α̃λ` stays consistent with the motion that actually happens (a damped
///   Richardson iteration on the dual system);
/// * `lambdas` — `[λ_H, λ_D]`, updated.
///
/// With `∇_j C = P b_j` and `Σ_j w_j b_j b_jᵀ = A_qq⁻¹`, the system matrix entries are
/// `⟨P_k A_qq⁻¹, P_l⟩`, and the member correction is
/// `Δx_j = scale · (Δλ_H P_H + Δλ_D P_D) A_qq⁻¹ q_j` — an affine map in `q_j`.
pub fn solve_neo_hookean(
    f: &Mat3,
    rest: &ClusterRest,
    volume: f32,
    mat: &NeoHookean,
    h2: f32,
    scale: f32,
    lambdas: &mut [f32; 2],
) -> ClusterCorrection {
    let ph = cofactor(f);
    let c_h = f.determinant() - mat.gamma;
    let norm = frob(f, f).sqrt();
    let (pd, c_d) = if norm > 1e-12 {
        (*f * (1.0 / norm), norm)
    } else {
        (Mat3::ZERO, 0.0)
    };
    let alpha_h = 1.0 / (mat.lambda * volume * h2);
    let alpha_d = 1.0 / (mat.mu * volume * h2);
    let ph_a = ph * rest.aqq_inv;
    let pd_a = pd * rest.aqq_inv;
    let a11 = frob(&ph_a, &ph);
    let a22 = frob(&pd_a, &pd);
    let a12 = frob(&ph_a, &pd);
    let r1 = -c_h - alpha_h * lambdas[0];
    let r2 = -c_d - alpha_d * lambdas[1];
    let m11 = a11 + alpha_h;
    let m22 = a22 + alpha_d;
    // det = (a11 a22 − a12²) + a11 α_D + a22 α_H + α_H α_D, the Gram part clamped at 0:
    // at rest P_H ∥ P_D and the exact Gram determinant is 0.
    let gram = (a11 * a22 - a12 * a12).max(0.0);
    let det = gram + a11 * alpha_d + a22 * alpha_h + alpha_h * alpha_d;
    if !(det > 0.0) || !det.is_finite() {
        return ClusterCorrection::ZERO;
    }
    let dl_h = scale * (m22 * r1 - a12 * r2) / det;
    let dl_d = scale * (m11 * r2 - a12 * r1) / det;
    lambdas[0] += dl_h;
    lambdas[1] += dl_d;
    let m = (ph * dl_h + pd * dl_d) * rest.aqq_inv;
    ClusterCorrection {
        m,
        t: -(m * rest.com),
        a: 0.0,
    }
}

/// Stable neo-Hookean energy density Ψ(F) in Pa (J/m³), for energy-based checks.
pub fn neo_hookean_energy(f: &Mat3, mat: &NeoHookean) -> f32 {
    let j = f.determinant() - mat.gamma;
    0.5 * mat.mu * (frob(f, f) - 3.0) + 0.5 * mat.lambda * j * j
        - 0.5 * mat.lambda * (1.0 - mat.gamma).powi(2)
}

/// Particle–particle contact (non-penetration `|p_i − p_j| ≥ d`): the correction of
/// particle `i` only (the solvers gather it per particle), mass-weighted
/// (Müller et al. 2006, eq. 9). Zero when separated or coincident.
#[inline]
pub fn solve_contact(pi: Vec3, pj: Vec3, wi: f32, wj: f32, d: f32) -> Vec3 {
    let delta = pi - pj;
    let l2 = delta.length_squared();
    let w = wi + wj;
    if l2 >= d * d || l2 <= 1e-24 || w <= 0.0 {
        return Vec3::ZERO;
    }
    let l = l2.sqrt();
    delta * ((d - l) / l * wi / w)
}
