//! The plugin's CPU path in an app without a renderer: a lattice body (hexahedral
//! elements, Newton–multigrid) steps on the CPU and equals the core solver run directly
//! on the same model, its draw mesh holds the CPU skinning of its particles, a forced
//! CPU backend runs a cluster body the same way, and a diverging body is put back at rest
//! with an error that says where, why and what to change.

use bevy::asset::AssetPlugin;
use bevy::diagnostic::{DiagnosticPath, DiagnosticsStore};
use bevy::prelude::*;
use bevy_tissue::core::model::Model;
use bevy_tissue::plugin::build::BuiltBody;
use bevy_tissue::plugin::cpu::{CpuBody, CpuWorld};
use bevy_tissue::prelude::*;
mod common;

/// An app with the plugin and no render sub-app; the clock takes exactly one step per
/// frame once unpaused.
fn app(settings: TissueSettings) -> App {
    let mut app = App::new();
    app.add_plugins((
        MinimalPlugins,
        AssetPlugin::default(),
        TransformPlugin,
        TissuePlugin { settings },
    ))
    .init_asset::<Mesh>();
    app.world_mut().resource_mut::<TissueClock>().paused = true;
    app.finish();
    app.cleanup();
    app
}

fn box_mesh() -> Mesh {
    Cuboid::new(0.12, 0.05, 0.05).mesh().build()
}

fn spawn(app: &mut App, at: Vec3, body: SoftBody, pinned: Pinned) -> Entity {
    let mesh = app
        .world_mut()
        .resource_mut::<Assets<Mesh>>()
        .add(box_mesh());
    app.world_mut()
        .spawn((
            Mesh3d(mesh),
            Transform::from_translation(at),
            body,
            pinned,
            ReadbackParticles { continuous: true },
        ))
        .id()
}

/// Updates until the body is built (at most 200 frames).
fn until_built(app: &mut App, e: Entity) {
    for _ in 0..200 {
        app.update();
        if app.world().get::<BuiltBody>(e).is_some() && app.world().get::<CpuBody>(e).is_some() {
            return;
        }
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    panic!("body not built: {:?}", app.world().get::<SoftBodyStatus>(e));
}

/// Takes `steps` steps (one per frame) and returns the body's particle positions.
fn run(app: &mut App, e: Entity, steps: u32) -> ParticlePositions {
    {
        let mut clock = app.world_mut().resource_mut::<TissueClock>();
        clock.paused = false;
        clock.fixed_steps_per_frame = Some(1);
    }
    for _ in 0..steps {
        app.update();
    }
    app.world_mut().resource_mut::<TissueClock>().paused = true;
    app.update();
    app.world()
        .get::<ParticlePositions>(e)
        .expect("particle positions")
        .clone()
}

/// The same body built and stepped on the core directly with the CPU path's settings.
fn core_reference(
    body: &SoftBody,
    pinned: &Pinned,
    at: Vec3,
    settings: &TissueSettings,
    steps: u32,
) -> (Model, Vec<Vec3>) {
    common::cpu_path_reference(body, pinned, &box_mesh(), at, settings, steps as u64)
}

#[test]
fn a_lattice_body_steps_on_the_cpu_like_the_core_and_is_drawn() {
    let settings = TissueSettings::default();
    let mut app = app(settings.clone());
    let at = Vec3::new(0.0, 0.3, 0.0);
    let (body, pinned) = common::lattice_body();
    let e = spawn(&mut app, at, body.clone(), pinned.clone());
    until_built(&mut app, e);
    let built = app.world().get::<BuiltBody>(e).unwrap().clone();
    assert!(
        !built.model.elements.is_empty(),
        "a lattice body has elements"
    );
    let read = run(&mut app, e, 30);
    let (model, x) = core_reference(&body, &pinned, at, &settings, 30);
    assert_eq!(read.positions.len(), x.len());
    let worst = common::max_distance(&read.positions, &x);
    assert!(worst < 1e-6, "plugin and core differ by {worst} m");
    // It moved (the free end sags under gravity) and stayed finite.
    let sag = common::max_sag(&x, &model.rest);
    assert!(sag > 1e-4, "no sag: {sag} m");
    // The draw mesh holds the CPU skinning of these particles, in the entity's frame.
    let skinned = common::skinned(&model, &x);
    let meshes = app.world().resource::<Assets<Mesh>>();
    let mesh = meshes.get(&built.draw_mesh).expect("draw mesh");
    let Some(bevy::mesh::VertexAttributeValues::Float32x3(pos)) =
        mesh.attribute(Mesh::ATTRIBUTE_POSITION)
    else {
        panic!("positions")
    };
    assert_eq!(pos.len(), skinned.len());
    let off = pos
        .iter()
        .zip(&skinned)
        .map(|(p, s)| (Vec3::from_array(*p) + at).distance(*s))
        .fold(0.0f32, f32::max);
    assert!(off < 1e-5, "draw mesh off the skinned surface by {off} m");
    // The main world's timings: one step measurement per stepping frame (30, not the
    // paused frames), skinning on every frame that wrote the mesh, and no GPU contact
    // search (the CPU solver's searches are part of its steps).
    let store = app.world().resource::<DiagnosticsStore>();
    let values = |path: &DiagnosticPath| -> Vec<f64> {
        store.get(path).unwrap().values().copied().collect()
    };
    let step = values(&TissueDiagnostics::STEP);
    assert_eq!(step.len(), 30, "step times {step:?}");
    assert!(
        step.iter().all(|ms| ms.is_finite() && *ms > 0.0),
        "{step:?}"
    );
    let skin = values(&TissueDiagnostics::SKIN);
    assert!(skin.len() >= 30, "skinning measured {} times", skin.len());
    assert!(
        skin.iter().all(|ms| ms.is_finite() && *ms > 0.0),
        "{skin:?}"
    );
    assert!(values(&TissueDiagnostics::CONTACTS).is_empty());
}

#[test]
fn the_cpu_backend_runs_cluster_bodies_like_the_core() {
    let settings = TissueSettings {
        backend: TissueBackend::Cpu,
        ..default()
    };
    let mut app = app(settings.clone());
    let at = Vec3::new(0.0, 0.3, 0.0);
    let (mut body, pinned) = common::lattice_body();
    body.discretisation = TissueDiscretisation::Clusters;
    body.neighbours = 16;
    let e = spawn(&mut app, at, body.clone(), pinned.clone());
    until_built(&mut app, e);
    let read = run(&mut app, e, 10);
    let (_, x) = core_reference(&body, &pinned, at, &settings, 10);
    let worst = common::max_distance(&read.positions, &x);
    assert!(worst < 1e-6, "plugin and core differ by {worst} m");
}

#[test]
fn a_diverging_cpu_body_is_put_back_at_rest_with_a_diagnosis() {
    // One step of a whole second of an extremely stiff body under XPBD blows up.
    let settings = TissueSettings {
        backend: TissueBackend::Cpu,
        dt: 1.0,
        gravity: Vec3::new(0.0, -2000.0, 0.0),
        max_steps_per_frame: 1,
        ..default()
    };
    let mut app = app(settings);
    let (mut body, pinned) = common::lattice_body();
    body.discretisation = TissueDiscretisation::Clusters;
    body.neighbours = 16;
    body.material = TissueMaterial::Hyperelastic {
        youngs_modulus: 1e9,
        poisson_ratio: 0.49,
    };
    let e = spawn(&mut app, Vec3::ZERO, body, pinned);
    until_built(&mut app, e);
    let mut errors: Vec<SoftBodyError> = Vec::new();
    {
        let mut clock = app.world_mut().resource_mut::<TissueClock>();
        clock.paused = false;
        clock.fixed_steps_per_frame = Some(1);
    }
    for _ in 0..5 {
        app.update();
        let msgs = app.world().resource::<Messages<SoftBodyError>>();
        errors.extend(msgs.iter_current_update_messages().cloned());
    }
    let Some(err) = errors.iter().find(|m| m.entity == e) else {
        panic!("no divergence reported");
    };
    assert!(
        err.error.contains("Remedy") && err.error.contains("put back at rest"),
        "{}",
        err.error
    );
    let world = app.world().resource::<CpuWorld>();
    assert!(world.state().unwrap().x.iter().all(|p| p.is_finite()));
}

/// Two lattice bodies on the CPU share one world: the upper one, dropped onto the lower
/// (held whole) one, rests on it through particle contacts instead of passing through, and
/// each body's particles are its own slice of the world. At the default `knn_every` of
/// 10 (searched only then, the body falling from 4 cm crossed the contact reach between
/// two searches): the contacts are searched again whenever particles may move out of
/// the last search's reach.
#[test]
fn cpu_bodies_touch_each_other() {
    let mut app = app(TissueSettings::default());
    assert_eq!(app.world().resource::<TissueSettings>().knn_every, 10);
    let (body, _) = common::lattice_body();
    // The lower body held whole (every particle pinned): a fixed shelf.
    let shelf = Pinned::region(PinShape::HalfSpace {
        point: Vec3::new(0.0, 1.0, 0.0),
        normal: -Vec3::Y,
    });
    let low = spawn(&mut app, Vec3::ZERO, body.clone(), shelf);
    // The upper body, free, above the lower one: the boxes are 5 cm tall and their
    // lattices reach up to half a cell (6 mm) past the surface, so 10 cm apart leaves a
    // gap of about 4 cm.
    let mesh = app
        .world_mut()
        .resource_mut::<Assets<Mesh>>()
        .add(box_mesh());
    let high = app
        .world_mut()
        .spawn((
            Mesh3d(mesh),
            Transform::from_xyz(0.0, 0.10, 0.0),
            body,
            ReadbackParticles { continuous: true },
        ))
        .id();
    until_built(&mut app, low);
    until_built(&mut app, high);
    let read = run(&mut app, high, 60);
    let world = app.world().resource::<CpuWorld>();
    assert_eq!(world.entities().count(), 2);
    let lower = app.world().get::<CpuBody>(low).unwrap().particles.clone();
    let state = world.state().unwrap();
    let top_of_low = state.x[lower]
        .iter()
        .map(|p| p.y)
        .fold(f32::NEG_INFINITY, f32::max);
    let bottom_of_high = read
        .positions
        .iter()
        .map(|p| p.y)
        .fold(f32::INFINITY, f32::min);
    // Fallen onto the lower body (it started about 4 cm above) but held above its top
    // layer.
    assert!(
        bottom_of_high < top_of_low + 0.02,
        "did not fall: {bottom_of_high} m"
    );
    assert!(
        bottom_of_high > top_of_low,
        "passed into the lower body: its bottom {bottom_of_high} m, the lower top {top_of_low} m"
    );
}

/// A lattice body has no clusters: changing its K (or its quality level) leaves it as it
/// is, where changing its material rebuilds it.
#[test]
fn a_lattice_body_is_rebuilt_for_its_material_not_its_k() {
    let mut app = app(TissueSettings::default());
    let (body, pinned) = common::lattice_body();
    let e = spawn(&mut app, Vec3::ZERO, body, pinned);
    until_built(&mut app, e);
    let generation = |app: &App| app.world().get::<BuiltBody>(e).unwrap().generation;
    let first = generation(&app);
    {
        let mut b = app.world_mut().get_mut::<SoftBody>(e).unwrap();
        b.neighbours = 40;
        b.quality = TissueQuality::Accurate;
    }
    app.update();
    assert!(
        matches!(
            app.world().get::<SoftBodyStatus>(e),
            Some(SoftBodyStatus::Ready { .. })
        ),
        "K and quality started a rebuild: {:?}",
        app.world().get::<SoftBodyStatus>(e)
    );
    for _ in 0..50 {
        app.update();
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    assert_eq!(
        generation(&app),
        first,
        "K and quality rebuilt the lattice body"
    );
    app.world_mut().get_mut::<SoftBody>(e).unwrap().material = TissueMaterial::Hyperelastic {
        youngs_modulus: 80_000.0,
        poisson_ratio: 0.4,
    };
    let mut rebuilt = false;
    for _ in 0..200 {
        app.update();
        if generation(&app) > first {
            rebuilt = true;
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    assert!(rebuilt, "the material change rebuilt the body");
}

/// The positions of `mesh` (entity frame, m).
fn mesh_positions(app: &App, mesh: &Handle<Mesh>) -> Vec<Vec3> {
    let meshes = app.world().resource::<Assets<Mesh>>();
    match meshes
        .get(mesh)
        .and_then(|m| m.attribute(Mesh::ATTRIBUTE_POSITION))
    {
        Some(bevy::mesh::VertexAttributeValues::Float32x3(p)) => {
            p.iter().map(|p| Vec3::from_array(*p)).collect()
        }
        _ => panic!("the draw mesh has no positions"),
    }
}

/// A body that comes to rest (pinned, sagging under gravity) stops being skinned and
/// written: its draw mesh stays the same, and its particles stay within `SKIN_STILL` of
/// their spacing of what it shows. A body put back at rest is written again at once.
#[test]
fn a_body_lying_still_is_not_skinned_again() {
    use bevy_tissue::plugin::cpu::SKIN_STILL;
    let mut app = app(TissueSettings::default());
    let at = Vec3::new(0.0, 0.3, 0.0);
    let (body, pinned) = common::lattice_body();
    let e = spawn(&mut app, at, body, pinned);
    until_built(&mut app, e);
    let built = app.world().get::<BuiltBody>(e).unwrap().clone();
    let spacing = built.model.bodies[0].spacing;
    // Sagging: the mesh follows step by step.
    let before = mesh_positions(&app, &built.draw_mesh);
    run(&mut app, e, 10);
    let sagging = mesh_positions(&app, &built.draw_mesh);
    assert!(common::max_distance(&before, &sagging) > 1e-4);
    // Settled: further steps change the particles by less than the threshold since
    // the mesh was last written, and the mesh not at all.
    run(&mut app, e, 400);
    let settled = mesh_positions(&app, &built.draw_mesh);
    let read = run(&mut app, e, 30);
    let still = mesh_positions(&app, &built.draw_mesh);
    assert_eq!(settled, still, "a body lying still was written again");
    // What the mesh shows is the skin of particles within the threshold of these.
    let skinned = common::skinned(&built.model, &read.positions);
    let off = still
        .iter()
        .zip(&skinned)
        .map(|(p, s)| (*p + at).distance(*s))
        .fold(0.0f32, f32::max);
    assert!(
        off < 4.0 * SKIN_STILL * spacing,
        "the mesh is {off} m off the particles' skin (spacing {spacing} m)"
    );
    // Put back at rest: written in the next step.
    app.world_mut().write_message(ResetSoftBody { entity: e });
    run(&mut app, e, 1);
    let reset = mesh_positions(&app, &built.draw_mesh);
    assert!(
        common::max_distance(&still, &reset) > 1e-4,
        "the reset body was not written"
    );
}
