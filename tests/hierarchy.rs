//! Hierarchy invariants (issue 4): levels shrink to between an eighth and a quarter,
//! every particle has the requested parents with weights summing to 1, and every
//! particle reaches the coarsest level.

use bevy_tissue::core::TissueError;
use bevy_tissue::core::hierarchy::{Hierarchy, HierarchyDesc};
use bevy_tissue::core::model::{BodyDesc, Model};
use bevy_tissue::core::procedural;
use bevy_tissue::core::sampling::Resolution;
use glam::Vec3;

fn body(mesh: &bevy_tissue::core::mesh::TriMesh, particles: u32) -> (Vec<Vec3>, f32) {
    let mut model = Model::new();
    let desc = BodyDesc {
        resolution: Resolution::Particles(particles),
        neighbours: 8,
        ..Default::default()
    };
    model.add_body(mesh, &desc).unwrap();
    (model.rest.clone(), model.bodies[0].spacing)
}

fn check(h: &Hierarchy, rest: &[Vec3], parents: u32) {
    let n = rest.len();
    assert_eq!(h.levels[0].particles.len(), n);
    for (l, pair) in h.levels.windows(2).enumerate() {
        let (fine, coarse) = (&pair[0], &pair[1]);
        let ratio = coarse.particles.len() as f64 / fine.particles.len() as f64;
        assert!(
            (0.1..=0.3).contains(&ratio),
            "level {l} → {}: ratio {ratio:.3}",
            l + 1
        );
        // The coarse level is a subset of the fine one.
        for i in &coarse.particles {
            assert!(
                fine.particles.binary_search(i).is_ok(),
                "level {} has a stranger",
                l + 1
            );
        }
        assert_eq!(fine.parent_start.len(), fine.particles.len() + 1);
        for p in 0..fine.particles.len() {
            let (a, b) = (
                fine.parent_start[p] as usize,
                fine.parent_start[p + 1] as usize,
            );
            assert_eq!(b - a, parents as usize, "level {l} particle {p}: parents");
            let sum: f32 = fine.weights[a..b].iter().sum();
            assert!(
                (sum - 1.0).abs() < 1e-5,
                "level {l} particle {p}: weights sum {sum}"
            );
            assert!(fine.weights[a..b].iter().all(|&w| w > 0.0));
            for &q in &fine.parents[a..b] {
                assert!((q as usize) < coarse.particles.len());
            }
            // The nearest parent is no farther than a coarse spacing (evenly spread).
            let me = rest[fine.particles[p] as usize];
            let nearest = fine.parents[a..b]
                .iter()
                .map(|&q| me.distance(rest[coarse.particles[q as usize] as usize]))
                .fold(f32::MAX, f32::min);
            assert!(
                nearest <= 1.8 * coarse.spacing,
                "level {l} particle {p}: nearest parent {nearest} m (coarse spacing {})",
                coarse.spacing
            );
        }
        assert!(coarse.spacing > fine.spacing);
    }
    // Every particle reaches the coarsest level through first parents.
    let top = h.levels.len() - 1;
    for p in 0..n {
        let mut idx = p;
        for l in 0..top {
            let lv = &h.levels[l];
            idx = lv.parents[lv.parent_start[idx] as usize] as usize;
        }
        assert!(idx < h.levels[top].particles.len());
    }
}

#[test]
fn hierarchy_invariants_on_the_liver_and_a_box() {
    for (name, mesh, n) in [
        ("liver", procedural::liver(4), 13824u32),
        (
            "bar",
            procedural::cuboid(Vec3::new(0.2, 0.05, 0.05), 4),
            20000,
        ),
    ] {
        let (rest, spacing) = body(&mesh, n);
        for parents in [2u32, 3, 4] {
            let h = Hierarchy::build(
                &rest,
                spacing,
                &HierarchyDesc {
                    parents,
                    ..Default::default()
                },
            )
            .unwrap();
            let sizes: Vec<usize> = h.levels.iter().map(|l| l.particles.len()).collect();
            eprintln!("{name}, {parents} parents: level sizes {sizes:?}");
            assert!(
                h.levels.len() >= 3,
                "{name}: only {} levels",
                h.levels.len()
            );
            assert!(*sizes.last().unwrap() >= 128);
            check(&h, &rest, parents);
        }
    }
}

#[test]
fn level_count_can_be_set_and_bad_parameters_are_errors() {
    let (rest, spacing) = body(&procedural::icosphere(0.05, 3), 3000);
    let h = Hierarchy::build(
        &rest,
        spacing,
        &HierarchyDesc {
            levels: Some(2),
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(h.levels.len(), 2);
    check(&h, &rest, 3);
    let one = Hierarchy::build(
        &rest,
        spacing,
        &HierarchyDesc {
            levels: Some(1),
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(one.levels.len(), 1);
    for bad in [
        HierarchyDesc {
            parents: 1,
            ..Default::default()
        },
        HierarchyDesc {
            parents: 5,
            ..Default::default()
        },
        HierarchyDesc {
            levels: Some(0),
            ..Default::default()
        },
        HierarchyDesc {
            levels: Some(9),
            ..Default::default()
        },
    ] {
        let e = Hierarchy::build(&rest, spacing, &bad).unwrap_err();
        assert!(matches!(e, TissueError::InvalidParameter { .. }), "{e}");
    }
    assert!(Hierarchy::build(&rest, f32::NAN, &HierarchyDesc::default()).is_err());
}
