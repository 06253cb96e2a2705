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
//! **Corrections as maps of the rest position.** Every cluster solve here returns a
//! [`ClusterCorrection`]; member `j` moves by `Δx_j = M X_j + t − a p_j` (`X_j` its rest
//! position). Shape matching gives `M = aR`, `t = a (x_cm − R X_cm)` (stored as `R`, `a t`,
//! `a`); XPBD gives `a = 0`. So a Jacobi pass is: one gather per cluster
//! (`A_pq`), a 3×3 solve, then one gather per particle over the clusters that contain it
//! — no scatter, no atomics, deterministic on every thread count and on the GPU.

use glam::{Mat3, Mat3A, Quat, Vec3, Vec3A, Vec4};

/// Rest data of one cluster.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClusterRest {
    /// Rest centre of mass `X_cm`, m.
    pub com: Vec3,
    /// `A_qq⁻¹` (m⁻²·kg⁻¹), regularised for flat clusters.
    pub aqq_inv: Mat3,
    /// Total mass of the members, kg.
    pub mass: f32,
    /// Inverse-mass metric `W = Σ_j w_j b_j b_jᵀ` of the XPBD solve with the members'
    /// true masses (Gauss–Seidel). Pinned members have `w_j = 0`.
    pub metric: Metric,
    /// The same with each member's mass split among the clusters that contain it
    /// (`w_j → n_j w_j`, Tonge et al. 2012 mass splitting): used by Jacobi, where every
    /// cluster owns only its share of each particle.
    pub metric_split: Metric,
}

impl ClusterRest {
    /// The rest data of a particle that owns no cluster (a particle of a hexahedral
    /// body, [`super::model::Discretisation::Lattice`]): no members, no mass.
    pub fn empty() -> Self {
        let zero = Metric {
            w: Mat3::ZERO,
            basis: Mat3::IDENTITY,
            values: Vec3::ZERO,
        };
        Self {
            com: Vec3::ZERO,
            aqq_inv: Mat3::ZERO,
            mass: 0.0,
            metric: zero,
            metric_split: zero,
        }
    }
}

/// The inverse-mass metric `W = A_qq⁻¹ (Σ_j w_j m_j² q_j q_jᵀ) A_qq⁻¹` (kg⁻¹·m⁻²) of a
/// cluster, with its eigen-decomposition (used to solve the deviatoric block exactly).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Metric {
    /// `W` itself.
    pub w: Mat3,
    /// Eigenvectors of `W` (columns).
    pub basis: Mat3,
    /// Eigenvalues of `W`.
    pub values: Vec3,
}

impl Metric {
    /// The metric `w` with its eigen-decomposition (eigenvalues clamped at 0).
    pub fn new(w: glam::DMat3) -> Self {
        let (vals, vecs) = sym_eigen(&w);
        Self {
            w: w.as_mat3(),
            basis: vecs.as_mat3(),
            values: glam::DVec3::from_array(vals)
                .max(glam::DVec3::ZERO)
                .as_vec3(),
        }
    }
}

/// Computes a cluster's rest data from its members' rest positions, masses, inverse
/// masses (`inv_mass[j] = 0` for pinned particles) and multiplicities (`mult[j]` = number
/// of clusters containing `j`).
///
/// `A_qq = Σ m_j q_j q_jᵀ` is inverted in f64 as a pseudo-inverse, so a coplanar or
/// collinear cluster gets a finite `A_qq⁻¹` instead of NaN.
pub fn init_cluster(
    members: &[u32],
    rest: &[Vec3],
    mass: &[f32],
    inv_mass: &[f32],
    mult: &[u32],
) -> ClusterRest {
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
    let inv = pseudo_inverse_sym(&aqq, 1e-6);
    let (mut free, mut split) = (glam::DMat3::ZERO, glam::DMat3::ZERO);
    for &j in members {
        let q = rest[j as usize].as_dvec3() - com;
        let m = mass[j as usize] as f64;
        let w = inv_mass[j as usize] as f64;
        free += outer_d(q * (m * m * w), q);
        split += outer_d(q * (m * m * w * mult[j as usize] as f64), q);
    }
    ClusterRest {
        com: com.as_vec3(),
        aqq_inv: inv.as_mat3(),
        mass: m_sum as f32,
        metric: Metric::new(inv * free * inv),
        metric_split: Metric::new(inv * split * inv),
    }
}

/// Pseudo-inverse of a symmetric positive semi-definite 3×3 matrix: eigenvalues below
/// `rel_eps` times the largest are treated as zero (a flat cluster gets no stiffness
/// across its plane instead of an infinite one). Exact inverse otherwise.
pub fn pseudo_inverse_sym(a: &glam::DMat3, rel_eps: f64) -> glam::DMat3 {
    let (vals, vecs) = sym_eigen(a);
    let max = vals.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let mut out = glam::DMat3::ZERO;
    for (k, &val) in vals.iter().enumerate() {
        if max > 0.0 && val > rel_eps * max {
            let v = vecs.col(k);
            out += outer_d(v / val, v);
        }
    }
    out
}

/// Applies the Jacobi rotation `(c, s)` to columns `p` and `q` of a column-major 3×3.
fn rotate_cols(m: &mut [[f64; 3]; 3], p: usize, q: usize, c: f64, s: f64) {
    let (cp, cq) = (m[p], m[q]);
    for k in 0..3 {
        m[p][k] = c * cp[k] - s * cq[k];
        m[q][k] = s * cp[k] + c * cq[k];
    }
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
            rotate_cols(&mut m, p, q, c, s);
            for row in m.iter_mut() {
                let (mpk, mqk) = (row[p], row[q]);
                row[p] = c * mpk - s * mqk;
                row[q] = s * mpk + c * mqk;
            }
            rotate_cols(&mut v, p, q, c, s);
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

/// Current centre of mass `x_cm`, `A_pq = Σ m_j (p_j − x_cm) q_jᵀ`, and the rest centre
/// of mass as the f32 members actually average to (`X_cm` plus the rounding offset
/// `Σ m_j q_j / M`), for one cluster.
///
/// Positions are taken relative to `p[members[0]]` before summing, which keeps f32
/// cancellation at the size of the cluster rather than of the world. Corrections built
/// with the returned rest centre conserve linear momentum to rounding instead of leaking
/// a constant bias every step.
#[inline]
pub fn cluster_moments(
    members: &[u32],
    p: &[Vec3],
    rest: &[Vec3],
    mass: &[f32],
    rest_data: &ClusterRest,
) -> (Vec3, Mat3, Vec3) {
    let origin = p[members[0] as usize];
    let (o, com) = (Vec3A::from(origin), Vec3A::from(rest_data.com));
    // 4-wide SIMD accumulation: the columns of Σ m d qᵀ are Σ (m d) q_k.
    let (mut mp, mut mq) = (Vec3A::ZERO, Vec3A::ZERO);
    let (mut a0, mut a1, mut a2) = (Vec3A::ZERO, Vec3A::ZERO, Vec3A::ZERO);
    for &j in members {
        let j = j as usize;
        let m = mass[j];
        let md = (Vec3A::from(p[j]) - o) * m;
        let q = Vec3A::from(rest[j]) - com;
        mp += md;
        mq += q * m;
        a0 += md * q.x;
        a1 += md * q.y;
        a2 += md * q.z;
    }
    let inv_m = 1.0 / rest_data.mass;
    let c_rel = Vec3::from(mp * inv_m);
    let mq = Vec3::from(mq);
    let mut a = Mat3::from_cols(a0.into(), a1.into(), a2.into());
    // Σ m (p − x_cm) qᵀ = Σ m p qᵀ − x_cm (Σ m q)ᵀ; the second term is zero up to rounding.
    a -= outer(c_rel, mq);
    (origin + c_rel, a, rest_data.com + mq * inv_m)
}

/// A cluster's correction of its members, in the two forms the GPU stores (its `corr`
/// buffer; `kernels/common.wgsl`): member `j` (rest position `X_j`, current `p_j`) moves by
/// - shape matching, [`Rigid`](Self::Rigid): `Δx_j = a (R X_j + t) − a p_j`, with `R` a
///   unit quaternion (32 bytes on the GPU);
/// - XPBD, [`Affine`](Self::Affine): `Δx_j = M X_j + t` (48 bytes).
///
/// [`apply`](Self::apply) evaluates both in the GPU's order of operations, so that the
/// CPU Jacobi solver stays the GPU's twin to rounding.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ClusterCorrection {
    /// Shape matching: `Δx = a (R X + t) − a p`.
    Rigid {
        /// Rotation `R` of the goal.
        rot: Quat,
        /// `a t` (m) in `xyz`, with `t = x_cm − R X_cm`, and `a` (dimensionless, in
        /// [0, 1]) in `w`.
        ta: Vec4,
    },
    /// XPBD: `Δx = M X + t`.
    Affine {
        /// `M` (dimensionless), applied to the rest position.
        m: Mat3A,
        /// `t`, m.
        t: Vec3A,
    },
}

impl ClusterCorrection {
    /// No correction.
    pub const ZERO: Self = Self::Affine {
        m: Mat3A::ZERO,
        t: Vec3A::ZERO,
    };

    /// The shape-matching correction toward the goal `R X + t` with weight `a`.
    #[inline]
    pub fn rigid(rot: Quat, t: Vec3, a: f32) -> Self {
        Self::Rigid {
            rot,
            ta: (t * a).extend(a),
        }
    }

    /// The affine correction `M X + t`.
    #[inline]
    pub fn affine(m: Mat3, t: Vec3) -> Self {
        Self::Affine {
            m: Mat3A::from(m),
            t: Vec3A::from(t),
        }
    }

    /// Weight `a` of the current position (0 for an affine correction).
    #[inline]
    pub fn a(&self) -> f32 {
        match self {
            Self::Rigid { ta, .. } => ta.w,
            Self::Affine { .. } => 0.0,
        }
    }

    /// `Δx + a p` (m) in `xyz` and `a` in `w` for a member with rest position `x_rest`:
    /// what a particle sums over its clusters (then `Δx = xyz − w p`).
    #[inline(always)]
    pub fn goal_part(&self, x_rest: Vec3A) -> Vec4 {
        match self {
            Self::Rigid { rot, ta } => {
                // X + 2w (q × X) + 2 q × (q × X), as kernels/gather.wgsl.
                let q = Vec3A::new(rot.x, rot.y, rot.z);
                let u = 2.0 * q.cross(x_rest);
                let rx = x_rest + rot.w * u + q.cross(u);
                (ta.w * rx).extend(0.0) + *ta
            }
            Self::Affine { m, t } => (*m * x_rest + *t).extend(0.0),
        }
    }

    /// The displacement of a member with rest position `x_rest` and current position `p`.
    #[inline(always)]
    pub fn apply(&self, x_rest: Vec3, p: Vec3) -> Vec3 {
        let g = self.goal_part(Vec3A::from(x_rest));
        g.truncate() - g.w * p
    }
}

/// Rotational part of `a` by the iterative method of Müller et al. 2016 ("A robust
/// method to extract the rotational part of deformations"), warm-started from `q`;
/// returns a proper rotation even for flat or inverted `a`. Updates `q` in place; stops
/// early once the update angle is below 1e-6 rad.
pub fn extract_rotation(a: &Mat3, q: &mut Quat, iterations: u32) {
    for _ in 0..iterations {
        let r = Mat3::from_quat(*q);
        let num = r.x_axis.cross(a.x_axis) + r.y_axis.cross(a.y_axis) + r.z_axis.cross(a.z_axis);
        let den = (r.x_axis.dot(a.x_axis) + r.y_axis.dot(a.y_axis) + r.z_axis.dot(a.z_axis)).abs()
            + 1.0e-9;
        let omega = num / den;
        let w = omega.length();
        if w.is_nan() || w < 1.0e-6 {
            break; // converged to ~1e-6 rad (or NaN input)
        }
        // exp(ω) ⊗ q; below 0.25 rad its first-order form (1, ω/2) is used (no
        // trigonometry): the iteration's fixed point ω = 0 is the same.
        let step = if w < 0.25 {
            Quat::from_xyzw(0.5 * omega.x, 0.5 * omega.y, 0.5 * omega.z, 1.0)
        } else {
            Quat::from_axis_angle(omega / w, w)
        };
        *q = (step * *q).normalize();
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
    ClusterCorrection::rigid(*rot, c - r * rest.com, alpha)
}

/// Lamé parameters `(μ, λ)` in Pa of Young's modulus `e` (Pa) and Poisson ratio `nu`.
pub fn lame(e: f32, nu: f32) -> (f32, f32) {
    let mu = e / (2.0 * (1.0 + nu));
    let lambda = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu));
    (mu, lambda)
}

/// Lamé parameters of one hyperelastic material.
///
/// Energy density: fixed corotated (Stomakhin et al. 2012, "Energetically consistent
/// invertible elasticity", eq. 2), `Ψ = μ ‖F − R‖² + λ/2 (det F − 1)²` with `R = polar(F)`,
/// solved as XPBD constraints (Macklin et al. 2016) on each cluster's `F`, split as in
/// Macklin & Müller 2021 ("A constraint-based formulation of stable neo-Hookean
/// materials") into a hydrostatic constraint `C_H = det F − 1` (compliance `1/(λV)`) and a
/// deviatoric one — here the strain tensor `E = sym(Rᵀ F) − I` itself (six components,
/// compliance `1/(2μV)` each), so that `½ α⁻¹ ‖E‖² = V μ ‖F − R‖²`. Both are zero at rest.
/// The small-strain limit is linear elasticity with E and ν.
///
/// Why not their stable neo-Hookean (`C_D = ‖F‖`, `C_H = det F − (1 + μ/λ)`)? Its
/// constraints are not zero at rest, so every cluster carries a rest pre-stress, and
/// XPBD's frozen-gradient update mis-estimates the geometric stiffness by the size of that
/// pre-stress: on overlapping clusters a body at rest drifted (E = 2 kPa) or blew up
/// (E ≥ 20 kPa, Gauss–Seidel). And why a tensor multiplier rather than the scalar
/// `‖F − R‖`? The scalar's gradient direction `E/‖E‖` turns from iteration to
/// iteration, the summed multiplier then overstates the force actually applied, and a
/// pinned bar crept downward without end; with a tensor multiplier the force `R Λ` is
/// linear in the strain and the bookkeeping stays exact.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hyperelastic {
    /// Shear modulus μ, Pa.
    pub mu: f32,
    /// Lamé's first parameter λ, Pa.
    pub lambda: f32,
}

impl Hyperelastic {
    /// From Young's modulus (Pa) and Poisson ratio.
    pub fn new(youngs_modulus: f32, poisson_ratio: f32) -> Self {
        let (mu, lambda) = lame(youngs_modulus, poisson_ratio);
        Self { mu, lambda }
    }

    /// Energy density Ψ(F) (Pa = J/m³) for rotation `r = polar(F)`.
    pub fn energy(&self, f: &Mat3, r: &Mat3) -> f32 {
        let d = *f - *r;
        let j = f.determinant() - 1.0;
        self.mu * frob(&d, &d) + 0.5 * self.lambda * j * j
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

/// XPBD multipliers of one cluster's hyperelastic constraints (N·s²·m⁻¹ scale):
/// `h` for `C_H`, and the symmetric deviatoric multiplier `Λ` as
/// `[Λxx, Λyy, Λzz, Λxy, Λxz, Λyz]`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Multipliers {
    /// Hydrostatic multiplier.
    pub h: f32,
    /// Deviatoric multiplier (symmetric 3×3, packed).
    pub d: [f32; 6],
}

impl Multipliers {
    /// All zero.
    pub const ZERO: Self = Self {
        h: 0.0,
        d: [0.0; 6],
    };

    /// The deviatoric multiplier as a matrix.
    #[inline]
    pub fn d_mat(&self) -> Mat3 {
        sym_from(self.d)
    }
}

#[inline]
fn sym_from(d: [f32; 6]) -> Mat3 {
    Mat3::from_cols(
        Vec3::new(d[0], d[3], d[4]),
        Vec3::new(d[3], d[1], d[5]),
        Vec3::new(d[4], d[5], d[2]),
    )
}

#[inline]
fn sym_pack(m: &Mat3) -> [f32; 6] {
    [
        m.x_axis.x, m.y_axis.y, m.z_axis.z, m.x_axis.y, m.x_axis.z, m.y_axis.z,
    ]
}

/// Hydrostatic constraint `C_H = det F − 1` (0 inside `dead_band`) and its gradient `cof F`.
#[inline]
pub fn hydrostatic_constraint(f: &Mat3, dead_band: f32) -> (f32, Mat3) {
    let c = f.determinant() - 1.0;
    (if c.abs() > dead_band { c } else { 0.0 }, cofactor(f))
}

/// Deviatoric strain `E = sym(Rᵀ F) − I` with `R = polar(F)` (warm-started in `rot`);
/// components inside `dead_band` are 0. Taking the symmetric part also removes the skew
/// error of an approximate `R`.
#[inline]
pub fn deviatoric_strain(
    f: &Mat3,
    rot: &mut Quat,
    rotation_iterations: u32,
    dead_band: f32,
) -> (Mat3, Mat3) {
    extract_rotation(f, rot, rotation_iterations);
    let r = Mat3::from_quat(*rot);
    let rtf = r.transpose() * *f;
    let mut e = (rtf + rtf.transpose()) * 0.5 - Mat3::IDENTITY;
    if frob(&e, &e) <= dead_band * dead_band {
        e = Mat3::ZERO;
    }
    (r, e)
}

/// One XPBD iteration of a cluster's hyperelastic constraints ([`Hyperelastic`]):
/// the hydrostatic constraint, then the deviatoric tensor constraint at the deformation
/// gradient the hydrostatic step leaves (block Gauss–Seidel inside the cluster; Macklin
/// et al. 2016, "XPBD", eq. 18, per constraint block).
///
/// * `f` — the cluster's deformation gradient `A_pq A_qq⁻¹`;
/// * `rot` — warm start of `R = polar(F)`, updated ([`extract_rotation`]);
/// * `volume` — the cluster's share of the body's rest volume, m³;
/// * `h2` — substep length squared, s²;
/// * `metric` — [`ClusterRest::metric`] for Gauss–Seidel, [`ClusterRest::metric_split`]
///   for Jacobi;
/// * `scale` — relaxation ω (1 for Gauss–Seidel); multiplier increments and the applied
///   correction are both scaled by it, so `C + α̃λ` stays consistent with the motion;
/// * `lam` — the multipliers, updated;
/// * `dead_band` — strains below it count as zero: the rounding level of `F` in f32
///   ([`strain_dead_band`]), so that a body at rest gets exactly zero correction
///   instead of jittering and random-walking at the rounding level.
///
/// With `∇_j C = P b_j` and `W = Σ_j w_j b_j b_jᵀ` ([`Metric`]): a multiplier
/// step `Δλ` along gradient `P` moves free member `j` by `Δλ P A_qq⁻¹ q_j` (as
/// `w_j b_j = A_qq⁻¹ q_j`) and changes `F` by `Δλ P W`. Hydrostatic:
/// `Δλ_H = (−C_H − α̃_H λ_H)/(⟨P_H W, P_H⟩ + α̃_H)`. Deviatoric: the force is `R Λ`, so
/// `ΔE = sym(ΔΛ W)`; in the eigenbasis of `W` (values `w_a`) each component solves
/// `ΔΛ_ab = (−E − α̃_D Λ)_ab / ((w_a + w_b)/2 + α̃_D)` exactly.
/// The returned correction is the affine map `Δx_j = (Δλ_H P_H + R ΔΛ) A_qq⁻¹ q_j`.
#[allow(clippy::too_many_arguments)]
pub fn solve_hyperelastic(
    f: &Mat3,
    rest: &ClusterRest,
    metric: &Metric,
    rot: &mut Quat,
    rotation_iterations: u32,
    volume: f32,
    mat: &Hyperelastic,
    h2: f32,
    scale: f32,
    lam: &mut Multipliers,
    dead_band: f32,
) -> ClusterCorrection {
    let g = hyperelastic_step(
        f,
        metric,
        rot,
        rotation_iterations,
        volume,
        mat,
        h2,
        scale,
        lam,
        dead_band,
    );
    correction_of(&g, rest)
}

/// The multiplier steps of [`solve_hyperelastic`] for any constraint set whose
/// deformation gradient is linear in the positions, `F = Σ_j x_j b_jᵀ` (a cluster, a
/// hexahedral element's centre): returns `G` such that member `j` moves by `w_j G b_j`,
/// with `metric` = `W = Σ_j w_j b_j b_jᵀ`. Arguments as [`solve_hyperelastic`].
#[allow(clippy::too_many_arguments)]
pub fn hyperelastic_step(
    f: &Mat3,
    metric: &Metric,
    rot: &mut Quat,
    rotation_iterations: u32,
    volume: f32,
    mat: &Hyperelastic,
    h2: f32,
    scale: f32,
    lam: &mut Multipliers,
    dead_band: f32,
) -> Mat3 {
    // Hydrostatic.
    let mut g = Mat3::ZERO;
    let mut f2 = *f;
    let alpha_h = 1.0 / (mat.lambda * volume * h2);
    if alpha_h.is_finite() {
        let (c_h, ph) = hydrostatic_constraint(f, dead_band);
        let r = -c_h - alpha_h * lam.h;
        if r != 0.0 {
            let a = frob(&(ph * metric.w), &ph);
            let dl = scale * r / (a + alpha_h);
            if dl.is_finite() {
                lam.h += dl;
                g += ph * dl;
                f2 += ph * metric.w * dl;
            }
        }
    }
    // Deviatoric.
    let alpha_d = 1.0 / (2.0 * mat.mu * volume * h2);
    if alpha_d.is_finite() {
        let (r, e) = deviatoric_strain(&f2, rot, rotation_iterations, dead_band);
        let lam_d = lam.d_mat();
        let rhs = -e - lam_d * alpha_d;
        if rhs != Mat3::ZERO {
            let q = metric.basis;
            let rp = q.transpose() * rhs * q;
            let wv = metric.values;
            let mut dl = Mat3::ZERO;
            for a in 0..3 {
                for b in 0..3 {
                    let denom = 0.5 * (wv[a] + wv[b]) + alpha_d;
                    dl.col_mut(b)[a] = scale * rp.col(b)[a] / denom;
                }
            }
            let dl = q * dl * q.transpose();
            let dl = (dl + dl.transpose()) * 0.5;
            if dl.is_finite() {
                lam.d = sym_pack(&(lam_d + dl));
                // The member displacements G A_qq⁻¹ q_j exert the torque axial(G Fᵀ − F Gᵀ)
                // (exactly, as Σ m (p − c)(A_qq⁻¹ q)ᵀ = F); an anisotropic W leaves a
                // little in R ΔΛ. Remove it: G' = G − skew(G Fᵀ) F⁻ᵀ makes G' Fᵀ symmetric,
                // so the correction conserves angular momentum.
                g += torque_free(r * dl, f);
            }
        }
    }
    g
}

/// `G − skew(G Fᵀ) F⁻ᵀ`: the part of a correction direction `G` whose member
/// displacements `G b_j` exert no torque (`G' Fᵀ` symmetric), so that it conserves angular
/// momentum; `G` itself when `F` is near singular.
#[inline]
pub fn torque_free(g: Mat3, f: &Mat3) -> Mat3 {
    let det = f.determinant();
    if det.abs() > 1e-3 {
        let k = g * f.transpose();
        let skew = (k - k.transpose()) * 0.5;
        g - skew * (cofactor(f) * (1.0 / det))
    } else {
        g
    }
}

/// The direction `G` (member `j` moves by `w_j G b_j`) that multipliers `lam` exert on a
/// constraint set with deformation gradient `f` and rotation `rot`: `λ_H cof F + R Λ`
/// (the forces of [`hyperelastic_step`]'s constraints, summed).
pub fn multiplier_direction(f: &Mat3, rot: &Quat, lam: &Multipliers) -> Mat3 {
    let r = Mat3::from_quat(*rot);
    cofactor(f) * lam.h + torque_free(r * lam.d_mat(), f)
}

/// `Δx_j = G A_qq⁻¹ q_j` as an affine map of the rest position.
#[inline]
fn correction_of(g: &Mat3, rest: &ClusterRest) -> ClusterCorrection {
    if *g == Mat3::ZERO {
        return ClusterCorrection::ZERO;
    }
    let m = *g * rest.aqq_inv;
    ClusterCorrection::affine(m, -(m * rest.com))
}

/// The strain that f32 rounding alone puts into a cluster's `F`: positions near
/// `coordinate` (m, largest absolute coordinate) resolved over a cluster of radius
/// `radius` (m), with a safety factor of 16 ulps.
#[inline]
pub fn strain_dead_band(coordinate: f32, radius: f32) -> f32 {
    16.0 * f32::EPSILON * (coordinate + radius) / radius
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
