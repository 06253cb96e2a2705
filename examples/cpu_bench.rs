//! CPU benchmark of the simulation core at the paper's sizes (Li & Kang 2014, Table 1):
//! the procedural liver sampled at 512, 4096, 13824 and 37982 particles, K = 32,
//! 10 iterations, dt = 1/60 s, pinned along its ligament, falling under gravity.
//!
//! Prints a Markdown table: ms per step for one-thread Gauss–Seidel (the paper's CPU
//! baseline) and all-core Jacobi, both elastic models, and ms per KNN refresh (K = 32,
//! all cores and one thread).
//!
//! With `--scale` it instead times the liver from 37,982 up to 1,000,000 particles (SPEC §6
//! scaling; shape matching k = 1, the plugin's default; Jacobi on all cores, 5 steps after
//! 5 warm-up steps, the same stage breakdown). `--sizes a,b,..` picks other counts
//! (sampled at the 37,982-particle spacing scaled by the cube root of the ratio).
//!
//! With `--contacts` it times the particle-contact search that the plugin's main world
//! runs for lattice bodies (from the positions read back): touching 5 cm lattice cubes
//! of 512 particles on a square grid (the GPU benchmark's "touching cubes"; `--bodies
//! a,b,..`, default 36, 100 and 1,000), at rest, all falling together at 1 m/s, and every
//! other body falling at 1 m/s past the others at rest (the search's reach widened for
//! their relative travel), the first search and the next one (which starts from the
//! last search's lists), on all cores.
//!
//! ```text
//! cargo run --release --example cpu_bench            # the full table
//! cargo run --release --example cpu_bench -- --quick # small sizes only, seconds
//! cargo run --release --example cpu_bench -- --scale # 38k to 1M particles, minutes
//! cargo run --release --example cpu_bench -- --contacts --bodies 36,1000
//! ```
#[path = "support/bench.rs"]
mod bench;

use bench::median;
use bevy_tissue::core::knn::knn_all;
use bevy_tissue::core::model::{BodyDesc, Material, Model, PinRegion};
use bevy_tissue::core::procedural;
use bevy_tissue::core::sampling::Resolution;
use bevy_tissue::core::solver::{Control, Method, Solver, SolverSettings, StageTimes, State};
use std::time::Instant;

/// Mean ms per step over `steps` steps (and the mean time per stage), or the error if
/// the run diverged.
fn time_steps(
    model: &Model,
    method: Method,
    threads: usize,
    steps: usize,
) -> Result<(f64, StageTimes), String> {
    let settings = SolverSettings {
        method,
        threads,
        iterations: 10,
        knn_every: 10,
        ..Default::default()
    };
    let mut solver = Solver::new(model, settings).map_err(|e| e.to_string())?;
    let mut state = State::new(model);
    let control = Control::default();
    // Warm-up: the body starts to sag and the contact KNN runs once.
    for _ in 0..5 {
        solver
            .step(model, &mut state, &control)
            .map_err(|e| e.to_string())?;
    }
    let mut per_step = Vec::with_capacity(steps);
    let mut stages = StageTimes::default();
    for _ in 0..steps {
        let t = Instant::now();
        let st = solver
            .step(model, &mut state, &control)
            .map_err(|e| e.to_string())?;
        per_step.push(t.elapsed().as_secs_f64() * 1e3);
        let s = st.timings;
        let w = 1.0 / steps as f64;
        stages.knn += s.knn * w;
        stages.predict += s.predict * w;
        stages.clusters += s.clusters * w;
        stages.gather += s.gather * w;
        stages.boundary += s.boundary * w;
        stages.finish += s.finish * w;
    }
    // Mean over the run (KNN refreshes included at their 1-in-10 rate).
    Ok((per_step.iter().sum::<f64>() / per_step.len() as f64, stages))
}

/// The stage times as Markdown cells (KNN, predict, clusters, gather, boundary, finish).
fn stage_cells(s: &StageTimes, decimals: usize) -> String {
    [s.knn, s.predict, s.clusters, s.gather, s.boundary, s.finish]
        .map(|v| format!("{v:.decimals$}"))
        .join(" | ")
}

fn cell(r: &Result<(f64, StageTimes), String>) -> String {
    match r {
        Ok((ms, _)) => format!("{ms:.1}"),
        Err(e) => {
            eprintln!("  run failed: {e}");
            "diverged".into()
        }
    }
}

/// `--scale`: Jacobi on all cores at growing sizes, ms per step and per stage.
fn scale() {
    let sizes: Vec<u32> =
        bench::Args::new().list("--sizes", &[37_982, 131_072, 524_288, 1_000_000]);
    let threads = bevy_tissue::core::par::default_threads();
    let mesh = procedural::liver(5);
    let (lo, hi) = procedural::liver_ligament();
    let desc = |resolution| BodyDesc {
        resolution,
        neighbours: 32,
        material: Material::ShapeMatching { stiffness: 1.0 },
        pins: vec![PinRegion::Box { min: lo, max: hi }],
        discretisation: bevy_tissue::core::model::Discretisation::Clusters,
        ..Default::default()
    };
    let mut base = Model::new();
    base.add_body(&mesh, &desc(Resolution::Particles(37_982)))
        .expect("the procedural liver is valid");
    let spacing = base.bodies[0].spacing;
    println!(
        "CPU scaling: Jacobi on {threads} threads, shape matching k = 1, K = 32, 10 iterations, \
         KNN every 10th step\n"
    );
    println!(
        "| particles | build s | ms per step | KNN | predict | clusters | gather | contacts/colliders/pins | finish |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for n in sizes {
        let t = Instant::now();
        let mut model = Model::new();
        let r = Resolution::Spacing(spacing * (37_982.0 / n as f32).cbrt());
        if let Err(e) = model.add_body(&mesh, &desc(r)) {
            eprintln!("{n}: {e}");
            continue;
        }
        let build = t.elapsed().as_secs_f64();
        eprintln!("built {} particles in {build:.1} s", model.particle_count());
        match time_steps(&model, Method::Jacobi, 0, 5) {
            Ok((ms, s)) => println!(
                "| {} | {build:.1} | {ms:.0} | {} |",
                model.particle_count(),
                stage_cells(&s, 0)
            ),
            Err(e) => println!(
                "| {} | {build:.1} | {e} | | | | | | |",
                model.particle_count()
            ),
        }
    }
}

fn main() {
    let args = bench::Args::new();
    if args.flag("--scale") {
        scale();
        return;
    }
    if args.flag("--contacts") {
        contacts(&args.list("--bodies", &[36, 100, 1000]));
        return;
    }
    let quick = args.flag("--quick");
    let sizes: &[u32] = if quick {
        &[512, 4096]
    } else {
        &[512, 4096, 13824, 37982]
    };
    let steps = if quick { 10 } else { 30 };
    let threads = bevy_tissue::core::par::default_threads();
    let mesh = procedural::liver(5);
    let (lo, hi) = procedural::liver_ligament();
    println!("CPU threads: {threads}; K = 32, 10 iterations, dt = 1/60 s, KNN every 10th step");
    println!();
    println!(
        "| particles | model | GS 1 thread ms/step | Jacobi {threads} threads ms/step | KNN {threads} threads ms | KNN 1 thread ms |"
    );
    println!("|---|---|---|---|---|---|");
    let mut breakdown = Vec::new();
    for &n in sizes {
        for (name, material) in [
            (
                "shape matching k=0.5",
                Material::ShapeMatching { stiffness: 0.5 },
            ),
            ("hyperelastic E=10 kPa", Material::default()),
        ] {
            let mut model = Model::new();
            let desc = BodyDesc {
                resolution: Resolution::Particles(n),
                neighbours: 32,
                material,
                pins: vec![PinRegion::Box { min: lo, max: hi }],
                discretisation: bevy_tissue::core::model::Discretisation::Clusters,
                ..Default::default()
            };
            let t = Instant::now();
            model
                .add_body(&mesh, &desc)
                .expect("the procedural liver is valid");
            eprintln!(
                "built {} particles ({name}) in {:.0} ms",
                model.particle_count(),
                t.elapsed().as_secs_f64() * 1e3
            );
            let gs = time_steps(&model, Method::GaussSeidel, 1, steps);
            let jc = time_steps(&model, Method::Jacobi, 0, steps);
            let knn = |th: usize| {
                median(
                    (0..3)
                        .map(|_| {
                            let t = Instant::now();
                            let _ = knn_all(&model.rest, 32, th);
                            t.elapsed().as_secs_f64() * 1e3
                        })
                        .collect(),
                )
            };
            let (k_all, k_one) = (knn(0), knn(1));
            println!(
                "| {} | {name} | {} | {} | {k_all:.1} | {k_one:.1} |",
                model.particle_count(),
                cell(&gs),
                cell(&jc)
            );
            for (method, r) in [("GS 1 thread", &gs), ("Jacobi all cores", &jc)] {
                if let Ok((_, s)) = r {
                    breakdown.push(format!(
                        "| {} | {name} | {method} | {} |",
                        model.particle_count(),
                        stage_cells(s, 1)
                    ));
                }
            }
        }
    }
    println!();
    println!("Mean ms per step by stage:");
    println!();
    println!(
        "| particles | model | method | KNN | predict | clusters | gather | contacts/colliders/pins | finish |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for row in breakdown {
        println!("{row}");
    }
}

/// `--contacts`: ms per particle-contact search over touching cubes, at rest and
/// moving, first search and next (median of 3 each), and after how many steps of that
/// motion the lists would be stale.
fn contacts(sizes: &[u32]) {
    let threads = bevy_tissue::core::par::default_threads();
    let settings = SolverSettings::default();
    println!(
        "Particle-contact search (K = {}), touching lattice cubes of 512 particles, {threads} threads\n",
        settings.contact_neighbours
    );
    println!(
        "| bodies | particles | motion | first ms | next ms | candidates | searched again after (steps) |"
    );
    println!("|---|---|---|---|---|---|---|");
    for &bodies in sizes {
        let model = match bench::cubes_at(bodies, 0.057) {
            Ok(m) => m,
            Err(e) => {
                eprintln!("{bodies} cubes: {e}");
                continue;
            }
        };
        let x = model.placed_rest();
        let n = x.len();
        for (motion, moving) in [
            ("at rest", 0u32),
            ("all falling at 1 m/s", 1),
            ("every other body at 1 m/s", 2),
        ] {
            let v: Vec<glam::Vec3> = (0..n)
                .map(|i| {
                    let b = model.particle_body[i];
                    let falls = moving == 1 || (moving == 2 && b.is_multiple_of(2));
                    glam::Vec3::new(0.0, if falls { -1.0 } else { 0.0 }, 0.0)
                })
                .collect();
            let (mut first, mut next, mut pairs) = (Vec::new(), Vec::new(), 0);
            let mut every = String::new();
            for _ in 0..3 {
                let mut solver = match Solver::new(&model, settings.clone()) {
                    Ok(s) => s,
                    Err(e) => {
                        eprintln!("{bodies} cubes: {e}");
                        return;
                    }
                };
                for times in [&mut first, &mut next] {
                    let t = Instant::now();
                    solver.refresh_contacts_if_due(&model, &x, &v, &[], 1, true);
                    times.push(t.elapsed().as_secs_f64() * 1e3);
                }
                pairs = solver.contact_lists().1.len();
                // Steps of this motion (kinematic) until the lists are stale.
                let travel = solver.contact_travel(&v, 1);
                every = (1..=20u32)
                    .find(|&s| {
                        let t = settings.dt * s as f32;
                        let moved: Vec<glam::Vec3> =
                            x.iter().zip(&v).map(|(p, u)| *p + *u * t).collect();
                        solver.contacts_stale(&moved, travel)
                    })
                    .map_or("over 20".into(), |s| s.to_string());
            }
            println!(
                "| {bodies} | {n} | {motion} | {:.1} | {:.1} | {pairs} | {every} |",
                median(first),
                median(next)
            );
        }
    }
}
