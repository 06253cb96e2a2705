//! Collider distances against analytic values, friction, and the residual measure.
use bevy_tissue::core::colliders::{Collider, ColliderShape, project_collider};
use bevy_tissue::core::model::{BodyDesc, Model};
use bevy_tissue::core::procedural;
use bevy_tissue::core::sampling::Resolution;
use bevy_tissue::core::solver::{Control, Method, Solver, SolverSettings, State};
use glam::{Quat, Vec3};

#[test]
fn signed_distances_match_analytic_shapes() {
    let rot = Quat::from_rotation_z(0.7);
    let c = Vec3::new(0.3, -0.2, 0.1);
    let sphere = Collider::new(ColliderShape::Sphere { radius: 0.5 }, c, rot);
    let capsule = Collider::new(
        ColliderShape::Capsule {
            half_length: 0.4,
            radius: 0.1,
        },
        c,
        rot,
    );
    let cuboid = Collider::new(
        ColliderShape::Cuboid {
            half_extents: Vec3::new(0.2, 0.3, 0.4),
        },
        c,
        rot,
    );
    let plane = Collider::new(ColliderShape::Plane, c, rot);
    let mut x = 0.123f32;
    for _ in 0..200 {
        x = (x * 9.73 + 0.31).fract();
        let local = Vec3::new(x - 0.5, (x * 7.1).fract() - 0.5, (x * 3.7).fract() - 0.5) * 2.0;
        let p = c + rot * local;
        let (d, n) = sphere.distance(p);
        assert!((d - (local.length() - 0.5)).abs() < 1e-5);
        assert!((n - rot * local.normalize()).length() < 1e-4);
        // capsule along local Y
        let seg = Vec3::new(0.0, local.y.clamp(-0.4, 0.4), 0.0);
        let (d, _) = capsule.distance(p);
        assert!((d - ((local - seg).length() - 0.1)).abs() < 1e-5);
        // box: outside distance or (negative) distance to the nearest face
        let q = local.abs() - Vec3::new(0.2, 0.3, 0.4);
        let expected = q.max(Vec3::ZERO).length() + q.max_element().min(0.0);
        let (d, n) = cuboid.distance(p);
        assert!((d - expected).abs() < 1e-5, "box: {d} vs {expected}");
        assert!((n.length() - 1.0).abs() < 1e-4);
        let (d, n) = plane.distance(p);
        assert!((d - local.y).abs() < 1e-5);
        assert!((n - rot * Vec3::Y).length() < 1e-5);
    }
}

#[test]
fn contact_pushes_out_and_friction_holds_or_slides() {
    let mut ground = Collider::ground(0.0);
    ground.friction = 0.5;
    let r = 0.01;
    // Sinking 4 mm while sliding 1 mm: static friction (1 mm < 0.5·4 mm) removes the slide.
    let x = Vec3::new(0.0, 0.01, 0.0);
    let p = Vec3::new(0.001, 0.006, 0.0);
    let q = p + project_collider(&ground, p, x, 1.0 / 60.0, r);
    assert!((q.y - r).abs() < 1e-6, "pushed out to the radius: {q}");
    assert!(q.x.abs() < 1e-7, "static friction holds: {q}");
    // Sliding 10 mm: kinetic friction removes μ·depth = 2 mm of it.
    let p = Vec3::new(0.01, 0.006, 0.0);
    let q = p + project_collider(&ground, p, x, 1.0 / 60.0, r);
    assert!((q.x - 0.008).abs() < 1e-6, "kinetic friction: {q}");
    // No friction: the slide is kept.
    ground.friction = 0.0;
    let q = p + project_collider(&ground, p, x, 1.0 / 60.0, r);
    assert!((q.x - 0.01).abs() < 1e-7);
    // Separated: untouched.
    assert_eq!(
        project_collider(&ground, Vec3::new(0.0, 0.5, 0.0), x, 1.0 / 60.0, r),
        Vec3::ZERO
    );
}

#[test]
fn body_resting_on_ground_reports_its_weight_as_collider_force() {
    let mut model = Model::new();
    let desc = BodyDesc {
        resolution: Resolution::Particles(500),
        neighbours: 16,
        translation: Vec3::new(0.0, 0.06, 0.0),
        discretisation: bevy_tissue::core::model::Discretisation::Clusters,
        ..Default::default()
    };
    model
        .add_body(&procedural::cuboid(Vec3::new(0.05, 0.05, 0.05), 2), &desc)
        .unwrap();
    let mut state = State::new(&model);
    let s = SolverSettings {
        method: Method::GaussSeidel,
        damping: 5.0,
        ..Default::default()
    };
    let mut solver = Solver::new(&model, s).unwrap();
    let control = Control {
        colliders: vec![Collider::ground(0.0)],
    };
    let mut force = Vec3::ZERO;
    for _ in 0..240 {
        force = solver
            .step(&model, &mut state, &control)
            .unwrap()
            .collider_forces[0];
    }
    let weight = model.mass.iter().sum::<f32>() * 9.81;
    // The ground is pushed down by the body's weight (force on the collider, N).
    assert!(
        (force.y + weight).abs() < 0.05 * weight,
        "force {force} vs weight {weight}"
    );
    assert!(force.x.abs() < 0.05 * weight && force.z.abs() < 0.05 * weight);
}

#[test]
fn residual_falls_with_more_iterations() {
    let mut model = Model::new();
    let desc = BodyDesc {
        resolution: Resolution::Particles(600),
        neighbours: 16,
        discretisation: bevy_tissue::core::model::Discretisation::Clusters,
        ..Default::default()
    };
    model
        .add_body(&procedural::icosphere(0.1, 2), &desc)
        .unwrap();
    let mut residuals = Vec::new();
    for iterations in [1, 4, 16, 64] {
        let mut state = State::new(&model);
        state.x = model
            .rest
            .iter()
            .map(|p| *p * Vec3::new(1.3, 0.8, 1.0))
            .collect();
        let s = SolverSettings {
            method: Method::GaussSeidel,
            iterations,
            gravity: Vec3::ZERO,
            ..Default::default()
        };
        let mut solver = Solver::new(&model, s).unwrap();
        solver
            .step(&model, &mut state, &Control::default())
            .unwrap();
        residuals.push(solver.residual(&model, &state));
    }
    for w in residuals.windows(2) {
        assert!(
            w[1] < w[0],
            "residual should fall with iterations: {residuals:?}"
        );
    }
}

/// Grasper rules (core::colliders::update_grab / grab_target): capture takes free
/// particles within reach and only those, hold takes none, open lets go, a collider that
/// is gone or not a grasper frees its particles; targets follow the grasper's pose.
#[test]
fn grasper_takes_holds_and_lets_go() {
    use bevy_tissue::core::colliders::{Grab, GraspMode, grab_target, update_grab};
    let grasper = |mode, at: Vec3, rot: Quat| {
        Collider::new(ColliderShape::Grasper { radius: 0.1, mode }, at, rot)
    };
    let points = [
        Vec3::new(0.05, 0.0, 0.0),
        Vec3::new(0.0, 0.099, 0.0),
        Vec3::new(0.0, 0.0, 0.11),
        Vec3::new(1.0, 0.0, 0.0),
    ];
    let mut grabs = [Grab::FREE; 4];
    // A sphere first (not a grasper), then the grasper at index 1.
    let sphere = Collider::new(
        ColliderShape::Sphere { radius: 5.0 },
        Vec3::ZERO,
        Quat::IDENTITY,
    );
    let take = [
        sphere,
        grasper(GraspMode::Capture, Vec3::ZERO, Quat::IDENTITY),
    ];
    for (p, g) in points.iter().zip(&mut grabs) {
        update_grab(&take, *p, g);
    }
    let held: Vec<u32> = grabs.iter().map(|g| g.collider).collect();
    assert_eq!(
        held,
        [1, 1, u32::MAX, u32::MAX],
        "only the particles within reach"
    );
    // Hold: moved and turned by a quarter turn about Y, nothing new is taken.
    let turn = Quat::from_rotation_y(std::f32::consts::FRAC_PI_2);
    let hold = [
        sphere,
        grasper(GraspMode::Hold, Vec3::new(0.0, 1.0, 0.0), turn),
    ];
    let mut far = Grab::FREE;
    update_grab(&hold, Vec3::new(0.0, 1.0, 0.0), &mut far);
    assert_eq!(far, Grab::FREE, "holding takes nothing new");
    for (p, g) in points.iter().zip(&mut grabs).take(2) {
        update_grab(&hold, *p, g);
        let t = grab_target(&hold, g).unwrap();
        assert!(
            t.distance(Vec3::new(0.0, 1.0, 0.0) + turn * *p) < 1e-6,
            "{t}"
        );
    }
    assert!(grab_target(&hold, &grabs[2]).is_none());
    // The grasper's distance function touches nothing.
    let (d, _) = hold[1].distance(Vec3::new(0.0, 1.0, 0.0));
    assert!(d.is_infinite());
    // Open lets go; so does a collider list without the grasper.
    let mut g0 = grabs[0];
    update_grab(
        &[sphere, grasper(GraspMode::Open, Vec3::ZERO, Quat::IDENTITY)],
        points[0],
        &mut g0,
    );
    assert_eq!(g0, Grab::FREE);
    let mut g1 = grabs[1];
    update_grab(&[sphere], points[1], &mut g1);
    assert_eq!(g1, Grab::FREE);
}
