//! GPU benchmark of the batched world (SPEC §7), outside Bevy's frame loop: the
//! procedural liver pinned at its ligament at the paper's largest size, 1,000,000
//! particles, and 1,000 bodies of 512 particles, K = 32, 10 iterations, dt = 1/60 s,
//! with the K = 32 neighbour search of every particle refreshed every 10th step.
//!
//! For each scene: ms per step (wall clock over many steps recorded into one
//! submission, GPU synchronised, median of 5 repeats), ms per KNN refresh (cold: no
//! previous lists; warm: starting from the previous search's lists, on unchanged
//! positions), and GPU time per pass from timestamp queries. Markdown on stdout.
//!
//! With `--scale` it instead runs the liver from 37,982 up to 4,000,000 particles (SPEC
//! §6 scaling; shape matching k = 1, the plugin's default; 50 steps, median of 3), with
//! the same per-pass table; `--sizes a,b,..` picks other counts.
//!
//! ```text
//! cargo run --release --example gpu_bench            # the full set (a real GPU)
//! cargo run --release --example gpu_bench -- --scale # 38k to 4M particles
//! cargo run --release --example gpu_bench -- --quick # small sizes (lavapipe: seconds)
//! cargo run --release --example gpu_bench -- --scenes 38k,1000 # some of the full set
//! ```
//!
//! `--scenes` picks from the full set by name: `38k`, `1000` (bodies × 512, 0.15 m apart,
//! falling together; f32 rounding far from the origin drifts some within the contact
//! reach of another, and the run prints how many), `he` (the hyperelastic liver),
//! `1m`; all four by default. `1000c` (the 1,000 bodies 0.1 m apart, every one touching
//! its neighbours: the contact search and pass run for all) only when named.
//! `1000g` (the 1,000 bodies resting on a ground plane in one layer, 0.15 m apart: near
//! no other, and they stay so) also only when named. `--bodies N` changes the body count
//! of those three scenes. `--contact-every N` solves particle contacts in every N-th iteration
//! and `--contact-relaxation W` relaxes them by ω_c (`SolverSettings::contact_every`,
//! `contact_relaxation`; by default the plugin's, `TissueSettings::default()`). `--no-knn-all` leaves the all-particle
//! K = 32 search out of the steps (the paper's every-10th-step search, which the plugin's
//! step never runs: it searches only for contact candidates, and those searches stay);
//! the KNN columns still time it on its own.
//!
//! `--edits` instead measures what changing the world costs a frame, as the plugin
//! changes it: the `1000g` bodies (`--bodies N`) stepped one step a frame with the
//! plugin's settings in a world with the plugin's room for more, then gravity halved
//! (`GpuWorld::set_settings`), a body despawned (`retire`), a body spawned (`append`), the
//! room grown by half on the GPU (`grow`, what a spawn past the room costs) and, for
//! comparison, the whole world made again (what every change cost before). For each:
//! the CPU time of the call, and the GPU and wall time of the frame after it, against
//! the median frame.
//!
//! `--webgpu-limits` holds the device to WebGPU's default limits (what every browser
//! guarantees; the tests run the example so).
#[path = "support/bench.rs"]
mod bench;

use bevy_tissue::core::colliders::Collider;
use bevy_tissue::core::model::{BodyDesc, Material, Model, PinRegion};
use bevy_tissue::core::procedural;
use bevy_tissue::core::sampling::Resolution;
use bevy_tissue::core::solver::{Method, SolverSettings, State};
use bevy_tissue::gpu::profile::GpuProfiler;
use bevy_tissue::gpu::world::read_vec3;
use bevy_tissue::gpu::{GpuWorld, Headless, NoTiming, PassRecorder};
use bevy_tissue::plugin::components::TissueSettings;
use glam::Vec3;
use std::time::Instant;

fn liver(resolution: Resolution, k: u32, material: Material) -> Model {
    let (lo, hi) = procedural::liver_ligament();
    let mut model = Model::new();
    let desc = BodyDesc {
        resolution,
        neighbours: k,
        material,
        pins: vec![PinRegion::Box { min: lo, max: hi }],
        discretisation: bevy_tissue::core::model::Discretisation::Clusters,
        ..Default::default()
    };
    model
        .add_body(&procedural::liver(4), &desc)
        .expect("liver model");
    model
}

fn many(bodies: u32, particles: u32, k: u32, material: Material, apart: f32) -> Model {
    let mut one = Model::new();
    let desc = BodyDesc {
        resolution: Resolution::Particles(particles),
        neighbours: k,
        material,
        discretisation: bevy_tissue::core::model::Discretisation::Clusters,
        ..Default::default()
    };
    one.add_body(&procedural::icosphere(0.05, 2), &desc)
        .expect("body");
    let mut model = Model::new();
    let side = (bodies as f32).cbrt().ceil() as u32;
    for i in 0..bodies {
        let mut b = one.clone();
        let (x, y, z) = (i % side, (i / side) % side, i / (side * side));
        b.bodies[0].translation = Vec3::new(x as f32, y as f32 + 1.0, z as f32) * apart;
        model.append(&b);
    }
    model
}

/// `bodies` balls like [`many`]'s in one layer on the ground (y = 0), `apart` m between
/// centres, each 1 cm above it at the start: they land and rest, apart.
fn on_ground(bodies: u32, particles: u32, k: u32, material: Material, apart: f32) -> Model {
    let one = many(1, particles, k, material, apart);
    let mut model = Model::new();
    let side = (bodies as f32).sqrt().ceil() as u32;
    for i in 0..bodies {
        let mut b = one.clone();
        let (x, z) = (i % side, i / side);
        b.bodies[0].translation = Vec3::new(x as f32 * apart, 0.06, z as f32 * apart);
        model.append(&b);
    }
    model
}

struct Row {
    scene: String,
    particles: u32,
    ms_step: f64,
    gpu_ms: f64,
    ms_knn: f64,
    ms_knn_cold: f64,
    passes: Vec<(&'static str, f64, f64)>,
}

fn record(
    g: &Headless,
    world: &mut GpuWorld,
    steps: u32,
    knn_every: u32,
    rec: &mut dyn PassRecorder,
) -> bevy::render::render_resource::CommandEncoder {
    let mut enc = g.device.create_command_encoder(&Default::default());
    record_into(g, world, &mut enc, steps, knn_every, rec);
    enc
}

/// Records `steps` steps into `enc`: the all-particle search every `knn_every`-th step,
/// the steps between two searches in one `record_steps` (as the plugin records a frame's
/// steps: the finish of one step and the predict of the next share a dispatch).
fn record_into(
    g: &Headless,
    world: &mut GpuWorld,
    enc: &mut bevy::render::render_resource::CommandEncoder,
    steps: u32,
    knn_every: u32,
    rec: &mut dyn PassRecorder,
) {
    let mut left = steps;
    while left > 0 {
        let mut run = left;
        if knn_every > 0 {
            let phase = (world.step % knn_every as u64) as u32;
            if phase == 0 && *KNN_ALL.get_or_init(|| true) {
                world.record_knn_all(enc, &g.kernels, rec);
            }
            run = run.min(knn_every - phase);
        }
        world.record_steps(enc, &g.kernels, run, rec);
        left -= run;
    }
}

/// Whether the steps include the all-particle K = 32 search every 10th step (the paper's
/// Table 1 setting; `--no-knn-all` leaves it out: the plugin's step never runs it, only
/// the contact search, which stays).
static KNN_ALL: std::sync::OnceLock<bool> = std::sync::OnceLock::new();

/// `SolverSettings::contact_every` and `contact_relaxation` of every scene
/// (`--contact-every`, `--contact-relaxation`; by default the plugin's, from
/// `TissueSettings::default()`).
static CONTACTS: std::sync::OnceLock<(u32, f32)> = std::sync::OnceLock::new();

/// The plugin's contact schedule: `TissueSettings::default()`'s.
fn plugin_contacts() -> (u32, f32) {
    let d = TissueSettings::default();
    (d.contact_every, d.contact_relaxation)
}

fn bench(g: &Headless, scene: &str, model: &Model, steps: u32, repeats: usize) -> Row {
    bench_with(g, scene, model, steps, repeats, &[])
}

/// [`bench`] with kinematic colliders.
fn bench_with(
    g: &Headless,
    scene: &str,
    model: &Model,
    steps: u32,
    repeats: usize,
    colliders: &[Collider],
) -> Row {
    let n = model.particle_count() as u32;
    let t0 = Instant::now();
    eprintln!("{scene}: {n} particles, uploading");
    let (contact_every, contact_relaxation) = *CONTACTS.get_or_init(plugin_contacts);
    let settings = SolverSettings {
        method: Method::Jacobi,
        iterations: 10,
        knn_every: 10,
        contact_every,
        contact_relaxation,
        ..Default::default()
    };
    let state = State::new(model);
    let mut world = GpuWorld::new(&g.device, &g.kernels, model, &state, settings, 32)
        .unwrap_or_else(|e| panic!("{scene}: {e}"));
    world
        .set_colliders(&g.queue, colliders)
        .unwrap_or_else(|e| panic!("{scene}: {e}"));
    world.write_params(&g.queue);
    eprintln!("  uploaded in {:.2} s", t0.elapsed().as_secs_f64());
    // Warm-up.
    let enc = record(g, &mut world, 20, 10, &mut NoTiming);
    g.queue.submit([enc.finish()]);
    bench::sync(g, &world);
    let mut per_step = Vec::new();
    for r in 0..repeats {
        let enc = record(g, &mut world, steps, 10, &mut NoTiming);
        let t = Instant::now();
        g.queue.submit([enc.finish()]);
        bench::sync(g, &world);
        let ms = t.elapsed().as_secs_f64() * 1e3 / steps as f64;
        eprintln!("  repeat {r}: {ms:.4} ms/step");
        per_step.push(ms);
    }
    eprintln!("  stepped; {:.2} s so far", t0.elapsed().as_secs_f64());
    // KNN refresh alone: cold (no previous lists), then warm (each search starting
    // from the one before, on unchanged positions: the bound is then exact, so this is
    // the best case; the steps above search on moving positions).
    let mut cold = Vec::new();
    for _ in 0..repeats {
        let mut enc = g.device.create_command_encoder(&Default::default());
        for _ in 0..10 {
            world.forget_neighbours();
            world.record_knn_all(&mut enc, &g.kernels, &mut NoTiming);
        }
        let t = Instant::now();
        g.queue.submit([enc.finish()]);
        bench::sync(g, &world);
        cold.push(t.elapsed().as_secs_f64() * 1e3 / 10.0);
    }
    let mut knn = Vec::new();
    for _ in 0..repeats {
        let mut enc = g.device.create_command_encoder(&Default::default());
        for _ in 0..10 {
            world.record_knn_all(&mut enc, &g.kernels, &mut NoTiming);
        }
        let t = Instant::now();
        g.queue.submit([enc.finish()]);
        bench::sync(g, &world);
        knn.push(t.elapsed().as_secs_f64() * 1e3 / 10.0);
    }
    // GPU timeline: timestamps before and after `steps` steps in one submission
    // (includes the gaps between dispatches, excludes the CPU's encoding).
    let mut gpu_ms = f64::NAN;
    if let Some(mut prof) = GpuProfiler::new(&g.device, &g.queue, 4) {
        let mut enc = g.device.create_command_encoder(&Default::default());
        prof.mark(&mut enc);
        record_into(g, &mut world, &mut enc, steps, 10, &mut NoTiming);
        prof.mark(&mut enc);
        prof.resolve(&mut enc);
        g.queue.submit([enc.finish()]);
        let m = prof.read_marks(&g.device, &g.queue);
        if m.len() == 2 {
            gpu_ms = (m[1] - m[0]) / steps as f64;
        }
    }
    // Per pass: 10 steps (one KNN refresh) under timestamp queries.
    let mut passes = Vec::new();
    if let Some(mut prof) = GpuProfiler::new(&g.device, &g.queue, 2048) {
        let mut enc = record(g, &mut world, 10, 10, &mut prof);
        prof.resolve(&mut enc);
        g.queue.submit([enc.finish()]);
        for (name, (ms, count)) in prof.read(&g.device, &g.queue) {
            passes.push((name, ms / 10.0, count as f64 / 10.0));
        }
    }
    let x = read_vec3(&g.device, &g.queue, world.positions(), n);
    let finite = x.iter().all(|p| p.is_finite());
    let r = Row {
        scene: if finite {
            scene.into()
        } else {
            format!("{scene} (DIVERGED: non-finite state)")
        },
        particles: n,
        ms_step: bench::median(per_step),
        gpu_ms,
        ms_knn: bench::median(knn),
        ms_knn_cold: bench::median(cold),
        passes,
    };
    println!(
        "| {} | {} | {:.3} | {:.3} | {:.3} | {:.3} |",
        r.scene, r.particles, r.gpu_ms, r.ms_step, r.ms_knn_cold, r.ms_knn
    );
    let per_pass: Vec<String> = r
        .passes
        .iter()
        .map(|(name, ms, count)| format!("{name} {ms:.4} ms ({count} dispatches)"))
        .collect();
    eprintln!("  per step: {}", per_pass.join(", "));
    let near = world.read_near_flags(&g.device, &g.queue);
    let count = near.iter().filter(|n| **n).count();
    eprintln!(
        "  bodies near another at the last contact refresh: {count} of {}",
        near.len()
    );
    r
}

/// What `--help` prints: the options (the module documentation says more).
const USAGE: &str = "gpu_bench: the batched GPU world's ms per step (SPEC §7)

options:
  --quick               small sizes (lavapipe: seconds)
  --scenes a,b,..       38k, 1000, he, 1m (the default set); 1000c, 1000g only when named
  --bodies N            body count of the 1000, 1000c and 1000g scenes (default 1000)
  --contact-every N     particle contacts every N-th iteration (default: the plugin's)
  --contact-relaxation W  their Jacobi relaxation ω_c (default: the plugin's)
  --no-knn-all          leave the paper's all-particle search out of the steps
  --steps N             steps per repeat (default 300; --quick 20)
  --repeats N           repeats (default 5; --quick 3)
  --scale [--sizes ..]  the liver from 37,982 to 4,000,000 particles
  --edits               what a gravity change, a despawn and a spawn cost a frame
  --help                this text";

/// One frame as the plugin records it (one step, no all-particle search), timed: GPU ms
/// between timestamps around the step, and wall ms from `since` to the GPU's end.
fn frame(g: &Headless, world: &mut GpuWorld, prof: &mut GpuProfiler, since: Instant) -> (f64, f64) {
    world.write_params(&g.queue);
    let mut enc = g.device.create_command_encoder(&Default::default());
    prof.mark(&mut enc);
    world.record_steps(&mut enc, &g.kernels, 1, &mut NoTiming);
    prof.mark(&mut enc);
    prof.resolve(&mut enc);
    g.queue.submit([enc.finish()]);
    let m = prof.read_marks(&g.device, &g.queue);
    let wall = since.elapsed().as_secs_f64() * 1e3;
    let gpu = if m.len() == 2 { m[1] - m[0] } else { f64::NAN };
    (gpu, wall)
}

/// `--edits`: what each change of the world costs a frame (see the module docs).
fn edits(g: &Headless, bodies: u32, quick: bool) {
    let sm = Material::ShapeMatching { stiffness: 1.0 };
    let model = on_ground(bodies, 512, 32, sm, 0.15);
    let settings = TissueSettings::default().to_core();
    let every = settings.knn_every.max(1) as u64;
    let ground = [Collider::ground(0.0)];
    let make = |model: &Model| {
        let state = State::new(model);
        GpuWorld::with_room(
            &g.device,
            &g.kernels,
            model,
            &state,
            settings.clone(),
            0,
            1.5,
        )
        .unwrap_or_else(|e| panic!("edits: {e}"))
    };
    let mut world = make(&model);
    world.set_colliders(&g.queue, &ground).unwrap();
    let Some(mut prof) = GpuProfiler::new(&g.device, &g.queue, 4) else {
        eprintln!("edits: no timestamp queries on this adapter");
        return;
    };
    let (frames, reps) = if quick { (10, 2) } else { (120, 5) };
    for _ in 0..frames / 2 {
        frame(g, &mut world, &mut prof, Instant::now());
    }
    // Frames with and without the contact search.
    let (mut plain, mut search) = ((Vec::new(), Vec::new()), (Vec::new(), Vec::new()));
    for _ in 0..frames {
        let due = world.step.is_multiple_of(every);
        let (a, b) = frame(g, &mut world, &mut prof, Instant::now());
        let into = if due { &mut search } else { &mut plain };
        into.0.push(a);
        into.1.push(b);
    }
    println!(
        "{} bodies x 512 on the ground, one step a frame with the plugin's settings \
         (contact search every {every} steps), room for {} particles and {} bodies; \
         medians of {reps} changes each, made where the next step has no contact search \
         of its own\n",
        bodies,
        world.capacity().particles,
        world.capacity().bodies
    );
    println!(
        "| change | CPU µs of the call | GPU ms of the next frame | wall ms of the next frame (from the call) | slowest wall ms of the 10 after |"
    );
    println!("|---|---|---|---|---|");
    for (name, (gpu, wall)) in [
        ("none: a frame", plain),
        ("none: a frame with the contact search", search),
    ] {
        if !gpu.is_empty() {
            println!(
                "| {name} (median of {}) | | {:.3} | {:.3} | |",
                gpu.len(),
                bench::median(gpu),
                bench::median(wall)
            );
        }
    }
    // Each change `reps` times, each where the next step has no search of its own, then
    // the frame after it and ten more.
    let mut change = |name: &str, world: &mut GpuWorld, f: &mut dyn FnMut(&mut GpuWorld, usize)| {
        let (mut calls, mut gpus, mut walls, mut after) =
            (Vec::new(), Vec::new(), Vec::new(), 0.0f64);
        for r in 0..reps {
            while world.step % every != every / 2 {
                frame(g, world, &mut prof, Instant::now());
            }
            let t = Instant::now();
            f(world, r);
            calls.push(t.elapsed().as_secs_f64() * 1e6);
            let (gpu, wall) = frame(g, world, &mut prof, t);
            gpus.push(gpu);
            walls.push(wall);
            for _ in 0..10 {
                after = after.max(frame(g, world, &mut prof, Instant::now()).1);
            }
        }
        println!(
            "| {name} | {:.0} | {:.3} | {:.3} | {after:.3} |",
            bench::median(calls),
            bench::median(gpus),
            bench::median(walls)
        );
    };
    change("gravity changed (set_settings)", &mut world, &mut |w, r| {
        let s = SolverSettings {
            gravity: settings.gravity * if r % 2 == 0 { 0.5 } else { 1.0 },
            ..settings.clone()
        };
        assert!(w.set_settings(&g.queue, s).unwrap(), "in place");
    });
    change("a body despawned (retire)", &mut world, &mut |w, r| {
        assert!(
            w.retire(&g.queue, bodies as usize / 2 + r).is_some(),
            "retired"
        );
    });
    // New balls on the ground beyond the others.
    let spawned: Vec<Model> = (0..reps)
        .map(|r| {
            let mut one = on_ground(1, 512, 32, sm, 0.15);
            one.bodies[0].translation = Vec3::new(-0.3 - 0.15 * r as f32, 0.06, -0.3);
            one
        })
        .collect();
    let used_before = world.used();
    change("a body spawned (append)", &mut world, &mut |w, r| {
        let state = State::new(&spawned[r]);
        assert!(
            w.append(&g.device, &g.queue, &spawned[r], &state).unwrap(),
            "appended in place"
        );
    });
    assert_eq!(world.used().bodies, used_before.bodies + reps as u32);
    // Of which the CPU packing of the body alone.
    let packing: Vec<f64> = spawned
        .iter()
        .map(|m| {
            let t = Instant::now();
            let p = bevy_tissue::gpu::buffers::Packed::new(m, &settings);
            std::hint::black_box(&p);
            t.elapsed().as_secs_f64() * 1e6
        })
        .collect();
    println!(
        "| of which packing the body's arrays (CPU) | {:.0} | | | |",
        bench::median(packing)
    );
    change("the room grown by half (grow)", &mut world, &mut |w, _| {
        let c = w.capacity();
        let half = |x: u32| x + x / 2;
        let more = bevy_tissue::gpu::world::Capacity {
            particles: half(c.particles),
            bodies: half(c.bodies),
            vertices: half(c.vertices),
            members: half(c.members),
            triangles: half(c.triangles),
        };
        assert!(
            w.grow(&g.device, &g.queue, &g.kernels, more).unwrap(),
            "grown"
        );
    });
    let mut all = model.clone();
    for m in &spawned {
        all.append(m);
    }
    change(
        "the world made again (what each change cost before)",
        &mut world,
        &mut |w, _| {
            *w = make(&all);
            w.set_colliders(&g.queue, &ground).unwrap();
        },
    );
    let x = read_vec3(
        &g.device,
        &g.queue,
        world.positions(),
        world.particle_count(),
    );
    assert!(x.iter().all(|p| p.is_finite()), "edits: non-finite state");
}

fn main() {
    let args = bench::Args::new();
    if args.flag("--help") || args.flag("-h") {
        println!("{USAGE}");
        return;
    }
    let quick = args.flag("--quick");
    let g = match bench::open_gpu() {
        Ok(g) => g,
        Err(e) => {
            eprintln!("gpu_bench: {e}");
            std::process::exit(1);
        }
    };
    if args.flag("--edits") {
        edits(
            &g,
            args.num("--bodies", if quick { 8 } else { 1000 }),
            quick,
        );
        return;
    }
    let (every, omega) = plugin_contacts();
    let every: u32 = args.num("--contact-every", every);
    let omega: f32 = args.num("--contact-relaxation", omega);
    // The body count of the `1000` and `1000c` scenes (fewer fit lavapipe's buffers).
    let bodies: u32 = args.num("--bodies", 1000);
    CONTACTS.set((every, omega)).ok();
    let knn_all = !args.flag("--no-knn-all");
    KNN_ALL.set(knn_all).ok();
    let limits = g.device.limits();
    println!("Particle contacts in every {every} iteration(s), relaxation ω_c = {omega}");
    if !knn_all {
        println!("Steps without the all-particle search (--no-knn-all): the plugin's step");
    }
    println!(
        "GPU: {} (workgroup memory {} bytes, {} invocations per workgroup)\n",
        g.adapter,
        limits.max_compute_workgroup_storage_size,
        limits.max_compute_invocations_per_workgroup
    );
    // Shape matching at the plugin's default stiffness (k = 1: softer k stretches far
    // under Jacobi averaging, BENCHMARKS.md).
    let sm = Material::ShapeMatching { stiffness: 1.0 };
    let he = Material::default();
    let steps: u32 = args.num("--steps", if quick { 20 } else { 300 });
    let repeats: usize = args.num("--repeats", if quick { 3 } else { 5 });
    let mut rows = Vec::new();
    println!(
        "| scene | particles | GPU ms per step | wall ms per step (incl. wgpu encoding) | wall ms per KNN (K=32), cold | wall ms per KNN, warm |"
    );
    println!("|---|---|---|---|---|---|");
    if quick {
        rows.push(bench(
            &g,
            "liver 4096, shape matching",
            &liver(Resolution::Particles(4096), 32, sm),
            steps,
            repeats,
        ));
        rows.push(bench(
            &g,
            "20 bodies x 512, hyperelastic",
            &many(20, 512, 32, he, 0.15),
            steps,
            repeats,
        ));
    } else if args.flag("--scale") {
        let sizes: Vec<u32> = args.list(
            "--sizes",
            &[37_982, 131_072, 524_288, 1_000_000, 2_000_000, 4_000_000],
        );
        let rigid = Material::ShapeMatching { stiffness: 1.0 };
        let s38 = liver(Resolution::Particles(37982), 32, rigid).bodies[0].spacing;
        for n in sizes {
            let t = Instant::now();
            let model = liver(
                Resolution::Spacing(s38 * (37982.0 / n as f32).cbrt()),
                32,
                rigid,
            );
            eprintln!(
                "{} particles built in {:.1} s",
                model.particle_count(),
                t.elapsed().as_secs_f64()
            );
            let check = SolverSettings {
                method: Method::Jacobi,
                ..Default::default()
            };
            if let Err(e) = GpuWorld::check_limits(&g.device.limits(), &model, &check) {
                println!(
                    "| liver {} | does not fit: {e} | | | |",
                    model.particle_count()
                );
                continue;
            }
            let name = format!("liver {}, shape matching k = 1", model.particle_count());
            rows.push(bench(&g, &name, &model, steps.min(50), repeats.min(3)));
        }
    } else {
        let all = ["38k", "1000", "1000c", "1000g", "he", "1m"].map(String::from);
        // All but the contact and ground variants of the 1,000 bodies by default.
        let default: Vec<String> = all
            .iter()
            .filter(|s| *s != "1000c" && *s != "1000g")
            .cloned()
            .collect();
        let scenes = args.text("--scenes").map_or(default, |s| {
            s.split(',').map(|x| x.trim().to_lowercase()).collect()
        });
        if let Some(bad) = scenes.iter().find(|s| !all.contains(s)) {
            eprintln!("gpu_bench: unknown scene `{bad}` (expected some of {all:?})");
            std::process::exit(2);
        }
        let on = |name: &str| scenes.iter().any(|s| s == name);
        let t = Instant::now();
        let l38 = liver(Resolution::Particles(37982), 32, sm);
        eprintln!("liver 37982 built in {:.1} s", t.elapsed().as_secs_f64());
        let s38 = l38.bodies[0].spacing;
        if on("38k") {
            rows.push(bench(
                &g,
                "liver 37982, shape matching",
                &l38,
                steps,
                repeats,
            ));
        }
        if on("1000") {
            rows.push(bench(
                &g,
                "1000 bodies x 512, shape matching",
                &many(bodies, 512, 32, sm, 0.15),
                steps,
                repeats,
            ));
        }
        if on("1000c") {
            // The same bodies 0.1 m apart: each 0.1 m sphere touches its neighbours, so
            // the contact broad phase skips none (only run when asked for).
            rows.push(bench(
                &g,
                "1000 bodies x 512 in contact, shape matching",
                &many(bodies, 512, 32, sm, 0.1),
                steps,
                repeats,
            ));
        }
        if on("1000g") {
            // Resting on a ground plane, apart: no drift into contact (the `1000` scene
            // falls without end and drifts), the ground collider for every particle.
            rows.push(bench_with(
                &g,
                "1000 bodies x 512 resting on the ground, shape matching",
                &on_ground(bodies, 512, 32, sm, 0.15),
                steps,
                repeats,
                &[Collider::ground(0.0)],
            ));
        }
        if on("he") {
            rows.push(bench(
                &g,
                "liver 13824, hyperelastic",
                &liver(Resolution::Particles(13824), 32, he),
                steps,
                repeats,
            ));
        }
        if on("1m") {
            let t = Instant::now();
            // Same shape, spacing scaled to ~1M particles (no count search).
            let big = liver(
                Resolution::Spacing(s38 * (37982.0f32 / 1.0e6).cbrt()),
                32,
                sm,
            );
            eprintln!("1M model built in {:.1} s", t.elapsed().as_secs_f64());
            rows.push(bench(&g, "liver 1M, shape matching", &big, 50, 3));
        }
    }
    for r in &rows {
        println!(
            "\nGPU time per pass, {} (per step; timestamp queries):\n",
            r.scene
        );
        println!("| pass | ms per step | dispatches per step |");
        println!("|---|---|---|");
        let total: f64 = r.passes.iter().map(|p| p.1).sum();
        for (name, ms, count) in &r.passes {
            println!("| {name} | {ms:.4} | {count} |");
        }
        println!("| sum | {total:.4} | |");
    }
}
