//! Jacobi passes B and C: gather of the cluster corrections per particle, then particle contacts, colliders and pins.
//!
//! Source: `gather.wgsl` (with `common.wgsl`, `bindings.wgsl` prepended).

/// WGSL source of this kernel's module (see [`super::bindings::compose`]).
pub fn source() -> String {
    super::bindings::compose(&[include_str!("gather.wgsl")])
}

/// Entry points of the module.
pub const ENTRY_POINTS: &[&str] = &["gather", "contact"];
