//! The dispatches of a world's time steps as data: a pure function of the world's
//! shape ([`Shape`]) and the solver settings, made and tested on the CPU; the world's
//! recording replays it (`record`).
//!
//! A step (the CPU Jacobi solver's, `core::solver`): contact neighbours every
//! `knn_every` steps (broad phase, grid, K nearest), then per substep predict (the first
//! substep of a recording only: a finish predicts the next), the hierarchy's coarse
//! levels, `iterations` Jacobi iterations (clusters and gather, or `body.wgsl` a
//! workgroup per small body) in blocks that each end with the particle-contact pass,
//! collider forces, finish.

use crate::core::solver::SolverSettings;
use crate::gpu::buffers::{FORCE_GROUPS, PackedLevel, SCAN_BLOCK, WORKGROUP};
use crate::gpu::kernels::{Kernel, Kernels};

/// A kernel of [`Kernels`], named without a device.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Op {
    /// Predict.
    Predict,
    /// The last substep's finish.
    Finish,
    /// A substep's finish and the next one's predict.
    FinishPredict,
    /// Per-body bounding boxes.
    BodyBounds,
    /// The contact broad phase.
    NearBodies,
    /// Zero the collider force totals.
    ForceClear,
    /// Collider force partial sums.
    ForcePartial,
    /// Collider force totals.
    ForceTotal,
    /// Grid: zero the counts.
    GridClear,
    /// Grid: cell counts.
    GridCount,
    /// Prefix sum: one level's blocks.
    ScanBlock,
    /// Prefix sum: one level's block offsets.
    ScanAdd,
    /// Grid: scatter.
    GridScatter,
    /// K nearest of every particle (`warm`: from the previous lists; `slots`: index
    /// into the list sizes, [`Kernels::knn_slots`]).
    KnnAll {
        /// Starts from the previous lists.
        warm: bool,
        /// List size index.
        slots: usize,
    },
    /// Contact candidates (as [`Op::KnnAll`]).
    KnnContacts {
        /// Starts from the previous lists.
        warm: bool,
        /// List size index.
        slots: usize,
    },
    /// Jacobi pass A, a thread per cluster.
    Clusters,
    /// Jacobi pass A, 8 threads per cluster.
    ClustersLanes,
    /// Jacobi pass B.
    Gather,
    /// Jacobi pass C (particle contacts).
    Contact,
    /// `body.wgsl`: every iteration of the bodies near no other.
    BodySubstep,
    /// `body.wgsl`: one block of iterations.
    BodyIteration,
    /// Hierarchy: snapshot.
    LevelSnapshot,
    /// Hierarchy: level-0 positions into a coarse level.
    LevelIn,
    /// Hierarchy: back to level 0.
    LevelOut,
    /// Hierarchy: prolongation.
    Prolong,
    /// Hierarchy: multiplier transfer.
    Transfer,
}

impl Op {
    /// The pipeline and layouts of this kernel (`None`: `body.wgsl`'s on an adapter
    /// without it).
    pub fn kernel(self, k: &Kernels) -> Option<&Kernel> {
        Some(match self {
            Op::Predict => &k.predict,
            Op::Finish => &k.finish,
            Op::FinishPredict => &k.finish_predict,
            Op::BodyBounds => &k.body_bounds,
            Op::NearBodies => &k.near_bodies,
            Op::ForceClear => &k.force_clear,
            Op::ForcePartial => &k.force_partial,
            Op::ForceTotal => &k.force_total,
            Op::GridClear => &k.grid_clear,
            Op::GridCount => &k.grid_count,
            Op::ScanBlock => &k.scan_block,
            Op::ScanAdd => &k.scan_add,
            Op::GridScatter => &k.grid_scatter,
            Op::KnnAll { warm, slots } => &k.knn_all[warm as usize][slots],
            Op::KnnContacts { warm, slots } => &k.knn_contacts[warm as usize][slots],
            Op::Clusters => &k.clusters,
            Op::ClustersLanes => &k.clusters_lanes,
            Op::Gather => &k.gather,
            Op::Contact => &k.contact,
            Op::BodySubstep => &k.body.as_ref()?.substep,
            Op::BodyIteration => &k.body.as_ref()?.iteration,
            Op::LevelSnapshot => &k.level_snapshot,
            Op::LevelIn => &k.level_in,
            Op::LevelOut => &k.level_out,
            Op::Prolong => &k.prolong,
            Op::Transfer => &k.transfer,
        })
    }
}

/// A dispatch's per-dispatch group (group 3).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Window {
    /// None.
    None,
    /// The world's range record of this index (`GpuRange`, 256 bytes each).
    Range(u32),
    /// The prefix sum's record of this index (`GpuScanLevel`, 256 bytes each; after
    /// the levels, the contacts' grid build, then the all-particle search's).
    Level(u32),
}

/// One dispatch of a plan.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Dispatch {
    /// The kernel.
    pub op: Op,
    /// Its pass name (profiles and diagnostics group by it).
    pub name: &'static str,
    /// Its per-dispatch record.
    pub window: Window,
    /// Workgroups (x, y).
    pub groups: (u32, u32),
}

/// What the plan needs of a world.
#[derive(Debug, Clone, PartialEq)]
pub struct Shape<'a> {
    /// Level-0 particles.
    pub n: u32,
    /// Bodies.
    pub bodies: u32,
    /// Colliders in use.
    pub colliders: u32,
    /// Particle contacts on (more than one body).
    pub contacts_on: bool,
    /// Contact candidates per particle.
    pub contact_k: u32,
    /// `body.wgsl` solves some bodies.
    pub body_kernel: bool,
    /// `body.wgsl` solves every body.
    pub all_in_body: bool,
    /// The hierarchy's coarse levels.
    pub coarse: &'a [PackedLevel],
    /// The prefix sum's levels (first element, elements).
    pub scan_levels: &'a [(u32, u32)],
    /// Elements of the prefix sum.
    pub scan_len: u32,
    /// Hash buckets of the grid.
    pub grid_table: u32,
    /// The first of level 0's iteration records (16 per block length).
    pub iteration_records: u32,
    /// Longest block of iterations the records were made for.
    pub block_records: u32,
    /// Cluster ranges below this many use 8 threads a cluster.
    pub lanes_below: u32,
}

/// What carries over from one recording to the next.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Cursor {
    /// Steps taken.
    pub step: u64,
    /// The contact lists hold a previous search.
    pub contacts_warm: bool,
    /// The next step searches contacts whatever the step count.
    pub refresh: bool,
}

/// `n` items at `per` a workgroup (at least one workgroup).
pub fn groups(n: u32, per: u32) -> u32 {
    n.div_ceil(per).max(1)
}

/// `g` workgroups as a 2-D grid within 65,535 per dimension.
pub fn grid_2d(g: u32) -> (u32, u32) {
    if g <= 65_535 {
        (g, 1)
    } else {
        let y = g.div_ceil(65_535);
        (g.div_ceil(y), y)
    }
}

/// Particles handled by one workgroup of the gather kernel (4 threads each; the lane
/// count is `LANES` in `gather.wgsl`).
pub const PER_LANE_GROUP: u32 = WORKGROUP / 4;

/// A 2-D grid of workgroups for the gather kernel (the kernels linearise it), so that
/// millions of particles stay under the 65,535 groups per dimension.
fn lane_groups(n: u32) -> (u32, u32) {
    grid_2d(groups(n, PER_LANE_GROUP))
}

/// Threads per cluster of `solve_clusters_lanes` (`LANES` in `cluster.wgsl`).
const CLUSTER_LANES: u32 = 8;

/// The cluster kernel for a range of `n` clusters and its workgroup grid (8 threads per
/// cluster below `lanes_below` clusters).
fn cluster_op(n: u32, lanes_below: u32) -> (Op, (u32, u32)) {
    if n < lanes_below {
        (
            Op::ClustersLanes,
            grid_2d(groups(n, WORKGROUP / CLUSTER_LANES)),
        )
    } else {
        (Op::Clusters, grid_2d(groups(n, WORKGROUP)))
    }
}

/// A workgroup per body for `nb` bodies, as the per-body kernels index them
/// (`wid.x + wid.y * 65535`: `body_bounds`, `near_bodies`).
pub fn per_body_groups(nb: u32) -> (u32, u32) {
    (nb.min(65_535), nb.div_ceil(65_535))
}

/// Most Jacobi iterations between two contact passes:
/// [`SolverSettings::contact_every`], at most `iterations`.
pub fn max_block(s: &SolverSettings) -> u32 {
    s.contact_every.clamp(1, s.iterations.max(1))
}

/// The grid build over the current positions (clear, counts, prefix sum, scatter);
/// `all` picks the all-particle search's cell size, else the contacts'.
pub fn grid(shape: &Shape, all: bool) -> Vec<Dispatch> {
    let mut out = Vec::new();
    let g = (groups(shape.n, WORKGROUP), 1);
    let cfg = Window::Level(shape.scan_levels.len() as u32 + all as u32);
    let clear = groups(shape.scan_len.max(shape.grid_table), WORKGROUP).min(65_535);
    let mut push = |op, name, window, groups| {
        out.push(Dispatch {
            op,
            name,
            window,
            groups,
        })
    };
    push(Op::GridClear, "tissue/grid", cfg, (clear, 1));
    push(Op::GridCount, "tissue/grid", cfg, g);
    for (l, &(_, c)) in shape.scan_levels.iter().enumerate() {
        let wg = (groups(c, SCAN_BLOCK), 1);
        push(Op::ScanBlock, "tissue/scan", Window::Level(l as u32), wg);
    }
    for l in (0..shape.scan_levels.len().saturating_sub(1)).rev() {
        let wg = (groups(shape.scan_levels[l].1, SCAN_BLOCK), 1);
        push(Op::ScanAdd, "tissue/scan", Window::Level(l as u32), wg);
    }
    push(Op::GridScatter, "tissue/grid", cfg, g);
    out
}

/// The K nearest neighbours of every particle (`knn_k`; `warm`: starting from the
/// previous search's lists), grid included.
pub fn knn_all(shape: &Shape, knn_k: u32, warm: bool) -> Vec<Dispatch> {
    let mut out = grid(shape, true);
    out.push(Dispatch {
        op: Op::KnnAll {
            warm,
            slots: Kernels::knn_slots(knn_k),
        },
        name: "tissue/knn",
        window: Window::None,
        groups: (groups(shape.n, WORKGROUP), 1),
    });
    out
}

/// `count` time steps from `cursor` (advanced past them). Within a recording a
/// substep's finish also predicts the next substep, so inputs such as colliders, pins
/// and sleep flags hold for all its steps.
pub fn steps(shape: &Shape, s: &SolverSettings, cursor: &mut Cursor, count: u32) -> Vec<Dispatch> {
    let mut out = Vec::new();
    let g = (groups(shape.n, WORKGROUP), 1);
    let lg = lane_groups(shape.n);
    let (cp, cg) = cluster_op(shape.n, shape.lanes_below);
    let body = shape.body_kernel;
    let all_in_body = body && shape.all_in_body;
    // With `body.wgsl` and contacts, an iteration's contact pass for its bodies runs at
    // the start of the next body_iteration (see the iteration loop below).
    let folded = body && shape.contacts_on;
    let nb = shape.bodies;
    let lv0 = Window::Range(0);
    for step in 0..count {
        let mut push = |op, name, window, groups| {
            out.push(Dispatch {
                op,
                name,
                window,
                groups,
            })
        };
        let due = cursor.step.is_multiple_of(s.knn_every.max(1) as u64) || cursor.refresh;
        if shape.contacts_on && due {
            cursor.refresh = false;
            // Broad phase first: bodies near no other skip the search and the contact
            // pass until the next refresh.
            let bg = per_body_groups(nb);
            push(Op::BodyBounds, "tissue/broad", Window::None, bg);
            push(Op::NearBodies, "tissue/broad", Window::None, bg);
            for d in grid(shape, false) {
                push(d.op, d.name, d.window, d.groups);
            }
            let knn = Op::KnnContacts {
                warm: cursor.contacts_warm,
                slots: Kernels::knn_slots(shape.contact_k),
            };
            cursor.contacts_warm = true;
            push(knn, "tissue/knn", Window::None, g);
        }
        let nc = shape.colliders;
        if nc > 0 {
            push(Op::ForceClear, "tissue/forces", Window::None, (1, 1));
        }
        for sub in 0..s.substeps {
            // The first substep of the recording predicts; the others were predicted
            // by the finish before them.
            if step == 0 && sub == 0 {
                push(Op::Predict, "tissue/predict", Window::None, g);
            }
            if s.coarse_iterations > 0 && !shape.coarse.is_empty() {
                levels(shape, s, &mut push);
            }
            // `body.wgsl`: all iterations of the bodies near no other at once, then one
            // dispatch per iteration block for those with contact candidates (only with
            // particle contacts on). With contacts the first of those solves the bodies
            // near no other too, so body_substep runs only without them.
            if body && !shape.contacts_on {
                push(Op::BodySubstep, "tissue/body_substep", lv0, grid_2d(nb));
            }
            // Iterations in blocks that end with one solving particle contacts (every
            // `contact_every`-th and the last; without contacts one block, which only
            // the cluster and gather kernels see). Blocks alternate between the halves
            // of p2. With `folded`, a block's contact pass for `body.wgsl`'s bodies runs
            // at the start of the next block's body_iteration (`prev`), so the contact
            // dispatch leaves them out (`skip`) but after the last block, and is not
            // needed at all before then when every body is `body.wgsl`'s.
            let every = if shape.contacts_on {
                // (At most the block length the records were made for, should the
                // settings have changed since.)
                max_block(s).min(shape.block_records)
            } else {
                s.iterations
            };
            let mut start = 0;
            let mut block = 0u32;
            while start < s.iterations {
                let end = (start + every).min(s.iterations);
                let last = end == s.iterations;
                let v = (block % 2)
                    | (((folded && block > 0) as u32) << 1)
                    | (((folded && !last) as u32) << 2);
                let rec = |v: u32, iters: u32| {
                    Window::Range(shape.iteration_records + v + 16 * (iters - 1))
                };
                if body && shape.contacts_on {
                    let d = rec(v, end - start);
                    push(Op::BodyIteration, "tissue/body_iteration", d, grid_2d(nb));
                }
                if !all_in_body {
                    for it in start..end {
                        // Iterations before the block's last: no contact pass (flag 0).
                        let one = if it + 1 == end {
                            rec(v, 1)
                        } else {
                            rec(v | 8, 1)
                        };
                        push(cp, "tissue/clusters", one, cg);
                        push(Op::Gather, "tissue/gather", one, lg);
                    }
                }
                if shape.contacts_on && (last || !(folded && all_in_body)) {
                    push(Op::Contact, "tissue/contacts", rec(v, 1), g);
                }
                start = end;
                block += 1;
            }
            if nc > 0 {
                let fg = (FORCE_GROUPS, nc);
                push(Op::ForcePartial, "tissue/forces", Window::None, fg);
                push(Op::ForceTotal, "tissue/forces", Window::None, (1, 1));
            }
            if step + 1 == count && sub + 1 == s.substeps {
                push(Op::Finish, "tissue/finish", Window::None, g);
            } else {
                push(Op::FinishPredict, "tissue/finish", Window::None, g);
            }
        }
        cursor.step += 1;
    }
    out
}

/// The hierarchy's coarse levels for one substep, coarsest first (the twin of
/// `core::solver::Solver::solve_levels`): snapshot, then per level: its particles in,
/// `coarse_iterations` Jacobi iterations over its range, out, prolongation, and its
/// multipliers handed to the finer level.
fn levels(
    shape: &Shape,
    s: &SolverSettings,
    push: &mut impl FnMut(Op, &'static str, Window, (u32, u32)),
) {
    let name = "tissue/levels";
    push(
        Op::LevelSnapshot,
        name,
        Window::None,
        (groups(shape.n, WORKGROUP), 1),
    );
    for (l, lv) in shape.coarse.iter().enumerate().rev() {
        let parts = Window::Range(1 + 3 * l as u32);
        let recs = Window::Range(2 + 3 * l as u32);
        let trs = Window::Range(3 + 3 * l as u32);
        let g = (groups(lv.count, WORKGROUP), 1);
        let (cp, cg) = cluster_op(lv.count, shape.lanes_below);
        push(Op::LevelIn, name, parts, g);
        for _ in 0..s.coarse_iterations {
            push(cp, name, parts, cg);
            push(Op::Gather, name, parts, lane_groups(lv.count));
        }
        push(Op::LevelOut, name, parts, g);
        push(
            Op::Prolong,
            name,
            recs,
            (groups(lv.rec_count, WORKGROUP), 1),
        );
        push(Op::Transfer, name, trs, (groups(lv.tr_count, WORKGROUP), 1));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::solver::Method;

    fn shape(n: u32, bodies: u32) -> Shape<'static> {
        Shape {
            n,
            bodies,
            colliders: 0,
            contacts_on: false,
            contact_k: 8,
            body_kernel: false,
            all_in_body: false,
            coarse: &[],
            // (Leaked: a test's few bytes, so that the shape can borrow them.)
            scan_levels: Vec::leak(vec![(0, 2 * n), (2 * n, 2 * n / SCAN_BLOCK + 1)]),
            scan_len: 2 * n + 2 * n / SCAN_BLOCK + 2,
            grid_table: 2 * n,
            iteration_records: 1,
            block_records: 2,
            lanes_below: 8192,
        }
    }

    fn settings(iterations: u32, substeps: u32) -> SolverSettings {
        SolverSettings {
            method: Method::Jacobi,
            iterations,
            substeps,
            knn_every: 5,
            contact_every: 2,
            ..Default::default()
        }
    }

    fn count(plan: &[Dispatch], op: Op) -> usize {
        plan.iter().filter(|d| d.op == op).count()
    }

    /// Without contacts or colliders: predict once, then per substep `iterations` ×
    /// (clusters, gather) and a finish, the last one not predicting.
    #[test]
    fn a_plain_step_is_predict_iterations_finish() {
        let s = settings(10, 2);
        let mut c = Cursor::default();
        let plan = steps(&shape(40_000, 1), &s, &mut c, 3);
        assert_eq!(plan.len(), 1 + 3 * 2 * (2 * 10 + 1));
        assert_eq!(plan[0].op, Op::Predict);
        assert_eq!(count(&plan, Op::Clusters), 60);
        assert_eq!(count(&plan, Op::Gather), 60);
        assert_eq!(count(&plan, Op::FinishPredict), 5);
        assert_eq!(plan.last().map(|d| d.op), Some(Op::Finish));
        assert_eq!(c.step, 3);
        // Small ranges take the 8-lane cluster kernel.
        let small = steps(&shape(1_000, 1), &s, &mut Cursor::default(), 1);
        assert_eq!(count(&small, Op::ClustersLanes), 20);
        assert_eq!(count(&small, Op::Clusters), 0);
    }

    /// Contacts are searched every `knn_every` steps (cold, then warm), or at once when
    /// a refresh is asked for; each substep's iterations come in blocks of
    /// `contact_every`, each ending with the contact pass.
    #[test]
    fn contacts_are_searched_on_schedule_and_passed_per_block() {
        let s = settings(10, 1);
        let sh = Shape {
            contacts_on: true,
            ..shape(40_000, 4)
        };
        let mut c = Cursor::default();
        let plan = steps(&sh, &s, &mut c, 10);
        let searches: Vec<Op> = plan
            .iter()
            .filter(|d| matches!(d.op, Op::KnnContacts { .. }))
            .map(|d| d.op)
            .collect();
        let slots = Kernels::knn_slots(8);
        assert_eq!(
            searches,
            [
                Op::KnnContacts { warm: false, slots },
                Op::KnnContacts { warm: true, slots }
            ]
        );
        assert_eq!(count(&plan, Op::NearBodies), 2);
        assert_eq!(count(&plan, Op::Contact), 10 * 5, "a pass per block of 2");
        // A refresh mid-schedule searches at the next step, then the schedule goes on.
        let mut c = Cursor {
            step: 7,
            contacts_warm: true,
            refresh: true,
        };
        let plan = steps(&sh, &s, &mut c, 4);
        assert_eq!(
            count(&plan, Op::NearBodies),
            1 + 1,
            "steps 7 (asked) and 10"
        );
        assert!(!c.refresh);
        // Without contacts nothing is searched, asked or not.
        let mut c = Cursor {
            refresh: true,
            ..Cursor::default()
        };
        let plan = steps(&shape(40_000, 4), &s, &mut c, 10);
        assert_eq!(count(&plan, Op::NearBodies), 0);
        assert_eq!(count(&plan, Op::Contact), 0);
    }

    /// With `body.wgsl` for every body and contacts on, each block is one
    /// body_iteration (its contact pass folded into the next) and the contact kernel
    /// runs once, after the last; without contacts one body_substep does everything.
    #[test]
    fn body_kernel_blocks_fold_the_contact_pass() {
        let s = settings(10, 1);
        let sh = Shape {
            contacts_on: true,
            body_kernel: true,
            all_in_body: true,
            ..shape(512_000, 1000)
        };
        let plan = steps(&sh, &s, &mut Cursor::default(), 1);
        assert_eq!(count(&plan, Op::BodyIteration), 5);
        assert_eq!(count(&plan, Op::Contact), 1);
        assert_eq!(count(&plan, Op::Clusters) + count(&plan, Op::Gather), 0);
        // Every record lies within the records made: 16 per block length.
        let end = sh.iteration_records + 16 * sh.block_records;
        for d in &plan {
            if let Window::Range(r) = d.window {
                assert!(r < end, "{d:?} reads record {r} of {end}");
            }
        }
        let alone = Shape {
            contacts_on: false,
            ..sh.clone()
        };
        let plan = steps(&alone, &s, &mut Cursor::default(), 1);
        assert_eq!(count(&plan, Op::BodySubstep), 1);
        assert_eq!(count(&plan, Op::BodyIteration), 0);
        assert_eq!(count(&plan, Op::Clusters), 0);
        // Bodies the kernel does not solve go on with clusters and gather.
        let mixed = Shape {
            all_in_body: false,
            ..sh
        };
        let plan = steps(&mixed, &s, &mut Cursor::default(), 1);
        assert_eq!(count(&plan, Op::BodyIteration), 5);
        assert_eq!(count(&plan, Op::Contact), 5);
        assert_eq!(
            count(&plan, Op::Clusters) + count(&plan, Op::ClustersLanes),
            10
        );
    }

    /// Colliders add the force clear once a step and partial and total sums per
    /// substep; the hierarchy runs its levels coarsest first every substep.
    #[test]
    fn colliders_and_levels_are_planned_per_substep() {
        let s = SolverSettings {
            coarse_iterations: 3,
            ..settings(10, 2)
        };
        let lv = |first, count| PackedLevel {
            first,
            count,
            rec_first: 0,
            rec_count: count,
            tr_first: 0,
            tr_count: count,
        };
        let levels = [lv(40_000, 5_000), lv(45_000, 700)];
        let sh = Shape {
            colliders: 3,
            coarse: &levels,
            iteration_records: 7,
            ..shape(40_000, 1)
        };
        let plan = steps(&sh, &s, &mut Cursor::default(), 2);
        assert_eq!(count(&plan, Op::ForceClear), 2);
        assert_eq!(count(&plan, Op::ForcePartial), 4);
        assert_eq!(count(&plan, Op::ForceTotal), 4);
        assert!(
            plan.iter()
                .all(|d| d.op != Op::ForcePartial || d.groups == (FORCE_GROUPS, 3))
        );
        assert_eq!(count(&plan, Op::LevelSnapshot), 4);
        let ins: Vec<Window> = plan
            .iter()
            .filter(|d| d.op == Op::LevelIn)
            .map(|d| d.window)
            .collect();
        assert_eq!(
            ins[..2],
            [Window::Range(4), Window::Range(1)],
            "coarsest first"
        );
        // 3 coarse iterations on each level, 10 on level 0, per substep.
        assert_eq!(count(&plan, Op::Gather), 2 * 2 * (10 + 2 * 3));
    }

    /// Workgroup grids stay within 65,535 per dimension and cover every item, up to
    /// 4M particles and 100,000 bodies; the grid build clears the whole table.
    #[test]
    fn workgroups_fit_and_cover() {
        for n in [1, 127, 128, 4_000_000] {
            let sh = Shape {
                contacts_on: true,
                ..shape(n, 100_000)
            };
            let plan = steps(&sh, &settings(10, 1), &mut Cursor::default(), 1);
            for d in &plan {
                assert!(d.groups.0 <= 65_535 && d.groups.1 <= 65_535, "{d:?}");
                assert!(d.groups.0 >= 1 && d.groups.1 >= 1, "{d:?}");
            }
            let gather = plan.iter().find(|d| d.op == Op::Gather).unwrap();
            let threads = gather.groups.0 as u64 * gather.groups.1 as u64 * PER_LANE_GROUP as u64;
            assert!(threads >= n as u64, "gather covers {n}");
            let bounds = plan.iter().find(|d| d.op == Op::BodyBounds).unwrap();
            assert!(bounds.groups.0 as u64 * bounds.groups.1 as u64 >= 100_000);
            let g = grid(&sh, true);
            assert_eq!(g[0].window, Window::Level(sh.scan_levels.len() as u32 + 1));
            assert!(
                g[0].groups.0 as u64 * WORKGROUP as u64
                    >= sh.grid_table.min(65_535 * WORKGROUP) as u64
            );
        }
    }
}
