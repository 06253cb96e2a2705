//! The GPU world against its CPU twin (core::solver Jacobi, core::knn, core::skin), on
//! whatever Vulkan adapter exists (Mesa's lavapipe in CI). Under `CI=true` a missing
//! adapter is a failure; elsewhere these tests say they were skipped.

mod common;

use bevy_tissue::core::colliders::{Collider, ColliderShape};
use bevy_tissue::core::model::{BodyDesc, Material, Model, PinRegion};
use bevy_tissue::core::procedural;
use bevy_tissue::core::sampling::Resolution;
use bevy_tissue::core::solver::{Control, Method, Solver, SolverSettings, State};
use bevy_tissue::core::{TissueError, knn, skin};
use bevy_tissue::gpu::world::{read_buffer, read_u32, read_vec3};
use bevy_tissue::gpu::{GpuWorld, Headless, NoTiming, headless};
use common::lattice_box_at;
use glam::{Quat, Vec3};
use std::sync::OnceLock;

/// The device of these tests: held to WebGPU's default limits (8 storage buffers per
/// stage, 16 KiB of workgroup memory, 256 invocations), whatever the adapter offers, so
/// that every kernel is tested as a browser or a Mac would run it.
fn gpu() -> Option<&'static Headless> {
    static GPU: OnceLock<Result<Headless, String>> = OnceLock::new();
    held(GPU.get_or_init(|| {
        bevy_tissue::gpu::headless_with(bevy::render::settings::WgpuSettings {
            constrained_limits: Some(bevy::render::settings::WgpuLimits::default()),
            ..Default::default()
        })
    }))
}

/// The device with the adapter's own limits (the optional workgroup-per-body kernel
/// needs more than WebGPU guarantees).
fn gpu_full() -> Option<&'static Headless> {
    static GPU: OnceLock<Result<Headless, String>> = OnceLock::new();
    held(GPU.get_or_init(headless))
}

fn held(device: &'static Result<Headless, String>) -> Option<&'static Headless> {
    match device {
        Ok(h) => Some(h),
        Err(e) => {
            if std::env::var("CI").is_ok_and(|v| v == "true") {
                panic!("CI=true but no GPU adapter: {e}");
            }
            eprintln!("skipped: {e}");
            None
        }
    }
}

fn settings() -> SolverSettings {
    SolverSettings {
        method: Method::Jacobi,
        iterations: 10,
        substeps: 2,
        ..Default::default()
    }
}

fn body(material: Material, at: Vec3, particles: u32, pins: Vec<PinRegion>) -> BodyDesc {
    BodyDesc {
        resolution: Resolution::Particles(particles),
        neighbours: 16,
        material,
        pins,
        translation: at,
        rotation: Quat::from_rotation_z(0.3),
        discretisation: bevy_tissue::core::model::Discretisation::Clusters,
        ..Default::default()
    }
}

/// A box hanging from its top face, pressed by a sphere, over the ground.
fn hanging(material: Material) -> (Model, Vec<Collider>) {
    let mut model = Model::new();
    let mesh = procedural::cuboid(Vec3::new(0.06, 0.03, 0.03), 4);
    let pin = PinRegion::HalfSpace {
        point: Vec3::new(0.0, 0.025, 0.0),
        normal: Vec3::Y,
    };
    model
        .add_body(
            &mesh,
            &body(material, Vec3::new(0.0, 0.2, 0.0), 600, vec![pin]),
        )
        .unwrap();
    let mut sphere = Collider::new(
        ColliderShape::Sphere { radius: 0.03 },
        Vec3::new(0.07, 0.17, 0.0),
        Quat::IDENTITY,
    );
    sphere.velocity = Vec3::new(-0.1, 0.0, 0.0);
    (model, vec![Collider::ground(0.175), sphere])
}

/// A GPU world of `model` at rest, with the test settings and no all-particle search.
fn fresh_world(g: &Headless, model: &Model) -> GpuWorld {
    fresh_world_with(g, model, settings())
}

fn fresh_world_with(g: &Headless, model: &Model, s: SolverSettings) -> GpuWorld {
    GpuWorld::new(&g.device, &g.kernels, model, &State::new(model), s, 0).unwrap()
}

/// Runs `steps` steps on the GPU (in chunks, one submission each).
fn run_gpu(g: &Headless, world: &mut GpuWorld, colliders: &[Collider], steps: u32) -> Vec<Vec3> {
    world.set_colliders(&g.queue, colliders).unwrap();
    world.write_params(&g.queue);
    let mut left = steps;
    while left > 0 {
        let chunk = left.min(50);
        let mut enc = g.device.create_command_encoder(&Default::default());
        world.record_steps(&mut enc, &g.kernels, chunk, &mut NoTiming);
        g.queue.submit([enc.finish()]);
        left -= chunk;
    }
    read_vec3(
        &g.device,
        &g.queue,
        world.positions(),
        world.particle_count(),
    )
}

fn run_cpu(model: &Model, colliders: &[Collider], steps: u32) -> (State, Vec<Vec3>) {
    run_cpu_with(model, colliders, steps, settings())
}

fn run_cpu_with(
    model: &Model,
    colliders: &[Collider],
    steps: u32,
    s: SolverSettings,
) -> (State, Vec<Vec3>) {
    let mut state = State::new(model);
    let mut solver = Solver::new(model, s).unwrap();
    let control = Control {
        colliders: colliders.to_vec(),
    };
    let mut forces = Vec::new();
    for _ in 0..steps {
        forces = solver
            .step(model, &mut state, &control)
            .unwrap()
            .collider_forces;
    }
    (state, forces)
}

fn max_dist(a: &[Vec3], b: &[Vec3]) -> f32 {
    a.iter()
        .zip(b)
        .map(|(p, q)| p.distance(*q))
        .fold(0.0, f32::max)
}

/// GPU positions `x` after 200 steps agree with the CPU's within 1e-4 of the body size,
/// and the scene moved (more than 1% of the size) so that the agreement means something.
fn assert_close_after_200_steps(label: &str, model: &Model, x: &[Vec3], cpu: &[Vec3]) {
    let size = model.bodies[0].size;
    let moved = max_dist(cpu, &State::new(model).x);
    let d = max_dist(x, cpu);
    eprintln!("{label}: GPU–CPU {d:.3e} m, body size {size:.3} m, moved {moved:.3e} m");
    assert!(moved > 0.01 * size, "the scene must deform ({moved} m)");
    assert!(
        d < 1e-4 * size,
        "{label}: GPU and CPU differ by {d} m after 200 steps (size {size} m)"
    );
}

#[test]
fn gpu_matches_cpu_jacobi_after_200_steps_both_models() {
    let Some(g) = gpu() else { return };
    for material in [
        Material::ShapeMatching { stiffness: 0.6 },
        Material::Hyperelastic {
            youngs_modulus: 20_000.0,
            poisson_ratio: 0.4,
        },
    ] {
        let (model, colliders) = hanging(material);
        let (cpu, cpu_forces) = run_cpu(&model, &colliders, 200);
        // Both cluster kernels: a thread per cluster, and 8 lanes (the default for a
        // range this small).
        for lanes_below in [0, u32::MAX] {
            let state = State::new(&model);
            let mut world =
                GpuWorld::new(&g.device, &g.kernels, &model, &state, settings(), 0).unwrap();
            world.lane_clusters_below = lanes_below;
            let x = run_gpu(g, &mut world, &colliders, 200);
            let kernel = if lanes_below == 0 {
                "a thread per cluster"
            } else {
                "8 lanes"
            };
            assert_close_after_200_steps(&format!("{material:?}, {kernel}"), &model, &x, &cpu.x);
            // Collider forces of the last step.
            let bytes = read_buffer(
                &g.device,
                &g.queue,
                world.forces(),
                world.force_offset(),
                colliders.len() as u64 * 16,
            );
            let gf: &[[f32; 4]] = bytemuck::cast_slice(&bytes);
            let gpu_forces: Vec<Vec3> = (0..colliders.len())
                .map(|k| Vec3::new(gf[k][0], gf[k][1], gf[k][2]))
                .collect();
            // The tissue's total push on the colliders agrees tightly. A particle pressed by
            // both the sphere and the ground charges its whole correction to the collider
            // that touched it last, so a few µm of rounding can move one particle's share
            // (~0.02 N here) from one to the other: each collider within 2% of the total.
            let (gt, ct) = (
                gpu_forces.iter().sum::<Vec3>(),
                cpu_forces.iter().sum::<Vec3>(),
            );
            assert!(
                gt.distance(ct) <= 1e-3 * ct.length(),
                "{material:?}: total GPU force {gt} N, CPU {ct} N"
            );
            for (k, (gv, f)) in gpu_forces.iter().zip(&cpu_forces).enumerate() {
                assert!(
                    gv.distance(*f) <= 2e-2 * ct.length(),
                    "{material:?}, collider {k}: GPU force {gv} N, CPU {f} N"
                );
            }
            assert!(
                cpu_forces[0].y < 0.0,
                "the tissue must press on the ground: {:?}",
                cpu_forces[0]
            );
        }
    }
}

#[test]
fn gpu_hierarchy_matches_the_cpu_hierarchy_after_200_steps() {
    // A bar with two coarse levels hanging from one end and touching the ground (the
    // coarse levels meet the collider too), batched with a flat body: levels exist for
    // one body only.
    let Some(g) = gpu() else { return };
    let hd = bevy_tissue::core::hierarchy::HierarchyDesc {
        levels: Some(3),
        ..Default::default()
    };
    for material in [
        Material::ShapeMatching { stiffness: 1.0 },
        Material::Hyperelastic {
            youngs_modulus: 50_000.0,
            poisson_ratio: 0.4,
        },
    ] {
        let mut model = Model::new();
        let pin = PinRegion::HalfSpace {
            point: Vec3::new(-0.05, 0.0, 0.0),
            normal: -Vec3::X,
        };
        let mut desc = body(material, Vec3::new(0.0, 0.2, 0.0), 1500, vec![pin]);
        desc.hierarchy = Some(hd);
        model
            .add_body(&procedural::cuboid(Vec3::new(0.06, 0.03, 0.03), 4), &desc)
            .unwrap();
        let top = PinRegion::HalfSpace {
            point: Vec3::new(0.0, 0.01, 0.0),
            normal: Vec3::Y,
        };
        model
            .add_body(
                &procedural::icosphere(0.02, 2),
                &body(material, Vec3::new(0.15, 0.25, 0.0), 200, vec![top]),
            )
            .unwrap();
        assert_eq!(model.levels.len(), 2);
        let colliders = vec![Collider::ground(0.15)];
        let (cpu, _) = run_cpu(&model, &colliders, 200);
        let state = State::new(&model);
        let mut world =
            GpuWorld::new(&g.device, &g.kernels, &model, &state, settings(), 0).unwrap();
        let x = run_gpu(g, &mut world, &colliders, 200);
        assert_close_after_200_steps(&format!("hierarchy, {material:?}"), &model, &x, &cpu.x);
    }
}

#[test]
fn knn_on_the_gpu_equals_the_cpu() {
    let Some(g) = gpu() else { return };
    let mut model = Model::new();
    model
        .add_body(
            &procedural::cuboid(Vec3::splat(0.05), 4),
            &body(Material::default(), Vec3::ZERO, 1500, vec![]),
        )
        .unwrap();
    let mut state = State::new(&model);
    // A lattice (many exact ties), the same points jittered, and then squashed to a
    // quarter of their size (the grid's cells keep the body's spacing, so each holds
    // ~60 particles: more candidates than a search round takes at once).
    for (jitter, squash) in [(0.0f32, false), (0.3, false), (0.0, true)] {
        let mut rng = 12345u32;
        let spacing = model.bodies[0].spacing;
        if squash {
            for p in &mut state.x {
                *p *= 0.25;
            }
        }
        for p in &mut state.x {
            let mut r = || {
                rng ^= rng << 13;
                rng ^= rng >> 17;
                rng ^= rng << 5;
                rng as f32 / u32::MAX as f32 - 0.5
            };
            *p += Vec3::new(r(), r(), r()) * jitter * spacing;
        }
        for k in [1u32, 16, 32, 64] {
            let mut world =
                GpuWorld::new(&g.device, &g.kernels, &model, &state, settings(), k).unwrap();
            let mut enc = g.device.create_command_encoder(&Default::default());
            world.record_knn_all(&mut enc, &g.kernels, &mut NoTiming);
            world.write_params(&g.queue);
            g.queue.submit([enc.finish()]);
            let n = world.particle_count();
            let got = read_u32(&g.device, &g.queue, world.knn_lists(), n as u64 * k as u64);
            let want = knn::knn_all(&state.x, k as usize, 0).unwrap();
            let wrong = got.iter().zip(&want).filter(|(a, b)| a != b).count();
            assert_eq!(
                wrong, 0,
                "jitter {jitter}, squashed {squash}, K = {k}: {wrong} entries differ"
            );
            // Again after the points moved by up to half a spacing: the search starts
            // from the lists above (their distances now bound the K-th best) and must
            // still equal the CPU's.
            let moved: Vec<Vec3> = state
                .x
                .iter()
                .enumerate()
                .map(|(i, p)| {
                    let a = i as f32 * 0.618;
                    *p + Vec3::new(a.sin(), (1.7 * a).cos(), (2.3 * a).sin()) * 0.3 * spacing
                })
                .collect();
            let x4: Vec<[f32; 4]> = moved.iter().map(|p| p.extend(0.0).to_array()).collect();
            g.queue
                .write_buffer(world.positions(), 0, bytemuck::cast_slice(&x4));
            let mut enc = g.device.create_command_encoder(&Default::default());
            world.record_knn_all(&mut enc, &g.kernels, &mut NoTiming);
            g.queue.submit([enc.finish()]);
            let got = read_u32(&g.device, &g.queue, world.knn_lists(), n as u64 * k as u64);
            let want = knn::knn_all(&moved, k as usize, 0).unwrap();
            let wrong = got.iter().zip(&want).filter(|(a, b)| a != b).count();
            assert_eq!(
                wrong, 0,
                "moved, jitter {jitter}, squashed {squash}, K = {k}: {wrong} entries differ"
            );
        }
    }
}

#[test]
fn contact_candidates_equal_the_cpu() {
    let Some(g) = gpu() else { return };
    let mut model = Model::new();
    let m = Material::default();
    let sphere = procedural::icosphere(0.03, 2);
    model
        .add_body(&sphere, &body(m, Vec3::ZERO, 400, vec![]))
        .unwrap();
    model
        .add_body(&sphere, &body(m, Vec3::new(0.055, 0.01, 0.0), 300, vec![]))
        .unwrap();
    let state = State::new(&model);
    let mut cpu = Solver::new(&model, settings()).unwrap();
    cpu.refresh_contacts(&model, &state.x);
    let mut world = GpuWorld::new(&g.device, &g.kernels, &model, &state, settings(), 0).unwrap();
    assert_eq!(world.contact_neighbours(), 16);
    run_gpu(g, &mut world, &[], 1);
    let pairs = assert_contact_lists(g, &world, &cpu, "first search");
    assert!(
        pairs > 100,
        "the bodies must touch ({pairs} candidate pairs)"
    );
    // Two searches later (every `knn_every` = 10 steps, each starting from the lists
    // before it) the lists still equal the CPU's for the positions searched: those at
    // the start of step 20.
    assert_eq!(settings().knn_every, 10);
    let x = run_gpu(g, &mut world, &[], 19);
    run_gpu(g, &mut world, &[], 1);
    cpu.refresh_contacts(&model, &x);
    assert_contact_lists(g, &world, &cpu, "search at step 20");
}

/// The GPU's contact lists equal `cpu`'s (its last `refresh_contacts`); returns the
/// number of candidate pairs.
fn assert_contact_lists(g: &Headless, world: &GpuWorld, cpu: &Solver, label: &str) -> usize {
    let (start, list) = cpu.contact_lists();
    let n = world.particle_count() as usize;
    let k = world.contact_neighbours() as usize;
    let got = read_u32(&g.device, &g.queue, world.contact_lists(), (n * k) as u64);
    let mut pairs = 0;
    for i in 0..n {
        let want = &list[start[i] as usize..start[i + 1] as usize];
        let row: Vec<u32> = got[i * k..(i + 1) * k]
            .iter()
            .copied()
            .filter(|&j| j != u32::MAX)
            .collect();
        assert_eq!(row, want, "{label}, particle {i}");
        pairs += want.len();
    }
    pairs
}

#[test]
fn small_shape_matching_bodies_in_a_workgroup_each_match_the_cpu() {
    // Three 300-particle balls dropped side by side onto the ground (contacts on, the
    // balls apart: stacked balls make the comparison with the CPU chaotic), and a fourth
    // like the first beside it, within the contact reach but not touching (they fall
    // alike): the contact broad phase finds the first and the fourth near each other,
    // so they run one iteration per dispatch with the contact pass between, and the
    // other two all iterations of a substep in one dispatch. Every body fits `body.wgsl`,
    // which needs the adapter's own limits.
    let Some(g) = gpu_full() else { return };
    let mesh = procedural::icosphere(0.03, 2);
    let stiffness = [0.6, 0.7, 0.8, 0.6];
    let build = |beside: f32| {
        let mut model = Model::new();
        for (i, at) in [
            Vec3::new(-0.1, 0.04, 0.0),
            Vec3::new(0.0, 0.06, 0.0),
            Vec3::new(0.1, 0.08, 0.01),
            Vec3::new(-0.1 - beside, 0.04, 0.0),
        ]
        .into_iter()
        .enumerate()
        {
            let m = Material::ShapeMatching {
                stiffness: stiffness[i],
            };
            model.add_body(&mesh, &body(m, at, 300, vec![])).unwrap();
        }
        model
    };
    // The gap between the first and the fourth ball's particles: 3 particle radii (the
    // contact distance is 2, the reach 4).
    let gap = |model: &Model| {
        let x = model.placed_rest();
        let (a, d) = (&model.bodies[0], &model.bodies[3]);
        let mut min = f32::MAX;
        for i in a.first..a.first + a.count {
            for j in d.first..d.first + d.count {
                min = min.min(x[i as usize].distance(x[j as usize]));
            }
        }
        min
    };
    let trial = build(0.07);
    let r = trial.bodies[0].radius;
    let model = build(0.07 + 3.0 * r - gap(&trial));
    let d = gap(&model);
    assert!(
        d > 2.2 * r && d < 3.8 * r,
        "the fourth ball must be within the reach without touching: gap {d} m, radius {r} m"
    );
    let colliders = [Collider::ground(0.0)];
    let (cpu, _) = run_cpu(&model, &colliders, 200);
    let mut runs = Vec::new();
    for on in [false, true] {
        let mut world = fresh_world(g, &model);
        assert!(world.contact_neighbours() > 0, "contacts must be on");
        assert!(
            world.body_kernel(),
            "the bodies fit body.wgsl on this adapter ({})",
            g.adapter
        );
        world.set_body_kernel(&g.queue, on);
        let x = run_gpu(g, &mut world, &colliders, 200);
        let label = if on {
            "a workgroup per body"
        } else {
            "cluster and gather kernels"
        };
        assert_close_after_200_steps(label, &model, &x, &cpu.x);
        // The broad phase's flags.
        let near = world.read_near_flags(&g.device, &g.queue);
        assert_eq!(near, [true, false, false, true], "{label}: near flags");
        runs.push(x);
    }
    // The two GPU paths differ only in the order of the gather's sums.
    let d = max_dist(&runs[0], &runs[1]);
    let size = model.bodies[0].size;
    eprintln!("workgroup per body against the cluster and gather kernels: {d:.3e} m");
    assert!(d < 1e-4 * size, "the two GPU paths differ by {d} m");
}

#[test]
fn broad_phase_flags_match_the_cpu() {
    // 600 small balls in a row, each pair of neighbours either within the contact reach
    // or well beyond it (an irregular pattern): the GPU's near flags equal the CPU twin's
    // (`knn::near_bodies`).
    let Some(g) = gpu() else { return };
    let mut one = Model::new();
    let m = Material::ShapeMatching { stiffness: 1.0 };
    one.add_body(
        &procedural::icosphere(0.01, 1),
        &body(m, Vec3::ZERO, 20, vec![]),
    )
    .unwrap();
    let rest = one.placed_rest();
    let (lo, hi) = rest
        .iter()
        .fold((Vec3::MAX, Vec3::MIN), |(l, h), p| (l.min(*p), h.max(*p)));
    let reach = knn::contact_reach_bound(one.bodies[0].radius);
    let nb = 600;
    let mut model = Model::new();
    let mut at = 0.0;
    for i in 0..nb {
        let mut b = one.clone();
        b.bodies[0].translation = Vec3::new(at, 0.5, 0.0);
        model.append(&b);
        let near = (i * 7919) % 11 < 4;
        at += hi.x - lo.x + if near { 0.5 * reach } else { 3.0 * reach };
    }
    let boxes = knn::body_boxes(
        &model.placed_rest(),
        model.bodies.iter().map(|b| (b.first, b.count)),
    );
    let want = knn::near_bodies(&boxes, reach);
    let near = want.iter().filter(|n| **n).count();
    assert!(near > 100 && near < nb - 100, "{near} near");
    let mut world = fresh_world(g, &model);
    run_gpu(g, &mut world, &[], 1);
    assert_eq!(
        world.read_near_flags(&g.device, &g.queue),
        want,
        "near flags"
    );
}

#[test]
fn touching_bodies_push_apart_as_on_the_cpu() {
    // Two 300-particle balls placed 5 mm into each other, falling together: only the
    // particle contacts separate them. Both GPU paths (a workgroup per body with the
    // contact pass folded into the next iteration, and the cluster, gather and contact
    // kernels) against the CPU Jacobi solver, with contacts in every iteration and in
    // every third (`contact_every`: blocks of 3, 3, 3 and 1 iterations), with the
    // contacts over-relaxed (`contact_relaxation` 2), and both in every 2nd iteration and
    // over-relaxed (the plugin's default).
    let Some(g) = gpu() else { return };
    let mesh = procedural::icosphere(0.03, 2);
    let mut model = Model::new();
    for (x, k) in [(0.0f32, 0.7f32), (0.055, 0.8)] {
        let m = Material::ShapeMatching { stiffness: k };
        model
            .add_body(&mesh, &body(m, Vec3::new(x, 0.5, 0.0), 300, vec![]))
            .unwrap();
    }
    let centre = |x: &[Vec3], b: usize| {
        let r = model.bodies[b].range();
        x[r.clone()].iter().copied().sum::<Vec3>() / r.len() as f32
    };
    let gap = |x: &[Vec3]| centre(x, 1).x - centre(x, 0).x;
    let steps = 60;
    // (2, 2.0) is the plugin's default (`TissueSettings`).
    for (every, omega) in [(1, 1.0), (3, 1.0), (1, 2.0), (2, 2.0)] {
        let s = SolverSettings {
            contact_every: every,
            contact_relaxation: omega,
            ..settings()
        };
        let (cpu, _) = run_cpu_with(&model, &[], steps, s.clone());
        let start = gap(&State::new(&model).x);
        eprintln!(
            "contacts every {every}, ω {omega}: centres {start:.4} m apart at the start, \
             {:.4} m on the CPU",
            gap(&cpu.x)
        );
        assert!(
            gap(&cpu.x) > start + 0.002,
            "contacts every {every}: the contacts must push the balls apart ({start} → {} m)",
            gap(&cpu.x)
        );
        touching_balls_on_the_gpu(g, &model, s, &cpu.x, steps);
    }
}

fn touching_balls_on_the_gpu(
    g: &Headless,
    model: &Model,
    s: SolverSettings,
    cpu: &[Vec3],
    steps: u32,
) {
    let size = model.bodies[0].size;
    let (every, omega) = (s.contact_every, s.contact_relaxation);
    for on in [true, false] {
        // The workgroup-per-body kernel needs the adapter's own limits.
        let g = if on { gpu_full().unwrap_or(g) } else { g };
        let mut world = fresh_world_with(g, model, s.clone());
        world.set_body_kernel(&g.queue, on);
        let x = run_gpu(g, &mut world, &[], steps);
        let d = max_dist(&x, cpu);
        eprintln!(
            "contacts every {every}, ω {omega}, body kernel {on}: GPU–CPU {d:.3e} m (size \
             {size:.3} m)"
        );
        // Looser than the 1e-4 of the scenes without contact: a contact acts or not at a
        // distance threshold, so a rounding difference (the gather kernel sums in another
        // order than the CPU) can switch one on a step earlier. Measured on lavapipe:
        // 8.8e-6 m with the workgroup kernel, 4.0e-5 m with the cluster and gather
        // kernels; the balls move 21 mm apart.
        assert!(
            d < 1e-3 * size,
            "contacts every {every}, ω {omega}, body kernel {on}: GPU and CPU differ by {d} m after \
             {steps} steps of contact"
        );
    }
}

#[test]
fn batched_bodies_equal_each_alone() {
    let Some(g) = gpu() else { return };
    let a = body(
        Material::ShapeMatching { stiffness: 0.5 },
        Vec3::new(-0.5, 0.1, 0.0),
        300,
        vec![],
    );
    let b = body(
        Material::Hyperelastic {
            youngs_modulus: 5_000.0,
            poisson_ratio: 0.45,
        },
        Vec3::new(0.5, 0.12, 0.0),
        400,
        vec![],
    );
    let mesh = procedural::icosphere(0.04, 2);
    let colliders = [Collider::ground(0.0)];
    let alone = |d: &BodyDesc| {
        let mut m = Model::new();
        m.add_body(&mesh, d).unwrap();
        let mut w = fresh_world(g, &m);
        run_gpu(g, &mut w, &colliders, 120)
    };
    let (xa, xb) = (alone(&a), alone(&b));
    let mut both = Model::new();
    both.add_body(&mesh, &a).unwrap();
    both.add_body(&mesh, &b).unwrap();
    let mut w = fresh_world(g, &both);
    let x = run_gpu(g, &mut w, &colliders, 120);
    let (na, _) = (xa.len(), xb.len());
    let da = max_dist(&x[..na], &xa);
    let db = max_dist(&x[na..], &xb);
    assert!(xa[0].y < 0.09, "body a must have fallen ({})", xa[0].y);
    assert_eq!((da, db), (0.0, 0.0), "batched differs from alone");
}

/// Skins every body into the world's own surface and reads it back (position, normal,
/// uv per render vertex).
fn draw_surface(g: &Headless, world: &GpuWorld) -> Vec<[f32; 8]> {
    world.set_draw(&g.queue, &world.surface_draw());
    let runs: Vec<(u32, u32)> = world
        .ranges
        .iter()
        .map(|r| (r.vfirst, r.vfirst + r.vcount))
        .collect();
    let group = world.slab_group(&g.device, &g.kernels, world.surface());
    let mut enc = g.device.create_command_encoder(&Default::default());
    world.record_draw(
        &g.queue,
        &mut enc,
        &g.kernels,
        &[(&group, &runs[..])],
        &mut NoTiming,
    );
    g.queue.submit([enc.finish()]);
    let nv = world.vertex_count() as u64;
    let bytes = read_buffer(&g.device, &g.queue, world.surface(), 0, nv * 32);
    bytemuck::pod_collect_to_vec(&bytes)
}

#[test]
fn drawn_surface_equals_cpu_skinning() {
    let Some(g) = gpu() else { return };
    let (model, colliders) = hanging(Material::default());
    let mut world = fresh_world(g, &model);
    let x = run_gpu(g, &mut world, &colliders, 60);
    let vtx = draw_surface(g, &world);
    let sk = &model.bodies[0].skin;
    let f = Solver::deformation_gradients(&model, &x);
    let mut pos = vec![Vec3::ZERO; sk.rest_vertices.len()];
    skin::skin_positions(sk, &x, &model.rest, &f, &mut pos);
    let mut nrm = vec![Vec3::ZERO; pos.len()];
    skin::skin_normals(sk, &pos, &mut nrm);
    let size = model.bodies[0].size;
    let mut dp = 0.0f32;
    let mut dn = 0.0f32;
    for (i, v) in vtx.iter().enumerate() {
        dp = dp.max(Vec3::new(v[0], v[1], v[2]).distance(pos[i]));
        dn = dn.max(Vec3::new(v[3], v[4], v[5]).distance(nrm[i]));
    }
    assert!(dp < 1e-5 * size, "skinned positions differ by {dp} m");
    assert!(dn < 1e-3, "normals differ by {dn}");
    assert!(max_dist(&pos, &sk.rest_vertices) > 0.0);
}

#[test]
fn a_model_too_big_for_the_adapter_is_a_clear_error() {
    let Some(g) = gpu() else { return };
    let (model, _) = hanging(Material::default());
    let mut limits = g.device.limits();
    limits.max_storage_buffer_binding_size = 64 * 1024;
    let err = GpuWorld::check_limits(&limits, &model, &settings()).unwrap_err();
    assert!(
        matches!(
            err,
            TissueError::GpuLimit {
                what: "cluster rest data",
                ..
            }
        ),
        "{err}"
    );
    assert!(err.to_string().contains("too big for the GPU"), "{err}");
    // And the real adapter takes it.
    GpuWorld::check_limits(&g.device.limits(), &model, &settings()).unwrap();
}

#[test]
fn a_diverging_body_is_held_and_flagged_and_does_not_poison_the_others() {
    let Some(g) = gpu() else { return };
    let mesh = procedural::icosphere(0.04, 2);
    let mut model = Model::new();
    for x in [-0.5f32, 0.5] {
        model
            .add_body(
                &mesh,
                &body(Material::default(), Vec3::new(x, 0.1, 0.0), 300, vec![]),
            )
            .unwrap();
    }
    let mut state = State::new(&model);
    state.v[3] = Vec3::NAN; // body 0 is poisoned
    let mut world = GpuWorld::new(&g.device, &g.kernels, &model, &state, settings(), 0).unwrap();
    let x = run_gpu(g, &mut world, &[Collider::ground(0.0)], 30);
    assert!(
        x.iter().all(|p| p.is_finite()),
        "NaN escaped into the positions"
    );
    let flags = read_u32(&g.device, &g.queue, world.status(), 2);
    assert!(flags[0] != 0 && flags[1] == 0, "status flags {flags:?}");
    // Body 1 is exactly what it would be alone.
    let mut alone = Model::new();
    alone
        .add_body(
            &mesh,
            &body(Material::default(), Vec3::new(0.5, 0.1, 0.0), 300, vec![]),
        )
        .unwrap();
    let mut w1 = fresh_world(g, &alone);
    let x1 = run_gpu(g, &mut w1, &[Collider::ground(0.0)], 30);
    let n0 = model.bodies[0].count as usize;
    assert_eq!(max_dist(&x[n0..], &x1), 0.0);
}

#[test]
fn gpu_steps_are_deterministic_run_to_run() {
    let Some(g) = gpu() else { return };
    // Two bodies in contact (contacts, grid, KNN, colliders all on): the same inputs give
    // bit-identical positions.
    let mut model = Model::new();
    let sphere = procedural::icosphere(0.03, 2);
    let m = Material::ShapeMatching { stiffness: 0.9 };
    model
        .add_body(&sphere, &body(m, Vec3::new(0.0, 0.04, 0.0), 300, vec![]))
        .unwrap();
    model
        .add_body(&sphere, &body(m, Vec3::new(0.01, 0.11, 0.0), 300, vec![]))
        .unwrap();
    let run = || {
        let mut w = fresh_world(g, &model);
        run_gpu(g, &mut w, &[Collider::ground(0.0)], 60)
    };
    let (a, b) = (run(), run());
    let bits = |x: &[Vec3]| {
        x.iter()
            .flat_map(|p| p.to_array().map(f32::to_bits))
            .collect::<Vec<_>>()
    };
    assert_eq!(bits(&a), bits(&b), "two runs differ");
    assert!(
        a[400].y < 0.1,
        "the top body must have fallen onto the other"
    );
}

/// A grasper closes on the free end of a pinned bar, pulls it down and sideways while
/// turning, then lets go: the GPU (which takes and holds particles in its predict kernel)
/// against the CPU solver after each phase, particles held, positions and the force.
#[test]
fn grasper_take_hold_and_release_match_the_cpu() {
    use bevy_tissue::core::colliders::GraspMode;
    let Some(g) = gpu() else { return };
    let mut model = Model::new();
    let mesh = procedural::cuboid(Vec3::new(0.06, 0.015, 0.015), 4);
    let pin = PinRegion::HalfSpace {
        point: Vec3::new(-0.05, 0.0, 0.0),
        normal: Vec3::NEG_X,
    };
    let desc = BodyDesc {
        rotation: Quat::IDENTITY,
        ..body(
            Material::Hyperelastic {
                youngs_modulus: 30_000.0,
                poisson_ratio: 0.45,
            },
            Vec3::new(0.0, 0.3, 0.0),
            500,
            vec![pin],
        )
    };
    model.add_body(&mesh, &desc).unwrap();
    let start = Vec3::new(0.055, 0.3, 0.0);
    let speed = Vec3::new(0.02, -0.06, 0.0); // m/s
    let grasper = |mode, t: f32| Collider {
        velocity: speed,
        ..Collider::new(
            ColliderShape::Grasper {
                radius: 0.012,
                mode,
            },
            start + speed * t,
            Quat::from_rotation_x(0.5 * t),
        )
    };
    // Four substeps: the spring-back after release stays smooth (at one substep this
    // stretched hyperelastic bar recoils chaotically, and CPU and GPU part ways).
    let settings = SolverSettings {
        substeps: 4,
        ..settings()
    };
    let dt = settings.dt;
    // (mode, steps): capture, hold while moving, let go.
    let phases = [
        (GraspMode::Capture, 2u32),
        (GraspMode::Hold, 60),
        (GraspMode::Open, 30),
    ];
    let mut cpu = State::new(&model);
    let mut solver = Solver::new(&model, settings.clone()).unwrap();
    let mut world = GpuWorld::new(&g.device, &g.kernels, &model, &cpu, settings, 0).unwrap();
    let size = model.bodies[0].size;
    let mut t = 0.0;
    let mut held_rest = Vec::new();
    for (mode, steps) in phases {
        let mut force = Vec3::ZERO;
        for _ in 0..steps {
            let colliders = vec![Collider::ground(0.0), grasper(mode, t)];
            let control = Control {
                colliders: colliders.clone(),
            };
            force = solver
                .step(&model, &mut cpu, &control)
                .unwrap()
                .collider_forces[1];
            let xg = run_gpu(g, &mut world, &colliders, 1);
            t += dt;
            if std::env::var("GRASP_TRACE").is_ok() {
                let vmax = cpu.v.iter().map(|v| v.length()).fold(0.0, f32::max);
                eprintln!(
                    "{mode:?} t {t:.3}: GPU–CPU {:.3e} m, max speed {vmax:.3} m/s",
                    max_dist(&xg, &cpu.x)
                );
            }
        }
        let x = read_vec3(
            &g.device,
            &g.queue,
            world.positions(),
            world.particle_count(),
        );
        let (grab_buffer, grab_at) = world.grabs();
        let grabs = read_buffer(
            &g.device,
            &g.queue,
            grab_buffer,
            grab_at,
            cpu.x.len() as u64 * 16,
        );
        let grabs: &[[f32; 4]] = bytemuck::cast_slice(&grabs);
        let held_cpu: Vec<usize> = (0..cpu.x.len())
            .filter(|&i| cpu.grab[i].collider == 1)
            .collect();
        let held_gpu: Vec<usize> = (0..cpu.x.len()).filter(|&i| grabs[i][3] == 2.0).collect();
        let d = max_dist(&x, &cpu.x);
        eprintln!(
            "{mode:?}: {} held (GPU {}), GPU–CPU {d:.3e} m, force on the grasper {force} N",
            held_cpu.len(),
            held_gpu.len()
        );
        assert_eq!(held_cpu, held_gpu, "{mode:?}: the same particles are held");
        assert!(d < 1e-4 * size, "{mode:?}: GPU and CPU differ by {d} m");
        match mode {
            GraspMode::Capture => {
                assert!(held_cpu.len() >= 3, "the grasper takes the bar's end");
                held_rest = held_cpu;
            }
            GraspMode::Hold => {
                assert_eq!(held_cpu, held_rest, "holding takes nothing new");
                // Held particles moved rigidly with the grasper: their distances to its
                // origin are the ones they had when taken.
                let c = grasper(mode, t - dt);
                for &i in &held_cpu {
                    let target = c.position + c.rotation * cpu.grab[i].offset;
                    assert!(cpu.x[i].distance(target) < 1e-5, "particle {i} is held");
                }
                // The grasper moved 2 cm away from the pinned end: the stretched bar pulls
                // it back along the bar.
                assert!(
                    force.x < -0.05 && force.x.abs() > force.y.abs(),
                    "pull on the grasper: {force} N"
                );
                let gpu_force = read_buffer(
                    &g.device,
                    &g.queue,
                    world.forces(),
                    world.force_offset() + 16,
                    16,
                );
                let gf: &[f32] = bytemuck::cast_slice(&gpu_force);
                let gv = Vec3::new(gf[0], gf[1], gf[2]);
                assert!(
                    gv.distance(force) <= 2e-3 * force.length(),
                    "GPU force {gv} N, CPU {force} N"
                );
            }
            GraspMode::Open => {
                assert!(held_cpu.is_empty(), "opening lets go");
            }
        }
    }
}

/// A device held to WebGPU's default limits (8 storage buffers per shader stage, 4 bind
/// groups, 16 KiB of workgroup memory, 256 invocations per workgroup) makes every kernel
/// of the render graph's world but the workgroup-per-body ones, whose workgroups are
/// larger than that; every pipeline made binds at most 8 storage buffers in at most 4
/// groups, and a world steps on it.
#[test]
fn kernels_fit_webgpu_default_limits() {
    let Some(g) = gpu() else { return };
    assert!(
        g.kernels.body.is_none(),
        "body.wgsl needs 32 KiB and 512 threads"
    );
    let all = g.kernels.all();
    assert_eq!(all.len(), 33, "every kernel made");
    for (i, k) in all.iter().enumerate() {
        assert_eq!(k.id, i);
        assert!(
            k.storage_buffers() <= 8,
            "{} binds {}",
            k.name,
            k.storage_buffers()
        );
        assert!(k.groups.len() <= 4, "{}", k.name);
    }
    // Two shape-matching boxes side by side falling onto the ground, touching each other
    // (particle contacts on, the hierarchy off): held to WebGPU's limits, the world steps
    // as on the full adapter (with its workgroup-per-body kernel switched off, which
    // sums in another order).
    let Some(full) = gpu_full() else { return };
    let (model, s, ground) = boxes_on_the_ground(0.5, &[-0.031, 0.031]);
    let mut held = fresh_world_with(g, &model, s.clone());
    let mut wide = fresh_world_with(full, &model, s);
    wide.set_body_kernel(&full.queue, false);
    let a = run_gpu(g, &mut held, &ground, 30);
    let b = run_gpu(full, &mut wide, &ground, 30);
    assert!(a.iter().all(|p| p.is_finite()));
    let d = max_dist(&a, &b);
    assert!(
        d < 1e-6,
        "held to WebGPU's limits vs the full adapter: {d} m"
    );
}

/// An adapter with fewer storage buffers per stage than a kernel binds (wgpu's downlevel
/// defaults: 4) cannot run the kernels: creating them fails with an error that names the
/// limit, what the kernels need and what the adapter allows (the plugin then falls back
/// to the CPU).
#[test]
fn kernels_name_the_limit_an_adapter_lacks() {
    if gpu().is_none() {
        return;
    }
    let err = match bevy_tissue::gpu::headless_with(bevy::render::settings::WgpuSettings {
        constrained_limits: Some(bevy::render::settings::WgpuLimits::downlevel_defaults()),
        ..Default::default()
    }) {
        Ok(_) => panic!("the kernels were created under the downlevel limits"),
        Err(e) => e,
    };
    assert!(
        err.contains("cannot run the simulation's kernels")
            && err.contains("storage buffers per shader stage needs")
            && err.contains("the adapter allows 4"),
        "{err}"
    );
}

/// Newton–multigrid's lattice kernels: each entry point's layout lists exactly the
/// bindings its shader uses (naga's analysis of the module), and none asks for more than
/// WebGPU guarantees: 8 storage buffers per stage, 16 KiB of workgroup memory, 256
/// invocations per workgroup.
#[test]
fn lattice_kernels_bind_only_what_they_use_within_webgpu_limits() {
    use bevy_tissue::gpu::kernels::lattice::{ENTRIES, SLOTS, source, storage_count};
    let src = source();
    let module = naga::front::wgsl::parse_str(&src).expect("lattice.wgsl parses");
    let info = naga::valid::Validator::new(
        naga::valid::ValidationFlags::all(),
        naga::valid::Capabilities::all(),
    )
    .validate(&module)
    .expect("lattice.wgsl validates");
    for entry in ENTRIES {
        let (i, ep) = module
            .entry_points
            .iter()
            .enumerate()
            .find(|(_, ep)| ep.name == entry.name)
            .unwrap_or_else(|| panic!("no entry point {}", entry.name));
        assert!(ep.workgroup_size.iter().product::<u32>() <= 256);
        let fi = info.get_entry_point(i);
        let mut used: Vec<&str> = Vec::new();
        // The workgroup memory the entry point uses (each variable it reaches).
        let mut workgroup_bytes = 0u32;
        for (h, g) in module.global_variables.iter() {
            if g.binding.is_some() && !fi[h].is_empty() {
                used.push(g.name.as_deref().unwrap_or(""));
            }
            if g.space == naga::AddressSpace::WorkGroup && !fi[h].is_empty() {
                workgroup_bytes += module.types[g.ty].inner.size(module.to_ctx());
            }
        }
        assert!(
            workgroup_bytes <= 16 * 1024,
            "{}: {workgroup_bytes} bytes of workgroup memory",
            entry.name
        );
        used.sort_by_key(|n| SLOTS.iter().position(|s| s.name == *n));
        assert_eq!(used, entry.uses, "bindings of {}", entry.name);
        assert!(storage_count(entry) <= 8, "{}", entry.name);
    }
}

/// A cantilever of lattice elements (24 × 3 × 3 cm, 3 cm / `spacing` + 1 particles
/// across), clamped at one end.
fn lattice_bar(spacing: f32) -> Model {
    let mut model = Model::new();
    model
        .add_body(
            &procedural::cuboid(Vec3::new(0.12, 0.015, 0.015), 2),
            &BodyDesc {
                resolution: Resolution::Spacing(spacing),
                density: 1000.0,
                material: Material::Hyperelastic {
                    youngs_modulus: 1e5,
                    poisson_ratio: 0.3,
                },
                discretisation: bevy_tissue::core::model::Discretisation::Lattice,
                pins: vec![PinRegion::HalfSpace {
                    point: Vec3::new(-0.1185, 0.0, 0.0),
                    normal: -Vec3::X,
                }],
                ..Default::default()
            },
        )
        .unwrap();
    model
}

fn lattice_settings() -> SolverSettings {
    SolverSettings {
        method: Method::GaussSeidel,
        iterations: 2,
        substeps: 1,
        gravity: Vec3::new(0.0, -9.81, 0.0),
        element_solver: bevy_tissue::core::solver::ElementSolver::Multigrid,
        particle_contacts: false,
        ..Default::default()
    }
}

/// Newton–multigrid on the GPU against the CPU solver (the same algorithm: V-cycles,
/// energy line search): a clamped bar falling under gravity from rest, after 1 and 30
/// steps of 1/60 s, with the kernels created on a device held to WebGPU's default
/// limits. The Chebyshev–Jacobi smoother (one dispatch a sweep) at 4 and 8 across
/// (5,265 particles), with every line-search candidate in the second pass and in the
/// first; Gauss–Seidel by colour; the hybrid (Gauss–Seidel on level 0, Chebyshev below);
/// conjugate gradients of 2 and 3 V-cycles; V-cycles of other sweep counts; and the bar
/// in one batch with a box falling freely beside it, each body taking its own steps; the
/// coarsest level's sweeps in one dispatch (bodies of up to 32 nodes there, the small
/// bodies' kernel; of up to 64 and 128) and a dispatch a sweep; the coarsest level solved
/// exactly (`Sweeps::exact_coarsest`, up to the most nodes it takes), its factor kept
/// from the Newton iteration's start or made in each V-cycle; each smoothing pass's row in
/// one thread and in eight.
#[test]
fn lattice_newton_multigrid_matches_the_cpu() {
    use bevy_tissue::gpu::kernels::lattice::LatticeKernels;
    use bevy_tissue::gpu::lattice::{GpuLattice, LatticeOptions};
    if gpu().is_none() {
        return;
    }
    let (device, queue, _) = bevy_tissue::gpu::device_with(bevy::render::settings::WgpuSettings {
        constrained_limits: Some(bevy::render::settings::WgpuLimits::default()),
        ..Default::default()
    })
    .expect("a device with WebGPU's default limits");
    let kernels = LatticeKernels::new(&device).expect("the lattice kernels fit WebGPU's limits");
    use bevy_tissue::core::multigrid::Smoother::{Chebyshev, GaussSeidel, Hybrid};
    use bevy_tissue::core::multigrid::Sweeps;
    // (spacing, line-search candidates in the first pass, smoother, V-cycles per Newton
    // iteration (more than 1: conjugate gradients), a second body beside the bar, the
    // V-cycle's sweeps).
    // The coarsest level swept (30 sweeps) and two sweeps before and after on the levels
    // between; the default (solved exactly, none before) is `ex` below.
    let d = Sweeps {
        coarse_before: 2,
        exact_coarsest: false,
        translation: true,
        ..Sweeps::DEFAULT
    };
    let few = Sweeps {
        fine: 1,
        fine_before: 1,
        coarse: 2,
        coarse_before: 2,
        coarsest: 10,
        exact_coarsest: false,
        translation: true,
    };
    let chebyshev = Sweeps {
        fine: 4,
        fine_before: 4,
        coarse: 2,
        coarse_before: 2,
        coarsest: 6,
        exact_coarsest: false,
        translation: true,
    };
    // The next to last: the most coarsest-level nodes of a body for that level's sweeps
    // to run in one dispatch (0: a dispatch a sweep).
    let f = LatticeOptions::default().fused_coarsest;
    // The last: the smoothing passes one thread a node (always) or eight (never).
    let (always, never) = (true, false);
    use bevy_tissue::core::multigrid::{LatticeMultigrid, MAX_LEVELS};
    let mut widths = [false; 3];
    let mut exact_rows = 0;
    // The coarsest level solved exactly (the hierarchy then coarsened to at most
    // EXACT_COARSEST nodes a body), no sweeps before the coarse correction but on the
    // coarsest level: the default.
    let ex = Sweeps::DEFAULT;
    assert!(ex.exact_coarsest && ex.coarse_before == 0);
    // (.., boxes beside the bar, ..)
    for (spacing, first, smoother, cycles, boxes, sweeps, fused, one_thread) in [
        (0.0075f32, 4, Chebyshev, 1, 0, d, f, never),
        (0.00375, 4, Chebyshev, 1, 0, d, f, never),
        (0.00375, 4, Chebyshev, 1, 0, d, 0, never),
        (0.0075, 0, Chebyshev, 1, 0, d, f, never),
        (0.0075, 13, Chebyshev, 1, 0, d, f, never),
        (0.0075, 4, Chebyshev, 2, 0, chebyshev, f, never),
        (0.0075, 4, GaussSeidel, 1, 0, d, f, never),
        (0.0075, 4, Hybrid, 1, 0, d, f, never),
        (0.00375, 4, Hybrid, 1, 0, d, f, never),
        (0.0075, 4, Hybrid, 2, 0, d, f, never),
        (0.00375, 4, Hybrid, 3, 0, d, f, never),
        (0.00375, 4, Hybrid, 2, 0, few, f, never),
        (0.00375, 4, Hybrid, 2, 0, few, 0, never),
        (0.0075, 4, Hybrid, 1, 1, d, f, never),
        (0.0075, 4, Hybrid, 2, 1, d, f, never),
        (0.0075, 4, Hybrid, 2, 1, d, 0, never),
        (0.00375, 4, Hybrid, 2, 0, d, f, always),
        (0.0075, 4, Chebyshev, 1, 0, d, 0, always),
        (0.0075, 4, Hybrid, 2, 1, d, f, always),
        // The bar's coarsest level has 99 nodes here (two threads a node when fused).
        (0.006, 4, Hybrid, 2, 1, d, f, never),
        (0.006, 4, Hybrid, 2, 1, d, 0, never),
        // And at most 32 here (eight threads a node, the small bodies' kernel).
        (0.01, 4, Hybrid, 2, 1, d, f, never),
        (0.01, 4, Hybrid, 2, 1, d, 0, never),
        // Solved exactly: the bar alone coarsened to 20 or 24 nodes there, or at 28 (the
        // most the exact solve takes) beside a box.
        (0.0075, 4, Chebyshev, 1, 0, ex, f, never),
        (0.00375, 13, GaussSeidel, 1, 0, ex, 0, never),
        (0.00375, 4, Hybrid, 2, 0, ex, f, never),
        (0.006, 4, Hybrid, 3, 0, ex, f, always),
        (0.01, 0, Hybrid, 1, 1, ex, f, never),
        (0.01, 4, Hybrid, 2, 1, ex, 0, never),
    ] {
        let mut model = lattice_bar(spacing);
        for i in 0..boxes {
            model.append(&common::lattice_box_at(
                Vec3::splat(0.016),
                Vec3::new(0.1 * i as f32, 0.5, 0.5),
            ));
        }
        let mg = LatticeMultigrid::new(&model, sweeps.min_nodes(), MAX_LEVELS);
        let exact = mg.coarsest_exact(sweeps);
        exact_rows += exact as u32;
        assert_eq!(exact, sweeps.exact_coarsest, "{spacing} m, {boxes} boxes");
        if fused > 0 && smoother != GaussSeidel && !exact {
            // Which of the fused kernels' ways the rows take: 8 (`smooth_coarsest_small`),
            // 4 or 2 threads a node for at most 32, 64 or 128 nodes a body.
            let most = mg.levels.last().map_or(0, |lv| {
                lv.body_start
                    .windows(2)
                    .map(|w| w[1] - w[0])
                    .max()
                    .unwrap_or(0)
            });
            widths[match most {
                0..=32 => 0,
                33..=64 => 1,
                _ => 2,
            }] = true;
        }
        let s = SolverSettings {
            smoother,
            newton_cycles: cycles,
            sweeps,
            ..lattice_settings()
        };
        let mut cpu_state = State::new(&model);
        let mut solver = Solver::new(&model, s.clone()).unwrap();
        let control = Control::default();
        // Solved exactly, a row whose fused limit is 0 has each V-cycle assemble and
        // factorise the coarsest level (`solve_coarsest`); the others keep its factor
        // from the Newton iteration's start (`factor_coarsest`, `solve_factored`).
        let keep = !(exact && fused == 0);
        let world = |fused_coarsest| {
            GpuLattice::new_with(
                &device,
                &kernels,
                &model,
                &cpu_state,
                &s,
                LatticeOptions {
                    first_candidates: first,
                    fused_coarsest,
                    one_thread_rows_from: if one_thread { 0 } else { u32::MAX },
                    keep_coarsest_factor: keep,
                    ..Default::default()
                },
            )
            .unwrap()
        };
        let gpu_world = world(fused);
        // These bodies are small: below level 0, their coarsest level's sweeps are one
        // dispatch unless the limit is 0 (or the level is solved exactly, one dispatch
        // either way).
        let apart = world(0);
        assert_eq!(
            gpu_world.dispatch_count() < apart.dispatch_count(),
            fused > 0 && smoother != GaussSeidel && !exact,
            "{smoother:?}, limit {fused}: {} dispatches a step, {} a sweep a dispatch",
            gpu_world.dispatch_count(),
            apart.dispatch_count()
        );
        drop(apart);
        let mut gpu_state = cpu_state.clone();
        let rest = model.rest.clone();
        let mut steps_done = 0;
        for steps in [1u32, 29] {
            for _ in 0..steps {
                solver.step(&model, &mut cpu_state, &control).unwrap();
            }
            let mut enc = device.create_command_encoder(&Default::default());
            gpu_world.record(&mut enc, &kernels, steps, None);
            queue.submit([enc.finish()]);
            gpu_world.download(&device, &queue, &mut gpu_state);
            steps_done += steps;
            let sag = max_dist(&rest, &cpu_state.x);
            let diff = max_dist(&gpu_state.x, &cpu_state.x);
            eprintln!(
                "{} particles, {smoother:?}, {cycles} cycle(s), {sweeps:?}, {first} first candidates, coarsest fused up to {fused}, one thread a row: {one_thread}, after {steps_done} steps: CPU moved {sag:.3e} m, GPU − CPU {diff:.3e} m",
                model.particle_count()
            );
            assert!(sag > 1e-4, "the bar moved ({sag} m)");
            assert!(
                diff <= 1e-3 * sag + 1e-6,
                "GPU − CPU {diff} m of {sag} m after {steps_done} steps ({} particles, {smoother:?}, {cycles} cycle(s), coarsest fused up to {fused}, one thread a row: {one_thread})",
                model.particle_count()
            );
        }
    }
    assert!(
        widths.iter().all(|&w| w),
        "the fused coarsest level's eight-, four- and two-thread ways are all tested: {widths:?}"
    );
    assert_eq!(exact_rows, 6, "rows that solve the coarsest level exactly");
}

/// A body with more level-0 nodes than 256 reduction chunks of 64 (where each `pick` sums
/// a thread's chunks four at a time into four sums) steps as on the CPU: the clamped bar
/// at 2.5 mm (16,393 particles), the hybrid smoother, conjugate gradients of two
/// V-cycles, 3 steps of 1/60 s. Every per-body sum of the step (the first iterate's and
/// the line search's energies, the translation step, the coarse corrections' steps, the
/// conjugate gradients' dots) goes through those picks.
#[test]
fn a_lattice_body_of_many_chunks_matches_the_cpu() {
    use bevy_tissue::core::multigrid::{Smoother, Sweeps};
    use bevy_tissue::gpu::kernels::lattice::LatticeKernels;
    use bevy_tissue::gpu::lattice::{GpuLattice, LatticeOptions};
    let Some(g) = gpu() else {
        return;
    };
    let (device, queue) = (&g.device, &g.queue);
    let kernels = LatticeKernels::new(device).expect("the lattice kernels");
    let model = lattice_bar(0.0025);
    let n = model.particle_count();
    assert!(n > 4 * 64 * 64, "{n} particles: more than 256 chunks");
    let s = SolverSettings {
        smoother: Smoother::Hybrid,
        newton_cycles: 2,
        sweeps: Sweeps::DEFAULT,
        ..lattice_settings()
    };
    let start = State::new(&model);
    let world = GpuLattice::new_with(
        device,
        &kernels,
        &model,
        &start,
        &s,
        LatticeOptions::default(),
    )
    .unwrap();
    let mut cpu = start.clone();
    let mut solver = Solver::new(&model, s.clone()).unwrap();
    for _ in 0..3 {
        solver.step(&model, &mut cpu, &Control::default()).unwrap();
    }
    let mut enc = device.create_command_encoder(&Default::default());
    world.record(&mut enc, &kernels, 3, None);
    queue.submit([enc.finish()]);
    let mut gpu_state = start.clone();
    world.download(device, queue, &mut gpu_state);
    let sag = max_dist(&model.rest, &cpu.x);
    let diff = max_dist(&gpu_state.x, &cpu.x);
    eprintln!("{n} particles, after 3 steps: CPU moved {sag:.3e} m, GPU − CPU {diff:.3e} m");
    assert!(sag > 1e-3, "the bar moved ({sag} m)");
    assert!(diff <= 1e-3 * sag + 1e-6, "GPU − CPU {diff} m of {sag} m");
}

/// A GPU lattice made from its bodies' own levels, each built from a model of that body
/// alone and joined (`LatticeMultigrid::from_bodies`, what the plugin does when a body
/// comes or goes), steps to the bit as one that coarsens the whole model itself: a
/// clamped bar beside a free box, falling for 10 steps. A hierarchy of another model
/// is refused, naming the mismatch.
#[test]
fn a_lattice_made_from_its_bodies_levels_steps_as_one_built_whole() {
    use bevy_tissue::core::multigrid::{BodyLevels, LatticeMultigrid, MAX_LEVELS};
    use bevy_tissue::gpu::kernels::lattice::LatticeKernels;
    use bevy_tissue::gpu::lattice::{GpuLattice, LatticeOptions};
    let Some(g) = gpu() else {
        return;
    };
    let kernels = LatticeKernels::new(&g.device).unwrap();
    let bodies = [
        lattice_bar(0.0075),
        lattice_box_at(Vec3::splat(0.02), Vec3::new(0.0, 0.2, 0.0)),
    ];
    let mut model = Model::new();
    for b in &bodies {
        model.append(b);
    }
    let parts: Vec<BodyLevels> = bodies.iter().map(|b| BodyLevels::new(b, 0)).collect();
    let s = lattice_settings();
    let min_nodes = s.sweeps.min_nodes();
    let joined =
        || LatticeMultigrid::from_bodies(&parts.iter().collect::<Vec<_>>(), min_nodes, MAX_LEVELS);
    assert!(joined().levels.len() >= 2);
    let start = State::new(&model);
    let run = |world: &GpuLattice| {
        let mut enc = g.device.create_command_encoder(&Default::default());
        world.record(&mut enc, &kernels, 10, None);
        g.queue.submit([enc.finish()]);
        let mut state = start.clone();
        world.download(&g.device, &g.queue, &mut state);
        state.x
    };
    let whole = GpuLattice::new(&g.device, &kernels, &model, &start, &s).unwrap();
    let from_parts = GpuLattice::with_levels(
        &g.device,
        &kernels,
        &model,
        joined(),
        &start,
        &s,
        LatticeOptions::default(),
    )
    .unwrap();
    let (a, b) = (run(&whole), run(&from_parts));
    assert!(max_dist(&a, &model.rest) > 1e-3, "the bodies fell");
    assert!(
        a == b,
        "joined levels step differently: {} m",
        max_dist(&a, &b)
    );
    let other = LatticeMultigrid::from_bodies(&[&parts[0]], min_nodes, MAX_LEVELS);
    let err = GpuLattice::with_levels(
        &g.device,
        &kernels,
        &model,
        other,
        &start,
        &s,
        LatticeOptions::default(),
    )
    .err()
    .expect("another model's levels refused")
    .to_string();
    assert!(err.contains("levels"), "{err}");
}

/// Three lattice bodies of different shapes (a bar, a cube, a box) apart, each with its
/// own multigrid levels: what the append tests add to a world one by one.
fn three_lattice_bodies() -> ([Model; 3], Vec<bevy_tissue::core::multigrid::BodyLevels>) {
    let bodies = [
        lattice_bar(0.0075),
        lattice_box_at(Vec3::splat(0.02), Vec3::new(0.0, 0.2, 0.0)),
        lattice_box_at(Vec3::new(0.03, 0.015, 0.02), Vec3::new(0.3, 0.1, 0.0)),
    ];
    let parts = bodies
        .iter()
        .map(|b| bevy_tissue::core::multigrid::BodyLevels::new(b, 0))
        .collect();
    (bodies, parts)
}

/// `bodies` appended into one model, in order.
fn joined(bodies: &[Model]) -> Model {
    let mut m = Model::new();
    for b in bodies {
        m.append(b);
    }
    m
}

/// A lattice body appended into a world's room (`GpuLattice::append`, what the plugin
/// does when a body spawns) steps to the bit as a world made with it from the start (the
/// same levels, the Chebyshev estimates the larger of the world's and the body's); a
/// world with room steps to the bit as one without; appending past the room refuses and
/// changes nothing.
#[test]
fn a_lattice_body_appended_into_room_steps_as_a_world_made_with_it() {
    use bevy_tissue::core::multigrid::{BodyLevels, LatticeMultigrid, MAX_LEVELS};
    use bevy_tissue::gpu::kernels::lattice::LatticeKernels;
    use bevy_tissue::gpu::lattice::{GpuLattice, LatticeOptions};
    let Some(g) = gpu() else {
        return;
    };
    let kernels = LatticeKernels::new(&g.device).unwrap();
    let (bodies, parts) = three_lattice_bodies();
    let (two, three) = (joined(&bodies[..2]), joined(&bodies[..3]));
    let refs: Vec<&BodyLevels> = parts.iter().collect();
    let depth = LatticeMultigrid::depth_of(
        &refs[..2],
        lattice_settings().sweeps.min_nodes(),
        MAX_LEVELS,
    );
    assert!(depth >= 2);
    let s = lattice_settings();
    let room = LatticeOptions {
        room: 1.5,
        ..Default::default()
    };
    let run = |world: &GpuLattice, model: &Model| {
        let mut enc = g.device.create_command_encoder(&Default::default());
        world.record(&mut enc, &kernels, 10, None);
        g.queue.submit([enc.finish()]);
        let mut state = State::new(model);
        world.download(&g.device, &g.queue, &mut state);
        state.x
    };
    let make = |model: &Model, mg: LatticeMultigrid, options: LatticeOptions| {
        GpuLattice::with_levels(
            &g.device,
            &kernels,
            model,
            mg,
            &State::new(model),
            &s,
            options,
        )
        .unwrap()
    };
    // Room changes nothing.
    let tight = make(
        &two,
        LatticeMultigrid::joined(&refs[..2], depth),
        LatticeOptions::default(),
    );
    let roomy = make(&two, LatticeMultigrid::joined(&refs[..2], depth), room);
    let (a, b) = (run(&tight, &two), run(&roomy, &two));
    assert!(max_dist(&a, &two.rest) > 1e-3, "the bodies fell");
    assert!(a == b, "room steps differently: {} m", max_dist(&a, &b));
    // No room: refused, nothing changed.
    let mut tight = make(
        &two,
        LatticeMultigrid::joined(&refs[..2], depth),
        LatticeOptions::default(),
    );
    let third = State::new(&bodies[2]);
    assert!(
        !tight
            .append(&g.device, &g.queue, &bodies[2], &parts[2], &third, &s)
            .unwrap()
    );
    assert_eq!(
        (tight.body_count(), tight.particle_count()),
        (2, two.particle_count())
    );
    // Appended, against made with it.
    let mut grown = make(&two, LatticeMultigrid::joined(&refs[..2], depth), room);
    assert!(
        grown
            .append(&g.device, &g.queue, &bodies[2], &parts[2], &third, &s)
            .unwrap()
    );
    assert_eq!(
        (grown.body_count(), grown.particle_count()),
        (3, three.particle_count())
    );
    let mut whole = LatticeMultigrid::joined(&refs, depth);
    let before = LatticeMultigrid::joined(&refs[..2], depth).chebyshev;
    let own = LatticeMultigrid::joined(&refs[2..], depth).chebyshev;
    for (l, c) in whole.chebyshev.iter_mut().enumerate() {
        *c = if own[l][0] < before[l][0] {
            own[l]
        } else {
            before[l]
        };
    }
    let made = make(&three, whole, LatticeOptions::default());
    let (a, b) = (run(&grown, &three), run(&made, &three));
    assert!(
        max_dist(
            &a[two.particle_count()..],
            &three.rest[two.particle_count()..]
        ) > 1e-3
    );
    assert!(
        a == b,
        "the appended body steps differently: {} m",
        max_dist(&a, &b)
    );
    // A model of two bodies is not one body to append.
    assert!(
        grown
            .append(&g.device, &g.queue, &two, &parts[0], &State::new(&two), &s)
            .is_err()
    );
}

/// Bodies packed on another thread against a snapshot of a GPU lattice
/// (`AppendBasis::prepare`, the second behind the first with `AppendBasis::after`), then
/// committed in order, make the world that appending them one by one makes, to the bit.
/// A packing committed out of order, or into another world, is refused with nothing
/// changed.
#[test]
fn bodies_packed_on_another_thread_commit_as_appended_here() {
    use bevy_tissue::core::multigrid::LatticeMultigrid;
    use bevy_tissue::gpu::kernels::lattice::LatticeKernels;
    use bevy_tissue::gpu::lattice::{GpuLattice, LatticeOptions};
    let Some(g) = gpu() else {
        return;
    };
    let kernels = LatticeKernels::new(&g.device).unwrap();
    let (bodies, parts) = three_lattice_bodies();
    let s = lattice_settings();
    let make = || {
        GpuLattice::with_levels(
            &g.device,
            &kernels,
            &bodies[0],
            LatticeMultigrid::joined(&[&parts[0]], parts[0].levels.len()),
            &State::new(&bodies[0]),
            &s,
            LatticeOptions {
                room: 4.0,
                ..Default::default()
            },
        )
        .unwrap()
    };
    let mut here = make();
    for b in 1..3 {
        let state = State::new(&bodies[b]);
        assert!(
            here.append(&g.device, &g.queue, &bodies[b], &parts[b], &state, &s)
                .unwrap()
        );
    }
    let mut there = make();
    let basis = there.append_basis();
    let (first, second) = std::thread::scope(|scope| {
        scope
            .spawn(|| {
                let pack = |basis: &bevy_tissue::gpu::lattice::AppendBasis, b: usize| {
                    let mut p = basis
                        .prepare(&bodies[b], &parts[b], &State::new(&bodies[b]), &s)
                        .unwrap()
                        .expect("room for it");
                    p.stage(&g.device);
                    p
                };
                let first = pack(&basis, 1);
                let second = pack(&basis.after(&first), 2);
                (first, second)
            })
            .join()
            .unwrap()
    });
    // Into another world made the same way: refused.
    let mut other = make();
    let stray = there
        .append_basis()
        .prepare(&bodies[1], &parts[1], &State::new(&bodies[1]), &s)
        .unwrap()
        .unwrap();
    assert!(!other.commit_append(&g.device, &g.queue, stray));
    assert_eq!(other.body_count(), 1);
    // Out of order: refused; in order: taken.
    assert!(!there.commit_append(&g.device, &g.queue, second));
    assert_eq!(there.body_count(), 1);
    let second = basis
        .after(&first)
        .prepare(&bodies[2], &parts[2], &State::new(&bodies[2]), &s)
        .unwrap()
        .unwrap();
    assert!(there.commit_append(&g.device, &g.queue, first));
    assert!(there.commit_append(&g.device, &g.queue, second));
    assert_eq!(
        (there.body_count(), there.particle_count()),
        (here.body_count(), here.particle_count())
    );
    let all = joined(&bodies);
    let run = |world: &GpuLattice| {
        let mut enc = g.device.create_command_encoder(&Default::default());
        world.record(&mut enc, &kernels, 10, None);
        g.queue.submit([enc.finish()]);
        let mut state = State::new(&all);
        world.download(&g.device, &g.queue, &mut state);
        state.x
    };
    let (a, b) = (run(&here), run(&there));
    assert!(max_dist(&a, &all.rest) > 1e-3, "the bodies fell");
    assert!(a == b, "committed differently: {} m", max_dist(&a, &b));
}

/// Past its room a GPU lattice is made again with more bodies, from the rest state, and
/// takes the state of the bodies it keeps from the old world by GPU copies
/// (`GpuLattice::carry_state`, what the plugin's installing frame does): the kept bodies
/// are where the old world left them, the new one at rest, and the world steps to the
/// bit as one that uploaded the same state from the CPU. A run past either world is
/// refused with nothing copied.
#[test]
fn a_lattice_made_again_takes_the_kept_bodies_state_by_gpu_copies() {
    use bevy_tissue::core::multigrid::{BodyLevels, LatticeMultigrid, MAX_LEVELS};
    use bevy_tissue::gpu::kernels::lattice::LatticeKernels;
    use bevy_tissue::gpu::lattice::{GpuLattice, LatticeOptions, StateRun};
    let Some(g) = gpu() else {
        return;
    };
    let kernels = LatticeKernels::new(&g.device).unwrap();
    let (bodies, parts) = three_lattice_bodies();
    let (two, three) = (joined(&bodies[..2]), joined(&bodies[..3]));
    let refs: Vec<&BodyLevels> = parts.iter().collect();
    let s = lattice_settings();
    let make = |model: &Model, n: usize| {
        let depth = LatticeMultigrid::depth_of(&refs[..n], s.sweeps.min_nodes(), MAX_LEVELS);
        GpuLattice::with_levels(
            &g.device,
            &kernels,
            model,
            LatticeMultigrid::joined(&refs[..n], depth),
            &State::new(model),
            &s,
            LatticeOptions {
                room: 1.5,
                ..Default::default()
            },
        )
        .unwrap()
    };
    let steps = |world: &GpuLattice, n: u32| {
        let mut enc = g.device.create_command_encoder(&Default::default());
        world.record(&mut enc, &kernels, n, None);
        g.queue.submit([enc.finish()]);
    };
    let read = |world: &GpuLattice, model: &Model| {
        let mut state = State::new(model);
        world.download(&g.device, &g.queue, &mut state);
        state
    };
    let old = make(&two, 2);
    steps(&old, 10);
    let left = read(&old, &two);
    let (np, ne) = (two.particle_count(), two.elements.len());
    assert!(
        max_dist(&left.x, &State::new(&two).x) > 1e-3,
        "the bodies fell"
    );
    // Made again with the third body; the first two take their state by copies.
    let mut copied = make(&three, 3);
    let runs = StateRun::joined((0..2).map(|b| {
        let p = two.bodies[b].range();
        let e0: usize = bodies[..b].iter().map(|m| m.elements.len()).sum();
        let e = e0..e0 + bodies[b].elements.len();
        StateRun {
            particles: p.start as u32..p.end as u32,
            to_particle: p.start as u32,
            elements: e.start as u32..e.end as u32,
            to_element: e.start as u32,
        }
    }));
    assert_eq!(runs.len(), 1, "two bodies in order make one run");
    // A run past the world the state comes from: refused, nothing copied.
    let past = StateRun {
        particles: 0..np as u32 + 1,
        ..runs[0].clone()
    };
    assert!(
        copied
            .carry_state(&g.device, &g.queue, &old, &[past])
            .is_err()
    );
    let rest = State::new(&three).x;
    let after = read(&copied, &three).x;
    assert!(
        after == rest,
        "a refused run copied: {} m",
        max_dist(&after, &rest)
    );
    copied
        .carry_state(&g.device, &g.queue, &old, &runs)
        .unwrap();
    let now = read(&copied, &three);
    assert!(now.x[..np] == left.x[..], "the kept bodies moved");
    assert!(
        now.v[..np] == left.v[..],
        "the kept bodies' velocities changed"
    );
    assert!(now.element_rot[..ne] == left.element_rot[..]);
    assert!(now.x[np..] == rest[np..], "the new body is not at rest");
    // The same state uploaded from the CPU.
    let mut uploaded = make(&three, 3);
    let mut state = State::new(&three);
    state.x[..np].copy_from_slice(&left.x);
    state.v[..np].copy_from_slice(&left.v);
    state.element_rot[..ne].copy_from_slice(&left.element_rot);
    uploaded.upload(&g.queue, &three, &state);
    steps(&copied, 10);
    steps(&uploaded, 10);
    let (a, b) = (read(&copied, &three).x, read(&uploaded, &three).x);
    assert!(max_dist(&a, &now.x) > 1e-4, "the world did not step on");
    assert!(
        a == b,
        "carried on the GPU, stepped differently from uploaded: {} m",
        max_dist(&a, &b)
    );
}

/// A GPU lattice takes a new time step, substeps and iteration counts in place
/// (`GpuLattice::set_steps`) and then steps to the bit as one made with them; a change it
/// cannot take (another smoother) is refused, nothing changed.
#[test]
fn a_lattice_takes_new_steps_in_place_as_one_made_with_them() {
    use bevy_tissue::core::multigrid::Smoother;
    use bevy_tissue::gpu::kernels::lattice::LatticeKernels;
    use bevy_tissue::gpu::lattice::GpuLattice;
    let Some(g) = gpu() else {
        return;
    };
    let kernels = LatticeKernels::new(&g.device).unwrap();
    let model = lattice_bar(0.0075);
    let start = State::new(&model);
    let before = lattice_settings();
    let after = SolverSettings {
        dt: 1.0 / 90.0,
        substeps: 2,
        iterations: 3,
        newton_iterations: 3,
        gravity: Vec3::new(0.0, -4.0, 0.0),
        damping: 0.5,
        ..before.clone()
    };
    let run = |world: &GpuLattice| {
        let mut enc = g.device.create_command_encoder(&Default::default());
        world.record(&mut enc, &kernels, 5, None);
        g.queue.submit([enc.finish()]);
        let mut state = start.clone();
        world.download(&g.device, &g.queue, &mut state);
        state.x
    };
    let mut changed = GpuLattice::new(&g.device, &kernels, &model, &start, &before).unwrap();
    let other = SolverSettings {
        smoother: if before.smoother == Smoother::Chebyshev {
            Smoother::GaussSeidel
        } else {
            Smoother::Chebyshev
        },
        ..after.clone()
    };
    assert!(
        !changed.set_steps(&g.queue, &other),
        "another smoother taken in place"
    );
    assert!(changed.set_steps(&g.queue, &after));
    let made = GpuLattice::new(&g.device, &kernels, &model, &start, &after).unwrap();
    let (a, b) = (run(&changed), run(&made));
    assert!(max_dist(&a, &model.rest) > 1e-4, "the bar moved");
    assert!(
        a == b,
        "new steps in place step differently: {} m",
        max_dist(&a, &b)
    );
    assert_eq!(changed.dispatch_count(), made.dispatch_count());
}

/// A lattice box of half extents `half` (8 mm spacing, E = 20 kPa, ν = 0.3) centred at
/// height `y`.
fn lattice_box(half: Vec3, y: f32) -> Model {
    lattice_box_at(half, Vec3::new(0.0, y, 0.0))
}

/// The CPU solver, perturbed CPU solvers (how sensitive the run is) and the GPU lattice
/// solver, stepped together.
struct Lockstep {
    model: Model,
    start: Vec<Vec3>,
    cpu: (Solver, State),
    /// The CPU started 0.1 µm away (each particle in a direction of its own: a rigid
    /// shift would leave the contact equilibrium, and the friction decided from it, as
    /// they were), and the CPU with Young's modulus a part in a million above and below:
    /// a contact penalty (a thousand times a node's own stiffness) dominates its node's
    /// diagonal block, whose inverse in f32 carries rounding of that size into the Newton
    /// direction and from it into the contacts' decisions, and the GPU's arithmetic
    /// (fused multiply–adds, summation order) rounds differently from the CPU's.
    probes: Vec<(Model, Solver, State)>,
    gpu: (bevy_tissue::gpu::lattice::GpuLattice, State),
    kernels: bevy_tissue::gpu::kernels::lattice::LatticeKernels,
    /// Builds the GPU's particle-contact lists from the GPU's own positions and
    /// velocities (the CPU's rule, every step).
    lists: Solver,
}

/// One step of a [`Lockstep`].
struct Compared {
    /// The CPU's collider forces, N.
    cpu_forces: Vec<Vec3>,
    /// The GPU's, N.
    gpu_forces: Vec<Vec3>,
    /// Per collider: the largest distance between the CPU's force and a perturbed
    /// CPU's, N (a force that is a small difference of large ones, as a grasper's pull
    /// on a box at rest, rounds as the step does).
    own_forces: Vec<f32>,
    /// Largest GPU − CPU distance, m.
    diff: f32,
    /// Largest distance between the CPU and a perturbed CPU, m.
    own: f32,
    /// Largest distance the CPU's particles moved from the start, m.
    moved: f32,
}

impl Lockstep {
    fn new(g: &Headless, model: Model) -> Self {
        let start = State::new(&model);
        Self::from_state(g, model, start)
    }

    fn from_state(g: &Headless, model: Model, cpu: State) -> Self {
        Self::with_settings(g, model, cpu, lattice_settings())
    }

    fn with_settings(g: &Headless, model: Model, cpu: State, s: SolverSettings) -> Self {
        use bevy_tissue::gpu::kernels::lattice::LatticeKernels;
        use bevy_tissue::gpu::lattice::GpuLattice;
        let kernels = LatticeKernels::new(&g.device).unwrap();
        let mut nudged = cpu.clone();
        for (i, p) in nudged.x.iter_mut().enumerate() {
            let h =
                |k: u32| ((i as u32).wrapping_mul(2_654_435_761) ^ k.wrapping_mul(40_503)) % 2001;
            *p += Vec3::new(h(1) as f32, h(2) as f32, h(3) as f32) * (1e-7 / 1000.0)
                - Vec3::splat(1e-7);
        }
        let stiffer = |factor: f32| {
            let mut m = model.clone();
            for b in &mut m.bodies {
                if let Material::Hyperelastic { youngs_modulus, .. } = &mut b.material {
                    *youngs_modulus *= factor;
                }
            }
            m
        };
        let mut probes = Vec::new();
        for (m, x) in [
            (model.clone(), nudged),
            (stiffer(1.0 + 1e-6), cpu.clone()),
            (stiffer(1.0 - 1e-6), cpu.clone()),
        ] {
            let solver = Solver::new(&m, s.clone()).unwrap();
            probes.push((m, solver, x));
        }
        let gpu = GpuLattice::new(&g.device, &kernels, &model, &cpu, &s).unwrap();
        Self {
            start: cpu.x.clone(),
            cpu: (Solver::new(&model, s.clone()).unwrap(), cpu.clone()),
            probes,
            lists: Solver::new(&model, s).unwrap(),
            gpu: (gpu, cpu),
            kernels,
            model,
        }
    }

    fn step(&mut self, g: &Headless, control: &Control) -> Compared {
        // The CPU's velocities at the step's start: the GPU's lists reach as far as the
        // CPU's (a reach from the GPU's own velocities, a rounding away, can take in or
        // leave out a far candidate, which changes a body's trust region).
        let v = self.cpu.1.v.clone();
        let stats = self
            .cpu
            .0
            .step(&self.model, &mut self.cpu.1, control)
            .unwrap();
        let mut own_forces = vec![0.0f32; stats.collider_forces.len()];
        for (m, solver, x) in &mut self.probes {
            let probe = solver.step(m, x, control).unwrap();
            for (o, (a, b)) in own_forces
                .iter_mut()
                .zip(probe.collider_forces.iter().zip(&stats.collider_forces))
            {
                *o = o.max(a.distance(*b));
            }
        }
        let (world, state) = &mut self.gpu;
        world.set_colliders(&g.queue, &control.colliders).unwrap();
        if world.has_particle_contacts() {
            // The CPU step's search (its reach widened by how far the particles may
            // move), every step as the CPU's `knn_every` of 1 in these tests.
            self.lists
                .refresh_contacts_if_due(&self.model, &state.x, &v, &[], 1, true);
            let (start, list) = self.lists.contact_lists();
            world.set_contacts(&g.queue, start, list).unwrap();
        }
        let mut enc = g.device.create_command_encoder(&Default::default());
        world.record(&mut enc, &self.kernels, 1, None);
        g.queue.submit([enc.finish()]);
        let gpu_forces = world.download(&g.device, &g.queue, state);
        assert_eq!(gpu_forces, world.read_forces(&g.device, &g.queue));
        Compared {
            cpu_forces: stats.collider_forces,
            gpu_forces,
            own_forces,
            diff: max_dist(&state.x, &self.cpu.1.x),
            own: self
                .probes
                .iter()
                .map(|p| max_dist(&p.2.x, &self.cpu.1.x))
                .fold(0.0, f32::max),
            moved: max_dist(&self.start, &self.cpu.1.x),
        }
    }
}

/// Newton–multigrid on the GPU with colliders against the CPU: a lattice box dropped on
/// the ground (friction 0.5) while a sphere moving sideways pushes into it. The colliders
/// act as penalties inside the Newton iterations and by projection after each. Contact
/// makes the motion sensitive: the friction of the projection is decided from the
/// penetration the penalty solve leaves, a fraction of a micrometre, so rounding alone
/// can flip a node between sticking and sliding (seen once the box lands, at step 5:
/// 0.25 mm). So the GPU must agree with the CPU to rounding for the first 5 steps, and
/// afterwards as well as the CPU agrees with itself started 0.1 µm away (each particle
/// in a direction of its own).
#[test]
fn lattice_colliders_match_the_cpu() {
    let Some(g) = gpu() else {
        return;
    };
    let mut run = Lockstep::new(g, lattice_box(Vec3::new(0.03, 0.02, 0.02), 0.03));
    let mut pressed = 0;
    for step in 0..40u32 {
        let mut sphere = Collider::new(
            ColliderShape::Sphere { radius: 0.02 },
            Vec3::new(0.06 - 0.001 * step as f32, 0.02, 0.0),
            Quat::IDENTITY,
        );
        sphere.velocity = Vec3::new(-0.06, 0.0, 0.0);
        let control = Control {
            colliders: vec![Collider::ground(0.0), sphere],
        };
        let c = run.step(g, &control);
        // The colliders' forces (the reactions of the particles touching them) agree
        // while the runs agree to a micrometre.
        if c.diff <= 1e-6 {
            for (k, (gf, cf)) in c.gpu_forces.iter().zip(&c.cpu_forces).enumerate() {
                assert!(
                    gf.distance(*cf) <= 1e-3 * cf.length() + 1e-4,
                    "step {step}, collider {k}: GPU {gf} N, CPU {cf} N"
                );
            }
            pressed += (c.cpu_forces[0].y < 0.0) as u32;
        }
        let bound = if step < 5 {
            1e-5 * c.moved + 1e-7
        } else {
            (2.0 * c.own).max(1e-3 * c.moved) + 1e-6
        };
        assert!(
            c.diff <= bound,
            "step {step}: GPU − CPU {} m (CPU moved {} m; CPU − nudged CPU {} m)",
            c.diff,
            c.moved,
            c.own
        );
    }
    assert!(
        pressed >= 3,
        "forces compared on the ground at {pressed} steps"
    );
    let lowest = run.cpu.1.x.iter().fold(f32::MAX, |a, p| a.min(p.y));
    let r = run.model.bodies[0].radius;
    assert!(
        lowest > 0.5 * r,
        "the box rests on the ground (lowest {lowest} m)"
    );
}

/// A world stepped without colliders records neither the reaction passes nor the
/// contact passes; given the ground later, it records them again and its collider forces
/// are the CPU's; with the ground taken away again, it leaves them out and the contact
/// stiffness the ground left behind in its buffers is not used: a box falls freely for
/// its first steps (no collider, nothing it could touch), then with the ground set lands
/// on it, then falls again from where it rested. The forces must agree while the runs
/// agree to a micrometre, over at least three steps of pressing on the ground, and the
/// fall after the ground is gone must stay as close to the CPU's as the rest was. Every
/// step's line search (read back) takes one of its candidates, the whole Newton step
/// while the box falls freely.
#[test]
fn lattice_collider_reactions_resume_when_colliders_are_set() {
    let Some(g) = gpu() else {
        return;
    };
    let mut run = Lockstep::new(g, lattice_box(Vec3::new(0.03, 0.02, 0.02), 0.03));
    let bare = run.gpu.0.dispatch_count();
    let mut pressed = 0;
    let mut with_ground = None;
    let mut resting_diff = 0.0f32;
    for step in 0..44u32 {
        let grounded = (2..34).contains(&step);
        let colliders = if grounded {
            vec![Collider::ground(0.0)]
        } else {
            Vec::new()
        };
        let c = run.step(g, &Control { colliders });
        let count = run.gpu.0.dispatch_count();
        // Each step's line search takes one of its candidates 1, ½, …, 2⁻¹², or 0; the
        // box falling freely before it first lands takes its whole Newton step.
        let taken = run.gpu.0.read_line_steps(&g.device, &g.queue);
        assert_eq!(taken.len(), 1, "one body");
        assert!(
            taken[0] == 0.0 || (0..13).any(|k| taken[0] == 0.5f32.powi(k)),
            "step {step}: the line search took {}",
            taken[0]
        );
        if step < 2 {
            assert_eq!(taken[0], 1.0, "step {step}: falling freely");
        }
        if !grounded {
            assert_eq!(
                count, bare,
                "step {step}: no colliders, no reaction or contact passes"
            );
            assert!(c.gpu_forces.is_empty() && c.cpu_forces.is_empty());
            if step >= 34 {
                // Stale contact blocks would hold the box's lowest nodes back by about
                // g h² (2.7 mm) a step.
                assert!(
                    c.diff <= (2.0 * resting_diff).max(1e-5),
                    "step {step}: falling again, GPU − CPU {} m (at rest {resting_diff} m)",
                    c.diff
                );
            }
            continue;
        }
        // `forces` at the substep's end, `force_partials` and `force_total`, and the
        // contact passes (`contacts` each Newton iteration, level 0's contact pass).
        let expected = *with_ground.get_or_insert(count);
        assert!(
            expected >= bare + 4,
            "step {step}: {expected} against {bare}"
        );
        assert_eq!(count, expected, "step {step}: the passes are back");
        resting_diff = c.diff;
        if c.diff <= 1e-6 {
            let (gf, cf) = (c.gpu_forces[0], c.cpu_forces[0]);
            assert!(
                gf.distance(cf) <= 1e-3 * cf.length() + 1e-4,
                "step {step}: GPU {gf} N, CPU {cf} N"
            );
            pressed += (cf.y < 0.0) as u32;
        }
    }
    assert!(
        pressed >= 3,
        "forces compared on the ground at {pressed} steps"
    );
}

/// Lattice bodies touching each other on the GPU against the CPU (Jacobi, particle
/// contacts in every Newton iteration, lists refreshed every step): a box dropped onto
/// another box that rests on the ground. The pairs push as penalties inside the Newton
/// iterations and are projected apart after each. The GPU must agree with the CPU to
/// rounding until the boxes touch, within three times what the perturbed CPUs differ
/// from it at the touching step and the next (one Newton iteration of two, the rest
/// projecting nothing on lattice particles, as on the GPU), and afterwards as well as the
/// CPU agrees with itself perturbed (over the run); the upper box must come to rest on
/// the lower one, not in it. With 2 Newton iterations of one V-cycle, and with 1 Newton
/// iteration of conjugate gradients over 2 V-cycles, smoothed both ways (Gauss–Seidel
/// and Chebyshev on level 0).
#[test]
fn lattice_bodies_in_contact_match_the_cpu() {
    let Some(g) = gpu() else {
        return;
    };
    use bevy_tissue::core::multigrid::Smoother;
    for (newton, cycles, smoother) in [
        (1u32, 1u32, Smoother::Chebyshev),
        (2, 1, Smoother::default()),
        (1, 2, Smoother::Hybrid),
        (1, 2, Smoother::Chebyshev),
    ] {
        let mut model = lattice_box(Vec3::new(0.03, 0.016, 0.03), 0.017);
        model.append(&upper_box());
        bodies_in_contact_match(g, model, newton, cycles, smoother);
    }
}

/// The falling box of the contact tests: a quarter spacing off the lower box's lattice,
/// so that it settles into the nearest hollow of the lower box's surface instead of
/// balancing on its particles.
fn upper_box() -> Model {
    lattice_box_at(Vec3::splat(0.016), Vec3::new(0.002, 0.085, 0.003))
}

/// As [`lattice_bodies_in_contact_match_the_cpu`], the upper box falling onto a lower box
/// whose top layers are pinned: the pairs' partners are held there (a held partner does
/// not move along the step and counts its pair once in the free node's block; a held
/// node's own candidates hold no contacts), as on the CPU.
#[test]
fn lattice_body_on_a_pinned_body_matches_the_cpu() {
    let Some(g) = gpu() else {
        return;
    };
    let mut model = common::lattice_box_pinned(
        Vec3::new(0.03, 0.016, 0.03),
        Vec3::new(0.0, 0.017, 0.0),
        vec![PinRegion::HalfSpace {
            point: Vec3::new(0.0, 0.005, 0.0),
            normal: Vec3::Y,
        }],
    );
    let pinned = model.pinned.len();
    assert!(
        pinned > 0 && pinned < model.particle_count(),
        "the lower box's top layers are pinned ({pinned} of {})",
        model.particle_count()
    );
    model.append(&upper_box());
    bodies_in_contact_match(
        g,
        model,
        1,
        1,
        bevy_tissue::core::multigrid::Smoother::Chebyshev,
    );
}

/// Drops body 1 of `model` onto its body 0 (resting on the ground) with particle contacts
/// in every Newton iteration, GPU and CPU in lockstep, and checks them against each other
/// and the upper body's rest (see [`lattice_bodies_in_contact_match_the_cpu`]).
fn bodies_in_contact_match(
    g: &Headless,
    model: Model,
    newton: u32,
    cycles: u32,
    smoother: bevy_tissue::core::multigrid::Smoother,
) {
    let s = SolverSettings {
        method: Method::Jacobi,
        newton_iterations: newton,
        newton_cycles: cycles,
        particle_contacts: true,
        knn_every: 1,
        contact_every: 1,
        smoother,
        ..lattice_settings()
    };
    let start = State::new(&model);
    let mut run = Lockstep::with_settings(g, model, start, s);
    let lower = run.model.bodies[0].range();
    let upper = run.model.bodies[1].range();
    let reach = run.model.bodies[0].radius + run.model.bodies[1].radius;
    let gap = |x: &[Vec3]| {
        let mut d = f32::MAX;
        for a in &x[lower.clone()] {
            for b in &x[upper.clone()] {
                d = d.min(a.distance(*b));
            }
        }
        d
    };
    let control = Control {
        colliders: vec![Collider::ground(0.0)],
    };
    // Each body's centre of mass.
    let centres = |x: &[Vec3]| {
        [lower.clone(), upper.clone()].map(|r| x[r.clone()].iter().sum::<Vec3>() / r.len() as f32)
    };
    let mut touched = None;
    let mut own_centre = 0.0f32;
    // The step of the largest GPU − CPU difference of the centres after contact, and it.
    let mut worst = (0u32, 0.0f32);
    for step in 0..40u32 {
        let c = run.step(g, &control);
        let [cpu, gpu] = [&run.cpu.1.x, &run.gpu.1.x].map(|x| centres(x));
        let centre_diff = (0..2).map(|b| gpu[b].distance(cpu[b])).fold(0.0, f32::max);
        for p in &run.probes {
            let probe = centres(&p.2.x);
            own_centre = (0..2)
                .map(|b| probe[b].distance(cpu[b]))
                .fold(own_centre, f32::max);
        }
        // Within 10 µm of the contact distance counts as touching: whether such a
        // pair acts is rounding's choice.
        if touched.is_none() && gap(&run.cpu.1.x) < reach + 1e-5 {
            touched = Some(step);
        }
        // The step the boxes meet and the next: the contact's first push, before a
        // slip decided by rounding, moves the GPU as it moves the CPU (as close as
        // the perturbed CPUs come to it).
        if touched.is_some_and(|t| step <= t + 1) {
            assert!(
                c.diff <= 3.0 * c.own + 1e-7,
                "{newton} × {cycles} ({smoother:?}), step {step}, first contact: GPU − CPU {} m (CPU − perturbed CPU {} m)",
                c.diff,
                c.own
            );
        }
        if touched.is_none() {
            assert!(
                c.diff <= 1e-5 * c.moved + 1e-7,
                "step {step}, before contact: GPU − CPU {} m (CPU moved {} m)",
                c.diff,
                c.moved
            );
        } else {
            // Which way a node slips off another is decided by rounding: the bodies'
            // motion is compared, as well as the CPU agrees with itself over the run (the
            // nudged CPU's own slip may come a step later than the GPU's).
            if centre_diff > worst.1 {
                worst = (step, centre_diff);
            }
        }
    }
    let (step, centre_diff) = worst;
    eprintln!(
        "{newton} × {cycles} ({smoother:?}): GPU − CPU centres of mass up to {centre_diff} m at step {step}, CPU − nudged CPU up to {own_centre} m"
    );
    assert!(
        centre_diff <= 2.0 * own_centre + 1e-4,
        "{newton} × {cycles} ({smoother:?}), step {step}: GPU − CPU centres of mass {centre_diff} m (CPU − nudged CPU up to {own_centre} m over the run)"
    );
    let touched = touched.expect("the boxes touched");
    assert!(
        touched > 2,
        "the upper box fell before touching (step {touched})"
    );
    for (label, x) in [("CPU", &run.cpu.1.x), ("GPU", &run.gpu.1.x)] {
        let g = gap(x);
        assert!(
            g > 0.6 * reach,
            "{label}: the upper box rests on the lower one, not in it (closest pair {g} m, contact distance {reach} m)"
        );
        let top_of_lower = x[lower.clone()].iter().fold(f32::MIN, |a, p| a.max(p.y));
        let bottom_of_upper = x[upper.clone()].iter().fold(f32::MAX, |a, p| a.min(p.y));
        assert!(
            bottom_of_upper > top_of_lower,
            "{label}: the upper box is above the lower one ({bottom_of_upper} m against {top_of_lower} m)"
        );
        let v = x[upper.clone()].len() as f32;
        let speed = run.gpu.1.v[upper.clone()]
            .iter()
            .map(|v| v.length())
            .sum::<f32>()
            / v;
        assert!(
            speed < 0.05,
            "{label}: the upper box settles (mean speed {speed} m/s)"
        );
    }
}

/// Graspers on the GPU lattice against the CPU: a grasper closes on the top of a lattice
/// box resting on the ground, lifts it by 2 cm and opens again. The grasped nodes, the
/// lift, the release and the forces on the ground and the grasper match the CPU (to
/// rounding before contact decisions can differ, then as well as the CPU matches itself
/// started 0.1 µm away, at most three times that difference's largest so far).
#[test]
fn lattice_graspers_match_the_cpu() {
    use bevy_tissue::core::colliders::GraspMode;
    let Some(g) = gpu() else {
        return;
    };
    let mut run = Lockstep::new(g, lattice_box(Vec3::splat(0.02), 0.025));
    let top = run.start.iter().fold(f32::MIN, |a, p| a.max(p.y));
    let mut lifted = 0.0f32;
    // The largest difference of the perturbed CPUs so far: while the box is held and
    // after its release the runs part as chaotically as the perturbed CPUs do, and the
    // GPU's rounding is a perturbation of its own (the order of its operations, fused
    // multiply-adds where the shader compiler makes them): GPU − CPU stays 10–100 times
    // below the perturbed CPUs' difference until the hold, then grows to it and, two steps
    // after the release, to 1.3–2.3 times it as the compiler's choices vary. The bound is
    // three times their largest difference so far (their difference at one step can dip).
    let mut own_so_far = 0.0f32;
    for step in 0..50u32 {
        let (mode, lift) = match step {
            0..10 => (GraspMode::Open, 0.0),
            10 => (GraspMode::Capture, 0.0),
            11..40 => (GraspMode::Hold, 0.02 * (step - 10) as f32 / 30.0),
            _ => (GraspMode::Open, 0.02),
        };
        let grasper = Collider::new(
            ColliderShape::Grasper {
                radius: 0.012,
                mode,
            },
            Vec3::new(0.0, top + lift, 0.0),
            Quat::IDENTITY,
        );
        let control = Control {
            colliders: vec![Collider::ground(0.0), grasper],
        };
        let c = run.step(g, &control);
        own_so_far = own_so_far.max(c.own);
        if c.own < 1e-6 {
            // Before the CPU's own decisions can differ: the ground's and the grasper's
            // forces as on the CPU (or as close as the perturbed CPU's are to it).
            for (k, (f, cf)) in c.gpu_forces.iter().zip(&c.cpu_forces).enumerate() {
                assert!(
                    f.distance(*cf) <= 0.02 * cf.length() + 1e-4 + 2.0 * c.own_forces[k],
                    "step {step}, collider {k}: GPU force {f} N, CPU {cf} N (perturbed CPU \
                     within {} N)",
                    c.own_forces[k]
                );
            }
        }
        assert!(
            c.diff <= (3.0 * own_so_far).max(1e-4 * c.moved) + 1e-6,
            "step {step}: GPU − CPU {} m (CPU moved {} m; CPU − nudged CPU {} m, at most {} m so far)",
            c.diff,
            c.moved,
            c.own,
            own_so_far
        );
        if step == 39 {
            lifted = run.gpu.1.x.iter().fold(f32::MIN, |a, p| a.max(p.y)) - top;
            let f = c.gpu_forces[1];
            assert!(f.y < -1e-3, "the grasper feels the box: {f}");
        }
    }
    assert!(lifted > 0.015, "the grasper lifted the top by {lifted} m");
}

/// A lattice box squashed to a fifth of its height lets go: far from its solution, the
/// Newton steps are cut by the trust region and halved by the line search, past its
/// first candidates (the second, indirect pass), as on the CPU.
#[test]
fn lattice_squashed_box_recovers_as_on_the_cpu() {
    let Some(g) = gpu() else {
        return;
    };
    let model = lattice_box(Vec3::splat(0.02), 0.5);
    let mut start = State::new(&model);
    for p in &mut start.x {
        p.y = 0.5 + (p.y - 0.5) * 0.2;
    }
    let mut run = Lockstep::from_state(g, model, start);
    let control = Control::default();
    for step in 0..10u32 {
        let c = run.step(g, &control);
        assert!(
            c.diff <= (2.0 * c.own).max(1e-4 * c.moved) + 1e-6,
            "step {step}: GPU − CPU {} m (CPU moved {} m; CPU − nudged CPU {} m)",
            c.diff,
            c.moved,
            c.own
        );
    }
    let height = |x: &[Vec3]| {
        x.iter().fold(f32::MIN, |a, p| a.max(p.y)) - x.iter().fold(f32::MAX, |a, p| a.min(p.y))
    };
    let h = height(&run.gpu.1.x);
    assert!(h > 0.03, "the box regained its height: {h} m");
}

/// A lattice box hitting the ground at 30 m/s: the first iterate, the trust region and
/// the line search's second pass (its first candidates all raise the energy) take
/// the impact as on the CPU (as well as the CPU agrees with itself started 0.1 µm away),
/// and the box comes to rest above the ground.
#[test]
fn lattice_impact_recovers_as_on_the_cpu() {
    let Some(g) = gpu() else {
        return;
    };
    let model = lattice_box(Vec3::new(0.03, 0.02, 0.02), 0.5);
    let r = model.bodies[0].radius;
    let mut start = State::new(&model);
    let low = start.x.iter().fold(f32::MAX, |a, p| a.min(p.y));
    for (x, v) in start.x.iter_mut().zip(&mut start.v) {
        x.y += r + 0.01 - low;
        *v = Vec3::new(0.0, -30.0, 0.0);
    }
    let mut run = Lockstep::from_state(g, model, start);
    let control = Control {
        colliders: vec![Collider::ground(0.0)],
    };
    for step in 0..20u32 {
        let c = run.step(g, &control);
        assert!(
            c.diff <= (2.0 * c.own).max(1e-4 * c.moved) + 1e-6,
            "step {step}: GPU − CPU {} m (CPU moved {} m; CPU − nudged CPU {} m)",
            c.diff,
            c.moved,
            c.own
        );
    }
    let lowest = run.gpu.1.x.iter().fold(f32::MAX, |a, p| a.min(p.y));
    assert!(
        lowest > 0.0 && lowest.is_finite(),
        "above the ground: {lowest} m"
    );
}

/// Under wgpu's downlevel limits (4 storage buffers per stage) the lattice kernels
/// cannot be created, and the error names the limit, what they need and what the
/// adapter allows.
#[test]
fn lattice_kernels_name_the_limit_a_downlevel_adapter_lacks() {
    use bevy_tissue::gpu::kernels::lattice::LatticeKernels;
    if gpu().is_none() {
        return;
    }
    let (device, _, _) = bevy_tissue::gpu::device_with(bevy::render::settings::WgpuSettings {
        constrained_limits: Some(bevy::render::settings::WgpuLimits::downlevel_defaults()),
        ..Default::default()
    })
    .expect("a device with the downlevel limits");
    let err = match LatticeKernels::new(&device) {
        Ok(_) => panic!("the lattice kernels were created under the downlevel limits"),
        Err(e) => e.to_string(),
    };
    assert!(
        err.contains("storage buffers per shader stage needs 8, the adapter allows 4"),
        "{err}"
    );
}

/// The lattice kernels' block inverse (`spd_inverse` in lattice.wgsl) equals its CPU twin
/// (`core::multigrid::spd_inverse`) on well-conditioned and contact-loaded blocks (a
/// penalty of 2.4e5 N/m along one direction on a node held by ~1 N/m in the others).
#[test]
fn the_block_inverse_equals_the_cpu() {
    use bevy::render::render_resource::*;
    use bevy_tissue::core::multigrid::spd_inverse;
    use glam::Mat3;
    let Some(g) = gpu() else {
        return;
    };
    let src = bevy_tissue::gpu::kernels::lattice::source();
    let start = src
        .find("fn spd_inverse")
        .expect("spd_inverse in lattice.wgsl");
    let end = start + src[start..].find("\n}\n").expect("its end") + 3;
    let shader = format!(
        "@group(0) @binding(0) var<storage, read_write> m: array<mat3x3<f32>>;\n{}\n\
         @compute @workgroup_size(1) fn main(@builtin(global_invocation_id) id: vec3<u32>) {{\n\
         m[id.x] = spd_inverse(m[id.x]);\n}}\n",
        &src[start..end]
    );
    let n = Vec3::new(0.6, 0.7, -0.4).normalize();
    let blocks = [
        Mat3::from_cols(
            Vec3::new(4.0, 1.0, 0.5),
            Vec3::new(1.0, 3.0, 0.2),
            Vec3::new(0.5, 0.2, 2.0),
        ),
        Mat3::from_cols(n * n.x, n * n.y, n * n.z) * 2.4e5
            + Mat3::from_diagonal(Vec3::new(0.6, 0.9, 0.7)),
        Mat3::from_diagonal(Vec3::new(1.0, -1.0, 1.0)),
    ];
    // mat3x3<f32> in a storage array: three columns of vec3 padded to 16 bytes.
    let bytes: Vec<f32> = blocks
        .iter()
        .flat_map(|m| {
            m.to_cols_array_2d()
                .into_iter()
                .flat_map(|c| [c[0], c[1], c[2], 0.0])
        })
        .collect();
    let buf = g.device.create_buffer_with_data(&BufferInitDescriptor {
        label: Some("blocks"),
        contents: bytemuck::cast_slice(&bytes),
        usage: BufferUsages::STORAGE | BufferUsages::COPY_SRC,
    });
    let module = g
        .device
        .create_and_validate_shader_module(ShaderModuleDescriptor {
            label: Some("spd_inverse"),
            source: ShaderSource::Wgsl(shader.into()),
        });
    let layout = g.device.create_bind_group_layout(
        "spd_inverse",
        &[BindGroupLayoutEntry {
            binding: 0,
            visibility: ShaderStages::COMPUTE,
            ty: BindingType::Buffer {
                ty: BufferBindingType::Storage { read_only: false },
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        }],
    );
    let pl = g.device.create_pipeline_layout(&PipelineLayoutDescriptor {
        label: None,
        bind_group_layouts: &[Some(&*layout)],
        immediate_size: 0,
    });
    let pipeline = g
        .device
        .create_compute_pipeline(&RawComputePipelineDescriptor {
            label: None,
            layout: Some(&pl),
            module: &module,
            entry_point: Some("main"),
            compilation_options: PipelineCompilationOptions::default(),
            cache: None,
        });
    let bg = g.device.create_bind_group(
        "spd_inverse",
        &layout,
        &[BindGroupEntry {
            binding: 0,
            resource: buf.as_entire_binding(),
        }],
    );
    let mut enc = g.device.create_command_encoder(&Default::default());
    {
        let mut pass = enc.begin_compute_pass(&Default::default());
        pass.set_pipeline(&pipeline);
        pass.set_bind_group(0, &bg, &[]);
        pass.dispatch_workgroups(blocks.len() as u32, 1, 1);
    }
    g.queue.submit([enc.finish()]);
    let out: Vec<f32> = bytemuck::pod_collect_to_vec(&read_buffer(
        &g.device,
        &g.queue,
        &buf,
        0,
        (bytes.len() * 4) as u64,
    ));
    for (k, m) in blocks.iter().enumerate() {
        let cpu = spd_inverse(*m);
        let c = |i: usize| {
            Vec3::new(
                out[12 * k + 4 * i],
                out[12 * k + 4 * i + 1],
                out[12 * k + 4 * i + 2],
            )
        };
        let gpu = Mat3::from_cols(c(0), c(1), c(2));
        let scale = cpu
            .to_cols_array()
            .iter()
            .fold(0.0f32, |a, v| a.max(v.abs()))
            .max(1e-30);
        let diff = (gpu - cpu)
            .to_cols_array()
            .iter()
            .fold(0.0f32, |a, v| a.max(v.abs()));
        eprintln!("block {k}: CPU {cpu}, GPU {gpu}");
        assert!(
            diff <= 1e-5 * scale,
            "block {k}: GPU − CPU {diff} of {scale}"
        );
    }
}

/// Per-step settings changed in place (`GpuWorld::set_settings`: gravity, dt, substeps,
/// iterations with shape matching's per-iteration stiffness, damping, relaxation) step
/// exactly as a world made with them; a change of the world's structure (particle
/// contacts switched) is refused and changes nothing.
#[test]
fn settings_changed_in_place_equal_a_world_made_with_them() {
    let Some(g) = gpu() else { return };
    let (model, colliders) = hanging(Material::ShapeMatching { stiffness: 0.6 });
    let a = settings();
    let b = SolverSettings {
        gravity: Vec3::new(1.0, -5.0, 0.5),
        dt: 1.0 / 90.0,
        substeps: 3,
        iterations: 7,
        damping: 2.0,
        relaxation: 1.2,
        ..a.clone()
    };
    assert!(a.differs_only_in_forces(&SolverSettings {
        gravity: b.gravity,
        damping: b.damping,
        ..a.clone()
    }));
    assert!(!a.differs_only_in_forces(&b));
    let mut changed = fresh_world_with(g, &model, a);
    assert!(changed.set_settings(&g.queue, b.clone()).unwrap());
    let mut made = fresh_world_with(g, &model, b.clone());
    let x1 = run_gpu(g, &mut changed, &colliders, 30);
    let x2 = run_gpu(g, &mut made, &colliders, 30);
    let d = max_dist(&x1, &x2);
    assert!(
        d == 0.0,
        "changed in place vs made with the settings: {d} m"
    );
    let structural = SolverSettings {
        particle_contacts: !b.particle_contacts,
        ..b.clone()
    };
    assert!(!changed.set_settings(&g.queue, structural).unwrap());
    assert_eq!(changed.settings, b);
    // Invalid settings are an error, not a change.
    let bad = SolverSettings {
        substeps: 0,
        ..b.clone()
    };
    assert!(changed.set_settings(&g.queue, bad).is_err());
    assert_eq!(changed.settings, b);
}

/// Two 6 cm shape-matching boxes of stiffness `k` side by side at `xs` (m), 10 cm above
/// the ground, with particle contacts on: the model, the settings and the ground.
fn boxes_on_the_ground(k: f32, xs: &[f32]) -> (Model, SolverSettings, [Collider; 1]) {
    let mut model = Model::new();
    let sm = Material::ShapeMatching { stiffness: k };
    let mesh = procedural::cuboid(Vec3::splat(0.03), 2);
    for &x in xs {
        model
            .add_body(&mesh, &body(sm, Vec3::new(x, 0.1, 0.0), 300, vec![]))
            .unwrap();
    }
    let s = SolverSettings {
        particle_contacts: true,
        ..settings()
    };
    (model, s, [Collider::ground(0.0)])
}

/// Bodies appended to a world (`GpuWorld::append`, what the plugin does on a spawn) move
/// and are drawn exactly as in a world made with them: a shape-matching box on the
/// ground, a second one touching it (particle contacts switch on with it) and a pinned
/// hyperelastic box, appended to a world of the first. Appending past the room refuses
/// and changes nothing.
#[test]
fn appended_bodies_equal_a_world_made_with_them() {
    let Some(g) = gpu() else { return };
    let (first, s, ground) = boxes_on_the_ground(0.6, &[-0.1]);
    let (touching, _, _) = boxes_on_the_ground(0.4, &[-0.068]);
    let (pinned, _) = hanging(Material::default());
    let mut more = touching.clone();
    more.append(&pinned);
    let mut all = first.clone();
    all.append(&more);
    let made = GpuWorld::with_room(
        &g.device,
        &g.kernels,
        &all,
        &State::new(&all),
        s.clone(),
        0,
        1.5,
    )
    .unwrap();
    let cap = made.capacity();
    let mut made = made;
    let mut grown = GpuWorld::with_capacity(
        &g.device,
        &g.kernels,
        &first,
        &State::new(&first),
        s,
        0,
        cap,
    )
    .unwrap();
    assert_eq!(grown.capacity(), cap);
    assert!(
        grown
            .append(&g.device, &g.queue, &more, &State::new(&more))
            .unwrap()
    );
    assert_eq!(grown.used(), made.used());
    assert_eq!(grown.ranges, made.ranges);
    assert!(
        grown.contact_neighbours() > 0,
        "contacts on with a second body"
    );
    let a = run_gpu(g, &mut made, &ground, 40);
    let b = run_gpu(g, &mut grown, &ground, 40);
    let d = max_dist(&a, &b);
    assert!(d == 0.0, "appended bodies moved differently by {d} m");
    assert!(max_dist(&a, &State::new(&all).x) > 0.005, "the scene moved");
    let (sa, sb) = (draw_surface(g, &made), draw_surface(g, &grown));
    assert_eq!(sa.len(), sb.len());
    let dv = sa
        .iter()
        .zip(&sb)
        .flat_map(|(p, q)| p.iter().zip(q).map(|(u, v)| (u - v).abs()))
        .fold(0.0f32, f32::max);
    assert!(
        dv == 0.0,
        "the appended bodies are drawn differently ({dv})"
    );
    // No room for another copy of everything: refused, nothing changed.
    let before = grown.used();
    assert!(
        !grown
            .append(&g.device, &g.queue, &all, &State::new(&all))
            .unwrap()
    );
    assert_eq!(grown.used(), before);
    assert_eq!(grown.ranges.len(), 3);
}

/// A body's model replaced in place (`GpuWorld::replace_body`: a new material, the same
/// sampling) keeps its pose and moves as in a world made with the new model; a model of
/// another size is refused; a body appended anew takes an old slot's pose
/// (`copy_body_state`).
#[test]
fn a_replaced_body_moves_as_in_a_world_made_with_it() {
    let Some(g) = gpu() else { return };
    let (two, s, ground) = boxes_on_the_ground(0.6, &[-0.2, 0.2]);
    let (stiffer, _, _) = boxes_on_the_ground(0.95, &[0.2]);
    let make = |m: &Model| {
        GpuWorld::with_room(&g.device, &g.kernels, m, &State::new(m), s.clone(), 0, 1.5).unwrap()
    };
    let mut replaced = make(&two);
    run_gpu(g, &mut replaced, &ground, 10);
    let before = read_vec3(
        &g.device,
        &g.queue,
        replaced.positions(),
        replaced.particle_count(),
    );
    assert!(
        replaced
            .replace_body(&g.device, &g.queue, 1, &stiffer, None)
            .unwrap()
    );
    let kept = read_vec3(
        &g.device,
        &g.queue,
        replaced.positions(),
        replaced.particle_count(),
    );
    assert_eq!(kept, before, "the pose is kept");
    // Against a world made with the stiffer body from the same pose.
    let mut both = Model::new();
    both.append(&boxes_on_the_ground(0.6, &[-0.2]).0);
    both.append(&stiffer);
    let mut made = make(&both);
    made.write_params(&g.queue);
    let mut enc = g.device.create_command_encoder(&Default::default());
    for b in 0..2 {
        let r = replaced.ranges[b];
        made.copy_state_from(&mut enc, &replaced, r.first, made.ranges[b].first, r.count);
    }
    g.queue.submit([enc.finish()]);
    made.step = replaced.step;
    made.forget_neighbours();
    replaced.forget_neighbours();
    let a = run_gpu(g, &mut replaced, &ground, 30);
    let b = run_gpu(g, &mut made, &ground, 30);
    assert_eq!(max_dist(&a, &b), 0.0, "moves as in a world made with it");
    assert!(max_dist(&a, &kept) > 1e-4, "the scene moved");
    // Another size: refused, nothing changed.
    let (bigger, _) = hanging(Material::ShapeMatching { stiffness: 0.6 });
    assert!(
        !replaced
            .replace_body(&g.device, &g.queue, 1, &bigger, None)
            .unwrap()
    );
    // A body appended anew takes an old slot's pose.
    let copy = boxes_on_the_ground(0.6, &[-0.2]).0;
    assert!(
        replaced
            .append(&g.device, &g.queue, &copy, &State::new(&copy))
            .unwrap()
    );
    replaced.copy_body_state(&g.device, &g.queue, 0, 2);
    let x = read_vec3(
        &g.device,
        &g.queue,
        replaced.positions(),
        replaced.particle_count(),
    );
    let (r0, r2) = (replaced.ranges[0], replaced.ranges[2]);
    let at =
        |r: bevy_tissue::gpu::world::BodyRange| (r.first as usize)..((r.first + r.count) as usize);
    assert_eq!(x[at(r0)], x[at(r2)], "the appended body took the pose");
}

/// A world grown on the GPU (`GpuWorld::grow`: new buffers, everything copied over) moves
/// on exactly as a world made with that room from the start, draws the same, and takes
/// appended bodies into its new room.
#[test]
fn a_grown_world_moves_on_as_one_made_with_the_room() {
    let Some(g) = gpu() else { return };
    let (two, s, ground) = boxes_on_the_ground(0.6, &[-0.1, -0.068]);
    let state = State::new(&two);
    let mut roomy =
        GpuWorld::with_room(&g.device, &g.kernels, &two, &state, s.clone(), 0, 2.5).unwrap();
    let cap = roomy.capacity();
    let mut grown = GpuWorld::new(&g.device, &g.kernels, &two, &state, s.clone(), 0).unwrap();
    assert!(grown.capacity().particles < cap.particles);
    run_gpu(g, &mut roomy, &ground, 10);
    run_gpu(g, &mut grown, &ground, 10);
    assert!(grown.grow(&g.device, &g.queue, &g.kernels, cap).unwrap());
    assert_eq!(grown.capacity(), cap);
    let a = run_gpu(g, &mut roomy, &ground, 30);
    let b = run_gpu(g, &mut grown, &ground, 30);
    assert!(
        max_dist(&a, &b) == 0.0,
        "moved on differently by {} m",
        max_dist(&a, &b)
    );
    assert!(max_dist(&a, &state.x) > 0.005, "the scene moved");
    assert_eq!(
        draw_surface(g, &roomy),
        draw_surface(g, &grown),
        "drawn the same"
    );
    // The new room takes a body.
    let (third, _, _) = boxes_on_the_ground(0.6, &[0.2]);
    let st = State::new(&third);
    assert!(roomy.append(&g.device, &g.queue, &third, &st).unwrap());
    assert!(grown.append(&g.device, &g.queue, &third, &st).unwrap());
    let a = run_gpu(g, &mut roomy, &ground, 20);
    let b = run_gpu(g, &mut grown, &ground, 20);
    assert!(
        max_dist(&a, &b) == 0.0,
        "with the appended body: {} m",
        max_dist(&a, &b)
    );
}

/// A retired body (`GpuWorld::retire`, what the plugin does on a despawn) leaves every
/// other body's motion exactly as it was, sleeps for good, and its particles are parked
/// far away; a world with hierarchy levels refuses (the caller rebuilds).
#[test]
fn a_retired_body_leaves_the_others_as_they_were() {
    let Some(g) = gpu() else { return };
    let sm = Material::ShapeMatching { stiffness: 0.6 };
    let (model, s, ground) = boxes_on_the_ground(0.6, &[-0.2, 0.2]);
    let mut kept = fresh_world_with(g, &model, s.clone());
    let mut retired = fresh_world_with(g, &model, s);
    run_gpu(g, &mut kept, &ground, 10);
    run_gpu(g, &mut retired, &ground, 10);
    let r = retired.ranges[1];
    assert_eq!(retired.retire(&g.queue, 1), Some(r.count));
    assert!(retired.is_retired(1) && !retired.is_retired(0));
    // The plugin's per-frame sleep flags cannot wake it.
    retired.set_asleep(&g.queue, [false, false]);
    let a = run_gpu(g, &mut kept, &ground, 30);
    let b = run_gpu(g, &mut retired, &ground, 30);
    let first = retired.ranges[0];
    let body0 = first.first as usize..(first.first + first.count) as usize;
    let d = max_dist(&a[body0.clone()], &b[body0]);
    assert!(d == 0.0, "the other body moved differently by {d} m");
    let parked = &b[r.first as usize..(r.first + r.count) as usize];
    assert!(parked.iter().all(|p| p.y > 1000.0), "parked far away");
    // Hierarchy levels: refused.
    let (hmodel, _) = hanging(sm);
    let mut h = Model::new();
    let desc = BodyDesc {
        hierarchy: Some(bevy_tissue::core::hierarchy::HierarchyDesc {
            min_particles: 32,
            ..Default::default()
        }),
        ..body(sm, Vec3::ZERO, 600, vec![])
    };
    h.add_body(&procedural::cuboid(Vec3::new(0.06, 0.03, 0.03), 4), &desc)
        .unwrap();
    h.append(&hmodel);
    assert!(!h.levels.is_empty(), "the world has hierarchy levels");
    let mut w = fresh_world_with(g, &h, settings());
    assert_eq!(w.retire(&g.queue, 1), None);
}
