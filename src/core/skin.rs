//! Surface embedding: every render-mesh vertex is bound once to its nearest particles
//! with weights, and deformed each step from the particles' positions and their clusters'
//! deformation gradients:
//!
//! `v = Σ_i w_i (x_i + F_i (V − X_i))`, `Σ_i w_i = 1`,
//!
//! with `V` the vertex's rest position, `X_i`/`x_i` particle `i`'s rest/current position
//! and `F_i` its own cluster's deformation gradient. Because `F` of a cluster is exact
//! for affine motion, the skinned surface follows any rigid or affine motion exactly.
//! Normals are recomputed from the deformed triangles over the welded topology (so
//! vertices split at UV seams get the same normal).

use super::knn::Grid;
use glam::{Mat3, Vec3};

/// Particles bound to each render vertex.
pub const SKIN_INFLUENCES: usize = 4;

/// The embedding of one body's render surface in its particles.
#[derive(Debug, Clone, Default)]
pub struct Skin {
    /// Rest positions of the render vertices, m (body frame).
    pub rest_vertices: Vec<Vec3>,
    /// For each render vertex, its particles (global indices into the model).
    pub particles: Vec<[u32; SKIN_INFLUENCES]>,
    /// Weights per influence (sum to 1; unused influences have weight 0).
    pub weights: Vec<[f32; SKIN_INFLUENCES]>,
    /// Render triangle list (as given, winding fixed if the surface was inverted).
    pub indices: Vec<u32>,
    /// Welded vertex of each render vertex (for seam-free normals).
    pub weld_map: Vec<u32>,
    /// Number of welded vertices.
    pub welded_count: u32,
    /// Triangles over welded vertices, outward.
    pub welded_triangles: Vec<[u32; 3]>,
}

/// Binds `vertices` (body frame) to the nearest of `particles` (body frame rest positions
/// whose global index starts at `first_particle`). Weights fall off as `1/(d + s/2)²`
/// with `s` the lattice spacing.
pub fn embed(
    vertices: &[Vec3],
    particles: &[Vec3],
    first_particle: u32,
    spacing: f32,
) -> Vec<([u32; SKIN_INFLUENCES], [f32; SKIN_INFLUENCES])> {
    let grid = Grid::build(particles, 2.0);
    let k = SKIN_INFLUENCES.min(particles.len());
    let mut buf = Vec::with_capacity(k + 1);
    vertices
        .iter()
        .map(|&v| {
            grid.knn_into(v, k, u32::MAX, &mut buf);
            let mut idx = [first_particle; SKIN_INFLUENCES];
            let mut w = [0.0f32; SKIN_INFLUENCES];
            let mut sum = 0.0;
            for (slot, &(d2, j)) in buf.iter().enumerate() {
                let wi = 1.0 / (d2.sqrt() + 0.5 * spacing).powi(2);
                idx[slot] = first_particle + j;
                w[slot] = wi;
                sum += wi;
            }
            for x in &mut w {
                *x /= sum;
            }
            (idx, w)
        })
        .collect()
}

/// Deforms the skin: writes every render vertex position into `out_positions`, using the
/// current particle positions `x`, rest positions `rest`, and the per-particle deformation
/// gradients `f` (one per particle: its own cluster's).
pub fn skin_positions(
    skin: &Skin,
    x: &[Vec3],
    rest: &[Vec3],
    f: &[Mat3],
    out_positions: &mut [Vec3],
) {
    for (v, out) in out_positions.iter_mut().enumerate() {
        let v0 = skin.rest_vertices[v];
        let mut acc = Vec3::ZERO;
        for s in 0..SKIN_INFLUENCES {
            let w = skin.weights[v][s];
            if w == 0.0 {
                continue;
            }
            let i = skin.particles[v][s] as usize;
            acc += w * (x[i] + f[i] * (v0 - rest[i]));
        }
        *out = acc;
    }
}

/// Recomputes normals of the deformed skin (area-weighted over the welded topology).
pub fn skin_normals(skin: &Skin, positions: &[Vec3], out_normals: &mut [Vec3]) {
    // One representative render vertex per welded vertex.
    let mut rep = vec![u32::MAX; skin.welded_count as usize];
    for (v, &w) in skin.weld_map.iter().enumerate() {
        if rep[w as usize] == u32::MAX {
            rep[w as usize] = v as u32;
        }
    }
    let welded_pos: Vec<Vec3> = rep.iter().map(|&v| positions[v as usize]).collect();
    let flat: Vec<u32> = skin.welded_triangles.iter().flatten().copied().collect();
    let n = super::mesh::vertex_normals(&welded_pos, &flat);
    for (v, out) in out_normals.iter_mut().enumerate() {
        *out = n[skin.weld_map[v] as usize];
    }
}
