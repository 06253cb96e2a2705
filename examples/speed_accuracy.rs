//! Speed against accuracy (issue 6, SPEC §6): every method and setting — elastic model,
//! solver (CPU Gauss–Seidel, CPU Jacobi, GPU Jacobi), iterations, substeps, hierarchy,
//! neighbour count K — run through four measurements, each charted as ms per step against
//! error with the Pareto front marked:
//!
//! * **reference** — a bar (24 × 3 × 3 cm) pinned at one end, released straight under
//!   gravity and swinging for 1 s; the error is the RMS distance of all particles from a
//!   converged reference run of the same model (CPU Gauss–Seidel with 16 substeps and 50
//!   iterations for the hyperelastic model, E = 500 kPa), sampled every 0.1 s, relative to
//!   the bar's length. The solver is f32 throughout (SPEC asks for an f64 reference; the
//!   core has no f64 path, and the reference self-check below shows the reference
//!   converged far below the errors charted). Shape matching's k is a per-substep
//!   stiffness (Müller et al. 2005) and Jacobi's averaging softens it, so the substep
//!   count and the method change its material: its reference is the same method (CPU
//!   Jacobi for the GPU) with 100 iterations at the same substep count.
//! * **cantilever** — the same bar, E = 100 kPa, ν = 0.3, settled for 3 s under a
//!   gravity of 0.2 m/s² (scaled down so that the strain is small — the tip drops about
//!   5% of the length — while the material stays as soft as the solvers can converge);
//!   the tip deflection against Euler–Bernoulli's `δ = q L⁴ / (8 E I)`. Hyperelastic
//!   only (shape matching's k is no modulus).
//! * **Poisson** — a 6 cm cube, E = 20 kPa, ν = 0.3, squeezed 5% between frictionless
//!   plates without gravity: the measured `ν = −ε_lateral / ε_axial` against the set ν
//!   (uniaxial stress, linear elasticity). Hyperelastic only.
//! * **volume** — the same cube at ν = 0.49 squeezed 20%: the relative change of the
//!   material volume `Σ V_c det F_c` (physically about 0.4% at this bulk modulus; shape
//!   matching is measured too).
//!
//! ms per step is the wall clock of the reference scene's steps (CPU), or of the GPU's
//! 6-step submissions from submit to completion. The sizes are small (about 1,000
//! particles) so that the CPU grid finishes; on the GPU a step this small sits at the
//! dispatch-latency floor.
//!
//! Writes `speed_accuracy.csv` (the table behind the chart) and `speed_accuracy.png`
//! (four panels, log–log) into the output folder, and Markdown on stdout: every run and
//! the Pareto front of each panel.
//!
//! ```text
//! cargo run --release --example speed_accuracy               # the full grid (CPU: ~20 min)
//! cargo run --release --example speed_accuracy -- --quick    # a small grid, under a minute
//! cargo run --release --example speed_accuracy -- --no-cpu   # the GPU rows only
//! ```
//! Options: `--quick`, `--no-cpu`, `--no-gpu`, `--particles N` (the bar), `--cube N`,
//! `--out DIR` (default `speed_accuracy_out`).

#[path = "support/bench.rs"]
mod bench;
#[path = "support/chart.rs"]
mod chart;

use bevy_tissue::core::colliders::{Collider, ColliderShape};
use bevy_tissue::core::hierarchy::HierarchyDesc;
use bevy_tissue::core::model::{BodyDesc, Material, Model, PinRegion};
use bevy_tissue::core::procedural;
use bevy_tissue::core::sampling::Resolution;
use bevy_tissue::core::solver::{Control, Method, Solver, SolverSettings, State};
use bevy_tissue::gpu::world::read_vec3;
use bevy_tissue::gpu::{GpuWorld, Headless, NoTiming, headless};
use glam::{Quat, Vec3};
use std::collections::HashMap;
use std::fmt::Write as _;
use std::time::Instant;

/// Half extents of the bar, m (length 0.24 along x).
const BAR: Vec3 = Vec3::new(0.12, 0.015, 0.015);
/// Half extent of the cube, m.
const CUBE: f32 = 0.03;
/// Density, kg/m³.
const DENSITY: f32 = 1000.0;
/// Gravity, m/s².
const G: f32 = 9.81;
/// The cantilever's gravity, m/s² (small strain at E = 100 kPa).
const G_CANTILEVER: f32 = 0.2;
/// Shape matching's stiffness in every scene.
const SM_K: f32 = 0.5;

/// The elastic model of a run.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
enum ModelKind {
    ShapeMatching,
    Hyperelastic,
}

impl ModelKind {
    fn name(self) -> &'static str {
        match self {
            ModelKind::ShapeMatching => "shape matching",
            ModelKind::Hyperelastic => "hyperelastic",
        }
    }
}

/// Where a run is solved.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
enum Backend {
    GaussSeidel,
    Jacobi,
    Gpu,
}

impl Backend {
    fn name(self) -> &'static str {
        match self {
            Backend::GaussSeidel => "CPU Gauss-Seidel",
            Backend::Jacobi => "CPU Jacobi",
            Backend::Gpu => "GPU Jacobi",
        }
    }
}

/// One method and setting.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
struct Config {
    model: ModelKind,
    backend: Backend,
    iterations: u32,
    substeps: u32,
    hierarchy: bool,
    k: u32,
}

impl Config {
    fn label(&self) -> String {
        format!(
            "{} / {} / {} it / {} sub / K {}{}",
            self.model.name(),
            self.backend.name(),
            self.iterations,
            self.substeps,
            self.k,
            if self.hierarchy { " / hierarchy" } else { "" }
        )
    }
}

/// The four measurements.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Scene {
    Reference,
    Cantilever,
    Poisson,
    Volume,
}

const SCENES: [Scene; 4] = [
    Scene::Reference,
    Scene::Cantilever,
    Scene::Poisson,
    Scene::Volume,
];

impl Scene {
    fn name(self) -> &'static str {
        match self {
            Scene::Reference => "reference",
            Scene::Cantilever => "cantilever",
            Scene::Poisson => "poisson",
            Scene::Volume => "volume",
        }
    }

    fn title(self) -> &'static str {
        match self {
            Scene::Reference => "(a) RMS distance from a converged run / length",
            Scene::Cantilever => "(b) cantilever tip vs Euler-Bernoulli",
            Scene::Poisson => "(b) Poisson ratio under uniaxial compression",
            Scene::Volume => "(b) volume change, nu = 0.49, 20% squeeze",
        }
    }

    fn applies(self, model: ModelKind) -> bool {
        model == ModelKind::Hyperelastic || matches!(self, Scene::Reference | Scene::Volume)
    }

    fn material(self, model: ModelKind) -> Material {
        let hyper = |e: f32, nu: f32| Material::Hyperelastic {
            youngs_modulus: e,
            poisson_ratio: nu,
        };
        match (model, self) {
            (ModelKind::ShapeMatching, _) => Material::ShapeMatching { stiffness: SM_K },
            (_, Scene::Reference) => hyper(500e3, 0.45),
            (_, Scene::Cantilever) => hyper(100e3, 0.3),
            (_, Scene::Poisson) => hyper(20e3, 0.3),
            (_, Scene::Volume) => hyper(20e3, 0.49),
        }
    }
}

/// Sizes and durations.
#[derive(Clone, Copy)]
struct Sizes {
    bar: u32,
    cube: u32,
    /// Simulated seconds of each scene: reference, cantilever, Poisson, volume.
    seconds: [f32; 4],
}

/// A scene's body.
fn build(scene: Scene, c: &Config, sizes: &Sizes) -> Model {
    let (mesh, particles, pins) = match scene {
        Scene::Reference | Scene::Cantilever => (
            procedural::cuboid(BAR, 2),
            sizes.bar,
            vec![PinRegion::HalfSpace {
                point: Vec3::new(-0.108, 0.0, 0.0),
                normal: -Vec3::X,
            }],
        ),
        Scene::Poisson | Scene::Volume => {
            (procedural::cuboid(Vec3::splat(CUBE), 2), sizes.cube, vec![])
        }
    };
    let desc = BodyDesc {
        resolution: Resolution::Particles(particles),
        density: DENSITY,
        neighbours: c.k,
        material: scene.material(c.model),
        pins,
        // Small bodies: coarse levels down to 32 particles, so the hierarchy is exercised.
        hierarchy: c.hierarchy.then_some(HierarchyDesc {
            min_particles: 32,
            ..Default::default()
        }),
        discretisation: bevy_tissue::core::model::Discretisation::Clusters,
        ..Default::default()
    };
    let mut model = Model::new();
    if let Err(e) = model.add_body(&mesh, &desc) {
        eprintln!(
            "speed_accuracy: cannot build the {} body: {e}",
            scene.name()
        );
        std::process::exit(1);
    }
    model
}

fn settings(scene: Scene, c: &Config) -> SolverSettings {
    let (gravity, damping) = match scene {
        Scene::Reference => (Vec3::new(0.0, -G, 0.0), 1.0),
        Scene::Cantilever => (Vec3::new(0.0, -G_CANTILEVER, 0.0), 8.0),
        Scene::Poisson | Scene::Volume => (Vec3::ZERO, 5.0),
    };
    SolverSettings {
        dt: 1.0 / 60.0,
        substeps: c.substeps,
        iterations: c.iterations,
        gravity,
        damping,
        method: if c.backend == Backend::GaussSeidel {
            Method::GaussSeidel
        } else {
            Method::Jacobi
        },
        threads: if c.backend == Backend::GaussSeidel {
            1
        } else {
            0
        },
        particle_contacts: false,
        coarse_iterations: if c.hierarchy { 20 } else { 0 },
        ..Default::default()
    }
}

/// The plates of the compression scenes at `step`: the ground below the cube and a plate
/// above it moving down by `squeeze` of the height over the first 60% of the run.
fn plates(model: &Model, squeeze: f32, step: usize, steps: usize) -> (Vec<Collider>, f32) {
    let r = model.bodies[0].radius;
    let top0 = model.rest.iter().map(|p| p.y).fold(f32::MIN, f32::max) + r;
    let bottom = model.rest.iter().map(|p| p.y).fold(f32::MAX, f32::min) - r;
    let ramp = (0.6 * steps as f32).max(1.0);
    let f = ((step + 1) as f32 / ramp).min(1.0);
    let y = top0 - squeeze * (top0 - bottom) * f;
    let mut ground = Collider::ground(bottom);
    ground.friction = 0.0;
    let mut plate = Collider::new(
        ColliderShape::Plane,
        Vec3::new(0.0, y, 0.0),
        Quat::from_rotation_x(std::f32::consts::PI),
    );
    plate.friction = 0.0;
    (vec![ground, plate], (y - bottom) / (top0 - bottom))
}

/// What a run produced: positions at the sample times (the reference scene: every 0.1 s;
/// the others: the last step only) and its cost.
struct Run {
    samples: Vec<Vec<Vec3>>,
    ms_per_step: f64,
}

/// Steps a scene on the CPU. `None` when the solver reported divergence.
fn run_cpu(scene: Scene, c: &Config, model: &Model, seconds: f32) -> Option<Run> {
    let s = settings(scene, c);
    let mut solver = Solver::new(model, s).ok()?;
    let mut state = State::new(model);
    let steps = (seconds * 60.0).round() as usize;
    let squeeze = squeeze(scene);
    let mut samples = Vec::new();
    let mut ms = 0.0;
    for step in 0..steps {
        let control = Control {
            colliders: if squeeze > 0.0 {
                plates(model, squeeze, step, steps).0
            } else {
                vec![]
            },
        };
        let t = Instant::now();
        solver.step(model, &mut state, &control).ok()?;
        ms += t.elapsed().as_secs_f64() * 1e3;
        if sampled(scene, step, steps) {
            samples.push(state.x.clone());
        }
    }
    Some(Run {
        samples,
        ms_per_step: ms / steps as f64,
    })
}

/// Steps a scene on the GPU (the same model and settings; the GPU always iterates Jacobi).
fn run_gpu(g: &Headless, scene: Scene, c: &Config, model: &Model, seconds: f32) -> Option<Run> {
    let state = State::new(model);
    let mut world =
        GpuWorld::new(&g.device, &g.kernels, model, &state, settings(scene, c), 0).ok()?;
    let steps = (seconds * 60.0).round() as usize;
    let squeeze = squeeze(scene);
    let n = world.particle_count();
    let mut samples = Vec::new();
    let mut ms = 0.0;
    let mut step = 0;
    while step < steps {
        // Steps without per-step input go in one submission up to the next sample.
        let batch = if squeeze > 0.0 {
            1
        } else {
            (1..=steps - step)
                .find(|b| sampled(scene, step + b - 1, steps))
                .unwrap_or(steps - step)
        };
        if squeeze > 0.0 {
            let (colliders, _) = plates(model, squeeze, step, steps);
            world.set_colliders(&g.queue, &colliders).ok()?;
        }
        world.write_params(&g.queue);
        let mut enc = g.device.create_command_encoder(&Default::default());
        world.record_steps(&mut enc, &g.kernels, batch as u32, &mut NoTiming);
        let t = Instant::now();
        g.queue.submit([enc.finish()]);
        bench::sync(g, &world);
        ms += t.elapsed().as_secs_f64() * 1e3;
        step += batch;
        if sampled(scene, step - 1, steps) {
            let x = read_vec3(&g.device, &g.queue, world.positions(), n);
            if !x.iter().all(|p| p.is_finite() && p.length() < 100.0) {
                return None;
            }
            samples.push(x);
        }
    }
    Some(Run {
        samples,
        ms_per_step: ms / steps as f64,
    })
}

fn squeeze(scene: Scene) -> f32 {
    match scene {
        Scene::Poisson => 0.05,
        Scene::Volume => 0.2,
        _ => 0.0,
    }
}

/// Whether the positions after `step` (0-based) are kept.
fn sampled(scene: Scene, step: usize, steps: usize) -> bool {
    match scene {
        Scene::Reference => (step + 1).is_multiple_of(6),
        _ => step + 1 == steps,
    }
}

/// Euler–Bernoulli tip deflection of a clamped beam under its own weight (m), and the
/// measured one: the mean drop of the tip particles. `L` runs from the clamp (halfway
/// between the last pinned and the first free particle) to the bar's end.
fn cantilever_error(model: &Model, x: &[Vec3]) -> f64 {
    let pinned: std::collections::HashSet<u32> = model.pinned.iter().copied().collect();
    let spacing = model.bodies[0].spacing;
    let last_pinned = (0..model.particle_count())
        .filter(|i| pinned.contains(&(*i as u32)))
        .map(|i| model.rest[i].x)
        .fold(f32::MIN, f32::max);
    let clamp = last_pinned + 0.5 * spacing;
    let end = BAR.x;
    let l = (end - clamp) as f64;
    let h = 2.0 * BAR.y as f64;
    // The body's own mass per length (the lattice's volume is close to, not exactly, the box's).
    let mass: f64 = model.mass.iter().map(|&m| m as f64).sum();
    let q = mass / (2.0 * BAR.x as f64) * G_CANTILEVER as f64;
    let Material::Hyperelastic { youngs_modulus, .. } = model.bodies[0].material else {
        return f64::NAN;
    };
    let i = h.powi(4) / 12.0;
    let theory = q * l.powi(4) / (8.0 * youngs_modulus as f64 * i);
    let tip: Vec<usize> = (0..model.particle_count())
        .filter(|&i| model.rest[i].x > end - spacing)
        .collect();
    let drop = tip
        .iter()
        .map(|&i| (model.rest[i].y - x[i].y) as f64)
        .sum::<f64>()
        / tip.len() as f64;
    (drop - theory).abs() / theory
}

/// Mean distance of the particles from the centroid along `axis`.
fn spread(x: &[Vec3], axis: usize) -> f64 {
    let c = x.iter().copied().sum::<Vec3>() / x.len() as f32;
    x.iter()
        .map(|p| (p[axis] - c[axis]).abs() as f64)
        .sum::<f64>()
        / x.len() as f64
}

/// `|ν_measured − ν| / ν` under uniaxial compression: the lateral strain from the mean
/// distance of the particles from the centroid across the load, the axial strain the
/// plates' imposed one.
fn poisson_error(model: &Model, x: &[Vec3]) -> f64 {
    let Material::Hyperelastic { poisson_ratio, .. } = model.bodies[0].material else {
        return f64::NAN;
    };
    // The imposed strain between the plates (the body touches both once squeezed).
    let axial = -squeeze(Scene::Poisson) as f64;
    let lateral =
        0.5 * (spread(x, 0) / spread(&model.rest, 0) + spread(x, 2) / spread(&model.rest, 2)) - 1.0;
    let nu = -lateral / axial;
    (nu - poisson_ratio as f64).abs() / poisson_ratio as f64
}

/// `|V / V₀ − 1|` of the material volume `Σ_c V_c det F_c`.
fn volume_error(model: &Model, x: &[Vec3]) -> f64 {
    let vol = |x: &[Vec3]| -> f64 {
        Solver::deformation_gradients(model, x)
            .iter()
            .zip(&model.cluster_volume)
            .map(|(f, &v)| (v * f.determinant()) as f64)
            .sum()
    };
    (vol(x) / vol(&model.rest) - 1.0).abs()
}

/// RMS distance between two runs' samples, relative to the bar's length.
fn rms_error(a: &[Vec<Vec3>], b: &[Vec<Vec3>]) -> f64 {
    let mut sum = 0.0;
    let mut n = 0usize;
    for (xa, xb) in a.iter().zip(b) {
        for (p, q) in xa.iter().zip(xb) {
            sum += p.distance_squared(*q) as f64;
            n += 1;
        }
    }
    if n == 0 || a.len() != b.len() || a.iter().zip(b).any(|(p, q)| p.len() != q.len()) {
        return f64::NAN;
    }
    (sum / n as f64).sqrt() / (2.0 * BAR.x as f64)
}

/// The reference configuration for `c`'s model (see the module docs).
fn reference_config(c: &Config) -> Config {
    match c.model {
        ModelKind::Hyperelastic => Config {
            backend: Backend::GaussSeidel,
            iterations: 50,
            substeps: 16,
            hierarchy: false,
            ..*c
        },
        ModelKind::ShapeMatching => Config {
            backend: match c.backend {
                Backend::GaussSeidel => Backend::GaussSeidel,
                _ => Backend::Jacobi,
            },
            iterations: 100,
            hierarchy: false,
            ..*c
        },
    }
}

/// One row of the result table.
struct Row {
    config: Config,
    scene: Scene,
    particles: usize,
    ms_per_step: f64,
    /// Relative error; `None` when the run diverged.
    error: Option<f64>,
}

/// The settings grid.
fn grid(quick: bool, cpu: bool, gpu: bool) -> Vec<Config> {
    let mut backends = Vec::new();
    if cpu {
        backends.extend([Backend::GaussSeidel, Backend::Jacobi]);
    }
    if gpu {
        backends.push(Backend::Gpu);
    }
    let (iters, subs, ks): (&[u32], &[u32], &[u32]) = if quick {
        (&[5, 20], &[1], &[16])
    } else {
        (&[5, 10, 20, 40], &[1, 2, 4], &[16, 48])
    };
    let mut out = Vec::new();
    for model in [ModelKind::Hyperelastic, ModelKind::ShapeMatching] {
        for &backend in &backends {
            let base = Config {
                model,
                backend,
                iterations: 10,
                substeps: 1,
                hierarchy: false,
                k: 32,
            };
            for &iterations in iters {
                for &substeps in subs {
                    out.push(Config {
                        iterations,
                        substeps,
                        ..base
                    });
                }
            }
            for &k in ks {
                out.push(Config { k, ..base });
            }
            let hier = if quick { 1 } else { 2 };
            for &iterations in &iters[..iters.len().min(hier)] {
                out.push(Config {
                    iterations,
                    hierarchy: true,
                    ..base
                });
            }
        }
    }
    out
}

/// Marks the Pareto front (no other point is both cheaper and more accurate) of `rows`.
fn pareto(rows: &[&Row]) -> Vec<usize> {
    let mut front = Vec::new();
    for (i, a) in rows.iter().enumerate() {
        let Some(ea) = a.error else { continue };
        let dominated = rows.iter().any(|b| {
            b.error.is_some_and(|eb| {
                b.ms_per_step <= a.ms_per_step
                    && eb <= ea
                    && (b.ms_per_step < a.ms_per_step || eb < ea)
            })
        });
        if !dominated {
            front.push(i);
        }
    }
    front.sort_by(|&i, &j| rows[i].ms_per_step.total_cmp(&rows[j].ms_per_step));
    front
}

fn main() {
    let args = bench::Args::new();
    let quick = args.flag("--quick");
    let out = args.path("--out", "speed_accuracy_out");
    let bar = args.num("--particles", if quick { 200 } else { 1000 });
    let sizes = Sizes {
        bar,
        cube: args.num("--cube", if quick { 343 } else { 1000 }),
        seconds: if quick {
            [0.3, 0.5, 0.4, 0.4]
        } else {
            [1.0, 3.0, 1.5, 1.5]
        },
    };
    let gpu = if args.flag("--no-gpu") {
        None
    } else {
        match headless() {
            Ok(g) => Some(g),
            Err(e) => {
                eprintln!("GPU rows skipped: no adapter ({e})");
                None
            }
        }
    };
    let configs = grid(quick, !args.flag("--no-cpu"), gpu.is_some());
    if let Err(e) = std::fs::create_dir_all(&out) {
        eprintln!("speed_accuracy: cannot create {}: {e}", out.display());
        std::process::exit(1);
    }

    // Converged references, by (scene, model, K, substeps for shape matching).
    let mut references: HashMap<(usize, Config), Vec<Vec<Vec3>>> = HashMap::new();
    let mut rows = Vec::new();
    let started = Instant::now();
    for (i, c) in configs.iter().enumerate() {
        eprintln!(
            "[{:>3}/{}] {:6.0} s  {}",
            i + 1,
            configs.len(),
            started.elapsed().as_secs_f64(),
            c.label()
        );
        for (si, &scene) in SCENES.iter().enumerate() {
            if !scene.applies(c.model) {
                continue;
            }
            let model = build(scene, c, &sizes);
            let seconds = sizes.seconds[si];
            let run = match c.backend {
                Backend::Gpu => gpu
                    .as_ref()
                    .and_then(|g| run_gpu(g, scene, c, &model, seconds)),
                _ => run_cpu(scene, c, &model, seconds),
            };
            let error = run.as_ref().and_then(|r| {
                let last = r.samples.last()?;
                let e = match scene {
                    Scene::Reference => {
                        let rc = reference_config(c);
                        let reference = references.entry((si, rc)).or_insert_with(|| {
                            let rm = build(scene, &rc, &sizes);
                            run_cpu(scene, &rc, &rm, seconds)
                                .map(|r| r.samples)
                                .unwrap_or_default()
                        });
                        rms_error(&r.samples, reference)
                    }
                    Scene::Cantilever => cantilever_error(&model, last),
                    Scene::Poisson => poisson_error(&model, last),
                    Scene::Volume => volume_error(&model, last),
                };
                e.is_finite().then_some(e)
            });
            rows.push(Row {
                config: *c,
                scene,
                particles: model.particle_count(),
                ms_per_step: run.as_ref().map_or(f64::NAN, |r| r.ms_per_step),
                error,
            });
        }
    }

    // Self-check of the hyperelastic reference: twice the substeps and iterations.
    if !quick && !args.flag("--no-cpu") {
        let base = Config {
            model: ModelKind::Hyperelastic,
            backend: Backend::GaussSeidel,
            iterations: 50,
            substeps: 16,
            hierarchy: false,
            k: 32,
        };
        let finer = Config {
            iterations: 100,
            substeps: 32,
            ..base
        };
        let model = build(Scene::Reference, &base, &sizes);
        if let (Some(a), Some(b)) = (
            references.get(&(0, base)),
            run_cpu(Scene::Reference, &finer, &model, sizes.seconds[0]),
        ) {
            println!(
                "Reference self-check: the hyperelastic reference (16 substeps, 50 iterations) \
                 is {:.2e} of the length from one with 32 substeps and 100 iterations.\n",
                rms_error(a, &b.samples)
            );
        }
    }

    // CSV, the table behind the chart.
    let mut csv = String::from(
        "scene,model,backend,iterations,substeps,k,hierarchy,particles,ms_per_step,error\n",
    );
    for r in &rows {
        let c = &r.config;
        let _ = writeln!(
            csv,
            "{},{},{},{},{},{},{},{},{:.4},{}",
            r.scene.name(),
            c.model.name(),
            c.backend.name(),
            c.iterations,
            c.substeps,
            c.k,
            c.hierarchy,
            r.particles,
            r.ms_per_step,
            r.error
                .map_or("diverged".to_string(), |e| format!("{e:.4e}"))
        );
    }
    if let Err(e) = std::fs::write(out.join("speed_accuracy.csv"), csv) {
        eprintln!("speed_accuracy: cannot write the CSV: {e}");
        std::process::exit(1);
    }

    // Markdown: every run, then each panel's Pareto front.
    let mut md = String::new();
    let _ = writeln!(
        md,
        "| model | backend | iterations | substeps | K | hierarchy | ms/step | reference | cantilever | Poisson | volume |\n|---|---|---|---|---|---|---|---|---|---|---|"
    );
    for c in &configs {
        let cell = |s: Scene| -> String {
            match rows.iter().find(|r| r.config == *c && r.scene == s) {
                None => "–".into(),
                Some(r) => r
                    .error
                    .map_or("diverged".into(), |e| format!("{:.2}%", e * 100.0)),
            }
        };
        let ms = rows
            .iter()
            .find(|r| r.config == *c && r.scene == Scene::Reference)
            .map_or(f64::NAN, |r| r.ms_per_step);
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} | {} | {:.3} | {} | {} | {} | {} |",
            c.model.name(),
            c.backend.name(),
            c.iterations,
            c.substeps,
            c.k,
            if c.hierarchy { "on" } else { "off" },
            ms,
            cell(Scene::Reference),
            cell(Scene::Cantilever),
            cell(Scene::Poisson),
            cell(Scene::Volume)
        );
    }
    let mut panels = Vec::new();
    for scene in SCENES {
        let these: Vec<&Row> = rows.iter().filter(|r| r.scene == scene).collect();
        let front = pareto(&these);
        let _ = writeln!(md, "\nPareto front, {}:\n", scene.title());
        for &i in &front {
            let r = these[i];
            let _ = writeln!(
                md,
                "- {:.3} ms/step, error {:.2}%: {}",
                r.ms_per_step,
                r.error.unwrap_or(f64::NAN) * 100.0,
                r.config.label()
            );
        }
        let mut series = Vec::new();
        let mut color = 0;
        for model in [ModelKind::Hyperelastic, ModelKind::ShapeMatching] {
            for backend in [Backend::GaussSeidel, Backend::Jacobi, Backend::Gpu] {
                let points: Vec<(f64, f64)> = these
                    .iter()
                    .filter(|r| r.config.model == model && r.config.backend == backend)
                    .filter_map(|r| Some((r.ms_per_step, r.error?)))
                    .collect();
                if !points.is_empty() {
                    series.push(chart::Series {
                        label: format!("{} {}", model.name(), backend.name()),
                        points,
                        color,
                        markers: true,
                        line: false,
                    });
                }
                color += 1;
            }
        }
        series.push(chart::Series {
            label: "Pareto front".into(),
            points: front
                .iter()
                .filter_map(|&i| Some((these[i].ms_per_step, these[i].error?)))
                .collect(),
            color: 7,
            markers: false,
            line: true,
        });
        panels.push(chart::Panel {
            title: scene.title().into(),
            x_label: "ms per step".into(),
            y_label: "relative error".into(),
            x_log: true,
            y_log: true,
            series,
        });
    }
    print!("{md}");
    if let Err(e) = chart::draw(&out.join("speed_accuracy.png"), &panels, 2, (800, 560)) {
        eprintln!("speed_accuracy: cannot draw the chart: {e}");
        std::process::exit(1);
    }
    eprintln!(
        "wrote {} and {} in {:.0} s",
        out.join("speed_accuracy.csv").display(),
        out.join("speed_accuracy.png").display(),
        started.elapsed().as_secs_f64()
    );
}
