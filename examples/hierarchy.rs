//! Hierarchical against flat PBD (issue 4): the residual against level-0 iterations and
//! against time, for a stiff bar (E = 1 MPa) released from a bent pose and for the
//! procedural liver (E = 1 MPa) pinned at its ligament and released from a squashed
//! pose, on the CPU (Jacobi, all cores) and on the GPU.
//!
//! CPU: one step with the residual traced after every iteration
//! ([`SolverSettings::trace_residual`]); time is the solve time so far. GPU: one fresh
//! world per iteration count, one step, positions and multipliers read back and the
//! residual evaluated by the CPU solver's [`Solver::residual_with`]; time is the GPU
//! time of that one step between two timestamps (restarted from the initial state by a
//! GPU-to-GPU copy, the least of 5; the host's wall clock where the adapter has no
//! timestamp queries).
//!
//! Writes `hierarchy.csv` and `hierarchy.png` into the output folder and a summary on
//! stdout: for each scene and backend, the time and iterations each solver needs to
//! reach the smallest residual both reach, and the speed-up.
//!
//! ```text
//! cargo run --release --example hierarchy                  # bar 20,000 + liver 37,982
//! cargo run --release --example hierarchy -- --quick       # small sizes, under a minute
//! cargo run --release --example hierarchy -- --bar 50000 --liver 0 --no-cpu
//! ```
//! Options: `--bar N`, `--liver N` (particles, 0 skips the scene), `--iters N` (most
//! level-0 iterations), `--coarse N` (iterations per coarse level, default 20),
//! `--levels N` (levels including level 0; default: chosen from the body's size),
//! `--no-cpu`, `--no-gpu`, `--out DIR` (default `hierarchy_out`).

#[path = "support/bench.rs"]
mod bench;
#[path = "support/chart.rs"]
mod chart;

use bevy_tissue::core::constraints::Multipliers;
use bevy_tissue::core::hierarchy::HierarchyDesc;
use bevy_tissue::core::model::{BodyDesc, Material, Model, PinRegion};
use bevy_tissue::core::procedural;
use bevy_tissue::core::sampling::Resolution;
use bevy_tissue::core::solver::{Control, Method, Solver, SolverSettings, State};
use bevy_tissue::gpu::buffers::GpuClusterState;
use bevy_tissue::gpu::profile::GpuProfiler;
use bevy_tissue::gpu::world::{read_buffer, read_vec3};
use bevy_tissue::gpu::{GpuWorld, Headless, NoTiming, headless};
use glam::{Quat, Vec3};
use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

/// One point of a convergence curve.
#[derive(Clone, Copy)]
struct Point {
    iterations: u32,
    ms: f64,
    residual: f32,
}

struct Curve {
    scene: &'static str,
    particles: usize,
    backend: &'static str,
    solver: &'static str,
    /// Coarse levels' work in level-0 iterations (particles × coarse iterations / n).
    coarse_work: f64,
    points: Vec<Point>,
}

struct Args {
    bar: u32,
    liver: u32,
    iters: u32,
    coarse: u32,
    levels: u32,
    cpu: bool,
    gpu: bool,
    out: PathBuf,
}

fn args() -> Args {
    let a = bench::Args::new();
    let quick = a.flag("--quick");
    Args {
        bar: a.num("--bar", if quick { 3000 } else { 20_000 }),
        liver: a.num("--liver", if quick { 3000 } else { 37_982 }),
        iters: a.num("--iters", if quick { 40 } else { 200 }),
        coarse: a.num("--coarse", SolverSettings::default().coarse_iterations),
        levels: a.num("--levels", 0),
        cpu: !a.flag("--no-cpu"),
        gpu: !a.flag("--no-gpu"),
        out: a.path("--out", "hierarchy_out"),
    }
}

const STIFF: Material = Material::Hyperelastic {
    youngs_modulus: 1.0e6,
    poisson_ratio: 0.3,
};

/// A scene: the model (flat, or with hierarchy `h`) and its deformed start.
fn scene(name: &str, n: u32, h: Option<HierarchyDesc>) -> (Model, State) {
    let mut model = Model::new();
    if name == "bar" {
        let half = Vec3::new(0.15, 0.03, 0.03);
        let desc = BodyDesc {
            resolution: Resolution::Particles(n),
            neighbours: 32,
            material: STIFF,
            pins: vec![PinRegion::HalfSpace {
                point: Vec3::new(-0.8 * half.x, 0.0, 0.0),
                normal: -Vec3::X,
            }],
            hierarchy: h,
            ..Default::default()
        };
        model
            .add_body(&procedural::cuboid(half, 2), &desc)
            .expect("bar");
        let mut state = State::new(&model);
        for (x, r) in state.x.iter_mut().zip(&model.rest) {
            let u = ((r.x + 0.8 * half.x) / (1.8 * half.x)).max(0.0);
            x.y -= 0.06 * u * u;
        }
        (model, state)
    } else {
        let (lo, hi) = procedural::liver_ligament();
        let desc = BodyDesc {
            resolution: Resolution::Particles(n),
            neighbours: 32,
            material: Material::Hyperelastic {
                youngs_modulus: 1.0e6,
                poisson_ratio: 0.45,
            },
            pins: vec![PinRegion::Box { min: lo, max: hi }],
            hierarchy: h,
            ..Default::default()
        };
        model.add_body(&procedural::liver(4), &desc).expect("liver");
        let mut state = State::new(&model);
        // Squashed by 15% towards the ligament's height, then released.
        let y0 = 0.5 * (lo.y + hi.y);
        for (i, x) in state.x.iter_mut().enumerate() {
            if !model.pinned.contains(&(i as u32)) {
                x.y = y0 + 0.85 * (x.y - y0);
            }
        }
        (model, state)
    }
}

fn settings(iterations: u32, coarse: u32) -> SolverSettings {
    SolverSettings {
        method: Method::Jacobi,
        iterations,
        coarse_iterations: coarse,
        particle_contacts: false,
        trace_residual: true,
        ..Default::default()
    }
}

fn coarse_work(model: &Model, s: &SolverSettings) -> f64 {
    let n0 = model.particle_count() as f64;
    model
        .levels
        .iter()
        .map(|l| l.model.particle_count() as f64 * s.coarse_iterations as f64 / n0)
        .sum()
}

fn cpu_curve(
    name: &'static str,
    n: u32,
    h: Option<HierarchyDesc>,
    iters: u32,
    coarse: u32,
) -> Curve {
    let hier = h.is_some();
    let (model, mut state) = scene(name, n, h);
    let s = settings(iters, coarse);
    let mut solver = Solver::new(&model, s.clone()).expect("solver");
    eprintln!(
        "  CPU {name} {}: {} particles, levels {:?}",
        if hier { "hierarchical" } else { "flat" },
        model.particle_count(),
        model
            .levels
            .iter()
            .map(|l| l.model.particle_count())
            .collect::<Vec<_>>()
    );
    let stats = solver
        .step(&model, &mut state, &Control::default())
        .expect("step");
    Curve {
        scene: name,
        particles: model.particle_count(),
        backend: "CPU",
        solver: if hier { "hierarchical" } else { "flat" },
        coarse_work: coarse_work(&model, &s),
        points: stats
            .residuals
            .iter()
            .map(|r| Point {
                iterations: r.iteration,
                ms: r.ms,
                residual: r.residual,
            })
            .collect(),
    }
}

fn gpu_curve(
    g: &Headless,
    name: &'static str,
    n: u32,
    h: Option<HierarchyDesc>,
    iters: u32,
    coarse: u32,
) -> Curve {
    let hier = h.is_some();
    let (model, state) = scene(name, n, h);
    let nn = model.particle_count();
    let mut counts: Vec<u32> = vec![1, 2, 3, 4, 6, 8, 11, 16, 23, 32, 45, 64, 90, 128, 181, 256];
    counts.extend([362, 512, 724, 1024]);
    counts.retain(|&c| c <= iters);
    if counts.last() != Some(&iters) {
        counts.push(iters);
    }
    let mut points = Vec::new();
    for &it in &counts {
        let s = settings(it, coarse);
        let mut world = GpuWorld::new(&g.device, &g.kernels, &model, &state, s.clone(), 0)
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        world.write_params(&g.queue);
        let mut enc = g.device.create_command_encoder(&Default::default());
        world.record_steps(&mut enc, &g.kernels, 1, &mut NoTiming);
        g.queue.submit([enc.finish()]);
        let x = read_vec3(&g.device, &g.queue, world.positions(), nn as u32);
        let bytes = read_buffer(
            &g.device,
            &g.queue,
            world.cluster_states(),
            0,
            (nn * size_of::<GpuClusterState>()) as u64,
        );
        let cs: &[GpuClusterState] = bytemuck::cast_slice(&bytes);
        let rot: Vec<Quat> = cs.iter().map(|c| Quat::from_array(c.rot)).collect();
        let lam: Vec<Multipliers> = cs
            .iter()
            .map(|c| Multipliers {
                h: c.lam0[0],
                d: [
                    c.lam0[1], c.lam0[2], c.lam0[3], c.lam1[0], c.lam1[1], c.lam1[2],
                ],
            })
            .collect();
        let cpu = Solver::new(&model, s).expect("solver");
        let residual = cpu.residual_with(&model, &x, &rot, &lam);
        // Time of this one step: restart from the initial state (a GPU-to-GPU copy from
        // an untouched twin world) and time one step, the least of 5 (so that the
        // timing never runs a diverging state).
        let base = GpuWorld::new(
            &g.device,
            &g.kernels,
            &model,
            &state,
            settings(it, coarse),
            0,
        )
        .unwrap_or_else(|e| panic!("{name}: {e}"));
        let mut prof = GpuProfiler::new(&g.device, &g.queue, 4);
        // Warm the GPU up first (1 s of steps): an idle GPU runs at a lower clock; after
        // the host built a model, short bursts (or 0.2 s of warm-up) timed up to 5x slower.
        let warm = Instant::now();
        while warm.elapsed().as_secs_f64() < 1.0 {
            let mut enc = g.device.create_command_encoder(&Default::default());
            world.record_steps(&mut enc, &g.kernels, 2, &mut NoTiming);
            g.queue.submit([enc.finish()]);
            bench::sync(g, &world);
        }
        let mut times = Vec::new();
        for _ in 0..5 {
            let mut enc = g.device.create_command_encoder(&Default::default());
            world.copy_state_from(&mut enc, &base, 0, 0, nn as u32);
            if let Some(p) = prof.as_mut() {
                p.mark(&mut enc);
            }
            world.record_steps(&mut enc, &g.kernels, 1, &mut NoTiming);
            if let Some(p) = prof.as_mut() {
                p.mark(&mut enc);
                p.resolve(&mut enc);
            }
            let cmd = enc.finish();
            bench::sync(g, &world);
            let t = Instant::now();
            g.queue.submit([cmd]);
            bench::sync(g, &world);
            let wall = t.elapsed().as_secs_f64() * 1e3;
            times.push(match prof.as_mut() {
                Some(p) => {
                    let m = p.read_marks(&g.device, &g.queue);
                    m[1] - m[0]
                }
                None => wall,
            });
        }
        // The least of 5: the GPU warmed up, no stall of the host in it.
        let ms = times.iter().copied().fold(f64::MAX, f64::min);
        points.push(Point {
            iterations: it,
            ms,
            residual,
        });
    }
    eprintln!(
        "  GPU {name} {}: {} points",
        if hier { "hierarchical" } else { "flat" },
        points.len()
    );
    Curve {
        scene: name,
        particles: nn,
        backend: "GPU",
        solver: if hier { "hierarchical" } else { "flat" },
        coarse_work: coarse_work(&model, &settings(1, coarse)),
        points,
    }
}

/// The first point at or below `target`.
fn reach(c: &Curve, target: f32) -> Option<Point> {
    c.points.iter().copied().find(|p| p.residual <= target)
}

fn main() {
    let a = args();
    std::fs::create_dir_all(&a.out).expect("output folder");
    let gpu = if a.gpu {
        match headless() {
            Ok(g) => Some(g),
            Err(e) => {
                eprintln!("no GPU adapter ({e}): GPU curves skipped");
                None
            }
        }
    } else {
        None
    };
    let mut scenes: Vec<(&'static str, u32)> = Vec::new();
    if a.bar > 0 {
        scenes.push(("bar", a.bar));
    }
    if a.liver > 0 {
        scenes.push(("liver", a.liver));
    }
    let mut curves = Vec::new();
    for &(name, n) in &scenes {
        eprintln!("{name}, {n} particles:");
        // `--levels 0` leaves the level count to the body's size.
        let hd = HierarchyDesc {
            levels: (a.levels > 0).then_some(a.levels),
            ..Default::default()
        };
        for h in [None, Some(hd)] {
            if a.cpu {
                curves.push(cpu_curve(name, n, h, a.iters, a.coarse));
            }
            if let Some(g) = &gpu {
                curves.push(gpu_curve(g, name, n, h, a.iters, a.coarse));
            }
        }
    }
    // CSV.
    let mut csv =
        String::from("scene,particles,backend,solver,coarse_work,iterations,ms,residual\n");
    for c in &curves {
        for p in &c.points {
            let _ = writeln!(
                csv,
                "{},{},{},{},{:.3},{},{:.4},{:.6e}",
                c.scene,
                c.particles,
                c.backend,
                c.solver,
                c.coarse_work,
                p.iterations,
                p.ms,
                p.residual
            );
        }
    }
    let csv_path = a.out.join("hierarchy.csv");
    std::fs::write(&csv_path, csv).expect("write CSV");
    // Summary: time to reach fixed residuals, and the smallest residual both reach.
    println!(
        "| scene | particles | backend | residual | flat: iterations / ms | hierarchical: iterations (+ coarse) / ms | speed-up |"
    );
    println!("|---|---|---|---|---|---|---|");
    for &(name, _) in &scenes {
        for backend in ["CPU", "GPU"] {
            let find = |solver: &str| {
                curves
                    .iter()
                    .find(|c| c.scene == name && c.backend == backend && c.solver == solver)
            };
            let (Some(f), Some(h)) = (find("flat"), find("hierarchical")) else {
                continue;
            };
            let best = |c: &Curve| c.points.iter().map(|p| p.residual).fold(f32::MAX, f32::min);
            let common = best(f).max(best(h));
            let mut targets = vec![1e-3f32, 5e-4, 3e-4];
            targets.retain(|&t| t > common);
            targets.push(common);
            for target in targets {
                let cell = |c: &Curve, coarse: bool| match reach(c, target) {
                    Some(p) if coarse => {
                        format!("{} (+{:.2}) / {:.2}", p.iterations, c.coarse_work, p.ms)
                    }
                    Some(p) => format!("{} / {:.2}", p.iterations, p.ms),
                    None => "not reached".into(),
                };
                let speed = match (reach(f, target), reach(h, target)) {
                    (Some(pf), Some(ph)) => format!("{:.1}x", pf.ms / ph.ms.max(1e-9)),
                    (None, Some(_)) => "flat never".into(),
                    _ => "-".into(),
                };
                println!(
                    "| {name} | {} | {backend} | {target:.2e}{} | {} | {} | {speed} |",
                    f.particles,
                    if target == common {
                        " (both's best)"
                    } else {
                        ""
                    },
                    cell(f, false),
                    cell(h, true),
                );
            }
        }
    }
    // Chart: per scene, residual against iterations and against time.
    let mut panels = Vec::new();
    for &(name, _) in &scenes {
        for by_time in [false, true] {
            let mut series = Vec::new();
            for (k, c) in curves.iter().filter(|c| c.scene == name).enumerate() {
                series.push(chart::Series {
                    label: format!("{} {}", c.backend, c.solver),
                    points: c
                        .points
                        .iter()
                        .map(|p| {
                            let x = if by_time { p.ms } else { p.iterations as f64 };
                            (x, p.residual as f64)
                        })
                        .collect(),
                    color: k,
                    markers: c.backend == "GPU",
                    line: true,
                });
            }
            panels.push(chart::Panel {
                title: format!(
                    "{name}: residual against {}",
                    if by_time { "time" } else { "iterations" }
                ),
                x_label: if by_time {
                    "ms (solve time of the step)".into()
                } else {
                    "level-0 iterations".into()
                },
                y_label: "residual / body size".into(),
                x_log: by_time,
                y_log: true,
                series,
            });
        }
    }
    let png = a.out.join("hierarchy.png");
    chart::draw(&png, &panels, 2, (720, 480)).expect("chart");
    eprintln!("wrote {} and {}", csv_path.display(), png.display());
}
