//! Growing a [`GpuLattice`] past its room: a world made again with more room (on any
//! thread, from the rest state) takes the moving state of the bodies it shares with the
//! world it replaces by GPU copies ([`GpuLattice::carry_state`]), so the frame that
//! swaps them uploads nothing from the CPU.

use super::GpuLattice;
use crate::core::TissueError;
use bevy::render::renderer::{RenderDevice, RenderQueue};
use std::ops::Range;

/// Regions of the `pos` buffer holding positions and velocities (`R_X`, `R_V` in
/// `lattice.wgsl`).
const R_X: u64 = 0;
const R_V: u64 = 3;
/// Region of the per-node collider state that holds the grasps (`C_GRAB` there).
const C_GRAB: u64 = 2;

/// Bytes of one vec4 record.
const VEC4: u64 = 16;

/// A run of bodies whose state moves from one world to another: the same particles and
/// level-0 elements, in the same order, at other places.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StateRun {
    /// The particles in the world the state comes from.
    pub particles: Range<u32>,
    /// Where the first of them is in the world that takes the state.
    pub to_particle: u32,
    /// The level-0 elements in the world the state comes from.
    pub elements: Range<u32>,
    /// Where the first of them is in the world that takes the state.
    pub to_element: u32,
}

impl StateRun {
    /// `runs` in order, each joined with the one before where both continue it in both
    /// worlds (bodies kept in order make one run).
    pub fn joined(runs: impl IntoIterator<Item = StateRun>) -> Vec<StateRun> {
        let mut out: Vec<StateRun> = Vec::new();
        for r in runs {
            if let Some(last) = out.last_mut() {
                let p = last.particles.len() as u32;
                let e = last.elements.len() as u32;
                if last.particles.end == r.particles.start
                    && last.elements.end == r.elements.start
                    && last.to_particle + p == r.to_particle
                    && last.to_element + e == r.to_element
                {
                    last.particles.end = r.particles.end;
                    last.elements.end = r.elements.end;
                    continue;
                }
            }
            out.push(r);
        }
        out
    }
}

impl GpuLattice {
    /// Copies the positions, velocities, level-0 element rotations and grasps of the
    /// particles and elements `runs` name from `from` into this world, on the GPU, in
    /// one submission; everything else here is left as it was made (a world made from
    /// the rest state holds the rest state of its other bodies). What `from` was
    /// stepping with is not carried: the colliders touched in its last substep are
    /// forgotten, as [`GpuLattice::upload`] forgets them. An error, and nothing
    /// copied, where a run reaches past either world's particles or elements.
    pub fn carry_state(
        &mut self,
        device: &RenderDevice,
        queue: &RenderQueue,
        from: &GpuLattice,
        runs: &[StateRun],
    ) -> Result<(), TissueError> {
        let (np_from, np_to) = (from.particle_count() as u64, self.particle_count() as u64);
        let (ne_from, ne_to) = (
            from.layout.elems[0].used as u64,
            self.layout.elems[0].used as u64,
        );
        for r in runs {
            let (p, e) = (r.particles.len() as u64, r.elements.len() as u64);
            let fits = r.particles.start <= r.particles.end
                && r.elements.start <= r.elements.end
                && r.particles.end as u64 <= np_from
                && r.to_particle as u64 + p <= np_to
                && r.elements.end as u64 <= ne_from
                && r.to_element as u64 + e <= ne_to;
            if !fits {
                return Err(TissueError::InvalidParameter {
                    name: "carried state",
                    value: format!(
                        "particles {:?} to {} of {np_from} → {np_to}, elements {:?} to {} of \
                         {ne_from} → {ne_to}",
                        r.particles, r.to_particle, r.elements, r.to_element
                    ),
                    expected: "runs within both worlds' particles and level-0 elements",
                });
            }
        }
        let (slots_from, slots_to) = (
            from.layout.n_slots() as u64 * VEC4,
            self.layout.n_slots() as u64 * VEC4,
        );
        let mut enc = device.create_command_encoder(&Default::default());
        for r in runs.iter().filter(|r| !r.particles.is_empty()) {
            let (at_from, at_to) = (r.particles.start as u64 * VEC4, r.to_particle as u64 * VEC4);
            let bytes = r.particles.len() as u64 * VEC4;
            for region in [R_X, R_V] {
                enc.copy_buffer_to_buffer(
                    &from.pos,
                    region * slots_from + at_from,
                    &self.pos,
                    region * slots_to + at_to,
                    bytes,
                );
            }
            enc.copy_buffer_to_buffer(
                &from.ccol,
                C_GRAB * slots_from + at_from,
                &self.ccol,
                C_GRAB * slots_to + at_to,
                bytes,
            );
        }
        for r in runs.iter().filter(|r| !r.elements.is_empty()) {
            enc.copy_buffer_to_buffer(
                &from.rot,
                r.elements.start as u64 * VEC4,
                &self.rot,
                r.to_element as u64 * VEC4,
                r.elements.len() as u64 * VEC4,
            );
        }
        queue.submit([enc.finish()]);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(p: Range<u32>, tp: u32, e: Range<u32>, te: u32) -> StateRun {
        StateRun {
            particles: p,
            to_particle: tp,
            elements: e,
            to_element: te,
        }
    }

    #[test]
    fn runs_that_continue_each_other_join() {
        let joined = StateRun::joined([
            run(0..10, 0, 0..4, 0),
            run(10..30, 10, 4..9, 4),
            // A gap in the world taking the state (a body between was reset).
            run(30..40, 50, 9..12, 20),
            run(40..45, 60, 12..13, 23),
        ]);
        assert_eq!(
            joined,
            vec![run(0..30, 0, 0..9, 0), run(30..45, 50, 9..13, 20)]
        );
        assert!(StateRun::joined([]).is_empty());
    }
}
