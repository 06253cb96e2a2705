//! The paper's Table 1 again (Li & Kang 2014; SPEC §6): the liver shape sampled at 512,
//! 4096, 13824 and 37982 particles, K = 32 and 64, shape matching (the paper's model),
//! 10 iterations, dt = 1/60 s, the K nearest neighbours of every particle refreshed every
//! 10th step, on three backends: the CPU's one-thread Gauss–Seidel (the paper's CPU
//! baseline), CPU Jacobi on all cores, and the GPU world.
//!
//! Each cell: ms per step, the median of `--repeats` runs of `--steps` steps after 10
//! warm-up steps (the GPU synchronised: one submission per run, timed from submit to
//! completion), and ms per KNN refresh (median of the same number of refreshes). The
//! speed-up is over this machine's one-thread CPU and over the paper's own number for
//! the same K and kind of backend (kept below as data).
//!
//! Markdown on stdout, `table1.json` and `table1.png` (log–log ms per step against
//! particles, the paper's points included) in the output folder.
//!
//! ```text
//! cargo run --release --example table1                 # the full table (long on 2 cores)
//! cargo run --release --example table1 -- --quick      # 512 and 4096 particles, seconds
//! cargo run --release --example table1 -- --no-cpu     # the GPU rows only
//! cargo run --release --example table1 -- --lattice    # the same sizes, the new default
//! ```
//! Options: `--steps N` (default 300), `--repeats N` (default 5), `--no-cpu`,
//! `--no-gpu`, `--k 32,64` (the neighbour counts to run), `--out DIR` (default
//! `table1_out`).
//!
//! `--lattice` times the plugin's and the core's default body on the same liver instead
//! (`--sizes a,b,..` for other particle counts, as in the scaling rows):
//! hexahedral lattice elements of liver tissue (E = 5.5 kPa, ν = 0.45), stepped by
//! Newton–multigrid with `SolverSettings::default()` (1 Newton iteration of 1 V-cycle per 1/60 s
//! step), on the CPU (all cores) and the GPU (`GpuLattice`). The GPU gets two figures
//! after at least 0.5 s of warm-up steps (the GPU's clocks come up from idle): GPU time
//! (timestamps around one submission of `--steps` steps; where the adapter has
//! timestamp queries) and wall clock (the median of `--repeats` submissions, each from
//! submit to completion). No KNN: a lattice body has no clusters. Markdown on stdout,
//! `table1_lattice.json` in the output folder.
//!
//! `--webgpu-limits` holds the device to WebGPU's default limits (what every browser
//! guarantees; the tests run the example so).

#[path = "support/bench.rs"]
mod bench;
#[path = "support/chart.rs"]
mod chart;

use bevy_tissue::core::knn::knn_all;
use bevy_tissue::core::model::{BodyDesc, Discretisation, Material, Model, PinRegion};
use bevy_tissue::core::procedural;
use bevy_tissue::core::sampling::Resolution;
use bevy_tissue::core::solver::{Control, Method, Solver, SolverSettings, State};
use bevy_tissue::gpu::kernels::lattice::LatticeKernels;
use bevy_tissue::gpu::lattice::GpuLattice;
use bevy_tissue::gpu::profile::GpuProfiler;
use bevy_tissue::gpu::world::{read_buffer, read_vec3};
use bevy_tissue::gpu::{GpuWorld, Headless, NoTiming, PassRecorder};
use std::fmt::Write as _;
use std::time::Instant;

/// The paper's Table 1, ms per time step: (K, backend, [512, 4096, 13824, 37982]).
/// Intel Xeon X3320 (one thread) and an NVIDIA GeForce GTX 560 Ti.
const PAPER: &[(u32, &str, [f64; 4])] = &[
    (32, "CPU", [25.0, 36.0, 1374.0, 4910.0]),
    (32, "GPU", [22.0, 27.0, 87.0, 263.0]),
    (64, "GPU", [34.0, 61.0, 209.0, 541.0]),
];
const SIZES: [u32; 4] = [512, 4096, 13824, 37982];

#[derive(Clone, Copy, PartialEq, Eq)]
enum Backend {
    CpuOneThread,
    CpuAllCores,
    Gpu,
}

impl Backend {
    fn name(self) -> &'static str {
        match self {
            Backend::CpuOneThread => "CPU Gauss–Seidel, 1 thread",
            Backend::CpuAllCores => "CPU Jacobi, all cores",
            Backend::Gpu => "GPU",
        }
    }
    fn paper_kind(self) -> &'static str {
        match self {
            Backend::Gpu => "GPU",
            _ => "CPU",
        }
    }
}

struct Cell {
    backend: Backend,
    k: u32,
    target: u32,
    particles: usize,
    ms_step: f64,
    ms_knn: f64,
    finite: bool,
}

/// The procedural liver of `particles` particles, pinned at its ligament, as `desc`
/// says otherwise.
fn liver_model(particles: u32, desc: BodyDesc) -> Model {
    let (lo, hi) = procedural::liver_ligament();
    let desc = BodyDesc {
        resolution: Resolution::Particles(particles),
        pins: vec![PinRegion::Box { min: lo, max: hi }],
        ..desc
    };
    let mut model = Model::new();
    model
        .add_body(&procedural::liver(4), &desc)
        .expect("liver model");
    model
}

/// The paper's liver: clusters of K neighbours, shape matching with k = 1.
fn liver(particles: u32, k: u32) -> Model {
    liver_model(
        particles,
        BodyDesc {
            neighbours: k,
            material: Material::ShapeMatching { stiffness: 1.0 },
            discretisation: Discretisation::Clusters,
            ..Default::default()
        },
    )
}

fn settings(method: Method, threads: usize) -> SolverSettings {
    SolverSettings {
        method,
        threads,
        iterations: 10,
        knn_every: 10,
        // One body: no particle contacts; the refresh timed is the K-nearest search of
        // every particle, as on the GPU.
        particle_contacts: false,
        ..Default::default()
    }
}

fn cpu_cell(
    model: &Model,
    k: u32,
    backend: Backend,
    steps: usize,
    repeats: usize,
) -> (f64, f64, bool) {
    let (method, threads) = match backend {
        Backend::CpuOneThread => (Method::GaussSeidel, 1),
        _ => (Method::Jacobi, 0),
    };
    let mut solver = Solver::new(model, settings(method, threads)).expect("solver");
    let mut state = State::new(model);
    let control = Control::default();
    let mut step = |state: &mut State| -> bool {
        if state.step.is_multiple_of(10) {
            let _ = knn_all(&state.x, k as usize, threads);
        }
        solver.step(model, state, &control).is_ok()
    };
    let mut ok = true;
    for _ in 0..10 {
        ok &= step(&mut state);
    }
    let mut runs = Vec::new();
    for _ in 0..repeats {
        let t = Instant::now();
        for _ in 0..steps {
            ok &= step(&mut state);
        }
        runs.push(t.elapsed().as_secs_f64() * 1e3 / steps as f64);
    }
    let mut knn = Vec::new();
    for _ in 0..repeats {
        let t = Instant::now();
        let _ = knn_all(&state.x, k as usize, threads);
        knn.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let finite = ok && state.x.iter().all(|p| p.is_finite());
    (bench::median(runs), bench::median(knn), finite)
}

fn gpu_cell(g: &Headless, model: &Model, k: u32, steps: u32, repeats: usize) -> (f64, f64, bool) {
    let state = State::new(model);
    let mut world = GpuWorld::new(
        &g.device,
        &g.kernels,
        model,
        &state,
        settings(Method::Jacobi, 0),
        k,
    )
    .expect("GPU world");
    world.write_params(&g.queue);
    let record = |world: &mut GpuWorld, steps: u32| {
        let mut enc = g.device.create_command_encoder(&Default::default());
        for _ in 0..steps {
            if world.step.is_multiple_of(10) {
                world.record_knn_all(&mut enc, &g.kernels, &mut NoTiming);
            }
            world.record_steps(&mut enc, &g.kernels, 1, &mut NoTiming);
        }
        enc.finish()
    };
    // Warm-up (and the GPU's clocks up): rounds of 10 steps.
    bench::keep_gpu_busy(bench::GPU_WARM_UP_S, || {
        let cmd = record(&mut world, 10);
        g.queue.submit([cmd]);
        bench::sync(g, &world);
    });
    let mut runs = Vec::new();
    for _ in 0..repeats {
        let cmd = record(&mut world, steps);
        let t = Instant::now();
        g.queue.submit([cmd]);
        bench::sync(g, &world);
        runs.push(t.elapsed().as_secs_f64() * 1e3 / steps as f64);
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
    let n = world.particle_count();
    let finite = read_vec3(&g.device, &g.queue, world.positions(), n)
        .iter()
        .all(|p| p.is_finite());
    (bench::median(runs), bench::median(knn), finite)
}

/// A speed-up as text: one decimal below 10x.
fn ratio(r: f64) -> String {
    if r < 10.0 {
        format!("{r:.1}x")
    } else {
        format!("{r:.0}x")
    }
}

fn paper(k: u32, kind: &str, target: u32) -> Option<f64> {
    let i = SIZES.iter().position(|&s| s == target)?;
    PAPER
        .iter()
        .find(|(pk, pb, _)| *pk == k && *pb == kind)
        .map(|(_, _, v)| v[i])
}

/// The liver as the default body: lattice elements of liver tissue, pinned at its
/// ligament.
fn lattice_liver(particles: u32) -> Model {
    liver_model(
        particles,
        BodyDesc {
            material: Material::Hyperelastic {
                youngs_modulus: 5_500.0,
                poisson_ratio: 0.45,
            },
            discretisation: Discretisation::Lattice,
            ..Default::default()
        },
    )
}

/// The default settings, one body (no particle contacts).
fn lattice_settings() -> SolverSettings {
    SolverSettings {
        particle_contacts: false,
        threads: 0,
        ..Default::default()
    }
}

/// ms per step of the default body on the CPU (all cores): the median of `repeats` runs
/// of `steps` steps after 5 warm-up steps; and whether every position stayed finite.
fn lattice_cpu(model: &Model, steps: usize, repeats: usize) -> (f64, bool) {
    let mut solver = Solver::new(model, lattice_settings()).expect("solver");
    let mut state = State::new(model);
    let control = Control::default();
    let mut ok = true;
    for _ in 0..5 {
        ok &= solver.step(model, &mut state, &control).is_ok();
    }
    let mut runs = Vec::new();
    for _ in 0..repeats {
        let t = Instant::now();
        for _ in 0..steps {
            ok &= solver.step(model, &mut state, &control).is_ok();
        }
        runs.push(t.elapsed().as_secs_f64() * 1e3 / steps as f64);
    }
    (
        bench::median(runs),
        ok && state.x.iter().all(|p| p.is_finite()),
    )
}

/// The default body's GPU figures, ms per step.
#[derive(Clone, Copy)]
struct LatticeGpu {
    /// Wall clock: the median of the timed submissions of `steps` steps, each from submit
    /// to completion (the host's submission and the wait included).
    wall: f64,
    /// GPU time: timestamps around one submission of `steps` steps; `None` where the
    /// device has no timestamp queries.
    gpu: Option<f64>,
    /// Every position stayed finite.
    finite: bool,
}

/// The default body on the GPU after a warm-up of at least 0.5 s of steps (pipelines,
/// caches, and the GPU's clocks up from idle: without it the small sizes' first
/// submissions ran at idle clocks), `repeats` submissions of `steps` steps timed from
/// submit to completion, then one more with timestamps around its steps.
fn lattice_gpu(
    g: &Headless,
    kernels: &LatticeKernels,
    model: &Model,
    steps: u32,
    repeats: usize,
) -> LatticeGpu {
    let mut state = State::new(model);
    let world =
        GpuLattice::new(&g.device, kernels, model, &state, &lattice_settings()).expect("world");
    let run = |n: u32, stamps: Option<&mut GpuProfiler>| {
        let mut enc = g.device.create_command_encoder(&Default::default());
        match stamps {
            Some(prof) => {
                let ts = prof.timestamps("lattice");
                world.record(&mut enc, kernels, n, ts.as_ref().map(|(q, i)| (q, *i)));
                prof.resolve(&mut enc);
            }
            None => world.record(&mut enc, kernels, n, None),
        }
        let t = Instant::now();
        g.queue.submit([enc.finish()]);
        let _ = read_buffer(&g.device, &g.queue, world.pos_buffer(), 0, 16);
        t.elapsed().as_secs_f64() * 1e3 / n as f64
    };
    bench::keep_gpu_busy(bench::GPU_WARM_UP_S, || {
        run(10, None);
    });
    let runs: Vec<f64> = (0..repeats).map(|_| run(steps, None)).collect();
    let gpu = GpuProfiler::new(&g.device, &g.queue, 1).and_then(|mut prof| {
        run(steps, Some(&mut prof));
        prof.read(&g.device, &g.queue)
            .get("lattice")
            .map(|v| v.0 / steps as f64)
    });
    world.download(&g.device, &g.queue, &mut state);
    LatticeGpu {
        wall: bench::median(runs),
        gpu,
        finite: state.x.iter().all(|p| p.is_finite()),
    }
}

/// `--lattice`: the default body at Table 1's sizes, CPU and GPU.
fn lattice_table(
    a: &bench::Args,
    sizes: &[u32],
    steps: usize,
    repeats: usize,
    out: &std::path::Path,
) {
    let gpu = if a.flag("--no-gpu") {
        None
    } else {
        bench::open_gpu().ok()
    };
    let kernels = gpu
        .as_ref()
        .and_then(|g| LatticeKernels::new(&g.device).ok());
    println!(
        "| particles | elements | CPU Newton–multigrid, all cores (ms per step) | GPU time (ms per step) | GPU wall clock (ms per step) | paper GPU, K = 32 (ms per step) | GPU wall clock over the paper's GPU |"
    );
    println!("|---|---|---|---|---|---|---|");
    let mut json = String::from("{\n  \"cells\": [\n");
    for (i, &target) in sizes.iter().enumerate() {
        let model = lattice_liver(target);
        let cpu = (!a.flag("--no-cpu")).then(|| lattice_cpu(&model, steps, repeats));
        let on_gpu = match (&gpu, &kernels) {
            (Some(g), Some(k)) => Some(lattice_gpu(g, k, &model, steps as u32, repeats)),
            _ => None,
        };
        let ms = |v: f64, ok: bool| format!("{v:.3}{}", if ok { "" } else { " (diverged)" });
        let cpu_cell = cpu.map_or("–".to_string(), |(v, ok)| ms(v, ok));
        let wall_cell = on_gpu.map_or("–".to_string(), |c| ms(c.wall, c.finite));
        let time_cell = on_gpu
            .and_then(|c| c.gpu.map(|v| ms(v, c.finite)))
            .unwrap_or_else(|| "–".to_string());
        let paper_gpu = paper(32, "GPU", target);
        eprintln!(
            "lattice, {} particles: CPU {cpu_cell}, GPU time {time_cell}, GPU wall clock {wall_cell}",
            model.particle_count(),
        );
        println!(
            "| {} | {} | {cpu_cell} | {time_cell} | {wall_cell} | {} | {} |",
            model.particle_count(),
            model.elements.len(),
            paper_gpu.map_or("–".into(), |v| format!("{v}")),
            match (paper_gpu, on_gpu) {
                (Some(p), Some(c)) => ratio(p / c.wall),
                _ => "–".into(),
            }
        );
        let num = |v: Option<f64>| v.map_or("null".to_string(), |v| format!("{v:.6}"));
        let _ = writeln!(
            json,
            "    {{\"target\": {target}, \"particles\": {}, \"elements\": {}, \"cpu_ms_per_step\": {}, \"gpu_time_ms_per_step\": {}, \"gpu_wall_ms_per_step\": {}, \"steps\": {steps}, \"repeats\": {repeats}}}{}",
            model.particle_count(),
            model.elements.len(),
            num(cpu.map(|c| c.0)),
            num(on_gpu.and_then(|c| c.gpu)),
            num(on_gpu.map(|c| c.wall)),
            if i + 1 < sizes.len() { "," } else { "" }
        );
    }
    json.push_str("  ]\n}\n");
    std::fs::write(out.join("table1_lattice.json"), json).expect("write JSON");
}

fn main() {
    let a = bench::Args::new();
    let quick = a.flag("--quick");
    let steps: usize = a.num("--steps", if quick { 20 } else { 300 });
    let repeats: usize = a.num("--repeats", if quick { 3 } else { 5 });
    let out = a.path("--out", "table1_out");
    std::fs::create_dir_all(&out).expect("output folder");
    let sizes: &[u32] = if quick { &SIZES[..2] } else { &SIZES };
    if a.flag("--lattice") {
        // `--sizes` takes the liver to other particle counts (the scaling rows).
        let sizes = a.list("--sizes", sizes);
        lattice_table(&a, &sizes, steps, repeats, &out);
        return;
    }
    let mut backends = Vec::new();
    if !a.flag("--no-cpu") {
        backends.extend([Backend::CpuOneThread, Backend::CpuAllCores]);
    }
    let gpu = if a.flag("--no-gpu") {
        None
    } else {
        match bench::open_gpu() {
            Ok(g) => {
                backends.push(Backend::Gpu);
                Some(g)
            }
            Err(e) => {
                eprintln!("no GPU adapter ({e}): GPU rows skipped");
                None
            }
        }
    };
    let ks: Vec<u32> = a.list("--k", &[32, 64]);
    let t0 = Instant::now();
    let mut cells = Vec::new();
    for &k in &ks {
        for &target in sizes {
            let model = liver(target, k);
            for &b in &backends {
                let (ms_step, ms_knn, finite) = match (b, &gpu) {
                    (Backend::Gpu, Some(g)) => gpu_cell(g, &model, k, steps as u32, repeats),
                    (Backend::Gpu, None) => continue,
                    _ => cpu_cell(&model, k, b, steps, repeats),
                };
                eprintln!(
                    "[{:6.1} s] K = {k}, {} particles, {}: {ms_step:.3} ms/step, KNN {ms_knn:.3} ms{}",
                    t0.elapsed().as_secs_f64(),
                    model.particle_count(),
                    b.name(),
                    if finite { "" } else { " (DIVERGED)" }
                );
                cells.push(Cell {
                    backend: b,
                    k,
                    target,
                    particles: model.particle_count(),
                    ms_step,
                    ms_knn,
                    finite,
                });
            }
        }
    }
    // Markdown.
    println!(
        "| K | particles | backend | ms per step | ms per KNN refresh | speed-up over 1-thread CPU | paper (ms per step) | speed-up over the paper |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for c in &cells {
        let base = cells
            .iter()
            .find(|o| o.k == c.k && o.target == c.target && o.backend == Backend::CpuOneThread)
            .map(|o| o.ms_step);
        let p = paper(c.k, c.backend.paper_kind(), c.target);
        println!(
            "| {} | {} | {} | {:.3}{} | {:.3} | {} | {} | {} |",
            c.k,
            c.particles,
            c.backend.name(),
            c.ms_step,
            if c.finite { "" } else { " (diverged)" },
            c.ms_knn,
            base.map_or("–".into(), |b| ratio(b / c.ms_step)),
            p.map_or("–".into(), |v| format!("{v}")),
            p.map_or("–".into(), |v| ratio(v / c.ms_step)),
        );
    }
    // JSON (hand-written: flat records of numbers and strings).
    let mut json = String::from("{\n  \"paper\": [\n");
    for (i, (k, b, v)) in PAPER.iter().enumerate() {
        let _ = writeln!(
            json,
            "    {{\"k\": {k}, \"backend\": \"{b}\", \"particles\": {SIZES:?}, \"ms_per_step\": {v:?}}}{}",
            if i + 1 < PAPER.len() { "," } else { "" }
        );
    }
    json.push_str("  ],\n  \"cells\": [\n");
    for (i, c) in cells.iter().enumerate() {
        let _ = writeln!(
            json,
            "    {{\"k\": {}, \"target\": {}, \"particles\": {}, \"backend\": \"{}\", \"ms_per_step\": {:.6}, \"ms_per_knn\": {:.6}, \"finite\": {}, \"steps\": {steps}, \"repeats\": {repeats}}}{}",
            c.k,
            c.target,
            c.particles,
            c.backend.name(),
            c.ms_step,
            c.ms_knn,
            c.finite,
            if i + 1 < cells.len() { "," } else { "" }
        );
    }
    json.push_str("  ]\n}\n");
    std::fs::write(out.join("table1.json"), json).expect("write JSON");
    // Chart.
    let mut series = Vec::new();
    let mut color = 0;
    for &k in &[32u32, 64] {
        for &b in &backends {
            let pts: Vec<(f64, f64)> = cells
                .iter()
                .filter(|c| c.k == k && c.backend == b)
                .map(|c| (c.particles as f64, c.ms_step))
                .collect();
            series.push(chart::Series {
                label: format!("{}, K = {k}", b.name()),
                points: pts,
                color,
                markers: true,
                line: true,
            });
            color += 1;
        }
    }
    for (k, b, v) in PAPER {
        series.push(chart::Series {
            label: format!("paper {b}, K = {k}"),
            points: SIZES.iter().zip(v).map(|(&s, &m)| (s as f64, m)).collect(),
            color,
            markers: true,
            line: false,
        });
        color += 1;
    }
    let panel = chart::Panel {
        title: "Table 1: ms per step against particles (liver, 10 iterations)".into(),
        x_label: "particles".into(),
        y_label: "ms per step".into(),
        x_log: true,
        y_log: true,
        series,
    };
    chart::draw(&out.join("table1.png"), &[panel], 1, (1000, 640)).expect("chart");
    eprintln!(
        "wrote {} and {}",
        out.join("table1.json").display(),
        out.join("table1.png").display()
    );
}
