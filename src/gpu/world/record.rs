//! Recording: a plan's dispatches ([`super::plan`]) replayed into a command encoder
//! with the world's bind groups.

use super::alloc::KernelBind;
use super::plan;
use crate::gpu::buffers::{GpuRange, GpuScanLevel};
use crate::gpu::kernels::{self, Kernels};
use bevy::render::render_resource::{
    BindGroup, CommandEncoder, ComputePass, ComputePassDescriptor,
};
use wgpu::{ComputePassTimestampWrites, QuerySet};

/// Hooks around every compute pass a world records: GPU timestamps for benchmarks, or
/// Bevy's render-diagnostic spans in the plugin.
pub trait PassRecorder {
    /// Timestamp writes for the pass named `name` (query set and the index of its
    /// beginning; the end is the next index), if this recorder takes them.
    fn timestamps(&mut self, _name: &'static str) -> Option<(QuerySet, u32)> {
        None
    }
    /// Called after the pass begins.
    fn begin(&mut self, _pass: &mut ComputePass<'_>, _name: &'static str) {}
    /// Called before the pass ends.
    fn end(&mut self, _pass: &mut ComputePass<'_>) {}
}

/// Records nothing around passes.
pub struct NoTiming;
impl PassRecorder for NoTiming {}

/// Dispatches recorded into one compute pass, or into a pass each when the recorder
/// times passes (timestamp writes are per pass). One pass per step spares the per-pass
/// cost of wgpu's resource tracking, which on an H100 was measured to exceed the kernels'
/// own time at 38k particles.
pub(super) struct Recording<'e, 'r, 'b> {
    encoder: &'e mut CommandEncoder,
    pass: Option<ComputePass<'static>>,
    rec: &'r mut dyn PassRecorder,
    /// The world's bind groups, by [`kernels::Kernel::id`].
    binds: &'b [KernelBind],
}

/// Group 3 (per dispatch) of a dispatch.
#[derive(Clone, Copy)]
pub(super) enum Bound<'a> {
    /// The kernel binds nothing per dispatch.
    None,
    /// The world's range or scan-level record at this byte offset.
    At(u32),
    /// A vertex slab's group (one of a [`SlabGroup`]) with the skin span at this offset.
    Slab(&'a BindGroup, u32),
}

impl<'e, 'r, 'b> Recording<'e, 'r, 'b> {
    pub(super) fn new(
        encoder: &'e mut CommandEncoder,
        rec: &'r mut dyn PassRecorder,
        binds: &'b [KernelBind],
    ) -> Self {
        Self {
            encoder,
            pass: None,
            rec,
            binds,
        }
    }

    pub(super) fn dispatch(
        &mut self,
        name: &'static str,
        kernel: &kernels::Kernel,
        window: Bound<'_>,
        workgroups: (u32, u32),
    ) {
        let ts = self.rec.timestamps(name);
        let mut own;
        let pass: &mut ComputePass<'static> = if ts.is_some() {
            let timestamp_writes = ts.as_ref().map(|(qs, i)| ComputePassTimestampWrites {
                query_set: qs,
                beginning_of_pass_write_index: Some(*i),
                end_of_pass_write_index: Some(*i + 1),
            });
            self.pass = None;
            own = self
                .encoder
                .begin_compute_pass(&ComputePassDescriptor {
                    label: Some(name),
                    timestamp_writes,
                })
                .forget_lifetime();
            &mut own
        } else {
            let enc = &mut *self.encoder;
            self.pass.get_or_insert_with(|| {
                enc.begin_compute_pass(&ComputePassDescriptor {
                    label: Some("tissue"),
                    timestamp_writes: None,
                })
                .forget_lifetime()
            })
        };
        self.rec.begin(pass, name);
        pass.set_pipeline(&kernel.pipeline);
        if let Some(bind) = self.binds.get(kernel.id) {
            for (g, group) in bind.fixed.iter().enumerate() {
                pass.set_bind_group(g as u32, group, &[]);
            }
            match window {
                Bound::None => {}
                Bound::At(offset) => {
                    if let Some(group) = &bind.window {
                        pass.set_bind_group(3, group, &[offset]);
                    }
                }
                Bound::Slab(group, offset) => pass.set_bind_group(3, group, &[offset]),
            }
        }
        pass.dispatch_workgroups(workgroups.0, workgroups.1, 1);
        self.rec.end(pass);
    }
}

/// Replays `plan` into `encoder` with the world's bind groups `binds` (one compute pass,
/// unless `rec` times passes). A dispatch of a kernel the adapter lacks is left out (the
/// plan has none where the world says so).
pub(super) fn replay(
    encoder: &mut CommandEncoder,
    rec: &mut dyn PassRecorder,
    binds: &[KernelBind],
    k: &Kernels,
    plan: &[plan::Dispatch],
) {
    let mut r = Recording::new(encoder, rec, binds);
    for d in plan {
        let Some(kernel) = d.op.kernel(k) else {
            continue;
        };
        let window = match d.window {
            plan::Window::None => Bound::None,
            plan::Window::Range(i) => Bound::At(i * size_of::<GpuRange>() as u32),
            plan::Window::Level(i) => Bound::At(i * size_of::<GpuScanLevel>() as u32),
        };
        r.dispatch(d.name, kernel, window, d.groups);
    }
}
