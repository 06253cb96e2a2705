//! The crate builds for `wasm32-unknown-unknown` (browsers), as a library. `.ci/run`
//! installs the target; elsewhere the test says it was skipped when the target is not
//! installed. The build has its own target directory (under cargo's per-test scratch
//! directory), so it neither waits for nor disturbs the native build.

mod common;

use std::process::Command;

#[test]
fn the_crate_builds_for_wasm32() {
    let installed = Command::new("rustup")
        .args(["target", "list", "--installed"])
        .output()
        .map(|o| String::from_utf8_lossy(&o.stdout).contains("wasm32-unknown-unknown"))
        .unwrap_or(false);
    if !installed {
        if common::ci() {
            panic!(
                "CI=true but the wasm32-unknown-unknown target is not installed \
                 (rustup target add wasm32-unknown-unknown)"
            );
        }
        eprintln!("skipped: the wasm32-unknown-unknown target is not installed");
        return;
    }
    let dir = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("wasm32");
    let out = Command::new(env!("CARGO"))
        .args(["build", "--lib", "--target", "wasm32-unknown-unknown"])
        .env("CARGO_TARGET_DIR", &dir)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("cargo runs");
    assert!(
        out.status.success(),
        "the wasm32 build failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
}
