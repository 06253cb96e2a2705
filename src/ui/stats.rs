//! Pure helpers behind the panel's timing section (testable without a window).

use crate::plugin::diagnostics::TissueDiagnostics;
use bevy::diagnostic::DiagnosticsStore;
use core::time::Duration;

/// Path prefix of the tissue passes in Bevy's render diagnostics.
pub(crate) const PASS_PREFIX: &str = "render/tissue/";
/// Path suffix of a span's GPU time (ms) in Bevy's render diagnostics.
pub(crate) const GPU_SUFFIX: &str = "/elapsed_gpu";
/// A pass whose latest GPU time is this much older than the newest tissue pass's is no
/// longer dispatched (e.g. `levels` after the hierarchy was turned off) and is left out.
pub(crate) const STALE_AFTER: Duration = Duration::from_secs(1);

/// The tissue passes' GPU times: `(pass, smoothed ms)` for every enabled diagnostic
/// `render/tissue/<pass>/elapsed_gpu` whose latest measurement is a number, sorted by
/// pass name;
/// passes not measured for [`STALE_AFTER`] before the newest one are left out.
///
/// Bevy's `RenderDiagnosticsPlugin` puts them there, timing what the plugin's spans in
/// `run_tissue` cover: the first dispatch of each kernel in a frame, not all its
/// dispatches ([`frame_total`] has them all); without it, or on a GPU without timestamp
/// queries, the list is empty.
pub(crate) fn pass_rows(store: &DiagnosticsStore) -> Vec<(String, f64)> {
    let found: Vec<_> = store
        .iter()
        .filter(|d| d.is_enabled)
        .filter_map(|d| {
            let pass = d
                .path()
                .as_str()
                .strip_prefix(PASS_PREFIX)?
                .strip_suffix(GPU_SUFFIX)?;
            // The latest measurement must be a number (a NaN-only history smooths to 0).
            let latest = d.measurement().filter(|m| m.value.is_finite())?;
            let ms = d.smoothed().filter(|ms| ms.is_finite())?;
            (!pass.is_empty()).then(|| (pass.to_string(), ms, latest.time))
        })
        .collect();
    let Some(newest) = found.iter().map(|r| r.2).max() else {
        return Vec::new();
    };
    let mut rows: Vec<(String, f64)> = found
        .into_iter()
        .filter(|r| newest.saturating_duration_since(r.2) <= STALE_AFTER)
        .map(|(pass, ms, _)| (pass, ms))
        .collect();
    rows.sort_by(|a, b| a.0.cmp(&b.0));
    rows
}

/// Path of the span around all of a frame's tissue GPU work (every dispatch).
pub(crate) const FRAME_TOTAL: &str = "render/tissue/elapsed_gpu";

/// The frame's tissue GPU time (every dispatch of the steps, the drawing and the bounds),
/// smoothed, ms.
pub(crate) fn frame_total(store: &DiagnosticsStore) -> Option<f64> {
    store
        .iter()
        .find(|d| d.is_enabled && d.path().as_str() == FRAME_TOTAL)?
        .smoothed()
        .filter(|ms| ms.is_finite())
}

/// The main world's share of the frame: `(label, smoothed ms)` for each enabled
/// [`TissueDiagnostics`] path measured with a number, in its order (step, contacts,
/// skin). Empty where no body is stepped from the main world.
pub(crate) fn main_rows(store: &DiagnosticsStore) -> Vec<(&'static str, f64)> {
    let labels = ["step", "contact search", "skinning"];
    TissueDiagnostics::ALL
        .iter()
        .zip(labels)
        .filter_map(|(path, label)| {
            let d = store.get(path).filter(|d| d.is_enabled)?;
            d.measurement().filter(|m| m.value.is_finite())?;
            let ms = d.smoothed().filter(|ms| ms.is_finite())?;
            Some((label, ms))
        })
        .collect()
}

/// GPU time per simulation step, ms: the frame's tissue GPU time ([`frame_total`])
/// over the steps the frame took. `None` when there is no time or no step (nothing to
/// divide).
pub(crate) fn ms_per_step(total_ms: Option<f64>, steps: u32) -> Option<f64> {
    let total = total_ms?;
    (steps > 0 && total.is_finite() && total > 0.0).then(|| total / steps as f64)
}

/// A time in ms for a label: `—` when unknown.
pub(crate) fn fmt_ms(ms: Option<f64>) -> String {
    match ms {
        Some(ms) if ms.is_finite() => format!("{ms:.3} ms"),
        _ => "—".to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bevy::diagnostic::{Diagnostic, DiagnosticMeasurement, DiagnosticPath};
    use bevy::platform::time::Instant;

    fn add(store: &mut DiagnosticsStore, path: &'static str, values: &[f64], time: Instant) {
        let mut d = Diagnostic::new(DiagnosticPath::new(path)).with_suffix("ms");
        for &value in values {
            d.add_measurement(DiagnosticMeasurement { time, value });
        }
        store.add(d);
    }

    #[test]
    fn rows_are_the_tissue_gpu_passes_sorted_and_the_frame_total_apart() {
        let now = Instant::now();
        let mut s = DiagnosticsStore::default();
        add(&mut s, "render/tissue/skin/elapsed_gpu", &[0.25], now);
        add(&mut s, "render/tissue/clusters/elapsed_gpu", &[1.5], now);
        add(&mut s, "render/tissue/gather/elapsed_gpu", &[0.5], now);
        // CPU time of a tissue pass, a non-tissue pass, a tissue-like prefix, the
        // frame time: all left out.
        add(&mut s, "render/tissue/clusters/elapsed_cpu", &[9.0], now);
        add(
            &mut s,
            "render/main_opaque_pass_3d/elapsed_gpu",
            &[7.0],
            now,
        );
        add(&mut s, "render/tissuex/foo/elapsed_gpu", &[7.0], now);
        add(&mut s, "frame_time", &[16.0], now);
        // Registered but never measured: left out.
        add(&mut s, "render/tissue/knn/elapsed_gpu", &[], now);
        // The span around all of the frame's tissue work: not a row, the frame total.
        add(&mut s, "render/tissue/elapsed_gpu", &[4.0], now);
        let rows = pass_rows(&s);
        let names: Vec<&str> = rows.iter().map(|r| r.0.as_str()).collect();
        assert_eq!(names, ["clusters", "gather", "skin"]);
        assert_eq!(rows[0].1, 1.5);
        assert_eq!(frame_total(&s), Some(4.0));
    }

    #[test]
    fn disabled_nan_and_stale_passes_are_left_out() {
        let now = Instant::now();
        let Some(old) = now.checked_sub(STALE_AFTER * 5) else {
            return; // a clock too young to go back: nothing to test
        };
        let mut s = DiagnosticsStore::default();
        add(&mut s, "render/tissue/predict/elapsed_gpu", &[0.1], now);
        add(&mut s, "render/tissue/levels/elapsed_gpu", &[3.0], old);
        add(&mut s, "render/tissue/nan/elapsed_gpu", &[f64::NAN], now);
        add(&mut s, "render/tissue/off/elapsed_gpu", &[1.0], now);
        s.get_mut(&DiagnosticPath::new("render/tissue/off/elapsed_gpu"))
            .unwrap()
            .is_enabled = false;
        let rows = pass_rows(&s);
        assert_eq!(rows, vec![("predict".to_string(), 0.1)]);
    }

    #[test]
    fn rows_use_the_smoothed_time() {
        let t0 = Instant::now();
        let mut s = DiagnosticsStore::default();
        let mut d = Diagnostic::new(DiagnosticPath::new("render/tissue/finish/elapsed_gpu"));
        d.add_measurement(DiagnosticMeasurement {
            time: t0,
            value: 1.0,
        });
        // A spike 10 ms later moves the moving average only part of the way.
        d.add_measurement(DiagnosticMeasurement {
            time: t0 + Duration::from_millis(10),
            value: 11.0,
        });
        s.add(d);
        let rows = pass_rows(&s);
        assert_eq!(rows.len(), 1);
        assert!(rows[0].1 > 1.0 && rows[0].1 < 11.0, "{rows:?}");
    }

    #[test]
    fn main_rows_are_the_main_world_diagnostics_in_order() {
        let now = Instant::now();
        let mut s = DiagnosticsStore::default();
        // Registered as the plugin does, skin first: the rows keep the paths' order.
        add(&mut s, "tissue/main/skin", &[0.5], now);
        add(&mut s, "tissue/main/step", &[2.0], now);
        // Registered, never measured (no GPU stepping): left out.
        add(&mut s, "tissue/main/contacts", &[], now);
        // A GPU pass: not a main-world row.
        add(&mut s, "render/tissue/skin/elapsed_gpu", &[9.0], now);
        assert_eq!(main_rows(&s), vec![("step", 2.0), ("skinning", 0.5)]);
        s.get_mut(&TissueDiagnostics::STEP).unwrap().is_enabled = false;
        assert_eq!(main_rows(&s), vec![("skinning", 0.5)]);
        assert!(main_rows(&DiagnosticsStore::default()).is_empty());
    }

    #[test]
    fn empty_store_has_no_rows_and_no_total() {
        let s = DiagnosticsStore::default();
        assert!(pass_rows(&s).is_empty());
        assert_eq!(frame_total(&s), None);
    }

    #[test]
    fn ms_per_step_divides_and_refuses_zero() {
        assert_eq!(ms_per_step(Some(3.0), 2), Some(1.5));
        assert_eq!(ms_per_step(Some(3.0), 0), None);
        assert_eq!(ms_per_step(None, 4), None);
        assert_eq!(ms_per_step(Some(0.0), 4), None);
        assert_eq!(ms_per_step(Some(f64::NAN), 4), None);
    }

    #[test]
    fn ms_format() {
        assert_eq!(fmt_ms(Some(1.23456)), "1.235 ms");
        assert_eq!(fmt_ms(None), "—");
        assert_eq!(fmt_ms(Some(f64::INFINITY)), "—");
    }
}
