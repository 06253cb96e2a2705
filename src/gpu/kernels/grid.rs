//! Uniform (hashed) grid by counting sort: counts, multi-level prefix sum, scatter.
//!
//! Source: `grid.wgsl` (with `common.wgsl`, `bindings.wgsl` prepended).

/// WGSL source of this kernel's module (see [`super::bindings::compose`]).
pub fn source() -> String {
    super::bindings::compose(&[include_str!("grid.wgsl")])
}

/// Entry points of the module.
pub const ENTRY_POINTS: &[&str] = &[
    "grid_clear",
    "grid_count",
    "scan_block",
    "scan_add",
    "grid_scatter",
];
