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
            Ok(sample_count(surface, n as usize))
        }
    }
}

/// Searches spacing and lattice offset for a count closest to `target`.
fn sample_count(surface: &Surface, target: usize) -> Samples {
    let count = |s: f64, shift: DVec3| sample_lattice(surface, s, shift);
    let centre = DVec3::splat(0.5);
    // Bisection on the spacing (count falls as spacing grows).
    let s0 = (surface.volume / target as f64).cbrt();
    let (mut lo, mut hi) = (s0 * 0.5, s0 * 2.0);
    let mut best = count(s0, centre);
    let score = |n: usize| (n as i64 - target as i64).unsigned_abs();
    for _ in 0..40 {
        let mid = 0.5 * (lo + hi);
        let smp = count(mid, centre);
        let n = smp.positions.len();
        if score(n) < score(best.positions.len()) {
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
    if score(best.positions.len()) <= tol {
        return best;
    }
    // Jumps too large (flat faces fill a whole lattice plane at once): also vary the
    // sub-cell offset of the lattice near the crossing spacing.
    let s_mid = best.spacing as f64;
    let shifts = [0.0, 0.25, 0.5, 0.75];
    'outer: for ds in -8..=8 {
        let s = s_mid * (1.0 + ds as f64 * 0.002);
        for &sx in &shifts {
            for &sy in &shifts {
                for &sz in &shifts {
                    let smp = count(s, DVec3::new(sx, sy, sz));
                    if score(smp.positions.len()) < score(best.positions.len()) {
                        best = smp;
                        if score(best.positions.len()) <= tol {
                            break 'outer;
                        }
                    }
                }
            }
        }
    }
    best
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
