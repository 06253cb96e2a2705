//! bevy_tissue: GPU-simulated soft tissue for Bevy — cluster-based position-based
//! dynamics (Li & Kang 2014) run as render-graph compute work and drawn straight from
//! the simulation's buffers.
//!
//! * [`core`] — the simulation core (no Bevy beyond glam): model building, constraint
//!   math, the CPU reference solver;
//! * [`gpu`] — buffers, kernels and the batched GPU world;
//! * [`plugin`] — the Bevy plugin: components, build systems, render-graph systems;
//! * [`interact`] — grab and pull bodies with the mouse;
//! * `ui` (feature `egui`) — the live settings and timing panel.
#![warn(missing_docs)]

pub mod core;
pub mod gpu;
pub mod interact;
pub mod plugin;
#[cfg(feature = "egui")]
pub mod ui;

/// Everything a scene needs: `use bevy_tissue::prelude::*;`.
pub mod prelude {
    pub use crate::interact::{DragGrasper, TissueDragPlugin, TissuePointer};
    pub use crate::plugin::components::{
        ColliderForce, ColliderKind, ParticlePositions, PinShape, Pinned, ReadbackParticles,
        ResetSoftBody, SoftBody, SoftBodyError, SoftBodyReady, SoftBodyStatus, TissueBackend,
        TissueClock, TissueCollider, TissueDiscretisation, TissueHierarchy, TissueMaterial,
        TissueQuality, TissueResolution, TissueSettings,
    };
    pub use crate::plugin::diagnostics::TissueDiagnostics;
    pub use crate::plugin::sleep::{BodyMotion, Sleeping, TissueSleep};
    pub use crate::plugin::{TissuePlugin, TissueSet};
}
