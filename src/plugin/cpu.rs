//! Bodies simulated from the main world: lattice bodies (which the render graph's
//! kernels do not run) and, under [`TissueBackend::Cpu`] (chosen, or switched to when
//! the adapter cannot run the kernels), every body. They are batched into one core
//! model, state and [`Solver`] (so they touch each other through particle contacts, as
//! on the GPU); every frame the world takes the clock's steps against the scene's
//! colliders, then each body's render surface is skinned on the CPU (bodies on all
//! cores) and written into its draw mesh (positions and normals, in the entity's frame),
//! unless its particles moved less than [`SKIN_STILL`] of their spacing since its mesh
//! was last written (a body lying still costs no skinning and no mesh upload). The
//! render world leaves these bodies alone ([`runs_on_cpu`]). What this costs the main
//! thread is measured as [`TissueDiagnostics`](super::diagnostics::TissueDiagnostics).
//!
//! Under [`TissueBackend::Auto`], when every body of this world is a hyperelastic lattice
//! body, the steps run on the GPU ([`GpuLattice`]: the same Newton–multigrid, colliders,
//! graspers and particle contacts between bodies) and the positions are read back for
//! the skinning; the contact candidates are searched on the CPU from those positions
//! (every [`TissueSettings::knn_every`] steps while they move relative to one another,
//! and whenever particles may move out of the last search's reach, as the CPU solver
//! does) and uploaded. The
//! CPU's solver takes over where the GPU path is not possible (it cannot be set up, more
//! than [`crate::gpu::kernels::lattice::MAX_COLLIDERS`] colliders).
//!
//! Bodies coming and going: each lattice body brings its multigrid levels from its build
//! ([`BuiltBody::levels`]) and a new batch joins them. While the batch steps on the
//! GPU, a body gone is retired in place ([`CpuWorld::is_retired`]: held still, out of
//! reach, until retired bodies hold a quarter of the particles), a new body is appended
//! in place into the room of the batch's GPU world ([`CpuWorld::appended_in_place`]:
//! packed on a worker thread while the batch steps on, then written in the frame it is
//! ready; a body rebuilt with a new material is packed in the frame, as it keeps its
//! pose), and a batch with rebuilt bodies, or new ones past the room, is made on a worker
//! thread while the old one steps on, its GPU world with it; they join when it is ready
//! (the bodies it keeps take their state from the old world by GPU copies). Gravity,
//! damping and the step's schedule (time step, substeps, iterations) change in place.
//! Anything else (other settings changes, the CPU path) makes the batch again at once.
//!
//! Not done on this path (yet): sleeping, and [`ColliderForce`] while some bodies are
//! stepped by the render graph (it is written when every built body is in this world).

use super::build::BuiltBody;
use super::components::*;
use super::diagnostics::{TissueDiagnostics, ms_since};
use super::render::{LastPose, core_collider};
use crate::core::TissueError;
use crate::core::colliders::{Collider, ColliderShape, GraspMode};
use crate::core::model::Model;
use crate::core::model::{Discretisation, Material};
use crate::core::multigrid::{BodyLevels, LatticeMultigrid, MAX_LEVELS};
use crate::core::skin::{skin_normals, skin_positions};
use crate::core::solver::{Control, Solver, SolverSettings, State};
use crate::gpu::kernels::lattice::{LatticeKernels, MAX_COLLIDERS};
use crate::gpu::lattice::{GpuLattice, LatticeOptions, PreparedAppend, StateRun};
use bevy::camera::primitives::Aabb;
use bevy::diagnostic::Diagnostics;
use bevy::math::Affine3A;
use bevy::mesh::VertexAttributeValues;
use bevy::platform::time::Instant;
use bevy::prelude::*;
use bevy::render::renderer::{RenderDevice, RenderQueue};
use bevy::tasks::{AsyncComputeTaskPool, Task, block_on, futures_lite::future};
use std::collections::HashMap;
use std::ops::Range;
use std::sync::Arc;

/// How far below its rest shape a retired body is held, m: out of any scene's reach,
/// near enough for `f32` to keep its shape (about 0.1 mm of rounding).
pub const RETIRED_DEPTH: f32 = 1000.0;

/// Room the batch's GPU world leaves for bodies spawned later: half as much again as
/// its bodies take, and one more of its largest.
const ROOM: f32 = 1.5;

/// Whether a built body steps on the CPU: every body under [`TissueBackend::Cpu`], and
/// lattice bodies (hexahedral elements) under [`TissueBackend::Auto`].
pub fn runs_on_cpu(model: &Model, settings: &TissueSettings) -> bool {
    settings.backend == TissueBackend::Cpu || !model.elements.is_empty()
}

/// Marks a body stepped on the CPU, and where its particles are in [`CpuWorld`].
#[derive(Component, Debug, Clone, PartialEq)]
pub struct CpuBody {
    /// Its body index in the CPU world's model.
    pub index: usize,
    /// Its particles in the CPU world's state.
    pub particles: Range<usize>,
}

/// The CPU bodies batched: one model (the bodies appended in entity order), its state
/// and its solver.
#[derive(Resource, Default)]
pub struct CpuWorld {
    /// (entity, [`BuiltBody::generation`]) of each body, in the model's order.
    keys: Vec<(Entity, u64)>,
    /// Per body of the model: gone from the scene and held out of the way on the GPU
    /// until the next rebuild ([`CpuWorld::is_retired`]).
    retired: Vec<bool>,
    /// The model index of each body not retired, by entity.
    slots: HashMap<Entity, usize>,
    model: Model,
    state: Option<State>,
    solver: Option<Solver>,
    settings: Option<SolverSettings>,
    /// Particle range and element range of each body.
    ranges: Vec<(Range<usize>, Range<usize>)>,
    /// Graspers that have had a CPU step while closed (they then hold, not capture).
    captured: Vec<Entity>,
    /// The lattice kernels and, once made, the world's bodies on the GPU.
    gpu: Option<LatticeOnGpu>,
    /// The GPU path failed for this model (kernels or buffers): the CPU steps it.
    gpu_failed: bool,
    /// The last step ran on the GPU.
    last_on_gpu: bool,
    /// Times the batched model was rebuilt (bodies came, went or changed, or settings
    /// changed what the solver precomputes).
    rebuilds: u64,
    /// The lattice bodies' multigrid levels, joined from each body's own since the last
    /// rebuild, for the next GPU world.
    levels: Option<LatticeMultigrid>,
    /// Bodies whose levels this world had to coarsen itself (they came without them).
    coarsened: u64,
    /// A batch being made on a worker thread for these bodies (the current one steps
    /// meanwhile).
    pending: Option<PendingBatch>,
    /// New bodies being packed on a worker thread for the GPU world's room.
    pending_append: Option<PendingAppend>,
    /// Rebuilds made on a worker thread.
    off_thread: u64,
    /// GPU worlds made on a worker thread with their batch.
    worlds_off_thread: u64,
    /// Worlds made again whose bodies took their state from the world before them by
    /// GPU copies.
    states_carried: u64,
    /// Bodies appended in place ([`CpuWorld::appended_in_place`]).
    appended: u64,
    /// Bodies were appended in place since the solver was made: it is made again
    /// before a CPU step.
    solver_stale: bool,
    /// The particles as the bodies' meshes last showed them (m; empty until written).
    shown: Vec<Vec3>,
    /// Wall time of the last GPU step's contact search (staleness test, search and
    /// upload), ms; `None` where that step had no particle contacts.
    contacts_ms: Option<f64>,
}

/// The CPU world's lattice bodies on the GPU.
struct LatticeOnGpu {
    kernels: LatticeKernels,
    world: Option<GpuLattice>,
    /// The GPU holds the CPU state's latest positions.
    synced: bool,
    /// The GPU's particle-contact candidates were searched from its current bodies.
    lists: bool,
    /// Gravity or damping changed since the GPU world was made or last told.
    forces_dirty: bool,
    /// The world `world` replaced, and the runs of bodies whose state it hands over by
    /// GPU copies ([`GpuLattice::carry_state`]) before `world` first steps.
    carry: Option<(GpuLattice, Vec<StateRun>)>,
}

/// Whether the GPU can step every body of `model` (hyperelastic lattice bodies).
fn gpu_can_step(model: &Model) -> bool {
    !model.bodies.is_empty()
        && model.bodies.iter().all(|b| {
            b.discretisation == Discretisation::Lattice
                && matches!(b.material, Material::Hyperelastic { .. })
        })
}

impl CpuWorld {
    /// Whether the last step ran on the GPU ([`GpuLattice`]) rather than the CPU's solver.
    pub fn stepped_on_gpu(&self) -> bool {
        self.last_on_gpu
    }

    /// How many times the batched model was rebuilt: bodies came, went or changed, or a
    /// settings change reached what the solver precomputes. Gravity, damping and the
    /// divergence speed change in place.
    pub fn rebuilds(&self) -> u64 {
        self.rebuilds
    }

    /// How many of the [`CpuWorld::rebuilds`] were made on a worker thread while the
    /// batch before them stepped on (bodies new or rebuilt while the batch steps on the
    /// GPU; the bodies join it when it is ready, some frames later).
    pub fn rebuilds_off_thread(&self) -> u64 {
        self.off_thread
    }

    /// How many of the batch's GPU worlds were made on a worker thread with their batch
    /// (a rebuild while the batch stepped on the GPU), not in the frame that steps them.
    pub fn gpu_worlds_made_off_thread(&self) -> u64 {
        self.worlds_off_thread
    }

    /// How many of the GPU worlds made on a worker thread took the state of the bodies
    /// they share with the world before them by copies on the GPU, the frame that
    /// installed them uploading nothing from the CPU.
    pub fn states_carried_on_gpu(&self) -> u64 {
        self.states_carried
    }

    /// How many bodies were appended to the batch in place: spawned while the batch
    /// stepped on the GPU, into the room of its GPU world, without a rebuild (the other
    /// bodies kept their state; see [`GpuLattice::append`] and
    /// [`crate::gpu::lattice::AppendBasis`]).
    pub fn appended_in_place(&self) -> u64 {
        self.appended
    }

    /// How many bodies' multigrid levels this world has coarsened itself. A lattice body
    /// brings its levels from its build ([`BuiltBody::levels`]), and a rebuild joins
    /// them, so bodies coming, going or changing do not coarsen the others again: this
    /// stays 0 unless a body came without them.
    pub fn coarsened_bodies(&self) -> u64 {
        self.coarsened
    }

    /// Takes `settings` in place where they differ from the current ones only in
    /// gravity, damping and the divergence speed, or, while the batch steps on the GPU,
    /// also in the step's schedule (time step, substeps, iterations, contact relaxation
    /// and schedule: [`GpuLattice::set_steps`]; the CPU's solver is then made again
    /// before it steps); false (nothing changed) otherwise.
    fn apply_in_place(&mut self, settings: &SolverSettings, queue: Option<&RenderQueue>) -> bool {
        let on_gpu = self.on_gpu_now();
        let (Some(old), Some(solver)) = (self.settings.as_mut(), self.solver.as_mut()) else {
            return false;
        };
        if !old.differs_only_in_forces(settings) {
            let world = self.gpu.as_mut().and_then(|g| g.world.as_mut());
            let (true, Some(queue), Some(world)) = (on_gpu, queue, world) else {
                return false;
            };
            if !world.set_steps(queue, settings) {
                return false;
            }
            self.solver_stale = true;
        }
        *old = settings.clone();
        solver.settings = settings.clone();
        if let Some(g) = self.gpu.as_mut() {
            g.forces_dirty = true;
        }
        true
    }

    /// The batched model of the CPU bodies.
    pub fn model(&self) -> &Model {
        &self.model
    }

    /// The batched state (`None` before the first CPU body).
    pub fn state(&self) -> Option<&State> {
        self.state.as_ref()
    }

    /// The entities of the CPU bodies, in the model's body order (retired ones
    /// included: see [`CpuWorld::is_retired`]).
    pub fn entities(&self) -> impl Iterator<Item = Entity> + '_ {
        self.keys.iter().map(|k| k.0)
    }

    /// Whether body `index` of the model is retired: it left the scene while the batch
    /// stepped on the GPU (or was rebuilt and appended anew in place),
    /// and instead of a rebuild it was held still, out of everyone's
    /// reach, until the batch is made again (when retired bodies hold a quarter of its
    /// particles, or for any other change).
    pub fn is_retired(&self, index: usize) -> bool {
        self.retired.get(index).copied().unwrap_or(false)
    }

    /// Whether the batch's bodies still in the scene are `keys` (in any order: bodies
    /// appended in place come after the others).
    fn holds_exactly(&self, keys: &[(Entity, u64)]) -> bool {
        keys.len() == self.slots.len()
            && keys
                .iter()
                .all(|k| self.slots.get(&k.0).is_some_and(|&i| self.keys[i] == *k))
    }

    /// Appends the bodies of `bodies` the batch does not have yet, and the ones rebuilt
    /// since it was made (a new material, say), to it in place, without a rebuild: into
    /// the room of its GPU world ([`GpuLattice::append`]) and onto its model and state.
    /// A rebuilt body's old slot is retired (as a body gone, [`CpuWorld::is_retired`]);
    /// the new one starts from the old one's pose where they have the same particles and
    /// elements and it does not ask to start at rest. Possible where the batch steps on
    /// the GPU, holds its latest state, every body coming is a lattice body that brought
    /// its levels, and retired bodies would then hold at most a quarter of the
    /// particles. True where the batch now holds exactly `bodies`; false where a rebuild
    /// is needed (the bodies appended before the one that did not fit stay, consistently
    /// on the CPU and the GPU).
    fn append_new(
        &mut self,
        bodies: &[(Entity, &BuiltBody)],
        device: &RenderDevice,
        queue: &RenderQueue,
    ) -> bool {
        if !self.on_gpu_now() {
            return false;
        }
        // Each body coming, with the slot it replaces (a rebuilt body).
        let coming: Vec<(Entity, &BuiltBody, Option<usize>)> = bodies
            .iter()
            .filter_map(|&(e, b)| match self.slots.get(&e) {
                None => Some((e, b, None)),
                Some(&i) if self.keys[i].1 != b.generation => Some((e, b, Some(i))),
                Some(_) => None,
            })
            .collect();
        let fresh_count = coming.iter().filter(|c| c.2.is_none()).count();
        let retiring: usize = coming
            .iter()
            .filter_map(|c| c.2)
            .chain((0..self.keys.len()).filter(|&i| self.retired[i]))
            .map(|i| self.ranges[i].0.len())
            .sum();
        let total = self.model.particle_count()
            + coming
                .iter()
                .map(|c| c.1.model.particle_count())
                .sum::<usize>();
        if coming.is_empty()
            || self.slots.len() + fresh_count != bodies.len()
            || 4 * retiring > total
            || coming
                .iter()
                .any(|(_, b, _)| b.levels.is_none() || !gpu_can_step(&b.model))
        {
            return false;
        }
        // A rebuilt body keeps its pose from the state as it is now: packed here. New
        // bodies are packed on a worker thread while the batch steps on.
        if coming.iter().any(|c| c.2.is_some()) {
            self.pending_append = None;
            return self.append_now(&coming, device, queue);
        }
        self.append_soon(&coming, device, queue)
    }

    /// Appends `coming` (each body with the slot it replaces) now, packed on this
    /// thread. False at the first that does not fit (those before it stay appended).
    fn append_now(
        &mut self,
        coming: &[(Entity, &BuiltBody, Option<usize>)],
        device: &RenderDevice,
        queue: &RenderQueue,
    ) -> bool {
        for &(entity, built, old) in coming {
            let (Some(levels), Some(settings), Some(state), Some(g)) = (
                built.levels.as_ref(),
                self.settings.as_ref(),
                self.state.as_mut(),
                self.gpu.as_mut(),
            ) else {
                return false;
            };
            let Some(world) = g.world.as_mut() else {
                return false;
            };
            let mut fresh = State::new(&built.model);
            // A rebuilt body with the same particles keeps its pose.
            if let Some(i) = old {
                let (p, e) = self.ranges[i].clone();
                if !built.reset && p.len() == fresh.x.len() && e.len() == fresh.element_rot.len() {
                    fresh.x.copy_from_slice(&state.x[p.clone()]);
                    fresh.v.copy_from_slice(&state.v[p.clone()]);
                    fresh.rot.copy_from_slice(&state.rot[p.clone()]);
                    fresh.grab.copy_from_slice(&state.grab[p]);
                    fresh.element_rot.copy_from_slice(&state.element_rot[e]);
                }
            }
            match world.append(device, queue, &built.model, levels, &fresh, settings) {
                Ok(true) => {}
                Ok(false) => return false,
                Err(e) => {
                    warn!("bevy_tissue: {e}");
                    return false;
                }
            }
            self.took(entity, built, &fresh, old, queue);
        }
        true
    }

    /// Appends new bodies `coming` from packings made on a worker thread against the
    /// GPU world as it is now ([`AppendBasis::prepare`]): starts them, or commits them
    /// once ready, so that the frame pays only for the writes. True while they are
    /// being packed and once committed; false (nothing changed) where they do not fit
    /// (the caller rebuilds).
    fn append_soon(
        &mut self,
        coming: &[(Entity, &BuiltBody, Option<usize>)],
        device: &RenderDevice,
        queue: &RenderQueue,
    ) -> bool {
        let keys: Vec<(Entity, u64)> = coming.iter().map(|c| (c.0, c.1.generation)).collect();
        // A packing for bodies that are no longer all coming is dropped.
        if self
            .pending_append
            .as_ref()
            .is_some_and(|p| !p.0.iter().all(|k| keys.contains(k)))
        {
            self.pending_append = None;
        }
        if self.pending_append.is_none() {
            let (Some(settings), Some(world)) = (
                self.settings.clone(),
                self.gpu.as_ref().and_then(|g| g.world.as_ref()),
            ) else {
                return false;
            };
            let mut basis = world.append_basis();
            let inputs: Vec<(Arc<Model>, Arc<BodyLevels>)> = coming
                .iter()
                .filter_map(|c| Some((c.1.model.clone(), c.1.levels.clone()?)))
                .collect();
            let device = device.clone();
            let task = AsyncComputeTaskPool::get().spawn(async move {
                let mut out = Vec::with_capacity(inputs.len());
                for (model, levels) in inputs {
                    let state = State::new(&model);
                    let Some(mut prepared) = basis.prepare(&model, &levels, &state, &settings)?
                    else {
                        return Ok(None);
                    };
                    prepared.stage(&device);
                    basis = basis.after(&prepared);
                    out.push(prepared);
                }
                Ok(Some(out))
            });
            self.pending_append = Some((keys, task));
        }
        let Some((_, task)) = self.pending_append.as_mut() else {
            return false;
        };
        let ready = match block_on(future::poll_once(task)) {
            None => return true,
            Some(Ok(Some(ready))) => ready,
            Some(Ok(None)) => {
                self.pending_append = None;
                return false;
            }
            Some(Err(e)) => {
                warn!("bevy_tissue: {e}");
                self.pending_append = None;
                return false;
            }
        };
        let Some((keys, _)) = self.pending_append.take() else {
            return false;
        };
        for (key, prepared) in keys.into_iter().zip(ready) {
            let Some(&(entity, built, _)) = coming.iter().find(|c| (c.0, c.1.generation) == key)
            else {
                break;
            };
            let Some(world) = self.gpu.as_mut().and_then(|g| g.world.as_mut()) else {
                return false;
            };
            // The world changed since the packing began: the rest are packed again.
            if !world.commit_append(device, queue, prepared) {
                break;
            }
            let fresh = State::new(&built.model);
            self.took(entity, built, &fresh, None, queue);
        }
        true
    }

    /// Takes `built` (as `entity`, from `fresh`), just appended to the GPU world, into
    /// the model and the state; retires the slot `old` it replaces.
    fn took(
        &mut self,
        entity: Entity,
        built: &BuiltBody,
        fresh: &State,
        old: Option<usize>,
        queue: &RenderQueue,
    ) {
        let (Some(state), Some(g)) = (self.state.as_mut(), self.gpu.as_mut()) else {
            return;
        };
        // The new body meets the others at the next step's contact search.
        g.lists = false;
        let (p0, e0) = (self.model.particle_count(), self.model.elements.len());
        self.model.append(&built.model);
        state.x.extend_from_slice(&fresh.x);
        state.v.extend_from_slice(&fresh.v);
        state.rot.extend_from_slice(&fresh.rot);
        state.element_rot.extend_from_slice(&fresh.element_rot);
        state.pin_targets.extend_from_slice(&fresh.pin_targets);
        state.grab.extend_from_slice(&fresh.grab);
        self.ranges.push((
            p0..self.model.particle_count(),
            e0..self.model.elements.len(),
        ));
        // The old slot of a rebuilt body is held still out of reach.
        if let Some(i) = old
            && let Some(world) = g.world.as_ref()
        {
            park(world, queue, &self.model, state, self.ranges[i].0.clone());
            self.retired[i] = true;
        }
        self.slots.insert(entity, self.keys.len());
        self.keys.push((entity, built.generation));
        self.retired.push(false);
        // The CPU's solver is made again before it steps this batch.
        self.solver_stale = true;
        self.appended += 1;
    }

    /// The model index of `entity`'s body (not retired).
    fn index_of(&self, entity: Entity) -> Option<usize> {
        self.slots.get(&entity).copied()
    }

    /// Whether the batch steps on the GPU, which holds its latest state.
    fn on_gpu_now(&self) -> bool {
        self.gpu
            .as_ref()
            .is_some_and(|g| g.world.is_some() && g.synced)
    }

    /// Retires the bodies of the batch whose entities `keys` (the scene's bodies) no
    /// longer has, without a rebuild: possible where the batch steps on the GPU, holds
    /// the latest state, and retired bodies would hold at most a quarter of its
    /// particles and not all of its bodies. Each is held still on the GPU
    /// ([`GpuLattice::hold`]) at its rest shape [`RETIRED_DEPTH`] below where it was
    /// built, so that it neither moves nor touches anything. True where nothing had to
    /// go; false (nothing changed) where a rebuild is needed.
    fn retire_gone(&mut self, keys: &[(Entity, u64)], queue: &RenderQueue) -> bool {
        let gone: Vec<usize> = self
            .slots
            .iter()
            .filter(|(e, _)| !keys.iter().any(|k| k.0 == **e))
            .map(|(_, &i)| i)
            .collect();
        if gone.is_empty() {
            return true;
        }
        if gone.len() == self.slots.len() || !self.on_gpu_now() {
            return false;
        }
        let (Some(world), Some(state)) = (
            self.gpu.as_ref().and_then(|g| g.world.as_ref()),
            self.state.as_mut(),
        ) else {
            return false;
        };
        let held: usize = (0..self.keys.len())
            .filter(|&i| self.retired[i] || gone.contains(&i))
            .map(|i| self.ranges[i].0.len())
            .sum();
        if 4 * held > self.model.particle_count() {
            return false;
        }
        for &b in &gone {
            park(world, queue, &self.model, state, self.ranges[b].0.clone());
            self.retired[b] = true;
            self.slots.remove(&self.keys[b].0);
        }
        true
    }

    /// Rebuilds the batched model for `bodies` (entity order), keeping the state of the
    /// bodies that were simulated before and are the same particles: unchanged ones,
    /// and rebuilt ones that do not ask to start at rest (a material change resamples
    /// nothing).
    fn rebuild(
        &mut self,
        bodies: &[(Entity, &BuiltBody)],
        settings: SolverSettings,
    ) -> Result<(), TissueError> {
        self.pending = None;
        let batch = make_batch(batch_inputs(bodies), settings, None)?;
        self.install(batch);
        Ok(())
    }

    /// Makes the batch for `bodies` on a worker thread while the current one steps on,
    /// where the current one steps on the GPU; installs it, the bodies already there
    /// carrying their latest pose over, on the first call after it is ready. False where
    /// a rebuild is needed instead (no GPU batch yet, or a different set of bodies
    /// finished first and was dropped: the caller rebuilds or calls again).
    fn rebuild_soon(
        &mut self,
        bodies: &[(Entity, &BuiltBody)],
        settings: &SolverSettings,
        device: Option<&RenderDevice>,
    ) -> bool {
        let keys: Vec<(Entity, u64)> = bodies.iter().map(|(e, b)| (*e, b.generation)).collect();
        if !self.on_gpu_now() || self.settings.as_ref() != Some(settings) {
            return false;
        }
        if self.pending.as_ref().is_none_or(|p| p.0 != keys) {
            let inputs = batch_inputs(bodies);
            let settings = settings.clone();
            // Its GPU world is made on the worker thread too: the frame that installs it
            // only uploads the latest state.
            let gpu = device
                .zip(self.gpu.as_ref())
                .map(|(d, g)| (d.clone(), g.kernels.clone()));
            let task =
                AsyncComputeTaskPool::get().spawn(async move { make_batch(inputs, settings, gpu) });
            self.pending = Some((keys, task));
        }
        let Some((_, task)) = self.pending.as_mut() else {
            return true;
        };
        match block_on(future::poll_once(task)) {
            None => true,
            Some(Ok(batch)) => {
                self.pending = None;
                self.install(batch);
                self.off_thread += 1;
                true
            }
            Some(Err(_)) => {
                self.pending = None;
                false
            }
        }
    }

    /// Takes `batch` as the world's bodies, their state carried over from the current
    /// batch where they are the same particles.
    fn install(&mut self, batch: Batch) {
        let Batch {
            bodies,
            model,
            ranges,
            solver,
            levels,
            coarsened,
            settings,
            world,
        } = batch;
        let mut state = State::new(&model);
        let mut runs = Vec::new();
        if let Some(old) = &self.state {
            for (&(entity, generation, reset), (p, e)) in bodies.iter().zip(&ranges) {
                let Some(k) = self.index_of(entity) else {
                    continue;
                };
                let (op, oe) = &self.ranges[k];
                let same = self.keys[k].1 == generation
                    || (!reset && op.len() == p.len() && oe.len() == e.len());
                if !same {
                    continue;
                }
                state.x[p.clone()].copy_from_slice(&old.x[op.clone()]);
                state.v[p.clone()].copy_from_slice(&old.v[op.clone()]);
                state.rot[p.clone()].copy_from_slice(&old.rot[op.clone()]);
                state.element_rot[e.clone()].copy_from_slice(&old.element_rot[oe.clone()]);
                runs.push(StateRun {
                    particles: op.start as u32..op.end as u32,
                    to_particle: p.start as u32,
                    elements: oe.start as u32..oe.end as u32,
                    to_element: e.start as u32,
                });
            }
            state.step = old.step;
        }
        self.pending_append = None;
        self.solver = Some(solver);
        self.levels = levels;
        self.coarsened += coarsened;
        self.settings = Some(settings);
        self.keys = bodies.iter().map(|&(e, g, _)| (e, g)).collect();
        self.retired = vec![false; self.keys.len()];
        self.slots = self
            .keys
            .iter()
            .enumerate()
            .map(|(i, k)| (k.0, i))
            .collect();
        self.model = model;
        self.state = Some(state);
        self.ranges = ranges;
        self.gpu_failed = false;
        self.solver_stale = false;
        self.rebuilds += 1;
        if let Some(g) = self.gpu.as_mut() {
            // A world made with the batch takes the state carried over at the next step:
            // by GPU copies from the world it replaces where that one is current.
            let synced_before = g.synced;
            g.synced = world.is_none();
            self.worlds_off_thread += world.is_some() as u64;
            let old = std::mem::replace(&mut g.world, world);
            g.carry = old
                .filter(|_| g.world.is_some() && synced_before)
                .map(|w| (w, StateRun::joined(runs)));
            g.lists = false;
            g.forces_dirty = false;
        }
    }

    /// Steps `steps` times on the GPU: `Some` with the colliders' forces, or the error
    /// of a diverged step (the body index in it); `None` where the GPU path is not
    /// available (the caller steps on the CPU).
    fn step_gpu(
        &mut self,
        render: (&RenderDevice, &RenderQueue),
        control: &Control,
        steps: u32,
    ) -> Option<Result<Vec<Vec3>, TissueError>> {
        let (device, queue) = render;
        let settings = self.settings.as_ref()?;
        if self.gpu_failed || control.colliders.len() > MAX_COLLIDERS || !gpu_can_step(&self.model)
        {
            return None;
        }
        let state = self.state.as_mut()?;
        if self.gpu.is_none() {
            match LatticeKernels::new(device) {
                Ok(kernels) => {
                    self.gpu = Some(LatticeOnGpu {
                        kernels,
                        world: None,
                        synced: false,
                        lists: false,
                        forces_dirty: false,
                        carry: None,
                    })
                }
                Err(e) => {
                    warn!("bevy_tissue: lattice bodies step on the CPU: {e}");
                    self.gpu_failed = true;
                    return None;
                }
            }
        }
        let g = self.gpu.as_mut()?;
        if g.world.is_none() {
            let made = match self.levels.take() {
                Some(mg) => GpuLattice::with_levels(
                    device,
                    &g.kernels,
                    &self.model,
                    mg,
                    state,
                    settings,
                    LatticeOptions {
                        room: ROOM,
                        ..Default::default()
                    },
                ),
                None => GpuLattice::new(device, &g.kernels, &self.model, state, settings),
            };
            match made {
                Ok(w) => {
                    g.world = Some(w);
                    g.synced = true;
                    g.lists = false;
                    g.forces_dirty = false;
                }
                Err(e) => {
                    warn!("bevy_tissue: lattice bodies step on the CPU: {e}");
                    self.gpu_failed = true;
                    return None;
                }
            }
        }
        let world = g.world.as_mut()?;
        if g.forces_dirty {
            world.set_forces(queue, settings.gravity, settings.damping);
            g.forces_dirty = false;
        }
        let carried = match g.carry.take() {
            Some((old, runs)) if !g.synced => match world.carry_state(device, queue, &old, &runs) {
                Ok(()) => true,
                Err(e) => {
                    warn!("bevy_tissue: the state is uploaded instead: {e}");
                    false
                }
            },
            _ => false,
        };
        if carried {
            self.states_carried += 1;
            g.synced = true;
            g.lists = false;
        }
        if !g.synced {
            world.upload(queue, &self.model, state);
            // The upload pins only the model's pins: the retired bodies are held again.
            for (b, _) in self.retired.iter().enumerate().filter(|(_, r)| **r) {
                let p = self.ranges[b].0.clone();
                world.hold(queue, &self.model, p.clone(), &state.x[p]);
            }
            g.synced = true;
            g.lists = false;
        }
        if let Err(e) = world.set_colliders(queue, &control.colliders) {
            return Some(Err(e));
        }
        // Particle-contact candidates, searched from the positions read back last frame
        // when one of this frame's steps is due a search and particles moved relative to
        // one another, or particles may move out of the last search's reach in this
        // frame's steps (the CPU solver's rule), or this world has no lists yet.
        let every = settings.knn_every.max(1) as u64;
        let due = (state.step..state.step + steps as u64).any(|s| s % every == 0);
        self.contacts_ms = None;
        if world.has_particle_contacts()
            && let Some(solver) = self.solver.as_mut()
        {
            let start = Instant::now();
            let periodic = !g.lists || (due && solver.contacts_moved(&state.x));
            // Retired bodies are parked far away: out of the search.
            let active: Vec<bool> = self.retired.iter().map(|r| !r).collect();
            let (x, v) = (&state.x, &state.v);
            if solver.refresh_contacts_if_due(&self.model, x, v, &active, steps, periodic) {
                let (start, list) = solver.contact_lists();
                if let Err(e) = world.set_contacts(queue, start, list) {
                    return Some(Err(e));
                }
                g.lists = true;
            }
            self.contacts_ms = Some(ms_since(start));
        }
        // The fastest particle of each body before the steps (for a divergence's advice).
        let bodies = &self.model.bodies;
        let threads = crate::core::par::threads_for(state.v.len(), 32768, 0);
        let before: Vec<f32> = crate::core::par::map(bodies.len(), threads, |b| {
            state.v[bodies[b].range()]
                .iter()
                .map(|v| v.length())
                .fold(0.0f32, f32::max)
        });
        let mut enc = device.create_command_encoder(&Default::default());
        world.record(&mut enc, &g.kernels, steps, None);
        queue.submit([enc.finish()]);
        let forces = world.download(device, queue, state);
        state.step += steps as u64;
        if let Some(worst) =
            crate::core::diagnose::worst_particle(&state.x, &state.v, settings.max_speed)
        {
            let body = self.model.particle_body[worst.0] as usize;
            g.synced = false;
            return Some(Err(crate::core::diagnose::diverged(
                &self.model,
                settings,
                state.step,
                worst,
                before.get(body).copied().unwrap_or(0.0),
            )));
        }
        Some(Ok(forces))
    }

    /// Puts body `index` back at rest (its particles at their rest positions, still).
    fn reset_body(&mut self, index: usize) {
        let (Some(state), Some((p, e))) = (self.state.as_mut(), self.ranges.get(index)) else {
            return;
        };
        let rest = State::new(&self.model);
        state.x[p.clone()].copy_from_slice(&rest.x[p.clone()]);
        state.v[p.clone()].copy_from_slice(&rest.v[p.clone()]);
        state.rot[p.clone()].copy_from_slice(&rest.rot[p.clone()]);
        state.grab[p.clone()].copy_from_slice(&rest.grab[p.clone()]);
        state.element_rot[e.clone()].copy_from_slice(&rest.element_rot[e.clone()]);
        if let Some(g) = self.gpu.as_mut() {
            g.synced = false;
        }
    }
}

/// Holds `model`'s particles `range` still on the GPU at their rest shape
/// [`RETIRED_DEPTH`] below where they were built, at rest in `state` too: a retired body,
/// out of everyone's reach.
fn park(
    world: &GpuLattice,
    queue: &RenderQueue,
    model: &Model,
    state: &mut State,
    range: Range<usize>,
) {
    let below = Vec3::new(0.0, -RETIRED_DEPTH, 0.0);
    for i in range.clone() {
        state.x[i] = model.rest[i] + below;
        state.v[i] = Vec3::ZERO;
    }
    world.hold(queue, model, range.clone(), &state.x[range]);
}

/// What making a batch takes from each body: entity, generation, whether it starts at
/// rest, its model and its multigrid levels.
type BatchInput = (Entity, u64, bool, Arc<Model>, Option<Arc<BodyLevels>>);

/// A batch in the making: the bodies it is for, and the task making it.
type PendingBatch = (Vec<(Entity, u64)>, Task<Result<Batch, TissueError>>);

/// Bodies (their keys, in order) packed on a worker thread for the GPU world's room:
/// each one's packing, or `None` where they do not all fit.
type PendingAppend = (
    Vec<(Entity, u64)>,
    Task<Result<Option<Vec<PreparedAppend>>, TissueError>>,
);

/// A batch of bodies made ready to step (off the main thread where it can be).
struct Batch {
    /// Per body: entity, generation, whether it starts at rest.
    bodies: Vec<(Entity, u64, bool)>,
    model: Model,
    /// Particle range and element range of each body.
    ranges: Vec<(Range<usize>, Range<usize>)>,
    solver: Solver,
    /// The lattice bodies' joined multigrid levels, where the GPU can step them all.
    levels: Option<LatticeMultigrid>,
    /// Bodies whose levels had to be coarsened here (they came without them).
    coarsened: u64,
    settings: SolverSettings,
    /// The GPU world of `levels`, made with the batch (at rest; the installing frame
    /// uploads the state it carries over).
    world: Option<GpuLattice>,
}

fn batch_inputs(bodies: &[(Entity, &BuiltBody)]) -> Vec<BatchInput> {
    bodies
        .iter()
        .map(|(e, b)| (*e, b.generation, b.reset, b.model.clone(), b.levels.clone()))
        .collect()
}

/// The batched model of `bodies` (in that order), its solver and, where the GPU can
/// step every body, the bodies' own multigrid levels joined.
/// Makes the batch of `bodies`, and with `gpu` (a device and the lattice kernels) its GPU
/// world where the GPU can step it.
fn make_batch(
    bodies: Vec<BatchInput>,
    settings: SolverSettings,
    gpu: Option<(RenderDevice, LatticeKernels)>,
) -> Result<Batch, TissueError> {
    let mut model = Model::new();
    let mut ranges = Vec::with_capacity(bodies.len());
    for (_, _, _, m, _) in &bodies {
        let (p0, e0) = (model.particle_count(), model.elements.len());
        model.append(m);
        ranges.push((p0..model.particle_count(), e0..model.elements.len()));
    }
    let solver = Solver::new(&model, settings.clone())?;
    let mut coarsened = 0;
    let levels = gpu_can_step(&model).then(|| {
        let own: Vec<Arc<BodyLevels>> = bodies
            .iter()
            .map(|(_, _, _, m, levels)| {
                levels.clone().unwrap_or_else(|| {
                    coarsened += 1;
                    Arc::new(BodyLevels::new(m, 0))
                })
            })
            .collect();
        let parts: Vec<&BodyLevels> = own.iter().map(Arc::as_ref).collect();
        LatticeMultigrid::from_bodies(&parts, settings.sweeps.min_nodes(), MAX_LEVELS)
    });
    let (levels, world) = match (levels, gpu) {
        (Some(mg), Some((device, kernels))) => {
            let options = LatticeOptions {
                room: ROOM,
                ..Default::default()
            };
            let rest = State::new(&model);
            // Where it cannot be made, the installing frame tries again (and says why).
            let made =
                GpuLattice::with_levels(&device, &kernels, &model, mg, &rest, &settings, options);
            (None, made.ok())
        }
        (levels, _) => (levels, None),
    };
    Ok(Batch {
        bodies: bodies.iter().map(|b| (b.0, b.1, b.2)).collect(),
        model,
        ranges,
        solver,
        levels,
        coarsened,
        settings,
        world,
    })
}

/// The scene's colliders as the core sees them, in spawn order (the same list the GPU
/// path builds), with their entities and velocities from their motion over the last
/// frame (`dt`, s); closed graspers capture (the CPU world latches them itself).
pub fn scene_colliders(
    colliders: &Query<(Entity, &TissueCollider, &GlobalTransform, Option<&LastPose>)>,
    dt: f32,
) -> Vec<(Entity, Collider)> {
    let mut list: Vec<(Entity, Collider)> = colliders
        .iter()
        .map(|(e, c, t, last)| (e, core_collider(c, t, last, None, dt)))
        .collect();
    list.sort_by_key(|c| c.0.index_u32());
    list
}

/// Steps the CPU bodies by the clock's steps of this frame, writes their meshes and
/// culling boxes (when they stepped, were rebuilt or moved) and, where asked, their
/// particle positions. A body whose step diverges
/// is put back at rest and reported ([`SoftBodyError`], with the core's diagnosis:
/// where, why, what to change); the others go on.
#[allow(clippy::type_complexity, clippy::too_many_arguments)]
pub fn step_cpu_bodies(
    mut commands: Commands,
    mut world: ResMut<CpuWorld>,
    clock: Res<TissueClock>,
    settings: Res<TissueSettings>,
    time: Res<Time>,
    mut meshes: ResMut<Assets<Mesh>>,
    bodies: Query<(
        Entity,
        &BuiltBody,
        Ref<GlobalTransform>,
        Option<&CpuBody>,
        Option<&ReadbackParticles>,
    )>,
    colliders: Query<(Entity, &TissueCollider, &GlobalTransform, Option<&LastPose>)>,
    forces: Query<(), With<ColliderForce>>,
    mut errors: MessageWriter<SoftBodyError>,
    render: (Option<Res<RenderDevice>>, Option<Res<RenderQueue>>),
    mut diagnostics: Diagnostics,
) {
    let mut cpu: Vec<(Entity, &BuiltBody)> = Vec::new();
    let mut all_cpu = true;
    for (entity, built, _, marker, _) in &bodies {
        if runs_on_cpu(&built.model, &settings) {
            cpu.push((entity, built));
        } else {
            all_cpu = false;
            if marker.is_some() {
                commands.entity(entity).remove::<CpuBody>();
            }
        }
    }
    cpu.sort_by_key(|b| b.0.index_u32());
    let core = settings.to_core_cpu();
    let keys: Vec<(Entity, u64)> = cpu.iter().map(|(e, b)| (*e, b.generation)).collect();
    // Whether the particles may differ from what the meshes show (a rebuild or a step).
    let mut dirty = clock.steps_this_frame > 0;
    // Whether every mesh is written whatever its body moved (the bodies were remade).
    let mut remade = false;
    let same_bodies = world.holds_exactly(&keys);
    let in_place = same_bodies
        && world.settings.as_ref() != Some(&core)
        && world.apply_in_place(&core, render.1.as_deref());
    if !in_place && (!same_bodies || world.settings.as_ref() != Some(&core)) {
        dirty = true;
        remade = true;
        // Bodies gone are retired in place, and bodies new or rebuilt made into a batch
        // on a worker thread, where the batch steps on the GPU and the settings are the
        // same; anything else makes the batch again now.
        let same = world.settings.as_ref() == Some(&core);
        let retired = same
            && render
                .1
                .as_ref()
                .is_some_and(|queue| world.retire_gone(&keys, queue));
        let now = !retired
            || (!world.holds_exactly(&keys)
                && !matches!(&render, (Some(device), Some(queue))
                    if world.append_new(&cpu, device, queue))
                && !world.rebuild_soon(&cpu, &core, render.0.as_deref()));
        if now && let Err(e) = world.rebuild(&cpu, core) {
            let error = e.to_string();
            warn!("bevy_tissue: the CPU bodies cannot be simulated: {error}");
            for (entity, _) in &cpu {
                errors.write(SoftBodyError {
                    entity: *entity,
                    error: error.clone(),
                });
            }
            *world = CpuWorld::default();
            return;
        }
        mark_bodies(&mut commands, &world, &cpu, |e| {
            bodies.get(e).ok().and_then(|b| b.3.cloned())
        });
    }
    if cpu.is_empty() {
        return;
    }
    let mut cols = scene_colliders(
        &colliders,
        clock.frame_seconds(settings.dt, time.delta_secs()),
    );
    // A grasper captures in the CPU steps right after it closed (whether it closed
    // before or after this system in the frame), then holds.
    for (entity, c) in &mut cols {
        if let ColliderShape::Grasper { mode, .. } = &mut c.shape {
            let seen = world.captured.contains(entity);
            match mode {
                GraspMode::Open => world.captured.retain(|e| e != entity),
                _ if seen => *mode = GraspMode::Hold,
                _ => {}
            }
        }
    }
    let control = Control {
        colliders: cols.iter().map(|c| c.1).collect(),
    };
    if clock.steps_this_frame > 0 {
        for (entity, c) in &cols {
            if matches!(c.shape, ColliderShape::Grasper { mode, .. } if mode != GraspMode::Open)
                && !world.captured.contains(entity)
            {
                world.captured.push(*entity);
            }
        }
    }
    let mut force = vec![Vec3::ZERO; cols.len()];
    let w = &mut *world;
    let mut diverged = None;
    let step_start = Instant::now();
    // Lattice bodies step on the GPU where they can; the CPU's solver steps the rest.
    let on_gpu = match (&render.0, &render.1) {
        (Some(device), Some(queue))
            if settings.backend == TissueBackend::Auto && clock.steps_this_frame > 0 =>
        {
            w.step_gpu((device, queue), &control, clock.steps_this_frame)
        }
        _ => None,
    };
    if clock.steps_this_frame > 0 {
        w.last_on_gpu = on_gpu.is_some();
    }
    match on_gpu {
        Some(Ok(f)) => force = f,
        Some(Err(e)) => diverged = Some(e),
        None => {
            // Retired bodies are held only on the GPU: the CPU steps a batch without them.
            if clock.steps_this_frame > 0
                && (w.retired.contains(&true) || w.solver_stale)
                && let Some(settings) = w.settings.clone()
            {
                if w.rebuild(&cpu, settings).is_err() {
                    return;
                }
                dirty = true;
                remade = true;
                mark_bodies(&mut commands, w, &cpu, |e| {
                    bodies.get(e).ok().and_then(|b| b.3.cloned())
                });
            }
            let (Some(solver), Some(state)) = (w.solver.as_mut(), w.state.as_mut()) else {
                return;
            };
            for _ in 0..clock.steps_this_frame {
                match solver.step(&w.model, state, &control) {
                    Ok(stats) => {
                        for (f, s) in force.iter_mut().zip(&stats.collider_forces) {
                            *f = *s;
                        }
                    }
                    Err(e) => {
                        diverged = Some(e);
                        break;
                    }
                }
            }
            if clock.steps_this_frame > 0
                && let Some(g) = w.gpu.as_mut()
            {
                g.synced = false;
            }
        }
    }
    if clock.steps_this_frame > 0 {
        let contacts = w.contacts_ms.take().filter(|_| w.last_on_gpu);
        let step = ms_since(step_start) - contacts.unwrap_or(0.0);
        diagnostics.add_measurement(&TissueDiagnostics::STEP, || step);
        if let Some(ms) = contacts {
            diagnostics.add_measurement(&TissueDiagnostics::CONTACTS, || ms);
        }
    }
    if let Some(e) = diverged {
        let body = match &e {
            TissueError::Diverged { body, .. } => *body,
            _ => 0,
        };
        if let Some(&(entity, _)) = w.keys.get(body) {
            let error = format!("{e}; the body was put back at rest");
            warn!("soft body {entity}: {error}");
            errors.write(SoftBodyError { entity, error });
        }
        w.reset_body(body);
    }
    if all_cpu && clock.steps_this_frame > 0 {
        for ((entity, _), f) in cols.iter().zip(&force) {
            if forces.contains(*entity) {
                commands.entity(*entity).insert(ColliderForce(*f));
            }
        }
    }
    // The particles as the meshes last showed them: a body that moved less than
    // `SKIN_STILL` of its spacing since is not skinned and written again.
    let mut shown = std::mem::take(&mut w.shown);
    let Some(state) = w.state.as_ref() else {
        return;
    };
    if shown.len() != state.x.len() {
        shown = state.x.clone();
        remade = true;
    }
    // Meshes are written only where something changed: a paused world re-uploads nothing.
    let moved = cpu
        .iter()
        .any(|(e, _)| bodies.get(*e).is_ok_and(|b| b.2.is_changed()));
    let skin_start = Instant::now();
    // The bodies whose meshes may be written this frame.
    let mut jobs: Vec<SkinJob> = Vec::new();
    for (entity, built) in &cpu {
        let Ok((_, _, to_world, _, readback)) = bodies.get(*entity) else {
            continue;
        };
        let Some(i) = w.index_of(*entity) else {
            continue;
        };
        if let Some(r) = readback {
            let mut e = commands.entity(*entity);
            e.insert(ParticlePositions {
                positions: state.x[w.ranges[i].0.clone()].to_vec(),
                step: clock.steps,
            });
            if !r.continuous {
                e.remove::<ReadbackParticles>();
            }
        }
        if dirty || to_world.is_changed() {
            jobs.push(SkinJob {
                entity: *entity,
                index: i,
                to_world: to_world.affine(),
                mesh: built.draw_mesh.clone(),
                write: remade || to_world.is_changed(),
                out: None,
            });
        }
    }
    let threads = w.settings.as_ref().map_or(0, |s| s.threads);
    let (model, ranges) = (&w.model, &w.ranges);
    // Which of them moved enough to be seen, then (only if any did) the deformation
    // gradients, then their skinning: on all cores.
    crate::core::par::for_chunks_mut(&mut jobs, 1, threads, |_, chunk| {
        for job in chunk.iter_mut().filter(|j| !j.write) {
            let p = ranges[job.index].0.clone();
            let still = SKIN_STILL * model.bodies.get(job.index).map_or(0.0, |b| b.spacing);
            job.write = state.x[p.clone()]
                .iter()
                .zip(&shown[p])
                .any(|(x, s)| x.distance_squared(*s) > still * still);
        }
    });
    let f = if jobs.iter().any(|j| j.write) {
        Solver::deformation_gradients(model, &state.x)
    } else {
        Vec::new()
    };
    crate::core::par::for_chunks_mut(&mut jobs, 1, threads, |_, chunk| {
        let mut scratch = (Vec::new(), Vec::new());
        for job in chunk.iter_mut().filter(|j| j.write) {
            let particles = ranges[job.index].0.clone();
            job.out = skin_body(
                model,
                job.index,
                particles,
                state,
                &f,
                &mut scratch,
                &job.to_world,
            );
        }
    });
    for job in jobs {
        let Some(out) = job.out else {
            continue;
        };
        if let Some(mut m) = meshes.get_mut(&job.mesh)
            && m.count_vertices() == out.positions.len()
        {
            m.insert_attribute(
                Mesh::ATTRIBUTE_POSITION,
                VertexAttributeValues::Float32x3(out.positions),
            );
            m.insert_attribute(
                Mesh::ATTRIBUTE_NORMAL,
                VertexAttributeValues::Float32x3(out.normals),
            );
            let p = ranges[job.index].0.clone();
            shown[p.clone()].copy_from_slice(&state.x[p]);
        }
        if let Some((lo, hi)) = out.bounds {
            commands
                .entity(job.entity)
                .insert(Aabb::from_min_max(lo, hi));
        }
    }
    w.shown = shown;
    if dirty || moved {
        let ms = ms_since(skin_start);
        diagnostics.add_measurement(&TissueDiagnostics::SKIN, || ms);
    }
}

/// Gives each of `cpu`'s bodies its [`CpuBody`] marker (its index and particles in
/// `world`), where `current` (its marker now) differs.
fn mark_bodies(
    commands: &mut Commands,
    world: &CpuWorld,
    cpu: &[(Entity, &BuiltBody)],
    current: impl Fn(Entity) -> Option<CpuBody>,
) {
    for (entity, _) in cpu {
        let Some(i) = world.index_of(*entity) else {
            continue;
        };
        let marker = CpuBody {
            index: i,
            particles: world.ranges[i].0.clone(),
        };
        if current(*entity).as_ref() != Some(&marker) {
            commands.entity(*entity).insert(marker);
        }
    }
}

/// How far (in its particle spacing) a body's particles must have moved since its mesh
/// was last written for the mesh to be skinned and written again: a body lying still
/// costs no skinning and no mesh upload, and its particles are never further than this
/// from where its mesh shows them.
pub const SKIN_STILL: f32 = 1.0e-3;

/// A body whose mesh may be written this frame: what to skin, and the result.
struct SkinJob {
    entity: Entity,
    /// The body's index in the batched model.
    index: usize,
    /// The entity's world-from-local transform.
    to_world: Affine3A,
    mesh: Handle<Mesh>,
    /// Skin and write it (it moved enough to be seen, or must be written anyway).
    write: bool,
    out: Option<SkinnedMesh>,
}

/// A body's skinned render surface in its entity's frame.
struct SkinnedMesh {
    positions: Vec<[f32; 3]>,
    normals: Vec<[f32; 3]>,
    /// The entity-local box of its particles, grown by the skin's reach past them (m).
    bounds: Option<(Vec3, Vec3)>,
}

/// Skins body `index`'s render surface on the CPU (particle positions and deformation
/// gradients `f` of the whole batch; `particles`: the body's) into its entity's frame
/// (`to_world`: world from local), with `scratch` for the world-frame positions and
/// normals. `None` for an index outside the model.
fn skin_body(
    model: &Model,
    index: usize,
    particles: Range<usize>,
    state: &State,
    f: &[Mat3],
    scratch: &mut (Vec<Vec3>, Vec<Vec3>),
    to_world: &Affine3A,
) -> Option<SkinnedMesh> {
    let info = model.bodies.get(index)?;
    let (positions, normals) = scratch;
    let vertices = info.skin.rest_vertices.len();
    positions.resize(vertices, Vec3::ZERO);
    normals.resize(vertices, Vec3::Y);
    skin_positions(&info.skin, &state.x, &model.rest, f, positions);
    skin_normals(&info.skin, positions, normals);
    let to_local = to_world.inverse();
    // Normals go back by the transpose of the entity's linear part (the inverse
    // transpose of world-from-local's inverse).
    let normal_to_local = to_world.matrix3.transpose();
    let bounds = crate::core::mesh::bounds_of(state.x.get(particles)?).map(|(lo, hi)| {
        let m = Vec3::splat(3.0 * info.spacing);
        transform_box(&to_local, lo - m, hi + m)
    });
    Some(SkinnedMesh {
        positions: positions
            .iter()
            .map(|p| to_local.transform_point3(*p).to_array())
            .collect(),
        normals: normals
            .iter()
            .map(|n| (normal_to_local * *n).normalize_or_zero().to_array())
            .collect(),
        bounds,
    })
}
