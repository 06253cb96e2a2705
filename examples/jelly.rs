//! A game-like scene: dozens of jelly bodies of several shapes (Bevy primitives) rain
//! onto ramps and a floor, bounce, pile up and push each other around. Grab any of them
//! with the mouse.
//!
//! ```text
//! cargo run --release --example jelly
//! cargo run --release --example jelly -- --bodies 64 --particles 400
//! cargo run --release --example jelly -- --clusters     # the paper's model
//! cargo run --release --example jelly -- --contact-every 1 --contact-relaxation 1
//! ```
//!
//! The jelly is a firm gelatin: hyperelastic, E = 20 kPa, ν = 0.45, 1060 kg/m³, on
//! hexahedral lattice elements (the plugin's default discretisation), which keep that
//! stiffness at any resolution: a 20 cm body settles about 5% under its own weight.
//! `--clusters` makes it the paper's model instead (shape matching, k = 0.85, K = 24).
//!
//! Controls: left mouse drags a body; R drops everything again; Space pauses. With
//! `--script` a mouse drag happens by itself (tests, screenshots); `--headless`,
//! `--size`, `--frames`, `--shot FRAME:PATH` as in `support/scene.rs`.
//!
//! `--events gravity@400,spawn@500,despawn@600` measures what changing the world costs
//! a frame: at each given frame it changes gravity (`TissueSettings::gravity`, halved and
//! restored in turn), spawns one more body or despawns one, and prints the slowest frame
//! of the 60 after it and the time those frames took beyond the median frame of the 60
//! before it.

#[path = "support/bench.rs"]
mod bench;
#[path = "support/scene.rs"]
mod scene;

use bevy::prelude::*;
use bevy_tissue::prelude::*;
use scene::SceneArgs;

#[derive(Resource)]
struct Jelly {
    bodies: u32,
    particles: u32,
    /// The paper's clusters (shape matching) instead of lattice elements.
    clusters: bool,
}

/// Young's modulus of the jelly, Pa (a firm gelatin).
const JELLY_E: f32 = 20_000.0;

/// A jelly body (R drops them all again from where they started).
#[derive(Component)]
struct JellyBody;

fn main() {
    let args = bench::Args::new();
    let scene = SceneArgs::parse(&args);
    let jelly = Jelly {
        bodies: args.num("--bodies", 36u32).max(1),
        particles: args.num("--particles", 500u32),
        clusters: args.flag("--clusters"),
    };
    let events = WorldEvents::parse(args.text("--events").map(String::as_str).unwrap_or(""));
    // The contact schedule can be set from the command line to compare it by eye.
    let d = TissueSettings::default();
    let settings = TissueSettings {
        contact_every: args.num("--contact-every", d.contact_every).max(1),
        contact_relaxation: args.num("--contact-relaxation", d.contact_relaxation),
        ..d
    };
    let mut app = scene::app(&scene, "bevy_tissue: jelly", settings);
    app.add_plugins(TissueDragPlugin::default())
        .insert_resource(jelly)
        .insert_resource(ClearColor(Color::srgb(0.55, 0.75, 0.95)))
        .add_systems(Startup, setup)
        .add_systems(Update, report);
    if !events.list.is_empty() {
        app.insert_resource(events)
            .add_systems(Update, world_events.before(TissueSet::Build));
    }
    if scene.script {
        app.add_systems(Update, (script.before(TissueSet::Build), drag_report));
    } else {
        app.add_systems(Update, keys);
    }
    app.run();
}

fn setup(
    mut commands: Commands,
    mut meshes: ResMut<Assets<Mesh>>,
    mut materials: ResMut<Assets<StandardMaterial>>,
    jelly: Res<Jelly>,
) {
    scene::spawn_view(
        &mut commands,
        Vec3::new(0.0, 1.7, 2.6),
        Vec3::new(0.0, 0.45, 0.0),
        Vec3::new(2.0, 5.0, 2.0),
        10_000.0,
    );
    let stone = materials.add(Color::srgb(0.45, 0.47, 0.5));
    // Static colliders, each drawn by the matching Bevy primitive.
    commands.spawn((
        Mesh3d(meshes.add(Plane3d::default().mesh().size(6.0, 6.0))),
        MeshMaterial3d(materials.add(Color::srgb(0.35, 0.55, 0.35))),
        TissueCollider::new(ColliderKind::Plane),
    ));
    for (x, tilt) in [(-0.7f32, -0.35f32), (0.7, 0.35)] {
        let half = Vec3::new(0.6, 0.05, 0.5);
        commands.spawn((
            Mesh3d(meshes.add(Cuboid::from_size(half * 2.0))),
            MeshMaterial3d(stone.clone()),
            Transform::from_xyz(x, 0.55, 0.0).with_rotation(Quat::from_rotation_z(tilt)),
            TissueCollider::new(ColliderKind::Cuboid { half_extents: half }),
        ));
    }
    commands.spawn((
        Mesh3d(meshes.add(Capsule3d::new(0.08, 1.2))),
        MeshMaterial3d(stone.clone()),
        Transform::from_xyz(0.0, 0.12, 0.6)
            .with_rotation(Quat::from_rotation_z(std::f32::consts::FRAC_PI_2)),
        TissueCollider::new(ColliderKind::Capsule {
            half_length: 0.6,
            radius: 0.08,
        }),
    ));
    // The jelly: shapes and colours in turn, on a grid in the air.
    let shapes: [Mesh; 6] = [
        Sphere::new(0.13).mesh().ico(3).unwrap(),
        Cuboid::new(0.22, 0.18, 0.22).mesh().build(),
        Capsule3d::new(0.08, 0.16)
            .mesh()
            .rings(4)
            .latitudes(12)
            .build(),
        Torus::new(0.05, 0.14).mesh().build(),
        Cylinder::new(0.11, 0.2).mesh().build(),
        Cone::new(0.13, 0.25).mesh().build(),
    ];
    let shapes: Vec<Handle<Mesh>> = shapes.into_iter().map(|m| meshes.add(m)).collect();
    let side = (jelly.bodies as f32).sqrt().ceil() as u32;
    for i in 0..jelly.bodies {
        let (gx, gz) = (i % side, i / side);
        let layer = i / (side * side).max(1);
        let x = (gx as f32 - (side - 1) as f32 / 2.0) * 0.36;
        let z = (gz % side) as f32 * 0.3 - 0.4;
        let at = Transform::from_xyz(x, 1.4 + 0.4 * layer as f32 + 0.05 * (i % 3) as f32, z)
            .with_rotation(Quat::from_euler(
                EulerRot::XYZ,
                0.3 * i as f32,
                0.7 * i as f32,
                0.0,
            ));
        let hue = (i as f32 * 47.0) % 360.0;
        commands.spawn((
            Name::new(format!("jelly {i}")),
            Mesh3d(shapes[i as usize % shapes.len()].clone()),
            MeshMaterial3d(materials.add(StandardMaterial {
                base_color: Color::hsl(hue, 0.75, 0.55),
                perceptual_roughness: 0.2,
                ..default()
            })),
            at,
            JellyBody,
            if jelly.clusters {
                SoftBody {
                    material: TissueMaterial::ShapeMatching { stiffness: 0.85 },
                    resolution: TissueResolution::Particles(jelly.particles),
                    neighbours: 24,
                    discretisation: TissueDiscretisation::Clusters,
                    ..default()
                }
            } else {
                SoftBody {
                    material: TissueMaterial::Hyperelastic {
                        youngs_modulus: JELLY_E,
                        poisson_ratio: 0.45,
                    },
                    resolution: TissueResolution::Particles(jelly.particles),
                    ..default()
                }
            },
        ));
    }
}

/// R drops everything again; Space pauses.
fn keys(
    keys: Res<ButtonInput<KeyCode>>,
    mut clock: ResMut<TissueClock>,
    bodies: Query<Entity, With<JellyBody>>,
    mut reset: MessageWriter<ResetSoftBody>,
) {
    if keys.just_pressed(KeyCode::KeyR) {
        for entity in &bodies {
            reset.write(ResetSoftBody { entity });
        }
    }
    if keys.just_pressed(KeyCode::Space) {
        clock.toggle_pause();
    }
}

/// `--script`: at frame 150 the mouse takes the highest body and lifts it 0.3 m for 60
/// frames.
#[allow(clippy::too_many_arguments)]
fn script(
    frames: Res<scene::Frames>,
    bodies: Query<(&bevy::camera::primitives::Aabb, &GlobalTransform), With<SoftBody>>,
    mut target: Local<Option<Vec3>>,
    mut pointer: scene::ScriptPointer,
) {
    let f = frames.count;
    if f == 145 {
        // The centre of the highest body's box (the top of the pile).
        *target = bodies
            .iter()
            .map(|(b, t)| t.transform_point(Vec3::from(b.center)))
            .max_by(|a, b| a.y.total_cmp(&b.y));
    }
    let Some(start) = *target else { return };
    let lift = ((f as f32 - 160.0) / 40.0).clamp(0.0, 1.0) * 0.3;
    let pressed = (150..210).contains(&f);
    pointer.drive(start + Vec3::Y * lift, pressed);
}

/// `--script`: the largest pull the mouse drag felt so far, every 50 frames.
fn drag_report(
    frames: Res<scene::Frames>,
    drag: Query<&ColliderForce, With<DragGrasper>>,
    ready: Query<&SoftBodyStatus>,
    mut max: Local<f32>,
) {
    for f in &drag {
        *max = max.max(f.0.length());
    }
    if frames.count.is_multiple_of(50) {
        let n = ready
            .iter()
            .filter(|s| matches!(s, SoftBodyStatus::Ready { .. }))
            .count();
        println!(
            "frame {}: {n} bodies ready; max force on the mouse drag {:.4} N",
            frames.count, *max
        );
    }
}

fn report(mut ready: MessageReader<SoftBodyReady>, mut errors: MessageReader<SoftBodyError>) {
    let n = ready.read().count();
    if n > 0 {
        info!("{n} jelly bodies ready");
    }
    for e in errors.read() {
        error!("soft body {}: {}", e.entity, e.error);
    }
}

/// `--events`: world changes at given frames and the frame time around each.
#[derive(Resource, Default)]
struct WorldEvents {
    /// (kind, frame), kind one of `gravity`, `spawn`, `despawn`.
    list: Vec<(String, u32)>,
    /// Wall time of every frame so far, ms (frame 1 first).
    times: Vec<f64>,
    last: Option<std::time::Instant>,
}

/// Frames before an event whose median is the baseline, and frames after it measured.
const EVENT_WINDOW: usize = 60;

impl WorldEvents {
    fn parse(text: &str) -> Self {
        let mut list = Vec::new();
        for item in text.split(',').filter(|t| !t.is_empty()) {
            let parsed = item.split_once('@').and_then(|(kind, frame)| {
                let ok = matches!(kind, "gravity" | "spawn" | "despawn");
                Some((kind.to_string(), frame.parse::<u32>().ok()?)).filter(|_| ok)
            });
            match parsed {
                Some(e) => list.push(e),
                None => {
                    eprintln!("--events: {item}: expected gravity@F, spawn@F or despawn@F");
                    std::process::exit(2);
                }
            }
        }
        Self {
            list,
            ..Default::default()
        }
    }
}

/// A jelly body's parts that a spawned copy takes.
type JellyParts<'a> = (
    Entity,
    &'a Mesh3d,
    &'a MeshMaterial3d<StandardMaterial>,
    &'a SoftBody,
    &'a Transform,
);

fn world_events(
    mut commands: Commands,
    frames: Res<scene::Frames>,
    mut events: ResMut<WorldEvents>,
    mut settings: ResMut<TissueSettings>,
    bodies: Query<JellyParts, With<JellyBody>>,
) {
    let now = std::time::Instant::now();
    if let Some(last) = events.last {
        let ms = now.duration_since(last).as_secs_f64() * 1e3;
        events.times.push(ms);
    }
    events.last = Some(now);
    let f = frames.count;
    let due: Vec<String> = events
        .list
        .iter()
        .filter(|e| e.1 == f)
        .map(|e| e.0.clone())
        .collect();
    for kind in due {
        match kind.as_str() {
            "gravity" => {
                let g = settings.gravity;
                settings.gravity = if g.y < -9.0 { g * 0.5 } else { g * 2.0 };
            }
            "spawn" => {
                if let Some((_, mesh, mat, body, at)) = bodies.iter().next() {
                    commands.spawn((
                        Name::new("jelly (spawned)"),
                        mesh.clone(),
                        mat.clone(),
                        Transform::from_translation(at.translation + Vec3::Y * 0.6),
                        JellyBody,
                        body.clone(),
                    ));
                }
            }
            _ => {
                if let Some((e, ..)) = bodies.iter().last() {
                    commands.entity(e).despawn();
                }
            }
        }
    }
    // Report each event once the frames after it have run.
    for (kind, at) in &events.list {
        let at = *at as usize;
        if f as usize != at + EVENT_WINDOW + 1 || at < EVENT_WINDOW + 1 {
            continue;
        }
        // times[k - 1] is frame k's (from its Update to the next).
        let before: Vec<f64> = events.times[at - 1 - EVENT_WINDOW..at - 1].to_vec();
        let after = &events.times[at - 1..at - 1 + EVENT_WINDOW];
        let median = bench::median(before);
        let (slowest, which) = after
            .iter()
            .enumerate()
            .fold((0.0f64, 0), |m, (i, &t)| if t > m.0 { (t, i) } else { m });
        let added: f64 = after.iter().map(|t| (t - median).max(0.0)).sum();
        println!(
            "event {kind} at frame {at}: slowest frame of the next {EVENT_WINDOW} {slowest:.2} ms \
             ({} frames later), added over them {added:.2} ms; median frame before {median:.3} ms",
            which
        );
    }
}
