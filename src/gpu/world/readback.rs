//! Blocking reads of GPU buffers (tests and benchmarks; the plugin reads back
//! asynchronously).

use bevy::render::render_resource::{Buffer, BufferDescriptor, BufferUsages, MapMode};
use bevy::render::renderer::{RenderDevice, RenderQueue};
use glam::Vec3;

/// Blocking read of `size` bytes at `offset` of `buffer` (tests and benchmarks; the
/// plugin reads back asynchronously).
pub fn read_buffer(
    device: &RenderDevice,
    queue: &RenderQueue,
    buffer: &Buffer,
    offset: u64,
    size: u64,
) -> Vec<u8> {
    read_buffers(device, queue, &[(buffer, offset, size)])
        .pop()
        .unwrap_or_default()
}

/// Blocking read of several `(buffer, byte offset, bytes)` ranges (offsets and sizes
/// multiples of 4) with one copy submission and one wait.
pub fn read_buffers(
    device: &RenderDevice,
    queue: &RenderQueue,
    ranges: &[(&Buffer, u64, u64)],
) -> Vec<Vec<u8>> {
    let total: u64 = ranges.iter().map(|r| r.2).sum();
    let staging = device.create_buffer(&BufferDescriptor {
        label: Some("tissue readback"),
        size: total.max(4),
        usage: BufferUsages::MAP_READ | BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut enc = device.create_command_encoder(&Default::default());
    let mut at = 0;
    for &(buffer, offset, size) in ranges {
        if size > 0 {
            enc.copy_buffer_to_buffer(buffer, offset, &staging, at, size);
        }
        at += size;
    }
    queue.submit([enc.finish()]);
    let slice = staging.slice(..);
    slice.map_async(MapMode::Read, |_| {});
    let _ = device.poll(bevy::render::render_resource::PollType::wait_indefinitely());
    let out = {
        let data = slice.get_mapped_range();
        let mut at = 0usize;
        ranges
            .iter()
            .map(|r| {
                let part = data[at..at + r.2 as usize].to_vec();
                at += r.2 as usize;
                part
            })
            .collect()
    };
    staging.unmap();
    out
}

/// Blocking read of a vec4 buffer's first `n` entries as `Vec3`s.
pub fn read_vec3(device: &RenderDevice, queue: &RenderQueue, buffer: &Buffer, n: u32) -> Vec<Vec3> {
    let bytes = read_buffer(device, queue, buffer, 0, n as u64 * 16);
    bytemuck::cast_slice::<u8, [f32; 4]>(&bytes)
        .iter()
        .map(|a| Vec3::new(a[0], a[1], a[2]))
        .collect()
}

/// Blocking read of a u32 buffer's first `n` entries.
pub fn read_u32(device: &RenderDevice, queue: &RenderQueue, buffer: &Buffer, n: u64) -> Vec<u32> {
    let bytes = read_buffer(device, queue, buffer, 0, n * 4);
    bytemuck::cast_slice(&bytes).to_vec()
}
