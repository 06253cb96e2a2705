//! Bad input gets a typed error naming the problem; nothing panics and nothing is added.
use bevy_tissue::core::error::{MeshError, TissueError};
use bevy_tissue::core::mesh::TriMesh;
use bevy_tissue::core::model::{BodyDesc, Material, Model};
use bevy_tissue::core::procedural;
use bevy_tissue::core::sampling::Resolution;
use bevy_tissue::core::solver::{Solver, SolverSettings};
use glam::Vec3;

fn add(mesh: &TriMesh, desc: &BodyDesc) -> Result<usize, TissueError> {
    let mut model = Model::new();
    let r = model.add_body(mesh, desc);
    if r.is_err() {
        assert_eq!(
            model.particle_count(),
            0,
            "a failed add must leave the model untouched"
        );
        assert!(model.bodies.is_empty());
    }
    r
}

fn small() -> BodyDesc {
    BodyDesc {
        resolution: Resolution::Particles(300),
        neighbours: 8,
        discretisation: bevy_tissue::core::model::Discretisation::Clusters,
        ..Default::default()
    }
}

#[test]
fn empty_mesh() {
    let e = add(&TriMesh::default(), &small()).unwrap_err();
    assert_eq!(e, TissueError::Mesh(MeshError::Empty));
    assert!(e.to_string().contains("empty"));
}

#[test]
fn nan_positions() {
    let mut m = procedural::icosphere(0.1, 2);
    m.positions[5].y = f32::NAN;
    m.positions[9].x = f32::INFINITY;
    let e = add(&m, &small()).unwrap_err();
    assert_eq!(
        e,
        TissueError::Mesh(MeshError::NonFinite {
            vertex: 5,
            count: 2
        })
    );
    assert!(e.to_string().contains("NaN"), "{e}");
}

#[test]
fn out_of_range_indices() {
    let mut m = procedural::icosphere(0.1, 2);
    let n = m.positions.len() as u32;
    m.indices[7] = n + 3;
    let e = add(&m, &small()).unwrap_err();
    assert_eq!(
        e,
        TissueError::Mesh(MeshError::IndexOutOfRange {
            index: n + 3,
            vertices: n as usize
        })
    );
    let mut m2 = procedural::icosphere(0.1, 1);
    m2.indices.pop();
    assert!(matches!(
        add(&m2, &small()).unwrap_err(),
        TissueError::Mesh(MeshError::NotTriangles { .. })
    ));
}

#[test]
fn open_and_degenerate_meshes() {
    let mut m = procedural::icosphere(0.1, 2);
    m.indices.truncate(m.indices.len() - 6); // remove two adjacent-ish triangles
    let e = add(&m, &small()).unwrap_err();
    match e {
        TissueError::Mesh(MeshError::NotClosed { boundary_edges }) => assert!(boundary_edges >= 4),
        other => panic!("expected NotClosed, got {other}"),
    }
    assert!(
        e.to_string()
            .starts_with("invalid mesh: surface not closed"),
        "{e}"
    );
    let mut d = procedural::icosphere(0.1, 2);
    d.indices.extend([0, 0, 1]);
    assert_eq!(
        add(&d, &small()).unwrap_err(),
        TissueError::Mesh(MeshError::DegenerateTriangles { count: 1 })
    );
    // One triangle flipped: inconsistent orientation.
    let mut f = procedural::icosphere(0.1, 2);
    f.indices.swap(0, 1);
    assert!(matches!(
        add(&f, &small()).unwrap_err(),
        TissueError::Mesh(MeshError::InconsistentOrientation { .. })
    ));
}

#[test]
fn bad_parameters() {
    let m = procedural::icosphere(0.1, 2);
    for density in [0.0, -5.0, f32::NAN] {
        let e = add(&m, &BodyDesc { density, ..small() }).unwrap_err();
        assert!(
            matches!(
                e,
                TissueError::InvalidParameter {
                    name: "density",
                    ..
                }
            ),
            "{e}"
        );
    }
    for s in [0.0, -0.01, f32::NAN] {
        let e = add(
            &m,
            &BodyDesc {
                resolution: Resolution::Spacing(s),
                ..small()
            },
        )
        .unwrap_err();
        assert!(
            matches!(
                e,
                TissueError::InvalidParameter {
                    name: "spacing",
                    ..
                }
            ),
            "{e}"
        );
    }
    for k in [0.0, -0.5, 1.5, f32::NAN] {
        let e = add(
            &m,
            &BodyDesc {
                material: Material::ShapeMatching { stiffness: k },
                ..small()
            },
        )
        .unwrap_err();
        assert!(
            matches!(
                e,
                TissueError::InvalidParameter {
                    name: "stiffness",
                    ..
                }
            ),
            "{e}"
        );
    }
    let e = add(
        &m,
        &BodyDesc {
            material: Material::Hyperelastic {
                youngs_modulus: -1.0,
                poisson_ratio: 0.3,
            },
            ..small()
        },
    )
    .unwrap_err();
    assert!(matches!(
        e,
        TissueError::InvalidParameter {
            name: "youngs_modulus",
            ..
        }
    ));
    let e = add(
        &m,
        &BodyDesc {
            material: Material::Hyperelastic {
                youngs_modulus: 1e4,
                poisson_ratio: 0.5,
            },
            ..small()
        },
    )
    .unwrap_err();
    assert!(matches!(
        e,
        TissueError::InvalidParameter {
            name: "poisson_ratio",
            ..
        }
    ));
    assert!(matches!(
        add(
            &m,
            &BodyDesc {
                resolution: Resolution::Particles(0),
                ..small()
            }
        )
        .unwrap_err(),
        TissueError::InvalidParameter {
            name: "particles",
            ..
        }
    ));
    assert!(matches!(
        add(
            &m,
            &BodyDesc {
                resolution: Resolution::Spacing(1e-6),
                ..small()
            }
        )
        .unwrap_err(),
        TissueError::TooManyParticles { .. }
    ));
    assert!(matches!(
        add(
            &m,
            &BodyDesc {
                neighbours: 0,
                ..small()
            }
        )
        .unwrap_err(),
        TissueError::InvalidParameter {
            name: "neighbours",
            ..
        }
    ));
}

#[test]
fn k_not_smaller_than_particle_count() {
    let m = procedural::icosphere(0.1, 2);
    let e = add(
        &m,
        &BodyDesc {
            resolution: Resolution::Particles(20),
            neighbours: 64,
            ..small()
        },
    )
    .unwrap_err();
    match &e {
        TissueError::TooFewParticles {
            particles,
            neighbours,
        } => {
            assert_eq!(*neighbours, 64);
            assert!(*particles <= 64);
        }
        other => panic!("expected TooFewParticles, got {other}"),
    }
    assert!(e.to_string().contains("K = 64"), "{e}");
}

#[test]
fn bad_solver_settings() {
    let mut model = Model::new();
    model
        .add_body(&procedural::icosphere(0.1, 2), &small())
        .unwrap();
    for (s, name) in [
        (
            SolverSettings {
                dt: 0.0,
                ..Default::default()
            },
            "dt",
        ),
        (
            SolverSettings {
                dt: f32::NAN,
                ..Default::default()
            },
            "dt",
        ),
        (
            SolverSettings {
                iterations: 0,
                ..Default::default()
            },
            "iterations",
        ),
        (
            SolverSettings {
                substeps: 0,
                ..Default::default()
            },
            "substeps",
        ),
        (
            SolverSettings {
                relaxation: -1.0,
                ..Default::default()
            },
            "relaxation",
        ),
        (
            SolverSettings {
                contact_every: 0,
                ..Default::default()
            },
            "contact_every",
        ),
        (
            SolverSettings {
                contact_relaxation: f32::NAN,
                ..Default::default()
            },
            "contact_relaxation",
        ),
        (
            SolverSettings {
                gravity: Vec3::NAN,
                ..Default::default()
            },
            "gravity",
        ),
    ] {
        match Solver::new(&model, s) {
            Err(TissueError::InvalidParameter { name: n, .. }) => assert_eq!(n, name),
            other => panic!("{name}: expected an error, got {other:?}"),
        }
    }
}
