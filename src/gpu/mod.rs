//! The GPU side: the batched buffers ([`buffers`]), one `.rs` + `.wgsl` pair
//! per kernel ([`kernels`]), and [`world::GpuWorld`], which records time steps and the
//! draw path into a command encoder. The plugin (`crate::plugin`) drives it from Bevy's
//! render graph; tests and benchmarks drive it standalone on a [`headless`] device.
//!
//! The GPU runs the CPU Jacobi solver's algorithm (`core::solver`, the CPU twin of every
//! kernel), in f32, with every sum in the same order, so the two agree to rounding.

pub mod buffers;
pub mod kernels;
pub mod lattice;
pub mod profile;
pub mod world;

use bevy::render::renderer::{RenderDevice, RenderQueue};

pub use kernels::Kernels;
pub use world::{GpuWorld, NoTiming, PassRecorder};

/// A GPU device opened without a window or a Bevy app (tests, benchmarks).
pub struct Headless {
    /// The device.
    pub device: RenderDevice,
    /// Its queue.
    pub queue: RenderQueue,
    /// Adapter name and driver, for reports.
    pub adapter: String,
    /// The compiled kernels.
    pub kernels: Kernels,
}

/// Opens the first Vulkan adapter (or any backend where Vulkan is missing) with every
/// feature and limit it has, and compiles the kernels. Returns a message naming the
/// problem where no adapter exists or the kernels cannot run on it.
pub fn headless() -> Result<Headless, String> {
    headless_with(bevy::render::settings::WgpuSettings::default())
}

/// [`headless`] with given settings (e.g. `constrained_limits`, to try a model against a
/// smaller GPU).
pub fn headless_with(settings: bevy::render::settings::WgpuSettings) -> Result<Headless, String> {
    let (device, queue, adapter) = device_with(settings)?;
    let kernels = Kernels::new(&device).map_err(|e| e.to_string())?;
    Ok(Headless {
        device,
        queue,
        adapter,
        kernels,
    })
}

/// A device and queue opened with `settings` and no kernels compiled, with the adapter's
/// name and driver. Returns a message naming the problem where no adapter exists.
pub fn device_with(
    settings: bevy::render::settings::WgpuSettings,
) -> Result<(RenderDevice, RenderQueue, String), String> {
    use bevy::render::settings::Backends;
    let backends = settings.backends.unwrap_or(Backends::all());
    let res = std::panic::catch_unwind(|| {
        bevy::tasks::block_on(bevy::render::renderer::initialize_renderer(
            backends, None, &settings,
        ))
    })
    .map_err(|_| {
        "no GPU adapter found (install a Vulkan driver, e.g. Mesa's lavapipe: mesa-vulkan-drivers)"
            .to_string()
    })?;
    let info = &res.2;
    let adapter = format!("{} ({:?}, {})", info.name, info.backend, info.driver);
    Ok((res.0, res.1, adapter))
}
