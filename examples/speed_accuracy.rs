//! Speed against accuracy: every method and setting, old and new, CPU and GPU, charted as
//! ms per step against its error, with the Pareto front marked. The errors of panels
//! (b)–(d) are against the independent references of the accuracy study
//! (`examples/support/accuracy.rs`): the quadratic-tetrahedron FEM in f64 for the
//! cantilever, and the homogeneous answer of the material between frictionless plates
//! for the Poisson ratio and the volume.
//!
//! The methods:
//! * the paper's **clusters** (K = 32): shape matching (k = 0.5, a per-substep
//!   stiffness) and the hyperelastic constraints under XPBD, iterated by CPU
//!   Gauss–Seidel (one thread), CPU Jacobi and GPU Jacobi (the render graph's kernels),
//!   with and without the hierarchy;
//! * the **lattice** elements (hexahedra on the sampling lattice, the default body):
//!   XPBD Gauss–Seidel, vertex block descent (Chen et al. 2024) and Newton–multigrid on
//!   the CPU, Newton–multigrid on the GPU (`gpu::lattice::GpuLattice`). For
//!   Newton–multigrid, "iterations" are Newton iterations per substep.
//!
//! The scenes (E, ν as said; 1000 kg/m³; 1/60 s steps):
//! * **(a) reference** — the 24 × 3 × 3 cm bar clamped at one end, released straight
//!   under gravity (9.81 m/s², E = 500 kPa, ν = 0.3) and swinging for 1 s; the RMS
//!   distance of all particles from a converged run of the same discretisation and
//!   material (clusters: CPU Gauss–Seidel, 16 substeps × 50 iterations; shape matching:
//!   the same method at 100 iterations and the same substeps, since k is a per-substep
//!   stiffness; lattice: CPU Newton–multigrid, 16 substeps × 4 Newton iterations),
//!   sampled every 0.1 s, relative to the length. This one is not against FEM: it is
//!   how far a setting is from its own model's converged motion.
//! * **(b) cantilever** — the same bar, E = 100 kPa, gravity 0.2 m/s² (small strain),
//!   damped at twice its first bending frequency and settled for 3 s: the tip's mean
//!   drop against the FEM's at the same points.
//! * **(c) Poisson** — a 6 cm cube, E = 20 kPa, ν = 0.3, squeezed 5% between
//!   frictionless plates: the Poisson ratio measured from the particles' own layers
//!   against the homogeneous answer of the material.
//! * **(d) volume** — the same cube at ν = 0.49 squeezed 20%: the material volume
//!   `Σ V det F` against the homogeneous answer (shape matching too, against the tissue
//!   it stands for).
//!
//! `--paper` adds the cantilever at the paper's sizes (8, 12 and 17 particles across:
//! about 4,096, 13,824 and 38,000 particles) for the real-time and converged settings of
//! each method, each against the same FEM (clusters on the CPU only up to 15,000
//! particles: Gauss–Seidel at 38,000 takes minutes a setting on 2 cores).
//!
//! ms per step is the wall clock of the steps on the CPU. On the GPU it is the GPU's own
//! time of the steps, from timestamps written before and after each batch of steps (the
//! wall clock from submission to completion where the adapter has no timestamp
//! queries); the GPU is kept busy for 0.5 s before each run, so that its clocks are up
//! from idle. The CSV has the GPU's wall clock as well: at ~1,000 particles it sits at
//! the submission's latency floor.
//!
//! Writes `speed_accuracy.csv` (every run) and `speed_accuracy.png` (one log–log panel
//! per scene, plus one per paper size with `--paper`) into the output folder, and
//! Markdown on stdout: every run and each panel's Pareto front.
//!
//! ```text
//! cargo run --release --example speed_accuracy               # the ~1,000-particle grid
//! cargo run --release --example speed_accuracy -- --paper    # and the paper's sizes
//! cargo run --release --example speed_accuracy -- --quick    # a small grid, a minute
//! cargo run --release --example speed_accuracy -- --no-cpu   # the GPU rows only
//! ```
//! Options: `--quick`, `--paper`, `--no-cpu`, `--no-gpu`, `--out DIR` (default
//! `speed_accuracy_out`).
//!
//! `--webgpu-limits` holds the device to WebGPU's default limits (what every browser
//! guarantees; the tests run the example so).

#[path = "support/accuracy.rs"]
mod accuracy;
#[path = "support/bench.rs"]
mod bench;
#[path = "support/chart.rs"]
mod chart;

use accuracy::{
    BAR_E, BAR_GRAVITY, BAR_NU, CUBE_E, Disc, bar_body, bar_fem, bar_fem_tip_at, bar_first_mode,
    bar_tip, cube_body, displacements, layer_strain, material_volume, measured_poisson, plates,
    uniaxial_lateral_stretch,
};
use bevy_tissue::core::colliders::Collider;
use bevy_tissue::core::fem::Solution;
use bevy_tissue::core::hierarchy::HierarchyDesc;
use bevy_tissue::core::model::{Material, Model};
use bevy_tissue::core::solver::{Control, ElementSolver, Method, Solver, SolverSettings, State};
use bevy_tissue::gpu::kernels::lattice::LatticeKernels;
use bevy_tissue::gpu::lattice::GpuLattice;
use bevy_tissue::gpu::profile::GpuProfiler;
use bevy_tissue::gpu::world::{read_buffer, read_vec3};
use bevy_tissue::gpu::{GpuWorld, Headless, NoTiming};
use glam::Vec3;
use std::collections::HashMap;
use std::fmt::Write as _;
use std::time::Instant;

/// Shape matching's stiffness in every scene.
const SM_K: f32 = 0.5;
/// Gravity of the swinging bar, m/s².
const G: f32 = 9.81;
/// Young's modulus of the swinging bar, Pa.
const SWING_E: f32 = 500e3;

/// A method: discretisation, elastic model and solver.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
enum Solve {
    /// Clusters, shape matching, CPU Gauss–Seidel.
    SmGs,
    /// Clusters, shape matching, CPU Jacobi.
    SmJacobi,
    /// Clusters, shape matching, GPU Jacobi.
    SmGpu,
    /// Clusters, hyperelastic XPBD, CPU Gauss–Seidel.
    ClGs,
    /// Clusters, hyperelastic XPBD, CPU Jacobi.
    ClJacobi,
    /// Clusters, hyperelastic XPBD, GPU Jacobi.
    ClGpu,
    /// Lattice, XPBD, CPU Gauss–Seidel.
    LatXpbd,
    /// Lattice, vertex block descent, CPU.
    LatVbd,
    /// Lattice, Newton–multigrid, CPU.
    LatMg,
    /// Lattice, Newton–multigrid, GPU.
    LatMgGpu,
}

const SOLVES: [Solve; 10] = [
    Solve::SmGs,
    Solve::SmJacobi,
    Solve::SmGpu,
    Solve::ClGs,
    Solve::ClJacobi,
    Solve::ClGpu,
    Solve::LatXpbd,
    Solve::LatVbd,
    Solve::LatMg,
    Solve::LatMgGpu,
];

impl Solve {
    fn lattice(self) -> bool {
        matches!(
            self,
            Solve::LatXpbd | Solve::LatVbd | Solve::LatMg | Solve::LatMgGpu
        )
    }
    fn shape_matching(self) -> bool {
        matches!(self, Solve::SmGs | Solve::SmJacobi | Solve::SmGpu)
    }
    fn gpu(self) -> bool {
        matches!(self, Solve::SmGpu | Solve::ClGpu | Solve::LatMgGpu)
    }
    fn discretisation(self) -> &'static str {
        if self.lattice() {
            "lattice"
        } else {
            "clusters"
        }
    }
    fn model(self) -> &'static str {
        if self.shape_matching() {
            "shape matching"
        } else {
            "hyperelastic"
        }
    }
    fn backend(self) -> &'static str {
        match self {
            Solve::SmGs | Solve::ClGs | Solve::LatXpbd => "CPU Gauss-Seidel",
            Solve::SmJacobi | Solve::ClJacobi => "CPU Jacobi",
            Solve::SmGpu | Solve::ClGpu => "GPU Jacobi",
            Solve::LatVbd => "CPU VBD",
            Solve::LatMg => "CPU Newton-MG",
            Solve::LatMgGpu => "GPU Newton-MG",
        }
    }
    fn name(self) -> String {
        format!(
            "{} {} {}",
            self.discretisation(),
            self.model(),
            self.backend()
        )
    }
}

/// One method and setting.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
struct Config {
    solve: Solve,
    iterations: u32,
    substeps: u32,
    hierarchy: bool,
}

impl Config {
    fn new(solve: Solve, iterations: u32, substeps: u32) -> Self {
        Self {
            solve,
            iterations,
            substeps,
            hierarchy: false,
        }
    }

    fn label(&self) -> String {
        format!(
            "{} / {} it / {} sub{}",
            self.solve.name(),
            self.iterations,
            self.substeps,
            if self.hierarchy { " / hierarchy" } else { "" }
        )
    }

    fn disc(&self) -> Disc {
        if self.solve.lattice() {
            Disc::Lattice
        } else {
            Disc::Clusters(32)
        }
    }

    /// The solver settings under `gravity` with velocity damping `damping` (1/s).
    fn settings(&self, gravity: Vec3, damping: f32) -> SolverSettings {
        let gauss_seidel = matches!(self.solve, Solve::SmGs | Solve::ClGs | Solve::LatXpbd);
        SolverSettings {
            dt: 1.0 / 60.0,
            substeps: self.substeps,
            iterations: self.iterations,
            newton_iterations: self.iterations,
            // A row's iterations are Newton iterations of one V-cycle each.
            newton_cycles: 1,
            gravity,
            damping,
            method: if gauss_seidel {
                Method::GaussSeidel
            } else {
                Method::Jacobi
            },
            element_solver: match self.solve {
                Solve::LatVbd => ElementSolver::VertexDescent,
                Solve::LatMg | Solve::LatMgGpu => ElementSolver::Multigrid,
                _ => ElementSolver::Xpbd,
            },
            threads: if gauss_seidel { 1 } else { 0 },
            particle_contacts: false,
            coarse_iterations: if self.hierarchy { 20 } else { 0 },
            ..Default::default()
        }
    }

    /// The converged run of the same model (panel (a)).
    fn reference(&self) -> Config {
        match self.solve {
            Solve::SmGs | Solve::SmJacobi | Solve::SmGpu => Config {
                solve: if self.solve == Solve::SmGs {
                    Solve::SmGs
                } else {
                    Solve::SmJacobi
                },
                iterations: 100,
                hierarchy: false,
                ..*self
            },
            Solve::ClGs | Solve::ClJacobi | Solve::ClGpu => Config::new(Solve::ClGs, 50, 16),
            _ => Config::new(Solve::LatMg, 4, 16),
        }
    }
}

/// The four measurements at ~1,000 particles, and the cantilever at a paper size.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Scene {
    Reference,
    Cantilever,
    Poisson,
    Volume,
    /// The cantilever with this many particles across.
    Paper(u32),
}

const SCENES: [Scene; 4] = [
    Scene::Reference,
    Scene::Cantilever,
    Scene::Poisson,
    Scene::Volume,
];

impl Scene {
    fn name(self) -> String {
        match self {
            Scene::Reference => "reference".into(),
            Scene::Cantilever => "cantilever".into(),
            Scene::Poisson => "poisson".into(),
            Scene::Volume => "volume".into(),
            Scene::Paper(n) => format!("cantilever {n} across"),
        }
    }

    fn title(self, particles: usize) -> String {
        match self {
            Scene::Reference => "(a) RMS distance from a converged run / length".into(),
            Scene::Cantilever => "(b) cantilever tip vs FEM".into(),
            Scene::Poisson => "(c) Poisson ratio vs the homogeneous answer".into(),
            Scene::Volume => "(d) volume at nu = 0.49, 20% squeeze, vs homogeneous".into(),
            Scene::Paper(n) => format!("cantilever tip vs FEM, {n} across (~{particles})"),
        }
    }

    fn applies(self, solve: Solve) -> bool {
        !solve.shape_matching() || matches!(self, Scene::Reference | Scene::Volume)
    }

    fn squeeze(self) -> f32 {
        match self {
            Scene::Poisson => 0.05,
            Scene::Volume => 0.2,
            _ => 0.0,
        }
    }

    fn nu(self) -> f32 {
        match self {
            Scene::Volume => 0.49,
            _ => BAR_NU,
        }
    }

    fn material(self, solve: Solve) -> Material {
        if solve.shape_matching() {
            return Material::ShapeMatching { stiffness: SM_K };
        }
        Material::Hyperelastic {
            youngs_modulus: match self {
                Scene::Reference => SWING_E,
                Scene::Cantilever | Scene::Paper(_) => BAR_E,
                Scene::Poisson | Scene::Volume => CUBE_E,
            },
            poisson_ratio: self.nu(),
        }
    }

    /// Gravity (m/s²) and damping (1/s).
    fn loading(self) -> (Vec3, f32) {
        match self {
            Scene::Reference => (Vec3::new(0.0, -G, 0.0), 1.0),
            Scene::Cantilever | Scene::Paper(_) => (
                Vec3::new(0.0, -BAR_GRAVITY as f32, 0.0),
                (2.0 * bar_first_mode(BAR_E as f64)) as f32,
            ),
            Scene::Poisson | Scene::Volume => (Vec3::ZERO, 5.0),
        }
    }

    /// Whether the positions after `step` (0-based) of `steps` are kept.
    fn sampled(self, step: usize, steps: usize) -> bool {
        match self {
            Scene::Reference => (step + 1).is_multiple_of(6),
            _ => step + 1 == steps,
        }
    }
}

/// Sizes and durations.
#[derive(Clone, Copy)]
struct Sizes {
    /// Particles across the bar's thickness.
    bar: u32,
    /// Particles along the cube's edge.
    cube: u32,
    /// Simulated seconds of the reference, cantilever, Poisson and volume scenes.
    seconds: [f32; 4],
}

impl Sizes {
    fn seconds(&self, scene: Scene) -> f32 {
        match scene {
            Scene::Reference => self.seconds[0],
            Scene::Cantilever | Scene::Paper(_) => self.seconds[1],
            Scene::Poisson => self.seconds[2],
            Scene::Volume => self.seconds[3],
        }
    }
}

/// A scene's body.
fn build(scene: Scene, c: &Config, sizes: &Sizes) -> Model {
    let hierarchy = c.hierarchy.then_some(HierarchyDesc {
        // Small bodies: coarse levels down to 32 particles, so the hierarchy is exercised.
        min_particles: 32,
        ..Default::default()
    });
    let material = scene.material(c.solve);
    let model = match scene {
        Scene::Reference | Scene::Cantilever => bar_body(c.disc(), sizes.bar, material, hierarchy),
        Scene::Paper(n) => bar_body(c.disc(), n, material, hierarchy),
        Scene::Poisson | Scene::Volume => cube_body(c.disc(), sizes.cube, material, hierarchy),
    };
    model.unwrap_or_else(|e| {
        eprintln!(
            "speed_accuracy: cannot build the {} body: {e}",
            scene.name()
        );
        std::process::exit(1)
    })
}

/// What a run produced: positions at the sample times and its cost.
struct Run {
    samples: Vec<Vec<Vec3>>,
    /// ms per step: the CPU's wall clock, or the GPU's own time (timestamps; its wall
    /// clock where the adapter has none).
    ms_per_step: f64,
    /// The GPU's wall clock per step from submission to completion (ms); `None` on the
    /// CPU.
    wall_ms_per_step: Option<f64>,
}

/// The compression plates of `scene` at `step` of `steps`, or none.
fn colliders(scene: Scene, model: &Model, step: usize, steps: usize) -> Vec<Collider> {
    if scene.squeeze() > 0.0 {
        plates(model, scene.squeeze(), step, steps)
    } else {
        vec![]
    }
}

/// Steps a scene on the CPU. `None` when the solver reported divergence.
fn run_cpu(scene: Scene, c: &Config, model: &Model, seconds: f32) -> Option<Run> {
    let (gravity, damping) = scene.loading();
    let mut solver = Solver::new(model, c.settings(gravity, damping)).ok()?;
    let mut state = State::new(model);
    let steps = (seconds * 60.0).round() as usize;
    let mut samples = Vec::new();
    let mut ms = 0.0;
    for step in 0..steps {
        let control = Control {
            colliders: colliders(scene, model, step, steps),
        };
        let t = Instant::now();
        solver.step(model, &mut state, &control).ok()?;
        ms += t.elapsed().as_secs_f64() * 1e3;
        if scene.sampled(step, steps) {
            samples.push(state.x.clone());
        }
    }
    Some(Run {
        samples,
        ms_per_step: ms / steps as f64,
        wall_ms_per_step: None,
    })
}

/// The GPU: the render graph's cluster kernels and the lattice kernels, and a small
/// world that keeps the GPU busy before each run.
struct Gpu {
    g: Headless,
    lattice: LatticeKernels,
    warm: GpuLattice,
}

impl Gpu {
    /// Steps the warm-up world for [`bench::GPU_WARM_UP_S`], so that the GPU's clocks are
    /// up from idle when a run starts (between runs the host builds models and measures
    /// errors).
    fn warm_up(&self) {
        bench::keep_gpu_busy(bench::GPU_WARM_UP_S, || {
            let mut enc = self.g.device.create_command_encoder(&Default::default());
            self.warm.record(&mut enc, &self.lattice, 10, None);
            self.g.queue.submit([enc.finish()]);
            drop(read_buffer(
                &self.g.device,
                &self.g.queue,
                self.warm.pos_buffer(),
                0,
                16,
            ));
        });
    }
}

/// A world on the GPU of either kind.
enum World {
    Clusters(Box<GpuWorld>),
    Lattice(Box<GpuLattice>),
}

/// Steps a scene on the GPU (the same model and settings): batches of steps without
/// per-step input in one submission, up to the next sample.
fn run_gpu(gpu: &Gpu, scene: Scene, c: &Config, model: &Model, seconds: f32) -> Option<Run> {
    let g = &gpu.g;
    let (gravity, damping) = scene.loading();
    let settings = c.settings(gravity, damping);
    let mut state = State::new(model);
    let mut world = if c.solve.lattice() {
        World::Lattice(Box::new(
            GpuLattice::new(&g.device, &gpu.lattice, model, &state, &settings).ok()?,
        ))
    } else {
        World::Clusters(Box::new(
            GpuWorld::new(&g.device, &g.kernels, model, &state, settings, 0).ok()?,
        ))
    };
    let steps = (seconds * 60.0).round() as usize;
    let squeezed = scene.squeeze() > 0.0;
    let n = model.particle_count();
    let mut samples = Vec::new();
    let mut ms = 0.0;
    let mut wall = 0.0;
    let mut stamps = GpuProfiler::new(&g.device, &g.queue, 2);
    gpu.warm_up();
    let mut step = 0;
    while step < steps {
        let batch = if squeezed {
            1
        } else {
            (1..=steps - step)
                .find(|b| scene.sampled(step + b - 1, steps))
                .unwrap_or(steps - step)
        };
        let cols = colliders(scene, model, step, steps);
        let mut enc = g.device.create_command_encoder(&Default::default());
        if let Some(p) = stamps.as_mut() {
            p.mark(&mut enc);
        }
        match &mut world {
            World::Clusters(w) => {
                if squeezed {
                    w.set_colliders(&g.queue, &cols).ok()?;
                }
                w.write_params(&g.queue);
                w.record_steps(&mut enc, &g.kernels, batch as u32, &mut NoTiming);
            }
            World::Lattice(w) => {
                if squeezed {
                    w.set_colliders(&g.queue, &cols).ok()?;
                }
                w.record(&mut enc, &gpu.lattice, batch as u32, None);
            }
        }
        if let Some(p) = stamps.as_mut() {
            p.mark(&mut enc);
            p.resolve(&mut enc);
        }
        let t = Instant::now();
        g.queue.submit([enc.finish()]);
        // A small read waits for everything submitted.
        match &world {
            World::Clusters(w) => drop(read_vec3(&g.device, &g.queue, w.positions(), 1)),
            World::Lattice(w) => drop(read_buffer(&g.device, &g.queue, w.pos_buffer(), 0, 16)),
        }
        wall += t.elapsed().as_secs_f64() * 1e3;
        ms += match stamps.as_mut().map(|p| p.read_marks(&g.device, &g.queue)) {
            Some(m) if m.len() == 2 => m[1] - m[0],
            _ => t.elapsed().as_secs_f64() * 1e3,
        };
        step += batch;
        if scene.sampled(step - 1, steps) {
            let x = match &world {
                World::Clusters(w) => read_vec3(&g.device, &g.queue, w.positions(), n as u32),
                World::Lattice(w) => {
                    w.download(&g.device, &g.queue, &mut state);
                    state.x.clone()
                }
            };
            if !x.iter().all(|p| p.is_finite() && p.length() < 100.0) {
                return None;
            }
            samples.push(x);
        }
    }
    Some(Run {
        samples,
        ms_per_step: ms / steps as f64,
        wall_ms_per_step: Some(wall / steps as f64),
    })
}

/// The relative error of the tip's drop against the FEM's at the same points.
fn cantilever_error(model: &Model, x: &[Vec3], fem: &Solution) -> f64 {
    let tip = bar_tip(model, &displacements(model, x));
    let reference = bar_fem_tip_at(fem, model);
    (tip / reference - 1.0).abs()
}

/// `|ν_measured − ν_ref| / ν_ref`, `ν_ref` the homogeneous answer at the measured axial
/// strain.
fn poisson_error(scene: Scene, model: &Model, x: &[Vec3]) -> f64 {
    let axial = layer_strain(model, x, 1);
    let b = uniaxial_lateral_stretch(CUBE_E as f64, scene.nu() as f64, 1.0 + axial);
    let reference = -(b - 1.0) / axial;
    (measured_poisson(model, x) / reference - 1.0).abs()
}

/// `|V / V₀ − V_ref / V₀|`, `V_ref` the homogeneous answer at the measured axial strain.
fn volume_error(scene: Scene, model: &Model, x: &[Vec3]) -> f64 {
    let axial = layer_strain(model, x, 1);
    let b = uniaxial_lateral_stretch(CUBE_E as f64, scene.nu() as f64, 1.0 + axial);
    let v = material_volume(model, x) / material_volume(model, &model.rest);
    (v - (1.0 + axial) * b * b).abs()
}

/// RMS distance between two runs' samples, relative to the bar's length.
fn rms_error(a: &[Vec<Vec3>], b: &[Vec<Vec3>]) -> f64 {
    if a.is_empty() || a.len() != b.len() || a.iter().zip(b).any(|(p, q)| p.len() != q.len()) {
        return f64::NAN;
    }
    let mut sum = 0.0;
    let mut n = 0usize;
    for (xa, xb) in a.iter().zip(b) {
        for (p, q) in xa.iter().zip(xb) {
            sum += p.distance_squared(*q) as f64;
            n += 1;
        }
    }
    (sum / n as f64).sqrt() / accuracy::BAR_LENGTH
}

/// One row of the result table.
struct Row {
    config: Config,
    scene: Scene,
    particles: usize,
    ms_per_step: f64,
    /// The GPU's wall clock per step (ms); `None` on the CPU or where the run failed.
    wall_ms_per_step: Option<f64>,
    /// Relative error; `None` when the run diverged.
    error: Option<f64>,
}

/// The settings grid at ~1,000 particles.
fn grid(quick: bool, cpu: bool, gpu: bool) -> Vec<Config> {
    let mut out = Vec::new();
    let on = |s: Solve| if s.gpu() { gpu } else { cpu };
    let its: &[u32] = if quick { &[5, 20] } else { &[5, 10, 20, 40] };
    let subs: &[u32] = if quick { &[1] } else { &[1, 4] };
    for solve in [Solve::ClGs, Solve::ClJacobi, Solve::ClGpu] {
        for &s in subs {
            for &i in its {
                out.push(Config::new(solve, i, s));
            }
        }
        out.push(Config {
            hierarchy: true,
            ..Config::new(solve, 10, 1)
        });
    }
    for solve in [Solve::SmGs, Solve::SmJacobi, Solve::SmGpu] {
        for &i in its {
            out.push(Config::new(solve, i, 1));
        }
    }
    let xpbd: &[(u32, u32)] = if quick {
        &[(10, 1)]
    } else {
        &[(10, 1), (40, 1), (10, 4), (40, 4)]
    };
    for solve in [Solve::LatXpbd, Solve::LatVbd] {
        for &(i, s) in xpbd {
            out.push(Config::new(solve, i, s));
        }
    }
    let newton: &[(u32, u32)] = if quick {
        &[(1, 1), (2, 1)]
    } else {
        &[(1, 1), (2, 1), (4, 1), (2, 2)]
    };
    for solve in [Solve::LatMg, Solve::LatMgGpu] {
        for &(i, s) in newton {
            out.push(Config::new(solve, i, s));
        }
    }
    out.retain(|c| on(c.solve));
    out
}

/// The settings run at the paper's sizes: each method's real-time and converged ones.
fn paper_grid(cpu: bool, gpu: bool) -> Vec<Config> {
    let mut out = vec![
        Config::new(Solve::ClGpu, 10, 1),
        Config::new(Solve::ClGpu, 40, 4),
        Config::new(Solve::LatMgGpu, 1, 1),
        Config::new(Solve::LatMgGpu, 2, 1),
        Config::new(Solve::LatMgGpu, 4, 1),
        Config::new(Solve::ClGs, 20, 4),
        Config::new(Solve::LatMg, 2, 1),
    ];
    out.retain(|c| if c.solve.gpu() { gpu } else { cpu });
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

fn fail(what: &str, e: impl std::fmt::Display) -> ! {
    eprintln!("speed_accuracy: {what}: {e}");
    std::process::exit(1)
}

/// Runs `config` on `scene` and measures its error.
struct Runner<'a> {
    gpu: Option<&'a Gpu>,
    sizes: Sizes,
    fem: &'a Solution,
    /// Converged runs of panel (a), by reference configuration.
    references: HashMap<Config, Vec<Vec<Vec3>>>,
}

impl Runner<'_> {
    fn measure(&mut self, scene: Scene, c: &Config) -> Row {
        let model = build(scene, c, &self.sizes);
        let seconds = self.sizes.seconds(scene);
        let run = if c.solve.gpu() {
            self.gpu.and_then(|g| run_gpu(g, scene, c, &model, seconds))
        } else {
            run_cpu(scene, c, &model, seconds)
        };
        let error = run.as_ref().and_then(|r| {
            let last = r.samples.last()?;
            let e = match scene {
                Scene::Reference => {
                    let rc = c.reference();
                    let sizes = self.sizes;
                    let reference = self.references.entry(rc).or_insert_with(|| {
                        eprintln!("         reference: {}", rc.label());
                        let rm = build(scene, &rc, &sizes);
                        run_cpu(scene, &rc, &rm, seconds)
                            .map(|r| r.samples)
                            .unwrap_or_default()
                    });
                    rms_error(&r.samples, reference)
                }
                Scene::Cantilever | Scene::Paper(_) => cantilever_error(&model, last, self.fem),
                Scene::Poisson => poisson_error(scene, &model, last),
                Scene::Volume => volume_error(scene, &model, last),
            };
            e.is_finite().then_some(e)
        });
        Row {
            config: *c,
            scene,
            particles: model.particle_count(),
            ms_per_step: run.as_ref().map_or(f64::NAN, |r| r.ms_per_step),
            wall_ms_per_step: run.as_ref().and_then(|r| r.wall_ms_per_step),
            error,
        }
    }
}

/// Series of one panel: one per method, and the Pareto front.
fn panel(title: String, rows: &[&Row], md: &mut String) -> chart::Panel {
    let front = pareto(rows);
    let _ = writeln!(md, "\nPareto front, {title}:\n");
    for &i in &front {
        let r = rows[i];
        let _ = writeln!(
            md,
            "- {:.3} ms/step, error {:.2}%: {}",
            r.ms_per_step,
            r.error.unwrap_or(f64::NAN) * 100.0,
            r.config.label()
        );
    }
    let mut series = Vec::new();
    for (color, solve) in SOLVES.iter().enumerate() {
        let points: Vec<(f64, f64)> = rows
            .iter()
            .filter(|r| r.config.solve == *solve)
            .filter_map(|r| Some((r.ms_per_step, r.error?)))
            .collect();
        if !points.is_empty() {
            series.push(chart::Series {
                label: solve.name(),
                points,
                color,
                markers: true,
                line: false,
            });
        }
    }
    series.push(chart::Series {
        label: "Pareto front".into(),
        points: front
            .iter()
            .filter_map(|&i| Some((rows[i].ms_per_step, rows[i].error?)))
            .collect(),
        color: SOLVES.len(),
        markers: false,
        line: true,
    });
    chart::Panel {
        title,
        x_label: "ms per step".into(),
        y_label: "relative error".into(),
        x_log: true,
        y_log: true,
        series,
    }
}

fn main() {
    let args = bench::Args::new();
    let quick = args.flag("--quick");
    let out = args.path("--out", "speed_accuracy_out");
    let sizes = Sizes {
        bar: if quick { 3 } else { 5 },
        cube: if quick { 6 } else { 10 },
        seconds: if quick {
            [0.3, 0.5, 0.4, 0.4]
        } else {
            [1.0, 3.0, 1.5, 1.5]
        },
    };
    let gpu = if args.flag("--no-gpu") {
        None
    } else {
        match bench::open_gpu().and_then(|g| {
            let lattice = LatticeKernels::new(&g.device).map_err(|e| e.to_string())?;
            let c = Config::new(Solve::LatMgGpu, 1, 1);
            let model = build(Scene::Cantilever, &c, &sizes);
            let state = State::new(&model);
            let warm = GpuLattice::new(
                &g.device,
                &lattice,
                &model,
                &state,
                &c.settings(Vec3::ZERO, 0.0),
            )
            .map_err(|e| e.to_string())?;
            Ok(Gpu { g, lattice, warm })
        }) {
            Ok(g) => Some(g),
            Err(e) => {
                eprintln!("GPU rows skipped: no adapter ({e})");
                None
            }
        }
    };
    if let Some(g) = &gpu {
        println!("GPU: {}\n", g.g.adapter);
    }
    let cpu = !args.flag("--no-cpu");
    let configs = grid(quick, cpu, gpu.is_some());
    if let Err(e) = std::fs::create_dir_all(&out) {
        fail(&format!("cannot create {}", out.display()), e);
    }
    let started = Instant::now();
    let cells = if quick { 2 } else { 8 };
    eprintln!(
        "FEM reference of the cantilever ({}×{cells}×{cells} cells) ...",
        8 * cells
    );
    let fem = bar_fem(cells).unwrap_or_else(|e| fail("the FEM reference", e));

    let mut runner = Runner {
        gpu: gpu.as_ref(),
        sizes,
        fem: &fem,
        references: HashMap::new(),
    };
    let mut rows = Vec::new();
    for (i, c) in configs.iter().enumerate() {
        eprintln!(
            "[{:>3}/{}] {:6.0} s  {}",
            i + 1,
            configs.len(),
            started.elapsed().as_secs_f64(),
            c.label()
        );
        for scene in SCENES {
            if scene.applies(c.solve) {
                rows.push(runner.measure(scene, c));
            }
        }
    }
    let paper_sizes: &[u32] = if args.flag("--paper") {
        &[8, 12, 17]
    } else {
        &[]
    };
    let paper = paper_grid(cpu, gpu.is_some());
    for &across in paper_sizes {
        for c in &paper {
            let scene = Scene::Paper(across);
            let model = build(scene, c, &sizes);
            if c.solve == Solve::ClGs && model.particle_count() > 15_000 {
                eprintln!(
                    "skipped {} at {} particles (minutes on this CPU)",
                    c.label(),
                    model.particle_count()
                );
                continue;
            }
            eprintln!(
                "[paper {across} across] {:6.0} s  {}",
                started.elapsed().as_secs_f64(),
                c.label()
            );
            rows.push(runner.measure(scene, c));
        }
    }

    // CSV, the table behind the chart.
    let mut csv = String::from(
        "scene,discretisation,model,backend,iterations,substeps,hierarchy,particles,ms_per_step,gpu_wall_ms_per_step,error\n",
    );
    for r in &rows {
        let c = &r.config;
        let _ = writeln!(
            csv,
            "{},{},{},{},{},{},{},{},{:.4},{},{}",
            r.scene.name(),
            c.solve.discretisation(),
            c.solve.model(),
            c.solve.backend(),
            c.iterations,
            c.substeps,
            c.hierarchy,
            r.particles,
            r.ms_per_step,
            r.wall_ms_per_step
                .map_or(String::new(), |w| format!("{w:.4}")),
            r.error
                .map_or("diverged".to_string(), |e| format!("{e:.4e}"))
        );
    }
    if let Err(e) = std::fs::write(out.join("speed_accuracy.csv"), csv) {
        fail("cannot write the CSV", e);
    }

    // Markdown: every run at ~1,000 particles, the paper's sizes, each panel's front.
    let mut md = String::new();
    let _ = writeln!(
        md,
        "| discretisation | model | backend | iterations | substeps | hierarchy | ms/step (a) | (a) reference | (b) cantilever vs FEM | (c) Poisson | (d) volume |\n|---|---|---|---|---|---|---|---|---|---|---|"
    );
    let cell = |c: &Config, s: Scene| -> String {
        match rows.iter().find(|r| r.config == *c && r.scene == s) {
            None => "–".into(),
            Some(r) => r
                .error
                .map_or("diverged".into(), |e| format!("{:.2}%", e * 100.0)),
        }
    };
    for c in &configs {
        let ms = rows
            .iter()
            .find(|r| r.config == *c && r.scene == Scene::Reference)
            .map_or(f64::NAN, |r| r.ms_per_step);
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} | {} | {:.3} | {} | {} | {} | {} |",
            c.solve.discretisation(),
            c.solve.model(),
            c.solve.backend(),
            c.iterations,
            c.substeps,
            if c.hierarchy { "on" } else { "off" },
            ms,
            cell(c, Scene::Reference),
            cell(c, Scene::Cantilever),
            cell(c, Scene::Poisson),
            cell(c, Scene::Volume)
        );
    }
    if !paper_sizes.is_empty() {
        let _ = writeln!(
            md,
            "\nThe cantilever at the paper's sizes, tip against the FEM:\n\n| across | particles | method | iterations × substeps | ms/step | error |\n|---|---|---|---|---|---|"
        );
        for r in rows.iter().filter(|r| matches!(r.scene, Scene::Paper(_))) {
            let Scene::Paper(n) = r.scene else { continue };
            let _ = writeln!(
                md,
                "| {n} | {} | {} | {} × {} | {:.3} | {} |",
                r.particles,
                r.config.solve.name(),
                r.config.iterations,
                r.config.substeps,
                r.ms_per_step,
                r.error
                    .map_or("diverged".into(), |e| format!("{:.2}%", e * 100.0))
            );
        }
    }
    let mut panels = Vec::new();
    let mut scenes: Vec<Scene> = SCENES.to_vec();
    scenes.extend(paper_sizes.iter().map(|&n| Scene::Paper(n)));
    for scene in scenes {
        let these: Vec<&Row> = rows.iter().filter(|r| r.scene == scene).collect();
        if these.is_empty() {
            continue;
        }
        let particles = these.iter().map(|r| r.particles).max().unwrap_or(0);
        panels.push(panel(scene.title(particles), &these, &mut md));
    }
    print!("{md}");
    if let Err(e) = chart::draw(&out.join("speed_accuracy.png"), &panels, 2, (800, 560)) {
        fail("cannot draw the chart", e);
    }
    eprintln!(
        "wrote {} and {} in {:.0} s",
        out.join("speed_accuracy.csv").display(),
        out.join("speed_accuracy.png").display(),
        started.elapsed().as_secs_f64()
    );
}
