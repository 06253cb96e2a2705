//! Hexahedral elements on the sampling lattice: the math of one element, as pure
//! functions (the model owns the arrays; the solvers call these).
//!
//! **Why.** A lattice cell whose eight corners are particles is a trilinear hexahedron.
//! Its deformation is split, as in reduced-integration finite elements, into the
//! deformation gradient at its centre and four hourglass modes per direction:
//!
//! * **Centre.** With corner signs `c_j ∈ {±1}³` and edge length `h`, the one-point
//!   gradient weights are `b_j = ∇N_j(0) = c_j / (4h)`, so `F = Σ_j x_j b_jᵀ` (exact for any
//!   affine motion: `Σ_j b_j = 0`, `Σ_j X_j b_jᵀ = I`). The element's hyperelastic energy
//!   `V Ψ(F)` is solved by the same XPBD constraints as a cluster's
//!   ([`super::constraints::hyperelastic_step`]), with the inverse-mass metric
//!   `W = Σ_j w_j b_j b_jᵀ`.
//! * **Hourglass.** One-point integration cannot see the bilinear and trilinear modes
//!   `ξη, ηζ, ζξ, ξηζ` (`h_α(c_j)` = the corner's sign products), which carry the bending
//!   of the element. Left free they are the zero-energy (odd–even) modes that make
//!   meshless clusters and one-point elements too soft. Their energy is taken from the
//!   hexahedron with incompatible modes (Wilson et al. 1973, "Incompatible displacement
//!   models"; Taylor, Beresford & Wilson 1976, "A non-conforming element for stress
//!   analysis"), which represents pure bending of a rectangular element exactly and does
//!   not lock in shear: its condensed 24 × 24 stiffness splits exactly into the one-point
//!   part and a 12 × 12 block on the hourglass coordinates `q_{iα} = Σ_j h_α(c_j) x_{ji}`
//!   (the linear–hourglass coupling vanishes on a cube). The block's eigenvectors are 12
//!   scalar constraints `c_m = Σ_j g_mj · Rᵀ x_j`, measured in the element's rotated frame
//!   (`R = polar(F)`, corotational hourglass control as in Belytschko & Bindeman 1993,
//!   "Assumed strain stabilization of the eight node hexahedral element"), each with its
//!   own stiffness `k_m` (XPBD compliance `1/k_m`).
//!
//! In the small-strain limit an element's energy is therefore exactly the incompatible-
//! mode hexahedron's, `½ uᵀ K u` ([`cube_stiffness`]): a converging finite-element
//! discretisation of the material E and ν set, rather than a meshless approximation of it.
//!
//! The same split makes `K x` cheap without the 24 × 24 matrix ([`CubeOperator`]): the
//! one-point part is the stress of the centre's strain, and by the cube's reflection
//! symmetry the 12 × 12 hourglass block couples the hourglass coordinates only in three
//! pairs, one triple and three singles (20 numbers a material, with μ and λ).

use super::constraints::{
    Hyperelastic, Metric, Multipliers, hyperelastic_step, multiplier_direction, outer,
};
use glam::{DMat3, DVec3, Mat3, Quat, Vec3};

/// Corners of a hexahedron.
pub const CORNERS: usize = 8;

/// Hourglass constraints per element (4 modes × 3 directions).
pub const HOURGLASS_MODES: usize = 12;

/// Sign vector `c_j ∈ {±1}³` of corner `j`: x from bit 0, y from bit 1, z from bit 2.
#[inline]
pub fn corner_sign(j: usize) -> Vec3 {
    Vec3::new(
        if j & 1 != 0 { 1.0 } else { -1.0 },
        if j & 2 != 0 { 1.0 } else { -1.0 },
        if j & 4 != 0 { 1.0 } else { -1.0 },
    )
}

/// The four hourglass base vectors at corner `j`: `ξη, ηζ, ζξ, ξηζ` of its signs.
#[inline]
pub fn hourglass_base(j: usize) -> [f32; 4] {
    let c = corner_sign(j);
    [c.x * c.y, c.y * c.z, c.z * c.x, c.x * c.y * c.z]
}

/// One-point gradient weights `b_j = c_j / (4h)` (1/m) of a cube of edge `h` (m):
/// `F = Σ_j x_j b_jᵀ`.
#[inline]
pub fn gradient_weight(j: usize, h: f32) -> Vec3 {
    corner_sign(j) / (4.0 * h)
}

/// Deformation gradient at the centre of a cube of edge `h` with corner positions `x`
/// (corner order of [`corner_sign`]). Positions are taken relative to corner 0, which
/// keeps f32 cancellation at the size of the element.
#[inline]
pub fn element_gradient(x: &[Vec3; CORNERS], h: f32) -> Mat3 {
    let o = x[0];
    let mut f = Mat3::ZERO;
    for (j, &xj) in x.iter().enumerate().skip(1) {
        f += outer(xj - o, gradient_weight(j, h));
    }
    f
}

/// Rest data of one element.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ElementRest {
    /// Rest centre, m (body frame).
    pub centre: Vec3,
    /// Edge length `h`, m.
    pub size: f32,
    /// Volume the element stands for, m³ (`h³` scaled so that a body's elements add up
    /// to the volume its surface encloses).
    pub volume: f32,
    /// `W = Σ_j w_j b_j b_jᵀ` with the corners' true inverse masses (Gauss–Seidel).
    pub metric: Metric,
    /// The same with each corner's mass split among the elements that share it
    /// (`w_j → n_j w_j`, Tonge et al. 2012): Jacobi.
    pub metric_split: Metric,
}

impl ElementRest {
    /// Rest data of a cube of edge `size` (m) centred at `centre` standing for `volume`
    /// (m³), whose corners have inverse masses `inv_mass` (0: pinned) and belong to
    /// `mult` elements each.
    pub fn new(
        centre: Vec3,
        size: f32,
        volume: f32,
        inv_mass: &[f32; CORNERS],
        mult: &[u32; CORNERS],
    ) -> Self {
        let (mut w, mut ws) = (DMat3::ZERO, DMat3::ZERO);
        for j in 0..CORNERS {
            let b = gradient_weight(j, size).as_dvec3();
            let bb = DMat3::from_cols(b * b.x, b * b.y, b * b.z);
            w += bb * inv_mass[j] as f64;
            ws += bb * (inv_mass[j] as f64 * mult[j] as f64);
        }
        Self {
            centre,
            size,
            volume,
            metric: Metric::new(w),
            metric_split: Metric::new(ws),
        }
    }

    /// Hourglass stiffness scale `V / h²` (m): an element's mode stiffnesses are
    /// [`HexModes::stiffness`] (those of a unit cube) times this, as a hexahedron's
    /// stiffness grows with its edge and, for a partial cell, with its volume.
    #[inline]
    pub fn hourglass_scale(&self) -> f32 {
        self.volume / (self.size * self.size)
    }
}

/// The hourglass constraints of one material: for a 1 m cube, the eigenvectors of the
/// incompatible-mode hexahedron's hourglass block and their stiffnesses.
#[derive(Debug, Clone, PartialEq)]
pub struct HexModes {
    /// Stiffness `k_m` of each mode for a 1 m cube, N/m.
    pub stiffness: [f32; HOURGLASS_MODES],
    /// Corner vectors `g_mj` (dimensionless): `c_m = Σ_j g_mj · Rᵀ x_j`.
    pub vectors: [[Vec3; CORNERS]; HOURGLASS_MODES],
    /// `Σ_j |g_mj|²` (the same for every mode: 8; kept for the solver's denominators).
    pub norm2: [f32; HOURGLASS_MODES],
}

impl HexModes {
    /// The modes of a material with Lamé parameters `mu`, `lambda` (Pa).
    pub fn new(mu: f64, lambda: f64) -> Self {
        let block = hourglass_block(&cube_stiffness(mu, lambda));
        let n = HOURGLASS_MODES;
        let hb: Vec<[f32; 4]> = (0..CORNERS).map(hourglass_base).collect();
        let (vals, vecs) = sym_eigen_n(&block, n);
        let mut out = Self {
            stiffness: [0.0; HOURGLASS_MODES],
            vectors: [[Vec3::ZERO; CORNERS]; HOURGLASS_MODES],
            norm2: [0.0; HOURGLASS_MODES],
        };
        for m in 0..n {
            out.stiffness[m] = vals[m].max(0.0) as f32;
            for (j, h) in hb.iter().enumerate() {
                let mut g = DVec3::ZERO;
                for a in 0..4 {
                    let u = DVec3::new(
                        vecs[(3 * a) * n + m],
                        vecs[(3 * a + 1) * n + m],
                        vecs[(3 * a + 2) * n + m],
                    );
                    g += u * h[a] as f64;
                }
                out.vectors[m][j] = g.as_vec3();
            }
            out.norm2[m] = out.vectors[m].iter().map(|g| g.length_squared()).sum();
        }
        out
    }

    /// The modes of a hyperelastic material ([`Hyperelastic`]'s μ and λ).
    pub fn of(mat: &Hyperelastic) -> Self {
        Self::new(mat.mu as f64, mat.lambda as f64)
    }
}

/// The hourglass block of the unit cube's stiffness `k` ([`cube_stiffness`], row-major
/// 24 × 24): `Q[(α,i),(β,l)] = Σ_jk h_α(j) h_β(k) K[3j+i][3k+l] / 64`, row-major 12 × 12
/// with index `3α + i` (mode α of [`hourglass_base`], direction i). With the hourglass
/// coordinates `q_{iα} = Σ_j h_α(c_j) x_{ji}` the hourglass part of `K x` at corner `a` is
/// `Σ_α h_α(a) (Q q)_α`.
fn hourglass_block(k: &[f64]) -> Vec<f64> {
    let n = HOURGLASS_MODES;
    let mut block = vec![0.0f64; n * n];
    let hb: Vec<[f32; 4]> = (0..CORNERS).map(hourglass_base).collect();
    for a in 0..4 {
        for i in 0..3 {
            for b in 0..4 {
                for l in 0..3 {
                    let mut s = 0.0;
                    for j in 0..CORNERS {
                        for m in 0..CORNERS {
                            s +=
                                hb[j][a] as f64 * hb[m][b] as f64 * k[(3 * j + i) * 24 + 3 * m + l];
                        }
                    }
                    block[(3 * a + i) * n + 3 * b + l] = s / 64.0;
                }
            }
        }
    }
    block
}

/// The hourglass coordinates `(α, i)` that the unit cube's hourglass block couples in
/// pairs: the cube's three reflections leave the block diagonal by parity, with three
/// 2 × 2 blocks ([`HOURGLASS_PAIRS`]), one 3 × 3 block ([`HOURGLASS_TRIPLE`]) and three
/// 1 × 1 blocks (the trilinear mode `ξηζ` in each direction).
pub const HOURGLASS_PAIRS: [[(usize, usize); 2]; 3] =
    [[(0, 0), (1, 2)], [(0, 1), (2, 2)], [(1, 1), (2, 0)]];

/// The hourglass coordinates `(α, i)` of the unit cube's 3 × 3 hourglass block (see
/// [`HOURGLASS_PAIRS`]).
pub const HOURGLASS_TRIPLE: [(usize, usize); 3] = [(0, 2), (1, 0), (2, 1)];

/// The unit cube's linearised stiffness ([`cube_stiffness`]) applied in factored form,
/// without its 24 × 24 matrix: the one-point part from the centre's strain and the
/// hourglass part from the twelve hourglass coordinates through the block's non-zero
/// entries (the split of the incompatible-mode hexahedron described in this module's
/// documentation). Per corner row it reads the eight corner values once and no
/// stiffness blocks, which is what makes it cheaper than the blocks on the GPU.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CubeOperator {
    /// Lamé `μ`, Pa.
    pub mu: f32,
    /// Lamé `λ`, Pa.
    pub lambda: f32,
    /// Each of the three 2 × 2 hourglass blocks ([`HOURGLASS_PAIRS`]) as its entries
    /// `(0,0)`, `(0,1)`, `(1,1)`, N/m (a 1 m cube).
    pub pairs: [[f32; 3]; 3],
    /// The 3 × 3 hourglass block ([`HOURGLASS_TRIPLE`]): its diagonal, then the entries
    /// `(0,1)`, `(1,2)`, `(2,0)`, N/m.
    pub triple: [f32; 6],
    /// The trilinear mode's stiffness in x, y, z, N/m.
    pub singles: [f32; 3],
}

impl CubeOperator {
    /// The operator of a material with Lamé parameters `mu`, `lambda` (Pa).
    pub fn new(mu: f64, lambda: f64) -> Self {
        Self::from_stiffness(mu, lambda, &cube_stiffness(mu, lambda))
    }

    /// The operator of a hyperelastic material ([`Hyperelastic`]'s μ and λ).
    pub fn of(mat: &Hyperelastic) -> Self {
        Self::new(mat.mu as f64, mat.lambda as f64)
    }

    /// The operator of a material with Lamé parameters `mu`, `lambda` (Pa) whose unit
    /// cube's stiffness [`cube_stiffness`] has already made as `k`.
    pub fn from_stiffness(mu: f64, lambda: f64, k: &[f64]) -> Self {
        let q = hourglass_block(k);
        let at = |(a, i): (usize, usize), (b, l): (usize, usize)| {
            q[(3 * a + i) * HOURGLASS_MODES + 3 * b + l] as f32
        };
        let t = HOURGLASS_TRIPLE;
        Self {
            mu: mu as f32,
            lambda: lambda as f32,
            pairs: HOURGLASS_PAIRS.map(|[u, v]| [at(u, u), at(u, v), at(v, v)]),
            triple: [
                at(t[0], t[0]),
                at(t[1], t[1]),
                at(t[2], t[2]),
                at(t[0], t[1]),
                at(t[1], t[2]),
                at(t[2], t[0]),
            ],
            singles: [at((3, 0), (3, 0)), at((3, 1), (3, 1)), at((3, 2), (3, 2))],
        }
    }

    /// The moments of corner values `x` (corner order of [`corner_sign`]) that the
    /// operator needs: `g = Σ_j x_j c_jᵀ` (four times the unit cube's gradient) and the
    /// hourglass coordinates `q_α = Σ_j h_α(c_j) x_j`.
    #[inline]
    pub fn moments(x: &[Vec3; CORNERS]) -> (Mat3, [Vec3; 4]) {
        // Sums and differences along x first, then y, then z (the GPU's order).
        let (s01, d01) = (x[1] + x[0], x[1] - x[0]);
        let (s23, d23) = (x[3] + x[2], x[3] - x[2]);
        let (s45, d45) = (x[5] + x[4], x[5] - x[4]);
        let (s67, d67) = (x[7] + x[6], x[7] - x[6]);
        let gx = (d01 + d23) + (d45 + d67);
        let gy = (s23 - s01) + (s67 - s45);
        let gz = (s45 + s67) - (s01 + s23);
        let xy = (d23 - d01) + (d67 - d45);
        let yz = (s67 - s45) - (s23 - s01);
        let zx = (d45 + d67) - (d01 + d23);
        let xyz = (d67 - d45) - (d23 - d01);
        (Mat3::from_cols(gx, gy, gz), [xy, yz, zx, xyz])
    }

    /// The hourglass coordinates `q_α = Σ_j h_α(c_j) x_j` of corner values `x` alone
    /// (the second part of [`Self::moments`]; pass values relative to a corner where
    /// they are positions: the coordinates do not change, their rounding does).
    #[inline]
    pub fn hourglass_coords(x: &[Vec3; CORNERS]) -> [Vec3; 4] {
        Self::moments(x).1
    }

    /// The operator's response to moments `(g, q)` ([`Self::moments`]): the stress
    /// `σ = 2μ ε + λ tr(ε) I` of the strain `ε = sym(g) / 4` (Pa), and the hourglass
    /// block times the coordinates, `(Q q)_α` ([`Self::hourglass`]).
    #[inline]
    pub fn response(&self, g: &Mat3, q: &[Vec3; 4]) -> (Mat3, [Vec3; 4]) {
        let e = (*g + g.transpose()) * 0.25;
        let tr = e.x_axis.x + e.y_axis.y + e.z_axis.z;
        let sigma = e * self.mu + Mat3::from_diagonal(Vec3::splat(0.5 * self.lambda * tr));
        (sigma, self.hourglass(q))
    }

    /// The hourglass block times hourglass coordinates `q`, `(Q q)_α` (N/m times m, a
    /// 1 m cube): `½ qᵀ Q q` is the unit cube's hourglass energy and
    /// [`Self::hourglass_row`] its corners' forces.
    #[inline]
    pub fn hourglass(&self, q: &[Vec3; 4]) -> [Vec3; 4] {
        let (x, y, z) = (q[0], q[1], q[2]);
        let [p0, p1, p2] = self.pairs;
        let t = self.triple;
        let s = self.singles;
        // Pairs: (xy·x, yz·z), (xy·y, zx·z), (yz·y, zx·x); triple: (xy·z, yz·x, zx·y).
        let r_xy = Vec3::new(
            p0[0] * x.x + p0[1] * y.z,
            p1[0] * x.y + p1[1] * z.z,
            t[0] * x.z + t[3] * y.x + t[5] * z.y,
        );
        let r_yz = Vec3::new(
            t[3] * x.z + t[1] * y.x + t[4] * z.y,
            p2[0] * y.y + p2[1] * z.x,
            p0[1] * x.x + p0[2] * y.z,
        );
        let r_zx = Vec3::new(
            p2[1] * y.y + p2[2] * z.x,
            t[5] * x.z + t[4] * y.x + t[2] * z.y,
            p1[1] * x.y + p1[2] * z.z,
        );
        let r_xyz = q[3] * Vec3::from_array(s);
        [r_xy, r_yz, r_zx, r_xyz]
    }

    /// Corner `a`'s share of the hourglass response `r` ([`Self::hourglass`]),
    /// `Σ_α h_α(a) r_α`.
    #[inline]
    pub fn hourglass_row(a: usize, r: &[Vec3; 4]) -> Vec3 {
        let h = hourglass_base(a);
        (r[0] * h[0] + r[1] * h[1]) + (r[2] * h[2] + r[3] * h[3])
    }

    /// Row `a` of the unit cube's stiffness times the corner values the response
    /// ([`Self::response`]) was made from: `σ c_a / 4 + Σ_α h_α(a) (Q q)_α` (N for values
    /// in m, a 1 m cube; an element of edge `h` and volume `V` scales it by `V / h²`).
    #[inline]
    pub fn row(a: usize, sigma: &Mat3, r: &[Vec3; 4]) -> Vec3 {
        *sigma * (corner_sign(a) * 0.25) + Self::hourglass_row(a, r)
    }

    /// `vᵀ K u` for the unit cube's stiffness `K` (N·m for values in m, a 1 m cube) from
    /// `u`'s response `(sigma, r)` ([`Self::response`]) and `v`'s moments `(g, q)`
    /// ([`Self::moments`]): `Σ_k σ_k · g_k / 4 + Σ_α r_α · q_α`, the sum over the corners
    /// of `v_a ·` [`Self::row`] without a row (both vectors' moments in one frame).
    #[inline]
    pub fn product(sigma: &Mat3, r: &[Vec3; 4], g: &Mat3, q: &[Vec3; 4]) -> f32 {
        let stress =
            sigma.x_axis.dot(g.x_axis) + sigma.y_axis.dot(g.y_axis) + sigma.z_axis.dot(g.z_axis);
        0.25 * stress + (r[0].dot(q[0]) + r[1].dot(q[1]) + r[2].dot(q[2]) + r[3].dot(q[3]))
    }

    /// The unit cube's stiffness times corner values `x`, every row (N for x in m).
    pub fn apply(&self, x: &[Vec3; CORNERS]) -> [Vec3; CORNERS] {
        let (g, q) = Self::moments(x);
        let (s, r) = self.response(&g, &q);
        std::array::from_fn(|a| Self::row(a, &s, &r))
    }
}

/// Symmetric 6 × 6 elasticity matrix (Voigt order xx, yy, zz, xy, yz, zx; engineering
/// shears) of an isotropic material.
fn elasticity(mu: f64, lambda: f64) -> [[f64; 6]; 6] {
    let mut d = [[0.0; 6]; 6];
    for (i, row) in d.iter_mut().enumerate().take(3) {
        for (j, v) in row.iter_mut().enumerate().take(3) {
            *v = lambda + if i == j { 2.0 * mu } else { 0.0 };
        }
    }
    for (i, row) in d.iter_mut().enumerate().skip(3) {
        row[i] = mu;
    }
    d
}

/// Strain–displacement rows of one gradient `g` (1/m) acting on a node's 3 DOFs:
/// `ε = B u` in the Voigt order of [`elasticity`].
fn b_rows(g: [f64; 3]) -> [[f64; 3]; 6] {
    [
        [g[0], 0.0, 0.0],
        [0.0, g[1], 0.0],
        [0.0, 0.0, g[2]],
        [g[1], g[0], 0.0],
        [0.0, g[2], g[1]],
        [g[2], 0.0, g[0]],
    ]
}

/// Adds `w Bᵢᵀ D Bⱼ` for every pair of columns of `ba` (rows `ra` nodes) and `bb`.
fn add_btdb(
    out: &mut [f64],
    ld: usize,
    ba: &[[f64; 3]],
    bb: &[[f64; 3]],
    d: &[[f64; 6]; 6],
    w: f64,
) {
    for (i, gi) in ba.iter().enumerate() {
        let bi = b_rows(*gi);
        for (j, gj) in bb.iter().enumerate() {
            let bj = b_rows(*gj);
            for a in 0..3 {
                for c in 0..3 {
                    let mut s = 0.0;
                    for p in 0..6 {
                        if bi[p][a] == 0.0 {
                            continue;
                        }
                        for q in 0..6 {
                            s += bi[p][a] * d[p][q] * bj[q][c];
                        }
                    }
                    out[(3 * i + a) * ld + 3 * j + c] += w * s;
                }
            }
        }
    }
}

/// Linear-elastic stiffness (N/m, row-major 24 × 24, DOF `3j + i` = corner `j`
/// ([`corner_sign`] order), direction `i`) of a 1 m cube: the trilinear hexahedron with
/// the nine incompatible modes `1 − ξ², 1 − η², 1 − ζ²` per direction condensed out
/// (Taylor, Beresford & Wilson 1976), integrated exactly by 2 × 2 × 2 Gauss points. A
/// cube of edge `h` has `h` times this stiffness.
pub fn cube_stiffness(mu: f64, lambda: f64) -> Vec<f64> {
    let d = elasticity(mu, lambda);
    let a = 0.5; // half edge of the unit cube
    let g = 1.0 / 3.0f64.sqrt();
    let mut kuu = vec![0.0; 24 * 24];
    let mut kua = vec![0.0; 24 * 9];
    let mut kaa = vec![0.0; 9 * 9];
    let w = a * a * a; // Gauss weight 1 × Jacobian a³
    for gp in 0..8 {
        let (xi, et, ze) = (
            if gp & 1 != 0 { g } else { -g },
            if gp & 2 != 0 { g } else { -g },
            if gp & 4 != 0 { g } else { -g },
        );
        let grads: Vec<[f64; 3]> = (0..CORNERS)
            .map(|j| {
                let c = corner_sign(j).as_dvec3();
                [
                    c.x * (1.0 + et * c.y) * (1.0 + ze * c.z) / (8.0 * a),
                    c.y * (1.0 + xi * c.x) * (1.0 + ze * c.z) / (8.0 * a),
                    c.z * (1.0 + xi * c.x) * (1.0 + et * c.y) / (8.0 * a),
                ]
            })
            .collect();
        // Incompatible modes: each direction gets 1 − ξ², 1 − η², 1 − ζ², gradients taken
        // at the centre's Jacobian (Taylor's correction; a cube's is constant anyway).
        let inc = [
            [-2.0 * xi / a, 0.0, 0.0],
            [0.0, -2.0 * et / a, 0.0],
            [0.0, 0.0, -2.0 * ze / a],
        ];
        add_btdb(&mut kuu, 24, &grads, &grads, &d, w);
        add_btdb(&mut kua, 9, &grads, &inc, &d, w);
        add_btdb(&mut kaa, 9, &inc, &inc, &d, w);
    }
    // Static condensation: K = Kuu − Kua Kaa⁻¹ Kuaᵀ.
    let x = solve_dense(&kaa, 9, &transpose(&kua, 24, 9), 24);
    for i in 0..24 {
        for j in 0..24 {
            let mut s = 0.0;
            for k in 0..9 {
                s += kua[i * 9 + k] * x[k * 24 + j];
            }
            kuu[i * 24 + j] -= s;
        }
    }
    kuu
}

fn transpose(a: &[f64], rows: usize, cols: usize) -> Vec<f64> {
    let mut t = vec![0.0; rows * cols];
    for i in 0..rows {
        for j in 0..cols {
            t[j * rows + i] = a[i * cols + j];
        }
    }
    t
}

/// Solves `A X = B` (`A` n × n symmetric positive definite, `B` n × m, row-major) by
/// Gaussian elimination with partial pivoting.
fn solve_dense(a: &[f64], n: usize, b: &[f64], m: usize) -> Vec<f64> {
    let mut a = a.to_vec();
    let mut x = b.to_vec();
    for col in 0..n {
        let piv = (col..n)
            .max_by(|&i, &j| a[i * n + col].abs().total_cmp(&a[j * n + col].abs()))
            .unwrap_or(col);
        if piv != col {
            for k in 0..n {
                a.swap(col * n + k, piv * n + k);
            }
            for k in 0..m {
                x.swap(col * m + k, piv * m + k);
            }
        }
        let p = a[col * n + col];
        if p == 0.0 {
            continue;
        }
        for r in col + 1..n {
            let f = a[r * n + col] / p;
            if f == 0.0 {
                continue;
            }
            for k in col..n {
                a[r * n + k] -= f * a[col * n + k];
            }
            for k in 0..m {
                x[r * m + k] -= f * x[col * m + k];
            }
        }
    }
    for col in (0..n).rev() {
        let p = a[col * n + col];
        for k in 0..m {
            let mut s = x[col * m + k];
            for j in col + 1..n {
                s -= a[col * n + j] * x[j * m + k];
            }
            x[col * m + k] = if p != 0.0 { s / p } else { 0.0 };
        }
    }
    x
}

/// Eigenvalues and eigenvectors (columns of the row-major `n × n` result) of a symmetric
/// matrix by cyclic Jacobi rotations.
pub fn sym_eigen_n(a: &[f64], n: usize) -> (Vec<f64>, Vec<f64>) {
    let mut m = a.to_vec();
    let mut v = vec![0.0; n * n];
    for i in 0..n {
        v[i * n + i] = 1.0;
    }
    for _sweep in 0..64 {
        let mut off = 0.0;
        let mut diag = 0.0;
        for i in 0..n {
            diag += m[i * n + i] * m[i * n + i];
            for j in i + 1..n {
                off += m[i * n + j] * m[i * n + j];
            }
        }
        if off <= 1e-30 * diag || off == 0.0 {
            break;
        }
        for p in 0..n {
            for q in p + 1..n {
                let apq = m[p * n + q];
                if apq == 0.0 {
                    continue;
                }
                let theta = (m[q * n + q] - m[p * n + p]) / (2.0 * apq);
                let t = if theta == 0.0 {
                    1.0
                } else {
                    theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt())
                };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                // A ← Jᵀ A J on rows and columns p, q.
                for k in 0..n {
                    let (akp, akq) = (m[k * n + p], m[k * n + q]);
                    m[k * n + p] = c * akp - s * akq;
                    m[k * n + q] = s * akp + c * akq;
                }
                for k in 0..n {
                    let (apk, aqk) = (m[p * n + k], m[q * n + k]);
                    m[p * n + k] = c * apk - s * aqk;
                    m[q * n + k] = s * apk + c * aqk;
                }
                for k in 0..n {
                    let (vkp, vkq) = (v[k * n + p], v[k * n + q]);
                    v[k * n + p] = c * vkp - s * vkq;
                    v[k * n + q] = s * vkp + c * vkq;
                }
            }
        }
    }
    ((0..n).map(|i| m[i * n + i]).collect(), v)
}

/// XPBD multipliers of one element: the centre's hyperelastic constraints and the 12
/// hourglass constraints.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ElementMultipliers {
    /// Hydrostatic and deviatoric multipliers of the centre's `F`.
    pub hyper: Multipliers,
    /// One multiplier per hourglass mode.
    pub hourglass: [f32; HOURGLASS_MODES],
}

impl ElementMultipliers {
    /// All zero.
    pub const ZERO: Self = Self {
        hyper: Multipliers::ZERO,
        hourglass: [0.0; HOURGLASS_MODES],
    };
}

/// Per-element settings of one solve.
#[derive(Debug, Clone, Copy)]
pub struct ElementSolve<'a> {
    /// The body's material.
    pub material: &'a Hyperelastic,
    /// The material's hourglass modes.
    pub modes: &'a HexModes,
    /// Substep length squared, s².
    pub h2: f32,
    /// Relaxation ω of the multiplier increments (1 for Gauss–Seidel).
    pub scale: f32,
    /// Most iterations of the warm-started rotation extraction.
    pub rotation_iterations: u32,
    /// Strains below this count as zero ([`super::constraints::strain_dead_band`]).
    pub dead_band: f32,
    /// Use [`ElementRest::metric_split`] (Jacobi) instead of [`ElementRest::metric`].
    pub split: bool,
}

/// One XPBD iteration of one element (block Gauss–Seidel inside it): the centre's
/// hydrostatic and deviatoric constraints (Macklin & Müller 2021's split of the fixed-
/// corotated energy, [`hyperelastic_step`]), then its 12 hourglass constraints
/// `c_m = Σ_j g_mj · Rᵀ (x_j − x_0)` with compliance `1 / (k_m V/h²)` (Macklin et al.
/// 2016, "XPBD", eq. 18, one scalar constraint at a time). `x` are the corner positions,
/// moved in place; `w` the inverse masses the element sees (1/kg; 0 for a pinned corner;
/// for Jacobi each corner's `n_j w_j`).
pub fn solve_element(
    x: &mut [Vec3; CORNERS],
    w: &[f32; CORNERS],
    rest: &ElementRest,
    s: &ElementSolve,
    rot: &mut Quat,
    lam: &mut ElementMultipliers,
) {
    let h = rest.size;
    let f = element_gradient(x, h);
    let metric = if s.split {
        &rest.metric_split
    } else {
        &rest.metric
    };
    let g = hyperelastic_step(
        &f,
        metric,
        rot,
        s.rotation_iterations,
        rest.volume,
        s.material,
        s.h2,
        s.scale,
        &mut lam.hyper,
        s.dead_band,
    );
    if g != Mat3::ZERO {
        for j in 0..CORNERS {
            x[j] += w[j] * (g * gradient_weight(j, h));
        }
    }
    // Hourglass modes in the element's rotated frame.
    let r = Mat3::from_quat(*rot);
    let rt = r.transpose();
    let scale_k = rest.hourglass_scale();
    // A mode of unit corner amplitude s gives c ≈ 8 s; the dead band is a strain.
    let band = 8.0 * h * s.dead_band;
    for m in 0..HOURGLASS_MODES {
        let k = s.modes.stiffness[m] * scale_k;
        if k <= 0.0 {
            continue;
        }
        let alpha = 1.0 / (k * s.h2);
        let gm = &s.modes.vectors[m];
        let o = x[0];
        let mut c = 0.0;
        let mut denom = alpha;
        for j in 0..CORNERS {
            c += gm[j].dot(rt * (x[j] - o));
            denom += w[j] * gm[j].length_squared();
        }
        if c.abs() <= band {
            c = 0.0;
        }
        let rhs = -c - alpha * lam.hourglass[m];
        if rhs == 0.0 {
            continue;
        }
        let dl = s.scale * rhs / denom;
        if !dl.is_finite() {
            continue;
        }
        lam.hourglass[m] += dl;
        for j in 0..CORNERS {
            if w[j] != 0.0 {
                x[j] += (w[j] * dl) * (r * gm[j]);
            }
        }
    }
}

/// The displacement of each corner (m) that multipliers `lam` exert at corner positions
/// `x` and rotation `rot`: `w_j (G b_j + Σ_m λ_m R g_mj)` with `G` the centre's
/// [`multiplier_direction`]. Applied at the start of a substep with the previous
/// substep's multipliers, it makes the static equilibrium the fixed point of the
/// iteration however few iterations run (a consistent warm start of XPBD: the positions
/// agree with the multipliers carried over).
pub fn multiplier_displacement(
    x: &[Vec3; CORNERS],
    w: &[f32; CORNERS],
    rest: &ElementRest,
    modes: &HexModes,
    rot: &Quat,
    lam: &ElementMultipliers,
) -> [Vec3; CORNERS] {
    let h = rest.size;
    let g = multiplier_direction(&element_gradient(x, h), rot, &lam.hyper);
    let r = Mat3::from_quat(*rot);
    std::array::from_fn(|j| {
        let mut d = g * gradient_weight(j, h);
        for m in 0..HOURGLASS_MODES {
            d += lam.hourglass[m] * (r * modes.vectors[m][j]);
        }
        w[j] * d
    })
}

/// The first Piola–Kirchhoff stress (Pa) of the fixed-corotated energy at deformation
/// gradient `f` with rotation `r ≈ polar(F)`: `P = 2μ R (sym(Rᵀ F) − I) + λ (J − 1) cof F`.
/// With the exact polar rotation this is Stomakhin et al. 2012's `2μ (F − R) + λ (J − 1)
/// cof F`; taking the symmetric part makes it insensitive (to first order) to an
/// approximate `R`, whose error would otherwise be a spurious stress as large as the
/// strain itself at small strains.
#[inline]
pub fn corotated_stress(f: &Mat3, r: &Mat3, mat: &Hyperelastic) -> Mat3 {
    let rtf = r.transpose() * *f;
    let e = (rtf + rtf.transpose()) * 0.5 - Mat3::IDENTITY;
    *r * e * (2.0 * mat.mu)
        + super::constraints::cofactor(f) * (mat.lambda * (f.determinant() - 1.0))
}

/// The elastic force on corner `corner` (N) and that corner's 3 × 3 stiffness block
/// (N/m, a positive definite approximation) of one element at corner positions `x`:
/// the centre's fixed-corotated stress ([`corotated_stress`]) giving `f_j = −V P b_j`, with block `V (2μ |b_j|² I + λ (cof F b_j)(cof F b_j)ᵀ)`
/// (R and the cofactor's own change frozen), and the hourglass modes'
/// `f_j = −Σ_m k_m c_m R g_mj`, block `Σ_m k_m (R g_mj)(R g_mj)ᵀ`. `rot` warm-starts and
/// receives `R = polar(F)`. What vertex block descent (Chen et al. 2024, "Vertex Block
/// Descent") needs per element of a vertex.
pub fn corner_force(
    x: &[Vec3; CORNERS],
    corner: usize,
    rest: &ElementRest,
    mat: &Hyperelastic,
    modes: &HexModes,
    rot: &mut Quat,
    rotation_iterations: u32,
) -> (Vec3, Mat3) {
    let h = rest.size;
    let f = element_gradient(x, h);
    super::constraints::extract_rotation(&f, rot, rotation_iterations);
    let r = Mat3::from_quat(*rot);
    let cof = super::constraints::cofactor(&f);
    let p = corotated_stress(&f, &r, mat);
    let b = gradient_weight(corner, h);
    let v = rest.volume;
    let mut force = -(p * b) * v;
    let cb = cof * b;
    let mut hess = Mat3::from_diagonal(Vec3::splat(2.0 * mat.mu * b.length_squared() * v))
        + outer(cb, cb) * (mat.lambda * v);
    let scale = rest.hourglass_scale();
    let rt = r.transpose();
    let o = x[0];
    for m in 0..HOURGLASS_MODES {
        let k = modes.stiffness[m] * scale;
        let gm = &modes.vectors[m];
        let mut c = 0.0;
        for (q, &xq) in x.iter().enumerate() {
            c += gm[q].dot(rt * (xq - o));
        }
        let rg = r * gm[corner];
        force -= rg * (k * c);
        hess += outer(rg, rg) * k;
    }
    (force, hess)
}

/// Linearised energy of an element at small displacements `u` (m) of its corners:
/// `½ V ε:C:ε + ½ Σ_m k_m (V/h²) c_m²` with `ε = sym(Σ_j u_j b_jᵀ)` (J). Equal to
/// `½ uᵀ (h V/h³) K u` with `K` = [`cube_stiffness`]; for tests and the static solve.
pub fn linear_energy(
    u: &[Vec3; CORNERS],
    rest: &ElementRest,
    mat: &Hyperelastic,
    modes: &HexModes,
) -> f64 {
    let h = rest.size;
    let mut grad = DMat3::ZERO;
    for (j, uj) in u.iter().enumerate() {
        let b = gradient_weight(j, h).as_dvec3();
        let uj = uj.as_dvec3();
        grad += DMat3::from_cols(uj * b.x, uj * b.y, uj * b.z);
    }
    let eps = (grad + grad.transpose()) * 0.5;
    let tr = eps.x_axis.x + eps.y_axis.y + eps.z_axis.z;
    let ee =
        eps.x_axis.length_squared() + eps.y_axis.length_squared() + eps.z_axis.length_squared();
    let psi = mat.mu as f64 * ee + 0.5 * mat.lambda as f64 * tr * tr;
    let mut e = rest.volume as f64 * psi;
    let scale = rest.hourglass_scale() as f64;
    for m in 0..HOURGLASS_MODES {
        let c: f64 = (0..CORNERS)
            .map(|j| modes.vectors[m][j].as_dvec3().dot(u[j].as_dvec3()))
            .sum();
        e += 0.5 * modes.stiffness[m] as f64 * scale * c * c;
    }
    e
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rest_cube(h: f32) -> ElementRest {
        ElementRest::new(Vec3::ZERO, h, h * h * h, &[1.0; CORNERS], &[1; CORNERS])
    }

    /// Deterministic pseudo-random numbers in [-1, 1].
    fn noise(seed: &mut u64) -> f32 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*seed >> 33) as f64 / (1u64 << 31) as f64 * 2.0 - 1.0) as f32
    }

    #[test]
    fn gradient_is_exact_for_affine_motion() {
        let h = 0.01;
        let a = Mat3::from_cols_array(&[1.1, 0.2, -0.1, 0.05, 0.9, 0.3, -0.2, 0.1, 1.2]);
        let t = Vec3::new(0.3, -0.2, 5.0);
        let x: [Vec3; CORNERS] = std::array::from_fn(|j| a * (corner_sign(j) * 0.5 * h) + t);
        let f = element_gradient(&x, h);
        assert!((f - a).abs_diff_eq(Mat3::ZERO, 1e-4), "{f} vs {a}");
    }

    #[test]
    fn hourglass_modes_are_orthogonal_to_affine_motion() {
        let modes = HexModes::new(1.0, 1.5);
        for m in 0..HOURGLASS_MODES {
            let sum: Vec3 = modes.vectors[m].iter().copied().sum();
            assert!(sum.length() < 1e-5, "mode {m} moves the centre");
            for axis in 0..3 {
                let mut lin = Vec3::ZERO;
                for j in 0..CORNERS {
                    lin += modes.vectors[m][j] * corner_sign(j)[axis];
                }
                assert!(lin.length() < 1e-5, "mode {m} sees a linear field");
            }
            assert!((modes.norm2[m] - 8.0).abs() < 1e-4);
            assert!(modes.stiffness[m] > 0.0);
        }
    }

    /// The split energy (centre + hourglass modes) is the incompatible-mode element's
    /// `½ uᵀ K u` for arbitrary small corner displacements.
    #[test]
    fn split_energy_equals_incompatible_element() {
        for &(e, nu) in &[(1.0e5f32, 0.3f32), (2.0e4, 0.49), (1.0e3, 0.0)] {
            let mat = Hyperelastic::new(e, nu);
            let modes = HexModes::of(&mat);
            let h = 0.02f32;
            let rest = rest_cube(h);
            let k = cube_stiffness(mat.mu as f64, mat.lambda as f64);
            let mut seed = 7u64;
            for _ in 0..5 {
                let u: [Vec3; CORNERS] = std::array::from_fn(|_| {
                    Vec3::new(noise(&mut seed), noise(&mut seed), noise(&mut seed)) * 1e-4
                });
                let flat: Vec<f64> = u.iter().flat_map(|v| v.to_array()).map(f64::from).collect();
                let mut quad = 0.0;
                for i in 0..24 {
                    for j in 0..24 {
                        quad += flat[i] * k[i * 24 + j] * flat[j];
                    }
                }
                let expected = 0.5 * h as f64 * quad;
                let got = linear_energy(&u, &rest, &mat, &modes);
                assert!(
                    (got - expected).abs() <= 1e-4 * expected.abs(),
                    "E {e} ν {nu}: {got} vs {expected}"
                );
            }
        }
    }

    /// Pure bending of a cube (`u_x = κ x y`, with the Poisson terms an element can hold)
    /// costs the continuum's energy `½ E κ² ∫y² dV` up to the Poisson coupling: the
    /// hourglass modes are not a zero-energy mode and not locked in shear.
    #[test]
    fn bending_mode_has_the_beam_energy() {
        let (e, nu) = (1.0e5f32, 0.0f32);
        let mat = Hyperelastic::new(e, nu);
        let modes = HexModes::of(&mat);
        let h = 0.01f32;
        let rest = rest_cube(h);
        let kappa = 1.0f32;
        let u: [Vec3; CORNERS] = std::array::from_fn(|j| {
            let p = corner_sign(j) * 0.5 * h;
            Vec3::new(-kappa * p.x * p.y, 0.5 * kappa * p.x * p.x, 0.0)
        });
        let got = linear_energy(&u, &rest, &mat, &modes);
        // ∫ y² dV over the cube = h² / 12 · h³.
        let exact = 0.5 * e as f64 * (kappa as f64).powi(2) * (h as f64).powi(5) / 12.0;
        assert!(
            (got - exact).abs() < 1e-3 * exact,
            "bending energy {got} vs beam {exact}"
        );
    }

    /// Repeated solves of a squeezed element conserve momentum and converge to a state
    /// whose hourglass coordinates are zero (a homogeneous squeeze has no hourglass).
    #[test]
    fn element_solve_recovers_rest_shape() {
        let mat = Hyperelastic::new(5.0e4, 0.3);
        let modes = HexModes::of(&mat);
        let h = 0.01f32;
        let rest = rest_cube(h);
        let mut seed = 3u64;
        let mut x: [Vec3; CORNERS] = std::array::from_fn(|j| {
            corner_sign(j) * 0.5 * h
                + Vec3::new(noise(&mut seed), noise(&mut seed), noise(&mut seed)) * 0.1 * h
        });
        let momentum0: Vec3 = x.iter().copied().sum();
        let mut rot = Quat::IDENTITY;
        let s = ElementSolve {
            material: &mat,
            modes: &modes,
            h2: 1.0,
            scale: 1.0,
            rotation_iterations: 4,
            dead_band: 0.0,
            split: false,
        };
        for _ in 0..200 {
            let mut lam = ElementMultipliers::ZERO;
            solve_element(&mut x, &[1.0; CORNERS], &rest, &s, &mut rot, &mut lam);
        }
        let momentum: Vec3 = x.iter().copied().sum();
        assert!((momentum - momentum0).length() < 1e-6);
        // Back to a rigid placement of the rest cube: all edge lengths h.
        for j in 0..CORNERS {
            for b in 0..3 {
                let k = j ^ (1 << b);
                let d = (x[j] - x[k]).length();
                assert!((d - h).abs() < 1e-3 * h, "edge {j}-{k}: {d}");
            }
        }
    }

    /// The factored operator is the incompatible-mode stiffness: the hourglass block has
    /// no entries outside the coupled pairs, triple and singles, and `K x` agrees with
    /// the 24 × 24 matrix for random corner values, for soft and nearly incompressible
    /// materials.
    #[test]
    fn cube_operator_is_the_cube_stiffness() {
        for (e, nu) in [(1.0e3f32, 0.3f32), (1.0e5, 0.45), (1.0e6, 0.49)] {
            let mat = Hyperelastic::new(e, nu);
            let (mu, lambda) = (mat.mu as f64, mat.lambda as f64);
            let k = cube_stiffness(mu, lambda);
            let q = hourglass_block(&k);
            let n = HOURGLASS_MODES;
            let mut coupled = vec![false; n * n];
            let mut couple = |u: (usize, usize), v: (usize, usize)| {
                coupled[(3 * u.0 + u.1) * n + 3 * v.0 + v.1] = true;
                coupled[(3 * v.0 + v.1) * n + 3 * u.0 + u.1] = true;
            };
            for [u, v] in HOURGLASS_PAIRS {
                couple(u, u);
                couple(u, v);
                couple(v, v);
            }
            for &u in &HOURGLASS_TRIPLE {
                for &v in &HOURGLASS_TRIPLE {
                    couple(u, v);
                }
            }
            for i in 0..3 {
                couple((3, i), (3, i));
            }
            let big = q.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            for (at, v) in q.iter().enumerate() {
                if !coupled[at] {
                    assert!(v.abs() <= 1e-12 * big, "entry {at}: {v} of {big}");
                }
            }
            let op = CubeOperator::of(&mat);
            let mut seed = 7u64;
            for _ in 0..20 {
                let x: [Vec3; CORNERS] = std::array::from_fn(|_| {
                    Vec3::new(noise(&mut seed), noise(&mut seed), noise(&mut seed))
                });
                let got = op.apply(&x);
                let scale: f64 = k.iter().fold(0.0, |m, v| m.max(v.abs()));
                for a in 0..CORNERS {
                    for i in 0..3 {
                        let want: f64 = (0..24)
                            .map(|c| k[(3 * a + i) * 24 + c] * x[c / 3][c % 3] as f64)
                            .sum();
                        let d = (got[a][i] as f64 - want).abs();
                        assert!(
                            d <= 1e-5 * scale,
                            "E {e} ν {nu} row {a}.{i}: {} vs {want}",
                            got[a][i]
                        );
                    }
                }
            }
        }
    }

    /// `product` is `vᵀ K u` of the 24 × 24 matrix, for random vectors in a random
    /// frame (both vectors' moments turned by one rotation, as the solvers take them),
    /// and symmetric in `u`, `v`.
    #[test]
    fn cube_product_is_the_stiffness_bilinear_form() {
        for (e, nu) in [(1.0e3f32, 0.3f32), (1.0e6, 0.49)] {
            let mat = Hyperelastic::new(e, nu);
            let k = cube_stiffness(mat.mu as f64, mat.lambda as f64);
            let op = CubeOperator::of(&mat);
            let scale: f64 = k.iter().fold(0.0, |m, v| m.max(v.abs()));
            let mut seed = 11u64;
            for _ in 0..20 {
                let mut corners = || -> [Vec3; CORNERS] {
                    std::array::from_fn(|_| {
                        Vec3::new(noise(&mut seed), noise(&mut seed), noise(&mut seed))
                    })
                };
                let (u, v) = (corners(), corners());
                let axis = Vec3::new(noise(&mut seed), noise(&mut seed), 1.0).normalize();
                let r = Mat3::from_axis_angle(axis, 2.0 * noise(&mut seed));
                let rt = r.transpose();
                let turned = |x: &[Vec3; CORNERS]| {
                    let (g, q) = CubeOperator::moments(x);
                    (rt * g, q.map(|w| rt * w))
                };
                let ((gu, qu), (gv, qv)) = (turned(&u), turned(&v));
                let (su, ru) = op.response(&gu, &qu);
                let (sv, rv) = op.response(&gv, &qv);
                let got = CubeOperator::product(&su, &ru, &gv, &qv) as f64;
                let back = CubeOperator::product(&sv, &rv, &gu, &qu) as f64;
                // vᵀ K u of the matrix, with both vectors in the element's frame.
                let (ul, vl) = (u.map(|w| rt * w), v.map(|w| rt * w));
                let want: f64 = (0..24)
                    .map(|a| {
                        let row: f64 = (0..24)
                            .map(|c| k[a * 24 + c] * ul[c / 3][c % 3] as f64)
                            .sum();
                        row * vl[a / 3][a % 3] as f64
                    })
                    .sum();
                let size = 24.0 * scale;
                assert!((got - want).abs() <= 1e-5 * size, "E {e}: {got} vs {want}");
                assert!(
                    (back - want).abs() <= 1e-5 * size,
                    "E {e}: {back} vs {want}"
                );
            }
        }
    }
}

#[cfg(test)]
mod force_tests {
    use super::*;

    /// `corner_force` is the negative gradient of the element's energy (small strain:
    /// the incompatible-mode stiffness times the displacement).
    #[test]
    fn corner_force_matches_the_linear_stiffness() {
        let mat = Hyperelastic::new(1.0e5, 0.3);
        let modes = HexModes::of(&mat);
        let h = 0.01f32;
        let rest = ElementRest::new(Vec3::ZERO, h, h * h * h, &[1.0; CORNERS], &[1; CORNERS]);
        let k = cube_stiffness(mat.mu as f64, mat.lambda as f64);
        let u: [Vec3; CORNERS] = std::array::from_fn(|j| {
            Vec3::new(
                (j as f32 * 0.37).sin(),
                (j as f32 * 1.1).cos(),
                (j as f32 * 0.7).sin(),
            ) * 1e-5
        });
        let x: [Vec3; CORNERS] = std::array::from_fn(|j| corner_sign(j) * 0.5 * h + u[j]);
        for corner in 0..CORNERS {
            let mut rot = Quat::IDENTITY;
            let (f, _) = corner_force(&x, corner, &rest, &mat, &modes, &mut rot, 8);
            let mut lin = DVec3::ZERO;
            for q in 0..CORNERS {
                for i in 0..3 {
                    for l in 0..3 {
                        lin[i] += h as f64 * k[(3 * corner + i) * 24 + 3 * q + l] * u[q][l] as f64;
                    }
                }
            }
            let f = f.as_dvec3();
            assert!(
                (f + lin).length() < 0.02 * lin.length(),
                "corner {corner}: force {f} vs -K u {}",
                -lin
            );
        }
    }
}
