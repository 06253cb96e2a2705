//! Jacobi pass A: every cluster's shape-matching or hyperelastic correction as an affine map.
//!
//! Source: `cluster.wgsl` (with `common.wgsl`, `bindings.wgsl`, `moments.wgsl` prepended).

/// WGSL source of this kernel's module (see [`super::bindings::compose`]).
pub fn source() -> String {
    super::bindings::compose(&[include_str!("moments.wgsl"), include_str!("cluster.wgsl")])
}

/// Entry points of the module.
pub const ENTRY_POINTS: &[&str] = &["solve_clusters", "solve_clusters_lanes"];
