//! A small coarse level of the hierarchy solved in one workgroup: all its Jacobi
//! iterations (cluster pass and gather) in one dispatch, separated by workgroup barriers.
//!
//! Source: `level.wgsl` (with `common.wgsl`, `bindings.wgsl`, `range.wgsl`,
//! `moments.wgsl`, `cluster.wgsl` and `gather.wgsl` prepended, whose functions it calls).

/// WGSL template of this kernel's module (before [`source`] sets the workgroup size).
pub const TEMPLATE: &str = concat!(
    include_str!("common.wgsl"),
    include_str!("bindings.wgsl"),
    include_str!("range.wgsl"),
    include_str!("moments.wgsl"),
    include_str!("cluster.wgsl"),
    include_str!("gather.wgsl"),
    include_str!("level.wgsl")
);

/// Entry points of the module (besides those of the cluster and gather kernels).
pub const ENTRY_POINTS: &[&str] = &["solve_level"];

/// The module's WGSL with `workgroup` threads in the one workgroup (the device's
/// `max_compute_invocations_per_workgroup`, at most 1,024).
pub fn source(workgroup: u32) -> String {
    TEMPLATE.replace("LEVEL_WG_VALUE", &workgroup.to_string())
}
