//! The CPU reference solver: fixed dt, substeps, iterations;
//! predict → neighbours → constraints → velocity update and damping.
//!
//! Two methods:
//! * [`Method::GaussSeidel`] — clusters solved one after another, each correction applied
//!   at once; one thread, deterministic: the paper's CPU baseline.
//! * [`Method::Jacobi`] — every cluster solved from the same positions (pass A, parallel
//!   over clusters), then every particle gathers the corrections of the clusters that
//!   contain it (pass B, parallel over particles); contacts, colliders and pins follow
//!   from the updated positions (pass C). Shape matching is averaged with the
//!   cluster weight `1/s_c` (constraint averaging, Macklin et al. 2014 §4.2, with a
//!   per-cluster weight so that momentum is conserved); the XPBD clusters are solved with
//!   split masses (each cluster owns `m_j/n_j` of each member, Tonge et al. 2012), which
//!   averages stiff corrections and lets compliant ones act in full. Both relaxed by ω.
//!   Results do not depend on the thread count.
//!
//! Each step checks for non-finite or exploding state; a bad step is undone and reported
//! as [`TissueError::Diverged`] instead of spreading NaN.

use super::colliders::{Collider, ColliderShape, Grab, grab_target, project_collider, update_grab};
use super::constraints::{
    ClusterCorrection, ClusterRest, Hyperelastic, Multipliers, cluster_moments, extract_rotation,
    iteration_stiffness, outer, solve_contact, solve_hyperelastic, solve_shape_matching,
    strain_dead_band,
};
use super::element::{
    CORNERS, ElementMultipliers, ElementSolve, HexModes, element_gradient, multiplier_displacement,
    solve_element,
};
use super::error::{TissueError, in_range, positive};
use super::model::{Level, Material, Model};
use super::par;
use glam::{Mat3, Quat, Vec3};

/// How constraints are iterated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Method {
    /// Sequential Gauss–Seidel on one thread. The default: on the hyperelastic liver at
    /// 13,824 particles it converges far better per millisecond than Jacobi on two cores
    /// (BENCHMARKS.md, "Gauss–Seidel or Jacobi").
    #[default]
    GaussSeidel,
    /// Parallel Jacobi with constraint averaging and relaxation.
    Jacobi,
}

/// How the hexahedral elements of lattice bodies are solved.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ElementSolver {
    /// XPBD constraints (the centre's hyperelastic constraints, the hourglass modes),
    /// iterated by [`SolverSettings::method`], multipliers from zero each substep (or
    /// carried over with [`SolverSettings::warm_start`]).
    #[default]
    Xpbd,
    /// Vertex block descent (Chen et al. 2024, "Vertex Block Descent"): each particle in
    /// turn takes a Newton step on the implicit-Euler energy of its elements,
    /// `(m/h² + H) Δx = m/h² (x̃ − x) + f`, from an initial guess that is the previous
    /// positions moved by the velocity and the acceleration of the last substep (their
    /// adaptive initialisation), so that a body at rest starts at rest and its static
    /// equilibrium is the iteration's fixed point at any iteration count. A Gauss–Seidel
    /// sweep over the particles whichever [`Method`] is set.
    VertexDescent,
    /// Newton's method on each substep's implicit-Euler equations, each iteration's
    /// linear solve one multigrid V-cycle on the lattice ([`super::multigrid`]): the
    /// residual `M/h² (x̃ − y) + f(y)`, the corotated element stiffness, smoothing by
    /// [`SolverSettings::smoother`], coarse lattices of 2 × 2 × 2 cells with the same element. Starts from
    /// the previous positions moved by their velocity, so a body at rest starts at rest
    /// and its static equilibrium is the fixed point; the coarse levels carry bending
    /// across the body in one iteration. Colliders enter the solve as stiff penalties
    /// (the contacts of the last substep and any penetration), so a body pressed by a
    /// collider is solved with the collider's push, not against it; the boundary
    /// projection then removes what penetration remains and applies friction. Runs the
    /// same whichever [`Method`] is set (the method still solves the clusters of other
    /// bodies).
    Multigrid,
}

/// Time stepping and solver settings.
#[derive(Debug, Clone, PartialEq)]
pub struct SolverSettings {
    /// Fixed time step, s.
    pub dt: f32,
    /// Substeps per step.
    pub substeps: u32,
    /// Constraint iterations per substep.
    pub iterations: u32,
    /// Gravity, m/s².
    pub gravity: Vec3,
    /// Velocity damping rate, 1/s (`v ← v·max(0, 1 − damping·h)`).
    pub damping: f32,
    /// Iteration method.
    pub method: Method,
    /// Jacobi relaxation of the particle contacts, ω_c: the averaged contact correction
    /// of a particle (each contact its mass share of the overlap) is scaled by it in
    /// Jacobi's pass C (Gauss–Seidel ignores it; Macklin et al. 2014, "Unified particle
    /// physics", §4.2, constraint averaging with over-relaxation). 1, the default here,
    /// resolves a contact between two free particles exactly; 2 lets each particle take
    /// the whole overlap, which holds piles more firmly under Jacobi (an ensemble of
    /// dropped piles: 68% of the contact distance deep against 86%; BENCHMARKS.md, "The
    /// plugin's contact schedule"). The plugin defaults to 2
    /// (`plugin::components::TissueSettings`). Particles of lattice bodies under
    /// [`ElementSolver::Multigrid`] take at most 1: their contacts already push as
    /// penalties inside the Newton iterations, and the projection after them only removes
    /// what overlap is left; over-relaxed, it overshoots against a held or heavier
    /// partner and the bodies bounce and jitter where they rest on each other.
    pub contact_relaxation: f32,
    /// Jacobi relaxation ω (1 = plain averaging; above 1 over-relaxes): shape-matching
    /// corrections are scaled by `ω/s_c`, XPBD multiplier increments (solved with split
    /// masses) and their corrections by `ω`.
    pub relaxation: f32,
    /// Worker threads for Jacobi and KNN (0 = all cores).
    pub threads: usize,
    /// Search the particle-contact neighbours at least every this many steps while the
    /// particles move relative to one another (the paper: 10; bodies lying still, or
    /// moving together, keep their lists: [`Solver::contacts_moved`]). [`Solver::step`]
    /// also searches whenever a particle may have moved out of the last search's reach
    /// ([`Solver::refresh_contacts_if_due`]: the search reaches farther the faster the
    /// particles move), so bodies meeting fast find each other whatever this is; the GPU
    /// world of the paper's clusters searches only on this schedule, moving or not.
    pub knn_every: u32,
    /// Particle–particle contacts between bodies on.
    pub particle_contacts: bool,
    /// Neighbours searched per particle for contacts.
    pub contact_neighbours: u32,
    /// Solve particle contacts in every this many iterations (and always in the last of
    /// a substep; 1, the default here, is every iteration); colliders and pins in every
    /// iteration. The GPU runs the iterations of a body near another one dispatch per
    /// contact pass, so 2 halves those dispatches. Alone a trade (`examples/contacts.rs`,
    /// BENCHMARKS.md): with 2 bodies press a little deeper into each other under Jacobi;
    /// from 3 Gauss–Seidel lets a ball through a slab. With `contact_relaxation` 2, under
    /// Jacobi, 2 and 2 held contacts more firmly than 1 and 1 in every ensemble and slab
    /// run measured (one regular pile excepted): the plugin's default
    /// (`plugin::components::TissueSettings`).
    pub contact_every: u32,
    /// Most iterations of the warm-started rotation extraction per cluster solve (it stops
    /// early once converged; usually 1–2 when warm).
    pub rotation_iterations: u32,
    /// A particle faster than this (m/s) marks the step as exploded.
    pub max_speed: f32,
    /// Record the residual after every iteration in [`StepStats::residuals`] (costs a
    /// residual evaluation per iteration; for convergence studies).
    pub trace_residual: bool,
    /// Iterations per coarse level of hierarchical PBD in each substep (Müller 2008's
    /// schedule: the coarsest level first, each level's corrections prolongated to the
    /// finer level, level 0 last with `iterations`). Only bodies built with a hierarchy
    /// ([`super::model::BodyDesc::hierarchy`]) have coarse levels; 0 skips them. The
    /// default 20 reaches tight residuals (5e-4 and below) much sooner than 10 or 5 on a
    /// stiff bar. For loose solves (a residual near 1e-3) use fewer, 3–5: a small level's
    /// dispatch costs about as much as a large one's, so on the GPU the coarse pass is
    /// then cheaper; 4 does well at both. BENCHMARKS.md ("Hierarchy") has the
    /// measurements.
    pub coarse_iterations: u32,
    /// The constraints of the coarse levels.
    pub coarse_constraint: CoarseConstraint,
    /// Carry the XPBD multipliers of lattice elements from one substep to the next,
    /// applying their displacement at the start of the substep (a consistent warm
    /// start). Plain XPBD starts every substep from zero multipliers, and a substep whose
    /// iterations stop short leaves the body softer than its material: its rest under a
    /// load is not the static equilibrium. With the warm start the static equilibrium is
    /// the iteration's fixed point at any iteration count; few iterations only slow the
    /// approach to it.
    pub warm_start: bool,
    /// How lattice bodies' elements are solved.
    pub element_solver: ElementSolver,
    /// [`ElementSolver::Multigrid`]: Newton iterations per substep, taken in the first
    /// iterations of the substep (0: one in every iteration). Lets a world of lattice
    /// and cluster bodies give the clusters their `iterations` and the lattice the few
    /// Newton iterations it needs. Each Newton iteration ends with the lattice
    /// particles' projections (particle contacts every [`Self::contact_every`]-th and in
    /// the last, then colliders and pins); the iterations after the last leave lattice
    /// particles where it put them. Default 1 (with [`Self::newton_cycles`] 1).
    pub newton_iterations: u32,
    /// Vertex block descent: start from the last substep's acceleration along gravity
    /// (Chen et al. 2024's adaptive initialisation) instead of the velocity alone.
    pub descent_adaptive_init: bool,
    /// [`ElementSolver::Multigrid`]: how the V-cycle smooths each level.
    pub smoother: super::multigrid::Smoother,
    /// [`ElementSolver::Multigrid`]: V-cycles per Newton iteration. 1: the Newton step is
    /// one V-cycle's correction and the last Newton step's answer, each body's two
    /// weights minimising the step's quadratic model
    /// ([`super::multigrid::LatticeMultigrid::two_direction`]). More: conjugate
    /// gradients preconditioned by the V-cycle solve the Newton system, one V-cycle per
    /// iteration ([`super::multigrid::LatticeMultigrid::krylov`]). Either way the same
    /// trust region and line search follow. Must be at least 1; default 1: within 1% of
    /// the static answer of a settled cantilever from 1 kPa to 1 MPa, as 2 V-cycles of
    /// conjugate gradients are, at the cost of one V-cycle and one product.
    pub newton_cycles: u32,
    /// [`ElementSolver::Multigrid`]: the V-cycle's smoothing sweeps on level 0, on the
    /// levels between and on the coarsest ([`super::multigrid::Sweeps`]; in pairs where
    /// [`Self::smoother`] smooths a level by Chebyshev). Default one sweep on level 0 and
    /// two on the levels between, each after the coarse correction and none before, and
    /// the coarsest level solved exactly where its bodies are small enough (30 sweeps
    /// where not).
    pub sweeps: super::multigrid::Sweeps,
}

/// What the coarse levels of hierarchical PBD solve. Level 0 is solved last in every
/// substep, but XPBD reads any motion its own multipliers did not make as an external
/// force, so the coarse motion is handed to level 0 with the coarse multipliers
/// ([`Solver`] interpolates them to the level-0 clusters). That hand-over is not exact: a
/// settled 30 kPa cantilever sags 7–9% less with the hierarchy than without
/// (BENCHMARKS.md, "Hierarchy", where the repairs tried are listed).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum CoarseConstraint {
    /// Coarse clusters of the body's own elastic model (each coarse particle and its K
    /// nearest coarse particles) with compliance matched to level 0: the same material,
    /// the cluster volumes partitioning the body, so the energy density is the same.
    #[default]
    Clusters,
    /// Unilateral distance constraints (Müller 2008 §4.3) between each coarse particle
    /// and its K nearest: they only resist stretching beyond the rest distance, so they
    /// never push a compressed region apart. Averaged like Jacobi.
    Distance,
}

impl Default for SolverSettings {
    /// The accurate real-time setting, the plugin's for lattice bodies: one step of
    /// 1/60 s, one substep, gravity −9.81 m/s² along y; lattice bodies by
    /// Newton–multigrid, one Newton iteration (one V-cycle and the two-direction step,
    /// then an energy line search), every step each body's own; the paper's clusters by 10 Gauss–Seidel
    /// iterations (lattice bodies take no part in the iterations after their Newton
    /// iteration: to the clusters they are obstacles held where it left them).
    fn default() -> Self {
        Self {
            dt: 1.0 / 60.0,
            substeps: 1,
            iterations: 10,
            gravity: Vec3::new(0.0, -9.81, 0.0),
            damping: 1.0,
            method: Method::GaussSeidel,
            relaxation: 1.0,
            contact_relaxation: 1.0,
            threads: 0,
            knn_every: 10,
            particle_contacts: true,
            contact_neighbours: 16,
            contact_every: 1,
            rotation_iterations: 2,
            max_speed: 500.0,
            trace_residual: false,
            coarse_iterations: 20,
            coarse_constraint: CoarseConstraint::Clusters,
            warm_start: false,
            element_solver: ElementSolver::Multigrid,
            newton_iterations: 1,
            descent_adaptive_init: false,
            smoother: Default::default(),
            newton_cycles: 1,
            sweeps: Default::default(),
        }
    }
}

impl SolverSettings {
    /// The Newton iterations a substep takes on lattice bodies under
    /// [`ElementSolver::Multigrid`]: the first [`Self::newton_iterations`] of the
    /// [`Self::iterations`], or all of them for 0.
    pub fn newton_count(&self) -> u32 {
        if self.newton_iterations == 0 {
            self.iterations
        } else {
            self.newton_iterations.min(self.iterations)
        }
    }

    /// Whether `other` differs from these settings only in what a step reads as it goes:
    /// gravity, velocity damping and the divergence speed. A [`Solver`] made with one
    /// then steps with the other once its [`Solver::settings`] are replaced; nothing it
    /// precomputed depends on them.
    pub fn differs_only_in_forces(&self, other: &SolverSettings) -> bool {
        let same_rest = SolverSettings {
            gravity: other.gravity,
            damping: other.damping,
            max_speed: other.max_speed,
            ..self.clone()
        };
        same_rest == *other
    }

    /// Whether `other` differs from these settings only in what [`Self::differs_only_in_forces`]
    /// names and in the step's schedule: `dt`, `substeps`, `iterations`,
    /// `newton_iterations`, `contact_relaxation`, `contact_every` and `knn_every` (what
    /// the GPU lattice world takes without being made again,
    /// `gpu::lattice::GpuLattice::set_steps`).
    pub fn differs_only_in_steps(&self, other: &SolverSettings) -> bool {
        let same_rest = SolverSettings {
            gravity: other.gravity,
            damping: other.damping,
            max_speed: other.max_speed,
            dt: other.dt,
            substeps: other.substeps,
            iterations: other.iterations,
            newton_iterations: other.newton_iterations,
            contact_relaxation: other.contact_relaxation,
            contact_every: other.contact_every,
            knn_every: other.knn_every,
            ..self.clone()
        };
        same_rest == *other
    }

    /// Checks every field.
    pub fn validate(&self) -> Result<(), TissueError> {
        positive("dt", self.dt)?;
        positive("relaxation", self.relaxation)?;
        positive("contact_relaxation", self.contact_relaxation)?;
        positive("max_speed", self.max_speed)?;
        in_range("damping", self.damping, 0.0, f32::MAX, "a finite value ≥ 0")?;
        let count = |name, v: u32| {
            if v == 0 {
                Err(TissueError::InvalidParameter {
                    name,
                    value: "0".into(),
                    expected: "at least 1",
                })
            } else {
                Ok(())
            }
        };
        count("substeps", self.substeps)?;
        count("iterations", self.iterations)?;
        count("knn_every", self.knn_every)?;
        count("contact_every", self.contact_every)?;
        count("newton_cycles", self.newton_cycles)?;
        self.sweeps.check()?;
        if !self.gravity.is_finite() {
            return Err(TissueError::InvalidParameter {
                name: "gravity",
                value: format!("{:?}", self.gravity),
                expected: "a finite vector",
            });
        }
        Ok(())
    }
}

/// The time-varying state of all particles.
#[derive(Debug, Clone, PartialEq)]
pub struct State {
    /// Positions, m (world).
    pub x: Vec<Vec3>,
    /// Velocities, m/s.
    pub v: Vec<Vec3>,
    /// Each cluster's last rotation (warm start of the rotation extraction).
    pub rot: Vec<Quat>,
    /// Each hexahedral element's last rotation (same role; [`Model::elements`]).
    pub element_rot: Vec<Quat>,
    /// Target of each pinned particle (same order as `Model::pinned`), m.
    pub pin_targets: Vec<Vec3>,
    /// Per particle: the grasper holding it, if any ([`ColliderShape::Grasper`]).
    pub grab: Vec<Grab>,
    /// Steps taken.
    pub step: u64,
}

impl State {
    /// The rest state: every body placed as its description said, at rest.
    pub fn new(model: &Model) -> Self {
        let x = model.placed_rest();
        let rot = model
            .particle_body
            .iter()
            .map(|&b| model.bodies[b as usize].rotation)
            .collect();
        let pin_targets = model.pinned.iter().map(|&i| x[i as usize]).collect();
        let element_rot = model
            .element_body
            .iter()
            .map(|&b| model.bodies[b as usize].rotation)
            .collect();
        Self {
            v: vec![Vec3::ZERO; x.len()],
            element_rot,
            grab: vec![Grab::FREE; x.len()],
            x,
            rot,
            pin_targets,
            step: 0,
        }
    }
}

/// What the scene drives: kinematic colliders.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Control {
    /// Kinematic colliders.
    pub colliders: Vec<Collider>,
}

/// Per-step outputs.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct StepStats {
    /// Force each collider received from the tissue over the step, N (same order as
    /// `Control::colliders`): the momentum its projection removed, or, on lattice bodies
    /// stepped by Newton–multigrid, the reaction of the particles touching it at each
    /// substep's end (what holds them against their inertia and their elements' forces:
    /// a body at rest presses on the ground with its weight); on a grasper, the tissue's
    /// pull on the particles it holds.
    pub collider_forces: Vec<Vec3>,
    /// Whether the particle-contact neighbours were refreshed this step.
    pub knn_refreshed: bool,
    /// Active particle contacts at the end of the step (pairs counted per particle).
    pub active_contacts: usize,
    /// Wall-clock time per stage of this step.
    pub timings: StageTimes,
    /// With [`SolverSettings::trace_residual`]: level 0's residual ([`Solver::residual`])
    /// before the first iteration of each substep, after its coarse levels and after each
    /// iteration, with the solve time spent up to that point (ms, not counting the
    /// residual evaluations themselves).
    pub residuals: Vec<ResidualSample>,
}

/// One point of a residual trace.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ResidualSample {
    /// Substep index.
    pub substep: u32,
    /// Level-0 iterations done in this substep (0: before any; the coarse levels, when
    /// present, have run).
    pub iteration: u32,
    /// Residual, relative to the body size (see [`Solver::residual`]).
    pub residual: f32,
    /// Solve time of the step so far, ms.
    pub ms: f64,
}

/// Wall-clock time per stage of a step, ms (as rapier reports its pipeline stages).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageTimes {
    /// Contact-neighbour KNN refresh.
    pub knn: f64,
    /// Prediction `p = x + h v`.
    pub predict: f64,
    /// Cluster solves (Jacobi pass A; the whole Gauss–Seidel sweep).
    pub clusters: f64,
    /// Jacobi pass B: every particle gathers its clusters' corrections.
    pub gather: f64,
    /// Contacts, colliders and pins (Jacobi pass C; the Gauss–Seidel particle loop).
    pub boundary: f64,
    /// Velocity update, damping, divergence check.
    pub finish: f64,
    /// Coarse levels of the hierarchy (their solves and the prolongation).
    pub coarse: f64,
}

impl StageTimes {
    /// Sum of all stages, ms.
    pub fn total(&self) -> f64 {
        self.knn
            + self.predict
            + self.clusters
            + self.gather
            + self.boundary
            + self.finish
            + self.coarse
    }
}

/// Milliseconds since `t`.
fn ms(t: std::time::Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// Per-body constants for one substep.
#[derive(Clone, Copy)]
enum BodyConst {
    Sm { k_iter: f32 },
    He { mat: Hyperelastic },
}

/// One element's XPBD multipliers and, under Jacobi, its last corner corrections.
#[derive(Debug, Clone, Copy)]
struct ElementWork {
    lam: ElementMultipliers,
    corr: [Vec3; CORNERS],
}

impl ElementWork {
    const ZERO: Self = Self {
        lam: ElementMultipliers::ZERO,
        corr: [Vec3::ZERO; CORNERS],
    };
}

/// The hourglass modes of a body's material, kept while E and ν stay the same.
#[derive(Debug, Clone)]
struct BodyModes {
    youngs_modulus: f32,
    poisson_ratio: f32,
    mat: Hyperelastic,
    modes: HexModes,
}

/// The CPU solver with its workspace.
#[derive(Debug, Clone)]
pub struct Solver {
    /// Settings used by [`Solver::step`].
    pub settings: SolverSettings,
    p: Vec<Vec3>,
    p2: Vec<Vec3>,
    /// Per cluster: last correction and XPBD multipliers `[λ_H, λ_D]`.
    work: Vec<(ClusterCorrection, Multipliers)>,
    pin_slot: Vec<u32>,
    contact_start: Vec<u32>,
    contact_list: Vec<u32>,
    /// Positions at the last particle-contact search, m (empty before the first).
    contact_ref: Vec<Vec3>,
    /// The least slack of the last search, m: every pair of particles of different
    /// bodies this much farther apart than their contact distance was left out.
    contact_skin: f32,
    /// Per particle: collider correction summed over the substep, and the collider.
    col: Vec<(Vec3, u32)>,
    timings: StageTimes,
    backup_x: Vec<Vec3>,
    backup_v: Vec<Vec3>,
    h: f32,
    /// One solver and state per coarse level of the hierarchy (`Model::levels`).
    levels: Vec<LevelSolver>,
    /// Positions at the start of the coarse levels' pass (prolongation reference).
    snap: Vec<Vec3>,
    /// Per-particle constraint counts of the distance iteration (kept to reuse).
    counts: Vec<u32>,
    /// Whether the current iteration solves particle contacts
    /// ([`SolverSettings::contact_every`]).
    contacts_now: bool,
    /// Whether the current iteration projects the particle contacts of lattice
    /// particles under Newton–multigrid: every [`SolverSettings::contact_every`]-th of
    /// the substep's Newton iterations and the last of them.
    lattice_contacts_now: bool,
    /// Per hexahedral element: multipliers and Jacobi corrections.
    element_work: Vec<ElementWork>,
    /// Per body: its hourglass modes (lattice bodies only).
    modes: Vec<Option<BodyModes>>,
    /// Vertex block descent: each particle's inertial target `x̃ = x + h v + h² g` of the
    /// substep, m.
    target: Vec<Vec3>,
    /// Vertex block descent: each particle's acceleration over the last substep, m/s².
    accel: Vec<Vec3>,
    /// Multigrid: the lattice hierarchy (built on first use) and its work space.
    mg: Option<Box<super::multigrid::LatticeMultigrid>>,
    mg_work: super::multigrid::MgWork,
    /// Per particle: the collider the boundary projection moved it out of in the last
    /// substep, or `u32::MAX` (multigrid: the contacts that start the next substep
    /// active).
    touched: Vec<u32>,
    /// Multigrid: per particle, whether the last particle-contact projection found one
    /// of its own candidates pressed into it ([`pressed_pair`]: a pair the Newton
    /// iteration left pressed together, held a little past touching in the next:
    /// [`PAIR_HOLD`]).
    pressed: Vec<bool>,
    /// Multigrid: the next Newton iteration is its substep's first.
    mg_fresh: bool,
    /// Multigrid: per particle, the force on a grasper (the pull it holds against) in the
    /// last Newton iteration, N, and which (`u32::MAX`:
    /// none).
    newton_force: Vec<(Vec3, u32)>,
    /// Multigrid: this iteration takes a Newton step ([`SolverSettings::newton_iterations`]).
    newton_now: bool,
    /// Substep length the element multipliers were made with (a multiplier is a force
    /// times h², so a warm start rescales them when h changes), s.
    element_h: f32,
}

/// A coarse level's own solver and state, and which of level 0's pin slots each of its
/// pins follows.
#[derive(Debug, Clone)]
struct LevelSolver {
    solver: Solver,
    state: State,
    pin_map: Vec<u32>,
}

impl Solver {
    /// A solver for `model`; fails on invalid settings.
    pub fn new(model: &Model, settings: SolverSettings) -> Result<Self, TissueError> {
        settings.validate()?;
        let n = model.particle_count();
        let mut pin_slot = vec![u32::MAX; n];
        for (s, &i) in model.pinned.iter().enumerate() {
            pin_slot[i as usize] = s as u32;
        }
        let mut levels = Vec::with_capacity(model.levels.len());
        for lv in &model.levels {
            let coarse = SolverSettings {
                iterations: settings.coarse_iterations.max(1),
                particle_contacts: false,
                ..settings.clone()
            };
            let pin_map = lv
                .model
                .pinned
                .iter()
                .map(|&i| pin_slot[lv.source[i as usize] as usize])
                .collect();
            levels.push(LevelSolver {
                solver: Solver::new(&lv.model, coarse)?,
                state: State::new(&lv.model),
                pin_map,
            });
        }
        Ok(Self {
            settings,
            p: vec![Vec3::ZERO; n],
            p2: vec![Vec3::ZERO; n],
            work: vec![(ClusterCorrection::ZERO, Multipliers::ZERO); n],
            pin_slot,
            contact_start: vec![0; n + 1],
            contact_list: Vec::new(),
            contact_ref: Vec::new(),
            contact_skin: 0.0,
            col: vec![(Vec3::ZERO, u32::MAX); n],
            timings: StageTimes::default(),
            backup_x: Vec::new(),
            backup_v: Vec::new(),
            h: 0.0,
            levels,
            snap: Vec::new(),
            counts: Vec::new(),
            contacts_now: true,
            lattice_contacts_now: true,
            element_work: vec![ElementWork::ZERO; model.elements.len()],
            modes: Vec::new(),
            element_h: 0.0,
            target: Vec::new(),
            accel: vec![Vec3::ZERO; n],
            mg: None,
            mg_work: Default::default(),
            touched: vec![u32::MAX; n],
            pressed: vec![false; n],
            mg_fresh: false,
            newton_force: Vec::new(),
            newton_now: true,
        })
    }

    /// Refreshes the hourglass modes of every lattice body whose material changed.
    fn refresh_modes(&mut self, model: &Model) {
        self.modes.resize(model.bodies.len(), None);
        for (b, body) in model.bodies.iter().enumerate() {
            let Material::Hyperelastic {
                youngs_modulus,
                poisson_ratio,
            } = body.material
            else {
                self.modes[b] = None;
                continue;
            };
            if body.discretisation != super::model::Discretisation::Lattice {
                continue;
            }
            let fresh = self.modes[b].as_ref().is_some_and(|m| {
                m.youngs_modulus == youngs_modulus && m.poisson_ratio == poisson_ratio
            });
            if !fresh {
                let mat = Hyperelastic::new(youngs_modulus, poisson_ratio);
                self.modes[b] = Some(BodyModes {
                    youngs_modulus,
                    poisson_ratio,
                    mat,
                    modes: HexModes::of(&mat),
                });
            }
        }
    }

    fn body_consts(&self, model: &Model) -> Vec<BodyConst> {
        model
            .bodies
            .iter()
            .map(|b| match b.material {
                Material::ShapeMatching { stiffness } => BodyConst::Sm {
                    k_iter: iteration_stiffness(stiffness, self.settings.iterations),
                },
                Material::Hyperelastic {
                    youngs_modulus,
                    poisson_ratio,
                } => BodyConst::He {
                    mat: Hyperelastic::new(youngs_modulus, poisson_ratio),
                },
            })
            .collect()
    }

    /// Advances `state` by one step of `settings.dt`. On divergence the state is restored
    /// to what it was before the call and an error names the particle.
    pub fn step(
        &mut self,
        model: &Model,
        state: &mut State,
        control: &Control,
    ) -> Result<StepStats, TissueError> {
        let s = self.settings.clone();
        s.validate()?;
        let n = model.particle_count();
        if state.x.len() != n
            || state.v.len() != n
            || state.rot.len() != n
            || state.grab.len() != n
            || state.element_rot.len() != model.elements.len()
        {
            return Err(TissueError::InvalidParameter {
                name: "state",
                value: format!("{} particles", state.x.len()),
                expected: "a State made for this model",
            });
        }
        self.backup_x.clone_from(&state.x);
        self.backup_v.clone_from(&state.v);
        let mut stats = StepStats {
            collider_forces: vec![Vec3::ZERO; control.colliders.len()],
            ..Default::default()
        };
        self.timings = StageTimes::default();
        if s.particle_contacts {
            let t = std::time::Instant::now();
            let periodic =
                state.step.is_multiple_of(s.knn_every as u64) && self.contacts_moved(&state.x);
            stats.knn_refreshed =
                self.refresh_contacts_if_due(model, &state.x, &state.v, &[], 1, periodic);
            self.timings.knn = ms(t);
        }
        let consts = self.body_consts(model);
        self.refresh_modes(model);
        if self.element_work.len() != model.elements.len() {
            self.element_work = vec![ElementWork::ZERO; model.elements.len()];
        }
        let h = s.dt / s.substeps as f32;
        self.h = h;
        let t_step = std::time::Instant::now();
        let mut traced = 0.0f64;
        for substep in 0..s.substeps {
            // 1. predict
            let t = std::time::Instant::now();
            let descent = s.element_solver != ElementSolver::Xpbd && !model.elements.is_empty();
            if descent {
                self.backup_substep_velocity(state);
            }
            for i in 0..n {
                state.v[i] += s.gravity * h;
                self.p[i] = state.x[i] + state.v[i] * h;
            }
            if descent {
                self.descent_initial_guess(model, state, h);
            }
            for (slot, &i) in model.pinned.iter().enumerate() {
                self.p[i as usize] = state.pin_targets[slot];
            }
            // Graspers let go and take particles; held particles start at their target.
            if !control.colliders.is_empty() {
                for i in 0..n {
                    if self.pin_slot[i] != u32::MAX {
                        continue;
                    }
                    update_grab(&control.colliders, state.x[i], &mut state.grab[i]);
                    if let Some(t) = grab_target(&control.colliders, &state.grab[i]) {
                        self.p[i] = t;
                    }
                }
            }
            // XPBD multipliers start from zero every substep (Macklin et al. 2016).
            self.work.iter_mut().for_each(|w| w.1 = Multipliers::ZERO);
            if s.warm_start && self.element_h > 0.0 {
                self.warm_start_elements(model, state, h);
            } else {
                self.element_work
                    .iter_mut()
                    .for_each(|w| w.lam = ElementMultipliers::ZERO);
            }
            self.element_h = h;
            self.col
                .iter_mut()
                .for_each(|d| *d = (Vec3::ZERO, u32::MAX));
            self.newton_force.clear();
            self.timings.predict += ms(t);
            // 2. constraints: the hierarchy's coarse levels, coarsest first, then level 0.
            if s.coarse_iterations > 0 && !model.levels.is_empty() {
                let t = std::time::Instant::now();
                self.solve_levels(model, state, control);
                self.timings.coarse += ms(t);
            }
            let mut trace = |me: &Self, iteration: u32, rot: &[Quat]| {
                if s.trace_residual {
                    let t = std::time::Instant::now();
                    let residual = me.residual_at(model, &me.p, rot);
                    stats.residuals.push(ResidualSample {
                        substep,
                        iteration,
                        residual,
                        ms: ms(t_step) - traced,
                    });
                    traced += ms(t);
                }
            };
            trace(self, 0, &state.rot);
            let newton = s.newton_count();
            for it in 0..s.iterations {
                self.contacts_now =
                    (it + 1).is_multiple_of(s.contact_every) || it + 1 == s.iterations;
                self.lattice_contacts_now =
                    (it + 1).is_multiple_of(s.contact_every) || it + 1 == newton;
                self.newton_now = it < newton;
                self.iterate(model, state, control, &consts);
                trace(self, it + 1, &state.rot);
            }
            // Collider forces: momentum the colliders removed over the substep; on
            // lattice particles stepped by Newton–multigrid, the reaction a collider
            // holds each particle touching it with (graspers as below).
            let t = std::time::Instant::now();
            let reactions = self.lattice_reactions(model, state, control);
            for (k, f) in reactions.iter().enumerate() {
                stats.collider_forces[k] += *f / s.substeps as f32;
            }
            for i in 0..n {
                let (dp, id) = self.col[i];
                self.touched[i] = id;
                let reacted = !reactions.is_empty()
                    && !model.elements_of(i).is_empty()
                    && control
                        .colliders
                        .get(id as usize)
                        .is_some_and(|c| !matches!(c.shape, ColliderShape::Grasper { .. }));
                if id != u32::MAX && !reacted {
                    let f = -dp * model.mass[i] / (h * h);
                    stats.collider_forces[id as usize] += f / s.substeps as f32;
                }
                // Newton–multigrid's colliders push through penalties and its graspers
                // hold without corrections: their forces of the substep's last iteration.
                if let Some(&(f, id)) = self.newton_force.get(i)
                    && id != u32::MAX
                    && let Some(c) = stats.collider_forces.get_mut(id as usize)
                {
                    *c += f / s.substeps as f32;
                }
            }
            // 3. velocity update and damping
            let keep = (1.0 - s.damping * h).max(0.0);
            for i in 0..n {
                state.v[i] = (self.p[i] - state.x[i]) / h * keep;
                state.x[i] = self.p[i];
            }
            if descent {
                for i in 0..n {
                    self.accel[i] = (state.v[i] - self.p2[i]) / h;
                }
            }
            self.timings.finish += ms(t);
        }
        let t = std::time::Instant::now();
        // 4. divergence check: the fastest particle over the speed limit, else the first
        // non-finite one, reported with its body, region, likely cause and remedy.
        if let Some(worst) = super::diagnose::worst_particle(&state.x, &state.v, s.max_speed) {
            state.x.clone_from(&self.backup_x);
            state.v.clone_from(&self.backup_v);
            let body = model.particle_body[worst.0] as usize;
            let before = model.bodies.get(body).map_or(0.0, |b| {
                state.v[b.range()]
                    .iter()
                    .map(|v| v.length())
                    .fold(0.0f32, f32::max)
            });
            return Err(super::diagnose::diverged(
                model, &s, state.step, worst, before,
            ));
        }
        stats.active_contacts = self.count_active_contacts(model, &state.x);
        self.timings.finish += ms(t);
        stats.timings = self.timings;
        state.step += 1;
        Ok(stats)
    }

    /// One iteration of the configured method over every cluster of `model`.
    fn iterate(
        &mut self,
        model: &Model,
        state: &mut State,
        control: &Control,
        consts: &[BodyConst],
    ) {
        match self.settings.method {
            Method::GaussSeidel => self.iterate_gs(model, state, control, consts),
            Method::Jacobi => self.iterate_jacobi(model, state, control, consts),
        }
    }

    /// The coarse levels of hierarchical PBD for one substep (Müller 2008 §4): from the
    /// coarsest level down, gather the level's particles from `self.p`, run
    /// `coarse_iterations` of its constraints, write them back, and move the finer
    /// level's other particles by their parents' total displacement since the pass
    /// began, `Δx_i = Σ_j w_ij Δx_j` (prolongation). Pinned particles stay at their targets.
    fn solve_levels(&mut self, model: &Model, state: &State, control: &Control) {
        self.snap.clone_from(&self.p);
        for ls in self.levels.iter_mut() {
            ls.solver
                .work
                .iter_mut()
                .for_each(|w| w.1 = Multipliers::ZERO);
        }
        let h = self.h;
        let (iters, kind) = (
            self.settings.coarse_iterations,
            self.settings.coarse_constraint,
        );
        for li in (0..model.levels.len()).rev() {
            let lv = &model.levels[li];
            let ls = &mut self.levels[li];
            let sv = &mut ls.solver;
            for (i, &src) in lv.source.iter().enumerate() {
                sv.p[i] = self.p[src as usize];
                ls.state.x[i] = state.x[src as usize];
            }
            for (slot, &main) in ls.pin_map.iter().enumerate() {
                if main != u32::MAX {
                    ls.state.pin_targets[slot] = state.pin_targets[main as usize];
                }
            }
            for &i in &lv.model.pinned {
                sv.p[i as usize] = ls.state.pin_targets[sv.pin_slot[i as usize] as usize];
            }
            sv.h = h;
            let consts = sv.body_consts(&lv.model);
            for _ in 0..iters {
                match kind {
                    CoarseConstraint::Clusters => {
                        sv.iterate(&lv.model, &mut ls.state, control, &consts)
                    }
                    CoarseConstraint::Distance => {
                        sv.iterate_distance(&lv.model, &ls.state, control)
                    }
                }
            }
            for (i, &src) in lv.source.iter().enumerate() {
                self.p[src as usize] = sv.p[i];
            }
            for (f, &i) in lv.fine.iter().enumerate() {
                let i = i as usize;
                if self.pin_slot[i] != u32::MAX {
                    continue;
                }
                let mut d = Vec3::ZERO;
                for s in lv.parent_start[f] as usize..lv.parent_start[f + 1] as usize {
                    let j = lv.source[lv.parents[s] as usize] as usize;
                    d += lv.weights[s] * (self.p[j] - self.snap[j]);
                }
                self.p[i] = self.snap[i] + d;
            }
            self.transfer_multipliers(lv, li);
        }
    }

    /// Warm-starts the finer level's XPBD multipliers from level `li`'s (interpolated by
    /// the prolongation weights and scaled by the cluster volumes, as a multiplier is
    /// stress × volume × h²).
    fn transfer_multipliers(&mut self, lv: &Level, li: usize) {
        let (coarse, finer) = self.levels.split_at_mut(li);
        let ls = &finer[0];
        let dst: &mut [(ClusterCorrection, Multipliers)] = if li == 0 {
            &mut self.work
        } else {
            &mut coarse[li - 1].solver.work
        };
        for (t, &c) in lv.transfer_cluster.iter().enumerate() {
            let mut m = Multipliers::ZERO;
            for s in lv.transfer_start[t] as usize..lv.transfer_start[t + 1] as usize {
                let src = &ls.solver.work[lv.transfer_parents[s] as usize].1;
                let wt = lv.transfer_weights[s];
                m.h += wt * src.h;
                for k in 0..6 {
                    m.d[k] += wt * src.d[k];
                }
            }
            dst[c as usize].1 = m;
        }
    }

    /// One iteration of unilateral distance constraints (Müller 2008): for every cluster,
    /// between its centre `i` and each member `j`, `C = |p_i − p_j| − |X_i − X_j| ≤ 0`,
    /// projected with the inverse masses when violated; every particle moves by the mean
    /// of its corrections (Jacobi averaging), then pins and colliders.
    fn iterate_distance(&mut self, model: &Model, state: &State, control: &Control) {
        let n = model.particle_count();
        self.p2.clear();
        self.p2.resize(n, Vec3::ZERO);
        let mut count = std::mem::take(&mut self.counts);
        count.clear();
        count.resize(n, 0);
        for c in 0..n {
            let wi = inv_mass(model, &self.pin_slot, c);
            for &j in &model.members(c)[1..] {
                let j = j as usize;
                let wj = inv_mass(model, &self.pin_slot, j);
                let d = self.p[c] - self.p[j];
                let (len, rest) = (d.length(), (model.rest[c] - model.rest[j]).length());
                if len <= rest || wi + wj == 0.0 || len == 0.0 {
                    continue;
                }
                let g = d / len * ((len - rest) / (wi + wj));
                self.p2[c] -= wi * g;
                self.p2[j] += wj * g;
                count[c] += 1;
                count[j] += 1;
            }
        }
        let omega = self.settings.relaxation;
        for (i, &k) in count.iter().enumerate() {
            let mut q = self.p[i];
            if k > 0 {
                q += self.p2[i] * (omega / k as f32);
            }
            self.p[i] = self.boundary(model, state, control, i, q);
        }
        self.counts = count;
    }

    /// Recomputes the particle-contact candidates from positions `x` (KNN on the grid):
    /// pairs of particles of different bodies. (Self-contact inside a body is left to its
    /// elastic model: with Jacobi, same-body contacts fighting the cluster corrections
    /// were measured to blow up on impact.)
    pub fn refresh_contacts(&mut self, model: &Model, x: &[Vec3]) {
        self.refresh_contacts_among(model, x, &[]);
    }

    /// [`Solver::refresh_contacts`] among the bodies `active` marks (per body; missing
    /// entries count as active): the others get no candidates and are nobody's
    /// candidate, and their positions do not shape the search grid (a body parked far
    /// away costs nothing).
    pub fn refresh_contacts_among(&mut self, model: &Model, x: &[Vec3], active: &[bool]) {
        self.search_contacts(model, x, active, 0.0);
    }

    /// How far a particle may move in the next `steps` steps relative to the others'
    /// common motion, m: the largest deviation of a particle's velocity from the middle
    /// of all velocities (the centre of their bounding box) over that time, plus twice
    /// gravity's fall from rest in it, `|v − v_mid|max T + |g| T²` (`T` = `steps` ×
    /// `dt`). Two particles approach each other by at most twice that. Zero where a speed
    /// is not finite (a diverged state, which the step reports).
    pub fn contact_travel(&self, v: &[Vec3], steps: u32) -> f32 {
        let (speed, fall) = self.motion(v, steps);
        speed + fall
    }

    /// The two parts of [`Solver::contact_travel`], m: the largest deviation from the
    /// middle velocity over the steps' time, and twice gravity's fall from rest in it
    /// (both zero where a speed is not finite).
    fn motion(&self, v: &[Vec3], steps: u32) -> (f32, f32) {
        let t = self.settings.dt * steps as f32;
        let speed = spread(v.iter().copied()) * t;
        let fall = self.settings.gravity.length() * t * t;
        if (speed + fall).is_finite() {
            (speed, fall)
        } else {
            (0.0, 0.0)
        }
    }

    /// Whether the particle-contact candidates must be searched again before particles
    /// move up to `travel` (m, relative to their common motion, as
    /// [`Solver::contact_travel`]) more: no search yet (or for another particle count),
    /// or a particle's displacement since that search may end farther than half the
    /// search's slack from the middle of all displacements, so that two particles left
    /// out of each other's lists could meet. (Moving together, as a pile falling or
    /// carried as one, changes no distance between particles: it never makes the lists
    /// stale.)
    pub fn contacts_stale(&self, x: &[Vec3], travel: f32) -> bool {
        match self.contact_motion(x) {
            Some(moved) => !moved.is_finite() || moved + travel > 0.5 * self.contact_skin,
            None => true,
        }
    }

    /// Whether the particles moved relative to one another since the last
    /// particle-contact search by more than a tenth of its slack (or there was none), so
    /// that a search on the [`SolverSettings::knn_every`] schedule could find other
    /// nearest candidates. Bodies lying still, or moving together, keep their lists:
    /// [`Solver::step`] searches on the schedule only when this holds.
    pub fn contacts_moved(&self, x: &[Vec3]) -> bool {
        match self.contact_motion(x) {
            Some(moved) => moved.is_nan() || moved > SCHEDULED_SEARCH_MOTION * self.contact_skin,
            None => true,
        }
    }

    /// How far the particles moved relative to their common motion since the last
    /// particle-contact search, m ([`spread`] of the displacements: infinite where a
    /// position is not finite), or `None` before a search (or for another particle
    /// count).
    fn contact_motion(&self, x: &[Vec3]) -> Option<f32> {
        if self.contact_ref.len() != x.len() {
            return None;
        }
        Some(spread(
            x.iter().zip(&self.contact_ref).map(|(a, b)| *a - *b),
        ))
    }

    /// Searches the particle-contact candidates among the bodies `active` marks (as
    /// [`Solver::refresh_contacts_among`]) when `periodic` (the caller's schedule,
    /// [`SolverSettings::knn_every`]) or when the lists are stale for the next `steps`
    /// steps ([`Solver::contacts_stale`] with [`Solver::contact_travel`] of velocities
    /// `v`, m/s). The search then reaches beyond contact by at least twice that travel
    /// plus 2.5 times the speed's part of it (`4.5 |v − v_mid| T + 2 |g| T²`), so that
    /// bodies approaching fast find each other before they meet however far they move
    /// between searches (searched again every other step while they approach steadily),
    /// and bodies at rest, or moving together, are searched within the usual reach.
    /// Returns whether it searched.
    pub fn refresh_contacts_if_due(
        &mut self,
        model: &Model,
        x: &[Vec3],
        v: &[Vec3],
        active: &[bool],
        steps: u32,
        periodic: bool,
    ) -> bool {
        let (speed, fall) = self.motion(v, steps);
        if !periodic && !self.contacts_stale(x, speed + fall) {
            return false;
        }
        self.search_contacts(model, x, active, 4.5 * speed + 2.0 * fall);
        true
    }

    /// The particle-contact search: each particle's K nearest particles of other bodies
    /// within its contact distance to the largest radius plus a slack, the larger of
    /// that distance and `skin_travel` (m).
    fn search_contacts(&mut self, model: &Model, x: &[Vec3], active: &[bool], skin_travel: f32) {
        let n = x.len();
        let min_r = model
            .bodies
            .iter()
            .map(|b| b.radius)
            .fold(f32::MAX, f32::min);
        let max_r = model.bodies.iter().map(|b| b.radius).fold(0.0f32, f32::max);
        self.contact_ref.clear();
        self.contact_ref.extend_from_slice(x);
        self.contact_skin = (min_r + max_r).max(skin_travel);
        let k = (self.settings.contact_neighbours as usize).min(n.saturating_sub(1));
        // The last search's lists bound this one's (see below).
        let old_start = std::mem::take(&mut self.contact_start);
        let old_list = std::mem::take(&mut self.contact_list);
        let warm = old_start.len() == n + 1;
        self.contact_start.push(0);
        if k == 0 {
            self.contact_start.resize(n + 1, 0);
            return;
        }
        let is_active = |b: u32| active.get(b as usize).copied().unwrap_or(true);
        // The searched particles (all, or those of active bodies) and their positions.
        let subset: Option<Vec<u32>> = (!active.iter().all(|&a| a)).then(|| {
            (0..n as u32)
                .filter(|&i| is_active(model.particle_body[i as usize]))
                .collect()
        });
        let points: Vec<Vec3> = match &subset {
            Some(ids) => ids.iter().map(|&i| x[i as usize]).collect(),
            None => Vec::new(),
        };
        let index = |j: u32| subset.as_ref().map_or(j, |ids| ids[j as usize]);
        // Per particle: the k nearest particles of other bodies within its reach (the
        // candidates until the next search).
        let mut grid = super::knn::Grid::build(if subset.is_some() { &points } else { x }, 2.0);
        // Cells holding one body's particles only are not visited for that body's own.
        grid.tag_cells(|j| model.particle_body[index(j) as usize]);
        // Broad phase: a body near no other searches nothing (its lists stay empty).
        let boxes = super::knn::body_boxes(x, model.bodies.iter().map(|b| (b.first, b.count)));
        // (The farthest reach below, with the same margin for rounding.)
        let bound = super::knn::contact_reach_bound(max_r)
            .max((2.0 * max_r + skin_travel) * 1.001 + 1.0e-6);
        let mut near = super::knn::near_bodies(&boxes, bound);
        for (b, nb) in near.iter_mut().enumerate() {
            *nb &= is_active(b as u32);
        }
        let mut lists = vec![u32::MAX; n * k];
        par::for_chunks_mut(&mut lists, k, self.settings.threads, |start, chunk| {
            let mut buf = Vec::with_capacity(k + 1);
            for (r, row) in chunk.chunks_exact_mut(k).enumerate() {
                let i = start + r;
                let bi = model.particle_body[i];
                if !near[bi as usize] {
                    continue;
                }
                let touch = model.bodies[bi as usize].radius + max_r;
                let reach = touch + touch.max(skin_travel);
                // A full row of the last search (k particles of other active bodies,
                // distinct) bounds the k-th nearest now by the farthest of them.
                let mut known = f32::INFINITY;
                if warm {
                    let row = &old_list[old_start[i] as usize..old_start[i + 1] as usize];
                    let other = |&j: &u32| {
                        let bj = model.particle_body[j as usize];
                        bj != bi && is_active(bj)
                    };
                    if row.len() == k && row.iter().all(other) {
                        let far = row
                            .iter()
                            .map(|&j| super::knn::dist2(x[i], x[j as usize]))
                            .fold(0.0f32, |a, d| {
                                if a.is_nan() || d.is_nan() {
                                    f32::NAN
                                } else {
                                    a.max(d)
                                }
                            });
                        if far.is_finite() {
                            known = far;
                        }
                    }
                }
                grid.knn_bounded_skipping(
                    x[i],
                    k,
                    reach,
                    known,
                    bi,
                    |j| model.particle_body[index(j) as usize] != bi,
                    &mut buf,
                );
                for (o, &(_, j)) in row.iter_mut().zip(&buf) {
                    *o = index(j);
                }
            }
        });
        for row in lists.chunks_exact(k) {
            self.contact_list
                .extend(row.iter().copied().filter(|&j| j != u32::MAX));
            self.contact_start.push(self.contact_list.len() as u32);
        }
    }

    /// The particle-contact candidates of the last refresh, as CSR: candidates of
    /// particle `i` are `list[start[i]..start[i + 1]]` (nearest first).
    pub fn contact_lists(&self) -> (&[u32], &[u32]) {
        (&self.contact_start, &self.contact_list)
    }

    fn count_active_contacts(&self, model: &Model, x: &[Vec3]) -> usize {
        let mut active = 0;
        for i in 0..x.len() {
            let bi = model.particle_body[i] as usize;
            for &j in &self.contact_list
                [self.contact_start[i] as usize..self.contact_start[i + 1] as usize]
            {
                let bj = model.particle_body[j as usize] as usize;
                let d = model.bodies[bi].radius + model.bodies[bj].radius;
                if x[i].distance_squared(x[j as usize]) < d * d {
                    active += 1;
                }
            }
        }
        active
    }

    /// Solves one cluster from positions `p`. Gauss–Seidel: `jacobi = None`. Jacobi:
    /// `Some(ω)`; shape matching is then averaged with the cluster weight `ω/s_c`, and the
    /// hyperelastic solve uses split masses ([`ClusterRest::metric_split`]) relaxed by ω.
    #[allow(clippy::too_many_arguments)]
    fn solve_cluster(
        model: &Model,
        c: usize,
        p: &[Vec3],
        consts: &[BodyConst],
        jacobi: Option<f32>,
        h2: f32,
        rot: &mut Quat,
        lambda: &mut Multipliers,
        rot_iters: u32,
    ) -> ClusterCorrection {
        if model.cluster_start[c] == model.cluster_start[c + 1] {
            return ClusterCorrection::ZERO; // a lattice body's particle: no cluster
        }
        let r = &model.cluster_rest[c];
        let (com, apq, rest_com) =
            cluster_moments(model.members(c), p, &model.rest, &model.mass, r);
        let rest_c = &ClusterRest {
            com: rest_com,
            ..*r
        };
        match consts[model.particle_body[c] as usize] {
            BodyConst::Sm { k_iter } => {
                let w = jacobi.map_or(1.0, |omega| omega * model.cluster_weight[c]);
                solve_shape_matching(com, &apq, rest_c, rot, k_iter * w, rot_iters)
            }
            BodyConst::He { mat } => {
                let f = apq * rest_c.aqq_inv;
                let v = model.cluster_volume[c];
                let spacing = model.bodies[model.particle_body[c] as usize].spacing;
                let band = strain_dead_band(com.abs().max_element(), spacing);
                let (metric, scale) = match jacobi {
                    None => (&r.metric, 1.0),
                    Some(omega) => (&r.metric_split, omega),
                };
                solve_hyperelastic(
                    &f, rest_c, metric, rot, rot_iters, v, &mat, h2, scale, lambda, band,
                )
            }
        }
    }

    /// Keeps each particle's velocity at the start of the substep (in `p2`, free until
    /// the iterations) for the acceleration of the substep.
    fn backup_substep_velocity(&mut self, state: &State) {
        self.p2.clear();
        self.p2.extend_from_slice(&state.v);
    }

    /// Vertex block descent's start: the inertial targets `x̃ = p` and, for the particles
    /// of lattice bodies, the initial guess `x + h v₀ + h² ã` with `ã` the last
    /// substep's acceleration along gravity, clamped to [0, |g|] (Chen et al. 2024,
    /// adaptive initialisation).
    fn descent_initial_guess(&mut self, model: &Model, state: &State, h: f32) {
        self.target.clone_from(&self.p);
        self.mg_fresh = true;
        let g = self.settings.gravity;
        let g_len = g.length();
        let g_dir = if g_len > 0.0 { g / g_len } else { Vec3::ZERO };
        for i in 0..model.particle_count() {
            if model.elements_of(i).is_empty() || self.pin_slot[i] != u32::MAX {
                continue;
            }
            let a = if self.settings.descent_adaptive_init
                && self.settings.element_solver == ElementSolver::VertexDescent
            {
                self.accel[i].dot(g_dir).clamp(0.0, g_len)
            } else {
                0.0
            };
            self.p[i] = state.x[i] + self.p2[i] * h + g_dir * (a * h * h);
        }
    }

    /// One Gauss–Seidel sweep of vertex block descent over the particles of lattice
    /// bodies: each free particle takes the Newton step of its local implicit-Euler
    /// energy, `(m/h² I + Σ_e H_e) Δx = m/h² (x̃ − x) + Σ_e f_e`
    /// ([`super::element::corner_force`]).
    fn descent_sweep(&mut self, model: &Model, state: &mut State) {
        let h2 = self.h * self.h;
        let ri = self.settings.rotation_iterations;
        for j in 0..model.particle_count() {
            let elements = model.elements_of(j);
            if elements.is_empty() || self.pin_slot[j] != u32::MAX {
                continue;
            }
            let mh = model.mass[j] / h2;
            let mut f = (self.target[j] - self.p[j]) * mh;
            let mut hess = Mat3::from_diagonal(Vec3::splat(mh));
            for &ec in elements {
                let (e, corner) = ((ec >> 3) as usize, (ec & 7) as usize);
                let b = model.element_body[e] as usize;
                let Some(m) = self.modes.get(b).and_then(|m| m.as_ref()) else {
                    continue;
                };
                let x = model.elements[e].map(|k| self.p[k as usize]);
                let (fe, he) = super::element::corner_force(
                    &x,
                    corner,
                    &model.element_rest[e],
                    &m.mat,
                    &m.modes,
                    &mut state.element_rot[e],
                    ri,
                );
                f += fe;
                hess += he;
            }
            if hess.determinant().abs() > f32::MIN_POSITIVE {
                let d = hess.inverse() * f;
                if d.is_finite() {
                    self.p[j] += d;
                }
            }
        }
    }

    /// One Newton iteration of the lattice bodies' substep, its linear solve one
    /// multigrid V-cycle ([`ElementSolver::Multigrid`]).
    fn newton_multigrid(&mut self, model: &Model, state: &mut State, control: &Control) {
        use super::multigrid::{LatticeMultigrid, element_forces};
        if model.elements.is_empty() || self.target.len() != model.particle_count() {
            return; // no lattice body
        }
        let stale = self.mg.as_ref().is_none_or(|mg| {
            mg.levels[0].nodes != model.particle_count()
                || mg.levels[0].elements.len() != model.elements.len()
        });
        if stale {
            self.mg = Some(Box::new(LatticeMultigrid::new(
                model,
                self.settings.sweeps.min_nodes(),
                super::multigrid::MAX_LEVELS,
            )));
        }
        if let Some(mg) = self.mg.as_mut() {
            mg.smoother = self.settings.smoother;
        }
        let Some(mg) = self.mg.take() else {
            return;
        };
        let n = model.particle_count();
        let h2 = self.h * self.h;
        let ri = self.settings.rotation_iterations;
        // Held nodes (pins, grasped particles, nodes outside the lattice) keep their
        // positions: zero correction.
        let fixed = &mg.levels[0].fixed;
        let held: Vec<bool> = (0..n)
            .map(|j| fixed[j] || self.pin_slot[j] != u32::MAX || state.grab[j].collider != u32::MAX)
            .collect();
        let bodies = model.bodies.len();
        if std::mem::take(&mut self.mg_fresh) {
            // The substep's first iterate: the previous positions moved by the velocity,
            // `x + s h v`, at the lowest energy of s = 1, ½, ¼, 0, each body its own. A
            // smooth motion keeps s = 1 (momentum carried exactly); a violent one (a body
            // flying apart or through itself within the step) starts from a shape the
            // linearisation can work from.
            let x = &state.x;
            let step: Vec<Vec3> = (0..n).map(|j| self.p[j] - x[j]).collect();
            let start = |j: usize| if held[j] { self.p[j] } else { x[j] };
            // Each body's energy at s, and its inertia and elasticity alone (the
            // energy's scale).
            let at_s = |s: f32| {
                let at = |j: usize| {
                    if held[j] {
                        self.p[j]
                    } else {
                        x[j] + step[j] * s
                    }
                };
                let mut g = substep_energy(
                    model,
                    &mg,
                    (&held, &self.target),
                    h2,
                    (ri, &state.element_rot),
                    (&[], control),
                    &at,
                );
                let scale = g.clone();
                self.pair_overlap_energy(model, &held, h2, &start, &at, &mut g);
                (g, scale)
            };
            // Another s is taken only where it lowers the body's energy by more than
            // FIRST_ITERATE_TIE of its scale: closer, the energies tie to rounding (a body
            // at rest) and s = 1 stays, whatever the rounding of the sums.
            let (ones, scale) = at_s(1.0);
            let mut best: Vec<(f64, f32)> = ones.into_iter().map(|g| (g, 1.0)).collect();
            for s in [0.5f32, 0.25, 0.0] {
                for (b, g) in at_s(s).0.into_iter().enumerate() {
                    if g < best[b].0 - FIRST_ITERATE_TIE * scale[b].abs() {
                        best[b] = (g, s);
                    }
                }
            }
            for j in 0..n {
                let s = best[model.particle_body[j] as usize].1;
                if !held[j] && s < 1.0 {
                    self.p[j] = x[j] + step[j] * s;
                }
            }
        }
        let mut force = vec![Vec3::ZERO; n];
        for (e, nodes) in model.elements.iter().enumerate() {
            let b = model.element_body[e] as usize;
            let (Some(mat), Some(op)) = (&mg.material[b], &mg.unit_operator[b]) else {
                continue;
            };
            let r = &model.element_rest[e];
            let x = nodes.map(|j| self.p[j as usize]);
            let f = element_forces(&x, r.size, r.volume, mat, op, &mut state.element_rot[e], ri);
            for (k, &j) in nodes.iter().enumerate() {
                force[j as usize] += f[k];
            }
        }
        // The residual force without the colliders: inertia and elasticity. On a grasped
        // particle it is what the grasper holds against: the tissue's pull on it.
        self.newton_force.clear();
        self.newton_force.resize(n, (Vec3::ZERO, u32::MAX));
        for j in 0..n {
            let r = (self.target[j] - self.p[j]) * (model.mass[j] / h2) + force[j];
            let grasper = state.grab[j].collider;
            if grasper != u32::MAX && self.pin_slot[j] == u32::MAX && !fixed[j] {
                self.newton_force[j] = (r, grasper);
            }
            force[j] = if held[j] { Vec3::ZERO } else { r };
        }
        // Colliders as penalties inside the solve (frictionless; the boundary projection
        // after it removes what penetration is left and applies friction). Active: any
        // penetration now, and the contacts the projection made in the last substep (so a
        // squeezed body is held where the plates are).
        let contacts = self.newton_contacts(model, control, &held, h2);
        let extra = &mut self.mg_work.extra;
        extra.resize(1, Vec::new());
        extra[0].clear();
        if !contacts.is_empty() {
            extra[0].resize(n, Mat3::ZERO);
        }
        for c in &contacts {
            let p = &self.p;
            let depth = c.depth(model, control, &|j| p[j]);
            let nn = outer(c.normal, c.normal) * c.stiffness;
            force[c.node] += c.normal * (c.stiffness * depth);
            match c.other {
                // Both particles move: each takes half (its block counts the pair twice,
                // the coupling the V-cycle does not see), the energy stays the pair's.
                ContactWith::Particle(j) if !held[j] => {
                    force[j] -= c.normal * (c.stiffness * depth);
                    extra[0][c.node] += nn * 2.0;
                    extra[0][j] += nn * 2.0;
                }
                _ => extra[0][c.node] += nn,
            }
        }
        mg.prepare(&state.element_rot, h2, &mut self.mg_work);
        self.mg_work.rhs[0].copy_from_slice(&force);
        self.mg_work.delta[0]
            .iter_mut()
            .for_each(|d| *d = Vec3::ZERO);
        if self.settings.newton_cycles == 1 {
            mg.two_direction(h2, self.settings.sweeps, &held, &mut self.mg_work);
        } else {
            mg.krylov(
                h2,
                self.settings.newton_cycles,
                self.settings.sweeps,
                &held,
                &mut self.mg_work,
            );
        }
        // Backtracking line search on the substep's energy
        // `Σ m/(2h²) |y − x̃|² + Σ_e E_e(y) + Σ_c k/2 depth_c(y)²` (active contacts and
        // the elements' rotations held, so that the forces above are its gradient), each
        // body on its own energy: the V-cycle's step, cut to the trust region below, is
        // taken when it lowers the energy, else halved until it does (Nocedal & Wright,
        // "Numerical Optimization", §3.1), so that a step far from the solution (an
        // impact, a squashed or inverted body, a long step) cannot raise it.
        let rots = &state.element_rot;
        let energy = |alpha: f32, p: &[Vec3], d: &[Vec3]| -> Vec<f64> {
            let at = |j: usize| if held[j] { p[j] } else { p[j] + d[j] * alpha };
            substep_energy(
                model,
                &mg,
                (&held, &self.target),
                h2,
                (0, rots),
                (&contacts, control),
                &at,
            )
        };
        // A trust region, body by body: no particle moves more than half its lattice
        // spacing in one iteration (the linearisation about a badly deformed shape can
        // ask for metres; bodies meeting are held back), plus the step `|v| h` of the
        // fastest collider the body touches (a tool pressing in moves the tissue it
        // touches that far), plus gravity's step from rest `|g| h²` where the particle
        // touches nothing (so that a finely sampled body falls at gravity's rate in one
        // iteration). Each body's step is scaled down to its own bound (so that a body
        // settling into a collider does not hold back another falling freely; a body
        // with a step that is not finite does not move); then halved until the energy
        // falls.
        let mut bound = vec![1.0f32; bodies];
        let fall = self.settings.gravity.length() * h2;
        // Each body's fastest touching collider's step; particles near something (a
        // collider contact, or another body's particle in their contact list) keep to
        // half a spacing (and that step).
        let mut tool = vec![0.0f32; bodies];
        let mut near = vec![false; n];
        for c in &contacts {
            if let ContactWith::Collider(k) = c.other {
                let b = model.particle_body[c.node] as usize;
                tool[b] = tool[b].max(control.colliders[k].velocity.length() * self.h);
                near[c.node] = true;
            }
        }
        if self.settings.particle_contacts && self.contact_start.len() == n + 1 {
            for (j, nj) in near.iter_mut().enumerate() {
                *nj |= self.contact_start[j] < self.contact_start[j + 1];
            }
        }
        for (j, dj) in self.mg_work.delta[0].iter().enumerate() {
            if held[j] {
                continue;
            }
            let b = model.particle_body[j] as usize;
            if !dj.is_finite() {
                bound[b] = 0.0;
                continue;
            }
            let reach = 0.5 * model.bodies[b].spacing + tool[b] + if near[j] { 0.0 } else { fall };
            let len = dj.length();
            if len * bound[b] > reach {
                bound[b] = reach / len;
            }
        }
        for (j, dj) in self.mg_work.delta[0].iter_mut().enumerate() {
            let t = bound[model.particle_body[j] as usize];
            if held[j] || t == 0.0 {
                *dj = Vec3::ZERO;
            } else {
                *dj *= t;
            }
        }
        let d = &self.mg_work.delta[0];
        let g0 = energy(0.0, &self.p, d);
        // Each body's step: the first of 1, ½, ¼, … (13 in all) that does not raise its
        // energy, else 0.
        let mut alpha: Vec<Option<f32>> = vec![None; bodies];
        let mut a = 1.0f32;
        for _ in 0..LINE_SEARCH_STEPS {
            if alpha.iter().all(Option::is_some) {
                break;
            }
            for (b, g) in energy(a, &self.p, d).into_iter().enumerate() {
                if alpha[b].is_none() && g <= g0[b] {
                    alpha[b] = Some(a);
                }
            }
            a *= 0.5;
        }
        for (j, dj) in d.iter().enumerate() {
            let a = alpha[model.particle_body[j] as usize].unwrap_or(0.0);
            if !held[j] && a > 0.0 {
                self.p[j] += *dj * a;
            }
        }
        self.mg = Some(mg);
    }

    /// The contacts of one Newton iteration of the lattice bodies: every free particle
    /// inside a collider now; every free particle the boundary projection moved out of a
    /// collider in the last substep that is still within a radius of it (bilateral at
    /// the collider's surface for this iteration); with particle contacts on, every pair
    /// of the contact lists (another body's particle) closer than their radii, or, where
    /// the last projection found the particle pressed into one of them, no more than
    /// [`PAIR_HOLD`] of that farther (then held at it for this iteration). The
    /// penalty stiffness is `PENALTY` times the particle's own stiffness scale,
    /// `m/h² + (λ + 2μ) s` (inertia plus the P-wave modulus times the lattice spacing
    /// `s`: what its elements hold it with), so that it dominates soft and stiff bodies
    /// alike.
    fn newton_contacts(
        &self,
        model: &Model,
        control: &Control,
        held: &[bool],
        h2: f32,
    ) -> Vec<NewtonContact> {
        let mut out = Vec::new();
        let pairs = self.settings.particle_contacts && !self.contact_list.is_empty();
        if control.colliders.is_empty() && !pairs {
            return out;
        }
        for (j, &held_j) in held.iter().enumerate() {
            if held_j || model.elements_of(j).is_empty() {
                continue;
            }
            let r = model.bodies[model.particle_body[j] as usize].radius;
            let stiffness = contact_stiffness(model, j, h2);
            for (k, col) in control.colliders.iter().enumerate() {
                if matches!(col.shape, ColliderShape::Grasper { .. }) {
                    continue;
                }
                let (d, normal) = col.distance(self.p[j]);
                // A contact of the last substep stays active while the particle is
                // within one radius of touching. (It lets go by itself: a particle the
                // solve leaves outside the collider is not projected, so not touched.)
                let active = d < r || (self.touched[j] == k as u32 && d < 2.0 * r);
                if !active || !d.is_finite() {
                    continue;
                }
                out.push(NewtonContact {
                    node: j,
                    other: ContactWith::Collider(k),
                    normal,
                    stiffness,
                });
            }
            if !pairs {
                continue;
            }
            for s in self.contact_start[j]..self.contact_start[j + 1] {
                let i = self.contact_list[s as usize] as usize;
                let reach = r + model.bodies[model.particle_body[i] as usize].radius;
                let d = self.p[j] - self.p[i];
                let len = d.length();
                let hold = if self.pressed[j] {
                    1.0 + PAIR_HOLD
                } else {
                    1.0
                };
                if len >= reach * hold || len <= 1e-12 {
                    continue;
                }
                out.push(NewtonContact {
                    node: j,
                    other: ContactWith::Particle(i),
                    normal: d / len,
                    stiffness,
                });
            }
        }
        out
    }

    /// Adds to `g` (J, by body) the particle contacts' penalty energy of moving from
    /// positions `from` to `at` in a straight line: `½ k (r_i + r_j − d)²` for every pair
    /// of the contact lists whose closest distance `d` along the way comes within their
    /// radii, held by the free lattice particle whose list has it (as in the Newton
    /// iterations), and counted to that particle's body. What the
    /// substep's first iterate weighs, so that a body arriving at another faster than a
    /// particle radius a step starts from where it meets it rather than from inside it or
    /// past it.
    fn pair_overlap_energy(
        &self,
        model: &Model,
        held: &[bool],
        h2: f32,
        from: &dyn Fn(usize) -> Vec3,
        at: &dyn Fn(usize) -> Vec3,
        g: &mut [f64],
    ) {
        if !self.settings.particle_contacts || self.contact_list.is_empty() {
            return;
        }
        for (j, &held_j) in held.iter().enumerate() {
            if held_j || model.elements_of(j).is_empty() {
                continue;
            }
            let r = model.bodies[model.particle_body[j] as usize].radius;
            let k = contact_stiffness(model, j, h2);
            for s in self.contact_start[j]..self.contact_start[j + 1] {
                let i = self.contact_list[s as usize] as usize;
                let reach = r + model.bodies[model.particle_body[i] as usize].radius;
                let r0 = from(j) - from(i);
                let v = at(j) - at(i) - r0;
                let vv = v.length_squared();
                let t = if vv > 0.0 {
                    (-r0.dot(v) / vv).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                let depth = (reach - (r0 + v * t).length()).max(0.0);
                g[model.particle_body[j] as usize] += 0.5 * (k * depth * depth) as f64;
            }
        }
    }

    /// The lattice bodies' elements under a Newton-type element solver (vertex block
    /// descent's sweep, or a Newton–multigrid iteration where
    /// [`SolverSettings::newton_iterations`] allows one); nothing under XPBD, whose
    /// elements the iteration solves with the clusters.
    fn newton_type_elements(&mut self, model: &Model, state: &mut State, control: &Control) {
        match self.settings.element_solver {
            ElementSolver::VertexDescent => self.descent_sweep(model, state),
            ElementSolver::Multigrid if self.newton_now => {
                self.newton_multigrid(model, state, control)
            }
            ElementSolver::Multigrid | ElementSolver::Xpbd => {}
        }
    }

    /// The consistent warm start of the element multipliers: rescales them to substep
    /// `h` and moves every free particle by the displacement they exert
    /// ([`multiplier_displacement`]) from the predicted positions.
    fn warm_start_elements(&mut self, model: &Model, state: &State, h: f32) {
        let ratio = (h / self.element_h).powi(2);
        if ratio != 1.0 {
            for w in &mut self.element_work {
                w.lam.hyper.h *= ratio;
                w.lam.hyper.d.iter_mut().for_each(|d| *d *= ratio);
                w.lam.hourglass.iter_mut().for_each(|l| *l *= ratio);
            }
        }
        let mut delta = vec![Vec3::ZERO; model.particle_count()];
        for e in 0..model.elements.len() {
            let b = model.element_body[e] as usize;
            let Some(m) = self.modes.get(b).and_then(|m| m.as_ref()) else {
                continue;
            };
            let nodes = model.elements[e];
            let x = nodes.map(|j| self.p[j as usize]);
            let w = nodes.map(|j| inv_mass(model, &self.pin_slot, j as usize));
            let d = multiplier_displacement(
                &x,
                &w,
                &model.element_rest[e],
                &m.modes,
                &state.element_rot[e],
                &self.element_work[e].lam,
            );
            for (k, &j) in nodes.iter().enumerate() {
                delta[j as usize] += d[k];
            }
        }
        for (p, d) in self.p.iter_mut().zip(&delta) {
            *p += *d;
        }
    }

    /// Jacobi pass A for element `e`: solved from positions `p` with each corner's mass
    /// split among the elements that share it (`w_j → n_j w_j`), multiplier steps relaxed
    /// by `omega`; the corner corrections (in the true masses, `Δx / n_j`) go to `work`.
    fn jacobi_element(
        &self,
        model: &Model,
        e: usize,
        p: &[Vec3],
        omega: f32,
        work: &mut ElementWork,
        rot: &mut Quat,
    ) {
        let nodes = model.elements[e];
        let x0 = nodes.map(|j| p[j as usize]);
        let mut x = x0;
        let mult = nodes.map(|j| model.elements_of(j as usize).len().max(1) as f32);
        let w: [f32; CORNERS] =
            std::array::from_fn(|k| inv_mass(model, &self.pin_slot, nodes[k] as usize) * mult[k]);
        work.corr = [Vec3::ZERO; CORNERS];
        let Some(s) = element_solve(
            &self.modes,
            &self.settings,
            model,
            e,
            &x,
            self.h,
            omega,
            true,
        ) else {
            return;
        };
        solve_element(&mut x, &w, &model.element_rest[e], &s, rot, &mut work.lam);
        for k in 0..CORNERS {
            work.corr[k] = (x[k] - x0[k]) / mult[k];
        }
    }

    fn iterate_gs(
        &mut self,
        model: &Model,
        state: &mut State,
        control: &Control,
        consts: &[BodyConst],
    ) {
        let t = std::time::Instant::now();
        let h2 = self.h * self.h;
        let n = model.particle_count();
        let ri = self.settings.rotation_iterations;
        for c in 0..n {
            let corr = Self::solve_cluster(
                model,
                c,
                &self.p,
                consts,
                None,
                h2,
                &mut state.rot[c],
                &mut self.work[c].1,
                ri,
            );
            for &j in model.members(c) {
                let j = j as usize;
                if self.pin_slot[j] != u32::MAX {
                    continue; // pinned: infinite mass, held at its target
                }
                let pj = self.p[j];
                self.p[j] = pj + corr.apply(model.rest[j], pj);
            }
        }
        self.newton_type_elements(model, state, control);
        for e in 0..model.elements.len() {
            if self.settings.element_solver != ElementSolver::Xpbd {
                break;
            }
            let nodes = model.elements[e];
            let mut x = nodes.map(|j| self.p[j as usize]);
            let w = nodes.map(|j| inv_mass(model, &self.pin_slot, j as usize));
            let Some(s) = element_solve(
                &self.modes,
                &self.settings,
                model,
                e,
                &x,
                self.h,
                1.0,
                false,
            ) else {
                continue;
            };
            solve_element(
                &mut x,
                &w,
                &model.element_rest[e],
                &s,
                &mut state.element_rot[e],
                &mut self.element_work[e].lam,
            );
            for (k, &j) in nodes.iter().enumerate() {
                if w[k] != 0.0 {
                    self.p[j as usize] = x[k];
                }
            }
        }
        self.timings.clusters += ms(t);
        let t = std::time::Instant::now();
        let p = std::mem::take(&mut self.p);
        self.mark_pressed_pairs(model, &state.x, &p);
        self.p = p;
        for i in 0..n {
            if self.settled(model, i) {
                continue;
            }
            if self.contacts_of(model, i) {
                let bi = model.particle_body[i] as usize;
                for s in self.contact_start[i]..self.contact_start[i + 1] {
                    let j = self.contact_list[s as usize] as usize;
                    let bj = model.particle_body[j] as usize;
                    let d = model.bodies[bi].radius + model.bodies[bj].radius;
                    let (wi, wj) = (
                        inv_mass(model, &self.pin_slot, i),
                        self.projection_inv_mass(model, j),
                    );
                    let di = solve_contact(self.p[i], self.p[j], wi, wj, d);
                    let dj = solve_contact(self.p[j], self.p[i], wj, wi, d);
                    self.p[i] += di;
                    self.p[j] += dj;
                }
            }
            self.p[i] = self.boundary(model, state, control, i, self.p[i]);
        }
        self.timings.boundary += ms(t);
    }

    /// Whether particle `j` is a lattice node stepped by Newton–multigrid.
    fn newton_particle(&self, model: &Model, j: usize) -> bool {
        self.settings.element_solver == ElementSolver::Multigrid && !model.elements_of(j).is_empty()
    }

    /// Whether the projection passes of this iteration leave particle `j` where it is: a
    /// lattice node under Newton–multigrid in an iteration after the substep's Newton
    /// iterations. Its particle contacts, colliders and pins are projected after each
    /// Newton iteration, the GPU's way; the iterations after them are the clusters' (to
    /// which it is an immovable obstacle).
    fn settled(&self, model: &Model, j: usize) -> bool {
        !self.newton_now && self.newton_particle(model, j)
    }

    /// Records for each lattice particle stepped by Newton–multigrid whose particle
    /// contacts this iteration projects (and which is not pinned) whether one of its own
    /// candidates is pressed into it ([`pressed_pair`]) at `p`, the positions the
    /// projection starts from (`x`: the substep's start): the pairs the Newton iteration
    /// left pressed together, which the next holds a little past touching
    /// ([`PAIR_HOLD`]). The GPU's `pair_project` records the same.
    fn mark_pressed_pairs(&mut self, model: &Model, x: &[Vec3], p: &[Vec3]) {
        for j in 0..p.len() {
            if !self.newton_particle(model, j)
                || self.settled(model, j)
                || !self.contacts_of(model, j)
            {
                continue;
            }
            let rj = model.bodies[model.particle_body[j] as usize].radius;
            let free = inv_mass(model, &self.pin_slot, j) > 0.0;
            self.pressed[j] = free
                && self.contact_list
                    [self.contact_start[j] as usize..self.contact_start[j + 1] as usize]
                    .iter()
                    .any(|&i| {
                        let i = i as usize;
                        let dist = rj + model.bodies[model.particle_body[i] as usize].radius;
                        pressed_pair(x[j] - x[i], p[j] - p[i], dist)
                    });
        }
    }

    /// Whether this iteration projects particle `j`'s particle contacts.
    fn contacts_of(&self, model: &Model, j: usize) -> bool {
        self.settings.particle_contacts
            && if self.newton_particle(model, j) {
                self.lattice_contacts_now
            } else {
                self.contacts_now
            }
    }

    /// Particle `j`'s inverse mass as a partner in this iteration's contact projection,
    /// 1/kg: 0 where pinned or [`Solver::settled`].
    fn projection_inv_mass(&self, model: &Model, j: usize) -> f32 {
        if self.settled(model, j) {
            0.0
        } else {
            inv_mass(model, &self.pin_slot, j)
        }
    }

    /// Colliders and pins for particle `i` at position `p` (records collider corrections).
    #[inline]
    fn boundary(
        &mut self,
        model: &Model,
        state: &State,
        control: &Control,
        i: usize,
        p: Vec3,
    ) -> Vec3 {
        let (q, id, dp) = boundary_at(
            model,
            &self.pin_slot,
            &state.pin_targets,
            &state.x,
            &state.grab,
            control,
            self.h,
            i,
            p,
        );
        if id != u32::MAX {
            self.col[i].0 += dp;
            self.col[i].1 = id;
        }
        q
    }

    fn iterate_jacobi(
        &mut self,
        model: &Model,
        state: &mut State,
        control: &Control,
        consts: &[BodyConst],
    ) {
        let h2 = self.h * self.h;
        let h = self.h;
        let ri = self.settings.rotation_iterations;
        let threads = self.settings.threads;
        let omega = self.settings.relaxation;
        let contact_omega = self.settings.contact_relaxation;
        // Lattice particles under Newton–multigrid: never over-relaxed (see the field).
        let lattice_omega = if self.settings.element_solver == ElementSolver::Multigrid {
            contact_omega.min(1.0)
        } else {
            contact_omega
        };
        let t = std::time::Instant::now();
        // Lattice bodies under a Newton-type element solver: solved first, on their own
        // (their particles belong to no cluster; the passes below add nothing to them
        // but particle contacts, colliders and pins, and after the substep's Newton
        // iterations nothing at all: `Solver::settled`).
        self.newton_type_elements(model, state, control);
        // Pass A: every cluster from the same positions.
        {
            let p = &self.p;
            par::for_chunks_mut2(
                &mut self.work,
                &mut state.rot,
                threads,
                |start, work, rot| {
                    for (k, ((cr, lam), r)) in work.iter_mut().zip(rot.iter_mut()).enumerate() {
                        let c = start + k;
                        *cr = Self::solve_cluster(model, c, p, consts, Some(omega), h2, r, lam, ri);
                    }
                },
            );
        }
        if !model.elements.is_empty() && self.settings.element_solver == ElementSolver::Xpbd {
            let mut ework = std::mem::take(&mut self.element_work);
            {
                let me = &*self;
                let p = &self.p;
                par::for_chunks_mut2(
                    &mut ework,
                    &mut state.element_rot,
                    threads,
                    |start, work, rot| {
                        for (k, (wk, r)) in work.iter_mut().zip(rot.iter_mut()).enumerate() {
                            me.jacobi_element(model, start + k, p, omega, wk, r);
                        }
                    },
                );
            }
            self.element_work = ework;
        }
        self.timings.clusters += ms(t);
        // Pass B: every particle gathers its clusters' corrections.
        let t = std::time::Instant::now();
        let mut out = std::mem::take(&mut self.p2);
        {
            let p = &self.p;
            let work = &self.work;
            let ework = &self.element_work;
            par::for_chunks_mut(&mut out, 1, threads, |start, out| {
                for (k, o) in out.iter_mut().enumerate() {
                    let j = start + k;
                    let mut d = gather(model, work, j, p[j]);
                    for &ec in model.elements_of(j) {
                        d += ework[(ec >> 3) as usize].corr[(ec & 7) as usize];
                    }
                    *o = p[j] + d;
                }
            });
        }
        self.timings.gather += ms(t);
        // Pass C: particle contacts (from the positions pass B left, so the two do not
        // correct the same overlap twice), then colliders and pins.
        let t = std::time::Instant::now();
        self.mark_pressed_pairs(model, &state.x, &out);
        {
            let mut projected = std::mem::take(&mut self.p);
            let mut col = std::mem::take(&mut self.col);
            let me = &*self;
            let p = &out;
            let cs = &self.contact_start;
            let cl = &self.contact_list;
            let pin_slot = &self.pin_slot;
            let pin_targets = &state.pin_targets;
            let x = &state.x;
            let grab = &state.grab;
            par::for_chunks_mut2(&mut projected, &mut col, threads, |start, dst, col| {
                for (k, (o, cid)) in dst.iter_mut().zip(col.iter_mut()).enumerate() {
                    let j = start + k;
                    let pj = p[j];
                    let mut q = pj;
                    if me.settled(model, j) {
                        *o = q;
                        continue;
                    }
                    if me.contacts_of(model, j) {
                        let bj = model.particle_body[j] as usize;
                        let wj = inv_mass(model, pin_slot, j);
                        let mut sum = Vec3::ZERO;
                        let mut cnt = 0u32;
                        for s in cs[j]..cs[j + 1] {
                            let i = cl[s as usize] as usize;
                            let bi = model.particle_body[i] as usize;
                            let dist = model.bodies[bi].radius + model.bodies[bj].radius;
                            let wi = me.projection_inv_mass(model, i);
                            let dc = solve_contact(pj, p[i], wj, wi, dist);
                            if dc != Vec3::ZERO {
                                sum += dc;
                                cnt += 1;
                            }
                        }
                        if cnt > 0 {
                            let omega = if model.elements_of(j).is_empty() {
                                contact_omega
                            } else {
                                lattice_omega
                            };
                            q += sum / cnt as f32 * omega;
                        }
                    }
                    let (q, id, dp) =
                        boundary_at(model, pin_slot, pin_targets, x, grab, control, h, j, q);
                    if id != u32::MAX {
                        cid.0 += dp;
                        cid.1 = id;
                    }
                    *o = q;
                }
            });
            self.p = projected;
            self.col = col;
        }
        self.p2 = out;
        self.timings.boundary += ms(t);
    }

    /// Each particle's own cluster's deformation gradient `F = A_pq A_qq⁻¹` at positions `x`
    /// (what the skinning uses). A lattice body's particle gets the mean of its elements'
    /// centre gradients. Computed on all cores; the result does not depend on their number.
    pub fn deformation_gradients(model: &Model, x: &[Vec3]) -> Vec<Mat3> {
        // Light work per item: threads only for thousands of items each.
        let threads = |items| par::threads_for(items, 8192, 0);
        let mut element_f = vec![Mat3::IDENTITY; model.elements.len()];
        let t = threads(element_f.len());
        par::for_chunks_mut(&mut element_f, 1, t, |first, out| {
            for (k, f) in out.iter_mut().enumerate() {
                let e = first + k;
                if let Some(r) = model.element_rest.get(e) {
                    *f = element_gradient(&model.elements[e].map(|j| x[j as usize]), r.size);
                }
            }
        });
        let mut f = vec![Mat3::IDENTITY; model.particle_count()];
        let t = threads(f.len());
        par::for_chunks_mut(&mut f, 1, t, |first, out| {
            for (k, f) in out.iter_mut().enumerate() {
                let c = first + k;
                let elements = model.elements_of(c);
                if !elements.is_empty() {
                    let sum: Mat3 = elements
                        .iter()
                        .map(|&ec| element_f[(ec >> 3) as usize])
                        .sum();
                    *f = sum * (1.0 / elements.len() as f32);
                } else if model.cluster_start[c] != model.cluster_start[c + 1] {
                    let r = &model.cluster_rest[c];
                    let (_, apq, _) =
                        cluster_moments(model.members(c), x, &model.rest, &model.mass, r);
                    *f = apq * r.aqq_inv;
                }
            }
        });
        f
    }

    /// Constraint residual at positions `x`: the mass-weighted RMS of the correction each
    /// cluster would ask for on its own (Gauss–Seidel style, stiffness 1 for shape
    /// matching; the current multipliers and substep for XPBD), divided by the body
    /// size. Zero exactly when every cluster is satisfied.
    pub fn residual(&self, model: &Model, state: &State) -> f32 {
        self.residual_at(model, &state.x, &state.rot)
    }

    /// [`Solver::residual`] at positions `x` with warm-start rotations `rot`.
    fn residual_at(&self, model: &Model, x: &[Vec3], rot: &[Quat]) -> f32 {
        let lam: Vec<Multipliers> = self.work.iter().map(|w| w.1).collect();
        self.residual_with(model, x, rot, &lam)
    }

    /// [`Solver::residual`] of a state from elsewhere (the GPU world, say): positions `x`
    /// (m), each cluster's rotation warm start `rot` and XPBD multipliers `lam`, at this
    /// solver's substep length.
    pub fn residual_with(
        &self,
        model: &Model,
        x: &[Vec3],
        rot: &[Quat],
        lam: &[Multipliers],
    ) -> f32 {
        let h2 = if self.h > 0.0 {
            self.h * self.h
        } else {
            (self.settings.dt / self.settings.substeps as f32).powi(2)
        };
        let mut consts = self.body_consts(model);
        for c in consts.iter_mut() {
            if let BodyConst::Sm { k_iter } = c {
                *k_iter = 1.0;
            }
        }
        let mut sum = 0.0f64;
        let mut msum = 0.0f64;
        for c in 0..model.particle_count() {
            let mut rot = rot[c];
            let mut lam = lam[c];
            let corr = Self::solve_cluster(model, c, x, &consts, None, h2, &mut rot, &mut lam, 20);
            let size = model.bodies[model.particle_body[c] as usize].size as f64;
            for &j in model.members(c) {
                let j = j as usize;
                let d = corr.apply(model.rest[j], x[j]).as_dvec3() / size;
                sum += model.mass[j] as f64 * d.length_squared();
                msum += model.mass[j] as f64;
            }
        }
        let mut modes = self.modes.clone();
        if modes.len() != model.bodies.len() {
            let mut me = self.clone();
            me.refresh_modes(model);
            modes = me.modes;
        }
        for e in 0..model.elements.len() {
            let nodes = model.elements[e];
            let x0 = nodes.map(|j| x[j as usize]);
            let mut xe = x0;
            let w = nodes.map(|j| inv_mass(model, &self.pin_slot, j as usize));
            let h = h2.sqrt();
            let Some(s) = element_solve(&modes, &self.settings, model, e, &xe, h, 1.0, false)
            else {
                continue;
            };
            let mut lam = self
                .element_work
                .get(e)
                .map_or(ElementMultipliers::ZERO, |w| w.lam);
            let mut rot = Quat::IDENTITY;
            let solve = ElementSolve {
                rotation_iterations: 20,
                ..s
            };
            solve_element(
                &mut xe,
                &w,
                &model.element_rest[e],
                &solve,
                &mut rot,
                &mut lam,
            );
            let size = model.bodies[model.element_body[e] as usize].size as f64;
            for k in 0..CORNERS {
                let j = nodes[k] as usize;
                let d = (xe[k] - x0[k]).as_dvec3() / size;
                sum += model.mass[j] as f64 * d.length_squared() / 8.0;
                msum += model.mass[j] as f64 / 8.0;
            }
        }
        (sum / msum.max(f64::MIN_POSITIVE)).sqrt() as f32
    }
}

/// Sum of the corrections of all clusters containing particle `j` (at position `pj`):
/// `Σ_c (M_c X_j + t_c − a_c p_j)`, summed as `Σ_c (M_c X_j + t_c) − (Σ_c a_c) p_j`.
///
/// Each cluster's map is applied to `X_j` and the results summed (as the GPU's gather
/// does, which reads each map once per member; the same sum as applying the summed maps,
/// up to rounding).
#[inline]
fn gather(model: &Model, work: &[(ClusterCorrection, Multipliers)], j: usize, pj: Vec3) -> Vec3 {
    let xr = glam::Vec3A::from(model.rest[j]);
    let mut acc = glam::Vec4::ZERO;
    for &c in model.clusters_of(j) {
        acc += work[c as usize].0.goal_part(xr);
    }
    acc.truncate() - acc.w * pj
}

/// The solve settings of element `e` at corner positions `x` with substep `h` (s),
/// relaxation `scale` and split masses or not (None: its body has no hourglass modes,
/// i.e. is not a hyperelastic lattice body).
#[allow(clippy::too_many_arguments)]
fn element_solve<'a>(
    modes: &'a [Option<BodyModes>],
    settings: &SolverSettings,
    model: &Model,
    e: usize,
    x: &[Vec3; CORNERS],
    h: f32,
    scale: f32,
    split: bool,
) -> Option<ElementSolve<'a>> {
    let b = model.element_body[e] as usize;
    let m = modes.get(b)?.as_ref()?;
    let coordinate = x.iter().fold(0.0f32, |a, p| a.max(p.abs().max_element()));
    Some(ElementSolve {
        material: &m.mat,
        modes: &m.modes,
        h2: h * h,
        scale,
        rotation_iterations: settings.rotation_iterations,
        dead_band: strain_dead_band(coordinate, model.element_rest[e].size),
        split,
    })
}

/// Inverse mass of particle `i`, 1/kg; 0 for a pinned particle (infinite mass).
#[inline]
fn inv_mass(model: &Model, pin_slot: &[u32], i: usize) -> f32 {
    if pin_slot[i] != u32::MAX {
        0.0
    } else {
        1.0 / model.mass[i]
    }
}

/// Pin, grasper or collider projection of particle `i` at `p`; returns the new position,
/// the last collider touched (or `u32::MAX`) and that collider's correction. A particle a
/// grasper holds goes to its target and records the correction against the grasper (so
/// the grasper's force is the tissue's pull on it).
#[allow(clippy::too_many_arguments)]
#[inline]
fn boundary_at(
    model: &Model,
    pin_slot: &[u32],
    pin_targets: &[Vec3],
    x: &[Vec3],
    grab: &[Grab],
    control: &Control,
    h: f32,
    i: usize,
    mut p: Vec3,
) -> (Vec3, u32, Vec3) {
    if pin_slot[i] != u32::MAX {
        return (pin_targets[pin_slot[i] as usize], u32::MAX, Vec3::ZERO);
    }
    if let Some(t) = grab_target(&control.colliders, &grab[i]) {
        return (t, grab[i].collider, t - p);
    }
    let r = model.bodies[model.particle_body[i] as usize].radius;
    let mut id = u32::MAX;
    let mut total = Vec3::ZERO;
    for (k, col) in control.colliders.iter().enumerate() {
        let dp = project_collider(col, p, x[i], h, r);
        if dp != Vec3::ZERO {
            p += dp;
            total += dp;
            id = k as u32;
        }
    }
    (p, id, total)
}

/// One contact inside a Newton iteration of the lattice bodies, with a collider or
/// another body's particle: the penalty energy `k/2 depth²` (`depth` the overlap of
/// radii), linearised about the iterate along its normal (`k n nᵀ`).
#[derive(Debug, Clone, Copy)]
struct NewtonContact {
    node: usize,
    other: ContactWith,
    /// Outward normal (the collider's, or from the other particle to this one) at the
    /// start of the iteration.
    normal: Vec3,
    /// Penalty stiffness, N/m.
    stiffness: f32,
}

/// What a [`NewtonContact`] is with.
#[derive(Debug, Clone, Copy)]
enum ContactWith {
    /// A collider, by index.
    Collider(usize),
    /// Another body's particle, by index.
    Particle(usize),
}

impl NewtonContact {
    /// Penetration at positions `y` (m): the particle's radius less its distance to the
    /// collider, or the two particles' radii less their distance (negative when apart:
    /// the bilateral part of an active contact).
    fn depth(&self, model: &Model, control: &Control, y: &dyn Fn(usize) -> Vec3) -> f32 {
        let radius = |i: usize| model.bodies[model.particle_body[i] as usize].radius;
        match self.other {
            ContactWith::Collider(k) => {
                let (d, _) = control.colliders[k].distance(y(self.node));
                radius(self.node) - d
            }
            ContactWith::Particle(i) => {
                radius(self.node) + radius(i) - (y(self.node) - y(i)).length()
            }
        }
    }
}

/// How far beyond its radius (a fraction of it) a lattice particle still touches a
/// collider for the collider's force: the substep's projection leaves a pressed
/// particle at its radius, the Newton iterate a little either side of it.
const TOUCH_TOLERANCE: f32 = 0.05;

impl Solver {
    /// The force on each collider (N, by collider; empty where no lattice body stepped
    /// by Newton–multigrid): every free lattice particle touching a collider (within
    /// [`TOUCH_TOLERANCE`] of its radius; of several, the one it is deepest in; not a
    /// grasper) at the substep's end puts on it the reaction of
    /// [`reaction_on_collider`].
    fn lattice_reactions(&self, model: &Model, state: &State, control: &Control) -> Vec<Vec3> {
        let n = model.particle_count();
        let Some(mg) = self.mg.as_deref() else {
            return Vec::new();
        };
        if control.colliders.is_empty()
            || self.target.len() != n
            || mg.levels[0].nodes != n
            || self.settings.element_solver != ElementSolver::Multigrid
        {
            return Vec::new();
        }
        let h2 = self.h * self.h;
        let fixed = &mg.levels[0].fixed;
        let mut out = vec![Vec3::ZERO; control.colliders.len()];
        for (j, &fixed_j) in fixed.iter().enumerate().take(n) {
            if fixed_j
                || self.pin_slot[j] != u32::MAX
                || state.grab[j].collider != u32::MAX
                || model.elements_of(j).is_empty()
            {
                continue;
            }
            let r = model.bodies[model.particle_body[j] as usize].radius;
            let mut best: Option<(f32, usize, Vec3)> = None;
            for (k, c) in control.colliders.iter().enumerate() {
                if matches!(c.shape, ColliderShape::Grasper { .. }) {
                    continue;
                }
                let (d, normal) = c.distance(self.p[j]);
                if d < r * (1.0 + TOUCH_TOLERANCE) && best.is_none_or(|b| d < b.0) {
                    best = Some((d, k, normal));
                }
            }
            if let Some((_, k, normal)) = best {
                out[k] += reaction_on_collider(
                    model,
                    mg,
                    &state.element_rot,
                    &self.p,
                    j,
                    (self.target[j], h2),
                    normal,
                );
            }
        }
        out
    }
}

/// The force a lattice particle `j` at `p[j]` puts on a collider whose outward normal
/// there is `normal`: the particle's residual force without the contact, its inertia
/// `m (x̃ − p) / h²` (`target` = (x̃, h²)) plus its elements' elastic forces (their
/// rotations `rot` held), which the collider balances at equilibrium (the reaction at
/// a constrained node, as in FEM); its part along the normal where it presses on the
/// collider, zero where it pulls away.
fn reaction_on_collider(
    model: &Model,
    mg: &super::multigrid::LatticeMultigrid,
    rot: &[Quat],
    p: &[Vec3],
    j: usize,
    target: (Vec3, f32),
    normal: Vec3,
) -> Vec3 {
    let mut r = (target.0 - p[j]) * (model.mass[j] / target.1);
    for &ec in model.elements_of(j) {
        let (e, corner) = ((ec >> 3) as usize, (ec & 7) as usize);
        let b = model.element_body[e] as usize;
        let (Some(mat), Some(op)) = (&mg.material[b], &mg.unit_operator[b]) else {
            continue;
        };
        let nodes = &model.elements[e];
        let rest = &model.element_rest[e];
        let mut q = rot[e];
        let f = super::multigrid::element_forces(
            &nodes.map(|i| p[i as usize]),
            rest.size,
            rest.volume,
            mat,
            op,
            &mut q,
            0,
        );
        r += f[corner];
    }
    normal * r.dot(normal).min(0.0)
}

/// Steps the lattice line search tries: 1, ½, ¼, … down to 2⁻¹²; none lowering the
/// energy, the body stays.
const LINE_SEARCH_STEPS: usize = 13;

/// The contact penalty stiffness of lattice particle `j` in a substep of `h2` (s²), N/m:
/// a thousand times its own stiffness scale `m/h² + (λ + 2μ) s` (inertia plus the P-wave
/// modulus times the lattice spacing `s`: what its elements hold it with), so that it
/// dominates soft and stiff bodies alike.
fn contact_stiffness(model: &Model, j: usize, h2: f32) -> f32 {
    /// Penalty stiffness over the particle's stiffness scale.
    const PENALTY: f32 = 1.0e3;
    let body = &model.bodies[model.particle_body[j] as usize];
    let modulus = match body.material {
        Material::Hyperelastic {
            youngs_modulus,
            poisson_ratio,
        } => {
            let m = Hyperelastic::new(youngs_modulus, poisson_ratio);
            m.lambda + 2.0 * m.mu
        }
        Material::ShapeMatching { .. } => 0.0,
    };
    PENALTY * (model.mass[j] / h2 + modulus * body.spacing)
}

/// How far past their contact distance (a fraction of it) a pair of particles of
/// different bodies that the last projection found pressed together still holds in the
/// next Newton iteration of the lattice bodies (bilateral there, for that iteration).
/// The projection leaves such pairs at their contact distance; held only while
/// overlapping, a body resting on another would fall into it in every other step and
/// be pushed out in the next (a buzz of about gravity's step, `|g| h²`). A pair the
/// iteration then leaves apart (pulled, not pressed) is not pressed at the projection,
/// so the next iteration lets it go: no pair sticks. GPU twin: `PAIR_HOLD` in
/// `lattice.wgsl` (set from this).
pub(crate) const PAIR_HOLD: f32 = 0.01;

/// Whether a pair of particles `d` apart (m; `d0` at the substep's start) is pressed
/// together closer than their contact distance `dist` (m) along the line between them
/// at the substep's start, `d · d0/|d0| < dist` (where `d0` is not zero; else `|d| <
/// dist`), while within the hold's reach, `|d| < (1 + PAIR_HOLD) dist`. Measured along
/// that fixed line, a pair the Newton iteration held at its contact distance while
/// sliding sideways over a partner reads as touching, as it is, not as parted by the
/// sliding's second-order lengthening of `|d|` (which, measured as `|d|`, left a body
/// resting on a held one unheld every other step).
pub fn pressed_pair(d0: Vec3, d: Vec3, dist: f32) -> bool {
    let l0 = d0.length();
    let along = if l0 > 1e-12 {
        d.dot(d0) / l0
    } else {
        d.length()
    };
    let l2 = d.length_squared();
    let zone = dist * (1.0 + PAIR_HOLD);
    along < dist && l2 > 1e-24 && l2 < zone * zone
}

/// The substep's first iterate ties: a candidate start lowering a body's energy by less
/// than this fraction of its inertial and elastic energy is not taken (the energies are
/// equal to rounding there).
const FIRST_ITERATE_TIE: f64 = 1e-5;

/// The implicit-Euler substep energy of the lattice bodies at positions `y(j)`, each
/// body's own (J, indexed by body): `Σ_free m/(2h²) |y − x̃|² + Σ_e E_e(y) + Σ_c k/2
/// depth_c(y)²`, the inertia of its free particles, its elements' energy
/// ([`super::multigrid::element_energy`]) with the rotation `rot.1[e]` refined by
/// `rot.0` iterations towards `polar(F(y))` (0: held, the energy whose gradient the
/// Newton step's forces are; more: the fixed-corotated energy itself), and the penalty
/// energy of the active contacts its particles hold. `free` = (held nodes, inertial
/// targets x̃ in m), `contacts` = (the active collider contacts, the colliders).
fn substep_energy(
    model: &Model,
    mg: &super::multigrid::LatticeMultigrid,
    free: (&[bool], &[Vec3]),
    h2: f32,
    rot: (u32, &[Quat]),
    contacts: (&[NewtonContact], &Control),
    y: &dyn Fn(usize) -> Vec3,
) -> Vec<f64> {
    let (held, target) = free;
    let mut g = vec![0.0f64; model.bodies.len()];
    for j in 0..model.particle_count() {
        if !held[j] {
            g[model.particle_body[j] as usize] +=
                0.5 * (model.mass[j] / h2) as f64 * (y(j) - target[j]).length_squared() as f64;
        }
    }
    for (e, nodes) in model.elements.iter().enumerate() {
        let b = model.element_body[e] as usize;
        let (Some(mat), Some(op)) = (&mg.material[b], &mg.unit_operator[b]) else {
            continue;
        };
        let r = &model.element_rest[e];
        let x = nodes.map(|j| y(j as usize));
        let mut q = rot.1[e];
        extract_rotation(&element_gradient(&x, r.size), &mut q, rot.0);
        g[b] +=
            super::multigrid::element_energy(&x, r.size, r.volume, mat, op, &Mat3::from_quat(q));
    }
    for c in contacts.0 {
        let depth = c.depth(model, contacts.1, y);
        g[model.particle_body[c.node] as usize] += 0.5 * (c.stiffness * depth * depth) as f64;
    }
    g
}

/// The share of the last contact search's slack that particles must have moved
/// relative to one another for a search on the `knn_every` schedule
/// ([`Solver::contacts_moved`]).
const SCHEDULED_SEARCH_MOTION: f32 = 0.1;

/// How far the vectors `v` spread: the largest distance of one from a common centre,
/// the middle of their bounding box or zero, whichever gives less (any two are at most
/// twice this apart); zero for none, infinite where one is not finite.
fn spread(v: impl Iterator<Item = Vec3> + Clone) -> f32 {
    let (lo, hi, nan) = v.clone().fold(
        (
            Vec3::splat(f32::INFINITY),
            Vec3::splat(f32::NEG_INFINITY),
            false,
        ),
        |(lo, hi, nan), p| (lo.min(p), hi.max(p), nan || p.is_nan()),
    );
    // (f32::min and max pass NaN over: a value that is not finite is caught here.)
    if nan {
        return f32::INFINITY;
    }
    if lo.x > hi.x {
        return 0.0; // none
    }
    if !(lo.is_finite() && hi.is_finite()) {
        return f32::INFINITY;
    }
    let mid = 0.5 * (lo + hi);
    let (around_mid, around_zero) = v.fold((0.0f32, 0.0f32), |(m, z), p| {
        (m.max(p.distance_squared(mid)), z.max(p.length_squared()))
    });
    around_mid.min(around_zero).sqrt()
}
