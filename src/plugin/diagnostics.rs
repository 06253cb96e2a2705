//! Where the main world's share of a frame goes, as Bevy diagnostics.
//!
//! Bodies stepped from the main world (lattice bodies on the GPU, and every body under
//! [`TissueBackend::Cpu`](super::components::TissueBackend)) cost the main thread their
//! steps, their particle-contact search and the skinning of their meshes. The plugin
//! measures each of these (wall time, ms) on the frames that do it and records it under
//! the paths of [`TissueDiagnostics`], so that Bevy's `LogDiagnosticsPlugin`, the
//! panel of [`TissueUiPlugin`](crate::ui::TissueUiPlugin) or a user's own system can
//! show them:
//!
//! ```no_run
//! use bevy::diagnostic::{DiagnosticsStore, LogDiagnosticsPlugin};
//! use bevy::prelude::*;
//! use bevy_tissue::prelude::*;
//!
//! fn show(store: Res<DiagnosticsStore>) {
//!     if let Some(ms) = store.get(&TissueDiagnostics::CONTACTS).and_then(|d| d.smoothed()) {
//!         info!("contact search: {ms:.2} ms");
//!     }
//! }
//!
//! App::new()
//!     .add_plugins((DefaultPlugins, TissuePlugin::default(), LogDiagnosticsPlugin::default()))
//!     .add_systems(Update, show)
//!     .run();
//! ```
//!
//! The GPU time of the render graph's work is Bevy's render diagnostics'
//! (`render/tissue/...`, with `RenderDiagnosticsPlugin`), not these.

use bevy::diagnostic::{Diagnostic, DiagnosticPath, RegisterDiagnostic};
use bevy::prelude::*;

/// Paths of the main world's timing diagnostics (wall time on the main thread, ms),
/// registered by [`TissuePlugin`](super::TissuePlugin).
///
/// Each is measured only on the frames that do that work: a frame that takes no step
/// adds no measurement, so the smoothed values are per working frame, not per frame.
#[derive(Debug, Clone, Copy)]
pub struct TissueDiagnostics;

impl TissueDiagnostics {
    /// The frame's steps of the bodies stepped from the main world, ms: on the GPU,
    /// telling it the colliders, recording and submitting the steps, waiting for them
    /// and reading the particles back; on the CPU, the solver's steps (with their own
    /// contact searches). Measured on frames that step.
    pub const STEP: DiagnosticPath = DiagnosticPath::const_new("tissue/main/step");
    /// The particle-contact search for lattice bodies stepped on the GPU, ms: the
    /// staleness test and, when lists are due or may go stale, the search on the CPU
    /// and their upload; `0` on frames whose lists were kept. Measured on frames that
    /// step on the GPU with particle contacts on.
    pub const CONTACTS: DiagnosticPath = DiagnosticPath::const_new("tissue/main/contacts");
    /// Skinning the render surfaces of the bodies stepped from the main world and
    /// writing their meshes and culling boxes, ms, with the test of which bodies moved
    /// enough to be drawn again. Measured on frames that step, rebuild or move a body.
    pub const SKIN: DiagnosticPath = DiagnosticPath::const_new("tissue/main/skin");

    /// Every path, in the order above.
    pub const ALL: [DiagnosticPath; 3] = [Self::STEP, Self::CONTACTS, Self::SKIN];

    /// Registers the diagnostics (suffix `ms`) with `app`'s `DiagnosticsStore`, which
    /// this makes if the app has none.
    pub(crate) fn register(app: &mut App) {
        for path in Self::ALL {
            app.register_diagnostic(Diagnostic::new(path).with_suffix("ms"));
        }
    }
}

/// Milliseconds since `start`.
pub(crate) fn ms_since(start: bevy::platform::time::Instant) -> f64 {
    start.elapsed().as_secs_f64() * 1e3
}
