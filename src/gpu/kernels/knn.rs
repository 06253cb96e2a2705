//! Exact K nearest neighbours on the grid: all particles (`knn_all`) and contact candidates of other bodies (`knn_contacts`).
//!
//! Source: `knn.wgsl` (with `common.wgsl`, `bindings.wgsl` prepended), a template whose
//! candidate list [`source`] writes out as scalar registers (`ld{s}`, `lj{s}`) for a given slot count.

use std::fmt::Write as _;

/// WGSL template of this kernel's own file (before [`source`] fills in the list).
pub const TEMPLATE: &str = include_str!("knn.wgsl");

/// Entry points of the module.
pub const ENTRY_POINTS: &[&str] = &["knn_all", "knn_contacts"];

/// List sizes compiled: a world uses the smallest that holds its K (fewer registers).
pub const SLOT_COUNTS: [u32; 2] = [32, 64];

/// The module's WGSL for a candidate list of `slots` entries (K ≤ `slots`): the
/// template with the list's declaration, insertion and output written out slot by slot,
/// so that every access has a constant index and the list stays in registers. `warm`:
/// the variant for searches after the first, which starts from each particle's previous
/// list (see `knn.wgsl`).
pub fn source(slots: u32, warm: bool) -> String {
    let n = slots as usize;
    let mut decl = String::new();
    let mut insert = String::new();
    let mut out = String::new();
    for s in 0..n {
        // Slots before `pad` hold the sentinel (−1, 0); the others start empty (FAR).
        let _ = writeln!(
            decl,
            "    var ld{s} = select(FAR, -1.0, {s}u < pad);\n    var lj{s} = select(NONE, 0u, {s}u < pad);"
        );
        let _ = writeln!(
            insert,
            "                        let c{s} = before(d2, j, ld{s}, lj{s});"
        );
        let _ = writeln!(
            out,
            "    if (pad <= {s}u) {{ put(mode, base + {s}u, ld{s}, lj{s}); }}"
        );
    }
    // From the last slot down, so that slot s − 1 still holds its old value.
    for s in (1..n).rev() {
        let p = s - 1;
        let _ = writeln!(
            insert,
            "                        if (c{p}) {{ ld{s} = ld{p}; lj{s} = lj{p}; }} else if (c{s}) {{ ld{s} = d2; lj{s} = j; }}"
        );
    }
    let _ = writeln!(
        insert,
        "                        if (c0) {{ ld0 = d2; lj0 = j; }}"
    );
    let last = n - 1;
    let own = TEMPLATE
        .replace("WARM_VALUE", if warm { "true" } else { "false" })
        .replace("LIST_SLOTS_VALUE", &slots.to_string())
        .replace(
            "SPARE_EXTRA",
            &format!("{}u", crate::gpu::buffers::SPARE_EXTRA),
        )
        .replace("//LIST_DECL\n", &decl)
        .replace("//LIST_INSERT\n", &insert)
        .replace("//LIST_OUT\n", &out)
        .replace("LAST_D", &format!("ld{last}"))
        .replace("LAST_J", &format!("lj{last}"));
    super::bindings::compose(&[&own])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_placeholder_is_filled() {
        for (slots, warm) in [(32, false), (32, true), (64, false), (64, true)] {
            let s = source(slots, warm);
            for token in [
                "LIST_SLOTS_VALUE",
                "WARM_VALUE",
                "SPARE_EXTRA",
                "//LIST_",
                "LAST_D",
                "LAST_J",
            ] {
                assert!(
                    !s.contains(token),
                    "{token} left in the {slots}-slot source"
                );
            }
            assert!(s.contains(&format!("var ld{} ", slots - 1)));
            assert!(!s.contains(&format!("var ld{} ", slots)));
        }
    }
}
