//! Exact KNN on the grid equals brute force, ties broken by index.
mod common;
use bevy_tissue::core::knn::{Grid, knn_all, knn_brute_force};
use common::Rng;
use glam::Vec3;

fn check(points: &[Vec3], what: &str) {
    for k in [1usize, 8, 32, 64] {
        let grid = knn_all(points, k, 2).unwrap();
        let brute = knn_brute_force(points, k).unwrap();
        let diff = grid.iter().zip(&brute).filter(|(a, b)| a != b).count();
        assert_eq!(
            diff, 0,
            "{what}, K = {k}: {diff} entries differ from brute force"
        );
        // Single-threaded gives the same answer.
        assert_eq!(
            knn_all(points, k, 1).unwrap(),
            grid,
            "{what}, K = {k}: thread count changed result"
        );
    }
}

#[test]
fn random_points() {
    let mut rng = Rng(0x9e3779b97f4a7c15);
    let pts: Vec<Vec3> = (0..2000)
        .map(|_| rng.vec3() * Vec3::new(1.0, 0.5, 2.0))
        .collect();
    check(&pts, "random");
}

#[test]
fn lattice_points_with_ties() {
    let mut pts = Vec::new();
    for k in 0..12 {
        for j in 0..12 {
            for i in 0..12 {
                pts.push(Vec3::new(i as f32, j as f32, k as f32) * 0.1);
            }
        }
    }
    check(&pts, "lattice");
}

#[test]
fn clustered_points() {
    let mut rng = Rng(12345);
    let centres: Vec<Vec3> = (0..6).map(|_| rng.vec3() * 10.0).collect();
    let pts: Vec<Vec3> = (0..1800)
        .map(|i| centres[i % 6] + (rng.vec3() - 0.5) * 0.05)
        .collect();
    check(&pts, "clustered");
}

#[test]
fn query_off_points_and_k_too_large() {
    let mut rng = Rng(7);
    let pts: Vec<Vec3> = (0..500).map(|_| rng.vec3()).collect();
    let grid = Grid::build(&pts, 2.0);
    let mut out = Vec::new();
    for _ in 0..50 {
        let q = rng.vec3() * 3.0 - 1.0; // also outside the grid
        grid.knn_into(q, 10, u32::MAX, &mut out);
        let mut all: Vec<(f32, u32)> = pts
            .iter()
            .enumerate()
            .map(|(i, p)| (bevy_tissue::core::knn::dist2(q, *p), i as u32))
            .collect();
        all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        assert_eq!(out, all[..10].to_vec());
    }
    assert!(knn_all(&pts, 500, 1).is_none(), "K = n must be refused");
    assert!(knn_brute_force(&pts, 500).is_none());
}
