//! The Bevy plugin: components a scene puts on entities, the systems that
//! build bodies off the main thread, and the render-world systems that run every step on
//! the GPU (in the render sub-app's `RenderGraph` schedule, before `camera_driver`) and
//! skin each body straight into its mesh's vertex buffer.
//!
//! ```no_run
//! use bevy::prelude::*;
//! use bevy_tissue::prelude::*;
//!
//! App::new()
//!     .add_plugins((DefaultPlugins, TissuePlugin::default()))
//!     .add_systems(Startup, |mut commands: Commands, mut meshes: ResMut<Assets<Mesh>>,
//!                            mut materials: ResMut<Assets<StandardMaterial>>| {
//!         commands.spawn((
//!             Mesh3d(meshes.add(Sphere::new(0.5).mesh().ico(4).unwrap())),
//!             MeshMaterial3d(materials.add(Color::srgb(0.8, 0.3, 0.3))),
//!             SoftBody::default(),
//!         ));
//!         commands.spawn((TissueCollider::new(ColliderKind::Plane), Transform::from_xyz(0.0, -1.0, 0.0)));
//!     })
//!     .run();
//! ```

pub mod build;
pub mod components;
pub mod cpu;
pub mod diagnostics;
pub mod quality;
pub mod render;
pub mod sleep;

use bevy::prelude::*;
use bevy::render::mesh::allocator::MeshAllocatorSettings;
use bevy::render::render_resource::BufferUsages;
use bevy::render::renderer::{RenderGraph, RenderGraphSystems};
use bevy::render::{ExtractSchedule, Render, RenderApp, RenderSystems};
use components::*;
use std::sync::{Mutex, mpsc};

/// Ordering of the plugin's main-world systems (all in `Update`).
#[derive(SystemSet, Debug, Clone, PartialEq, Eq, Hash)]
pub enum TissueSet {
    /// Start and collect body builds.
    Build,
    /// Advance the clock (how many steps this frame takes).
    Clock,
    /// Step the bodies simulated on the CPU ([`cpu`]) and write their meshes.
    Cpu,
    /// Deliver readback results to entities.
    Readback,
}

/// Adds soft bodies to an app: register the components, build bodies, simulate them on
/// the GPU and draw them from the simulation; lattice bodies (and, under
/// [`TissueBackend::Cpu`], every body) step on the CPU and are written into their meshes
/// ([`cpu`]). The GPU path needs Bevy's render plugins (`DefaultPlugins`); without a
/// render sub-app only the CPU bodies are simulated.
#[derive(Debug, Clone, Default)]
pub struct TissuePlugin {
    /// Initial settings (also editable later as the [`TissueSettings`] resource).
    pub settings: TissueSettings,
}

impl Plugin for TissuePlugin {
    fn build(&self, app: &mut App) {
        let (tx, rx) = mpsc::channel();
        app.insert_resource(self.settings.clone())
            .init_resource::<TissueClock>()
            .init_resource::<sleep::TissueSleep>()
            .init_resource::<cpu::CpuWorld>()
            .insert_resource(render::ReadbackReceiver(Mutex::new(rx)))
            .add_message::<SoftBodyError>()
            .add_message::<SoftBodyReady>()
            .add_message::<ResetSoftBody>()
            .register_type::<SoftBody>()
            .register_type::<TissueDiscretisation>()
            .register_type::<TissueBackend>()
            .register_type::<Pinned>()
            .register_type::<TissueCollider>()
            .register_type::<ColliderForce>()
            .register_type::<ReadbackParticles>()
            .register_type::<ParticlePositions>()
            .register_type::<SoftBodyStatus>()
            .register_type::<TissueSettings>()
            .register_type::<TissueClock>()
            .register_type::<sleep::TissueSleep>()
            .register_type::<quality::TissueQuality>()
            .register_type::<sleep::Sleeping>()
            .register_type::<sleep::BodyMotion>()
            .configure_sets(
                Update,
                (
                    TissueSet::Build,
                    TissueSet::Clock,
                    TissueSet::Cpu,
                    TissueSet::Readback,
                )
                    .chain(),
            )
            .add_systems(
                Update,
                (
                    (
                        quality::apply_quality,
                        build::reset_bodies,
                        build::start_builds,
                        build::finish_builds,
                    )
                        .chain()
                        .in_set(TissueSet::Build),
                    render::advance_clock.in_set(TissueSet::Clock),
                    cpu::step_cpu_bodies.in_set(TissueSet::Cpu),
                    (render::receive_readbacks, sleep::update_sleep)
                        .chain()
                        .in_set(TissueSet::Readback),
                ),
            )
            .add_systems(Last, render::remember_collider_poses)
            .add_systems(First, render::latch_graspers)
            .add_observer(add_last_pose)
            .add_observer(remove_soft_body);
        diagnostics::TissueDiagnostics::register(app);
        let Some(render_app) = app.get_sub_app_mut(RenderApp) else {
            return;
        };
        if let Some(mut s) = render_app
            .world_mut()
            .get_resource_mut::<MeshAllocatorSettings>()
        {
            s.extra_buffer_usages |= BufferUsages::STORAGE;
        }
        render_app
            .init_resource::<render::TissueGpu>()
            .insert_resource(render::ReadbackSender(tx))
            .add_systems(ExtractSchedule, render::extract_tissue)
            .add_systems(
                Render,
                (
                    render::prepare_tissue.in_set(RenderSystems::PrepareResources),
                    render::map_readbacks.in_set(RenderSystems::Cleanup),
                ),
            )
            .add_systems(
                RenderGraph,
                render::run_tissue
                    .in_set(RenderGraphSystems::Render)
                    .before(bevy::core_pipeline::schedule::camera_driver),
            );
    }

    fn finish(&self, app: &mut App) {
        // The mesh allocator's slabs must be storage buffers for the skinning kernel to
        // write the bodies' vertices in place (as in Bevy's `compute_mesh` example).
        let Some(render_app) = app.get_sub_app_mut(RenderApp) else {
            return;
        };
        render_app
            .world_mut()
            .resource_mut::<MeshAllocatorSettings>()
            .extra_buffer_usages |= BufferUsages::STORAGE;
    }
}

/// A removed `SoftBody` stops being simulated; its entity keeps the draw mesh (at its
/// last pose) and the user's source mesh handle.
fn remove_soft_body(remove: On<Remove, SoftBody>, mut commands: Commands) {
    if let Ok(mut e) = commands.get_entity(remove.entity) {
        // `try_remove`: on a despawn the entity is gone by the time the command runs.
        e.try_remove::<(build::BuiltBody, build::BuildTask, build::BuiltFrom)>();
    }
}

fn add_last_pose(add: On<Add, TissueCollider>, mut commands: Commands) {
    commands
        .entity(add.entity)
        .insert((render::LastPose::default(), render::GraspLatch::default()));
}
