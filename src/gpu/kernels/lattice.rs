//! Newton–multigrid on lattice bodies: the kernels of one implicit-Euler substep
//! (predict, element forces, the V-cycle's smoothing, restriction and prolongation, the
//! line search's energy and its reductions, finish).
//!
//! Source: `lattice.wgsl`, with `common.wgsl` and the declarations made from [`SLOTS`]
//! prepended. [`SLOTS`] is the one binding table of these kernels: each kernel's layout
//! and bind group hold only the slots its entry point uses ([`ENTRIES`]), so every
//! pipeline fits WebGPU's guaranteed limits (at most 8 storage buffers per stage, one
//! bind group, at most 256 invocations and 16 KiB of workgroup memory per workgroup).

use crate::core::TissueError;
use crate::core::dense::packed_len;
use crate::core::multigrid::EXACT_COARSEST;
use bevy::render::render_resource::{
    BindGroupLayout, BindGroupLayoutEntry, BindingType, BufferBindingType, ComputePipeline,
    PipelineCompilationOptions, PipelineLayoutDescriptor, RawComputePipelineDescriptor,
    ShaderModuleDescriptor, ShaderSource, ShaderStages,
};
use bevy::render::renderer::RenderDevice;
use std::borrow::Cow;

pub use super::bindings::Access;

/// One binding of the lattice kernels: its name in WGSL, its WGSL type and access. Its
/// binding number is its index in [`SLOTS`]; every slot is in group 0.
#[derive(Debug, Clone, Copy)]
pub struct Slot {
    /// Variable name in WGSL.
    pub name: &'static str,
    /// WGSL type.
    pub ty: &'static str,
    /// Access.
    pub access: Access,
}

/// The binding table, grouped by lifetime: per-world parameters and per-dispatch ranges;
/// per-step state and solver work; the static model.
pub const SLOTS: &[Slot] = &[
    Slot {
        name: "params",
        ty: "LatticeParams",
        access: Access::Uniform,
    },
    Slot {
        name: "pc",
        ty: "Pass",
        access: Access::Dynamic,
    },
    Slot {
        name: "cols",
        ty: "array<Collider, 32>",
        access: Access::Uniform,
    },
    Slot {
        name: "pos",
        ty: "array<vec4<f32>>",
        access: Access::ReadWrite,
    },
    Slot {
        name: "rot",
        ty: "array<vec4<f32>>",
        access: Access::ReadWrite,
    },
    Slot {
        name: "ef",
        ty: "array<vec4<f32>>",
        access: Access::ReadWrite,
    },
    Slot {
        name: "vecs",
        ty: "array<vec4<f32>>",
        access: Access::ReadWrite,
    },
    Slot {
        name: "nblk",
        ty: "array<vec4<f32>>",
        access: Access::ReadWrite,
    },
    Slot {
        name: "red",
        ty: "array<f32>",
        access: Access::ReadWrite,
    },
    Slot {
        name: "args",
        ty: "array<atomic<u32>>",
        access: Access::ReadWrite,
    },
    Slot {
        name: "ccol",
        ty: "array<vec4<f32>>",
        access: Access::ReadWrite,
    },
    Slot {
        name: "elems",
        ty: "array<vec4<u32>>",
        access: Access::Read,
    },
    Slot {
        name: "kmat",
        ty: "array<vec4<f32>>",
        access: Access::Read,
    },
    Slot {
        name: "topo",
        ty: "array<u32>",
        access: Access::Read,
    },
    Slot {
        name: "nodes",
        ty: "array<vec4<f32>>",
        access: Access::Read,
    },
    Slot {
        name: "mats",
        ty: "array<vec4<f32>>",
        access: Access::Read,
    },
    Slot {
        name: "bodyt",
        ty: "array<atomic<u32>>",
        access: Access::ReadWrite,
    },
    Slot {
        name: "cfac",
        ty: "array<f32>",
        access: Access::ReadWrite,
    },
];

/// The entry points of `lattice.wgsl`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Kernel {
    /// `predict`: inertial targets, first iterates, grasps.
    Predict,
    /// `energy_first`: energy changes of the first iterate's candidates.
    EnergyFirst,
    /// `energy`: energy changes of the line search's candidate steps.
    Energy,
    /// `pick`: sums each body's partial sums and picks its step.
    Pick,
    /// `pick_pending`: the line search's second pick, for the bodies its first left
    /// pending (dispatched indirectly, only where there are any).
    PickPending,
    /// `advance`: takes the picked step (and, for the line search's step where no
    /// particle-contact projection follows, the boundary's projection).
    Advance,
    /// `forces`: element forces and rotations.
    Forces,
    /// `residual`: the Newton residual, level 0's right-hand side.
    Residual,
    /// `coarsen_level`: a coarse level's element rotations and contact stiffness from
    /// the finer level's.
    CoarsenLevel,
    /// `diag`: inverted diagonal blocks of a level.
    Diag,
    /// `smooth_colour`: one colour of a Gauss–Seidel sweep.
    Smooth,
    /// `smooth_chebyshev`: one Chebyshev–Jacobi sweep of a level.
    Chebyshev,
    /// `contact_smooth`: level 0's contact pass after its Chebyshev sweeps (each node
    /// with a contact penalty solved for its own block, over the list of such nodes
    /// [`Kernel::Contacts`] made).
    ContactSmooth,
    /// `smooth_coarsest`: every Chebyshev sweep of the coarsest level, a workgroup per
    /// body.
    Coarsest,
    /// `smooth_coarsest_small`: as `smooth_coarsest`, where no body has more than
    /// [`SMALL_COARSEST`](crate::gpu::lattice::SMALL_COARSEST) nodes on the coarsest
    /// level (each thread holds one element from sweep to sweep, not up to four).
    CoarsestSmall,
    /// `solve_coarsest`: the coarsest level solved exactly, a workgroup per body (its
    /// system factorised, `L D Lᵀ`, in workgroup memory), where no body has more than
    /// [`EXACT_COARSEST`] nodes there.
    CoarsestExact,
    /// `factor_coarsest`: each body's coarsest-level matrix factorised, `L D Lᵀ`, into
    /// the world's factor buffer, once a Newton iteration (where the world keeps it).
    FactorCoarsest,
    /// `solve_factored`: the coarsest level solved exactly from the factor
    /// [`Kernel::FactorCoarsest`] kept (the same answer as [`Kernel::CoarsestExact`]).
    CoarsestFactored,
    /// `fine_residual`: a level's residual before restriction.
    FineResidual,
    /// `restrict_residual`: the next coarser level's right-hand side.
    Restrict,
    /// `prolong`: the coarse correction on the finer level.
    Prolong,
    /// `alpha_terms`: partial sums of the coarse correction's step.
    AlphaTerms,
    /// `correct`: adds the scaled coarse correction.
    Correct,
    /// `trust_scale`: each body's step scaled to its trust-region bound.
    TrustScale,
    /// `finish`: velocities and positions at the end of a substep.
    Finish,
    /// `contacts`: penalty contacts with the colliders and between bodies; lists the
    /// nodes with a contact block for [`Kernel::ContactSmooth`].
    Contacts,
    /// `pair_project`: the particle contacts' Jacobi projection between bodies.
    PairProject,
    /// `boundary`: projection out of the colliders, grasp targets, contact forces.
    Boundary,
    /// `force_partials`: partial sums of the forces on each collider.
    ForcePartials,
    /// `force_total`: the step's force on each collider.
    ForceTotal,
    /// `force_clear`: zeroes the step's collider forces.
    ForceClear,
    /// `cg_dots`: partial sums of the next conjugate direction's β.
    CgDots,
    /// `cg_direction`: the next conjugate direction.
    CgDirection,
    /// `cg_two_terms`: the two-direction step's partial sums (its directions' products
    /// with the Newton matrix, element by element, over the energy table's chunks).
    CgTwoTerms,
    /// `cg_matvec`: the direction times the Newton matrix, and the step's partial sums.
    CgMatvec,
    /// `cg_update`: the conjugate gradients' step on the iterate and the residual, or the
    /// two-direction step; after the last, each body's trust bound.
    CgUpdate,
    /// `translate_terms`: partial sums of each body's level-0 residual and mass for its
    /// translation step.
    TranslateTerms,
    /// `translate`: each free body's translation step on its level-0 correction and
    /// residual.
    Translate,
}

/// One entry point and the slots it uses.
#[derive(Debug, Clone, Copy)]
pub struct Entry {
    /// The kernel.
    pub kernel: Kernel,
    /// Entry point name in WGSL.
    pub name: &'static str,
    /// Slots (by name) the entry point uses, in [`SLOTS`] order.
    pub uses: &'static [&'static str],
}

/// Every entry point with its slots (a test checks them against the shader).
pub const ENTRIES: &[Entry] = &[
    Entry {
        kernel: Kernel::Predict,
        name: "predict",
        uses: &["params", "cols", "pos", "ccol", "nodes", "mats"],
    },
    Entry {
        kernel: Kernel::EnergyFirst,
        name: "energy_first",
        uses: &[
            "params", "pc", "pos", "rot", "red", "ccol", "elems", "nodes", "mats",
        ],
    },
    Entry {
        kernel: Kernel::Energy,
        name: "energy",
        uses: &[
            "params", "pc", "cols", "pos", "rot", "vecs", "red", "ccol", "elems", "nodes", "mats",
        ],
    },
    Entry {
        kernel: Kernel::Pick,
        name: "pick",
        uses: &["params", "pc", "red", "args", "elems"],
    },
    Entry {
        kernel: Kernel::PickPending,
        name: "pick_pending",
        uses: &["params", "pc", "red", "elems"],
    },
    Entry {
        kernel: Kernel::Advance,
        name: "advance",
        uses: &[
            "params", "pc", "cols", "pos", "vecs", "red", "args", "ccol", "nodes", "mats", "bodyt",
        ],
    },
    Entry {
        kernel: Kernel::Forces,
        name: "forces",
        uses: &["params", "pc", "pos", "rot", "ef", "elems", "mats"],
    },
    Entry {
        kernel: Kernel::Residual,
        name: "residual",
        uses: &[
            "params", "pos", "ef", "vecs", "args", "ccol", "topo", "nodes",
        ],
    },
    Entry {
        kernel: Kernel::CoarsenLevel,
        name: "coarsen_level",
        uses: &["params", "pc", "rot", "nblk", "topo"],
    },
    Entry {
        kernel: Kernel::Diag,
        name: "diag",
        uses: &[
            "params", "pc", "rot", "nblk", "elems", "kmat", "topo", "nodes",
        ],
    },
    Entry {
        kernel: Kernel::Smooth,
        name: "smooth_colour",
        uses: &[
            "params", "pc", "rot", "vecs", "nblk", "ccol", "elems", "kmat", "topo", "nodes",
        ],
    },
    Entry {
        kernel: Kernel::Chebyshev,
        name: "smooth_chebyshev",
        uses: &[
            "params", "pc", "rot", "vecs", "nblk", "ccol", "elems", "kmat", "topo", "nodes",
        ],
    },
    Entry {
        kernel: Kernel::ContactSmooth,
        name: "contact_smooth",
        uses: &[
            "params", "rot", "vecs", "nblk", "ccol", "elems", "kmat", "topo", "nodes",
        ],
    },
    Entry {
        kernel: Kernel::Coarsest,
        name: "smooth_coarsest",
        uses: &[
            "params", "pc", "rot", "vecs", "nblk", "elems", "kmat", "topo", "nodes",
        ],
    },
    Entry {
        kernel: Kernel::CoarsestSmall,
        name: "smooth_coarsest_small",
        uses: &[
            "params", "pc", "rot", "vecs", "nblk", "elems", "kmat", "topo", "nodes",
        ],
    },
    Entry {
        kernel: Kernel::CoarsestExact,
        name: "solve_coarsest",
        uses: &[
            "params", "pc", "rot", "vecs", "nblk", "elems", "kmat", "topo", "nodes",
        ],
    },
    Entry {
        kernel: Kernel::FactorCoarsest,
        name: "factor_coarsest",
        uses: &[
            "params", "pc", "rot", "nblk", "elems", "kmat", "topo", "nodes", "cfac",
        ],
    },
    Entry {
        kernel: Kernel::CoarsestFactored,
        name: "solve_factored",
        uses: &["params", "pc", "vecs", "elems", "nodes", "cfac"],
    },
    Entry {
        kernel: Kernel::FineResidual,
        name: "fine_residual",
        uses: &[
            "params", "pc", "rot", "vecs", "nblk", "ccol", "elems", "kmat", "topo", "nodes",
        ],
    },
    Entry {
        kernel: Kernel::Restrict,
        name: "restrict_residual",
        uses: &["params", "pc", "vecs", "topo", "nodes"],
    },
    Entry {
        kernel: Kernel::Prolong,
        name: "prolong",
        uses: &["params", "pc", "vecs", "ccol", "topo", "nodes"],
    },
    Entry {
        kernel: Kernel::AlphaTerms,
        name: "alpha_terms",
        uses: &[
            "params", "pc", "rot", "vecs", "nblk", "red", "elems", "kmat", "topo", "nodes",
        ],
    },
    Entry {
        kernel: Kernel::Correct,
        name: "correct",
        uses: &["params", "pc", "vecs", "red", "nodes"],
    },
    Entry {
        kernel: Kernel::TrustScale,
        name: "trust_scale",
        uses: &["params", "vecs", "ccol", "nodes", "bodyt"],
    },
    Entry {
        kernel: Kernel::Finish,
        name: "finish",
        uses: &[
            "params", "cols", "pos", "ef", "ccol", "topo", "nodes", "mats",
        ],
    },
    Entry {
        kernel: Kernel::Contacts,
        name: "contacts",
        uses: &[
            "params", "cols", "pos", "vecs", "nblk", "args", "ccol", "nodes", "mats", "bodyt",
        ],
    },
    Entry {
        kernel: Kernel::PairProject,
        name: "pair_project",
        uses: &["params", "pos", "vecs", "ccol", "nodes", "mats"],
    },
    Entry {
        kernel: Kernel::Boundary,
        name: "boundary",
        uses: &[
            "params", "pc", "cols", "pos", "vecs", "ccol", "nodes", "mats",
        ],
    },
    Entry {
        kernel: Kernel::ForcePartials,
        name: "force_partials",
        uses: &["params", "cols", "red", "ccol", "nodes"],
    },
    Entry {
        kernel: Kernel::ForceTotal,
        name: "force_total",
        uses: &["params", "pc", "red"],
    },
    Entry {
        kernel: Kernel::ForceClear,
        name: "force_clear",
        uses: &["params", "red"],
    },
    Entry {
        kernel: Kernel::CgDots,
        name: "cg_dots",
        uses: &["params", "pc", "vecs", "red", "elems"],
    },
    Entry {
        kernel: Kernel::CgDirection,
        name: "cg_direction",
        uses: &["params", "pc", "vecs", "red", "ccol", "nodes"],
    },
    Entry {
        kernel: Kernel::CgTwoTerms,
        name: "cg_two_terms",
        uses: &[
            "params", "pc", "rot", "vecs", "nblk", "red", "ccol", "elems", "kmat", "nodes",
        ],
    },
    Entry {
        kernel: Kernel::CgMatvec,
        name: "cg_matvec",
        uses: &[
            "params", "pc", "rot", "vecs", "nblk", "red", "elems", "kmat", "topo", "nodes",
        ],
    },
    Entry {
        kernel: Kernel::CgUpdate,
        name: "cg_update",
        uses: &["params", "pc", "vecs", "red", "ccol", "nodes", "bodyt"],
    },
    Entry {
        kernel: Kernel::TranslateTerms,
        name: "translate_terms",
        uses: &[
            "params", "pc", "vecs", "nblk", "red", "ccol", "elems", "nodes",
        ],
    },
    Entry {
        kernel: Kernel::Translate,
        name: "translate",
        uses: &["params", "pc", "vecs", "nblk", "red", "ccol", "nodes"],
    },
];

/// Floats each body's coarsest-level factor takes in the factor buffer
/// ([`Kernel::FactorCoarsest`]): the packed lower triangle of [`EXACT_COARSEST`] nodes'
/// rows, then whether every pivot was positive (1 or 0).
pub const FACTOR_STRIDE: usize = packed_len(3 * EXACT_COARSEST) + 1;

/// Colliders the lattice kernels take at once.
pub const MAX_COLLIDERS: usize = 32;

/// Threads per workgroup of every lattice kernel.
pub const WORKGROUP: u32 = 64;

/// The slot index (binding number) of `name`.
pub fn slot(name: &str) -> Option<u32> {
    SLOTS.iter().position(|s| s.name == name).map(|i| i as u32)
}

/// The module's WGSL: `common.wgsl`, the declarations of [`SLOTS`], the size of the
/// exact coarsest solve ([`EXACT_COARSEST`] nodes), `lattice.wgsl`.
pub fn source() -> String {
    let mut s = String::from(include_str!("common.wgsl"));
    let rows = 3 * EXACT_COARSEST;
    s.push_str(&format!(
        "\n// The exact coarsest solve's most nodes a body, its rows, the packed length of its\n\
         // bordered matrix, and the floats a body's factor takes in `cfac`\n\
         // (core::multigrid::EXACT_COARSEST).\n\
         const EXACT_NODES: u32 = {EXACT_COARSEST}u;\n\
         const EXACT_ROWS: u32 = {rows}u;\n\
         const EXACT_PACKED: u32 = {}u;\n\
         const FACTOR_STRIDE: u32 = {FACTOR_STRIDE}u;\n\
         // Vec4s of a body's material record in `mats` (gpu::lattice's MAT_RECORD).\n\
         const MAT_STRIDE: u32 = {}u;\n\
         // How far past their contact distance (a fraction of it) two nodes of different\n\
         // bodies still hold each other in a Newton iteration (core::solver::PAIR_HOLD).\n\
         const PAIR_HOLD: f32 = {:?};\n",
        packed_len(rows + 1),
        crate::gpu::lattice::MAT_RECORD,
        crate::core::solver::PAIR_HOLD,
    ));
    s.push_str("\n// Bindings (src/gpu/kernels/lattice.rs, SLOTS).\n");
    // The declarations refer to the structs of lattice.wgsl; WGSL resolves them in any
    // order.
    for (i, slot) in SLOTS.iter().enumerate() {
        let space = match slot.access {
            Access::Uniform | Access::Dynamic => "uniform".to_string(),
            Access::Read => "storage, read".to_string(),
            Access::ReadWrite => "storage, read_write".to_string(),
        };
        s.push_str(&format!(
            "@group(0) @binding({i}) var<{space}> {}: {};\n",
            slot.name, slot.ty
        ));
    }
    s.push_str(include_str!("lattice.wgsl"));
    s
}

/// The storage buffers an entry point binds.
pub fn storage_count(entry: &Entry) -> u32 {
    entry
        .uses
        .iter()
        .filter(|n| {
            SLOTS
                .iter()
                .any(|s| s.name == **n && matches!(s.access, Access::Read | Access::ReadWrite))
        })
        .count() as u32
}

/// Compiled lattice pipelines with their layouts (cheap to clone: the pipelines are
/// shared).
#[derive(Clone)]
pub struct LatticeKernels {
    /// Per [`ENTRIES`] entry: its pipeline and the layout of its one bind group.
    pub pipelines: Vec<(ComputePipeline, BindGroupLayout)>,
}

impl LatticeKernels {
    /// Compiles every lattice kernel for `device`, each with a layout of only the slots
    /// it uses. Fails with [`TissueError::GpuUnsupported`] where the adapter binds fewer
    /// storage buffers per stage than a kernel needs.
    pub fn new(device: &RenderDevice) -> Result<Self, TissueError> {
        let limits = device.limits();
        let needed = ENTRIES.iter().map(storage_count).max().unwrap_or(0);
        if limits.max_storage_buffers_per_shader_stage < needed {
            return Err(TissueError::GpuUnsupported {
                what: "storage buffers per shader stage",
                needed: needed as u64,
                limit: limits.max_storage_buffers_per_shader_stage as u64,
            });
        }
        let module = device.create_and_validate_shader_module(ShaderModuleDescriptor {
            label: Some("tissue lattice"),
            source: ShaderSource::Wgsl(Cow::Owned(source())),
        });
        let mut pipelines = Vec::with_capacity(ENTRIES.len());
        for entry in ENTRIES {
            let mut layout_entries = Vec::new();
            for name in entry.uses {
                let Some(b) = slot(name) else {
                    continue;
                };
                let ty = match SLOTS[b as usize].access {
                    Access::Uniform | Access::Dynamic => BindingType::Buffer {
                        ty: BufferBindingType::Uniform,
                        has_dynamic_offset: SLOTS[b as usize].access == Access::Dynamic,
                        min_binding_size: None,
                    },
                    Access::Read | Access::ReadWrite => BindingType::Buffer {
                        ty: BufferBindingType::Storage {
                            read_only: SLOTS[b as usize].access == Access::Read,
                        },
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                };
                layout_entries.push(BindGroupLayoutEntry {
                    binding: b,
                    visibility: ShaderStages::COMPUTE,
                    ty,
                    count: None,
                });
            }
            let bgl = device.create_bind_group_layout(entry.name, &layout_entries);
            let layout = device.create_pipeline_layout(&PipelineLayoutDescriptor {
                label: Some(entry.name),
                bind_group_layouts: &[Some(&*bgl)],
                immediate_size: 0,
            });
            let pipeline = device.create_compute_pipeline(&RawComputePipelineDescriptor {
                label: Some(entry.name),
                layout: Some(&layout),
                module: &module,
                entry_point: Some(entry.name),
                compilation_options: PipelineCompilationOptions::default(),
                cache: None,
            });
            pipelines.push((pipeline, bgl));
        }
        Ok(Self { pipelines })
    }

    /// Index of `kernel` in [`LatticeKernels::pipelines`] and [`ENTRIES`].
    pub fn index(kernel: Kernel) -> usize {
        ENTRIES
            .iter()
            .position(|e| e.kernel == kernel)
            .unwrap_or_default()
    }
}
