//! Exact KNN on the grid equals brute force, ties broken by index.
mod common;
use bevy_tissue::core::knn::{Grid, knn_all, knn_brute_force};
use common::Rng;
use glam::Vec3;

fn check(points: &[Vec3], what: &str) {
    for k in [1usize, 8, 32, 64] {
        let grid = knn_all(points, k, 2).unwrap();
        let brute = knn_brute_force(points, k).unwrap();
        let diff = grid.iter().zip(&brute).filter(|(a, b)| a != b).count();
        assert_eq!(
            diff, 0,
            "{what}, K = {k}: {diff} entries differ from brute force"
        );
        // Single-threaded gives the same answer.
        assert_eq!(
            knn_all(points, k, 1).unwrap(),
            grid,
            "{what}, K = {k}: thread count changed result"
        );
    }
}

#[test]
fn random_points() {
    let mut rng = Rng(0x9e3779b97f4a7c15);
    let pts: Vec<Vec3> = (0..2000)
        .map(|_| rng.vec3() * Vec3::new(1.0, 0.5, 2.0))
        .collect();
    check(&pts, "random");
}

#[test]
fn lattice_points_with_ties() {
    let mut pts = Vec::new();
    for k in 0..12 {
        for j in 0..12 {
            for i in 0..12 {
                pts.push(Vec3::new(i as f32, j as f32, k as f32) * 0.1);
            }
        }
    }
    check(&pts, "lattice");
}

#[test]
fn clustered_points() {
    let mut rng = Rng(12345);
    let centres: Vec<Vec3> = (0..6).map(|_| rng.vec3() * 10.0).collect();
    let pts: Vec<Vec3> = (0..1800)
        .map(|i| centres[i % 6] + (rng.vec3() - 0.5) * 0.05)
        .collect();
    check(&pts, "clustered");
}

#[test]
fn query_off_points_and_k_too_large() {
    let mut rng = Rng(7);
    let pts: Vec<Vec3> = (0..500).map(|_| rng.vec3()).collect();
    let grid = Grid::build(&pts, 2.0);
    let mut out = Vec::new();
    for _ in 0..50 {
        let q = rng.vec3() * 3.0 - 1.0; // also outside the grid
        grid.knn_into(q, 10, u32::MAX, &mut out);
        let mut all: Vec<(f32, u32)> = pts
            .iter()
            .enumerate()
            .map(|(i, p)| (bevy_tissue::core::knn::dist2(q, *p), i as u32))
            .collect();
        all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        assert_eq!(out, all[..10].to_vec());
    }
    assert!(knn_all(&pts, 500, 1).is_none(), "K = n must be refused");
    assert!(knn_brute_force(&pts, 500).is_none());
}

/// Queries within a reach, filtered, and bounded by a known distance
/// (`Grid::knn_bounded`) equal brute force: on random points and on a lattice (ties),
/// from inside and outside the grid, with reaches from under a cell to the whole set
/// and with known bounds at, above and far above the true K-th distance. Skipping cells
/// by their box distance, and stopping the rings once they cover the reach, must lose
/// nothing.
#[test]
fn bounded_and_filtered_queries_equal_brute_force() {
    let mut rng = Rng(0x5eed);
    let random: Vec<Vec3> = (0..1500)
        .map(|_| rng.vec3() * Vec3::new(1.0, 0.3, 0.7))
        .collect();
    let lattice: Vec<Vec3> = (0..1000)
        .map(|i| Vec3::new((i % 10) as f32, ((i / 10) % 10) as f32, (i / 100) as f32) * 0.05)
        .collect();
    let mut out = Vec::new();
    for (what, pts) in [("random", &random), ("lattice", &lattice)] {
        let grid = Grid::build(pts, 2.0);
        let accept = |j: u32| !j.is_multiple_of(3);
        for t in 0..120 {
            let q = if t % 4 == 0 {
                rng.vec3() * 1.6 - 0.3 // also outside the grid
            } else {
                pts[(rng.vec3().x * pts.len() as f32) as usize % pts.len()]
            };
            let reach = [0.01f32, 0.04, 0.07, 0.12, 0.3, 5.0][t % 6];
            let k = [1usize, 5, 16][t % 3];
            let mut all: Vec<(f32, u32)> = pts
                .iter()
                .enumerate()
                .map(|(i, p)| (bevy_tissue::core::knn::dist2(q, *p), i as u32))
                .filter(|&(d2, i)| accept(i) && d2 <= reach * reach)
                .collect();
            all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            all.truncate(k);
            grid.knn_filtered(q, k, reach, accept, &mut out);
            assert_eq!(out, all, "{what}, query {t}: filtered, reach {reach}");
            // Known bounds: none, the K-th distance itself, and above it.
            let kth = match all.len() == k {
                true => all[k - 1].0,
                false => f32::INFINITY,
            };
            for known in [f32::INFINITY, kth, kth * 1.5 + 1e-4, kth * 30.0] {
                grid.knn_bounded(q, k, reach, known, accept, &mut out);
                assert_eq!(out, all, "{what}, query {t}: reach {reach}, known {known}");
            }
        }
    }
}

/// Queries that skip the cells of their own "body" (a tag by region) find what a brute
/// force finds among the other bodies' points, and each cell's tag is the one its points
/// share, or none.
#[test]
fn queries_skipping_own_cells_equal_brute_force() {
    use bevy_tissue::core::knn::NO_TAG;
    let mut rng = Rng(0x7a65);
    let mut pts: Vec<Vec3> = (0..1000)
        .map(|i| Vec3::new((i % 10) as f32, ((i / 10) % 10) as f32, (i / 100) as f32) * 0.05)
        .collect();
    pts.extend((0..800).map(|_| rng.vec3() * 0.45));
    let tag_of = |p: Vec3| match (p.x < 0.22, p.y < 0.2) {
        (true, _) => 0u32,
        (false, true) => 1,
        (false, false) => 2,
    };
    let tags: Vec<u32> = pts.iter().map(|p| tag_of(*p)).collect();
    let mut grid = Grid::build(&pts, 2.0);
    grid.tag_cells(|j| tags[j as usize]);
    let (mut single, mut mixed) = (0, 0);
    for c in 0..grid.cell_start.len() - 1 {
        let slots = &grid.sorted[grid.cell_start[c] as usize..grid.cell_start[c + 1] as usize];
        let first = slots.first().map(|&j| tags[j as usize]);
        let common = first.filter(|t| slots.iter().all(|&j| tags[j as usize] == *t));
        assert_eq!(grid.cell_tag[c], common.unwrap_or(NO_TAG), "cell {c}");
        match common {
            Some(_) => single += 1,
            None if !slots.is_empty() => mixed += 1,
            None => {}
        }
    }
    assert!(
        single > 50 && mixed > 10,
        "{single} single-tag, {mixed} mixed cells"
    );
    let mut out = Vec::new();
    for t in 0..300 {
        let i = (rng.vec3().x * pts.len() as f32) as usize % pts.len();
        let (q, own) = (pts[i], tags[i]);
        let reach = [0.03f32, 0.08, 0.2, 5.0][t % 4];
        let k = [1usize, 8, 24][t % 3];
        let accept = |j: u32| tags[j as usize] != own;
        let mut all: Vec<(f32, u32)> = pts
            .iter()
            .enumerate()
            .map(|(j, p)| (bevy_tissue::core::knn::dist2(q, *p), j as u32))
            .filter(|&(d2, j)| accept(j) && d2 <= reach * reach)
            .collect();
        all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        all.truncate(k);
        grid.knn_bounded_skipping(q, k, reach, f32::INFINITY, own, accept, &mut out);
        assert_eq!(out, all, "query {t} (tag {own}, reach {reach}, k {k})");
    }
}

/// Three lattice boxes: 4 cm at the origin, 4 cm at `second` and 3.2 cm at `third` (m).
fn three_boxes(second: Vec3, third: Vec3) -> bevy_tissue::core::model::Model {
    let mut model = common::lattice_box_at(Vec3::splat(0.02), Vec3::ZERO);
    model.append(&common::lattice_box_at(Vec3::splat(0.02), second));
    model.append(&common::lattice_box_at(Vec3::splat(0.016), third));
    model
}

/// A contact search that starts from the last one's lists (each full row's farthest
/// candidate, measured again, bounds the search) gives the lists a search from scratch
/// gives, equal to brute force, after the bodies moved: two lattice boxes sliding past
/// each other and a third dropped between them, searched every step.
#[test]
fn contact_searches_after_the_first_equal_brute_force() {
    use bevy_tissue::core::solver::{Solver, SolverSettings};
    let model = three_boxes(Vec3::new(0.041, 0.0, 0.0), Vec3::new(0.02, 0.05, 0.0));
    let settings = SolverSettings::default();
    let k = settings.contact_neighbours as usize;
    let max_r = model.bodies.iter().map(|b| b.radius).fold(0.0f32, f32::max);
    let mut x = model.placed_rest();
    let mut solver = Solver::new(&model, settings).unwrap();
    let mut full_rows = 0;
    for step in 0..12 {
        solver.refresh_contacts(&model, &x);
        let (start, list) = solver.contact_lists();
        for (i, &q) in x.iter().enumerate() {
            let bi = model.particle_body[i];
            let reach = 2.0 * (model.bodies[bi as usize].radius + max_r);
            let mut all: Vec<(f32, u32)> = x
                .iter()
                .enumerate()
                .filter(|&(j, _)| model.particle_body[j] != bi)
                .map(|(j, p)| (bevy_tissue::core::knn::dist2(q, *p), j as u32))
                .filter(|&(d2, _)| d2 <= reach * reach)
                .collect();
            all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            all.truncate(k);
            let want: Vec<u32> = all.iter().map(|&(_, j)| j).collect();
            let got = &list[start[i] as usize..start[i + 1] as usize];
            assert_eq!(got, &want[..], "step {step}, particle {i}");
            full_rows += (got.len() == k) as usize;
        }
        let mut fresh = Solver::new(&model, SolverSettings::default()).unwrap();
        fresh.refresh_contacts(&model, &x);
        assert_eq!(fresh.contact_lists(), solver.contact_lists(), "step {step}");
        // The second box slides along the first (y), the third sinks between them.
        for (p, &b) in x.iter_mut().zip(&model.particle_body) {
            match b {
                1 => p.y += 0.003,
                2 => *p += Vec3::new(0.0005, -0.002, 0.001),
                _ => {}
            }
        }
    }
    // The warm bound was at work: many rows were full.
    assert!(full_rows > 1000, "{full_rows} full rows");
}

/// The contact broad phase (`near_bodies`) is conservative: every pair of particles of
/// two bodies within the largest contact reach marks both bodies near, and it is exact
/// for its boxes (a body is near another only if its grown box overlaps that box).
#[test]
fn contact_broad_phase_is_conservative_and_exact_for_boxes() {
    use bevy_tissue::core::knn::{body_boxes, contact_reach_bound, near_bodies};
    let mut rng = Rng(0x2545f4914f6cdd1d);
    let max_r = 0.01;
    let reach = contact_reach_bound(max_r);
    let (mut some_near, mut some_apart) = (false, false);
    for trial in 0..20 {
        // 12 clouds of 30 points, centres spread so that some are near and some apart.
        let mut x = Vec::new();
        let mut ranges = Vec::new();
        for _ in 0..12 {
            let c = rng.vec3() * 0.3;
            ranges.push((x.len() as u32, 30u32));
            for _ in 0..30 {
                x.push(c + rng.vec3() * 0.05);
            }
        }
        let boxes = body_boxes(&x, ranges.iter().copied());
        let near = near_bodies(&boxes, reach);
        for (a, &(fa, ca)) in ranges.iter().enumerate() {
            for (b, &(fb, cb)) in ranges.iter().enumerate() {
                if a == b {
                    continue;
                }
                let close = (fa..fa + ca).any(|i| {
                    (fb..fb + cb).any(|j| x[i as usize].distance(x[j as usize]) <= 4.0 * max_r)
                });
                if close {
                    assert!(
                        near[a] && near[b],
                        "trial {trial}: bodies {a}, {b} within reach"
                    );
                }
            }
            let overlaps = (0..ranges.len()).any(|b| {
                b != a
                    && (0..3).all(|k| {
                        boxes[a].0[k] - reach <= boxes[b].1[k]
                            && boxes[b].0[k] <= boxes[a].1[k] + reach
                    })
            });
            assert_eq!(near[a], overlaps, "trial {trial}, body {a}");
        }
        some_near |= near.iter().any(|n| *n);
        some_apart |= near.iter().any(|n| !n);
    }
    assert!(
        some_near && some_apart,
        "the trials must have near and isolated bodies"
    );
    // Beyond the pair-test limit every body counts as near (conservative).
    use bevy_tissue::core::knn::BROAD_MAX_BODIES;
    let apart: Vec<(Vec3, Vec3)> = (0..=BROAD_MAX_BODIES)
        .map(|i| (Vec3::splat(i as f32), Vec3::splat(i as f32 + 0.1)))
        .collect();
    assert!(near_bodies(&apart, reach).iter().all(|n| *n));
    assert!(
        near_bodies(&apart[..BROAD_MAX_BODIES], reach)
            .iter()
            .all(|n| !n)
    );
}

/// The solver's contact candidates with the broad phase equal a search of every
/// particle (the k nearest of other bodies within its reach) without it.
#[test]
fn contact_lists_with_the_broad_phase_equal_a_full_search() {
    use bevy_tissue::core::model::{BodyDesc, Material, Model};
    use bevy_tissue::core::procedural;
    use bevy_tissue::core::sampling::Resolution;
    use bevy_tissue::core::solver::{Solver, SolverSettings, State};
    let mut model = Model::new();
    let sphere = procedural::icosphere(0.03, 2);
    // Three touching balls and two apart.
    for at in [
        Vec3::ZERO,
        Vec3::new(0.058, 0.0, 0.0),
        Vec3::new(0.0, 0.058, 0.0),
        Vec3::new(0.3, 0.0, 0.0),
        Vec3::new(0.0, 0.0, 0.4),
    ] {
        let desc = BodyDesc {
            resolution: Resolution::Particles(250),
            material: Material::default(),
            translation: at,
            discretisation: bevy_tissue::core::model::Discretisation::Clusters,
            ..Default::default()
        };
        model.add_body(&sphere, &desc).unwrap();
    }
    let state = State::new(&model);
    let settings = SolverSettings::default();
    let k = settings.contact_neighbours as usize;
    let mut solver = Solver::new(&model, settings).unwrap();
    solver.refresh_contacts(&model, &state.x);
    let (start, list) = solver.contact_lists();
    let grid = Grid::build(&state.x, 2.0);
    let max_r = model.bodies.iter().map(|b| b.radius).fold(0.0f32, f32::max);
    let mut buf = Vec::new();
    let mut with = vec![0usize; model.bodies.len()];
    for (i, &q) in state.x.iter().enumerate() {
        let bi = model.particle_body[i];
        let reach = 2.0 * (model.bodies[bi as usize].radius + max_r);
        grid.knn_filtered(
            q,
            k,
            reach,
            |j| model.particle_body[j as usize] != bi,
            &mut buf,
        );
        let want: Vec<u32> = buf.iter().map(|&(_, j)| j).collect();
        assert_eq!(
            &list[start[i] as usize..start[i + 1] as usize],
            &want[..],
            "particle {i}"
        );
        with[bi as usize] += !want.is_empty() as usize;
    }
    // The scene has what it claims: candidates on the first three balls, none on the
    // last two.
    assert!(
        with[..3].iter().all(|&c| c > 0) && with[3..] == [0, 0],
        "{with:?}"
    );
}

/// Contact candidates among some bodies only (`refresh_contacts_among`): a body left
/// out has no candidates and is nobody's, even where it overlaps the others, and the
/// others' lists are those of a model without it; parked 1 km away it does not change
/// them either (the search grid is made from the searched particles alone).
#[test]
fn contact_lists_among_active_bodies_leave_the_others_out() {
    use bevy_tissue::core::model::{BodyDesc, Model};
    use bevy_tissue::core::procedural;
    use bevy_tissue::core::sampling::Resolution;
    use bevy_tissue::core::solver::{Solver, SolverSettings, State};
    let sphere = procedural::icosphere(0.03, 2);
    let ball = |at: Vec3| {
        let mut m = Model::new();
        let desc = BodyDesc {
            resolution: Resolution::Particles(250),
            translation: at,
            ..Default::default()
        };
        m.add_body(&sphere, &desc).unwrap();
        m
    };
    // Two touching balls, and a third overlapping both (left out).
    let (a, b, c) = (
        ball(Vec3::ZERO),
        ball(Vec3::new(0.058, 0.0, 0.0)),
        ball(Vec3::new(0.03, 0.01, 0.0)),
    );
    let mut two = Model::new();
    two.append(&a);
    two.append(&b);
    let mut three = two.clone();
    three.append(&c);
    let lists = |model: &Model, x: &[Vec3], active: &[bool]| {
        let mut solver = Solver::new(model, SolverSettings::default()).unwrap();
        solver.refresh_contacts_among(model, x, active);
        let (start, list) = solver.contact_lists();
        (start.to_vec(), list.to_vec())
    };
    let (s2, l2) = lists(&two, &State::new(&two).x, &[]);
    assert!(!l2.is_empty(), "the two balls touch");
    let n2 = two.particle_count();
    let mut x = State::new(&three).x;
    for far in [false, true] {
        if far {
            for p in &mut x[n2..] {
                p.y -= 1000.0;
            }
        }
        let (s3, l3) = lists(&three, &x, &[true, true, false]);
        assert_eq!(&s3[..=n2], &s2[..], "far {far}");
        assert!(
            s3[n2..].iter().all(|&s| s == s3[n2]),
            "the third has candidates"
        );
        assert_eq!(l3, l2, "far {far}");
    }
    // All active: the overlapping third body is everyone's candidate.
    let (_, l_all) = lists(&three, &State::new(&three).x, &[]);
    assert!(l_all.iter().any(|&j| j as usize >= n2));
}

/// Bodies approaching fast find each other before they meet, whatever `knn_every`
/// (`Solver::refresh_contacts_if_due`, the CPU step's rule): two lattice boxes flying at
/// each other at 4 m/s each (67 mm a step, about eight particle radii) and a third
/// falling onto them, moved kinematically; searched when due with the default
/// `knn_every` (10) and when stale, at every step's end every pair of particles of
/// different bodies within contact distance (brute force) is in the lists made before
/// the step, unless the particle's list is full of nearer candidates. A search only
/// every 10 steps (the schedule alone) misses most of the pairs; the rule searches
/// again while they approach, and only on the schedule once everything rests.
#[test]
fn contact_lists_keep_up_with_fast_bodies() {
    use bevy_tissue::core::solver::{Solver, SolverSettings};
    let mut model = common::lattice_box_at(Vec3::splat(0.02), Vec3::new(-0.5, 0.1, 0.0));
    model.append(&common::lattice_box_at(
        Vec3::splat(0.02),
        Vec3::new(0.5, 0.105, 0.01),
    ));
    model.append(&common::lattice_box_at(
        Vec3::splat(0.016),
        Vec3::new(0.0, 0.6, 0.0),
    ));
    let speed = [
        Vec3::new(4.0, 0.0, 0.0),
        Vec3::new(-4.0, 0.0, 0.0),
        Vec3::ZERO,
    ];
    let settings = SolverSettings::default();
    assert_eq!(settings.knn_every, 10);
    let (h, g) = (settings.dt, settings.gravity);
    let k = settings.contact_neighbours as usize;
    let n = model.particle_count();
    let mut x: Vec<Vec3> = model.rest.clone();
    // The second box placed so that the two meet in the 7th step, overlapping by 2 mm.
    let body = |b: usize| model.bodies[b].range();
    let touch = model.bodies[0].radius + model.bodies[1].radius;
    let face = |b: usize, sign: f32| {
        x[body(b)]
            .iter()
            .map(|p| sign * p.x)
            .fold(f32::MIN, f32::max)
    };
    let gap = -face(1, -1.0) - face(0, 1.0);
    let shift = 7.0 * 8.0 * h - (touch - 0.002) - gap;
    for p in &mut x[body(1)] {
        p.x += shift;
    }
    let mut v: Vec<Vec3> = (0..n)
        .map(|i| speed[model.particle_body[i] as usize])
        .collect();
    // The schedule alone (searched every 10 steps) against the rule.
    let mut every = Solver::new(&model, settings.clone()).unwrap();
    let mut solver = Solver::new(&model, settings).unwrap();
    let (mut met, mut missed_by_schedule, mut searches) = (0usize, 0usize, [0u32; 2]);
    for step in 0..42u64 {
        let periodic = step % 10 == 0;
        let searched = solver.refresh_contacts_if_due(&model, &x, &v, &[], 1, periodic);
        searches[(step > 22) as usize] += searched as u32;
        if periodic {
            every.refresh_contacts(&model, &x);
        }
        // The step: the two fly on until they meet in the middle, then part slowly; the
        // third box falls under gravity onto them (from step 22 on, everything rests).
        for (i, (p, u)) in x.iter_mut().zip(v.iter_mut()).enumerate() {
            let b = model.particle_body[i] as usize;
            if step >= 22 {
                *u = Vec3::ZERO;
            } else if b == 2 {
                *u += g * h;
            } else if step == 7 {
                // Met: they part slowly.
                *u = -0.02 * speed[b];
            }
            *p += *u * h;
        }
        let (start, list) = solver.contact_lists();
        let (start_e, list_e) = every.contact_lists();
        for i in 0..n {
            let bi = model.particle_body[i];
            let ri = model.bodies[bi as usize].radius;
            let own = &list[start[i] as usize..start[i + 1] as usize];
            for j in 0..n {
                let bj = model.particle_body[j];
                let touch = ri + model.bodies[bj as usize].radius;
                if bj == bi || x[i].distance(x[j]) >= touch {
                    continue;
                }
                met += 1;
                let e = &list_e[start_e[i] as usize..start_e[i + 1] as usize];
                missed_by_schedule += !e.contains(&(j as u32)) as usize;
                assert!(
                    own.contains(&(j as u32)) || own.len() == k,
                    "step {step}: particles {i} (body {bi}) and {j} (body {bj}) touch, {} m apart, but {j} is not in {i}'s {} candidates",
                    x[i].distance(x[j]),
                    own.len()
                );
            }
        }
    }
    assert!(met > 100, "the bodies must meet ({met} touching pairs)");
    assert!(
        missed_by_schedule > met / 2,
        "the schedule alone would have missed most ({missed_by_schedule} of {met})"
    );
    // While they approach, searches at least every other step; at rest, only the
    // schedule's (steps 30 and 40).
    assert!(
        searches[0] >= 8,
        "searched {} times approaching",
        searches[0]
    );
    assert_eq!(searches[1], 2, "searches at rest");
}

/// Bodies moving together (a pile carried sideways at 5 m/s while falling) change no
/// distance between their particles, so their contact lists stay valid: searched only
/// on the `knn_every` schedule, never for their speed, and every touching pair stays in
/// the lists. A rule that bounds travel by the fastest particle's speed instead of the
/// spread of the velocities searches every other step.
#[test]
fn bodies_moving_together_keep_their_contact_lists() {
    use bevy_tissue::core::solver::{Solver, SolverSettings};
    let model = three_boxes(Vec3::new(0.0, 0.047, 0.003), Vec3::new(0.046, 0.0, -0.004));
    let settings = SolverSettings::default();
    let (h, g, k) = (
        settings.dt,
        settings.gravity,
        settings.contact_neighbours as usize,
    );
    let mut x = model.placed_rest();
    let n = x.len();
    let mut v = vec![Vec3::new(5.0, 0.0, 0.0); n];
    let mut solver = Solver::new(&model, settings).unwrap();
    let (mut searches, mut touching) = (0, 0);
    for step in 0..30u64 {
        searches += solver.refresh_contacts_if_due(&model, &x, &v, &[], 1, step % 10 == 0) as u32;
        for (p, u) in x.iter_mut().zip(v.iter_mut()) {
            *u += g * h;
            *p += *u * h;
        }
        let (start, list) = solver.contact_lists();
        for i in 0..n {
            let bi = model.particle_body[i];
            let own = &list[start[i] as usize..start[i + 1] as usize];
            for j in 0..n {
                let bj = model.particle_body[j];
                let touch = model.bodies[bi as usize].radius + model.bodies[bj as usize].radius;
                if bj == bi || x[i].distance(x[j]) >= touch {
                    continue;
                }
                touching += 1;
                assert!(
                    own.contains(&(j as u32)) || own.len() == k,
                    "step {step}: particles {i} and {j} touch but {j} is not in {i}'s list"
                );
            }
        }
    }
    assert!(touching > 100, "the boxes must touch ({touching} pairs)");
    assert_eq!(
        searches, 3,
        "searches: only the schedule's (steps 0, 10, 20)"
    );
}
