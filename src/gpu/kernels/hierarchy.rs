//! The coarse levels of hierarchical PBD: snapshot, level in/out, prolongation and the
//! multiplier hand-over
//! (the levels' constraints run through the cluster and gather kernels over each level's
//! particle range).
//!
//! Source: `hierarchy.wgsl` (with `common.wgsl` and `bindings.wgsl` prepended).

/// WGSL source of this kernel's module (see [`super::bindings::compose`]).
pub fn source() -> String {
    super::bindings::compose(&[include_str!("hierarchy.wgsl")])
}

/// Entry points of the module.
pub const ENTRY_POINTS: &[&str] = &[
    "level_snapshot",
    "level_in",
    "level_out",
    "prolong",
    "transfer",
];
