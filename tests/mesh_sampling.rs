//! Mesh checks, sampling counts, the shared meshes.
mod common;
use bevy_tissue::core::error::{MeshError, TissueError};
use bevy_tissue::core::mesh::{Surface, TriMesh};
use bevy_tissue::core::model::{BodyDesc, Model};
use bevy_tissue::core::procedural;
use bevy_tissue::core::sampling::{Resolution, sample};
use glam::Vec3;

#[test]
fn procedural_shapes_are_valid_closed_surfaces() {
    for (name, mesh) in [
        ("sphere", procedural::icosphere(0.5, 3)),
        ("box", procedural::cuboid(Vec3::new(0.3, 0.1, 0.2), 4)),
        ("liver", procedural::liver(4)),
    ] {
        let s = Surface::new(&mesh).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert!(!s.flipped, "{name} should be outward");
        assert!(s.volume > 0.0);
    }
    // Sphere volume close to 4/3 π r³ (the icosphere is slightly smaller).
    let s = Surface::new(&procedural::icosphere(0.5, 4)).unwrap();
    let exact = 4.0 / 3.0 * std::f64::consts::PI * 0.125;
    assert!(
        (s.volume - exact).abs() / exact < 0.01,
        "volume {}",
        s.volume
    );
    // The box welds its split edges: 6·5·5 grid vertices become 6·16+2 = 98... check closed.
    let b = Surface::new(&procedural::cuboid(Vec3::ONE, 4)).unwrap();
    assert_eq!(b.positions.len(), 98);
    assert!((b.volume - 8.0).abs() < 1e-9);
}

/// A mesh placed far from the origin whose seam has twin vertices a rounding step apart
/// (as a primitive's seam becomes once its vertices are moved to world space, where an
/// f32 step at 9 m is about 1 µm) is still one closed surface.
#[test]
fn a_seam_a_rounding_step_apart_far_from_the_origin_is_welded() {
    let mut mesh = procedural::icosphere(0.13, 3);
    for p in &mut mesh.positions {
        *p += Vec3::new(5.6, 1.4, 9.0);
    }
    // Vertex 0's twin, one f32 step further along z, taken by the triangles after the
    // first that use vertex 0.
    let p = mesh.positions[0];
    let twin = Vec3::new(p.x, p.y, f32::from_bits(p.z.to_bits() + 1));
    assert!(twin.z > p.z);
    mesh.positions.push(twin);
    let t = (mesh.positions.len() - 1) as u32;
    let mut seen = false;
    for tri in mesh.indices.chunks_exact_mut(3) {
        if tri.contains(&0) {
            if seen {
                for i in tri.iter_mut().filter(|i| **i == 0) {
                    *i = t;
                }
            }
            seen = true;
        }
    }
    let s = Surface::new(&mesh).unwrap_or_else(|e| panic!("the seam was not welded: {e}"));
    assert!(s.volume > 0.0);
}

#[test]
fn inverted_surface_is_flipped() {
    let mut m = procedural::icosphere(0.3, 2);
    for t in m.indices.chunks_exact_mut(3) {
        t.swap(1, 2);
    }
    let s = Surface::new(&m).unwrap();
    assert!(s.flipped);
    assert!(s.volume > 0.0);
    // and it samples the same as the outward one
    let a = sample(&s, Resolution::Spacing(0.05)).unwrap();
    let b = sample(
        &Surface::new(&procedural::icosphere(0.3, 2)).unwrap(),
        Resolution::Spacing(0.05),
    )
    .unwrap();
    assert_eq!(a.positions.len(), b.positions.len());
}

#[test]
fn lattice_inside_test_matches_analytic_sphere() {
    // Points of a lattice inside a fine icosphere vs the analytic ball (away from the
    // surface by more than the tessellation error).
    let r = 1.0;
    let s = Surface::new(&procedural::icosphere(r, 5)).unwrap();
    let smp = sample(&s, Resolution::Spacing(0.07)).unwrap();
    for p in &smp.positions {
        assert!(p.length() < r + 1e-3, "point {p} outside the ball");
    }
    // Count close to the lattice count of the analytic ball.
    let n = smp.positions.len() as f64;
    let expected = 4.0 / 3.0 * std::f64::consts::PI / 0.07f64.powi(3);
    assert!((n - expected).abs() / expected < 0.03, "{n} vs {expected}");
}

fn check_counts(mesh: &TriMesh, name: &str, targets: &[u32]) {
    let s = Surface::new(mesh).unwrap_or_else(|e| panic!("{name}: {e}"));
    for &t in targets {
        let smp = sample(&s, Resolution::Particles(t)).unwrap();
        let n = smp.positions.len() as f64;
        let err = (n - t as f64).abs() / t as f64;
        assert!(
            err <= 0.01,
            "{name}: asked {t}, got {n} ({:.2}%)",
            err * 100.0
        );
    }
}

#[test]
fn sampling_hits_paper_counts_on_procedural_liver() {
    check_counts(
        &procedural::liver(4),
        "procedural liver",
        &[512, 4096, 13824, 37982],
    );
    check_counts(&procedural::icosphere(0.2, 3), "sphere", &[512, 4096]);
}

#[test]
fn sampling_hits_paper_counts_on_shared_liver() {
    let Some(dir) = common::meshes_dir() else {
        return;
    };
    let mesh = common::load_obj(&dir.join("liver2.obj"));
    check_counts(&mesh, "liver2.obj", &[512, 4096, 13824, 37982]);
}

#[test]
fn masses_come_from_density() {
    let mut model = Model::new();
    let desc = BodyDesc {
        resolution: Resolution::Particles(2000),
        density: 1000.0,
        neighbours: 8,
        discretisation: bevy_tissue::core::model::Discretisation::Clusters,
        ..Default::default()
    };
    model
        .add_body(&procedural::icosphere(0.1, 4), &desc)
        .unwrap();
    let total: f64 = model.mass.iter().map(|&m| m as f64).sum();
    let volume = Surface::new(&procedural::icosphere(0.1, 4)).unwrap().volume;
    assert!(
        (total - 1000.0 * volume).abs() / (1000.0 * volume) < 1e-4,
        "mass {total}"
    );
}

#[test]
fn every_closed_shared_mesh_loads_and_dragon_is_refused() {
    let Some(dir) = common::meshes_dir() else {
        return;
    };
    let closed = [
        ("liver2.obj", common::load_obj(&dir.join("liver2.obj"))),
        ("bunny.obj", common::load_obj(&dir.join("bunny.obj"))),
        ("Bunny.stl", common::load_stl(&dir.join("Bunny.stl"))),
        (
            "spot_low_resolution.obj",
            common::load_obj(&dir.join("spot_low_resolution.obj")),
        ),
        (
            "odedstein_sphere.obj",
            common::load_obj(&dir.join("odedstein_sphere.obj")),
        ),
        (
            "odedstein_torus.obj",
            common::load_obj(&dir.join("odedstein_torus.obj")),
        ),
        (
            "Armadillo_verysimplified.obj",
            common::load_obj(&dir.join("Armadillo_verysimplified.obj")),
        ),
        (
            "liver2.msh (boundary)",
            common::load_msh_v1_surface(&dir.join("liver2.msh")),
        ),
    ];
    for (name, mesh) in &closed {
        let mut model = Model::new();
        let desc = BodyDesc {
            resolution: Resolution::Particles(1000),
            neighbours: 16,
            discretisation: bevy_tissue::core::model::Discretisation::Clusters,
            ..Default::default()
        };
        let id = model
            .add_body(mesh, &desc)
            .unwrap_or_else(|e| panic!("{name} should load: {e}"));
        let n = model.bodies[id].count;
        assert!((990..=1010).contains(&n), "{name}: {n} particles");
    }
    let dragon = common::load_obj(&dir.join("dragon.obj"));
    let err = Model::new()
        .add_body(&dragon, &BodyDesc::default())
        .unwrap_err();
    match &err {
        TissueError::Mesh(MeshError::NonManifold { edges }) => assert!(*edges > 0),
        TissueError::Mesh(MeshError::NotClosed { .. })
        | TissueError::Mesh(MeshError::DegenerateTriangles { .. }) => {}
        other => panic!("dragon: unexpected error {other}"),
    }
    let text = err.to_string();
    assert!(
        text.contains("mesh"),
        "message should name the problem: {text}"
    );
    eprintln!("dragon.obj: {text}");
}
