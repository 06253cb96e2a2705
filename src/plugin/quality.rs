//! Quality presets: a body asks for an
//! accuracy level ([`TissueQuality`]) instead of iteration and substep counts, and the
//! world runs the cheapest setting on the measured Pareto front that gives every body at
//! least what it asked for.
//!
//! Iterations and substeps are per world (all bodies are solved in one batch), so the
//! most demanding body sets them: [`apply_quality`] writes the largest preset over the
//! bodies into [`TissueSettings`] whenever it differs (which rebuilds the GPU world with
//! the poses kept). Bodies left at [`TissueQuality::Custom`] (the default) ask for
//! nothing; with none asking, the settings are the user's. While a body asks, its
//! preset's iterations and substeps win over edits of the settings (the egui panel's
//! sliders included).
//!
//! ```
//! use bevy::prelude::*;
//! use bevy_tissue::prelude::*;
//! // A background body that only has to look soft, and an organ that must be right:
//! // the world runs the organ's preset.
//! let background = SoftBody { quality: TissueQuality::Fast, ..default() };
//! let organ = SoftBody {
//!     material: TissueMaterial::Hyperelastic { youngs_modulus: 30e3, poisson_ratio: 0.45 },
//!     quality: TissueQuality::Accurate,
//!     ..default()
//! };
//! let demand = bevy_tissue::plugin::quality::demanded([&background, &organ]);
//! assert_eq!(demand, Some((40, 4)));
//! ```
//!
//! The presets come from `examples/speed_accuracy.rs` on the H100 (BENCHMARKS.md,
//! "Speed against accuracy"; 1,000-particle bar, GPU Jacobi, K = 32). The error is the
//! RMS distance from a converged run over 1 s of swinging, relative to the bar's length
//! (shape matching), and the volume change of a 20% squeeze at ν = 0.49 (hyperelastic):
//!
//! | preset | shape matching: it × substeps, error | hyperelastic: it × substeps, volume error |
//! |---|---|---|
//! | `Fast` | 5 × 1, 8.6% | 10 × 2, 12.2% |
//! | `Balanced` | 10 × 1, 4.1% | 20 × 4, 5.2% |
//! | `Accurate` | 40 × 1, 0.7% | 40 × 4, 2.3% |
//!
//! Substeps buy shape matching nothing (its k is a per-substep stiffness: more substeps
//! make a stiffer material, not a more accurate one), so its presets only add
//! iterations; the hyperelastic model needs substeps to converge and to stay stable under
//! Jacobi (at one substep 20 and 40 iterations diverged in the swinging-bar run).

use super::components::*;
use bevy::prelude::*;

/// How accurately a body wants to be solved (see the module docs for what each level
/// measured). Per body; the world takes the most demanding.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, PartialOrd, Ord, Reflect)]
pub enum TissueQuality {
    /// No demand: [`TissueSettings`]' iterations and substeps as set.
    #[default]
    Custom,
    /// The cheapest setting on the front (games, background bodies).
    Fast,
    /// The middle of the front.
    Balanced,
    /// The most accurate setting measured before the front flattens.
    Accurate,
}

impl TissueQuality {
    /// `(iterations, substeps)` of this level for `material`, or `None` for
    /// [`TissueQuality::Custom`].
    pub fn preset(self, material: &TissueMaterial) -> Option<(u32, u32)> {
        let hyper = matches!(material, TissueMaterial::Hyperelastic { .. });
        Some(match (self, hyper) {
            (TissueQuality::Custom, _) => return None,
            (TissueQuality::Fast, false) => (5, 1),
            (TissueQuality::Balanced, false) => (10, 1),
            (TissueQuality::Accurate, false) => (40, 1),
            (TissueQuality::Fast, true) => (10, 2),
            (TissueQuality::Balanced, true) => (20, 4),
            (TissueQuality::Accurate, true) => (40, 4),
        })
    }
}

/// The iterations and substeps the bodies ask for: the largest of their presets, or
/// `None` when no body asks.
pub fn demanded<'a>(bodies: impl IntoIterator<Item = &'a SoftBody>) -> Option<(u32, u32)> {
    bodies
        .into_iter()
        .filter_map(|b| b.quality.preset(&b.material))
        .reduce(|a, b| (a.0.max(b.0), a.1.max(b.1)))
}

/// Writes the bodies' demanded iterations and substeps into [`TissueSettings`] (only when
/// they differ, so an unchanged demand rebuilds nothing).
pub fn apply_quality(bodies: Query<&SoftBody>, mut settings: ResMut<TissueSettings>) {
    if let Some((iterations, substeps)) = demanded(bodies)
        && (settings.iterations, settings.substeps) != (iterations, substeps)
    {
        settings.iterations = iterations;
        settings.substeps = substeps;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn body(quality: TissueQuality, material: TissueMaterial) -> SoftBody {
        SoftBody {
            quality,
            material,
            ..Default::default()
        }
    }

    const SHAPE_MATCHING: TissueMaterial = TissueMaterial::ShapeMatching { stiffness: 1.0 };

    const HYPER: TissueMaterial = TissueMaterial::Hyperelastic {
        youngs_modulus: 30e3,
        poisson_ratio: 0.45,
    };

    #[test]
    fn presets_grow_with_the_level_and_custom_asks_nothing() {
        for m in [SHAPE_MATCHING, HYPER] {
            assert_eq!(TissueQuality::Custom.preset(&m), None);
            let f = TissueQuality::Fast.preset(&m).unwrap();
            let b = TissueQuality::Balanced.preset(&m).unwrap();
            let a = TissueQuality::Accurate.preset(&m).unwrap();
            assert!(f.0 * f.1 < b.0 * b.1 && b.0 * b.1 < a.0 * a.1, "{m:?}");
        }
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
    }
}
