//! What `SolverSettings::contact_every` (and `contact_relaxation`, `--contact-relaxation`)
//! does to particle contacts (CPU, `core::solver`):
//! contacts solved in every iteration (1, the default) or in every 2nd, 3rd, 5th or 10th
//! (fewer contact passes let the GPU run a body near another in fewer dispatches). Two
//! scenes, both settled on a ground plane for `--seconds` (default 3), at the plugin's
//! settings (dt = 1/60 s, 1 substep, 10 iterations, contacts refreshed every 10 steps):
//!
//! - **pile**: 27 shape-matching balls (k = 1, 512 particles, 5 cm radius) dropped as a
//!   3 × 3 × 3 block of touching balls: the 1,000-body benchmark's bodies, in contact;
//! - **slab**: a 1 MPa hyperelastic ball dropped 5 cm onto a slab lying on the ground
//!   (`tests/solver.rs`, `two_bodies_collide_without_passing_through`), with Jacobi and
//!   with Gauss–Seidel.
//!
//! For each: the deepest penetration between two bodies at the end (contact distance
//! minus the closest pair of particles of different bodies, as a fraction of the contact
//! distance; brute force); because one instant's deepest pair is noisy, the same at six
//! instants over the last second (mean and largest), and over those instants the
//! particles that overlap a particle of another body (each one's deepest overlap,
//! averaged; and how many); the mean and largest particle speed over the last second
//! (m/s: jitter of bodies that should rest), the top body's centre height, and ms per
//! step (the solver alone). Markdown on stdout.
//!
//! ```text
//! cargo run --release --example contacts
//! cargo run --release --example contacts -- --quick   # 1 s, the pile only
//! cargo run --release --example contacts -- --knn-every 1 --substeps 4
//! cargo run --release --example contacts -- --contact-relaxation 1,2 --every 1,2
//! ```
//!
//! `--contact-relaxation` and `--every` take comma-separated lists (ω_c; n);
//! `--jacobi-only` leaves out the Gauss–Seidel rows; `--seeds 0,1,2` runs the pile with
//! the balls 6 mm apart and each moved by up to ±3 mm (a fixed hash of the seed; 0, the
//! default, is the regular touching pile), an ensemble that shows how much one pile's
//! outcome is chance.
//!
//! A third table: two balls meeting head-on at 0.5 m/s (no gravity, candidates every
//! step), their restitution and how far into each other they end.
#[path = "support/bench.rs"]
mod bench;

use bevy_tissue::core::colliders::Collider;
use bevy_tissue::core::model::{BodyDesc, Material, Model};
use bevy_tissue::core::procedural;
use bevy_tissue::core::sampling::Resolution;
use bevy_tissue::core::solver::{Control, Method, Solver, SolverSettings, State};
use glam::Vec3;
use std::time::Instant;

/// One of the pile's balls at the origin.
fn ball() -> Model {
    let mut one = Model::new();
    let desc = BodyDesc {
        resolution: Resolution::Particles(512),
        neighbours: 32,
        material: Material::ShapeMatching { stiffness: 1.0 },
        discretisation: bevy_tissue::core::model::Discretisation::Clusters,
        ..Default::default()
    };
    one.add_body(&procedural::icosphere(0.05, 2), &desc)
        .expect("ball");
    one
}

/// The pile; with `seed` > 0 the balls start 6 mm apart and each is moved by up to ±3 mm
/// along each axis (a fixed hash of the seed and the ball), so that several seeds give an
/// ensemble of piles: one pile's outcome hangs on where its few deepest contacts form.
fn pile(seed: u32) -> Model {
    let one = ball();
    let mut model = Model::new();
    for i in 0..27u32 {
        let mut b = one.clone();
        let (x, y, z) = (i % 3, (i / 3) % 3, i / 9);
        let jitter = Vec3::from_array(std::array::from_fn(|a| {
            if seed == 0 {
                return 0.0;
            }
            let h = (seed.wrapping_mul(0x9E37_79B9) ^ (i * 3 + a as u32).wrapping_mul(0x85EB_CA6B))
                .wrapping_mul(0xC2B2_AE35);
            ((h >> 8) as f32 / (1u32 << 24) as f32 - 0.5) * 0.006
        }));
        // With a seed the balls are 6 mm further apart, so that no jitter starts two of
        // them in each other (particle contacts cannot part meshed lattices).
        let spacing = if seed == 0 { 0.1 } else { 0.106 };
        b.bodies[0].translation =
            Vec3::new(x as f32 - 1.0, y as f32 + 0.6, z as f32 - 1.0) * spacing + jitter;
        model.append(&b);
    }
    model
}

fn slab() -> Model {
    let mut model = Model::new();
    let shapes = [
        procedural::cuboid(Vec3::new(0.08, 0.03, 0.08), 2),
        procedural::icosphere(0.05, 2),
    ];
    for ((mesh, y), n) in shapes.iter().zip([0.03f32, 0.15]).zip([2000, 400]) {
        let desc = BodyDesc {
            resolution: Resolution::Particles(n),
            neighbours: 16,
            material: Material::Hyperelastic {
                youngs_modulus: 1e6,
                poisson_ratio: 0.3,
            },
            translation: Vec3::new(0.0, y, 0.0),
            discretisation: bevy_tissue::core::model::Discretisation::Clusters,
            ..Default::default()
        };
        model.add_body(mesh, &desc).expect("slab scene");
    }
    model
}

/// Overlaps between bodies (brute force), as fractions of the contact distance (the two
/// particles' radii): the deepest pair, and over the particles that overlap a particle of
/// another body, each one's deepest overlap averaged, and how many they are.
#[derive(Clone, Copy, Default)]
struct Overlap {
    deepest: f32,
    mean: f32,
    particles: usize,
}

fn overlap(model: &Model, x: &[Vec3]) -> Overlap {
    let mut each = vec![0.0f32; x.len()];
    for a in 0..model.bodies.len() {
        for b in a + 1..model.bodies.len() {
            let d = model.bodies[a].radius + model.bodies[b].radius;
            for i in model.bodies[a].range() {
                for j in model.bodies[b].range() {
                    let l = x[i].distance(x[j]);
                    if l < d {
                        let o = (d - l) / d;
                        each[i] = each[i].max(o);
                        each[j] = each[j].max(o);
                    }
                }
            }
        }
    }
    let hit: Vec<f32> = each.into_iter().filter(|o| *o > 0.0).collect();
    Overlap {
        deepest: hit.iter().copied().fold(0.0, f32::max),
        mean: hit.iter().sum::<f32>() / hit.len().max(1) as f32,
        particles: hit.len(),
    }
}

/// The deepest penetration between two bodies, as a fraction of their contact distance.
fn deepest(model: &Model, x: &[Vec3]) -> f32 {
    overlap(model, x).deepest
}

struct Outcome {
    depth: f32,
    /// [`Overlap`] at 6 instants over the last second: the deepest pair's mean and
    /// largest, the overlapping particles' mean overlap and their mean count.
    depth_mean: f32,
    depth_max: f32,
    overlap_mean: f32,
    overlapping: f32,
    mean_speed: f32,
    max_speed: f32,
    top: f32,
    ms: f64,
}

fn run(model: &Model, settings: SolverSettings, seconds: f32) -> Result<Outcome, String> {
    let mut state = State::new(model);
    let mut solver = Solver::new(model, settings.clone()).map_err(|e| e.to_string())?;
    let control = Control {
        colliders: vec![Collider::ground(0.0)],
    };
    let steps = (seconds / settings.dt).round() as usize;
    let last = (1.0 / settings.dt).round() as usize;
    let (mut sum, mut count, mut max) = (0.0f64, 0usize, 0.0f32);
    let mut depths = Vec::new();
    let mut solve = std::time::Duration::ZERO;
    for k in 0..steps {
        let t = Instant::now();
        solver
            .step(model, &mut state, &control)
            .map_err(|e| e.to_string())?;
        solve += t.elapsed();
        // Six samples of the deepest penetration over the last second (one instant's
        // deepest pair is noisy), outside the timed solve.
        if k + last >= steps && (steps - 1 - k).is_multiple_of(last.div_ceil(6).max(1)) {
            depths.push(overlap(model, &state.x));
        }
        if k + last >= steps {
            for v in &state.v {
                let s = v.length();
                sum += s as f64;
                max = max.max(s);
            }
            count += state.v.len();
        }
        if k % 60 == 59 {
            eprintln!("  {:.1} s simulated", (k + 1) as f32 * settings.dt);
        }
    }
    let ms = solve.as_secs_f64() * 1e3 / steps as f64;
    let top = (0..model.bodies.len())
        .map(|b| {
            let r = model.bodies[b].range();
            r.clone().map(|i| state.x[i].y).sum::<f32>() / r.len() as f32
        })
        .fold(f32::MIN, f32::max);
    let depth = depths.last().copied().unwrap_or_default().deepest;
    let samples = depths.len().max(1) as f32;
    Ok(Outcome {
        depth,
        depth_mean: depths.iter().map(|o| o.deepest).sum::<f32>() / samples,
        depth_max: depths.iter().map(|o| o.deepest).fold(0.0, f32::max),
        overlap_mean: depths.iter().map(|o| o.mean).sum::<f32>() / samples,
        overlapping: depths.iter().map(|o| o.particles as f32).sum::<f32>() / samples,
        mean_speed: (sum / count.max(1) as f64) as f32,
        max_speed: max,
        top,
        ms,
    })
}

/// Two of the pile's balls meeting head-on at 0.5 m/s (no gravity, candidates every
/// step): the coefficient of restitution, the centres' separation speed after 0.5 s over
/// their closing speed (0: they stick, 1: elastic; above 1 the contacts add energy).
fn restitution(settings: &SolverSettings) -> Result<(f32, f32, f32), String> {
    let mut model = Model::new();
    for x in [-0.075f32, 0.075] {
        let mut one = ball();
        one.bodies[0].translation = Vec3::new(x, 1.0, 0.0);
        model.append(&one);
    }
    let s = SolverSettings {
        gravity: Vec3::ZERO,
        knn_every: 1,
        ..settings.clone()
    };
    let mut state = State::new(&model);
    let centre = |st: &State, b: usize| {
        let r = model.bodies[b].range();
        let n = r.len() as f32;
        (
            r.clone().map(|i| st.x[i]).sum::<Vec3>() / n,
            r.clone().map(|i| st.v[i]).sum::<Vec3>() / n,
        )
    };
    for b in 0..2 {
        let dir = if b == 0 { 1.0 } else { -1.0 };
        for i in model.bodies[b].range() {
            state.v[i] = Vec3::X * (0.25 * dir);
        }
    }
    let mut solver = Solver::new(&model, s.clone()).map_err(|e| e.to_string())?;
    for _ in 0..(0.5 / s.dt).round() as usize {
        solver
            .step(&model, &mut state, &Control::default())
            .map_err(|e| e.to_string())?;
    }
    let ((ca, va), (cb, vb)) = (centre(&state, 0), centre(&state, 1));
    Ok(((vb.x - va.x) / 0.5, cb.x - ca.x, deepest(&model, &state.x)))
}

fn main() {
    let args = bench::Args::new();
    let quick = args.flag("--quick");
    let seconds: f32 = args.num("--seconds", if quick { 1.0 } else { 3.0 });
    let knn_every: u32 = args.num("--knn-every", 10);
    let substeps: u32 = args.num("--substeps", 1);
    let relaxations: Vec<f32> = args.list("--contact-relaxation", &[1.0]);
    let everys: Vec<u32> = args.list("--every", &[1, 2, 3, 5, 10]);
    let seeds: Vec<u32> = args.list("--seeds", &[0]);
    let mut scenes: Vec<(String, Model, Method)> = seeds
        .iter()
        .map(|&k| {
            let name = match k {
                0 => "pile of 27 balls".to_string(),
                k => format!("pile of 27 balls, seed {k}"),
            };
            (name, pile(k), Method::Jacobi)
        })
        .collect();
    if !quick {
        scenes.push(("ball onto slab".into(), slab(), Method::Jacobi));
        if !args.flag("--jacobi-only") {
            scenes.push(("ball onto slab".into(), slab(), Method::GaussSeidel));
        }
    }
    println!(
        "| scene | method | ω_c | contacts every n iterations | deepest penetration at the end (of the contact distance) | deepest over the last second: mean / largest of 6 samples | overlapping particles over the last second: mean overlap, mean count | mean / max speed over the last second, m/s | top centre, m | ms per step |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for (name, model, method) in &scenes {
        for &w in &relaxations {
            // Gauss–Seidel ignores ω_c: one row of each n.
            if *method == Method::GaussSeidel && w != relaxations[0] {
                continue;
            }
            for &every in &everys {
                eprintln!("{name}, {method:?}, ω_c {w}, contacts every {every} iterations");
                let settings = SolverSettings {
                    method: *method,
                    contact_every: every,
                    knn_every,
                    substeps,
                    contact_relaxation: w,
                    ..Default::default()
                };
                match run(model, settings, seconds) {
                    Ok(o) => println!(
                        "| {name} | {method:?} | {w} | {every} | {:.0}% | {:.0}% / {:.0}% | {:.1}%, {:.0} | {:.3} / {:.3} | {:.4} | {:.1} |",
                        o.depth * 100.0,
                        o.depth_mean * 100.0,
                        o.depth_max * 100.0,
                        o.overlap_mean * 100.0,
                        o.overlapping,
                        o.mean_speed,
                        o.max_speed,
                        o.top,
                        o.ms
                    ),
                    Err(e) => println!("| {name} | {method:?} | {w} | {every} | {e} | | | | | |"),
                }
            }
        }
    }
    println!(
        "\n| head-on collision at 0.5 m/s, Jacobi | ω_c | contacts every n iterations | restitution | centres apart after 0.5 s, m (touching: 0.1) | deepest penetration |"
    );
    println!("|---|---|---|---|---|---|");
    for &w in &relaxations {
        for &every in &everys {
            let settings = SolverSettings {
                method: Method::Jacobi,
                contact_every: every,
                substeps,
                contact_relaxation: w,
                ..Default::default()
            };
            match restitution(&settings) {
                Ok((e, gap, depth)) => println!(
                    "| two balls | {w} | {every} | {e:.3} | {gap:.4} | {:.0}% |",
                    depth * 100.0
                ),
                Err(e) => println!("| two balls | {w} | {every} | {e} | | |"),
            }
        }
    }
}
