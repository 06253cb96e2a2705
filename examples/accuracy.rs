//! Accuracy against an independent finite-element reference: does the material simulated
//! mean the E and ν that were set, and does it converge to them as the resolution grows?
//!
//! 1. **The reference.** Quadratic-tetrahedron FEM in f64 (`bevy_tissue::core::fem`), refined
//!    until its answer moves less than 0.5%: the cantilever (24 × 3 × 3 cm, clamped at one
//!    end, E = 100 kPa, ν = 0.3, 1000 kg/m³, gravity 0.2 m/s²) and the liver
//!    (`liver2.msh` scaled to 20 cm, held in its top 15%, E = 5 kPa, ν = 0.45,
//!    1060 kg/m³, gravity 0.5 m/s²). Euler–Bernoulli as a sanity check.
//! 2. **Convergence with resolution** of each discretisation's own energy, solved
//!    statically (`bevy_tissue::core::statics`, the equilibrium the time stepper settles
//!    to under these small loads): the hexahedral lattice elements and the paper's KNN
//!    clusters, tip deflection and sag against the FEM at the same points, the Poisson
//!    ratio between frictionless plates (static, linear: the answer is ν). A log–log
//!    chart of the error against particles across, with the fitted slopes.
//! 3. **The time stepper converged** (CPU Gauss–Seidel, many substeps and iterations,
//!    settled with damping) at small sizes: it lands on the static answer; the Poisson
//!    ratio (ν = 0.3, 0.45, 5% squeeze) and the volume (ν = 0.49, 20% squeeze) between
//!    frictionless plates against the homogeneous answer of the same material.
//!
//! Writes `accuracy.csv` and `accuracy.png` into the output folder and Markdown on
//! stdout.
//!
//! ```text
//! cargo run --release --example accuracy              # everything (~10 min on 2 cores)
//! cargo run --release --example accuracy -- --quick   # small sizes, under a minute
//! ```
//! Options: `--quick`, `--max-across N` (the bar's finest lattice; default 16),
//! `--no-dynamic`, `--no-liver`, `--meshes DIR` (default `../shared/meshes` or
//! `$BEVY_TISSUE_MESHES`), `--out DIR` (default `accuracy_out`).

#[path = "support/accuracy.rs"]
mod accuracy;
#[path = "support/chart.rs"]
mod chart;

use accuracy::*;
use glam::{DVec3, Vec3};
use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

struct Args {
    quick: bool,
    realtime: bool,
    max_across: u32,
    dynamic: bool,
    liver: bool,
    meshes: PathBuf,
    out: PathBuf,
}

fn args() -> Args {
    let mut a = Args {
        quick: false,
        realtime: true,
        max_across: 16,
        dynamic: true,
        liver: true,
        meshes: std::env::var_os("BEVY_TISSUE_MESHES")
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from("../shared/meshes")),
        out: PathBuf::from("accuracy_out"),
    };
    let mut it = std::env::args().skip(1);
    while let Some(arg) = it.next() {
        let mut value = |name: &str| {
            it.next().unwrap_or_else(|| {
                eprintln!("accuracy: {name} needs a value");
                std::process::exit(2)
            })
        };
        match arg.as_str() {
            "--quick" => a.quick = true,
            "--no-dynamic" => a.dynamic = false,
            "--no-realtime" => a.realtime = false,
            "--only-realtime" => {
                a.realtime = true;
                a.dynamic = false;
                a.liver = false;
                a.max_across = 3;
            }
            "--no-liver" => a.liver = false,
            "--max-across" => {
                a.max_across = value("--max-across").parse().unwrap_or_else(|_| {
                    eprintln!("accuracy: --max-across takes a particle count (≥ 3)");
                    std::process::exit(2)
                })
            }
            "--meshes" => a.meshes = PathBuf::from(value("--meshes")),
            "--out" => a.out = PathBuf::from(value("--out")),
            "--help" | "-h" => {
                println!(
                    "accuracy [--quick] [--max-across N] [--no-dynamic] [--no-liver] [--meshes DIR] [--out DIR]"
                );
                std::process::exit(0);
            }
            other => {
                eprintln!("accuracy: unknown option {other} (try --help)");
                std::process::exit(2);
            }
        }
    }
    if a.quick {
        a.max_across = a.max_across.min(6);
    }
    a.max_across = a.max_across.max(3);
    a
}

/// One measured point of the convergence study.
struct Point {
    scene: &'static str,
    disc: String,
    across: f64,
    particles: usize,
    value: f64,
    reference: f64,
}

impl Point {
    fn error(&self) -> f64 {
        self.value / self.reference - 1.0
    }
}

/// Least-squares slope of log|error| against log(across).
fn slope(points: &[&Point]) -> f64 {
    let xy: Vec<(f64, f64)> = points
        .iter()
        .filter(|p| p.error() != 0.0 && p.error().is_finite())
        .map(|p| (p.across.ln(), p.error().abs().ln()))
        .collect();
    let n = xy.len() as f64;
    if n < 2.0 {
        return f64::NAN;
    }
    let (mx, my) = (
        xy.iter().map(|p| p.0).sum::<f64>() / n,
        xy.iter().map(|p| p.1).sum::<f64>() / n,
    );
    let sxy: f64 = xy.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let sxx: f64 = xy.iter().map(|p| (p.0 - mx).powi(2)).sum();
    sxy / sxx
}

fn fail(what: &str, e: impl std::fmt::Display) -> ! {
    eprintln!("accuracy: {what}: {e}");
    std::process::exit(1)
}

fn main() {
    let a = args();
    std::fs::create_dir_all(&a.out).unwrap_or_else(|e| fail("output folder", e));
    let mut md = String::new();
    let mut points: Vec<Point> = Vec::new();

    // 1. The FEM reference of the cantilever, refined until it moves < 0.5%.
    let _ = writeln!(md, "## FEM reference (quadratic tetrahedra, f64)\n");
    let _ = writeln!(
        md,
        "| scene | mesh | nodes | CG iterations | answer (mm) | change | s |\n|---|---|---|---|---|---|---|"
    );
    let eb = euler_bernoulli_tip();
    let fem_cells: &[usize] = if a.quick { &[2, 4] } else { &[2, 4, 8] };
    let mut bar_ref = None;
    let mut prev = f64::NAN;
    let mut tips = Vec::new();
    for &c in fem_cells {
        eprintln!("FEM cantilever {}x{c}x{c} cells ...", 8 * c);
        let t = Instant::now();
        let sol = bar_fem(c).unwrap_or_else(|e| fail("FEM cantilever", e));
        let tip = -sol
            .mean_over(|p| p.x >= BAR_LENGTH - 1e-12)
            .unwrap_or(DVec3::NAN)
            .y;
        let _ = writeln!(
            md,
            "| cantilever tip | {}×{c}×{c} cells × 6 tets | {} | {} | {:.4} | {} | {:.1} |",
            8 * c,
            sol.nodes.len(),
            sol.iterations,
            tip * 1e3,
            if prev.is_finite() {
                format!("{:+.2}%", (tip / prev - 1.0) * 100.0)
            } else {
                "-".into()
            },
            t.elapsed().as_secs_f64()
        );
        prev = tip;
        tips.push(tip);
        bar_ref = Some(sol);
    }
    // Richardson extrapolation of the last three refinements (each halves the cells):
    // the FEM's own remaining error, so that the finest discretisations are not
    // measured against a reference no better than they are.
    let mut ref_scale = 1.0;
    if let [.., t0, t1, t2] = tips[..] {
        let order = ((t1 - t0) / (t2 - t1)).log2();
        let limit = t2 + (t2 - t1) / (2f64.powf(order) - 1.0);
        if limit.is_finite() && order > 0.5 {
            ref_scale = limit / t2;
            let _ = writeln!(
                md,
                "\nRichardson extrapolation of the last three: {:.4} mm (observed order {order:.2}); the references below are the finest FEM scaled by {ref_scale:.5}.",
                limit * 1e3
            );
        }
    }
    let bar_ref = bar_ref.unwrap_or_else(|| fail("FEM cantilever", "no mesh"));
    let _ = writeln!(
        md,
        "\nEuler–Bernoulli: {:.4} mm (the FEM's finest: {:.4}x).\n",
        eb * 1e3,
        prev / eb
    );

    // 2. Static convergence of each discretisation, the cantilever.
    let _ = writeln!(
        md,
        "## Cantilever: static tip deflection against the FEM at the same points\n"
    );
    let _ = writeln!(
        md,
        "| discretisation | particles across | particles | tip (mm) | FEM there (mm) | ratio | CG iterations |\n|---|---|---|---|---|---|---|"
    );
    let lattice_across: Vec<u32> = [3u32, 4, 5, 6, 8, 10, 12, 14, 16, 20]
        .into_iter()
        .filter(|&n| n <= a.max_across)
        .collect();
    let cluster_across: Vec<u32> = [4u32, 5, 6, 8, 10, 12]
        .into_iter()
        .filter(|&n| n <= a.max_across.min(12))
        .collect();
    for (disc, list) in [
        (Disc::Lattice, &lattice_across),
        (Disc::Clusters(32), &cluster_across),
    ] {
        for &n in list.iter() {
            eprintln!("static cantilever, {}, {n} across ...", disc.name());
            let model = bar_model(disc, n).unwrap_or_else(|e| fail("cantilever model", e));
            let (tip, iters) =
                bar_static_tip(&model).unwrap_or_else(|e| fail("cantilever static solve", e));
            let reference = bar_fem_tip_at(&bar_ref, &model) * ref_scale;
            let _ = writeln!(
                md,
                "| {} | {n} | {} | {:.4} | {:.4} | {:.4} | {iters} |",
                disc.name(),
                model.particle_count(),
                tip * 1e3,
                reference * 1e3,
                tip / reference
            );
            points.push(Point {
                scene: "cantilever",
                disc: disc.name(),
                across: n as f64,
                particles: model.particle_count(),
                value: tip,
                reference,
            });
        }
    }

    // Poisson ratio, static (linear), between frictionless plates.
    let _ = writeln!(
        md,
        "\n## Poisson ratio: static, 5% squeeze between frictionless plates (answer: ν)\n"
    );
    let _ = writeln!(
        md,
        "| discretisation | ν | particles across | measured ν | error |\n|---|---|---|---|---|"
    );
    let cube_across: &[u32] = if a.quick { &[4, 6] } else { &[4, 6, 8, 12] };
    for disc in [Disc::Lattice, Disc::Clusters(32)] {
        for nu in [0.3f32, 0.45] {
            for &n in cube_across {
                let model = cube_model(disc, n, nu).unwrap_or_else(|e| fail("cube model", e));
                let m = cube_static_poisson(&model).unwrap_or_else(|e| fail("cube static", e));
                let _ = writeln!(
                    md,
                    "| {} | {nu} | {n} | {m:.4} | {:+.2}% |",
                    disc.name(),
                    (m / nu as f64 - 1.0) * 100.0
                );
                points.push(Point {
                    scene: if nu < 0.4 {
                        "poisson 0.3"
                    } else {
                        "poisson 0.45"
                    },
                    disc: disc.name(),
                    across: n as f64,
                    particles: model.particle_count(),
                    value: m,
                    reference: nu as f64,
                });
            }
        }
    }

    // The liver.
    if a.liver {
        let path = a.meshes.join("liver2.msh");
        match std::fs::read_to_string(&path) {
            Err(e) => eprintln!("accuracy: liver skipped ({}: {e})", path.display()),
            Ok(text) => liver(&a, &text, &mut md, &mut points),
        }
    }

    // 3. The time stepper, converged.
    if a.dynamic {
        dynamic(&a, &mut md);
    }
    // 4. The time stepper at real-time budgets.
    if a.realtime {
        realtime(&a, &mut md);
    }

    // Slopes and the chart.
    let _ = writeln!(
        md,
        "\n## Convergence slopes (log |error| against log particles across)\n"
    );
    let _ = writeln!(
        md,
        "| scene | discretisation | slope | finest error |\n|---|---|---|---|"
    );
    let mut groups: Vec<(&str, String)> = Vec::new();
    for p in &points {
        if !groups.iter().any(|g| g.0 == p.scene && g.1 == p.disc) {
            groups.push((p.scene, p.disc.clone()));
        }
    }
    let mut panels: Vec<chart::Panel> = Vec::new();
    for scene in ["cantilever", "liver", "poisson 0.3", "poisson 0.45"] {
        let mut series = Vec::new();
        for (k, (_, disc)) in groups.iter().filter(|g| g.0 == scene).enumerate() {
            let pts: Vec<&Point> = points
                .iter()
                .filter(|p| p.scene == scene && &p.disc == disc)
                .collect();
            let s = slope(&pts);
            let last = pts.last().map_or(f64::NAN, |p| p.error());
            let _ = writeln!(md, "| {scene} | {disc} | {s:.2} | {:+.2}% |", last * 100.0);
            series.push(chart::Series {
                label: format!("{disc} (slope {s:.2})"),
                points: pts.iter().map(|p| (p.across, p.error().abs())).collect(),
                color: k,
                markers: true,
                line: true,
            });
        }
        if !series.is_empty() {
            panels.push(chart::Panel {
                title: format!("{scene}: |error| against the FEM reference"),
                x_label: if scene == "liver" {
                    "particles across the liver's height".into()
                } else {
                    "particles across".into()
                },
                y_label: "|relative error|".into(),
                x_log: true,
                y_log: true,
                series,
            });
        }
    }
    let mut csv = String::from("scene,discretisation,across,particles,value,reference,error\n");
    for p in &points {
        let _ = writeln!(
            csv,
            "{},{},{},{},{:e},{:e},{:e}",
            p.scene,
            p.disc,
            p.across,
            p.particles,
            p.value,
            p.reference,
            p.error()
        );
    }
    let csv_path = a.out.join("accuracy.csv");
    std::fs::write(&csv_path, csv).unwrap_or_else(|e| fail("accuracy.csv", e));
    let png = a.out.join("accuracy.png");
    chart::draw(&png, &panels, 2, (720, 480)).unwrap_or_else(|e| fail("accuracy.png", e));
    print!("{md}");
    eprintln!("wrote {} and {}", csv_path.display(), png.display());
}

/// The liver's FEM reference and each discretisation's static sag against it.
fn liver(a: &Args, text: &str, md: &mut String, points: &mut Vec<Point>) {
    let tets = liver_tets(text).unwrap_or_else(|e| fail("liver2.msh", e));
    let _ = writeln!(md, "\n## Liver: mean sag against the FEM\n");
    let _ = writeln!(
        md,
        "| FEM mesh | nodes | CG iterations | mean sag (mm) | change |\n|---|---|---|---|---|"
    );
    let refinements: &[u32] = if a.quick { &[0, 1] } else { &[0, 1, 2] };
    let mut reference = f64::NAN;
    for &r in refinements {
        eprintln!("FEM liver, {r} refinements ...");
        let sol = liver_fem(&tets, r).unwrap_or_else(|e| fail("FEM liver", e));
        let sag = -sol.mean_displacement().y;
        let _ = writeln!(
            md,
            "| liver2.msh refined {r}× | {} | {} | {:.4} | {} |",
            sol.nodes.len(),
            sol.iterations,
            sag * 1e3,
            if reference.is_finite() {
                format!("{:+.2}%", (sag / reference - 1.0) * 100.0)
            } else {
                "-".into()
            }
        );
        reference = sag;
    }
    let (lo, hi) = tets.bounds();
    let height = hi.y - lo.y;
    let _ = writeln!(
        md,
        "\n| discretisation | particles across the height | particles | sag (mm) | FEM (mm) | ratio |\n|---|---|---|---|---|---|"
    );
    let across: &[u32] = if a.quick {
        &[6, 8]
    } else {
        &[6, 8, 12, 16, 24]
    };
    for disc in [Disc::Lattice, Disc::Clusters(32)] {
        for &n in across {
            let spacing = disc.spacing(height, n);
            eprintln!("static liver, {}, spacing {spacing:.4} ...", disc.name());
            let model = match liver_model(&tets, disc, spacing) {
                Ok(m) => m,
                Err(e) => {
                    eprintln!("accuracy: liver model at {n} across: {e}");
                    continue;
                }
            };
            let (sag, _) = liver_static_sag(&model).unwrap_or_else(|e| fail("liver static", e));
            let _ = writeln!(
                md,
                "| {} | {n} | {} | {:.4} | {:.4} | {:.4} |",
                disc.name(),
                model.particle_count(),
                sag * 1e3,
                reference * 1e3,
                sag / reference
            );
            points.push(Point {
                scene: "liver",
                disc: disc.name(),
                across: n as f64,
                particles: model.particle_count(),
                value: sag,
                reference,
            });
        }
    }
}

/// The converged time stepper at small sizes: the cantilever settles on the static
/// answer; the Poisson ratio and the volume under large squeezes.
fn dynamic(a: &Args, md: &mut String) {
    let _ = writeln!(
        md,
        "\n## The time stepper, converged (CPU Gauss–Seidel, settled with damping)\n"
    );
    let _ = writeln!(
        md,
        "| scene | discretisation | across | substeps × iterations | simulated s | measured | reference | error | wall s |\n|---|---|---|---|---|---|---|---|---|"
    );
    let across: &[u32] = if a.quick { &[4] } else { &[4, 6] };
    for disc in [Disc::Lattice, Disc::Clusters(32)] {
        for &n in across {
            let model = bar_model(disc, n).unwrap_or_else(|e| fail("cantilever model", e));
            let (stat, _) = bar_static_tip(&model).unwrap_or_else(|e| fail("static", e));
            let t = Instant::now();
            let st = Stepping::CONVERGED;
            let (sub, it, secs) = (st.substeps, st.iterations, 6.0);
            let (x, _) = settle(
                &model,
                Vec3::new(0.0, -BAR_GRAVITY as f32, 0.0),
                0.0,
                secs,
                &st,
            )
            .unwrap_or_else(|e| fail("cantilever settle", e));
            let tip = bar_tip(&model, &displacements(&model, &x));
            let _ = writeln!(
                md,
                "| cantilever tip (mm) vs the static solve | {} | {n} | {sub} × {it} | {secs} | {:.4} | {:.4} | {:+.2}% | {:.1} |",
                disc.name(),
                tip * 1e3,
                stat * 1e3,
                (tip / stat - 1.0) * 100.0,
                t.elapsed().as_secs_f64()
            );
        }
    }
    let cube_n: u32 = if a.quick { 5 } else { 7 };
    for disc in [Disc::Lattice, Disc::Clusters(32)] {
        for (nu, squeeze) in [(0.3f32, 0.05f32), (0.45, 0.05), (0.49, 0.2)] {
            let model = cube_model(disc, cube_n, nu).unwrap_or_else(|e| fail("cube model", e));
            let t = Instant::now();
            let st = Stepping {
                damping: 5.0,
                ..Stepping::CONVERGED
            };
            let (sub, it, secs) = (st.substeps, st.iterations, 3.0);
            let (x, _) = settle(&model, Vec3::ZERO, squeeze, secs, &st)
                .unwrap_or_else(|e| fail("cube settle", e));
            let axial = layer_strain(&model, &x, 1);
            let b = uniaxial_lateral_stretch(CUBE_E as f64, nu as f64, 1.0 + axial);
            if squeeze < 0.1 {
                let m = measured_poisson(&model, &x);
                let r = -(b - 1.0) / axial;
                let _ = writeln!(
                    md,
                    "| Poisson ratio, ν = {nu}, {:.1}% squeeze | {} | {cube_n} | {sub} × {it} | {secs} | {m:.4} | {r:.4} | {:+.2}% | {:.1} |",
                    -axial * 100.0,
                    disc.name(),
                    (m / r - 1.0) * 100.0,
                    t.elapsed().as_secs_f64()
                );
            } else {
                let v = material_volume(&model, &x) / material_volume(&model, &model.rest);
                let r = (1.0 + axial) * b * b;
                let _ = writeln!(
                    md,
                    "| volume ratio, ν = {nu}, {:.1}% squeeze | {} | {cube_n} | {sub} × {it} | {secs} | {v:.4} | {r:.4} | {:+.2}% | {:.1} |",
                    -axial * 100.0,
                    disc.name(),
                    (v - r) * 100.0,
                    t.elapsed().as_secs_f64()
                );
            }
        }
    }
}

/// The cantilever (lattice, 6 across) settled at real-time budgets — 1/60 s steps of a
/// few substeps × iterations — against the static answer of the same model, for E from
/// 1 kPa to 1 MPa (gravity scaled with E, so the strain is the same).
fn realtime(a: &Args, md: &mut String) {
    let _ = writeln!(
        md,
        "\n## Real-time budgets: the settled cantilever (lattice, 6 across) against its static answer\n"
    );
    let _ = writeln!(
        md,
        "| E (Pa) | stepping | simulated s | tip / static | ms per step (CPU) |\n|---|---|---|---|---|"
    );
    let youngs: &[f32] = if a.quick { &[1e5] } else { &[1e3, 1e5, 1e6] };
    use bevy_tissue::core::solver::{ElementSolver, Method};
    let mut steppings = Vec::new();
    for (method, element_solver) in [
        (Method::GaussSeidel, ElementSolver::Xpbd),
        (Method::Jacobi, ElementSolver::Xpbd),
        (Method::GaussSeidel, ElementSolver::VertexDescent),
        (Method::GaussSeidel, ElementSolver::Multigrid),
    ] {
        for (sub, it) in [
            (1u32, 10u32),
            (2, 5),
            (5, 2),
            (10, 1),
            (1, 1),
            (1, 2),
            (2, 1),
        ] {
            // XPBD and VBD at the two ends of the 10-iteration budget; Newton–multigrid
            // also at 1 and 2 iterations a step.
            let mg = element_solver == ElementSolver::Multigrid;
            if (!mg && !matches!((sub, it), (1, 10) | (10, 1))) || (mg && sub * it > 10) {
                continue;
            }
            steppings.push(Stepping {
                substeps: sub,
                iterations: it,
                method,
                warm_start: false,
                element_solver,
                damping: 0.0,
            });
        }
    }
    if a.quick {
        steppings.retain(|s| {
            s.substeps == 1 && (s.iterations == 10 || s.element_solver == ElementSolver::Multigrid)
        });
    }
    for &e in youngs {
        let model = bar_model_with(Disc::Lattice, 6, e).unwrap_or_else(|err| fail("bar", err));
        let g = BAR_GRAVITY * e as f64 / BAR_E as f64;
        let (stat, _) = bar_static_tip_under(&model, g).unwrap_or_else(|err| fail("static", err));
        // Critically damp the first bending mode and settle for ~8 of its time constants.
        let w1 = bar_first_mode(e as f64);
        let secs = (8.0 / w1).clamp(1.0, 20.0) as f32;
        for st in &steppings {
            let st = Stepping {
                damping: (2.0 * w1) as f32,
                ..*st
            };
            eprintln!("real-time cantilever, E = {e}, {} ...", st.label());
            let gravity = Vec3::new(0.0, -g as f32, 0.0);
            let row = match settle(&model, gravity, 0.0, secs, &st) {
                Ok((x, ms)) => {
                    let tip = bar_tip(&model, &displacements(&model, &x));
                    format!("{:.4} | {ms:.2}", tip / stat)
                }
                Err(err) => format!("diverged ({err}) | -"),
            };
            let _ = writeln!(md, "| {e} | {} | {secs:.1} | {row} |", st.label());
        }
    }
}
