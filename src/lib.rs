//! bevy_tissue: GPU-simulated soft tissue for Bevy — cluster-based position-based
//! dynamics (Li & Kang 2014) run as render-graph compute work and drawn straight from
//! the simulation's buffers.
//!
//! * [`core`] — the simulation core (no Bevy beyond glam): model building, constraint
//!   math, the CPU reference solver;
//! * [`gpu`] — buffers, kernels and the batched GPU world.
pub mod core;
pub mod gpu;
