//! Graph colouring of clusters for a coloured Gauss–Seidel iteration: clusters of one
//! colour share no particle, so they can be solved in parallel and applied at once.
//!
//! Whether coloured Gauss–Seidel converges faster per millisecond than Jacobi on the
//! GPU is a measured question. The colour count decides the cost side: one dispatch per colour
//! per iteration instead of Jacobi's two (BENCHMARKS.md, "Coloured Gauss–Seidel").

use super::model::Model;

/// Greedy colouring in cluster order: each cluster takes the smallest colour that no
/// cluster sharing a particle with it has. Returns the colour of every cluster.
pub fn greedy_cluster_colours(model: &Model) -> Vec<u32> {
    let n = model.particle_count();
    let mut colour = vec![u32::MAX; n];
    let mut stamp: Vec<usize> = Vec::new();
    for c in 0..n {
        // Colours used by the clusters that share a member with c.
        for &j in model.members(c) {
            for &other in model.clusters_of(j as usize) {
                let k = colour[other as usize];
                if k != u32::MAX {
                    if stamp.len() <= k as usize {
                        stamp.resize(k as usize + 1, usize::MAX);
                    }
                    stamp[k as usize] = c;
                }
            }
        }
        let free = (0..).find(|&k| stamp.get(k).is_none_or(|&s| s != c));
        colour[c] = free.unwrap_or(0) as u32;
    }
    colour
}

/// Number of colours used.
pub fn colour_count(colours: &[u32]) -> u32 {
    colours.iter().copied().max().map_or(0, |m| m + 1)
}
