//! [`GpuWorld`]: every body of a scene in one set of GPU buffers, and the recording of
//! time steps and of the draw path into a command encoder.
//!
//! A step is the CPU Jacobi solver's step (`core::solver`, its twin) as dispatches:
//! contact neighbours (every `knn_every` steps: the broad phase, which finds the bodies
//! near another, then grid + KNN), then per substep predict, `iterations` × (clusters,
//! gather, contacts), collider forces, finish. Small shape-matching bodies are solved a
//! workgroup each (`body.wgsl`): all `iterations` at once for those near no other, one
//! iteration per dispatch for the others, each starting with the contact pass of the
//! iteration before for its body (the contact dispatch then only runs for the other
//! bodies, and after the last iteration). Results are
//! deterministic: no float atomics, every sum in a fixed order.
//!
//! The world works on a bare `RenderDevice`/`RenderQueue`, so it runs inside Bevy's
//! render graph (the plugin) and standalone (tests, benchmarks) alike.
//!
//! It changes without being made again: per-step settings go to the parameters
//! ([`GpuWorld::set_settings`]), a despawned body is retired in place
//! ([`GpuWorld::retire`]), and a new one is appended into the room the buffers were made
//! with ([`GpuWorld::with_room`], [`GpuWorld::append`]); every other body keeps its state
//! and neighbour lists.
//!
//! Parts: [`plan`] (the steps' dispatches as data, a pure function of the world's shape
//! and the settings), `record` (replays a plan into an encoder), `alloc` (the buffers
//! by bind group, their room, the bind groups, limit checks, uploads), `readback`.
//!
//! ```no_run
//! # use bevy_tissue::core::model::{BodyDesc, Model};
//! # use bevy_tissue::core::{procedural, solver::{SolverSettings, State}};
//! # use bevy_tissue::gpu::{headless, GpuWorld, NoTiming};
//! let g = headless().expect("a GPU adapter");
//! let desc = BodyDesc {
//!     discretisation: bevy_tissue::core::model::Discretisation::Clusters,
//!     ..Default::default()
//! };
//! let mut one = Model::new();
//! one.add_body(&procedural::cuboid(glam::Vec3::splat(0.05), 2), &desc)?;
//! let s = SolverSettings::default();
//! // Room for half as much again (and at least one more of the largest body).
//! let mut world = GpuWorld::with_room(&g.device, &g.kernels, &one, &State::new(&one), s, 0, 1.5)?;
//! // A second body later, without a new world.
//! let mut two = Model::new();
//! let beside = BodyDesc { translation: glam::Vec3::new(0.2, 0.0, 0.0), ..desc };
//! two.add_body(&procedural::cuboid(glam::Vec3::splat(0.05), 2), &beside)?;
//! assert!(world.append(&g.device, &g.queue, &two, &State::new(&two))?);
//! world.write_params(&g.queue);
//! let mut enc = g.device.create_command_encoder(&Default::default());
//! world.record_steps(&mut enc, &g.kernels, 1, &mut NoTiming);
//! g.queue.submit([enc.finish()]);
//! # Ok::<(), bevy_tissue::core::TissueError>(())
//! ```

use super::buffers::*;
use super::kernels::{self, Kernels};
use crate::core::TissueError;
use crate::core::colliders::Collider;
use crate::core::model::Model;
use crate::core::solver::{SolverSettings, State};
use bevy::render::render_resource::{
    BindGroup, BindingResource, Buffer, BufferBinding, BufferUsages, CommandEncoder,
};
use bevy::render::renderer::{RenderDevice, RenderQueue};
use glam::Vec3;

mod alloc;
use alloc::*;
pub mod plan;
mod readback;
mod record;
pub use alloc::{Capacity, SlabGroup};
use plan::groups;
pub use readback::{Staging, read_buffer, read_buffers, read_buffers_with, read_u32, read_vec3};
use record::{Bound, Recording};
pub use record::{NoTiming, PassRecorder};

/// Per body: particle range and render-vertex range.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BodyRange {
    /// First particle.
    pub first: u32,
    /// Particles.
    pub count: u32,
    /// First render vertex.
    pub vfirst: u32,
    /// Render vertices.
    pub vcount: u32,
}

/// Where one body's arrays are in the world's buffers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
struct BodySlot {
    /// First particle, the body's index, first render vertex, first membership and
    /// first adjacency triangle.
    start: Capacity,
    /// How many of each (one body).
    size: Capacity,
    /// First pin slot.
    pin_start: u32,
    /// Pins.
    pins: u32,
}

impl BodySlot {
    /// The body's particle and render-vertex ranges.
    fn range(&self) -> BodyRange {
        BodyRange {
            first: self.start.particles,
            count: self.size.particles,
            vfirst: self.start.vertices,
            vcount: self.size.vertices,
        }
    }
}

/// The slots of the bodies of `model` packed as `packed`, numbered on from `at` (pins
/// from `pins`).
fn body_slots(model: &Model, packed: &Packed, at: Capacity, pins: u32) -> Vec<BodySlot> {
    let mut pin = pins;
    model
        .bodies
        .iter()
        .enumerate()
        .map(|(i, b)| {
            let (p0, p1) = (b.first as usize, (b.first + b.count) as usize);
            let v0 = packed.vfirst[i] as usize;
            let v1 = v0 + b.skin.rest_vertices.len();
            let count = model
                .pinned
                .iter()
                .filter(|&&p| (p0..p1).contains(&(p as usize)))
                .count() as u32;
            let slot = BodySlot {
                start: at.add(Capacity {
                    particles: b.first,
                    bodies: i as u32,
                    vertices: v0 as u32,
                    members: packed.pinfo[p0][3],
                    triangles: packed.adj[v0],
                }),
                size: Capacity {
                    particles: b.count,
                    bodies: 1,
                    vertices: (v1 - v0) as u32,
                    members: packed.pinfo[p1][3] - packed.pinfo[p0][3],
                    triangles: packed.adj[v1] - packed.adj[v0],
                },
                pin_start: pin,
                pins: count,
            };
            pin += count;
            slot
        })
        .collect()
}

/// All bodies of a scene on the GPU (see the module docs).
pub struct GpuWorld {
    /// Solver settings (the same fields as the CPU solver's; `method` is ignored: the GPU
    /// runs Jacobi).
    pub settings: SolverSettings,
    /// Steps taken.
    pub step: u64,
    /// Particle and vertex ranges of the bodies, in model order.
    pub ranges: Vec<BodyRange>,
    /// Ranges of fewer clusters than this are solved with 8 threads per cluster, larger
    /// ones with a thread per cluster ([`LANE_CLUSTERS_BELOW`] by default; the two give
    /// the same result up to the order of the member sums).
    pub lane_clusters_below: u32,
    /// Whether `body.wgsl` solves level 0 of the bodies it fits ([`GpuWorld::set_body_kernel`]).
    body_kernel: bool,
    /// Per body: shape matching, at most [`kernels::body::BODY_MAX`] particles, no
    /// hierarchy levels in the world, and an adapter whose workgroups are large enough.
    body_fits: Vec<bool>,
    b: Buffers,
    surface: Buffer,
    levels: Vec<(u32, u32)>,
    scan_len: u32,
    /// The per-dispatch records: the prefix sum's levels and grid builds (rewritten
    /// when an appended body needs larger grid cells), the ranges (rewritten when bodies
    /// are appended), the skinning spans (one 256-byte record per skin dispatch).
    records: DispatchBuffers,
    /// Every kernel's bind groups, by [`kernels::Kernel::id`] (they keep the per-dispatch
    /// records alive: the prefix sum's levels, `level`, one 256-byte record per level and
    /// the two build configurations; the ranges, `range`: level 0's particles, then per
    /// coarse level its particles, prolongation and transfer records, then level 0's
    /// iteration records).
    binds: Vec<KernelBind>,
    /// Where the arrays that share a buffer start.
    regions: Regions,
    /// Record of level 0's first iteration record in the ranges (16 variants per
    /// body_iteration block length, `block_records` lengths).
    iteration_records: u32,
    /// Longest body_iteration block the records were built for (`max_block` at creation).
    block_records: u32,
    /// The hierarchy's coarse levels in the particle arrays.
    coarse: Vec<PackedLevel>,
    n: u32,
    n_vertices: u32,
    n_colliders: u32,
    contact_k: u32,
    knn_k: u32,
    contacts_on: bool,
    /// Whether the all-particle (contact) lists hold a previous search, so that the next
    /// one runs the warm variant.
    knn_warm: bool,
    contacts_warm: bool,
    params: GpuParams,
    /// Which bodies sleep (the `asleep` word of their `Body` record).
    asleep: Vec<bool>,
    /// Per body, shape matching's stiffness k (its per-iteration stiffness depends on the
    /// iteration count), or `None` for a hyperelastic body.
    stiffness: Vec<Option<f32>>,
    /// Per body, whether it was retired ([`GpuWorld::retire`]).
    retired: Vec<bool>,
    /// Per body: where its arrays start (particles, its body index, render vertices,
    /// cluster memberships, adjacency triangles) and how much of each it holds, and
    /// its first pin slot and pin count.
    slots: Vec<BodySlot>,
    /// What the buffers have room for, and what the bodies use of it.
    cap: Capacity,
    used: Capacity,
    /// Pin targets in use (slots of the pin region).
    pins: u32,
    /// Largest lattice spacing of any body, m (the contact grid's cell is made for it).
    max_spacing: f32,
    /// Where the hierarchy's prolongation records start in its table.
    records_base: u32,
    /// The adapter runs `body.wgsl`.
    has_body_kernel: bool,
    /// The next step refreshes the contact lists whatever the step count (bodies were
    /// appended: theirs are empty, and the others' do not list them).
    refresh_contacts: bool,
}

/// Where a retired body's particles are parked, m: far from any scene, a tenth of a metre
/// apart (so that they fill grid cells of their own and meet nothing).
const PARKED: Vec3 = Vec3::splat(1.0e4);

/// The per-step values of `params` that come from `s` alone: gravity, substep, damping,
/// relaxations, rotation and Jacobi iterations, the divergence speed.
fn step_params(params: &mut GpuParams, s: &SolverSettings) {
    let h = s.dt / s.substeps as f32;
    params.gravity = s.gravity.extend(0.0).to_array();
    params.rot_iters = s.rotation_iterations;
    params.h = h;
    params.h2 = h * h;
    params.keep = (1.0 - s.damping * h).max(0.0);
    params.omega = s.relaxation;
    params.inv_substeps = 1.0 / s.substeps as f32;
    params.max_speed = s.max_speed;
    params.iterations = s.iterations;
    params.contact_omega = s.contact_relaxation;
}

/// Largest number of skin dispatches (runs of bodies sharing a vertex slab) per frame.
pub const MAX_SKIN_RUNS: usize = 64;

/// `list` with `by` added to every entry.
fn shift_by(list: &[u32], by: u32) -> Vec<u32> {
    list.iter().map(|i| i + by).collect()
}

/// Shape matching's stiffness k of a body, `None` for a hyperelastic one.
fn shape_stiffness(m: &crate::core::model::Material) -> Option<f32> {
    match *m {
        crate::core::model::Material::ShapeMatching { stiffness } => Some(stiffness),
        _ => None,
    }
}

/// The prefix sum's levels (first element, elements) over a grid of `table` buckets,
/// and the scan's length.
fn scan_layout(table: u32) -> (Vec<(u32, u32)>, u32) {
    let mut levels = Vec::new();
    let mut off = 0u32;
    for c in scan_levels(table + 1) {
        levels.push((off, c));
        off += c;
    }
    (levels, off + 1)
}

/// Whether particle contacts run: asked for, more than one body, and room for candidates.
fn contacts_run(settings: &SolverSettings, bodies: usize, contact_k: u32) -> bool {
    settings.particle_contacts && bodies > 1 && contact_k > 0
}

/// Contact candidates kept per particle in a world with room for `particles`.
fn contact_k(settings: &SolverSettings, particles: u32) -> u32 {
    settings
        .contact_neighbours
        .min(particles.saturating_sub(1))
        .min(MAX_GPU_K)
}

/// Whether `body.wgsl` can solve level 0 of `b` (on an adapter that runs it, in a world
/// without hierarchy levels): shape matching of at most [`kernels::body::BODY_MAX`]
/// particles.
fn body_fits(b: &GpuBody) -> bool {
    b.kind == 0 && b.count <= kernels::body::BODY_MAX
}

/// The per-dispatch range records (`GpuRange`, one 256-byte uniform record each): level
/// 0's particles; per coarse level its particles, its prolongation records and its
/// multiplier-transfer records; then level 0's iteration records (from
/// [`iteration_records`]): 16 variants (half | prev << 1 | skip << 2 | no contacts << 3)
/// per body_iteration block of 1 to `block_records` iterations.
fn range_records(
    n: u32,
    contacts_on: bool,
    coarse: &[PackedLevel],
    records_base: u32,
    block_records: u32,
) -> Vec<GpuRange> {
    let range = |first, count, base, flag| GpuRange {
        first,
        count,
        base,
        flag,
        ..bytemuck::Zeroable::zeroed()
    };
    let mut lrecs = vec![range(0, n, 0, contacts_on as u32)];
    let coarsest = coarse.len().saturating_sub(1);
    for (l, lv) in coarse.iter().enumerate() {
        // Level in reads `base` as "zero the multipliers" (the coarsest level only);
        // the gather reads `flag` = 0: no contact pass, boundary at once.
        lrecs.push(range(lv.first, lv.count, (l == coarsest) as u32, 0));
        lrecs.push(range(lv.rec_first, lv.rec_count, records_base, 0));
        lrecs.push(range(lv.tr_first, lv.tr_count, records_base, 0));
    }
    for iters in 1..=block_records {
        for v in 0..16u32 {
            lrecs.push(GpuRange {
                half: v & 1,
                prev: (v >> 1) & 1,
                skip: (v >> 2) & 1,
                iters,
                ..range(0, n, 0, (contacts_on && v < 8) as u32)
            });
        }
    }
    lrecs
}

/// The prefix sum's records (one 256-byte uniform record per level of `levels`, bound
/// with dynamic offsets), then two grid-build configurations: contacts (cell edge
/// `cell`, m), then the all-particle search (`knn_cell`).
fn scan_records(
    levels: &[(u32, u32)],
    scan_len: u32,
    cell: f32,
    knn_cell: f32,
) -> Vec<GpuScanLevel> {
    let mut recs: Vec<GpuScanLevel> = levels
        .iter()
        .enumerate()
        .map(|(l, &(o, c))| GpuScanLevel {
            offset: o,
            count: c,
            sums: levels.get(l + 1).map_or(scan_len - 1, |nx| nx.0),
            cell,
            pad: [0; 60],
        })
        .collect();
    for c in [cell, knn_cell] {
        recs.push(GpuScanLevel {
            offset: 0,
            count: 0,
            sums: 0,
            cell: c,
            pad: [0; 60],
        });
    }
    recs
}

/// The first of level 0's iteration records in [`range_records`].
fn iteration_records(coarse: &[PackedLevel]) -> u32 {
    1 + 3 * coarse.len() as u32
}

/// An error for a model with lattice elements (they step on [`crate::gpu::GpuLattice`]).
fn no_elements(model: &Model) -> Result<(), TissueError> {
    if model.elements.is_empty() {
        return Ok(());
    }
    Err(TissueError::InvalidParameter {
        name: "discretisation",
        value: format!("{} lattice elements", model.elements.len()),
        expected: "cluster bodies only (lattice bodies run on the CPU solver)",
    })
}

/// Below this many clusters a range is solved by `solve_clusters_lanes` (8 threads per
/// cluster), from it on by `solve_clusters` (a thread per cluster): a thread per cluster
/// was measured faster on large ranges, 8 lanes on the hierarchy's small coarse levels
/// (BENCHMARKS.md, "GPU" and "Hierarchy").
pub const LANE_CLUSTERS_BELOW: u32 = 8192;

impl GpuWorld {
    /// Uploads `model` with its current `state`. `knn_k` is the K of the optional
    /// all-particle neighbour search ([`GpuWorld::record_knn_all`]; 0 = not used).
    /// Fails with [`TissueError::GpuLimit`] when a buffer or a dispatch exceeds the
    /// adapter's limits, and on invalid settings.
    pub fn new(
        device: &RenderDevice,
        kernels: &Kernels,
        model: &Model,
        state: &State,
        settings: SolverSettings,
        knn_k: u32,
    ) -> Result<Self, TissueError> {
        Self::check_model(device, model, &settings, knn_k)?;
        Self::new_unchecked(
            device,
            kernels,
            model,
            state,
            settings,
            knn_k,
            Sizing::Exact,
        )
    }

    /// [`GpuWorld::new`] with room for bodies appended later ([`GpuWorld::append`]):
    /// `growth` times what `model` needs of each count (particles, bodies, render
    /// vertices, cluster memberships, adjacency triangles), and at least one more of its
    /// largest body. A world with hierarchy levels gets no room.
    pub fn with_room(
        device: &RenderDevice,
        kernels: &Kernels,
        model: &Model,
        state: &State,
        settings: SolverSettings,
        knn_k: u32,
        growth: f32,
    ) -> Result<Self, TissueError> {
        Self::check_model(device, model, &settings, knn_k)?;
        let sizing = Sizing::Grow(growth);
        Self::new_unchecked(device, kernels, model, state, settings, knn_k, sizing)
    }

    /// [`GpuWorld::new`] with room for at least `capacity` (and at least what `model`
    /// needs). A world with hierarchy levels gets no room.
    pub fn with_capacity(
        device: &RenderDevice,
        kernels: &Kernels,
        model: &Model,
        state: &State,
        settings: SolverSettings,
        knn_k: u32,
        capacity: Capacity,
    ) -> Result<Self, TissueError> {
        Self::check_model(device, model, &settings, knn_k)?;
        let sizing = Sizing::AtLeast(capacity);
        Self::new_unchecked(device, kernels, model, state, settings, knn_k, sizing)
    }

    /// What the buffers have room for ([`GpuWorld::append`] fills it).
    pub fn capacity(&self) -> Capacity {
        self.cap
    }

    /// What the bodies use of [`GpuWorld::capacity`] (retired bodies included: they keep
    /// their place until the world is made again).
    pub fn used(&self) -> Capacity {
        self.used
    }

    /// The checks of [`GpuWorld::new`] before anything is made.
    fn check_model(
        device: &RenderDevice,
        model: &Model,
        settings: &SolverSettings,
        knn_k: u32,
    ) -> Result<(), TissueError> {
        no_elements(model)?;
        let limits = device.limits();
        Self::check_limits(&limits, model, settings)?;
        // The neighbour search's candidate store (`spare`) also depends on `knn_k`.
        let k = knn_k.max(settings.contact_neighbours).min(MAX_GPU_K);
        check_binding(
            &limits,
            "neighbour search candidate store",
            model.particle_count() as u64 * (k + SPARE_EXTRA) as u64 * 4,
        )
    }

    /// Checks that `model` fits a device with `limits`: every buffer binding and the
    /// per-particle dispatch size. [`GpuWorld::new`] runs this first.
    pub fn check_limits(
        limits: &bevy::render::render_resource::WgpuLimits,
        model: &Model,
        settings: &SolverSettings,
    ) -> Result<(), TissueError> {
        let n = (model.particle_count()
            + model
                .levels
                .iter()
                .map(|l| l.model.particle_count())
                .sum::<usize>()) as u64;
        let nv: u64 = model
            .bodies
            .iter()
            .map(|b| b.skin.rest_vertices.len() as u64)
            .sum();
        let lists = std::iter::once(model)
            .chain(model.levels.iter().map(|l| &l.model))
            .map(|m| (m.cluster_members.len() + m.inv_clusters.len()) as u64)
            .sum::<u64>();
        let bodies = model.bodies.len() as u64;
        let n0 = model.particle_count() as u64;
        check_counts(limits, [n, n0, nv, lists, bodies], settings)
    }

    fn new_unchecked(
        device: &RenderDevice,
        kernels: &Kernels,
        model: &Model,
        state: &State,
        settings: SolverSettings,
        knn_k: u32,
        sizing: Sizing,
    ) -> Result<Self, TissueError> {
        settings.validate()?;
        let n = model.particle_count() as u32;
        if n == 0 {
            return Err(TissueError::InvalidParameter {
                name: "model",
                value: "0 particles".into(),
                expected: "at least one body",
            });
        }
        if knn_k > MAX_GPU_K || knn_k >= n {
            return Err(TissueError::InvalidParameter {
                name: "knn_k",
                value: knn_k.to_string(),
                expected: "K ≤ 64 and smaller than the particle count",
            });
        }
        let packed = Packed::new(model, &settings);
        let (used, largest) = packed_use(model, &packed);
        let cap = match sizing {
            _ if !packed.levels.is_empty() => used,
            Sizing::Exact => used,
            Sizing::Grow(g) => used.grown(g, largest),
            Sizing::AtLeast(c) => used.max(c),
        };
        // Particles of all levels (the coarse levels' follow level 0's), with room.
        let total = (packed.total_particles() - n + cap.particles) as u64;
        let (pcap, bcap, vcap) = (cap.particles, cap.bodies, cap.vertices);
        check_counts(
            &device.limits(),
            [
                total,
                pcap as u64,
                vcap as u64,
                2 * cap.members as u64,
                bcap as u64,
            ],
            &settings,
        )?;
        // Bodies whose level 0 `body.wgsl` solves (a workgroup each).
        let body_fits: Vec<bool> = packed
            .bodies
            .iter()
            .map(|b| kernels.body.is_some() && packed.levels.is_empty() && body_fits(b))
            .collect();
        let mut gpu_bodies = packed.bodies.clone();
        for (b, fits) in gpu_bodies.iter_mut().zip(&body_fits) {
            b.in_workgroup = *fits as u32;
        }
        gpu_bodies.resize(
            packed.bodies.len() + (bcap - used.bodies) as usize,
            GpuBody::default(),
        );
        let nv = packed.vertex_count() as u32;
        let contact_k = contact_k(&settings, pcap);
        let contacts_on = contacts_run(&settings, model.bodies.len(), contact_k);
        let spare_stride = knn_k.max(contact_k) + SPARE_EXTRA;
        let (cell, knn_cell, table) = grid_params(pcap as usize, packed.max_spacing);
        let (levels, scan_len) = scan_layout(table);
        let regions = Regions::new(pcap, total as u32, total as u32, bcap);
        let st = StateArrays::new(model, &packed, state, pcap, total, &regions);
        let ma = ModelArrays::new(&packed, state, cap, total, gpu_bodies);
        let b = Buffers {
            frame: FrameBuffers::new(device, bcap),
            state: StateBuffers::new(
                device,
                Some(&st),
                &StateSizes {
                    particles: pcap as u64,
                    total,
                    bodies: bcap as u64,
                    contact_k,
                    knn_k,
                    spare_stride,
                    scan_len,
                    table,
                    aux: regions.aux_len as u64,
                },
            ),
            model: ModelBuffers::new(device, &ma, &packed.hier),
        };
        let recs = scan_records(&levels, scan_len, cell, knn_cell);
        let block_records = plan::max_block(&settings);
        let lrecs = range_records(
            n,
            contacts_on,
            &packed.levels,
            packed.records_base,
            block_records,
        );
        let iteration_records = iteration_records(&packed.levels);
        let records = DispatchBuffers::new(device, &recs, &lrecs);
        let surface = zeroed(
            device,
            "tissue surface",
            vcap as u64 * 32,
            BufferUsages::STORAGE
                | BufferUsages::VERTEX
                | BufferUsages::COPY_SRC
                | BufferUsages::COPY_DST,
        );
        let binds = kernels
            .all()
            .iter()
            .map(|k| KernelBind::new(device, k, &b, &records.scan, &records.ranges))
            .collect();
        let slots = body_slots(model, &packed, Capacity::default(), 0);
        let ranges = slots.iter().map(BodySlot::range).collect();
        let mut params = GpuParams {
            n,
            contacts: contacts_on as u32,
            contact_k,
            n_vertices: nv,
            grid_cell: cell,
            grid_table: table,
            max_radius: packed.max_radius,
            knn_k,
            n_bodies: model.bodies.len() as u32,
            knn_cell,
            spare_stride,
            contact_reach: crate::core::knn::contact_reach_bound(packed.max_radius),
            ..Default::default()
        };
        regions.write_bases(&mut params, cap);
        step_params(&mut params, &settings);
        Ok(Self {
            settings,
            step: state.step,
            ranges,
            lane_clusters_below: LANE_CLUSTERS_BELOW,
            body_kernel: true,
            body_fits,
            b,
            surface,
            levels,
            scan_len,
            records,
            binds,
            regions,
            iteration_records,
            block_records,
            coarse: packed.levels.clone(),
            n,
            n_vertices: nv,
            n_colliders: 0,
            contact_k,
            knn_k,
            contacts_on,
            knn_warm: false,
            contacts_warm: false,
            params,
            asleep: vec![false; packed.bodies.len()],
            retired: vec![false; model.bodies.len()],
            stiffness: model
                .bodies
                .iter()
                .map(|b| shape_stiffness(&b.material))
                .collect(),
            slots,
            cap,
            used,
            pins: model.pinned.len() as u32,
            max_spacing: packed.max_spacing,
            records_base: packed.records_base,
            has_body_kernel: kernels.body.is_some(),
            refresh_contacts: false,
        })
    }

    /// Marks bodies asleep or awake (one flag per body in model order; bodies past the
    /// end stay as they are). The kernels skip a sleeping body's particles and clusters:
    /// they keep their positions and zero velocity. Writes only what changed.
    pub fn set_asleep(&mut self, queue: &RenderQueue, asleep: impl IntoIterator<Item = bool>) {
        let n = self.ranges.len();
        for (b, (mine, want)) in self.asleep[..n].iter_mut().zip(asleep).enumerate() {
            // A retired body sleeps for good.
            let want = want || self.retired[b];
            if *mine != want {
                *mine = want;
                let offset = (b * size_of::<GpuBody>() + 12) as u64;
                queue.write_buffer(
                    &self.b.model.bodies,
                    offset,
                    bytemuck::bytes_of(&(want as u32)),
                );
            }
        }
    }

    /// Retires body `body` (model order) without rebuilding the world: it sleeps from now
    /// on (the kernels skip it), its particles are parked far from everything at rest
    /// (no other body or collider meets them, and they are not drawn by callers that skip
    /// retired bodies), and its grabs are let go. Every other body keeps its state. The
    /// world's arrays keep the body's place until it is rebuilt. Returns the particles
    /// retired so far (a caller compacts by rebuilding when they are many); `None` for a
    /// body out of range or in a world with hierarchy levels (whose coarse particles
    /// would still meet the body's).
    pub fn retire(&mut self, queue: &RenderQueue, body: usize) -> Option<u32> {
        let r = *self.ranges.get(body)?;
        if !self.coarse.is_empty() {
            return None;
        }
        if !self.retired[body] {
            self.retired[body] = true;
            self.asleep[body] = true;
            let offset = (body * size_of::<GpuBody>() + 12) as u64;
            queue.write_buffer(&self.b.model.bodies, offset, bytemuck::bytes_of(&1u32));
            let parked: Vec<[f32; 4]> = (0..r.count)
                .map(|i| (PARKED + Vec3::X * (0.1 * i as f32)).extend(0.0).to_array())
                .collect();
            let bytes: &[u8] = bytemuck::cast_slice(&parked);
            let at = r.first as u64 * 16;
            queue.write_buffer(&self.b.state.x, at, bytes);
            queue.write_buffer(&self.b.state.x, self.regions.p_base as u64 * 16 + at, bytes);
            let zeros = vec![0u8; r.count as usize * 16];
            queue.write_buffer(&self.b.state.v, at, &zeros);
            queue.write_buffer(
                &self.b.state.aux,
                self.regions.grab_base as u64 * 16 + at,
                &zeros,
            );
        }
        Some(
            self.ranges
                .iter()
                .zip(&self.retired)
                .filter(|(_, r)| **r)
                .map(|(range, _)| range.count)
                .sum(),
        )
    }

    /// Appends the bodies of `model` (cluster bodies, no hierarchy levels) with their
    /// `state` to the world without rebuilding it: their arrays are written into the room
    /// the buffers were made with ([`GpuWorld::with_room`]), after every other body,
    /// which keeps its state and neighbour lists. The new bodies come after the world's
    /// in its body order, with their particles, vertices, pins and grasps numbered on
    /// from the world's. The next step searches contact candidates whatever the step
    /// count (with grid cells for the largest spacing). Returns `Ok(false)` and changes
    /// nothing where they do not fit in place: no room left, or a world or model with
    /// hierarchy levels (the caller then makes the world again, with room). Write the
    /// parameters ([`GpuWorld::write_params`]) before the next steps.
    pub fn append(
        &mut self,
        device: &RenderDevice,
        queue: &RenderQueue,
        model: &Model,
        state: &State,
    ) -> Result<bool, TissueError> {
        no_elements(model)?;
        let m = model.particle_count();
        if state.x.len() != m || state.v.len() != m || state.pin_targets.len() != model.pinned.len()
        {
            return Err(TissueError::InvalidParameter {
                name: "state",
                value: format!("{} positions for {m} particles", state.x.len()),
                expected: "the state of the appended model",
            });
        }
        if m == 0 {
            return Ok(true);
        }
        if !self.coarse.is_empty() || !model.levels.is_empty() {
            return Ok(false);
        }
        let packed = Packed::new(model, &self.settings);
        let (more, _) = packed_use(model, &packed);
        if !self.used.fits(more, self.cap) {
            return Ok(false);
        }
        self.widen_grid(queue, packed.max_spacing);
        let at = self.used;
        let mut up = Uploads::default();
        self.write_bodies(&mut up, &packed, at, self.pins, Some(state), true);
        up.submit(device, queue);
        let slots = body_slots(model, &packed, at, self.pins);
        self.ranges.extend(slots.iter().map(BodySlot::range));
        self.slots.extend(slots);
        // The world's own records of the bodies.
        for (i, body) in model.bodies.iter().enumerate() {
            self.body_fits
                .push(self.has_body_kernel && body_fits(&packed.bodies[i]));
            self.asleep.push(false);
            self.retired.push(false);
            self.stiffness.push(shape_stiffness(&body.material));
        }
        self.used = at.add(more);
        self.pins += model.pinned.len() as u32;
        self.n = self.used.particles;
        self.n_vertices = self.used.vertices;
        self.contacts_on = contacts_run(&self.settings, self.ranges.len(), self.contact_k);
        let p = &mut self.params;
        p.n = self.n;
        p.n_bodies = self.ranges.len() as u32;
        p.n_vertices = self.n_vertices;
        p.contacts = self.contacts_on as u32;
        let lrecs = range_records(
            self.n,
            self.contacts_on,
            &self.coarse,
            self.records_base,
            self.block_records,
        );
        queue.write_buffer(&self.records.ranges, 0, bytemuck::cast_slice(&lrecs));
        self.widen_reach(packed.max_radius);
        self.refresh_contacts = self.contacts_on;
        Ok(true)
    }

    /// Writes the bodies of `packed` into the world's arrays from `at` (particles, body
    /// index, render vertices, memberships, triangles) and pin slot `pins`, their indices
    /// numbered on from there, with their `state` where given; with `sentinel`, also the
    /// particle row after their last (where the lists' ends are read: the world's end).
    fn write_bodies<'a>(
        &'a self,
        up: &mut Uploads<'a>,
        packed: &Packed,
        at: Capacity,
        pins: u32,
        state: Option<&State>,
        sentinel: bool,
    ) {
        let (n0, b0, v0) = (at.particles, at.bodies, at.vertices);
        let b = &self.b;
        if let Some(state) = state {
            // Positions (and the predicted ones), velocities, cluster states, grabs, pin
            // targets.
            let (x, v, cstate) = pack_state(state);
            let grab: Vec<[f32; 4]> = state.grab.iter().map(grab_record).collect();
            up.put(&b.state.x, n0, bytemuck::cast_slice(&x), 16);
            let p_at = self.regions.p_base + n0;
            up.put(&b.state.x, p_at, bytemuck::cast_slice(&x), 16);
            up.put(&b.state.v, n0, bytemuck::cast_slice(&v), 16);
            up.put(&b.state.cstate, n0, bytemuck::cast_slice(&cstate), 48);
            let g_at = self.regions.grab_base + n0;
            up.put(&b.state.aux, g_at, bytemuck::cast_slice(&grab), 16);
            let targets: Vec<[f32; 4]> = state
                .pin_targets
                .iter()
                .map(|p| p.extend(0.0).to_array())
                .collect();
            let pin_at = self.regions.pin_base + pins;
            up.put(&b.model.rest, pin_at, bytemuck::cast_slice(&targets), 16);
        }
        up.put(&b.model.rest, n0, bytemuck::cast_slice(&packed.rest), 16);
        let pinfo: Vec<[u32; 4]> = packed
            .pinfo
            .iter()
            .map(|&[body, slot, inv, start]| {
                [
                    body + b0,
                    if slot == NONE { NONE } else { slot + pins },
                    inv + at.members,
                    start + at.members,
                ]
            })
            .collect();
        let rows = if sentinel {
            pinfo.len()
        } else {
            pinfo.len() - 1
        };
        up.put(&b.model.pinfo, n0, bytemuck::cast_slice(&pinfo[..rows]), 16);
        // Members are particles and the inverse lists' entries clusters: both numbered
        // as the particles.
        let (members, inverse) = packed.lists.split_at(packed.inv_offset as usize);
        let members = shift_by(members, n0);
        up.put(
            &b.model.lists,
            at.members,
            bytemuck::cast_slice(&members),
            4,
        );
        let inv_at = self.cap.members + at.members;
        let inverse = shift_by(inverse, n0);
        up.put(&b.model.lists, inv_at, bytemuck::cast_slice(&inverse), 4);
        let crest_size = size_of::<GpuClusterRest>();
        up.put(
            &b.model.crest,
            n0,
            bytemuck::cast_slice(&packed.crest),
            crest_size,
        );
        let bodies: Vec<GpuBody> = packed
            .bodies
            .iter()
            .enumerate()
            .map(|(i, g)| {
                let fits = self.has_body_kernel && body_fits(g);
                let asleep = self.asleep.get(b0 as usize + i).copied().unwrap_or(false);
                GpuBody {
                    first: g.first + n0,
                    asleep: asleep as u32,
                    in_workgroup: (fits && self.body_kernel) as u32,
                    ..*g
                }
            })
            .collect();
        let body_size = size_of::<GpuBody>();
        up.put(
            &b.model.bodies,
            b0,
            bytemuck::cast_slice(&bodies),
            body_size,
        );
        // Skin: influences are particles; the body index rides in the rest vertex's w.
        let nv = packed.vertex_count();
        let vinf: Vec<[u32; 4]> = packed.vinf.iter().map(|i| i.map(|p| p + n0)).collect();
        let vrest: Vec<[f32; 4]> = packed
            .vrest
            .iter()
            .map(|&[x, y, z, w]| [x, y, z, f32::from_bits(w.to_bits() + b0)])
            .collect();
        up.put(&b.model.vinf, v0, bytemuck::cast_slice(&vinf), 16);
        up.put(&b.model.vwt, v0, bytemuck::cast_slice(&packed.vwt), 16);
        up.put(&b.model.vrest, v0, bytemuck::cast_slice(&vrest), 16);
        let starts: Vec<u32> = packed.adj[..=nv].iter().map(|s| s + at.triangles).collect();
        let corners = shift_by(&packed.adj[nv + 1..], v0);
        up.put(&b.model.adj, v0, bytemuck::cast_slice(&starts), 4);
        let corner_at = self.cap.vertices + 1 + 3 * at.triangles;
        up.put(&b.model.adj, corner_at, bytemuck::cast_slice(&corners), 4);
    }

    /// [`GpuWorld::append`], growing the room first where it is too small
    /// ([`GpuWorld::grow`]: to `growth` times what the bodies then use, and at least one
    /// more of the largest appended). `Ok(false)` where the world has hierarchy levels.
    #[allow(clippy::too_many_arguments)]
    pub fn append_or_grow(
        &mut self,
        device: &RenderDevice,
        queue: &RenderQueue,
        kernels: &Kernels,
        model: &Model,
        state: &State,
        growth: f32,
    ) -> Result<bool, TissueError> {
        if self.append(device, queue, model, state)? {
            return Ok(true);
        }
        if !self.coarse.is_empty() || !model.levels.is_empty() {
            return Ok(false);
        }
        let packed = Packed::new(model, &self.settings);
        let (more, largest) = packed_use(model, &packed);
        let want = self.used.add(more).grown(growth, largest);
        if !self.grow(device, queue, kernels, want)? {
            return Ok(false);
        }
        self.append(device, queue, model, state)
    }

    /// Grows the world's room to at least `capacity` without making it again from the
    /// models: new buffers, into which every body's state, model, neighbour lists and
    /// draw arrays are copied on the GPU (one submission); the grid is made for the new
    /// room at the next step's contact search. Every body moves on as before. Returns
    /// `Ok(false)` for a world with hierarchy levels (it has no room), and an error
    /// where the adapter cannot bind that much.
    pub fn grow(
        &mut self,
        device: &RenderDevice,
        queue: &RenderQueue,
        kernels: &Kernels,
        capacity: Capacity,
    ) -> Result<bool, TissueError> {
        if !self.coarse.is_empty() {
            return Ok(false);
        }
        let cap = self.cap.max(capacity);
        if cap == self.cap {
            return Ok(true);
        }
        let (pcap, bcap, vcap) = (cap.particles, cap.bodies, cap.vertices);
        let p64 = pcap as u64;
        let limits = device.limits();
        let counts = [p64, p64, vcap as u64, 2 * cap.members as u64, bcap as u64];
        check_counts(&limits, counts, &self.settings)?;
        let contact_k = contact_k(&self.settings, pcap);
        let spare_stride = self.knn_k.max(contact_k) + SPARE_EXTRA;
        let (cell, knn_cell, table) = grid_params(pcap as usize, self.max_spacing);
        let (levels, scan_len) = scan_layout(table);
        let regions = Regions::new(pcap, pcap, pcap, bcap);
        let b = Buffers {
            frame: FrameBuffers::new(device, bcap),
            state: StateBuffers::new(
                device,
                None,
                &StateSizes {
                    particles: p64,
                    total: p64,
                    bodies: bcap as u64,
                    contact_k,
                    knn_k: self.knn_k,
                    spare_stride,
                    scan_len,
                    table,
                    aux: regions.aux_len as u64,
                },
            ),
            model: ModelBuffers::zeroed(
                device,
                &ModelSizes {
                    total: p64,
                    particles: p64,
                    members: cap.members as u64,
                    bodies: bcap as u64,
                    vertices: vcap as u64,
                    triangles: cap.triangles as u64,
                },
            ),
        };
        let surface = zeroed(
            device,
            "tissue surface",
            vcap as u64 * 32,
            BufferUsages::STORAGE
                | BufferUsages::VERTEX
                | BufferUsages::COPY_SRC
                | BufferUsages::COPY_DST,
        );
        // Everything the bodies hold, old place to new (scratch is remade by the steps).
        let (n, nb, nv) = (
            self.n as u64,
            self.ranges.len() as u64,
            self.n_vertices as u64,
        );
        let (u, o, r) = (self.used, self.regions, regions);
        let (os, ns, om, nm) = (&self.b.state, &b.state, &self.b.model, &b.model);
        let mut copies: Vec<(&Buffer, u64, &Buffer, u64, u64)> = vec![
            (&os.x, 0, &ns.x, 0, n * 16),
            (
                &os.x,
                o.p_base as u64 * 16,
                &ns.x,
                r.p_base as u64 * 16,
                n * 16,
            ),
            (&os.v, 0, &ns.v, 0, n * 16),
            (
                &os.cstate,
                0,
                &ns.cstate,
                0,
                n * size_of::<GpuClusterState>() as u64,
            ),
            (
                &os.aux,
                o.grab_base as u64 * 16,
                &ns.aux,
                r.grab_base as u64 * 16,
                n * 16,
            ),
            (&os.knn_out, 0, &ns.knn_out, 0, n * self.knn_k as u64 * 4),
            (&os.status, 0, &ns.status, 0, nb * 4),
            (&om.rest, 0, &nm.rest, 0, n * 16),
            (
                &om.rest,
                o.pin_base as u64 * 16,
                &nm.rest,
                r.pin_base as u64 * 16,
                self.pins as u64 * 16,
            ),
            (&om.pinfo, 0, &nm.pinfo, 0, (n + 1) * 16),
            (&om.lists, 0, &nm.lists, 0, u.members as u64 * 4),
            (
                &om.lists,
                self.cap.members as u64 * 4,
                &nm.lists,
                cap.members as u64 * 4,
                u.members as u64 * 4,
            ),
            (
                &om.crest,
                0,
                &nm.crest,
                0,
                n * size_of::<GpuClusterRest>() as u64,
            ),
            (
                &om.bodies,
                0,
                &nm.bodies,
                0,
                nb * size_of::<GpuBody>() as u64,
            ),
            (&om.vinf, 0, &nm.vinf, 0, nv * 16),
            (&om.vwt, 0, &nm.vwt, 0, nv * 16),
            (&om.vrest, 0, &nm.vrest, 0, nv * 16),
            (&om.adj, 0, &nm.adj, 0, (nv + 1) * 4),
            (
                &om.adj,
                (self.cap.vertices as u64 + 1) * 4,
                &nm.adj,
                (vcap as u64 + 1) * 4,
                3 * u.triangles as u64 * 4,
            ),
            (&self.surface, 0, &surface, 0, nv * 32),
        ];
        // Contact lists keep their stride only where K is the same (else they start
        // cold).
        let same_k = contact_k == self.contact_k;
        if same_k {
            copies.push((&os.contacts, 0, &ns.contacts, 0, n * contact_k as u64 * 4));
        }
        let mut enc = device.create_command_encoder(&Default::default());
        for (from, at, to, to_at, bytes) in copies {
            if bytes > 0 {
                enc.copy_buffer_to_buffer(from, at, to, to_at, bytes);
            }
        }
        queue.submit([enc.finish()]);
        let p = &mut self.params;
        r.write_bases(p, cap);
        p.grid_cell = cell;
        p.knn_cell = knn_cell;
        p.grid_table = table;
        p.contact_k = contact_k;
        p.spare_stride = spare_stride;
        let contacts_on = contacts_run(&self.settings, self.ranges.len(), contact_k);
        p.contacts = contacts_on as u32;
        let recs = scan_records(&levels, scan_len, cell, knn_cell);
        let lrecs = range_records(
            self.n,
            contacts_on,
            &self.coarse,
            self.records_base,
            self.block_records,
        );
        let records = DispatchBuffers::new(device, &recs, &lrecs);
        self.binds = kernels
            .all()
            .iter()
            .map(|k| KernelBind::new(device, k, &b, &records.scan, &records.ranges))
            .collect();
        self.b = b;
        self.surface = surface;
        self.records = records;
        self.regions = regions;
        self.levels = levels;
        self.scan_len = scan_len;
        self.cap = cap;
        self.contacts_on = contacts_on;
        self.contact_k = contact_k;
        self.contacts_warm &= same_k;
        // The grid is made for the new room at the next search.
        self.refresh_contacts = self.contacts_on;
        Ok(true)
    }

    /// The contact search's reach for a particle radius of `radius` where it is larger
    /// than the world's largest (the broad phase's bound follows it).
    fn widen_reach(&mut self, radius: f32) {
        let p = &mut self.params;
        p.max_radius = p.max_radius.max(radius);
        p.contact_reach = crate::core::knn::contact_reach_bound(p.max_radius);
    }

    /// Grid cells for a lattice spacing of `spacing` where it is larger than the grid was
    /// made for (the next contact search builds them).
    fn widen_grid(&mut self, queue: &RenderQueue, spacing: f32) {
        if spacing <= self.max_spacing {
            return;
        }
        self.max_spacing = spacing;
        let (cell, knn_cell, _) = grid_params(self.cap.particles as usize, spacing);
        self.params.grid_cell = cell;
        self.params.knn_cell = knn_cell;
        let recs = scan_records(&self.levels, self.scan_len, cell, knn_cell);
        queue.write_buffer(&self.records.scan, 0, bytemuck::cast_slice(&recs));
    }

    /// Replaces body `body`'s model with `model` (one cluster body) in place, where it
    /// holds as many particles, render vertices, cluster memberships, adjacency triangles
    /// and pins: a new material, density, stiffness or pin targets, the same sampling.
    /// With `state` the body starts from it (a reset); without, it keeps its positions,
    /// velocities and cluster states. Every other body is untouched. Returns `Ok(false)`
    /// and changes nothing where the sizes differ, the body was retired, or the world has
    /// hierarchy levels (the caller then retires the body and appends the new model).
    pub fn replace_body(
        &mut self,
        device: &RenderDevice,
        queue: &RenderQueue,
        body: usize,
        model: &Model,
        state: Option<&State>,
    ) -> Result<bool, TissueError> {
        no_elements(model)?;
        let Some(&slot) = self.slots.get(body) else {
            return Ok(false);
        };
        if self.retired[body] || !self.coarse.is_empty() || !model.levels.is_empty() {
            return Ok(false);
        }
        if let Some(st) = state
            && (st.x.len() != model.particle_count() || st.pin_targets.len() != model.pinned.len())
        {
            return Err(TissueError::InvalidParameter {
                name: "state",
                value: format!(
                    "{} positions for {} particles",
                    st.x.len(),
                    model.particle_count()
                ),
                expected: "the state of the new model",
            });
        }
        let packed = Packed::new(model, &self.settings);
        let (size, _) = packed_use(model, &packed);
        if size != slot.size || model.pinned.len() as u32 != slot.pins {
            return Ok(false);
        }
        self.widen_grid(queue, packed.max_spacing);
        let mut up = Uploads::default();
        // (The row after the body's last particle already holds the list ends: the sizes
        // are the same.)
        self.write_bodies(&mut up, &packed, slot.start, slot.pin_start, state, false);
        up.submit(device, queue);
        let b = &model.bodies[0];
        self.body_fits[body] = self.has_body_kernel && body_fits(&packed.bodies[0]);
        self.stiffness[body] = shape_stiffness(&b.material);
        self.widen_reach(packed.max_radius);
        Ok(true)
    }

    /// Whether body `body` (model order) was retired ([`GpuWorld::retire`]).
    pub fn is_retired(&self, body: usize) -> bool {
        self.retired.get(body).copied().unwrap_or(false)
    }

    /// Whether level 0 of the small shape-matching bodies (at most
    /// [`kernels::body::BODY_MAX`] particles, in a world without hierarchy levels) is
    /// solved by `body.wgsl`, a workgroup per body that keeps the body in workgroup
    /// memory and runs both passes of a Jacobi iteration in one dispatch (on by default),
    /// or by the cluster and gather kernels. The two agree up to the order of the gather's
    /// sums (the workgroup kernel adds them in the CPU twin's order). A body's result does
    /// not depend on which other bodies share the world.
    pub fn set_body_kernel(&mut self, queue: &RenderQueue, on: bool) {
        self.body_kernel = on;
        for (b, fits) in self.body_fits.iter().enumerate() {
            if *fits {
                let offset =
                    (b * size_of::<GpuBody>() + std::mem::offset_of!(GpuBody, in_workgroup)) as u64;
                queue.write_buffer(
                    &self.b.model.bodies,
                    offset,
                    bytemuck::bytes_of(&(on as u32)),
                );
            }
        }
    }

    /// Whether `body.wgsl` solves some body ([`GpuWorld::set_body_kernel`]).
    pub fn body_kernel(&self) -> bool {
        self.body_kernel && self.body_fits.iter().any(|f| *f)
    }

    /// Whether every body sleeps (a frame then records no step).
    pub fn all_asleep(&self) -> bool {
        !self.ranges.is_empty() && self.asleep[..self.ranges.len()].iter().all(|a| *a)
    }

    /// Particles in the world.
    pub fn particle_count(&self) -> u32 {
        self.n
    }

    /// Render vertices in the world.
    pub fn vertex_count(&self) -> u32 {
        self.n_vertices
    }

    /// K of the all-particle neighbour search ([`GpuWorld::record_knn_all`]).
    pub fn knn_k(&self) -> u32 {
        self.knn_k
    }

    /// Contact candidates kept per particle (0 when particle contacts are off).
    pub fn contact_neighbours(&self) -> u32 {
        if self.contacts_on { self.contact_k } else { 0 }
    }

    /// The world's own vertex buffer (STORAGE | VERTEX): 8 floats per render vertex
    /// (position, normal, uv), used when no mesh allocator slab is given.
    pub fn surface(&self) -> &Buffer {
        &self.surface
    }

    /// Per particle (all levels): the grasper holding it, `[offset (m, grasper frame),
    /// grasper index + 1, or 0 when free]` (16 bytes each;
    /// [`crate::core::colliders::Grab`]'s twin): the buffer and the byte offset of the
    /// first particle's record.
    pub fn grabs(&self) -> (&Buffer, u64) {
        (&self.b.state.aux, self.regions.grab_base as u64 * 16)
    }

    /// Lets every held particle go (the plugin does this when the collider list changes
    /// order, since grabs name graspers by index).
    pub fn release_grabs(&self, queue: &RenderQueue) {
        let records = (self.regions.bounds_base - self.regions.grab_base) as usize;
        let zeros = vec![0u8; records * 16];
        queue.write_buffer(
            &self.b.state.aux,
            self.regions.grab_base as u64 * 16,
            &zeros,
        );
    }

    /// Cluster states ([`GpuClusterState`]: warm-start rotation and XPBD multipliers),
    /// level 0's clusters first (then the hierarchy's coarse levels).
    pub fn cluster_states(&self) -> &Buffer {
        &self.b.state.cstate
    }

    /// Positions buffer (vec4 per particle, m, from offset 0; the predicted positions
    /// follow every level's particles).
    pub fn positions(&self) -> &Buffer {
        &self.b.state.x
    }

    /// Velocities buffer (vec4 per particle, m/s).
    pub fn velocities(&self) -> &Buffer {
        &self.b.state.v
    }

    /// Contact candidate lists (`contact_neighbours()` per particle, `u32::MAX` padded).
    pub fn contact_lists(&self) -> &Buffer {
        &self.b.state.contacts
    }

    /// Forgets the previous neighbour searches, so that the next ones run the cold
    /// variant. A search after the first starts from each particle's previous list,
    /// whose distances bound the K-th best from above; the result is the same either way,
    /// only the time differs (benchmarks time both).
    pub fn forget_neighbours(&mut self) {
        self.knn_warm = false;
        self.contacts_warm = false;
    }

    /// Output of [`GpuWorld::record_knn_all`] (`knn_k` per particle).
    pub fn knn_lists(&self) -> &Buffer {
        &self.b.state.knn_out
    }

    /// Collider forces buffer: after a step, vec4 (N) per collider at
    /// [`GpuWorld::force_offset`].
    pub fn forces(&self) -> &Buffer {
        &self.b.state.forces
    }

    /// Byte offset of the collider force totals in [`GpuWorld::forces`].
    pub fn force_offset(&self) -> u64 {
        self.n_colliders as u64 * FORCE_GROUPS as u64 * 16
    }

    /// Per-body divergence flags (u32 per body; nonzero once a particle of the body
    /// diverged and was held). Clear with [`GpuWorld::clear_status`].
    pub fn status(&self) -> &Buffer {
        &self.b.state.status
    }

    /// Per-body bounding boxes of the particles (two vec4 per body: min, max; m, world
    /// frame; the min's w is the body's divergence flag, the max's w its fastest
    /// particle's speed in m/s), written by [`GpuWorld::record_bounds`] (and at each
    /// contact refresh); after them, one vec4 per body whose x is the contact broad
    /// phase's flag (1: near another body at the last refresh) and y how many bodies are
    /// near it; after those, per body the indices of the bodies near it (`NEAR_SLOTS`
    /// u32, when that many or fewer). Returns the buffer and the byte offset of the first
    /// body's box.
    pub fn bounds(&self) -> (&Buffer, u64) {
        (&self.b.state.aux, self.regions.bounds_base as u64 * 16)
    }

    /// The contact broad phase's flags of the last contact refresh, one per body in model
    /// order (true: near another body), read back from [`GpuWorld::bounds`] (blocking:
    /// for tests and benchmarks).
    pub fn read_near_flags(&self, device: &RenderDevice, queue: &RenderQueue) -> Vec<bool> {
        let (nb, cap) = (self.ranges.len(), self.cap.bodies as usize);
        let (buffer, at) = self.bounds();
        let bytes = read_buffer(device, queue, buffer, at, (3 * cap * 16) as u64);
        let words: Vec<u32> = bytemuck::pod_collect_to_vec(&bytes);
        (0..nb)
            .map(|b| f32::from_bits(words[(2 * cap + b) * 4]) != 0.0)
            .collect()
    }

    /// Records the per-body bounding boxes of the current positions.
    pub fn record_bounds(
        &self,
        encoder: &mut CommandEncoder,
        k: &Kernels,
        rec: &mut dyn PassRecorder,
    ) {
        let groups = plan::per_body_groups(self.ranges.len() as u32);
        let mut r = Recording::new(encoder, rec, &self.binds);
        r.dispatch("tissue/bounds", &k.body_bounds, Bound::None, groups);
    }

    /// Clears the divergence flags.
    pub fn clear_status(&self, encoder: &mut CommandEncoder) {
        encoder.clear_buffer(&self.b.state.status, 0, None);
    }

    /// Colliders in use.
    pub fn collider_count(&self) -> u32 {
        self.n_colliders
    }

    /// Replaces the colliders (at most [`MAX_COLLIDERS`]; extra ones are an error).
    pub fn set_colliders(
        &mut self,
        queue: &RenderQueue,
        colliders: &[Collider],
    ) -> Result<(), TissueError> {
        let data = super::buffers::pack_colliders(
            colliders,
            MAX_COLLIDERS,
            "at most 128 colliders per world",
        )?;
        if !data.is_empty() {
            queue.write_buffer(&self.b.frame.colliders, 0, bytemuck::cast_slice(&data));
        }
        self.n_colliders = colliders.len() as u32;
        Ok(())
    }

    /// Writes the per-body draw records (one per body, in model order).
    pub fn set_draw(&self, queue: &RenderQueue, draw: &[GpuDrawBody]) {
        if !draw.is_empty() {
            queue.write_buffer(&self.b.frame.draw, 0, bytemuck::cast_slice(draw));
        }
    }

    /// Draw records for the world's own [`GpuWorld::surface`] with every body drawn in
    /// world space.
    pub fn surface_draw(&self) -> Vec<GpuDrawBody> {
        self.ranges
            .iter()
            .map(|r| GpuDrawBody::new(glam::Affine3A::IDENTITY, r.vfirst * 8, r.vfirst, 8))
            .collect()
    }

    /// Moves pinned particles' targets (same order as `Model::pinned`), m.
    pub fn set_pin_targets(&self, queue: &RenderQueue, targets: &[Vec3]) {
        let data: Vec<[f32; 4]> = targets.iter().map(|p| p.extend(0.0).to_array()).collect();
        if !data.is_empty() {
            let at = self.regions.pin_base as u64 * 16;
            queue.write_buffer(&self.b.model.rest, at, bytemuck::cast_slice(&data));
        }
    }

    /// Takes `settings` for the steps recorded from now on without rebuilding the world,
    /// where what they change is per-step: gravity, dt and substeps, damping, the
    /// relaxations, iterations (shape matching's per-iteration stiffness is rewritten),
    /// rotation iterations, the divergence speed, the contact search interval and the
    /// hierarchy's coarse iterations. Returns `Ok(false)` and changes nothing where a new
    /// world is needed: particle contacts switched, another contact-neighbour count, or
    /// contacts every more iterations than the world's records were made for. Write the
    /// parameters ([`GpuWorld::write_params`]) before the next steps.
    pub fn set_settings(
        &mut self,
        queue: &RenderQueue,
        settings: SolverSettings,
    ) -> Result<bool, TissueError> {
        settings.validate()?;
        let old = &self.settings;
        if settings.particle_contacts != old.particle_contacts
            || settings.contact_neighbours != old.contact_neighbours
            || plan::max_block(&settings) > self.block_records
        {
            return Ok(false);
        }
        if settings.iterations != old.iterations {
            for (b, k) in self.stiffness.iter().enumerate() {
                let Some(k) = k else { continue };
                let k_iter = crate::core::constraints::iteration_stiffness(*k, settings.iterations);
                let offset =
                    (b * size_of::<GpuBody>() + std::mem::offset_of!(GpuBody, k_iter)) as u64;
                queue.write_buffer(&self.b.model.bodies, offset, bytemuck::bytes_of(&k_iter));
            }
        }
        step_params(&mut self.params, &settings);
        self.settings = settings;
        Ok(true)
    }

    /// Writes the per-step constants (call before submitting recorded steps).
    pub fn write_params(&mut self, queue: &RenderQueue) {
        self.params.n_colliders = self.n_colliders;
        queue.write_buffer(&self.b.frame.params, 0, bytemuck::bytes_of(&self.params));
    }

    /// What the dispatch plan needs of the world.
    fn shape(&self) -> plan::Shape<'_> {
        plan::Shape {
            n: self.n,
            bodies: self.ranges.len() as u32,
            colliders: self.n_colliders,
            contacts_on: self.contacts_on,
            contact_k: self.contact_k,
            body_kernel: self.has_body_kernel && self.body_kernel(),
            all_in_body: self.body_fits.iter().all(|f| *f),
            coarse: &self.coarse,
            scan_levels: &self.levels,
            scan_len: self.scan_len,
            grid_table: self.params.grid_table,
            iteration_records: self.iteration_records,
            block_records: self.block_records,
            lanes_below: self.lane_clusters_below,
        }
    }

    /// Records the exact K nearest neighbours of every particle (K = `knn_k` given at
    /// creation) into [`GpuWorld::knn_lists`], grid included.
    pub fn record_knn_all(
        &mut self,
        encoder: &mut CommandEncoder,
        k: &Kernels,
        rec: &mut dyn PassRecorder,
    ) {
        let plan = plan::knn_all(&self.shape(), self.knn_k, self.knn_warm);
        self.knn_warm = true;
        record::replay(encoder, rec, &self.binds, k, &plan);
    }

    /// Records `steps` time steps ([`plan::steps`]; one compute pass, unless the
    /// recorder times passes). Call [`GpuWorld::write_params`] before submitting.
    /// Within a recording a substep's finish also predicts the next substep (one
    /// dispatch fewer each), so colliders, pin targets and sleep flags set before the
    /// call hold for all its steps.
    pub fn record_steps(
        &mut self,
        encoder: &mut CommandEncoder,
        k: &Kernels,
        steps: u32,
        rec: &mut dyn PassRecorder,
    ) {
        let mut cursor = plan::Cursor {
            step: self.step,
            contacts_warm: self.contacts_warm,
            refresh: self.refresh_contacts,
        };
        let plan = plan::steps(&self.shape(), &self.settings, &mut cursor, steps);
        self.step = cursor.step;
        self.contacts_warm = cursor.contacts_warm;
        self.refresh_contacts = cursor.refresh;
        record::replay(encoder, rec, &self.binds, k, &plan);
    }

    /// The bind groups that let the draw kernels write into `slab` (the world's own
    /// [`GpuWorld::surface`] or a mesh allocator slab). Callers keep them while the slab
    /// lives (the plugin caches one per slab buffer).
    pub fn slab_group(&self, device: &RenderDevice, k: &Kernels, slab: &Buffer) -> SlabGroup {
        let resource = |name: &str| -> Option<BindingResource<'_>> {
            match name {
                "slab" => Some(slab.as_entire_binding()),
                "span" => Some(BindingResource::Buffer(BufferBinding {
                    buffer: &self.records.spans,
                    offset: 0,
                    size: std::num::NonZeroU64::new(size_of::<u32>() as u64 * 4),
                })),
                _ => None,
            }
        };
        let group = |kernel: &kernels::Kernel| -> BindGroup {
            match kernel.groups.get(3) {
                Some((layout, uses)) => bind_group(device, kernel.name, layout, uses, &resource),
                None => {
                    let layout = device.create_bind_group_layout(kernel.name, &[]);
                    device.create_bind_group(kernel.name, &layout, &[])
                }
            }
        };
        SlabGroup {
            skin: group(&k.skin),
            normals: group(&k.normals),
        }
    }

    /// Records the draw path: deformation gradients once, then for every slab (its
    /// groups from [`GpuWorld::slab_group`]) and every run `(first vertex, end)` of bodies
    /// whose vertices live in it, skinning and normals. The draw records
    /// ([`GpuWorld::set_draw`]) say where each body's vertices are. At most
    /// [`MAX_SKIN_RUNS`] runs in all.
    pub fn record_draw(
        &self,
        queue: &RenderQueue,
        encoder: &mut CommandEncoder,
        k: &Kernels,
        slabs: &[(&SlabGroup, &[(u32, u32)])],
        rec: &mut dyn PassRecorder,
    ) {
        // Every run gets its own range record (one write), so runs of different slabs
        // never share an offset.
        let mut jobs: Vec<(&SlabGroup, u32, u32, u32)> = Vec::new();
        for (group, runs) in slabs {
            for &(b, e) in runs.iter() {
                if jobs.len() < MAX_SKIN_RUNS {
                    let off = (jobs.len() * size_of::<GpuSkinRange>()) as u32;
                    jobs.push((group, off, b, e));
                }
            }
        }
        if jobs.is_empty() {
            return;
        }
        let recs: Vec<GpuSkinRange> = jobs
            .iter()
            .map(|&(_, _, b, e)| GpuSkinRange {
                begin: b,
                end: e,
                pad: [0; 62],
            })
            .collect();
        queue.write_buffer(&self.records.spans, 0, bytemuck::cast_slice(&recs));
        let g = groups(self.n, WORKGROUP);
        let mut r = Recording::new(encoder, rec, &self.binds);
        r.dispatch("tissue/deform", &k.deform, Bound::None, (g, 1));
        for &(group, off, b, e) in &jobs {
            let wg = groups(e.saturating_sub(b), WORKGROUP);
            r.dispatch(
                "tissue/skin",
                &k.skin,
                Bound::Slab(&group.skin, off),
                (wg, 1),
            );
        }
        for &(group, off, b, e) in &jobs {
            let wg = groups(e.saturating_sub(b), WORKGROUP);
            let slab = Bound::Slab(&group.normals, off);
            r.dispatch("tissue/normals", &k.normals, slab, (wg, 1));
        }
    }

    /// Copies body `from`'s positions, velocities, cluster states and grabs onto body
    /// `to` (the same particle count; model order), through a temporary buffer (a buffer
    /// cannot be copied onto itself): a body appended anew for a new model keeps the pose
    /// of its old slot. Does nothing where the counts differ.
    pub fn copy_body_state(
        &self,
        device: &RenderDevice,
        queue: &RenderQueue,
        from: usize,
        to: usize,
    ) {
        let (Some(f), Some(t)) = (self.ranges.get(from), self.ranges.get(to)) else {
            return;
        };
        if f.count != t.count || f.count == 0 {
            return;
        }
        let c = f.count as u64;
        let grab = self.regions.grab_base as u64 * 16;
        let parts: [(&Buffer, u64, u64); 4] = [
            (&self.b.state.x, 0, 16),
            (&self.b.state.v, 0, 16),
            (&self.b.state.cstate, 0, 48),
            (&self.b.state.aux, grab, 16),
        ];
        let temp = device.create_buffer(&bevy::render::render_resource::BufferDescriptor {
            label: Some("tissue body state"),
            size: c * (16 + 16 + 48 + 16),
            usage: BufferUsages::COPY_SRC | BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut enc = device.create_command_encoder(&Default::default());
        let mut at = 0;
        for &(buffer, base, stride) in &parts {
            enc.copy_buffer_to_buffer(
                buffer,
                base + f.first as u64 * stride,
                &temp,
                at,
                c * stride,
            );
            at += c * stride;
        }
        at = 0;
        for &(buffer, base, stride) in &parts {
            enc.copy_buffer_to_buffer(
                &temp,
                at,
                buffer,
                base + t.first as u64 * stride,
                c * stride,
            );
            at += c * stride;
        }
        queue.submit([enc.finish()]);
    }

    /// Copies `count` particles' positions, velocities, cluster states and grabs starting at
    /// `from` in `other` to `to` in this world (GPU to GPU: a rebuilt world keeps the
    /// pose of the bodies it had).
    pub fn copy_state_from(
        &self,
        encoder: &mut CommandEncoder,
        other: &GpuWorld,
        from: u32,
        to: u32,
        count: u32,
    ) {
        let (f, t, c) = (from as u64, to as u64, count as u64);
        encoder.copy_buffer_to_buffer(&other.b.state.x, f * 16, &self.b.state.x, t * 16, c * 16);
        encoder.copy_buffer_to_buffer(&other.b.state.v, f * 16, &self.b.state.v, t * 16, c * 16);
        encoder.copy_buffer_to_buffer(
            &other.b.state.cstate,
            f * 48,
            &self.b.state.cstate,
            t * 48,
            c * 48,
        );
        let (from_grab, to_grab) = (
            other.regions.grab_base as u64 * 16,
            self.regions.grab_base as u64 * 16,
        );
        encoder.copy_buffer_to_buffer(
            &other.b.state.aux,
            from_grab + f * 16,
            &self.b.state.aux,
            to_grab + t * 16,
            c * 16,
        );
    }
}
