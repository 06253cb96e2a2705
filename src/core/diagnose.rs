//! What to tell a user when a step diverges: where in the body it happened (in words, not
//! a particle index), the likely cause, and what to change; and when a body's size or
//! mass is implausible (a unit slip). Pure functions of the model, the settings and the
//! motion, used by the CPU solver's divergence check and the plugin's body builds.

use super::constraints::Hyperelastic;
use super::error::{DivergenceKind, TissueError};
use super::model::{BodyInfo, Discretisation, Material, Model};
use super::solver::{ElementSolver, Method, SolverSettings};
use glam::Vec3;

/// Where particle `particle` lies in its body, in words: the faces of the body's rest
/// bounding box its rest position is near (within the outer quarter of the half extent
/// on each axis; "in the interior" when none), and that rest position from the body's
/// centre, m. An empty string for an index outside the model.
pub fn region(model: &Model, particle: usize) -> String {
    let Some(&b) = model.particle_body.get(particle) else {
        return String::new();
    };
    let range = model.bodies[b as usize].range();
    let (lo, hi) = model.rest[range].iter().fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    );
    let centre = (lo + hi) * 0.5;
    let half = ((hi - lo) * 0.5).max(Vec3::splat(f32::MIN_POSITIVE));
    let at = model.rest[particle] - centre;
    let mut sides = Vec::new();
    for (axis, name) in ["x", "y", "z"].iter().enumerate() {
        let f = at[axis] / half[axis];
        if f > 0.5 {
            sides.push(format!("+{name}"));
        } else if f < -0.5 {
            sides.push(format!("−{name}"));
        }
    }
    let place = match sides.len() {
        0 => "in the interior".to_string(),
        1 => format!("near the {} face", sides[0]),
        2 => format!("near the {} edge", sides.join(" ")),
        _ => format!("near the {} corner", sides.join(" ")),
    };
    format!(
        "{place}, rest position ({:.3}, {:.3}, {:.3}) m from the body's centre",
        at.x, at.y, at.z
    )
}

/// Motion of more than this many particle spacings per substep reads as "fast motion".
pub const FAST_SPACINGS: f32 = 1.0;
/// A P-wave crossing more than this many particle spacings per substep reads as "stiff
/// for the substep" (XPBD's iterations carry a correction about one spacing each).
pub const STIFF_SPACINGS: f32 = 10.0;

/// The likely cause of a divergence in body `body` and its remedy, in words, from the
/// settings and the body's fastest speed at the start of the step (`speed_before`,
/// m/s). In order: a body moving more than [`FAST_SPACINGS`] particle spacings per
/// substep (an impact or a fast tool: more substeps); a material stiff for the substep
/// (the P-wave speed `√((λ + 2μ)/ρ)` crossing more than [`STIFF_SPACINGS`] spacings per
/// substep, under XPBD: more substeps, a softer material, a coarser body or, for a
/// lattice body, Newton–multigrid); over-relaxed Jacobi (ω > 1); otherwise an iteration
/// that does not converge at this resolution.
pub fn advice(model: &Model, settings: &SolverSettings, body: usize, speed_before: f32) -> String {
    let Some(info) = model.bodies.get(body) else {
        return String::new();
    };
    let h = settings.dt / settings.substeps as f32;
    let s = info.spacing;
    let crossing = speed_before * h / s;
    if crossing > FAST_SPACINGS {
        let need = (settings.substeps as f32 * crossing / FAST_SPACINGS).ceil() as u32;
        return format!(
            "Likely cause: fast motion ({speed_before:.2} m/s moves a particle {crossing:.1} spacings per substep: an impact, a thrown body or a fast tool). Remedy: about {need} substeps, or slower motion."
        );
    }
    if let Material::Hyperelastic {
        youngs_modulus,
        poisson_ratio,
    } = info.material
    {
        let m = Hyperelastic::new(youngs_modulus, poisson_ratio);
        let wave = ((m.lambda + 2.0 * m.mu) / info.density).sqrt();
        let cells = wave * h / s;
        let newton = info.discretisation == Discretisation::Lattice
            && settings.element_solver == ElementSolver::Multigrid;
        if cells > STIFF_SPACINGS && !newton {
            let need = (settings.substeps as f32 * cells / STIFF_SPACINGS).ceil() as u32;
            let lattice = if info.discretisation == Discretisation::Lattice {
                ", or `ElementSolver::Multigrid` (implicit, any stiffness)"
            } else {
                ""
            };
            return format!(
                "Likely cause: the material is stiff for the substep (E = {youngs_modulus:.3e} Pa: sound crosses {cells:.1} particle spacings of {s:.4} m per substep). Remedy: about {need} substeps, a softer material or a coarser resolution{lattice}."
            );
        }
    }
    if settings.method == Method::Jacobi && settings.relaxation > 1.0 {
        return format!(
            "Likely cause: over-relaxed Jacobi (relaxation {}). Remedy: relaxation 1 or below.",
            settings.relaxation
        );
    }
    "Likely cause: the iterations overshoot at this resolution and load. Remedy: more substeps, fewer particles, or a softer material.".to_string()
}

/// Smallest body size (m, bounding-box diagonal) that [`implausible`] accepts.
pub const MIN_PLAUSIBLE_SIZE: f32 = 0.005;
/// Largest body size (m, bounding-box diagonal) that [`implausible`] accepts.
pub const MAX_PLAUSIBLE_SIZE: f32 = 5.0;
/// Largest body mass (kg) that [`implausible`] accepts.
pub const MAX_PLAUSIBLE_MASS: f32 = 1000.0;

/// A warning for a body whose size or mass is implausible for soft tissue (outside
/// [`MIN_PLAUSIBLE_SIZE`]–[`MAX_PLAUSIBLE_SIZE`] across, or over [`MAX_PLAUSIBLE_MASS`]):
/// most often a mesh in millimetres or centimetres read as metres. Names the size and
/// mass and the scale that would fix a unit slip. `None` for a plausible body.
pub fn implausible(info: &BodyInfo) -> Option<String> {
    let (size, mass) = (info.size, info.volume * info.density);
    let too_big = size > MAX_PLAUSIBLE_SIZE || mass > MAX_PLAUSIBLE_MASS;
    if !too_big && size >= MIN_PLAUSIBLE_SIZE {
        return None;
    }
    let hint = if too_big {
        "a mesh in millimetres read as metres is 1000x too big: scale its transform by 0.001 (0.01 for centimetres)"
    } else {
        "a mesh in metres read as millimetres is 1000x too small: scale its transform by 1000"
    };
    Some(format!(
        "the body is {size:.3} m across and weighs {mass:.3e} kg, implausible for soft tissue ({MIN_PLAUSIBLE_SIZE} to {MAX_PLAUSIBLE_SIZE} m, at most {MAX_PLAUSIBLE_MASS} kg expected); {hint}"
    ))
}

/// The particle that shows a step diverged, if one does: the fastest over `max_speed`
/// (m/s; the first of equals), else the first whose position or velocity is not finite.
/// Checked on all cores for large states; the answer does not depend on their number.
pub fn worst_particle(x: &[Vec3], v: &[Vec3], max_speed: f32) -> Option<(usize, DivergenceKind)> {
    let n = x.len().min(v.len());
    let threads = super::par::threads_for(n, 32768, 0);
    let per = n.div_ceil(threads).max(1);
    // Per run of particles: its fastest over the limit and its first not finite.
    let runs = super::par::map(n.div_ceil(per), threads, |r| {
        let first = r * per;
        let last = (first + per).min(n);
        let mut fastest: Option<(usize, f32)> = None;
        let mut non_finite = None;
        for i in first..last {
            let (x, v) = (x[i], v[i]);
            if !x.is_finite() || !v.is_finite() {
                non_finite = non_finite.or(Some(i));
                continue;
            }
            let speed = v.length();
            if speed > max_speed && fastest.is_none_or(|(_, w)| speed > w) {
                fastest = Some((i, speed));
            }
        }
        (fastest, non_finite)
    });
    // Runs in order: a later run wins only with a faster particle.
    let mut fastest: Option<(usize, f32)> = None;
    let mut non_finite = None;
    for (f, nf) in runs {
        if let Some((i, speed)) = f
            && fastest.is_none_or(|(_, w)| speed > w)
        {
            fastest = Some((i, speed));
        }
        non_finite = non_finite.or(nf);
    }
    match (fastest, non_finite) {
        (Some((i, speed)), _) => Some((i, DivergenceKind::Exploding { speed })),
        (None, Some(i)) => Some((i, DivergenceKind::NonFinite)),
        (None, None) => None,
    }
}

/// The error of a step that diverged at `particle` for `reason`: its body, region, the
/// likely cause and the remedy (`speed_before`: the body's fastest particle before the
/// step, m/s).
pub fn diverged(
    model: &Model,
    settings: &SolverSettings,
    step: u64,
    (particle, reason): (usize, DivergenceKind),
    speed_before: f32,
) -> TissueError {
    let body = model.particle_body.get(particle).copied().unwrap_or(0) as usize;
    TissueError::Diverged {
        step,
        body,
        particle,
        region: region(model, particle),
        reason,
        advice: advice(model, settings, body, speed_before),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::model::BodyDesc;
    use crate::core::procedural;
    use crate::core::sampling::Resolution;

    /// The particle a plain loop finds (what [`worst_particle`] must equal).
    fn worst_by_loop(x: &[Vec3], v: &[Vec3], max: f32) -> Option<(usize, DivergenceKind)> {
        let mut fastest: Option<(usize, f32)> = None;
        let mut non_finite = None;
        for (i, (x, v)) in x.iter().zip(v).enumerate() {
            if !x.is_finite() || !v.is_finite() {
                non_finite = non_finite.or(Some(i));
            } else if v.length() > max && fastest.is_none_or(|(_, w)| v.length() > w) {
                fastest = Some((i, v.length()));
            }
        }
        match (fastest, non_finite) {
            (Some((i, speed)), _) => Some((i, DivergenceKind::Exploding { speed })),
            (None, Some(i)) => Some((i, DivergenceKind::NonFinite)),
            (None, None) => None,
        }
    }

    #[test]
    fn worst_particle_equals_a_plain_loop_on_a_large_state() {
        // Enough particles for several threads' runs; speeds below the limit but for
        // the particles set below.
        let n: usize = 300_000;
        let x: Vec<Vec3> = (0..n).map(|i| Vec3::splat(i as f32 * 1e-3)).collect();
        let mut v: Vec<Vec3> = (0..n)
            .map(|i| Vec3::new(((i * 7919) % 1000) as f32 * 1e-2, 0.0, 0.0))
            .collect();
        let max = 50.0;
        let check = |x: &[Vec3], v: &[Vec3]| {
            let got = format!("{:?}", worst_particle(x, v, max));
            assert_eq!(got, format!("{:?}", worst_by_loop(x, v, max)));
            got
        };
        assert_eq!(check(&x, &v), "None");
        // A non-finite velocity late and a position early: the first is named.
        v[250_000].y = f32::NAN;
        let mut xs = x.clone();
        xs[100_001] = Vec3::INFINITY;
        assert!(check(&xs, &v).contains("100001"));
        // Equal fastest particles in different runs: the first wins, and a fast one
        // wins over any non-finite.
        v[10] = Vec3::X * 80.0;
        v[290_000] = Vec3::X * 80.0;
        v[150_000] = Vec3::X * 60.0;
        assert!(check(&xs, &v).starts_with("Some((10,"));
        v[290_000] = Vec3::X * 81.0;
        assert!(check(&xs, &v).starts_with("Some((290000,"));
    }

    fn brick(material: Material, discretisation: Discretisation) -> Model {
        let mut model = Model::new();
        model
            .add_body(
                &procedural::cuboid(Vec3::new(0.1, 0.02, 0.02), 2),
                &BodyDesc {
                    resolution: Resolution::Particles(300),
                    neighbours: 16,
                    material,
                    discretisation,
                    ..Default::default()
                },
            )
            .unwrap();
        model
    }

    #[test]
    fn region_names_the_end_of_a_bar() {
        let model = brick(Material::default(), Discretisation::Clusters);
        let far = (0..model.particle_count())
            .max_by(|&a, &b| model.rest[a].x.total_cmp(&model.rest[b].x))
            .unwrap();
        let text = region(&model, far);
        assert!(text.contains("+x"), "{text}");
        assert!(!text.contains("−x"), "{text}");
        let centre = (0..model.particle_count())
            .min_by(|&a, &b| {
                model.rest[a]
                    .length_squared()
                    .total_cmp(&model.rest[b].length_squared())
            })
            .unwrap();
        assert!(region(&model, centre).contains("interior"));
        assert_eq!(region(&model, usize::MAX), "");
    }

    #[test]
    fn advice_names_the_cause() {
        let stiff = Material::Hyperelastic {
            youngs_modulus: 1e8,
            poisson_ratio: 0.3,
        };
        let model = brick(stiff, Discretisation::Clusters);
        let s = SolverSettings::default();
        let fast = advice(&model, &s, 0, 100.0);
        assert!(fast.contains("fast motion"), "{fast}");
        let text = advice(&model, &s, 0, 0.0);
        assert!(text.contains("stiff for the substep"), "{text}");
        // The substeps it asks for bring the wave under a spacing per substep.
        let need: u32 = text
            .split("about ")
            .nth(1)
            .and_then(|t| t.split(' ').next())
            .and_then(|n| n.parse().ok())
            .unwrap();
        let calm = SolverSettings {
            substeps: need,
            ..SolverSettings::default()
        };
        assert!(!advice(&model, &calm, 0, 0.0).contains("stiff"));
        let soft = brick(Material::default(), Discretisation::Clusters);
        let over = SolverSettings {
            method: Method::Jacobi,
            relaxation: 1.9,
            ..SolverSettings::default()
        };
        assert!(advice(&soft, &over, 0, 0.0).contains("over-relaxed"));
        assert!(advice(&soft, &s, 5, 0.0).is_empty());
    }

    #[test]
    fn millimetre_meshes_are_flagged() {
        let model = brick(Material::default(), Discretisation::Clusters);
        assert_eq!(implausible(&model.bodies[0]), None);
        let mut big = model.bodies[0].clone();
        big.size *= 1000.0;
        big.volume *= 1e9;
        let text = implausible(&big).unwrap();
        assert!(
            text.contains("0.001") && text.contains("m across"),
            "{text}"
        );
        let mut small = model.bodies[0].clone();
        small.size *= 0.001;
        small.volume *= 1e-9;
        assert!(implausible(&small).unwrap().contains("too small"));
    }
}
