//! Blocking reads of GPU buffers: tests and benchmarks, and the main world's lattice
//! bodies, whose state the main thread reads back after each frame's steps (with a
//! staging buffer kept between reads, [`Staging`]). The render graph's bodies read back
//! asynchronously.

use bevy::render::render_resource::{Buffer, BufferDescriptor, BufferUsages, MapMode};
use bevy::render::renderer::{RenderDevice, RenderQueue};
use glam::Vec3;
use std::sync::Mutex;

/// A mappable buffer kept between blocking reads ([`read_buffers_with`]), grown when a
/// read needs more: a read every frame does not allocate and map a new one.
#[derive(Default)]
pub struct Staging(Mutex<Option<Buffer>>);

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
    read_buffers_with(device, queue, &Staging::default(), ranges, |parts| {
        parts.iter().map(|p| p.to_vec()).collect()
    })
}

/// Blocking read of several `(buffer, byte offset, bytes)` ranges (offsets and sizes
/// multiples of 4) with one copy submission and one wait, through `staging` (made or
/// grown here when it is smaller than the ranges together): `read` gets the ranges'
/// bytes in the mapped buffer itself, one slice per range (each as aligned as its
/// offset in the staging buffer: the first at 8 bytes or more), and its result is
/// returned.
pub fn read_buffers_with<R>(
    device: &RenderDevice,
    queue: &RenderQueue,
    staging: &Staging,
    ranges: &[(&Buffer, u64, u64)],
    read: impl FnOnce(&[&[u8]]) -> R,
) -> R {
    let total: u64 = ranges.iter().map(|r| r.2).sum();
    let mut kept = staging.0.lock().unwrap_or_else(|e| e.into_inner());
    if kept.as_ref().is_none_or(|b| b.size() < total.max(4)) {
        // A quarter more than asked: a world that grows a little is not remade each time.
        *kept = Some(device.create_buffer(&BufferDescriptor {
            label: Some("tissue readback"),
            size: (total.max(4) + total / 4).next_multiple_of(4),
            usage: BufferUsages::MAP_READ | BufferUsages::COPY_DST,
            mapped_at_creation: false,
        }));
    }
    let Some(staging) = kept.as_ref() else {
        return read(&[]);
    };
    let mut enc = device.create_command_encoder(&Default::default());
    let mut at = 0;
    for &(buffer, offset, size) in ranges {
        if size > 0 {
            enc.copy_buffer_to_buffer(buffer, offset, staging, at, size);
        }
        at += size;
    }
    queue.submit([enc.finish()]);
    let slice = staging.slice(..total.max(4));
    slice.map_async(MapMode::Read, |_| {});
    let _ = device.poll(bevy::render::render_resource::PollType::wait_indefinitely());
    let out = {
        let data = slice.get_mapped_range();
        let mut at = 0usize;
        let parts: Vec<&[u8]> = ranges
            .iter()
            .map(|r| {
                let part = &data[at..at + r.2 as usize];
                at += r.2 as usize;
                part
            })
            .collect();
        read(&parts)
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
