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
//! The residual counts the constraints only (`C + α̃λ`), not the momentum balance
//! `M(x − x̃) = Jᵀλ` that the hierarchy's multiplier hand-over leaves unbalanced, so the
//! example also solves the step to convergence (flat Gauss–Seidel, `--reference`
//! iterations) and measures each solver's distance to it at the sampled iteration
//! counts (fresh one-step solves; RMS over the particles, relative to the step's RMS
//! motion).
//!
//! Writes `hierarchy.csv` and `hierarchy.png` into the output folder and two summaries
//! on stdout: for each scene and backend, the time and iterations each solver needs to
//! reach a residual, and to come within 90%, 80%, … of the step's motion of the
//! converged step (each down to the smallest both reach), with the speed-ups.
//!
//! ```text
//! cargo run --release --example hierarchy                  # bar 20,000 + liver 37,982
//! cargo run --release --example hierarchy -- --quick       # small sizes, under a minute
//! cargo run --release --example hierarchy -- --bar 50000 --liver 0 --no-cpu
//! ```
//! Options: `--bar N`, `--liver N` (particles, 0 skips the scene), `--iters N` (most
//! level-0 iterations), `--coarse N` (iterations per coarse level, default 20),
//! `--levels N` (levels including level 0; default: chosen from the body's size),
//! `--reference N` (flat Gauss–Seidel iterations of the converged step that both solvers'
//! positions are compared with; default 8,000, `--quick` 4,000, 0 skips it), `--no-cpu`,
//! `--no-gpu`, `--out DIR` (default `hierarchy_out`), `--reference-dir DIR` (where the
//! converged step is saved and, if there from an earlier run, read; default the output
//! folder).
//!
//! `--webgpu-limits` holds the device to WebGPU's default limits (what every browser
//! guarantees; the tests run the example so).

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
use bevy_tissue::gpu::{GpuWorld, Headless, NoTiming};
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
    /// Distance to the converged step ([`Reference`]) relative to the step's motion
    /// (`None`: not computed at this iteration count, or no reference).
    error: Option<f32>,
}

/// The step solved to convergence: flat Gauss–Seidel with many iterations, from the
/// same start. Both solvers' positions are compared with it, so the comparison counts
/// what the residual does not: the momentum balance `M(x − x̃) = Jᵀλ`, which the
/// hierarchy's hand-over leaves unbalanced (BENCHMARKS.md, "Hierarchy").
struct Reference {
    start: Vec<Vec3>,
    x: Vec<Vec3>,
    /// Distance between the solves with half and all of the reference's iterations,
    /// relative to the step's motion: how far the reference itself is from converged.
    own_error: f32,
}

impl Reference {
    /// The reference of scene `name` with `n` particles, read from `dir` if an earlier
    /// run saved it there (same particles, same start), else solved and saved. The file
    /// holds `own_error`, then the start and converged positions (f32, native order).
    fn cached(dir: &std::path::Path, name: &str, n: u32, iterations: u32) -> Self {
        let path = dir.join(format!("reference-{name}-{n}-{iterations}.bin"));
        let (model, state) = scene(name, n, None);
        let len = state.x.len();
        if let Ok(bytes) = std::fs::read(&path)
            && bytes.len() == 4 + 2 * size_of::<Vec3>() * len
        {
            let (head, body) = bytes.split_at(4);
            let saved: Vec<Vec3> = body
                .chunks_exact(size_of::<Vec3>())
                .map(bytemuck::pod_read_unaligned)
                .collect();
            if saved[..len] == state.x[..] {
                eprintln!("  reference read from {}", path.display());
                return Self {
                    start: state.x,
                    x: saved[len..].to_vec(),
                    own_error: bytemuck::pod_read_unaligned(head),
                };
            }
        }
        let r = Self::solve(&model, &state, iterations);
        let mut bytes = bytemuck::bytes_of(&r.own_error).to_vec();
        bytes.extend_from_slice(bytemuck::cast_slice(&r.start));
        bytes.extend_from_slice(bytemuck::cast_slice(&r.x));
        if let Err(e) = std::fs::write(&path, bytes) {
            eprintln!("  reference not saved to {}: {e}", path.display());
        }
        r
    }

    /// Solves one step of `model` from `state` with `iterations` flat Gauss–Seidel
    /// iterations, and with half as many to estimate how far that is from converged.
    fn solve(model: &Model, state: &State, iterations: u32) -> Self {
        let step = |iterations: u32| {
            let mut st = state.clone();
            let s = SolverSettings {
                method: Method::GaussSeidel,
                iterations,
                particle_contacts: false,
                ..Default::default()
            };
            let mut solver = Solver::new(model, s).expect("solver");
            solver
                .step(model, &mut st, &Control::default())
                .expect("reference step");
            st.x
        };
        let half = step(iterations / 2);
        let mut r = Self {
            start: state.x.clone(),
            x: step(iterations),
            own_error: 0.0,
        };
        r.own_error = r.error(&half);
        r
    }

    /// RMS distance of `x` to the converged step over the RMS motion of that step.
    fn error(&self, x: &[Vec3]) -> f32 {
        let (mut num, mut den) = (0.0f64, 0.0f64);
        for ((x, r), s) in x.iter().zip(&self.x).zip(&self.start) {
            num += x.distance_squared(*r) as f64;
            den += r.distance_squared(*s) as f64;
        }
        (num / den.max(1e-30)).sqrt() as f32
    }
}

/// The iteration counts sampled by fresh one-step solves, up to `iters`.
fn counts(iters: u32) -> Vec<u32> {
    let mut counts: Vec<u32> = vec![1, 2, 3, 4, 6, 8, 11, 16, 23, 32, 45, 64, 90, 128, 181, 256];
    counts.extend([362, 512, 724, 1024]);
    counts.retain(|&c| c <= iters);
    if counts.last() != Some(&iters) {
        counts.push(iters);
    }
    counts
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
    reference: u32,
    reference_dir: PathBuf,
    cpu: bool,
    gpu: bool,
    out: PathBuf,
}

fn args() -> Args {
    let a = bench::Args::new();
    let quick = a.flag("--quick");
    let out = a.path("--out", "hierarchy_out");
    Args {
        bar: a.num("--bar", if quick { 3000 } else { 20_000 }),
        liver: a.num("--liver", if quick { 3000 } else { 37_982 }),
        iters: a.num("--iters", if quick { 40 } else { 200 }),
        coarse: a.num("--coarse", SolverSettings::default().coarse_iterations),
        levels: a.num("--levels", 0),
        reference: a.num("--reference", if quick { 4000 } else { 8000 }),
        reference_dir: a.path("--reference-dir", &out.to_string_lossy()),
        cpu: !a.flag("--no-cpu"),
        gpu: !a.flag("--no-gpu"),
        out,
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
            discretisation: bevy_tissue::core::model::Discretisation::Clusters,
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
            discretisation: bevy_tissue::core::model::Discretisation::Clusters,
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
    reference: Option<&Reference>,
) -> Curve {
    let hier = h.is_some();
    let (model, mut state) = scene(name, n, h);
    let start = state.clone();
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
    let mut points: Vec<Point> = stats
        .residuals
        .iter()
        .map(|r| Point {
            iterations: r.iteration,
            ms: r.ms,
            residual: r.residual,
            error: None,
        })
        .collect();
    // The distance to the converged step at the sampled counts: fresh untraced solves
    // (the traced run above gives the times).
    if let Some(r) = reference {
        for it in counts(iters) {
            let mut st = start.clone();
            let untraced = SolverSettings {
                trace_residual: false,
                ..settings(it, coarse)
            };
            let mut sv = Solver::new(&model, untraced).expect("solver");
            if sv.step(&model, &mut st, &Control::default()).is_ok()
                && let Some(p) = points.iter_mut().find(|p| p.iterations == it)
            {
                p.error = Some(r.error(&st.x));
            }
        }
    }
    Curve {
        scene: name,
        particles: model.particle_count(),
        backend: "CPU",
        solver: if hier { "hierarchical" } else { "flat" },
        coarse_work: coarse_work(&model, &s),
        points,
    }
}

fn gpu_curve(
    g: &Headless,
    name: &'static str,
    n: u32,
    h: Option<HierarchyDesc>,
    iters: u32,
    coarse: u32,
    reference: Option<&Reference>,
) -> Curve {
    let hier = h.is_some();
    let (model, state) = scene(name, n, h);
    let nn = model.particle_count();
    let mut points = Vec::new();
    for it in counts(iters) {
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
        bench::keep_gpu_busy(1.0, || {
            let mut enc = g.device.create_command_encoder(&Default::default());
            world.record_steps(&mut enc, &g.kernels, 2, &mut NoTiming);
            g.queue.submit([enc.finish()]);
            bench::sync(g, &world);
        });
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
            error: reference.map(|r| r.error(&x)),
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

/// Prints a table: per scene and backend, the time and level-0 iterations each solver
/// needs to bring `value` (residual or distance) down to each of `fixed` and to the
/// smallest value both reach, and the hierarchy's speed-up.
fn summary(
    curves: &[Curve],
    scenes: &[(&'static str, u32)],
    what: &str,
    value: fn(&Point) -> Option<f32>,
    fixed: &[f32],
    show: fn(f32) -> String,
) {
    println!(
        "| scene | particles | backend | {what} | flat: iterations / ms | hierarchical: iterations (+ coarse) / ms | speed-up |"
    );
    println!("|---|---|---|---|---|---|---|");
    for &(name, _) in scenes {
        for backend in ["CPU", "GPU"] {
            let find = |solver: &str| {
                curves
                    .iter()
                    .find(|c| c.scene == name && c.backend == backend && c.solver == solver)
            };
            let (Some(f), Some(h)) = (find("flat"), find("hierarchical")) else {
                continue;
            };
            let best = |c: &Curve| {
                c.points
                    .iter()
                    .filter_map(value)
                    .filter(|v| v.is_finite())
                    .fold(f32::MAX, f32::min)
            };
            if best(f) == f32::MAX || best(h) == f32::MAX {
                continue;
            }
            let common = best(f).max(best(h));
            let mut targets = fixed.to_vec();
            targets.retain(|&t| t > common);
            targets.push(common);
            let reach = |c: &Curve, target: f32| {
                c.points
                    .iter()
                    .copied()
                    .find(|p| value(p).is_some_and(|v| v <= target))
            };
            for target in targets {
                let cell = |c: &Curve, coarse: bool| match reach(c, target) {
                    Some(p) if coarse => {
                        format!("{} (+{:.2}) / {:.2}", p.iterations, c.coarse_work, p.ms)
                    }
                    Some(p) => format!("{} / {:.2}", p.iterations, p.ms),
                    None => format!("not reached (best {:.2e})", best(c)),
                };
                let speed = match (reach(f, target), reach(h, target)) {
                    (Some(pf), Some(ph)) => format!("{:.1}x", pf.ms / ph.ms.max(1e-9)),
                    (None, Some(_)) => "flat never".into(),
                    (Some(_), None) => "hierarchical never".into(),
                    _ => "-".into(),
                };
                println!(
                    "| {name} | {} | {backend} | {}{} | {} | {} | {speed} |",
                    f.particles,
                    show(target),
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
}

fn main() {
    let a = args();
    std::fs::create_dir_all(&a.out).expect("output folder");
    let gpu = if a.gpu {
        match bench::open_gpu() {
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
        let reference = (a.reference > 0).then(|| {
            let t = Instant::now();
            let r = Reference::cached(&a.reference_dir, name, n, a.reference);
            eprintln!(
                "  reference: flat Gauss–Seidel, {} iterations (ready in {:.1} s); {} and {} \
                 iterations differ by {:.2e} of the step's motion",
                a.reference,
                t.elapsed().as_secs_f64(),
                a.reference / 2,
                a.reference,
                r.own_error
            );
            r
        });
        for h in [None, Some(hd)] {
            if a.cpu {
                curves.push(cpu_curve(name, n, h, a.iters, a.coarse, reference.as_ref()));
            }
            if let Some(g) = &gpu {
                curves.push(gpu_curve(
                    g,
                    name,
                    n,
                    h,
                    a.iters,
                    a.coarse,
                    reference.as_ref(),
                ));
            }
        }
    }
    // CSV.
    let mut csv =
        String::from("scene,particles,backend,solver,coarse_work,iterations,ms,residual,error\n");
    for c in &curves {
        for p in &c.points {
            let _ = writeln!(
                csv,
                "{},{},{},{},{:.3},{},{:.4},{:.6e},{}",
                c.scene,
                c.particles,
                c.backend,
                c.solver,
                c.coarse_work,
                p.iterations,
                p.ms,
                p.residual,
                p.error.map(|e| format!("{e:.6e}")).unwrap_or_default()
            );
        }
    }
    let csv_path = a.out.join("hierarchy.csv");
    std::fs::write(&csv_path, csv).expect("write CSV");
    // Summaries: time to reach fixed residuals, and to come within fractions of the
    // step's motion of the converged step (both's convergence in this norm is slow, in
    // their low modes), each down to the smallest value both reach.
    summary(
        &curves,
        &scenes,
        "residual",
        |p| Some(p.residual),
        &[1e-3, 5e-4, 3e-4],
        |t| format!("{t:.2e}"),
    );
    println!();
    summary(
        &curves,
        &scenes,
        "error (of the step's motion)",
        |p| p.error,
        &[0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3, 0.1],
        |t| format!("{t:.3}"),
    );
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
    // And the distance to the converged step against time.
    for &(name, _) in &scenes {
        let series: Vec<chart::Series> = curves
            .iter()
            .filter(|c| c.scene == name)
            .enumerate()
            .map(|(k, c)| chart::Series {
                label: format!("{} {}", c.backend, c.solver),
                points: c
                    .points
                    .iter()
                    .filter_map(|p| p.error.filter(|e| e.is_finite()).map(|e| (p.ms, e as f64)))
                    .collect(),
                color: k,
                markers: true,
                line: true,
            })
            .filter(|s| !s.points.is_empty())
            .collect();
        if !series.is_empty() {
            panels.push(chart::Panel {
                title: format!("{name}: distance to the converged step against time"),
                x_label: "ms (solve time of the step)".into(),
                y_label: "RMS error / RMS motion of the step".into(),
                x_log: true,
                y_log: true,
                series,
            });
        }
    }
    let png = a.out.join("hierarchy.png");
    chart::draw(&png, &panels, 2, (720, 480)).expect("chart");
    eprintln!("wrote {} and {}", csv_path.display(), png.display());
}
