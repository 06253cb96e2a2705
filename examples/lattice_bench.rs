//! Newton–multigrid for lattice bodies on the GPU (`bevy_tissue::gpu::lattice`): speed at
//! the paper's sizes and accuracy at real-time budgets.
//!
//! 1. **Speed.** The procedural liver as a lattice body pinned at its ligament
//!    (37,982 particles requested; the lattice's own count is printed), E = 30 kPa,
//!    ν = 0.45, and 1,000 lattice cubes of 8 × 8 × 8 particles (512 each) falling
//!    side by side, E = 100 kPa. 1/60 s steps of 1 substep × 1 or 2 Newton iterations
//!    (each of `--cycles` V-cycles).
//!    Per scene: ms per step of GPU time (timestamps around the steps' compute pass),
//!    ms per step of wall clock (many steps in one submission, GPU synchronised, median of
//!    5), and dispatches per step.
//! 2. **Accuracy.** The cantilever of the accuracy example (24 × 3 × 3 cm, lattice,
//!    6 and 12 particles across, clamped) settled on the GPU at 1/60 s steps, against
//!    the static answer of the same model (`core::statics`), E from 1 kPa to 1 MPa
//!    (gravity scaled with E), critically damped as in `accuracy -- --only-realtime`.
//!
//! 3. **Organ meshes** (`--organs`): the meshes of `$BEVY_TISSUE_MESHES` (else
//!    `../shared/meshes`) scaled to 20 cm, E = 5 kPa, ν = 0.45, 1060 kg/m³, at 4,000 and
//!    40,000 particles, resting on the ground and hung from their top 10%, 1 s each at
//!    1/60 s (the default Newton iterations) on the GPU: whether every position stays finite,
//!    the volume over the rest volume, the lowest point against the ground.
//!
//! Speed and accuracy run once per V-cycle smoother (`--smoother chebyshev`, `hybrid` or
//! `gs` for one of them). Markdown on stdout.
//!
//! ```text
//! cargo run --release --example lattice_bench            # everything (a real GPU)
//! cargo run --release --example lattice_bench -- --quick # small sizes (lavapipe: a minute)
//! ```
//! Options: `--no-speed`, `--no-accuracy`, `--organs`, `--bodies N` (default 1,000),
//! `--newton N,...` (Newton iterations per step to compare, default 1,2),
//! `--cycles N,...` (V-cycles per Newton iteration to compare, more than 1 being
//! conjugate gradients; default 1), `--sweeps F/C/K,...` (the V-cycle's smoothing
//! sweeps to compare: on level 0, the levels between and the coarsest,
//! `SolverSettings::sweeps`; `F/C/Kx`: the coarsest level solved exactly where its
//! bodies are small enough, `Sweeps::exact_coarsest`, and `F/C/Kt` or `F/C/Kxt` each
//! V-cycle's translation step, `Sweeps::translation`; `B:A` for a level's sweeps before
//! and after the coarse correction where they differ; default the library's,
//! `0:1/0:2/30x`), `--no-touching` (speed: leave out
//! the touching cubes), `--moving-lists` (speed: also the touching cubes with the
//! contact lists the plugin searches while every other body moves at 1 m/s past the
//! others, a reach widened for that travel),
//! `--smoother chebyshev|hybrid|gs`, `--first N,...` (speed only: line-search candidates
//! of the first energy pass, `LatticeOptions::first_candidates`, values to compare,
//! default the library's), `--room R` (speed only: the worlds made with room for bodies
//! appended later, `LatticeOptions::room`; default none), `--fused N,...` (speed only:
//! the most coarsest-level nodes a body may have for that level's sweeps to run in one
//! dispatch, `LatticeOptions::fused_coarsest`, values to compare, 0 never; default the
//! library's), `--rows N,...` (speed only: the fewest nodes a smoothing pass has for it
//! to sum each node's row in one thread rather than eight,
//! `LatticeOptions::one_thread_rows_from`, values to compare, 0 always, 4294967295
//! never; default the library's), `--keep-factor N,...` (speed only: 1 keeps the
//! exactly solved coarsest level's factor from the Newton iteration's start for its
//! V-cycles, 0 makes it again in each, `LatticeOptions::keep_coarsest_factor`; default
//! the library's), `--profile` (GPU time
//! per kernel of each speed row: timestamps between the dispatches of one pass where the
//! device writes them there, else every dispatch in its own timed pass; these stall the
//! GPU at each dispatch, so they give shares, not costs), `--costs` (each dispatch's
//! cost in each speed row's step: the step's GPU time with that dispatch recorded twice
//! less the plain step's), `--line-steps` (each speed row's line search after the
//! warm-up and after the timed steps: how many bodies took each step).
//!
//! `--changes` (what changing a world of `--bodies` touching cubes costs: made again
//! for one more body, one appended into its room, one retired, gravity; and the step's
//! GPU time with room).
//!
//! `--webgpu-limits` holds the device to WebGPU's default limits (what every browser
//! guarantees; the tests run the example so).
#[path = "support/accuracy.rs"]
mod accuracy;
#[path = "support/bench.rs"]
mod bench;
#[path = "../tests/common/mod.rs"]
mod common;

use accuracy::*;
use bevy::render::renderer::{RenderDevice, RenderQueue};
use bevy_tissue::core::colliders::Collider;
use bevy_tissue::core::model::{BodyDesc, Discretisation, Material, Model, PinRegion};
use bevy_tissue::core::multigrid::{Smoother, Sweeps};
use bevy_tissue::core::procedural;
use bevy_tissue::core::sampling::Resolution;
use bevy_tissue::core::solver::{ElementSolver, Method, Solver, SolverSettings, State};
use bevy_tissue::gpu::kernels::lattice::LatticeKernels;
use bevy_tissue::gpu::lattice::{GpuLattice, LatticeOptions};
use bevy_tissue::gpu::profile::GpuProfiler;
use bevy_tissue::gpu::world::read_buffer;
use bevy_tissue::gpu::{PassRecorder, device_with};
use glam::Vec3;
use std::time::Instant;

fn fail(what: &str, e: impl std::fmt::Display) -> ! {
    eprintln!("{what}: {e}");
    std::process::exit(1)
}

fn settings(iterations: u32, gravity: Vec3, damping: f32, smoother: Smoother) -> SolverSettings {
    SolverSettings {
        smoother,
        method: Method::GaussSeidel,
        element_solver: ElementSolver::Multigrid,
        substeps: 1,
        iterations,
        newton_iterations: iterations,
        // One V-cycle a Newton iteration unless a run asks for more.
        newton_cycles: 1,
        gravity,
        damping,
        particle_contacts: false,
        coarse_iterations: 0,
        ..Default::default()
    }
}

fn liver(particles: u32) -> Model {
    let (lo, hi) = procedural::liver_ligament();
    let mut model = Model::new();
    model
        .add_body(
            &procedural::liver(5),
            &BodyDesc {
                resolution: Resolution::Particles(particles),
                material: Material::Hyperelastic {
                    youngs_modulus: 30e3,
                    poisson_ratio: 0.45,
                },
                discretisation: Discretisation::Lattice,
                pins: vec![PinRegion::Box { min: lo, max: hi }],
                ..Default::default()
            },
        )
        .unwrap_or_else(|e| fail("liver", e));
    model
}

fn cubes(bodies: u32) -> Model {
    cubes_at(bodies, 0.1)
}

/// `bodies` cubes of 512 particles on a square grid of `pitch` (m) between centres.
fn cubes_at(bodies: u32, pitch: f32) -> Model {
    bench::cubes_at(bodies, pitch).unwrap_or_else(|e| fail("cube", e))
}

struct Gpu {
    device: RenderDevice,
    queue: RenderQueue,
    kernels: LatticeKernels,
}

fn wait(g: &Gpu, world: &GpuLattice) {
    let _ = read_buffer(&g.device, &g.queue, world.pos_buffer(), 0, 16);
}

/// A world of `model` with its contact candidates of the start (the bodies fall
/// together, side by side), stepped 5 times (pipelines, caches, the first steps' larger
/// line-search work). `moving`: the candidates instead searched as the plugin would for
/// every other body moving at 1 m/s past the others (a reach widened for that travel;
/// the state stepped still starts at rest).
fn warm_world(
    g: &Gpu,
    model: &Model,
    s: &SolverSettings,
    options: LatticeOptions,
    moving: bool,
) -> GpuLattice {
    let state = State::new(model);
    let mut world = GpuLattice::new_with(&g.device, &g.kernels, model, &state, s, options)
        .unwrap_or_else(|e| fail("GPU lattice", e));
    if world.has_particle_contacts() {
        let mut lists = Solver::new(model, s.clone()).unwrap_or_else(|e| fail("solver", e));
        // The plugin's search (at rest: the usual reach; moving: widened).
        let v: Vec<Vec3> = (0..model.particle_count())
            .map(
                |i| match moving && model.particle_body[i].is_multiple_of(2) {
                    true => Vec3::new(0.0, -1.0, 0.0),
                    false => Vec3::ZERO,
                },
            )
            .collect();
        lists.refresh_contacts_if_due(model, &state.x, &v, &[], 1, true);
        let (start, list) = lists.contact_lists();
        world
            .set_contacts(&g.queue, start, list)
            .unwrap_or_else(|e| fail("contact lists", e));
    }
    let mut enc = g.device.create_command_encoder(&Default::default());
    world.record(&mut enc, &g.kernels, 5, None);
    g.queue.submit([enc.finish()]);
    wait(g, &world);
    world
}

/// GPU ms per step of `steps` steps of `world` (timestamps around them), with its
/// `twice`-th dispatch of a step recorded twice where given; `None` without timestamps.
fn gpu_ms(g: &Gpu, world: &GpuLattice, steps: u32, twice: Option<usize>) -> Option<f64> {
    let mut prof = GpuProfiler::new(&g.device, &g.queue, 1)?;
    let mut enc = g.device.create_command_encoder(&Default::default());
    let ts = prof.timestamps("lattice");
    world.record_doubling(
        &mut enc,
        &g.kernels,
        steps,
        ts.as_ref().map(|(q, i)| (q, *i)),
        twice,
    );
    prof.resolve(&mut enc);
    g.queue.submit([enc.finish()]);
    let t = prof.read(&g.device, &g.queue);
    t.get("lattice").map(|v| v.0 / steps as f64)
}

/// Each dispatch's cost in the step, by doubling: the GPU time per step with that one
/// dispatch recorded twice, less the plain step's timed just before it (the median of 3
/// rounds; each run 20 steps of the same world, each from the state after the warm-up,
/// so that every run steps the same scene: falling bodies do not fall further run by
/// run). No timestamps between the dispatches, so nothing stalls; a doubled dispatch
/// that changes the state (an `advance`, a sweep) also changes the work after it.
fn costs(
    g: &Gpu,
    name: &str,
    model: &Model,
    s: &SolverSettings,
    options: LatticeOptions,
) -> String {
    use std::fmt::Write;
    const STEPS: u32 = 20;
    const ROUNDS: usize = 3;
    let mut out = String::new();
    let mut world = warm_world(g, model, s, options, false);
    let mut start = State::new(model);
    world.download(&g.device, &g.queue, &mut start);
    let names = world.dispatch_names();
    // Each doubled run beside a plain one just before it, both from the same state: the
    // GPU's clocks move on, so a plain step timed once would not be the one to subtract.
    let mut plain = Vec::new();
    let mut extra = vec![Vec::new(); names.len()];
    let mut run = |twice: Option<usize>| {
        world.upload(&g.queue, model, &start);
        gpu_ms(g, &world, STEPS, twice)
    };
    for _ in 0..ROUNDS {
        for (k, d) in extra.iter_mut().enumerate() {
            let (Some(base), Some(twice)) = (run(None), run(Some(k))) else {
                return out;
            };
            plain.push(base);
            d.push(twice - base);
        }
    }
    let base = bench::median(plain);
    let _ = writeln!(
        out,
        "
Cost of each dispatch by doubling, {name}, {} Newton iteration(s) of {} V-cycle(s): the plain step {base:.4} ms (median of its runs of {STEPS} steps)
",
        s.newton_iterations, s.newton_cycles
    );
    let _ = writeln!(
        out,
        "| # | dispatch | µs per step |
|---|---|---|"
    );
    let mut sum = 0.0;
    for (k, (n, d)) in names.iter().zip(extra).enumerate() {
        let us = bench::median(d) * 1e3;
        sum += us;
        let _ = writeln!(out, "| {k} | {n} | {us:.1} |");
    }
    let _ = writeln!(out, "| | sum | {sum:.1} (the step: {:.1}) |", base * 1e3);
    out
}

/// GPU ms per step (timestamps), wall ms per step (median of 5), dispatches per step.
fn time(
    g: &Gpu,
    model: &Model,
    s: &SolverSettings,
    steps: u32,
    options: LatticeOptions,
    line_steps: bool,
    moving: bool,
) -> (Option<f64>, f64, usize) {
    let world = warm_world(g, model, s, options, moving);
    if line_steps {
        eprintln!("line search after the warm-up: {}", line_summary(g, &world));
    }
    let mut walls = Vec::new();
    for _ in 0..5 {
        let t = Instant::now();
        let mut enc = g.device.create_command_encoder(&Default::default());
        world.record(&mut enc, &g.kernels, steps, None);
        g.queue.submit([enc.finish()]);
        wait(g, &world);
        walls.push(t.elapsed().as_secs_f64() * 1e3 / steps as f64);
    }
    walls.sort_by(f64::total_cmp);
    let gpu = gpu_ms(g, &world, steps, None);
    if line_steps {
        eprintln!(
            "line search after the timed steps: {}",
            line_summary(g, &world)
        );
    }
    (gpu, walls[2], world.dispatch_count())
}

/// How the bodies' last line search went (`--line-steps`): how many bodies took each
/// step (below the first pass's candidates, the second pass ran), and the first
/// particle's height (m).
fn line_summary(g: &Gpu, world: &GpuLattice) -> String {
    let mut by = std::collections::BTreeMap::new();
    for a in world.read_line_steps(&g.device, &g.queue) {
        *by.entry(format!("{a}")).or_insert(0u32) += 1;
    }
    let y = bytes_to_y(&read_buffer(&g.device, &g.queue, world.pos_buffer(), 0, 16));
    format!("bodies by step taken {by:?}; first particle's height {y:.2} m")
}

/// The y coordinate (m) of the first position record read into `b` (NaN where `b` is
/// too short).
fn bytes_to_y(b: &[u8]) -> f32 {
    bytemuck::pod_collect_to_vec::<u8, f32>(b)
        .get(1)
        .copied()
        .unwrap_or(f32::NAN)
}

/// GPU ms per step of each kernel: timestamps between the dispatches of one pass where
/// the device can write them there (the median of 5 steps per dispatch), else every
/// dispatch its own timed pass (which adds a pass's cost to each).
fn profile(
    g: &Gpu,
    name: &str,
    model: &Model,
    s: &SolverSettings,
    options: LatticeOptions,
) -> String {
    use std::fmt::Write;
    let mut out = String::new();
    let state = State::new(model);
    let world = GpuLattice::new_with(&g.device, &g.kernels, model, &state, s, options)
        .unwrap_or_else(|e| fail("GPU lattice", e));
    const STEPS: u32 = 5;
    let stamps = world.dispatch_count() as u32 + 2;
    let Some(mut prof) = GpuProfiler::new(&g.device, &g.queue, STEPS * stamps) else {
        return out;
    };
    let mut enc = g.device.create_command_encoder(&Default::default());
    world.record(&mut enc, &g.kernels, 3, None);
    g.queue.submit([enc.finish()]);
    let mut t = std::collections::BTreeMap::<&str, (f64, u32)>::new();
    let how;
    if GpuProfiler::inside_passes(&g.device) {
        how = "timestamps between the dispatches of one pass, median of 5 steps";
        let mut enc = g.device.create_command_encoder(&Default::default());
        let mut runs = Vec::new();
        for _ in 0..STEPS {
            let Some((set, first)) = prof.reserve(stamps) else {
                return out;
            };
            runs.push((first, world.record_timed(&mut enc, &g.kernels, &set, first)));
        }
        prof.resolve(&mut enc);
        g.queue.submit([enc.finish()]);
        let ts = prof.read_stamps(&g.device, &g.queue);
        let names = &runs[0].1;
        let mut whole = Vec::new();
        for (i, name) in names.iter().enumerate() {
            let times: Vec<f64> = runs
                .iter()
                .map(|(first, _)| {
                    let f = *first as usize + i;
                    ts.get(f + 1)
                        .zip(ts.get(f))
                        .map_or(f64::NAN, |(b, a)| b - a)
                })
                .collect();
            let e = t.entry(name).or_insert((0.0, 0));
            e.0 += bench::median(times);
            e.1 += 1;
        }
        for (first, n) in &runs {
            let f = *first as usize;
            if let (Some(a), Some(b)) = (ts.get(f), ts.get(f + n.len())) {
                whole.push(b - a);
            }
        }
        if !whole.is_empty() {
            let _ = writeln!(
                out,
                "\n{name}: the timed step, first to last timestamp: {:.4} ms (median of {STEPS})",
                bench::median(whole)
            );
        }
    } else {
        how = "every dispatch its own pass";
        let mut enc = g.device.create_command_encoder(&Default::default());
        world.record_profiled(&mut enc, &g.kernels, 1, &mut prof);
        prof.resolve(&mut enc);
        g.queue.submit([enc.finish()]);
        t = prof.read(&g.device, &g.queue);
    }
    let _ = writeln!(
        out,
        "\nGPU time per kernel, {name}, {} Newton iteration(s) of {} V-cycle(s), one step ({how}):\n",
        s.newton_iterations, s.newton_cycles
    );
    let _ = writeln!(
        out,
        "| kernel | ms per step | dispatches per step |\n|---|---|---|"
    );
    let mut sum = 0.0;
    for (k, (ms, count)) in &t {
        let _ = writeln!(out, "| {k} | {ms:.4} | {count} |");
        sum += ms;
    }
    let _ = writeln!(out, "| sum | {sum:.4} | |");
    out
}

#[allow(clippy::too_many_arguments)]
fn speed(
    g: &Gpu,
    quick: bool,
    bodies: u32,
    profile_kernels: bool,
    cost_kernels: bool,
    line_steps: bool,
    smoothers: &[Smoother],
    firsts: &[u32],
    fuseds: &[u32],
    rows: &[u32],
    keeps: &[u32],
    room: f32,
    steps_of: &StepsOf,
    touching: bool,
    moving_lists: bool,
) {
    println!("\n## Speed: Newton–multigrid on the GPU, 1/60 s steps of 1 substep\n");
    println!(
        "| scene | particles | elements | smoother | first-pass candidates | coarsest fused up to (nodes) | one thread a row from (nodes) | coarsest factor kept | Newton iterations × V-cycles | sweeps (fine/coarse/coarsest) | GPU ms per step | wall ms per step | dispatches per step |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    // Touching cubes: centres 5.7 cm apart, so that the facing layers of particles
    // (radius 3.6 mm) overlap their neighbours' and every face is in contact.
    let mut scenes: Vec<(String, Model)> = if quick {
        vec![
            ("liver".into(), liver(3000)),
            ("cubes × 20".into(), cubes(20)),
            ("touching cubes × 20".into(), cubes_at(20, 0.057)),
        ]
    } else {
        vec![
            ("liver (paper's size)".into(), liver(37_982)),
            (format!("{bodies} cubes × 512"), cubes(bodies)),
            (
                format!("{bodies} touching cubes × 512"),
                cubes_at(bodies, 0.057),
            ),
        ]
    };
    if moving_lists && touching {
        let n = if quick { 20 } else { bodies };
        scenes.push((
            format!("{n} touching cubes × 512, lists of bodies moving past"),
            cubes_at(n, 0.057),
        ));
    }
    if !touching {
        scenes.retain(|(name, _)| !name.contains("touching"));
    }
    let steps = if quick { 5 } else { 60 };
    let mut profiles = Vec::new();
    for (name, model) in &scenes {
        for &sm in smoothers {
            for (&first, &fused, &row) in firsts.iter().flat_map(|f| {
                fuseds
                    .iter()
                    .flat_map(move |u| rows.iter().map(move |r| (f, u, r)))
            }) {
                for (it, c, sw, keep) in steps_of
                    .each()
                    .into_iter()
                    .flat_map(|(it, c, sw)| keeps.iter().map(move |&k| (it, c, sw, k != 0)))
                {
                    let s = SolverSettings {
                        // Particle contacts in every Newton iteration where bodies touch.
                        particle_contacts: name.contains("touching"),
                        contact_every: 1,
                        newton_cycles: c,
                        sweeps: sw,
                        ..settings(it, Vec3::new(0.0, -9.81, 0.0), 0.0, sm)
                    };
                    if let Err(e) = s.validate() {
                        eprintln!("speed: {sm:?} with {}: {e}", sweeps_name(sw));
                        continue;
                    }
                    eprintln!(
                        "speed: {name}, {sm:?}, {first} first candidates, {it} Newton iteration(s) × {c}, sweeps {} ...",
                        sweeps_name(sw)
                    );
                    let options = LatticeOptions {
                        first_candidates: first,
                        room,
                        fused_coarsest: fused,
                        one_thread_rows_from: row,
                        keep_coarsest_factor: keep,
                    };
                    let (gpu_ms, wall, dispatches) = time(
                        g,
                        model,
                        &s,
                        steps,
                        options,
                        line_steps,
                        name.contains("moving"),
                    );
                    println!(
                        "| {name} | {} | {} | {sm:?} | {first} | {fused} | {row} | {} | {it} × {c} | {} | {} | {wall:.3} | {dispatches} |",
                        model.particle_count(),
                        model.elements.len(),
                        if keep { "yes" } else { "no" },
                        sweeps_name(sw),
                        gpu_ms.map_or("n/a".into(), |v| format!("{v:.3}")),
                    );
                    let label = format!(
                        "{name}, {sm:?}, rows {row}, fused {fused}, first {first}, sweeps {}",
                        sweeps_name(sw)
                    );
                    if cost_kernels {
                        profiles.push(costs(g, &label, model, &s, options));
                    }
                    if profile_kernels {
                        profiles.push(profile(g, &label, model, &s, options));
                    }
                }
            }
        }
    }
    for p in &profiles {
        print!("{p}");
    }
}

/// Settles `model` on the GPU for `secs` and returns the final positions.
fn settle_gpu(
    g: &Gpu,
    model: &Model,
    s: &SolverSettings,
    secs: f32,
    colliders: &[Collider],
) -> Vec<Vec3> {
    let mut state = State::new(model);
    let mut world = GpuLattice::new(&g.device, &g.kernels, model, &state, s)
        .unwrap_or_else(|e| fail("GPU lattice", e));
    world
        .set_colliders(&g.queue, colliders)
        .unwrap_or_else(|e| fail("colliders", e));
    let steps = (secs * 60.0).round() as u32;
    let mut done = 0;
    while done < steps {
        let chunk = (steps - done).min(120);
        let mut enc = g.device.create_command_encoder(&Default::default());
        world.record(&mut enc, &g.kernels, chunk, None);
        g.queue.submit([enc.finish()]);
        wait(g, &world);
        done += chunk;
    }
    world.download(&g.device, &g.queue, &mut state);
    state.x
}

fn accuracy(g: &Gpu, quick: bool, smoothers: &[Smoother], steps_of: &StepsOf) {
    println!(
        "\n## Accuracy on the GPU: the settled cantilever (lattice) against its static answer\n"
    );
    println!(
        "| across | particles | E (Pa) | smoother | Newton iterations × V-cycles per 1/60 s step | sweeps (fine/coarse/coarsest) | simulated s | tip / static |\n|---|---|---|---|---|---|---|---|"
    );
    let cases: &[(u32, f32)] = if quick {
        &[(6, 1e5)]
    } else {
        &[(6, 1e3), (6, 1e5), (6, 1e6), (12, 1e5)]
    };
    for &(across, e) in cases {
        let model = bar_model_with(Disc::Lattice, across, e).unwrap_or_else(|err| fail("bar", err));
        let gv = BAR_GRAVITY * e as f64 / BAR_E as f64;
        let (stat, _) = bar_static_tip_under(&model, gv).unwrap_or_else(|err| fail("static", err));
        let w1 = bar_first_mode(e as f64);
        let secs = if quick {
            1.0
        } else {
            (8.0 / w1).clamp(1.0, 20.0) as f32
        };
        for &sm in smoothers {
            for (it, c, sw) in steps_of.each() {
                let s = SolverSettings {
                    newton_cycles: c,
                    sweeps: sw,
                    ..settings(it, Vec3::new(0.0, -gv as f32, 0.0), (2.0 * w1) as f32, sm)
                };
                if s.validate().is_err() {
                    continue;
                }
                eprintln!(
                    "accuracy: {across} across, E = {e}, {sm:?}, {it} iteration(s) × {c}, sweeps {} ...",
                    sweeps_name(sw)
                );
                let x = settle_gpu(g, &model, &s, secs, &[]);
                let tip = bar_tip(&model, &displacements(&model, &x));
                println!(
                    "| {across} | {} | {e} | {sm:?} | {it} × {c} | {} | {secs:.1} | {:.4} |",
                    model.particle_count(),
                    sweeps_name(sw),
                    tip / stat
                );
            }
        }
    }
}

/// The organ meshes resting on the ground and hanging from their top 10% on the GPU.
fn organs(g: &Gpu, quick: bool) {
    let Some(dir) = common::meshes_dir() else {
        return;
    };
    println!(
        "\n## Organ meshes on the GPU: 1 s resting on the ground and hanging, the default Newton iterations and V-cycles per 1/60 s step\n"
    );
    println!(
        "| mesh | particles | scene | finite | volume / rest | lowest − ground (mm) |\n|---|---|---|---|---|---|"
    );
    let all = [
        "liver2.obj",
        "bunny.obj",
        "spot_low_resolution.obj",
        "Armadillo_verysimplified.obj",
        "odedstein_torus.obj",
    ];
    let sizes: &[(u32, &[&str])] = if quick {
        &[(4000, &all[..1])]
    } else {
        &[(4000, &all), (40_000, &all)]
    };
    for &(particles, names) in sizes {
        for &name in names {
            let path = dir.join(name);
            if !path.is_file() {
                eprintln!("organs: {} missing", path.display());
                continue;
            }
            let mesh = common::load_obj(&path);
            for hang in [false, true] {
                let (model, ground) = match common::organ(&mesh, particles, hang) {
                    Ok(m) => m,
                    Err(e) => {
                        println!("| {name} | {particles} | build failed: {e} | | | |");
                        continue;
                    }
                };
                let colliders = if hang {
                    vec![]
                } else {
                    vec![Collider::ground(ground)]
                };
                eprintln!("organs: {name}, {particles}, hanging {hang} ...");
                let s = SolverSettings {
                    element_solver: ElementSolver::Multigrid,
                    particle_contacts: false,
                    ..Default::default()
                };
                let x = settle_gpu(g, &model, &s, 1.0, &colliders);
                let finite = x.iter().all(|p| p.is_finite());
                let v = material_volume(&model, &x) / material_volume(&model, &model.rest);
                let low = x.iter().map(|p| p.y).fold(f32::INFINITY, f32::min);
                println!(
                    "| {name} | {} | {} | {} | {v:.4} | {} |",
                    model.particle_count(),
                    if hang { "hanging" } else { "resting" },
                    if finite { "yes" } else { "**no**" },
                    if hang {
                        "".into()
                    } else {
                        format!("{:.2}", (low - ground) * 1e3)
                    },
                );
            }
        }
    }
}

/// The step shapes a run measures: Newton iterations, V-cycles per iteration and the
/// V-cycle's sweeps, every combination.
struct StepsOf {
    newton: Vec<u32>,
    cycles: Vec<u32>,
    sweeps: Vec<Sweeps>,
}

impl StepsOf {
    fn each(&self) -> Vec<(u32, u32, Sweeps)> {
        let mut out = Vec::new();
        for &it in &self.newton {
            for &c in &self.cycles {
                for &sw in &self.sweeps {
                    out.push((it, c, sw));
                }
            }
        }
        out
    }
}

fn sweeps_name(s: Sweeps) -> String {
    let exact = match (s.exact_coarsest, s.translation) {
        (true, true) => "xt",
        (true, false) => "x",
        (false, true) => "t",
        (false, false) => "",
    };
    let fine = count_name(s.fine_before, s.fine);
    let coarse = count_name(s.coarse_before, s.coarse);
    format!("{fine}/{coarse}/{}{exact}", s.coarsest)
}

/// A level's sweep counts as `--sweeps` takes them ([`before_after`]'s inverse).
fn count_name(before: u32, after: u32) -> String {
    if before == after {
        after.to_string()
    } else {
        format!("{before}:{after}")
    }
}

/// A sweep count, or `before:after` (each from 0).
fn before_after(text: &str) -> (Option<u32>, u32) {
    let num = |t: &str| t.trim().parse().unwrap_or_else(|e| fail("--sweeps", e));
    match text.split_once(':') {
        Some((b, a)) => (Some(num(b)), num(a)),
        None => (None, num(text)),
    }
}

/// `--sweeps 2/2/30,1/2/30x,0:1/0:2/30`: each entry fine/coarse/coarsest (fine and
/// coarse as before:after where they differ), the coarsest count followed by `x` where
/// the coarsest level is solved exactly where its bodies are small enough
/// (`Sweeps::exact_coarsest`; the count then only for larger bodies), then `t` where each
/// V-cycle takes the bodies' translation step (`Sweeps::translation`).
fn parse_sweeps(text: &str) -> Vec<Sweeps> {
    text.split(',')
        .map(|one| {
            let one = one.trim();
            // Suffixes: `t` the translation step, then or before it `x` the exact solve.
            let (counts, translation) = match one.strip_suffix('t') {
                Some(rest) => (rest, true),
                None => (one, false),
            };
            let (counts, exact_coarsest) = match counts.strip_suffix('x') {
                Some(rest) => (rest, true),
                None => (counts, false),
            };
            // Level 0's and the levels between's counts may be `before:after`.
            let n: Vec<(Option<u32>, u32)> = counts.split('/').map(before_after).collect();
            match n[..] {
                [
                    (fine_before, fine),
                    (coarse_before, coarse),
                    (None, coarsest),
                ] => Sweeps {
                    fine,
                    fine_before: fine_before.unwrap_or(fine),
                    coarse,
                    coarse_before: coarse_before.unwrap_or(coarse),
                    coarsest,
                    exact_coarsest,
                    translation,
                },
                _ => fail(
                    "--sweeps",
                    format!("{one}: expected fine/coarse/coarsest[x][t]"),
                ),
            }
        })
        .collect()
}

fn main() {
    let a = bench::Args::new();
    let quick = a.flag("--quick");
    let smoothers: Vec<Smoother> = match a.text("--smoother").map(String::as_str) {
        None => vec![Smoother::Chebyshev, Smoother::Hybrid, Smoother::GaussSeidel],
        Some("hybrid") => vec![Smoother::Hybrid],
        Some("chebyshev") => vec![Smoother::Chebyshev],
        Some("gs") => vec![Smoother::GaussSeidel],
        Some(other) => fail(
            "--smoother",
            format!("{other}: expected hybrid, chebyshev or gs"),
        ),
    };
    let (device, queue, adapter) =
        device_with(bench::gpu_settings()).unwrap_or_else(|e| fail("GPU", e));
    let kernels = LatticeKernels::new(&device).unwrap_or_else(|e| fail("kernels", e));
    println!("# Newton–multigrid on the GPU\n\nAdapter: {adapter}");
    let g = Gpu {
        device,
        queue,
        kernels,
    };
    let steps_of = StepsOf {
        newton: a.list("--newton", &[1u32, 2]),
        cycles: a.list("--cycles", &[1u32]),
        sweeps: a
            .text("--sweeps")
            .map_or(vec![Sweeps::DEFAULT], |t| parse_sweeps(t)),
    };
    if !a.flag("--no-speed") {
        speed(
            &g,
            quick,
            a.num("--bodies", 1000u32),
            a.flag("--profile"),
            a.flag("--costs"),
            a.flag("--line-steps"),
            &smoothers,
            &a.list("--first", &[LatticeOptions::default().first_candidates]),
            &a.list("--fused", &[LatticeOptions::default().fused_coarsest]),
            &a.list("--rows", &[LatticeOptions::default().one_thread_rows_from]),
            &a.list(
                "--keep-factor",
                &[LatticeOptions::default().keep_coarsest_factor as u32],
            ),
            a.num("--room", LatticeOptions::default().room),
            &steps_of,
            !a.flag("--no-touching"),
            a.flag("--moving-lists"),
        );
    }
    if !a.flag("--no-accuracy") {
        accuracy(&g, quick, &smoothers, &steps_of);
    }
    if a.flag("--organs") {
        organs(&g, quick);
    }
    if a.flag("--changes") {
        changes(
            &g,
            if quick {
                20
            } else {
                a.num("--bodies", 1000u32)
            },
        );
    }
}

/// Median of 5 of the milliseconds `f` takes on this thread, and until the GPU has
/// finished what it queued.
fn thread_then_gpu(
    g: &Gpu,
    world: &mut GpuLattice,
    mut f: impl FnMut(&mut GpuLattice),
) -> (f64, f64) {
    let (mut here, mut done) = (Vec::new(), Vec::new());
    for _ in 0..5 {
        let t = Instant::now();
        f(world);
        here.push(t.elapsed().as_secs_f64() * 1e3);
        wait(g, world);
        done.push(t.elapsed().as_secs_f64() * 1e3);
    }
    (bench::median(here), bench::median(done))
}

/// Milliseconds `f` takes, the GPU's work it queued finished (what an empty
/// submission and wait take is printed as a row of its own).
fn timed<T>(g: &Gpu, world: &mut GpuLattice, f: impl FnOnce(&mut GpuLattice) -> T) -> (T, f64) {
    let t = Instant::now();
    let out = f(world);
    g.queue.submit([]);
    wait(g, world);
    (out, t.elapsed().as_secs_f64() * 1e3)
}

/// What changing a world of `bodies` touching cubes costs (`--changes`): making it again
/// for one more body (the join of the bodies' levels, then the GPU world, as the plugin's
/// rebuild does), appending one into its room (`GpuLattice::append`), retiring one
/// (`GpuLattice::hold`), changing gravity (`GpuLattice::set_forces`); and the GPU time
/// of a step with and without room, before and after the appends.
fn changes(g: &Gpu, bodies: u32) {
    use bevy_tissue::core::multigrid::{BodyLevels, LatticeMultigrid, MAX_LEVELS, MIN_NODES};
    let s = SolverSettings {
        particle_contacts: true,
        contact_every: 1,
        ..settings(2, Vec3::new(0.0, -9.81, 0.0), 0.0, Smoother::default())
    };
    eprintln!("changes: {bodies} touching cubes ...");
    let model = cubes_at(bodies, 0.057);
    // Every cube is the same body moved: one body's levels stand for each.
    let one = cubes_at(1, 0.057);
    let part = BodyLevels::new(&one, 0);
    let parts: Vec<&BodyLevels> = (0..bodies + 1).map(|_| &part).collect();
    let state = State::new(&model);
    let room = LatticeOptions {
        room: 1.5,
        ..Default::default()
    };
    let make = |options: LatticeOptions| {
        let mg = LatticeMultigrid::from_bodies(&parts[..bodies as usize], MIN_NODES, MAX_LEVELS);
        GpuLattice::with_levels(&g.device, &g.kernels, &model, mg, &state, &s, options)
            .unwrap_or_else(|e| fail("GPU lattice", e))
    };
    let step_ms = |world: &GpuLattice| -> f64 {
        let mut enc = g.device.create_command_encoder(&Default::default());
        world.record(&mut enc, &g.kernels, 5, None);
        g.queue.submit([enc.finish()]);
        wait(g, world);
        GpuProfiler::new(&g.device, &g.queue, 1).map_or(f64::NAN, |mut prof| {
            let mut enc = g.device.create_command_encoder(&Default::default());
            let ts = prof.timestamps("lattice");
            world.record(&mut enc, &g.kernels, 30, ts.as_ref().map(|(q, i)| (q, *i)));
            prof.resolve(&mut enc);
            g.queue.submit([enc.finish()]);
            let t = prof.read(&g.device, &g.queue);
            t.get("lattice").map_or(f64::NAN, |v| v.0 / 30.0)
        })
    };
    println!("\n{bodies} touching cubes × 512, 2 Newton iterations:\n");
    println!("| change | ms (median of 5) |\n|---|---|");
    let tight = make(LatticeOptions::default());
    let tight_step = step_ms(&tight);
    drop(tight);
    let mut world = make(room);
    let room_step = step_ms(&world);
    // Making the world again for one more body: the join, then the GPU world.
    let mut plus = model.clone();
    plus.append(&cubes_at(1, 0.057));
    let plus_state = State::new(&plus);
    let mut join = Vec::new();
    let mut remake = Vec::new();
    for _ in 0..5 {
        let t = Instant::now();
        let mg = LatticeMultigrid::from_bodies(&parts, MIN_NODES, MAX_LEVELS);
        join.push(t.elapsed().as_secs_f64() * 1e3);
        let (made, ms) = timed(g, &mut world, |_| {
            GpuLattice::with_levels(&g.device, &g.kernels, &plus, mg, &plus_state, &s, room)
        });
        drop(made.unwrap_or_else(|e| fail("GPU lattice", e)));
        remake.push(ms);
    }
    println!("| remake: join the levels | {:.3} |", bench::median(join));
    println!("| remake: the GPU world | {:.3} |", bench::median(remake));
    // What the frame that takes the world made again does: the bodies it keeps take
    // their state from the old world by GPU copies.
    let mg = LatticeMultigrid::from_bodies(&parts, MIN_NODES, MAX_LEVELS);
    let mut again =
        GpuLattice::with_levels(&g.device, &g.kernels, &plus, mg, &plus_state, &s, room)
            .unwrap_or_else(|e| fail("GPU lattice", e));
    let kept = [bevy_tissue::gpu::lattice::StateRun {
        particles: 0..model.particle_count() as u32,
        to_particle: 0,
        elements: 0..model.elements.len() as u32,
        to_element: 0,
    }];
    let (carries, carried) = thread_then_gpu(g, &mut again, |w| {
        w.carry_state(&g.device, &g.queue, &world, &kept)
            .unwrap_or_else(|e| fail("carry the state", e));
    });
    println!(
        "| remake: the kept bodies' state by GPU copies ({} particles), this thread | {carries:.3} |",
        model.particle_count(),
    );
    println!("| remake: the GPU copies, then wait for the GPU | {carried:.3} |");
    drop(again);
    // Appending: a cube at a time, into the room.
    let cube = cubes_at(1, 0.057);
    let cube_state = State::new(&cube);
    let mut grown = model.clone();
    let mut appends = Vec::new();
    for _ in 0..5 {
        let (ok, ms) = timed(g, &mut world, |w| {
            w.append(&g.device, &g.queue, &cube, &part, &cube_state, &s)
        });
        if !ok.unwrap_or_else(|e| fail("append", e)) {
            fail("append", "no room");
        }
        grown.append(&cube);
        appends.push(ms);
    }
    println!("| append one body | {:.3} |", bench::median(appends));
    // The same in two parts, as the plugin does: packed (and staged on the device) on a
    // worker thread, then committed on the frame's thread.
    let (mut packs, mut commits, mut waited) = (Vec::new(), Vec::new(), Vec::new());
    let mut bytes = 0;
    for _ in 0..5 {
        let t = Instant::now();
        let mut prepared = world
            .append_basis()
            .prepare(&cube, &part, &cube_state, &s)
            .unwrap_or_else(|e| fail("append", e))
            .unwrap_or_else(|| fail("append", "no room"));
        prepared.stage(&g.device);
        packs.push(t.elapsed().as_secs_f64() * 1e3);
        bytes = prepared.bytes();
        let t = Instant::now();
        let ok = world.commit_append(&g.device, &g.queue, prepared);
        commits.push(t.elapsed().as_secs_f64() * 1e3);
        wait(g, &world);
        waited.push(t.elapsed().as_secs_f64() * 1e3);
        if !ok {
            fail("commit", "a stale packing");
        }
        grown.append(&cube);
    }
    println!(
        "| append: pack and stage ({bytes} bytes; any thread) | {:.3} |",
        bench::median(packs)
    );
    println!(
        "| append: commit (the frame's thread) | {:.3} |",
        bench::median(commits)
    );
    println!(
        "| append: commit and wait for the GPU | {:.3} |",
        bench::median(waited)
    );
    let empty: Vec<f64> = (0..5).map(|_| timed(g, &mut world, |_| ()).1).collect();
    println!(
        "| (an empty submission and wait) | {:.3} |",
        bench::median(empty)
    );
    let appended_step = step_ms(&world);
    // Retiring one (held still where it is), and gravity.
    let mut holds = Vec::new();
    for b in 0..5 {
        let r = grown.bodies[b].range();
        let at: Vec<Vec3> = grown.rest[r.clone()].to_vec();
        holds.push(timed(g, &mut world, |w| w.hold(&g.queue, &grown, r, &at)).1);
    }
    println!("| retire one body | {:.3} |", bench::median(holds));
    let mut gravity = Vec::new();
    for k in 0..5 {
        let gy = if k % 2 == 0 { -4.9 } else { -9.81 };
        gravity.push(
            timed(g, &mut world, |w| {
                w.set_forces(&g.queue, Vec3::new(0.0, gy, 0.0), 0.0)
            })
            .1,
        );
    }
    println!("| gravity | {:.3} |", bench::median(gravity));
    // What the frame that takes a world made again on a worker thread does with it:
    // upload the state it carries over (on this thread, then with the GPU's copies).
    let state = State::new(&grown);
    let (uploads, uploaded) = thread_then_gpu(g, &mut world, |w| {
        w.upload(&g.queue, &grown, &state);
        g.queue.submit([]);
    });
    println!(
        "| upload the state ({} particles; the frame taking a world made again), this thread | {uploads:.3} |",
        grown.particle_count(),
    );
    println!("| upload the state, then wait for the GPU | {uploaded:.3} |");
    println!(
        "\nGPU ms per step: no room {tight_step:.3}; room 1.5 {room_step:.3}; after 10 appended {appended_step:.3}"
    );
}
