//! The plugin in a scene: three soft bodies made from Bevy primitives — a ball, a box
//! and a capsule — drop onto the ground while a kinematic sphere sweeps through them.
//! The plugin's default bodies (hexahedral lattice elements), stepped on the GPU and
//! drawn with ordinary `StandardMaterial`s (lit, shadowed).
//!
//! ```text
//! cargo run --release --example drop
//! cargo run --release --example drop -- --frames 300 --screenshot drop.png   # then exit
//! ```
use bevy::prelude::*;
use bevy::render::view::screenshot::{Screenshot, save_to_disk};
use bevy_tissue::prelude::*;

/// Command-line options.
#[derive(Resource, Default)]
struct Options {
    frames: Option<u32>,
    screenshot: Option<String>,
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let value = |name: &str| {
        args.iter()
            .position(|a| a == name)
            .and_then(|i| args.get(i + 1).cloned())
    };
    let options = Options {
        frames: value("--frames").and_then(|v| v.parse().ok()),
        screenshot: value("--screenshot"),
    };
    App::new()
        .add_plugins((DefaultPlugins, TissuePlugin::default()))
        .insert_resource(options)
        .add_systems(Startup, setup)
        .add_systems(Update, (sweep, report, finish))
        .run();
}

fn setup(
    mut commands: Commands,
    mut meshes: ResMut<Assets<Mesh>>,
    mut materials: ResMut<Assets<StandardMaterial>>,
) {
    commands.spawn((
        Camera3d::default(),
        Transform::from_xyz(0.0, 0.9, 1.6).looking_at(Vec3::new(0.0, 0.2, 0.0), Vec3::Y),
    ));
    commands.spawn((
        DirectionalLight {
            shadow_maps_enabled: true,
            illuminance: 8000.0,
            ..default()
        },
        Transform::from_xyz(2.0, 4.0, 1.0).looking_at(Vec3::ZERO, Vec3::Y),
    ));
    // Ground: drawn by a plane mesh, felt through a plane collider.
    commands.spawn((
        Mesh3d(meshes.add(Plane3d::default().mesh().size(4.0, 4.0))),
        MeshMaterial3d(materials.add(Color::srgb(0.35, 0.37, 0.4))),
        TissueCollider::new(ColliderKind::Plane),
    ));
    // The plugin's default body (hexahedral lattice elements, stepped by Newton–multigrid)
    // of a soft hyperelastic material, E = 30 kPa: a 30 cm body settles a few per cent
    // under its own weight.
    let body = |particles| SoftBody {
        resolution: TissueResolution::Particles(particles),
        material: TissueMaterial::Hyperelastic {
            youngs_modulus: 30_000.0,
            poisson_ratio: 0.45,
        },
        ..default()
    };
    commands.spawn((
        Mesh3d(meshes.add(Sphere::new(0.15).mesh().ico(4).unwrap())),
        MeshMaterial3d(materials.add(Color::srgb(0.85, 0.3, 0.3))),
        Transform::from_xyz(-0.4, 0.5, 0.0),
        body(3000),
    ));
    commands.spawn((
        Mesh3d(meshes.add(Cuboid::new(0.25, 0.2, 0.25))),
        MeshMaterial3d(materials.add(Color::srgb(0.3, 0.7, 0.4))),
        Transform::from_xyz(0.0, 0.45, 0.0).with_rotation(Quat::from_rotation_z(0.4)),
        body(3000),
    ));
    commands.spawn((
        Mesh3d(meshes.add(Capsule3d::new(0.08, 0.25).mesh().rings(8).latitudes(16))),
        MeshMaterial3d(materials.add(Color::srgb(0.3, 0.45, 0.85))),
        Transform::from_xyz(0.4, 0.6, 0.0).with_rotation(Quat::from_rotation_x(1.2)),
        body(2000),
    ));
    // A kinematic sphere that sweeps through the bodies; its force is read back.
    commands.spawn((
        Mesh3d(meshes.add(Sphere::new(0.07).mesh().ico(3).unwrap())),
        MeshMaterial3d(materials.add(Color::srgb(0.9, 0.85, 0.5))),
        Transform::from_xyz(0.0, 0.08, 0.4),
        TissueCollider::new(ColliderKind::Sphere { radius: 0.07 }),
        ColliderForce::default(),
    ));
}

fn sweep(time: Res<Time>, mut q: Query<(&mut Transform, &TissueCollider)>) {
    for (mut t, c) in &mut q {
        if matches!(c.kind, ColliderKind::Sphere { .. }) {
            t.translation.x = 0.6 * (0.5 * time.elapsed_secs()).sin();
            t.translation.z = 0.1 * (0.5 * time.elapsed_secs()).cos();
        }
    }
}

fn report(
    mut ready: MessageReader<SoftBodyReady>,
    mut errors: MessageReader<SoftBodyError>,
    force: Query<&ColliderForce>,
    clock: Res<TissueClock>,
) {
    for r in ready.read() {
        info!("soft body {} ready: {} particles", r.entity, r.particles);
    }
    for e in errors.read() {
        error!("soft body {}: {}", e.entity, e.error);
    }
    if clock.steps > 0 && clock.steps.is_multiple_of(120) && clock.steps_this_frame > 0 {
        for f in &force {
            info!(
                "step {}: force on the sweeping sphere {:.3} N",
                clock.steps, f.0
            );
        }
    }
}

fn finish(
    mut frame: Local<u32>,
    options: Res<Options>,
    mut commands: Commands,
    mut exit: MessageWriter<AppExit>,
) {
    *frame += 1;
    let Some(frames) = options.frames else { return };
    if *frame == frames
        && let Some(path) = &options.screenshot
    {
        commands
            .spawn(Screenshot::primary_window())
            .observe(save_to_disk(path.clone()));
    }
    if *frame >= frames + 10 {
        exit.write(AppExit::Success);
    }
}
