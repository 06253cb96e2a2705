//! Predict and finish: the explicit parts of a substep.
//!
//! Source: `integrate.wgsl` (with `common.wgsl`, `bindings.wgsl` prepended).

/// WGSL source of this kernel's module (see [`super::bindings::compose`]).
pub fn source() -> String {
    super::bindings::compose(&[include_str!("integrate.wgsl")])
}

/// Entry points of the module.
pub const ENTRY_POINTS: &[&str] = &["predict", "finish", "finish_predict"];
