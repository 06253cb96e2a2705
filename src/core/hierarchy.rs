//! The particle hierarchy of hierarchical position-based dynamics (Müller 2008,
//! "Hierarchical position based dynamics", §4): level 0 is a body's particles; level
//! l + 1 is an evenly spread subset of level l (the lattice points whose coordinates at
//! level l's spacing are all even, under the best of the eight parities: at least an
//! eighth of the level); every particle of level l is linked to its `parents` nearest
//! particles of level l + 1 with interpolation weights that sum to 1 (weights fall off
//! as `1/(d + s/2)²`, `s` the coarse spacing, as in the skin).
//!
//! This module builds the hierarchy and checks it; the coarse-level constraints and the
//! coarse-to-fine schedule build on it.

use super::error::TissueError;
use super::knn::Grid;
use glam::{IVec3, Vec3};

/// How a hierarchy is built.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HierarchyDesc {
    /// Number of levels including level 0; `None` chooses it from the body's size:
    /// coarsen while the next level keeps at least `min_particles` particles.
    pub levels: Option<u32>,
    /// Parents per particle on the next level (2–4).
    pub parents: u32,
    /// Fewest particles a coarse level may have when the level count is automatic.
    pub min_particles: u32,
}

impl Default for HierarchyDesc {
    fn default() -> Self {
        Self {
            levels: None,
            parents: 3,
            min_particles: 128,
        }
    }
}

/// Most levels a hierarchy may have.
pub const MAX_LEVELS: u32 = 8;

/// One level of a hierarchy.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct HierarchyLevel {
    /// The level's particles, as indices into the level-0 particle array.
    pub particles: Vec<u32>,
    /// Lattice spacing of the level, m (level 0: the sampling spacing; doubles per level).
    pub spacing: f32,
    /// For each particle of this level, its parents on the next level: CSR starts into
    /// `parents`/`weights` (length `particles.len() + 1`; empty on the coarsest level).
    pub parent_start: Vec<u32>,
    /// Parents, as positions in the next level's `particles`.
    pub parents: Vec<u32>,
    /// Interpolation weight of each parent (per particle they sum to 1).
    pub weights: Vec<f32>,
}

/// A body's particle hierarchy, finest level first.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Hierarchy {
    /// Levels, `levels[0]` holding every particle.
    pub levels: Vec<HierarchyLevel>,
}

impl Hierarchy {
    /// Builds the hierarchy of the lattice-sampled particles `rest` (body frame, m)
    /// whose lattice spacing is `spacing` (m). Fails on invalid parameters.
    pub fn build(rest: &[Vec3], spacing: f32, desc: &HierarchyDesc) -> Result<Self, TissueError> {
        if !(2..=4).contains(&desc.parents) {
            return Err(TissueError::InvalidParameter {
                name: "parents",
                value: desc.parents.to_string(),
                expected: "2 to 4 parents per particle",
            });
        }
        if let Some(l) = desc.levels
            && !(1..=MAX_LEVELS).contains(&l)
        {
            return Err(TissueError::InvalidParameter {
                name: "levels",
                value: l.to_string(),
                expected: "1 to 8 levels",
            });
        }
        if !(spacing.is_finite() && spacing > 0.0) {
            return Err(TissueError::InvalidParameter {
                name: "spacing",
                value: spacing.to_string(),
                expected: "a finite spacing > 0",
            });
        }
        let mut levels = vec![HierarchyLevel {
            particles: (0..rest.len() as u32).collect(),
            spacing,
            ..Default::default()
        }];
        let origin = rest
            .iter()
            .fold(Vec3::splat(f32::INFINITY), |a, p| a.min(*p));
        loop {
            let fine = levels.last().expect("level 0 exists");
            let want_more = match desc.levels {
                Some(l) => (levels.len() as u32) < l,
                None => levels.len() < MAX_LEVELS as usize,
            };
            if !want_more {
                break;
            }
            let coarse = subset(rest, origin, fine);
            let enough = match desc.levels {
                Some(_) => coarse.len() > desc.parents as usize,
                None => coarse.len() >= desc.min_particles.max(desc.parents + 1) as usize,
            };
            if !enough {
                break;
            }
            let spacing = fine.spacing * 2.0;
            levels.push(HierarchyLevel {
                particles: coarse,
                spacing,
                ..Default::default()
            });
        }
        // Parents of every level but the coarsest.
        for l in 0..levels.len().saturating_sub(1) {
            let (fine, coarse) = {
                let (a, b) = levels.split_at_mut(l + 1);
                (&mut a[l], &b[0])
            };
            link(rest, fine, coarse, desc.parents as usize);
        }
        Ok(Self { levels })
    }
}

/// The evenly spread subset of `fine`: lattice points (at `fine.spacing`) whose integer
/// coordinates have the parity, among the eight, that keeps the most points.
fn subset(rest: &[Vec3], origin: Vec3, fine: &HierarchyLevel) -> Vec<u32> {
    let coords: Vec<IVec3> = fine
        .particles
        .iter()
        .map(|&i| {
            ((rest[i as usize] - origin) / fine.spacing)
                .round()
                .as_ivec3()
        })
        .collect();
    let parity = |c: IVec3| ((c.x & 1) | ((c.y & 1) << 1) | ((c.z & 1) << 2)) as usize;
    let mut counts = [0usize; 8];
    for &c in &coords {
        counts[parity(c)] += 1;
    }
    let best = (0..8)
        .max_by_key(|&p| (counts[p], usize::MAX - p))
        .unwrap_or(0);
    fine.particles
        .iter()
        .zip(&coords)
        .filter(|(_, c)| parity(**c) == best)
        .map(|(&i, _)| i)
        .collect()
}

/// Links every particle of `fine` to its `k` nearest particles of `coarse`.
fn link(rest: &[Vec3], fine: &mut HierarchyLevel, coarse: &HierarchyLevel, k: usize) {
    let pts: Vec<Vec3> = coarse.particles.iter().map(|&i| rest[i as usize]).collect();
    let grid = Grid::build(&pts, 2.0);
    let k = k.min(pts.len());
    let mut buf = Vec::with_capacity(k + 1);
    fine.parent_start = vec![0];
    fine.parents.clear();
    fine.weights.clear();
    for &i in &fine.particles {
        grid.knn_into(rest[i as usize], k, u32::MAX, &mut buf);
        let w: Vec<f32> = buf
            .iter()
            .map(|&(d2, _)| 1.0 / (d2.sqrt() + 0.5 * coarse.spacing).powi(2))
            .collect();
        let sum: f32 = w.iter().sum();
        for (&(_, j), wi) in buf.iter().zip(w) {
            fine.parents.push(j);
            fine.weights.push(wi / sum);
        }
        fine.parent_start.push(fine.parents.len() as u32);
    }
}
