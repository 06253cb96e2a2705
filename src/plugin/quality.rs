//! Quality presets: a body asks for an accuracy level ([`TissueQuality`]) instead of
//! iteration and substep counts, and the world runs the cheapest setting measured to
//! give every body at least what it asked for.
//!
//! The settings are per world (all bodies are solved in one batch), so the most
//! demanding body sets them: [`apply_quality`] writes the largest preset over the bodies
//! into [`TissueSettings`] whenever it differs. Bodies left at [`TissueQuality::Custom`]
//! (the default) ask for nothing; with none asking, the settings are the user's. While a
//! body asks, its preset wins over edits of the settings (the egui panel's sliders
//! included).
//!
//! ```
//! use bevy::prelude::*;
//! use bevy_tissue::prelude::*;
//! use bevy_tissue::plugin::quality::{Preset, demanded};
//! // A background body that only has to look soft, and an organ that must be right:
//! // the world runs the organ's preset.
//! let background = SoftBody { quality: TissueQuality::Fast, ..default() };
//! let organ = SoftBody { quality: TissueQuality::Accurate, ..default() };
//! let demand = demanded([&background, &organ]).unwrap();
//! assert_eq!((demand.newton_iterations, demand.newton_cycles), (Some(1), Some(2)));
//! ```
//!
//! **Lattice bodies** (the default, [`TissueDiscretisation::Lattice`]) are stepped by
//! Newton–multigrid at one substep of the step; a level sets its Newton iterations and
//! the V-cycles of each (one: the two-direction step, the V-cycle's correction and the
//! last step's answer combined; more: conjugate gradients). The error is that of the
//! settled cantilever's tip (24 × 3 × 3 cm, 6 and 12 particles across, E from 1 kPa to
//! 1 MPa) against the static answer of the same model, on the GPU, with the default
//! V-cycle and smoother (BENCHMARKS.md, "The two-direction step"):
//!
//! | preset | Newton iterations × V-cycles | error of the settled tip |
//! |---|---|---|
//! | `Fast`, `Balanced` | 1 × 1 (the default) | ≤ 1% everywhere measured |
//! | `Accurate` | 1 × 2 | ≤ 1% everywhere measured |
//!
//! `Fast` and `Balanced` are the same step for lattice bodies: nothing cheaper than one
//! V-cycle a step was measured within a few percent (one V-cycle without the last
//! step's answer is 26% short at 1 MPa). `Accurate` solves each Newton step more
//! exactly, for scenes harder than the cantilever.
//!
//! **Cluster bodies** (the paper's model) come from `examples/speed_accuracy.rs` on the
//! H100 (BENCHMARKS.md, "Speed against accuracy"; 1,000-particle bar, GPU Jacobi,
//! K = 32). The error is the RMS distance from a converged run over 1 s of swinging,
//! relative to the bar's length (shape matching), and the volume change of a 20% squeeze
//! at ν = 0.49 (hyperelastic):
//!
//! | preset | shape matching: it × substeps, error | hyperelastic: it × substeps, volume error |
//! |---|---|---|
//! | `Fast` | 5 × 1, 8.6% | 10 × 2, 12.2% |
//! | `Balanced` | 10 × 1, 4.1% | 20 × 4, 5.2% |
//! | `Accurate` | 40 × 1, 0.7% | 40 × 4, 2.3% |
//!
//! Substeps buy shape matching nothing (its k is a per-substep stiffness: more substeps
//! make a stiffer material, not a more accurate one), so its presets only add
//! iterations; the hyperelastic clusters need substeps to converge and to stay stable
//! under Jacobi (at one substep 20 and 40 iterations diverged in the swinging-bar run).

use super::components::*;
use bevy::prelude::*;

/// How accurately a body wants to be solved (see the module docs for what each level
/// measured). Per body; the world takes the most demanding.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, PartialOrd, Ord, Reflect)]
pub enum TissueQuality {
    /// No demand: [`TissueSettings`] as set.
    #[default]
    Custom,
    /// The cheapest level measured (games, background bodies).
    Fast,
    /// The middle level (the plugin's defaults for lattice bodies).
    Balanced,
    /// The most accurate level measured before the error stops falling.
    Accurate,
}

/// What a body's quality level asks of the world's settings (`None`: nothing).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Preset {
    /// [`TissueSettings::iterations`] (cluster bodies).
    pub iterations: Option<u32>,
    /// [`TissueSettings::substeps`] (cluster bodies).
    pub substeps: Option<u32>,
    /// [`TissueSettings::newton_iterations`] (lattice bodies).
    pub newton_iterations: Option<u32>,
    /// [`TissueSettings::newton_cycles`] (lattice bodies).
    pub newton_cycles: Option<u32>,
}

impl Preset {
    /// The larger demand of each field.
    fn max(self, other: Preset) -> Preset {
        let m = |a: Option<u32>, b: Option<u32>| match (a, b) {
            (Some(a), Some(b)) => Some(a.max(b)),
            (a, b) => a.or(b),
        };
        Preset {
            iterations: m(self.iterations, other.iterations),
            substeps: m(self.substeps, other.substeps),
            newton_iterations: m(self.newton_iterations, other.newton_iterations),
            newton_cycles: m(self.newton_cycles, other.newton_cycles),
        }
    }
}

impl TissueQuality {
    /// What this level asks of the world for `body` (by its discretisation and
    /// material), or `None` for [`TissueQuality::Custom`].
    pub fn preset(self, body: &SoftBody) -> Option<Preset> {
        if self == TissueQuality::Custom {
            return None;
        }
        if body.discretisation == TissueDiscretisation::Lattice {
            let (newton, cycles) = match self {
                // One V-cycle is already within 1% (see the module's table).
                TissueQuality::Fast | TissueQuality::Balanced => (1, 1),
                _ => (1, 2),
            };
            return Some(Preset {
                newton_iterations: Some(newton),
                newton_cycles: Some(cycles),
                ..Default::default()
            });
        }
        let hyper = matches!(body.material, TissueMaterial::Hyperelastic { .. });
        let (iterations, substeps) = match (self, hyper) {
            (TissueQuality::Fast, false) => (5, 1),
            (TissueQuality::Balanced, false) => (10, 1),
            (_, false) => (40, 1),
            (TissueQuality::Fast, true) => (10, 2),
            (TissueQuality::Balanced, true) => (20, 4),
            (_, true) => (40, 4),
        };
        Some(Preset {
            iterations: Some(iterations),
            substeps: Some(substeps),
            newton_iterations: None,
            newton_cycles: None,
        })
    }
}

/// What the bodies ask of the world: the largest of their presets, field by field, or
/// `None` when no body asks.
pub fn demanded<'a>(bodies: impl IntoIterator<Item = &'a SoftBody>) -> Option<Preset> {
    bodies
        .into_iter()
        .filter_map(|b| b.quality.preset(b))
        .reduce(Preset::max)
}

/// Writes the bodies' demand into [`TissueSettings`] (only what differs, so an
/// unchanged demand rebuilds nothing).
pub fn apply_quality(bodies: Query<&SoftBody>, mut settings: ResMut<TissueSettings>) {
    let Some(d) = demanded(bodies) else {
        return;
    };
    let want = (
        d.iterations.unwrap_or(settings.iterations),
        d.substeps.unwrap_or(settings.substeps),
        d.newton_iterations.unwrap_or(settings.newton_iterations),
        d.newton_cycles.unwrap_or(settings.newton_cycles),
    );
    if (
        settings.iterations,
        settings.substeps,
        settings.newton_iterations,
        settings.newton_cycles,
    ) != want
    {
        settings.iterations = want.0;
        settings.substeps = want.1;
        settings.newton_iterations = want.2;
        settings.newton_cycles = want.3;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn body(quality: TissueQuality, material: TissueMaterial) -> SoftBody {
        SoftBody {
            quality,
            material,
            discretisation: TissueDiscretisation::Clusters,
            ..Default::default()
        }
    }

    const SHAPE_MATCHING: TissueMaterial = TissueMaterial::ShapeMatching { stiffness: 1.0 };

    const HYPER: TissueMaterial = TissueMaterial::Hyperelastic {
        youngs_modulus: 30e3,
        poisson_ratio: 0.45,
    };

    fn work(p: Preset) -> u32 {
        p.iterations.unwrap_or(1)
            * p.substeps.unwrap_or(1)
            * p.newton_iterations.unwrap_or(1)
            * p.newton_cycles.unwrap_or(1)
    }

    #[test]
    fn presets_grow_with_the_level_and_custom_asks_nothing() {
        let lattice = SoftBody::default();
        for b in [
            body(TissueQuality::Custom, SHAPE_MATCHING),
            body(TissueQuality::Custom, HYPER),
            lattice.clone(),
        ] {
            assert_eq!(TissueQuality::Custom.preset(&b), None);
            let f = work(TissueQuality::Fast.preset(&b).unwrap());
            let m = work(TissueQuality::Balanced.preset(&b).unwrap());
            let a = work(TissueQuality::Accurate.preset(&b).unwrap());
            // Lattice bodies: `Fast` is `Balanced` (nothing cheaper is accurate).
            if b.discretisation == TissueDiscretisation::Lattice {
                assert!(f == m && m < a, "{b:?}");
            } else {
                assert!(f < m && m < a, "{b:?}");
            }
        }
        // Lattice bodies ask for Newton iterations only; the balanced level is the
        // plugin's default.
        let p = TissueQuality::Balanced.preset(&lattice).unwrap();
        assert_eq!(p.iterations, None);
        assert_eq!(p.newton_iterations, Some(TissueSettings::NEWTON_ITERATIONS));
        assert_eq!(p.newton_cycles, Some(TissueSettings::NEWTON_CYCLES));
    }

    #[test]
    fn the_most_demanding_body_sets_the_world_and_custom_bodies_leave_it() {
        let mut app = App::new();
        app.insert_resource(TissueSettings::default())
            .add_systems(Update, apply_quality);
        let custom = app
            .world_mut()
            .spawn(body(TissueQuality::Custom, HYPER))
            .id();
        app.update();
        let s = app.world().resource::<TissueSettings>();
        assert_eq!((s.iterations, s.substeps), (10, 1), "no demand: untouched");
        app.world_mut()
            .spawn(body(TissueQuality::Fast, SHAPE_MATCHING));
        let accurate = app
            .world_mut()
            .spawn(body(TissueQuality::Accurate, HYPER))
            .id();
        app.update();
        let s = app.world().resource::<TissueSettings>();
        assert_eq!((s.iterations, s.substeps), (40, 4));
        app.world_mut().despawn(accurate);
        app.world_mut().despawn(custom);
        app.update();
        let s = app.world().resource::<TissueSettings>();
        assert_eq!((s.iterations, s.substeps), (5, 1), "the fast body alone");
        // A lattice body at the accurate level adds its Newton iterations and V-cycles and
        // leaves the clusters' iterations to the fast body.
        app.world_mut().spawn(SoftBody {
            quality: TissueQuality::Accurate,
            ..Default::default()
        });
        app.update();
        let s = app.world().resource::<TissueSettings>();
        assert_eq!(
            (
                s.iterations,
                s.substeps,
                s.newton_iterations,
                s.newton_cycles
            ),
            (5, 1, 1, 2)
        );
    }
}
