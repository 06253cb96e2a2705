//! Model building for new or changed [`SoftBody`] entities, off the main thread
//! (`AsyncComputeTaskPool`), and the per-body draw mesh the GPU writes into.

use super::components::*;
use crate::core::TissueError;
use crate::core::mesh::TriMesh;
use crate::core::model::{BodyDesc, Discretisation, Model};
use crate::core::multigrid::BodyLevels;
use bevy::asset::RenderAssetUsages;
use bevy::mesh::{Indices, PrimitiveTopology, VertexAttributeValues};
use bevy::prelude::*;
use bevy::tasks::{AsyncComputeTaskPool, Task, block_on, futures_lite::future};
use std::sync::Arc;

/// The mesh the user gave (kept so that rebuilds start from it, not from the draw mesh).
#[derive(Component, Debug, Clone)]
pub struct SourceMesh(pub Handle<Mesh>);

/// A build in flight.
#[derive(Component)]
pub struct BuildTask(Task<Result<(Model, Option<BodyLevels>), TissueError>>);

/// A built body, ready for the GPU: its one-body model (world frame at build time), the
/// entity's draw mesh, and a generation that changes with every rebuild.
#[derive(Component, Clone)]
pub struct BuiltBody {
    /// The model (one body).
    pub model: Arc<Model>,
    /// A lattice body's multigrid levels, built with the model (the world joins its
    /// bodies' levels instead of coarsening every body again when one changes).
    pub levels: Option<Arc<BodyLevels>>,
    /// Counts rebuilds (the render world re-uploads when it changes).
    pub generation: u64,
    /// The draw mesh the GPU writes (the entity's `Mesh3d`).
    pub draw_mesh: Handle<Mesh>,
    /// This generation starts from the rest pose ([`ResetSoftBody`]) instead of keeping
    /// the simulated pose.
    pub reset: bool,
}

/// What a body was last built from: its [`SoftBody`] and [`Pinned`] as they were then.
#[derive(Component, Debug, Clone, PartialEq)]
pub struct BuiltFrom {
    /// The body's settings.
    pub body: SoftBody,
    /// Its pinned regions.
    pub pinned: Option<Pinned>,
}

/// Whether `new` builds the same model as `old`: the quality level sets the world's
/// settings, not the body; a lattice body has no clusters, so K and the hierarchy mean
/// nothing to it.
pub fn same_model(old: &SoftBody, new: &SoftBody) -> bool {
    let model_part = |b: &SoftBody| {
        let lattice = b.discretisation == TissueDiscretisation::Lattice;
        SoftBody {
            quality: Default::default(),
            neighbours: if lattice { 0 } else { b.neighbours },
            hierarchy: if lattice {
                TissueHierarchy::default()
            } else {
                b.hierarchy
            },
            ..b.clone()
        }
    };
    model_part(old) == model_part(new)
}

/// Puts bodies named by [`ResetSoftBody`] messages back at rest: a new generation of the
/// same model that the GPU world uploads from the rest state.
pub fn reset_bodies(mut messages: MessageReader<ResetSoftBody>, mut bodies: Query<&mut BuiltBody>) {
    for m in messages.read() {
        if let Ok(mut b) = bodies.get_mut(m.entity) {
            b.generation += 1;
            b.reset = true;
        }
    }
}

/// Converts a Bevy mesh to the core's triangle mesh, transformed by `to_world`.
pub fn tri_mesh(mesh: &Mesh, to_world: &GlobalTransform) -> Result<TriMesh, TissueError> {
    let bad = |value: String, expected: &'static str| TissueError::InvalidParameter {
        name: "mesh",
        value,
        expected,
    };
    if mesh.primitive_topology() != PrimitiveTopology::TriangleList {
        return Err(bad(
            format!("{:?}", mesh.primitive_topology()),
            "a TriangleList mesh",
        ));
    }
    let Some(VertexAttributeValues::Float32x3(pos)) = mesh.attribute(Mesh::ATTRIBUTE_POSITION)
    else {
        return Err(bad(
            "no Float32x3 positions".into(),
            "a mesh with Float32x3 vertex positions",
        ));
    };
    let a = to_world.affine();
    let positions = pos
        .iter()
        .map(|p| a.transform_point3(Vec3::from_array(*p)))
        .collect::<Vec<_>>();
    let indices = match mesh.indices() {
        Some(Indices::U16(i)) => i.iter().map(|&v| v as u32).collect(),
        Some(Indices::U32(i)) => i.clone(),
        None => (0..positions.len() as u32).collect(),
    };
    Ok(TriMesh::new(positions, indices))
}

/// The draw mesh: the source mesh's positions, normals and UVs (zeros where absent)
/// with its indices — exactly the layout the skinning kernel writes (8 floats per
/// vertex).
fn draw_mesh(source: &Mesh) -> Mesh {
    let n = source.count_vertices();
    let pos = match source.attribute(Mesh::ATTRIBUTE_POSITION) {
        Some(VertexAttributeValues::Float32x3(p)) => p.clone(),
        _ => vec![[0.0; 3]; n],
    };
    let nrm = match source.attribute(Mesh::ATTRIBUTE_NORMAL) {
        Some(VertexAttributeValues::Float32x3(p)) => p.clone(),
        _ => vec![[0.0, 1.0, 0.0]; n],
    };
    let uv = match source.attribute(Mesh::ATTRIBUTE_UV_0) {
        Some(VertexAttributeValues::Float32x2(p)) => p.clone(),
        _ => vec![[0.0; 2]; n],
    };
    let mut m = Mesh::new(
        PrimitiveTopology::TriangleList,
        RenderAssetUsages::default(),
    )
    .with_inserted_attribute(Mesh::ATTRIBUTE_POSITION, pos)
    .with_inserted_attribute(Mesh::ATTRIBUTE_NORMAL, nrm)
    .with_inserted_attribute(Mesh::ATTRIBUTE_UV_0, uv);
    if let Some(i) = source.indices() {
        m.insert_indices(i.clone());
    }
    m
}

/// The core's description of a body placed by `to_world` (pins in world space).
///
/// The hierarchy ([`SoftBody::hierarchy`]) is decided on the requested particle count;
/// under `Auto` a body given by spacing gets coarse levels when they keep at least 128
/// particles. A lattice body never has one.
pub fn body_desc(body: &SoftBody, pinned: Option<&Pinned>, to_world: &GlobalTransform) -> BodyDesc {
    let particles = match body.resolution {
        TissueResolution::Particles(n) => n,
        TissueResolution::Spacing(_) => u32::MAX,
    };
    let lattice = body.discretisation == TissueDiscretisation::Lattice;
    BodyDesc {
        // Lattice bodies have no cluster levels (their solver is a multigrid of its own).
        hierarchy: if lattice {
            None
        } else {
            body.hierarchy.to_core(particles, &body.material)
        },
        discretisation: body.discretisation.to_core(),
        resolution: body.resolution.to_core(),
        density: body.density,
        neighbours: body.neighbours,
        material: body.material.to_core(),
        pins: pinned
            .map(|p| p.regions.iter().map(|r| r.to_core(to_world)).collect())
            .unwrap_or_default(),
        ..Default::default()
    }
}

/// Starts builds for new and changed bodies whose mesh is loaded.
#[allow(clippy::type_complexity)]
pub fn start_builds(
    mut commands: Commands,
    meshes: Res<Assets<Mesh>>,
    mut bodies: Query<(
        Entity,
        &SoftBody,
        Option<&Pinned>,
        &Mesh3d,
        Option<&SourceMesh>,
        &GlobalTransform,
        &mut SoftBodyStatus,
        Option<&BuiltBody>,
        Option<&BuiltFrom>,
    )>,
    changed: Query<Entity, Or<(Changed<SoftBody>, Changed<Pinned>)>>,
    fresh: Query<(), Added<GlobalTransform>>,
    settings: Res<TissueSettings>,
) {
    for (entity, body, pinned, mesh3d, source, to_world, mut status, built, from) in &mut bodies {
        // A change rebuilds the body unless it leaves the model as it is (the quality
        // level; K or the hierarchy of a lattice body).
        let is_changed = changed.contains(entity)
            && built.is_some()
            && !from.is_some_and(|f| f.pinned.as_ref() == pinned && same_model(&f.body, body));
        if !(matches!(*status, SoftBodyStatus::Pending) || is_changed) {
            continue;
        }
        if fresh.contains(entity) {
            // Spawned since the last build pass: its world transform may not have been
            // propagated yet (it would be built at the origin); wait one frame.
            continue;
        }
        let handle = source.map_or(mesh3d.0.clone(), |s| s.0.clone());
        let Some(mesh) = meshes.get(&handle) else {
            continue; // not loaded yet
        };
        let tri = tri_mesh(mesh, to_world);
        let desc = body_desc(body, pinned, to_world);
        let solver = settings.to_core();
        let task = AsyncComputeTaskPool::get().spawn(async move {
            solver.validate()?;
            let tri = tri?;
            let mut model = Model::new();
            model.add_body(&tri, &desc)?;
            let levels = (desc.discretisation == Discretisation::Lattice)
                .then(|| BodyLevels::new(&model, 0));
            Ok((model, levels))
        });
        if source.is_none() {
            commands.entity(entity).insert(SourceMesh(handle));
        }
        commands.entity(entity).insert((
            BuildTask(task),
            BuiltFrom {
                body: body.clone(),
                pinned: pinned.cloned(),
            },
        ));
        *status = SoftBodyStatus::Building;
    }
}

/// Collects finished builds: a ready body gets its draw mesh and [`BuiltBody`]; a failed
/// one its error ([`SoftBodyError`], a warning, [`SoftBodyStatus::Failed`]).
#[allow(clippy::type_complexity)]
pub fn finish_builds(
    mut commands: Commands,
    mut meshes: ResMut<Assets<Mesh>>,
    mut tasks: Query<(
        Entity,
        &mut BuildTask,
        &SourceMesh,
        &mut SoftBodyStatus,
        Option<&BuiltBody>,
    )>,
    mut errors: MessageWriter<SoftBodyError>,
    mut ready: MessageWriter<SoftBodyReady>,
) {
    for (entity, mut task, source, mut status, built) in &mut tasks {
        let Some(result) = block_on(future::poll_once(&mut task.0)) else {
            continue;
        };
        commands.entity(entity).remove::<BuildTask>();
        match result {
            Ok((model, levels)) => {
                let Some(src) = meshes.get(&source.0) else {
                    continue;
                };
                let draw = match built {
                    Some(b) => b.draw_mesh.clone(),
                    None => {
                        let m = draw_mesh(src);
                        meshes.add(m)
                    }
                };
                let b = &model.bodies[0];
                if let Some(w) = crate::core::diagnose::implausible(b) {
                    warn!("soft body {entity}: {w}");
                }
                *status = SoftBodyStatus::Ready {
                    particles: b.count,
                    vertices: b.skin.rest_vertices.len() as u32,
                };
                ready.write(SoftBodyReady {
                    entity,
                    particles: b.count,
                });
                commands
                    .entity(entity)
                    .remove::<super::render::DivergenceReported>();
                commands.entity(entity).insert((
                    Mesh3d(draw.clone()),
                    BuiltBody {
                        model: Arc::new(model),
                        levels: levels.map(Arc::new),
                        generation: built.map_or(0, |b| b.generation + 1),
                        draw_mesh: draw,
                        reset: false,
                    },
                ));
            }
            Err(e) => {
                let msg = e.to_string();
                warn!("soft body {entity}: {msg}; left unsimulated");
                errors.write(SoftBodyError {
                    entity,
                    error: msg.clone(),
                });
                *status = SoftBodyStatus::Failed(msg);
                commands.entity(entity).remove::<BuiltBody>();
            }
        }
    }
}
