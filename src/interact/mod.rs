//! Interaction: grab any soft body with the mouse and pull it.
//!
//! [`TissueDragPlugin`] turns a click on a body into a grasp: the press reads the
//! particles back once (asynchronously, a frame or two), picks the particle the cursor ray
//! meets first, and closes a grasper ([`ColliderKind::Grasper`]) there; while the button
//! is held the grasper follows the cursor ray at the depth it was picked at, pulling the
//! particles it took with it; release lets go. The pull is [`ColliderForce`] on the
//! [`DragGrasper`] entity.
//!
//! ```no_run
//! use bevy::prelude::*;
//! use bevy_tissue::interact::TissueDragPlugin;
//! use bevy_tissue::prelude::*;
//!
//! App::new()
//!     .add_plugins((DefaultPlugins, TissuePlugin::default(), TissueDragPlugin::default()))
//!     .run();
//! ```
//!
//! The pointer comes from the primary window and the mouse ([`TissuePointer`], filled
//! every frame); a scene without a window (headless, scripted) can write
//! [`TissuePointer`] itself.

use crate::plugin::TissueSet;
use crate::plugin::build::BuiltBody;
use crate::plugin::components::*;
use bevy::prelude::*;
use bevy::window::PrimaryWindow;

/// Mouse grab-and-pull of soft bodies.
#[derive(Debug, Clone)]
pub struct TissueDragPlugin {
    /// The button that grabs.
    pub button: MouseButton,
    /// Reach of the grasp around the picked particle, in particle spacings.
    pub reach_spacings: f32,
    /// Largest distance (in particle spacings) between the cursor ray and a particle that
    /// still counts as a hit.
    pub pick_spacings: f32,
}

impl Default for TissueDragPlugin {
    fn default() -> Self {
        Self {
            button: MouseButton::Left,
            reach_spacings: 1.6,
            pick_spacings: 0.9,
        }
    }
}

/// Where the pointer is and whether it grabs, in the viewport of the active camera
/// (logical pixels). Filled from the primary window and the mouse each frame (in
/// `PreUpdate`); write it in `Update` before [`TissueSet::Build`] to script a drag.
#[derive(Resource, Debug, Clone, Copy, Default, PartialEq, Reflect)]
#[reflect(Resource)]
pub struct TissuePointer {
    /// Cursor position, logical px from the viewport's top-left (None: outside).
    pub position: Option<Vec2>,
    /// The grab button is down.
    pub pressed: bool,
    /// The pointer belongs to something else this frame (a UI panel): no new grab starts.
    pub blocked: bool,
}

/// The one grasper the mouse drives (spawned by [`TissueDragPlugin`], open while idle).
#[derive(Component, Debug, Clone, Copy, Default, Reflect)]
#[reflect(Component)]
pub struct DragGrasper;

/// What the mouse drag is doing.
#[derive(Resource, Debug, Clone, Default, PartialEq, Reflect)]
#[reflect(Resource)]
pub enum DragState {
    /// Nothing.
    #[default]
    Idle,
    /// Button pressed: waiting for the bodies' particles to pick from.
    Picking {
        /// Frames waited so far.
        frames: u32,
    },
    /// Holding a body.
    Dragging {
        /// The body grabbed.
        body: Entity,
        /// Depth of the grasp along the camera's forward axis, m.
        depth: f32,
        /// The grasp's offset from the cursor ray's point at that depth, m (the grasp
        /// starts where it was picked).
        offset: Vec3,
    },
}

#[derive(Resource, Clone, Copy)]
struct DragConfig {
    button: MouseButton,
    reach: f32,
    pick: f32,
}

impl Plugin for TissueDragPlugin {
    fn build(&self, app: &mut App) {
        app.init_resource::<TissuePointer>()
            .init_resource::<DragState>()
            .register_type::<TissuePointer>()
            .register_type::<DragState>()
            .register_type::<DragGrasper>()
            .insert_resource(DragConfig {
                button: self.button,
                reach: self.reach_spacings,
                pick: self.pick_spacings,
            })
            .add_systems(Startup, spawn_drag_grasper)
            .add_systems(PreUpdate, read_mouse.after(bevy::input::InputSystems))
            .add_systems(Update, drag.after(TissueSet::Readback));
    }
}

fn spawn_drag_grasper(mut commands: Commands) {
    commands.spawn((
        Name::new("mouse drag"),
        DragGrasper,
        TissueCollider::new(ColliderKind::Grasper {
            radius: 0.0,
            closed: false,
        }),
        ColliderForce::default(),
        Transform::default(),
    ));
}

/// Fills [`TissuePointer`] from the primary window's cursor and the mouse (blocked while
/// the egui panel has the pointer, with the `egui` feature).
fn read_mouse(
    config: Res<DragConfig>,
    window: Query<&Window, With<PrimaryWindow>>,
    mouse: Option<Res<ButtonInput<MouseButton>>>,
    mut pointer: ResMut<TissuePointer>,
    #[cfg(feature = "egui")] focus: Option<Res<crate::ui::TissueUiFocus>>,
) {
    let Ok(window) = window.single() else { return };
    pointer.position = window.cursor_position();
    pointer.pressed = mouse.is_some_and(|m| m.pressed(config.button));
    #[cfg(feature = "egui")]
    {
        pointer.blocked = focus.is_some_and(|f| f.wants_pointer);
    }
}

/// The active camera that draws last (highest order): the one the user looks through.
fn view_camera<'a>(
    cameras: &'a Query<(&Camera, &GlobalTransform)>,
) -> Option<(&'a Camera, &'a GlobalTransform)> {
    cameras
        .iter()
        .filter(|(c, _)| c.is_active)
        .max_by_key(|(c, _)| c.order)
}

/// The first particle the ray meets: among particles within `max_dist` (m) of the ray,
/// the one nearest the ray's origin along it. Returns its index and position.
pub fn pick_particle(ray: Ray3d, positions: &[Vec3], max_dist: f32) -> Option<(usize, Vec3)> {
    let d = *ray.direction;
    let mut best: Option<(f32, usize)> = None;
    for (i, p) in positions.iter().enumerate() {
        let rel = *p - ray.origin;
        let t = rel.dot(d);
        if t.is_nan() || t <= 0.0 {
            continue;
        }
        let off = (rel - d * t).length_squared();
        if off <= max_dist * max_dist && best.is_none_or(|(bt, _)| t < bt) {
            best = Some((t, i));
        }
    }
    best.map(|(_, i)| (i, positions[i]))
}

#[allow(clippy::too_many_arguments, clippy::type_complexity)]
fn drag(
    mut commands: Commands,
    config: Res<DragConfig>,
    pointer: Res<TissuePointer>,
    mut state: ResMut<DragState>,
    cameras: Query<(&Camera, &GlobalTransform)>,
    bodies: Query<(
        Entity,
        &BuiltBody,
        Option<&ParticlePositions>,
        Option<&ReadbackParticles>,
    )>,
    mut grasper: Query<(&mut TissueCollider, &mut Transform), With<DragGrasper>>,
) {
    let Ok((mut collider, mut pose)) = grasper.single_mut() else {
        return;
    };
    let ray = view_camera(&cameras).and_then(|(camera, at)| {
        let ray = camera.viewport_to_world(at, pointer.position?).ok()?;
        Some((ray, at.forward()))
    });
    let set_closed = |collider: &mut TissueCollider, closed: bool, radius: f32| {
        let kind = ColliderKind::Grasper { radius, closed };
        if collider.kind != kind {
            collider.kind = kind;
        }
    };
    match *state {
        DragState::Idle => {
            if pointer.pressed && !pointer.blocked && ray.is_some() {
                // Read every body's particles back once, fresh.
                for (e, _, _, request) in &bodies {
                    if request.is_none() {
                        commands
                            .entity(e)
                            .remove::<ParticlePositions>()
                            .insert(ReadbackParticles { continuous: false });
                    }
                }
                *state = DragState::Picking { frames: 0 };
            }
        }
        DragState::Picking { frames } => {
            if !pointer.pressed {
                *state = DragState::Idle;
                return;
            }
            let waiting = bodies
                .iter()
                .any(|(_, _, p, r)| p.is_none() && r.is_some_and(|r| !r.continuous));
            if waiting && frames < 30 {
                *state = DragState::Picking { frames: frames + 1 };
                return;
            }
            let Some((ray, forward)) = ray else {
                *state = DragState::Idle;
                return;
            };
            // The nearest hit over all bodies.
            let mut best: Option<(f32, Entity, Vec3, f32)> = None;
            for (e, built, positions, _) in &bodies {
                let (Some(positions), Some(b)) = (positions, built.model.bodies.first()) else {
                    continue;
                };
                if let Some((_, p)) =
                    pick_particle(ray, &positions.positions, config.pick * b.spacing)
                {
                    let t = (p - ray.origin).dot(*ray.direction);
                    if best.is_none_or(|(bt, ..)| t < bt) {
                        best = Some((t, e, p, b.spacing));
                    }
                }
            }
            let Some((_, body, at, spacing)) = best else {
                *state = DragState::Idle;
                return;
            };
            let depth = (at - ray.origin).dot(*forward);
            let on_ray = point_at_depth(ray, *forward, depth).unwrap_or(at);
            pose.translation = at;
            pose.rotation = Quat::IDENTITY;
            set_closed(&mut collider, true, config.reach * spacing);
            *state = DragState::Dragging {
                body,
                depth,
                offset: at - on_ray,
            };
        }
        DragState::Dragging { depth, offset, .. } => {
            if !pointer.pressed {
                set_closed(&mut collider, false, 0.0);
                *state = DragState::Idle;
                return;
            }
            if let Some((ray, forward)) = ray
                && let Some(p) = point_at_depth(ray, *forward, depth)
            {
                pose.translation = p + offset;
            }
        }
    }
}

/// The point of `ray` at `depth` (m) along the camera's `forward` axis.
fn point_at_depth(ray: Ray3d, forward: Vec3, depth: f32) -> Option<Vec3> {
    let c = ray.direction.dot(forward);
    (c > 1e-6).then(|| ray.origin + *ray.direction * (depth / c))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pick_takes_the_first_particle_along_the_ray_within_reach() {
        let ray = Ray3d::new(Vec3::ZERO, Dir3::X);
        let pts = [
            Vec3::new(3.0, 0.05, 0.0),  // on the ray's path, far
            Vec3::new(1.0, 0.5, 0.0),   // near but off the ray
            Vec3::new(2.0, 0.0, -0.08), // the first within reach
            Vec3::new(-1.0, 0.0, 0.0),  // behind
        ];
        assert_eq!(pick_particle(ray, &pts, 0.1).map(|h| h.0), Some(2));
        assert_eq!(pick_particle(ray, &pts, 0.01), None);
        assert_eq!(pick_particle(ray, &[], 1.0), None);
    }

    #[test]
    fn the_point_at_a_depth_lies_on_the_ray() {
        let ray = Ray3d::new(Vec3::ONE, Dir3::new(Vec3::new(1.0, 0.0, -1.0)).unwrap());
        let p = point_at_depth(ray, Vec3::NEG_Z, 2.0).unwrap();
        assert!((p - Vec3::new(3.0, 1.0, -1.0)).length() < 1e-5, "{p}");
        assert!(
            point_at_depth(ray, Vec3::Z, 2.0).is_none(),
            "behind the camera"
        );
    }
}
