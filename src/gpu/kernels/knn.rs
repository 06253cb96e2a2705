//! Exact K nearest neighbours on the grid: all particles (`knn_all`) and contact candidates of other bodies (`knn_contacts`).
//!
//! Source: `knn.wgsl` (with `common.wgsl`, `bindings.wgsl` prepended).

/// WGSL source of this kernel's module.
pub const SOURCE: &str = concat!(
    include_str!("common.wgsl"),
    include_str!("bindings.wgsl"),
    include_str!("knn.wgsl")
);

/// Entry points of the module.
pub const ENTRY_POINTS: &[&str] = &["knn_all", "knn_contacts"];
