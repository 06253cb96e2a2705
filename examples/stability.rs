//! Stability where methods fail (SPEC §6): scenarios that break PBD solvers, run with
//! every method, and a map of where each one recovers, loses (or gains) volume, stays
//! inverted or deformed, or blows up.
//!
//! Methods (rows): shape matching (k = 0.5) and hyperelastic XPBD (fixed-corotated,
//! E = 100 kPa, ν = 0.45), each with CPU Gauss–Seidel and CPU Jacobi; hyperelastic with a
//! two-level hierarchy (Müller 2008, Jacobi); the same material on the lattice
//! discretisation (hexahedra on the sampling lattice: `Discretisation::Lattice`) with XPBD
//! Gauss–Seidel and with Newton–multigrid (`ElementSolver::Multigrid`); and, where an
//! adapter exists, the GPU world (Jacobi on the GPU) with both cluster materials and
//! Newton–multigrid on the GPU (`gpu::lattice::GpuLattice`, the lattice material). The
//! lattice rows have no `K = 4` column (no neighbourhoods) and no coplanar plate (a plate
//! thinner than a cell has no cell); they are measured on their own hexahedra.
//!
//! Scenarios (columns), on a brick of 12 × 8 × 8 cm sampled with `--particles` particles
//! (a plate for the coplanar one). Gravity is off, so the rest shape is the only
//! equilibrium and any lasting deformation is the method's doing (`--gravity` puts the
//! bricks on a ground plane under gravity instead: then the iteration-limited stiffness
//! of each method shows as sag and volume loss, an accuracy matter more than stability):
//! * `baseline` — dt = 1/60 s, 10 iterations, K = 32, released squashed to 50% height;
//! * `large dt` — dt = 1/10 s; `stiff` — E = 10 MPa, or k = 1; `1 iteration`;
//!   `K = 4`; `over-relaxed` — Jacobi ω = 1.9 (Gauss–Seidel has no ω in this solver:
//!   "n/a") — each the baseline with that one change;
//! * `squashed flat` (5% of its height), `inverted` (mirrored through a plane, det F = −1),
//!   `stretched 4×` (300% strain along its length), `impact 30 m/s` (thrown at a ground
//!   plane 1 cm below it), all released with the baseline settings;
//! * `coplanar` — a plate one particle thick (every cluster is flat), released bent.
//!
//! Each cell runs `--seconds` of simulated time (steps = seconds / dt), then classifies
//! the end state by its volume and its shape error:
//! * volume: `V = Σ_c V_c det F_c` over the clusters of a measuring model (the same
//!   particles with K = 32, so every scenario is measured alike; `F_c` its clusters'
//!   least-squares deformation gradients, `V_c` their shares of the rest volume). A flat
//!   cluster (the plate) has no thickness to measure: it counts its area ratio
//!   `|F a × F b|` (a, b spanning its plane) instead, so the plate reports area change;
//! * shape error: RMS distance of the particles from the rest shape after the best rigid
//!   alignment (mass-weighted), as a fraction of the body's size (bounding-box diagonal).
//!
//! Outcomes, in the order they are tested:
//! * `blows up` — the CPU solver returned `Diverged` (NaN, or a particle faster than
//!   `max_speed` = 500 m/s; it restores the state before the step, which is what is
//!   measured), or the GPU flagged the body (it holds diverged particles);
//! * `inverted` — the signed volume is negative: the body ends inside out;
//! * `volume lost` / `volume gained` — volume off by more than 5%;
//! * `stuck` — volume within 5% but the shape error above 3% of the body size;
//! * `recovers` — volume within 5% and shape error within 3%.
//!
//! Markdown on stdout (the map, then shape errors), `stability.json` and `stability.png`
//! (the map: colour = outcome, text = volume change and shape error) in the output folder.
//!
//! ```text
//! cargo run --release --example stability               # ~1,500 particles, 3 s each
//! cargo run --release --example stability -- --quick    # ~160 particles, 1 s each
//! cargo run --release --example stability -- --gravity --no-gpu
//! ```
//! Options: `--particles N` (brick, default 1500; quick 160), `--seconds S` (simulated
//! time per cell, default 3; quick 1), `--stiffness K` (shape matching, default 0.5),
//! `--youngs E` (Pa, default 1e5), `--gravity`, `--no-cpu`, `--no-gpu`, `--out DIR`
//! (default `stability_out`). CPU cells run in parallel, one per core, each solver on one
//! thread; GPU cells meanwhile, one at a time.
//!
//! `--webgpu-limits` holds the device to WebGPU's default limits (what every browser
//! guarantees; the tests run the example so).

#[path = "support/accuracy.rs"]
mod accuracy;
#[path = "support/bench.rs"]
mod bench;
#[path = "support/chart.rs"]
mod chart;

use bevy_tissue::core::TissueError;
use bevy_tissue::core::colliders::Collider;
use bevy_tissue::core::constraints::sym_eigen;
use bevy_tissue::core::diagnose;
use bevy_tissue::core::element::element_gradient;
use bevy_tissue::core::hierarchy::HierarchyDesc;
use bevy_tissue::core::mesh::TriMesh;
use bevy_tissue::core::model::{BodyDesc, Discretisation, Material, Model};
use bevy_tissue::core::procedural;
use bevy_tissue::core::sampling::Resolution;
use bevy_tissue::core::solver::{Control, ElementSolver, Method, Solver, SolverSettings, State};
use bevy_tissue::gpu::kernels::lattice::LatticeKernels;
use bevy_tissue::gpu::lattice::GpuLattice;
use bevy_tissue::gpu::world::{read_u32, read_vec3};
use bevy_tissue::gpu::{GpuWorld, Headless, NoTiming};
use glam::Vec3;
use std::fmt::Write as _;
use std::path::PathBuf;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

/// Volume off by more than this fraction is `volume lost` / `volume gained`.
const VOLUME_TOL: f32 = 0.05;
/// Shape error (fraction of the body size) above which a body has not recovered.
const SHAPE_TOL: f32 = 0.03;
/// The over-relaxed Jacobi's ω.
const OMEGA: f32 = 1.9;
/// Height the baseline (and every scenario that only changes settings) starts at.
const SQUASH: f32 = 0.5;
/// Impact speed, m/s.
const IMPACT_SPEED: f32 = 30.0;
/// Half extents of the brick, m.
const BRICK: Vec3 = Vec3::new(0.06, 0.04, 0.04);
/// Half extents of the plate (thinner than its lattice spacing: one particle layer), m.
const PLATE: Vec3 = Vec3::new(0.08, 0.003, 0.08);

/// A column of the map: what is done to the body or to the solver.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Scenario {
    Baseline,
    LargeDt,
    Stiff,
    OneIteration,
    SmallK,
    OverRelaxed,
    Flat,
    Inverted,
    Stretched,
    Impact,
    Coplanar,
}

impl Scenario {
    const ALL: [Scenario; 11] = [
        Scenario::Baseline,
        Scenario::LargeDt,
        Scenario::Stiff,
        Scenario::OneIteration,
        Scenario::SmallK,
        Scenario::OverRelaxed,
        Scenario::Flat,
        Scenario::Inverted,
        Scenario::Stretched,
        Scenario::Impact,
        Scenario::Coplanar,
    ];

    /// Identifier in the JSON.
    fn key(self) -> &'static str {
        match self {
            Scenario::Baseline => "baseline",
            Scenario::LargeDt => "large_dt",
            Scenario::Stiff => "stiff",
            Scenario::OneIteration => "one_iteration",
            Scenario::SmallK => "small_k",
            Scenario::OverRelaxed => "over_relaxed",
            Scenario::Flat => "squashed_flat",
            Scenario::Inverted => "inverted",
            Scenario::Stretched => "stretched",
            Scenario::Impact => "impact",
            Scenario::Coplanar => "coplanar",
        }
    }

    /// Column header (`\n` breaks lines in the chart).
    fn label(self) -> String {
        match self {
            Scenario::Baseline => format!("baseline\n({:.0}% height)", SQUASH * 100.0),
            Scenario::LargeDt => "large dt\n(1/10 s)".into(),
            Scenario::Stiff => "stiff\n(10 MPa / k = 1)".into(),
            Scenario::OneIteration => "1 iteration".into(),
            Scenario::SmallK => "K = 4".into(),
            Scenario::OverRelaxed => format!("over-relaxed\n(ω = {OMEGA})"),
            Scenario::Flat => "squashed flat\n(5% height)".into(),
            Scenario::Inverted => "inverted\n(mirrored)".into(),
            Scenario::Stretched => "stretched 4×\n(+300%)".into(),
            Scenario::Impact => format!("impact\n({IMPACT_SPEED} m/s)"),
            Scenario::Coplanar => "coplanar\n(1-layer plate)".into(),
        }
    }

    /// What the scenario does, for the legend.
    fn what(self) -> String {
        match self {
            Scenario::Baseline => format!(
                "dt = 1/60 s, 10 iterations, K = 32, released squashed to {:.0}% of its height",
                SQUASH * 100.0
            ),
            Scenario::LargeDt => "the baseline with dt = 1/10 s".into(),
            Scenario::Stiff => {
                "the baseline with E = 10 MPa (hyperelastic) or k = 1 (shape matching)".into()
            }
            Scenario::OneIteration => "the baseline with 1 iteration per substep".into(),
            Scenario::SmallK => "the baseline with K = 4 neighbours per cluster".into(),
            Scenario::OverRelaxed => format!(
                "the baseline with Jacobi relaxation ω = {OMEGA} (Gauss–Seidel: n/a, it has no ω)"
            ),
            Scenario::Flat => "released from 5% of its height (squashed flat)".into(),
            Scenario::Inverted => {
                "released mirrored through its mid-plane x = 0 (det F = −1 everywhere)".into()
            }
            Scenario::Stretched => "released at 4× its length (300% strain)".into(),
            Scenario::Impact => format!(
                "thrown at {IMPACT_SPEED} m/s onto a ground plane 1 cm below it (friction 0.5)"
            ),
            Scenario::Coplanar => {
                "a plate one particle thick (every cluster coplanar), released bent; volume = area"
                    .into()
            }
        }
    }

    /// Whether the scenario starts from the baseline's mild squash.
    fn settings_only(self) -> bool {
        matches!(
            self,
            Scenario::Baseline
                | Scenario::LargeDt
                | Scenario::Stiff
                | Scenario::OneIteration
                | Scenario::SmallK
                | Scenario::OverRelaxed
        )
    }
}

/// A row of the map: elastic model, solver method, hierarchy, backend.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Row {
    SmGs,
    SmJacobi,
    HeGs,
    HeJacobi,
    HeHierarchy,
    LatticeGs,
    LatticeMg,
    GpuSm,
    GpuHe,
    GpuLatticeMg,
}

impl Row {
    const CPU: [Row; 7] = [
        Row::SmGs,
        Row::SmJacobi,
        Row::HeGs,
        Row::HeJacobi,
        Row::HeHierarchy,
        Row::LatticeGs,
        Row::LatticeMg,
    ];
    const GPU: [Row; 3] = [Row::GpuSm, Row::GpuHe, Row::GpuLatticeMg];

    /// Identifier in the JSON.
    fn key(self) -> &'static str {
        match self {
            Row::SmGs => "sm_gs",
            Row::SmJacobi => "sm_jacobi",
            Row::HeGs => "he_gs",
            Row::HeJacobi => "he_jacobi",
            Row::HeHierarchy => "he_hierarchy_jacobi",
            Row::LatticeGs => "lattice_xpbd_gs",
            Row::LatticeMg => "lattice_newton_mg",
            Row::GpuSm => "gpu_sm",
            Row::GpuHe => "gpu_he",
            Row::GpuLatticeMg => "gpu_lattice_newton_mg",
        }
    }

    /// Row label.
    fn name(self) -> &'static str {
        match self {
            Row::SmGs => "shape matching, Gauss–Seidel",
            Row::SmJacobi => "shape matching, Jacobi",
            Row::HeGs => "hyperelastic, Gauss–Seidel",
            Row::HeJacobi => "hyperelastic, Jacobi",
            Row::HeHierarchy => "hyperelastic + hierarchy, Jacobi",
            Row::LatticeGs => "lattice hexahedra, XPBD Gauss–Seidel",
            Row::LatticeMg => "lattice hexahedra, Newton–multigrid",
            Row::GpuSm => "GPU Jacobi, shape matching",
            Row::GpuHe => "GPU Jacobi, hyperelastic",
            Row::GpuLatticeMg => "GPU lattice hexahedra, Newton–multigrid",
        }
    }

    /// Shape matching (else hyperelastic).
    fn shape_matching(self) -> bool {
        matches!(self, Row::SmGs | Row::SmJacobi | Row::GpuSm)
    }

    /// CPU method (the GPU always runs Jacobi).
    fn method(self) -> Method {
        match self {
            Row::SmGs | Row::HeGs | Row::LatticeGs | Row::LatticeMg | Row::GpuLatticeMg => {
                Method::GaussSeidel
            }
            _ => Method::Jacobi,
        }
    }

    /// The lattice discretisation (hexahedral elements on the sampling lattice), else the
    /// paper's clusters.
    fn lattice(self) -> bool {
        matches!(self, Row::LatticeGs | Row::LatticeMg | Row::GpuLatticeMg)
    }

    /// Runs on the GPU (the world's kernels, or the lattice's).
    fn gpu(self) -> bool {
        matches!(self, Row::GpuSm | Row::GpuHe | Row::GpuLatticeMg)
    }
}

/// How a cell ended.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Outcome {
    Recovers,
    Stuck,
    VolumeLost,
    VolumeGained,
    Inverted,
    BlowsUp,
    NotApplicable,
}

impl Outcome {
    const ALL: [Outcome; 7] = [
        Outcome::Recovers,
        Outcome::Stuck,
        Outcome::VolumeLost,
        Outcome::VolumeGained,
        Outcome::Inverted,
        Outcome::BlowsUp,
        Outcome::NotApplicable,
    ];

    /// Name in tables and the JSON.
    fn name(self) -> &'static str {
        match self {
            Outcome::Recovers => "recovers",
            Outcome::Stuck => "stuck",
            Outcome::VolumeLost => "volume lost",
            Outcome::VolumeGained => "volume gained",
            Outcome::Inverted => "inverted",
            Outcome::BlowsUp => "blows up",
            Outcome::NotApplicable => "n/a",
        }
    }

    /// Map colour.
    fn color(self) -> (u8, u8, u8) {
        match self {
            Outcome::Recovers => (120, 200, 120),
            Outcome::Stuck => (240, 215, 90),
            Outcome::VolumeLost => (245, 155, 75),
            Outcome::VolumeGained => (200, 160, 235),
            Outcome::Inverted => (120, 170, 235),
            Outcome::BlowsUp => (230, 85, 75),
            Outcome::NotApplicable => (210, 210, 210),
        }
    }
}

/// One scenario × method result.
struct Cell {
    row: Row,
    scenario: Scenario,
    outcome: Outcome,
    /// Signed volume change of the end state, % (`None` for n/a).
    volume_pct: Option<f32>,
    /// Shape error after rigid alignment, % of the body size.
    shape_pct: Option<f32>,
    /// Share of the rest volume in clusters with det F < 0 at the end, %.
    inverted_pct: Option<f32>,
    /// Fastest particle at the end, m/s.
    end_speed: Option<f32>,
    /// Steps asked for and steps completed.
    steps: u32,
    steps_run: u32,
    /// The step that diverged (GPU: at the latest), 1-based.
    diverged_at: Option<u32>,
    particles: usize,
    /// Wall-clock time of the cell, ms.
    ms: f64,
    /// Why n/a, or how it blew up.
    note: String,
}

/// Options.
struct Config {
    particles: u32,
    seconds: f32,
    plate_spacing: f32,
    stiffness: f32,
    youngs: f32,
    gravity: bool,
    cpu: bool,
    gpu: bool,
    out: PathBuf,
}

/// Parses the command line.
fn config() -> Config {
    let a = bench::Args::new();
    let quick = a.flag("--quick");
    Config {
        particles: a.num("--particles", if quick { 160 } else { 1500 }),
        seconds: a.num("--seconds", if quick { 1.0 } else { 3.0 }),
        plate_spacing: if quick { 0.016 } else { 0.008 },
        stiffness: a.num("--stiffness", 0.5),
        youngs: a.num("--youngs", 1.0e5),
        gravity: a.flag("--gravity"),
        cpu: !a.flag("--no-cpu"),
        gpu: !a.flag("--no-gpu"),
        out: a.path("--out", "stability_out"),
    }
}

/// The body of a scenario: surface and resolution.
fn body(scenario: Scenario, cfg: &Config) -> (TriMesh, Resolution) {
    if scenario == Scenario::Coplanar {
        (
            procedural::cuboid(PLATE, 4),
            Resolution::Spacing(cfg.plate_spacing),
        )
    } else {
        (
            procedural::cuboid(BRICK, 2),
            Resolution::Particles(cfg.particles),
        )
    }
}

/// The elastic model of a row in a scenario.
fn material(scenario: Scenario, row: Row, cfg: &Config) -> Material {
    let stiff = scenario == Scenario::Stiff;
    if row.shape_matching() {
        Material::ShapeMatching {
            stiffness: if stiff { 1.0 } else { cfg.stiffness },
        }
    } else {
        Material::Hyperelastic {
            youngs_modulus: if stiff { 1.0e7 } else { cfg.youngs },
            poisson_ratio: 0.45,
        }
    }
}

/// Solver settings of a row in a scenario (gravity off, no particle contacts: one body).
fn settings(scenario: Scenario, row: Row, cfg: &Config) -> SolverSettings {
    let mut s = SolverSettings {
        method: row.method(),
        gravity: if cfg.gravity && scenario != Scenario::Coplanar {
            SolverSettings::default().gravity
        } else {
            Vec3::ZERO
        },
        particle_contacts: false,
        threads: 1,
        element_solver: if matches!(row, Row::LatticeMg | Row::GpuLatticeMg) {
            ElementSolver::Multigrid
        } else {
            ElementSolver::Xpbd
        },
        // Every iteration a Newton iteration of one V-cycle under Newton–multigrid.
        newton_iterations: 0,
        newton_cycles: 1,
        ..Default::default()
    };
    match scenario {
        Scenario::LargeDt => s.dt = 0.1,
        Scenario::OneIteration => s.iterations = 1,
        Scenario::OverRelaxed => s.relaxation = OMEGA,
        _ => {}
    }
    s
}

/// The model, start state and colliders of a cell.
fn setup(scenario: Scenario, row: Row, cfg: &Config) -> Result<(Model, State, Control), String> {
    let (mesh, resolution) = body(scenario, cfg);
    let desc = BodyDesc {
        resolution,
        neighbours: if scenario == Scenario::SmallK { 4 } else { 32 },
        material: material(scenario, row, cfg),
        hierarchy: (row == Row::HeHierarchy).then_some(HierarchyDesc {
            levels: Some(2),
            ..Default::default()
        }),
        discretisation: if row.lattice() {
            Discretisation::Lattice
        } else {
            Discretisation::Clusters
        },
        ..Default::default()
    };
    let mut model = Model::new();
    model.add_body(&mesh, &desc).map_err(|e| e.to_string())?;
    let mut state = State::new(&model);
    let mut control = Control::default();
    let c = state.x.iter().copied().sum::<Vec3>() / state.x.len() as f32;
    let about = |x: &mut Vec3, scale: Vec3| *x = c + (*x - c) * scale;
    match scenario {
        s if s.settings_only() => {
            for x in &mut state.x {
                about(x, Vec3::new(1.0, SQUASH, 1.0));
            }
        }
        Scenario::Flat => {
            for x in &mut state.x {
                about(x, Vec3::new(1.0, 0.05, 1.0));
            }
        }
        Scenario::Inverted => {
            for x in &mut state.x {
                about(x, Vec3::new(-1.0, 1.0, 1.0));
            }
        }
        Scenario::Stretched => {
            for x in &mut state.x {
                about(x, Vec3::new(4.0, 1.0, 1.0));
            }
        }
        Scenario::Impact => {
            for v in &mut state.v {
                *v = Vec3::new(0.0, -IMPACT_SPEED, 0.0);
            }
        }
        Scenario::Coplanar => {
            // A cylindrical bend: the edges 2 cm above the middle.
            for x in &mut state.x {
                x.y += 0.02 * (x.x / PLATE.x).powi(2);
            }
        }
        _ => {}
    }
    if scenario == Scenario::Impact || (cfg.gravity && scenario != Scenario::Coplanar) {
        // On the ground (y = 0): the lowest particle one radius above it, 1 cm higher for
        // the impact.
        let r = model.bodies[0].radius;
        let gap = if scenario == Scenario::Impact {
            0.01
        } else {
            0.0
        };
        let low = state.x.iter().map(|x| x.y).fold(f32::INFINITY, f32::min);
        for x in &mut state.x {
            x.y += r + gap - low;
        }
        control.colliders.push(Collider::ground(0.0));
    }
    Ok((model, state, control))
}

/// What measures the end states of one scenario: a flat model of the same particles with
/// K = 32, and for each of its flat clusters an orthonormal pair spanning its plane; for
/// the lattice rows, the lattice model itself (volume `Σ_e V_e det F_e` over its
/// hexahedra).
struct Meter {
    model: Model,
    plane: Vec<Option<(Vec3, Vec3)>>,
}

impl Meter {
    /// The measuring model of a scenario's body (`lattice`: of its lattice model).
    fn new(scenario: Scenario, cfg: &Config, lattice: bool) -> Result<Self, String> {
        let (mesh, resolution) = body(scenario, cfg);
        let desc = BodyDesc {
            resolution,
            neighbours: 32,
            material: if lattice {
                Material::Hyperelastic {
                    youngs_modulus: cfg.youngs,
                    poisson_ratio: 0.45,
                }
            } else {
                Material::ShapeMatching { stiffness: 1.0 }
            },
            discretisation: if lattice {
                Discretisation::Lattice
            } else {
                Discretisation::Clusters
            },
            ..Default::default()
        };
        let mut model = Model::new();
        model.add_body(&mesh, &desc).map_err(|e| e.to_string())?;
        let plane = model
            .cluster_rest
            .iter()
            .map(|r| {
                // A_qq⁻¹ of a flat cluster is a pseudo-inverse with a zero eigenvalue along
                // the cluster's normal.
                let (vals, vecs) = sym_eigen(&r.aqq_inv.as_dmat3());
                let max = vals.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                let k = (0..3).min_by(|&a, &b| vals[a].total_cmp(&vals[b]))?;
                (vals[k] <= 1e-6 * max).then(|| {
                    let a = vecs.col((k + 1) % 3).as_vec3().normalize();
                    let b = vecs.col((k + 2) % 3).as_vec3().normalize();
                    (a, b)
                })
            })
            .collect();
        Ok(Self { model, plane })
    }

    /// Volume of positions `x` relative to the rest volume, and the share of the rest
    /// volume in inverted clusters (det F < 0).
    fn volume(&self, x: &[Vec3]) -> (f32, f32) {
        if !self.model.elements.is_empty() {
            let (mut v, mut inv, mut total) = (0.0f64, 0.0f64, 0.0f64);
            for (nodes, r) in self.model.elements.iter().zip(&self.model.element_rest) {
                let j = element_gradient(&nodes.map(|k| x[k as usize]), r.size).determinant();
                v += (r.volume * j) as f64;
                total += r.volume as f64;
                if j < 0.0 {
                    inv += r.volume as f64;
                }
            }
            return ((v / total) as f32, (inv / total) as f32);
        }
        let f = Solver::deformation_gradients(&self.model, x);
        let (mut v, mut inv, mut total) = (0.0f64, 0.0f64, 0.0f64);
        for ((fc, plane), &vc) in f.iter().zip(&self.plane).zip(&self.model.cluster_volume) {
            let j = match plane {
                Some((a, b)) => (*fc * *a).cross(*fc * *b).length(),
                None => fc.determinant(),
            } as f64;
            v += vc as f64 * j;
            total += vc as f64;
            if j < 0.0 {
                inv += vc as f64;
            }
        }
        ((v / total) as f32, (inv / total) as f32)
    }

    /// RMS distance of `x` from the rest shape after the best rigid alignment
    /// (mass-weighted), relative to the body size (bounding-box diagonal).
    fn shape_error(&self, x: &[Vec3]) -> f32 {
        accuracy::rigid_fit_error(&self.model, x) / self.model.bodies[0].size
    }
}

/// The end of a run: final positions and velocities, steps completed, divergence.
struct RunEnd {
    x: Vec<Vec3>,
    v: Vec<Vec3>,
    steps_run: u32,
    /// The step (1-based) that diverged, or for the GPU the last step of the chunk that
    /// raised the flag, and what happened.
    diverged: Option<(u32, String)>,
}

/// Runs `steps` steps on the CPU; stops at the first divergence (the solver has restored
/// the state before the step).
fn run_cpu(
    model: &Model,
    mut state: State,
    control: &Control,
    settings: SolverSettings,
    steps: u32,
) -> Result<RunEnd, String> {
    let mut solver = Solver::new(model, settings).map_err(|e| e.to_string())?;
    let mut diverged = None;
    let mut done = 0;
    for _ in 0..steps {
        match solver.step(model, &mut state, control) {
            Ok(_) => done += 1,
            Err(e @ TissueError::Diverged { .. }) => {
                diverged = Some((done + 1, e.to_string()));
                break;
            }
            Err(e) => return Err(e.to_string()),
        }
    }
    Ok(RunEnd {
        x: state.x,
        v: state.v,
        steps_run: done,
        diverged,
    })
}

/// Runs `steps` steps in about 20 chunks: `chunk(done, k)` takes `k` more steps after
/// `done` and says what diverged, if anything. Returns the steps taken before the chunk
/// that diverged (all of them otherwise) and, for that chunk, its last step and the note.
fn in_chunks(
    steps: u32,
    mut chunk: impl FnMut(u32, u32) -> Option<String>,
) -> (u32, Option<(u32, String)>) {
    let size = steps.div_ceil(20).max(1);
    let mut done = 0;
    while done < steps {
        let k = size.min(steps - done);
        if let Some(note) = chunk(done, k) {
            return (done, Some((done + k, note)));
        }
        done += k;
    }
    (done, None)
}

/// Runs `steps` steps on the GPU in chunks, reading the body's divergence flag after
/// each; stops at the first chunk that raised it.
fn run_gpu(
    g: &Headless,
    model: &Model,
    state: &State,
    control: &Control,
    settings: SolverSettings,
    steps: u32,
) -> Result<RunEnd, String> {
    let mut world = GpuWorld::new(&g.device, &g.kernels, model, state, settings, 0)
        .map_err(|e| e.to_string())?;
    world
        .set_colliders(&g.queue, &control.colliders)
        .map_err(|e| e.to_string())?;
    world.write_params(&g.queue);
    let n = world.particle_count();
    let (done, diverged) = in_chunks(steps, |done, k| {
        let mut enc = g.device.create_command_encoder(&Default::default());
        world.record_steps(&mut enc, &g.kernels, k, &mut NoTiming);
        g.queue.submit([enc.finish()]);
        let flag = read_u32(&g.device, &g.queue, world.status(), 1);
        (flag[0] != 0).then(|| {
            format!(
                "the GPU flagged the body as diverged in steps {}..={}",
                done + 1,
                done + k
            )
        })
    });
    Ok(RunEnd {
        x: read_vec3(&g.device, &g.queue, world.positions(), n),
        v: read_vec3(&g.device, &g.queue, world.velocities(), n),
        steps_run: done,
        diverged,
    })
}

/// Runs `steps` steps of Newton–multigrid on the GPU (`GpuLattice`) in chunks, checking
/// the particles for divergence after each (as the CPU solver does after every step);
/// stops at the first chunk that diverged.
fn run_gpu_lattice(
    g: &Headless,
    model: &Model,
    state: &State,
    control: &Control,
    settings: SolverSettings,
    steps: u32,
) -> Result<RunEnd, String> {
    let kernels = LatticeKernels::new(&g.device).map_err(|e| e.to_string())?;
    let mut world =
        GpuLattice::new(&g.device, &kernels, model, state, &settings).map_err(|e| e.to_string())?;
    world
        .set_colliders(&g.queue, &control.colliders)
        .map_err(|e| e.to_string())?;
    let mut st = state.clone();
    let (done, diverged) = in_chunks(steps, |done, k| {
        let mut enc = g.device.create_command_encoder(&Default::default());
        world.record(&mut enc, &kernels, k, None);
        g.queue.submit([enc.finish()]);
        world.download(&g.device, &g.queue, &mut st);
        let worst = diagnose::worst_particle(&st.x, &st.v, settings.max_speed)?;
        let e = diagnose::diverged(model, &settings, st.step + (done + k) as u64, worst, 0.0);
        Some(format!("{e} (in steps {}..={})", done + 1, done + k))
    });
    Ok(RunEnd {
        x: st.x,
        v: st.v,
        steps_run: done,
        diverged,
    })
}

/// Classifies an end state from its divergence, volume ratio and shape error.
fn classify(diverged: bool, volume: f32, shape: f32) -> Outcome {
    if diverged || !volume.is_finite() || !shape.is_finite() {
        Outcome::BlowsUp
    } else if volume < 0.0 {
        Outcome::Inverted
    } else if volume < 1.0 - VOLUME_TOL {
        Outcome::VolumeLost
    } else if volume > 1.0 + VOLUME_TOL {
        Outcome::VolumeGained
    } else if shape > SHAPE_TOL {
        Outcome::Stuck
    } else {
        Outcome::Recovers
    }
}

/// Runs one cell.
fn run_cell(
    scenario: Scenario,
    row: Row,
    cfg: &Config,
    meter: Result<&Meter, String>,
    gpu: Option<&Headless>,
) -> Cell {
    let t = Instant::now();
    let s = settings(scenario, row, cfg);
    let steps = (cfg.seconds / s.dt).round().max(1.0) as u32;
    let mut cell = Cell {
        row,
        scenario,
        outcome: Outcome::NotApplicable,
        volume_pct: None,
        shape_pct: None,
        inverted_pct: None,
        end_speed: None,
        steps,
        steps_run: 0,
        diverged_at: None,
        particles: meter.as_ref().map_or(0, |m| m.model.particle_count()),
        ms: 0.0,
        note: String::new(),
    };
    let meter = match meter {
        Ok(m) => m,
        Err(e) => {
            // The one-layer plate has no lattice cell (no cell centre inside it).
            cell.note = format!("no lattice body: {e}");
            return cell;
        }
    };
    if scenario == Scenario::SmallK && row.lattice() {
        cell.note = "the lattice has no neighbourhoods (K)".into();
        return cell;
    }
    if scenario == Scenario::OverRelaxed
        && row.method() == Method::GaussSeidel
        && (!row.gpu() || row.lattice())
    {
        cell.note = "Gauss–Seidel applies each correction in full; this solver's ω is Jacobi's \
                     (no successive over-relaxation)"
            .into();
        return cell;
    }
    let run = setup(scenario, row, cfg).and_then(|(model, state, control)| {
        if model.rest != meter.model.rest {
            return Err("the measuring model's particles differ".into());
        }
        match gpu {
            Some(g) if row.lattice() => run_gpu_lattice(g, &model, &state, &control, s, steps),
            Some(g) => run_gpu(g, &model, &state, &control, s, steps),
            None => run_cpu(&model, state, &control, s, steps),
        }
    });
    match run {
        Ok(end) => {
            let (volume, inverted) = meter.volume(&end.x);
            let shape = meter.shape_error(&end.x);
            cell.outcome = classify(end.diverged.is_some(), volume, shape);
            cell.volume_pct = Some((volume - 1.0) * 100.0);
            cell.shape_pct = Some(shape * 100.0);
            cell.inverted_pct = Some(inverted * 100.0);
            cell.end_speed = Some(end.v.iter().map(|v| v.length()).fold(0.0, f32::max));
            cell.steps_run = end.steps_run;
            if let Some((at, note)) = end.diverged {
                cell.diverged_at = Some(at);
                cell.note = note;
            }
        }
        Err(e) => {
            // A model or solver that cannot be built is a failure of the method here.
            cell.outcome = Outcome::BlowsUp;
            cell.note = format!("could not run: {e}");
        }
    }
    cell.ms = t.elapsed().as_secs_f64() * 1e3;
    cell
}

/// A signed percentage with a real minus sign.
fn pct(v: f32) -> String {
    let s = if v.abs() >= 100.0 {
        format!("{v:+.0}%")
    } else if v.abs() >= 10.0 {
        format!("{v:+.1}%")
    } else {
        format!("{v:+.2}%")
    };
    s.replace('-', "−")
}

/// Where a cell blew up: "step N" (CPU, exact), "by step N" (GPU, checked per chunk).
fn step_text(c: &Cell) -> String {
    match (c.diverged_at, c.row.gpu()) {
        (Some(n), false) => format!("step {n}"),
        (Some(n), true) => format!("by step {n}"),
        (None, _) => "could not run".into(),
    }
}

/// The map cell's text in the Markdown table.
fn md_cell(c: &Cell) -> String {
    match (c.outcome, c.volume_pct) {
        (Outcome::NotApplicable, _) | (_, None) => c.outcome.name().into(),
        (Outcome::BlowsUp, _) => format!("**blows up** ({})", step_text(c)),
        (o, Some(v)) => format!("{} {}", o.name(), pct(v)),
    }
}

/// A JSON number or `null`.
fn num(v: Option<f32>) -> String {
    match v {
        Some(x) if x.is_finite() => format!("{x:.4}"),
        _ => "null".into(),
    }
}

/// A JSON string (quotes and backslashes escaped).
fn jstr(s: &str) -> String {
    format!("\"{}\"", s.replace('\\', "\\\\").replace('"', "\\\""))
}

fn main() {
    let cfg = config();
    std::fs::create_dir_all(&cfg.out).expect("output folder");
    let gpu = if cfg.gpu {
        match bench::open_gpu() {
            Ok(g) => {
                eprintln!("GPU: {}", g.adapter);
                Some(g)
            }
            Err(e) => {
                eprintln!("no GPU adapter ({e}): GPU rows skipped");
                None
            }
        }
    } else {
        None
    };
    let mut rows: Vec<Row> = Vec::new();
    if cfg.cpu {
        rows.extend(Row::CPU);
    }
    if gpu.is_some() {
        rows.extend(Row::GPU);
    }
    let t0 = Instant::now();
    let meters: Vec<Meter> = Scenario::ALL
        .iter()
        .map(|&s| Meter::new(s, &cfg, false).expect("measuring model"))
        .collect();
    // The lattice's (none where the body has no cell: the one-layer plate).
    let lattice_meters: Vec<Result<Meter, String>> = Scenario::ALL
        .iter()
        .map(|&s| Meter::new(s, &cfg, true))
        .collect();
    let meter_of = |s: usize, r: Row| -> Result<&Meter, String> {
        if r.lattice() {
            lattice_meters[s].as_ref().map_err(|e| e.clone())
        } else {
            Ok(&meters[s])
        }
    };
    let jobs: Vec<(usize, Row)> = (0..Scenario::ALL.len())
        .flat_map(|s| rows.iter().map(move |&r| (s, r)))
        .collect();
    // CPU cells on worker threads (one per core, each solver on one thread: the bodies
    // are small, and Jacobi's results do not depend on the thread count); GPU cells on
    // this thread meanwhile.
    let next = AtomicUsize::new(0);
    let done = Mutex::new(Vec::new());
    let workers = std::thread::available_parallelism().map_or(1, |n| n.get());
    let report = |c: Cell| {
        eprintln!(
            "[{:6.1} s] {:<14} {:<34} {:<13} volume {:>9} shape {:>8} ({} particles, {}/{} steps, {:.0} ms){}",
            t0.elapsed().as_secs_f64(),
            c.scenario.key(),
            c.row.name(),
            c.outcome.name(),
            c.volume_pct.map_or("–".into(), pct),
            c.shape_pct.map_or("–".into(), |s| format!("{s:.2}%")),
            c.particles,
            c.steps_run,
            c.steps,
            c.ms,
            if c.note.is_empty() {
                String::new()
            } else {
                format!(": {}", c.note)
            }
        );
        done.lock().expect("results").push(c);
    };
    std::thread::scope(|scope| {
        for _ in 0..workers {
            scope.spawn(|| {
                let cpu: Vec<&(usize, Row)> = jobs.iter().filter(|j| !j.1.gpu()).collect();
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some(&&(s, r)) = cpu.get(i) else { break };
                    report(run_cell(Scenario::ALL[s], r, &cfg, meter_of(s, r), None));
                }
            });
        }
        for &(s, r) in jobs.iter().filter(|j| j.1.gpu()) {
            report(run_cell(
                Scenario::ALL[s],
                r,
                &cfg,
                meter_of(s, r),
                gpu.as_ref(),
            ));
        }
    });
    let mut cells = done.into_inner().expect("results");
    let order = |c: &Cell| {
        let s = Scenario::ALL.iter().position(|&s| s == c.scenario);
        (s, rows.iter().position(|&r| r == c.row))
    };
    cells.sort_by_key(order);
    let cell = |r: Row, s: Scenario| cells.iter().find(|c| c.row == r && c.scenario == s);
    // Markdown: the map, then the shape errors, then the legend.
    let header = |title: &str| {
        let mut h = format!("| {title} |");
        for s in Scenario::ALL {
            let _ = write!(h, " {} |", s.label().replace('\n', " "));
        }
        h.push_str("\n|---|");
        h.push_str(&"---|".repeat(Scenario::ALL.len()));
        h
    };
    println!(
        "Outcome and volume change after {} s (simulated, gravity {}), brick of {} particles, plate of {}:\n",
        cfg.seconds,
        if cfg.gravity { "on" } else { "off" },
        cells
            .iter()
            .find(|c| c.scenario == Scenario::Baseline)
            .map_or(0, |c| c.particles),
        cells
            .iter()
            .find(|c| c.scenario == Scenario::Coplanar)
            .map_or(0, |c| c.particles),
    );
    println!("{}", header("method"));
    for &r in &rows {
        let mut line = format!("| {} |", r.name());
        for s in Scenario::ALL {
            let _ = write!(line, " {} |", cell(r, s).map_or("–".into(), md_cell));
        }
        println!("{line}");
    }
    println!("\nShape error after rigid alignment, % of the body size:\n");
    println!("{}", header("method"));
    for &r in &rows {
        let mut line = format!("| {} |", r.name());
        for s in Scenario::ALL {
            let text = cell(r, s)
                .and_then(|c| c.shape_pct)
                .map_or("–".into(), |v| format!("{v:.2}"));
            let _ = write!(line, " {text} |");
        }
        println!("{line}");
    }
    println!("\n| scenario | what |\n|---|---|");
    for s in Scenario::ALL {
        println!("| {} | {} |", s.label().replace('\n', " "), s.what());
    }
    println!(
        "\nOutcomes: blows up = solver reported divergence (NaN or > 500 m/s); inverted = negative \
         signed volume; volume lost/gained = |ΔV| > {:.0}%; stuck = shape error > {:.0}% of the \
         body size; recovers = neither.",
        VOLUME_TOL * 100.0,
        SHAPE_TOL * 100.0
    );
    // JSON: one cell per line.
    let mut json = String::from("{\n");
    let _ = writeln!(
        json,
        "  \"seconds\": {}, \"gravity\": {}, \"volume_tolerance\": {VOLUME_TOL}, \"shape_tolerance\": {SHAPE_TOL}, \"omega\": {OMEGA},",
        cfg.seconds, cfg.gravity
    );
    json.push_str("  \"scenarios\": [\n");
    for (i, s) in Scenario::ALL.iter().enumerate() {
        let _ = writeln!(
            json,
            "    {{\"key\": {}, \"label\": {}, \"what\": {}}}{}",
            jstr(s.key()),
            jstr(&s.label().replace('\n', " ")),
            jstr(&s.what()),
            if i + 1 < Scenario::ALL.len() { "," } else { "" }
        );
    }
    json.push_str("  ],\n  \"methods\": [\n");
    for (i, r) in rows.iter().enumerate() {
        let _ = writeln!(
            json,
            "    {{\"key\": {}, \"name\": {}}}{}",
            jstr(r.key()),
            jstr(r.name()),
            if i + 1 < rows.len() { "," } else { "" }
        );
    }
    json.push_str("  ],\n  \"cells\": [\n");
    for (i, c) in cells.iter().enumerate() {
        let _ = writeln!(
            json,
            "    {{\"method\": {}, \"scenario\": {}, \"outcome\": {}, \"volume_change_pct\": {}, \"shape_error_pct\": {}, \"inverted_pct\": {}, \"end_speed\": {}, \"steps\": {}, \"steps_run\": {}, \"diverged_at\": {}, \"particles\": {}, \"ms\": {:.1}, \"note\": {}}}{}",
            jstr(c.row.key()),
            jstr(c.scenario.key()),
            jstr(c.outcome.name()),
            num(c.volume_pct),
            num(c.shape_pct),
            num(c.inverted_pct),
            num(c.end_speed),
            c.steps,
            c.steps_run,
            c.diverged_at.map_or("null".into(), |n| n.to_string()),
            c.particles,
            c.ms,
            jstr(&c.note),
            if i + 1 < cells.len() { "," } else { "" }
        );
    }
    json.push_str("  ]\n}\n");
    let json_path = cfg.out.join("stability.json");
    std::fs::write(&json_path, json).expect("write JSON");
    // The map.
    let map = chart::Map {
        title: format!(
            "Stability where methods fail: outcome after {} s (text: volume change, shape error)",
            cfg.seconds
        ),
        row_labels: rows.iter().map(|r| r.name().to_string()).collect(),
        col_labels: Scenario::ALL.iter().map(|s| s.label()).collect(),
        cells: rows
            .iter()
            .map(|&r| {
                Scenario::ALL
                    .iter()
                    .map(|&s| match cell(r, s) {
                        Some(c) => chart::MapCell {
                            color: c.outcome.color(),
                            lines: match (c.outcome, c.volume_pct, c.shape_pct) {
                                (Outcome::BlowsUp, _, _) => {
                                    vec!["blows up".into(), step_text(c)]
                                }
                                (_, Some(v), Some(e)) => {
                                    vec![format!("ΔV {}", pct(v)), format!("shape {e:.1}%")]
                                }
                                _ => vec![c.outcome.name().into()],
                            },
                        },
                        None => chart::MapCell {
                            color: (255, 255, 255),
                            lines: vec![],
                        },
                    })
                    .collect()
            })
            .collect(),
        legend: Outcome::ALL
            .iter()
            .map(|o| (o.name().to_string(), o.color()))
            .collect(),
        notes: vec![
            format!(
                "volume: Σ V_c det F_c over K = 32 clusters (the plate: area); |ΔV| > {:.0}% is a volume failure; shape error: RMS after rigid alignment / body size, > {:.0}% is stuck",
                VOLUME_TOL * 100.0,
                SHAPE_TOL * 100.0
            ),
            format!(
                "{}; shape matching k = {}, hyperelastic E = {} kPa, ν = 0.45 unless the column says otherwise",
                if cfg.gravity {
                    "gravity on, bricks on a ground plane (the plate floats)"
                } else {
                    "gravity off"
                },
                cfg.stiffness,
                cfg.youngs / 1e3
            ),
        ],
    };
    let png = cfg.out.join("stability.png");
    chart::draw_map(&png, &map, (128, 54), 270).expect("chart");
    eprintln!(
        "[{:6.1} s] wrote {} and {}",
        t0.elapsed().as_secs_f64(),
        json_path.display(),
        png.display()
    );
}
