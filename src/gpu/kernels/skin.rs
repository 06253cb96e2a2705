//! The draw path: deformation gradients, skinning into the mesh's vertex slab, normals.
//!
//! Source: `skin.wgsl` (with `common.wgsl`, `bindings.wgsl`, `moments.wgsl` prepended).

/// WGSL source of this kernel's module (see [`super::bindings::compose`]).
pub fn source() -> String {
    super::bindings::compose(&[include_str!("moments.wgsl"), include_str!("skin.wgsl")])
}

/// Entry points of the module.
pub const ENTRY_POINTS: &[&str] = &["deform", "skin", "normals"];
