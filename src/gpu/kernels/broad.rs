//! Broad phase of the particle contacts: which bodies are near another (their bounding
//! boxes within the contact reach), so that the contact search and pass skip the others.
//!
//! Source: `broad.wgsl` (with `common.wgsl`, `bindings.wgsl` prepended).
//! CPU twin: [`crate::core::knn::near_bodies`].

/// WGSL source of this kernel's module (see [`super::bindings::compose`]).
pub fn source() -> String {
    super::bindings::compose(&[include_str!("broad.wgsl")])
}

/// Entry points of the module.
pub const ENTRY_POINTS: &[&str] = &["near_bodies"];

/// Near bodies listed per body after the flags in the `bounds` buffer (`NEAR_SLOTS` in
/// `bindings.wgsl`; `knn_contacts` tests a particle against their boxes).
pub const NEAR_SLOTS: u32 = 32;

#[cfg(test)]
mod tests {
    #[test]
    fn the_body_limit_matches_the_cpu_twin() {
        let line = format!(
            "const BROAD_MAX_BODIES: u32 = {}u;",
            crate::core::knn::BROAD_MAX_BODIES
        );
        assert!(
            super::source().contains(&line),
            "broad.wgsl must declare `{line}`"
        );
    }

    #[test]
    fn the_near_list_length_matches_the_buffer_layout() {
        let line = format!("const NEAR_SLOTS: u32 = {}u;", super::NEAR_SLOTS);
        assert!(
            super::source().contains(&line),
            "bindings.wgsl must declare `{line}`"
        );
    }
}
