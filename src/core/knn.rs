//! Neighbour search: a uniform grid built by counting sort (cell counts, prefix sum,
//! scatter — the same three passes the GPU runs) and exact K-nearest-neighbour queries
//! on it, with a brute-force reference.
//!
//! Exactness: a query expands shells of cells (Chebyshev rings) around its cell and
//! stops only once the K-th best distance is no larger than the distance to any cell not
//! yet visited. Candidates are ordered by `(squared distance, index)`, so ties are broken
//! by the smaller index and the result is unique; the brute-force reference uses the same
//! order and the same [`dist2`] arithmetic, so both agree bit for bit.

use glam::Vec3;

/// Squared distance with a fixed evaluation order (shared by every search so ties agree).
#[inline(always)]
pub fn dist2(a: Vec3, b: Vec3) -> f32 {
    let d = a - b;
    d.x * d.x + d.y * d.y + d.z * d.z
}

/// A uniform grid over a point set, built by counting sort.
#[derive(Debug, Clone)]
pub struct Grid {
    /// Lower corner of cell (0, 0, 0), m.
    pub origin: Vec3,
    /// Cell edge length, m.
    pub cell: f32,
    /// Cells per axis.
    pub dims: [u32; 3],
    /// Exclusive prefix sum of points per cell; `cell_start[c]..cell_start[c + 1]` are the
    /// slots of cell `c` in `sorted`. Length `cells + 1`.
    pub cell_start: Vec<u32>,
    /// Point indices sorted by cell.
    pub sorted: Vec<u32>,
    /// Point positions in `sorted` order (a copy, for coherent reads).
    pub sorted_pos: Vec<Vec3>,
    /// Per cell, the tag all its points share ([`Grid::tag_cells`]), or [`NO_TAG`]
    /// (mixed or empty cells, or no tags given). Empty until tagged.
    pub cell_tag: Vec<u32>,
}

/// The tag of a grid cell whose points do not all share one ([`Grid::tag_cells`]).
pub const NO_TAG: u32 = u32::MAX;

impl Grid {
    /// Builds a grid over `points` with roughly `points_per_cell` points per cell on
    /// average over the bounding box (at most ~4 cells per point).
    pub fn build(points: &[Vec3], points_per_cell: f32) -> Grid {
        let (lo, hi) = super::mesh::bounds_of(points).unwrap_or((Vec3::ZERO, Vec3::ZERO));
        let ext = (hi - lo).max(Vec3::splat(1e-6));
        let n = points.len().max(1) as f32;
        let vol = ext.x * ext.y * ext.z;
        let mut cell = (vol * points_per_cell.max(0.25) / n).cbrt();
        // Keep the cell count bounded for flat or degenerate sets.
        let max_cells = (n * 4.0).max(64.0);
        loop {
            let d = (ext / cell).ceil() + Vec3::ONE;
            if d.x * d.y * d.z <= max_cells {
                break;
            }
            cell *= 1.25;
        }
        Self::build_with_cell(points, lo, cell)
    }

    /// Builds a grid with a given origin and cell size.
    pub fn build_with_cell(points: &[Vec3], origin: Vec3, cell: f32) -> Grid {
        let (_, hi) = super::mesh::bounds_of(points).unwrap_or((origin, origin));
        let d = ((hi - origin) / cell).floor() + Vec3::ONE;
        let dims = [
            d.x.max(1.0) as u32,
            d.y.max(1.0) as u32,
            d.z.max(1.0) as u32,
        ];
        let mut g = Grid {
            origin,
            cell,
            dims,
            cell_start: Vec::new(),
            sorted: Vec::new(),
            sorted_pos: Vec::new(),
            cell_tag: Vec::new(),
        };
        let cells = g.cell_count();
        // 1. counts
        let mut counts = vec![0u32; cells + 1];
        let cell_of: Vec<u32> = points.iter().map(|p| g.cell_index(*p)).collect();
        for &c in &cell_of {
            counts[c as usize] += 1;
        }
        // 2. exclusive prefix sum
        let mut acc = 0u32;
        for c in counts.iter_mut() {
            let v = *c;
            *c = acc;
            acc += v;
        }
        // 3. scatter (stable: points keep index order within a cell)
        let mut cursor = counts.clone();
        let mut sorted = vec![0u32; points.len()];
        for (i, &c) in cell_of.iter().enumerate() {
            sorted[cursor[c as usize] as usize] = i as u32;
            cursor[c as usize] += 1;
        }
        g.sorted_pos = sorted.iter().map(|&i| points[i as usize]).collect();
        g.sorted = sorted;
        g.cell_start = counts;
        g
    }

    /// Total number of cells.
    pub fn cell_count(&self) -> usize {
        self.dims[0] as usize * self.dims[1] as usize * self.dims[2] as usize
    }

    /// Integer cell coordinates of a point (clamped into the grid).
    #[inline]
    pub fn cell_coords(&self, p: Vec3) -> [i32; 3] {
        let c = ((p - self.origin) / self.cell).floor();
        [
            (c.x as i32).clamp(0, self.dims[0] as i32 - 1),
            (c.y as i32).clamp(0, self.dims[1] as i32 - 1),
            (c.z as i32).clamp(0, self.dims[2] as i32 - 1),
        ]
    }

    /// Linear cell index of a point.
    #[inline]
    pub fn cell_index(&self, p: Vec3) -> u32 {
        let c = self.cell_coords(p);
        c[0] as u32 + self.dims[0] * (c[1] as u32 + self.dims[1] * c[2] as u32)
    }

    /// The K nearest points to `q` (excluding index `skip`, pass `u32::MAX` for none),
    /// written into `out` as `(squared distance, index)` in increasing order. Returns the
    /// number found (less than K only if the set is smaller).
    pub fn knn_into(&self, q: Vec3, k: usize, skip: u32, out: &mut Vec<(f32, u32)>) -> usize {
        self.knn_filtered(q, k, f32::INFINITY, |i| i != skip, out)
    }

    /// The K nearest points to `q` that `accept` and that lie within `max_dist` (m), in
    /// increasing `(squared distance, index)` order. The shell expansion stops at
    /// `max_dist`, so a query far from every accepted point stays cheap.
    pub fn knn_filtered(
        &self,
        q: Vec3,
        k: usize,
        max_dist: f32,
        accept: impl Fn(u32) -> bool,
        out: &mut Vec<(f32, u32)>,
    ) -> usize {
        self.knn_bounded(q, k, max_dist, f32::INFINITY, accept, out)
    }

    /// [`Grid::knn_filtered`] given `known2` (m²): a squared distance within which at
    /// least `k` accepted points are known to lie (for instance the farthest of a
    /// previous search's `k` results, measured again), or infinity. Cells wholly beyond
    /// it (or beyond `max_dist`) are not visited; the result is the same, found sooner.
    /// A `known2` smaller than the truth drops points: it must be an upper bound.
    pub fn knn_bounded(
        &self,
        q: Vec3,
        k: usize,
        max_dist: f32,
        known2: f32,
        accept: impl Fn(u32) -> bool,
        out: &mut Vec<(f32, u32)>,
    ) -> usize {
        self.knn_bounded_skipping(q, k, max_dist, known2, NO_TAG, accept, out)
    }

    /// Tags every cell with the tag its points share (`tag` of each point index; for
    /// instance its body), or [`NO_TAG`] where they differ or there are none, for
    /// [`Grid::knn_bounded_skipping`].
    pub fn tag_cells(&mut self, tag: impl Fn(u32) -> u32) {
        let cells = self.cell_start.len().saturating_sub(1);
        self.cell_tag = (0..cells)
            .map(|c| {
                let slots =
                    &self.sorted[self.cell_start[c] as usize..self.cell_start[c + 1] as usize];
                let Some(&first) = slots.first() else {
                    return NO_TAG;
                };
                let t = tag(first);
                if slots.iter().all(|&j| tag(j) == t) {
                    t
                } else {
                    NO_TAG
                }
            })
            .collect();
    }

    /// [`Grid::knn_bounded`], not visiting the cells tagged `skip` ([`Grid::tag_cells`]):
    /// `accept` must refuse every point of tag `skip` (for instance, `skip` the query's
    /// own body when only other bodies' points are accepted), so the result is the same,
    /// found without measuring those points. [`NO_TAG`] skips nothing.
    #[allow(clippy::too_many_arguments)]
    pub fn knn_bounded_skipping(
        &self,
        q: Vec3,
        k: usize,
        max_dist: f32,
        known2: f32,
        skip: u32,
        accept: impl Fn(u32) -> bool,
        out: &mut Vec<(f32, u32)>,
    ) -> usize {
        out.clear();
        if k == 0 {
            return 0;
        }
        let c = self.cell_coords(q);
        // Unclamped position of q relative to the grid, to bound unvisited cells.
        let rel = (q - self.origin) / self.cell;
        // How far q's cell may be off by the rounding of `rel`, in cells.
        let ring_eps = 1.0e-3 + 1.0e-6 * rel.abs().max_element();
        let max_ring = self.dims.iter().copied().max().unwrap_or(1) as i32;
        let max2 = max_dist as f64 * max_dist as f64;
        let max2 = if max2 >= f32::MAX as f64 {
            f32::INFINITY
        } else {
            max2 as f32
        };
        // Only points within `bound2` can enter the list.
        let bound2 = max2.min(known2.max(0.0));
        let bound = bound2.sqrt();
        for r in 0..=max_ring {
            let lo = [c[0] - r, c[1] - r, c[2] - r];
            let hi = [c[0] + r, c[1] + r, c[2] + r];
            for z in lo[2].max(0)..=hi[2].min(self.dims[2] as i32 - 1) {
                let zr = z == lo[2] || z == hi[2];
                let gz = axis_gap(z, rel.z);
                for y in lo[1].max(0)..=hi[1].min(self.dims[1] as i32 - 1) {
                    let yr = zr || y == lo[1] || y == hi[1];
                    // Cells whose every point is beyond what can still enter the list
                    // are skipped: their box distance (in cells, squared) against the
                    // bound, widened by the rounding slack. Whole rows first.
                    let cut = match out.len() == k {
                        true => bound2.min(out[k - 1].0),
                        false => bound2,
                    };
                    let lim = if cut < f32::INFINITY {
                        (cut.sqrt() / self.cell + ring_eps).powi(2)
                    } else {
                        f32::INFINITY
                    };
                    let gy = axis_gap(y, rel.y);
                    let gzy = gz * gz + gy * gy;
                    if gzy > lim {
                        continue;
                    }
                    let row =
                        self.dims[0] as usize * (y as usize + self.dims[1] as usize * z as usize);
                    let mut x = lo[0].max(0);
                    let x1 = hi[0].min(self.dims[0] as i32 - 1);
                    while x <= x1 {
                        // Interior of the ring was visited earlier: skip straight across.
                        if !yr && x != lo[0] && x != hi[0] {
                            x = hi[0];
                            continue;
                        }
                        let gx = axis_gap(x, rel.x);
                        if gzy + gx * gx > lim {
                            x += 1;
                            continue;
                        }
                        let ci = x as usize + row;
                        if skip != NO_TAG && self.cell_tag.get(ci) == Some(&skip) {
                            x += 1;
                            continue;
                        }
                        let (s, e) = (
                            self.cell_start[ci] as usize,
                            self.cell_start[ci + 1] as usize,
                        );
                        for slot in s..e {
                            let idx = self.sorted[slot];
                            let d2 = dist2(q, self.sorted_pos[slot]);
                            if d2 <= bound2 && accept(idx) {
                                insert_sorted(out, k, (d2, idx));
                            }
                        }
                        x += 1;
                    }
                }
            }
            // Everything within the bound has been visited once the ring covers it: a
            // cell outside rings 0..=r is at least r cells from q's cell along an axis,
            // so at least r cell edges from q (less a little for q's cell rounding).
            if (r as f32 - ring_eps) * self.cell >= bound {
                break;
            }
            if out.len() == k {
                // Distance from q to the outside of the visited cube of cells.
                let mut bound = f32::MAX;
                for a in 0..3 {
                    let lo_face = (c[a] - r) as f32;
                    let hi_face = (c[a] + r + 1) as f32;
                    if c[a] - r > 0 {
                        bound = bound.min(rel[a] - lo_face);
                    }
                    if c[a] + r + 1 < self.dims[a] as i32 {
                        bound = bound.min(hi_face - rel[a]);
                    }
                }
                if bound == f32::MAX {
                    break; // the whole grid was visited
                }
                let b = (bound.max(0.0) * self.cell) as f64;
                if (out[k - 1].0 as f64) < b * b {
                    break;
                }
            }
        }
        out.len()
    }
}

/// Distance (in cells) from grid coordinate `rel` to cell `i`'s slab along one axis
/// (zero inside it).
#[inline(always)]
fn axis_gap(i: i32, rel: f32) -> f32 {
    let lo = i as f32;
    (lo - rel).max(rel - lo - 1.0).max(0.0)
}

/// How far apart two bodies' particle bounding boxes must be (m) for no contact
/// candidate between them: the largest contact reach, `4 × max_radius` (a particle of a
/// body with radius `r` searches within `2 (r + max_radius)`), plus a margin for f32
/// rounding. The broad phase below and its GPU twin (`broad.wgsl`) use it.
pub fn contact_reach_bound(max_radius: f32) -> f32 {
    4.0 * max_radius * 1.001 + 1.0e-6
}

/// Bodies beyond which the contact broad phase ([`near_bodies`]) counts every body as
/// near another instead of testing all pairs (`BROAD_MAX_BODIES` in `broad.wgsl`).
pub const BROAD_MAX_BODIES: usize = 2048;

/// Broad phase of the particle contacts: per body, whether its bounding box `boxes[b]`
/// (min, max; m), grown by `reach` (m) on every side, overlaps another body's box. A body
/// that is near no other has no contact candidates, and no other body's particle has one
/// of its particles as candidate, so its contact search, its contact pass and its copy
/// through the contact buffer are skipped, with the same result. O(bodies²) box tests, so
/// above [`BROAD_MAX_BODIES`] bodies every body counts as near (no skipping, the same
/// result). GPU twin: `near_bodies` in `broad.wgsl`.
pub fn near_bodies(boxes: &[(Vec3, Vec3)], reach: f32) -> Vec<bool> {
    if boxes.len() > BROAD_MAX_BODIES {
        return vec![true; boxes.len()];
    }
    boxes
        .iter()
        .enumerate()
        .map(|(b, &(lo, hi))| {
            let (lo, hi) = (lo - Vec3::splat(reach), hi + Vec3::splat(reach));
            boxes
                .iter()
                .enumerate()
                .any(|(c, &(l, h))| c != b && lo.cmple(h).all() && l.cmple(hi).all())
        })
        .collect()
}

/// Each body's bounding box of `x` (bodies as `(first, count)` particle ranges).
pub fn body_boxes(x: &[Vec3], ranges: impl Iterator<Item = (u32, u32)>) -> Vec<(Vec3, Vec3)> {
    ranges
        .map(|(first, count)| {
            x[first as usize..(first + count) as usize].iter().fold(
                (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
                |(lo, hi), &p| (lo.min(p), hi.max(p)),
            )
        })
        .collect()
}

/// Inserts `cand` into the sorted list `out` (at most `k` long), ordered by
/// `(distance², index)`.
#[inline]
pub fn insert_sorted(out: &mut Vec<(f32, u32)>, k: usize, cand: (f32, u32)) {
    let less = |a: &(f32, u32), b: &(f32, u32)| a.0 < b.0 || (a.0 == b.0 && a.1 < b.1);
    if out.len() == k {
        if !less(&cand, &out[k - 1]) {
            return;
        }
        out.pop();
    }
    let mut i = out.len();
    out.push(cand);
    while i > 0 && less(&cand, &out[i - 1]) {
        out[i] = out[i - 1];
        i -= 1;
    }
    out[i] = cand;
}

/// K nearest neighbours of every point (itself excluded), as a flat `n × k` array of
/// indices, nearest first; uses the grid and all cores.
///
/// Returns `None` when `k >= points.len()`.
pub fn knn_all(points: &[Vec3], k: usize, threads: usize) -> Option<Vec<u32>> {
    if k >= points.len() {
        return None;
    }
    let grid = Grid::build(points, 2.0);
    let mut out = vec![0u32; points.len() * k];
    super::par::for_chunks_mut(&mut out, k, threads, |start, chunk| {
        let mut buf = Vec::with_capacity(k + 1);
        for (r, row) in chunk.chunks_exact_mut(k).enumerate() {
            let i = start + r;
            grid.knn_into(points[i], k, i as u32, &mut buf);
            for (o, (_, j)) in row.iter_mut().zip(&buf) {
                *o = *j;
            }
        }
    });
    Some(out)
}

/// Brute-force K nearest neighbours of every point (the reference for tests).
pub fn knn_brute_force(points: &[Vec3], k: usize) -> Option<Vec<u32>> {
    if k >= points.len() {
        return None;
    }
    let mut out = Vec::with_capacity(points.len() * k);
    let mut buf = Vec::with_capacity(k + 1);
    for (i, &q) in points.iter().enumerate() {
        buf.clear();
        for (j, &p) in points.iter().enumerate() {
            if j != i {
                insert_sorted(&mut buf, k, (dist2(q, p), j as u32));
            }
        }
        out.extend(buf.iter().map(|&(_, j)| j));
    }
    Some(out)
}
