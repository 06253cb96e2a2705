//! What a scene writes: the [`SoftBody`] component and its companions, the global
//! [`TissueSettings`], the [`TissueClock`], and the messages the plugin sends.

pub use super::quality::TissueQuality;
use crate::core::colliders::{Collider, ColliderShape, GraspMode};
use crate::core::hierarchy::HierarchyDesc;
use crate::core::model::{Discretisation, Material, PinRegion};
use crate::core::multigrid::Sweeps;
use crate::core::sampling::Resolution;
use crate::core::solver::{ElementSolver, Method, SolverSettings};
use bevy::prelude::*;

/// The elastic model of a body, in SI units.
#[derive(Debug, Clone, Copy, PartialEq, Reflect)]
pub enum TissueMaterial {
    /// Shape matching (Müller et al. 2005), the paper's model: stiffness `k` in (0, 1]
    /// reached after a substep's iterations (dimensionless).
    ShapeMatching {
        /// Stiffness k in (0, 1].
        stiffness: f32,
    },
    /// XPBD fixed-corotated hyperelasticity on clusters (see
    /// [`crate::core::constraints::Hyperelastic`]).
    Hyperelastic {
        /// Young's modulus E, Pa.
        youngs_modulus: f32,
        /// Poisson ratio ν in [0, 0.5).
        poisson_ratio: f32,
    },
}

impl Default for TissueMaterial {
    /// Soft tissue: hyperelastic, E = 10 kPa, ν = 0.45 (the core's
    /// [`crate::core::model::Material::default`]).
    fn default() -> Self {
        TissueMaterial::Hyperelastic {
            youngs_modulus: 10_000.0,
            poisson_ratio: 0.45,
        }
    }
}

impl TissueMaterial {
    /// The core's material.
    pub fn to_core(self) -> Material {
        match self {
            TissueMaterial::ShapeMatching { stiffness } => Material::ShapeMatching { stiffness },
            TissueMaterial::Hyperelastic {
                youngs_modulus,
                poisson_ratio,
            } => Material::Hyperelastic {
                youngs_modulus,
                poisson_ratio,
            },
        }
    }
}

/// How a body's elasticity is discretised over its particles.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Reflect)]
pub enum TissueDiscretisation {
    /// The paper's clusters: each particle and its K nearest rest neighbours (stepped
    /// in the render graph's compute passes). Fast; softer than its E and ν say, and it
    /// does not converge to them with resolution. Shape matching's `k` and `K` apply to
    /// it only.
    Clusters,
    /// The default: hexahedral elements on the sampling lattice (the cells whose centres
    /// are inside the surface; the particles are their corners). Converges to the
    /// material set (against an independent finite-element reference). Hyperelastic
    /// material only; stepped by Newton–multigrid
    /// ([`TissueSettings::newton_iterations`]) on the GPU, or on the CPU where the GPU
    /// cannot.
    #[default]
    Lattice,
}

impl TissueDiscretisation {
    /// The core's discretisation.
    pub fn to_core(self) -> Discretisation {
        match self {
            TissueDiscretisation::Clusters => Discretisation::Clusters,
            TissueDiscretisation::Lattice => Discretisation::Lattice,
        }
    }
}

/// Where bodies are simulated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Reflect)]
pub enum TissueBackend {
    /// On the GPU: cluster bodies in the render graph's compute passes; lattice bodies
    /// ([`TissueDiscretisation::Lattice`]) by Newton–multigrid submitted from the main
    /// world, their positions read back and skinned on the CPU (on the CPU instead where
    /// the GPU cannot take them: more colliders than its kernels take, kernels or
    /// buffers that cannot be made, no GPU).
    #[default]
    Auto,
    /// Every body on the CPU, by the core's solver on the main thread (Jacobi for
    /// clusters, Newton–multigrid for lattice bodies), its mesh written each frame.
    /// Slower; needs no compute-capable adapter.
    Cpu,
}

/// How finely a body is sampled with particles.
#[derive(Debug, Clone, Copy, PartialEq, Reflect)]
pub enum TissueResolution {
    /// Lattice spacing, m.
    Spacing(f32),
    /// Target particle count (met within 1% where the shape allows it).
    Particles(u32),
}

impl Default for TissueResolution {
    fn default() -> Self {
        TissueResolution::Particles(2000)
    }
}

impl TissueResolution {
    /// The core's resolution.
    pub fn to_core(self) -> Resolution {
        match self {
            TissueResolution::Spacing(s) => Resolution::Spacing(s),
            TissueResolution::Particles(n) => Resolution::Particles(n),
        }
    }
}

/// Hierarchical PBD for a body (Müller 2008; see `core::model::Level`): coarse levels
/// solved first in every substep carry stiffness through a large body in a few
/// iterations instead of hundreds.
///
/// It costs a coarse pass per substep, several level-0 iterations' time: on the GPU the
/// coarse levels' many small dispatches run at the dispatch-latency floor. So it pays
/// where a flat solver would need many iterations: stiff, large bodies held to a tight
/// residual (the measurements are in BENCHMARKS.md, "Hierarchy").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Reflect)]
pub enum TissueHierarchy {
    /// On where the measurements say it pays: hyperelastic bodies with E ≥
    /// [`TissueHierarchy::AUTO_MIN_YOUNGS`] of at least
    /// [`TissueHierarchy::AUTO_MIN_PARTICLES`] particles (there a stiff bar and a stiff
    /// liver reach a given residual sooner with it, on the CPU and the GPU, and flat
    /// Jacobi diverged on the GPU where the hierarchy held; BENCHMARKS.md, "Hierarchy").
    /// Off otherwise: at real-time iteration counts the coarse pass costs more than it
    /// gains on soft or small bodies.
    #[default]
    Auto,
    /// Flat: level 0 only.
    Off,
    /// This many levels (2–8, counting level 0), each particle linked to `parents`
    /// (2–4) particles of the next level.
    Levels {
        /// Levels including level 0.
        levels: u32,
        /// Parents per particle.
        parents: u32,
    },
}

impl TissueHierarchy {
    /// Smallest body that [`TissueHierarchy::Auto`] gives a hierarchy.
    pub const AUTO_MIN_PARTICLES: u32 = 20_000;
    /// Smallest Young's modulus (Pa) that [`TissueHierarchy::Auto`] gives a hierarchy.
    pub const AUTO_MIN_YOUNGS: f32 = 500_000.0;

    /// The core's hierarchy description for a body of `particles` particles of
    /// `material` (`None`: flat).
    pub fn to_core(self, particles: u32, material: &TissueMaterial) -> Option<HierarchyDesc> {
        match self {
            TissueHierarchy::Auto => {
                let stiff = matches!(material, TissueMaterial::Hyperelastic { youngs_modulus, .. }
                    if *youngs_modulus >= Self::AUTO_MIN_YOUNGS);
                (stiff && particles >= Self::AUTO_MIN_PARTICLES).then(HierarchyDesc::default)
            }
            TissueHierarchy::Off => None,
            TissueHierarchy::Levels { levels, parents } => Some(HierarchyDesc {
                levels: Some(levels),
                parents,
                ..Default::default()
            }),
        }
    }
}

/// A soft body: put it on an entity with a `Mesh3d` (any closed triangle mesh) and a
/// material. The plugin samples particles inside the mesh, builds the body off the main
/// thread, simulates it on the GPU and draws the entity's mesh from the simulation.
/// Changing any field rebuilds the body (for a cluster body on the GPU, that body alone:
/// a new material or stiffness is written in place, keeping its pose; lattice bodies are
/// rebuilt together). The default is soft tissue that means its SI
/// parameters: hyperelastic, E = 10 kPa, ν = 0.45, 1060 kg/m³, on hexahedral lattice
/// elements ([`TissueDiscretisation::Lattice`]); the paper's clusters are
/// [`TissueDiscretisation::Clusters`].
///
/// ```no_run
/// use bevy::prelude::*;
/// use bevy_tissue::prelude::*;
///
/// fn setup(mut commands: Commands, mut meshes: ResMut<Assets<Mesh>>,
///          mut materials: ResMut<Assets<StandardMaterial>>) {
///     commands.spawn((
///         Mesh3d(meshes.add(Sphere::new(0.5).mesh().ico(4).unwrap())),
///         MeshMaterial3d(materials.add(Color::srgb(0.8, 0.3, 0.3))),
///         SoftBody::default(),
///         Pinned::region(PinShape::HalfSpace { point: Vec3::new(0.0, 0.4, 0.0), normal: Vec3::Y }),
///     ));
/// }
/// ```
#[derive(Component, Debug, Clone, PartialEq, Reflect)]
#[reflect(Component, Default)]
#[require(Transform, Visibility, SoftBodyStatus, super::sleep::BodyMotion)]
pub struct SoftBody {
    /// Elastic model and stiffness.
    pub material: TissueMaterial,
    /// Density, kg/m³ (soft tissue ≈ 1060).
    pub density: f32,
    /// Neighbour count K: each cluster is a particle and its K nearest rest neighbours.
    pub neighbours: u32,
    /// Particle sampling.
    pub resolution: TissueResolution,
    /// Hierarchical PBD levels (clusters only).
    pub hierarchy: TissueHierarchy,
    /// Clusters (the paper's, on the GPU) or lattice hexahedra (accurate, on the CPU).
    pub discretisation: TissueDiscretisation,
    /// Accuracy level: when not [`TissueQuality::Custom`] (the default), it sets the
    /// world's iterations and substeps (the most demanding body's; see
    /// [`super::quality`]).
    pub quality: TissueQuality,
}

impl Default for SoftBody {
    fn default() -> Self {
        Self {
            material: TissueMaterial::default(),
            density: 1060.0,
            neighbours: 32,
            resolution: TissueResolution::default(),
            hierarchy: TissueHierarchy::default(),
            discretisation: TissueDiscretisation::default(),
            quality: TissueQuality::default(),
        }
    }
}

/// A region of a body's rest shape, in the entity's local frame (the mesh's frame).
#[derive(Debug, Clone, Copy, PartialEq, Reflect)]
pub enum PinShape {
    /// Axis-aligned box, m.
    Box {
        /// Lower corner, m.
        min: Vec3,
        /// Upper corner, m.
        max: Vec3,
    },
    /// Ball.
    Sphere {
        /// Centre, m.
        center: Vec3,
        /// Radius, m.
        radius: f32,
    },
    /// Everything on the side of the plane the normal points to.
    HalfSpace {
        /// A point on the plane, m.
        point: Vec3,
        /// Normal (need not be unit).
        normal: Vec3,
    },
}

impl PinShape {
    /// The region in world space for a body placed by `to_world`.
    pub fn to_core(self, to_world: &GlobalTransform) -> PinRegion {
        let a = to_world.affine();
        match self {
            PinShape::Box { min, max } => {
                let (lo, hi) = transform_box(&a, min, max);
                PinRegion::Box { min: lo, max: hi }
            }
            PinShape::Sphere { center, radius } => PinRegion::Sphere {
                center: a.transform_point3(center),
                radius: radius * to_world.scale().max_element(),
            },
            PinShape::HalfSpace { point, normal } => PinRegion::HalfSpace {
                point: a.transform_point3(point),
                normal: a.matrix3.inverse().transpose() * normal,
            },
        }
    }
}

/// The axis-aligned box around the image of the box `lo..hi` under `a` (its 8 corners).
pub fn transform_box(a: &bevy::math::Affine3A, lo: Vec3, hi: Vec3) -> (Vec3, Vec3) {
    let (mut l, mut h) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for i in 0..8 {
        let c = Vec3::new(
            if i & 1 == 0 { lo.x } else { hi.x },
            if i & 2 == 0 { lo.y } else { hi.y },
            if i & 4 == 0 { lo.z } else { hi.z },
        );
        let p = a.transform_point3(c);
        l = l.min(p);
        h = h.max(p);
    }
    (l, h)
}

/// Pinned regions of a [`SoftBody`]: particles inside are held where they rest.
#[derive(Component, Debug, Clone, Default, PartialEq, Reflect)]
#[reflect(Component, Default)]
pub struct Pinned {
    /// The regions (any particle in any region is pinned).
    pub regions: Vec<PinShape>,
}

impl Pinned {
    /// One region.
    pub fn region(shape: PinShape) -> Self {
        Self {
            regions: vec![shape],
        }
    }
}

/// Shape of a [`TissueCollider`], in its entity's local frame.
#[derive(Debug, Clone, Copy, PartialEq, Reflect)]
pub enum ColliderKind {
    /// The half-space below the local XZ plane (normal +Y).
    Plane,
    /// Sphere.
    Sphere {
        /// Radius, m.
        radius: f32,
    },
    /// Capsule along local Y.
    Capsule {
        /// Half the length of the inner segment, m.
        half_length: f32,
        /// Radius, m.
        radius: f32,
    },
    /// Box.
    Cuboid {
        /// Half extents, m.
        half_extents: Vec3,
    },
    /// A grasper (forceps, a mouse drag): pushes nothing; while `closed`, the particles
    /// within `radius` of its origin at the moment it closed move rigidly with it, and
    /// [`ColliderForce`] reads the force they pull on it with. Opening lets them go.
    Grasper {
        /// Reach when closing, m.
        radius: f32,
        /// Holding (`true`) or open.
        closed: bool,
    },
}

/// A kinematic collider that pushes tissue: it follows its entity's `Transform` (its
/// velocity, for friction, from the motion between frames) and is pushed by nothing.
/// The force the tissue exerts on it is available through [`ColliderForce`].
#[derive(Component, Debug, Clone, Copy, PartialEq, Reflect)]
#[reflect(Component)]
#[require(Transform)]
pub struct TissueCollider {
    /// Geometry.
    pub kind: ColliderKind,
    /// Coulomb friction coefficient (dimensionless, ≥ 0).
    pub friction: f32,
}

impl TissueCollider {
    /// A collider of the given shape with friction 0.5.
    pub fn new(kind: ColliderKind) -> Self {
        Self {
            kind,
            friction: 0.5,
        }
    }

    /// The core's collider at a world pose.
    pub fn to_core(&self, pose: &GlobalTransform, velocity: Vec3) -> Collider {
        let (scale, rotation, position) = pose.to_scale_rotation_translation();
        let s = scale.max_element();
        let shape = match self.kind {
            ColliderKind::Plane => ColliderShape::Plane,
            ColliderKind::Sphere { radius } => ColliderShape::Sphere { radius: radius * s },
            ColliderKind::Capsule {
                half_length,
                radius,
            } => ColliderShape::Capsule {
                half_length: half_length * scale.y,
                radius: radius * s,
            },
            ColliderKind::Cuboid { half_extents } => ColliderShape::Cuboid {
                half_extents: half_extents * scale,
            },
            // Closed: capture; the plugin turns it into hold once the capture ran.
            ColliderKind::Grasper { radius, closed } => ColliderShape::Grasper {
                radius: radius * s,
                mode: if closed {
                    GraspMode::Capture
                } else {
                    GraspMode::Open
                },
            },
        };
        Collider {
            shape,
            position,
            rotation,
            velocity,
            friction: self.friction.max(0.0),
        }
    }
}

/// Puts a body back at its rest pose (the pose it was built in), velocities zero
/// (message; the body keeps its settings).
#[derive(Message, Debug, Clone, Copy, PartialEq, Eq)]
pub struct ResetSoftBody {
    /// The body.
    pub entity: Entity,
}

/// The force (N, world frame) the tissue exerted on a [`TissueCollider`] over the last
/// step read back; insert it on the collider to have it updated (async readback, a frame
/// or two behind). On lattice bodies it is the reaction of the particles touching the
/// collider (see [`crate::core::solver::StepStats::collider_forces`]).
#[derive(Component, Debug, Clone, Copy, Default, PartialEq, Reflect)]
#[reflect(Component, Default)]
pub struct ColliderForce(pub Vec3);

/// Ask for a body's particle positions: insert it on a [`SoftBody`] entity; the plugin
/// reads the positions back asynchronously and puts them in [`ParticlePositions`]. With
/// `continuous` the request stays and the positions are refreshed every frame; without,
/// the request is removed once served.
#[derive(Component, Debug, Clone, Copy, Default, PartialEq, Reflect)]
#[reflect(Component, Default)]
pub struct ReadbackParticles {
    /// Keep reading every frame.
    pub continuous: bool,
}

/// Particle positions read back from the GPU (world frame, m).
#[derive(Component, Debug, Clone, Default, PartialEq, Reflect)]
#[reflect(Component, Default)]
pub struct ParticlePositions {
    /// One per particle, in the body's sampling order.
    pub positions: Vec<Vec3>,
    /// The world's step counter when they were read.
    pub step: u64,
}

/// Where a [`SoftBody`] is in its life.
#[derive(Component, Debug, Clone, Default, PartialEq, Reflect)]
#[reflect(Component, Default)]
pub enum SoftBodyStatus {
    /// Waiting for its mesh asset or for a build slot.
    #[default]
    Pending,
    /// Particles and clusters being built off the main thread.
    Building,
    /// Simulated.
    Ready {
        /// Particles.
        particles: u32,
        /// Render vertices.
        vertices: u32,
    },
    /// Not simulated; the message names the problem (also sent as [`SoftBodyError`]).
    Failed(String),
}

/// Sent when a soft body cannot be simulated: a bad mesh, bad parameters, a model too
/// big for the GPU. The entity is left unsimulated; the app keeps running.
#[derive(Message, Debug, Clone, PartialEq)]
pub struct SoftBodyError {
    /// The entity.
    pub entity: Entity,
    /// What is wrong.
    pub error: String,
}

/// Sent when a soft body starts simulating (after a build or a rebuild).
#[derive(Message, Debug, Clone, Copy, PartialEq, Eq)]
pub struct SoftBodyReady {
    /// The entity.
    pub entity: Entity,
    /// Particles sampled.
    pub particles: u32,
}

/// Global simulation settings, in SI units.
#[derive(Resource, Debug, Clone, PartialEq, Reflect)]
#[reflect(Resource, Default)]
pub struct TissueSettings {
    /// Fixed time step, s.
    pub dt: f32,
    /// Substeps per step.
    pub substeps: u32,
    /// Constraint iterations per substep.
    pub iterations: u32,
    /// Iterations per coarse level of the bodies that have a hierarchy
    /// ([`SoftBody::hierarchy`]; default 20). Fewer (3–5) pay for loose solves, 10–20 for
    /// tight ones ([`crate::core::solver::SolverSettings::coarse_iterations`]).
    pub coarse_iterations: u32,
    /// Gravity, m/s².
    pub gravity: Vec3,
    /// Velocity damping rate, 1/s.
    pub damping: f32,
    /// Jacobi relaxation ω.
    pub relaxation: f32,
    /// Search the contact neighbours at least every this many steps (the paper: 10).
    /// Bodies stepped from the main world (lattice bodies, the default, and every body
    /// on the CPU) are searched on it only while they move relative to one another
    /// (lying still, or moving together, they keep their lists), and also whenever a
    /// particle may have moved out of the last search's reach, so they meet however fast
    /// they move; the render graph's cluster bodies are searched only on this schedule
    /// (fast impacts want 1 there).
    pub knn_every: u32,
    /// Particle contacts between bodies.
    pub particle_contacts: bool,
    /// Contact neighbours per particle.
    pub contact_neighbours: u32,
    /// Solve particle contacts in every this many iterations (and always in the last of
    /// a substep; default 2, with `contact_relaxation` 2). On the GPU a body near another
    /// runs one dispatch per contact pass, so 2 halves those dispatches and shortens the
    /// step of many touching bodies; alone, 2 holds contacts less firmly than 1, which
    /// the relaxation of 2 more than makes up for (measured in BENCHMARKS.md, "The
    /// plugin's contact schedule";
    /// [`crate::core::solver::SolverSettings::contact_every`]).
    pub contact_every: u32,
    /// Jacobi relaxation ω_c of the particle contacts (default 2: each particle takes
    /// the whole averaged overlap, which holds piles more firmly than 1;
    /// [`crate::core::solver::SolverSettings::contact_relaxation`]).
    pub contact_relaxation: f32,
    /// Most steps per frame (the accumulator drops time beyond it, so a slow frame does
    /// not snowball).
    pub max_steps_per_frame: u32,
    /// Where bodies are simulated (GPU, with the CPU for what it cannot run; or all on
    /// the CPU).
    pub backend: TissueBackend,
    /// Newton iterations per substep of lattice bodies (default 1). Their accuracy does
    /// not hang on it the way XPBD's hangs on `iterations`: one of one V-cycle lands
    /// within 1% of the static answer of a cantilever from 1 kPa to 1 MPa (BENCHMARKS.md,
    /// "The two-direction step").
    pub newton_iterations: u32,
    /// Multigrid V-cycles per Newton iteration of lattice bodies (default 1). One: each
    /// body's step is the V-cycle's correction and the last step's answer, weighted to
    /// minimise the step's energy model over the two (the last answer carries the
    /// smooth bending one V-cycle resolves slowly, so a stiff body settles at the rate
    /// gravity sets). More than one solve the Newton step by conjugate gradients, each
    /// V-cycle a preconditioner step.
    pub newton_cycles: u32,
    /// The V-cycle's smoothing sweeps for lattice bodies, after and before the coarse
    /// correction on the particles and on the levels between, and on the coarsest level
    /// (default 1 and 0 on the particles, 2 and 0 between, 30; each after-count from 1
    /// to 1,000, each before-count from 0), and whether the coarsest level is solved
    /// exactly where its bodies are small enough (default on; see
    /// [`Sweeps::exact_coarsest`]). The coarsest level's solve carries a stiff body's
    /// bending: swept instead, fewer sweeps leave a 1 MPa body too soft at real-time
    /// settings ([`crate::core::solver::SolverSettings::sweeps`]).
    #[reflect(ignore)]
    pub sweeps: Sweeps,
}

impl Default for TissueSettings {
    /// The core solver's defaults (the paper's dt, iterations and KNN interval), at most
    /// 4 steps per frame, except the contact schedule: the core defaults to Gauss–Seidel
    /// with contacts in every iteration, the plugin solves with Jacobi and defaults to
    /// contacts in every 2nd iteration relaxed by 2 ([`Self::PLUGIN_CONTACT_EVERY`],
    /// [`Self::PLUGIN_CONTACT_RELAXATION`]).
    fn default() -> Self {
        let c = SolverSettings::default();
        Self {
            dt: c.dt,
            substeps: c.substeps,
            iterations: c.iterations,
            coarse_iterations: c.coarse_iterations,
            gravity: c.gravity,
            damping: c.damping,
            relaxation: c.relaxation,
            knn_every: c.knn_every,
            particle_contacts: c.particle_contacts,
            contact_neighbours: c.contact_neighbours,
            contact_every: Self::PLUGIN_CONTACT_EVERY,
            contact_relaxation: Self::PLUGIN_CONTACT_RELAXATION,
            max_steps_per_frame: 4,
            backend: TissueBackend::default(),
            newton_iterations: Self::NEWTON_ITERATIONS,
            newton_cycles: Self::NEWTON_CYCLES,
            sweeps: c.sweeps,
        }
    }
}

impl TissueSettings {
    /// The plugin's default [`Self::contact_every`]: 2. Measured (CPU, Jacobi,
    /// `examples/contacts.rs`) with [`Self::PLUGIN_CONTACT_RELAXATION`] against contacts in
    /// every iteration unrelaxed: less overlap between bodies in ensembles of dropped
    /// piles (1, 2 and 4 substeps) and for a ball on a slab, in all but one regular pile
    /// (44% against 40% of the contact distance), similar mean jitter with larger peaks
    /// in some scenes, no bounce gained in a head-on collision; and on the GPU 15% less
    /// time per step for 1,000 touching bodies (BENCHMARKS.md, "The plugin's contact
    /// schedule").
    pub const PLUGIN_CONTACT_EVERY: u32 = 2;
    /// The plugin's default [`Self::contact_relaxation`], ω_c = 2 (see
    /// [`Self::PLUGIN_CONTACT_EVERY`]).
    pub const PLUGIN_CONTACT_RELAXATION: f32 = 2.0;
    /// The default [`Self::newton_iterations`]: 1.
    pub const NEWTON_ITERATIONS: u32 = 1;
    /// The default [`Self::newton_cycles`]: 1 (the two-direction step).
    pub const NEWTON_CYCLES: u32 = 1;

    /// The core solver settings of the CPU path ([`super::cpu`]): [`Self::to_core`] with
    /// Newton–multigrid for lattice bodies, [`Self::newton_iterations`] of them in each
    /// substep (cluster bodies keep `iterations`), on every core.
    pub fn to_core_cpu(&self) -> SolverSettings {
        SolverSettings {
            element_solver: ElementSolver::Multigrid,
            newton_iterations: self.newton_iterations.max(1),
            newton_cycles: self.newton_cycles.max(1),
            threads: 0,
            ..self.to_core()
        }
    }

    /// The core solver settings (Jacobi: the GPU's method).
    pub fn to_core(&self) -> SolverSettings {
        SolverSettings {
            dt: self.dt,
            substeps: self.substeps,
            iterations: self.iterations,
            coarse_iterations: self.coarse_iterations,
            gravity: self.gravity,
            damping: self.damping,
            relaxation: self.relaxation,
            knn_every: self.knn_every,
            particle_contacts: self.particle_contacts,
            contact_neighbours: self.contact_neighbours,
            contact_every: self.contact_every,
            contact_relaxation: self.contact_relaxation,
            sweeps: self.sweeps,
            method: Method::Jacobi,
            ..Default::default()
        }
    }
}

/// The simulation clock: a fixed-dt accumulator over `Time`, with pause and single step.
#[derive(Resource, Debug, Clone, Default, PartialEq, Reflect)]
#[reflect(Resource, Default)]
pub struct TissueClock {
    /// No steps while paused (except single steps).
    pub paused: bool,
    /// Steps to take on the next frame regardless of time and pause (single stepping;
    /// also how tests and benchmarks drive an exact number of steps).
    pub pending_steps: u32,
    /// When set, exactly this many steps per frame, ignoring `Time` (headless runs).
    pub fixed_steps_per_frame: Option<u32>,
    /// Unsimulated time, s.
    pub accumulator: f32,
    /// Steps taken so far.
    pub steps: u64,
    /// Steps of the current frame.
    pub steps_this_frame: u32,
}

impl TissueClock {
    /// Pause or resume.
    pub fn toggle_pause(&mut self) {
        self.paused = !self.paused;
    }

    /// Take one step on the next frame (also while paused).
    pub fn step_once(&mut self) {
        self.pending_steps += 1;
    }

    /// The simulated time a frame spans, s, over which a collider's motion in that
    /// frame is its velocity: `n` steps of `dt` (s) where the clock takes exactly `n`
    /// steps a frame (headless and scripted runs, whatever the frame's wall time), else
    /// the frame's wall time `wall` (s).
    pub fn frame_seconds(&self, dt: f32, wall: f32) -> f32 {
        match self.fixed_steps_per_frame {
            Some(n) if n > 0 => n as f32 * dt,
            _ => wall,
        }
        .max(1e-6)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A scripted run's collider moves its frame's distance in the frame's fixed steps,
    /// not in the frame's wall time; a real-time run's in the wall time.
    #[test]
    fn a_frame_spans_its_fixed_steps_or_its_wall_time() {
        let dt = 1.0 / 60.0;
        let fixed = TissueClock {
            fixed_steps_per_frame: Some(2),
            ..Default::default()
        };
        assert_eq!(fixed.frame_seconds(dt, 0.25), 2.0 * dt);
        assert_eq!(TissueClock::default().frame_seconds(dt, 0.25), 0.25);
        assert!(TissueClock::default().frame_seconds(dt, 0.0) > 0.0);
    }

    #[test]
    fn settings_reach_the_core_solver_field_by_field() {
        let core = SolverSettings::default();
        let d = TissueSettings::default().to_core();
        // The plugin's own contact schedule; the rest is the core's.
        assert_eq!((d.contact_every, d.contact_relaxation), (2, 2.0));
        assert_eq!((core.contact_every, core.contact_relaxation), (1, 1.0));
        assert_eq!(d.knn_every, core.knn_every);
        assert_eq!(
            (d.dt, d.iterations, d.substeps),
            (core.dt, core.iterations, core.substeps)
        );
        let s = TissueSettings {
            contact_every: 3,
            contact_relaxation: 2.0,
            knn_every: 5,
            iterations: 7,
            ..Default::default()
        }
        .to_core();
        assert_eq!((s.contact_every, s.knn_every, s.iterations), (3, 5, 7));
        assert_eq!(s.contact_relaxation, 2.0);
        assert_eq!(s.method, Method::Jacobi);
        assert!(s.validate().is_ok());
        let bad = TissueSettings {
            contact_every: 0,
            ..Default::default()
        };
        assert!(bad.to_core().validate().is_err());
        // The V-cycle's sweeps reach the core, on either path; a count of 0 is refused.
        let sweeps = Sweeps {
            fine: 2,
            fine_before: 2,
            coarse: 3,
            coarse_before: 3,
            coarsest: 12,
            exact_coarsest: false,
            translation: true,
        };
        let s = TissueSettings {
            sweeps,
            ..Default::default()
        };
        assert_eq!(
            (s.to_core().sweeps, s.to_core_cpu().sweeps),
            (sweeps, sweeps)
        );
        assert_eq!(TissueSettings::default().sweeps, Sweeps::DEFAULT);
        let bad = TissueSettings {
            sweeps: Sweeps {
                coarsest: 0,
                ..sweeps
            },
            ..Default::default()
        };
        let e = bad.to_core().validate().unwrap_err().to_string();
        assert!(e.contains("coarsest"), "{e}");
    }
}
