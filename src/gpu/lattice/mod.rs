//! [`GpuLattice`]: Newton–multigrid for lattice bodies on the GPU
//! ([`crate::core::solver::ElementSolver::Multigrid`]'s algorithm, kernels in
//! [`super::kernels::lattice`]).
//!
//! Each substep: predict the inertial target and the first iterate; then per Newton
//! iteration the element forces and rotations, the residual, the Newton step — one
//! V-cycle of the configured smoother on every level of the hierarchy
//! (Chebyshev-accelerated block Jacobi, one dispatch a sweep, or block Gauss–Seidel by
//! colour; coarse corrections taken with their energy-minimising step), or conjugate
//! gradients preconditioned by several — a trust region and a backtracking line search
//! on the substep energy; finally the velocity update. The sequence of dispatches
//! is [`plan`], a pure function of the hierarchy's shape and the settings; recording
//! replays it. Scope: lattice bodies with pins, colliders and graspers under gravity
//! (particle contacts between bodies, collider forces and the divergence check stay on
//! the CPU path).

use super::buffers::GpuCollider;
use super::kernels::lattice::{
    FACTOR_STRIDE, Kernel, LatticeKernels, MAX_COLLIDERS, SLOTS, WORKGROUP,
};
use crate::core::TissueError;
use crate::core::colliders::Collider;
use crate::core::model::{Discretisation, Material, Model};
use crate::core::multigrid::{
    COLOURS, EXACT_COARSEST, LatticeMultigrid, MAX_LEVELS as MG_LEVELS, Smoother, Sweeps,
};
use crate::core::solver::{SolverSettings, State};
use bevy::render::render_resource::{
    BindGroup, BindGroupEntry, BindingResource, Buffer, BufferBinding, BufferUsages,
    CommandEncoder, ComputePassDescriptor,
};
use bevy::render::renderer::{RenderDevice, RenderQueue};
use bytemuck::{Pod, Zeroable};
use glam::{Quat, Vec3};
use layout::{Buf, Layout, Writes};

mod append;
mod carry;
mod layout;
pub(crate) use layout::MAT_RECORD;

pub use append::{AppendBasis, PreparedAppend};
pub use carry::StateRun;

/// Byte stride of the per-dispatch records (the minimum uniform offset alignment
/// WebGPU guarantees).
const PASS_STRIDE: u64 = 256;
/// Levels the parameter block holds.
const MAX_LEVELS: usize = 8;
/// Floats per workgroup's partial sums (at the start of `red`; see `lattice.wgsl`).
const RED_STRIDE: usize = 16;
/// Most workgroups of the collider forces' reduction (see [`reduction_groups`]).
const MAX_PARTIALS: u32 = 1024;
/// Most chunks a body's items make in one reduction table: a chunk holds a multiple of
/// [`WORKGROUP`] items, as few as that allows (see [`chunk_table`]).
const MAX_BODY_CHUNKS: usize = 1024;
/// Floats of each body's scalars in `red` (`BODY_SLOTS` in `lattice.wgsl`).
const BODY_SLOTS: usize = 16;
/// Most workgroups of a `pick` (they stride over the bodies).
const MAX_PICK_GROUPS: u32 = 65_535;
/// Most workgroups of a Chebyshev sweep (they stride over larger levels).
const CHEBYSHEV_GROUPS: u32 = 8192;
/// A smoothing pass's mode bit (`ROW_MODE` in the shader): one thread a node.
const ROW_MODE: u32 = 0x10000;
/// A Chebyshev sweep's mode bit (`COPY_MODE` in the shader): its result copied for level
/// 0's contact pass.
const COPY_MODE: u32 = 0x20000;
/// [`LatticeOptions::fused_coarsest`]'s default and its most: up to four rounds of 32
/// nodes a sweep in a body's workgroup, the body's iterates in its workgroup memory
/// (`COARSEST_NODES` in the shader).
pub const FUSED_COARSEST: u32 = 128;
/// Where no body has more than this many nodes on a fused coarsest level, its sweeps run
/// in `smooth_coarsest_small`, whose threads (eight a node) each hold one element's data
/// from sweep to sweep rather than room for four: fewer registers, more bodies at once
/// on the GPU. The same sums as `smooth_coarsest`'s.
pub const SMALL_COARSEST: u32 = 32;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Params {
    gravity: [f32; 4],
    h: f32,
    h2: f32,
    keep: f32,
    rot_iters: u32,
    n: u32,
    ne: u32,
    levels: u32,
    n_total: u32,
    order_base: u32,
    prol_base: u32,
    restr_base: u32,
    child_base: u32,
    lv: [[u32; 4]; MAX_LEVELS],
    sweeps: [u32; 4],
    colours: [[u32; 4]; 2 * MAX_LEVELS * COLOURS / 4],
    misc: [u32; 4],
    cheb: [[f32; 4]; MAX_LEVELS],
    pair: [u32; 4],
    chunks: [u32; 4],
    count: [u32; 4],
    nbrs: [u32; 4],
}

/// Byte offset of `misc` (the collider count first) in the parameter block.
const MISC_OFFSET: u64 = std::mem::offset_of!(Params, misc) as u64;

/// One dispatch's range and mode (`Pass` in `lattice.wgsl`).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Pod, Zeroable)]
pub struct PassRecord {
    /// First node or element (or position in the colour order).
    pub first: u32,
    /// Nodes or elements (or partial sums to add, for `pick`).
    pub count: u32,
    /// Level.
    pub level: u32,
    /// Mode (see the kernel).
    pub mode: u32,
}

/// One dispatch of the plan.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Dispatch {
    /// The kernel.
    pub kernel: Kernel,
    /// Its range and mode.
    pub pass: PassRecord,
    /// Workgroups (at most: an indirect dispatch takes its count from the GPU).
    pub groups: u32,
    /// Where the workgroup count is, where a kernel before it writes it: the `args`
    /// word ([`ARGS_LINE`], [`ARGS_PENDING`], [`ARGS_CONTACT`]); `None`, `groups`.
    pub indirect: Option<u32>,
}

/// `args` word of the line search's second energy pass's workgroups (set by the first
/// pass's `pick` where some body's first candidates all failed; else 0).
pub const ARGS_LINE: u32 = 0;
/// `args` word of that second pass's `pick` (set with [`ARGS_LINE`]).
pub const ARGS_PENDING: u32 = 4;
/// `args` word of level 0's contact pass after the Chebyshev sweeps (set by `contacts`
/// where some node has a contact block, cleared by `residual` before it).
pub const ARGS_CONTACT: u32 = 8;
/// `args` word of the length of the list of level-0 nodes with a contact block that
/// `contacts` makes for the contact pass (set with [`ARGS_CONTACT`], which is the list's
/// workgroups).
pub const ARGS_CONTACT_COUNT: u32 = 12;

/// The indirect dispatches' `args`: three (x, y, z) workgroup counts, each padded to four
/// words, x 0 until a kernel sets it; then the contact list's length.
const ARGS_INITIAL: [u32; 16] = [0, 1, 1, 0, 0, 1, 1, 0, 0, 1, 1, 0, 0, 0, 0, 0];

/// Whether dispatch `d` makes the colliders' reactions (their forces at the substep's
/// end and the sums of them): nothing to do without colliders.
fn for_reactions(d: &Dispatch) -> bool {
    matches!(d.kernel, Kernel::ForcePartials | Kernel::ForceTotal)
        || (d.kernel == Kernel::Forces && d.pass.mode == 1)
}

/// Whether dispatch `d` makes or takes the level-0 contact blocks (`contacts`, and
/// the contact pass after the Chebyshev sweeps): nothing to do where nothing can touch
/// (no colliders, no particle contacts), where the kernels read every contact block as
/// zero.
fn for_contacts(d: &Dispatch) -> bool {
    matches!(d.kernel, Kernel::Contacts | Kernel::ContactSmooth)
}

/// Whether dispatch `d` of the plan is recorded in a world with `colliders` and, if
/// `pairs`, particle contacts between its bodies.
fn runs(d: &Dispatch, colliders: bool, pairs: bool) -> bool {
    (colliders || !for_reactions(d)) && (colliders || pairs || !for_contacts(d))
}

/// The shape of a hierarchy as the plan needs it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Shape {
    /// Per level: first node, node count, first element, element count.
    pub levels: Vec<[u32; 4]>,
    /// Per level and colour: where its nodes start and end in the colour order
    /// (absolute positions in the topology buffer).
    pub colours: Vec<[[u32; 2]; COLOURS]>,
    /// The reductions' tables (0: the energy's elements and nodes; 1 + l: level l's
    /// nodes): each one's first chunk and chunk count. Every workgroup of a reduction sums
    /// one chunk, a run of one body's items.
    pub tables: Vec<[u32; 2]>,
    /// Bodies (each `pick` decides per body).
    pub bodies: u32,
    /// How each level is smoothed.
    pub smoother: Smoother,
    /// With particle contacts between bodies: their projection runs after every this
    /// many Newton iterations and after the last (as the CPU's `contact_every`).
    pub pairs: Option<u32>,
    /// V-cycles per Newton iteration (more than 1: conjugate gradients preconditioned
    /// by them, [`SolverSettings::newton_cycles`]).
    pub cycles: u32,
    /// The V-cycle's smoothing sweeps ([`SolverSettings::sweeps`]).
    pub sweeps: Sweeps,
    /// The most nodes one body has on the coarsest level.
    pub most_coarsest: u32,
    /// [`LatticeOptions::fused_coarsest`].
    pub fused_coarsest: u32,
    /// [`LatticeOptions::one_thread_rows_from`].
    pub one_thread_rows_from: u32,
    /// The world keeps each body's coarsest-level factor between V-cycles
    /// ([`LatticeOptions::keep_coarsest_factor`], and the factor buffer fits the device).
    pub factor_kept: bool,
}

impl Shape {
    /// Whether the coarsest level's sweeps run in one dispatch (`smooth_coarsest`, or
    /// `smooth_coarsest_small` up to [`SMALL_COARSEST`] nodes a body; a workgroup per
    /// body): it is smoothed by Chebyshev, below level 0, and no body has
    /// more than [`Shape::fused_coarsest`] nodes there (nor more than
    /// [`FUSED_COARSEST`]).
    pub fn coarsest_fused(&self) -> bool {
        let l = self.levels.len().saturating_sub(1);
        l > 0
            && self.smoother.on_level(l) == Smoother::Chebyshev
            && self.most_coarsest <= self.fused_coarsest.min(FUSED_COARSEST)
    }

    /// Whether the coarsest level is solved exactly (`solve_coarsest`, a workgroup per
    /// body; [`LatticeMultigrid::coarsest_exact`]): [`Sweeps::exact_coarsest`], below
    /// level 0, and no body has more than [`EXACT_COARSEST`] nodes there.
    pub fn coarsest_exact(&self) -> bool {
        self.sweeps.exact_coarsest
            && self.levels.len() > 1
            && self.most_coarsest as usize <= EXACT_COARSEST
    }

    /// Whether the coarsest level, solved exactly, is factorised once a Newton iteration
    /// (`factor_coarsest`) and solved from that factor in each V-cycle
    /// (`solve_factored`), rather than assembled and factorised in each V-cycle
    /// (`solve_coarsest`). The answers are the same.
    pub fn coarsest_factored(&self) -> bool {
        self.coarsest_exact() && self.factor_kept
    }
}

/// How [`GpuLattice`] schedules its work (the answer is the same either way).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LatticeOptions {
    /// Line-search candidates (of 13) tried in the first energy pass; the rest in a
    /// second pass only for the bodies none of these lowers the energy of. Default 4.
    pub first_candidates: u32,
    /// Room for bodies appended later ([`GpuLattice::append`]), as a multiple of what
    /// the world's bodies take, plus one more of their largest; at most 1: none.
    /// Default 1.
    pub room: f32,
    /// The coarsest level's smoothing sweeps run in one dispatch, a workgroup per body,
    /// where no body has more than this many nodes there (and the level is smoothed by
    /// Chebyshev); otherwise a dispatch a sweep. 0: never. Default and most
    /// [`FUSED_COARSEST`], 128 (a larger value counts as 128: the dispatch keeps a body's
    /// iterates in its workgroup memory).
    pub fused_coarsest: u32,
    /// A smoothing pass (a Gauss–Seidel colour or a Chebyshev sweep, but the fused
    /// coarsest level) over at least this many nodes sums each node's row in one thread,
    /// its elements in a loop; a smaller one in eight threads, one element each, summed
    /// through workgroup memory. Eight threads a node keep a small pass's GPU busy; one
    /// thread a node skips the workgroup sums where there are nodes enough to fill it.
    /// The sums' order differs, so the answers differ by rounding. 0: always one thread a
    /// node; `u32::MAX`: never. Default 16,384.
    pub one_thread_rows_from: u32,
    /// Where the coarsest level is solved exactly ([`Sweeps::exact_coarsest`]), each
    /// body's matrix is factorised once a Newton iteration and the factor kept for its
    /// V-cycles (the matrix does not change between them), at 4 × `FACTOR_STRIDE` bytes
    /// a body (about 14 KB); false, or where that buffer would pass the device's largest
    /// storage binding, each V-cycle assembles and factorises it again. The answer is
    /// the same either way. Default true.
    pub keep_coarsest_factor: bool,
}

/// [`LatticeOptions::one_thread_rows_from`]'s default.
pub const ONE_THREAD_ROWS_FROM: u32 = 16_384;

impl Default for LatticeOptions {
    fn default() -> Self {
        Self {
            first_candidates: 4,
            room: 1.0,
            fused_coarsest: FUSED_COARSEST,
            one_thread_rows_from: ONE_THREAD_ROWS_FROM,
            keep_coarsest_factor: true,
        }
    }
}

/// Workgroups of a `pick`: one per body, striding over the bodies past the most one
/// dispatch takes.
fn pick_groups(shape: &Shape) -> u32 {
    shape.bodies.clamp(1, MAX_PICK_GROUPS)
}

fn groups(count: u32) -> u32 {
    count.div_ceil(WORKGROUP)
}

/// Workgroups of the collider forces' reduction over `count` items (each thread strides
/// over several when there are many, so that the single-workgroup sum after it reads few
/// partials).
fn reduction_groups(count: u32) -> u32 {
    groups(count).min(MAX_PARTIALS)
}

/// The dispatches of one substep with `newton` Newton iterations.
pub fn plan(shape: &Shape, newton: u32) -> Vec<Dispatch> {
    let mut out = Vec::new();
    let (n, ne) = (shape.levels[0][1], shape.levels[0][3]);
    let mut push = |kernel, first, count, level, mode, groups: u32| {
        if groups > 0 {
            out.push(Dispatch {
                kernel,
                pass: PassRecord {
                    first,
                    count,
                    level,
                    mode,
                },
                groups,
                indirect: None,
            });
        }
    };
    let picks = pick_groups(shape);
    let [e0, ec] = shape.tables[0];
    let [n0, nc] = shape.tables[1];
    push(Kernel::Predict, 0, n, 0, 0, groups(n));
    for it in 0..newton {
        if it == 0 {
            push(Kernel::EnergyFirst, e0, ec, 0, 0, ec);
            push(Kernel::Pick, 0, ec, 0, 0, picks);
            push(Kernel::Advance, 0, n, 0, 0, groups(n));
        }
        push(Kernel::Forces, 0, ne, 0, 0, groups(ne));
        push(Kernel::Residual, 0, n, 0, 0, groups(n));
        push(Kernel::Contacts, 0, n, 0, 0, groups(n));
        // Each coarse level's rotations and contact stiffness from the finer level's,
        // one dispatch a level.
        for (l, lv) in shape.levels.iter().enumerate().skip(1) {
            let items = lv[1].max(lv[3]);
            push(
                Kernel::CoarsenLevel,
                lv[0],
                items,
                l as u32,
                0,
                groups(items),
            );
        }
        // Every level's diagonal blocks at once (a node's block reads only its own
        // level's rotations and contact blocks, all made above).
        let total = shape.levels.last().map_or(0, |lv| lv[0] + lv[1]);
        push(Kernel::Diag, 0, total, 0, 0, groups(total));
        // The coarsest level's factor for this iteration's V-cycles (its matrix reads the
        // rotations and contact blocks made above).
        if shape.coarsest_factored() {
            let l = shape.levels.len() - 1;
            let [t0, tn] = shape.tables[1 + l];
            push(Kernel::FactorCoarsest, t0, tn, l as u32, 0, picks);
        }
        if shape.cycles <= 1 {
            // The two-direction step (LatticeMultigrid::two_direction): the V-cycle's
            // correction and the last solve's answer, weighted per body; its update takes
            // each body's trust bound, as conjugate gradients' last does.
            // Its sums go element by element, over the energy table.
            vcycle(shape, 0, &mut push);
            push(Kernel::CgTwoTerms, e0, ec, 0, 0, ec);
            push(Kernel::Pick, 0, ec, 0, 8, picks);
            push(Kernel::CgUpdate, 0, n, 0, 4 | 2, groups(n));
        } else {
            // Conjugate gradients, a V-cycle per iteration (LatticeMultigrid::krylov).
            for k in 0..shape.cycles {
                vcycle(shape, 0, &mut push);
                if k > 0 {
                    push(Kernel::CgDots, n0, nc, 0, 0, nc);
                    push(Kernel::Pick, 0, nc, 0, 5, picks);
                }
                push(Kernel::CgDirection, 0, n, 0, k.min(1), groups(n));
                push(Kernel::CgMatvec, n0, nc, 0, 0, nc);
                push(Kernel::Pick, 0, nc, 0, 6, picks);
                let last = (k + 1 == shape.cycles) as u32;
                push(Kernel::CgUpdate, 0, n, 0, k.min(1) | last << 1, groups(n));
            }
        }
        // The last update took each body's trust bound.
        push(Kernel::TrustScale, 0, n, 0, 0, groups(n));
        push(Kernel::Energy, e0, ec, 0, 1, ec);
        push(Kernel::Pick, 0, ec, 0, 1, picks);
        push(Kernel::Energy, e0, ec, 0, 2, ec);
        push(Kernel::PickPending, 0, ec, 0, 4, picks);
        let pairs = shape
            .pairs
            .is_some_and(|every| (it + 1) % every.max(1) == 0 || it + 1 == newton);
        if pairs {
            push(Kernel::Advance, 0, n, 0, 1, groups(n));
            push(Kernel::PairProject, 0, n, 0, 0, groups(n));
            push(Kernel::Boundary, 0, n, 0, 1, groups(n));
        } else {
            // The step and the boundary's projection in one pass (mode bit 1).
            push(Kernel::Advance, 0, n, 0, 1 | 2, groups(n));
        }
    }
    // The element forces at the substep's end, for the colliders' reactions.
    push(Kernel::Forces, 0, ne, 0, 1, groups(ne));
    push(Kernel::Finish, 0, n, 0, 0, groups(n));
    push(Kernel::ForcePartials, 0, n, 0, 0, reduction_groups(n));
    push(Kernel::ForceTotal, 0, reduction_groups(n), 0, 0, 1);
    for d in &mut out {
        d.indirect = match (d.kernel, d.pass.mode) {
            (Kernel::Energy, 2) => Some(ARGS_LINE),
            (Kernel::PickPending, _) => Some(ARGS_PENDING),
            (Kernel::ContactSmooth, _) => Some(ARGS_CONTACT),
            _ => None,
        };
    }
    out
}

fn sweeps(
    shape: &Shape,
    l: usize,
    count: u32,
    push: &mut impl FnMut(Kernel, u32, u32, u32, u32, u32),
) {
    // Eight threads a node (one element each) or, over enough nodes, one (`ROW_MODE`,
    // see `smooth_colour`).
    let rows = |len: u32| {
        if len >= shape.one_thread_rows_from {
            (ROW_MODE, WORKGROUP)
        } else {
            (0, 8)
        }
    };
    if shape.smoother.on_level(l) == Smoother::Chebyshev {
        // An even count ends in the correction's own region (see `chebyshev_node`).
        debug_assert!(count.is_multiple_of(2), "Chebyshev sweeps come in pairs");
        let [first, len, _, _] = shape.levels[l];
        let (mode, per_group) = rows(len);
        // Level 0's last sweep copies its result for the contact pass after it
        // (`LatticeMultigrid`'s `contact_pass`).
        let contacts = l == 0 && count > 0;
        for k in 0..count {
            let copy = if contacts && k + 1 == count {
                COPY_MODE
            } else {
                0
            };
            push(
                Kernel::Chebyshev,
                first,
                len,
                l as u32,
                k | mode | copy,
                len.div_ceil(per_group).min(CHEBYSHEV_GROUPS),
            );
        }
        if contacts {
            push(Kernel::ContactSmooth, first, len, 0, 0, groups(len));
        }
        return;
    }
    let c = &shape.colours[l];
    for _ in 0..count {
        for [start, end] in c {
            let len = end - start;
            let (mode, per_group) = rows(len);
            push(
                Kernel::Smooth,
                *start,
                len,
                l as u32,
                mode,
                len.div_ceil(per_group),
            );
        }
    }
}

fn vcycle(shape: &Shape, l: usize, push: &mut impl FnMut(Kernel, u32, u32, u32, u32, u32)) {
    if l + 1 == shape.levels.len() {
        let count = shape.sweeps.on_level(l, true, shape.smoother);
        if shape.coarsest_exact() {
            let [t0, tn] = shape.tables[1 + l];
            let kernel = if shape.coarsest_factored() {
                Kernel::CoarsestFactored
            } else {
                Kernel::CoarsestExact
            };
            push(kernel, t0, tn, l as u32, 0, pick_groups(shape));
        } else if shape.coarsest_fused() {
            // Every sweep in one dispatch, a workgroup per body (its nodes from the
            // level's reduction table).
            let [t0, tn] = shape.tables[1 + l];
            let kernel = if shape.most_coarsest <= SMALL_COARSEST {
                Kernel::CoarsestSmall
            } else {
                Kernel::Coarsest
            };
            push(kernel, t0, tn, l as u32, count, pick_groups(shape));
        } else {
            sweeps(shape, l, count, push);
        }
        return;
    }
    let count = shape.sweeps.on_level(l, false, shape.smoother);
    let before = shape.sweeps.before_on_level(l, shape.smoother);
    let lv = shape.levels[l];
    let cv = shape.levels[l + 1];
    let ll = l as u32;
    sweeps(shape, l, before, push);
    // Unsmoothed, the correction is still zero and the residual the right-hand side:
    // no pass makes it (mode 1: the passes that read it read the right-hand side).
    let unsmoothed = (before == 0) as u32;
    if unsmoothed == 0 {
        push(Kernel::FineResidual, lv[0], lv[1], ll, 0, groups(lv[1]));
    }
    // Where the restriction finds the residual: level 0's translation step writes it.
    let mut restrict_mode = unsmoothed;
    if l == 0 && shape.sweeps.translation {
        // Each body's translation step (`translate_bodies`; none with fixed nodes).
        let [n0, nc] = shape.tables[1];
        push(Kernel::TranslateTerms, n0, nc, 0, unsmoothed, nc);
        push(Kernel::Pick, 0, nc, 0, 7, pick_groups(shape));
        push(
            Kernel::Translate,
            lv[0],
            lv[1],
            0,
            unsmoothed,
            groups(lv[1]),
        );
        restrict_mode = 0;
    }
    push(
        Kernel::Restrict,
        cv[0],
        cv[1],
        ll + 1,
        restrict_mode,
        groups(cv[1]),
    );
    vcycle(shape, l + 1, push);
    if l == 0 || shape.coarsest_exact() {
        // Level 0 takes the coarse correction whole: added as it is prolongated (mode 1);
        // so do the levels between where the coarsest level is solved exactly
        // (`LatticeMultigrid::vcycle`).
        push(Kernel::Prolong, lv[0], lv[1], ll, 1, groups(lv[1]));
    } else {
        // The levels between take it with its energy-minimising step.
        push(Kernel::Prolong, lv[0], lv[1], ll, 0, groups(lv[1]));
        let [c0, cn] = shape.tables[1 + l];
        push(Kernel::AlphaTerms, c0, cn, ll, unsmoothed, cn);
        push(Kernel::Pick, 0, cn, ll, 3, pick_groups(shape));
        push(Kernel::Correct, lv[0], lv[1], ll, 0, groups(lv[1]));
    }
    sweeps(shape, l, count, push);
}

/// The `nodes` record of particle `j` (a level-0 node): mass (kg), held, the trust
/// region's reach (half its body's lattice spacing, m), body.
fn particle_node(model: &Model, j: usize, held: bool) -> [f32; 4] {
    let body = model.particle_body[j];
    let reach = 0.5 * model.bodies[body as usize].spacing;
    [model.mass[j], held as u32 as f32, reach, body as f32]
}

fn vec4(v: Vec3) -> [f32; 4] {
    v.extend(0.0).to_array()
}

/// The parameter block of `layout` as packed so far: `cheb` each level's Chebyshev
/// `1/θ` and `ρ²`, `pairs` whether `ccol` holds particle-contact lists.
fn params_of(
    layout: &Layout,
    settings: &SolverSettings,
    options: LatticeOptions,
    cheb: &[[f32; 2]],
    smoother: Smoother,
    pairs: bool,
) -> Params {
    let nl = layout.levels();
    let h = settings.dt / settings.substeps as f32;
    let mut lv = [[0u32; 4]; MAX_LEVELS];
    for (out, (n, e)) in lv.iter_mut().zip(layout.nodes.iter().zip(&layout.elems)) {
        *out = [n.start, n.end(), e.start, e.end()];
    }
    let mut colours = [[0u32; 4]; 2 * MAX_LEVELS * COLOURS / 4];
    for (l, segs) in layout.order.iter().enumerate() {
        for (k, c) in segs.iter().enumerate() {
            let i = l * 2 * COLOURS + 2 * k;
            colours[i / 4][i % 4] = c.start;
            colours[i / 4][i % 4 + 1] = c.end();
        }
    }
    // `red`: the reductions' partial sums (a chunk's each), each body's scalars, the
    // collider forces' partial sums, their totals.
    let body_base = RED_STRIDE as u32 * layout.most_chunks();
    let force_base = body_base + BODY_SLOTS as u32 * layout.bodies.cap;
    let force_partials = 4 * MAX_COLLIDERS as u32 * MAX_PARTIALS;
    Params {
        gravity: vec4(settings.gravity),
        h,
        h2: h * h,
        keep: (1.0 - settings.damping * h).max(0.0),
        rot_iters: settings.rotation_iterations,
        n: layout.n_slots(),
        ne: layout.ne_slots(),
        levels: nl as u32,
        n_total: layout.node_slots(),
        order_base: layout.order[0][0].start,
        prol_base: layout.prol_base,
        restr_base: layout.restr_base,
        child_base: layout.child_base,
        lv,
        sweeps: [
            settings.sweeps.fine,
            settings.sweeps.coarse,
            settings.sweeps.coarsest,
            options.first_candidates,
        ],
        colours,
        misc: [
            0,
            settings.substeps,
            force_base,
            force_base + force_partials,
        ],
        cheb: std::array::from_fn(|l| {
            let [inv_theta, rho2] = cheb.get(l).copied().unwrap_or([1.0, 0.0]);
            let chebyshev = smoother.on_level(l) == Smoother::Chebyshev;
            [inv_theta, rho2, chebyshev as u32 as f32, 0.0]
        }),
        // The contacts' relaxation, never above 1 on lattice bodies (core::solver's rule).
        pair: [
            pairs as u32,
            0,
            settings.contact_relaxation.min(1.0).to_bits(),
            0,
        ],
        chunks: [
            layout.chunk_base,
            layout.starts_base,
            layout.bodies.cap,
            body_base,
        ],
        count: [layout.bodies.used, 0, 0, 0],
        nbrs: [layout.nbr_base, 0, 0, 0],
    }
}

/// The shape the plan needs of `layout` as packed so far.
fn shape_of(
    layout: &Layout,
    smoother: Smoother,
    pairs: Option<u32>,
    cycles: u32,
    sweeps: Sweeps,
    fused_coarsest: u32,
    one_thread_rows_from: u32,
) -> Shape {
    Shape {
        levels: layout
            .nodes
            .iter()
            .zip(&layout.elems)
            .map(|(n, e)| [n.start, n.used, e.start, e.used])
            .collect(),
        colours: layout
            .order
            .iter()
            .map(|segs| segs.map(|c| [c.start, c.end()]))
            .collect(),
        tables: layout.tables.iter().map(|t| [t.start, t.used]).collect(),
        bodies: layout.bodies.used,
        smoother,
        pairs,
        cycles: cycles.max(1),
        sweeps,
        most_coarsest: layout.most_nodes.last().copied().unwrap_or(0),
        fused_coarsest,
        one_thread_rows_from,
        factor_kept: false,
    }
}

/// Entries each of the particle-contact lists (a node's candidates, and the nodes that
/// list it) can hold for `slots` level-0 node slots: the contact neighbours per node when
/// the world has particle contacts between bodies, else 0.
fn pair_capacity(model: &Model, settings: &SolverSettings, slots: usize) -> usize {
    let n = model.particle_count();
    if !settings.particle_contacts || model.bodies.len() < 2 {
        return 0;
    }
    slots * (settings.contact_neighbours as usize).min(n.saturating_sub(1))
}

/// The dispatches of one substep of `shape` with `newton` Newton iterations, their
/// distinct pass records, and each dispatch's record.
fn passes_of(shape: &Shape, newton: u32) -> (Vec<Dispatch>, Vec<PassRecord>, Vec<u32>) {
    let dispatches = plan(shape, newton);
    let mut records: Vec<PassRecord> = Vec::new();
    let mut index = Vec::with_capacity(dispatches.len());
    for d in &dispatches {
        let i = match records.iter().position(|r| *r == d.pass) {
            Some(i) => i,
            None => {
                records.push(d.pass);
                records.len() - 1
            }
        };
        index.push(i as u32);
    }
    (dispatches, records, index)
}

/// The pass buffer's bytes: `records` at [`PASS_STRIDE`], `room` records long.
fn pass_bytes(records: &[PassRecord], room: usize) -> Vec<u8> {
    let mut bytes = vec![0u8; room.max(records.len()).max(1) * PASS_STRIDE as usize];
    for (i, r) in records.iter().enumerate() {
        let at = i * PASS_STRIDE as usize;
        bytes[at..at + 16].copy_from_slice(bytemuck::bytes_of(r));
    }
    bytes
}

/// Floats of the reduction buffer for `misc` (see `params_of`).
fn red_floats(misc: [u32; 4]) -> usize {
    misc[3] as usize + 4 * MAX_COLLIDERS
}

/// Lattice bodies stepped by Newton–multigrid on the GPU.
pub struct GpuLattice {
    /// Where everything is in the buffers, and how much room is left.
    layout: Layout,
    /// This world among all made (what an append was packed against, with
    /// `generation`: [`AppendBasis`]).
    id: u64,
    /// Counts the changes of layout and plan (appends, new steps).
    generation: u64,
    /// The parameter block as last written.
    params_now: Params,
    /// Each level's Chebyshev `1/θ` and `ρ²`.
    cheb: Vec<[f32; 2]>,
    shape: Shape,
    /// The settings the world steps with.
    settings: SolverSettings,
    newton: u32,
    substeps: u32,
    /// The substep, s.
    h: f32,
    dispatches: Vec<Dispatch>,
    pass_index: Vec<u32>,
    /// Pass records the pass buffer holds.
    pass_room: usize,
    groups: Vec<BindGroup>,
    /// Positions, iterate, target, velocity and pin targets (5 regions of
    /// `layout.n_slots()` vec4; the iterate's w: the particle's contact tag).
    pos: Buffer,
    /// Element rotations of every level (quaternions; level 0 first).
    rot: Buffer,
    params: Buffer,
    passes: Buffer,
    cols: Buffer,
    /// Collider state per node: corrections, touched colliders and contacts, grasps,
    /// Newton forces.
    ccol: Buffer,
    /// Reductions and the collider forces.
    red: Buffer,
    /// The indirect dispatches' workgroup counts ([`ARGS_LINE`] and the others).
    args: Buffer,
    /// Where the collider force totals start in `red` (floats).
    force_out: u32,
    colliders: usize,
    /// Entries each particle-contact list can hold (0: no particle contacts).
    pair_capacity: usize,
    /// Per node of every level: mass, held, reach, body.
    nodes: Buffer,
    elems: Buffer,
    kmat: Buffer,
    topo: Buffer,
    mats: Buffer,
    /// Per body, two regions: the Newton step's trust bound (f32 bits) and the step of
    /// the fastest collider it touches (f32 bits, m).
    bodyt: Buffer,
    _keep: Vec<Buffer>,
    /// The mappable buffer [`GpuLattice::download`] reads through, kept between reads.
    staging: super::world::Staging,
}

impl GpuLattice {
    /// Uploads `model` (lattice bodies only, hyperelastic, pins allowed) in `state` with
    /// `settings` (dt, substeps, iterations, Newton iterations, gravity, damping,
    /// rotation iterations). Errors name what the GPU path does not run yet, or a model
    /// without elements.
    pub fn new(
        device: &RenderDevice,
        kernels: &LatticeKernels,
        model: &Model,
        state: &State,
        settings: &SolverSettings,
    ) -> Result<Self, TissueError> {
        Self::new_with(
            device,
            kernels,
            model,
            state,
            settings,
            LatticeOptions::default(),
        )
    }

    /// [`GpuLattice::new`] with other [`LatticeOptions`] (for tests and tuning).
    pub fn new_with(
        device: &RenderDevice,
        kernels: &LatticeKernels,
        model: &Model,
        state: &State,
        settings: &SolverSettings,
        options: LatticeOptions,
    ) -> Result<Self, TissueError> {
        let mg = LatticeMultigrid::new(model, settings.sweeps.min_nodes(), MG_LEVELS);
        Self::with_levels(device, kernels, model, mg, state, settings, options)
    }

    /// [`GpuLattice::new_with`] from the model's hierarchy made already (say by
    /// [`LatticeMultigrid::from_bodies`] from hierarchies of its bodies kept from before,
    /// so that a body coming or going does not coarsen every body again). The hierarchy
    /// must be the model's: an error names a mismatch in nodes, elements or bodies.
    pub fn with_levels(
        device: &RenderDevice,
        kernels: &LatticeKernels,
        model: &Model,
        mut mg: LatticeMultigrid,
        state: &State,
        settings: &SolverSettings,
        options: LatticeOptions,
    ) -> Result<Self, TissueError> {
        settings.validate()?;
        if model.elements.is_empty() {
            return Err(TissueError::InvalidParameter {
                name: "model",
                value: "no lattice elements".into(),
                expected: "at least one body with Discretisation::Lattice",
            });
        }
        for b in &model.bodies {
            if b.discretisation != Discretisation::Lattice
                || !matches!(b.material, Material::Hyperelastic { .. })
            {
                return Err(TissueError::InvalidParameter {
                    name: "model",
                    value: "a body that is not a hyperelastic lattice".into(),
                    expected: "only hyperelastic lattice bodies on the GPU lattice solver",
                });
            }
        }
        let n = model.particle_count();
        if state.x.len() != n || state.element_rot.len() != model.elements.len() {
            return Err(TissueError::InvalidParameter {
                name: "state",
                value: format!("{} particles", state.x.len()),
                expected: "a State made for this model",
            });
        }
        let fine = mg.levels.first();
        if fine.is_none_or(|f| {
            f.nodes != model.particle_count() || f.elements.len() != model.elements.len()
        }) || mg.unit.len() != model.bodies.len()
        {
            return Err(TissueError::InvalidParameter {
                name: "levels",
                value: format!(
                    "{} nodes, {} elements, {} bodies",
                    fine.map_or(0, |f| f.nodes),
                    fine.map_or(0, |f| f.elements.len()),
                    mg.unit.len()
                ),
                expected: "the hierarchy of this model (LatticeMultigrid::new or from_bodies)",
            });
        }
        mg.smoother = settings.smoother;
        let mut layout = Layout::new(&mg, options.room);
        let mut writes = Writes::default();
        if !layout.pack_all(model, &mg, state, &mut writes) {
            return Err(TissueError::InvalidParameter {
                name: "levels",
                value: "a hierarchy whose bodies do not fit their own layout".into(),
                expected: "the hierarchy of this model (LatticeMultigrid::new or from_bodies)",
            });
        }
        let pair_capacity = pair_capacity(model, settings, layout.n_slots() as usize);
        let params = params_of(
            &layout,
            settings,
            options,
            &mg.chebyshev,
            mg.smoother,
            pair_capacity > 0,
        );
        let mut shape = shape_of(
            &layout,
            mg.smoother,
            (pair_capacity > 0).then_some(settings.contact_every),
            settings.newton_cycles,
            settings.sweeps,
            options.fused_coarsest,
            options.one_thread_rows_from,
        );
        // Every buffer's contents: zero, then the bodies' writes.
        let (n, nt) = (layout.n_slots() as usize, layout.node_slots() as usize);
        let bodies = layout.bodies.cap as usize;
        let words = |buf: Buf| -> usize {
            match buf {
                Buf::Elems => 4 * layout.elems_len as usize,
                Buf::Kmat => 12 * layout.kmat.cap as usize,
                Buf::Topo => layout.topo_len as usize,
                Buf::Nodes => 4 * nt,
                Buf::Mats => 4 * bodies * layout::MAT_RECORD,
                Buf::Rot => 4 * layout.elem_slots() as usize,
                Buf::Pos => 4 * 5 * n,
                // Region 4 (every node's list ranges) and the lists (both of them, four
                // u32 a vec4) where there are particle contacts.
                Buf::Ccol if pair_capacity > 0 => 4 * (5 * n + (2 * pair_capacity).div_ceil(4)),
                Buf::Ccol => 4 * 4 * n,
                Buf::Bodyt => 2 * bodies,
            }
        };
        let image = |buf: Buf| -> Vec<u32> {
            let mut v = vec![0u32; words(buf)];
            if buf == Buf::Rot {
                // Rotations at rest where nothing is.
                for q in v.chunks_exact_mut(4) {
                    q[3] = 1.0f32.to_bits();
                }
            }
            for (_, at, data) in writes.0.iter().filter(|w| w.0 == buf) {
                v[*at as usize..*at as usize + data.len()].copy_from_slice(data);
            }
            v
        };
        let limit = device.limits().max_storage_buffer_binding_size;
        let st = BufferUsages::STORAGE | BufferUsages::COPY_DST | BufferUsages::COPY_SRC;
        let make =
            |label: &str, bytes: &[u8], usage: BufferUsages| -> Result<Buffer, TissueError> {
                if bytes.len() as u64 > limit {
                    return Err(TissueError::GpuUnsupported {
                        what: "bytes per storage buffer binding",
                        needed: bytes.len() as u64,
                        limit,
                    });
                }
                let padded;
                let contents = if bytes.len() < 16 {
                    padded = [bytes, &[0u8; 16][bytes.len()..]].concat();
                    &padded
                } else {
                    bytes
                };
                Ok(device.create_buffer_with_data(
                    &bevy::render::render_resource::BufferInitDescriptor {
                        label: Some(label),
                        contents,
                        usage,
                    },
                ))
            };
        let made = |label: &str, buf: Buf| make(label, bytemuck::cast_slice(&image(buf)), st);
        // Scratch: zeroed by the device, nothing uploaded.
        let zeroed = |label: &str, bytes: u64| -> Result<Buffer, TissueError> {
            if bytes > limit {
                return Err(TissueError::GpuUnsupported {
                    what: "bytes per storage buffer binding",
                    needed: bytes,
                    limit,
                });
            }
            Ok(
                device.create_buffer(&bevy::render::render_resource::BufferDescriptor {
                    label: Some(label),
                    size: bytes.max(16),
                    usage: st,
                    mapped_at_creation: false,
                }),
            )
        };
        let pos = made("tissue lattice pos", Buf::Pos)?;
        let rot = made("tissue lattice rot", Buf::Rot)?;
        let ef = zeroed("tissue lattice forces", layout.ne_slots() as u64 * 8 * 16)?;
        // The V-cycle's 4 regions of every level's nodes, then conjugate gradients'
        // iterate, direction and product (level 0's nodes each; the two-direction step of
        // one V-cycle uses the first: its answer, kept as the next step's second
        // direction).
        let cg = if shape.cycles > 1 { 3 * n } else { n };
        let vecs = zeroed("tissue lattice vectors", ((nt * 4 + cg) * 16) as u64)?;
        let nblk = zeroed("tissue lattice blocks", (nt * 6 * 16) as u64)?;
        // Each body's coarsest-level factor, kept between V-cycles where it fits.
        let factor_bytes = (bodies * FACTOR_STRIDE * 4) as u64;
        shape.factor_kept =
            options.keep_coarsest_factor && settings.sweeps.exact_coarsest && factor_bytes <= limit;
        let cfac = zeroed(
            "tissue lattice coarsest factor",
            if shape.factor_kept { factor_bytes } else { 16 },
        )?;
        let red = zeroed(
            "tissue lattice reductions",
            (red_floats(params.misc) * 4) as u64,
        )?;
        let elems = made("tissue lattice elements", Buf::Elems)?;
        let kmat = made("tissue lattice stiffness", Buf::Kmat)?;
        let topo = made("tissue lattice topology", Buf::Topo)?;
        let nodes = made("tissue lattice nodes", Buf::Nodes)?;
        // Each body's trust-region bound (f32 bits), 1 between iterations; then each
        // body's fastest touching collider's step (m, f32 bits), 0 between iterations.
        let bodyt = made("tissue lattice body trust", Buf::Bodyt)?;
        let mats = made("tissue lattice materials", Buf::Mats)?;
        let ccol = made("tissue lattice collider state", Buf::Ccol)?;
        let args = make(
            "tissue lattice indirect",
            bytemuck::cast_slice(&ARGS_INITIAL),
            BufferUsages::STORAGE | BufferUsages::INDIRECT | BufferUsages::COPY_DST,
        )?;
        let cols = make(
            "tissue lattice colliders",
            &vec![0u8; MAX_COLLIDERS * std::mem::size_of::<GpuCollider>()],
            BufferUsages::UNIFORM | BufferUsages::COPY_DST,
        )?;
        let params_buf = make(
            "tissue lattice params",
            bytemuck::bytes_of(&params),
            BufferUsages::UNIFORM | BufferUsages::COPY_DST,
        )?;
        let newton = settings.newton_count();
        let (dispatches, records, pass_index) = passes_of(&shape, newton);
        // Room for records that an appended body makes distinct.
        let pass_room = records.len().max(1) * 2 + 16;
        let passes = make(
            "tissue lattice passes",
            &pass_bytes(&records, pass_room),
            BufferUsages::UNIFORM | BufferUsages::COPY_DST,
        )?;
        let by_name = |name: &str| -> &Buffer {
            match name {
                "params" => &params_buf,
                "pc" => &passes,
                "cols" => &cols,
                "ccol" => &ccol,
                "args" => &args,
                "pos" => &pos,
                "rot" => &rot,
                "ef" => &ef,
                "vecs" => &vecs,
                "nblk" => &nblk,
                "red" => &red,
                "elems" => &elems,
                "kmat" => &kmat,
                "topo" => &topo,
                "nodes" => &nodes,
                "bodyt" => &bodyt,
                "cfac" => &cfac,
                _ => &mats,
            }
        };
        let mut bind_groups = Vec::new();
        for (entry, (_, layout)) in super::kernels::lattice::ENTRIES
            .iter()
            .zip(&kernels.pipelines)
        {
            let mut entries = Vec::new();
            for name in entry.uses {
                let Some(b) = super::kernels::lattice::slot(name) else {
                    continue;
                };
                let size = (SLOTS[b as usize].name == "pc")
                    .then(|| std::num::NonZeroU64::new(16))
                    .flatten();
                entries.push(BindGroupEntry {
                    binding: b,
                    resource: BindingResource::Buffer(BufferBinding {
                        buffer: by_name(name),
                        offset: 0,
                        size,
                    }),
                });
            }
            bind_groups.push(device.create_bind_group(entry.name, layout, &entries));
        }
        /// Numbers the worlds made.
        static WORLDS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        Ok(Self {
            layout,
            id: WORLDS.fetch_add(1, std::sync::atomic::Ordering::Relaxed),
            generation: 0,
            params_now: params,
            cheb: mg.chebyshev.clone(),
            shape,
            settings: settings.clone(),
            newton,
            substeps: settings.substeps,
            h: params.h,
            dispatches,
            pass_index,
            pass_room,
            groups: bind_groups,
            pos,
            rot,
            params: params_buf,
            passes,
            cols,
            ccol,
            args,
            force_out: params.misc[3],
            red,
            colliders: 0,
            pair_capacity,
            nodes,
            elems,
            kmat,
            topo,
            mats,
            bodyt,
            _keep: vec![ef, vecs, nblk, cfac],
            staging: Default::default(),
        })
    }

    /// Takes `settings` for the steps recorded from now on without making anything
    /// again, where they differ from the world's only in gravity, damping, the time step,
    /// substeps, iterations, Newton iterations and the particle contacts' relaxation and
    /// schedule ([`SolverSettings::differs_only_in_steps`]): parameter writes and a new
    /// plan. False (nothing changed) otherwise, or for settings that do not validate.
    pub fn set_steps(&mut self, queue: &RenderQueue, settings: &SolverSettings) -> bool {
        if !self.settings.differs_only_in_steps(settings) || settings.validate().is_err() {
            return false;
        }
        let newton = settings.newton_count();
        let mut shape = self.shape.clone();
        shape.pairs = shape.pairs.map(|_| settings.contact_every);
        let (dispatches, records, pass_index) = passes_of(&shape, newton);
        if records.len() > self.pass_room {
            return false;
        }
        self.h = settings.dt / settings.substeps as f32;
        self.substeps = settings.substeps;
        self.newton = newton;
        self.settings = settings.clone();
        self.shape = shape;
        self.dispatches = dispatches;
        self.pass_index = pass_index;
        self.generation += 1;
        queue.write_buffer(&self.passes, 0, &pass_bytes(&records, self.pass_room));
        self.write_params(queue);
        true
    }

    /// Writes the parameter block for the layout and the settings as they are now (the
    /// colliders as last set).
    fn write_params(&mut self, queue: &RenderQueue) {
        let now = self.params_now;
        let fresh = params_of(
            &self.layout,
            &self.settings,
            LatticeOptions::default(),
            &self.cheb,
            self.shape.smoother,
            now.pair[0] != 0,
        );
        // What is not the layout's or the settings': the colliders set, the line
        // search's first-pass candidates.
        self.params_now = Params {
            misc: [now.misc[0], fresh.misc[1], fresh.misc[2], fresh.misc[3]],
            sweeps: now.sweeps,
            ..fresh
        };
        queue.write_buffer(&self.params, 0, bytemuck::bytes_of(&self.params_now));
    }

    /// Bodies of the world (appended ones included).
    pub fn body_count(&self) -> usize {
        self.layout.bodies.used as usize
    }

    /// Particles of the world (appended bodies' included).
    pub fn particle_count(&self) -> usize {
        self.layout.nodes[0].used as usize
    }

    /// Sets gravity (m/s²) and velocity damping (1/s) for the steps recorded from now on,
    /// without rebuilding anything (a parameter write).
    pub fn set_forces(&mut self, queue: &RenderQueue, gravity: Vec3, damping: f32) {
        queue.write_buffer(&self.params, 0, bytemuck::bytes_of(&vec4(gravity)));
        let keep = (1.0 - damping * self.h).max(0.0);
        self.params_now.gravity = vec4(gravity);
        self.params_now.keep = keep;
        self.settings.gravity = gravity;
        self.settings.damping = damping;
        queue.write_buffer(
            &self.params,
            std::mem::offset_of!(Params, keep) as u64,
            bytemuck::bytes_of(&keep),
        );
    }

    /// Dispatches of one time step (with the colliders as last set; the clearing of their
    /// force sums once a step not counted).
    pub fn dispatch_count(&self) -> usize {
        self.running().count() * self.substeps as usize
    }

    /// The buffer of positions and velocities: five regions (positions, iterate,
    /// inertial target, velocity, pin target), each a vec4 per particle slot (the world's
    /// particles first, then the room for bodies appended later). The iterate's w is the
    /// solver's own during a substep (the particle's contact radius in metres, its sign
    /// bit set where the particle is held); the positions' w is 0.
    pub fn pos_buffer(&self) -> &Buffer {
        &self.pos
    }

    /// The parameter block (uniform).
    pub fn params_buffer(&self) -> &Buffer {
        &self.params
    }

    /// Records `steps` time steps into `encoder`, in one compute pass (with GPU
    /// timestamps at its ends when `timestamps` is given).
    pub fn record(
        &self,
        encoder: &mut CommandEncoder,
        kernels: &LatticeKernels,
        steps: u32,
        timestamps: Option<(&wgpu::QuerySet, u32)>,
    ) {
        self.record_doubling(encoder, kernels, steps, timestamps, None);
    }

    /// The names of one substep's dispatches as recorded with the world as it is now, in
    /// order (a kernel's name; smoothing per level, "smooth_chebyshev L0", ...). The
    /// position in this list is what [`GpuLattice::record_doubling`] takes.
    pub fn dispatch_names(&self) -> Vec<&'static str> {
        self.running()
            .map(|i| Self::dispatch_name(&self.dispatches[i]))
            .collect()
    }

    /// Records as [`GpuLattice::record`] does, with the `twice`-th dispatch of each
    /// substep (its position in [`GpuLattice::dispatch_names`]) encoded twice in a row.
    /// The GPU time this adds over the plain recording is that dispatch's cost in the
    /// step, its barrier included, measured without the timestamps between dispatches
    /// that stall the GPU. A dispatch that changes the state, done twice, changes what
    /// the steps after it compute: time few steps.
    pub fn record_doubling(
        &self,
        encoder: &mut CommandEncoder,
        kernels: &LatticeKernels,
        steps: u32,
        timestamps: Option<(&wgpu::QuerySet, u32)>,
        twice: Option<usize>,
    ) {
        let timestamp_writes = timestamps.map(|(qs, i)| wgpu::ComputePassTimestampWrites {
            query_set: qs,
            beginning_of_pass_write_index: Some(i),
            end_of_pass_write_index: Some(i + 1),
        });
        let mut pass = encoder.begin_compute_pass(&ComputePassDescriptor {
            label: Some("tissue lattice"),
            timestamp_writes,
        });
        for i in 0..steps * self.substeps {
            if i % self.substeps == 0 && self.colliders > 0 {
                self.encode_clear(&mut pass, kernels);
            }
            for (k, i) in self.running().enumerate() {
                self.encode(&mut pass, kernels, i);
                if twice == Some(k) {
                    self.encode(&mut pass, kernels, i);
                }
            }
        }
    }

    /// The plan's dispatches that run with the world as it is now (its indices): the
    /// colliders' reaction passes only where there are colliders (`set_colliders`;
    /// without, they would find nothing to sum), the contact passes only where there are
    /// colliders or particle contacts (without, no node has a contact block).
    fn running(&self) -> impl Iterator<Item = usize> + '_ {
        let colliders = self.colliders > 0;
        let pairs = self.params_now.pair[0] != 0;
        (0..self.dispatches.len()).filter(move |&i| runs(&self.dispatches[i], colliders, pairs))
    }

    /// Encodes the clearing of the colliders' force sums, once a step.
    fn encode_clear(&self, pass: &mut wgpu::ComputePass<'_>, kernels: &LatticeKernels) {
        let clear = LatticeKernels::index(Kernel::ForceClear);
        pass.set_pipeline(&kernels.pipelines[clear].0);
        pass.set_bind_group(0, &self.groups[clear], &[]);
        pass.dispatch_workgroups(1, 1, 1);
    }

    /// Encodes dispatch `i` of the plan into `pass`: its pipeline, its bind group at its
    /// range's offset, and its workgroups (or the indirect count).
    fn encode(&self, pass: &mut wgpu::ComputePass<'_>, kernels: &LatticeKernels, i: usize) {
        let d = &self.dispatches[i];
        let k = LatticeKernels::index(d.kernel);
        pass.set_pipeline(&kernels.pipelines[k].0);
        let offset = [self.pass_index[i] * PASS_STRIDE as u32];
        let offsets: &[u32] = if super::kernels::lattice::ENTRIES[k].uses.contains(&"pc") {
            &offset
        } else {
            &[]
        };
        pass.set_bind_group(0, &self.groups[k], offsets);
        if let Some(word) = d.indirect {
            pass.dispatch_workgroups_indirect(&self.args, 4 * word as u64);
        } else {
            pass.dispatch_workgroups(d.groups, 1, 1);
        }
    }

    /// The name a profile gives dispatch `d`: its kernel's, smoothing per level
    /// ("smooth_colour L0", ...).
    fn dispatch_name(d: &Dispatch) -> &'static str {
        const SMOOTH: [&str; 8] = [
            "smooth_colour L0",
            "smooth_colour L1",
            "smooth_colour L2",
            "smooth_colour L3",
            "smooth_colour L4",
            "smooth_colour L5",
            "smooth_colour L6",
            "smooth_colour L7",
        ];
        const CHEBYSHEV: [&str; 8] = [
            "smooth_chebyshev L0",
            "smooth_chebyshev L1",
            "smooth_chebyshev L2",
            "smooth_chebyshev L3",
            "smooth_chebyshev L4",
            "smooth_chebyshev L5",
            "smooth_chebyshev L6",
            "smooth_chebyshev L7",
        ];
        if d.kernel == Kernel::Smooth {
            SMOOTH[(d.pass.level as usize).min(7)]
        } else if d.kernel == Kernel::Chebyshev {
            CHEBYSHEV[(d.pass.level as usize).min(7)]
        } else {
            super::kernels::lattice::ENTRIES[LatticeKernels::index(d.kernel)].name
        }
    }

    /// Records `steps` time steps with each dispatch in its own compute pass, timed by
    /// `rec` under the kernel's name (smoothing per level: "smooth_colour L0", ...): for
    /// profiling (separate passes add their own cost).
    pub fn record_profiled(
        &self,
        encoder: &mut CommandEncoder,
        kernels: &LatticeKernels,
        steps: u32,
        rec: &mut dyn super::world::PassRecorder,
    ) {
        for _ in 0..steps * self.substeps {
            for i in self.running() {
                let name = Self::dispatch_name(&self.dispatches[i]);
                let ts = rec.timestamps(name);
                let timestamp_writes =
                    ts.as_ref().map(|(qs, i)| wgpu::ComputePassTimestampWrites {
                        query_set: qs,
                        beginning_of_pass_write_index: Some(*i),
                        end_of_pass_write_index: Some(*i + 1),
                    });
                let mut pass = encoder.begin_compute_pass(&ComputePassDescriptor {
                    label: Some(name),
                    timestamp_writes,
                });
                self.encode(&mut pass, kernels, i);
            }
        }
    }

    /// Records one time step in one compute pass, as [`GpuLattice::record`] does, with a
    /// GPU timestamp before its first dispatch and after each one, into `set` from index
    /// `first` (one more timestamp than dispatches). The device needs
    /// `TIMESTAMP_QUERY_INSIDE_PASSES`. A dispatch's time is the difference between the
    /// timestamps on either side of it (its barrier included), with much less added than a
    /// pass a dispatch. Returns the dispatches' names in order (as `record_profiled` names
    /// them).
    pub fn record_timed(
        &self,
        encoder: &mut CommandEncoder,
        kernels: &LatticeKernels,
        set: &wgpu::QuerySet,
        first: u32,
    ) -> Vec<&'static str> {
        let mut pass = encoder.begin_compute_pass(&ComputePassDescriptor {
            label: Some("tissue lattice (timed)"),
            timestamp_writes: None,
        });
        let mut names = Vec::new();
        pass.write_timestamp(set, first);
        self.encode_clear(&mut pass, kernels);
        names.push("force_clear");
        pass.write_timestamp(set, first + 1);
        for _ in 0..self.substeps {
            for i in self.running() {
                self.encode(&mut pass, kernels, i);
                names.push(Self::dispatch_name(&self.dispatches[i]));
                pass.write_timestamp(set, first + names.len() as u32);
            }
        }
        names
    }

    /// Sets the colliders of the next steps (at most [`MAX_COLLIDERS`]). They push as
    /// stiff penalties inside the Newton iterations and by projection with friction
    /// after each; graspers capture nodes within their radius and hold them, as on the
    /// CPU.
    pub fn set_colliders(
        &mut self,
        queue: &RenderQueue,
        colliders: &[Collider],
    ) -> Result<(), TissueError> {
        let packed = super::buffers::pack_colliders(
            colliders,
            MAX_COLLIDERS,
            "at most 32 colliders for the GPU lattice solver",
        )?;
        if !packed.is_empty() {
            queue.write_buffer(&self.cols, 0, bytemuck::cast_slice(&packed));
        }
        queue.write_buffer(
            &self.params,
            MISC_OFFSET,
            bytemuck::bytes_of(&(colliders.len() as u32)),
        );
        self.colliders = colliders.len();
        self.params_now.misc[0] = colliders.len() as u32;
        Ok(())
    }

    /// Whether this world solves particle contacts between its bodies (made with
    /// `particle_contacts` on and more than one body); their candidates come from
    /// [`GpuLattice::set_contacts`].
    pub fn has_particle_contacts(&self) -> bool {
        self.pair_capacity > 0
    }

    /// Sets the particle-contact candidates of the next steps, as the CPU solver's
    /// [`crate::core::solver::Solver::contact_lists`] gives them (CSR: node `i`'s
    /// candidates are `list[start[i]..start[i + 1]]`, other bodies' nodes). Each pair
    /// closer than the two radii pushes as a stiff penalty inside the Newton iterations
    /// and is projected apart (Jacobi, relaxed by `contact_relaxation` up to 1) after every
    /// `contact_every`-th Newton iteration and the last, as on the CPU under
    /// [`crate::core::solver::Method::Jacobi`]. Errors when the world has no particle
    /// contacts or the lists do not fit it (nothing is written then).
    pub fn set_contacts(
        &mut self,
        queue: &RenderQueue,
        start: &[u32],
        list: &[u32],
    ) -> Result<(), TissueError> {
        let n = self.particle_count();
        let slots = self.layout.n_slots() as usize;
        if self.pair_capacity == 0 {
            return Err(TissueError::InvalidParameter {
                name: "particle contacts",
                value: "a world made without them".into(),
                expected: "particle_contacts on and at least two bodies when the GPU lattice world is made",
            });
        }
        let sorted = start.windows(2).all(|w| w[0] <= w[1]);
        if start.len() != n + 1
            || start.last().copied() != Some(list.len() as u32)
            || !sorted
            || list.iter().any(|&i| i as usize >= n)
        {
            return Err(TissueError::InvalidParameter {
                name: "contact lists",
                value: format!("{} starts, {} candidates", start.len(), list.len()),
                expected: "CSR lists of this world's nodes (one start per node and one more)",
            });
        }
        if list.len() > self.pair_capacity {
            return Err(TissueError::InvalidParameter {
                name: "contact lists",
                value: format!("{} candidates", list.len()),
                expected: "at most contact_neighbours per node",
            });
        }
        // The reverse lists: for each node, the nodes whose candidates it is.
        let mut rev_start = vec![0u32; n + 1];
        for &i in list {
            rev_start[i as usize + 1] += 1;
        }
        for i in 0..n {
            rev_start[i + 1] += rev_start[i];
        }
        let mut fill = rev_start.clone();
        let mut rev = vec![0u32; list.len()];
        for owner in 0..n {
            for &i in &list[start[owner] as usize..start[owner + 1] as usize] {
                rev[fill[i as usize] as usize] = owner as u32;
                fill[i as usize] += 1;
            }
        }
        let base = list.len() as u32;
        let ranges: Vec<[u32; 4]> = (0..n)
            .map(|j| {
                [
                    start[j],
                    start[j + 1],
                    base + rev_start[j],
                    base + rev_start[j + 1],
                ]
            })
            .collect();
        queue.write_buffer(
            &self.ccol,
            (4 * slots * 16) as u64,
            bytemuck::cast_slice(&ranges),
        );
        // The lists after the regions: each node's candidates, then the reverse lists.
        if !list.is_empty() {
            let at = (5 * slots * 16) as u64;
            queue.write_buffer(&self.ccol, at, bytemuck::cast_slice(list));
            let at = at + 4 * list.len() as u64;
            queue.write_buffer(&self.ccol, at, bytemuck::cast_slice(&rev));
        }
        Ok(())
    }

    /// Holds particles `range` of `model` still at `at` (one position each, m) from now
    /// on: they are put there at rest, pinned there and left out of every correction, so
    /// that they neither move nor move anything (what a despawned body becomes until the
    /// world is made again without it, placed out of everyone's reach). A range outside
    /// the model, or `at` of another length, changes nothing.
    pub fn hold(
        &self,
        queue: &RenderQueue,
        model: &Model,
        range: std::ops::Range<usize>,
        at: &[Vec3],
    ) {
        let n = self.layout.n_slots() as usize;
        if range.end > self.particle_count()
            || range.end > model.particle_count()
            || at.len() != range.len()
        {
            return;
        }
        let put = |region: usize, values: Vec<[f32; 4]>| {
            let offset = ((region * n + range.start) * 16) as u64;
            queue.write_buffer(&self.pos, offset, bytemuck::cast_slice(&values));
        };
        put(0, at.iter().map(|p| vec4(*p)).collect());
        put(1, at.iter().map(|p| vec4(*p)).collect());
        put(3, vec![[0.0; 4]; range.len()]);
        put(4, at.iter().map(|p| p.extend(1.0).to_array()).collect());
        let nodes: Vec<[f32; 4]> = range
            .clone()
            .map(|j| particle_node(model, j, true))
            .collect();
        queue.write_buffer(
            &self.nodes,
            (range.start * 16) as u64,
            bytemuck::cast_slice(&nodes),
        );
    }

    /// Writes `state`'s positions, velocities, pin targets, element rotations and grasps
    /// (the colliders touched in the last substep are forgotten).
    pub fn upload(&mut self, queue: &RenderQueue, model: &Model, state: &State) {
        let n = state.x.len();
        if n != self.particle_count() {
            return;
        }
        let slots = self.layout.n_slots() as u64 * 16;
        let regions = pos_regions(model, state);
        for r in [0, 3, 4] {
            queue.write_buffer(
                &self.pos,
                r as u64 * slots,
                bytemuck::cast_slice(&regions[r * n..(r + 1) * n]),
            );
        }
        let rots: Vec<[f32; 4]> = state.element_rot.iter().map(|q| q.to_array()).collect();
        queue.write_buffer(&self.rot, 0, bytemuck::cast_slice(&rots));
        let ccol = ccol_regions(state);
        for r in 0..4 {
            queue.write_buffer(
                &self.ccol,
                r as u64 * slots,
                bytemuck::cast_slice(&ccol[r * n..(r + 1) * n]),
            );
        }
    }

    /// Blocking read of the force (N) the bodies put on each collider set by
    /// [`GpuLattice::set_colliders`] in the last recorded step: the reactions of the
    /// particles touching it at each substep's end, and for a grasper the pull of what
    /// it holds (as the CPU solver's `StepStats::collider_forces`).
    pub fn read_forces(&self, device: &RenderDevice, queue: &RenderQueue) -> Vec<Vec3> {
        if self.colliders == 0 {
            return Vec::new();
        }
        let bytes = super::world::read_buffer(
            device,
            queue,
            &self.red,
            self.force_out as u64 * 4,
            self.colliders as u64 * 16,
        );
        forces_of(&bytes)
    }

    /// Blocking read of each body's last line search (of the last recorded step's last
    /// Newton iteration): the fraction of its Newton step it took (1, ½, …, 2⁻¹², or 0:
    /// none lowered its energy). A diagnostic: which bodies make the solver search, and
    /// run the search's second pass (a step below the first pass's candidates).
    pub fn read_line_steps(&self, device: &RenderDevice, queue: &RenderQueue) -> Vec<f32> {
        let bodies = self.params_now.count[0] as usize;
        if bodies == 0 {
            return Vec::new();
        }
        let bytes = super::world::read_buffer(
            device,
            queue,
            &self.red,
            self.params_now.chunks[3] as u64 * 4,
            (bodies * BODY_SLOTS) as u64 * 4,
        );
        // Each body's B_ALPHA, slot 0 of its slots in `lattice.wgsl`.
        bytemuck::pod_collect_to_vec::<u8, [f32; BODY_SLOTS]>(&bytes)
            .iter()
            .map(|slots| slots[0])
            .collect()
    }

    /// Blocking read of positions, velocities, level-0 element rotations and grasps into
    /// `state` (its step count is the caller's to advance), in one submission with the
    /// forces on the colliders, which it returns (as [`GpuLattice::read_forces`]).
    pub fn download(
        &self,
        device: &RenderDevice,
        queue: &RenderQueue,
        state: &mut State,
    ) -> Vec<Vec3> {
        let n = self.particle_count() as u64 * 16;
        let slots = self.layout.n_slots() as u64 * 16;
        let ne = self.layout.elems[0].used as u64 * 16;
        let ranges = [
            (&self.pos, 0, n),
            (&self.pos, 3 * slots, n),
            (&self.rot, 0, ne),
            (&self.ccol, 2 * slots, n),
            (
                &self.red,
                self.force_out as u64 * 4,
                self.colliders as u64 * 16,
            ),
        ];
        super::world::read_buffers_with(device, queue, &self.staging, &ranges, |parts| {
            let [x, v, rot, grab, forces] = parts else {
                return Vec::new();
            };
            let (x, v, rot, grab) = (vec4s(x), vec4s(v), vec4s(rot), vec4s(grab));
            // Copies: threads only for tens of thousands of particles each.
            let threads = crate::core::par::threads_for(state.x.len(), 32768, 0);
            let (xs, vs) = (&mut state.x, &mut state.v);
            crate::core::par::for_chunks_mut2(xs, vs, threads, |first, xs, vs| {
                let (x, v) = (x.get(first..).unwrap_or(&[]), v.get(first..).unwrap_or(&[]));
                let read = x.iter().zip(v);
                for ((xo, vo), (a, b)) in xs.iter_mut().zip(vs.iter_mut()).zip(read) {
                    *xo = Vec3::new(a[0], a[1], a[2]);
                    *vo = Vec3::new(b[0], b[1], b[2]);
                }
            });
            for (q, r) in rot.iter().zip(state.element_rot.iter_mut()) {
                *r = Quat::from_array(*q);
            }
            for (g, s) in grab.iter().zip(state.grab.iter_mut()) {
                *s = if g[3] > 0.5 {
                    crate::core::colliders::Grab {
                        collider: g[3] as u32 - 1,
                        offset: Vec3::new(g[0], g[1], g[2]),
                    }
                } else {
                    crate::core::colliders::Grab::FREE
                };
            }
            forces_of(forces)
        })
    }
}

/// Collider forces (vec4 each, N) as `Vec3`s.
fn forces_of(bytes: &[u8]) -> Vec<Vec3> {
    vec4s(bytes)
        .iter()
        .map(|f| Vec3::new(f[0], f[1], f[2]))
        .collect()
}

/// Bytes read back as vec4s: in place where they are aligned for `f32` (a mapped
/// buffer's are), else copied out.
fn vec4s(bytes: &[u8]) -> std::borrow::Cow<'_, [[f32; 4]]> {
    let whole = &bytes[..bytes.len() / 16 * 16];
    match bytemuck::try_cast_slice(whole) {
        Ok(v) => std::borrow::Cow::Borrowed(v),
        Err(_) => std::borrow::Cow::Owned(bytemuck::pod_collect_to_vec(whole)),
    }
}

/// The `ccol` buffer's regions for `state`: no collider corrections yet (w = −1),
/// nothing touched (x = −1) and no contacts (y), `state`'s grasps (offset, grasper + 1),
/// no Newton forces (w = −1).
fn ccol_regions(state: &State) -> Vec<[f32; 4]> {
    let n = state.x.len();
    let mut out: Vec<[f32; 4]> = vec![[0.0, 0.0, 0.0, -1.0]; n];
    out.extend(std::iter::repeat_n([-1.0, 0.0, 0.0, 0.0], n));
    out.extend(state.grab.iter().map(|g| {
        if g.collider == u32::MAX {
            [0.0; 4]
        } else {
            g.offset.extend(g.collider as f32 + 1.0).to_array()
        }
    }));
    out.extend(std::iter::repeat_n([0.0, 0.0, 0.0, -1.0], n));
    out
}

/// The `pos` buffer's regions for `state`: x, (iterate), (target), v, pin targets
/// (w = 1 on pinned particles).
fn pos_regions(model: &Model, state: &State) -> Vec<[f32; 4]> {
    let n = state.x.len();
    let mut out = vec![[0.0f32; 4]; 5 * n];
    for i in 0..n {
        out[i] = vec4(state.x[i]);
        out[3 * n + i] = vec4(state.v[i]);
    }
    for (slot, &i) in model.pinned.iter().enumerate() {
        let t = state
            .pin_targets
            .get(slot)
            .copied()
            .unwrap_or(state.x[i as usize]);
        out[4 * n + i as usize] = t.extend(1.0).to_array();
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shape() -> Shape {
        Shape {
            levels: vec![[0, 100, 0, 60], [100, 20, 60, 8], [120, 8, 68, 1]],
            colours: [
                [0, 13, 26, 39, 52, 65, 78, 91, 100],
                [100, 103, 106, 109, 112, 115, 118, 118, 120],
                [120, 121, 122, 123, 124, 125, 126, 127, 128],
            ]
            .iter()
            .map(|c| std::array::from_fn(|k| [c[k], c[k + 1]]))
            .collect(),
            // The energy's table, then each level's (3 bodies).
            tables: vec![[0, 5], [5, 3], [8, 3], [11, 3]],
            bodies: 3,
            smoother: Smoother::GaussSeidel,
            pairs: None,
            cycles: 1,
            // V(2, 2), 30 on the coarsest (what these tests count).
            sweeps: Sweeps {
                fine: 2,
                fine_before: 2,
                coarse: 2,
                coarse_before: 2,
                coarsest: 30,
                exact_coarsest: false,
                translation: true,
            },
            // The coarsest level's sweeps a dispatch each (what these tests count).
            most_coarsest: 3,
            fused_coarsest: 0,
            one_thread_rows_from: u32::MAX,
            factor_kept: false,
        }
    }

    /// A smoothing pass (Gauss–Seidel colour or Chebyshev sweep) over at least
    /// `one_thread_rows_from` nodes carries the row mode bit beside its sweep index and a
    /// workgroup per 64 nodes, a smaller one eight threads a node; the plan is otherwise
    /// the same. 0 marks every pass, and a limit between the passes' sizes some of them.
    #[test]
    fn one_thread_rows_mark_the_smoothing_passes_over_enough_nodes() {
        for smoother in [Smoother::GaussSeidel, Smoother::Chebyshev, Smoother::Hybrid] {
            let split = Shape {
                smoother,
                ..shape()
            };
            let a = plan(&split, 2);
            let sizes: Vec<u32> = a
                .iter()
                .filter(|d| matches!(d.kernel, Kernel::Smooth | Kernel::Chebyshev))
                .map(|d| d.pass.count)
                .collect();
            let (lo, hi) = (*sizes.iter().min().unwrap(), *sizes.iter().max().unwrap());
            assert!(lo < hi, "the test's passes differ in size");
            let mut marked_some = false;
            for from in [0, hi, u32::MAX] {
                let rows = Shape {
                    one_thread_rows_from: from,
                    ..split.clone()
                };
                let b = plan(&rows, 2);
                assert_eq!(a.len(), b.len());
                for (x, y) in a.iter().zip(&b) {
                    assert_eq!(
                        (x.kernel, x.pass.first, x.pass.count),
                        (y.kernel, y.pass.first, y.pass.count)
                    );
                    assert_eq!(x.pass.mode & ROW_MODE, 0);
                    if matches!(x.kernel, Kernel::Smooth | Kernel::Chebyshev)
                        && x.pass.count >= from
                    {
                        marked_some |= from > 0;
                        assert_eq!(y.pass.mode, x.pass.mode | ROW_MODE);
                        assert_eq!(x.groups, x.pass.count.div_ceil(8));
                        assert_eq!(y.groups, y.pass.count.div_ceil(WORKGROUP));
                    } else {
                        assert_eq!((x.pass.mode, x.groups), (y.pass.mode, y.groups));
                    }
                }
            }
            assert!(marked_some, "a limit at the largest pass marks it");
        }
    }

    /// Under Chebyshev on level 0, each run of its sweeps ends in one that copies its
    /// result (and only that one), followed at once by the contact pass over level 0's
    /// nodes (dispatched indirectly, with the `contacts` pass's workgroups where that
    /// finds a contact); where level 0 is smoothed by Gauss–Seidel there is no contact
    /// pass.
    #[test]
    fn level_zero_chebyshev_sweeps_end_in_the_contact_pass() {
        for smoother in [Smoother::GaussSeidel, Smoother::Chebyshev, Smoother::Hybrid] {
            let s = Shape {
                smoother,
                ..shape()
            };
            let p = plan(&s, 2);
            let passes = p
                .iter()
                .filter(|d| d.kernel == Kernel::ContactSmooth)
                .count();
            if smoother.on_level(0) != Smoother::Chebyshev {
                assert_eq!(passes, 0, "{smoother:?}");
                assert!(p.iter().all(|d| d.pass.mode & COPY_MODE == 0));
                continue;
            }
            // Two Newton iterations, the shape's cycles each, a pass after the sweeps
            // before the coarse correction and after it.
            let runs = 1 + (s.sweeps.before_on_level(0, smoother) > 0) as usize;
            assert_eq!(runs, 2, "the shape smooths level 0 before and after");
            assert_eq!(passes, 2 * s.cycles as usize * runs, "{smoother:?}");
            for (i, d) in p.iter().enumerate() {
                let copies = d.pass.mode & COPY_MODE != 0;
                let next = p.get(i + 1).map(|d| d.kernel);
                assert_eq!(copies, next == Some(Kernel::ContactSmooth), "{i}");
                if copies {
                    assert_eq!((d.kernel, d.pass.level), (Kernel::Chebyshev, 0));
                }
                if d.kernel == Kernel::ContactSmooth {
                    let lv = s.levels[0];
                    assert_eq!((d.pass.first, d.pass.count), (lv[0], lv[1]));
                    assert_eq!(d.groups, groups(lv[1]));
                    // Dispatched with the workgroups `contacts` writes where it finds a
                    // contact block: its own.
                    assert_eq!(d.indirect, Some(ARGS_CONTACT));
                    let contacts = p.iter().find(|c| c.kernel == Kernel::Contacts);
                    assert_eq!(contacts.map(|c| c.groups), Some(d.groups));
                }
            }
        }
    }

    /// A world records the reaction passes only with colliders, and the contact passes
    /// (`contacts` and level 0's contact pass) only with colliders or particle
    /// contacts; every other dispatch of the plan always.
    #[test]
    fn idle_passes_are_left_out_where_nothing_can_touch() {
        let s = Shape {
            smoother: Smoother::Chebyshev,
            ..shape()
        };
        let p = plan(&s, 2);
        let count = |k: Kernel| p.iter().filter(|d| d.kernel == k).count();
        assert!(count(Kernel::Contacts) > 0 && count(Kernel::ContactSmooth) > 0);
        for (colliders, pairs) in [(false, false), (false, true), (true, false), (true, true)] {
            let kept: Vec<&Dispatch> = p.iter().filter(|d| runs(d, colliders, pairs)).collect();
            let reactions = kept.iter().filter(|d| for_reactions(d)).count();
            let contacts = kept.iter().filter(|d| for_contacts(d)).count();
            assert_eq!(reactions > 0, colliders, "{colliders} {pairs}");
            assert_eq!(
                contacts,
                if colliders || pairs {
                    count(Kernel::Contacts) + count(Kernel::ContactSmooth)
                } else {
                    0
                },
                "{colliders} {pairs}"
            );
            let others = p
                .iter()
                .filter(|d| !for_reactions(d) && !for_contacts(d))
                .count();
            assert_eq!(kept.len(), others + reactions + contacts);
        }
        // The reaction passes: `forces` at the substep's end, its partial sums, the total.
        assert_eq!(p.iter().filter(|d| for_reactions(d)).count(), 3);
    }

    /// Where every body has few nodes on the coarsest level, and it is smoothed by
    /// Chebyshev, its sweeps are one dispatch (a workgroup per body, the sweep count its
    /// mode, its reduction table its range); a larger body, a limit of 0 or a
    /// Gauss–Seidel coarsest level keep a dispatch a sweep.
    #[test]
    fn small_coarsest_levels_take_their_sweeps_in_one_dispatch() {
        let fused = Shape {
            smoother: Smoother::Hybrid,
            fused_coarsest: 3,
            ..shape()
        };
        assert!(fused.coarsest_fused());
        let p = plan(&fused, 2);
        let fused_kernel =
            |d: &&Dispatch| matches!(d.kernel, Kernel::Coarsest | Kernel::CoarsestSmall);
        // Its bodies have at most 3 nodes there: the small bodies' kernel.
        assert!(p.iter().all(|d| d.kernel != Kernel::Coarsest));
        let one: Vec<&Dispatch> = p.iter().filter(fused_kernel).collect();
        // Two Newton iterations, one V-cycle each.
        assert_eq!(one.len(), 2);
        for d in &one {
            assert_eq!(d.pass.level, 2);
            assert_eq!(d.pass.mode, 30);
            assert_eq!([d.pass.first, d.pass.count], fused.tables[3]);
            assert_eq!(d.groups, 3);
        }
        assert!(
            p.iter()
                .all(|d| d.kernel != Kernel::Chebyshev || d.pass.level != 2)
        );
        // Everything else as a dispatch a sweep would have it.
        let apart = plan(
            &Shape {
                fused_coarsest: 0,
                ..fused.clone()
            },
            2,
        );
        assert_eq!(apart.len(), p.len() - 2 + 2 * 30);
        // A body past SMALL_COARSEST nodes there takes the general kernel.
        let larger = Shape {
            most_coarsest: SMALL_COARSEST + 1,
            fused_coarsest: FUSED_COARSEST,
            ..fused.clone()
        };
        let general = plan(&larger, 2);
        assert_eq!(
            general
                .iter()
                .filter(|d| d.kernel == Kernel::Coarsest)
                .count(),
            2
        );
        assert!(general.iter().all(|d| d.kernel != Kernel::CoarsestSmall));
        for unfused in [
            Shape {
                most_coarsest: 4,
                ..fused.clone()
            },
            Shape {
                smoother: Smoother::GaussSeidel,
                ..fused.clone()
            },
            Shape {
                levels: fused.levels[..1].to_vec(),
                smoother: Smoother::Chebyshev,
                ..fused.clone()
            },
        ] {
            assert!(!unfused.coarsest_fused(), "{unfused:?}");
            assert!(
                plan(&unfused, 2)
                    .iter()
                    .all(|d| !matches!(d.kernel, Kernel::Coarsest | Kernel::CoarsestSmall))
            );
        }
    }

    /// Where the coarsest level is solved exactly (asked for, below level 0, no body
    /// past `EXACT_COARSEST` nodes there), each V-cycle takes one `solve_coarsest`
    /// dispatch there (a workgroup per body, its range the level's reduction table) in
    /// place of every sweep of it, whatever the smoother and the fused limit, and the
    /// levels between take the coarse correction whole; otherwise none.
    #[test]
    fn small_coarsest_levels_are_solved_exactly_where_asked() {
        let exact = |base: Shape| Shape {
            sweeps: Sweeps {
                exact_coarsest: true,
                translation: true,
                ..base.sweeps
            },
            ..base
        };
        for base in [
            shape(),
            Shape {
                smoother: Smoother::Hybrid,
                fused_coarsest: 3,
                ..shape()
            },
        ] {
            let swept = plan(&base, 2);
            let solved = exact(base.clone());
            assert!(solved.coarsest_exact());
            let p = plan(&solved, 2);
            let one: Vec<&Dispatch> = p
                .iter()
                .filter(|d| d.kernel == Kernel::CoarsestExact)
                .collect();
            assert_eq!(one.len(), 2, "two Newton iterations, one V-cycle each");
            for d in &one {
                assert_eq!(d.pass.level, 2);
                assert_eq!([d.pass.first, d.pass.count], solved.tables[3]);
                assert_eq!(d.groups, 3);
            }
            // Every level takes the coarse correction whole (no step along it).
            assert!(
                p.iter()
                    .filter(|d| d.kernel == Kernel::Prolong)
                    .all(|d| d.pass.mode == 1)
            );
            assert!(
                p.iter()
                    .all(|d| !matches!(d.kernel, Kernel::AlphaTerms | Kernel::Correct))
            );
            assert!(
                swept
                    .iter()
                    .any(|d| d.kernel == Kernel::AlphaTerms && d.pass.level == 1)
            );
            // No sweep of the coarsest level is left; everything else is as swept but the
            // levels between's steps.
            assert!(p.iter().all(|d| d.pass.level != 2
                || !matches!(
                    d.kernel,
                    Kernel::Chebyshev | Kernel::Smooth | Kernel::Coarsest | Kernel::CoarsestSmall
                )));
            let without = |v: &[Dispatch]| -> Vec<Kernel> {
                v.iter()
                    .filter(|d| {
                        d.pass.level != 2
                            || !matches!(
                                d.kernel,
                                Kernel::Chebyshev
                                    | Kernel::Smooth
                                    | Kernel::Coarsest
                                    | Kernel::CoarsestSmall
                                    | Kernel::CoarsestExact
                            )
                    })
                    .filter(|d| {
                        let step = matches!(d.kernel, Kernel::AlphaTerms | Kernel::Correct)
                            || (d.kernel == Kernel::Pick && d.pass.mode == 3);
                        !step
                    })
                    .map(|d| d.kernel)
                    .collect()
            };
            assert_eq!(without(&p), without(&swept));
            // With the factor kept: one factorisation a Newton iteration right after the
            // diagonal blocks, over the same table, and each V-cycle's solve from it.
            let kept = Shape {
                factor_kept: true,
                ..solved.clone()
            };
            assert!(kept.coarsest_factored() && !solved.coarsest_factored());
            let pk = plan(&kept, 2);
            let mut expect = Vec::new();
            for d in &p {
                let mut d = *d;
                if d.kernel == Kernel::CoarsestExact {
                    d.kernel = Kernel::CoarsestFactored;
                }
                expect.push(d);
                if d.kernel == Kernel::Diag {
                    expect.push(Dispatch {
                        kernel: Kernel::FactorCoarsest,
                        pass: PassRecord {
                            first: solved.tables[3][0],
                            count: solved.tables[3][1],
                            level: 2,
                            mode: 0,
                        },
                        groups: 3,
                        indirect: None,
                    });
                }
            }
            assert_eq!(pk, expect);
            assert_eq!(
                pk.iter()
                    .filter(|d| d.kernel == Kernel::FactorCoarsest)
                    .count(),
                2
            );
        }
        for swept in [
            // A body past the most nodes the exact solve takes.
            Shape {
                most_coarsest: EXACT_COARSEST as u32 + 1,
                ..exact(shape())
            },
            // Not asked for.
            shape(),
            // A single level (level 0 is never solved exactly).
            Shape {
                levels: shape().levels[..1].to_vec(),
                ..exact(shape())
            },
        ] {
            assert!(!swept.coarsest_exact(), "{swept:?}");
            // Nothing exact is planned, whether or not the world keeps a factor.
            for factor_kept in [false, true] {
                let sh = Shape {
                    factor_kept,
                    ..swept.clone()
                };
                assert!(plan(&sh, 2).iter().all(|d| !matches!(
                    d.kernel,
                    Kernel::CoarsestExact | Kernel::FactorCoarsest | Kernel::CoarsestFactored
                )));
            }
        }
    }

    /// Each level is smoothed as many times as the settings' sweeps say: level 0
    /// `fine_before` times before and `fine` after, the levels between `coarse_before`
    /// and `coarse`, the coarsest `coarsest`, each Gauss–Seidel sweep a dispatch per
    /// non-empty colour; a level not smoothed before the correction gets no residual
    /// pass, its right-hand side read in its place.
    #[test]
    fn each_level_takes_its_own_sweeps() {
        let s = Shape {
            sweeps: Sweeps {
                fine: 1,
                fine_before: 1,
                coarse: 3,
                coarse_before: 3,
                coarsest: 5,
                exact_coarsest: false,
                translation: true,
            },
            ..shape()
        };
        let count = |l: u32| {
            plan(&s, 1)
                .iter()
                .filter(|d| d.kernel == Kernel::Smooth && d.pass.level == l)
                .count()
        };
        // Level 1 has an empty colour.
        assert_eq!((count(0), count(1), count(2)), (2 * 8, 2 * 3 * 7, 5 * 8));
        // None before on level 0: its sweeps only after the correction, and no pass
        // makes its residual (the translation step writes it from the right-hand side,
        // mode 1); the levels between make theirs.
        let after = Shape {
            sweeps: Sweeps {
                fine_before: 0,
                ..s.sweeps
            },
            ..s.clone()
        };
        let p = plan(&after, 1);
        let smooth0 = p
            .iter()
            .filter(|d| d.kernel == Kernel::Smooth && d.pass.level == 0)
            .count();
        assert_eq!(smooth0, 8);
        let residuals: Vec<(u32, u32)> = p
            .iter()
            .filter(|d| d.kernel == Kernel::FineResidual)
            .map(|d| (d.pass.level, d.pass.mode))
            .collect();
        assert_eq!(residuals, vec![(1, 0)]);
        let modes = |p: &[Dispatch], k: Kernel| -> Vec<(u32, u32)> {
            p.iter()
                .filter(|d| d.kernel == k)
                .map(|d| (d.pass.level, d.pass.mode))
                .collect()
        };
        assert_eq!(modes(&p, Kernel::Translate), vec![(0, 1)]);
        assert_eq!(modes(&p, Kernel::TranslateTerms), vec![(0, 1)]);
        assert_eq!(modes(&p, Kernel::Restrict), vec![(1, 0), (2, 0)]);
        assert_eq!(modes(&p, Kernel::AlphaTerms), vec![(1, 0)]);
        // None before on the levels between either: no residual pass at all, and level
        // 1's restriction and step read its right-hand side (mode 1).
        let plain = Shape {
            sweeps: Sweeps {
                fine_before: 0,
                coarse_before: 0,
                ..s.sweeps
            },
            ..s.clone()
        };
        let q = plan(&plain, 1);
        assert_eq!(modes(&q, Kernel::FineResidual), vec![]);
        assert_eq!(modes(&q, Kernel::Restrict), vec![(1, 0), (2, 1)]);
        assert_eq!(modes(&q, Kernel::AlphaTerms), vec![(1, 1)]);
        let smooth1 = |p: &[Dispatch]| {
            p.iter()
                .filter(|d| d.kernel == Kernel::Smooth && d.pass.level == 1)
                .count()
        };
        assert_eq!(smooth1(&q) * 2, smooth1(&p));
        // Without the translation step (the default), level 0's restriction reads its
        // right-hand side too, and nothing else changes.
        let still = Shape {
            sweeps: Sweeps {
                translation: false,
                ..plain.sweeps
            },
            ..s.clone()
        };
        let r = plan(&still, 1);
        assert_eq!(modes(&r, Kernel::Restrict), vec![(1, 1), (2, 1)]);
        assert_eq!(modes(&r, Kernel::TranslateTerms), vec![]);
        assert_eq!(modes(&r, Kernel::Translate), vec![]);
        assert_eq!(r.len() + 3, q.len());
        assert!(
            r.iter()
                .all(|d| !(d.kernel == Kernel::Pick && d.pass.mode == 7))
        );
        // With sweeps before on level 0, its residual pass and the translation from it.
        let p0 = plan(&s, 1);
        assert_eq!(modes(&p0, Kernel::FineResidual), vec![(0, 0), (1, 0)]);
        assert_eq!(modes(&p0, Kernel::Translate), vec![(0, 0)]);
        // The first level-0 sweep comes after the prolongation to level 0.
        let first = p
            .iter()
            .position(|d| d.kernel == Kernel::Smooth && d.pass.level == 0);
        let prolong = p
            .iter()
            .position(|d| d.kernel == Kernel::Prolong && d.pass.level == 0);
        assert!(first > prolong, "{first:?} {prolong:?}");
    }

    /// Particle contacts are projected after every `contact_every`-th Newton iteration
    /// and after the last, each time right before the colliders' projection, which then
    /// starts from its result (mode 1); without them nothing is dispatched for them, and
    /// the line search's step takes the colliders' projection in the same pass
    /// (`advance`, mode bit 1).
    #[test]
    fn particle_contacts_are_projected_on_their_schedule() {
        let p = plan(&shape(), 3);
        assert!(
            p.iter()
                .all(|d| !matches!(d.kernel, Kernel::PairProject | Kernel::Boundary))
        );
        let steps: Vec<u32> = p
            .iter()
            .filter(|d| d.kernel == Kernel::Advance)
            .map(|d| d.pass.mode)
            .collect();
        assert_eq!(steps, [0, 3, 3, 3]);
        for (every, newton, expect) in [
            (1, 3, vec![0, 1, 2]),
            (2, 3, vec![1, 2]),
            (2, 4, vec![1, 3]),
            (5, 2, vec![1]),
        ] {
            let s = Shape {
                pairs: Some(every),
                ..shape()
            };
            let p = plan(&s, newton);
            // Each Newton iteration's line-search step: with the projection after it
            // (mode 1), or with the colliders' projection in the same pass (mode 3).
            let steps: Vec<&Dispatch> = p
                .iter()
                .filter(|d| d.kernel == Kernel::Advance && d.pass.mode != 0)
                .collect();
            assert_eq!(steps.len(), newton as usize);
            let with: Vec<usize> = (0..steps.len())
                .filter(|&k| steps[k].pass.mode == 1)
                .collect();
            assert_eq!(with, expect, "every {every}, {newton} Newton iterations");
            assert_eq!(
                p.iter().filter(|d| d.kernel == Kernel::Boundary).count(),
                expect.len()
            );
            for (k, d) in p.iter().enumerate() {
                if d.kernel == Kernel::Advance && d.pass.mode == 1 {
                    assert_eq!(p[k + 1].kernel, Kernel::PairProject);
                }
            }
            for (k, d) in p.iter().enumerate() {
                if d.kernel == Kernel::PairProject {
                    assert_eq!(p[k + 1].kernel, Kernel::Boundary);
                    assert_eq!(p[k + 1].pass.mode, 1);
                }
            }
            assert_eq!(
                p.iter().filter(|d| d.kernel == Kernel::PairProject).count(),
                expect.len()
            );
        }
    }

    /// The Chebyshev smoother is one dispatch per level and sweep (over the whole level,
    /// its sweep index the pass's mode), where Gauss–Seidel is one per colour.
    #[test]
    fn a_chebyshev_plan_sweeps_each_level_at_once() {
        let s = Shape {
            smoother: Smoother::Chebyshev,
            ..shape()
        };
        let p = plan(&s, 2);
        let cheb: Vec<&Dispatch> = p.iter().filter(|d| d.kernel == Kernel::Chebyshev).collect();
        assert_eq!(p.iter().filter(|d| d.kernel == Kernel::Smooth).count(), 0);
        assert_eq!(cheb.len(), 2 * (4 + 4 + 30));
        for d in &cheb {
            let [first, count, _, _] = s.levels[d.pass.level as usize];
            assert_eq!((d.pass.first, d.pass.count), (first, count));
            assert_eq!(d.groups, count.div_ceil(8));
        }
        // Each smoothing run counts its sweeps from 0 (the Chebyshev weights restart).
        // (Level 0's last sweep of a run copies its result for the contact pass.)
        let modes: Vec<u32> = cheb.iter().take(4).map(|d| d.pass.mode).collect();
        assert_eq!(modes, [0, 1 | COPY_MODE, 0, 1]);
        // The hybrid: Gauss–Seidel by colour on level 0, Chebyshev below.
        let p = plan(
            &Shape {
                smoother: Smoother::Hybrid,
                ..shape()
            },
            2,
        );
        let on = |k: Kernel| -> Vec<u32> {
            let mut l: Vec<u32> = p
                .iter()
                .filter(|d| d.kernel == k)
                .map(|d| d.pass.level)
                .collect();
            l.dedup();
            l.sort();
            l.dedup();
            l
        };
        assert_eq!(on(Kernel::Smooth), [0]);
        assert_eq!(on(Kernel::Chebyshev), [1, 2]);
        assert_eq!(
            p.iter().filter(|d| d.kernel == Kernel::Smooth).count(),
            2 * 8 * 4
        );
    }

    /// With conjugate gradients (3 V-cycles a Newton iteration), each Newton iteration
    /// runs 3 V-cycles, each followed by its direction, product and update; from the
    /// second on a `pick` of β first; the last update marks the Newton step; then the
    /// trust region as with one V-cycle.
    #[test]
    fn a_conjugate_gradient_plan_runs_its_cycles_between_directions() {
        let s = Shape {
            cycles: 3,
            ..shape()
        };
        let p = plan(&s, 2);
        let count = |k: Kernel| p.iter().filter(|d| d.kernel == k).count();
        assert_eq!(count(Kernel::Restrict), 2 * 3 * 2);
        assert_eq!(count(Kernel::CgMatvec), 2 * 3);
        assert_eq!(count(Kernel::CgDots), 2 * 2);
        let cg: Vec<(Kernel, u32)> = p
            .iter()
            .filter(|d| {
                matches!(
                    d.kernel,
                    Kernel::CgDots | Kernel::CgDirection | Kernel::CgMatvec | Kernel::CgUpdate
                ) || (d.kernel == Kernel::Pick && (5..=6).contains(&d.pass.mode))
            })
            .map(|d| (d.kernel, d.pass.mode))
            .take(16)
            .collect();
        use Kernel::*;
        assert_eq!(
            cg,
            [
                (CgDirection, 0),
                (CgMatvec, 0),
                (Pick, 6),
                (CgUpdate, 0),
                (CgDots, 0),
                (Pick, 5),
                (CgDirection, 1),
                (CgMatvec, 0),
                (Pick, 6),
                (CgUpdate, 1),
                (CgDots, 0),
                (Pick, 5),
                (CgDirection, 1),
                (CgMatvec, 0),
                (Pick, 6),
                (CgUpdate, 3),
            ]
        );
        // The last update takes the trust bounds (mode bit 1); the scaling follows it.
        for (k, d) in p.iter().enumerate() {
            if d.kernel == CgUpdate && d.pass.mode & 2 != 0 {
                assert_eq!(p[k + 1].kernel, TrustScale);
            }
        }
        assert_eq!(count(Kernel::TrustScale), 2);
        assert_eq!(count(Kernel::CgTwoTerms), 0);
        // One V-cycle: the two-direction step after it (its sums over the energy table,
        // its weights, its update taking the trust bounds), no conjugate gradients.
        let one = plan(&shape(), 2);
        assert!(
            one.iter()
                .all(|d| !matches!(d.kernel, CgDots | CgDirection | CgMatvec))
        );
        let after: Vec<(Kernel, u32)> = one
            .iter()
            .enumerate()
            .filter(|(_, d)| d.kernel == Kernel::CgTwoTerms)
            .flat_map(|(k, _)| one[k..k + 4].iter().map(|d| (d.kernel, d.pass.mode)))
            .collect();
        let step = [
            (CgTwoTerms, 0),
            (Pick, 8),
            (CgUpdate, 4 | 2),
            (TrustScale, 0),
        ];
        assert_eq!(after, [step, step].concat());
    }

    /// The plan visits every level once per V-cycle, smooths each colour the configured
    /// number of times, skips empty colours; each reduction dispatches one workgroup per
    /// chunk of its table, and the `pick` after it reads that table's chunks, one
    /// workgroup per body.
    #[test]
    fn plan_is_a_v_cycle_per_newton_iteration() {
        let s = shape();
        let p = plan(&s, 2);
        let count = |k: Kernel| p.iter().filter(|d| d.kernel == k).count();
        assert_eq!(count(Kernel::Predict), 1);
        assert_eq!(count(Kernel::Finish), 1);
        // One per Newton iteration, and one (rotations held) for the colliders'
        // reactions at the substep's end, just before `finish`.
        assert_eq!(count(Kernel::Forces), 3);
        let last = p.len()
            - 1
            - p.iter()
                .rev()
                .position(|d| d.kernel == Kernel::Forces)
                .unwrap();
        assert_eq!(p[last].pass.mode, 1);
        assert_eq!(p[last + 1].kernel, Kernel::Finish);
        // Every level's diagonal blocks in one dispatch, over all 128 nodes.
        assert_eq!(count(Kernel::Diag), 2);
        assert!(
            p.iter()
                .filter(|d| d.kernel == Kernel::Diag)
                .all(|d| (d.pass.first, d.pass.count) == (0, 128))
        );
        assert_eq!(count(Kernel::Restrict), 2 * 2);
        assert_eq!(count(Kernel::Prolong), 2 * 2);
        // Level 0 takes the coarse correction whole as it is prolongated (mode 1, no
        // step along it); level 1 with its step (alpha terms, pick, correct).
        for (i, d) in p.iter().enumerate() {
            if d.kernel == Kernel::Prolong {
                let whole = d.pass.level == 0;
                assert_eq!(d.pass.mode, whole as u32);
                let next = p[i + 1].kernel;
                assert_eq!(
                    next == Kernel::AlphaTerms,
                    !whole,
                    "after prolong: {next:?}"
                );
            }
        }
        assert!(
            p.iter()
                .filter(|d| matches!(d.kernel, Kernel::AlphaTerms | Kernel::Correct))
                .all(|d| d.pass.level == 1)
        );
        // Each V-cycle's translation step, between level 0's residual and its
        // restriction (no residual pass where level 0 is not smoothed before: then it
        // follows the coarse levels' diagonal or the conjugate gradients' last pass).
        assert_eq!(count(Kernel::TranslateTerms), 2);
        let smoothed_before = s.sweeps.fine_before > 0;
        for (i, d) in p.iter().enumerate() {
            if d.kernel == Kernel::TranslateTerms {
                assert_eq!(
                    p[i - 1].kernel == Kernel::FineResidual,
                    smoothed_before,
                    "{:?}",
                    p[i - 1].kernel
                );
                assert_eq!(d.pass.mode, !smoothed_before as u32);
                assert_eq!((p[i + 1].kernel, p[i + 1].pass.mode), (Kernel::Pick, 7));
                assert_eq!(p[i + 2].kernel, Kernel::Translate);
                assert_eq!(p[i + 3].kernel, Kernel::Restrict);
            }
        }
        // Level 1 has an empty colour (7): 7 colours × 4 sweeps; level 0: 8 × 4;
        // coarsest: 8 × 30.
        assert_eq!(count(Kernel::Smooth), 2 * (8 * 4 + 7 * 4 + 8 * 30));
        // One energy pass for the first iterate, two per line search (the second and its
        // `pick` indirect: they run only when the first candidates fail).
        assert_eq!(count(Kernel::EnergyFirst), 1);
        assert_eq!(count(Kernel::Energy), 4);
        let indirect: Vec<(Kernel, u32, Option<u32>)> = p
            .iter()
            .filter(|d| d.indirect.is_some())
            .map(|d| (d.kernel, d.pass.mode, d.indirect))
            .collect();
        let line = [
            (Kernel::Energy, 2, Some(ARGS_LINE)),
            (Kernel::PickPending, 4, Some(ARGS_PENDING)),
        ];
        assert_eq!(indirect, [line, line].concat());
        for (i, d) in p.iter().enumerate() {
            if matches!(d.kernel, Kernel::Pick | Kernel::PickPending) {
                let before = &p[i - 1];
                assert_eq!(d.kernel == Kernel::PickPending, d.pass.mode == 4);
                assert_eq!(d.groups, s.bodies);
                let table = match before.kernel {
                    Kernel::Energy | Kernel::EnergyFirst => 0,
                    Kernel::AlphaTerms => 1 + before.pass.level as usize,
                    Kernel::TranslateTerms => {
                        assert_eq!(d.pass.mode, 7);
                        1
                    }
                    Kernel::CgTwoTerms => {
                        assert_eq!(d.pass.mode, 8);
                        0
                    }
                    other => panic!("pick after {other:?}"),
                };
                let [first, count] = s.tables[table];
                assert_eq!((before.pass.first, before.pass.count), (first, count));
                assert_eq!((before.groups, d.pass.count), (count, count));
                if before.kernel == Kernel::AlphaTerms {
                    assert_eq!(d.pass.level, before.pass.level);
                }
            }
            assert!(d.groups > 0);
        }
        // The trust region needs no reduction: each body's bound by atomics, in the
        // step's update.
        assert!(
            p.iter()
                .filter(|d| d.kernel == Kernel::CgUpdate)
                .all(|d| d.groups == 100u32.div_ceil(WORKGROUP))
        );
    }

    /// A reduction table's chunks cover every item of every body once, each chunk within
    /// one body's run, a multiple of the workgroup long but for a run's last, at most
    /// [`MAX_BODY_CHUNKS`] per body; each body's chunks are where its starts say.
    #[test]
    fn chunks_cover_each_body_apart() {
        let big = (WORKGROUP as usize * MAX_BODY_CHUNKS) as u32 * 3 + 5;
        let runs = [
            [0..10, 100..400],
            [10..10, 400..400],
            [10..10 + big, 0..0],
            [10 + big..10 + big + 64, 400..401],
        ];
        let mut records = Vec::new();
        let mut starts = vec![0u32];
        for (b, r) in runs.iter().enumerate() {
            records.extend(layout::body_chunks(b as u32, r.clone()));
            starts.push(records.len() as u32);
        }
        for (b, r) in runs.iter().enumerate() {
            let own = &records[starts[b] as usize..starts[b + 1] as usize];
            assert!(own.iter().all(|c| c[2] == b as u32));
            assert!(own.len() <= MAX_BODY_CHUNKS);
            let mut items: Vec<u32> = own.iter().flat_map(|c| c[0]..c[0] + c[1]).collect();
            let mut want: Vec<u32> = r.iter().flat_map(|r| r.clone()).collect();
            items.sort();
            want.sort();
            assert_eq!(items, want, "body {b}");
            for c in own {
                let run = r.iter().find(|r| r.contains(&c[0])).unwrap();
                assert!(c[0] + c[1] <= run.end);
                assert!(c[1] % WORKGROUP == 0 || c[0] + c[1] == run.end);
            }
        }
        assert_eq!(starts[1] - starts[0], 1 + 5); // 10 items, then 300 in 64s
        assert_eq!(starts[2], starts[1]); // a body without items
    }
}
