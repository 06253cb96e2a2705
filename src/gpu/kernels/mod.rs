//! The compute kernels, one `.rs` + `.wgsl` pair each, and [`Kernels`], their compiled
//! pipelines.
//!
//! Every kernel binds the same "world" bind group (group 0, declared once in
//! `bindings.wgsl`): all bodies' buffers, so one dispatch serves every body. The prefix
//! sum, the cluster, gather and hierarchy kernels (their particle range: level 0 or a
//! coarse level) and the skinning add a small group 1 (a per-dispatch uniform with a
//! dynamic offset; the skinning also the mesh allocator's vertex slab). Shaders are embedded in
//! the binary (`include_str!`), so a user of the crate copies no files.

pub mod body;
pub mod broad;
pub mod cluster;
pub mod forces;
pub mod gather;
pub mod grid;
pub mod hierarchy;
pub mod integrate;
pub mod knn;
pub mod lattice;
pub mod skin;

use crate::core::TissueError;
use bevy::render::render_resource::{
    BindGroupLayout, BindGroupLayoutEntry, BindingType, BufferBindingType, ComputePipeline,
    PipelineCompilationOptions, PipelineLayoutDescriptor, ShaderModuleDescriptor, ShaderSource,
    ShaderStages,
};
use bevy::render::renderer::RenderDevice;
use std::borrow::Cow;

/// Bindings of the world group that the kernels only read.
const READ_ONLY: &[u32] = &[6, 7, 8, 9, 10, 13, 22, 23, 24, 25, 26, 30];
/// Bindings of the world group (0 and 1 are uniforms, the rest storage buffers).
pub const WORLD_BINDINGS: u32 = 33;
/// Storage buffers a kernel binds at most (world group plus the vertex slab).
pub const STORAGE_BUFFERS_NEEDED: u32 = WORLD_BINDINGS - 2 + 1;

fn uniform(binding: u32, dynamic: bool) -> BindGroupLayoutEntry {
    BindGroupLayoutEntry {
        binding,
        visibility: ShaderStages::COMPUTE,
        ty: BindingType::Buffer {
            ty: BufferBindingType::Uniform,
            has_dynamic_offset: dynamic,
            min_binding_size: None,
        },
        count: None,
    }
}

fn storage(binding: u32, read_only: bool) -> BindGroupLayoutEntry {
    BindGroupLayoutEntry {
        binding,
        visibility: ShaderStages::COMPUTE,
        ty: BindingType::Buffer {
            ty: BufferBindingType::Storage { read_only },
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

/// The two entry points of `body.wgsl`.
pub struct BodyKernels {
    /// All iterations of a substep for the bodies near no other.
    pub substep: ComputePipeline,
    /// One iteration for the bodies with contact candidates.
    pub iteration: ComputePipeline,
}

/// All compiled pipelines and bind group layouts (one per device, shared by every world).
pub struct Kernels {
    /// Group 0 of every kernel.
    pub world_layout: BindGroupLayout,
    /// Group 1 of the prefix sum (the scan level) and of the cluster, gather and
    /// hierarchy kernels (the range): one uniform with a dynamic offset.
    pub scan_layout: BindGroupLayout,
    /// Group 1 of the draw path: the vertex slab and the range uniform (dynamic offset).
    pub skin_layout: BindGroupLayout,
    /// `integrate.wgsl`: predict.
    pub predict: ComputePipeline,
    /// `integrate.wgsl`: finish.
    pub finish: ComputePipeline,
    /// `integrate.wgsl`: a substep's finish and the next one's predict.
    pub finish_predict: ComputePipeline,
    /// `grid.wgsl`: zero the counts.
    pub grid_clear: ComputePipeline,
    /// `forces.wgsl`: each body's bounding box.
    pub body_bounds: ComputePipeline,
    /// `broad.wgsl`: which bodies are near another (contact broad phase).
    pub near_bodies: ComputePipeline,
    /// `forces.wgsl`: zero the totals.
    pub force_clear: ComputePipeline,
    /// `grid.wgsl`: cell counts.
    pub grid_count: ComputePipeline,
    /// `grid.wgsl`: block scan.
    pub scan_block: ComputePipeline,
    /// `grid.wgsl`: block offsets.
    pub scan_add: ComputePipeline,
    /// `grid.wgsl`: scatter.
    pub grid_scatter: ComputePipeline,
    /// `knn.wgsl`: K nearest of all particles, one pipeline per variant (cold: the first
    /// search; warm: later ones, starting from the previous lists) and list size
    /// ([`knn::SLOT_COUNTS`]; pick with `[warm as usize][Kernels::knn_slots(k)]`).
    pub knn_all: [[ComputePipeline; 2]; 2],
    /// `knn.wgsl`: contact candidates, per variant and list size like `knn_all`.
    pub knn_contacts: [[ComputePipeline; 2]; 2],
    /// `cluster.wgsl`: Jacobi pass A, a thread per cluster.
    pub clusters: ComputePipeline,
    /// `cluster.wgsl`: Jacobi pass A, 8 threads per cluster (small ranges).
    pub clusters_lanes: ComputePipeline,
    /// `gather.wgsl`: Jacobi pass B.
    pub gather: ComputePipeline,
    /// `gather.wgsl`: Jacobi pass C.
    pub contact: ComputePipeline,
    /// `body.wgsl`: passes A and B of small shape-matching bodies, a workgroup each;
    /// `None` where the adapter's workgroups are too small for it.
    pub body: Option<BodyKernels>,
    /// `hierarchy.wgsl`: positions at the start of the coarse pass.
    pub level_snapshot: ComputePipeline,
    /// `hierarchy.wgsl`: level-0 positions into a coarse level.
    pub level_in: ComputePipeline,
    /// `hierarchy.wgsl`: a coarse level's positions back to level 0.
    pub level_out: ComputePipeline,
    /// `hierarchy.wgsl`: prolongation to the finer level.
    pub prolong: ComputePipeline,
    /// `hierarchy.wgsl`: multipliers handed to the finer level.
    pub transfer: ComputePipeline,
    /// `forces.wgsl`: partial sums.
    pub force_partial: ComputePipeline,
    /// `forces.wgsl`: totals.
    pub force_total: ComputePipeline,
    /// `skin.wgsl`: deformation gradients.
    pub deform: ComputePipeline,
    /// `skin.wgsl`: skinning.
    pub skin: ComputePipeline,
    /// `skin.wgsl`: normals.
    pub normals: ComputePipeline,
}

impl Kernels {
    /// Index into [`Kernels::knn_all`] and [`Kernels::knn_contacts`] of the smallest list
    /// that holds `k` neighbours.
    pub fn knn_slots(k: u32) -> usize {
        knn::SLOT_COUNTS
            .iter()
            .position(|&s| k <= s)
            .unwrap_or(knn::SLOT_COUNTS.len() - 1)
    }

    /// Compiles every kernel for `device`. Fails with [`TissueError::GpuUnsupported`] if
    /// the adapter cannot bind the storage buffers the kernels need.
    pub fn new(device: &RenderDevice) -> Result<Self, TissueError> {
        let limits = device.limits();
        if limits.max_storage_buffers_per_shader_stage < STORAGE_BUFFERS_NEEDED {
            return Err(TissueError::GpuUnsupported {
                what: "storage buffers per shader stage",
                needed: STORAGE_BUFFERS_NEEDED as u64,
                limit: limits.max_storage_buffers_per_shader_stage as u64,
            });
        }
        let mut world = vec![uniform(0, false), uniform(1, false)];
        for b in 2..WORLD_BINDINGS {
            world.push(storage(b, READ_ONLY.contains(&b)));
        }
        let world_layout = device.create_bind_group_layout("tissue world", &world);
        let scan_layout = device.create_bind_group_layout("tissue scan level", &[uniform(0, true)]);
        let skin_layout = device
            .create_bind_group_layout("tissue vertex slab", &[storage(0, false), uniform(1, true)]);
        let layout = |extra: Option<&BindGroupLayout>| {
            let groups: Vec<Option<&wgpu::BindGroupLayout>> = match extra {
                Some(e) => vec![Some(&*world_layout), Some(&**e)],
                None => vec![Some(&*world_layout)],
            };
            device.create_pipeline_layout(&PipelineLayoutDescriptor {
                label: Some("tissue"),
                bind_group_layouts: &groups,
                immediate_size: 0,
            })
        };
        let world_only = layout(None);
        let with_scan = layout(Some(&scan_layout));
        let with_skin = layout(Some(&skin_layout));
        let module = |name: &str, src: &'static str| {
            device.create_and_validate_shader_module(ShaderModuleDescriptor {
                label: Some(name),
                source: ShaderSource::Wgsl(Cow::Borrowed(src)),
            })
        };
        let integrate_m = module("tissue integrate", integrate::SOURCE);
        let grid_m = module("tissue grid", grid::SOURCE);
        let knn_m = [false, true].map(|warm| {
            knn::SLOT_COUNTS.map(|slots| {
                device.create_and_validate_shader_module(ShaderModuleDescriptor {
                    label: Some("tissue knn"),
                    source: ShaderSource::Wgsl(Cow::Owned(knn::source(slots, warm))),
                })
            })
        });
        let cluster_m = module("tissue cluster", cluster::SOURCE);
        let gather_m = module("tissue gather", gather::SOURCE);
        let body_fits = limits.max_compute_workgroup_storage_size >= body::WORKGROUP_BYTES
            && limits.max_compute_invocations_per_workgroup >= body::THREADS
            && limits.max_compute_workgroup_size_x >= body::THREADS;
        let body_m = body_fits.then(|| module("tissue body", body::SOURCE));
        let hier_m = module("tissue hierarchy", hierarchy::SOURCE);
        let forces_m = module("tissue forces", forces::SOURCE);
        let broad_m = module("tissue broad phase", broad::SOURCE);
        let skin_m = module("tissue skin", skin::SOURCE);
        let pipe = |m: &bevy::render::render_resource::ShaderModule,
                    l: &bevy::render::render_resource::PipelineLayout,
                    entry: &'static str| {
            device.create_compute_pipeline(
                &bevy::render::render_resource::RawComputePipelineDescriptor {
                    label: Some(entry),
                    layout: Some(l),
                    module: m,
                    entry_point: Some(entry),
                    compilation_options: PipelineCompilationOptions::default(),
                    cache: None,
                },
            )
        };
        Ok(Self {
            predict: pipe(&integrate_m, &world_only, "predict"),
            finish: pipe(&integrate_m, &world_only, "finish"),
            finish_predict: pipe(&integrate_m, &world_only, "finish_predict"),
            grid_clear: pipe(&grid_m, &with_scan, "grid_clear"),
            force_clear: pipe(&forces_m, &world_only, "force_clear"),
            body_bounds: pipe(&forces_m, &world_only, "body_bounds"),
            near_bodies: pipe(&broad_m, &world_only, "near_bodies"),
            grid_count: pipe(&grid_m, &with_scan, "grid_count"),
            scan_block: pipe(&grid_m, &with_scan, "scan_block"),
            scan_add: pipe(&grid_m, &with_scan, "scan_add"),
            grid_scatter: pipe(&grid_m, &with_scan, "grid_scatter"),
            knn_all: knn_m
                .each_ref()
                .map(|v| v.each_ref().map(|m| pipe(m, &world_only, "knn_all"))),
            knn_contacts: knn_m
                .each_ref()
                .map(|v| v.each_ref().map(|m| pipe(m, &world_only, "knn_contacts"))),
            clusters: pipe(&cluster_m, &with_scan, "solve_clusters"),
            clusters_lanes: pipe(&cluster_m, &with_scan, "solve_clusters_lanes"),
            gather: pipe(&gather_m, &with_scan, "gather"),
            contact: pipe(&gather_m, &with_scan, "contact"),
            body: body_m.map(|m| BodyKernels {
                substep: pipe(&m, &with_scan, "body_substep"),
                iteration: pipe(&m, &with_scan, "body_iteration"),
            }),
            level_snapshot: pipe(&hier_m, &world_only, "level_snapshot"),
            level_in: pipe(&hier_m, &with_scan, "level_in"),
            level_out: pipe(&hier_m, &with_scan, "level_out"),
            prolong: pipe(&hier_m, &with_scan, "prolong"),
            transfer: pipe(&hier_m, &with_scan, "transfer"),
            force_partial: pipe(&forces_m, &world_only, "force_partial"),
            force_total: pipe(&forces_m, &world_only, "force_total"),
            deform: pipe(&skin_m, &with_skin, "deform"),
            skin: pipe(&skin_m, &with_skin, "skin"),
            normals: pipe(&skin_m, &with_skin, "normals"),
            world_layout,
            scan_layout,
            skin_layout,
        })
    }
}
