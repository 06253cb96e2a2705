//! The model: everything that does not change while simulating (rest positions, masses,
//! clusters, inverse lists, pins, skin), for any number of bodies batched in flat
//! struct-of-arrays buffers laid out the way the GPU wants them (f32/u32, particles in
//! spatial order per body, clusters and inverse lists as CSR index arrays), so that an
//! upload is a copy. The time-varying part is [`super::solver::State`] (Newton's
//! Model / State / Control split).

use super::constraints::{ClusterRest, init_cluster};
use super::error::{TissueError, in_range, positive};
use super::mesh::{Surface, TriMesh};
use super::sampling::{Resolution, sample};
use super::skin::{Skin, embed};
use glam::{Quat, Vec3};

/// Largest neighbour count K supported.
pub const MAX_NEIGHBOURS: u32 = 128;

/// The elastic model of a body (SPEC §2).
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
}

impl Default for BodyDesc {
    fn default() -> Self {
        Self {
            resolution: Resolution::default(),
            density: 1060.0,
            neighbours: 32,
            material: Material::default(),
            pins: Vec::new(),
            translation: Vec3::ZERO,
            rotation: Quat::IDENTITY,
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
}

/// Index of a body in a [`Model`].
pub type BodyId = usize;

impl Model {
    /// An empty model.
    pub fn new() -> Self {
        Self {
            cluster_start: vec![0],
            inv_start: vec![0],
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
        let samples = sample(&surface, desc.resolution)?;
        let n = samples.positions.len();
        let k = desc.neighbours as usize;
        if k >= n {
            return Err(TissueError::TooFewParticles {
                particles: n,
                neighbours: k,
            });
        }
        let first = self.rest.len() as u32;
        let volume = surface.volume as f32;
        let m = desc.density * volume / n as f32;
        let rest = samples.positions;
        let knn = super::knn::knn_all(&rest, k, 0).ok_or(TissueError::TooFewParticles {
            particles: n,
            neighbours: k,
        })?;
        // Clusters (local indices).
        let mut members = Vec::with_capacity(n * (k + 1));
        for i in 0..n {
            members.push(i as u32);
            members.extend_from_slice(&knn[i * k..(i + 1) * k]);
        }
        // Multiplicity n_j and inverse lists.
        let mut mult = vec![0u32; n];
        for &j in &members {
            mult[j as usize] += 1;
        }
        let masses = vec![m; n];
        // Pins (local indices), needed by the clusters' inverse-mass metric.
        let pinned_local: Vec<u32> = (0..n as u32)
            .filter(|&i| desc.pins.iter().any(|r| r.contains(i, rest[i as usize])))
            .collect();
        let mut inv_mass = vec![1.0 / m; n];
        for &i in &pinned_local {
            inv_mass[i as usize] = 0.0;
        }
        let mut cluster_rest = Vec::with_capacity(n);
        let mut cluster_volume = Vec::with_capacity(n);
        let mut cluster_weight = Vec::with_capacity(n);
        for c in 0..n {
            let mem = &members[c * (k + 1)..(c + 1) * (k + 1)];
            cluster_rest.push(init_cluster(mem, &rest, &masses, &inv_mass, &mult));
            let v: f32 = mem
                .iter()
                .map(|&j| m / desc.density / mult[j as usize] as f32)
                .sum();
            cluster_volume.push(v);
            let s = mem.iter().map(|&j| mult[j as usize]).max().unwrap_or(1);
            cluster_weight.push(1.0 / s as f32);
        }
        let mut inv: Vec<Vec<u32>> = vec![Vec::new(); n];
        for c in 0..n {
            for &j in &members[c * (k + 1)..(c + 1) * (k + 1)] {
                inv[j as usize].push(first + c as u32);
            }
        }
        let pinned: Vec<u32> = pinned_local.iter().map(|i| first + i).collect();
        // Skin.
        let (lo, hi) = surface.bounds();
        let size = (hi - lo).length() as f32;
        let bind = embed(&mesh.positions, &rest, first, samples.spacing);
        let mut indices = mesh.indices.clone();
        if surface.flipped {
            for t in indices.chunks_exact_mut(3) {
                t.swap(1, 2);
            }
        }
        let skin = Skin {
            rest_vertices: mesh.positions.clone(),
            particles: bind.iter().map(|b| b.0).collect(),
            weights: bind.iter().map(|b| b.1).collect(),
            indices,
            weld_map: surface.weld_map.clone(),
            welded_count: surface.positions.len() as u32,
            welded_triangles: surface.triangles.clone(),
        };

        // Commit (nothing above touched self).
        let id = self.bodies.len();
        if self.cluster_start.is_empty() {
            self.cluster_start.push(0);
        }
        if self.inv_start.is_empty() {
            self.inv_start.push(0);
        }
        for c in 0..n {
            for &j in &members[c * (k + 1)..(c + 1) * (k + 1)] {
                self.cluster_members.push(first + j);
            }
            self.cluster_start.push(self.cluster_members.len() as u32);
        }
        for list in inv {
            self.inv_clusters.extend_from_slice(&list);
            self.inv_start.push(self.inv_clusters.len() as u32);
        }
        self.rest.extend_from_slice(&rest);
        self.mass.extend_from_slice(&masses);
        self.particle_body.extend(std::iter::repeat_n(id as u32, n));
        // Cluster rest centres are in the body frame like `rest`.
        self.cluster_rest.extend(cluster_rest);
        self.cluster_volume.extend(cluster_volume);
        self.cluster_weight.extend(cluster_weight);
        self.pinned.extend(pinned);
        self.bodies.push(BodyInfo {
            first,
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
            skin,
            flipped: surface.flipped,
        });
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
