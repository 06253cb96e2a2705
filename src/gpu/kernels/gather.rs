//! Jacobi passes B and C: gather of the cluster corrections per particle, then particle contacts, colliders and pins.
//!
//! Source: `gather.wgsl` (with `common.wgsl`, `bindings.wgsl`, `range.wgsl` prepended).

/// WGSL source of this kernel's module.
pub const SOURCE: &str = concat!(
    include_str!("common.wgsl"),
    include_str!("bindings.wgsl"),
    include_str!("range.wgsl"),
    include_str!("gather.wgsl")
);

/// Entry points of the module.
pub const ENTRY_POINTS: &[&str] = &["gather", "contact"];
