//! Kinematic colliders (ground plane, sphere, capsule, box) as signed distance functions,
//! the contact projection with Coulomb friction used by every solver, and graspers that
//! hold particles rigidly in their frame (tools, mouse drags).

use glam::{Quat, Vec3};

/// Collider geometry in the collider's local frame (centred at its origin).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ColliderShape {
    /// Half-space below the plane through the origin with local normal +Y.
    Plane,
    /// Sphere of the given radius, m.
    Sphere {
        /// Radius, m.
        radius: f32,
    },
    /// Capsule along the local Y axis.
    Capsule {
        /// Half the length of the inner segment, m.
        half_length: f32,
        /// Radius, m.
        radius: f32,
    },
    /// Box with the given half extents, m.
    Cuboid {
        /// Half extents along local X, Y, Z, m.
        half_extents: Vec3,
    },
    /// A grasper: pushes nothing; holds particles ([`Grab`]) rigidly in its frame.
    Grasper {
        /// Reach of a capture: particles within this distance of the origin, m.
        radius: f32,
        /// What it does this step.
        mode: GraspMode,
    },
}

/// What a [`ColliderShape::Grasper`] does in a step.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum GraspMode {
    /// Holds nothing: every particle it held is let go.
    #[default]
    Open,
    /// Takes every free particle within its radius (at the start of each substep) and
    /// holds it, as well as those it already holds.
    Capture,
    /// Holds what it holds, takes nothing new.
    Hold,
}

/// Which grasper holds a particle, and where in the grasper's frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Grab {
    /// Index of the grasper in `Control::colliders`, or `u32::MAX` when free.
    pub collider: u32,
    /// The particle's position in the grasper's frame when it was taken, m.
    pub offset: Vec3,
}

impl Grab {
    /// A free particle.
    pub const FREE: Grab = Grab {
        collider: u32::MAX,
        offset: Vec3::ZERO,
    };
}

/// Updates a particle's grab at the start of a substep (particle at `x`, m): a grab whose
/// collider is gone, not a grasper or open is let go; a free particle within reach of a
/// capturing grasper is taken (the first in collider order). GPU twin: `update_grab` in
/// `integrate.wgsl`.
pub fn update_grab(colliders: &[Collider], x: Vec3, grab: &mut Grab) {
    if grab.collider != u32::MAX {
        let keep = colliders.get(grab.collider as usize).is_some_and(
            |c| matches!(c.shape, ColliderShape::Grasper { mode, .. } if mode != GraspMode::Open),
        );
        if !keep {
            *grab = Grab::FREE;
        }
    }
    if grab.collider != u32::MAX {
        return;
    }
    for (k, c) in colliders.iter().enumerate() {
        if let ColliderShape::Grasper {
            radius,
            mode: GraspMode::Capture,
        } = c.shape
            && (x - c.position).length() <= radius
        {
            *grab = Grab {
                collider: k as u32,
                offset: c.rotation.inverse() * (x - c.position),
            };
            return;
        }
    }
}

/// Where a held particle must be (m, world), or `None` when it is free.
#[inline]
pub fn grab_target(colliders: &[Collider], grab: &Grab) -> Option<Vec3> {
    let c = colliders.get(grab.collider as usize)?;
    Some(c.position + c.rotation * grab.offset)
}

/// A kinematic collider: moves as the scene says, is pushed by nothing.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Collider {
    /// Geometry.
    pub shape: ColliderShape,
    /// Position of the local origin, m.
    pub position: Vec3,
    /// Orientation.
    pub rotation: Quat,
    /// Linear velocity, m/s (friction acts on the motion relative to it).
    pub velocity: Vec3,
    /// Coulomb friction coefficient (static and kinetic), dimensionless, ≥ 0.
    pub friction: f32,
}

impl Collider {
    /// A resting collider.
    pub fn new(shape: ColliderShape, position: Vec3, rotation: Quat) -> Self {
        Self {
            shape,
            position,
            rotation,
            velocity: Vec3::ZERO,
            friction: 0.5,
        }
    }

    /// A ground plane at height `y` (m), normal +Y.
    pub fn ground(y: f32) -> Self {
        Self::new(ColliderShape::Plane, Vec3::new(0.0, y, 0.0), Quat::IDENTITY)
    }

    /// Signed distance (m) from `p` to the surface and the outward unit normal there.
    pub fn distance(&self, p: Vec3) -> (f32, Vec3) {
        let local = self.rotation.inverse() * (p - self.position);
        let (d, n) = match self.shape {
            ColliderShape::Plane => (local.y, Vec3::Y),
            ColliderShape::Sphere { radius } => sphere_sdf(local, radius),
            ColliderShape::Capsule {
                half_length,
                radius,
            } => {
                let y = local.y.clamp(-half_length, half_length);
                sphere_sdf(local - Vec3::new(0.0, y, 0.0), radius)
            }
            ColliderShape::Cuboid { half_extents } => box_sdf(local, half_extents),
            ColliderShape::Grasper { .. } => (f32::INFINITY, Vec3::Y),
        };
        (d, self.rotation * n)
    }
}

fn sphere_sdf(local: Vec3, radius: f32) -> (f32, Vec3) {
    let l = local.length();
    let n = if l > 1e-12 { local / l } else { Vec3::Y };
    (l - radius, n)
}

fn box_sdf(local: Vec3, he: Vec3) -> (f32, Vec3) {
    let q = local.abs() - he;
    let outside = q.max(Vec3::ZERO);
    let ol = outside.length();
    if ol > 0.0 {
        let n = (outside * local.signum()) / ol;
        return (ol, n);
    }
    // Inside: nearest face.
    let axis = if q.x >= q.y && q.x >= q.z {
        0
    } else if q.y >= q.z {
        1
    } else {
        2
    };
    let mut n = Vec3::ZERO;
    n[axis] = if local[axis] >= 0.0 { 1.0 } else { -1.0 };
    (q[axis], n)
}

/// Projects a particle of radius `radius` (m) out of `collider`, with friction.
///
/// `p` is the predicted position, `x` the position at the start of the substep and `h`
/// the substep (s). Friction follows Macklin et al. 2014 ("Unified particle physics",
/// eq. 24): the tangential motion relative to the collider over the substep is removed
/// entirely when it is below `μ·depth` (static), reduced by `μ·depth` otherwise.
/// Returns the correction applied to `p` (m).
#[inline]
pub fn project_collider(collider: &Collider, p: Vec3, x: Vec3, h: f32, radius: f32) -> Vec3 {
    let (d, n) = collider.distance(p);
    let depth = radius - d;
    if depth.is_nan() || depth <= 0.0 {
        return Vec3::ZERO;
    }
    let mut dp = n * depth;
    let mu = collider.friction;
    if mu > 0.0 {
        let rel = (p + dp - x) - collider.velocity * h;
        let tangential = rel - n * rel.dot(n);
        let t = tangential.length();
        if t > 0.0 {
            if t <= mu * depth {
                dp -= tangential;
            } else {
                dp -= tangential * (mu * depth / t);
            }
        }
    }
    dp
}
