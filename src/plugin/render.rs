//! The render-world side: extraction of bodies, colliders and the clock; the batched
//! [`GpuWorld`] kept in step with the scene's bodies; the render-graph system that
//! records the frame's steps and the draw path; async readback.

use super::build::BuiltBody;
use super::components::*;
use crate::core::TissueError;
use crate::core::colliders::{Collider, ColliderShape, GraspMode};
use crate::core::model::Model;
use crate::gpu::buffers::GpuDrawBody;
use crate::gpu::{GpuWorld, Kernels, PassRecorder};
use bevy::camera::primitives::Aabb;
use bevy::prelude::*;
use bevy::render::Extract;
use bevy::render::diagnostic::{DiagnosticsRecorder, RecordDiagnostics};
use bevy::render::mesh::allocator::MeshAllocator;
use bevy::render::render_resource::{Buffer, BufferDescriptor, BufferUsages, ComputePass, MapMode};
use bevy::render::renderer::{RenderContext, RenderDevice, RenderQueue};
use std::sync::{Arc, Mutex, mpsc};

/// One body as the render world sees it.
#[derive(Clone)]
pub struct ExtractedBody {
    /// The entity.
    pub entity: Entity,
    /// Its model.
    pub model: Arc<Model>,
    /// Rebuild counter.
    pub generation: u64,
    /// The draw mesh.
    pub mesh: AssetId<Mesh>,
    /// The entity's world transform now.
    pub to_world: GlobalTransform,
    /// Positions requested this frame.
    pub readback: bool,
    /// This generation starts from rest ([`ResetSoftBody`]).
    pub reset: bool,
    /// The body sleeps ([`super::sleep::Sleeping`]): the GPU skips it.
    pub asleep: bool,
}

/// What the main world hands the render world each frame.
#[derive(Resource, Default, Clone)]
pub struct ExtractedTissue {
    /// Ready bodies, in a stable order (spawn order: entity index).
    pub bodies: Vec<ExtractedBody>,
    /// Colliders, and whether each wants its force read back.
    pub colliders: Vec<(Entity, Collider, bool)>,
    /// Settings.
    pub settings: TissueSettings,
    /// Steps to take this frame.
    pub steps: u32,
}

/// Readback results travelling from the render world to the main world.
pub enum ReadbackResult {
    /// Particle positions of a body.
    Positions(Entity, Vec<Vec3>, u64),
    /// A collider's force, N.
    Force(Entity, Vec3),
    /// A GPU-side error for a body.
    Error(Entity, String),
    /// A body's particle bounds (world frame, m), for culling, whether any of its
    /// particles diverged (and was held), and its fastest particle's speed (m/s).
    Bounds(Entity, Vec3, Vec3, bool, f32),
    /// The adapter cannot run the simulation's kernels (why): the main world moves every
    /// body to the CPU ([`TissueBackend::Cpu`]).
    GpuUnavailable(String),
}

/// What a readback item is.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Item {
    Positions,
    Force,
    Bounds,
}

/// The channel's receiving end (main world).
#[derive(Resource)]
pub struct ReadbackReceiver(pub Mutex<mpsc::Receiver<ReadbackResult>>);

/// The channel's sending end (render world).
#[derive(Resource, Clone)]
pub struct ReadbackSender(pub mpsc::Sender<ReadbackResult>);

/// Host ↔ GPU traffic of the last frame.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FrameTraffic {
    /// Bytes written from the host (settings, colliders, draw records).
    pub uploaded_bytes: u64,
    /// Bytes copied for readback (only what was asked for).
    pub readback_bytes: u64,
    /// Bytes of per-body bounds copied for culling (32 per body).
    pub bounds_bytes: u64,
    /// Steps recorded (0 when every body sleeps).
    pub steps: u32,
}

/// The render world's simulation state.
#[derive(Resource, Default)]
pub struct TissueGpu {
    traffic: FrameTraffic,
    kernels: Option<Result<Kernels, String>>,
    world: Option<GpuWorld>,
    /// Extracted bodies (entity, generation) the world was last built for.
    keys: Vec<(Entity, u64)>,
    /// The bodies in the world, in its order (some extracted ones may not fit).
    world_keys: Vec<(Entity, u64)>,
    warned_colliders: bool,
    /// The world's bodies in its order; `None` for a retired one (despawned since the
    /// world was built, still holding its place in the arrays).
    bodies: Vec<Option<ExtractedBody>>,
    settings: Option<TissueSettings>,
    steps: u32,
    colliders: Vec<(Entity, Collider, bool)>,
    /// The collider entities of the last frame, in order (grabs name graspers by index).
    collider_entities: Vec<Entity>,
    pending: Vec<Pending>,
    /// Vertex-slab bind groups of the current world, by slab buffer (slabs can move:
    /// a new buffer gets a new group, groups of slabs no longer used are dropped).
    slab_groups: Vec<(
        bevy::render::render_resource::BufferId,
        crate::gpu::world::SlabGroup,
    )>,
    /// Mapped-and-read staging buffers, reused by later readbacks.
    staging: Arc<Mutex<Vec<Buffer>>>,
    /// Readbacks mapped but not delivered yet.
    in_flight: Arc<std::sync::atomic::AtomicUsize>,
    warned_in_flight: bool,
    /// Times the world was rebuilt.
    rebuilds: u64,
}

/// Frames of readbacks outstanding at which the render world waits for the GPU (frame
/// pacing where no swapchain does it, see [`map_readbacks`]).
const MAX_FRAMES_BEHIND: usize = 3;

/// Readbacks in flight beyond which a frame issues none (a driver that delivers them late
/// must not make the staging buffers pile up).
const MAX_READBACKS_IN_FLIGHT: usize = 16;

impl TissueGpu {
    /// Host ↔ GPU traffic of the last frame.
    pub fn stats(&self) -> FrameTraffic {
        self.traffic
    }

    /// The batched GPU world, once bodies exist.
    pub fn world(&self) -> Option<&GpuWorld> {
        self.world.as_ref()
    }

    /// How many times the world was made again: its room ran out, retired bodies came to
    /// hold a quarter of its particles (compaction), or a settings change reached its
    /// structure (particle contacts, contact neighbours). Bodies spawned, despawned or
    /// rebuilt change it in place, and per-step settings (gravity, damping, dt,
    /// iterations, ...) go to its parameters.
    pub fn rebuilds(&self) -> u64 {
        self.rebuilds
    }
}

struct Pending {
    buffer: Buffer,
    items: Vec<(Entity, u64, u64, Item)>, // entity, byte offset in staging, bytes, kind
    step: u64,
}

/// Main-world clock: how many steps this frame takes.
pub fn advance_clock(
    time: Res<Time>,
    settings: Res<TissueSettings>,
    mut clock: ResMut<TissueClock>,
) {
    let mut steps = 0;
    if let Some(n) = clock.fixed_steps_per_frame {
        if !clock.paused {
            steps = n;
        }
    } else if !clock.paused && settings.dt > 0.0 {
        clock.accumulator += time.delta_secs();
        let due = (clock.accumulator / settings.dt).floor() as u32;
        steps = due.min(settings.max_steps_per_frame);
        clock.accumulator -= due as f32 * settings.dt;
    }
    steps += std::mem::take(&mut clock.pending_steps);
    clock.steps_this_frame = steps;
    clock.steps += steps as u64;
}

/// Tracks collider velocities from their motion between frames.
#[derive(Component, Default)]
pub struct LastPose(pub Option<Vec3>);

/// Copies what the GPU needs into the render world.
#[allow(clippy::type_complexity)]
pub fn extract_tissue(
    mut commands: Commands,
    bodies: Extract<
        Query<(
            Entity,
            &BuiltBody,
            &GlobalTransform,
            Option<&ReadbackParticles>,
            Has<super::sleep::Sleeping>,
        )>,
    >,
    colliders: Extract<
        Query<(
            Entity,
            &TissueCollider,
            &GlobalTransform,
            Option<&LastPose>,
            Option<&ColliderForce>,
            Option<&GraspLatch>,
        )>,
    >,
    settings: Extract<Res<TissueSettings>>,
    clock: Extract<Res<TissueClock>>,
    time: Extract<Res<Time>>,
) {
    // Bodies the CPU steps (`super::cpu`) are not the GPU's.
    let mut list: Vec<ExtractedBody> = bodies
        .iter()
        .filter(|(_, b, ..)| !super::cpu::runs_on_cpu(&b.model, &settings))
        .map(|(e, b, t, r, asleep)| ExtractedBody {
            entity: e,
            model: b.model.clone(),
            generation: b.generation,
            mesh: b.draw_mesh.id(),
            to_world: *t,
            readback: r.is_some(),
            reset: b.reset,
            asleep,
        })
        .collect();
    list.sort_by_key(|b| b.entity.index_u32());
    let dt = clock.frame_seconds(settings.dt, time.delta_secs());
    let mut cols: Vec<(Entity, Collider, bool)> = colliders
        .iter()
        .map(|(e, c, t, last, force, latch)| {
            (e, core_collider(c, t, last, latch, dt), force.is_some())
        })
        .collect();
    // Spawn order (entity index), stable: colliders act in sequence within a projection
    // pass, and the first MAX_COLLIDERS are the ones kept.
    cols.sort_by_key(|c| c.0.index_u32());
    commands.insert_resource(ExtractedTissue {
        bodies: list,
        colliders: cols,
        settings: settings.clone(),
        steps: clock.steps_this_frame,
    });
}

/// A scene collider as the core sees it: its pose, its velocity from its motion over
/// the last frame (`dt`, s), and a grasper that has had its capture steps holding
/// instead of capturing.
pub fn core_collider(
    c: &TissueCollider,
    t: &GlobalTransform,
    last: Option<&LastPose>,
    latch: Option<&GraspLatch>,
    dt: f32,
) -> Collider {
    let pos = t.translation();
    let vel = last
        .and_then(|l| l.0)
        .map_or(Vec3::ZERO, |p| (pos - p) / dt);
    let mut core = c.to_core(t, vel);
    // A grasper takes particles in the steps right after it closed, then holds.
    if let ColliderShape::Grasper { mode, .. } = &mut core.shape
        && *mode == GraspMode::Capture
        && latch.is_some_and(|l| l.0)
    {
        *mode = GraspMode::Hold;
    }
    core
}

/// Whether a closed grasper has had its capture steps (it then only holds).
#[derive(Component, Default)]
pub struct GraspLatch(pub bool);

/// At the start of a frame: a closed grasper whose capture went out with last frame's
/// steps now only holds; an open one is ready to capture again.
pub fn latch_graspers(clock: Res<TissueClock>, mut q: Query<(&TissueCollider, &mut GraspLatch)>) {
    for (c, mut latch) in &mut q {
        let closed = matches!(c.kind, ColliderKind::Grasper { closed: true, .. });
        let captured = closed && (latch.0 || clock.steps_this_frame > 0);
        if latch.0 != captured {
            latch.0 = captured;
        }
    }
}

/// Records collider positions for the next frame's velocity.
pub fn remember_collider_poses(mut q: Query<(&GlobalTransform, &mut LastPose)>) {
    for (t, mut last) in &mut q {
        last.0 = Some(t.translation());
    }
}

/// Keeps the GPU world in step with the extracted bodies: changes it in place when
/// bodies come, go or are rebuilt (appended into its room, retired, replaced), and makes
/// it again (keeping the state of surviving bodies, with room) when that cannot be done;
/// updates colliders and params.
pub fn prepare_tissue(
    mut gpu: ResMut<TissueGpu>,
    extracted: Option<Res<ExtractedTissue>>,
    device: Res<RenderDevice>,
    queue: Res<RenderQueue>,
    sender: Res<ReadbackSender>,
) {
    let Some(ex) = extracted else { return };
    gpu.traffic = FrameTraffic::default();
    // The kernels are made for the first body the render graph steps (lattice bodies step
    // from the main world with kernels of their own, which fit WebGPU's limits): an
    // adapter that cannot run these switches the world to the CPU only once it has to.
    if gpu.kernels.is_none() && !ex.bodies.is_empty() {
        gpu.kernels = Some(Kernels::new(&device).map_err(|e| e.to_string()));
        if let Some(Err(e)) = &gpu.kernels {
            let _ = sender.0.send(ReadbackResult::GpuUnavailable(e.clone()));
        }
    }
    let Some(Ok(_)) = &gpu.kernels else { return };
    let keys: Vec<(Entity, u64)> = ex.bodies.iter().map(|b| (b.entity, b.generation)).collect();
    let settings_changed = gpu.settings.as_ref() != Some(&ex.settings);
    // Per-step settings (gravity, damping, dt, iterations, ...) go to the parameters; a
    // change of the world's structure rebuilds it.
    let in_place = keys == gpu.keys
        && settings_changed
        && gpu.world.as_mut().is_some_and(|w| {
            w.set_settings(&queue, ex.settings.to_core())
                .unwrap_or(false)
        });
    if in_place {
        gpu.settings = Some(ex.settings.clone());
    } else if keys != gpu.keys || settings_changed {
        // Bodies that went away are retired in place, rebuilt ones replaced and new ones
        // appended; no room left (or too much retired) rebuilds the world.
        if settings_changed || !edit_in_place(&mut gpu, &ex, &keys, &device, &queue, &sender) {
            rebuild(&mut gpu, &ex, &device, &queue, &sender, keys);
        }
    }
    // The bodies in the world's order (a body left out by a rebuild, or retired, is
    // neither stepped nor drawn).
    gpu.bodies = gpu
        .world_keys
        .iter()
        .map(|k| ex.bodies.iter().find(|b| b.entity == k.0).cloned())
        .collect();
    gpu.steps = ex.steps;
    // At most MAX_COLLIDERS colliders act (the first spawned); the rest are ignored,
    // with one warning.
    let max = crate::gpu::buffers::MAX_COLLIDERS;
    if ex.colliders.len() > max && !gpu.warned_colliders {
        warn!(
            "bevy_tissue: {} colliders, only the first {max} act on soft bodies",
            ex.colliders.len()
        );
        gpu.warned_colliders = true;
    }
    gpu.colliders = ex.colliders.iter().take(max).cloned().collect();
    let cols: Vec<Collider> = gpu.colliders.iter().map(|c| c.1).collect();
    // Grabs name their grasper by index: if a collider before another moved, let go.
    let entities: Vec<Entity> = gpu.colliders.iter().map(|c| c.0).collect();
    let same = gpu
        .collider_entities
        .iter()
        .zip(&entities)
        .all(|(a, b)| a == b);
    if !same && let Some(world) = gpu.world.as_ref() {
        world.release_grabs(&queue);
    }
    gpu.collider_entities = entities;
    if let Some(world) = gpu.world.as_mut() {
        if let Err(e) = world.set_colliders(&queue, &cols) {
            warn!("bevy_tissue: {e}");
        }
        world.write_params(&queue);
        gpu.traffic.uploaded_bytes += (size_of::<crate::gpu::buffers::GpuParams>()
            + cols.len() * size_of::<crate::gpu::buffers::GpuCollider>())
            as u64;
    }
}

/// Room a rebuilt world leaves for bodies spawned later: half as much again as its
/// bodies need, and at least one more of its largest.
const ROOM: f32 = 1.5;

/// Where `keys` are the world's bodies less some, plus some, and some rebuilt, changes
/// the world in place instead of rebuilding it: retires the ones that went
/// ([`GpuWorld::retire`]), replaces a rebuilt one's model where it has as many
/// particles (a new material or stiffness: [`GpuWorld::replace_body`], keeping its
/// pose unless it was reset) or else retires it and appends it anew, and appends the new
/// ones ([`GpuWorld::append_or_grow`]: into the room, grown on the GPU where it is too
/// small); every other body keeps its state. Returns false (the caller rebuilds, which
/// compacts) where retired bodies would then hold more than a quarter of its particles.
/// A new body too big for the adapter is reported and left out, as in a rebuild.
fn edit_in_place(
    gpu: &mut TissueGpu,
    ex: &ExtractedTissue,
    keys: &[(Entity, u64)],
    device: &RenderDevice,
    queue: &RenderQueue,
    sender: &ReadbackSender,
) -> bool {
    let TissueGpu {
        world: Some(world),
        world_keys,
        kernels: Some(Ok(kernels)),
        slab_groups,
        ..
    } = gpu
    else {
        return false;
    };
    // Rebuilt bodies (same entity, new generation) in place where their sizes allow;
    // the others are appended anew with the new bodies, and their old slots retired.
    let mut moved = Vec::new();
    for b in &ex.bodies {
        let Some(i) = world_keys
            .iter()
            .position(|k| k.0 == b.entity && k.1 != b.generation)
        else {
            continue;
        };
        let state = b.reset.then(|| crate::core::solver::State::new(&b.model));
        match world.replace_body(device, queue, i, &b.model, state.as_ref()) {
            Ok(true) => world_keys[i].1 = b.generation,
            Ok(false) => moved.push((i, b)),
            Err(e) => {
                warn!("bevy_tissue: {e}");
                return false;
            }
        }
    }
    let new: Vec<&ExtractedBody> = ex
        .bodies
        .iter()
        .filter(|b| !world_keys.contains(&(b.entity, b.generation)))
        .collect();
    // Check the new bodies before changing anything (no room: rebuild).
    let solver = ex.settings.to_core();
    let fitting = that_fit(new, device, &solver, sender);
    let mut model = Model::new();
    for b in &fitting {
        model.append(&b.model);
    }
    let added: Vec<(Entity, u64)> = fitting.iter().map(|b| (b.entity, b.generation)).collect();
    if !added.is_empty() {
        // Into the room; where it is too small the room grows on the GPU first.
        let state = crate::core::solver::State::new(&model);
        let room = world.capacity();
        let appended = world.append_or_grow(device, queue, kernels, &model, &state, ROOM);
        if world.capacity() != room {
            // New buffers: the slabs' bind groups are made again.
            slab_groups.clear();
        }
        match appended {
            Ok(true) => world_keys.extend(added),
            Ok(false) => return false,
            Err(e) => {
                warn!("bevy_tissue: {e}");
                return false;
            }
        }
    }
    // A rebuilt body appended anew keeps its pose where its particles are the same
    // points (same count, not reset), as in a rebuild of the world.
    for (old, b) in moved {
        let Some(new) = world_keys
            .iter()
            .position(|k| *k == (b.entity, b.generation))
        else {
            continue;
        };
        if !b.reset && world.ranges[old].count == world.ranges[new].count {
            world.copy_body_state(device, queue, old, new);
        }
        // The old slot no longer stands for the entity.
        world_keys[old] = (Entity::PLACEHOLDER, u64::MAX);
    }
    let mut retired = 0;
    for (i, k) in world_keys.iter().enumerate() {
        if !keys.contains(k) {
            match world.retire(queue, i) {
                Some(n) => retired = n,
                None => return false,
            }
        }
    }
    if retired as u64 * 4 > world.particle_count() as u64 {
        return false;
    }
    gpu.keys = keys.to_vec();
    true
}

/// The `bodies` the adapter can hold on their own; each other one is reported (and left
/// out).
fn that_fit<'a>(
    bodies: impl IntoIterator<Item = &'a ExtractedBody>,
    device: &RenderDevice,
    solver: &crate::core::solver::SolverSettings,
    sender: &ReadbackSender,
) -> Vec<&'a ExtractedBody> {
    let limits = device.limits();
    bodies
        .into_iter()
        .filter(
            |b| match GpuWorld::check_limits(&limits, &b.model, solver) {
                Ok(()) => true,
                Err(e) => {
                    let _ = sender
                        .0
                        .send(ReadbackResult::Error(b.entity, e.to_string()));
                    false
                }
            },
        )
        .collect()
}

fn rebuild(
    gpu: &mut TissueGpu,
    ex: &ExtractedTissue,
    device: &RenderDevice,
    queue: &RenderQueue,
    sender: &ReadbackSender,
    keys: Vec<(Entity, u64)>,
) {
    let old_keys = std::mem::take(&mut gpu.world_keys);
    let old_world = gpu.world.take();
    gpu.rebuilds += 1;
    gpu.settings = Some(ex.settings.clone());
    gpu.keys = keys;
    if ex.bodies.is_empty() {
        return;
    }
    // A body too big for the adapter on its own is reported and left out.
    let solver = ex.settings.to_core();
    let fits = that_fit(ex.bodies.iter(), device, &solver, sender);
    let mut model = Model::new();
    for b in &fits {
        model.append(&b.model);
    }
    if fits.is_empty() {
        return;
    }
    let new_keys: Vec<(Entity, u64)> = fits.iter().map(|b| (b.entity, b.generation)).collect();
    let state = crate::core::solver::State::new(&model);
    let Some(Ok(kernels)) = &gpu.kernels else {
        return;
    };
    // Room for bodies spawned later; where the adapter cannot bind that much, none.
    let made = match GpuWorld::with_room(device, kernels, &model, &state, solver.clone(), 0, ROOM) {
        Err(TissueError::GpuLimit { .. }) => {
            GpuWorld::new(device, kernels, &model, &state, solver, 0)
        }
        other => other,
    };
    match made {
        Ok(world) => {
            // Keep the pose of bodies that were already simulated: unchanged ones, and
            // rebuilt ones with the same particles (a new K or material resamples
            // nothing, so particle i is the same point of the body).
            if let Some(old) = &old_world {
                let mut enc = device.create_command_encoder(&Default::default());
                for (i, key) in new_keys.iter().enumerate() {
                    let Some(j) = old_keys.iter().position(|k| k.0 == key.0) else {
                        continue;
                    };
                    if fits[i].reset && old_keys[j].1 != key.1 {
                        continue; // reset to rest
                    }
                    let (from, to) = (old.ranges[j], world.ranges[i]);
                    if from.count == to.count {
                        world.copy_state_from(&mut enc, old, from.first, to.first, to.count);
                    }
                }
                queue.submit([enc.finish()]);
            }
            gpu.world = Some(world);
            gpu.world_keys = new_keys;
            gpu.slab_groups.clear();
        }
        Err(e) => {
            // The whole batch does not fit: report every body, simulate none.
            error!("bevy_tissue: {e}");
            for b in &fits {
                let _ = sender
                    .0
                    .send(ReadbackResult::Error(b.entity, e.to_string()));
            }
        }
    }
}

/// Bevy's render-diagnostic spans (`RenderDiagnosticsPlugin`): one span `tissue` around
/// all of the frame's tissue work (`render/tissue/elapsed_gpu`: every dispatch), and
/// inside it the first dispatch of each kernel (`render/tissue/<kernel>/…`), so that
/// every pass is reported while the frame's ~35 dispatches per step leave Bevy's 256
/// timestamp queries to its own passes.
struct Spans<'a> {
    recorder: Option<&'a DiagnosticsRecorder>,
    seen: Vec<&'static str>,
    open: bool,
}

impl PassRecorder for Spans<'_> {
    fn begin(&mut self, pass: &mut ComputePass<'_>, name: &'static str) {
        self.open = false;
        if let Some(r) = self.recorder
            && !self.seen.contains(&name)
        {
            self.seen.push(name);
            // Inside the `tissue` span: `tissue/clusters` is reported as
            // `render/tissue/clusters`.
            r.begin_pass_span(pass, name.strip_prefix("tissue/").unwrap_or(name).into());
            self.open = true;
        }
    }
    fn end(&mut self, pass: &mut ComputePass<'_>) {
        if let Some(r) = self.recorder
            && self.open
        {
            r.end_pass_span(pass);
            self.open = false;
        }
    }
}

/// The render-graph work of a frame: the frame's steps, then each body's surface
/// skinned straight into its mesh's vertex slab, then the readback copies.
pub fn run_tissue(
    mut ctx: RenderContext,
    mut gpu: ResMut<TissueGpu>,
    allocator: Res<MeshAllocator>,
    queue: Res<RenderQueue>,
) {
    let gpu = &mut *gpu;
    let (Some(Ok(kernels)), Some(world)) = (&gpu.kernels, gpu.world.as_mut()) else {
        return;
    };
    let device = ctx.render_device().clone();
    let recorder = ctx.diagnostic_recorder();
    let recorder = recorder.as_deref();
    // Sleeping bodies are skipped by the kernels; when all sleep, no step is recorded.
    world.set_asleep(
        &queue,
        gpu.bodies
            .iter()
            .map(|b| b.as_ref().is_none_or(|b| b.asleep)),
    );
    let steps = if world.all_asleep() { 0 } else { gpu.steps };
    gpu.traffic.steps = steps;
    // Draw records: where each body's vertices are in the allocator's slabs (slabs can
    // move, so this is looked up every frame).
    let mut draws = Vec::with_capacity(gpu.bodies.len());
    let mut slabs: Vec<(Buffer, Vec<(u32, u32)>)> = Vec::new();
    for (b, r) in gpu.bodies.iter().zip(&world.ranges) {
        let Some(b) = b else {
            draws.push(GpuDrawBody::default());
            continue;
        };
        let slice = allocator.mesh_vertex_slice(&b.mesh);
        let Some(slice) = slice.filter(|s| s.range.len() as u32 == r.vcount) else {
            draws.push(GpuDrawBody::default());
            continue;
        };
        draws.push(GpuDrawBody::new(
            b.to_world.affine(),
            slice.range.start * 8,
            r.vfirst,
            8,
        ));
        let run = (r.vfirst, r.vfirst + r.vcount);
        match slabs
            .iter_mut()
            .find(|(buf, _)| buf.id() == slice.buffer.id())
        {
            Some((_, runs)) => match runs.last_mut() {
                Some(last) if last.1 == run.0 => last.1 = run.1,
                _ => runs.push(run),
            },
            None => slabs.push((slice.buffer.clone(), vec![run])),
        }
    }
    world.set_draw(&queue, &draws);
    gpu.traffic.uploaded_bytes += (draws.len() * size_of::<GpuDrawBody>()
        + slabs.iter().map(|s| s.1.len()).sum::<usize>()
            * size_of::<crate::gpu::buffers::GpuSkinRange>())
        as u64;
    gpu.slab_groups
        .retain(|(id, _)| slabs.iter().any(|(b, _)| b.id() == *id));
    for (slab, _) in &slabs {
        if !gpu.slab_groups.iter().any(|(id, _)| *id == slab.id()) {
            let group = world.slab_group(&device, kernels, slab);
            gpu.slab_groups.push((slab.id(), group));
        }
    }
    let draw_jobs: Vec<(&crate::gpu::world::SlabGroup, &[(u32, u32)])> = slabs
        .iter()
        .filter_map(|(slab, runs)| {
            let (_, g) = gpu.slab_groups.iter().find(|(id, _)| *id == slab.id())?;
            Some((g, &runs[..]))
        })
        .collect();
    let encoder = ctx.command_encoder();
    let mut spans = Spans {
        recorder,
        seen: Vec::new(),
        open: false,
    };
    if let Some(r) = recorder {
        r.begin_time_span(encoder, "tissue".into());
    }
    world.record_steps(encoder, kernels, steps, &mut spans);
    world.record_draw(&queue, encoder, kernels, &draw_jobs, &mut spans);
    // Per-body bounds, every frame (32 bytes a body), for frustum culling.
    world.record_bounds(encoder, kernels, &mut spans);
    if let Some(r) = recorder {
        r.end_time_span(encoder);
    }
    // Readback copies.
    let mut items = Vec::new();
    for (i, b) in gpu.bodies.iter().enumerate() {
        if let Some(b) = b {
            items.push((b.entity, i as u64 * 32, 32, Item::Bounds));
        }
    }
    for (b, r) in gpu.bodies.iter().zip(&world.ranges) {
        let Some(b) = b else { continue };
        if b.readback {
            let item = (
                b.entity,
                r.first as u64 * 16,
                r.count as u64 * 16,
                Item::Positions,
            );
            items.push(item);
        }
    }
    for (k, (e, _, wants)) in gpu.colliders.iter().enumerate() {
        if *wants {
            items.push((*e, world.force_offset() + k as u64 * 16, 16, Item::Force));
        }
    }
    if items.is_empty() {
        return;
    }
    if gpu.in_flight.load(std::sync::atomic::Ordering::Relaxed) >= MAX_READBACKS_IN_FLIGHT {
        if !gpu.warned_in_flight {
            warn!(
                "bevy_tissue: {MAX_READBACKS_IN_FLIGHT} readbacks not delivered yet: readbacks \
                 (bounds, forces, positions) are skipped until they are"
            );
            gpu.warned_in_flight = true;
        }
        return;
    }
    let total: u64 = items.iter().map(|i| i.2).sum();
    gpu.traffic.readback_bytes = items
        .iter()
        .filter(|i| i.3 != Item::Bounds)
        .map(|i| i.2)
        .sum();
    gpu.traffic.bounds_bytes = total - gpu.traffic.readback_bytes;
    let reused = gpu.staging.lock().ok().and_then(|mut pool| {
        let i = pool.iter().position(|b| b.size() >= total)?;
        Some(pool.swap_remove(i))
    });
    let staging = reused.unwrap_or_else(|| {
        device.create_buffer(&BufferDescriptor {
            label: Some("tissue readback"),
            size: total,
            usage: BufferUsages::MAP_READ | BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    });
    let mut at = 0;
    let mut placed = Vec::new();
    for (e, off, len, kind) in items {
        let (src, base) = match kind {
            Item::Force => (world.forces(), 0),
            Item::Positions => (world.positions(), 0),
            Item::Bounds => world.bounds(),
        };
        encoder.copy_buffer_to_buffer(src, base + off, &staging, at, len);
        placed.push((e, at, len, kind));
        at += len;
    }
    gpu.pending.push(Pending {
        buffer: staging,
        items: placed,
        step: world.step,
    });
}

/// After the frame is submitted: poll the device (non-blocking) so finished readbacks are
/// delivered, and map this frame's readback buffers; the callbacks send the data to the
/// main world when the GPU is done.
pub fn map_readbacks(
    mut gpu: ResMut<TissueGpu>,
    sender: Res<ReadbackSender>,
    device: Res<RenderDevice>,
) {
    // Deliver the readbacks of earlier frames that the GPU has finished: without a poll
    // some drivers (NVIDIA's Vulkan, measured) run the map callbacks only when something
    // else polls the device, seconds later.
    //
    // Frame pacing: with nothing else to hold the CPU back (headless, no swapchain) it
    // runs ever further ahead of the GPU; on the H100 the per-frame bounds readback then
    // arrived tens of frames late and a mouse drag's pick timed out. When readbacks of
    // MAX_FRAMES_BEHIND frames are outstanding, poll until the oldest is delivered (not
    // until the GPU is idle: the frames behind it keep the GPU busy meanwhile), for at
    // most a second. A window's swapchain keeps the lag below that, so this only acts
    // where nothing else paces.
    let start = std::time::Instant::now();
    loop {
        if let Err(e) = device.poll(wgpu::PollType::Poll) {
            warn!("bevy_tissue: device poll failed: {e}");
            break;
        }
        let behind = gpu.in_flight.load(std::sync::atomic::Ordering::Relaxed);
        if behind < MAX_FRAMES_BEHIND || start.elapsed().as_secs_f32() > 1.0 {
            break;
        }
        std::thread::sleep(std::time::Duration::from_micros(50));
    }
    let pool = gpu.staging.clone();
    let in_flight = gpu.in_flight.clone();
    for p in gpu.pending.drain(..) {
        let tx = sender.0.clone();
        let pool = pool.clone();
        let in_flight = in_flight.clone();
        in_flight.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let buf = p.buffer.clone();
        let items = p.items;
        let step = p.step;
        p.buffer.slice(..).map_async(MapMode::Read, move |res| {
            in_flight.fetch_sub(1, std::sync::atomic::Ordering::Relaxed);
            if let Err(e) = res {
                warn!("bevy_tissue: a readback failed to map: {e}");
                return;
            }
            debug!(
                "bevy_tissue: readback of step {step}: {} items, {} bytes",
                items.len(),
                buf.size()
            );
            {
                let data = buf.slice(..).get_mapped_range();
                for (e, at, len, kind) in items {
                    let bytes = &data[at as usize..(at + len) as usize];
                    let v: &[[f32; 4]] = bytemuck::cast_slice(bytes);
                    let p: Vec<Vec3> = v.iter().map(|a| Vec3::new(a[0], a[1], a[2])).collect();
                    let msg = match kind {
                        Item::Force => ReadbackResult::Force(e, p[0]),
                        Item::Positions => ReadbackResult::Positions(e, p, step),
                        Item::Bounds => {
                            ReadbackResult::Bounds(e, p[0], p[1], v[0][3] != 0.0, v[1][3])
                        }
                    };
                    let _ = tx.send(msg);
                }
            }
            buf.unmap();
            if let Ok(mut pool) = pool.lock() {
                pool.push(buf);
            }
        });
    }
}

/// A body whose simulation diverged: how often it was put back at rest since it was
/// built, and when last (frames of [`receive_readbacks`]).
#[derive(Component, Debug, Clone, Copy)]
pub struct DivergenceReported {
    /// Recoveries (resets to rest) so far.
    pub recoveries: u32,
    /// Frame of the last report.
    pub frame: u64,
    /// Recovery was given up: the body is left held where it diverged.
    pub given_up: bool,
}

/// Times a diverged body is put back at rest before it is left held (per build).
pub const MAX_RECOVERIES: u32 = 3;
/// Frames after a recovery during which divergence flags (readbacks of the world before
/// the reset, still in flight) are ignored.
const RECOVERY_QUIET_FRAMES: u64 = 8;

/// Main world: delivers readback results to their entities. A body whose step diverged
/// (the GPU held the offending particles and flagged it) is put back at rest and
/// reported, up to [`MAX_RECOVERIES`] times per build; then it is left held, reported
/// once more. When the adapter cannot run the kernels, every body moves to the CPU
/// ([`TissueBackend::Cpu`], one warning).
#[allow(clippy::too_many_arguments)]
pub fn receive_readbacks(
    mut commands: Commands,
    rx: Res<ReadbackReceiver>,
    mut settings: ResMut<TissueSettings>,
    mut bodies: Query<(&mut BuiltBody, &GlobalTransform)>,
    reported: Query<&DivergenceReported>,
    requests: Query<&ReadbackParticles>,
    mut status: Query<&mut SoftBodyStatus>,
    mut motion: Query<&mut super::sleep::BodyMotion>,
    sleep: Res<super::sleep::TissueSleep>,
    mut errors: MessageWriter<SoftBodyError>,
    mut frame: Local<u64>,
) {
    *frame += 1;
    // Bodies already handled this frame (two frames' flags can arrive together).
    let mut handled: Vec<Entity> = Vec::new();
    let Ok(rx) = rx.0.lock() else { return };
    while let Ok(msg) = rx.try_recv() {
        match msg {
            ReadbackResult::Positions(e, positions, step) => {
                let Ok(mut ec) = commands.get_entity(e) else {
                    continue;
                };
                ec.insert(ParticlePositions { positions, step });
                if requests.get(e).is_ok_and(|r| !r.continuous) {
                    ec.remove::<ReadbackParticles>();
                }
            }
            ReadbackResult::Force(e, f) => {
                if let Ok(mut ec) = commands.get_entity(e) {
                    ec.insert(ColliderForce(f));
                }
            }
            ReadbackResult::Bounds(e, lo, hi, diverged, speed) => {
                if let Ok(mut m) = motion.get_mut(e) {
                    m.record(lo, hi, if diverged { f32::INFINITY } else { speed }, &sleep);
                }
                let prev = reported.get(e).ok().copied();
                let quiet = handled.contains(&e)
                    || prev.is_some_and(|r| r.given_up || *frame < r.frame + RECOVERY_QUIET_FRAMES);
                if diverged && !quiet {
                    handled.push(e);
                    let n = prev.map_or(0, |r| r.recoveries);
                    let recover = n < MAX_RECOVERIES;
                    let what = if recover {
                        format!("put back at rest (recovery {} of {MAX_RECOVERIES})", n + 1)
                    } else {
                        format!("left held where it diverged after {MAX_RECOVERIES} recoveries")
                    };
                    let error = format!(
                        "the simulation diverged (NaN or a particle faster than max_speed) and \
                         the body was {what}; lower dt, raise iterations/substeps or K, or use \
                         shape matching"
                    );
                    warn!("soft body {e}: {error}");
                    errors.write(SoftBodyError { entity: e, error });
                    if recover && let Ok((mut b, _)) = bodies.get_mut(e) {
                        b.generation += 1;
                        b.reset = true;
                    }
                    if let Ok(mut ec) = commands.get_entity(e) {
                        ec.insert(DivergenceReported {
                            recoveries: n + recover as u32,
                            frame: *frame,
                            given_up: !recover,
                        });
                    }
                }
                // The entity-local box of the particles, grown by the skin's reach past
                // them (a few lattice spacings) and the motion of a frame or two.
                let Ok((b, to_world)) = bodies.get(e) else {
                    continue;
                };
                if !(lo.is_finite() && hi.is_finite()) || lo.cmpgt(hi).any() {
                    continue;
                }
                let spacing = b.model.bodies.first().map_or(0.0, |b| b.spacing);
                let m = Vec3::splat(3.0 * spacing);
                let (l, h) = transform_box(&to_world.affine().inverse(), lo - m, hi + m);
                if let Ok(mut ec) = commands.get_entity(e) {
                    ec.insert(Aabb::from_min_max(l, h));
                }
            }
            ReadbackResult::GpuUnavailable(why) => {
                warn!(
                    "bevy_tissue: {why}; every soft body is simulated on the CPU instead \
                     (slower; TissueSettings::backend is now Cpu)"
                );
                settings.backend = TissueBackend::Cpu;
            }
            ReadbackResult::Error(e, error) => {
                if let Ok(mut s) = status.get_mut(e) {
                    *s = SoftBodyStatus::Failed(error.clone());
                }
                if let Ok(mut ec) = commands.get_entity(e) {
                    ec.remove::<BuiltBody>();
                }
                errors.write(SoftBodyError { entity: e, error });
            }
        }
    }
}
