//! Procedural closed surfaces made by the project itself (no asset files needed): an
//! icosphere, a subdivided box, and a liver — right and left lobe, wedge shaped, a
//! convex diaphragmatic top and a flatter visceral underside, a notch at the ligament.

use super::mesh::TriMesh;
use glam::Vec3;
use std::collections::HashMap;

/// A unit-radius icosphere with `subdivisions` levels (0 = icosahedron), scaled by
/// `radius` (m). Outward, counter-clockwise triangles.
pub fn icosphere(radius: f32, subdivisions: u32) -> TriMesh {
    let t = (1.0 + 5.0f32.sqrt()) / 2.0;
    let mut v: Vec<Vec3> = [
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ]
    .iter()
    .map(|a| Vec3::from_array(*a).normalize())
    .collect();
    let mut f: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..subdivisions {
        let mut mid: HashMap<(u32, u32), u32> = HashMap::new();
        let mut nf = Vec::with_capacity(f.len() * 4);
        let mut midpoint = |a: u32, b: u32, v: &mut Vec<Vec3>| -> u32 {
            *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                v.push(((v[a as usize] + v[b as usize]) * 0.5).normalize());
                (v.len() - 1) as u32
            })
        };
        for [a, b, c] in f {
            let ab = midpoint(a, b, &mut v);
            let bc = midpoint(b, c, &mut v);
            let ca = midpoint(c, a, &mut v);
            nf.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        f = nf;
    }
    TriMesh::new(
        v.into_iter().map(|p| p * radius).collect(),
        f.into_iter().flatten().collect(),
    )
}

/// A box of the given half extents (m), each face a `segments × segments` grid. Faces are
/// generated separately (vertices repeated along edges, as render meshes do).
pub fn cuboid(half_extents: Vec3, segments: u32) -> TriMesh {
    let n = segments.max(1);
    let mut positions = Vec::new();
    let mut indices = Vec::new();
    // (normal axis, sign): face spanned by the other two axes, counter-clockwise outward.
    for axis in 0..3 {
        for sign in [-1.0f32, 1.0] {
            let (u_ax, v_ax) = ((axis + 1) % 3, (axis + 2) % 3);
            let base = positions.len() as u32;
            for j in 0..=n {
                for i in 0..=n {
                    let mut p = Vec3::ZERO;
                    p[axis] = sign * half_extents[axis];
                    p[u_ax] = (2.0 * i as f32 / n as f32 - 1.0) * half_extents[u_ax];
                    p[v_ax] = (2.0 * j as f32 / n as f32 - 1.0) * half_extents[v_ax];
                    positions.push(p);
                }
            }
            for j in 0..n {
                for i in 0..n {
                    let a = base + j * (n + 1) + i;
                    let (b, c, d) = (a + 1, a + n + 1, a + n + 2);
                    if sign > 0.0 {
                        indices.extend([a, b, d, a, d, c]);
                    } else {
                        indices.extend([a, d, b, a, c, d]);
                    }
                }
            }
        }
    }
    TriMesh::new(positions, indices)
}

/// A procedural liver about 0.22 m wide (x), up to 0.13 m thick (y) and 0.16 m deep (z),
/// centred at the origin: a thick right lobe (+x) tapering into a thin left lobe (−x),
/// domed on top, flatter underneath, with a notch where the falciform ligament runs
/// (around x = −0.03 m on the top). The ligament line is returned by [`liver_ligament`].
pub fn liver(subdivisions: u32) -> TriMesh {
    let sphere = icosphere(1.0, subdivisions);
    let positions = sphere.positions.iter().map(|&d| liver_map(d)).collect();
    TriMesh::new(positions, sphere.indices)
}

fn smoothstep(e0: f32, e1: f32, x: f32) -> f32 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Maps a unit-sphere point onto the liver (monotone in each coordinate for fixed x, so
/// the surface stays closed, manifold and non-self-intersecting).
fn liver_map(d: Vec3) -> Vec3 {
    let x = d.x;
    // Thickness: thin left lobe to thick right lobe.
    let lobe = smoothstep(-0.9, 0.6, x);
    let half_thick = 0.012 + 0.055 * lobe;
    // Ligament notch on the top between the lobes.
    let notch = 1.0 - 0.35 * (-((x + 0.25) / 0.12).powi(2)).exp();
    let top = half_thick * notch * 1.15;
    let bottom = half_thick * 0.75;
    let y = if d.y >= 0.0 { d.y * top } else { d.y * bottom };
    // Depth: the right lobe reaches further back; slight wedge toward the front.
    let depth = 0.05 + 0.035 * lobe;
    let z = d.z * depth * if d.z > 0.0 { 0.9 } else { 1.0 };
    // Width with the right lobe slightly larger.
    let xw = if x >= 0.0 { x * 0.12 } else { x * 0.10 };
    // Gentle downward curve of the left lobe tip.
    let droop = -0.02 * smoothstep(0.0, 1.0, -x) * (1.0 - x * x).max(0.0).sqrt();
    Vec3::new(xw, y + droop, z)
}

/// Points (m) along the falciform ligament / coronary attachment of [`liver`]: the band
/// on top of the organ between the lobes and along its back, where a scene pins it.
pub fn liver_ligament() -> (Vec3, Vec3) {
    // Axis-aligned box around the attachment region (upper back of the right lobe).
    (Vec3::new(-0.06, 0.02, -0.09), Vec3::new(0.10, 0.2, -0.02))
}
