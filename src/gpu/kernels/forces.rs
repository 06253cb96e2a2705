//! Collider forces: a deterministic two-stage reduction of the collider corrections.
//!
//! Source: `forces.wgsl` (with `common.wgsl`, `bindings.wgsl` prepended).

/// WGSL source of this kernel's module (see [`super::bindings::compose`]).
pub fn source() -> String {
    super::bindings::compose(&[include_str!("forces.wgsl")])
}

/// Entry points of the module.
pub const ENTRY_POINTS: &[&str] = &["body_bounds", "force_clear", "force_partial", "force_total"];
