//! A live settings and timing panel for soft bodies (feature `egui`): one collapsible
//! egui window, "Tissue", at the top left of the primary window.
//!
//! * **Body**: pick a [`SoftBody`] (by `Name`), see its [`SoftBodyStatus`], and edit its
//!   elastic model (shape-matching stiffness k; hyperelastic Young's modulus E in kPa
//!   and Poisson ratio ν), density (kg/m³), neighbour count K and hierarchy;
//! * **Simulation**: the [`TissueSettings`] (iterations, substeps, coarse iterations,
//!   damping in 1/s, gravity on/off) and the [`TissueClock`] (pause, single step, reset
//!   the selected body with [`ResetSoftBody`]);
//! * **Timing**: FPS, frame time (ms), steps this frame, the GPU time (ms) of every
//!   tissue pass from Bevy's render diagnostics, their total and the time per step;
//! * **Tool forces**: the force (N) on every collider with a [`ColliderForce`].
//!
//! The panel writes a component or resource only when a widget really changed it, and
//! a slider's value only when it is released (see [`TissuePanel::live_drag`]): every
//! write of a [`SoftBody`] rebuilds the body and every write of [`TissueSettings`] the
//! GPU world. While the pointer or the keyboard is busy with egui, [`TissueUiFocus`]
//! says so; the app's own mouse and key handling should read it.
//!
//! ```no_run
//! use bevy::prelude::*;
//! use bevy_tissue::prelude::*;
//! use bevy_tissue::ui::TissueUiPlugin;
//!
//! App::new()
//!     .add_plugins((DefaultPlugins, TissuePlugin::default(), TissueUiPlugin::default()))
//!     .add_systems(Startup, |mut commands: Commands| {
//!         // egui draws on the first camera.
//!         commands.spawn(Camera3d::default());
//!     })
//!     .run();
//! ```

mod panel;
mod stats;

use crate::plugin::components::{
    ColliderForce, ResetSoftBody, SoftBody, SoftBodyStatus, TissueClock, TissueSettings,
};
use bevy::diagnostic::{DiagnosticsStore, FrameTimeDiagnosticsPlugin};
use bevy::prelude::*;
use bevy::render::diagnostic::RenderDiagnosticsPlugin;
use bevy_egui::egui::{self, collapsing_header::CollapsingState};
use bevy_egui::input::EguiWantsInput;
use bevy_egui::{EguiContexts, EguiPlugin, EguiPostUpdateSet, EguiPrimaryContextPass};
use panel::commit_edit;

/// Adds the "Tissue" egui panel (see the [module docs](crate::ui)).
///
/// Adds, unless the app already has them: `bevy_egui`'s `EguiPlugin`, Bevy's
/// `FrameTimeDiagnosticsPlugin` and (with [`TissueUiPlugin::gpu_timings`]) Bevy's
/// `RenderDiagnosticsPlugin`. Bevy refuses a plugin added twice, so an app that adds
/// any of these itself adds it **before** this plugin. Add this plugin after
/// `DefaultPlugins`. Without [`crate::plugin::TissuePlugin`] the panel still shows
/// the timing; the sections that need its resources are left out.
#[derive(Debug, Clone)]
pub struct TissueUiPlugin {
    /// Add `RenderDiagnosticsPlugin` (GPU timestamp queries around Bevy's and the
    /// tissue's passes) so the panel can show the GPU time of each tissue pass.
    /// Default: `true`.
    pub gpu_timings: bool,
}

impl Default for TissueUiPlugin {
    fn default() -> Self {
        Self { gpu_timings: true }
    }
}

impl Plugin for TissueUiPlugin {
    fn build(&self, app: &mut App) {
        if !app.is_plugin_added::<EguiPlugin>() {
            app.add_plugins(EguiPlugin::default());
        }
        if !app.is_plugin_added::<FrameTimeDiagnosticsPlugin>() {
            app.add_plugins(FrameTimeDiagnosticsPlugin::default());
        }
        if self.gpu_timings && !app.is_plugin_added::<RenderDiagnosticsPlugin>() {
            app.add_plugins(RenderDiagnosticsPlugin);
        }
        // `add_message` registers a message once; a second call is a no-op.
        app.init_resource::<DiagnosticsStore>()
            .init_resource::<TissuePanel>()
            .init_resource::<TissueUiFocus>()
            .add_message::<ResetSoftBody>()
            .add_systems(EguiPrimaryContextPass, draw_panel)
            .add_systems(
                PostUpdate,
                update_focus.after(EguiPostUpdateSet::ProcessOutput),
            );
    }
}

/// Whether egui is using the pointer or the keyboard (updated every frame, at the end
/// of `PostUpdate`, so a system in `Update` sees the last frame's state). Mouse picking,
/// camera orbiting and key bindings should do nothing while the matching flag is set.
#[derive(Resource, Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TissueUiFocus {
    /// The pointer is over the panel (or any egui area or popup), or egui is dragging a
    /// widget. A drag that began in the scene and passes over the panel also sets it:
    /// check it when a drag starts, not while it goes on.
    pub wants_pointer: bool,
    /// egui has keyboard focus (a value being typed) or a popup is open.
    pub wants_keyboard: bool,
}

/// The panel's state: which body it edits and how it is shown. Change it from the app
/// to open, collapse or move the panel or to select a body.
#[derive(Resource, Debug, Clone, PartialEq)]
pub struct TissuePanel {
    /// Show the panel (there is no close button: toggle this, e.g. from a key binding).
    /// Default: `true`.
    pub open: bool,
    /// Only the title bar is shown (kept in sync with the collapse button).
    /// Default: `false`.
    pub collapsed: bool,
    /// Pinned to the top-left corner of the window; `false`: movable, starting there.
    /// Default: `true`.
    pub anchored: bool,
    /// The body edited (an entity with a [`SoftBody`]); `None` or a stale entity is
    /// replaced by the first body.
    pub selected: Option<Entity>,
    /// Write slider edits while the slider is still dragged, instead of once when it is
    /// released. Every write of a [`SoftBody`] rebuilds the body (clusters built off
    /// the main thread) and every write of [`TissueSettings`] the GPU world, so this is
    /// only for cheap scenes. Default: `false`.
    pub live_drag: bool,
    /// The selected body's values while a slider is dragged (not written yet).
    body_draft: Option<(Entity, panel::Draft<SoftBody>)>,
    /// The settings while a slider is dragged (not written yet).
    settings_draft: Option<panel::Draft<TissueSettings>>,
    /// Gravity the gravity switch restores, m/s².
    last_gravity: Vec3,
}

impl Default for TissuePanel {
    fn default() -> Self {
        Self {
            open: true,
            collapsed: false,
            anchored: true,
            selected: None,
            live_drag: false,
            body_draft: None,
            settings_draft: None,
            last_gravity: panel::EARTH_GRAVITY,
        }
    }
}

/// egui id of the panel's window.
const WINDOW_ID: &str = "bevy_tissue_panel";
/// Margin between the panel and the window's corner, logical px.
const MARGIN: f32 = 8.0;

fn update_focus(wants: Option<Res<EguiWantsInput>>, mut focus: ResMut<TissueUiFocus>) {
    let new = wants.map_or_else(TissueUiFocus::default, |w| TissueUiFocus {
        wants_pointer: w.wants_any_pointer_input(),
        wants_keyboard: w.wants_any_keyboard_input(),
    });
    focus.set_if_neq(new);
}

/// The soft bodies, to list and to edit.
type BodyQuery<'w, 's> = Query<
    'w,
    's,
    (
        Entity,
        Option<&'static Name>,
        Option<&'static SoftBodyStatus>,
        &'static mut SoftBody,
    ),
>;

#[allow(clippy::too_many_arguments)]
fn draw_panel(
    mut contexts: EguiContexts,
    mut state: ResMut<TissuePanel>,
    mut bodies: BodyQuery,
    forces: Query<(Entity, Option<&Name>, &ColliderForce)>,
    mut settings: Option<ResMut<TissueSettings>>,
    mut clock: Option<ResMut<TissueClock>>,
    store: Option<Res<DiagnosticsStore>>,
    mut reset: MessageWriter<ResetSoftBody>,
) {
    if !state.open {
        return;
    }
    let Ok(ctx) = contexts.ctx_mut() else {
        return;
    };
    let ctx = ctx.clone();
    // Edit a copy: the resource is written (and marked changed) only if it differs.
    let mut p = state.clone();

    let id = egui::Id::new(WINDOW_ID);
    let collapse_id = id.with("collapsing");
    if CollapsingState::load(&ctx, collapse_id).is_none_or(|c| c.is_open() == p.collapsed) {
        let mut c = CollapsingState::load_with_default_open(&ctx, collapse_id, !p.collapsed);
        c.set_open(!p.collapsed);
        c.store(&ctx);
    }
    let mut window = egui::Window::new("Tissue")
        .id(id)
        .collapsible(true)
        .default_open(!p.collapsed)
        .default_width(300.0)
        .vscroll(true)
        // Tall enough that the timing and the tool forces show without scrolling, where
        // the window allows.
        .min_height((ctx.content_rect().height() - 2.0 * MARGIN).clamp(0.0, 760.0));
    window = if p.anchored {
        window.anchor(egui::Align2::LEFT_TOP, [MARGIN, MARGIN])
    } else {
        window.default_pos([MARGIN, MARGIN])
    };

    let forces = panel::force_rows(forces.iter());
    window.show(&ctx, |ui| {
        egui::CollapsingHeader::new("Body")
            .default_open(true)
            .show(ui, |ui| body_section(ui, &mut p, &mut bodies));
        egui::CollapsingHeader::new("Simulation")
            .default_open(true)
            .show(ui, |ui| {
                panel::clock_widgets(ui, clock.as_mut(), p.selected, &mut reset);
                if let Some(settings) = settings.as_mut() {
                    settings_section(ui, &mut p, settings);
                }
            });
        egui::CollapsingHeader::new("Timing")
            .default_open(true)
            .show(ui, |ui| {
                panel::timing_widgets(ui, store.as_deref(), clock.as_deref());
            });
        if !forces.is_empty() {
            egui::CollapsingHeader::new("Tool forces")
                .default_open(true)
                .show(ui, |ui| panel::force_widgets(ui, &forces));
        }
    });
    if let Some(c) = CollapsingState::load(&ctx, collapse_id) {
        p.collapsed = !c.is_open();
    }
    state.set_if_neq(p);
}

/// The selector, the status line and the selected body's parameters.
fn body_section(ui: &mut egui::Ui, p: &mut TissuePanel, bodies: &mut BodyQuery) {
    let mut list: Vec<_> = bodies
        .iter()
        .map(|(e, name, status, _)| (e, panel::body_label(e, name), status.cloned()))
        .collect();
    // Spawn order (entity index; `Entity`'s own order is not the index order).
    list.sort_by_key(|b| b.0.index_u32());
    if !p.selected.is_some_and(|s| list.iter().any(|b| b.0 == s)) {
        p.selected = list.first().map(|b| b.0);
    }
    let Some(selected) = p.selected else {
        p.body_draft = None;
        ui.weak("No soft bodies.");
        return;
    };
    let label = |e: Entity| list.iter().find(|b| b.0 == e).map(|b| b.1.clone());
    let mut choice = selected;
    egui::ComboBox::from_id_salt("tissue_body")
        .selected_text(label(selected).unwrap_or_default())
        .show_ui(ui, |ui| {
            for (e, text, _) in &list {
                ui.selectable_value(&mut choice, *e, text.as_str());
            }
        });
    if choice != selected {
        p.selected = Some(choice);
        p.body_draft = None;
    }
    let selected = choice;
    let status = list
        .iter()
        .find(|b| b.0 == selected)
        .and_then(|b| b.2.as_ref());
    let text = panel::status_text(status);
    if matches!(status, Some(SoftBodyStatus::Failed(_))) {
        ui.colored_label(ui.visuals().error_fg_color, text);
    } else {
        ui.weak(text);
    }

    let Ok((.., mut body)) = bodies.get_mut(selected) else {
        return;
    };
    let mut draft = p
        .body_draft
        .take()
        .filter(|(e, _)| *e == selected)
        .map(|(_, b)| b);
    // Read through `Deref` (no change mark); write only a real change.
    let new = commit_edit(&*body, &mut draft, p.live_drag, |b| {
        panel::body_widgets(ui, b)
    });
    p.body_draft = draft.map(|b| (selected, b));
    if let Some(new) = new {
        body.set_if_neq(new);
    }
}

/// The global settings, written only on a real change.
fn settings_section(ui: &mut egui::Ui, p: &mut TissuePanel, settings: &mut ResMut<TissueSettings>) {
    ui.separator();
    if settings.gravity != Vec3::ZERO {
        p.last_gravity = settings.gravity;
    }
    let last_gravity = p.last_gravity;
    let new = commit_edit(&**settings, &mut p.settings_draft, p.live_drag, |s| {
        panel::settings_widgets(ui, s, last_gravity)
    });
    if let Some(new) = new {
        settings.set_if_neq(new);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plugin::components::TissueMaterial;
    use bevy::window::{ExitCondition, WindowPlugin};
    use bevy_egui::{EguiGlobalSettings, PrimaryEguiContext};

    /// Writes of the watched component and resources seen in `Last`.
    #[derive(Resource, Default)]
    struct Writes {
        bodies: u32,
        settings: u32,
    }

    fn count_writes(
        bodies: Query<(), Changed<SoftBody>>,
        settings: Option<Res<TissueSettings>>,
        mut writes: ResMut<Writes>,
    ) {
        writes.bodies += bodies.iter().count() as u32;
        writes.settings += u32::from(settings.is_some_and(|s| s.is_changed()));
    }

    /// A windowless app whose egui context runs the panel every update.
    fn app(with_tissue_resources: bool) -> App {
        let mut app = App::new();
        app.add_plugins((
            MinimalPlugins,
            AssetPlugin::default(),
            bevy::input::InputPlugin,
            WindowPlugin {
                primary_window: None,
                exit_condition: ExitCondition::DontExit,
                ..default()
            },
        ))
        // What bevy_egui's renderer registers its shader and textures in.
        .init_asset::<bevy::shader::Shader>()
        .init_asset::<Image>()
        .add_plugins(TissueUiPlugin { gpu_timings: false });
        app.world_mut()
            .resource_mut::<EguiGlobalSettings>()
            .auto_create_primary_context = false;
        app.world_mut().spawn(PrimaryEguiContext);
        if with_tissue_resources {
            app.insert_resource(TissueSettings::default())
                .init_resource::<TissueClock>();
        }
        app.init_resource::<Writes>()
            .add_systems(Last, count_writes);
        app
    }

    #[test]
    fn looking_at_the_panel_writes_nothing() {
        let mut app = app(true);
        let body = app
            .world_mut()
            .spawn((
                Name::new("liver"),
                SoftBody {
                    // Outside the sliders' ranges: must stay as it is.
                    density: 5000.0,
                    neighbours: 100,
                    material: TissueMaterial::Hyperelastic {
                        youngs_modulus: 5.0e7,
                        poisson_ratio: 0.3,
                    },
                    discretisation: crate::prelude::TissueDiscretisation::Clusters,
                    ..Default::default()
                },
            ))
            .id();
        app.world_mut().resource_mut::<TissueSettings>().iterations = 200;
        for _ in 0..3 {
            app.update();
        }
        // The panel ran: it selected the only body.
        assert_eq!(app.world().resource::<TissuePanel>().selected, Some(body));
        *app.world_mut().resource_mut::<Writes>() = Writes::default();
        for _ in 0..10 {
            app.update();
        }
        let w = app.world().resource::<Writes>();
        assert_eq!((w.bodies, w.settings), (0, 0), "the panel wrote unasked");
        let b = app.world().get::<SoftBody>(body).unwrap();
        assert_eq!((b.density, b.neighbours), (5000.0, 100));
        assert_eq!(app.world().resource::<TissueSettings>().iterations, 200);
    }

    #[test]
    fn collapsed_state_follows_the_resource() {
        let mut app = app(true);
        app.update();
        app.world_mut().resource_mut::<TissuePanel>().collapsed = true;
        for _ in 0..3 {
            app.update();
        }
        assert!(app.world().resource::<TissuePanel>().collapsed);
        app.world_mut().resource_mut::<TissuePanel>().collapsed = false;
        for _ in 0..3 {
            app.update();
        }
        assert!(!app.world().resource::<TissuePanel>().collapsed);
    }

    /// Where the test moves egui's pointer on the next update.
    #[derive(Resource, Default)]
    struct PointerTo(Option<egui::Pos2>);

    /// Feeds the pointer move straight into the context's input (after bevy_egui has
    /// gathered its own input: a windowless context has none).
    fn feed_pointer(mut to: ResMut<PointerTo>, mut inputs: Query<&mut bevy_egui::EguiInput>) {
        if let Some(p) = to.0.take() {
            for mut input in &mut inputs {
                input.events.push(egui::Event::PointerMoved(p));
            }
        }
    }

    #[test]
    fn pointer_over_the_panel_is_reported() {
        let mut app = app(true);
        app.init_resource::<PointerTo>().add_systems(
            PreUpdate,
            feed_pointer.after(bevy_egui::EguiPreUpdateSet::ProcessInput),
        );
        app.update();
        let move_to = |app: &mut App, x: f32, y: f32| {
            app.world_mut().resource_mut::<PointerTo>().0 = Some(egui::pos2(x, y));
            app.update();
            *app.world().resource::<TissueUiFocus>()
        };
        // Just inside the top-left corner of the anchored window.
        assert!(move_to(&mut app, MARGIN + 20.0, MARGIN + 10.0).wants_pointer);
        assert!(!move_to(&mut app, 3000.0, 3000.0).wants_pointer);
        assert!(move_to(&mut app, MARGIN + 20.0, MARGIN + 10.0).wants_pointer);
    }

    #[test]
    fn no_tissue_plugin_no_bodies_no_panic() {
        let mut app = app(false);
        for _ in 0..3 {
            app.update();
        }
        assert_eq!(app.world().resource::<TissuePanel>().selected, None);
        assert_eq!(
            *app.world().resource::<TissueUiFocus>(),
            TissueUiFocus::default()
        );
    }
}
