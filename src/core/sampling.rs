//! Particles sampled inside a closed surface on a cubic lattice, from a spacing or from a
//! target particle count, stored in spatial (Morton) order.

use super::error::TissueError;
use super::mesh::Surface;
use glam::{DVec3, Vec3};

/// Most particles one body may have (model building refuses more).
pub const MAX_PARTICLES_PER_BODY: usize = 16_000_000;

/// How finely a body is sampled.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Resolution {
    /// Lattice spacing in metres.
    Spacing(f32),
    /// Target particle count; the lattice spacing and offset are searched so that the
    /// count is within 1% of the target where the shape allows it (it does for smooth
    /// shapes; a box has only the counts `nx·ny·nz`).
    Particles(u32),
}

impl Default for Resolution {
    fn default() -> Self {
        Resolution::Particles(4096)
    }
}

/// Lattice samples of a body.
#[derive(Debug, Clone)]
pub struct Samples {
    /// Particle positions (m), Morton-ordered along the lattice.
    pub positions: Vec<Vec3>,
    /// Lattice spacing used, m.
    pub spacing: f32,
}

/// Samples the interior of `surface` on a lattice centred in its bounding box, with a
/// sub-cell offset `shift` (fractions of the spacing, each in [0, 1)).
pub fn sample_lattice(surface: &Surface, spacing: f64, shift: DVec3) -> Samples {
    let (lo, hi) = surface.bounds();
    let ext = hi - lo;
    let dims_f = (ext / spacing).floor() + DVec3::ONE;
    let dims = [dims_f.x as usize, dims_f.y as usize, dims_f.z as usize];
    let used = (dims_f - DVec3::ONE) * spacing;
    let origin = lo + (ext - used) * 0.5 + (shift - DVec3::splat(0.5)) * spacing * 0.999;
    let dims = [dims[0] + 1, dims[1] + 1, dims[2] + 1];
    let inside = surface.classify_lattice(origin, spacing, dims);
    let mut pts: Vec<(u64, Vec3)> = Vec::new();
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                if inside[i + dims[0] * (j + dims[1] * k)] {
                    let p = origin + DVec3::new(i as f64, j as f64, k as f64) * spacing;
                    pts.push((morton3(i as u32, j as u32, k as u32), p.as_vec3()));
                }
            }
        }
    }
    pts.sort_by_key(|(m, _)| *m);
    Samples {
        positions: pts.into_iter().map(|(_, p)| p).collect(),
        spacing: spacing as f32,
    }
}

/// Samples `surface` at the requested resolution.
pub fn sample(surface: &Surface, resolution: Resolution) -> Result<Samples, TissueError> {
    let volume = surface.volume;
    match resolution {
        Resolution::Spacing(s) => {
            let s = super::error::positive("spacing", s)? as f64;
            let estimate = volume / (s * s * s);
            if estimate > MAX_PARTICLES_PER_BODY as f64 {
                return Err(TissueError::TooManyParticles {
                    requested: estimate as usize,
                    limit: MAX_PARTICLES_PER_BODY,
                });
            }
            Ok(sample_lattice(surface, s, DVec3::splat(0.5)))
        }
        Resolution::Particles(n) => {
            check_count(n)?;
            Ok(sample_count(surface, n as usize))
        }
    }
}

/// Searches spacing and lattice offset for a particle count closest to `target`.
fn sample_count(surface: &Surface, target: usize) -> Samples {
    search_count(
        surface.volume,
        target,
        |s, shift| sample_lattice(surface, s, shift),
        |smp| smp.positions.len(),
        |smp| smp.spacing as f64,
    )
}

/// Searches the lattice spacing (bisection from `(volume / target)^⅓`) and, where the
/// count jumps past the target (flat faces fill a whole lattice plane at once), the
/// lattice's sub-cell offset, for the sampling `make(spacing, shift)` whose `count` is
/// closest to `target`.
fn search_count<T>(
    volume: f64,
    target: usize,
    make: impl Fn(f64, DVec3) -> T,
    count: impl Fn(&T) -> usize,
    spacing: impl Fn(&T) -> f64,
) -> T {
    let centre = DVec3::splat(0.5);
    // Bisection on the spacing (count falls as spacing grows).
    let s0 = (volume / target as f64).cbrt();
    let (mut lo, mut hi) = (s0 * 0.5, s0 * 2.0);
    let mut best = make(s0, centre);
    let score = |n: usize| (n as i64 - target as i64).unsigned_abs();
    for _ in 0..40 {
        let mid = 0.5 * (lo + hi);
        let smp = make(mid, centre);
        let n = count(&smp);
        if score(n) < score(count(&best)) {
            best = smp;
        }
        if n == target {
            return best;
        }
        if n > target {
            lo = mid;
        } else {
            hi = mid;
        }
        if (hi - lo) < s0 * 1e-6 {
            break;
        }
    }
    let tol = (target as f64 * 0.002).max(0.5) as u64;
    if score(count(&best)) <= tol {
        return best;
    }
    let s_mid = spacing(&best);
    let shifts = [0.0, 0.25, 0.5, 0.75];
    'outer: for ds in -8..=8 {
        let s = s_mid * (1.0 + ds as f64 * 0.002);
        for &sx in &shifts {
            for &sy in &shifts {
                for &sz in &shifts {
                    let smp = make(s, DVec3::new(sx, sy, sz));
                    if score(count(&smp)) < score(count(&best)) {
                        best = smp;
                        if score(count(&best)) <= tol {
                            break 'outer;
                        }
                    }
                }
            }
        }
    }
    best
}

/// The cells of a lattice inside a closed surface and their corner nodes: the
/// hexahedral elements of a [`super::model::Discretisation::Lattice`] body.
#[derive(Debug, Clone)]
pub struct Voxels {
    /// Corner nodes (the body's particles), m, Morton-ordered along the node lattice.
    pub nodes: Vec<Vec3>,
    /// Each cell's eight nodes (indices into `nodes`), corner `j` at the cell's
    /// `(−1)^(1 + bit)` side per axis: x from bit 0, y from bit 1, z from bit 2
    /// ([`super::element::corner_sign`]).
    pub cells: Vec<[u32; 8]>,
    /// Cell centres, m.
    pub centres: Vec<Vec3>,
    /// Cell edge length, m.
    pub spacing: f32,
}

/// The cells of edge `spacing` (m) whose centres are inside `surface`, on a lattice
/// that covers the bounding box with whole cells, centred on it, shifted by `shift`
/// (fractions of a cell, each in [0, 1); 0.5 is centred). A box whose sides are
/// multiples of the spacing is tiled exactly: its faces are lattice planes.
pub fn voxelize_lattice(surface: &Surface, spacing: f64, shift: DVec3) -> Voxels {
    let (lo, hi) = surface.bounds();
    let ext = hi - lo;
    let cells_f = (ext / spacing - DVec3::splat(1e-6)).ceil().max(DVec3::ONE);
    // Cell-centre lattice: one point more each way than the cells that cover the box,
    // so that a shifted lattice still covers it.
    let dims = [
        cells_f.x as usize + 1,
        cells_f.y as usize + 1,
        cells_f.z as usize + 1,
    ];
    let used = (cells_f - DVec3::ONE) * spacing;
    let origin = lo + (ext - used) * 0.5 + (shift - DVec3::splat(0.5)) * spacing * 0.999;
    let inside = surface.classify_lattice(origin, spacing, dims);
    // Nodes: corners of the inside cells on the node lattice (dims + 1 per axis).
    let nd = [dims[0] + 1, dims[1] + 1, dims[2] + 1];
    let node_id = |i: usize, j: usize, k: usize| i + nd[0] * (j + nd[1] * k);
    let mut used_node = vec![false; nd[0] * nd[1] * nd[2]];
    let mut cell_list = Vec::new();
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                if inside[i + dims[0] * (j + dims[1] * k)] {
                    cell_list.push([i, j, k]);
                    for c in 0..8 {
                        used_node[node_id(i + (c & 1), j + ((c >> 1) & 1), k + ((c >> 2) & 1))] =
                            true;
                    }
                }
            }
        }
    }
    let mut order: Vec<(u64, usize)> = Vec::new();
    for k in 0..nd[2] {
        for j in 0..nd[1] {
            for i in 0..nd[0] {
                if used_node[node_id(i, j, k)] {
                    order.push((morton3(i as u32, j as u32, k as u32), node_id(i, j, k)));
                }
            }
        }
    }
    order.sort_unstable_by_key(|&(m, _)| m);
    let mut index = vec![u32::MAX; used_node.len()];
    let mut nodes = Vec::with_capacity(order.len());
    let node_origin = origin - DVec3::splat(0.5 * spacing);
    for (n, &(_, id)) in order.iter().enumerate() {
        index[id] = n as u32;
        let (i, j, k) = (id % nd[0], (id / nd[0]) % nd[1], id / (nd[0] * nd[1]));
        nodes.push((node_origin + DVec3::new(i as f64, j as f64, k as f64) * spacing).as_vec3());
    }
    // Cells in the Morton order of their lowest corner (the solver's sweep order).
    cell_list.sort_unstable_by_key(|c| morton3(c[0] as u32, c[1] as u32, c[2] as u32));
    let cells = cell_list
        .iter()
        .map(|&[i, j, k]| {
            std::array::from_fn(|c| {
                index[node_id(i + (c & 1), j + ((c >> 1) & 1), k + ((c >> 2) & 1))]
            })
        })
        .collect();
    let centres = cell_list
        .iter()
        .map(|&[i, j, k]| (origin + DVec3::new(i as f64, j as f64, k as f64) * spacing).as_vec3())
        .collect();
    Voxels {
        nodes,
        cells,
        centres,
        spacing: spacing as f32,
    }
}

/// The cells and nodes of `surface` at the requested resolution: a spacing, or a node
/// (particle) count searched for as [`sample`] does.
pub fn voxelize(surface: &Surface, resolution: Resolution) -> Result<Voxels, TissueError> {
    let voxels = match resolution {
        Resolution::Spacing(s) => {
            let s = super::error::positive("spacing", s)? as f64;
            let estimate = surface.volume / (s * s * s);
            if estimate > MAX_PARTICLES_PER_BODY as f64 {
                return Err(TissueError::TooManyParticles {
                    requested: estimate as usize,
                    limit: MAX_PARTICLES_PER_BODY,
                });
            }
            voxelize_lattice(surface, s, DVec3::splat(0.5))
        }
        Resolution::Particles(n) => {
            check_count(n)?;
            search_count(
                surface.volume,
                n as usize,
                |s, shift| voxelize_lattice(surface, s, shift),
                |v| v.nodes.len(),
                |v| v.spacing as f64,
            )
        }
    };
    if voxels.cells.is_empty() {
        return Err(TissueError::InvalidParameter {
            name: "resolution",
            value: format!("spacing {} m", voxels.spacing),
            expected: "a spacing smaller than the body (no lattice cell centre falls inside it)",
        });
    }
    Ok(voxels)
}

/// Checks a requested particle count.
fn check_count(n: u32) -> Result<(), TissueError> {
    if n == 0 {
        return Err(TissueError::InvalidParameter {
            name: "particles",
            value: "0".into(),
            expected: "a particle count > 0",
        });
    }
    if n as usize > MAX_PARTICLES_PER_BODY {
        return Err(TissueError::TooManyParticles {
            requested: n as usize,
            limit: MAX_PARTICLES_PER_BODY,
        });
    }
    Ok(())
}

/// Interleaves the low 21 bits of three integers (Morton / Z-order code).
pub fn morton3(x: u32, y: u32, z: u32) -> u64 {
    fn spread(v: u32) -> u64 {
        let mut x = (v as u64) & 0x1f_ffff;
        x = (x | (x << 32)) & 0x1f00000000ffff;
        x = (x | (x << 16)) & 0x1f0000ff0000ff;
        x = (x | (x << 8)) & 0x100f00f00f00f00f;
        x = (x | (x << 4)) & 0x10c30c30c30c30c3;
        x = (x | (x << 2)) & 0x1249249249249249;
        x
    }
    spread(x) | (spread(y) << 1) | (spread(z) << 2)
}
