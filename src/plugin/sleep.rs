//! Sleeping: a body whose particles have
//! all been slower than [`TissueSleep::speed`] for [`TissueSleep::frames`] frames gets
//! [`Sleeping`], and the GPU skips its particles and clusters (no prediction, no cluster
//! solve, no gathering, no velocity update); when every body of the world sleeps, no step
//! is recorded at all. A body wakes (the component is removed) when
//!
//! * a collider that moved, or whose kind changed (a grasper closing), comes within reach
//!   of its bounds — the mouse drag is such a collider;
//! * an awake body faster than [`TissueSleep::wake_speed`] comes within reach of its
//!   bounds (a slower neighbour does not: in a pile, one creeping body would otherwise
//!   keep every body it touches awake);
//! * its [`SoftBody`] or [`Pinned`] or its transform changes, or it is reset;
//! * [`TissueSettings`] change (gravity, for one).
//!
//! The speed is the largest particle speed of the body, computed on the GPU with the
//! per-body bounds that are read back every frame for culling (no extra transfer).

use super::build::BuiltBody;
use super::components::*;
use super::render::LastPose;
use crate::core::colliders::ColliderShape;
use bevy::prelude::*;

/// When bodies fall asleep (a resource; insert your own to change it).
#[derive(Resource, Debug, Clone, Copy, PartialEq, Reflect)]
#[reflect(Resource, Default)]
pub struct TissueSleep {
    /// A body is still while its fastest particle is slower than this, m/s. 0 turns
    /// sleeping off.
    pub speed: f32,
    /// Frames a body must stay still before it sleeps.
    pub frames: u32,
    /// Reach around a body's particle bounds within which a moving collider or an awake
    /// body wakes it, m.
    pub margin: f32,
    /// A neighbouring body wakes a sleeping one only while its fastest particle is faster
    /// than this, m/s.
    pub wake_speed: f32,
}

impl Default for TissueSleep {
    /// 2 mm/s for 60 frames (a second at 60 Hz), woken within 2 cm, by neighbours
    /// faster than 5 cm/s.
    fn default() -> Self {
        Self {
            speed: 0.002,
            frames: 60,
            margin: 0.02,
            wake_speed: 0.05,
        }
    }
}

/// A soft body that sleeps: the GPU does no work on it until it is woken (see the module
/// docs). Added and removed by the plugin; remove it yourself to wake a body.
#[derive(Component, Debug, Clone, Copy, Default, PartialEq, Eq, Reflect)]
#[reflect(Component, Default)]
pub struct Sleeping;

/// A body's recent motion, from the per-frame bounds readback.
#[derive(Component, Debug, Clone, Copy, Default, PartialEq, Reflect)]
#[reflect(Component, Default)]
pub struct BodyMotion {
    /// Speed of its fastest particle at the last readback, m/s.
    pub max_speed: f32,
    /// Consecutive readbacks below [`TissueSleep::speed`].
    pub still_frames: u32,
    /// World-frame bounds of its particles at the last readback, m.
    pub min: Vec3,
    /// World-frame bounds of its particles at the last readback, m.
    pub max: Vec3,
    /// Bounds have been read at least once.
    pub known: bool,
}

impl BodyMotion {
    /// Records one readback.
    pub fn record(&mut self, min: Vec3, max: Vec3, max_speed: f32, sleep: &TissueSleep) {
        self.min = min;
        self.max = max;
        self.known = true;
        self.max_speed = max_speed;
        if max_speed.is_finite() && max_speed < sleep.speed {
            self.still_frames = self.still_frames.saturating_add(1);
        } else {
            self.still_frames = 0;
        }
    }

    fn overlaps(&self, min: Vec3, max: Vec3, margin: f32) -> bool {
        self.known && (self.min - margin).cmple(max).all() && (self.max + margin).cmpge(min).all()
    }
}

/// World-frame box a collider can touch (`None`: unbounded, a plane).
fn collider_box(c: &TissueCollider, t: &GlobalTransform) -> Option<(Vec3, Vec3)> {
    let core = c.to_core(t, Vec3::ZERO);
    let reach = match core.shape {
        ColliderShape::Plane => return None,
        ColliderShape::Sphere { radius } => radius,
        ColliderShape::Capsule {
            radius,
            half_length,
        } => radius + half_length,
        ColliderShape::Cuboid { half_extents } => half_extents.length(),
        ColliderShape::Grasper { radius, .. } => radius,
    };
    Some((core.position - reach, core.position + reach))
}

/// Puts still bodies to sleep and wakes the ones something reaches (module docs).
#[allow(clippy::type_complexity)]
pub fn update_sleep(
    mut commands: Commands,
    sleep: Res<TissueSleep>,
    settings: Res<TissueSettings>,
    mut bodies: Query<(
        Entity,
        &mut BodyMotion,
        Has<Sleeping>,
        Ref<SoftBody>,
        Ref<GlobalTransform>,
        Option<Ref<Pinned>>,
        Ref<BuiltBody>,
    )>,
    colliders: Query<(Ref<TissueCollider>, Ref<GlobalTransform>, Option<&LastPose>)>,
    mut resets: MessageReader<ResetSoftBody>,
) {
    let reset: Vec<Entity> = resets.read().map(|r| r.entity).collect();
    let everything = settings.is_changed() || sleep.is_changed();
    // Colliders that moved or changed since the last frame: their reach (None: a plane).
    // One spawned this frame is not placed yet (its global transform comes later this
    // frame): it counts from the next frame, when its placement shows as a change.
    let active: Vec<Option<(Vec3, Vec3)>> = colliders
        .iter()
        .filter(|(c, t, last)| {
            let placed = last.is_some_and(|l| l.0.is_some());
            placed && (t.is_changed() || c.is_changed())
        })
        .map(|(c, t, _)| collider_box(&c, &t))
        .collect();
    // Bodies moving fast enough to wake their neighbours.
    let awake: Vec<(Vec3, Vec3)> = bodies
        .iter()
        .filter(|b| !b.2 && b.1.known && b.1.max_speed > sleep.wake_speed.max(sleep.speed))
        .map(|b| (b.1.min, b.1.max))
        .collect();
    for (e, mut motion, asleep, body, transform, pinned, built) in &mut bodies {
        let m = sleep.margin;
        let wake = everything
            || reset.contains(&e)
            || body.is_changed()
            || transform.is_changed()
            || pinned.is_some_and(|p| p.is_changed())
            || built.is_changed()
            || active.iter().any(|a| match a {
                None => true,
                Some((lo, hi)) => motion.overlaps(*lo, *hi, m),
            })
            || (asleep && awake.iter().any(|(lo, hi)| motion.overlaps(*lo, *hi, m)));
        if wake {
            if motion.still_frames != 0 {
                motion.still_frames = 0;
            }
            if asleep {
                commands.entity(e).remove::<Sleeping>();
            }
        } else if !asleep && sleep.speed > 0.0 && motion.still_frames >= sleep.frames.max(1) {
            commands.entity(e).insert(Sleeping);
        }
    }
}
