//! Geometric multigrid on the lattice of [`super::model::Discretisation::Lattice`] bodies:
//! the linear solve inside each Newton iteration of an implicit-Euler substep.
//!
//! A substep seeks `y` with `M/h² (y − x̃) = f(y)` (`x̃ = x + h v + h² g`). Each Newton
//! iteration solves `A δ = r` with the residual `r = M/h² (x̃ − y) + f(y)` and
//! `A = M/h² + K`, `K` the elements' corotated stiffness (each element's
//! incompatible-mode stiffness [`super::element::cube_stiffness`] turned by the
//! element's rotation `R = polar(F)`), then sets `y ← y + δ`. The solve is one V-cycle
//! (Briggs, Henson & McCormick, "A Multigrid Tutorial", 2000): smoothing on each level
//! ([`Smoother`]: Chebyshev-accelerated block Jacobi or colour-ordered Gauss–Seidel), the residual restricted to the next coarser lattice (cells of 2 × 2 × 2,
//! restriction = transposed trilinear prolongation), the coarse operator re-discretised
//! with the same element at twice the edge (so a coarse level carries bending as well as
//! the fine one), the coarse correction prolongated back. The hierarchy only speeds the
//! solve: when `r = 0` every correction is zero, so the fine level's equilibrium is the
//! answer with or without it.

use super::constraints::{Hyperelastic, extract_rotation};
use super::element::corotated_stress;
use super::element::{CORNERS, CubeOperator, cube_stiffness, element_gradient};
use super::error::TissueError;
use super::model::{Discretisation, Material, Model};
use glam::{DMat3, DVec3, IVec3, Mat3, Quat, Vec3};
use std::collections::HashMap;

/// One level of the lattice hierarchy (level 0 is the model's own elements).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MgLevel {
    /// Node (particle) count of the level.
    pub nodes: usize,
    /// Each element's corner nodes ([`super::element::corner_sign`] order).
    pub elements: Vec<[u32; CORNERS]>,
    /// Each element's body.
    pub body: Vec<u32>,
    /// Where each body's nodes start on this level, and where the last ends (bodies + 1
    /// entries; a body's nodes are contiguous). The coarse corrections' steps and the
    /// conjugate gradients' scalars are each body's own, over these ranges, so that a body
    /// steps as it would alone.
    pub body_start: Vec<u32>,
    /// Each element's stiffness scale `V / h²` (m): its stiffness is this times the
    /// body's unit-cube stiffness.
    pub scale: Vec<f32>,
    /// CSR offsets of each node's elements.
    pub inv_start: Vec<u32>,
    /// Elements of each node as `element << 3 | corner`.
    pub inv: Vec<u32>,
    /// Lumped mass of each node, kg (level 0: the particles'; coarser: restricted).
    pub mass: Vec<f32>,
    /// Nodes held at zero correction (pins; nodes of bodies without elements).
    pub fixed: Vec<bool>,
    /// Prolongation from the next coarser level: CSR offsets per node of this level.
    pub prolong_start: Vec<u32>,
    /// Coarse node of each prolongation weight.
    pub prolong_node: Vec<u32>,
    /// Prolongation weights (per node they sum to 1).
    pub prolong_weight: Vec<f32>,
    /// Coarse levels: each element's unrotated stiffness (row-major 24 × 24 per element,
    /// N/m), the Galerkin product `Σ Pᵀ K P` of the finer elements inside it (`P` the
    /// cell's trilinear interpolation), so that a cell the body fills only in part is as
    /// stiff as that part. Empty on level 0 (its elements use the body's unit-cube
    /// stiffness times `scale`).
    pub stiffness: Vec<f32>,
    /// `stiffness` as 3 × 3 blocks, 64 per element (corner `a`, corner `b` at
    /// `64 e + 8 a + b`): what the V-cycle reads.
    pub blocks: Vec<Mat3>,
    /// For each element of the next coarser level, the elements of this level inside it
    /// (CSR: `child_start`, `child`); their rotations average to the coarse one.
    pub child_start: Vec<u32>,
    /// See `child_start`.
    pub child: Vec<u32>,
    /// The level's nodes in Gauss–Seidel order: by colour (the parity of the node's
    /// lattice coordinates, `x & 1 | (y & 1) << 1 | (z & 1) << 2`), ascending within a
    /// colour. Two nodes of one colour never share an element, so a colour's updates are
    /// independent: the GPU smooths a colour at once and gets the same answer.
    pub order: Vec<u32>,
    /// Where each colour starts in `order` (colour `c`: `colour_start[c]..colour_start[c + 1]`).
    pub colour_start: [u32; COLOURS + 1],
}

/// Gauss–Seidel colours of a hexahedral lattice (node coordinate parities).
pub const COLOURS: usize = 8;

/// How the V-cycle smooths each level.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Smoother {
    /// Block Gauss–Seidel in colour order ([`MgLevel::order`]): each node's 3 × 3 block
    /// solved in turn, the eight colours one after another.
    GaussSeidel,
    /// Chebyshev-accelerated block Jacobi (Golub & Varga 1961; as a multigrid smoother,
    /// Adams et al. 2003, "Parallel multigrid smoothing: polynomial versus Gauss–Seidel";
    /// for simulation, Wang 2015, "A Chebyshev semi-iterative approach for accelerating
    /// projective and position-based dynamics"): every node updated at once from the
    /// last sweep's values, `x̂ = x_k + D⁻¹ (b − A x_k) / θ`,
    /// `x_{k+1} = ω_{k+1} (x̂ − x_{k−1}) + x_{k−1}`, with `θ` and `ω` from the interval
    /// `[λ_max / 10, 1.1 λ_max]` of `D⁻¹ A` ([`LatticeMultigrid::chebyshev`]). One
    /// parallel pass a sweep where Gauss–Seidel needs eight, in pairs (the [`Sweeps`]
    /// counts rounded up to even). At the default Newton iteration (conjugate gradients
    /// over two V-cycles) it is as accurate as [`Smoother::Hybrid`] on a cantilever and
    /// takes fewer GPU passes. On the finest level, where contacts add stiff penalties
    /// to single nodes, the damped polynomial updates alone would leave part of a
    /// penalty unresolved (a box dropped on another would never come to rest), so each
    /// run of sweeps there ends in one block-Jacobi pass over the nodes that carry a
    /// contact penalty, each solving its own block whole from the sweeps' result. The
    /// default (BENCHMARKS.md compares the smoothers).
    #[default]
    Chebyshev,
    /// Gauss–Seidel on the finest level (each node's block, its contact penalties
    /// included, solved exactly in turn) and Chebyshev on the coarse levels (small,
    /// where a pass's fixed cost dominates and eight per sweep add up). As accurate as
    /// [`Smoother::Chebyshev`] and as good at contacts, but eight passes a sweep on the
    /// largest level.
    Hybrid,
}

impl Smoother {
    /// The smoother used on level `l` (0 the finest).
    pub fn on_level(self, l: usize) -> Smoother {
        match self {
            Smoother::Hybrid if l == 0 => Smoother::GaussSeidel,
            Smoother::Hybrid => Smoother::Chebyshev,
            s => s,
        }
    }
}

/// Power iterations of the estimate of `λ_max(D⁻¹ K)` per level.
const POWER_ITERATIONS: usize = 12;
/// The Chebyshev interval: `[λ / CHEBYSHEV_RATIO, CHEBYSHEV_MARGIN λ]`, `λ` the estimate.
const CHEBYSHEV_MARGIN: f32 = 1.1;
/// See [`CHEBYSHEV_MARGIN`].
const CHEBYSHEV_RATIO: f32 = 10.0;

/// The weight `ω_{k+1}` of Chebyshev sweep `k` (0-based) for an iteration whose spectral
/// radius squared is `rho2`: `ω_1 = 1`, `ω_2 = 2 / (2 − ρ²)`, `ω_{k+1} = 4 / (4 − ρ² ω_k)`
/// (Golub & Varga 1961).
pub fn chebyshev_weight(k: u32, rho2: f32) -> f32 {
    let mut w = 1.0f32;
    for i in 1..=k {
        w = if i == 1 {
            2.0 / (2.0 - rho2)
        } else {
            4.0 / (4.0 - rho2 * w)
        };
    }
    w
}

/// `order` and `colour_start` of [`MgLevel`] for nodes at lattice coordinates `coords`.
fn colour_order(coords: &[IVec3]) -> (Vec<u32>, [u32; COLOURS + 1]) {
    let colour = |c: &IVec3| (c.x & 1 | (c.y & 1) << 1 | (c.z & 1) << 2) as usize;
    let mut start = [0u32; COLOURS + 1];
    for c in coords {
        start[colour(c) + 1] += 1;
    }
    for k in 0..COLOURS {
        start[k + 1] += start[k];
    }
    let mut next = start;
    let mut order = vec![0u32; coords.len()];
    for (j, c) in coords.iter().enumerate() {
        let k = colour(c);
        order[next[k] as usize] = j as u32;
        next[k] += 1;
    }
    (order, start)
}

/// The lattice hierarchy of a model and the per-body unit-cube stiffnesses.
#[derive(Debug, Clone, Default)]
pub struct LatticeMultigrid {
    /// Levels, finest first.
    pub levels: Vec<MgLevel>,
    /// Per body: the unit-cube stiffness (24 × 24, N/m) of its material, if a lattice
    /// body.
    pub unit: Vec<Option<Vec<f32>>>,
    /// `unit` as 3 × 3 blocks (64 per body, `8 a + b`).
    pub unit_blocks: Vec<Option<Vec<Mat3>>>,
    /// Per body: `unit` in factored form, which level 0's rows are applied with.
    pub unit_operator: Vec<Option<CubeOperator>>,
    /// Per body: its material's Lamé parameters.
    pub material: Vec<Option<Hyperelastic>>,
    /// The smoother of every level.
    pub smoother: Smoother,
    /// Per level: the Chebyshev smoother's `1/θ` and `ρ²` (`θ` the centre of the
    /// interval the smoother damps, `ρ` the damped Jacobi iteration's spectral radius on
    /// it), from a power-iteration estimate of `λ_max(D⁻¹ K)` at rest, `D` the diagonal
    /// blocks (the mass only lowers it).
    pub chebyshev: Vec<[f32; 2]>,
}

/// Most levels a hierarchy has.
pub const MAX_LEVELS: usize = 8;
/// A hierarchy is coarsened while its bodies have more than this many nodes each (on
/// average) on its coarsest level ([`EXACT_COARSEST`] instead where the coarsest level is
/// to be solved exactly, [`Sweeps::min_nodes`]).
pub const MIN_NODES: usize = 64;
/// Most nodes a body may have on the coarsest level for that level to be solved exactly
/// ([`Sweeps::exact_coarsest`]): 84 unknowns, whose packed factor bordered by the
/// right-hand side (14.3 KiB) the GPU keeps in one workgroup's memory within the 16 KiB
/// WebGPU guarantees.
pub const EXACT_COARSEST: usize = 28;

/// One body's lattice hierarchy, built on its own: the part of a [`LatticeMultigrid`]
/// that depends on that body alone. [`LatticeMultigrid::from_bodies`] joins such parts
/// into the hierarchy of a model of those bodies (the same hierarchy as
/// [`LatticeMultigrid::new`] builds for it), so that a body coming, going or changing
/// costs its own part, not every body's.
///
/// ```
/// use bevy_tissue::core::model::{BodyDesc, Discretisation, Material, Model};
/// use bevy_tissue::core::multigrid::{BodyLevels, LatticeMultigrid, MAX_LEVELS, MIN_NODES};
/// use bevy_tissue::core::{procedural, sampling::Resolution};
/// let desc = BodyDesc {
///     resolution: Resolution::Particles(300),
///     material: Material::Hyperelastic { youngs_modulus: 20e3, poisson_ratio: 0.45 },
///     discretisation: Discretisation::Lattice,
///     ..Default::default()
/// };
/// let mut one = Model::new();
/// one.add_body(&procedural::cuboid(glam::Vec3::splat(0.05), 1), &desc).unwrap();
/// // Built once per body (on a worker thread, say) ...
/// let part = BodyLevels::new(&one, 0);
/// // ... and joined for any model of such bodies.
/// let mut two = Model::new();
/// two.append(&one);
/// two.append(&one);
/// let joined = LatticeMultigrid::from_bodies(&[&part, &part], MIN_NODES, MAX_LEVELS);
/// let whole = LatticeMultigrid::new(&two, MIN_NODES, MAX_LEVELS);
/// assert_eq!(joined.levels.len(), whole.levels.len());
/// assert_eq!(joined.levels[0].nodes, two.particle_count());
/// ```
#[derive(Debug, Clone, Default)]
pub struct BodyLevels {
    /// The body's levels, finest first, coarsened [`MAX_LEVELS`] deep (a body without
    /// lattice elements has only its finest level, every node held). Element bodies are
    /// 0 and indices are the body's own.
    pub levels: Vec<MgLevel>,
    /// The unit-cube stiffness of the body's material (24 × 24, N/m), if a hyperelastic
    /// lattice body.
    pub unit: Option<Vec<f32>>,
    /// `unit` as 3 × 3 blocks (`8 a + b`).
    pub unit_blocks: Option<Vec<Mat3>>,
    /// `unit` in factored form, which level 0's rows are applied with.
    pub unit_operator: Option<CubeOperator>,
    /// The material's Lamé parameters.
    pub material: Option<Hyperelastic>,
    /// Per level: the Chebyshev smoother's `1/θ` and `ρ²` for this body alone (see
    /// [`LatticeMultigrid::chebyshev`]), estimated with the levels, so that appending
    /// the body to a world costs no power iteration.
    pub chebyshev: Vec<[f32; 2]>,
}

impl BodyLevels {
    /// The hierarchy of body `body` of `model`.
    pub fn new(model: &Model, body: usize) -> Self {
        // A model's elements are in body order.
        let erange = model.element_body.partition_point(|&b| (b as usize) < body)
            ..model
                .element_body
                .partition_point(|&b| (b as usize) <= body);
        let info = &model.bodies[body];
        let (unit, unit_blocks, unit_operator, material) =
            match (info.discretisation, info.material) {
                (
                    Discretisation::Lattice,
                    Material::Hyperelastic {
                        youngs_modulus,
                        poisson_ratio,
                    },
                ) => {
                    let mat = Hyperelastic::new(youngs_modulus, poisson_ratio);
                    let (mu, lambda) = (mat.mu as f64, mat.lambda as f64);
                    let k64 = cube_stiffness(mu, lambda);
                    let k: Vec<f32> = k64.iter().map(|&v| v as f32).collect();
                    let blocks = to_blocks(&k);
                    let op = CubeOperator::from_stiffness(mu, lambda, &k64);
                    (Some(k), Some(blocks), Some(op), Some(mat))
                }
                _ => (None, None, None, None),
            };
        let range = info.range();
        let (p0, e0) = (range.start, erange.start);
        let pinned: std::collections::HashSet<u32> = model
            .pinned
            .iter()
            .copied()
            .filter(|&p| range.contains(&(p as usize)))
            .collect();
        let mut fine = MgLevel {
            nodes: range.len(),
            elements: model.elements[erange.clone()]
                .iter()
                .map(|el| el.map(|j| j - p0 as u32))
                .collect(),
            body: vec![0; erange.len()],
            scale: model.element_rest[erange.clone()]
                .iter()
                .map(|r| r.hourglass_scale())
                .collect(),
            inv_start: vec![0],
            mass: model.mass[range.clone()].to_vec(),
            ..Default::default()
        };
        for i in range.clone() {
            let own = model.elements_of(i);
            let at = fine.inv.len();
            fine.inv
                .extend(own.iter().map(|&ec| ec - ((e0 as u32) << 3)));
            // A node's elements by where they lie around it (the node is corner `a` of
            // the element on its `7 − a` side), as the GPU's neighbour records take
            // them, so that both sum a row in one order.
            fine.inv[at..].sort_by_key(|&ec| std::cmp::Reverse(ec & 7));
            fine.inv_start.push(fine.inv.len() as u32);
            fine.fixed
                .push(own.is_empty() || pinned.contains(&(i as u32)));
        }
        // Integer lattice coordinates of the nodes.
        let mut coords = vec![IVec3::ZERO; range.len()];
        if info.discretisation == Discretisation::Lattice {
            let lo = model.rest[range.clone()]
                .iter()
                .fold(Vec3::splat(f32::MAX), |a, p| a.min(*p));
            for (c, p) in coords.iter_mut().zip(&model.rest[range.clone()]) {
                *c = ((*p - lo) / info.spacing).round().as_ivec3();
            }
        }
        (fine.order, fine.colour_start) = colour_order(&coords);
        let mut levels = vec![fine];
        let mut cell_origin: Vec<IVec3> = levels[0]
            .elements
            .iter()
            .map(|e| coords[e[0] as usize])
            .collect();
        let units = [unit.clone()];
        while levels.len() < MAX_LEVELS {
            let Some((mut coarse, origins, coarse_coords)) = coarsen(
                levels.last_mut().expect("a level"),
                &cell_origin,
                &coords,
                &units,
            ) else {
                break;
            };
            (coarse.order, coarse.colour_start) = colour_order(&coarse_coords);
            levels.push(coarse);
            cell_origin = origins;
            coords = coarse_coords;
        }
        for lv in &mut levels {
            lv.blocks = to_blocks(&lv.stiffness);
            lv.body_start = vec![0, lv.nodes as u32];
        }
        let mut out = Self {
            levels,
            unit,
            unit_blocks,
            unit_operator,
            material,
            chebyshev: Vec::new(),
        };
        out.chebyshev = LatticeMultigrid::joined(&[&out], out.levels.len()).chebyshev;
        out
    }
}

impl LatticeMultigrid {
    /// Builds the hierarchy of every lattice body of `model`, coarsening until a level
    /// has at most `min_nodes` nodes per body or stops shrinking (at most `max_levels`,
    /// itself at most [`MAX_LEVELS`]): each body's [`BodyLevels`], joined.
    pub fn new(model: &Model, min_nodes: usize, max_levels: usize) -> Self {
        let parts: Vec<BodyLevels> =
            super::par::map(model.bodies.len(), 0, |b| BodyLevels::new(model, b));
        let parts: Vec<&BodyLevels> = parts.iter().collect();
        Self::from_bodies(&parts, min_nodes, max_levels)
    }

    /// The hierarchy of a model made of `parts`' bodies in that order (each part built
    /// by [`BodyLevels::new`] from a model with that body): their levels joined, as deep
    /// as [`LatticeMultigrid::new`] would make it (coarsening while the bodies have more
    /// than `min_nodes` nodes each on average, and the level shrinks by half, at most
    /// `max_levels` deep).
    pub fn from_bodies(parts: &[&BodyLevels], min_nodes: usize, max_levels: usize) -> Self {
        Self::joined(parts, Self::depth_of(parts, min_nodes, max_levels))
    }

    /// How many levels [`LatticeMultigrid::from_bodies`] makes for `parts`.
    pub fn depth_of(parts: &[&BodyLevels], min_nodes: usize, max_levels: usize) -> usize {
        let nodes_at = |l: usize| -> usize {
            parts
                .iter()
                .map(|p| p.levels.get(l).map_or(0, |lv| lv.nodes))
                .sum()
        };
        let max_levels = max_levels.min(MAX_LEVELS);
        let mut depth = 1;
        while depth < max_levels {
            let last = nodes_at(depth - 1);
            if last / parts.len().max(1) <= min_nodes {
                break;
            }
            let coarser = parts.iter().any(|p| {
                p.levels
                    .get(depth - 1)
                    .is_some_and(|lv| !lv.elements.is_empty())
            });
            if !coarser {
                break;
            }
            depth += 1;
            if nodes_at(depth - 1) * 2 >= last {
                break;
            }
        }
        depth
    }

    /// [`LatticeMultigrid::joined`] without the Chebyshev estimates (`chebyshev` empty:
    /// the caller's to give, say from the parts' own [`BodyLevels::chebyshev`]).
    pub fn join(parts: &[&BodyLevels], depth: usize) -> Self {
        let depth = depth.clamp(1, MAX_LEVELS);
        Self {
            levels: (0..depth)
                .map(|l| join_level(parts, l, l + 1 < depth))
                .collect(),
            unit: parts.iter().map(|p| p.unit.clone()).collect(),
            unit_blocks: parts.iter().map(|p| p.unit_blocks.clone()).collect(),
            unit_operator: parts.iter().map(|p| p.unit_operator).collect(),
            material: parts.iter().map(|p| p.material).collect(),
            smoother: Smoother::default(),
            chebyshev: Vec::new(),
        }
    }

    /// `parts`' levels joined `depth` deep (at most [`MAX_LEVELS`]; a body with fewer
    /// levels has no nodes on the deeper ones), with their Chebyshev estimates: what a
    /// body appended to a hierarchy of that depth brings.
    pub fn joined(parts: &[&BodyLevels], depth: usize) -> Self {
        let mut mg = Self::join(parts, depth);
        mg.chebyshev = (0..mg.levels.len())
            .map(|l| {
                let b = CHEBYSHEV_MARGIN * mg.lambda_max(l).max(1.0);
                let a = b / CHEBYSHEV_RATIO;
                let (theta, delta) = (0.5 * (b + a), 0.5 * (b - a));
                let rho = delta / theta;
                [1.0 / theta, rho * rho]
            })
            .collect();
        mg
    }

    /// A power-iteration estimate of the largest eigenvalue of `D⁻¹ K` on level `l` at
    /// rest (unit rotations, no mass; held nodes out): the Rayleigh quotient
    /// `xᵀ K x / xᵀ D x` of the last iterate, a lower bound that approaches it.
    pub fn lambda_max(&self, l: usize) -> f32 {
        let lv = &self.levels[l];
        let mut diag = vec![Mat3::ZERO; lv.nodes];
        for (e, el) in lv.elements.iter().enumerate() {
            if let Some((k, sc)) = self.element_stiffness(l, e) {
                for (a, &j) in el.iter().enumerate() {
                    diag[j as usize] += k[9 * a] * sc;
                }
            }
        }
        let diag_inv: Vec<Mat3> = (0..lv.nodes)
            .map(|j| {
                if lv.fixed[j] {
                    Mat3::ZERO
                } else {
                    spd_inverse(diag[j])
                }
            })
            .collect();
        let free = |j: usize| diag_inv[j] != Mat3::ZERO;
        // A deterministic start with every frequency in it.
        let mut x: Vec<Vec3> = (0..lv.nodes)
            .map(|j| {
                if !free(j) {
                    return Vec3::ZERO;
                }
                let h = |s: u32| {
                    let v = (j as u32).wrapping_mul(2_654_435_761).wrapping_add(s) ^ 0x9e37_79b9;
                    let v = v.wrapping_mul(0x85eb_ca6b) ^ (v >> 13);
                    (v % 2001) as f32 / 1000.0 - 1.0
                };
                Vec3::new(h(1), h(2), h(3))
            })
            .collect();
        let rot = vec![Mat3::IDENTITY; lv.elements.len()];
        let mut lambda = 0.0f32;
        let mut y = vec![Vec3::ZERO; lv.nodes];
        for _ in 0..POWER_ITERATIONS {
            super::par::for_chunks_mut(&mut y, 1, 0, |first, chunk| {
                for (i, yj) in chunk.iter_mut().enumerate() {
                    let j = first + i;
                    *yj = if free(j) {
                        self.stiffness_row(l, j, &x, &rot)
                    } else {
                        Vec3::ZERO
                    };
                }
            });
            let (mut num, mut den) = (0.0f64, 0.0f64);
            for j in 0..lv.nodes {
                num += x[j].dot(y[j]) as f64;
                den += x[j].dot(diag[j] * x[j]) as f64;
            }
            if den <= 0.0 {
                return 1.0;
            }
            lambda = (num / den) as f32;
            let mut norm = 0.0f64;
            for j in 0..lv.nodes {
                x[j] = diag_inv[j] * y[j];
                norm += x[j].length_squared() as f64;
            }
            let inv = (1.0 / norm.sqrt().max(f64::MIN_POSITIVE)) as f32;
            x.iter_mut().for_each(|v| *v *= inv);
        }
        if lambda.is_finite() { lambda } else { 1.0 }
    }

    /// `(K x)_j` on level `l` with element rotations `rot` (no mass, no extra stiffness).
    fn stiffness_row(&self, l: usize, j: usize, x: &[Vec3], rot: &[Mat3]) -> Vec3 {
        let lv = &self.levels[l];
        let mut y = Vec3::ZERO;
        for &ec in &lv.inv[lv.inv_start[j] as usize..lv.inv_start[j + 1] as usize] {
            let (e, a) = ((ec >> 3) as usize, (ec & 7) as usize);
            let r = rot[e];
            let rt = r.transpose();
            if lv.blocks.is_empty() {
                // Level 0: the body's unit cube in factored form, as the GPU applies it.
                let Some(op) = &self.unit_operator[lv.body[e] as usize] else {
                    continue;
                };
                let xs = lv.elements[e].map(|q| x[q as usize]);
                let (g, q) = CubeOperator::moments(&xs);
                let q = q.map(|v| rt * v);
                let (sigma, resp) = op.response(&(rt * g), &q);
                y += r * CubeOperator::row(a, &sigma, &resp) * lv.scale[e];
                continue;
            }
            let Some((k, sc)) = self.element_stiffness(l, e) else {
                continue;
            };
            let mut acc = Vec3::ZERO;
            for (kab, &q) in k[8 * a..8 * a + 8].iter().zip(&lv.elements[e]) {
                acc += *kab * (rt * x[q as usize]);
            }
            y += r * acc * sc;
        }
        y
    }
}

/// Level `l` of the hierarchy of `parts`' bodies: their levels `l` one after another
/// (indices shifted past the bodies before, element bodies numbered by part), colours
/// in the order of [`MgLevel::order`]; with `links`, the prolongation to the next level
/// and the child lists of its elements (the coarsest level has neither).
fn join_level(parts: &[&BodyLevels], l: usize, links: bool) -> MgLevel {
    let mut out = MgLevel {
        inv_start: vec![0],
        body_start: vec![0],
        ..Default::default()
    };
    if links {
        out.prolong_start.push(0);
        out.child_start.push(0);
    }
    let mut bases = Vec::with_capacity(parts.len());
    // Nodes of the parts before, on the next level.
    let mut coarse_base = 0u32;
    for (b, part) in parts.iter().enumerate() {
        let Some(lv) = part.levels.get(l) else {
            bases.push(out.nodes as u32);
            out.body_start.push(out.nodes as u32);
            continue;
        };
        let (n0, e0) = (out.nodes as u32, out.elements.len() as u32);
        bases.push(n0);
        out.nodes += lv.nodes;
        out.body_start.push(out.nodes as u32);
        out.elements
            .extend(lv.elements.iter().map(|el| el.map(|j| j + n0)));
        out.body
            .extend(std::iter::repeat_n(b as u32, lv.elements.len()));
        out.scale.extend_from_slice(&lv.scale);
        out.stiffness.extend_from_slice(&lv.stiffness);
        out.blocks.extend_from_slice(&lv.blocks);
        out.mass.extend_from_slice(&lv.mass);
        out.fixed.extend_from_slice(&lv.fixed);
        let i0 = out.inv.len() as u32;
        out.inv
            .extend(lv.inv.iter().map(|&ec| (((ec >> 3) + e0) << 3) | (ec & 7)));
        out.inv_start
            .extend(lv.inv_start[1..].iter().map(|&s| s + i0));
        if links {
            if lv.prolong_start.is_empty() {
                // A body without elements: no coarse nodes for its nodes.
                let at = out.prolong_node.len() as u32;
                out.prolong_start.extend(std::iter::repeat_n(at, lv.nodes));
            } else {
                let p0 = out.prolong_node.len() as u32;
                out.prolong_start
                    .extend(lv.prolong_start[1..].iter().map(|&s| s + p0));
                out.prolong_node
                    .extend(lv.prolong_node.iter().map(|&k| k + coarse_base));
                out.prolong_weight.extend_from_slice(&lv.prolong_weight);
            }
            if !lv.child_start.is_empty() {
                let c0 = out.child.len() as u32;
                out.child_start
                    .extend(lv.child_start[1..].iter().map(|&s| s + c0));
                out.child.extend(lv.child.iter().map(|&e| e + e0));
            }
            coarse_base += part.levels.get(l + 1).map_or(0, |c| c.nodes as u32);
        }
    }
    for k in 0..COLOURS {
        for (part, &n0) in parts.iter().zip(&bases) {
            if let Some(lv) = part.levels.get(l) {
                let (a, b) = (lv.colour_start[k] as usize, lv.colour_start[k + 1] as usize);
                out.order.extend(lv.order[a..b].iter().map(|&j| j + n0));
            }
        }
        out.colour_start[k + 1] = out.order.len() as u32;
    }
    out
}

/// Row-major 24 × 24 stiffness matrices (one after another) as 3 × 3 blocks, 64 per
/// matrix (corner `a`, corner `b` at `8 a + b`).
fn to_blocks(k: &[f32]) -> Vec<Mat3> {
    k.chunks_exact(576)
        .flat_map(|m| (0..64).map(move |ab| block(m, ab / 8, ab % 8)))
        .collect()
}

/// The next coarser level of `fine` (whose cells have lowest-corner coordinates
/// `origin` and whose nodes have coordinates `coords`): cells of 2 × 2 × 2 fine cells,
/// nodes at even fine coordinates. Fills `fine`'s prolongation and child lists.
fn coarsen(
    fine: &mut MgLevel,
    origin: &[IVec3],
    coords: &[IVec3],
    unit: &[Option<Vec<f32>>],
) -> Option<(MgLevel, Vec<IVec3>, Vec<IVec3>)> {
    if fine.elements.is_empty() {
        return None;
    }
    // Coarse cells keyed by (body, coarse lowest corner).
    let mut cell_of: HashMap<(u32, IVec3), u32> = HashMap::new();
    let mut cells: Vec<(u32, IVec3)> = Vec::new();
    let mut children: Vec<Vec<u32>> = Vec::new();
    for (e, o) in origin.iter().enumerate() {
        let key = (fine.body[e], o.div_euclid(IVec3::splat(2)));
        let c = *cell_of.entry(key).or_insert_with(|| {
            cells.push(key);
            children.push(Vec::new());
            (cells.len() - 1) as u32
        });
        children[c as usize].push(e as u32);
    }
    // Coarse nodes: corners of the coarse cells.
    let mut node_of: HashMap<(u32, IVec3), u32> = HashMap::new();
    let mut coarse_coords = Vec::new();
    let mut elements = Vec::with_capacity(cells.len());
    for &(b, c) in &cells {
        let corners: [u32; CORNERS] = std::array::from_fn(|j| {
            let p = c + IVec3::new((j & 1) as i32, ((j >> 1) & 1) as i32, ((j >> 2) & 1) as i32);
            *node_of.entry((b, p)).or_insert_with(|| {
                coarse_coords.push(p);
                (coarse_coords.len() - 1) as u32
            })
        });
        elements.push(corners);
    }
    let nc = coarse_coords.len();
    // Body of every fine node (from its elements).
    let mut node_body = vec![u32::MAX; fine.nodes];
    for (e, el) in fine.elements.iter().enumerate() {
        for &j in el {
            node_body[j as usize] = fine.body[e];
        }
    }
    // Prolongation: trilinear from the coarse nodes around each fine node.
    fine.prolong_start = vec![0];
    fine.prolong_node.clear();
    fine.prolong_weight.clear();
    for (j, c) in coords.iter().enumerate().take(fine.nodes) {
        let b = node_body[j];
        if b != u32::MAX {
            let axis = |v: i32| -> [(i32, f32); 2] {
                if v.rem_euclid(2) == 0 {
                    [(v.div_euclid(2), 1.0), (0, 0.0)]
                } else {
                    [(v.div_euclid(2), 0.5), (v.div_euclid(2) + 1, 0.5)]
                }
            };
            let (ax, ay, az) = (axis(c.x), axis(c.y), axis(c.z));
            let mut total = 0.0;
            let start = fine.prolong_node.len();
            for &(x, wx) in &ax {
                for &(y, wy) in &ay {
                    for &(z, wz) in &az {
                        let w = wx * wy * wz;
                        if w == 0.0 {
                            continue;
                        }
                        if let Some(&k) = node_of.get(&(b, IVec3::new(x, y, z))) {
                            fine.prolong_node.push(k);
                            fine.prolong_weight.push(w);
                            total += w;
                        }
                    }
                }
            }
            if total > 0.0 {
                for w in &mut fine.prolong_weight[start..] {
                    *w /= total;
                }
            }
        }
        fine.prolong_start.push(fine.prolong_node.len() as u32);
    }
    // Coarse masses (restriction of the fine ones) and fixed nodes (a coarse node at a
    // fixed fine node's place).
    let mut mass = vec![0.0f32; nc];
    for j in 0..fine.nodes {
        for s in fine.prolong_start[j] as usize..fine.prolong_start[j + 1] as usize {
            mass[fine.prolong_node[s] as usize] += fine.prolong_weight[s] * fine.mass[j];
        }
    }
    let mut fixed = vec![false; nc];
    for j in 0..fine.nodes {
        if !fine.fixed[j] {
            continue;
        }
        let (a, b) = (
            fine.prolong_start[j] as usize,
            fine.prolong_start[j + 1] as usize,
        );
        if b - a == 1 && fine.prolong_weight[a] == 1.0 {
            fixed[fine.prolong_node[a] as usize] = true;
        }
    }
    let scale: Vec<f32> = children
        .iter()
        .map(|ch| ch.iter().map(|&e| fine.scale[e as usize] * 0.25).sum())
        .collect();
    // Galerkin stiffness of each coarse cell from its children.
    let mut stiffness = vec![0.0f32; cells.len() * 576];
    for (c, ch) in children.iter().enumerate() {
        let base = cells[c].1 * 2;
        let kc = &mut stiffness[c * 576..(c + 1) * 576];
        for &e in ch {
            let e = e as usize;
            let (kf, sf): (&[f32], f32) = if fine.stiffness.is_empty() {
                match &unit[fine.body[e] as usize] {
                    Some(k) => (k, fine.scale[e]),
                    None => continue,
                }
            } else {
                (&fine.stiffness[e * 576..(e + 1) * 576], 1.0)
            };
            // Trilinear weights of the child's corners on the coarse corners.
            let mut pw = [[0.0f32; CORNERS]; CORNERS];
            for (k, row) in pw.iter_mut().enumerate() {
                let t = (origin[e] + corner_offset(k) - base).as_vec3() * 0.5;
                for (a, w) in row.iter_mut().enumerate() {
                    let o = corner_offset(a);
                    let f = |bit: i32, t: f32| if bit == 1 { t } else { 1.0 - t };
                    *w = f(o.x, t.x) * f(o.y, t.y) * f(o.z, t.z);
                }
            }
            for a in 0..CORNERS {
                for b in 0..CORNERS {
                    for i in 0..3 {
                        for j in 0..3 {
                            let mut sum = 0.0;
                            for k in 0..CORNERS {
                                if pw[k][a] == 0.0 {
                                    continue;
                                }
                                for l in 0..CORNERS {
                                    if pw[l][b] == 0.0 {
                                        continue;
                                    }
                                    sum += pw[k][a] * kf[(3 * k + i) * 24 + 3 * l + j] * pw[l][b];
                                }
                            }
                            kc[(3 * a + i) * 24 + 3 * b + j] += sf * sum;
                        }
                    }
                }
            }
        }
    }
    fine.child_start = vec![0];
    fine.child.clear();
    for ch in &children {
        fine.child.extend_from_slice(ch);
        fine.child_start.push(fine.child.len() as u32);
    }
    let mut inv: Vec<Vec<u32>> = vec![Vec::new(); nc];
    for (e, el) in elements.iter().enumerate() {
        for (corner, &j) in el.iter().enumerate() {
            inv[j as usize].push(((e as u32) << 3) | corner as u32);
        }
    }
    let mut level = MgLevel {
        nodes: nc,
        body: cells.iter().map(|c| c.0).collect(),
        elements,
        scale,
        stiffness,
        mass,
        fixed,
        inv_start: vec![0],
        ..Default::default()
    };
    for list in inv {
        level.inv.extend_from_slice(&list);
        level.inv_start.push(level.inv.len() as u32);
    }
    let origins = cells.iter().map(|c| c.1).collect();
    Some((level, origins, coarse_coords))
}

/// The elastic forces (N) on the corners of one element at corner positions `x`
/// (fixed-corotated centre stress and hourglass modes, as
/// [`super::element::corner_force`], for all corners at once); updates `rot` to
/// `polar(F)`.
#[allow(clippy::too_many_arguments)]
pub fn element_forces(
    x: &[Vec3; CORNERS],
    size: f32,
    volume: f32,
    mat: &Hyperelastic,
    op: &CubeOperator,
    rot: &mut Quat,
    rotation_iterations: u32,
) -> [Vec3; CORNERS] {
    let f = element_gradient(x, size);
    extract_rotation(&f, rot, rotation_iterations);
    let r = Mat3::from_quat(*rot);
    let p = corotated_stress(&f, &r, mat);
    let pv = p * volume;
    let mut out: [Vec3; CORNERS] =
        std::array::from_fn(|j| -(pv * super::element::gradient_weight(j, size)));
    // Hourglass: −R Σ_α h_α(j) (Q q)_α (V/h²) with q = Rᵀ q(x) (the GPU's `forces`).
    let scale = volume / (size * size);
    let rt = r.transpose();
    let rel = x.map(|p| p - x[0]);
    let rq = op.hourglass(&CubeOperator::hourglass_coords(&rel).map(|v| rt * v));
    for (j, o) in out.iter_mut().enumerate() {
        *o -= r * (CubeOperator::hourglass_row(j, &rq) * scale);
    }
    out
}

/// The elastic energy (J) of one element at corner positions `x` with its rotation `r`
/// held: `V (μ ‖sym(Rᵀ F) − I‖² + λ/2 (det F − 1)²) + ½ (V/h²) qᵀ Q q` (`q` the
/// hourglass coordinates in the element's frame, `Q` the operator's hourglass block:
/// the twelve modes' `½ Σ_m k_m c_m²`), whose gradient with `R` frozen is
/// [`element_forces`]' negative. For line searches.
pub fn element_energy(
    x: &[Vec3; CORNERS],
    size: f32,
    volume: f32,
    mat: &Hyperelastic,
    op: &CubeOperator,
    r: &Mat3,
) -> f64 {
    let f = element_gradient(x, size);
    let rtf = r.transpose() * f;
    let e = (rtf + rtf.transpose()) * 0.5 - Mat3::IDENTITY;
    let ee = e.x_axis.length_squared() + e.y_axis.length_squared() + e.z_axis.length_squared();
    let j = f.determinant() - 1.0;
    let out =
        volume as f64 * (mat.mu as f64 * ee as f64 + 0.5 * mat.lambda as f64 * (j * j) as f64);
    let scale = (volume / (size * size)) as f64;
    let rt = r.transpose();
    let rel = x.map(|p| p - x[0]);
    let q = CubeOperator::hourglass_coords(&rel).map(|v| rt * v);
    let rq = op.hourglass(&q);
    let qq: f32 = q.iter().zip(&rq).map(|(a, b)| a.dot(*b)).sum();
    out + 0.5 * scale * qq as f64
}

/// Work space of the V-cycle, one entry per level.
#[derive(Debug, Clone, Default)]
pub struct MgWork {
    /// Rotation of every element of every level.
    pub rot: Vec<Vec<Mat3>>,
    /// Right-hand side per level.
    pub rhs: Vec<Vec<Vec3>>,
    /// Correction per level.
    pub delta: Vec<Vec<Vec3>>,
    /// Inverted diagonal blocks per level.
    pub diag_inv: Vec<Vec<Mat3>>,
    /// Extra node stiffness per level, N/m (contact penalties `k n nᵀ`). The caller fills
    /// level 0 (one block per node, or leaves it empty for none) before
    /// [`LatticeMultigrid::prepare`], which lumps it onto the coarser levels
    /// (`Σ_j w_jc S_j`: exact for a uniform correction).
    pub extra: Vec<Vec<Mat3>>,
    /// Level 0's nodes held at zero correction in this solve besides the level's fixed
    /// ones (grasped particles; empty: none): the V-cycle neither smooths nor corrects
    /// them and leaves their residual out of the coarse levels', as
    /// [`LatticeMultigrid::krylov`] leaves them out of its directions.
    pub held: Vec<bool>,
    /// Level 0's answer of the last solve by [`LatticeMultigrid::krylov`] or
    /// [`LatticeMultigrid::two_direction`] (empty: none yet): the next two-direction
    /// step's second direction.
    pub last: Vec<Vec3>,
}

impl LatticeMultigrid {
    /// Prepares the V-cycle for substep `h2` (s²) with level 0's element rotations
    /// `rot0`: coarse rotations (the normalised mean of their children's) and every
    /// level's inverted diagonal blocks `M/h² + Σ_e R K_jj Rᵀ`.
    pub fn prepare(&self, rot0: &[Quat], h2: f32, work: &mut MgWork) {
        let nl = self.levels.len();
        work.rot.resize(nl, Vec::new());
        work.rhs.resize(nl, Vec::new());
        work.delta.resize(nl, Vec::new());
        work.diag_inv.resize(nl, Vec::new());
        work.extra.resize(nl, Vec::new());
        if work.extra[0].len() != self.levels[0].nodes {
            work.extra[0].clear();
        }
        for l in 1..nl {
            let fine = std::mem::take(&mut work.extra[l - 1]);
            let mut coarse = Vec::new();
            if !fine.is_empty() {
                let lv = &self.levels[l - 1];
                coarse = vec![Mat3::ZERO; self.levels[l].nodes];
                for (j, s) in fine.iter().enumerate() {
                    if *s == Mat3::ZERO {
                        continue;
                    }
                    for t in lv.prolong_start[j] as usize..lv.prolong_start[j + 1] as usize {
                        coarse[lv.prolong_node[t] as usize] += *s * lv.prolong_weight[t];
                    }
                }
            }
            work.extra[l - 1] = fine;
            work.extra[l] = coarse;
        }
        let mut quats: Vec<Quat> = rot0.to_vec();
        for l in 0..nl {
            let lv = &self.levels[l];
            work.rot[l] = quats.iter().map(|q| Mat3::from_quat(*q)).collect();
            let mut diag: Vec<Mat3> = lv
                .mass
                .iter()
                .map(|&m| Mat3::from_diagonal(Vec3::splat(m / h2)))
                .collect();
            for (d, s) in diag.iter_mut().zip(&work.extra[l]) {
                *d += *s;
            }
            for (e, el) in lv.elements.iter().enumerate() {
                let Some((k, sc)) = self.element_stiffness(l, e) else {
                    continue;
                };
                let r = work.rot[l][e];
                for (a, &j) in el.iter().enumerate() {
                    let kb = k[9 * a] * sc;
                    diag[j as usize] += r * kb * r.transpose();
                }
            }
            work.diag_inv[l] = diag.iter().map(|d| spd_inverse(*d)).collect();
            work.rhs[l].resize(lv.nodes, Vec3::ZERO);
            work.delta[l].resize(lv.nodes, Vec3::ZERO);
            if l + 1 < nl {
                let mut next = Vec::with_capacity(lv.child_start.len().saturating_sub(1));
                for c in 0..lv.child_start.len().saturating_sub(1) {
                    let ch = &lv.child[lv.child_start[c] as usize..lv.child_start[c + 1] as usize];
                    let first = quats[ch[0] as usize];
                    let mut sum = Quat::from_xyzw(0.0, 0.0, 0.0, 0.0);
                    for &e in ch {
                        let q = quats[e as usize];
                        let q = if q.dot(first) < 0.0 { -q } else { q };
                        sum += q;
                    }
                    next.push(sum.normalize());
                }
                quats = next;
            }
        }
    }

    /// Element `e` of level `l`: its unrotated stiffness as 64 blocks (`8 a + b`) and
    /// the factor it is scaled by.
    fn element_stiffness(&self, l: usize, e: usize) -> Option<(&[Mat3], f32)> {
        let lv = &self.levels[l];
        if lv.blocks.is_empty() {
            self.unit_blocks[lv.body[e] as usize]
                .as_deref()
                .map(|k| (k, lv.scale[e]))
        } else {
            Some((&lv.blocks[e * 64..(e + 1) * 64], 1.0))
        }
    }

    /// `y = A x` on level `l` (`A = M/h² + S + Σ_e R K Rᵀ`, `S` the extra node
    /// stiffness) for node `j` only.
    fn apply_row(&self, l: usize, j: usize, x: &[Vec3], h2: f32, work: &MgWork) -> Vec3 {
        let lv = &self.levels[l];
        let mut y = x[j] * (lv.mass[j] / h2);
        if let Some(s) = work.extra[l].get(j) {
            y += *s * x[j];
        }
        y + self.stiffness_row(l, j, x, &work.rot[l])
    }

    /// Node `j` of level `l`'s own block of the Newton matrix, `m_j/h² I + S_j` (N/m;
    /// `S_j` its contact block, where it has one).
    fn own_block(&self, l: usize, j: usize, h2: f32, work: &MgWork) -> Mat3 {
        let m = Mat3::from_diagonal(Vec3::splat(self.levels[l].mass[j] / h2));
        match work.extra.get(l).and_then(|e| e.get(j)) {
            Some(s) => m + *s,
            None => m,
        }
    }

    /// Whether node `j` of level `l` keeps a zero correction: fixed on its level, or on
    /// level 0 held in this solve ([`MgWork::held`]).
    fn fixed_at(&self, l: usize, j: usize, work: &MgWork) -> bool {
        self.levels[l].fixed[j] || (l == 0 && work.held.get(j).copied().unwrap_or(false))
    }

    /// Whether the V-cycle solves the coarsest level exactly under `sweeps`
    /// ([`Sweeps::exact_coarsest`]): it is asked for, the coarsest level is below level
    /// 0, and no body has more than [`EXACT_COARSEST`] nodes there.
    pub fn coarsest_exact(&self, sweeps: Sweeps) -> bool {
        let l = self.levels.len().saturating_sub(1);
        sweeps.exact_coarsest
            && l > 0
            && self.levels[l]
                .body_start
                .windows(2)
                .all(|w| w[1].saturating_sub(w[0]) as usize <= EXACT_COARSEST)
    }

    /// The coarsest level's `A δ = rhs` solved exactly, each body's system on its own:
    /// its matrix `M/h² + S + Σ_e R K Rᵀ` over the body's free nodes assembled as a
    /// packed lower triangle (fixed nodes' rows and columns those of the identity, their
    /// right-hand side 0), bordered by the right-hand side and solved by `L D Lᵀ`
    /// elimination ([`super::dense::solve_bordered`]). Each
    /// entry sums the node's own terms, then its elements' blocks in the node's element
    /// order, as the GPU's `solve_coarsest` and `factor_coarsest` do. (The GPU may
    /// factorise the matrix once a Newton iteration and solve each V-cycle's right-hand
    /// side through the kept factor: the same numbers, the matrix being the same in every
    /// V-cycle of a Newton iteration; this twin makes it again each time.) A body whose
    /// matrix is not numerically positive definite keeps a zero correction (its coarse
    /// level then does not help this V-cycle).
    fn solve_coarsest(&self, h2: f32, work: &mut MgWork) {
        use super::dense::{packed, packed_len, solve_bordered};
        let l = self.levels.len() - 1;
        let lv = &self.levels[l];
        // A, bordered by the right-hand side as row m: one buffer for every body, the
        // largest body's length.
        let most = lv
            .body_start
            .windows(2)
            .map(|w| w[1].saturating_sub(w[0]) as usize)
            .max()
            .unwrap_or(0);
        let mut buffer = vec![0.0f32; packed_len(3 * most + 1)];
        for w in lv.body_start.windows(2) {
            let (base, nn) = (w[0] as usize, w[1].saturating_sub(w[0]) as usize);
            let m = 3 * nn;
            let a = &mut buffer[..packed_len(m + 1)];
            a.fill(0.0);
            // Adds block `blk` at nodes (i, k) (local, k ≤ i), its lower part where i = k.
            let add = |a: &mut [f32], i: usize, k: usize, blk: Mat3| {
                for r in 0..3 {
                    for c in 0..3 {
                        if 3 * k + c <= 3 * i + r {
                            a[packed(3 * i + r, 3 * k + c)] += blk.col(c)[r];
                        }
                    }
                }
            };
            for i in 0..nn {
                let j = base + i;
                if lv.fixed[j] {
                    add(a, i, i, Mat3::IDENTITY);
                    continue;
                }
                add(a, i, i, self.own_block(l, j, h2, work));
                for (r, v) in work.rhs[l][j].to_array().into_iter().enumerate() {
                    a[packed(m, 3 * i + r)] = v;
                }
            }
            for i in 0..nn {
                let j = base + i;
                if lv.fixed[j] {
                    continue;
                }
                for &ec in &lv.inv[lv.inv_start[j] as usize..lv.inv_start[j + 1] as usize] {
                    let (e, corner) = ((ec >> 3) as usize, (ec & 7) as usize);
                    let Some((k, sc)) = self.element_stiffness(l, e) else {
                        continue;
                    };
                    let r = work.rot[l][e];
                    for (b, &node) in lv.elements[e].iter().enumerate() {
                        let node = node as usize;
                        if node > j || lv.fixed[node] {
                            continue;
                        }
                        let blk = r * (k[8 * corner + b] * sc) * r.transpose();
                        add(a, i, node - base, blk);
                    }
                }
            }
            let x = solve_bordered(a, m);
            for i in 0..nn {
                let j = base + i;
                work.delta[l][j] = match &x {
                    Some(x) if !lv.fixed[j] => Vec3::from_slice(&x[3 * i..3 * i + 3]),
                    _ => Vec3::ZERO,
                };
            }
        }
    }

    /// `sweeps` sweeps of [`LatticeMultigrid::smoother`] on `A δ = rhs` of level `l`
    /// (fixed nodes stay 0).
    fn smooth(&self, l: usize, sweeps: u32, h2: f32, work: &mut MgWork) {
        match self.smoother.on_level(l) {
            Smoother::Chebyshev => self.smooth_chebyshev(l, sweeps, h2, work),
            _ => self.smooth_gauss_seidel(l, sweeps, h2, work),
        }
    }

    /// `sweeps` Chebyshev-accelerated block Jacobi sweeps ([`Smoother::Chebyshev`]).
    fn smooth_chebyshev(&self, l: usize, sweeps: u32, h2: f32, work: &mut MgWork) {
        let lv = &self.levels[l];
        let [inv_theta, rho2] = self.chebyshev[l];
        let mut prev = work.delta[l].clone();
        let mut next = vec![Vec3::ZERO; lv.nodes];
        for k in 0..sweeps {
            let w = chebyshev_weight(k, rho2);
            let cur = &work.delta[l];
            for (j, n) in next.iter_mut().enumerate() {
                *n = if self.fixed_at(l, j, work) {
                    cur[j]
                } else {
                    let ax = self.apply_row(l, j, cur, h2, work);
                    let xh = cur[j] + work.diag_inv[l][j] * (work.rhs[l][j] - ax) * inv_theta;
                    (xh - prev[j]) * w + prev[j]
                };
            }
            std::mem::swap(&mut prev, &mut next);
            std::mem::swap(&mut prev, &mut work.delta[l]);
        }
        if l == 0 && sweeps > 0 {
            self.contact_pass(h2, work);
        }
    }

    /// One block-Jacobi pass over level 0's free nodes that carry a contact penalty,
    /// after its Chebyshev sweeps: `δ_j += D_j⁻¹ (rhs − A δ)_j`, every update computed
    /// from the sweeps' result. The polynomial's damped updates leave part of a stiff
    /// penalty on a single node unresolved (a box dropped on another never comes to
    /// rest); this pass solves each such node's own block whole, as Gauss–Seidel does,
    /// and leaves every other node as the sweeps left it.
    fn contact_pass(&self, h2: f32, work: &mut MgWork) {
        let Some(extra) = work.extra.first() else {
            return;
        };
        let updates: Vec<(usize, Vec3)> = extra
            .iter()
            .enumerate()
            .filter(|&(j, s)| *s != Mat3::ZERO && !self.fixed_at(0, j, work))
            .map(|(j, _)| {
                let ax = self.apply_row(0, j, &work.delta[0], h2, work);
                (j, work.diag_inv[0][j] * (work.rhs[0][j] - ax))
            })
            .collect();
        for (j, d) in updates {
            work.delta[0][j] += d;
        }
    }

    /// `sweeps` Gauss–Seidel sweeps in colour order ([`Smoother::GaussSeidel`]).
    fn smooth_gauss_seidel(&self, l: usize, sweeps: u32, h2: f32, work: &mut MgWork) {
        let lv = &self.levels[l];
        for _ in 0..sweeps {
            for &j in &lv.order {
                let j = j as usize;
                if self.fixed_at(l, j, work) {
                    continue;
                }
                let ax = self.apply_row(l, j, &work.delta[l], h2, work);
                let d = work.diag_inv[l][j] * (work.rhs[l][j] - ax);
                work.delta[l][j] += d;
            }
        }
    }

    /// Solves level 0's `A δ = work.rhs[0]` by conjugate gradients preconditioned with
    /// `cycles` V-cycles, one per iteration (flexible CG: Notay 2000, "Flexible conjugate
    /// gradients", the V-cycle's energy-minimising coarse steps making it a nonlinear
    /// preconditioner; `β = zₖᵀ (rₖ − rₖ₋₁) / zₖ₋₁ᵀ rₖ₋₁`, `α = rₖᵀ pₖ / pₖᵀ A pₖ`). The
    /// answer is left in `work.delta[0]`; `work.rhs[0]` becomes the last residual. Nodes
    /// `held` (and the level's fixed ones) keep a zero correction. With one cycle this is
    /// the V-cycle's correction scaled by its energy-minimising step.
    pub fn krylov(&self, h2: f32, cycles: u32, sweeps: Sweeps, held: &[bool], work: &mut MgWork) {
        let n = self.levels[0].nodes;
        let free = |j: usize| !held.get(j).copied().unwrap_or(false) && !self.levels[0].fixed[j];
        // The V-cycles hold them too.
        work.held.clear();
        work.held.extend_from_slice(held);
        let mut x = vec![Vec3::ZERO; n];
        let mut p = vec![Vec3::ZERO; n];
        let mut q = vec![Vec3::ZERO; n];
        // Each body's own scalars (sums over its nodes), so that a body steps as it
        // would alone: α and zᵀ r of the last iteration.
        let starts = &self.levels[0].body_start;
        let bodies: Vec<std::ops::Range<usize>> = starts
            .windows(2)
            .map(|w| w[0] as usize..w[1] as usize)
            .collect();
        let mut alpha = vec![0.0f64; bodies.len()];
        let mut rz = vec![0.0f64; bodies.len()];
        for k in 0..cycles.max(1) {
            work.delta[0].iter_mut().for_each(|d| *d = Vec3::ZERO);
            self.vcycle(0, h2, sweeps, work);
            let z = &work.delta[0];
            for (b, range) in bodies.iter().enumerate() {
                let beta = if k == 0 {
                    0.0
                } else {
                    let zq: f64 = range
                        .clone()
                        .filter(|&j| free(j))
                        .map(|j| z[j].dot(q[j]) as f64)
                        .sum();
                    finite_or_zero(-alpha[b] * zq / rz[b])
                };
                for j in range.clone() {
                    p[j] = if free(j) {
                        z[j] + p[j] * beta as f32
                    } else {
                        Vec3::ZERO
                    };
                }
            }
            for (b, range) in bodies.iter().enumerate() {
                let (mut pq, mut rp, mut rz_now) = (0.0f64, 0.0f64, 0.0f64);
                for j in range.clone() {
                    q[j] = if free(j) {
                        self.apply_row(0, j, &p, h2, work)
                    } else {
                        Vec3::ZERO
                    };
                    let r = work.rhs[0][j];
                    pq += p[j].dot(q[j]) as f64;
                    rp += r.dot(p[j]) as f64;
                    rz_now += r.dot(z[j]) as f64;
                }
                alpha[b] = if pq > 0.0 {
                    finite_or_zero(rp / pq)
                } else {
                    0.0
                };
                rz[b] = rz_now;
                let a = alpha[b] as f32;
                for j in range.clone() {
                    x[j] += p[j] * a;
                    work.rhs[0][j] -= q[j] * a;
                }
            }
        }
        work.last.clone_from(&x);
        work.delta[0] = x;
    }

    /// Solves level 0's `A δ = work.rhs[0]` approximately by one V-cycle and the last
    /// solve's answer `p` ([`MgWork::last`]): each body's `δ = a z + b p`, `z` the
    /// V-cycle's correction, `a` and `b` minimising the quadratic model `½ δᵀ A δ − δᵀ r`
    /// over the span of `z` and `p` (a two-dimensional Galerkin step, as recycled Krylov
    /// methods reuse an earlier solve's subspace: Parks et al. 2006, "Recycling Krylov
    /// subspaces for sequences of linear systems"). Successive Newton systems of a
    /// settling body differ little and their answers share the smooth bending a V-cycle
    /// corrects slowly (its coarse trilinear elements are stiff in bending), so the last
    /// answer supplies what the V-cycle misses. Where `p` adds nothing (zero, the first
    /// solve, or nearly parallel to `z`: [`two_direction_weights`]) it is the V-cycle's correction scaled by its
    /// energy-minimising step. The answer is left in `work.delta[0]`, and kept as the
    /// next solve's `p`; nodes `held` (and the level's fixed ones) keep a zero correction,
    /// and `p` is zero there too (and wherever it is not finite).
    pub fn two_direction(&self, h2: f32, sweeps: Sweeps, held: &[bool], work: &mut MgWork) {
        let n = self.levels[0].nodes;
        let free = |j: usize| !held.get(j).copied().unwrap_or(false) && !self.levels[0].fixed[j];
        work.held.clear();
        work.held.extend_from_slice(held);
        work.delta[0].iter_mut().for_each(|d| *d = Vec3::ZERO);
        self.vcycle(0, h2, sweeps, work);
        let z = std::mem::take(&mut work.delta[0]);
        // A last answer of another length (none yet, or another model) is no direction.
        let mut p = std::mem::take(&mut work.last);
        if p.len() != n {
            p = vec![Vec3::ZERO; n];
        }
        for (j, v) in p.iter_mut().enumerate() {
            if !free(j) || !v.is_finite() {
                *v = Vec3::ZERO;
            }
        }
        let sums = self.two_direction_sums(h2, &z, &p, &free, work);
        let mut x = vec![Vec3::ZERO; n];
        for (w, t) in self.levels[0].body_start.windows(2).zip(sums) {
            let (a, b) = two_direction_weights(t);
            for j in w[0] as usize..w[1] as usize {
                x[j] = z[j] * a + p[j] * b;
            }
        }
        work.delta[0].clone_from(&x);
        work.last = x;
    }

    /// Each body's `[zᵀAz, pᵀAz, pᵀAp, rᵀz, rᵀp]` on level 0 (`r` its right-hand side; `z`
    /// and `p` zero where not `free`), as the GPU's `cg_two_terms` sums them: each
    /// element's three stiffness products once, from both vectors' moments in its frame
    /// ([`CubeOperator::product`]), then each free node's own terms (`M/h² + S` and the
    /// residual). Together they are the rows' sums `Σ_j z_j · (A z)_j` and so on, without
    /// a row.
    fn two_direction_sums(
        &self,
        h2: f32,
        z: &[Vec3],
        p: &[Vec3],
        free: &impl Fn(usize) -> bool,
        work: &MgWork,
    ) -> Vec<[f64; 5]> {
        let lv = &self.levels[0];
        let mut t = vec![[0.0f64; 5]; lv.body_start.len().saturating_sub(1)];
        for (e, corners) in lv.elements.iter().enumerate() {
            let b = lv.body[e] as usize;
            let (Some(Some(op)), Some(sums)) = (self.unit_operator.get(b), t.get_mut(b)) else {
                continue;
            };
            let rt = work.rot[0][e].transpose();
            let moments = |v: &[Vec3]| {
                let (g, q) = CubeOperator::moments(&corners.map(|c| v[c as usize]));
                (rt * g, q.map(|w| rt * w))
            };
            let ((gz, qz), (gp, qp)) = (moments(z), moments(p));
            let (sz, rz) = op.response(&gz, &qz);
            let (sp, rp) = op.response(&gp, &qp);
            let s = lv.scale[e];
            sums[0] += (s * CubeOperator::product(&sz, &rz, &gz, &qz)) as f64;
            sums[1] += (s * CubeOperator::product(&sz, &rz, &gp, &qp)) as f64;
            sums[2] += (s * CubeOperator::product(&sp, &rp, &gp, &qp)) as f64;
        }
        for (w, sums) in lv.body_start.windows(2).zip(t.iter_mut()) {
            for j in (w[0] as usize..w[1] as usize).filter(|&j| free(j)) {
                let a = self.own_block(0, j, h2, work);
                let (az, r) = (a * z[j], work.rhs[0][j]);
                for (s, v) in sums.iter_mut().zip([
                    z[j].dot(az),
                    p[j].dot(az),
                    p[j].dot(a * p[j]),
                    r.dot(z[j]),
                    r.dot(p[j]),
                ]) {
                    *s += v as f64;
                }
            }
        }
        t
    }

    /// Each body's translation step on level 0: `t = (Σ m/h² I + S_j)⁻¹ Σ r` over its
    /// nodes (`S_j` a node's contact block), added to every node's correction, the
    /// residual updated by it (`r_j −= (m_j/h² I + S_j) t`). Elements store no energy in
    /// a translation, so this is the exact minimiser of the step's energy along the
    /// body's translations (the contacts as the V-cycle sees them): the rigid motion a
    /// stiff body's mass alone resists (`M/h²`, small against its stiffness), which
    /// smoothing barely moves and the coarse levels approximate, is taken whole. Bodies
    /// with a fixed node (pinned, or outside the lattice) take none.
    fn translate_bodies(&self, h2: f32, r: &mut [Vec3], work: &mut MgWork) {
        for w in self.levels[0].body_start.windows(2) {
            let nodes = w[0] as usize..w[1] as usize;
            if nodes.clone().any(|j| self.fixed_at(0, j, work)) {
                continue;
            }
            let (mut sum, mut a) = (DVec3::ZERO, DMat3::ZERO);
            for j in nodes.clone() {
                sum += r[j].as_dvec3();
                a += self.own_block(0, j, h2, work).as_dmat3();
            }
            let t = a.inverse() * sum;
            if a.determinant() <= 0.0 || !t.is_finite() {
                continue;
            }
            let t = t.as_vec3();
            for j in nodes {
                r[j] -= self.own_block(0, j, h2, work) * t;
                work.delta[0][j] += t;
            }
        }
    }

    /// One V-cycle from level `l` down, smoothing each level `sweeps` times:
    /// `work.delta[l]` improves on `A δ = work.rhs[l]`.
    pub fn vcycle(&self, l: usize, h2: f32, sweeps: Sweeps, work: &mut MgWork) {
        let nl = self.levels.len();
        if l + 1 == nl {
            if self.coarsest_exact(sweeps) {
                self.solve_coarsest(h2, work);
            } else {
                self.smooth(l, sweeps.on_level(l, true, self.smoother), h2, work);
            }
            return;
        }
        let count = sweeps.on_level(l, false, self.smoother);
        let before = sweeps.before_on_level(l, self.smoother);
        self.smooth(l, before, h2, work);
        // Restrict the residual: r_c = Pᵀ (rhs − A δ); unsmoothed, δ is still zero and
        // the residual the right-hand side.
        let lv = &self.levels[l];
        let nc = self.levels[l + 1].nodes;
        let mut rc = vec![Vec3::ZERO; nc];
        let mut rf = vec![Vec3::ZERO; lv.nodes];
        for (j, rfj) in rf.iter_mut().enumerate() {
            if !self.fixed_at(l, j, work) {
                *rfj = if before == 0 {
                    work.rhs[l][j]
                } else {
                    work.rhs[l][j] - self.apply_row(l, j, &work.delta[l], h2, work)
                };
            }
        }
        if l == 0 && sweeps.translation {
            self.translate_bodies(h2, &mut rf, work);
        }
        for (j, r) in rf.iter().enumerate() {
            for s in lv.prolong_start[j] as usize..lv.prolong_start[j + 1] as usize {
                rc[lv.prolong_node[s] as usize] += *r * lv.prolong_weight[s];
            }
        }
        let cfixed = &self.levels[l + 1].fixed;
        for (k, r) in rc.iter_mut().enumerate() {
            if cfixed[k] {
                *r = Vec3::ZERO;
            }
        }
        work.rhs[l + 1] = rc;
        work.delta[l + 1].iter_mut().for_each(|d| *d = Vec3::ZERO);
        self.vcycle(l + 1, h2, sweeps, work);
        // Prolongate the coarse correction `e = P δ_c`. On level 0 take it whole: the
        // sweeps after it smooth what it overshoots, and the step along the cycle's result
        // is chosen around the cycle (`krylov`: conjugate gradients, or one cycle's own
        // energy-minimising step), so a product `A e` over the particles a cycle is saved.
        // On the levels between, where the coarsest level is swept, take it with the step
        // `α = eᵀ r / eᵀ A e` that minimises the finer level's energy along it: the coarse
        // operator (each coarse cell's stiffness turned by one mean rotation) is exact
        // only where the cell's elements turn alike, and a correction it overestimates is
        // scaled back instead of spoiling the finer solution (never made worse: α ≥ 0);
        // without it a stiff body comes out too soft. Where the coarsest level is solved
        // exactly they take it whole too: the step then buys nothing measurable at two
        // V-cycles a Newton iteration and costs the stiffer bodies accuracy at one.
        let mut e = vec![Vec3::ZERO; lv.nodes];
        for (j, ej) in e.iter_mut().enumerate() {
            if self.fixed_at(l, j, work) {
                continue;
            }
            for s in lv.prolong_start[j] as usize..lv.prolong_start[j + 1] as usize {
                *ej += work.delta[l + 1][lv.prolong_node[s] as usize] * lv.prolong_weight[s];
            }
        }
        if l == 0 || self.coarsest_exact(sweeps) {
            for (d, ej) in work.delta[l].iter_mut().zip(&e) {
                *d += *ej;
            }
            self.smooth(l, count, h2, work);
            return;
        }
        // Each body's own step (its nodes' sums), so that a body steps as it would alone.
        for b in 0..lv.body_start.len().saturating_sub(1) {
            let range = lv.body_start[b] as usize..lv.body_start[b + 1] as usize;
            let (mut num, mut den) = (0.0f64, 0.0f64);
            for j in range.clone() {
                if lv.fixed[j] {
                    continue;
                }
                num += rf[j].dot(e[j]) as f64;
                den += self.apply_row(l, j, &e, h2, work).dot(e[j]) as f64;
            }
            let alpha = correction_step(num, den);
            for j in range {
                work.delta[l][j] += e[j] * alpha;
            }
        }
        self.smooth(l, count, h2, work);
    }
}

/// Smoothing sweeps of a V-cycle ([`LatticeMultigrid::vcycle`]). A level smoothed by
/// [`Smoother::Chebyshev`] takes its sweeps in pairs (a sweep alternates between two
/// buffers): an odd count there is one more ([`Sweeps::on_level`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Sweeps {
    /// On level 0 (the particles), after the coarse correction.
    pub fine: u32,
    /// On level 0 before the coarse correction (0: none; each V-cycle starts from a zero
    /// correction, so level 0's residual is then its right-hand side, and the cycle takes
    /// one pass over the particles fewer).
    pub fine_before: u32,
    /// On each level between level 0 and the coarsest, after the coarse correction.
    pub coarse: u32,
    /// On each level between level 0 and the coarsest, before the coarse correction (0:
    /// none; that level's correction starts from zero, so its residual is then its
    /// right-hand side).
    pub coarse_before: u32,
    /// On the coarsest level, where it is not solved exactly.
    pub coarsest: u32,
    /// Solve the coarsest level exactly (each body's system factorised, `L D Lᵀ`,
    /// [`super::dense`]) instead of sweeping it, where it is below level 0 and no body has
    /// more than [`EXACT_COARSEST`] nodes there ([`LatticeMultigrid::coarsest_exact`];
    /// hierarchies are then coarsened that far, [`Sweeps::min_nodes`]). The coarsest
    /// level carries a stiff body's bending: solved exactly, a 1 MPa body comes closer to
    /// its material at the real-time setting than after `coarsest` sweeps, for about the
    /// sweeps' GPU time, and the levels between then take their coarse correction whole
    /// (no energy-minimising step along it, which a swept coarsest level needs), which
    /// saves three passes a level and V-cycle. On by default. (Level 0 holds grasped
    /// particles inside each V-cycle, so the exact coarse answer does not move them; see
    /// `MgWork::held`.)
    pub exact_coarsest: bool,
    /// Each V-cycle takes each free body's translation step on level 0 before
    /// restricting its residual (`t = (Σ m/h² I + S_j)⁻¹ Σ r` over the body's nodes, `S_j`
    /// a node's contact block; bodies with a held node take none): the exact minimiser of
    /// the step's energy along the body's translations, the rigid motion a stiff body's
    /// mass alone resists and smoothing barely moves. With the coarsest level swept it is
    /// what keeps a stiff free body falling at gravity's rate; solved exactly, the coarse
    /// levels carry that motion themselves (a free stiff box falls at gravity's rate at
    /// the default Newton iteration of two V-cycles without it), so it is off by
    /// default; it helps a very stiff body stepped by a single V-cycle. Off, each V-cycle
    /// takes three dispatches and two passes over the particles fewer on the GPU.
    pub translation: bool,
}

impl Sweeps {
    /// One sweep on level 0 and two on the levels between, each after the coarse
    /// correction and none before it, and the coarsest level solved exactly where its
    /// bodies are small enough (30 sweeps where not), and no translation step: the
    /// coarsest level's exact solve carries a stiff body's bending and its rigid motion,
    /// and the sweeps after the correction each level's own error, contacts included.
    /// No level then needs a pass that makes its residual: each V-cycle starts from a
    /// zero correction on every level, so the residual is the right-hand side.
    pub const DEFAULT: Sweeps = Sweeps {
        fine: 1,
        fine_before: 0,
        coarse: 2,
        coarse_before: 0,
        coarsest: 30,
        exact_coarsest: true,
        translation: false,
    };

    /// The sweeps `smoother` takes on level `l` before the coarse correction (level 0:
    /// [`Sweeps::fine_before`]; the levels between: [`Sweeps::coarse_before`]); rounded
    /// up to even where the level is smoothed by Chebyshev.
    pub fn before_on_level(&self, l: usize, smoother: Smoother) -> u32 {
        let n = if l > 0 {
            self.coarse_before
        } else {
            self.fine_before
        };
        if smoother.on_level(l) == Smoother::Chebyshev {
            n + n % 2
        } else {
            n
        }
    }

    /// The sweeps `smoother` takes on level `l`: after the coarse correction (and before
    /// it but on level 0), or all of them where `l` is the coarsest level; rounded up to
    /// even where the level is smoothed by Chebyshev.
    pub fn on_level(&self, l: usize, coarsest: bool, smoother: Smoother) -> u32 {
        let n = if coarsest {
            self.coarsest
        } else if l == 0 {
            self.fine
        } else {
            self.coarse
        };
        if smoother.on_level(l) == Smoother::Chebyshev {
            n + n % 2
        } else {
            n
        }
    }

    /// How far hierarchies are coarsened for these sweeps: while their bodies have more
    /// than this many nodes each on average on the coarsest level ([`EXACT_COARSEST`]
    /// where the coarsest level is to be solved exactly, else [`MIN_NODES`]).
    pub fn min_nodes(&self) -> usize {
        if self.exact_coarsest {
            EXACT_COARSEST
        } else {
            MIN_NODES
        }
    }

    /// An error naming a count out of range: every count from 1 to 1,000.
    pub fn check(&self) -> Result<(), TissueError> {
        for (name, v) in [
            ("sweeps.fine_before", self.fine_before),
            ("sweeps.coarse_before", self.coarse_before),
        ] {
            if v > 1000 {
                return Err(TissueError::InvalidParameter {
                    name,
                    value: v.to_string(),
                    expected: "a count from 0 to 1000",
                });
            }
        }
        for (name, v) in [
            ("sweeps.fine", self.fine),
            ("sweeps.coarse", self.coarse),
            ("sweeps.coarsest", self.coarsest),
        ] {
            if v == 0 || v > 1000 {
                return Err(TissueError::InvalidParameter {
                    name,
                    value: v.to_string(),
                    expected: "a count from 1 to 1000",
                });
            }
        }
        Ok(())
    }
}

impl Default for Sweeps {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// The weights `(a, b)` of the two-direction step ([`LatticeMultigrid::two_direction`])
/// from a body's sums `[zᵀAz, pᵀAz, pᵀAp, rᵀz, rᵀp]`: the minimiser of the quadratic model
/// over `a z + b p` (Cramer's rule on the 2 × 2 system); `z` alone, scaled by its
/// energy-minimising step, where `p` is zero or within about 6° of `z` in the energy
/// norm (`det < 0.01 zᵀAz pᵀAp`: closer, the weights would amplify rounding, and `p`
/// adds little); zeros where nothing is finite and positive.
pub fn two_direction_weights(t: [f64; 5]) -> (f32, f32) {
    let [zz, pz, pp, rz, rp] = t;
    let det = zz * pp - pz * pz;
    let (a, b) = if pp > 0.0 && det > 1e-2 * zz * pp {
        ((rz * pp - rp * pz) / det, (zz * rp - pz * rz) / det)
    } else if zz > 0.0 {
        (rz / zz, 0.0)
    } else {
        (0.0, 0.0)
    };
    if a.is_finite() && b.is_finite() {
        (a as f32, b as f32)
    } else {
        (0.0, 0.0)
    }
}

fn finite_or_zero(v: f64) -> f64 {
    if v.is_finite() { v } else { 0.0 }
}

/// A coarse correction's energy-minimising step `eᵀ r / eᵀ A e` from those two sums:
/// 0 unless both are positive and the quotient is finite.
fn correction_step(num: f64, den: f64) -> f32 {
    let a = if den > 0.0 && num > 0.0 {
        (num / den) as f32
    } else {
        0.0
    };
    if a.is_finite() { a } else { 0.0 }
}

/// The inverse of a symmetric positive definite 3 × 3 block, by its Cholesky factor
/// `L` (`A = L Lᵀ`, `A⁻¹ = L⁻ᵀ L⁻¹`; of `½ (a + aᵀ)`, so that rounding in either
/// triangle counts alike), or zero where a pivot is not positive (the block is not
/// numerically positive definite).
///
/// The multigrid's diagonal blocks are inverted this way rather than by cofactors: a
/// contact penalty makes a block a large rank-one term plus a small one (a node's mass
/// and elements), and in `f32` the cofactor determinant of such a block cancels to noise
/// (even to the wrong sign), where Cholesky is backward stable.
pub fn spd_inverse(a: Mat3) -> Mat3 {
    let (a00, a11, a22) = (a.x_axis.x, a.y_axis.y, a.z_axis.z);
    let a10 = 0.5 * (a.x_axis.y + a.y_axis.x);
    let a20 = 0.5 * (a.x_axis.z + a.z_axis.x);
    let a21 = 0.5 * (a.y_axis.z + a.z_axis.y);
    if a00.is_nan() || a00 <= 0.0 {
        return Mat3::ZERO;
    }
    let l00 = a00.sqrt();
    let l10 = a10 / l00;
    let l20 = a20 / l00;
    let t11 = a11 - l10 * l10;
    if t11.is_nan() || t11 <= 0.0 {
        return Mat3::ZERO;
    }
    let l11 = t11.sqrt();
    let l21 = (a21 - l20 * l10) / l11;
    let t22 = a22 - l20 * l20 - l21 * l21;
    if t22.is_nan() || t22 <= 0.0 {
        return Mat3::ZERO;
    }
    let l22 = t22.sqrt();
    // L⁻¹ (lower triangular).
    let i00 = 1.0 / l00;
    let i11 = 1.0 / l11;
    let i22 = 1.0 / l22;
    let i10 = -(l10 * i00) * i11;
    let i21 = -(l21 * i11) * i22;
    let i20 = -(l20 * i00 + l21 * i10) * i22;
    // A⁻¹ = (L⁻¹)ᵀ L⁻¹.
    let b00 = i00 * i00 + i10 * i10 + i20 * i20;
    let b10 = i11 * i10 + i21 * i20;
    let b20 = i22 * i20;
    let b11 = i11 * i11 + i21 * i21;
    let b21 = i22 * i21;
    let b22 = i22 * i22;
    Mat3::from_cols(
        Vec3::new(b00, b10, b20),
        Vec3::new(b10, b11, b21),
        Vec3::new(b20, b21, b22),
    )
}

/// Lattice offset of corner `j` (0 or 1 per axis).
#[inline]
fn corner_offset(j: usize) -> IVec3 {
    IVec3::new((j & 1) as i32, ((j >> 1) & 1) as i32, ((j >> 2) & 1) as i32)
}

/// The 3 × 3 block (corner `a`, corner `b`) of a row-major 24 × 24 stiffness.
#[inline]
fn block(k: &[f32], a: usize, b: usize) -> Mat3 {
    let at = |i: usize, j: usize| k[(3 * a + i) * 24 + 3 * b + j];
    Mat3::from_cols(
        Vec3::new(at(0, 0), at(1, 0), at(2, 0)),
        Vec3::new(at(0, 1), at(1, 1), at(2, 1)),
        Vec3::new(at(0, 2), at(1, 2), at(2, 2)),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::model::{BodyDesc, PinRegion};
    use crate::core::procedural;
    use crate::core::sampling::Resolution;

    /// The cantilever's 1/60 s substep system on a 6 mm lattice: the model, its
    /// multigrid, `h²` (s²), unrotated elements, and the free nodes `j` with
    /// `j % every == at` marked held (as grasped ones are).
    fn bar_system(every: usize, at: usize) -> (Model, LatticeMultigrid, f32, Vec<Quat>, Vec<bool>) {
        let model = bar(0.006);
        let mg = LatticeMultigrid::new(&model, 64, 8);
        let rot = vec![Quat::IDENTITY; model.elements.len()];
        let held = (0..model.particle_count())
            .map(|j| j % every == at && !mg.levels[0].fixed[j])
            .collect();
        (model, mg, 1.0 / 3600.0, rot, held)
    }

    fn bar(spacing: f32) -> Model {
        let mut model = Model::new();
        model
            .add_body(
                &procedural::cuboid(Vec3::new(0.12, 0.015, 0.015), 2),
                &BodyDesc {
                    resolution: Resolution::Spacing(spacing),
                    density: 1000.0,
                    material: Material::Hyperelastic {
                        youngs_modulus: 1e5,
                        poisson_ratio: 0.3,
                    },
                    discretisation: Discretisation::Lattice,
                    pins: vec![PinRegion::HalfSpace {
                        point: Vec3::new(-0.1185, 0.0, 0.0),
                        normal: -Vec3::X,
                    }],
                    ..Default::default()
                },
            )
            .unwrap();
        model
    }

    fn residual_norm(mg: &LatticeMultigrid, h2: f32, work: &MgWork) -> f32 {
        let lv = &mg.levels[0];
        let mut s = 0.0;
        for j in 0..lv.nodes {
            if lv.fixed[j] {
                continue;
            }
            let r = work.rhs[0][j] - mg.apply_row(0, j, &work.delta[0], h2, work);
            s += r.length_squared();
        }
        s.sqrt()
    }

    /// The V-cycle as a stationary iteration on the cantilever's substep system
    /// contracts, with a real-time substep (1/60 s, nearly the static problem) as well
    /// as a short one, for a lattice that coarsens into whole cells (8 across) and one
    /// whose coarse cells are partly empty (5 across: the Galerkin coarse stiffness).
    /// The Cholesky inverse of a diagonal block: exact on well-conditioned blocks, still
    /// an inverse (where the cofactor inverse is not) on a contact-loaded block — a
    /// penalty of 2.4e5 N/m along one direction on a node held by 0.6 N/m in the others
    /// — and zero on a block that is not positive definite.
    #[test]
    fn diagonal_blocks_invert_stably() {
        let check = |a: Mat3| -> f64 {
            let inv = spd_inverse(a).as_dmat3();
            let r = inv * a.as_dmat3() - glam::DMat3::IDENTITY;
            r.to_cols_array().iter().fold(0.0f64, |m, v| m.max(v.abs()))
        };
        let well = Mat3::from_cols(
            Vec3::new(4.0, 1.0, 0.5),
            Vec3::new(1.0, 3.0, 0.2),
            Vec3::new(0.5, 0.2, 2.0),
        );
        assert!(check(well) < 1e-6, "{}", check(well));
        let n = Vec3::new(0.6, 0.7, -0.4).normalize();
        let loaded = Mat3::from_cols(n * n.x, n * n.y, n * n.z) * 2.4e5
            + Mat3::from_diagonal(Vec3::new(0.6, 0.9, 0.7));
        let err = check(loaded);
        assert!(err < 0.05, "Cholesky inverse off by {err}");
        let cofactor = loaded.inverse().as_dmat3() * loaded.as_dmat3() - glam::DMat3::IDENTITY;
        let cofactor = cofactor
            .to_cols_array()
            .iter()
            .fold(0.0f64, |m, v| m.max(v.abs()));
        eprintln!("loaded block: Cholesky inverse off by {err:.2e}, cofactors by {cofactor:.2e}");
        let indefinite = Mat3::from_diagonal(Vec3::new(1.0, -1.0, 1.0));
        assert_eq!(spd_inverse(indefinite), Mat3::ZERO);
        assert_eq!(spd_inverse(Mat3::ZERO), Mat3::ZERO);
    }

    /// V(2, 2) with 30 on the coarsest (what these tests were written with).
    const V22: Sweeps = Sweeps {
        fine: 2,
        fine_before: 2,
        coarse: 2,
        coarse_before: 2,
        coarsest: 30,
        exact_coarsest: false,
        translation: true,
    };

    #[test]
    fn sweeps_are_counted_per_level_and_checked() {
        let odd = Sweeps {
            fine: 1,
            fine_before: 1,
            coarse: 3,
            coarse_before: 3,
            coarsest: 9,
            exact_coarsest: false,
            translation: true,
        };
        assert!(odd.check().is_ok());
        // Gauss–Seidel takes the counts as they are; Chebyshev in pairs.
        assert_eq!(odd.on_level(0, false, Smoother::Hybrid), 1);
        assert_eq!(odd.on_level(1, false, Smoother::Hybrid), 4);
        assert_eq!(odd.on_level(2, true, Smoother::Hybrid), 10);
        assert_eq!(odd.on_level(0, false, Smoother::Chebyshev), 2);
        assert_eq!(odd.on_level(1, false, Smoother::GaussSeidel), 3);
        assert_eq!(odd.on_level(2, true, Smoother::GaussSeidel), 9);
        // A single level is the coarsest.
        assert_eq!(odd.on_level(0, true, Smoother::Hybrid), 9);
        let none = Sweeps { coarsest: 0, ..odd };
        let err = none.check().unwrap_err().to_string();
        assert!(err.contains("sweeps.coarsest"), "{err}");
        assert!(Sweeps { fine: 5000, ..odd }.check().is_err());
        // Level 0's sweeps before the correction: any count from 0, in pairs under
        // Chebyshev; the other levels' are their count after.
        let after = Sweeps {
            fine_before: 0,
            ..odd
        };
        assert!(after.check().is_ok());
        assert_eq!(after.before_on_level(0, Smoother::Hybrid), 0);
        assert_eq!(after.before_on_level(0, Smoother::Chebyshev), 0);
        assert_eq!(odd.before_on_level(0, Smoother::Chebyshev), 2);
        assert_eq!(after.before_on_level(1, Smoother::Hybrid), 4);
        // The levels between's before the correction: from 0 too, in pairs under
        // Chebyshev, and only on those levels.
        let plain = Sweeps {
            coarse_before: 0,
            ..odd
        };
        assert!(plain.check().is_ok());
        assert_eq!(plain.before_on_level(1, Smoother::Hybrid), 0);
        assert_eq!(plain.on_level(1, false, Smoother::Hybrid), 4);
        assert_eq!(plain.before_on_level(0, Smoother::Hybrid), 1);
        assert_eq!(
            Sweeps {
                coarse_before: 1,
                ..odd
            }
            .before_on_level(1, Smoother::Hybrid),
            2
        );
        let err = Sweeps {
            coarse_before: 1001,
            ..odd
        }
        .check()
        .unwrap_err()
        .to_string();
        assert!(err.contains("sweeps.coarse_before"), "{err}");
        assert_eq!(after.on_level(0, false, Smoother::Hybrid), 1);
        let err = Sweeps {
            fine_before: 1001,
            ..odd
        }
        .check()
        .unwrap_err()
        .to_string();
        assert!(err.contains("sweeps.fine_before"), "{err}");
    }

    #[test]
    fn vcycle_contracts() {
        for (spacing, bound, smoother) in [
            (0.00375f32, 0.05f32, Smoother::GaussSeidel),
            (0.006, 0.1, Smoother::GaussSeidel),
            (0.00375f32, 0.05f32, Smoother::Chebyshev),
            (0.006, 0.1, Smoother::Chebyshev),
            (0.00375f32, 0.05f32, Smoother::Hybrid),
            (0.006, 0.1, Smoother::Hybrid),
        ] {
            let model = bar(spacing);
            let mut mg = LatticeMultigrid::new(&model, 64, 8);
            mg.smoother = smoother;
            eprintln!("{smoother:?} chebyshev {:?}", mg.chebyshev);
            assert!(mg.levels.len() >= 3, "levels {}", mg.levels.len());
            for h in [1.0f32 / 600.0, 1.0 / 60.0] {
                let h2 = h * h;
                let mut work = MgWork::default();
                let rot = vec![Quat::IDENTITY; model.elements.len()];
                mg.prepare(&rot, h2, &mut work);
                for j in 0..model.particle_count() {
                    work.rhs[0][j] = if mg.levels[0].fixed[j] {
                        Vec3::ZERO
                    } else {
                        Vec3::new(0.0, -0.2 * model.mass[j], 0.0)
                    };
                }
                let r0 = residual_norm(&mg, h2, &work);
                for _ in 0..6 {
                    mg.vcycle(0, h2, V22, &mut work);
                }
                let r6 = residual_norm(&mg, h2, &work) / r0;
                eprintln!("{smoother:?} spacing {spacing} h {h}: {r6}");
                assert!(
                    r6 < bound,
                    "spacing {spacing}, h {h}: residual after 6 cycles {r6}"
                );
            }
        }
    }

    /// The exact coarsest solve leaves no residual on the coarsest level (relative to its
    /// right-hand side, in f32), fixed nodes at zero, where 30 Chebyshev sweeps leave
    /// some; turned and loaded like a substep mid-bend (random rotations, contact blocks
    /// on some nodes). With two bodies, each body's system is solved on its own.
    #[test]
    fn the_exact_coarsest_solve_leaves_no_coarsest_residual() {
        let mut model = bar(0.006);
        model.append(&bar(0.0075));
        let exact = Sweeps {
            exact_coarsest: true,
            translation: true,
            ..Sweeps::DEFAULT
        };
        let mut mg = LatticeMultigrid::new(&model, exact.min_nodes(), MAX_LEVELS);
        mg.smoother = Smoother::Hybrid;
        let l = mg.levels.len() - 1;
        assert!(mg.coarsest_exact(exact), "levels {}", mg.levels.len());
        assert_eq!(mg.levels[l].body_start.len(), 3);
        let swept = Sweeps {
            exact_coarsest: false,
            translation: true,
            ..exact
        };
        assert!(!mg.coarsest_exact(swept));
        let h2 = (1.0f32 / 60.0).powi(2);
        let rot: Vec<Quat> = (0..model.elements.len())
            .map(|e| Quat::from_axis_angle(Vec3::new(1.0, 2.0, 0.5).normalize(), 0.01 * e as f32))
            .collect();
        // A contact penalty k n nᵀ (n = y) on every seventh particle.
        let contact = Mat3::from_diagonal(Vec3::new(0.0, 1e4, 0.0));
        let mut work = MgWork {
            extra: vec![
                (0..model.particle_count())
                    .map(|j| if j % 7 == 0 { contact } else { Mat3::ZERO })
                    .collect(),
            ],
            ..Default::default()
        };
        mg.prepare(&rot, h2, &mut work);
        let lv = &mg.levels[l];
        let rhs: Vec<Vec3> = (0..lv.nodes)
            .map(|j| {
                if lv.fixed[j] {
                    Vec3::ZERO
                } else {
                    Vec3::new((j as f32).sin(), (0.3 * j as f32).cos(), 0.5) * 1e-3
                }
            })
            .collect();
        let residual = |work: &MgWork| -> f32 {
            let (mut r, mut b) = (0.0f32, 0.0f32);
            for (j, bj) in rhs.iter().enumerate() {
                if !lv.fixed[j] {
                    let aj = mg.apply_row(l, j, &work.delta[l], h2, work);
                    r = r.max((*bj - aj).length());
                    b = b.max(bj.length());
                }
            }
            r / b
        };
        let mut left = [0.0f32; 2];
        for (k, sweeps) in [exact, swept].into_iter().enumerate() {
            work.rhs[l] = rhs.clone();
            work.delta[l].iter_mut().for_each(|d| *d = Vec3::ZERO);
            mg.vcycle(l, h2, sweeps, &mut work);
            left[k] = residual(&work);
            if k == 0 {
                assert!((0..lv.nodes).all(|j| !lv.fixed[j] || work.delta[l][j] == Vec3::ZERO));
            }
        }
        eprintln!(
            "coarsest residual: exact {:.2e}, 30 sweeps {:.2e}",
            left[0], left[1]
        );
        assert!(left[0] < 1e-3, "exact: {}", left[0]);
        assert!(left[1] > 10.0 * left[0], "swept: {}", left[1]);
    }

    /// A V-cycle leaves the nodes held in its solve ([`MgWork::held`]) at zero
    /// correction and moves the others; without them held it moves those too.
    #[test]
    fn a_vcycle_keeps_held_nodes_still() {
        let (model, mg, h2, rot, held) = bar_system(13, 4);
        let n = model.particle_count();
        let run = |hold: bool| {
            let mut work = MgWork::default();
            mg.prepare(&rot, h2, &mut work);
            for j in 0..n {
                work.rhs[0][j] = Vec3::new(0.0, -0.2 * model.mass[j], 0.0);
            }
            if hold {
                work.held = held.clone();
            }
            mg.vcycle(0, h2, Sweeps::DEFAULT, &mut work);
            work.delta[0].clone()
        };
        let (kept, free) = (run(true), run(false));
        let count = held.iter().filter(|&&h| h).count();
        assert!(count > 10, "{count} held");
        for j in (0..n).filter(|&j| held[j]) {
            assert_eq!(kept[j], Vec3::ZERO, "held node {j}");
            assert!(free[j].length() > 0.0, "node {j} unheld");
        }
        let moved = (0..n)
            .filter(|&j| !held[j] && kept[j].length() > 0.0)
            .count();
        assert!(moved > n / 2, "{moved} of {n} moved");
    }

    /// The two-direction weights solve their 2 × 2 system (the model's gradient along
    /// both directions is zero), and fall back to the first direction's own step where
    /// the second adds little (zero, or within about 6° of the first) or nothing is
    /// finite.
    #[test]
    fn two_direction_weights_minimise_the_model() {
        for t in [
            [2.0, 0.5, 1.0, 1.0, 0.25],
            [1.0e-3, -2.0e-4, 5.0e-3, 3.0e-4, -1.0e-4],
            [4.0, 3.9, 4.0, 1.0, 1.2],
        ] {
            let [zz, pz, pp, rz, rp] = t;
            let (a, b) = two_direction_weights(t);
            let (a, b) = (a as f64, b as f64);
            for (got, want) in [(zz * a + pz * b, rz), (pz * a + pp * b, rp)] {
                assert!(
                    (got - want).abs() <= 1e-5 * want.abs().max(zz * a.abs()),
                    "{t:?}"
                );
            }
        }
        assert_eq!(two_direction_weights([2.0, 0.0, 0.0, 1.0, 0.0]), (0.5, 0.0));
        // p = 2 z: parallel.
        assert_eq!(two_direction_weights([1.0, 2.0, 4.0, 3.0, 6.0]), (3.0, 0.0));
        assert_eq!(two_direction_weights([0.0; 5]), (0.0, 0.0));
        assert_eq!(
            two_direction_weights([f64::NAN, 0.0, 1.0, 1.0, 1.0]),
            (0.0, 0.0)
        );
    }

    /// The two-direction step on the cantilever's 1/60 s substep system: with no last
    /// answer it is the V-cycle's correction scaled by its energy-minimising step
    /// (conjugate gradients of one cycle); given the system's own answer as the last, it
    /// returns that answer (the model's minimum over a span that contains it); given a
    /// last answer of a nearby system (gravity 10% stronger), it leaves a smaller error
    /// than one or two cycles of conjugate gradients. Held nodes stay at zero, and the
    /// answer is kept for the next step.
    #[test]
    fn the_two_direction_step_uses_the_last_answer() {
        let (model, mg, h2, rot, held) = bar_system(97, 5);
        let n = model.particle_count();
        let free = |j: usize| !held[j] && !mg.levels[0].fixed[j];
        let fresh = |g: f32| {
            let mut work = MgWork::default();
            mg.prepare(&rot, h2, &mut work);
            for j in 0..n {
                work.rhs[0][j] = if free(j) {
                    Vec3::new(0.0, -g * model.mass[j], 0.0)
                } else {
                    Vec3::ZERO
                };
            }
            work
        };
        let b = fresh(0.2);
        let error = |delta: &[Vec3], exact: &[Vec3]| -> f32 {
            let d: Vec<Vec3> = (0..n).map(|j| delta[j] - exact[j]).collect();
            let ea: f32 = (0..n)
                .filter(|&j| free(j))
                .map(|j| d[j].dot(mg.apply_row(0, j, &d, h2, &b)))
                .sum();
            let xa: f32 = (0..n)
                .filter(|&j| free(j))
                .map(|j| exact[j].dot(mg.apply_row(0, j, exact, h2, &b)))
                .sum();
            (ea / xa).sqrt()
        };
        let mut exact = fresh(0.2);
        mg.krylov(h2, 40, Sweeps::DEFAULT, &held, &mut exact);
        let exact = exact.delta[0].clone();
        // No last answer: conjugate gradients' one cycle.
        let mut first = fresh(0.2);
        mg.two_direction(h2, Sweeps::DEFAULT, &held, &mut first);
        let mut cg1 = fresh(0.2);
        mg.krylov(h2, 1, Sweeps::DEFAULT, &held, &mut cg1);
        for (j, x) in exact.iter().enumerate() {
            assert!(
                first.delta[0][j].distance(cg1.delta[0][j]) <= 1e-5 * x.length() + 1e-9,
                "node {j}"
            );
        }
        assert_eq!(first.last, first.delta[0]);
        // The answer itself as the last.
        let mut again = fresh(0.2);
        again.last = exact.clone();
        mg.two_direction(h2, Sweeps::DEFAULT, &held, &mut again);
        let e = error(&again.delta[0], &exact);
        assert!(e < 1e-3, "the exact answer given: error {e}");
        // A nearby system's answer as the last.
        let mut near = fresh(0.22);
        mg.krylov(h2, 40, Sweeps::DEFAULT, &held, &mut near);
        let mut two = fresh(0.2);
        two.last = near.delta[0].clone();
        mg.two_direction(h2, Sweeps::DEFAULT, &held, &mut two);
        let mut cg2 = fresh(0.2);
        mg.krylov(h2, 2, Sweeps::DEFAULT, &held, &mut cg2);
        let (e2, e_cg1, e_cg2) = (
            error(&two.delta[0], &exact),
            error(&cg1.delta[0], &exact),
            error(&cg2.delta[0], &exact),
        );
        eprintln!("error: two-direction {e2:.3e}, CG 1 {e_cg1:.3e}, CG 2 {e_cg2:.3e}");
        assert!(e2 < e_cg1 && e2 < e_cg2, "{e2} against {e_cg1}, {e_cg2}");
        for j in (0..n).filter(|&j| !free(j)) {
            assert_eq!(two.delta[0][j], Vec3::ZERO, "held node {j}");
        }
    }

    /// Conjugate gradients preconditioned by the V-cycle ([`LatticeMultigrid::krylov`])
    /// on the cantilever's 1/60 s substep system. What they minimise, the error's energy
    /// `φ(δ) − φ*` (`φ(δ) = ½ δᵀ A δ − bᵀ δ`; `φ*` its minimum, from 40 cycles), falls
    /// with every added cycle, below what as many plain V-cycles leave, and in 8 cycles
    /// to within 1e-5 of the start's (what f32 resolves); the residual left in `rhs` is
    /// the true one. With some free nodes
    /// held (as grasped ones are), they stay at zero and the rest converges, more slowly.
    #[test]
    fn krylov_beats_as_many_vcycles() {
        let (model, mg, h2, rot, some) = bar_system(97, 5);
        let n = model.particle_count();
        let none = vec![false; n];
        for held in [&none, &some] {
            let free = |j: usize| !held[j] && !mg.levels[0].fixed[j];
            let fresh = || {
                let mut work = MgWork::default();
                mg.prepare(&rot, h2, &mut work);
                for j in 0..n {
                    work.rhs[0][j] = if free(j) {
                        Vec3::new(0.0, -0.2 * model.mass[j], 0.0)
                    } else {
                        Vec3::ZERO
                    };
                }
                work
            };
            let b = fresh();
            // φ(δ) over the free rows, and each free row's residual.
            let phi = |delta: &[Vec3]| {
                let mut value = 0.0f64;
                let rows: Vec<Vec3> = (0..n)
                    .map(|j| {
                        if !free(j) {
                            return Vec3::ZERO;
                        }
                        let ad = mg.apply_row(0, j, delta, h2, &b);
                        value += (0.5 * delta[j].dot(ad) - b.rhs[0][j].dot(delta[j])) as f64;
                        b.rhs[0][j] - ad
                    })
                    .collect();
                (value, rows)
            };
            let mut best = fresh();
            mg.krylov(h2, 40, V22, held, &mut best);
            let least = phi(&best.delta[0]).0;
            let gap = |delta: &[Vec3]| (phi(delta).0 - least) / -least;
            let mut last = f64::MAX;
            for cycles in [1u32, 2, 3] {
                let mut work = fresh();
                mg.krylov(h2, cycles, V22, held, &mut work);
                let e = gap(&work.delta[0]);
                let mut plain = fresh();
                for _ in 0..cycles {
                    mg.vcycle(0, h2, V22, &mut plain);
                }
                let plain_e = gap(&plain.delta[0]);
                eprintln!("{cycles} cycles: CG {e:.3e}, plain V-cycles {plain_e:.3e}");
                assert!(e < last, "{cycles} cycles: {e} after {last}");
                if cycles > 1 && held == &none {
                    assert!(e < plain_e, "{cycles} cycles: CG {e}, V-cycles {plain_e}");
                }
                let rows = phi(&work.delta[0]).1;
                let scale = rows.iter().map(|r| r.length()).fold(0.0f32, f32::max);
                for (j, row) in rows.iter().enumerate() {
                    if !free(j) {
                        assert_eq!(work.delta[0][j], Vec3::ZERO);
                        continue;
                    }
                    assert!(
                        (work.rhs[0][j] - *row).length() <= 1e-3 * scale + 1e-6,
                        "node {j}: residual kept {} against {row}",
                        work.rhs[0][j],
                    );
                }
                last = e;
            }
            // 8 cycles: as near the minimum as f32 resolves it; with held nodes, which
            // the V-cycle moves (only its levels' fixed nodes it keeps), more slowly.
            let mut work = fresh();
            mg.krylov(h2, 8, V22, held, &mut work);
            let e = gap(&work.delta[0]);
            let bound = if held == &none { 1e-5 } else { 1e-3 };
            assert!(e.abs() < bound, "8 cycles leave {e}");
        }
    }

    /// Four bodies built alone: a pinned lattice box, a cluster body (no elements: only
    /// held nodes on the finest level), a lattice liver and a lattice body of one cell.
    fn separate_bodies() -> Vec<Model> {
        let hyper = |e: f32| Material::Hyperelastic {
            youngs_modulus: e,
            poisson_ratio: 0.45,
        };
        let lattice = |particles: u32, e: f32, at: Vec3, pins: Vec<PinRegion>| BodyDesc {
            resolution: Resolution::Particles(particles),
            material: hyper(e),
            discretisation: Discretisation::Lattice,
            translation: at,
            pins,
            ..Default::default()
        };
        let one = |mesh: &crate::core::mesh::TriMesh, desc: &BodyDesc| {
            let mut m = Model::new();
            m.add_body(mesh, desc).unwrap();
            m
        };
        vec![
            one(
                &procedural::cuboid(Vec3::new(0.11, 0.05, 0.07), 1),
                &lattice(
                    600,
                    2e4,
                    Vec3::ZERO,
                    vec![PinRegion::HalfSpace {
                        point: Vec3::new(-0.08, 0.0, 0.0),
                        normal: -Vec3::X,
                    }],
                ),
            ),
            one(
                &procedural::cuboid(Vec3::splat(0.05), 1),
                &BodyDesc {
                    resolution: Resolution::Particles(200),
                    material: Material::ShapeMatching { stiffness: 0.8 },
                    discretisation: Discretisation::Clusters,
                    translation: Vec3::X,
                    ..Default::default()
                },
            ),
            one(&procedural::liver(3), &lattice(3000, 5e3, Vec3::Y, vec![])),
            one(
                &procedural::cuboid(Vec3::splat(0.02), 1),
                &lattice(8, 1e5, Vec3::Z, vec![]),
            ),
        ]
    }

    /// Levels built per body, each from a model of that body alone, and joined, are the
    /// levels built for the model of all of them: the hierarchy does not depend on which
    /// bodies were built together.
    #[test]
    fn levels_joined_from_bodies_are_the_whole_models() {
        let bodies = separate_bodies();
        let mut whole = Model::new();
        for b in &bodies {
            whole.append(b);
        }
        let parts: Vec<BodyLevels> = bodies.iter().map(|b| BodyLevels::new(b, 0)).collect();
        let refs: Vec<&BodyLevels> = parts.iter().collect();
        let joined = LatticeMultigrid::from_bodies(&refs, MIN_NODES, MAX_LEVELS);
        let built = LatticeMultigrid::new(&whole, MIN_NODES, MAX_LEVELS);
        assert!(built.levels.len() >= 2, "{} levels", built.levels.len());
        assert_eq!(joined.levels.len(), built.levels.len());
        for (l, (a, b)) in joined.levels.iter().zip(&built.levels).enumerate() {
            assert!(a == b, "level {l} differs");
        }
        assert_eq!(joined.unit, built.unit);
        assert_eq!(joined.chebyshev, built.chebyshev);
        // The same bodies in another order: each body's levels are found, shifted, in
        // the other order's hierarchy.
        let flipped = LatticeMultigrid::from_bodies(
            &[&parts[2], &parts[0], &parts[3], &parts[1]],
            MIN_NODES,
            MAX_LEVELS,
        );
        let n0 = bodies[2].particle_count();
        let e0 = bodies[2].elements.len() as u32;
        let a = &flipped.levels[0];
        let own = &parts[0].levels[0];
        for (e, el) in own.elements.iter().enumerate() {
            assert_eq!(a.elements[e0 as usize + e], el.map(|j| j + n0 as u32));
        }
        assert_eq!(&a.mass[n0..n0 + own.nodes], &own.mass[..]);
    }

    /// The joined hierarchy is consistent level by level: each node's element list names
    /// elements that have it at that corner; an element's corners are nodes of its own
    /// body; each colour is a set of nodes no two of which share an element, and the
    /// colours together are every node once; prolongation weights of a node inside a
    /// body's lattice sum to 1 over coarse nodes of its own body; every element has
    /// exactly one coarse parent, of its own body.
    #[test]
    fn joined_levels_are_consistent() {
        let bodies = separate_bodies();
        let parts: Vec<BodyLevels> = bodies.iter().map(|b| BodyLevels::new(b, 0)).collect();
        let refs: Vec<&BodyLevels> = parts.iter().collect();
        let mg = LatticeMultigrid::from_bodies(&refs, MIN_NODES, MAX_LEVELS);
        // Each node's body, from the elements (u32::MAX: no element).
        let node_body = |lv: &MgLevel| {
            let mut nb = vec![u32::MAX; lv.nodes];
            for (el, &b) in lv.elements.iter().zip(&lv.body) {
                for &j in el {
                    assert!(nb[j as usize] == u32::MAX || nb[j as usize] == b);
                    nb[j as usize] = b;
                }
            }
            nb
        };
        for (l, lv) in mg.levels.iter().enumerate() {
            let nb = node_body(lv);
            for j in 0..lv.nodes {
                let list = &lv.inv[lv.inv_start[j] as usize..lv.inv_start[j + 1] as usize];
                for &ec in list {
                    assert_eq!(lv.elements[(ec >> 3) as usize][(ec & 7) as usize], j as u32);
                }
            }
            let corners: usize = lv.elements.len() * CORNERS;
            assert_eq!(lv.inv.len(), corners, "level {l}: corner lists");
            let mut seen = vec![false; lv.nodes];
            for c in 0..COLOURS {
                let colour =
                    &lv.order[lv.colour_start[c] as usize..lv.colour_start[c + 1] as usize];
                let mut touched = std::collections::HashSet::new();
                for &j in colour {
                    assert!(!std::mem::replace(&mut seen[j as usize], true));
                    let list = &lv.inv
                        [lv.inv_start[j as usize] as usize..lv.inv_start[j as usize + 1] as usize];
                    for &ec in list {
                        assert!(
                            touched.insert(ec >> 3),
                            "level {l}: colour {c} shares an element"
                        );
                    }
                }
            }
            assert!(
                seen.iter().all(|&s| s),
                "level {l}: a node without a colour"
            );
            let Some(coarse) = mg.levels.get(l + 1) else {
                assert!(lv.prolong_start.is_empty() && lv.child_start.is_empty());
                continue;
            };
            let cb = node_body(coarse);
            for (j, &body) in nb.iter().enumerate() {
                let r = lv.prolong_start[j] as usize..lv.prolong_start[j + 1] as usize;
                if body == u32::MAX {
                    assert!(r.is_empty());
                    continue;
                }
                let sum: f32 = lv.prolong_weight[r.clone()].iter().sum();
                assert!(
                    (sum - 1.0).abs() < 1e-5,
                    "level {l}, node {j}: weights sum to {sum}"
                );
                for &k in &lv.prolong_node[r] {
                    assert_eq!(
                        cb[k as usize], body,
                        "level {l}: prolongation across bodies"
                    );
                }
            }
            let mut parent = vec![u32::MAX; lv.elements.len()];
            for c in 0..coarse.elements.len() {
                for &e in &lv.child[lv.child_start[c] as usize..lv.child_start[c + 1] as usize] {
                    assert_eq!(parent[e as usize], u32::MAX, "level {l}: two parents");
                    parent[e as usize] = c as u32;
                    assert_eq!(lv.body[e as usize], coarse.body[c]);
                }
            }
            assert!(
                parent.iter().all(|&p| p != u32::MAX),
                "level {l}: an orphan"
            );
        }
    }
}
