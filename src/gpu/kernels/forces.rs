//! Collider forces: a deterministic two-stage reduction of the collider corrections.
//!
//! Source: `forces.wgsl` (with `common.wgsl`, `bindings.wgsl` prepended).

/// WGSL source of this kernel's module.
pub const SOURCE: &str = concat!(
    include_str!("common.wgsl"),
    include_str!("bindings.wgsl"),
    include_str!("forces.wgsl")
);

/// Entry points of the module.
pub const ENTRY_POINTS: &[&str] = &["body_bounds", "force_clear", "force_partial", "force_total"];
