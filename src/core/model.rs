//! The model: everything that does not change while simulating (rest positions, masses,
//! clusters, inverse lists, pins, skin), for any number of bodies batched in flat
//! struct-of-arrays buffers laid out the way the GPU wants them (f32/u32, particles in
//! spatial order per body, clusters and inverse lists as CSR index arrays), so that an
//! upload is a copy. The time-varying part is [`super::solver::State`] (Newton's
//! Model / State / Control split).

use super::constraints::{ClusterRest, init_cluster};
use super::element::{CORNERS, ElementRest};
use super::error::{TissueError, in_range, positive};
use super::hierarchy::{Hierarchy, HierarchyDesc};
use super::mesh::{Surface, TriMesh};
use super::sampling::{Resolution, Voxels, sample, voxelize};
use super::skin::{Skin, embed};
use glam::{Quat, Vec3};

/// Largest neighbour count K supported.
pub const MAX_NEIGHBOURS: u32 = 128;

/// The elastic model of a body.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Material {
    /// Shape matching (Müller et al. 2005), the paper's model.
    ShapeMatching {
        /// Stiffness k in (0, 1] reached after all iterations of a substep.
        stiffness: f32,
    },
    /// XPBD hyperelasticity on clusters: fixed-corotated energy (Stomakhin et al. 2012) as
    /// deviatoric + hydrostatic constraints (Macklin & Müller 2021's split, both zero at
    /// rest; see [`super::constraints::Hyperelastic`]). Stiffness set in SI units, independent of time step and
    /// iteration count once converged.
    Hyperelastic {
        /// Young's modulus E, Pa.
        youngs_modulus: f32,
        /// Poisson ratio ν in [0, 0.5).
        poisson_ratio: f32,
    },
}

impl Default for Material {
    /// Soft tissue: E = 10 kPa, ν = 0.45.
    fn default() -> Self {
        Material::Hyperelastic {
            youngs_modulus: 10_000.0,
            poisson_ratio: 0.45,
        }
    }
}

impl Material {
    /// Checks the parameters.
    pub fn validate(&self) -> Result<(), TissueError> {
        match *self {
            Material::ShapeMatching { stiffness } => {
                in_range(
                    "stiffness",
                    stiffness,
                    f32::MIN_POSITIVE,
                    1.0,
                    "a value in (0, 1]",
                )?;
            }
            Material::Hyperelastic {
                youngs_modulus,
                poisson_ratio,
            } => {
                positive("youngs_modulus", youngs_modulus)?;
                in_range(
                    "poisson_ratio",
                    poisson_ratio,
                    0.0,
                    0.4999,
                    "a value in [0, 0.5)",
                )?;
            }
        }
        Ok(())
    }
}

/// How a body's elastic energy is discretised over its particles.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Discretisation {
    /// The paper's clusters: each particle and its K nearest rest neighbours, sampled
    /// inside the surface, with a least-squares deformation gradient (a generalised
    /// tetrahedron; Müller et al. 2005, 2022). Fast and robust, but its hyperelastic
    /// material is softer than E and ν say and does not converge to them as the
    /// resolution grows (BENCHMARKS.md, "Accuracy against FEM").
    Clusters,
    /// Hexahedral finite elements on the sampling lattice: the lattice cells whose
    /// centres are inside the surface, with their corners as particles; each cell's
    /// centre gradient and hourglass modes ([`super::element`]). Converges to the
    /// material set (a finite-element discretisation with the incompatible-mode
    /// hexahedron's stiffness). Hyperelastic material only; no hierarchy. The default:
    /// solved by Newton–multigrid ([`super::solver::ElementSolver::Multigrid`]) on the
    /// CPU ([`super::solver::Solver`]) or the GPU (`gpu::lattice::GpuLattice`).
    #[default]
    Lattice,
}

/// A region of the rest shape whose particles are pinned (held at a kinematic target).
#[derive(Debug, Clone, PartialEq)]
pub enum PinRegion {
    /// Axis-aligned box in the body frame, m.
    Box {
        /// Lower corner, m.
        min: Vec3,
        /// Upper corner, m.
        max: Vec3,
    },
    /// Ball in the body frame.
    Sphere {
        /// Centre, m.
        center: Vec3,
        /// Radius, m.
        radius: f32,
    },
    /// Every particle on the side of the plane its normal points to.
    HalfSpace {
        /// A point on the plane, m.
        point: Vec3,
        /// Normal (need not be unit).
        normal: Vec3,
    },
    /// Particles by index within the body (sampling order).
    Indices(Vec<u32>),
}

impl PinRegion {
    fn contains(&self, i: u32, p: Vec3) -> bool {
        match self {
            PinRegion::Box { min, max } => p.cmpge(*min).all() && p.cmple(*max).all(),
            PinRegion::Sphere { center, radius } => p.distance_squared(*center) <= radius * radius,
            PinRegion::HalfSpace { point, normal } => (p - *point).dot(*normal) >= 0.0,
            PinRegion::Indices(list) => list.contains(&i),
        }
    }
}

/// Everything needed to build one body.
#[derive(Debug, Clone, PartialEq)]
pub struct BodyDesc {
    /// Sampling resolution (spacing in m, or a particle count).
    pub resolution: Resolution,
    /// Density, kg/m³ (soft tissue ≈ 1060).
    pub density: f32,
    /// Neighbour count K: each cluster is a particle and its K nearest rest neighbours.
    pub neighbours: u32,
    /// Elastic model and its parameters.
    pub material: Material,
    /// Pinned regions.
    pub pins: Vec<PinRegion>,
    /// Rigid placement of the body frame in the world: translation, m.
    pub translation: Vec3,
    /// Rigid placement of the body frame in the world: rotation.
    pub rotation: Quat,
    /// Hierarchical PBD (Müller 2008): the coarse levels to build, or `None` for a flat
    /// body. Solved only when the solver's schedule asks for it
    /// ([`super::solver::SolverSettings::coarse_iterations`]).
    pub hierarchy: Option<HierarchyDesc>,
    /// Clusters (the paper's, with `neighbours` = K) or hexahedral lattice elements.
    pub discretisation: Discretisation,
}

impl Default for BodyDesc {
    /// A lattice body ([`Discretisation::Lattice`]) of soft tissue: hyperelastic,
    /// E = 10 kPa, ν = 0.45 ([`Material::default`]), 1060 kg/m³, 4,096 particles
    /// ([`Resolution::default`]), unpinned, at the origin.
    fn default() -> Self {
        Self {
            resolution: Resolution::default(),
            density: 1060.0,
            neighbours: 32,
            material: Material::default(),
            pins: Vec::new(),
            translation: Vec3::ZERO,
            rotation: Quat::IDENTITY,
            hierarchy: None,
            discretisation: Discretisation::Lattice,
        }
    }
}

/// One body's slice of the batched model.
#[derive(Debug, Clone)]
pub struct BodyInfo {
    /// First particle (and cluster) index.
    pub first: u32,
    /// Particle (and cluster) count.
    pub count: u32,
    /// Elastic model.
    pub material: Material,
    /// Neighbour count K.
    pub neighbours: u32,
    /// Density, kg/m³.
    pub density: f32,
    /// Lattice spacing, m.
    pub spacing: f32,
    /// Contact radius of each particle (half the spacing), m.
    pub radius: f32,
    /// Enclosed rest volume, m³.
    pub volume: f32,
    /// Diagonal of the rest bounding box, m (the "size" used by tolerances).
    pub size: f32,
    /// World placement at build time: translation, m.
    pub translation: Vec3,
    /// World placement at build time: rotation.
    pub rotation: Quat,
    /// The render surface embedded in the particles.
    pub skin: Skin,
    /// True when the input surface was inside-out and was flipped.
    pub flipped: bool,
    /// Clusters or lattice elements.
    pub discretisation: Discretisation,
}

impl BodyInfo {
    /// Particle index range.
    pub fn range(&self) -> std::ops::Range<usize> {
        self.first as usize..(self.first + self.count) as usize
    }
}

/// All bodies' rest data, batched.
#[derive(Debug, Clone, Default)]
pub struct Model {
    /// Bodies in insertion order.
    pub bodies: Vec<BodyInfo>,
    /// Rest positions in each body's frame, m.
    pub rest: Vec<Vec3>,
    /// Particle masses, kg.
    pub mass: Vec<f32>,
    /// Body of each particle.
    pub particle_body: Vec<u32>,
    /// CSR offsets of cluster members (cluster `c` is centred on particle `c`).
    pub cluster_start: Vec<u32>,
    /// Cluster members (global particle indices); the centre particle comes first.
    pub cluster_members: Vec<u32>,
    /// Rest data per cluster.
    pub cluster_rest: Vec<ClusterRest>,
    /// The cluster's share of its body's rest volume, m³ (partition of unity over clusters).
    pub cluster_volume: Vec<f32>,
    /// Jacobi weight `1/s_c`, `s_c` = the largest number of clusters any member belongs to.
    pub cluster_weight: Vec<f32>,
    /// CSR offsets of the inverse lists (clusters containing each particle).
    pub inv_start: Vec<u32>,
    /// Clusters containing each particle, ascending.
    pub inv_clusters: Vec<u32>,
    /// Pinned particles (global indices).
    pub pinned: Vec<u32>,
    /// Coarse levels of hierarchical PBD, level 1 first (empty: every body is flat). A
    /// body with fewer levels than another is simply absent from the deeper ones.
    pub levels: Vec<Level>,
    /// Hexahedral elements of [`Discretisation::Lattice`] bodies: each one's eight
    /// particles (global indices) in [`super::element::corner_sign`] order. The particles
    /// of such bodies own no cluster (their cluster runs are empty).
    pub elements: Vec<[u32; CORNERS]>,
    /// Rest data per element.
    pub element_rest: Vec<ElementRest>,
    /// Body of each element.
    pub element_body: Vec<u32>,
    /// CSR offsets of each particle's elements.
    pub inv_element_start: Vec<u32>,
    /// Elements containing each particle, as `element << 3 | corner`, ascending.
    pub inv_elements: Vec<u32>,
}

/// One coarse level of the hierarchy (Müller 2008), batched over all bodies that have it.
///
/// Its particles are a subset of the finer level's, which are a subset of level 0's: a
/// coarse particle is a level-0 particle that also carries coarse clusters. Each is a
/// particle of [`Level::model`] (its own compact indices, rest positions, masses, clusters
/// and pins, the body's material), so a level is solved by the same code as level 0.
/// After a level is solved, the finer level's particles that are not on it follow their
/// parents by prolongation: `Δx_i = Σ_j w_ij Δx_j`.
#[derive(Debug, Clone, Default)]
pub struct Level {
    /// The level's particles and coarse clusters as a model: masses are the finer
    /// level's restricted by the interpolation weights (`M_j = Σ_i w_ij m_i`, so the total
    /// is kept), clusters are each particle's K nearest level particles, cluster volumes
    /// partition the body (so hyperelastic coarse clusters have the fine level's energy
    /// density: matched compliance). No skin.
    pub model: Model,
    /// Level-0 index of each of the level's particles.
    pub source: Vec<u32>,
    /// Level-0 indices of the finer level's particles that are not on this level; they
    /// follow this level by prolongation.
    pub fine: Vec<u32>,
    /// CSR offsets into `parents`/`weights`, one run per `fine` entry.
    pub parent_start: Vec<u32>,
    /// Parents of each `fine` particle, as indices into this level's particles.
    pub parents: Vec<u32>,
    /// Interpolation weights (per `fine` particle they sum to 1).
    pub weights: Vec<f32>,
    /// Multiplier transfer to the finer level: the finer level's clusters that receive
    /// (indices into level 0's particles for level 1, else into the finer level's model).
    pub transfer_cluster: Vec<u32>,
    /// One CSR run per `transfer_cluster` entry: offsets into
    /// `transfer_parents`/`transfer_weights`.
    pub transfer_start: Vec<u32>,
    /// This level's clusters each finer cluster takes its multipliers from (itself when
    /// its centre is on this level, else its centre's parents).
    pub transfer_parents: Vec<u32>,
    /// `w_ij V_i / V_j`: interpolation weight times the volume ratio (an XPBD multiplier
    /// is stress × volume × h², so it scales with the cluster volume).
    pub transfer_weights: Vec<f32>,
}

impl Level {
    /// An empty level.
    pub fn new() -> Self {
        Self {
            model: Model::new(),
            parent_start: vec![0],
            transfer_start: vec![0],
            ..Default::default()
        }
    }
}

/// Index of a body in a [`Model`].
pub type BodyId = usize;

impl Model {
    /// An empty model.
    pub fn new() -> Self {
        Self {
            cluster_start: vec![0],
            inv_start: vec![0],
            inv_element_start: vec![0],
            ..Default::default()
        }
    }

    /// Number of particles (= clusters).
    pub fn particle_count(&self) -> usize {
        self.rest.len()
    }

    /// Builds a body from a closed triangle mesh (body frame, metres) and appends it.
    /// On error nothing is added.
    pub fn add_body(&mut self, mesh: &TriMesh, desc: &BodyDesc) -> Result<BodyId, TissueError> {
        positive("density", desc.density)?;
        desc.material.validate()?;
        if desc.neighbours == 0 || desc.neighbours > MAX_NEIGHBOURS {
            return Err(TissueError::InvalidParameter {
                name: "neighbours",
                value: desc.neighbours.to_string(),
                expected: "K in 1..=128",
            });
        }
        if !desc.translation.is_finite() || !desc.rotation.is_finite() {
            return Err(TissueError::InvalidParameter {
                name: "translation/rotation",
                value: format!("{:?} / {:?}", desc.translation, desc.rotation),
                expected: "finite values",
            });
        }
        let surface = Surface::new(mesh)?;
        if desc.discretisation == Discretisation::Lattice {
            return self.add_lattice_body(mesh, &surface, desc);
        }
        let samples = sample(&surface, desc.resolution)?;
        let n = samples.positions.len();
        let k = desc.neighbours as usize;
        if k >= n {
            return Err(TissueError::TooFewParticles {
                particles: n,
                neighbours: k,
            });
        }
        let volume = surface.volume as f32;
        let m = desc.density * volume / n as f32;
        let rest = samples.positions;
        let pinned_local: Vec<u32> = (0..n as u32)
            .filter(|&i| desc.pins.iter().any(|r| r.contains(i, rest[i as usize])))
            .collect();
        let (lo, hi) = surface.bounds();
        let size = (hi - lo).length() as f32;
        let info = BodyInfo {
            first: 0,
            count: n as u32,
            material: desc.material,
            neighbours: desc.neighbours,
            density: desc.density,
            spacing: samples.spacing,
            radius: 0.5 * samples.spacing,
            volume,
            size,
            translation: desc.translation,
            rotation: desc.rotation,
            skin: Skin::default(),
            flipped: surface.flipped,
            discretisation: Discretisation::Clusters,
        };
        let mut body = single_body(&rest, vec![m; n], &pinned_local, k, info)?;
        // The hierarchy's coarse levels (built before anything is committed).
        if let Some(hd) = &desc.hierarchy {
            body.levels = build_levels(&body, samples.spacing, &pinned_local, desc, hd)?;
        }
        body.bodies[0].skin = make_skin(mesh, &surface, &rest, samples.spacing);
        // Commit (nothing above touched self).
        let id = self.bodies.len();
        self.append(&body);
        Ok(id)
    }

    /// [`Model::add_body`] for a [`Discretisation::Lattice`] body.
    fn add_lattice_body(
        &mut self,
        mesh: &TriMesh,
        surface: &Surface,
        desc: &BodyDesc,
    ) -> Result<BodyId, TissueError> {
        if !matches!(desc.material, Material::Hyperelastic { .. }) {
            return Err(TissueError::InvalidParameter {
                name: "discretisation",
                value: "Lattice with shape matching".into(),
                expected: "Lattice with a hyperelastic material (shape matching runs on clusters)",
            });
        }
        if desc.hierarchy.is_some() {
            return Err(TissueError::InvalidParameter {
                name: "hierarchy",
                value: "coarse levels on a Lattice body".into(),
                expected: "no hierarchy (the hierarchy is built for cluster bodies)",
            });
        }
        let voxels = voxelize(surface, desc.resolution)?;
        let volume = surface.volume as f32;
        let (lo, hi) = surface.bounds();
        let info = BodyInfo {
            first: 0,
            count: 0,
            material: desc.material,
            neighbours: desc.neighbours,
            density: desc.density,
            spacing: voxels.spacing,
            radius: 0.5 * voxels.spacing,
            volume,
            size: (hi - lo).length() as f32,
            translation: desc.translation,
            rotation: desc.rotation,
            skin: Skin::default(),
            flipped: surface.flipped,
            discretisation: Discretisation::Lattice,
        };
        let mut body = lattice_body(&voxels, desc, info);
        body.bodies[0].skin = make_skin(mesh, surface, &voxels.nodes, voxels.spacing);
        let id = self.bodies.len();
        self.append(&body);
        Ok(id)
    }

    /// Appends every body of `other` (its indices shifted past this model's particles),
    /// so that bodies built separately (in parallel, say) can be batched into one model.
    pub fn append(&mut self, other: &Model) {
        let off = self.rest.len() as u32;
        let body_off = self.bodies.len() as u32;
        if self.cluster_start.is_empty() {
            self.cluster_start.push(0);
        }
        if self.inv_start.is_empty() {
            self.inv_start.push(0);
        }
        let (m0, i0) = (
            self.cluster_members.len() as u32,
            self.inv_clusters.len() as u32,
        );
        self.cluster_start
            .extend(other.cluster_start.iter().skip(1).map(|s| s + m0));
        self.cluster_members
            .extend(other.cluster_members.iter().map(|j| j + off));
        self.inv_start
            .extend(other.inv_start.iter().skip(1).map(|s| s + i0));
        self.inv_clusters
            .extend(other.inv_clusters.iter().map(|c| c + off));
        self.rest.extend_from_slice(&other.rest);
        self.mass.extend_from_slice(&other.mass);
        self.particle_body
            .extend(other.particle_body.iter().map(|b| b + body_off));
        self.cluster_rest.extend_from_slice(&other.cluster_rest);
        self.cluster_volume.extend_from_slice(&other.cluster_volume);
        self.cluster_weight.extend_from_slice(&other.cluster_weight);
        self.pinned.extend(other.pinned.iter().map(|i| i + off));
        if self.inv_element_start.is_empty() {
            self.inv_element_start.push(0);
        }
        let (e0, ie0) = (self.elements.len() as u32, self.inv_elements.len() as u32);
        self.elements
            .extend(other.elements.iter().map(|e| e.map(|j| j + off)));
        self.element_rest.extend_from_slice(&other.element_rest);
        self.element_body
            .extend(other.element_body.iter().map(|b| b + body_off));
        let other_inv_start: &[u32] = if other.inv_element_start.is_empty() {
            &[0]
        } else {
            &other.inv_element_start
        };
        // Particles of `other` without an element run (an empty model's) get empty runs.
        let runs = other_inv_start.len() - 1;
        self.inv_element_start
            .extend(other_inv_start.iter().skip(1).map(|s| s + ie0));
        let last = *self.inv_element_start.last().unwrap_or(&0);
        self.inv_element_start
            .extend(std::iter::repeat_n(last, other.rest.len() - runs));
        self.inv_elements
            .extend(other.inv_elements.iter().map(|c| c + (e0 << 3)));
        // Particle offset of each of this model's levels before the append (level 0 first).
        let mut finer_off = vec![off];
        finer_off.extend(self.levels.iter().map(|l| l.model.particle_count() as u32));
        for (l, lv) in other.levels.iter().enumerate() {
            if self.levels.len() <= l {
                self.levels.push(Level::new());
            }
            let foff = finer_off.get(l).copied().unwrap_or(0);
            let dst = &mut self.levels[l];
            let (poff, soff) = (
                dst.model.particle_count() as u32,
                *dst.parent_start.last().unwrap_or(&0),
            );
            dst.source.extend(lv.source.iter().map(|i| i + off));
            dst.fine.extend(lv.fine.iter().map(|i| i + off));
            dst.parent_start
                .extend(lv.parent_start.iter().skip(1).map(|s| s + soff));
            dst.parents.extend(lv.parents.iter().map(|j| j + poff));
            dst.weights.extend_from_slice(&lv.weights);
            let toff = *dst.transfer_start.last().unwrap_or(&0);
            dst.transfer_cluster
                .extend(lv.transfer_cluster.iter().map(|c| c + foff));
            dst.transfer_start
                .extend(lv.transfer_start.iter().skip(1).map(|s| s + toff));
            dst.transfer_parents
                .extend(lv.transfer_parents.iter().map(|j| j + poff));
            dst.transfer_weights.extend_from_slice(&lv.transfer_weights);
            dst.model.append(&lv.model);
        }
        for b in &other.bodies {
            let mut b = b.clone();
            b.first += off;
            for inf in &mut b.skin.particles {
                for i in inf.iter_mut() {
                    *i += off;
                }
            }
            self.bodies.push(b);
        }
    }

    /// Members of cluster `c`.
    #[inline]
    pub fn members(&self, c: usize) -> &[u32] {
        &self.cluster_members[self.cluster_start[c] as usize..self.cluster_start[c + 1] as usize]
    }

    /// Clusters containing particle `j`.
    #[inline]
    pub fn clusters_of(&self, j: usize) -> &[u32] {
        &self.inv_clusters[self.inv_start[j] as usize..self.inv_start[j + 1] as usize]
    }

    /// Elements containing particle `j`, as `element << 3 | corner`.
    #[inline]
    pub fn elements_of(&self, j: usize) -> &[u32] {
        match (
            self.inv_element_start.get(j),
            self.inv_element_start.get(j + 1),
        ) {
            (Some(&a), Some(&b)) => &self.inv_elements[a as usize..b as usize],
            _ => &[],
        }
    }

    /// World position of each particle's rest position under its body's placement.
    pub fn placed_rest(&self) -> Vec<Vec3> {
        self.rest
            .iter()
            .zip(&self.particle_body)
            .map(|(p, &b)| {
                let body = &self.bodies[b as usize];
                body.translation + body.rotation * *p
            })
            .collect()
    }
}

/// One body's particles (rest positions `rest` in the body frame, m; masses, kg; pinned
/// local indices) as a one-body model: clusters of each particle and its `k` nearest
/// neighbours, their rest data, volumes (the body's volume partitioned by the members'
/// multiplicities) and inverse lists. `info` supplies the body's fields (`first` and
/// `count` are set here).
fn single_body(
    rest: &[Vec3],
    masses: Vec<f32>,
    pinned_local: &[u32],
    k: usize,
    mut info: BodyInfo,
) -> Result<Model, TissueError> {
    let n = rest.len();
    let knn = super::knn::knn_all(rest, k, 0).ok_or(TissueError::TooFewParticles {
        particles: n,
        neighbours: k,
    })?;
    let mut model = Model::new();
    for i in 0..n {
        model.cluster_members.push(i as u32);
        model
            .cluster_members
            .extend_from_slice(&knn[i * k..(i + 1) * k]);
        model.cluster_start.push(model.cluster_members.len() as u32);
    }
    // Multiplicity n_j and inverse lists.
    let mut mult = vec![0u32; n];
    for &j in &model.cluster_members {
        mult[j as usize] += 1;
    }
    let mut inv_mass: Vec<f32> = masses.iter().map(|m| 1.0 / m).collect();
    for &i in pinned_local {
        inv_mass[i as usize] = 0.0;
    }
    let mut inv: Vec<Vec<u32>> = vec![Vec::new(); n];
    for c in 0..n {
        let mem = &model.cluster_members
            [model.cluster_start[c] as usize..model.cluster_start[c + 1] as usize];
        model
            .cluster_rest
            .push(init_cluster(mem, rest, &masses, &inv_mass, &mult));
        let v: f32 = mem
            .iter()
            .map(|&j| masses[j as usize] / info.density / mult[j as usize] as f32)
            .sum();
        model.cluster_volume.push(v);
        let s = mem.iter().map(|&j| mult[j as usize]).max().unwrap_or(1);
        model.cluster_weight.push(1.0 / s as f32);
        for &j in mem {
            inv[j as usize].push(c as u32);
        }
    }
    for list in inv {
        model.inv_clusters.extend_from_slice(&list);
        model.inv_start.push(model.inv_clusters.len() as u32);
    }
    model.rest = rest.to_vec();
    model.mass = masses;
    model.particle_body = vec![0; n];
    model.pinned = pinned_local.to_vec();
    info.first = 0;
    info.count = n as u32;
    model.bodies.push(info);
    Ok(model)
}

/// The coarse levels of one body (local indices): the [`Hierarchy`] of its particles,
/// each level made a one-body model with masses restricted from the finer level.
fn build_levels(
    body: &Model,
    spacing: f32,
    pinned_local: &[u32],
    desc: &BodyDesc,
    hd: &HierarchyDesc,
) -> Result<Vec<Level>, TissueError> {
    let rest = &body.rest[..];
    let size = body.bodies[0].size;
    let h = Hierarchy::build(rest, spacing, hd)?;
    let mut fine_mass = body.mass.clone();
    let mut fine_volume = body.cluster_volume.clone();
    let mut out = Vec::new();
    for l in 1..h.levels.len() {
        let (fine, coarse) = (&h.levels[l - 1], &h.levels[l]);
        let nc = coarse.particles.len();
        if nc < 2 {
            break;
        }
        // Restriction of the masses: M_j = Σ_i w_ij m_i.
        let mut cm = vec![0.0f32; nc];
        for (p, &m) in fine_mass.iter().enumerate() {
            let (a, b) = (
                fine.parent_start[p] as usize,
                fine.parent_start[p + 1] as usize,
            );
            for s in a..b {
                cm[fine.parents[s] as usize] += fine.weights[s] * m;
            }
        }
        let pts: Vec<Vec3> = coarse.particles.iter().map(|&i| rest[i as usize]).collect();
        let pins: Vec<u32> = coarse
            .particles
            .iter()
            .enumerate()
            .filter(|(_, i)| pinned_local.binary_search(i).is_ok())
            .map(|(j, _)| j as u32)
            .collect();
        let info = BodyInfo {
            first: 0,
            count: 0,
            material: desc.material,
            neighbours: desc.neighbours.min(nc as u32 - 1),
            density: desc.density,
            spacing: coarse.spacing,
            // Coarse particles are level-0 particles: they collide at the fine radius.
            radius: 0.5 * spacing,
            volume: body.bodies[0].volume,
            size,
            translation: desc.translation,
            rotation: desc.rotation,
            skin: Skin::default(),
            flipped: false,
            discretisation: Discretisation::Clusters,
        };
        let k = desc.neighbours.min(nc as u32 - 1) as usize;
        let model = single_body(&pts, cm.clone(), &pins, k, info)?;
        let mut level = Level::new();
        level.source = coarse.particles.clone();
        for (p, &i) in fine.particles.iter().enumerate() {
            if coarse.particles.binary_search(&i).is_ok() {
                continue;
            }
            level.fine.push(i);
            let (a, b) = (
                fine.parent_start[p] as usize,
                fine.parent_start[p + 1] as usize,
            );
            level.parents.extend_from_slice(&fine.parents[a..b]);
            level.weights.extend_from_slice(&fine.weights[a..b]);
            level.parent_start.push(level.parents.len() as u32);
        }
        // Multiplier transfer, per finer-level cluster (finer level order).
        for (p, &i) in fine.particles.iter().enumerate() {
            level.transfer_cluster.push(p as u32);
            if let Ok(j) = coarse.particles.binary_search(&i) {
                level.transfer_parents.push(j as u32);
                level
                    .transfer_weights
                    .push(fine_volume[p] / model.cluster_volume[j]);
            } else {
                let (a, b) = (
                    fine.parent_start[p] as usize,
                    fine.parent_start[p + 1] as usize,
                );
                for s in a..b {
                    let j = fine.parents[s] as usize;
                    level.transfer_parents.push(j as u32);
                    level
                        .transfer_weights
                        .push(fine.weights[s] * fine_volume[p] / model.cluster_volume[j]);
                }
            }
            level
                .transfer_start
                .push(level.transfer_parents.len() as u32);
        }
        fine_volume = model.cluster_volume.clone();
        level.model = model;
        out.push(level);
        fine_mass = cm;
    }
    Ok(out)
}

/// The render surface `mesh` embedded in the particles `rest` (body frame) of lattice
/// spacing `spacing` (m), with its triangles' winding fixed if the surface was flipped.
fn make_skin(mesh: &TriMesh, surface: &Surface, rest: &[Vec3], spacing: f32) -> Skin {
    let bind = embed(&mesh.positions, rest, 0, spacing);
    let mut indices = mesh.indices.clone();
    if surface.flipped {
        for t in indices.chunks_exact_mut(3) {
            t.swap(1, 2);
        }
    }
    Skin {
        rest_vertices: mesh.positions.clone(),
        particles: bind.iter().map(|b| b.0).collect(),
        weights: bind.iter().map(|b| b.1).collect(),
        indices,
        weld_map: surface.weld_map.clone(),
        welded_count: surface.positions.len() as u32,
        welded_triangles: surface.triangles.clone(),
    }
}

/// One lattice body (local indices): its cells as hexahedral elements, each standing for
/// an equal share of the volume the surface encloses (so the body's mass is its
/// density times that volume), each corner taking an eighth of its cells' masses. The
/// particles own no clusters.
fn lattice_body(voxels: &Voxels, desc: &BodyDesc, mut info: BodyInfo) -> Model {
    let n = voxels.nodes.len();
    let cells = voxels.cells.len();
    let v_e = info.volume / cells as f32;
    let mut mass = vec![0.0f32; n];
    let mut mult = vec![0u32; n];
    for cell in &voxels.cells {
        for &j in cell {
            mass[j as usize] += desc.density * v_e / CORNERS as f32;
            mult[j as usize] += 1;
        }
    }
    let rest = voxels.nodes.clone();
    let pinned: Vec<u32> = (0..n as u32)
        .filter(|&i| desc.pins.iter().any(|r| r.contains(i, rest[i as usize])))
        .collect();
    let mut inv_mass: Vec<f32> = mass.iter().map(|m| 1.0 / m).collect();
    for &i in &pinned {
        inv_mass[i as usize] = 0.0;
    }
    let mut model = Model::new();
    let mut inv: Vec<Vec<u32>> = vec![Vec::new(); n];
    for (e, (cell, &centre)) in voxels.cells.iter().zip(&voxels.centres).enumerate() {
        let w = cell.map(|j| inv_mass[j as usize]);
        let m = cell.map(|j| mult[j as usize]);
        model.elements.push(*cell);
        model
            .element_rest
            .push(ElementRest::new(centre, voxels.spacing, v_e, &w, &m));
        model.element_body.push(0);
        for (corner, &j) in cell.iter().enumerate() {
            inv[j as usize].push(((e as u32) << 3) | corner as u32);
        }
    }
    for list in inv {
        model.inv_elements.extend_from_slice(&list);
        model
            .inv_element_start
            .push(model.inv_elements.len() as u32);
    }
    model.cluster_start = vec![0; n + 1];
    model.inv_start = vec![0; n + 1];
    model.cluster_rest = vec![ClusterRest::empty(); n];
    model.cluster_volume = vec![0.0; n];
    model.cluster_weight = vec![0.0; n];
    model.rest = rest;
    model.mass = mass;
    model.particle_body = vec![0; n];
    model.pinned = pinned;
    info.first = 0;
    info.count = n as u32;
    model.bodies.push(info);
    model
}
