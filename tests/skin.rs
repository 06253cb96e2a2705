//! The skinned surface follows rigid and affine motion exactly; normals are recomputed.
mod common;
use bevy_tissue::core::mesh::vertex_normals;
use bevy_tissue::core::model::{BodyDesc, Model};
use bevy_tissue::core::procedural;
use bevy_tissue::core::sampling::Resolution;
use bevy_tissue::core::skin::skin_normals;
use glam::{Mat3, Quat, Vec3};

fn model() -> Model {
    let mut m = Model::new();
    let desc = BodyDesc {
        resolution: Resolution::Particles(800),
        neighbours: 16,
        discretisation: bevy_tissue::core::model::Discretisation::Clusters,
        ..Default::default()
    };
    m.add_body(&procedural::liver(3), &desc).unwrap();
    m
}

fn check_map(model: &Model, a: Mat3, t: Vec3, what: &str) {
    let x: Vec<Vec3> = model.rest.iter().map(|p| a * *p + t).collect();
    let skin = &model.bodies[0].skin;
    let out = common::skinned(model, &x);
    let size = model.bodies[0].size;
    let err = out
        .iter()
        .zip(&skin.rest_vertices)
        .map(|(v, v0)| v.distance(a * *v0 + t))
        .fold(0.0f32, f32::max);
    assert!(
        err < 1e-5 * size,
        "{what}: max error {err:e} m (size {size} m)"
    );
}

#[test]
fn skin_follows_rigid_motion_exactly() {
    let m = model();
    let r = Mat3::from_quat(Quat::from_euler(glam::EulerRot::XYZ, 0.7, -1.2, 2.1));
    check_map(&m, r, Vec3::new(0.3, -0.2, 0.15), "rigid");
}

#[test]
fn skin_follows_affine_deformation_exactly() {
    let m = model();
    let a = Mat3::from_cols(
        Vec3::new(1.3, 0.1, 0.0),
        Vec3::new(0.2, 0.7, -0.1),
        Vec3::new(0.0, 0.15, 1.1),
    );
    check_map(&m, a, Vec3::new(-0.05, 0.1, 0.02), "affine");
}

#[test]
fn skin_normals_are_outward_and_rotate_with_the_body() {
    let m = model();
    let skin = &m.bodies[0].skin;
    let r = Quat::from_rotation_z(0.9);
    let x: Vec<Vec3> = m.rest.iter().map(|p| r * *p).collect();
    let pos = common::skinned(&m, &x);
    let mut nrm = vec![Vec3::ZERO; pos.len()];
    skin_normals(skin, &pos, &mut nrm);
    let rest_n = vertex_normals(&skin.rest_vertices, &skin.indices);
    for (n, n0) in nrm.iter().zip(&rest_n) {
        assert!((n.length() - 1.0).abs() < 1e-4);
        assert!(
            n.dot(r * *n0) > 0.999,
            "normal {n} vs rotated rest normal {}",
            r * *n0
        );
    }
    // The deformed surface encloses the same volume after a rigid motion.
    let v = common::enclosed_volume(&pos, &skin.indices);
    assert!((v - m.bodies[0].volume as f64).abs() / v < 1e-4);
}
