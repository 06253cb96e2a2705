//! Bodies simulated on the CPU, in the main world: lattice bodies (which the GPU cannot
//! run yet) and, under [`TissueBackend::Cpu`], every body. Each such body keeps its own
//! core [`Solver`] and [`State`]; every frame it takes the clock's steps against the
//! scene's colliders, then its render surface is skinned on the CPU and written into its
//! draw mesh (positions and normals, in the entity's frame). The render world leaves
//! these bodies alone ([`runs_on_cpu`]).
//!
//! What the CPU path does not do (yet): particle contacts between bodies, collider
//! forces ([`ColliderForce`] reports only the GPU's bodies) and sleeping.

use super::build::BuiltBody;
use super::components::*;
use super::render::{GraspLatch, LastPose, core_collider};
use crate::core::colliders::Collider;
use crate::core::model::Model;
use crate::core::skin::{skin_normals, skin_positions};
use crate::core::solver::{Control, Solver, State};
use bevy::mesh::VertexAttributeValues;
use bevy::prelude::*;

/// Whether a built body steps on the CPU: every body under [`TissueBackend::Cpu`], and
/// lattice bodies (hexahedral elements) under [`TissueBackend::Auto`].
pub fn runs_on_cpu(model: &Model, settings: &TissueSettings) -> bool {
    settings.backend == TissueBackend::Cpu || !model.elements.is_empty()
}

/// A body stepping on the CPU: its solver and state, for the [`BuiltBody`] generation
/// they were made from.
#[derive(Component)]
pub struct CpuBody {
    /// The [`BuiltBody::generation`] the state belongs to.
    pub generation: u64,
    /// The body's particles (the same order as the model's).
    pub state: State,
    solver: Solver,
    positions: Vec<Vec3>,
    normals: Vec<Vec3>,
}

/// The scene's colliders as the core sees them, in spawn order (the same list the GPU
/// path builds), with velocities from their motion over the last frame (`dt`, s).
pub fn scene_colliders(
    colliders: &Query<(
        Entity,
        &TissueCollider,
        &GlobalTransform,
        Option<&LastPose>,
        Option<&GraspLatch>,
    )>,
    dt: f32,
) -> Vec<Collider> {
    let mut list: Vec<(Entity, Collider)> = colliders
        .iter()
        .map(|(e, c, t, last, latch)| (e, core_collider(c, t, last, latch, dt)))
        .collect();
    list.sort_by_key(|c| c.0.index_u32());
    list.into_iter().map(|c| c.1).collect()
}

/// Steps the CPU bodies by the clock's steps of this frame, writes their meshes and, where
/// asked, their particle positions. A body whose step diverges is put back at rest and
/// reported ([`SoftBodyError`], with the core's diagnosis: where, why, what to change).
#[allow(clippy::type_complexity, clippy::too_many_arguments)]
pub fn step_cpu_bodies(
    mut commands: Commands,
    clock: Res<TissueClock>,
    settings: Res<TissueSettings>,
    time: Res<Time>,
    mut meshes: ResMut<Assets<Mesh>>,
    mut bodies: Query<(
        Entity,
        &BuiltBody,
        &GlobalTransform,
        Option<&mut CpuBody>,
        Option<&ReadbackParticles>,
    )>,
    colliders: Query<(
        Entity,
        &TissueCollider,
        &GlobalTransform,
        Option<&LastPose>,
        Option<&GraspLatch>,
    )>,
    mut errors: MessageWriter<SoftBodyError>,
) {
    let control = Control {
        colliders: scene_colliders(&colliders, time.delta_secs().max(1e-6)),
    };
    for (entity, built, to_world, cpu, readback) in &mut bodies {
        let model = &built.model;
        if !runs_on_cpu(model, &settings) {
            if cpu.is_some() {
                commands.entity(entity).remove::<CpuBody>();
            }
            continue;
        }
        let core = settings.to_core_cpu(!model.elements.is_empty());
        let mut fresh = None;
        let body = match cpu {
            Some(b) if b.generation == built.generation => b.into_inner(),
            old => {
                // A new build: keep the simulated pose across a rebuild of the same
                // particles (a material change), start at rest otherwise.
                let mut state = State::new(model);
                if let Some(old) = old
                    && !built.reset
                    && old.state.x.len() == state.x.len()
                {
                    state.x.clone_from(&old.state.x);
                    state.v.clone_from(&old.state.v);
                }
                let solver = match Solver::new(model, core.clone()) {
                    Ok(s) => s,
                    Err(e) => {
                        let error = e.to_string();
                        warn!("soft body {entity}: {error}");
                        errors.write(SoftBodyError { entity, error });
                        continue;
                    }
                };
                let vertices = model
                    .bodies
                    .first()
                    .map_or(0, |b| b.skin.rest_vertices.len());
                fresh.insert(CpuBody {
                    generation: built.generation,
                    state,
                    solver,
                    positions: vec![Vec3::ZERO; vertices],
                    normals: vec![Vec3::Y; vertices],
                })
            }
        };
        body.solver.settings = core;
        for _ in 0..clock.steps_this_frame {
            if let Err(e) = body.solver.step(model, &mut body.state, &control) {
                let error = format!("{e}; the body was put back at rest");
                warn!("soft body {entity}: {error}");
                errors.write(SoftBodyError { entity, error });
                body.state = State::new(model);
                break;
            }
        }
        write_mesh(model, body, to_world, &built.draw_mesh, &mut meshes);
        // The entity-local box of the particles, grown by the skin's reach past them.
        if let Some((lo, hi)) = crate::core::mesh::bounds_of(&body.state.x) {
            let spacing = model.bodies.first().map_or(0.0, |b| b.spacing);
            let m = Vec3::splat(3.0 * spacing);
            let (l, h) = transform_box(&to_world.affine().inverse(), lo - m, hi + m);
            commands
                .entity(entity)
                .insert(bevy::camera::primitives::Aabb::from_min_max(l, h));
        }
        if readback.is_some() {
            let mut e = commands.entity(entity);
            e.insert(ParticlePositions {
                positions: body.state.x.clone(),
                step: clock.steps,
            });
            if readback.is_some_and(|r| !r.continuous) {
                e.remove::<ReadbackParticles>();
            }
        }
        if let Some(b) = fresh {
            commands.entity(entity).insert(b);
        }
    }
}

/// Skins `body`'s render surface on the CPU and writes positions and normals (entity
/// frame) into its draw mesh.
fn write_mesh(
    model: &Model,
    body: &mut CpuBody,
    to_world: &GlobalTransform,
    mesh: &Handle<Mesh>,
    meshes: &mut Assets<Mesh>,
) {
    let Some(info) = model.bodies.first() else {
        return;
    };
    let f = Solver::deformation_gradients(model, &body.state.x);
    skin_positions(
        &info.skin,
        &body.state.x,
        &model.rest,
        &f,
        &mut body.positions,
    );
    skin_normals(&info.skin, &body.positions, &mut body.normals);
    let Some(mut m) = meshes.get_mut(mesh) else {
        return;
    };
    if m.count_vertices() != body.positions.len() {
        return;
    }
    let to_local = to_world.affine().inverse();
    // Normals go back by the transpose of the entity's linear part (the inverse
    // transpose of world-from-local's inverse).
    let normal_to_local = to_world.affine().matrix3.transpose();
    let pos: Vec<[f32; 3]> = body
        .positions
        .iter()
        .map(|p| to_local.transform_point3(*p).to_array())
        .collect();
    let nrm: Vec<[f32; 3]> = body
        .normals
        .iter()
        .map(|n| (normal_to_local * *n).normalize_or_zero().to_array())
        .collect();
    m.insert_attribute(
        Mesh::ATTRIBUTE_POSITION,
        VertexAttributeValues::Float32x3(pos),
    );
    m.insert_attribute(
        Mesh::ATTRIBUTE_NORMAL,
        VertexAttributeValues::Float32x3(nrm),
    );
}
