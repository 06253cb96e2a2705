//! The surgical-training prototype: a liver (made by the project: right and left lobe,
//! wedge shaped) held along its ligament, with a probe that presses into it, a grasper
//! that takes and pulls it, and a mouse drag on any point of it. The forces on the tools
//! are shown live in the panel, next to the tissue's settings and GPU timings.
//!
//! ```text
//! cargo run --release --example liver
//! cargo run --release --example liver -- --particles 38000         # finer (GPU)
//! cargo run --release --example liver -- --headless --frames 600   # frame rate, no window
//! cargo run --release --example liver -- --clusters                 # the paper's model
//! ```
//!
//! The liver is human liver tissue as published: E = 5.5 kPa, the middle of the normal
//! range of transient elastography, 3.3–7.8 kPa (Del Poggio & Colombo, "Is transient
//! elastography a useful tool for screening liver disease?", World J. Gastroenterol.
//! 15(12), 2009); ν = 0.45, nearly incompressible (elastography takes soft tissue as
//! incompressible; 0.45 keeps the bulk stiffness at 9 times the shear stiffness); and
//! 1060 kg/m³ (adult liver, ICRU Report 44, 1989). It is built from hexahedral
//! elements on its sampling lattice, which converge to the E and ν set, and stepped by
//! Newton–multigrid at one 1/60 s step a frame: on the GPU, its positions read back and
//! skinned on the CPU, or on the CPU where there is no GPU (default 3,000 particles,
//! which any adapter, and the CPU, steps at frame rate).
//!
//! `--clusters` runs the paper's model instead, as it was benchmarked: its clusters
//! (37,982 particles, K = 32, E = 30 kPa, steps of 1/240 s), softer than the E and ν
//! they are given. `--lattice` (the default) is accepted for scripts of before.
//!
//! Controls: probe W/A/S/D (across), Q/E (down/up); grasper I/J/K/L, U/O, G closes and
//! opens it; left mouse drags the tissue; R puts the liver back at rest; Space pauses.
//! With `--script` the tools and a mouse drag move by themselves and K changes at frame
//! 320 (tests, screenshots); `--no-ui` hides the panel; `--headless`, `--size`,
//! `--frames`, `--shot FRAME:PATH`, `--lite` as in `support/scene.rs`.

#[path = "support/bench.rs"]
mod bench;
#[path = "support/scene.rs"]
mod scene;

use bevy::asset::RenderAssetUsages;
use bevy::mesh::{Indices, PrimitiveTopology};
use bevy::prelude::*;
use bevy_tissue::core::procedural;
use bevy_tissue::prelude::*;
use bevy_tissue::ui::TissueUiPlugin;
use scene::SceneArgs;

/// Particles of the liver under `--clusters` (the paper's largest model, Table 1).
const DEFAULT_CLUSTER_PARTICLES: u32 = 37_982;
/// Particles of the liver as a lattice body (the default).
const DEFAULT_LATTICE_PARTICLES: u32 = 3_000;
/// Young's modulus of the liver, Pa: the middle of the normal range measured by
/// transient elastography, 3.3–7.8 kPa (Del Poggio & Colombo 2009).
const LIVER_E: f32 = 5_500.0;
/// Poisson's ratio of the liver: nearly incompressible.
const LIVER_NU: f32 = 0.45;
/// Density of adult liver, kg/m³ (ICRU Report 44).
const LIVER_DENSITY: f32 = 1060.0;
/// Where the liver's centre sits, m (the tray is at y = 0).
const LIVER_AT: Vec3 = Vec3::new(0.0, 0.05, 0.0);
/// Tool speed under the keys, m/s.
const TOOL_SPEED: f32 = 0.08;

#[derive(Component)]
struct Liver;

#[derive(Component)]
struct Probe;

#[derive(Component)]
struct Grasper;

/// The grasper's two jaws (drawn open or closed).
#[derive(Component)]
struct Jaw(f32);

#[derive(Resource)]
struct Particles(u32);

/// The liver is a lattice body (hexahedral elements, stepped by Newton–multigrid; the
/// default), or the paper's clusters (`--clusters`).
#[derive(Resource)]
struct Lattice(bool);

fn main() {
    let args = bench::Args::new();
    let scene = SceneArgs::parse(&args);
    let lattice = !args.flag("--clusters");
    let particles = args.num(
        "--particles",
        if lattice {
            DEFAULT_LATTICE_PARTICLES
        } else {
            DEFAULT_CLUSTER_PARTICLES
        },
    );
    // Steps of 1/240 s, one substep each: a step for every frame of a 240 Hz display,
    // and a step small enough for the hyperelastic Jacobi solve of this pinned liver,
    // which is not stable at one substep of 1/60 s (BENCHMARKS.md, "Stability"). Steps
    // of 1/120 s are stable too and halve the GPU work per simulated second, but leave
    // the surface visibly wrinkled (less converged); on a smaller GPU, fewer particles
    // (`--particles 8000`) are the better saving.
    // Lattice bodies step by Newton–multigrid, stable and within a few percent of the
    // material at a step of 1/60 s (BENCHMARKS.md, "Newton–multigrid").
    let settings = TissueSettings {
        dt: if lattice { 1.0 / 60.0 } else { 1.0 / 240.0 },
        substeps: 1,
        ..default()
    };
    let mut app = scene::app(&scene, "bevy_tissue: liver", settings);
    app.add_plugins(TissueDragPlugin::default());
    if !args.flag("--no-ui") {
        app.add_plugins(TissueUiPlugin::default());
    }
    app.insert_resource(Particles(particles))
        .insert_resource(Lattice(lattice))
        .insert_resource(ClearColor(Color::srgb(0.06, 0.07, 0.09)))
        .add_systems(Startup, setup)
        .add_systems(Update, (report, jaws));
    if scene.script {
        app.add_systems(Update, (script.before(TissueSet::Build), script_report));
    } else {
        app.add_systems(Update, keys);
    }
    app.run();
}

/// The procedural liver as a Bevy mesh (smooth normals).
fn liver_mesh() -> Mesh {
    let tri = procedural::liver(5);
    let positions: Vec<[f32; 3]> = tri.positions.iter().map(|p| p.to_array()).collect();
    Mesh::new(
        PrimitiveTopology::TriangleList,
        RenderAssetUsages::default(),
    )
    .with_inserted_attribute(Mesh::ATTRIBUTE_POSITION, positions)
    .with_inserted_indices(Indices::U32(tri.indices.clone()))
    .with_computed_smooth_normals()
}

fn setup(
    mut commands: Commands,
    mut meshes: ResMut<Assets<Mesh>>,
    mut materials: ResMut<Assets<StandardMaterial>>,
    particles: Res<Particles>,
    lattice: Res<Lattice>,
) {
    scene::spawn_view(
        &mut commands,
        Vec3::new(0.02, 0.22, 0.3),
        Vec3::new(0.0, 0.05, 0.0),
        Vec3::new(0.6, 1.2, 0.8),
        9000.0,
    );
    commands.insert_resource(GlobalAmbientLight {
        brightness: 300.0,
        ..default()
    });
    // The tray: drawn by a plane, felt through a plane collider.
    commands.spawn((
        Name::new("tray"),
        Mesh3d(meshes.add(Plane3d::default().mesh().size(0.8, 0.6))),
        MeshMaterial3d(materials.add(StandardMaterial {
            base_color: Color::srgb(0.55, 0.6, 0.62),
            metallic: 0.8,
            perceptual_roughness: 0.35,
            ..default()
        })),
        TissueCollider::new(ColliderKind::Plane),
    ));
    // The liver, held along its ligament: liver tissue as published (lattice), or the
    // paper's clusters as benchmarked (`--clusters`).
    let (lo, hi) = procedural::liver_ligament();
    commands.spawn((
        Name::new("liver"),
        Liver,
        Mesh3d(meshes.add(liver_mesh())),
        MeshMaterial3d(materials.add(StandardMaterial {
            base_color: Color::srgb(0.30, 0.06, 0.045),
            perceptual_roughness: 0.3,
            reflectance: 0.6,
            ..default()
        })),
        Transform::from_translation(LIVER_AT),
        SoftBody {
            material: TissueMaterial::Hyperelastic {
                youngs_modulus: if lattice.0 { LIVER_E } else { 30_000.0 },
                poisson_ratio: LIVER_NU,
            },
            density: LIVER_DENSITY,
            resolution: TissueResolution::Particles(particles.0),
            discretisation: if lattice.0 {
                TissueDiscretisation::Lattice
            } else {
                TissueDiscretisation::Clusters
            },
            ..default()
        },
        Pinned::region(PinShape::Box { min: lo, max: hi }),
    ));
    let steel = materials.add(StandardMaterial {
        base_color: Color::srgb(0.8, 0.82, 0.85),
        metallic: 1.0,
        perceptual_roughness: 0.25,
        ..default()
    });
    // The probe: a ball-tipped rod; the ball is the collider.
    commands
        .spawn((
            Name::new("probe"),
            Probe,
            Mesh3d(meshes.add(Sphere::new(0.01).mesh().ico(3).unwrap())),
            MeshMaterial3d(steel.clone()),
            Transform::from_xyz(0.06, 0.23, 0.0),
            TissueCollider::new(ColliderKind::Sphere { radius: 0.01 }),
            ColliderForce::default(),
        ))
        .with_child((
            Mesh3d(meshes.add(Cylinder::new(0.003, 0.12))),
            MeshMaterial3d(steel.clone()),
            Transform::from_xyz(0.0, 0.065, 0.0),
        ));
    // The grasper: two jaws on a shaft; closed, it holds what lies within 15 mm.
    commands
        .spawn((
            Name::new("grasper"),
            Grasper,
            Transform::from_xyz(-0.08, 0.2, 0.01),
            Visibility::default(),
            TissueCollider::new(ColliderKind::Grasper {
                radius: 0.015,
                closed: false,
            }),
            ColliderForce::default(),
        ))
        .with_children(|g| {
            g.spawn((
                Mesh3d(meshes.add(Cylinder::new(0.004, 0.12))),
                MeshMaterial3d(steel.clone()),
                Transform::from_xyz(0.0, 0.075, 0.0),
            ));
            for side in [-1.0f32, 1.0] {
                g.spawn((
                    Jaw(side),
                    Mesh3d(meshes.add(Cuboid::new(0.004, 0.02, 0.008))),
                    MeshMaterial3d(steel.clone()),
                    Transform::from_xyz(side * 0.008, 0.008, 0.0),
                ));
            }
        });
}

/// Keys move the tools; G closes or opens the grasper; R resets; Space pauses.
#[allow(clippy::type_complexity)]
fn keys(
    keys: Res<ButtonInput<KeyCode>>,
    time: Res<Time>,
    mut probe: Query<&mut Transform, (With<Probe>, Without<Grasper>)>,
    mut grasper: Query<(&mut Transform, &mut TissueCollider), With<Grasper>>,
    liver: Query<Entity, With<Liver>>,
    mut clock: ResMut<TissueClock>,
    mut reset: MessageWriter<ResetSoftBody>,
) {
    let axis = |k: [KeyCode; 6]| {
        let v =
            |a: KeyCode, b: KeyCode| keys.pressed(b) as i32 as f32 - keys.pressed(a) as i32 as f32;
        Vec3::new(v(k[0], k[1]), v(k[2], k[3]), v(k[4], k[5]))
    };
    let step = TOOL_SPEED * time.delta_secs();
    use KeyCode::*;
    if let Ok(mut t) = probe.single_mut() {
        t.translation += axis([KeyA, KeyD, KeyQ, KeyE, KeyW, KeyS]) * step;
    }
    if let Ok((mut t, mut c)) = grasper.single_mut() {
        t.translation += axis([KeyJ, KeyL, KeyU, KeyO, KeyI, KeyK]) * step;
        if keys.just_pressed(KeyG)
            && let ColliderKind::Grasper { closed, .. } = &mut c.kind
        {
            *closed = !*closed;
        }
    }
    if keys.just_pressed(KeyR) {
        for e in &liver {
            reset.write(ResetSoftBody { entity: e });
        }
    }
    if keys.just_pressed(Space) {
        clock.toggle_pause();
    }
}

/// `--script`: a probe press, a grasp and lift, and a mouse drag, on a fixed timeline
/// (frames; one step per frame).
#[allow(clippy::type_complexity, clippy::too_many_arguments)]
fn script(
    frames: Res<scene::Frames>,
    mut probe: Query<&mut Transform, (With<Probe>, Without<Grasper>)>,
    mut grasper: Query<(&mut Transform, &mut TissueCollider), With<Grasper>>,
    mut pointer: scene::ScriptPointer,
    mut liver: Query<&mut SoftBody, With<Liver>>,
) {
    let f = frames.count as f32;
    // The neighbour count changes at run time (as from the panel): the body rebuilds
    // its clusters and keeps its pose.
    if frames.count == 320
        && let Ok(mut body) = liver.single_mut()
    {
        body.neighbours = 40;
    }
    let ramp = |a: f32, b: f32| ((f - a) / (b - a)).clamp(0.0, 1.0);
    // Probe: down onto the right lobe (its top settles at y ≈ 0.086 m) and 2 cm into it
    // over frames 40–80, held, back up by 120.
    if let Ok(mut t) = probe.single_mut() {
        t.translation.y = 0.23 - 0.154 * ramp(40.0, 80.0) + 0.154 * ramp(100.0, 120.0);
    }
    // Grasper: down onto the left lobe (it settles on the tray, top at y ≈ 0.019 m) over
    // 120–150, closes at 150, lifts 5 cm by 200, opens at 220.
    if let Ok((mut t, mut c)) = grasper.single_mut() {
        t.translation.y = 0.2 - 0.185 * ramp(120.0, 150.0)
            + 0.05 * ramp(155.0, 200.0)
            + 0.05 * ramp(222.0, 235.0);
        let closed = (150.0..220.0).contains(&f);
        let kind = ColliderKind::Grasper {
            radius: 0.015,
            closed,
        };
        if c.kind != kind {
            c.kind = kind;
        }
    }
    // Mouse: press over the right lobe at 240 (the cursor over a point inside it, so the
    // ray meets its top), pull up and right, release at 310.
    let from = LIVER_AT + Vec3::new(0.05, 0.01, 0.03);
    let to = from + Vec3::new(0.04, 0.05, 0.0);
    let p = from.lerp(to, ramp(250.0, 300.0));
    let pressed = (240.0..310.0).contains(&f);
    if f >= 235.0 {
        pointer.drive(p, pressed);
    }
}

/// `--script`: the largest force each tool felt so far, every 50 frames (the tests read
/// the last line), and the liver's status.
fn script_report(
    frames: Res<scene::Frames>,
    tools: Query<(&Name, &ColliderForce)>,
    liver: Query<(&SoftBody, &SoftBodyStatus), With<Liver>>,
    time: Res<Time<Real>>,
    lattice: Res<Lattice>,
    cpu_world: Option<Res<bevy_tissue::plugin::cpu::CpuWorld>>,
    mut max: Local<Vec<(String, f32)>>,
) {
    for (name, f) in &tools {
        let name = name.to_string();
        match max.iter_mut().find(|m| m.0 == name) {
            Some(m) => m.1 = m.1.max(f.0.length()),
            None => max.push((name, f.0.length())),
        }
    }
    if frames.count.is_multiple_of(50) {
        let list: Vec<String> = max.iter().map(|(n, f)| format!("{n} {f:.4} N")).collect();
        let status = liver
            .single()
            .map(|(b, s)| format!("K = {}, {s:?}", b.neighbours))
            .unwrap_or_default();
        let stepping = match (lattice.0, cpu_world) {
            (true, Some(w)) if w.stepped_on_gpu() => "; lattice stepped on the GPU",
            (true, _) => "; lattice stepped on the CPU",
            _ => "",
        };
        println!(
            "frame {} ({:.2} s): max forces: {}; liver {status}{stepping}",
            frames.count,
            time.elapsed_secs(),
            list.join(", ")
        );
    }
}

/// Opens and closes the grasper's jaws with its state.
fn jaws(grasper: Query<&TissueCollider, With<Grasper>>, mut jaws: Query<(&Jaw, &mut Transform)>) {
    let Ok(c) = grasper.single() else { return };
    let closed = matches!(c.kind, ColliderKind::Grasper { closed: true, .. });
    for (jaw, mut t) in &mut jaws {
        let x = jaw.0 * if closed { 0.003 } else { 0.009 };
        if t.translation.x != x {
            t.translation.x = x;
        }
    }
}

/// Logs readiness, errors, and the tool forces once a second.
fn report(
    mut ready: MessageReader<SoftBodyReady>,
    mut errors: MessageReader<SoftBodyError>,
    tools: Query<(&Name, &ColliderForce)>,
    time: Res<Time>,
    mut last: Local<f32>,
) {
    for r in ready.read() {
        info!("liver ready: {} particles", r.particles);
    }
    for e in errors.read() {
        error!("soft body {}: {}", e.entity, e.error);
    }
    if time.elapsed_secs() - *last >= 1.0 {
        *last = time.elapsed_secs();
        let forces: Vec<String> = tools
            .iter()
            .filter(|(_, f)| f.0 != Vec3::ZERO)
            .map(|(n, f)| format!("{n} {:.3} N", f.0.length()))
            .collect();
        if !forces.is_empty() {
            info!("forces on the tools: {}", forces.join(", "));
        }
    }
}
