//! Jacobi iterations of every small shape-matching body, a workgroup per body, its
//! positions, rest records and corrections in workgroup memory (passes A and B in one
//! dispatch): all iterations of a substep at once for the bodies near no other
//! (`body_substep`), one per dispatch for those with contact candidates
//! (`body_iteration`, which starts with the previous iteration's contact pass for the
//! body's particles).
//!
//! Source: `body.wgsl` (with `common.wgsl`, `bindings.wgsl`, `moments.wgsl`
//! and `gather.wgsl` prepended: the moments, the rotation, the correction and the
//! boundary are theirs).

/// WGSL source of this kernel's module (see [`super::bindings::compose`]).
pub fn source() -> String {
    super::bindings::compose(&[
        include_str!("moments.wgsl"),
        include_str!("gather.wgsl"),
        include_str!("body.wgsl"),
    ])
}

/// Entry points of the module.
pub const ENTRY_POINTS: &[&str] = &["body_substep", "body_iteration"];

/// Largest body (particles) the kernel takes (`BODY_MAX` in `body.wgsl`): one less than
/// its threads, so that its four arrays and its one flag fit 32 KiB of workgroup memory.
pub const BODY_MAX: u32 = 511;

/// Workgroup memory the kernel needs (four `vec4` arrays of [`BODY_MAX`] and a `u32`
/// flag), bytes.
pub const WORKGROUP_BYTES: u32 = 4 * BODY_MAX * 16 + 4;

/// Threads per workgroup (`BODY_WG` in `body.wgsl`).
pub const THREADS: u32 = 512;
