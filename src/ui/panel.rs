//! The panel's sections: the widgets, and the pure editing helpers behind them.
//!
//! Every editable section works on a copy of the component or resource and reports
//! whether a widget changed it ([`Edit`]); [`commit_edit`] decides what (if anything)
//! is written back, so that merely looking at the panel writes nothing.

use super::stats;
use crate::plugin::components::{
    ColliderForce, ResetSoftBody, SoftBody, SoftBodyStatus, TissueBackend, TissueClock,
    TissueDiscretisation, TissueHierarchy, TissueMaterial, TissueSettings,
};
use bevy::diagnostic::{DiagnosticPath, DiagnosticsStore, FrameTimeDiagnosticsPlugin};
use bevy::prelude::*;
use bevy_egui::egui;
use core::ops::RangeInclusive;

/// Gravity that the gravity switch turns on, m/s².
pub(crate) const EARTH_GRAVITY: Vec3 = Vec3::new(0.0, -9.81, 0.0);
/// Young's modulus a body switched to the hyperelastic model starts with, Pa.
pub(crate) const DEFAULT_YOUNGS: f32 = 1.0e5;
/// Poisson ratio a body switched to the hyperelastic model starts with.
pub(crate) const DEFAULT_POISSON: f32 = 0.45;
/// Shape-matching stiffness a body switched to shape matching starts with.
pub(crate) const DEFAULT_STIFFNESS: f32 = 1.0;
/// `(levels, parents)` a body switched to explicit hierarchy levels starts with.
pub(crate) const DEFAULT_LEVELS: (u32, u32) = (3, 3);
/// Young's modulus slider range, Pa (shown in kPa, logarithmic).
pub(crate) const YOUNGS_RANGE_PA: RangeInclusive<f64> = 1.0e3..=1.0e7;

/// What the widgets of a section did this frame.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(crate) struct Edit {
    /// A widget changed its value.
    pub changed: bool,
    /// A widget is being dragged or held (a slider mid-drag).
    pub dragging: bool,
}

impl Edit {
    /// Folds in a widget's response.
    pub fn add(&mut self, r: &egui::Response) {
        self.changed |= r.changed();
        self.dragging |= r.dragged() || r.is_pointer_button_down_on();
    }
}

/// A drag in progress: the value as the panel last saw it, and the edited copy.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Draft<T> {
    /// The component or resource when the draft was last updated.
    pub base: T,
    /// The copy the widgets edit.
    pub value: T,
}

/// `current` with the fields of `edited` that differ from `base` (the fields the panel
/// changed); every other field keeps `current`'s value, so a change made elsewhere
/// while a slider was held (a script, a game system) is not undone by the release.
fn merge_edits<T: Struct + Clone>(base: &T, edited: &T, current: &T) -> T {
    let mut out = current.clone();
    for i in 0..edited.field_len() {
        let (Some(e), Some(b)) = (edited.field_at(i), base.field_at(i)) else {
            continue;
        };
        if e.reflect_partial_eq(b) != Some(true)
            && let Some(o) = out.field_at_mut(i)
        {
            // Same type on both sides: cannot fail; on failure the field keeps `current`.
            let _ = o.try_apply(e);
        }
    }
    out
}

/// Runs the widgets `ui` on a copy of `current` (or on the `draft` left by a drag in
/// progress, carried over onto `current`) and returns the value to write back, if any:
///
/// * while a widget is dragged and `live` is off, the edited copy is kept in `draft`
///   and nothing is written (each write rebuilds the body or the GPU world);
/// * otherwise the copy is written when a widget changed it (or a drag just ended)
///   and it differs from `current`.
///
/// A draft carries only the fields the panel edited: fields changed elsewhere during
/// the drag keep their new values. Nothing is written when no widget reported a change:
/// a value that never equals itself (NaN) or a widget that re-rounds a value does not
/// produce writes every frame.
pub(crate) fn commit_edit<T: Clone + PartialEq + Struct>(
    current: &T,
    draft: &mut Option<Draft<T>>,
    live: bool,
    ui: impl FnOnce(&mut T) -> Edit,
) -> Option<T> {
    let had_draft = draft.is_some();
    let mut value = match draft.take() {
        Some(d) => merge_edits(&d.base, &d.value, current),
        None => current.clone(),
    };
    let edit = ui(&mut value);
    if edit.dragging && !live {
        *draft = Some(Draft {
            base: current.clone(),
            value,
        });
        return None;
    }
    ((edit.changed || had_draft) && value != *current).then_some(value)
}

/// A body's label in the selector: its `Name`, else `body <entity>`.
pub(crate) fn body_label(entity: Entity, name: Option<&Name>) -> String {
    match name {
        Some(n) if !n.as_str().is_empty() => n.as_str().to_string(),
        _ => format!("body {entity}"),
    }
}

/// A body's status for the panel.
pub(crate) fn status_text(status: Option<&SoftBodyStatus>) -> String {
    match status {
        None | Some(SoftBodyStatus::Pending) => "waiting for its mesh…".to_string(),
        Some(SoftBodyStatus::Building) => "building…".to_string(),
        Some(SoftBodyStatus::Ready {
            particles,
            vertices,
        }) => format!("{particles} particles, {vertices} vertices"),
        Some(SoftBodyStatus::Failed(e)) => format!("failed: {e}"),
    }
}

/// The gravity switch: on gives `on_value` (or [`EARTH_GRAVITY`] when that is zero),
/// off gives zero.
pub(crate) fn switch_gravity(on: bool, on_value: Vec3) -> Vec3 {
    match (on, on_value == Vec3::ZERO) {
        (false, _) => Vec3::ZERO,
        (true, true) => EARTH_GRAVITY,
        (true, false) => on_value,
    }
}

/// The material after the model radio chose `hyperelastic` (unchanged when the model
/// is already that one).
pub(crate) fn switch_model(m: TissueMaterial, hyperelastic: bool) -> TissueMaterial {
    match (m, hyperelastic) {
        (TissueMaterial::ShapeMatching { .. }, true) => TissueMaterial::Hyperelastic {
            youngs_modulus: DEFAULT_YOUNGS,
            poisson_ratio: DEFAULT_POISSON,
        },
        (TissueMaterial::Hyperelastic { .. }, false) => TissueMaterial::ShapeMatching {
            stiffness: DEFAULT_STIFFNESS,
        },
        (m, _) => m,
    }
}

/// A body switched to `discretisation`: the lattice takes only the hyperelastic model,
/// so a shape-matching body switched to it becomes hyperelastic (default E and ν); every
/// other field is kept.
pub(crate) fn switch_discretisation(
    b: &SoftBody,
    discretisation: TissueDiscretisation,
) -> SoftBody {
    let mut b = b.clone();
    b.discretisation = discretisation;
    if discretisation == TissueDiscretisation::Lattice {
        b.material = switch_model(b.material, true);
    }
    b
}

/// The hierarchy radio's choices.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum HierarchyKind {
    Auto,
    Off,
    Levels,
}

impl HierarchyKind {
    pub fn of(h: TissueHierarchy) -> Self {
        match h {
            TissueHierarchy::Auto => HierarchyKind::Auto,
            TissueHierarchy::Off => HierarchyKind::Off,
            TissueHierarchy::Levels { .. } => HierarchyKind::Levels,
        }
    }

    /// `h` switched to this kind (unchanged when it is already this kind).
    pub fn apply(self, h: TissueHierarchy) -> TissueHierarchy {
        match self {
            _ if HierarchyKind::of(h) == self => h,
            HierarchyKind::Auto => TissueHierarchy::Auto,
            HierarchyKind::Off => TissueHierarchy::Off,
            HierarchyKind::Levels => TissueHierarchy::Levels {
                levels: DEFAULT_LEVELS.0,
                parents: DEFAULT_LEVELS.1,
            },
        }
    }
}

/// A slider that never touches a value it is not dragged or typed into: existing
/// values outside `range` stay (only edits are clamped), and typed values apply on
/// Enter or when the field loses focus, not per key press.
fn slider<'a, N: egui::emath::Numeric>(
    value: &'a mut N,
    range: RangeInclusive<N>,
    text: &str,
) -> egui::Slider<'a> {
    egui::Slider::new(value, range)
        .text(text)
        .clamping(egui::SliderClamping::Edits)
        .update_while_editing(false)
}

/// The selected body's widgets on `b`.
pub(crate) fn body_widgets(ui: &mut egui::Ui, b: &mut SoftBody) -> Edit {
    let mut e = Edit::default();

    ui.label("Discretisation");
    ui.horizontal(|ui| {
        let mut d = b.discretisation;
        let r = ui.radio_value(&mut d, TissueDiscretisation::Lattice, "lattice")
            | ui.radio_value(&mut d, TissueDiscretisation::Clusters, "clusters (paper)");
        e.add(&r.on_hover_text(
            "Lattice (the default): hexahedral elements that converge to E and ν, stepped \
             by Newton–multigrid on the GPU (hyperelastic only). Clusters: the paper's \
             model, softer than E and ν say. Switching rebuilds the body",
        ));
        if d != b.discretisation {
            *b = switch_discretisation(b, d);
        }
    });
    let lattice = b.discretisation == TissueDiscretisation::Lattice;

    ui.label("Elastic model");
    ui.horizontal(|ui| {
        let mut hyper = matches!(b.material, TissueMaterial::Hyperelastic { .. });
        let r = ui
            .add_enabled_ui(!lattice, |ui| {
                ui.radio_value(&mut hyper, false, "shape matching")
            })
            .inner
            | ui.radio_value(&mut hyper, true, "hyperelastic");
        e.add(&r);
        if r.changed() && (hyper || !lattice) {
            b.material = switch_model(b.material, hyper);
        }
    });
    match &mut b.material {
        TissueMaterial::ShapeMatching { stiffness } => {
            let r = ui.add(slider(stiffness, 0.01..=1.0, "stiffness k"));
            e.add(&r.on_hover_text("Shape-matching stiffness reached per substep, in (0, 1]"));
        }
        TissueMaterial::Hyperelastic {
            youngs_modulus,
            poisson_ratio,
        } => {
            let mut kpa = *youngs_modulus as f64 / 1e3;
            let range = YOUNGS_RANGE_PA.start() / 1e3..=YOUNGS_RANGE_PA.end() / 1e3;
            let r = ui.add(
                slider(&mut kpa, range, "Young's modulus E")
                    .logarithmic(true)
                    .suffix(" kPa"),
            );
            if r.changed() {
                *youngs_modulus = (kpa * 1e3) as f32;
            }
            e.add(&r.on_hover_text(format!("E = {:.0} Pa", *youngs_modulus)));
            let r = ui.add(slider(poisson_ratio, 0.0..=0.49, "Poisson ratio ν"));
            e.add(&r);
        }
    }
    let r = ui.add(slider(&mut b.density, 100.0..=3000.0, "density").suffix(" kg/m³"));
    e.add(&r);
    if lattice {
        return e; // no clusters: K and the hierarchy do not apply
    }
    let r = ui.add(slider(&mut b.neighbours, 4..=64, "neighbours K"));
    e.add(&r.on_hover_text(
        "Cluster size: each cluster is a particle and its K nearest rest neighbours \
         (rebuilds the clusters; the body keeps its pose)",
    ));

    ui.label("Hierarchy");
    ui.horizontal(|ui| {
        let mut kind = HierarchyKind::of(b.hierarchy);
        let r = ui.radio_value(&mut kind, HierarchyKind::Auto, "auto")
            | ui.radio_value(&mut kind, HierarchyKind::Off, "off")
            | ui.radio_value(&mut kind, HierarchyKind::Levels, "levels");
        e.add(&r);
        if r.changed() {
            b.hierarchy = kind.apply(b.hierarchy);
        }
    });
    if let TissueHierarchy::Levels { levels, parents } = &mut b.hierarchy {
        e.add(&ui.add(slider(levels, 1..=4, "levels (incl. level 0)")));
        e.add(&ui.add(slider(parents, 2..=4, "parents per particle")));
    }
    e
}

/// The global settings' widgets on `s`.
pub(crate) fn settings_widgets(
    ui: &mut egui::Ui,
    s: &mut TissueSettings,
    last_gravity: Vec3,
) -> Edit {
    let mut e = Edit::default();
    e.add(&ui.add(slider(&mut s.iterations, 1..=50, "iterations / substep")));
    e.add(&ui.add(slider(&mut s.substeps, 1..=8, "substeps / step")));
    let r = ui.add(slider(
        &mut s.newton_iterations,
        1..=10,
        "Newton iterations",
    ));
    e.add(&r.on_hover_text(
        "Newton–multigrid iterations per substep of lattice bodies (default 1: with 1 \
         V-cycle, within 1% of the static answer from 1 kPa to 1 MPa)",
    ));
    let r = ui.add(slider(
        &mut s.newton_cycles,
        1..=6,
        "V-cycles / Newton iteration",
    ));
    e.add(&r.on_hover_text(
        "Multigrid V-cycles per Newton iteration of lattice bodies (default 1: the \
         V-cycle's correction combined with the last step's answer; more than one solve \
         the Newton step by conjugate gradients)",
    ));
    let r = ui.add(slider(
        &mut s.sweeps.coarsest,
        2..=100,
        "coarsest-level sweeps",
    ));
    e.add(&r.on_hover_text(
        "Smoothing sweeps on the coarsest multigrid level of lattice bodies where it is \
         not solved exactly (default 30): they carry a stiff body's bending; fewer are \
         faster but leave a 1 MPa body too soft",
    ));
    let r = ui.checkbox(&mut s.sweeps.exact_coarsest, "exact coarsest solve");
    e.add(&r.on_hover_text(format!(
        "Solve the coarsest multigrid level of lattice bodies exactly (a dense L D Lᵀ \
         factorisation of each body's small system) where every body has at most {} \
         nodes there, instead of sweeping it (default on: stiff bodies come closer to \
         their material at about the sweeps' cost)",
        crate::core::multigrid::EXACT_COARSEST
    )));
    ui.horizontal(|ui| {
        let r = ui.radio_value(&mut s.backend, TissueBackend::Auto, "GPU")
            | ui.radio_value(&mut s.backend, TissueBackend::Cpu, "CPU only");
        e.add(&r.on_hover_text(
            "Where bodies step: the GPU (lattice bodies on the CPU), or every body on the \
             CPU (slower; what the plugin falls back to when the adapter cannot run the \
             kernels)",
        ));
    });
    let r = ui.add(slider(
        &mut s.coarse_iterations,
        1..=40,
        "coarse iterations",
    ));
    e.add(&r.on_hover_text("Iterations per coarse level, for bodies with a hierarchy"));
    if s.particle_contacts {
        let r = ui.add(slider(
            &mut s.contact_every,
            1..=10,
            "contacts every n iterations",
        ));
        e.add(&r.on_hover_text(
            "Particle contacts between bodies in every n-th iteration (and the last; \
             default 2): 2 needs half the GPU dispatches of 1 for bodies in contact; \
             with relaxation 2 contacts hold as firmly as 1 unrelaxed",
        ));
        let r = ui.add(slider(
            &mut s.contact_relaxation,
            0.5..=2.0,
            "contact relaxation",
        ));
        e.add(&r.on_hover_text(
            "Jacobi relaxation of the particle contacts: 1 resolves a contact between two \
             free particles exactly, 2 lets each take the whole overlap (firmer piles)",
        ));
    }
    e.add(&ui.add(slider(&mut s.damping, 0.0..=20.0, "damping").suffix(" 1/s")));
    let mut on = s.gravity != Vec3::ZERO;
    let r = ui.checkbox(&mut on, "gravity");
    if r.changed() {
        s.gravity = switch_gravity(on, last_gravity);
    }
    let g = s.gravity;
    e.add(&r.on_hover_text(format!("({:.2}, {:.2}, {:.2}) m/s²", g.x, g.y, g.z)));
    ui.weak(format!("dt {:.2} ms", s.dt * 1e3));
    e
}

/// Pause / step / reset.
pub(crate) fn clock_widgets(
    ui: &mut egui::Ui,
    clock: Option<&mut ResMut<TissueClock>>,
    selected: Option<Entity>,
    reset: &mut MessageWriter<ResetSoftBody>,
) {
    ui.horizontal(|ui| {
        if let Some(clock) = clock {
            let paused = clock.paused;
            if ui.button(if paused { "Resume" } else { "Pause" }).clicked() {
                clock.toggle_pause();
            }
            let step = ui.add_enabled(paused, egui::Button::new("Step"));
            if step.on_hover_text("One step (while paused)").clicked() {
                clock.step_once();
            }
        }
        let r = ui.add_enabled(selected.is_some(), egui::Button::new("Reset"));
        if r.on_hover_text("Put the selected body back at its rest pose")
            .clicked()
            && let Some(entity) = selected
        {
            reset.write(ResetSoftBody { entity });
        }
    });
}

/// Frame and GPU timing.
pub(crate) fn timing_widgets(
    ui: &mut egui::Ui,
    store: Option<&DiagnosticsStore>,
    clock: Option<&TissueClock>,
) {
    let smoothed = |path: &DiagnosticPath| store.and_then(|s| s.get(path))?.smoothed();
    let fps = smoothed(&FrameTimeDiagnosticsPlugin::FPS);
    let frame = smoothed(&FrameTimeDiagnosticsPlugin::FRAME_TIME);
    let rows = store.map(stats::pass_rows).unwrap_or_default();
    let total = store.and_then(stats::frame_total);
    let steps = clock.map(|c| c.steps_this_frame);
    egui::Grid::new("tissue_timing")
        .num_columns(2)
        .show(ui, |ui| {
            ui.label("FPS");
            ui.label(fps.map_or("—".to_string(), |f| format!("{f:.1}")));
            ui.end_row();
            ui.label("frame");
            ui.label(stats::fmt_ms(frame));
            ui.end_row();
            if let Some(steps) = steps {
                ui.label("steps this frame");
                ui.label(steps.to_string());
                ui.end_row();
            }
        });
    let main = store.map(stats::main_rows).unwrap_or_default();
    if !main.is_empty() {
        ui.label("Main thread per working frame (smoothed)")
            .on_hover_text(
                "Bodies stepped from the main world (lattice bodies, or all under the CPU \
             backend): their steps (on the GPU: submitting, waiting and reading back), \
             their contact search on the CPU and the skinning of their meshes. From the \
             tissue/main/* diagnostics.",
            );
        egui::Grid::new("tissue_main_times")
            .num_columns(2)
            .striped(true)
            .show(ui, |ui| {
                for (label, ms) in &main {
                    ui.label(*label);
                    ui.monospace(stats::fmt_ms(Some(*ms)));
                    ui.end_row();
                }
            });
    }
    if rows.is_empty() {
        ui.weak(
            "No per-pass GPU times: they need Bevy's RenderDiagnosticsPlugin \
             (TissueUiPlugin::gpu_timings) and a GPU with timestamp queries.",
        );
        return;
    }
    ui.label("GPU time per tissue kernel (first dispatch in a frame, smoothed)")
        .on_hover_text(
            "From Bevy's render diagnostics. Each kernel row times its first dispatch in \
             the frame; the frame row times all of the frame's tissue work (steps, \
             drawing, bounds), and per step divides it by the steps the frame took.",
        );
    egui::Grid::new("tissue_passes")
        .num_columns(2)
        .striped(true)
        .show(ui, |ui| {
            for (pass, ms) in &rows {
                ui.monospace(pass);
                ui.monospace(stats::fmt_ms(Some(*ms)));
                ui.end_row();
            }
            ui.strong("frame (all dispatches)");
            ui.strong(stats::fmt_ms(total));
            ui.end_row();
            ui.label("per step");
            ui.label(stats::fmt_ms(stats::ms_per_step(total, steps.unwrap_or(0))));
            ui.end_row();
        });
}

/// The force each tool collider feels.
pub(crate) fn force_widgets(ui: &mut egui::Ui, forces: &[(String, Vec3)]) {
    egui::Grid::new("tissue_forces")
        .num_columns(3)
        .striped(true)
        .show(ui, |ui| {
            for (label, f) in forces {
                ui.label(label);
                ui.monospace(format!("{:.3} N", f.length()));
                ui.monospace(format!("({:+.3}, {:+.3}, {:+.3})", f.x, f.y, f.z));
                ui.end_row();
            }
        });
}

/// Tool force rows: `(label, force N)` in spawn order (by entity index).
pub(crate) fn force_rows<'a>(
    forces: impl Iterator<Item = (Entity, Option<&'a Name>, &'a ColliderForce)>,
) -> Vec<(String, Vec3)> {
    let mut v: Vec<_> = forces.map(|(e, n, f)| (e, n, f.0)).collect();
    v.sort_by_key(|r| r.0.index_u32());
    v.into_iter()
        .map(|(e, n, f)| {
            let label = match n {
                Some(n) if !n.as_str().is_empty() => n.as_str().to_string(),
                _ => format!("collider {e}"),
            };
            (label, f)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn edit(changed: bool, dragging: bool) -> Edit {
        Edit { changed, dragging }
    }

    #[test]
    fn untouched_widgets_write_nothing() {
        let mut draft = None;
        let body = SoftBody::default();
        assert_eq!(
            commit_edit(&body, &mut draft, false, |_| edit(false, false)),
            None
        );
        assert!(draft.is_none());
    }

    #[test]
    fn a_change_to_an_equal_value_writes_nothing() {
        let mut draft = None;
        let body = SoftBody::default();
        let out = commit_edit(&body, &mut draft, false, |b| {
            b.density = body.density;
            edit(true, false)
        });
        assert_eq!(out, None);
    }

    #[test]
    fn nan_is_not_rewritten_every_frame() {
        let mut draft = None;
        let body = SoftBody {
            density: f32::NAN,
            discretisation: TissueDiscretisation::Clusters,
            material: TissueMaterial::ShapeMatching { stiffness: 1.0 },
            ..Default::default()
        };
        assert!(commit_edit(&body, &mut draft, false, |_| edit(false, false)).is_none());
    }

    #[test]
    fn a_real_change_is_written() {
        let mut draft = None;
        let body = SoftBody::default();
        let out = commit_edit(&body, &mut draft, false, |b| {
            b.neighbours = 12;
            edit(true, false)
        });
        assert_eq!(out.map(|b| b.neighbours), Some(12));
    }

    #[test]
    fn a_drag_is_committed_once_on_release() {
        let body = SoftBody::default();
        let mut draft = None;
        // Frame 1: the drag starts and moves the value: kept as a draft.
        let out = commit_edit(&body, &mut draft, false, |b| {
            b.density = 1500.0;
            edit(true, true)
        });
        assert_eq!(out, None);
        assert_eq!(draft.as_ref().map(|d| d.value.density), Some(1500.0));
        // Frame 2: still held, not moved: the draft (not the component) is edited.
        let out = commit_edit(&body, &mut draft, false, |b| {
            assert_eq!(b.density, 1500.0);
            edit(false, true)
        });
        assert_eq!(out, None);
        // Frame 3: released without moving: the draft is written.
        let out = commit_edit(&body, &mut draft, false, |_| edit(false, false));
        assert_eq!(out.map(|b| b.density), Some(1500.0));
        assert!(draft.is_none());
        // Frame 4: nothing more.
        assert_eq!(
            commit_edit(&body, &mut draft, false, |_| edit(false, false)),
            None
        );
    }

    #[test]
    fn a_drag_back_to_the_start_writes_nothing() {
        let body = SoftBody::default();
        let mut draft = None;
        let _ = commit_edit(&body, &mut draft, false, |b| {
            b.density = 1500.0;
            edit(true, true)
        });
        let out = commit_edit(&body, &mut draft, false, |b| {
            b.density = body.density;
            edit(true, false)
        });
        assert_eq!(out, None);
    }

    #[test]
    fn a_drag_keeps_changes_made_elsewhere_meanwhile() {
        // The density slider is held while a script sets K; the release writes the new
        // density and keeps the script's K.
        let body = SoftBody::default();
        let mut draft = None;
        let _ = commit_edit(&body, &mut draft, false, |b| {
            b.density = 1500.0;
            edit(true, true)
        });
        let changed = SoftBody {
            neighbours: 40,
            ..body.clone()
        };
        let out = commit_edit(&changed, &mut draft, false, |b| {
            assert_eq!((b.density, b.neighbours), (1500.0, 40));
            edit(false, true)
        });
        assert_eq!(out, None);
        let out = commit_edit(&changed, &mut draft, false, |_| edit(false, false));
        let out = out.expect("the drag is written on release");
        assert_eq!((out.density, out.neighbours), (1500.0, 40));
        // An enum field edited by the panel is carried too.
        let mut draft = None;
        let _ = commit_edit(&body, &mut draft, false, |b| {
            b.material = TissueMaterial::ShapeMatching { stiffness: 0.3 };
            edit(true, true)
        });
        let out = commit_edit(&changed, &mut draft, false, |_| edit(false, false)).unwrap();
        assert_eq!(
            (out.material, out.neighbours),
            (TissueMaterial::ShapeMatching { stiffness: 0.3 }, 40)
        );
    }

    #[test]
    fn live_drags_write_every_change() {
        let body = SoftBody::default();
        let mut draft = None;
        let out = commit_edit(&body, &mut draft, true, |b| {
            b.density = 1500.0;
            edit(true, true)
        });
        assert_eq!(out.map(|b| b.density), Some(1500.0));
        assert!(draft.is_none());
    }

    #[test]
    fn labels_and_status() {
        let e = Entity::from_raw_u32(7).unwrap();
        assert_eq!(body_label(e, Some(&Name::new("liver"))), "liver");
        assert_eq!(body_label(e, None), format!("body {e}"));
        assert_eq!(body_label(e, Some(&Name::new(""))), format!("body {e}"));
        assert_eq!(status_text(Some(&SoftBodyStatus::Building)), "building…");
        assert_eq!(
            status_text(Some(&SoftBodyStatus::Ready {
                particles: 2000,
                vertices: 642
            })),
            "2000 particles, 642 vertices"
        );
        assert_eq!(
            status_text(Some(&SoftBodyStatus::Failed("bad mesh".into()))),
            "failed: bad mesh"
        );
    }

    #[test]
    fn gravity_switch() {
        assert_eq!(switch_gravity(false, EARTH_GRAVITY), Vec3::ZERO);
        assert_eq!(switch_gravity(true, Vec3::ZERO), EARTH_GRAVITY);
        let moon = Vec3::new(0.0, -1.62, 0.0);
        assert_eq!(switch_gravity(true, moon), moon);
    }

    #[test]
    fn model_and_hierarchy_switches_keep_or_default() {
        let sm = TissueMaterial::ShapeMatching { stiffness: 0.3 };
        assert_eq!(switch_model(sm, false), sm);
        assert_eq!(
            switch_model(sm, true),
            TissueMaterial::Hyperelastic {
                youngs_modulus: DEFAULT_YOUNGS,
                poisson_ratio: DEFAULT_POISSON
            }
        );
        let he = TissueMaterial::Hyperelastic {
            youngs_modulus: 2e6,
            poisson_ratio: 0.3,
        };
        assert_eq!(switch_model(he, true), he);
        assert_eq!(
            switch_model(he, false),
            TissueMaterial::ShapeMatching {
                stiffness: DEFAULT_STIFFNESS
            }
        );
        let lv = TissueHierarchy::Levels {
            levels: 4,
            parents: 2,
        };
        assert_eq!(HierarchyKind::Levels.apply(lv), lv);
        assert_eq!(HierarchyKind::Off.apply(lv), TissueHierarchy::Off);
        assert_eq!(
            HierarchyKind::Levels.apply(TissueHierarchy::Auto),
            TissueHierarchy::Levels {
                levels: DEFAULT_LEVELS.0,
                parents: DEFAULT_LEVELS.1
            }
        );
    }

    #[test]
    fn switching_to_the_lattice_makes_a_body_hyperelastic() {
        let sm = SoftBody {
            material: TissueMaterial::ShapeMatching { stiffness: 0.3 },
            neighbours: 20,
            discretisation: TissueDiscretisation::Clusters,
            ..default()
        };
        let lat = switch_discretisation(&sm, TissueDiscretisation::Lattice);
        assert_eq!(lat.discretisation, TissueDiscretisation::Lattice);
        assert_eq!(lat.material, switch_model(sm.material, true));
        assert_eq!(lat.neighbours, 20, "other fields kept");
        let he = switch_discretisation(&lat, TissueDiscretisation::Clusters);
        assert_eq!(
            he.material, lat.material,
            "back to clusters keeps the material"
        );
    }

    #[test]
    fn force_rows_are_sorted_and_labelled() {
        let a = Entity::from_raw_u32(3).unwrap();
        let b = Entity::from_raw_u32(1).unwrap();
        let name = Name::new("forceps");
        let fa = ColliderForce(Vec3::new(0.0, 2.0, 0.0));
        let fb = ColliderForce(Vec3::X);
        let rows = force_rows([(a, Some(&name), &fa), (b, None, &fb)].into_iter());
        assert_eq!(rows[0], (format!("collider {b}"), Vec3::X));
        assert_eq!(rows[1], ("forceps".to_string(), Vec3::new(0.0, 2.0, 0.0)));
    }
}
