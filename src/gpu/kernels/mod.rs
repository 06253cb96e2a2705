//! The compute kernels, one `.rs` + `.wgsl` pair each, and [`Kernels`], their compiled
//! pipelines.
//!
//! Every binding of the simulation and draw kernels is declared once, in the binding
//! table of [`bindings`], grouped by lifetime (per-frame parameters, particle state, the
//! static model, per-dispatch ranges). Each kernel's pipeline layout holds only the
//! bindings its entry point uses, found by naga's analysis of its module, so one dispatch
//! still serves every body while no kernel asks for more than it needs. Shaders are
//! embedded in the binary (`include_str!`), so a user of the crate copies no files.

pub mod bindings;
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
    BindGroupLayout, ComputePipeline, PipelineCompilationOptions, PipelineLayoutDescriptor,
    RawComputePipelineDescriptor, ShaderModule, ShaderModuleDescriptor, ShaderSource,
};
use bevy::render::renderer::RenderDevice;
use bindings::{Analysis, TABLE};
use std::borrow::Cow;

/// Storage buffers per shader stage that WebGPU guarantees; every kernel but the
/// optional workgroup-per-body ones ([`BodyKernels`]) fits it.
pub const WEBGPU_STORAGE_BUFFERS: u32 = 8;

/// One compiled kernel: its pipeline and, per bind group up to the last it uses, the
/// layout of the bindings it uses there (an empty layout for a group it skips).
pub struct Kernel {
    /// Entry point name.
    pub name: &'static str,
    /// Index among the kernels of one [`Kernels`] (worlds keep bind groups by it).
    pub id: usize,
    /// The pipeline.
    pub pipeline: ComputePipeline,
    /// Per group: its layout and the [`bindings::TABLE`] entries in it.
    pub groups: Vec<(BindGroupLayout, Vec<usize>)>,
}

impl Kernel {
    /// Every [`bindings::TABLE`] entry the kernel binds.
    pub fn uses(&self) -> Vec<usize> {
        self.groups
            .iter()
            .flat_map(|g| g.1.iter().copied())
            .collect()
    }

    /// Storage buffers the kernel binds.
    pub fn storage_buffers(&self) -> u32 {
        bindings::storage_count(&self.uses())
    }
}

/// The two entry points of `body.wgsl`: made only where the adapter allows their
/// workgroups ([`body::WORKGROUP_BYTES`], [`body::THREADS`]) and their storage buffers
/// (more than WebGPU guarantees); elsewhere the cluster and gather kernels solve every
/// body.
pub struct BodyKernels {
    /// All iterations of a substep for the bodies near no other.
    pub substep: Kernel,
    /// One iteration for the bodies with contact candidates.
    pub iteration: Kernel,
}

/// All compiled kernels (one per device, shared by every world).
pub struct Kernels {
    /// `integrate.wgsl`: predict.
    pub predict: Kernel,
    /// `integrate.wgsl`: finish.
    pub finish: Kernel,
    /// `integrate.wgsl`: a substep's finish and the next one's predict.
    pub finish_predict: Kernel,
    /// `grid.wgsl`: zero the counts.
    pub grid_clear: Kernel,
    /// `forces.wgsl`: each body's bounding box.
    pub body_bounds: Kernel,
    /// `broad.wgsl`: which bodies are near another (contact broad phase).
    pub near_bodies: Kernel,
    /// `forces.wgsl`: zero the totals.
    pub force_clear: Kernel,
    /// `grid.wgsl`: cell counts.
    pub grid_count: Kernel,
    /// `grid.wgsl`: block scan.
    pub scan_block: Kernel,
    /// `grid.wgsl`: block offsets.
    pub scan_add: Kernel,
    /// `grid.wgsl`: scatter.
    pub grid_scatter: Kernel,
    /// `knn.wgsl`: K nearest of all particles, one pipeline per variant (cold: the first
    /// search; warm: later ones, starting from the previous lists) and list size
    /// ([`knn::SLOT_COUNTS`]; pick with `[warm as usize][Kernels::knn_slots(k)]`).
    pub knn_all: [[Kernel; 2]; 2],
    /// `knn.wgsl`: contact candidates, per variant and list size like `knn_all`.
    pub knn_contacts: [[Kernel; 2]; 2],
    /// `cluster.wgsl`: Jacobi pass A, a thread per cluster.
    pub clusters: Kernel,
    /// `cluster.wgsl`: Jacobi pass A, 8 threads per cluster (small ranges).
    pub clusters_lanes: Kernel,
    /// `gather.wgsl`: Jacobi pass B.
    pub gather: Kernel,
    /// `gather.wgsl`: Jacobi pass C.
    pub contact: Kernel,
    /// `body.wgsl`: passes A and B of small shape-matching bodies, a workgroup each;
    /// `None` where the adapter's workgroups are too small for it.
    pub body: Option<BodyKernels>,
    /// `hierarchy.wgsl`: positions at the start of the coarse pass.
    pub level_snapshot: Kernel,
    /// `hierarchy.wgsl`: level-0 positions into a coarse level.
    pub level_in: Kernel,
    /// `hierarchy.wgsl`: a coarse level's positions back to level 0.
    pub level_out: Kernel,
    /// `hierarchy.wgsl`: prolongation to the finer level.
    pub prolong: Kernel,
    /// `hierarchy.wgsl`: multipliers handed to the finer level.
    pub transfer: Kernel,
    /// `forces.wgsl`: partial sums.
    pub force_partial: Kernel,
    /// `forces.wgsl`: totals.
    pub force_total: Kernel,
    /// `skin.wgsl`: deformation gradients.
    pub deform: Kernel,
    /// `skin.wgsl`: skinning.
    pub skin: Kernel,
    /// `skin.wgsl`: normals.
    pub normals: Kernel,
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

    /// Every kernel, in [`Kernel::id`] order.
    pub fn all(&self) -> Vec<&Kernel> {
        let mut v = vec![
            &self.predict,
            &self.finish,
            &self.finish_predict,
            &self.grid_clear,
            &self.body_bounds,
            &self.near_bodies,
            &self.force_clear,
            &self.grid_count,
            &self.scan_block,
            &self.scan_add,
            &self.grid_scatter,
        ];
        v.extend(self.knn_all.iter().flatten());
        v.extend(self.knn_contacts.iter().flatten());
        v.extend([
            &self.clusters,
            &self.clusters_lanes,
            &self.gather,
            &self.contact,
            &self.level_snapshot,
            &self.level_in,
            &self.level_out,
            &self.prolong,
            &self.transfer,
            &self.force_partial,
            &self.force_total,
            &self.deform,
            &self.skin,
            &self.normals,
        ]);
        if let Some(b) = &self.body {
            v.extend([&b.substep, &b.iteration]);
        }
        v.sort_by_key(|k| k.id);
        v
    }

    /// Compiles every kernel for `device`, each with the layouts of only the bindings it
    /// uses. Fails with [`TissueError::GpuUnsupported`] naming the limit where the
    /// adapter cannot bind the storage buffers a kernel needs, or offers less workgroup
    /// memory or fewer invocations per workgroup than it uses (the workgroup-per-body
    /// kernels are left out instead, where they do not fit).
    pub fn new(device: &RenderDevice) -> Result<Self, TissueError> {
        let mut b = Builder {
            device,
            next: 0,
            limits: device.limits(),
        };
        let integrate_m = b.module("integrate", integrate::source())?;
        let grid_m = b.module("grid", grid::source())?;
        let mut knn_m = Vec::new();
        for warm in [false, true] {
            let mut sizes = Vec::new();
            for slots in knn::SLOT_COUNTS {
                sizes.push(b.module("knn", knn::source(slots, warm))?);
            }
            knn_m.push(sizes);
        }
        let cluster_m = b.module("cluster", cluster::source())?;
        let gather_m = b.module("gather", gather::source())?;
        let hier_m = b.module("hierarchy", hierarchy::source())?;
        let forces_m = b.module("forces", forces::source())?;
        let broad_m = b.module("broad phase", broad::source())?;
        let skin_m = b.module("skin", skin::source())?;
        let mut knn_kernels = |entry: &'static str| -> Result<[[Kernel; 2]; 2], TissueError> {
            let mut out = Vec::new();
            for variant in &knn_m {
                let mut two = Vec::new();
                for m in variant {
                    two.push(b.kernel(m, entry)?);
                }
                out.push(<[Kernel; 2]>::try_from(two).map_err(|_| shader_error("knn"))?);
            }
            <[[Kernel; 2]; 2]>::try_from(out).map_err(|_| shader_error("knn"))
        };
        let knn_all = knn_kernels("knn_all")?;
        let knn_contacts = knn_kernels("knn_contacts")?;
        let kernels = Self {
            predict: b.kernel(&integrate_m, "predict")?,
            finish: b.kernel(&integrate_m, "finish")?,
            finish_predict: b.kernel(&integrate_m, "finish_predict")?,
            grid_clear: b.kernel(&grid_m, "grid_clear")?,
            force_clear: b.kernel(&forces_m, "force_clear")?,
            body_bounds: b.kernel(&forces_m, "body_bounds")?,
            near_bodies: b.kernel(&broad_m, "near_bodies")?,
            grid_count: b.kernel(&grid_m, "grid_count")?,
            scan_block: b.kernel(&grid_m, "scan_block")?,
            scan_add: b.kernel(&grid_m, "scan_add")?,
            grid_scatter: b.kernel(&grid_m, "grid_scatter")?,
            knn_all,
            knn_contacts,
            clusters: b.kernel(&cluster_m, "solve_clusters")?,
            clusters_lanes: b.kernel(&cluster_m, "solve_clusters_lanes")?,
            gather: b.kernel(&gather_m, "gather")?,
            contact: b.kernel(&gather_m, "contact")?,
            body: None,
            level_snapshot: b.kernel(&hier_m, "level_snapshot")?,
            level_in: b.kernel(&hier_m, "level_in")?,
            level_out: b.kernel(&hier_m, "level_out")?,
            prolong: b.kernel(&hier_m, "prolong")?,
            transfer: b.kernel(&hier_m, "transfer")?,
            force_partial: b.kernel(&forces_m, "force_partial")?,
            force_total: b.kernel(&forces_m, "force_total")?,
            deform: b.kernel(&skin_m, "deform")?,
            skin: b.kernel(&skin_m, "skin")?,
            normals: b.kernel(&skin_m, "normals")?,
        };
        // The workgroup-per-body kernels: only where the adapter takes their workgroups
        // and their storage buffers.
        let source = body::source();
        let analysis = Analysis::new(&source).map_err(|m| shader_error_with("body", m))?;
        let mut fits = true;
        for entry in ["body_substep", "body_iteration"] {
            match b.check(&analysis, "body", entry) {
                Ok(_) => {}
                Err(TissueError::GpuUnsupported { .. }) => fits = false,
                Err(e) => return Err(e),
            }
        }
        let body = if fits {
            let m = b.module_from("body", source, analysis);
            Some(BodyKernels {
                substep: b.kernel(&m, "body_substep")?,
                iteration: b.kernel(&m, "body_iteration")?,
            })
        } else {
            None
        };
        Ok(Self { body, ..kernels })
    }
}

fn shader_error(module: &'static str) -> TissueError {
    shader_error_with(module, "unexpected kernel count".into())
}

fn shader_error_with(module: &'static str, message: String) -> TissueError {
    TissueError::GpuShader { module, message }
}

/// A compiled module with its analysis.
struct Module {
    name: &'static str,
    shader: ShaderModule,
    analysis: Analysis,
}

/// Makes kernels with consecutive ids.
struct Builder<'a> {
    device: &'a RenderDevice,
    next: usize,
    /// The adapter's limits.
    limits: bevy::render::settings::WgpuLimits,
}

impl Builder<'_> {
    fn module(&self, name: &'static str, source: String) -> Result<Module, TissueError> {
        let analysis = Analysis::new(&source).map_err(|m| shader_error_with(name, m))?;
        Ok(self.module_from(name, source, analysis))
    }

    fn module_from(&self, name: &'static str, source: String, analysis: Analysis) -> Module {
        let shader = self
            .device
            .create_and_validate_shader_module(ShaderModuleDescriptor {
                label: Some(name),
                source: ShaderSource::Wgsl(Cow::Owned(source)),
            });
        Module {
            name,
            shader,
            analysis,
        }
    }

    /// The bindings `entry` of `analysis` (module `name`) uses, once its storage
    /// buffers, workgroup memory and invocations are checked against the adapter's
    /// limits ([`TissueError::GpuUnsupported`] names the one it lacks).
    fn check(
        &self,
        analysis: &Analysis,
        name: &'static str,
        entry: &str,
    ) -> Result<Vec<usize>, TissueError> {
        let err = |e| shader_error_with(name, e);
        let uses = analysis.uses(entry).map_err(err)?;
        let l = &self.limits;
        let checks = [
            (
                "storage buffers per shader stage",
                bindings::storage_count(&uses),
                l.max_storage_buffers_per_shader_stage,
            ),
            (
                "workgroup memory (bytes)",
                analysis.workgroup_bytes(entry).map_err(err)?,
                l.max_compute_workgroup_storage_size,
            ),
            (
                "invocations per workgroup",
                analysis.invocations(entry).map_err(err)?,
                l.max_compute_invocations_per_workgroup
                    .min(l.max_compute_workgroup_size_x),
            ),
        ];
        for (what, needed, limit) in checks {
            if needed > limit {
                return Err(TissueError::GpuUnsupported {
                    what,
                    needed: needed as u64,
                    limit: limit as u64,
                });
            }
        }
        Ok(uses)
    }

    /// The kernel of `entry` in `m`, with a layout per group up to the last it uses.
    fn kernel(&mut self, m: &Module, entry: &'static str) -> Result<Kernel, TissueError> {
        let uses = self.check(&m.analysis, m.name, entry)?;
        let last = uses
            .iter()
            .map(|&i| bindings::location(i).0)
            .max()
            .map_or(0, |g| g as usize + 1);
        let mut groups = Vec::with_capacity(last);
        for g in 0..last as u32 {
            let mine: Vec<usize> = uses
                .iter()
                .copied()
                .filter(|&i| bindings::location(i).0 == g)
                .collect();
            let entries: Vec<_> = mine.iter().map(|&i| bindings::layout_entry(i)).collect();
            let layout = self.device.create_bind_group_layout(entry, &entries);
            groups.push((layout, mine));
        }
        let refs: Vec<Option<&wgpu::BindGroupLayout>> =
            groups.iter().map(|(l, _)| Some(&**l)).collect();
        let layout = self
            .device
            .create_pipeline_layout(&PipelineLayoutDescriptor {
                label: Some(entry),
                bind_group_layouts: &refs,
                immediate_size: 0,
            });
        let pipeline = self
            .device
            .create_compute_pipeline(&RawComputePipelineDescriptor {
                label: Some(entry),
                layout: Some(&layout),
                module: &m.shader,
                entry_point: Some(entry),
                compilation_options: PipelineCompilationOptions::default(),
                cache: None,
            });
        let id = self.next;
        self.next += 1;
        Ok(Kernel {
            name: entry,
            id,
            pipeline,
            groups,
        })
    }
}

/// The binding table's entries by name, for messages and tests.
pub fn binding_names(uses: &[usize]) -> Vec<&'static str> {
    uses.iter().map(|&i| TABLE[i].name).collect()
}

#[cfg(test)]
mod tests {
    use super::bindings::{Analysis, storage_count};
    use super::*;

    /// Every module with its entry points, as `Kernels::new` makes them.
    fn modules() -> Vec<(String, String, &'static [&'static str])> {
        let mut v = vec![
            (
                "integrate".into(),
                integrate::source(),
                integrate::ENTRY_POINTS,
            ),
            ("grid".into(), grid::source(), grid::ENTRY_POINTS),
            ("cluster".into(), cluster::source(), cluster::ENTRY_POINTS),
            ("gather".into(), gather::source(), gather::ENTRY_POINTS),
            ("body".into(), body::source(), body::ENTRY_POINTS),
            (
                "hierarchy".into(),
                hierarchy::source(),
                hierarchy::ENTRY_POINTS,
            ),
            ("forces".into(), forces::source(), forces::ENTRY_POINTS),
            ("broad".into(), broad::source(), broad::ENTRY_POINTS),
            ("skin".into(), skin::source(), skin::ENTRY_POINTS),
        ];
        for warm in [false, true] {
            for slots in knn::SLOT_COUNTS {
                v.push((
                    format!("knn {slots} {warm}"),
                    knn::source(slots, warm),
                    knn::ENTRY_POINTS,
                ));
            }
        }
        v
    }

    /// Every pipeline but the workgroup-per-body ones fits WebGPU's guaranteed limits:
    /// at most 8 storage buffers per stage, 4 bind groups, 16 KiB of workgroup memory
    /// and 256 invocations per workgroup (naga's analysis of each entry point, as the
    /// layouts are made). The body kernels need more and are made only where the
    /// adapter allows.
    #[test]
    fn every_pipeline_fits_webgpu_limits() {
        let mut worst = 0;
        for (name, source, entries) in modules() {
            let a = Analysis::new(&source).unwrap_or_else(|e| panic!("{name}: {e}"));
            for entry in entries {
                let uses = a.uses(entry).unwrap();
                let storage = storage_count(&uses);
                let groups = uses
                    .iter()
                    .map(|&i| bindings::location(i).0 + 1)
                    .max()
                    .unwrap_or(0);
                let bytes = a.workgroup_bytes(entry).unwrap();
                let threads = a.invocations(entry).unwrap();
                if name == "body" {
                    assert!(bytes > 16 * 1024 || threads > 256 || storage > 8);
                    continue;
                }
                worst = worst.max(storage);
                assert!(
                    storage <= WEBGPU_STORAGE_BUFFERS,
                    "{name}/{entry}: {storage} storage buffers ({:?})",
                    binding_names(&uses)
                );
                assert!(groups <= 4, "{name}/{entry}: {groups} groups");
                assert!(bytes <= 16 * 1024, "{name}/{entry}: {bytes} bytes");
                assert!(threads <= 256, "{name}/{entry}: {threads} invocations");
            }
        }
        assert_eq!(worst, WEBGPU_STORAGE_BUFFERS, "the busiest kernel");
    }

    /// The body kernels' requirement, which `Kernels::new` checks against the adapter.
    #[test]
    fn the_body_kernels_need_more_than_webgpu_guarantees() {
        let a = Analysis::new(&body::source()).unwrap();
        assert_eq!(
            a.workgroup_bytes("body_substep").unwrap(),
            body::WORKGROUP_BYTES
        );
        const { assert!(body::WORKGROUP_BYTES <= 32 * 1024) };
        assert_eq!(a.invocations("body_iteration").unwrap(), body::THREADS);
    }
}
