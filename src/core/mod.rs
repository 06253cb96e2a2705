//! The simulation core: no Bevy dependency beyond glam (Bevy's math), so it is easy to
//! test and serves as the reference the GPU path is checked against.
//!
//! * [`mesh`] — closed-surface checks, welding, the lattice inside test;
//! * [`sampling`] — particles on a lattice from a spacing or a count;
//! * [`hierarchy`] — the particle levels of hierarchical PBD (Müller 2008);
//! * [`knn`] — uniform grid (counting sort) and exact K nearest neighbours;
//! * [`constraints`] — shape matching, stable neo-Hookean XPBD, contacts (pure functions);
//! * [`element`] — hexahedral elements on the lattice (centre gradient + hourglass modes);
//! * [`colliders`] — kinematic plane, sphere, capsule and box with friction;
//! * [`colouring`] — cluster colouring for a coloured Gauss–Seidel iteration;
//! * [`dense`] — packed `L D Lᵀ` solves of small dense systems (the multigrid's coarsest);
//! * [`diagnose`] — where a divergence happened, its likely cause and remedy, in words;
//! * [`model`] — the batched rest data of all bodies;
//! * [`multigrid`] — geometric multigrid on lattice bodies (Newton's linear solve);
//! * [`skin`] — the render surface embedded in the particles;
//! * [`solver`] — CPU Gauss–Seidel and Jacobi time stepping;
//! * [`statics`] — static equilibrium of the linearised energy (accuracy studies);
//! * [`fem`] — an independent static finite-element reference (quadratic tetrahedra, f64);
//! * [`procedural`] — shapes made in code (sphere, box, liver).
//!
//! ```
//! use bevy_tissue::core::{model::*, procedural, sampling::Resolution, solver::*};
//! let mut model = Model::new();
//! let desc = BodyDesc { resolution: Resolution::Particles(300), neighbours: 16, ..Default::default() };
//! model.add_body(&procedural::icosphere(0.1, 2), &desc).unwrap();
//! let mut state = State::new(&model);
//! let mut solver = Solver::new(&model, SolverSettings::default()).unwrap();
//! solver.step(&model, &mut state, &Control::default()).unwrap();
//! assert!(state.x.iter().all(|p| p.is_finite()));
//! ```

pub mod colliders;
pub mod colouring;
pub mod constraints;
pub mod dense;
pub mod diagnose;
pub mod element;
pub mod error;
pub mod fem;
pub mod hierarchy;
pub mod knn;
pub mod mesh;
pub mod model;
pub mod multigrid;
pub mod par;
pub mod procedural;
pub mod sampling;
pub mod skin;
pub mod solver;
pub mod statics;

pub use error::{MeshError, TissueError};
