//! Closed triangle surfaces: validation, repair of a globally inverted surface, volume,
//! and the inside test used for sampling.
//!
//! A [`TriMesh`] holds what a Bevy `Mesh` holds (positions and a triangle index list).
//! [`Surface::new`] welds coincident vertices (render meshes split vertices at UV
//! seams), checks the surface and returns the closed, consistently outward-oriented
//! topology that the model builder needs, or a [`MeshError`] naming the problem.

use super::error::MeshError;
use glam::{DVec2, DVec3, Vec3};
use std::collections::HashMap;

/// A triangle mesh as positions (m) and a flat triangle index list.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TriMesh {
    /// Vertex positions in metres (body-local frame).
    pub positions: Vec<Vec3>,
    /// Triangle list: three indices per triangle, counter-clockwise seen from outside.
    pub indices: Vec<u32>,
}

impl TriMesh {
    /// A mesh from positions and a triangle index list.
    pub fn new(positions: Vec<Vec3>, indices: Vec<u32>) -> Self {
        Self { positions, indices }
    }

    /// Number of triangles (`indices.len() / 3`).
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }

    /// Axis-aligned bounds `(min, max)`; `None` when empty.
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        bounds_of(&self.positions)
    }
}

/// Axis-aligned bounds of a point set.
pub fn bounds_of(points: &[Vec3]) -> Option<(Vec3, Vec3)> {
    let first = *points.first()?;
    Some(
        points
            .iter()
            .fold((first, first), |(lo, hi), p| (lo.min(*p), hi.max(*p))),
    )
}

/// A validated closed surface: welded vertices, outward orientation.
#[derive(Debug, Clone)]
pub struct Surface {
    /// Welded vertex positions, m.
    pub positions: Vec<DVec3>,
    /// Triangles over the welded vertices, outward (counter-clockwise from outside).
    pub triangles: Vec<[u32; 3]>,
    /// For every vertex of the input mesh, its welded vertex.
    pub weld_map: Vec<u32>,
    /// True when the input was inside-out and has been flipped.
    pub flipped: bool,
    /// Enclosed volume, m³.
    pub volume: f64,
}

impl Surface {
    /// Welds, validates and orients `mesh`. Errors name the first problem found:
    /// empty, not triangles, index out of range, NaN, degenerate, non-manifold, not
    /// closed, inconsistent orientation, zero volume (in that order).
    pub fn new(mesh: &TriMesh) -> Result<Self, MeshError> {
        if mesh.positions.is_empty() || mesh.indices.is_empty() {
            return Err(MeshError::Empty);
        }
        if !mesh.indices.len().is_multiple_of(3) {
            return Err(MeshError::NotTriangles {
                indices: mesh.indices.len(),
            });
        }
        if let Some(&index) = mesh
            .indices
            .iter()
            .find(|&&i| i as usize >= mesh.positions.len())
        {
            return Err(MeshError::IndexOutOfRange {
                index,
                vertices: mesh.positions.len(),
            });
        }
        let bad: Vec<usize> = mesh
            .positions
            .iter()
            .enumerate()
            .filter(|(_, p)| !p.is_finite())
            .map(|(i, _)| i)
            .collect();
        if let Some(&vertex) = bad.first() {
            return Err(MeshError::NonFinite {
                vertex,
                count: bad.len(),
            });
        }
        let (positions, weld_map) = weld(&mesh.positions);
        let (lo, hi) = mesh.bounds().ok_or(MeshError::Empty)?;
        let diag = (hi - lo).as_dvec3().length().max(f64::MIN_POSITIVE);
        let area_eps = (diag * 1e-7).powi(2);
        let mut triangles = Vec::with_capacity(mesh.triangle_count());
        let mut degenerate = 0;
        for t in mesh.indices.chunks_exact(3) {
            let tri = [
                weld_map[t[0] as usize],
                weld_map[t[1] as usize],
                weld_map[t[2] as usize],
            ];
            let [a, b, c] = tri.map(|i| positions[i as usize]);
            if tri[0] == tri[1]
                || tri[1] == tri[2]
                || tri[0] == tri[2]
                || (b - a).cross(c - a).length() * 0.5 <= area_eps
            {
                degenerate += 1;
            }
            triangles.push(tri);
        }
        if degenerate > 0 {
            return Err(MeshError::DegenerateTriangles { count: degenerate });
        }
        // Undirected edge use counts and directed duplicates.
        let mut undirected: HashMap<(u32, u32), u32> = HashMap::with_capacity(triangles.len() * 2);
        let mut directed: HashMap<(u32, u32), u32> = HashMap::with_capacity(triangles.len() * 3);
        for t in &triangles {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                *undirected.entry((a.min(b), a.max(b))).or_default() += 1;
                *directed.entry((a, b)).or_default() += 1;
            }
        }
        let non_manifold = undirected.values().filter(|&&c| c > 2).count();
        if non_manifold > 0 {
            return Err(MeshError::NonManifold {
                edges: non_manifold,
            });
        }
        let boundary = undirected.values().filter(|&&c| c == 1).count();
        if boundary > 0 {
            return Err(MeshError::NotClosed {
                boundary_edges: boundary,
            });
        }
        let inconsistent = directed.values().filter(|&&c| c > 1).count();
        if inconsistent > 0 {
            return Err(MeshError::InconsistentOrientation {
                edges: inconsistent,
            });
        }
        let mut volume = signed_volume(&positions, &triangles);
        if volume.abs() <= diag.powi(3) * 1e-12 {
            return Err(MeshError::ZeroVolume);
        }
        let flipped = volume < 0.0;
        if flipped {
            for t in &mut triangles {
                t.swap(1, 2);
            }
            volume = -volume;
        }
        Ok(Self {
            positions,
            triangles,
            weld_map,
            flipped,
            volume,
        })
    }

    /// Axis-aligned bounds of the welded vertices.
    pub fn bounds(&self) -> (DVec3, DVec3) {
        self.positions.iter().fold(
            (DVec3::splat(f64::MAX), DVec3::splat(f64::MIN)),
            |(lo, hi), p| (lo.min(*p), hi.max(*p)),
        )
    }

    /// Inside/outside classification of the lattice points
    /// `origin + spacing * (i, j, k)` for `i < dims.x` etc.; the result is indexed
    /// `i + dims.x * (j + dims.y * k)`.
    ///
    /// Robust inside test: ray parity along all three axes (scanlines, one ray per
    /// lattice row, with a tie rule on shared edges so that no crossing is counted twice)
    /// and a majority vote of the three.
    pub fn classify_lattice(&self, origin: DVec3, spacing: f64, dims: [usize; 3]) -> Vec<bool> {
        let n = dims[0] * dims[1] * dims[2];
        let mut votes = vec![0u8; n];
        for axis in 0..3 {
            self.scan_axis(axis, origin, spacing, dims, &mut votes);
        }
        votes.into_iter().map(|v| v >= 2).collect()
    }

    /// Parity along one axis: adds one vote to every lattice point found inside.
    fn scan_axis(
        &self,
        axis: usize,
        origin: DVec3,
        spacing: f64,
        dims: [usize; 3],
        votes: &mut [u8],
    ) {
        let (b, c) = ((axis + 1) % 3, (axis + 2) % 3);
        let (nb, nc) = (dims[b], dims[c]);
        if nb == 0 || nc == 0 || dims[axis] == 0 {
            return;
        }
        // Bucket triangles by the lattice rows their (b, c) bounding box covers.
        let mut rows: Vec<Vec<u32>> = vec![Vec::new(); nb * nc];
        for (ti, t) in self.triangles.iter().enumerate() {
            let p = t.map(|i| self.positions[i as usize]);
            let (mut lo, mut hi) = (DVec2::splat(f64::MAX), DVec2::splat(f64::MIN));
            for q in p {
                let v = DVec2::new(q[b], q[c]);
                lo = lo.min(v);
                hi = hi.max(v);
            }
            let jb0 = ((lo.x - origin[b]) / spacing).ceil().max(0.0) as usize;
            let jb1 = ((hi.x - origin[b]) / spacing).floor();
            let jc0 = ((lo.y - origin[c]) / spacing).ceil().max(0.0) as usize;
            let jc1 = ((hi.y - origin[c]) / spacing).floor();
            if jb1 < 0.0 || jc1 < 0.0 {
                continue;
            }
            let jb1 = (jb1 as usize).min(nb - 1);
            let jc1 = (jc1 as usize).min(nc - 1);
            for jc in jc0..=jc1 {
                for jb in jb0..=jb1 {
                    rows[jb + nb * jc].push(ti as u32);
                }
            }
        }
        let mut hits: Vec<f64> = Vec::new();
        for jc in 0..nc {
            for jb in 0..nb {
                let tris = &rows[jb + nb * jc];
                if tris.is_empty() {
                    continue;
                }
                let q = DVec2::new(
                    origin[b] + spacing * jb as f64,
                    origin[c] + spacing * jc as f64,
                );
                hits.clear();
                for &ti in tris {
                    let p = self.triangles[ti as usize].map(|i| self.positions[i as usize]);
                    if let Some(t) = ray_hit(&p, axis, b, c, q) {
                        hits.push(t);
                    }
                }
                if hits.len() < 2 {
                    continue;
                }
                hits.sort_by(f64::total_cmp);
                // Points between the 1st and 2nd, 3rd and 4th, ... crossings are inside.
                for pair in hits.chunks_exact(2) {
                    let i0 = ((pair[0] - origin[axis]) / spacing).ceil().max(0.0) as usize;
                    let i1 = ((pair[1] - origin[axis]) / spacing).floor();
                    if i1 < 0.0 {
                        continue;
                    }
                    let i1 = (i1 as usize).min(dims[axis] - 1);
                    for i in i0..=i1 {
                        let mut idx = [0usize; 3];
                        idx[axis] = i;
                        idx[b] = jb;
                        idx[c] = jc;
                        votes[idx[0] + dims[0] * (idx[1] + dims[1] * idx[2])] += 1;
                    }
                }
            }
        }
    }
}

/// Where the ray through `q` (in the (b, c) plane) along `axis` crosses triangle `p`, if
/// it does. Edge functions with a tie rule: a point exactly on an edge shared by two
/// triangles is counted for exactly one of them.
fn ray_hit(p: &[DVec3; 3], axis: usize, b: usize, c: usize, q: DVec2) -> Option<f64> {
    let v = p.map(|x| DVec2::new(x[b], x[c]) - q);
    let area = cross2(v[1] - v[0], v[2] - v[0]);
    if area == 0.0 {
        return None; // triangle seen edge-on: the neighbours carry the crossing
    }
    let s = area.signum();
    let mut w = [0.0; 3];
    for k in 0..3 {
        let (a0, a1) = (v[(k + 1) % 3], v[(k + 2) % 3]);
        let e = cross2(a0, a1) * s;
        if e < 0.0 {
            return None;
        }
        if e == 0.0 {
            // On the edge a0 -> a1: count only for "top-left" edges of the
            // orientation-normalised triangle.
            let d = (a1 - a0) * s;
            if !(d.y > 0.0 || (d.y == 0.0 && d.x < 0.0)) {
                return None;
            }
        }
        w[k] = e;
    }
    let sum = w[0] + w[1] + w[2];
    if sum <= 0.0 {
        return None;
    }
    Some((w[0] * p[0][axis] + w[1] * p[1][axis] + w[2] * p[2][axis]) / sum)
}

fn cross2(a: DVec2, b: DVec2) -> f64 {
    a.x * b.y - a.y * b.x
}

/// Signed enclosed volume (divergence theorem), m³; positive for outward triangles.
pub fn signed_volume(positions: &[DVec3], triangles: &[[u32; 3]]) -> f64 {
    triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| positions[i as usize]);
            a.dot(b.cross(c))
        })
        .sum::<f64>()
        / 6.0
}

/// Merges vertices closer than 1e-6 of the bounding-box diagonal, or than four f32
/// rounding steps of the largest coordinate where that is more: a seam's twin vertices,
/// equal in the mesh's own frame, can land a rounding step apart once placed far from
/// the origin. Returns the welded positions and, for each input vertex, its welded
/// index.
pub fn weld(points: &[Vec3]) -> (Vec<DVec3>, Vec<u32>) {
    let Some((lo, hi)) = bounds_of(points) else {
        return (Vec::new(), Vec::new());
    };
    let far = lo.abs().max(hi.abs()).max_element() as f64;
    let eps = ((hi - lo).as_dvec3().length() * 1e-6)
        .max(far * 4.0 * f32::EPSILON as f64)
        .max(1e-30);
    let key = |p: DVec3| -> [i64; 3] { (p / eps).floor().to_array().map(|x| x as i64) };
    let mut cells: HashMap<[i64; 3], Vec<u32>> = HashMap::new();
    let mut out: Vec<DVec3> = Vec::new();
    let mut map = Vec::with_capacity(points.len());
    for p in points {
        let p = p.as_dvec3();
        let k = key(p);
        let mut found = None;
        'search: for dz in -1..=1 {
            for dy in -1..=1 {
                for dx in -1..=1 {
                    if let Some(list) = cells.get(&[k[0] + dx, k[1] + dy, k[2] + dz]) {
                        for &w in list {
                            if out[w as usize].distance(p) <= eps {
                                found = Some(w);
                                break 'search;
                            }
                        }
                    }
                }
            }
        }
        let id = found.unwrap_or_else(|| {
            let id = out.len() as u32;
            out.push(p);
            cells.entry(k).or_default().push(id);
            id
        });
        map.push(id);
    }
    (out, map)
}

/// Area-weighted vertex normals of a triangle list (unit length; zero for unused vertices).
pub fn vertex_normals(positions: &[Vec3], indices: &[u32]) -> Vec<Vec3> {
    let mut n = vec![Vec3::ZERO; positions.len()];
    accumulate_normals(positions, indices, &mut n);
    for v in &mut n {
        *v = v.normalize_or_zero();
    }
    n
}

/// Adds each triangle's area-weighted normal (the un-normalised cross product) to its
/// three vertices' entries of `normals`.
pub fn accumulate_normals(positions: &[Vec3], indices: &[u32], normals: &mut [Vec3]) {
    for t in indices.chunks_exact(3) {
        let (a, b, c) = (t[0] as usize, t[1] as usize, t[2] as usize);
        let fnrm = (positions[b] - positions[a]).cross(positions[c] - positions[a]);
        normals[a] += fnrm;
        normals[b] += fnrm;
        normals[c] += fnrm;
    }
}
