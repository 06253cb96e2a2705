//! GPU time per pass from timestamp queries, for benchmarks run outside Bevy (inside
//! Bevy, the plugin reports the same passes through `RenderDiagnosticsPlugin`).

use super::world::PassRecorder;
use bevy::render::render_resource::{Buffer, BufferDescriptor, BufferUsages, CommandEncoder};
use bevy::render::renderer::{RenderDevice, RenderQueue};
use std::collections::BTreeMap;
use wgpu::{QuerySet, QuerySetDescriptor, QueryType};

/// Timestamp queries around every pass, summed per pass name.
pub struct GpuProfiler {
    set: QuerySet,
    resolve: Buffer,
    capacity: u32,
    names: Vec<&'static str>,
    period_ns: f32,
}

impl GpuProfiler {
    /// A profiler for up to `passes` passes per submission; `None` where the device has
    /// no timestamp queries.
    pub fn new(device: &RenderDevice, queue: &RenderQueue, passes: u32) -> Option<Self> {
        if !device
            .features()
            .contains(bevy::render::render_resource::WgpuFeatures::TIMESTAMP_QUERY)
        {
            return None;
        }
        let capacity = (passes * 2).min(4096);
        let set = device.wgpu_device().create_query_set(&QuerySetDescriptor {
            label: Some("tissue timestamps"),
            ty: QueryType::Timestamp,
            count: capacity,
        });
        let resolve = device.create_buffer(&BufferDescriptor {
            label: Some("tissue timestamps"),
            size: capacity as u64 * 8,
            usage: BufferUsages::QUERY_RESOLVE | BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        Some(Self {
            set,
            resolve,
            capacity,
            names: Vec::new(),
            period_ns: queue.get_timestamp_period(),
        })
    }

    /// Records an empty pass that writes one timestamp on the GPU timeline (the time
    /// between two marks covers everything the GPU did in between, gaps included).
    pub fn mark(&mut self, encoder: &mut CommandEncoder) {
        let i = self.names.len() as u32 * 2;
        if i + 2 > self.capacity {
            return;
        }
        self.names.push("mark");
        let _ = encoder.begin_compute_pass(&bevy::render::render_resource::ComputePassDescriptor {
            label: Some("tissue mark"),
            timestamp_writes: Some(wgpu::ComputePassTimestampWrites {
                query_set: &self.set,
                beginning_of_pass_write_index: Some(i),
                end_of_pass_write_index: Some(i + 1),
            }),
        });
    }

    /// Reads the marks back (blocking): the raw end-of-mark times in ms, in order.
    pub fn read_marks(&mut self, device: &RenderDevice, queue: &RenderQueue) -> Vec<f64> {
        let used = self.names.len() as u64 * 2;
        if used == 0 {
            return Vec::new();
        }
        let bytes = super::world::read_buffer(device, queue, &self.resolve, 0, used * 8);
        let ts: &[u64] = bytemuck::cast_slice(&bytes);
        let out = (0..self.names.len())
            .map(|i| ts[2 * i + 1] as f64 * self.period_ns as f64 * 1e-6)
            .collect();
        self.names.clear();
        out
    }

    /// Reserves `count` single timestamps for writes inside a pass (device feature
    /// `TIMESTAMP_QUERY_INSIDE_PASSES`, see [`GpuProfiler::inside_passes`]): the query set
    /// and the first index, `None` past the profiler's capacity. Read them with
    /// [`GpuProfiler::read_stamps`] after [`GpuProfiler::resolve`].
    pub fn reserve(&mut self, count: u32) -> Option<(QuerySet, u32)> {
        let first = self.names.len() as u32 * 2;
        let pairs = count.div_ceil(2);
        if first + pairs * 2 > self.capacity {
            return None;
        }
        self.names
            .extend(std::iter::repeat_n("stamps", pairs as usize));
        Some((self.set.clone(), first))
    }

    /// Whether `device` can write timestamps between a pass's dispatches.
    pub fn inside_passes(device: &RenderDevice) -> bool {
        device
            .features()
            .contains(bevy::render::render_resource::WgpuFeatures::TIMESTAMP_QUERY_INSIDE_PASSES)
    }

    /// Reads every timestamp reserved since the last read back (blocking), in ms on the
    /// GPU's clock (only differences mean anything), indexed as
    /// [`GpuProfiler::reserve`] gave them. Resets for the next submission.
    pub fn read_stamps(&mut self, device: &RenderDevice, queue: &RenderQueue) -> Vec<f64> {
        let used = self.names.len() as u64 * 2;
        self.names.clear();
        if used == 0 {
            return Vec::new();
        }
        let bytes = super::world::read_buffer(device, queue, &self.resolve, 0, used * 8);
        let ts: &[u64] = bytemuck::cast_slice(&bytes);
        ts.iter()
            .map(|&t| t as f64 * self.period_ns as f64 * 1e-6)
            .collect()
    }

    /// Records the resolve of this submission's queries (call after the passes).
    pub fn resolve(&self, encoder: &mut CommandEncoder) {
        let used = self.names.len() as u32 * 2;
        if used > 0 {
            encoder.resolve_query_set(&self.set, 0..used, &self.resolve, 0);
        }
    }

    /// Reads the resolved times back (blocking): milliseconds per pass name, summed over
    /// the passes of that name, and how many there were. Resets for the next submission.
    pub fn read(
        &mut self,
        device: &RenderDevice,
        queue: &RenderQueue,
    ) -> BTreeMap<&'static str, (f64, u32)> {
        let used = self.names.len() as u64 * 2;
        let mut out = BTreeMap::new();
        if used == 0 {
            return out;
        }
        let bytes = super::world::read_buffer(device, queue, &self.resolve, 0, used * 8);
        let ts: &[u64] = bytemuck::cast_slice(&bytes);
        for (i, name) in self.names.iter().enumerate() {
            let d = ts[2 * i + 1].saturating_sub(ts[2 * i]) as f64 * self.period_ns as f64 * 1e-6;
            let e = out.entry(*name).or_insert((0.0, 0));
            e.0 += d;
            e.1 += 1;
        }
        self.names.clear();
        out
    }
}

impl PassRecorder for GpuProfiler {
    fn timestamps(&mut self, name: &'static str) -> Option<(QuerySet, u32)> {
        let i = self.names.len() as u32 * 2;
        if i + 2 > self.capacity {
            return None;
        }
        self.names.push(name);
        Some((self.set.clone(), i))
    }
}
