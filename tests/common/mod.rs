//! Test helpers: the third-party meshes in ../shared/meshes and small utilities.
#![allow(dead_code)]

use bevy_tissue::core::mesh::TriMesh;
use glam::Vec3;
use std::path::PathBuf;

/// The folder of third-party test meshes: `$BEVY_TISSUE_MESHES`, else `../shared/meshes`
/// beside the crate. `None` (the tests say they were skipped) on a user's clone without
/// it; under CI (`CI=true`) a missing folder is a failure.
pub fn meshes_dir() -> Option<PathBuf> {
    let dir = std::env::var_os("BEVY_TISSUE_MESHES")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/meshes"));
    if dir.is_dir() {
        return Some(dir);
    }
    if ci() {
        panic!(
            "CI=true but the shared meshes folder {} is missing",
            dir.display()
        );
    }
    eprintln!("skipped: shared meshes folder {} not found", dir.display());
    None
}

/// Loads an OBJ file (polygons triangulated, vertices unmerged as in the file).
pub fn load_obj(path: &std::path::Path) -> TriMesh {
    let (models, _) = tobj::load_obj(
        path,
        &tobj::LoadOptions {
            triangulate: true,
            single_index: true,
            ..Default::default()
        },
    )
    .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut mesh = TriMesh::default();
    for m in models {
        let base = mesh.positions.len() as u32;
        mesh.positions.extend(
            m.mesh
                .positions
                .chunks_exact(3)
                .map(|p| Vec3::new(p[0], p[1], p[2])),
        );
        mesh.indices.extend(m.mesh.indices.iter().map(|i| i + base));
    }
    mesh
}

/// Loads a binary or ASCII STL file as an indexed mesh.
pub fn load_stl(path: &std::path::Path) -> TriMesh {
    let mut f = std::fs::File::open(path).unwrap();
    let m = stl_io::read_stl(&mut f).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    TriMesh::new(
        m.vertices
            .iter()
            .map(|v| Vec3::new(v[0], v[1], v[2]))
            .collect(),
        m.faces
            .iter()
            .flat_map(|f| f.vertices.iter().map(|&i| i as u32))
            .collect(),
    )
}

/// Loads the boundary surface of a Gmsh MSH v1 tetrahedral mesh (faces of exactly one
/// tetrahedron, oriented away from it).
pub fn load_msh_v1_surface(path: &std::path::Path) -> TriMesh {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let mut nodes = std::collections::HashMap::new();
    let mut positions = Vec::new();
    let mut tets: Vec<[u32; 4]> = Vec::new();
    while let Some(l) = lines.next() {
        match l.trim() {
            "$NOD" => {
                let n: usize = lines.next().unwrap().trim().parse().unwrap();
                for _ in 0..n {
                    let v: Vec<f64> = lines
                        .next()
                        .unwrap()
                        .split_whitespace()
                        .map(|s| s.parse().unwrap())
                        .collect();
                    nodes.insert(v[0] as u64, positions.len() as u32);
                    positions.push(Vec3::new(v[1] as f32, v[2] as f32, v[3] as f32));
                }
            }
            "$ELM" => {
                let n: usize = lines.next().unwrap().trim().parse().unwrap();
                for _ in 0..n {
                    let v: Vec<u64> = lines
                        .next()
                        .unwrap()
                        .split_whitespace()
                        .map(|s| s.parse().unwrap())
                        .collect();
                    // elm-number elm-type reg-phys reg-elem number-of-nodes node-list
                    if v[1] == 4 {
                        let nn = &v[5..9];
                        tets.push([nodes[&nn[0]], nodes[&nn[1]], nodes[&nn[2]], nodes[&nn[3]]]);
                    }
                }
            }
            _ => {}
        }
    }
    let mut faces: std::collections::HashMap<[u32; 3], ([u32; 3], u32)> = Default::default();
    for t in &tets {
        for (f, opp) in [
            ([t[1], t[2], t[3]], t[0]),
            ([t[0], t[3], t[2]], t[1]),
            ([t[0], t[1], t[3]], t[2]),
            ([t[0], t[2], t[1]], t[3]),
        ] {
            let mut key = f;
            key.sort();
            let e = faces.entry(key).or_insert((f, opp));
            e.1 = if e.0 == f { opp } else { u32::MAX };
            if e.0 != f {
                e.0 = [u32::MAX; 3];
            }
        }
    }
    let mut indices = Vec::new();
    for (_, (f, opp)) in faces {
        if f[0] == u32::MAX {
            continue;
        }
        // Orient away from the opposite vertex.
        let [a, b, c] = f.map(|i| positions[i as usize]);
        let n = (b - a).cross(c - a);
        if n.dot(positions[opp as usize] - a) > 0.0 {
            indices.extend([f[0], f[2], f[1]]);
        } else {
            indices.extend(f);
        }
    }
    TriMesh::new(positions, indices)
}

/// Deterministic pseudo-random numbers (xorshift), no dependency.
pub struct Rng(pub u64);
impl Rng {
    pub fn next_f32(&mut self) -> f32 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 40) as f32 / (1u64 << 24) as f32
    }
    pub fn vec3(&mut self) -> Vec3 {
        Vec3::new(self.next_f32(), self.next_f32(), self.next_f32())
    }
}

/// The skinned render-surface positions of body 0 at particle positions `x`.
pub fn skinned(model: &bevy_tissue::core::model::Model, x: &[Vec3]) -> Vec<Vec3> {
    let skin = &model.bodies[0].skin;
    let f = bevy_tissue::core::solver::Solver::deformation_gradients(model, x);
    let mut out = vec![Vec3::ZERO; skin.rest_vertices.len()];
    bevy_tissue::core::skin::skin_positions(skin, x, &model.rest, &f, &mut out);
    out
}

/// Enclosed volume (m³) of a triangle list over `positions`.
pub fn enclosed_volume(positions: &[Vec3], indices: &[u32]) -> f64 {
    let p64: Vec<glam::DVec3> = positions.iter().map(|p| p.as_dvec3()).collect();
    let tris: Vec<[u32; 3]> = indices
        .chunks_exact(3)
        .map(|t| [t[0], t[1], t[2]])
        .collect();
    bevy_tissue::core::mesh::signed_volume(&p64, &tris)
}

/// An example binary: `cargo test` builds the examples next to the test's own
/// executable (`target/<profile>/examples/`).
pub fn example(name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("test executable");
    let dir = exe
        .parent()
        .and_then(|d| d.parent())
        .expect("target/<profile>/deps");
    dir.join("examples").join(name)
}

/// Under `CI=true` nothing may be skipped (a missing GPU or Xvfb is a failure).
pub fn ci() -> bool {
    std::env::var("CI").is_ok_and(|v| v == "true")
}

/// The largest distance between corresponding points of `a` and `b`, m.
pub fn max_distance(a: &[Vec3], b: &[Vec3]) -> f32 {
    a.iter()
        .zip(b)
        .map(|(p, q)| p.distance(*q))
        .fold(0.0f32, f32::max)
}

/// The largest drop of any point of `x` below its rest position `rest` (m, along −y).
pub fn max_sag(x: &[Vec3], rest: &[Vec3]) -> f32 {
    x.iter()
        .zip(rest)
        .map(|(p, r)| r.y - p.y)
        .fold(0.0f32, f32::max)
}

/// A plugin body (`body`, `pinned`, built from `mesh` placed at `at`) built and stepped
/// `steps` times on the core directly with the plugin's CPU-path settings
/// (`TissueSettings::to_core_cpu`): what the plugin's CPU path must reproduce.
pub fn cpu_path_reference(
    body: &bevy_tissue::prelude::SoftBody,
    pinned: &bevy_tissue::prelude::Pinned,
    mesh: &bevy::prelude::Mesh,
    at: Vec3,
    settings: &bevy_tissue::prelude::TissueSettings,
    steps: u64,
) -> (bevy_tissue::core::model::Model, Vec<Vec3>) {
    use bevy::prelude::{GlobalTransform, Transform};
    use bevy_tissue::core::solver::{Control, Solver, State};
    use bevy_tissue::plugin::build::{body_desc, tri_mesh};
    let to_world = GlobalTransform::from(Transform::from_translation(at));
    let tri = tri_mesh(mesh, &to_world).expect("a triangle mesh");
    let mut model = bevy_tissue::core::model::Model::new();
    model
        .add_body(&tri, &body_desc(body, Some(pinned), &to_world))
        .expect("the body builds");
    let mut solver = Solver::new(&model, settings.to_core_cpu()).expect("settings");
    let mut state = State::new(&model);
    for _ in 0..steps {
        solver
            .step(&model, &mut state, &Control::default())
            .expect("a step");
    }
    (model, state.x)
}

/// A lattice box of half extents `half` (8 mm spacing, E = 20 kPa, ν = 0.3) centred at
/// `at`: the core's contact and falling scenes.
pub fn lattice_box_at(half: Vec3, at: Vec3) -> bevy_tissue::core::model::Model {
    lattice_box_pinned(half, at, Vec::new())
}

/// [`lattice_box_at`] with the particles in `pins` (body frame) pinned.
pub fn lattice_box_pinned(
    half: Vec3,
    at: Vec3,
    pins: Vec<bevy_tissue::core::model::PinRegion>,
) -> bevy_tissue::core::model::Model {
    use bevy_tissue::core::model::{BodyDesc, Discretisation, Material, Model};
    let mut model = Model::new();
    model
        .add_body(
            &bevy_tissue::core::procedural::cuboid(half, 2),
            &BodyDesc {
                resolution: bevy_tissue::core::sampling::Resolution::Spacing(0.008),
                material: Material::Hyperelastic {
                    youngs_modulus: 20e3,
                    poisson_ratio: 0.3,
                },
                discretisation: Discretisation::Lattice,
                translation: at,
                pins,
                ..Default::default()
            },
        )
        .unwrap();
    model
}

/// A 12 × 5 × 5 cm lattice body of about 400 particles (E = 50 kPa, ν = 0.4), pinned at
/// its −x end (the plugin tests' accurate body).
pub fn lattice_body() -> (
    bevy_tissue::plugin::components::SoftBody,
    bevy_tissue::plugin::components::Pinned,
) {
    use bevy_tissue::plugin::components::*;
    (
        SoftBody {
            resolution: TissueResolution::Particles(400),
            material: TissueMaterial::Hyperelastic {
                youngs_modulus: 50_000.0,
                poisson_ratio: 0.4,
            },
            discretisation: TissueDiscretisation::Lattice,
            ..Default::default()
        },
        Pinned::region(PinShape::HalfSpace {
            point: Vec3::new(-0.05, 0.0, 0.0),
            normal: -Vec3::X,
        }),
    )
}

/// An organ scene of the rest-and-hang checks: `mesh` centred and scaled to 20 cm, one
/// lattice body of `particles` particles (E = 5 kPa, ν = 0.45, 1060 kg/m³), pinned in its
/// top 10% when `hang`; with the height (m) of a ground 5 mm below it, for the resting
/// scene.
pub fn organ(
    mesh: &TriMesh,
    particles: u32,
    hang: bool,
) -> Result<(bevy_tissue::core::model::Model, f32), bevy_tissue::core::TissueError> {
    use bevy_tissue::core::model::{BodyDesc, Discretisation, Material, Model, PinRegion};
    let (lo, hi) = mesh
        .bounds()
        .ok_or(bevy_tissue::core::TissueError::InvalidParameter {
            name: "mesh",
            value: "no vertices".into(),
            expected: "a surface mesh",
        })?;
    let scale = 0.2 / (hi - lo).max_element();
    let centre = (lo + hi) * 0.5;
    let mut scaled = mesh.clone();
    for p in &mut scaled.positions {
        *p = (*p - centre) * scale;
    }
    let (top, bottom) = ((hi.y - centre.y) * scale, (lo.y - centre.y) * scale);
    let mut model = Model::new();
    model.add_body(
        &scaled,
        &BodyDesc {
            resolution: bevy_tissue::core::sampling::Resolution::Particles(particles),
            material: Material::Hyperelastic {
                youngs_modulus: 5e3,
                poisson_ratio: 0.45,
            },
            density: 1060.0,
            discretisation: Discretisation::Lattice,
            pins: if hang {
                vec![PinRegion::HalfSpace {
                    point: Vec3::new(0.0, top - 0.1 * (top - bottom), 0.0),
                    normal: Vec3::Y,
                }]
            } else {
                vec![]
            },
            ..Default::default()
        },
    )?;
    let ground = bottom - model.bodies[0].radius - 0.005;
    Ok((model, ground))
}
