//! The simulation core on its own, headless: a procedural liver pinned along its
//! ligament sags under gravity and is prodded by a moving probe sphere. Prints progress
//! and what happened (sag, volume, probe force). The Bevy plugin builds on this core.
//!
//! Everything is the core's default: the body (`BodyDesc::default()`: lattice elements
//! of soft tissue, E = 10 kPa, ν = 0.45, 1060 kg/m³) and the solver
//! (`SolverSettings::default()`: Newton–multigrid, 1 Newton iteration of 1 V-cycle per 1/60 s step).
//!
//! ```text
//! cargo run --release --example core_demo
//! ```
use bevy_tissue::core::colliders::{Collider, ColliderShape};
use bevy_tissue::core::model::{BodyDesc, Model, PinRegion};
use bevy_tissue::core::procedural;
use bevy_tissue::core::sampling::Resolution;
use bevy_tissue::core::solver::{Control, Solver, SolverSettings, State};
use glam::{Quat, Vec3};
use std::time::Instant;

fn main() {
    let mesh = procedural::liver(4);
    let (lo, hi) = procedural::liver_ligament();
    let mut model = Model::new();
    let desc = BodyDesc {
        resolution: Resolution::Particles(2048),
        pins: vec![PinRegion::Box { min: lo, max: hi }],
        ..Default::default()
    };
    let t = Instant::now();
    if let Err(e) = model.add_body(&mesh, &desc) {
        eprintln!("could not build the liver: {e}");
        std::process::exit(1);
    }
    let body = &model.bodies[0];
    println!(
        "liver: {} particles ({} pinned), spacing {:.1} mm, volume {:.0} cm³, mass {:.2} kg, built in {:.0} ms",
        body.count,
        model.pinned.len(),
        body.spacing * 1e3,
        body.volume * 1e6,
        model.mass.iter().sum::<f32>(),
        t.elapsed().as_secs_f64() * 1e3
    );
    let settings = SolverSettings::default();
    let mut solver = Solver::new(&model, settings).expect("valid settings");
    let mut state = State::new(&model);
    let free: Vec<usize> = (0..model.particle_count())
        .filter(|i| !model.pinned.contains(&(*i as u32)))
        .collect();
    let mean_y = |s: &State| free.iter().map(|&i| s.x[i].y).sum::<f32>() / free.len() as f32;
    let y0 = mean_y(&state);
    let steps = 240;
    let t = Instant::now();
    for step in 0..steps {
        // A probe sphere (1.5 cm) moves down into the right lobe during the second second.
        let time = step as f32 / 60.0;
        let depth = ((time - 1.0).clamp(0.0, 1.0) * std::f32::consts::PI).sin() * 0.03;
        let mut probe = Collider::new(
            ColliderShape::Sphere { radius: 0.015 },
            Vec3::new(0.05, 0.08 - depth, 0.0),
            Quat::IDENTITY,
        );
        probe.friction = 0.3;
        let control = Control {
            colliders: vec![probe],
        };
        match solver.step(&model, &mut state, &control) {
            Ok(stats) => {
                if step % 30 == 0 || step == steps - 1 {
                    println!(
                        "step {step:4} t = {time:.2} s: mean sag {:.1} mm, probe force {:.3} N, residual {:.2e}",
                        (y0 - mean_y(&state)) * 1e3,
                        stats.collider_forces[0].length(),
                        solver.residual(&model, &state)
                    );
                }
            }
            Err(e) => {
                eprintln!("step {step}: {e}");
                std::process::exit(2);
            }
        }
    }
    println!(
        "{steps} steps in {:.2} s ({:.1} ms per step, Newton–multigrid, {} Newton iteration(s) of {} V-cycles a step)",
        t.elapsed().as_secs_f64(),
        t.elapsed().as_secs_f64() * 1e3 / steps as f64,
        SolverSettings::default().newton_iterations,
        SolverSettings::default().newton_cycles
    );
}
