//! Predict and finish: the explicit parts of a substep.
//!
//! Source: `integrate.wgsl` (with `common.wgsl`, `bindings.wgsl` prepended).

/// WGSL source of this kernel's module.
pub const SOURCE: &str = concat!(
    include_str!("common.wgsl"),
    include_str!("bindings.wgsl"),
    include_str!("integrate.wgsl")
);

/// Entry points of the module.
pub const ENTRY_POINTS: &[&str] = &["predict", "finish", "finish_predict"];
