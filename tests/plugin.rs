//! The plugin in a headless Bevy app (no window; Mesa's lavapipe in CI): a body
//! simulated through the render graph matches the CPU Jacobi solver, the mesh's own
//! vertex buffer holds the CPU skinning of the same particles, bad input becomes an
//! error message while the app keeps running, and no particle data crosses to the host
//! unless asked for.

use bevy::camera::primitives::Aabb;
use bevy::prelude::*;
use bevy::render::RenderApp;
use bevy::render::mesh::allocator::MeshAllocator;
use bevy::render::renderer::{RenderDevice, RenderQueue};
use bevy::render::settings::{RenderCreation, WgpuSettings};
use bevy::window::ExitCondition;
use bevy_tissue::core::model::Model;
use bevy_tissue::core::solver::{Control, Solver, State};
use bevy_tissue::gpu::world::read_buffer;
use bevy_tissue::plugin::build::{BuiltBody, body_desc, tri_mesh};
use bevy_tissue::plugin::render::TissueGpu;
use bevy_tissue::prelude::*;
use std::sync::Mutex;
mod common;

/// Bevy apps in one process one at a time.
static ONE_APP: Mutex<()> = Mutex::new(());

fn gpu_available() -> bool {
    match bevy_tissue::gpu::headless() {
        Ok(_) => true,
        Err(e) => {
            if std::env::var("CI").is_ok_and(|v| v == "true") {
                panic!("CI=true but no GPU adapter: {e}");
            }
            eprintln!("skipped: {e}");
            false
        }
    }
}

fn app(wgpu: WgpuSettings) -> App {
    app_with(wgpu, |_| {})
}

/// A headless app with the tissue plugin on a device held to `wgpu`'s limits, or to
/// WebGPU's default limits where it names none (every plugin test runs as a browser or
/// a Mac would).
fn app_with(mut wgpu: WgpuSettings, extra: impl FnOnce(&mut App)) -> App {
    if wgpu.constrained_limits.is_none() {
        wgpu.constrained_limits = Some(bevy::render::settings::WgpuLimits::default());
    }
    let mut app = App::new();
    app.add_plugins(
        DefaultPlugins
            .set(WindowPlugin {
                primary_window: None,
                exit_condition: ExitCondition::DontExit,
                ..default()
            })
            .set(bevy::render::RenderPlugin {
                render_creation: RenderCreation::Automatic(Box::new(wgpu)),
                synchronous_pipeline_compilation: true,
                ..default()
            })
            .disable::<bevy::winit::WinitPlugin>()
            // The render world stays on this thread, so the test can inspect it.
            .disable::<bevy::render::pipelined_rendering::PipelinedRenderingPlugin>(),
    )
    .add_plugins(TissuePlugin::default());
    extra(&mut app);
    app.world_mut().resource_mut::<TissueClock>().paused = true;
    while app.plugins_state() == bevy::app::PluginsState::Adding {
        bevy::tasks::tick_global_task_pools_on_main_thread();
    }
    app.finish();
    app.cleanup();
    app
}

fn box_mesh() -> Mesh {
    Cuboid::new(0.12, 0.05, 0.05).mesh().build()
}

fn spawn_body(app: &mut App, at: Vec3, body: SoftBody, pinned: Option<Pinned>) -> Entity {
    let mesh = app
        .world_mut()
        .resource_mut::<Assets<Mesh>>()
        .add(box_mesh());
    let mat = app
        .world_mut()
        .resource_mut::<Assets<StandardMaterial>>()
        .add(Color::WHITE);
    let mut e = app.world_mut().spawn((
        Mesh3d(mesh),
        MeshMaterial3d(mat),
        Transform::from_translation(at),
        body,
    ));
    if let Some(p) = pinned {
        e.insert(p);
    }
    e.id()
}

/// Updates until `done` holds (at most `max` frames), collecting every `SoftBodyError`.
fn until_collecting(
    app: &mut App,
    max: u32,
    errors: &mut Vec<SoftBodyError>,
    mut done: impl FnMut(&mut App, &[SoftBodyError]) -> bool,
) -> bool {
    until(app, max, |app| {
        let msgs = app.world().resource::<Messages<SoftBodyError>>();
        errors.extend(msgs.iter_current_update_messages().cloned());
        done(app, errors)
    })
}

/// Updates until `done` holds (at most `max` frames).
fn until(app: &mut App, max: u32, mut done: impl FnMut(&mut App) -> bool) -> bool {
    for _ in 0..max {
        app.update();
        if done(app) {
            return true;
        }
    }
    false
}

const HYPER: TissueMaterial = TissueMaterial::Hyperelastic {
    youngs_modulus: 20_000.0,
    poisson_ratio: 0.4,
};
const SHAPE: TissueMaterial = TissueMaterial::ShapeMatching { stiffness: 0.8 };

fn body_spec() -> (SoftBody, Pinned) {
    body_of(HYPER)
}

fn body_of(material: TissueMaterial) -> (SoftBody, Pinned) {
    (
        SoftBody {
            resolution: TissueResolution::Particles(500),
            neighbours: 16,
            material,
            discretisation: TissueDiscretisation::Clusters,
            ..default()
        },
        Pinned::region(PinShape::HalfSpace {
            point: Vec3::new(0.0, 0.02, 0.0),
            normal: Vec3::Y,
        }),
    )
}

/// The same body built and stepped `steps` times on the CPU (Jacobi), in world space.
fn cpu_reference(
    material: TissueMaterial,
    at: Vec3,
    steps: u64,
    settings: &TissueSettings,
) -> (Model, Vec<Vec3>) {
    let (body, pinned) = body_of(material);
    cpu_reference_of(body, pinned, at, steps, settings)
}

/// [`cpu_reference`] of any body.
fn cpu_reference_of(
    body: SoftBody,
    pinned: Pinned,
    at: Vec3,
    steps: u64,
    settings: &TissueSettings,
) -> (Model, Vec<Vec3>) {
    let to_world = GlobalTransform::from(Transform::from_translation(at));
    let tri = tri_mesh(&box_mesh(), &to_world).unwrap();
    let desc = body_desc(&body, Some(&pinned), &to_world);
    let mut model = Model::new();
    model.add_body(&tri, &desc).unwrap();
    let mut state = State::new(&model);
    let mut solver = Solver::new(&model, settings.to_core()).unwrap();
    for _ in 0..steps {
        solver
            .step(&model, &mut state, &Control::default())
            .unwrap();
    }
    (model, state.x)
}

/// Takes `frames` × 20 steps with the clock, pauses, and reads the body's particles back.
fn step_and_read(app: &mut App, e: Entity, frames: u32) -> ParticlePositions {
    for _ in 0..3 {
        app.update();
    }
    {
        let mut clock = app.world_mut().resource_mut::<TissueClock>();
        clock.paused = false;
        clock.fixed_steps_per_frame = Some(20);
    }
    for _ in 0..frames {
        app.update();
    }
    app.world_mut().resource_mut::<TissueClock>().paused = true;
    for _ in 0..3 {
        app.update();
    }
    read_now(app, e)
}

#[test]
fn a_body_in_a_headless_app_matches_the_cpu_and_is_drawn_from_the_gpu() {
    let _one = ONE_APP.lock().unwrap_or_else(|e| e.into_inner());
    if !gpu_available() {
        return;
    }
    let mut app = app(WgpuSettings::default());
    // Both elastic models, batched in one world (far apart: no contacts).
    let at = Vec3::new(0.0, 0.5, 0.0);
    let at2 = Vec3::new(1.0, 0.5, 0.0);
    let (body, pinned) = body_of(HYPER);
    let e = spawn_body(&mut app, at, body, Some(pinned));
    let (body2, pinned2) = body_of(SHAPE);
    let e2 = spawn_body(&mut app, at2, body2, Some(pinned2));
    let ready = |app: &mut App, e: Entity| {
        matches!(
            app.world().get::<SoftBodyStatus>(e),
            Some(SoftBodyStatus::Ready { .. })
        )
    };
    assert!(
        until(&mut app, 600, |app| ready(app, e) && ready(app, e2)),
        "the bodies never became ready: {:?}",
        app.world().get::<SoftBodyStatus>(e)
    );
    // Let the render world upload it, then take exactly 200 steps, 20 per frame.
    let got = step_and_read(&mut app, e, 10);
    assert!(
        app.world().get::<ReadbackParticles>(e).is_none(),
        "a one-shot request is removed once served"
    );
    assert_eq!(
        got.step, 200,
        "the GPU world took a different number of steps"
    );
    let settings = app.world().resource::<TissueSettings>().clone();
    let (model, cpu) = cpu_reference(HYPER, at, got.step, &settings);
    let size = model.bodies[0].size;
    let d = got
        .positions
        .iter()
        .zip(&cpu)
        .map(|(a, b)| a.distance(*b))
        .fold(0.0f32, f32::max);
    let sag = cpu
        .iter()
        .zip(&model.placed_rest())
        .map(|(a, b)| a.distance(*b))
        .fold(0.0f32, f32::max);
    eprintln!("GPU–CPU after 200 steps: {d:.3e} m (size {size:.3} m, sag {sag:.3e} m)");
    assert!(sag > 0.002, "the body must sag under gravity ({sag} m)");
    assert!(d < 1e-4 * size, "GPU and CPU differ by {d} m");

    // The mesh's own vertex buffer (the allocator slab) holds the CPU skinning of the
    // same particle positions, in the entity's local frame.
    let draw = app.world().get::<BuiltBody>(e).unwrap().draw_mesh.id();
    let rw = app.sub_app(RenderApp).world();
    let alloc = rw.resource::<MeshAllocator>();
    let slice = alloc.mesh_vertex_slice(&draw).expect("mesh uploaded");
    let (dev, queue) = (rw.resource::<RenderDevice>(), rw.resource::<RenderQueue>());
    let nv = slice.range.len() as u64;
    let bytes = read_buffer(
        dev,
        queue,
        slice.buffer,
        slice.range.start as u64 * 32,
        nv * 32,
    );
    let vtx: &[[f32; 8]] = bytemuck::cast_slice(&bytes);
    let skinned = {
        let sk = &model.bodies[0].skin;
        let f = Solver::deformation_gradients(&model, &got.positions);
        let mut out = vec![Vec3::ZERO; sk.rest_vertices.len()];
        bevy_tissue::core::skin::skin_positions(sk, &got.positions, &model.rest, &f, &mut out);
        out
    };
    assert_eq!(vtx.len(), skinned.len());
    let dv = vtx
        .iter()
        .zip(&skinned)
        .map(|(v, s)| Vec3::new(v[0], v[1], v[2]).distance(*s - at))
        .fold(0.0f32, f32::max);
    // Culling bounds follow the deformed body: the entity's Aabb (local frame) holds
    // every drawn vertex.
    let aabb = *app.world().get::<Aabb>(e).expect("culling bounds");
    let (c, he) = (Vec3::from(aabb.center), Vec3::from(aabb.half_extents));
    for v in vtx {
        let p = Vec3::new(v[0], v[1], v[2]);
        assert!(
            ((p - c).abs() - he).max_element() <= 1e-6,
            "vertex {p} outside the culling box {c} ± {he}"
        );
    }
    // ... and it is the particles' own box (read back, paused) grown by three spacings.
    let m = 3.0 * model.bodies[0].spacing;
    let lo = got.positions.iter().fold(Vec3::MAX, |a, p| a.min(*p)) - at - m;
    let hi = got.positions.iter().fold(Vec3::MIN, |a, p| a.max(*p)) - at + m;
    assert!(
        (c - he - lo).abs().max_element() < 1e-5 && (c + he - hi).abs().max_element() < 1e-5,
        "culling box {c} ± {he} is not the particles' box {lo}..{hi} grown by {m} m"
    );
    assert!(
        dv < 1e-5 * size,
        "drawn vertices differ from the CPU skinning by {dv} m"
    );

    // Nothing per particle crosses to the host unless asked for.
    let stats = rw.resource::<TissueGpu>().stats();
    assert_eq!(stats.readback_bytes, 0, "no readback requested this frame");
    assert!(
        stats.uploaded_bytes < 2048,
        "per-frame uploads must not scale with particles: {} bytes",
        stats.uploaded_bytes
    );
}

#[test]
fn a_bad_mesh_is_an_error_message_and_the_app_keeps_running() {
    let _one = ONE_APP.lock().unwrap_or_else(|e| e.into_inner());
    if !gpu_available() {
        return;
    }
    let mut app = app(WgpuSettings::default());
    // An open mesh: a box without its last face.
    let mut open = box_mesh();
    if let Some(bevy::mesh::Indices::U32(i)) = open.indices_mut() {
        i.truncate(i.len() - 6);
    }
    let open = app.world_mut().resource_mut::<Assets<Mesh>>().add(open);
    let bad = app
        .world_mut()
        .spawn((Mesh3d(open), SoftBody::default()))
        .id();
    let (body, pinned) = body_spec();
    let good = spawn_body(&mut app, Vec3::ZERO, body, Some(pinned));
    // K larger than the body: a clear error too.
    let tiny = spawn_body(
        &mut app,
        Vec3::X,
        SoftBody {
            resolution: TissueResolution::Particles(20),
            neighbours: 64,
            discretisation: TissueDiscretisation::Clusters,
            material: TissueMaterial::ShapeMatching { stiffness: 1.0 },
            ..default()
        },
        None,
    );
    let mut errors: Vec<SoftBodyError> = Vec::new();
    until_collecting(&mut app, 600, &mut errors, |app, errors| {
        errors.len() >= 2
            && matches!(
                app.world().get::<SoftBodyStatus>(good),
                Some(SoftBodyStatus::Ready { .. })
            )
    });
    let bad_err = errors
        .iter()
        .find(|m| m.entity == bad)
        .expect("error for the open mesh");
    assert!(bad_err.error.contains("not closed"), "{}", bad_err.error);
    let tiny_err = errors
        .iter()
        .find(|m| m.entity == tiny)
        .expect("error for K too large");
    assert!(
        tiny_err.error.contains("neighbour count"),
        "{}",
        tiny_err.error
    );
    assert!(matches!(
        app.world().get::<SoftBodyStatus>(bad),
        Some(SoftBodyStatus::Failed(_))
    ));
    // The good body simulates on.
    {
        let mut clock = app.world_mut().resource_mut::<TissueClock>();
        clock.paused = false;
        clock.fixed_steps_per_frame = Some(5);
    }
    app.world_mut()
        .entity_mut(good)
        .insert(ReadbackParticles { continuous: true });
    assert!(until(&mut app, 60, |app| app
        .world()
        .get::<ParticlePositions>(good)
        .is_some_and(|p| p.step >= 50)));
    let p = app.world().get::<ParticlePositions>(good).unwrap();
    assert!(p.positions.iter().all(|x| x.is_finite()));
}

#[test]
fn a_body_too_big_for_the_adapter_is_a_clear_error() {
    let _one = ONE_APP.lock().unwrap_or_else(|e| e.into_inner());
    if !gpu_available() {
        return;
    }
    let mut limits = bevy_tissue::gpu::headless().unwrap().device.limits();
    limits.max_storage_buffer_binding_size = 256 * 1024;
    let mut app = app(WgpuSettings {
        constrained_limits: Some(limits),
        ..default()
    });
    let big = spawn_body(
        &mut app,
        Vec3::ZERO,
        SoftBody {
            resolution: TissueResolution::Particles(3000),
            neighbours: 8,
            discretisation: TissueDiscretisation::Clusters,
            material: TissueMaterial::ShapeMatching { stiffness: 1.0 },
            ..default()
        },
        None,
    );
    let mut errors: Vec<SoftBodyError> = Vec::new();
    until_collecting(&mut app, 600, &mut errors, |_, errors| !errors.is_empty());
    let e = errors
        .iter()
        .find(|m| m.entity == big)
        .expect("an error for the big body");
    assert!(e.error.contains("too big for the GPU"), "{}", e.error);
}

#[test]
fn changing_k_rebuilds_and_removing_the_component_stops_the_simulation() {
    let _one = ONE_APP.lock().unwrap_or_else(|e| e.into_inner());
    if !gpu_available() {
        return;
    }
    let mut app = app(WgpuSettings::default());
    let (body, pinned) = body_spec();
    let e = spawn_body(&mut app, Vec3::ZERO, body, Some(pinned));
    let other = spawn_body(&mut app, Vec3::new(1.0, 0.0, 0.0), body_spec().0, None);
    let ready = |app: &mut App, e: Entity| {
        matches!(
            app.world().get::<SoftBodyStatus>(e),
            Some(SoftBodyStatus::Ready { .. })
        )
    };
    assert!(until(&mut app, 600, |app| ready(app, e) && ready(app, other)));
    // The particles of the world's bodies that are not retired.
    let particles = |app: &App| {
        app.sub_app(RenderApp)
            .world()
            .resource::<TissueGpu>()
            .world()
            .map(|w| {
                (0..w.ranges.len())
                    .filter(|&i| !w.is_retired(i))
                    .map(|i| w.ranges[i].count)
                    .sum::<u32>()
            })
    };
    let rebuilds = |app: &App| {
        app.sub_app(RenderApp)
            .world()
            .resource::<TissueGpu>()
            .rebuilds()
    };
    assert!(until(&mut app, 10, |app| particles(app).is_some()));
    let before = particles(&app).unwrap();
    // Let it sag, pause, and note the pose.
    {
        let mut clock = app.world_mut().resource_mut::<TissueClock>();
        clock.paused = false;
        clock.fixed_steps_per_frame = Some(10);
    }
    for _ in 0..6 {
        app.update();
    }
    app.world_mut().resource_mut::<TissueClock>().paused = true;
    app.update();
    let read = |app: &mut App| {
        app.world_mut().entity_mut(e).remove::<ParticlePositions>();
        app.world_mut()
            .entity_mut(e)
            .insert(ReadbackParticles::default());
        assert!(until(app, 30, |app| app
            .world()
            .get::<ParticlePositions>(e)
            .is_some()));
        app.world()
            .get::<ParticlePositions>(e)
            .unwrap()
            .positions
            .clone()
    };
    let sagged = read(&mut app);
    let rest = app.world().get::<BuiltBody>(e).unwrap().model.placed_rest();
    let sag = sagged
        .iter()
        .zip(&rest)
        .map(|(a, b)| a.distance(*b))
        .fold(0.0f32, f32::max);
    assert!(sag > 1e-3, "the body must have moved ({sag} m)");
    let gen0 = app.world().get::<BuiltBody>(e).unwrap().generation;
    app.world_mut().get_mut::<SoftBody>(e).unwrap().neighbours = 8;
    assert!(until(&mut app, 600, |app| app
        .world()
        .get::<BuiltBody>(e)
        .is_some_and(
            |b| b.generation == gen0 + 1 && b.model.bodies[0].neighbours == 8
        )));
    app.update();
    app.update();
    assert_eq!(
        particles(&app),
        Some(before),
        "same particles, new clusters"
    );
    // The rebuilt body keeps its pose (paused: exactly).
    let after = read(&mut app);
    assert_eq!(after, sagged, "the rebuild lost the body's pose");
    // (New clusters: the body is appended anew and its old slot retired; with two bodies
    // that retires a third of the particles, so the world is compacted, made again.)
    let made = rebuilds(&app);
    let gen1 = gen0 + 1;
    // A new stiffness only: replaced in place, pose kept, the world not made again.
    app.world_mut().get_mut::<SoftBody>(e).unwrap().material =
        TissueMaterial::ShapeMatching { stiffness: 0.2 };
    assert!(until(&mut app, 600, |app| app
        .world()
        .get::<BuiltBody>(e)
        .is_some_and(|b| b.generation == gen1 + 1)));
    app.update();
    app.update();
    assert_eq!(
        read(&mut app),
        sagged,
        "a new stiffness lost the body's pose"
    );
    assert_eq!(rebuilds(&app), made, "a new stiffness made the world again");
    assert_eq!(particles(&app), Some(before));
    // Removing the component drops the body from the GPU world.
    app.world_mut().entity_mut(e).remove::<SoftBody>();
    let other_count = app
        .world()
        .get::<BuiltBody>(other)
        .unwrap()
        .model
        .particle_count() as u32;
    assert!(until(&mut app, 10, |app| particles(app) == Some(other_count)));
}

#[test]
fn a_diverging_body_is_put_back_at_rest_reported_and_the_others_simulate_on() {
    let _one = ONE_APP.lock().unwrap_or_else(|e| e.into_inner());
    if !gpu_available() {
        return;
    }
    let mut app = app(WgpuSettings::default());
    // Nearly incompressible and very stiff, dropped hard onto the ground: too stiff for
    // 10 Jacobi iterations at 1/60 s.
    let wild = spawn_body(
        &mut app,
        Vec3::new(0.0, 0.3, 0.0),
        SoftBody {
            resolution: TissueResolution::Particles(400),
            neighbours: 16,
            material: TissueMaterial::Hyperelastic {
                youngs_modulus: 1.0e9,
                poisson_ratio: 0.499,
            },
            discretisation: TissueDiscretisation::Clusters,
            ..default()
        },
        None,
    );
    let (calm, pinned) = body_of(SHAPE);
    let calm = spawn_body(&mut app, Vec3::new(2.0, 0.5, 0.0), calm, Some(pinned));
    app.world_mut()
        .spawn(TissueCollider::new(ColliderKind::Plane));
    {
        let mut clock = app.world_mut().resource_mut::<TissueClock>();
        clock.paused = false;
        clock.fixed_steps_per_frame = Some(4);
    }
    app.world_mut()
        .entity_mut(calm)
        .insert(ReadbackParticles { continuous: true });
    let mut errors: Vec<SoftBodyError> = Vec::new();
    until_collecting(&mut app, 200, &mut errors, |app, _| {
        app.world()
            .get::<ParticlePositions>(calm)
            .is_some_and(|p| p.step >= 300)
    });
    // Put back at rest (and reported) up to MAX_RECOVERIES times, then left held with
    // one last report: this body diverges every time.
    let wild_errors: Vec<_> = errors.iter().filter(|m| m.entity == wild).collect();
    let max = bevy_tissue::plugin::render::MAX_RECOVERIES as usize;
    assert_eq!(wild_errors.len(), max + 1, "{errors:?}");
    for (i, m) in wild_errors.iter().enumerate() {
        assert!(m.error.contains("diverged"), "{}", m.error);
        let expected = if i < max {
            "put back at rest"
        } else {
            "left held"
        };
        assert!(m.error.contains(expected), "report {i}: {}", m.error);
    }
    assert!(errors.iter().all(|m| m.entity != calm), "{errors:?}");
    let p = app.world().get::<ParticlePositions>(calm).unwrap();
    assert!(p.positions.iter().all(|x| x.is_finite() && x.y > 0.3));
}

#[test]
fn gpu_passes_are_reported_through_render_diagnostics() {
    let _one = ONE_APP.lock().unwrap_or_else(|e| e.into_inner());
    if !gpu_available() {
        return;
    }
    let mut app = app_with(WgpuSettings::default(), |app| {
        app.add_plugins(bevy::render::diagnostic::RenderDiagnosticsPlugin);
    });
    let (body, pinned) = body_spec();
    spawn_body(&mut app, Vec3::ZERO, body, Some(pinned));
    {
        let mut clock = app.world_mut().resource_mut::<TissueClock>();
        clock.paused = false;
        clock.fixed_steps_per_frame = Some(2);
    }
    let has = |app: &App, name: &str| {
        app.world()
            .resource::<bevy::diagnostic::DiagnosticsStore>()
            .iter()
            .any(|d| d.path().as_str().starts_with(name) && d.measurement().is_some())
    };
    let found = until(&mut app, 600, |app| {
        [
            "render/tissue/clusters",
            "render/tissue/gather",
            "render/tissue/skin",
        ]
        .iter()
        .all(|n| has(app, n))
    });
    let paths: Vec<String> = app
        .world()
        .resource::<bevy::diagnostic::DiagnosticsStore>()
        .iter()
        .map(|d| d.path().as_str().to_string())
        .collect();
    assert!(
        found,
        "tissue passes missing from the render diagnostics: {paths:?}"
    );
}

#[test]
fn more_colliders_than_the_gpu_takes_are_capped_not_fatal() {
    let _one = ONE_APP.lock().unwrap_or_else(|e| e.into_inner());
    if !gpu_available() {
        return;
    }
    let mut app = app(WgpuSettings::default());
    // The ground first (the first-spawned colliders are kept), then 200 far-away spheres.
    app.world_mut()
        .spawn(TissueCollider::new(ColliderKind::Plane));
    for i in 0..200 {
        app.world_mut().spawn((
            TissueCollider::new(ColliderKind::Sphere { radius: 0.01 }),
            Transform::from_xyz(10.0 + i as f32, 0.0, 0.0),
        ));
    }
    let (body, _) = body_of(SHAPE);
    let e = spawn_body(&mut app, Vec3::new(0.0, 0.1, 0.0), body, None);
    {
        let mut clock = app.world_mut().resource_mut::<TissueClock>();
        clock.paused = false;
        clock.fixed_steps_per_frame = Some(5);
    }
    app.world_mut()
        .entity_mut(e)
        .insert(ReadbackParticles { continuous: true });
    assert!(until(&mut app, 400, |app| app
        .world()
        .get::<ParticlePositions>(e)
        .is_some_and(|p| p.step >= 120)));
    let rw = app.sub_app(RenderApp).world();
    let world = rw.resource::<TissueGpu>().world().unwrap();
    assert_eq!(world.collider_count(), 128);
    // The body fell 2 s onto the ground and rests on it (the plane acts).
    let p = app.world().get::<ParticlePositions>(e).unwrap();
    let lowest = p.positions.iter().map(|x| x.y).fold(f32::MAX, f32::min);
    assert!(
        (-0.01..0.05).contains(&lowest),
        "lowest particle at y = {lowest} m"
    );
}

#[test]
fn a_body_with_a_hierarchy_matches_the_cpu_hierarchy() {
    // The plugin path of hierarchical PBD: SoftBody::hierarchy → coarse levels in the
    // batched GPU world → the same positions as the CPU hierarchy.
    let stiff = TissueMaterial::Hyperelastic {
        youngs_modulus: 1.0e6,
        poisson_ratio: 0.3,
    };
    let auto = TissueHierarchy::Auto;
    assert_eq!(auto.to_core(19_999, &stiff), None);
    assert!(auto.to_core(20_000, &stiff).is_some());
    assert_eq!(auto.to_core(50_000, &HYPER), None, "soft bodies stay flat");
    assert_eq!(auto.to_core(50_000, &SHAPE), None);
    assert_eq!(TissueHierarchy::Off.to_core(100_000, &stiff), None);
    let _one = ONE_APP.lock().unwrap_or_else(|e| e.into_inner());
    if !gpu_available() {
        return;
    }
    let mut app = app(WgpuSettings::default());
    let at = Vec3::new(0.0, 0.5, 0.0);
    let (mut body, pinned) = body_of(HYPER);
    body.hierarchy = TissueHierarchy::Levels {
        levels: 2,
        parents: 3,
    };
    let e = spawn_body(&mut app, at, body.clone(), Some(pinned.clone()));
    assert!(
        until(&mut app, 600, |app| matches!(
            app.world().get::<SoftBodyStatus>(e),
            Some(SoftBodyStatus::Ready { .. })
        )),
        "the body never became ready"
    );
    let got = step_and_read(&mut app, e, 5);
    assert_eq!(got.step, 100);
    let settings = app.world().resource::<TissueSettings>().clone();
    let (model, cpu) = cpu_reference_of(body, pinned, at, got.step, &settings);
    assert_eq!(model.levels.len(), 1, "the body must have one coarse level");
    let size = model.bodies[0].size;
    let d = got
        .positions
        .iter()
        .zip(&cpu)
        .map(|(a, b)| a.distance(*b))
        .fold(0.0f32, f32::max);
    let moved = cpu
        .iter()
        .zip(&model.placed_rest())
        .map(|(a, b)| a.distance(*b))
        .fold(0.0f32, f32::max);
    eprintln!("hierarchical body: GPU–CPU {d:.2e} m after 100 steps, moved {moved:.2e} m");
    assert!(moved > 0.01 * size, "the body must deform ({moved} m)");
    assert!(
        d < 1e-4 * size,
        "GPU and CPU differ by {d} m (size {size} m)"
    );
}

/// Updates until the body's `Sleeping` marker is `asleep` (at most `max` frames).
fn until_asleep(app: &mut App, e: Entity, asleep: bool, max: u32) -> bool {
    until(app, max, |app| {
        app.world().get::<Sleeping>(e).is_some() == asleep
    })
}

/// Steps the GPU world has taken.
fn gpu_steps(app: &App) -> u64 {
    let rw = app.sub_app(RenderApp).world();
    rw.resource::<TissueGpu>().world().map_or(0, |w| w.step)
}

/// Reads the body's particles once.
fn read_now(app: &mut App, e: Entity) -> ParticlePositions {
    app.world_mut().entity_mut(e).remove::<ParticlePositions>();
    app.world_mut()
        .entity_mut(e)
        .insert(ReadbackParticles::default());
    assert!(
        until(app, 30, |app| app
            .world()
            .get::<ParticlePositions>(e)
            .is_some()),
        "no readback arrived"
    );
    app.world().get::<ParticlePositions>(e).unwrap().clone()
}

#[test]
fn a_body_at_rest_sleeps_without_gpu_work_and_wakes_on_settings_and_contact() {
    let _one = ONE_APP.lock().unwrap_or_else(|e| e.into_inner());
    if !gpu_available() {
        return;
    }
    let mut app = app(WgpuSettings::default());
    app.insert_resource(TissueSleep {
        speed: 0.01,
        frames: 5,
        margin: 0.02,
        ..default()
    });
    app.world_mut()
        .spawn(TissueCollider::new(ColliderKind::Plane));
    let (body, _) = body_of(SHAPE);
    // The box is 5 cm tall: it drops 5 mm onto the ground and comes to rest.
    let e = spawn_body(&mut app, Vec3::new(0.0, 0.03, 0.0), body, None);
    {
        let mut clock = app.world_mut().resource_mut::<TissueClock>();
        clock.paused = false;
        clock.fixed_steps_per_frame = Some(5);
    }
    assert!(
        until_asleep(&mut app, e, true, 300),
        "the body never fell asleep (motion {:?})",
        app.world().get::<BodyMotion>(e)
    );
    let speed = app.world().get::<BodyMotion>(e).unwrap().max_speed;
    assert!(speed < 0.01, "asleep while moving at {speed} m/s");

    // Asleep: no step is recorded and the particles do not move at all.
    let a = read_now(&mut app, e);
    let steps = gpu_steps(&app);
    for _ in 0..10 {
        app.update();
    }
    let b = read_now(&mut app, e);
    assert_eq!(
        gpu_steps(&app),
        steps,
        "steps were recorded for a sleeping world"
    );
    let rw = app.sub_app(RenderApp).world();
    assert_eq!(rw.resource::<TissueGpu>().stats().steps, 0);
    assert_eq!(a.positions, b.positions, "a sleeping body moved");
    assert!(app.world().get::<Sleeping>(e).is_some());

    // A settings change wakes it; it falls asleep again.
    app.world_mut().resource_mut::<TissueSettings>().damping = 2.0;
    assert!(
        until_asleep(&mut app, e, false, 3),
        "a settings change did not wake it"
    );
    app.update();
    let rw = app.sub_app(RenderApp).world();
    assert_eq!(
        rw.resource::<TissueGpu>().stats().steps,
        5,
        "awake, but no steps"
    );
    assert!(
        until_asleep(&mut app, e, true, 300),
        "it did not fall asleep again"
    );

    // A collider far away, even moving, leaves it asleep...
    let ball = app
        .world_mut()
        .spawn((
            TissueCollider::new(ColliderKind::Sphere { radius: 0.02 }),
            Transform::from_xyz(0.0, 0.3, 0.0),
        ))
        .id();
    for i in 0..5 {
        app.world_mut()
            .entity_mut(ball)
            .insert(Transform::from_xyz(0.01 * i as f32, 0.3, 0.0));
        app.update();
    }
    assert!(
        app.world().get::<Sleeping>(e).is_some(),
        "woken by a far collider"
    );
    // ...one pressed into it wakes it, and the body gives way.
    let before = read_now(&mut app, e);
    app.world_mut()
        .entity_mut(ball)
        .insert(Transform::from_xyz(0.0, 0.025, 0.0));
    assert!(
        until_asleep(&mut app, e, false, 3),
        "a collider pressing in did not wake it"
    );
    for _ in 0..10 {
        app.update();
    }
    let after = read_now(&mut app, e);
    let moved = before
        .positions
        .iter()
        .zip(&after.positions)
        .map(|(p, q)| p.distance(*q))
        .fold(0.0, f32::max);
    assert!(moved > 1e-3, "the woken body did not give way ({moved} m)");
}

/// A device with WebGPU's default limits (8 storage buffers per stage) cannot run the
/// kernels as they are bound today: the plugin says so once, moves every body to the
/// CPU (`TissueBackend::Cpu`) and the body simulates there, exactly as the core does.
/// Spawns a body with continuous read-back and updates until it steps from the main
/// world (`plugin::cpu`).
fn spawn_on_main_world_path(
    app: &mut App,
    at: Vec3,
    body: SoftBody,
    pinned: Option<Pinned>,
) -> Entity {
    let e = spawn_body(app, at, body, pinned);
    app.world_mut()
        .entity_mut(e)
        .insert(ReadbackParticles { continuous: true });
    let built = until(app, 600, |app| {
        app.world()
            .get::<bevy_tissue::plugin::cpu::CpuBody>(e)
            .is_some()
    });
    assert!(built, "the body never reached the main world's path");
    e
}

/// Unpauses the clock at one step a frame.
fn run_one_step_a_frame(app: &mut App) {
    let mut clock = app.world_mut().resource_mut::<TissueClock>();
    clock.paused = false;
    clock.fixed_steps_per_frame = Some(1);
}

/// Takes one step a frame for `frames` frames, then pauses.
fn step_frames(app: &mut App, frames: u32) {
    run_one_step_a_frame(app);
    for _ in 0..frames {
        app.update();
    }
    app.world_mut().resource_mut::<TissueClock>().paused = true;
    app.update();
}

#[test]
fn the_cpu_takes_over_where_the_gpu_cannot_run_the_kernels() {
    let _one = ONE_APP.lock().unwrap_or_else(|e| e.into_inner());
    if !gpu_available() {
        return;
    }
    // 8 KiB of workgroup memory: less than the render graph's kernels use (Bevy's own
    // pipelines run with it).
    let mut app = app(WgpuSettings {
        constrained_limits: Some(bevy::render::settings::WgpuLimits {
            max_compute_workgroup_storage_size: 8 * 1024,
            ..default()
        }),
        ..default()
    });
    let (body, pinned) = body_spec();
    let at = Vec3::new(0.0, 0.5, 0.0);
    let e = spawn_on_main_world_path(&mut app, at, body, Some(pinned));
    assert_eq!(
        app.world().resource::<TissueSettings>().backend,
        TissueBackend::Cpu
    );
    step_frames(&mut app, 20);
    let read = app.world().get::<ParticlePositions>(e).unwrap().clone();
    let settings = app.world().resource::<TissueSettings>().clone();
    let steps = app
        .world()
        .resource::<bevy_tissue::plugin::cpu::CpuWorld>()
        .state()
        .unwrap()
        .step;
    // The core, stepped as often with the CPU path's settings, lands on the same particles.
    let (body, pinned) = body_spec();
    let (model, x) = common::cpu_path_reference(&body, &pinned, &box_mesh(), at, &settings, steps);
    assert!(steps >= 20, "{steps} steps");
    let worst = common::max_distance(&read.positions, &x);
    assert!(worst < 1e-6, "plugin and core differ by {worst} m");
    let sag = common::max_sag(&x, &model.rest);
    assert!(sag > 1e-4, "the body did not move: {sag} m");
}

/// Two lattice bodies touching each other step on the GPU: the upper one, dropped onto
/// the lower (held whole) one, rests on it through particle contacts instead of passing
/// through (the scene of the CPU backend's `cpu_bodies_touch_each_other`), at the
/// default `knn_every` of 10: the contacts are searched again whenever particles may
/// move out of the last search's reach.
#[test]
fn lattice_bodies_touch_each_other_on_the_gpu() {
    let _one = ONE_APP.lock().unwrap_or_else(|e| e.into_inner());
    if !gpu_available() {
        return;
    }
    let mut app = app(WgpuSettings::default());
    assert_eq!(app.world().resource::<TissueSettings>().knn_every, 10);
    let (body, _) = common::lattice_body();
    // The lower body held whole (every particle pinned): a fixed shelf.
    let shelf = Pinned::region(PinShape::HalfSpace {
        point: Vec3::new(0.0, 1.0, 0.0),
        normal: -Vec3::Y,
    });
    let low = spawn_on_main_world_path(&mut app, Vec3::ZERO, body.clone(), Some(shelf));
    // 10 cm above: a gap of about 4 cm between the 5 cm boxes' lattices.
    let high = spawn_on_main_world_path(&mut app, Vec3::new(0.0, 0.10, 0.0), body, None);
    step_frames(&mut app, 60);
    let world = app.world().resource::<bevy_tissue::plugin::cpu::CpuWorld>();
    assert!(
        world.stepped_on_gpu(),
        "the touching bodies stepped on the CPU"
    );
    let state = world.state().unwrap();
    let part = |e: Entity| {
        app.world()
            .get::<bevy_tissue::plugin::cpu::CpuBody>(e)
            .unwrap()
            .particles
            .clone()
    };
    let top_of_low = state.x[part(low)]
        .iter()
        .map(|p| p.y)
        .fold(f32::MIN, f32::max);
    let bottom_of_high = state.x[part(high)]
        .iter()
        .map(|p| p.y)
        .fold(f32::MAX, f32::min);
    assert!(
        bottom_of_high < top_of_low + 0.02,
        "did not fall: {bottom_of_high} m (the lower top {top_of_low} m)"
    );
    assert!(
        bottom_of_high > top_of_low,
        "passed into the lower body: its bottom {bottom_of_high} m, the lower top {top_of_low} m"
    );
    let speed = state.v[part(high)]
        .iter()
        .map(|v| v.length())
        .fold(0.0, f32::max);
    assert!(
        speed < 0.2,
        "the upper body settles (fastest particle {speed} m/s)"
    );
    // The contact search's time was measured on every frame that stepped on the GPU.
    let store = app.world().resource::<bevy::diagnostic::DiagnosticsStore>();
    let count =
        |path: &bevy::diagnostic::DiagnosticPath| store.get(path).map_or(0, |d| d.history_len());
    let steps = count(&TissueDiagnostics::STEP);
    assert!(steps > 0, "no step times");
    assert_eq!(count(&TissueDiagnostics::CONTACTS), steps);
    let contacts = store.get(&TissueDiagnostics::CONTACTS).unwrap();
    assert!(contacts.values().all(|ms| ms.is_finite() && *ms >= 0.0));
}

/// On a device held to WebGPU's default limits (8 storage buffers per stage, 16 KiB of
/// workgroup memory, 256 invocations), every body steps on the GPU: a lattice body (the
/// default, `GpuLattice`) and a cluster body (the render graph's kernels, whose layouts
/// hold only what each kernel uses), and the world stays on `TissueBackend::Auto`.
#[test]
fn every_body_steps_on_the_gpu_under_webgpu_limits() {
    let _one = ONE_APP.lock().unwrap_or_else(|e| e.into_inner());
    if !gpu_available() {
        return;
    }
    let mut app = app(WgpuSettings {
        constrained_limits: Some(bevy::render::settings::WgpuLimits::default()),
        ..default()
    });
    let (body, pinned) = common::lattice_body();
    spawn_on_main_world_path(&mut app, Vec3::new(0.0, 0.3, 0.0), body, Some(pinned));
    let (clusters, pinned) = body_spec();
    let c = spawn_body(&mut app, Vec3::new(0.5, 0.3, 0.0), clusters, Some(pinned));
    app.world_mut()
        .entity_mut(c)
        .insert(ReadbackParticles { continuous: true });
    run_one_step_a_frame(&mut app);
    assert!(
        until(&mut app, 120, |app| app
            .world()
            .get::<ParticlePositions>(c)
            .is_some_and(|p| p.step >= 10)),
        "the cluster body did not step"
    );
    assert_eq!(
        app.world().resource::<TissueSettings>().backend,
        TissueBackend::Auto,
        "the world was switched to the CPU"
    );
    let world = app.world().resource::<bevy_tissue::plugin::cpu::CpuWorld>();
    assert!(
        world.stepped_on_gpu(),
        "the lattice body stepped on the CPU"
    );
    assert!(world.state().unwrap().step >= 10);
    let p = app.world().get::<ParticlePositions>(c).unwrap();
    assert!(p.positions.iter().all(|x| x.is_finite()));
}

/// A lattice body steps on the GPU (Newton–multigrid, `GpuLattice`) from the plugin and
/// lands where the core's CPU solver does with the same settings.
#[test]
fn a_lattice_body_steps_on_the_gpu_like_the_core() {
    let _one = ONE_APP.lock().unwrap_or_else(|e| e.into_inner());
    if !gpu_available() {
        return;
    }
    let mut app = app(WgpuSettings::default());
    let (body, pinned) = common::lattice_body();
    let at = Vec3::new(0.0, 0.3, 0.0);
    let e = spawn_on_main_world_path(&mut app, at, body.clone(), Some(pinned.clone()));
    step_frames(&mut app, 30);
    let world = app.world().resource::<bevy_tissue::plugin::cpu::CpuWorld>();
    assert!(
        world.stepped_on_gpu(),
        "the lattice body stepped on the CPU"
    );
    let steps = world.state().unwrap().step;
    let read = app.world().get::<ParticlePositions>(e).unwrap().clone();
    let settings = app.world().resource::<TissueSettings>().clone();
    let (model, x) = common::cpu_path_reference(&body, &pinned, &box_mesh(), at, &settings, steps);
    let sag = common::max_sag(&x, &model.rest);
    let worst = common::max_distance(&read.positions, &x);
    assert!(steps >= 30 && sag > 1e-4, "{steps} steps, sag {sag} m");
    assert!(
        worst <= 1e-4 * sag + 1e-6,
        "plugin (GPU) and core (CPU) differ by {worst} m of {sag} m"
    );
}

/// Changing gravity rebuilds neither world: the render graph's (a cluster body) and the
/// main world's (a lattice body on the GPU) take it as a parameter. The bodies feel it:
/// with gravity turned upwards, both rise above where they hung, which they cannot do
/// under the old gravity. A new time step and substeps rebuild neither either, and the
/// lattice body steps on, on the GPU.
#[test]
fn gravity_and_the_time_step_change_without_a_rebuild() {
    let _one = ONE_APP.lock().unwrap_or_else(|e| e.into_inner());
    if !gpu_available() {
        return;
    }
    let mut app = app(WgpuSettings::default());
    let (body, pinned) = common::lattice_body();
    let l = spawn_on_main_world_path(&mut app, Vec3::new(0.0, 0.3, 0.0), body, Some(pinned));
    // Shape matching: the hyperelastic clusters under Jacobi diverge when gravity turns
    // over (with a rebuild as without one).
    let (clusters, pinned) = body_of(TissueMaterial::ShapeMatching { stiffness: 0.5 });
    let c = spawn_body(&mut app, Vec3::new(0.5, 0.3, 0.0), clusters, Some(pinned));
    app.world_mut()
        .entity_mut(c)
        .insert(ReadbackParticles { continuous: true });
    run_one_step_a_frame(&mut app);
    let mean_y = |app: &App, e: Entity| -> Option<(f32, u64)> {
        let p = app.world().get::<ParticlePositions>(e)?;
        let n = p.positions.len().max(1) as f32;
        Some((p.positions.iter().map(|x| x.y).sum::<f32>() / n, p.step))
    };
    assert!(
        until(&mut app, 200, |app| mean_y(app, c)
            .is_some_and(|m| m.1 >= 1)
            && mean_y(app, l).is_some()),
        "the bodies did not step"
    );
    // Both boxes are centred where they were spawned: their particles' mean height at
    // rest is 0.3 m. Averaged over 30 frames (the bodies swing), under gravity they hang
    // below it.
    let rest = 0.3;
    let average = |app: &mut App| -> [f32; 2] {
        let mut sum = [0.0; 2];
        for _ in 0..30 {
            app.update();
            sum[0] += mean_y(app, l).unwrap().0 / 30.0;
            sum[1] += mean_y(app, c).unwrap().0 / 30.0;
        }
        sum
    };
    for _ in 0..30 {
        app.update();
    }
    let hung = average(&mut app);
    for (i, y) in hung.iter().enumerate() {
        assert!(*y < rest - 1e-4, "body {i} did not hang: {hung:?}");
    }
    let gpu_rebuilds = app
        .sub_app(RenderApp)
        .world()
        .resource::<TissueGpu>()
        .rebuilds();
    let cpu_rebuilds = app
        .world()
        .resource::<bevy_tissue::plugin::cpu::CpuWorld>()
        .rebuilds();
    app.world_mut().resource_mut::<TissueSettings>().gravity = Vec3::new(0.0, 9.81, 0.0);
    for _ in 0..30 {
        app.update();
    }
    let risen = average(&mut app);
    for (i, y) in risen.iter().enumerate() {
        assert!(
            *y > rest + 1e-4,
            "body {i} did not rise: hung {hung:?}, now {risen:?}"
        );
    }
    let world = app.world().resource::<bevy_tissue::plugin::cpu::CpuWorld>();
    assert!(world.stepped_on_gpu(), "the lattice body left the GPU");
    assert_eq!(
        world.rebuilds(),
        cpu_rebuilds,
        "the lattice world was rebuilt"
    );
    let gpu = app.sub_app(RenderApp).world().resource::<TissueGpu>();
    assert_eq!(
        gpu.rebuilds(),
        gpu_rebuilds,
        "the render graph's world was rebuilt"
    );
    // A new time step and substeps: parameters and plans too, in both worlds.
    let step = |app: &App| {
        app.world()
            .resource::<bevy_tissue::plugin::cpu::CpuWorld>()
            .state()
            .map_or(0, |s| s.step)
    };
    let before = step(&app);
    {
        let mut s = app.world_mut().resource_mut::<TissueSettings>();
        s.dt = 1.0 / 90.0;
        s.substeps = 2;
    }
    for _ in 0..20 {
        app.update();
    }
    let world = app.world().resource::<bevy_tissue::plugin::cpu::CpuWorld>();
    assert!(world.stepped_on_gpu(), "the lattice body left the GPU");
    assert!(step(&app) >= before + 10, "the lattice body stopped");
    assert_eq!(
        world.rebuilds(),
        cpu_rebuilds,
        "a new dt rebuilt the lattice world"
    );
    assert!(
        world.state().unwrap().x.iter().all(|p| p.is_finite()),
        "the lattice body diverged"
    );
    let gpu = app.sub_app(RenderApp).world().resource::<TissueGpu>();
    assert_eq!(
        gpu.rebuilds(),
        gpu_rebuilds,
        "a new dt rebuilt the render graph's world"
    );
}

/// Despawning a body retires it in the render graph's world instead of rebuilding it:
/// the other bodies step on with their state, and the world is not rebuilt.
#[test]
fn despawning_or_spawning_a_body_does_not_rebuild_the_world() {
    let _one = ONE_APP.lock().unwrap_or_else(|e| e.into_inner());
    if !gpu_available() {
        return;
    }
    let mut app = app(WgpuSettings::default());
    let mut bodies = Vec::new();
    for x in [-0.5, 0.0, 0.5, 1.0] {
        let (b, pinned) = body_of(TissueMaterial::ShapeMatching { stiffness: 0.5 });
        let e = spawn_body(&mut app, Vec3::new(x, 0.3, 0.0), b, Some(pinned));
        app.world_mut()
            .entity_mut(e)
            .insert(ReadbackParticles { continuous: true });
        bodies.push(e);
    }
    run_one_step_a_frame(&mut app);
    let step = |app: &App, e: Entity| app.world().get::<ParticlePositions>(e).map(|p| p.step);
    assert!(
        until(&mut app, 200, |app| bodies
            .iter()
            .all(|&e| step(app, e).is_some_and(|s| s >= 5))),
        "the bodies did not step"
    );
    let rebuilds = app
        .sub_app(RenderApp)
        .world()
        .resource::<TissueGpu>()
        .rebuilds();
    let before = step(&app, bodies[0]).unwrap();
    app.world_mut().entity_mut(bodies[1]).despawn();
    for _ in 0..20 {
        app.update();
    }
    let gpu = app.sub_app(RenderApp).world().resource::<TissueGpu>();
    assert_eq!(
        gpu.rebuilds(),
        rebuilds,
        "the world was rebuilt for a despawn"
    );
    let world = gpu.world().expect("world");
    assert!(world.is_retired(1), "the despawned body is retired");
    for &e in [bodies[0], bodies[2], bodies[3]].iter() {
        let p = app.world().get::<ParticlePositions>(e).unwrap();
        assert!(p.step >= before + 10, "body {e} stopped: step {}", p.step);
        assert!(p.positions.iter().all(|x| x.is_finite() && x.y < 1.0));
    }
    // A spawned body is appended into the world's room: no rebuild, and it steps (it
    // sags from its pins) while the others go on.
    let (b, pinned) = body_of(TissueMaterial::ShapeMatching { stiffness: 0.5 });
    let new = spawn_body(&mut app, Vec3::new(1.5, 0.3, 0.0), b, Some(pinned));
    app.world_mut()
        .entity_mut(new)
        .insert(ReadbackParticles { continuous: true });
    let now = step(&app, bodies[0]).unwrap();
    assert!(
        until(&mut app, 200, |app| step(app, new).is_some()),
        "the spawned body did not step"
    );
    let first = app.world().get::<ParticlePositions>(new).unwrap().clone();
    assert!(
        until(&mut app, 200, |app| step(app, new)
            .is_some_and(|s| s >= first.step + 20)),
        "the spawned body stopped"
    );
    let gpu = app.sub_app(RenderApp).world().resource::<TissueGpu>();
    assert_eq!(
        gpu.rebuilds(),
        rebuilds,
        "the world was rebuilt for a spawn"
    );
    assert_eq!(gpu.world().expect("world").ranges.len(), 5, "appended");
    let p = app.world().get::<ParticlePositions>(new).unwrap();
    assert!(p.positions.iter().all(|x| x.is_finite()));
    let moved = p
        .positions
        .iter()
        .zip(&first.positions)
        .map(|(a, b)| a.distance(*b))
        .fold(0.0f32, f32::max);
    assert!(moved > 1e-5, "sags from its pins: moved {moved} m");
    assert!(
        step(&app, bodies[0]).unwrap() >= now + 20,
        "the others go on"
    );
    // More at once than the room holds: it grows on the GPU, still no rebuild.
    let room = gpu_world_capacity(&app);
    let used = app
        .sub_app(RenderApp)
        .world()
        .resource::<TissueGpu>()
        .world()
        .map_or(0, |w| w.ranges.len() as u32);
    let more: Vec<Entity> = (0..room + 1 - used)
        .map(|i| {
            let x = 2.0 + 0.5 * i as f32;
            let (b, pinned) = body_of(TissueMaterial::ShapeMatching { stiffness: 0.5 });
            let e = spawn_body(&mut app, Vec3::new(x, 0.3, 0.0), b, Some(pinned));
            app.world_mut()
                .entity_mut(e)
                .insert(ReadbackParticles { continuous: true });
            e
        })
        .collect();
    assert!(
        until(&mut app, 300, |app| more
            .iter()
            .all(|&e| step(app, e).is_some())),
        "the bodies spawned past the room did not step"
    );
    let gpu = app.sub_app(RenderApp).world().resource::<TissueGpu>();
    let world = gpu.world().expect("world");
    assert_eq!(
        gpu.rebuilds(),
        rebuilds,
        "the world was rebuilt past its room"
    );
    assert_eq!(world.ranges.len() as u32, room + 1);
    assert!(
        world.capacity().bodies > room,
        "the room grew ({} bodies, was {room})",
        world.capacity().bodies
    );
}

/// Lattice bodies step from the main world, batched into one `GpuLattice`. A body
/// coming is appended into the room of that batch in place (`GpuLattice::append`, no
/// rebuild); past the room the batch is made again, on a worker thread while it steps
/// on, from each body's own multigrid levels, made when the body was built: nobody's
/// levels are coarsened again (`CpuWorld::coarsened_bodies` stays 0). A body rebuilt
/// (a new material) is appended anew in place, keeping its pose. A body going is
/// retired in place: held still, far out of reach, with no
/// rebuild, until retired bodies would hold more than a quarter of the particles (then
/// the batch is made again without them). Through all of it the bodies already there
/// keep their pose and step on, on the GPU, and a new one steps with them.
#[test]
fn lattice_bodies_come_and_go_without_coarsening_or_rebuilding_the_others() {
    let _one = ONE_APP.lock().unwrap_or_else(|e| e.into_inner());
    if !gpu_available() {
        return;
    }
    let mut app = app(WgpuSettings::default());
    let (body, pinned) = common::lattice_body();
    let spawn = |app: &mut App, x: f32| {
        spawn_on_main_world_path(
            app,
            Vec3::new(x, 0.0, 0.0),
            body.clone(),
            Some(pinned.clone()),
        )
    };
    let a = spawn(&mut app, 0.0);
    let b = spawn(&mut app, 0.5);
    step_frames(&mut app, 10);
    fn cpu(app: &App) -> &bevy_tissue::plugin::cpu::CpuWorld {
        app.world().resource::<bevy_tissue::plugin::cpu::CpuWorld>()
    }
    let marker = |app: &App, e: Entity| {
        app.world()
            .get::<bevy_tissue::plugin::cpu::CpuBody>(e)
            .expect("a main-world body")
            .clone()
    };
    let pose = |app: &App, e: Entity| {
        let range = marker(app, e).particles;
        cpu(app).state().expect("a state").x[range].to_vec()
    };
    let rebuilds = cpu(&app).rebuilds();
    let sagged = pose(&app, a);
    let step = cpu(&app).state().unwrap().step;
    // Three more bodies, spawned while the clock is paused. The batch of two has room
    // for four: the first two are appended in place, A's pose untouched.
    let c = spawn(&mut app, 1.0);
    let more0 = spawn(&mut app, 1.5);
    assert_eq!(
        cpu(&app).rebuilds(),
        rebuilds,
        "a spawn into the room rebuilt"
    );
    assert_eq!(cpu(&app).appended_in_place(), 2);
    assert_eq!(pose(&app, a), sagged, "the first body lost its pose");
    // The third finds no room: the batch is made again on a worker thread, A's pose
    // carried over exactly.
    let more = [more0, spawn(&mut app, 2.0)];
    assert_eq!(
        cpu(&app).rebuilds(),
        rebuilds + 1,
        "past the room: one rebuild"
    );
    assert_eq!(
        cpu(&app).rebuilds_off_thread(),
        1,
        "the batch stepping on the GPU is rebuilt on a worker thread"
    );
    assert_eq!(
        cpu(&app).gpu_worlds_made_off_thread(),
        1,
        "its GPU world made with it there"
    );
    assert_eq!(cpu(&app).appended_in_place(), 2);
    assert_eq!(cpu(&app).coarsened_bodies(), 0, "levels coarsened again");
    assert_eq!(pose(&app, a), sagged, "the first body lost its pose");
    // The new GPU world takes A's state from the old one by GPU copies: a frame later A
    // is where it sagged to, not back at rest.
    step_frames(&mut app, 1);
    assert_eq!(
        cpu(&app).states_carried_on_gpu(),
        1,
        "the bodies kept took their state from the old GPU world"
    );
    let sag = |x: &[Vec3]| x.iter().map(|p| -p.y).fold(f32::MIN, f32::max);
    let moved = pose(&app, a)
        .iter()
        .zip(&sagged)
        .map(|(p, q)| p.distance(*q))
        .fold(0.0f32, f32::max);
    assert!(
        moved <= 0.2 * sag(&sagged).abs() + 1e-4,
        "the first body moved {moved} m in the frame its state was carried over (it had \
         sagged {} m)",
        sag(&sagged)
    );
    step_frames(&mut app, 9);
    assert!(cpu(&app).stepped_on_gpu(), "the batch stepped on the CPU");
    assert!(cpu(&app).state().unwrap().step >= step + 10);
    // The new body sags from its pins as the first did in its first 10 steps.
    let c_now = pose(&app, c);
    assert!(
        (sag(&c_now) - sag(&sagged)).abs() <= 0.05 * sag(&sagged).abs() + 1e-4,
        "the new body: {} m down, the first after as many steps: {} m",
        sag(&c_now),
        sag(&sagged)
    );
    // B goes (a fifth of the particles): retired in place, no rebuild, the others keep
    // their places in the batch and their pose.
    let rebuilds = cpu(&app).rebuilds();
    let b_index = marker(&app, b).index;
    let b_range = marker(&app, b).particles;
    let (a_marker, a_held) = (marker(&app, a), pose(&app, a));
    app.world_mut().entity_mut(b).despawn();
    for _ in 0..3 {
        app.update();
    }
    assert_eq!(cpu(&app).rebuilds(), rebuilds, "rebuilt for a despawn");
    assert!(cpu(&app).is_retired(b_index));
    assert_eq!(marker(&app, a), a_marker);
    assert_eq!(pose(&app, a), a_held, "the first body lost its pose");
    let held = cpu(&app).state().unwrap().x[b_range.clone()].to_vec();
    let deep = held.iter().map(|p| p.y).fold(f32::MIN, f32::max);
    assert!(deep < -900.0, "the retired body is out of reach: {deep} m");
    let (c_before, step) = (pose(&app, c), cpu(&app).state().unwrap().step);
    step_frames(&mut app, 10);
    assert!(cpu(&app).stepped_on_gpu());
    assert!(cpu(&app).state().unwrap().step >= step + 10);
    assert_eq!(
        cpu(&app).state().unwrap().x[b_range].to_vec(),
        held,
        "the retired body moved"
    );
    let moved = pose(&app, c)
        .iter()
        .zip(&c_before)
        .map(|(p, q)| p.distance(*q))
        .fold(0.0f32, f32::max);
    assert!(moved > 1e-6, "the others stopped: moved {moved} m");
    // Another goes: retired bodies would hold two fifths, so the batch is made again
    // without them (from the bodies' own levels), the rest keeping their pose.
    let c_held = pose(&app, c);
    app.world_mut().entity_mut(more[0]).despawn();
    for _ in 0..3 {
        app.update();
    }
    assert_eq!(cpu(&app).rebuilds(), rebuilds + 1, "not compacted");
    assert_eq!(
        cpu(&app).rebuilds_off_thread(),
        1,
        "compacted on a worker thread"
    );
    assert_eq!(cpu(&app).model().bodies.len(), 3);
    assert!((0..3).all(|i| !cpu(&app).is_retired(i)));
    assert_eq!(cpu(&app).coarsened_bodies(), 0, "levels coarsened again");
    assert_eq!(pose(&app, c), c_held, "a body lost its pose");
    step_frames(&mut app, 5);
    assert!(cpu(&app).stepped_on_gpu());
    assert!(pose(&app, more[1]).iter().all(|p| p.is_finite()));
    // C's material changes: C is rebuilt and appended anew in place, starting from its
    // pose (the same particles), its old slot retired; no rebuild of the batch.
    let (rebuilds, appended) = (cpu(&app).rebuilds(), cpu(&app).appended_in_place());
    let (c_old, c_held) = (marker(&app, c).index, pose(&app, c));
    if let Some(mut body) = app.world_mut().get_mut::<SoftBody>(c) {
        body.material = TissueMaterial::Hyperelastic {
            youngs_modulus: 80_000.0,
            poisson_ratio: 0.4,
        };
    }
    let moved = until(&mut app, 600, |app| marker(app, c).index != c_old);
    assert!(moved, "the rebuilt body never joined the batch");
    assert_eq!(
        cpu(&app).rebuilds(),
        rebuilds,
        "a material change rebuilt the batch"
    );
    assert_eq!(cpu(&app).appended_in_place(), appended + 1);
    assert!(cpu(&app).is_retired(c_old));
    assert_eq!(pose(&app, c), c_held, "the rebuilt body lost its pose");
    step_frames(&mut app, 5);
    assert!(cpu(&app).stepped_on_gpu());
    assert!(pose(&app, c).iter().all(|p| p.is_finite()));
}

/// Bodies the render graph's world has room for.
fn gpu_world_capacity(app: &App) -> u32 {
    app.sub_app(RenderApp)
        .world()
        .resource::<TissueGpu>()
        .world()
        .map_or(0, |w| w.capacity().bodies)
}
