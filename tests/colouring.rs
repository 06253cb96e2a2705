//! Cluster colouring: no two clusters of one colour share a particle, and the count is
//! what the coloured Gauss–Seidel would dispatch per iteration.

use bevy_tissue::core::colouring::{colour_count, greedy_cluster_colours};
use bevy_tissue::core::model::{BodyDesc, Model, PinRegion};
use bevy_tissue::core::procedural;
use bevy_tissue::core::sampling::Resolution;

#[test]
fn colours_are_valid_and_bounded() {
    // `BEVY_TISSUE_COLOUR_N` sets the particle count (for BENCHMARKS.md's table).
    let particles = std::env::var("BEVY_TISSUE_COLOUR_N")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(4096);
    for k in [16u32, 32] {
        let (lo, hi) = procedural::liver_ligament();
        let mut model = Model::new();
        let desc = BodyDesc {
            resolution: Resolution::Particles(particles),
            neighbours: k,
            pins: vec![PinRegion::Box { min: lo, max: hi }],
            discretisation: bevy_tissue::core::model::Discretisation::Clusters,
            ..Default::default()
        };
        model.add_body(&procedural::liver(4), &desc).unwrap();
        let colours = greedy_cluster_colours(&model);
        let count = colour_count(&colours);
        // Valid: every particle's clusters have pairwise different colours.
        for j in 0..model.particle_count() {
            let mut seen: Vec<u32> = model
                .clusters_of(j)
                .iter()
                .map(|&c| colours[c as usize])
                .collect();
            let len = seen.len();
            seen.sort_unstable();
            seen.dedup();
            assert_eq!(
                seen.len(),
                len,
                "particle {j}: two of its clusters share a colour"
            );
        }
        // At least the largest number of clusters on one particle; greedy stays within
        // the conflict degree + 1.
        let max_inv = (0..model.particle_count())
            .map(|j| model.clusters_of(j).len())
            .max()
            .unwrap() as u32;
        assert!(count >= max_inv, "{count} colours < {max_inv}");
        let largest = (0..count)
            .map(|c| colours.iter().filter(|&&x| x == c).count())
            .max()
            .unwrap();
        eprintln!(
            "{} particles, K = {k}: {count} colours (≥ {max_inv} clusters on one particle), largest colour {largest} clusters",
            model.particle_count()
        );
        assert!(count <= 4 * (k + 1) * 2, "{count} colours for K = {k}");
    }
}
