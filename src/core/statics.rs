//! Static equilibrium of a model's linearised elastic energy, in f64: the answer the
//! dynamic solver settles to under small loads, found directly by conjugate gradients
//! instead of thousands of damped steps. For accuracy studies (resolution convergence
//! against [`super::fem`]'s reference) at sizes the time stepper would take far too long
//! to settle, and to check that the time stepper does settle there.
//!
//! The energy is the small-strain limit of each body's hyperelastic material
//! (`Ψ = μ ‖ε‖² + λ/2 (tr ε)²`, the linearisation of [`super::constraints::Hyperelastic`]):
//! * a [`Discretisation::Lattice`] body: each element's
//!   `½ uᵀ K u` with `K` = (`V/h²`) × [`cube_stiffness`] (its centre gradient and
//!   hourglass modes, [`super::element`]);
//! * a [`Discretisation::Clusters`] body: `Σ_c V_c Ψ(ε_c)` with `ε_c = sym(Σ_j u_j b_jᵀ)`,
//!   `b_j = m_j A_qq⁻¹ q_j` (each cluster's least-squares gradient).
//!
//! Loads are gravity on the particle masses; particles are held by the model's pins and
//! by [`StaticLoad::constraints`] (a per-axis prescribed displacement: a frictionless
//! plate holds one axis).

use super::element::cube_stiffness;
use super::error::TissueError;
use super::fem::{SymOperator, pcg};
use super::model::{Discretisation, Material, Model};
use glam::{DMat3, DVec3};

/// What loads and holds a model in [`solve_static`].
#[derive(Debug, Clone, Default, PartialEq)]
pub struct StaticLoad {
    /// Gravity, m/s², acting on every particle's mass.
    pub gravity: DVec3,
    /// Extra per-axis constraints: (particle, which axes are held, their displacement
    /// in m). Pinned particles are held at zero displacement on every axis.
    pub constraints: Vec<(u32, [bool; 3], DVec3)>,
}

/// Result of [`solve_static`].
#[derive(Debug, Clone, PartialEq)]
pub struct StaticSolution {
    /// Displacement of every particle from its rest position, m.
    pub displacement: Vec<DVec3>,
    /// Conjugate-gradient iterations taken.
    pub iterations: usize,
}

/// The linearised stiffness of every body of a model, applied without assembling it.
struct ModelOperator<'a> {
    model: &'a Model,
    /// Per body: Lamé μ, λ (Pa).
    lame: Vec<(f64, f64)>,
    /// Per body: the incompatible-mode cube stiffness of a 1 m cube (lattice bodies).
    cube: Vec<Option<Vec<f64>>>,
    threads: usize,
}

impl<'a> ModelOperator<'a> {
    fn new(model: &'a Model) -> Result<Self, TissueError> {
        let mut lame = Vec::new();
        let mut cube = Vec::new();
        for b in &model.bodies {
            let Material::Hyperelastic {
                youngs_modulus,
                poisson_ratio,
            } = b.material
            else {
                return Err(TissueError::InvalidParameter {
                    name: "material",
                    value: "shape matching".into(),
                    expected: "hyperelastic bodies (shape matching has no modulus)",
                });
            };
            let (mu, la) = super::constraints::lame(youngs_modulus, poisson_ratio);
            let (mu, la) = (mu as f64, la as f64);
            lame.push((mu, la));
            cube.push(
                (b.discretisation == Discretisation::Lattice).then(|| cube_stiffness(mu, la)),
            );
        }
        Ok(Self {
            model,
            lame,
            cube,
            threads: super::par::default_threads(),
        })
    }

    /// Cluster `c`'s gradient weights `b_j` (1/m) and members, or None for an empty run.
    fn cluster_weights(&self, c: usize) -> Option<(&[u32], Vec<DVec3>)> {
        let m = self.model;
        let members = m.members(c);
        if members.is_empty() {
            return None;
        }
        let r = &m.cluster_rest[c];
        let inv = r.aqq_inv.as_dmat3();
        let com = r.com.as_dvec3();
        let b = members
            .iter()
            .map(|&j| inv * ((m.rest[j as usize].as_dvec3() - com) * m.mass[j as usize] as f64))
            .collect();
        Some((members, b))
    }

    /// Adds the operator's action on `x` for clusters `cs` and elements `es` into `y`.
    fn apply_range(
        &self,
        x: &[f64],
        y: &mut [f64],
        cs: std::ops::Range<usize>,
        es: std::ops::Range<usize>,
    ) {
        let m = self.model;
        let get = |j: u32| {
            let k = 3 * j as usize;
            DVec3::new(x[k], x[k + 1], x[k + 2])
        };
        for c in cs {
            let Some((members, b)) = self.cluster_weights(c) else {
                continue;
            };
            let (mu, la) = self.lame[m.particle_body[c] as usize];
            let mut g = DMat3::ZERO;
            for (&j, bj) in members.iter().zip(&b) {
                let u = get(j);
                g += DMat3::from_cols(u * bj.x, u * bj.y, u * bj.z);
            }
            let eps = (g + g.transpose()) * 0.5;
            let tr = eps.x_axis.x + eps.y_axis.y + eps.z_axis.z;
            let sigma = eps * (2.0 * mu) + DMat3::from_diagonal(DVec3::splat(la * tr));
            let v = m.cluster_volume[c] as f64;
            for (&j, bj) in members.iter().zip(&b) {
                let f = sigma * *bj * v;
                let k = 3 * j as usize;
                y[k] += f.x;
                y[k + 1] += f.y;
                y[k + 2] += f.z;
            }
        }
        for e in es {
            let body = m.element_body[e] as usize;
            let Some(k) = &self.cube[body] else {
                continue;
            };
            let r = &m.element_rest[e];
            let scale = r.volume as f64 / (r.size as f64 * r.size as f64);
            let nodes = m.elements[e];
            let mut u = [0.0f64; 24];
            for (a, &j) in nodes.iter().enumerate() {
                let v = get(j);
                u[3 * a] = v.x;
                u[3 * a + 1] = v.y;
                u[3 * a + 2] = v.z;
            }
            for (a, &j) in nodes.iter().enumerate() {
                for i in 0..3 {
                    let row = &k[(3 * a + i) * 24..(3 * a + i + 1) * 24];
                    let s: f64 = row.iter().zip(&u).map(|(kk, uu)| kk * uu).sum();
                    y[3 * j as usize + i] += scale * s;
                }
            }
        }
    }
}

impl SymOperator for ModelOperator<'_> {
    fn dofs(&self) -> usize {
        3 * self.model.particle_count()
    }

    fn apply(&self, x: &[f64], y: &mut [f64]) {
        y.iter_mut().for_each(|v| *v = 0.0);
        let (nc, ne) = (self.model.particle_count(), self.model.elements.len());
        let t = self.threads.max(1);
        if t == 1 || nc + ne < 4096 {
            self.apply_range(x, y, 0..nc, 0..ne);
            return;
        }
        // Each thread accumulates its share of clusters and elements into its own
        // buffer (their supports overlap), then the buffers are summed.
        let parts: Vec<Vec<f64>> = std::thread::scope(|scope| {
            let handles: Vec<_> = (0..t)
                .map(|i| {
                    let (c0, c1) = (nc * i / t, nc * (i + 1) / t);
                    let (e0, e1) = (ne * i / t, ne * (i + 1) / t);
                    let len = y.len();
                    scope.spawn(move || {
                        let mut buf = vec![0.0; len];
                        self.apply_range(x, &mut buf, c0..c1, e0..e1);
                        buf
                    })
                })
                .collect();
            handles
                .into_iter()
                .map(|h| h.join().unwrap_or_default())
                .collect()
        });
        for p in parts {
            for (a, b) in y.iter_mut().zip(&p) {
                *a += b;
            }
        }
    }

    fn block_diagonal(&self) -> Vec<[f64; 9]> {
        let m = self.model;
        let mut out = vec![[0.0; 9]; m.particle_count()];
        for c in 0..m.particle_count() {
            let Some((members, b)) = self.cluster_weights(c) else {
                continue;
            };
            let (mu, la) = self.lame[m.particle_body[c] as usize];
            let v = m.cluster_volume[c] as f64;
            for (&j, bj) in members.iter().zip(&b) {
                // Bᵀ D B for one node: μ |b|² I + (μ + λ) b bᵀ.
                let blk = &mut out[j as usize];
                for r in 0..3 {
                    for s in 0..3 {
                        let id = if r == s {
                            mu * bj.length_squared()
                        } else {
                            0.0
                        };
                        blk[3 * r + s] += v * (id + (mu + la) * bj[r] * bj[s]);
                    }
                }
            }
        }
        for e in 0..m.elements.len() {
            let Some(k) = &self.cube[m.element_body[e] as usize] else {
                continue;
            };
            let r = &m.element_rest[e];
            let scale = r.volume as f64 / (r.size as f64 * r.size as f64);
            for (a, &j) in m.elements[e].iter().enumerate() {
                let blk = &mut out[j as usize];
                for r in 0..3 {
                    for s in 0..3 {
                        blk[3 * r + s] += scale * k[(3 * a + r) * 24 + 3 * a + s];
                    }
                }
            }
        }
        out
    }
}

/// Solves the linearised statics of `model` under `load` to a relative residual `tol`:
/// the displacement of every particle at equilibrium. Fails on shape-matching bodies
/// (no modulus), on a model nothing holds (a free body has rigid modes: no equilibrium
/// under gravity), or when conjugate gradients do not converge.
pub fn solve_static(
    model: &Model,
    load: &StaticLoad,
    tol: f64,
) -> Result<StaticSolution, TissueError> {
    let op = ModelOperator::new(model)?;
    let n = model.particle_count();
    let mut b = vec![0.0; 3 * n];
    for (i, &m) in model.mass.iter().enumerate() {
        let f = load.gravity * m as f64;
        b[3 * i] = f.x;
        b[3 * i + 1] = f.y;
        b[3 * i + 2] = f.z;
    }
    let mut fixed = vec![false; 3 * n];
    let mut x = vec![0.0; 3 * n];
    for &i in &model.pinned {
        fixed[3 * i as usize..3 * i as usize + 3].fill(true);
    }
    for &(i, axes, value) in &load.constraints {
        let i = i as usize;
        if i >= n {
            return Err(TissueError::InvalidParameter {
                name: "constraints",
                value: format!("particle {i}"),
                expected: "particle indices of the model",
            });
        }
        for a in 0..3 {
            if axes[a] {
                fixed[3 * i + a] = true;
                x[3 * i + a] = value[a];
            }
        }
    }
    if !fixed.iter().any(|&f| f) {
        return Err(TissueError::InvalidParameter {
            name: "constraints",
            value: "nothing held".into(),
            expected: "pins or constraints that hold the model (a free body has no equilibrium)",
        });
    }
    let max_iter = (3 * n).clamp(1000, 200_000);
    let iterations = pcg(&op, &b, &mut x, &fixed, tol, max_iter, None).map_err(|e| {
        TissueError::InvalidParameter {
            name: "static solve",
            value: e.to_string(),
            expected: "a model held so that it has an equilibrium",
        }
    })?;
    Ok(StaticSolution {
        displacement: x
            .chunks_exact(3)
            .map(|c| DVec3::new(c[0], c[1], c[2]))
            .collect(),
        iterations,
    })
}
