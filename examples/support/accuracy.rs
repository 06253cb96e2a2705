//! The accuracy scenes, each measured against the independent finite-element reference
//! (`bevy_tissue::core::fem`: quadratic tetrahedra, f64): a cantilever under its own
//! weight, a cube squeezed between frictionless plates (its Poisson ratio, and its volume
//! at ν = 0.49), and a liver (`liver2.msh`) hanging from a region under gravity.
//! Shared by `examples/accuracy.rs` and `tests/accuracy.rs`.
#![allow(dead_code)]

use bevy_tissue::core::TissueError;
use bevy_tissue::core::colliders::{Collider, ColliderShape};
use bevy_tissue::core::fem::{Fem, FemError, Solution, TetMesh};
use bevy_tissue::core::hierarchy::HierarchyDesc;
use bevy_tissue::core::mesh::TriMesh;
use bevy_tissue::core::model::{BodyDesc, Discretisation, Material, Model, PinRegion};
use bevy_tissue::core::procedural;
use bevy_tissue::core::sampling::Resolution;
use bevy_tissue::core::solver::{Control, ElementSolver, Method, Solver, SolverSettings, State};
use bevy_tissue::core::statics::{StaticLoad, solve_static};
use glam::{DVec3, Quat, Vec3};

/// The cantilever: length (m, along x from the clamp at x = 0).
pub const BAR_LENGTH: f64 = 0.24;
/// The cantilever's square section, m.
pub const BAR_THICKNESS: f64 = 0.03;
/// The cantilever's Young's modulus, Pa.
pub const BAR_E: f32 = 100e3;
/// The cantilever's Poisson ratio.
pub const BAR_NU: f32 = 0.3;
/// Density of the bar and the cube, kg/m³.
pub const DENSITY: f32 = 1000.0;
/// The cantilever's gravity, m/s² (small: the tip drops under 5% of the length).
pub const BAR_GRAVITY: f64 = 0.2;
/// Euler–Bernoulli's tip deflection `q L⁴ / (8 E I)` of the cantilever, m.
pub fn euler_bernoulli_tip() -> f64 {
    let a = BAR_THICKNESS * BAR_THICKNESS;
    let q = DENSITY as f64 * a * BAR_GRAVITY;
    let i = BAR_THICKNESS.powi(4) / 12.0;
    q * BAR_LENGTH.powi(4) / (8.0 * BAR_E as f64 * i)
}

/// Edge of the compression cube, m.
pub const CUBE: f64 = 0.06;
/// The compression cube's Young's modulus, Pa.
pub const CUBE_E: f32 = 20e3;

/// The liver: Young's modulus (Pa), Poisson ratio and density (kg/m³) of the accuracy
/// scene, and its gravity (m/s², small so that the sag stays in small strain).
pub const LIVER_E: f32 = 5e3;
/// The liver's Poisson ratio.
pub const LIVER_NU: f32 = 0.45;
/// The liver's density, kg/m³.
pub const LIVER_DENSITY: f32 = 1060.0;
/// The liver scene's gravity, m/s².
pub const LIVER_GRAVITY: f64 = 0.5;
/// The liver's longest side after scaling, m.
pub const LIVER_SIZE: f64 = 0.2;
/// The liver is held by the particles (and FEM nodes) in the top slab of this fraction
/// of its height.
pub const LIVER_PIN_SLAB: f64 = 0.15;

/// A discretisation to measure: the hexahedral lattice, or the paper's clusters with K.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Disc {
    /// Hexahedral lattice elements.
    Lattice,
    /// KNN clusters with K neighbours.
    Clusters(u32),
}

impl Disc {
    /// Label for tables.
    pub fn name(&self) -> String {
        match self {
            Disc::Lattice => "lattice hexahedra".into(),
            Disc::Clusters(k) => format!("clusters K={k}"),
        }
    }

    fn core(&self) -> (Discretisation, u32) {
        match *self {
            Disc::Lattice => (Discretisation::Lattice, 32),
            Disc::Clusters(k) => (Discretisation::Clusters, k),
        }
    }

    /// Lattice spacing (m) that puts `across` particles across a side `side` (m): the
    /// lattice's nodes lie on the faces (`across − 1` cells), the clusters' particles at
    /// half a spacing inside them (the sampling lattice is centred; the spacing is nudged
    /// so that rounding cannot put a row on a face).
    pub fn spacing(&self, side: f64, across: u32) -> f64 {
        match self {
            Disc::Lattice => side / (across.max(2) - 1) as f64,
            Disc::Clusters(_) => side / across.max(1) as f64 * (1.0 + 1e-4),
        }
    }
}

/// The cantilever's first bending frequency (Euler–Bernoulli, clamped–free),
/// `ω₁ = 1.875² √(E I / (ρ A L⁴))`, rad/s, for Young's modulus `e` (Pa).
pub fn bar_first_mode(e: f64) -> f64 {
    let a = BAR_THICKNESS * BAR_THICKNESS;
    let i = BAR_THICKNESS.powi(4) / 12.0;
    1.875f64.powi(2) * (e * i / (DENSITY as f64 * a * BAR_LENGTH.powi(4))).sqrt()
}

/// A box mesh from `lo` to `hi` (m).
pub fn box_mesh(lo: DVec3, hi: DVec3) -> TriMesh {
    let half = ((hi - lo) * 0.5).as_vec3();
    let centre = ((hi + lo) * 0.5).as_vec3();
    let mut m = procedural::cuboid(half, 2);
    for p in &mut m.positions {
        *p += centre;
    }
    m
}

fn build(
    mesh: &TriMesh,
    disc: Disc,
    spacing: f64,
    material: Material,
    density: f32,
    pins: Vec<PinRegion>,
    hierarchy: Option<HierarchyDesc>,
) -> Result<Model, TissueError> {
    let (discretisation, k) = disc.core();
    let desc = BodyDesc {
        resolution: Resolution::Spacing(spacing as f32),
        density,
        neighbours: k,
        material,
        pins,
        discretisation,
        hierarchy,
        ..Default::default()
    };
    let mut model = Model::new();
    model.add_body(mesh, &desc)?;
    Ok(model)
}

/// The cantilever with `across` particles across its thickness, clamped at x = 0: the
/// lattice's nodes on that face, the clusters' first layer of particles.
pub fn bar_model(disc: Disc, across: u32) -> Result<Model, TissueError> {
    bar_model_with(disc, across, BAR_E)
}

/// [`bar_model`] with Young's modulus `youngs_modulus` (Pa).
pub fn bar_model_with(disc: Disc, across: u32, youngs_modulus: f32) -> Result<Model, TissueError> {
    bar_body(
        disc,
        across,
        Material::Hyperelastic {
            youngs_modulus,
            poisson_ratio: BAR_NU,
        },
        None,
    )
}

/// [`bar_model`] of any material, with an optional hierarchy (clusters only).
pub fn bar_body(
    disc: Disc,
    across: u32,
    material: Material,
    hierarchy: Option<HierarchyDesc>,
) -> Result<Model, TissueError> {
    let t = BAR_THICKNESS;
    let mesh = box_mesh(
        DVec3::new(0.0, -0.5 * t, -0.5 * t),
        DVec3::new(BAR_LENGTH, 0.5 * t, 0.5 * t),
    );
    let s = disc.spacing(t, across);
    let clamp = match disc {
        Disc::Lattice => 0.25 * s,
        Disc::Clusters(_) => s,
    };
    build(
        &mesh,
        disc,
        s,
        material,
        DENSITY,
        vec![PinRegion::HalfSpace {
            point: Vec3::new(clamp as f32, 0.0, 0.0),
            normal: -Vec3::X,
        }],
        hierarchy,
    )
}

/// The particles of the bar's last layer (the tip): within a quarter spacing of the
/// largest x.
pub fn bar_tip_particles(model: &Model) -> Vec<usize> {
    let xmax = model.rest.iter().map(|p| p.x).fold(f32::MIN, f32::max);
    let s = model.bodies[0].spacing;
    (0..model.particle_count())
        .filter(|&i| model.rest[i].x > xmax - 0.25 * s)
        .collect()
}

/// Mean downward displacement (m) of the tip particles for displacements `u`.
pub fn bar_tip(model: &Model, u: &[DVec3]) -> f64 {
    let tip = bar_tip_particles(model);
    -tip.iter().map(|&i| u[i].y).sum::<f64>() / tip.len() as f64
}

/// The FEM reference of the cantilever with `cells` tetrahedral cells (each split in 6)
/// across the thickness and 8× that along the length, clamped at x = 0.
pub fn bar_fem(cells: usize) -> Result<Solution, FemError> {
    let t = BAR_THICKNESS;
    let mesh = TetMesh::box_mesh(
        DVec3::new(0.0, -0.5 * t, -0.5 * t),
        DVec3::new(BAR_LENGTH, 0.5 * t, 0.5 * t),
        [8 * cells, cells, cells],
    )?;
    let mut fem = Fem::new(&mesh, BAR_E as f64, BAR_NU as f64)?;
    fem.fix_nodes(|p| p.x <= 1e-12, [true; 3], DVec3::ZERO);
    fem.gravity(DENSITY as f64, DVec3::new(0.0, -BAR_GRAVITY, 0.0));
    fem.solve(1e-10)
}

/// The FEM's mean downward displacement (m) at the rest positions of the model's tip
/// particles (the clusters' tip layer lies half a spacing inside the end face).
pub fn bar_fem_tip_at(fem: &Solution, model: &Model) -> f64 {
    let tip = bar_tip_particles(model);
    let eps = 1e-9;
    let mut sum = 0.0;
    for &i in &tip {
        let p = model.rest[i].as_dvec3();
        let q = p.clamp(
            DVec3::new(eps, -0.5 * BAR_THICKNESS + eps, -0.5 * BAR_THICKNESS + eps),
            DVec3::new(
                BAR_LENGTH - eps,
                0.5 * BAR_THICKNESS - eps,
                0.5 * BAR_THICKNESS - eps,
            ),
        );
        sum += fem.displacement_at(q).map_or(f64::NAN, |u| -u.y);
    }
    sum / tip.len() as f64
}

/// The bar's static tip deflection (m) under the linearised energy of `model` and
/// gravity [`BAR_GRAVITY`].
pub fn bar_static_tip(model: &Model) -> Result<(f64, usize), TissueError> {
    bar_static_tip_under(model, BAR_GRAVITY)
}

/// [`bar_static_tip`] under gravity `g` (m/s², downward).
pub fn bar_static_tip_under(model: &Model, g: f64) -> Result<(f64, usize), TissueError> {
    let sol = solve_static(
        model,
        &StaticLoad {
            gravity: DVec3::new(0.0, -g, 0.0),
            constraints: vec![],
        },
        1e-9,
    )?;
    Ok((bar_tip(model, &sol.displacement), sol.iterations))
}

/// The compression cube (edge [`CUBE`], from the origin) with `across` particles along
/// each edge and Poisson ratio `nu`.
pub fn cube_model(disc: Disc, across: u32, nu: f32) -> Result<Model, TissueError> {
    cube_body(
        disc,
        across,
        Material::Hyperelastic {
            youngs_modulus: CUBE_E,
            poisson_ratio: nu,
        },
        None,
    )
}

/// [`cube_model`] of any material, with an optional hierarchy (clusters only).
pub fn cube_body(
    disc: Disc,
    across: u32,
    material: Material,
    hierarchy: Option<HierarchyDesc>,
) -> Result<Model, TissueError> {
    let mesh = box_mesh(DVec3::ZERO, DVec3::splat(CUBE));
    build(
        &mesh,
        disc,
        disc.spacing(CUBE, across),
        material,
        DENSITY,
        vec![],
        hierarchy,
    )
}

/// Indices of the particles in the model's outermost layer on the `axis` side `high`.
pub fn layer(model: &Model, axis: usize, high: bool) -> Vec<usize> {
    let s = model.bodies[0].spacing;
    let ext = model.rest.iter().map(|p| p[axis]);
    let edge = if high {
        ext.fold(f32::MIN, f32::max)
    } else {
        ext.fold(f32::MAX, f32::min)
    };
    (0..model.particle_count())
        .filter(|&i| (model.rest[i][axis] - edge).abs() < 0.25 * s)
        .collect()
}

/// Mean coordinate `axis` of particles `ids` at positions `x`.
fn mean_coord(x: &[Vec3], ids: &[usize], axis: usize) -> f64 {
    ids.iter().map(|&i| x[i][axis] as f64).sum::<f64>() / ids.len().max(1) as f64
}

/// The particles' own strains along `axis`: the change of the distance between the two
/// outermost layers, relative to their rest distance.
pub fn layer_strain(model: &Model, x: &[Vec3], axis: usize) -> f64 {
    let (lo, hi) = (layer(model, axis, false), layer(model, axis, true));
    let rest = mean_coord(&model.rest, &hi, axis) - mean_coord(&model.rest, &lo, axis);
    (mean_coord(x, &hi, axis) - mean_coord(x, &lo, axis)) / rest - 1.0
}

/// Poisson ratio measured from positions `x` of a cube squeezed along y: `−ε_lateral /
/// ε_axial`, both from the particles' own layers (x and z averaged).
pub fn measured_poisson(model: &Model, x: &[Vec3]) -> f64 {
    let axial = layer_strain(model, x, 1);
    let lateral = 0.5 * (layer_strain(model, x, 0) + layer_strain(model, x, 2));
    -lateral / axial
}

/// Static Poisson test of the linearised energy: the bottom layer held at y, the top
/// layer moved down by 5% of the height, the x-low and z-low layers held on their axis
/// (frictionless rollers, which the homogeneous solution satisfies). Returns the
/// measured Poisson ratio.
pub fn cube_static_poisson(model: &Model) -> Result<f64, TissueError> {
    let height = layer_distance(model, 1);
    let mut constraints = Vec::new();
    for i in layer(model, 1, false) {
        constraints.push((i as u32, [false, true, false], DVec3::ZERO));
    }
    for i in layer(model, 1, true) {
        constraints.push((
            i as u32,
            [false, true, false],
            DVec3::new(0.0, -0.05 * height, 0.0),
        ));
    }
    for (axis, held) in [(0usize, [true, false, false]), (2, [false, false, true])] {
        for i in layer(model, axis, false) {
            constraints.push((i as u32, held, DVec3::ZERO));
        }
    }
    let sol = solve_static(
        model,
        &StaticLoad {
            gravity: DVec3::ZERO,
            constraints,
        },
        1e-10,
    )?;
    let x: Vec<Vec3> = model
        .rest
        .iter()
        .zip(&sol.displacement)
        .map(|(r, u)| *r + u.as_vec3())
        .collect();
    Ok(measured_poisson(model, &x))
}

fn layer_distance(model: &Model, axis: usize) -> f64 {
    let (lo, hi) = (layer(model, axis, false), layer(model, axis, true));
    mean_coord(&model.rest, &hi, axis) - mean_coord(&model.rest, &lo, axis)
}

/// The homogeneous answer of uniaxial compression between frictionless plates for the
/// fixed-corotated material (`Ψ = μ‖F − R‖² + λ/2 (det F − 1)²`) at axial stretch `a`:
/// the lateral stretch `b` with zero lateral stress, `2μ(b − 1) + λ(ab² − 1)ab = 0`
/// (Newton from b = 1). What any converged discretisation that reproduces homogeneous
/// states gives; the small-strain limit is `b − 1 = −ν (a − 1)`.
pub fn uniaxial_lateral_stretch(e: f64, nu: f64, a: f64) -> f64 {
    let mu = e / (2.0 * (1.0 + nu));
    let la = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu));
    let mut b = 1.0 - nu * (a - 1.0);
    for _ in 0..50 {
        let f = 2.0 * mu * (b - 1.0) + la * (a * b * b - 1.0) * a * b;
        let df = 2.0 * mu + la * (3.0 * a * a * b * b - a);
        let step = f / df;
        b -= step;
        if step.abs() < 1e-15 {
            break;
        }
    }
    b
}

/// The plates of a dynamic compression: the ground under the cube and a plate above it
/// moving down by `squeeze` of the height over the first 60% of `steps`, both
/// frictionless, touching the particles at their contact radius.
pub fn plates(model: &Model, squeeze: f32, step: usize, steps: usize) -> Vec<Collider> {
    let r = model.bodies[0].radius;
    let top0 = model.rest.iter().map(|p| p.y).fold(f32::MIN, f32::max) + r;
    let bottom = model.rest.iter().map(|p| p.y).fold(f32::MAX, f32::min) - r;
    let ramp = (0.6 * steps as f32).max(1.0);
    let f = ((step + 1) as f32 / ramp).min(1.0);
    let y = top0 - squeeze * (top0 - bottom - 2.0 * r) * f;
    let mut ground = Collider::ground(bottom);
    ground.friction = 0.0;
    let mut plate = Collider::new(
        ColliderShape::Plane,
        Vec3::new(0.0, y, 0.0),
        Quat::from_rotation_x(std::f32::consts::PI),
    );
    plate.friction = 0.0;
    vec![ground, plate]
}

/// How a scene is time-stepped: 1/60 s steps of `substeps` × `iterations`, the method,
/// the consistent multiplier warm start, damping (1/s); no particle contacts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stepping {
    /// Substeps per 1/60 s step.
    pub substeps: u32,
    /// Iterations per substep.
    pub iterations: u32,
    /// Gauss–Seidel or Jacobi.
    pub method: Method,
    /// [`SolverSettings::warm_start`].
    pub warm_start: bool,
    /// XPBD or vertex block descent for lattice elements.
    pub element_solver: ElementSolver,
    /// Velocity damping, 1/s.
    pub damping: f32,
}

impl Stepping {
    /// The converged setting of the accuracy study: Gauss–Seidel, 4 × 30, damping 4/s.
    pub const CONVERGED: Self = Self {
        substeps: 4,
        iterations: 30,
        method: Method::GaussSeidel,
        warm_start: false,
        element_solver: ElementSolver::Xpbd,
        damping: 4.0,
    };

    /// Label for tables.
    pub fn label(&self) -> String {
        format!(
            "{} {} × {}{}",
            match (self.element_solver, self.method) {
                (ElementSolver::VertexDescent, _) => "VBD",
                (ElementSolver::Multigrid, _) => "Newton-MG",
                (_, Method::GaussSeidel) => "GS",
                (_, Method::Jacobi) => "Jacobi",
            },
            self.substeps,
            self.iterations,
            if self.warm_start { ", warm start" } else { "" }
        )
    }

    /// The solver settings under `gravity`.
    pub fn settings(&self, gravity: Vec3) -> SolverSettings {
        SolverSettings {
            substeps: self.substeps,
            iterations: self.iterations,
            gravity,
            damping: self.damping,
            method: self.method,
            warm_start: self.warm_start,
            element_solver: self.element_solver,
            // Every iteration a Newton iteration of one V-cycle under Newton–multigrid.
            newton_iterations: 0,
            newton_cycles: 1,
            threads: if self.method == Method::GaussSeidel {
                1
            } else {
                0
            },
            particle_contacts: false,
            coarse_iterations: 0,
            ..Default::default()
        }
    }
}

/// Time-steps `model` under `gravity` for `seconds` with `stepping`, with the
/// compression plates when `squeeze > 0`. Returns the final positions and the wall
/// time per step (ms), or the error of a diverged step.
pub fn settle(
    model: &Model,
    gravity: Vec3,
    squeeze: f32,
    seconds: f32,
    stepping: &Stepping,
) -> Result<(Vec<Vec3>, f64), TissueError> {
    let mut solver = Solver::new(model, stepping.settings(gravity))?;
    let mut state = State::new(model);
    let steps = (seconds * 60.0).round() as usize;
    let t = std::time::Instant::now();
    for step in 0..steps {
        let control = Control {
            colliders: if squeeze > 0.0 {
                plates(model, squeeze, step, steps)
            } else {
                vec![]
            },
        };
        solver.step(model, &mut state, &control)?;
    }
    Ok((
        state.x,
        t.elapsed().as_secs_f64() * 1e3 / steps.max(1) as f64,
    ))
}

/// Displacements of positions `x` from the rest positions, m.
pub fn displacements(model: &Model, x: &[Vec3]) -> Vec<DVec3> {
    model
        .rest
        .iter()
        .zip(x)
        .map(|(r, p)| (*p - *r).as_dvec3())
        .collect()
}

/// The material volume of positions `x`: `Σ_e V_e det F_e` over a lattice body's
/// elements, or `Σ_c V_c det F_c` over a cluster body's clusters, m³.
pub fn material_volume(model: &Model, x: &[Vec3]) -> f64 {
    if !model.elements.is_empty() {
        return model
            .elements
            .iter()
            .zip(&model.element_rest)
            .map(|(nodes, r)| {
                let f = bevy_tissue::core::element::element_gradient(
                    &nodes.map(|j| x[j as usize]),
                    r.size,
                );
                r.volume as f64 * f.determinant() as f64
            })
            .sum();
    }
    Solver::deformation_gradients(model, x)
        .iter()
        .zip(&model.cluster_volume)
        .map(|(f, &v)| (v * f.determinant()) as f64)
        .sum()
}

/// The liver's tetrahedral mesh (`liver2.msh`), scaled so that its longest side is
/// [`LIVER_SIZE`] with its lowest corner at the origin.
pub fn liver_tets(msh_text: &str) -> Result<TetMesh, FemError> {
    let raw = TetMesh::from_gmsh_v1(msh_text)?;
    let (lo, hi) = raw.bounds();
    let scale = LIVER_SIZE / (hi - lo).max_element();
    Ok(raw.transformed(scale, -lo * scale))
}

/// The liver's surface (the tetrahedral mesh's boundary) as a render mesh.
pub fn liver_surface(tets: &TetMesh) -> TriMesh {
    TriMesh::new(
        tets.nodes.iter().map(|p| p.as_vec3()).collect(),
        tets.boundary_triangles()
            .iter()
            .flatten()
            .copied()
            .collect(),
    )
}

/// The top of the liver's pinned slab (y, m).
pub fn liver_pin_y(tets: &TetMesh) -> f64 {
    let (lo, hi) = tets.bounds();
    hi.y - LIVER_PIN_SLAB * (hi.y - lo.y)
}

/// The liver as a model at lattice spacing `spacing` (m), held in its top slab.
pub fn liver_model(tets: &TetMesh, disc: Disc, spacing: f64) -> Result<Model, TissueError> {
    build(
        &liver_surface(tets),
        disc,
        spacing,
        Material::Hyperelastic {
            youngs_modulus: LIVER_E,
            poisson_ratio: LIVER_NU,
        },
        LIVER_DENSITY,
        vec![PinRegion::HalfSpace {
            point: Vec3::new(0.0, liver_pin_y(tets) as f32, 0.0),
            normal: Vec3::Y,
        }],
        None,
    )
}

/// The FEM reference of the liver after `refinements` 1→8 refinements of its mesh:
/// nodes in the top slab held, gravity down.
pub fn liver_fem(tets: &TetMesh, refinements: u32) -> Result<Solution, FemError> {
    let mut mesh = tets.clone();
    for _ in 0..refinements {
        mesh = mesh.refine();
    }
    let mut fem = Fem::new(&mesh, LIVER_E as f64, LIVER_NU as f64)?;
    let y = liver_pin_y(tets);
    fem.fix_nodes(|p| p.y >= y, [true; 3], DVec3::ZERO);
    fem.gravity(LIVER_DENSITY as f64, DVec3::new(0.0, -LIVER_GRAVITY, 0.0));
    fem.solve(1e-10)
}

/// The liver's sag: the mass-weighted mean downward displacement of the whole body
/// (m), for displacements `u` of the model's particles.
pub fn mean_sag(model: &Model, u: &[DVec3]) -> f64 {
    let m: f64 = model.mass.iter().map(|&m| m as f64).sum();
    -model
        .mass
        .iter()
        .zip(u)
        .map(|(&mi, ui)| mi as f64 * ui.y)
        .sum::<f64>()
        / m
}

/// The liver model's static sag (m) under the linearised energy.
pub fn liver_static_sag(model: &Model) -> Result<(f64, usize), TissueError> {
    let sol = solve_static(
        model,
        &StaticLoad {
            gravity: DVec3::new(0.0, -LIVER_GRAVITY, 0.0),
            constraints: vec![],
        },
        1e-9,
    )?;
    Ok((mean_sag(model, &sol.displacement), sol.iterations))
}

/// RMS distance (m) of positions `x` from `model`'s rest shape after the best rigid
/// fit (mass-weighted; the rotation of `Σ m (x − c_x)(X − c_X)ᵀ`, taken from four
/// starts half a turn apart so that the iteration cannot stop at a saddle).
pub fn rigid_fit_error(model: &Model, x: &[Vec3]) -> f32 {
    use bevy_tissue::core::constraints::{extract_rotation, outer};
    let (rest, mass) = (&model.rest, &model.mass);
    let m: f32 = mass.iter().sum();
    let cx = x.iter().zip(mass).map(|(p, &w)| *p * w).sum::<Vec3>() / m;
    let cr = rest.iter().zip(mass).map(|(p, &w)| *p * w).sum::<Vec3>() / m;
    let mut a = glam::Mat3::ZERO;
    for ((p, r), &w) in x.iter().zip(rest).zip(mass) {
        a += outer(*p - cx, *r - cr) * w;
    }
    [
        Quat::IDENTITY,
        Quat::from_rotation_x(std::f32::consts::PI),
        Quat::from_rotation_y(std::f32::consts::PI),
        Quat::from_rotation_z(std::f32::consts::PI),
    ]
    .iter()
    .map(|&q0| {
        let mut q = q0;
        extract_rotation(&a, &mut q, 200);
        let r = glam::Mat3::from_quat(q);
        let s: f32 = x
            .iter()
            .zip(rest)
            .zip(mass)
            .map(|((p, q0), &w)| w * (*p - cx - r * (*q0 - cr)).length_squared())
            .sum();
        (s / m).sqrt()
    })
    .fold(f32::INFINITY, f32::min)
}
