//! The benchmark examples' `--quick` modes run (as CI does) and fill every cell with a
//! finite number. `cargo test` builds the examples; the binaries are found next to this
//! test's own executable (`target/<profile>/examples/`).

use std::path::PathBuf;
use std::process::Command;

mod common;
use common::{ci, example};

/// Runs `name --quick --out <temp dir>`, asserts it succeeded, and returns the output
/// folder, stdout and stderr.
fn run_quick(name: &str) -> (PathBuf, String, String) {
    let bin = example(name);
    assert!(bin.exists(), "{} not built", bin.display());
    let out = std::env::temp_dir().join(format!("bevy_tissue_{name}_{}", std::process::id()));
    let run = Command::new(&bin)
        .args(["--quick", "--out"])
        .arg(&out)
        .output()
        .expect("run the example");
    let stderr = String::from_utf8_lossy(&run.stderr).into_owned();
    assert!(run.status.success(), "{name} --quick failed:\n{stderr}");
    (
        out,
        String::from_utf8_lossy(&run.stdout).into_owned(),
        stderr,
    )
}

#[test]
fn hierarchy_quick_writes_complete_curves() {
    let (out, stdout, stderr) = run_quick("hierarchy");
    let csv = std::fs::read_to_string(out.join("hierarchy.csv")).expect("CSV written");
    assert!(out.join("hierarchy.png").exists(), "PNG written");
    let mut curves = std::collections::BTreeMap::<String, Vec<(u32, f64, f64)>>::new();
    for line in csv.lines().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        assert_eq!(f.len(), 8, "row {line}");
        let key = format!("{} {} {}", f[0], f[2], f[3]);
        let it: u32 = f[5].parse().unwrap();
        let ms: f64 = f[6].parse().unwrap();
        let r: f64 = f[7].parse().unwrap();
        assert!(ms.is_finite() && ms >= 0.0, "{line}");
        assert!(r.is_finite() && r >= 0.0, "{line}");
        curves.entry(key).or_default().push((it, ms, r));
    }
    let gpu = !stderr.contains("GPU curves skipped");
    if ci() {
        assert!(gpu, "CI=true but the GPU curves were skipped:\n{stderr}");
    }
    let backends: &[&str] = if gpu { &["CPU", "GPU"] } else { &["CPU"] };
    for scene in ["bar", "liver"] {
        for backend in backends {
            for solver in ["flat", "hierarchical"] {
                let key = format!("{scene} {backend} {solver}");
                let c = curves.get(&key).unwrap_or_else(|| panic!("no curve {key}"));
                assert!(c.len() >= 5, "{key}: {} points", c.len());
            }
            // The hierarchy is ahead at every sampled iteration count of the bar.
            if scene == "bar" {
                let f = &curves[&format!("bar {backend} flat")];
                let h = &curves[&format!("bar {backend} hierarchical")];
                for &(it, _, rh) in h {
                    if let Some(&(_, _, rf)) = f.iter().find(|p| p.0 == it) {
                        assert!(rh < rf, "{backend} bar, {it} iterations: {rh} vs flat {rf}");
                    }
                }
            }
        }
    }
    assert!(stdout.contains("| bar |"), "summary table:\n{stdout}");
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn table1_quick_fills_every_cell() {
    let (out, stdout, stderr) = run_quick("table1");
    let json = std::fs::read_to_string(out.join("table1.json")).expect("JSON written");
    assert!(out.join("table1.png").exists(), "PNG written");
    let gpu = !stderr.contains("GPU rows skipped");
    if ci() {
        assert!(gpu, "CI=true but the GPU rows were skipped:\n{stderr}");
    }
    // Cells: 2 sizes × 2 K × (2 CPU backends + the GPU).
    let cells: Vec<&str> = json.lines().filter(|l| l.contains("\"target\"")).collect();
    assert_eq!(cells.len(), 4 * if gpu { 3 } else { 2 }, "{json}");
    let number = |line: &str, key: &str| -> f64 {
        let i = line
            .find(&format!("\"{key}\": "))
            .unwrap_or_else(|| panic!("{key} in {line}"));
        let rest = &line[i + key.len() + 4..];
        let end = rest.find([',', '}']).unwrap();
        rest[..end].trim().parse().unwrap()
    };
    for c in &cells {
        for key in ["ms_per_step", "ms_per_knn"] {
            let v = number(c, key);
            assert!(v.is_finite() && v > 0.0, "{key} = {v} in {c}");
        }
        assert!(c.contains("\"finite\": true"), "a run diverged: {c}");
    }
    // The Markdown table has a row per cell, each with the paper's number where it
    // has one.
    assert_eq!(
        stdout
            .lines()
            .filter(|l| l.starts_with("| 32 ") || l.starts_with("| 64 "))
            .count(),
        cells.len()
    );
    let _ = std::fs::remove_dir_all(&out);
}
