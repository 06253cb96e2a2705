//! Shared by the examples: command-line options, the median, and waiting for the GPU.
//! Included with `#[path = "support/bench.rs"] mod bench;`.
#![allow(dead_code)]

use bevy_tissue::gpu::world::read_vec3;
use bevy_tissue::gpu::{GpuWorld, Headless};
use std::path::PathBuf;
use std::str::FromStr;

/// The command line (after the program name).
pub struct Args(Vec<String>);

impl Args {
    /// The process's arguments.
    pub fn new() -> Self {
        Self(std::env::args().skip(1).collect())
    }

    /// Whether `--name` was given.
    pub fn flag(&self, name: &str) -> bool {
        self.0.iter().any(|s| s == name)
    }

    /// The text after the last `name` (a later option overrides an earlier one).
    fn value(&self, name: &str) -> Option<&String> {
        self.0
            .iter()
            .rposition(|s| s == name)
            .and_then(|i| self.0.get(i + 1))
    }

    /// The text after the last `name`, if given.
    pub fn text(&self, name: &str) -> Option<&String> {
        self.value(name)
    }

    /// The texts after every `name` (a repeatable option).
    pub fn all(&self, name: &str) -> Vec<String> {
        self.0
            .windows(2)
            .filter(|w| w[0] == name)
            .map(|w| w[1].clone())
            .collect()
    }

    /// The number after `name`, or `default`; exits with a message on a bad number.
    pub fn num<T: FromStr>(&self, name: &str, default: T) -> T {
        match self.value(name) {
            Some(v) => v.parse().unwrap_or_else(|_| {
                eprintln!("{name} needs a number, got {v}");
                std::process::exit(2)
            }),
            None => default,
        }
    }

    /// The comma-separated numbers after `name` (`--sizes 1000,2000`), or `default`;
    /// exits with a message on a bad number.
    pub fn list<T: FromStr + Clone>(&self, name: &str, default: &[T]) -> Vec<T> {
        match self.value(name) {
            Some(v) => v
                .split(',')
                .map(|s| {
                    s.trim().parse().unwrap_or_else(|_| {
                        eprintln!("{name} needs comma-separated numbers, got {v}");
                        std::process::exit(2)
                    })
                })
                .collect(),
            None => default.to_vec(),
        }
    }

    /// The path after `name`, or `default`.
    pub fn path(&self, name: &str, default: &str) -> PathBuf {
        PathBuf::from(self.value(name).map_or(default, |v| v.as_str()))
    }
}

/// Median of a non-empty list.
pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// The device settings of a benchmark: the adapter's own limits, or with
/// `--webgpu-limits` WebGPU's default limits (what every browser guarantees; the tests
/// run the examples so).
pub fn gpu_settings() -> bevy::render::settings::WgpuSettings {
    let mut s = bevy::render::settings::WgpuSettings::default();
    if Args::new().flag("--webgpu-limits") {
        s.constrained_limits = Some(bevy::render::settings::WgpuLimits::default());
    }
    s
}

/// [`bevy_tissue::gpu::headless`] with [`gpu_settings`].
pub fn open_gpu() -> Result<Headless, String> {
    bevy_tissue::gpu::headless_with(gpu_settings())
}

/// Seconds of GPU work before a timed GPU run: an idle GPU runs at a lower clock, and
/// after the host has spent seconds building a model or measuring an error, runs timed
/// after a shorter warm-up (0.2 s) were measured up to 5x slower.
pub const GPU_WARM_UP_S: f64 = 0.5;

/// Calls `round` (a submission of a few steps, waited for) at least once and then until
/// `seconds` have passed since the first call: keeps the GPU busy so that its clocks are
/// up for what is timed next.
pub fn keep_gpu_busy(seconds: f64, mut round: impl FnMut()) {
    let t = std::time::Instant::now();
    loop {
        round();
        if t.elapsed().as_secs_f64() >= seconds {
            break;
        }
    }
}

/// Waits for all submitted GPU work (a one-particle read cannot finish before it).
pub fn sync(g: &Headless, world: &GpuWorld) {
    let _ = read_vec3(&g.device, &g.queue, world.positions(), 1);
}

/// `bodies` lattice cubes of 5 cm with 8 particles across (512 each; E = 100 kPa, ν =
/// 0.3) on a square grid of `pitch` (m) between centres, 0.5 m up: 0.1 m apart, or
/// 0.057 m so that the facing layers of particles (radius 3.6 mm) touch.
pub fn cubes_at(
    bodies: u32,
    pitch: f32,
) -> Result<bevy_tissue::core::model::Model, bevy_tissue::core::error::TissueError> {
    use bevy_tissue::core::model::{BodyDesc, Discretisation, Material, Model};
    use bevy_tissue::core::sampling::Resolution;
    use glam::Vec3;
    let mut model = Model::new();
    let side = (bodies as f32).sqrt().ceil() as u32;
    // 8 particles across a 5 cm cube: spacing 5 cm / 7.
    let mesh = bevy_tissue::core::procedural::cuboid(Vec3::splat(0.025), 1);
    for b in 0..bodies {
        let at = Vec3::new((b % side) as f32 * pitch, 0.5, (b / side) as f32 * pitch);
        let desc = BodyDesc {
            resolution: Resolution::Spacing(0.05 / 7.0),
            material: Material::Hyperelastic {
                youngs_modulus: 100e3,
                poisson_ratio: 0.3,
            },
            discretisation: Discretisation::Lattice,
            translation: at,
            ..Default::default()
        };
        model.add_body(&mesh, &desc)?;
    }
    Ok(model)
}
