//! Shared by the scene examples (liver, jelly): a window or a headless render target of a
//! given size, PNG frames at given frames, a frame limit, a frame-rate report, and a
//! scripted pointer (the mouse drag driven by the script instead of the hand).
//! Included with `#[path = "support/scene.rs"] mod scene;` (needs `mod bench;` too).
//!
//! Options every scene example takes:
//!
//! ```text
//! --frames N          exit after N frames
//! --headless          no window: draw into an image of --size (default 1920x1080)
//! --size WxH          window or image size, px
//! --shot F:PATH       write frame F as a PNG (repeatable)
//! --script            scripted input (tool moves, a drag) and one step per frame
//! --warmup N          frames before the frame-rate report starts (default 120)
//! --lite              no shadow maps, no MSAA (software rasterisers, CI)
//! --no-sleep          bodies never sleep (to measure what sleeping saves)
//! --sleep-speed V     bodies sleep below V m/s (TissueSleep::speed)
//! --msaa N            MSAA samples, 1, 2 or 4 (default: 4 where the adapter can
//!                     multisample the scene's formats 4x, else 1; --lite: 1)
//! --pause             start with the simulation paused (what drawing alone costs)
//! --profile           where a frame's time goes: the main world's update (and the
//!                     plugin's steps, contact search and skinning in it), the render
//!                     world's stages, and CPU and GPU ms per render pass
//! --webgpu-limits     hold the device to WebGPU's default limits (what every browser
//!                     guarantees; the tests run the scenes so)
//! ```
#![allow(dead_code)]

use crate::bench::Args;
use bevy::camera::RenderTarget;
use bevy::ecs::system::SystemParam;
use bevy::input::ButtonState;
use bevy::input::mouse::MouseButtonInput;
use bevy::prelude::*;
use bevy::render::render_resource::TextureFormat;
use bevy::render::view::screenshot::{Screenshot, save_to_disk};
use bevy::window::{ExitCondition, PrimaryWindow, WindowResolution};
use bevy_tissue::prelude::*;
use std::time::{Duration, Instant};

/// The scene options.
#[derive(Resource, Clone, Debug)]
pub struct SceneArgs {
    /// Exit after this many frames.
    pub frames: Option<u32>,
    /// Draw into an image instead of a window.
    pub headless: bool,
    /// Window or image size, px.
    pub size: UVec2,
    /// PNG frames to write: (frame, path).
    pub shots: Vec<(u32, String)>,
    /// Scripted input, one step per frame.
    pub script: bool,
    /// Frames before the frame-rate report starts.
    pub warmup: u32,
    /// No shadow maps and no MSAA (for software rasterisers such as lavapipe).
    pub lite: bool,
    /// Bodies never sleep (to measure what sleeping saves).
    pub no_sleep: bool,
    /// Sleep threshold, m/s (`TissueSleep::speed`; `None`: the plugin's default).
    pub sleep_speed: Option<f32>,
    /// MSAA samples (1, 2 or 4); `None`: what the adapter supports ([`adapter_msaa`]).
    pub msaa: Option<u32>,
    /// Start with the simulation clock paused.
    pub pause: bool,
    /// Report where a frame's time goes.
    pub profile: bool,
    /// Hold the device to WebGPU's default limits.
    pub webgpu_limits: bool,
}

impl SceneArgs {
    /// From the command line; exits with a message on a bad option.
    pub fn parse(args: &Args) -> Self {
        let size = args.text("--size").map_or(UVec2::new(1920, 1080), |s| {
            let parsed = s
                .split_once('x')
                .and_then(|(w, h)| Some(UVec2::new(w.parse().ok()?, h.parse().ok()?)));
            parsed.filter(|v| v.min_element() > 0).unwrap_or_else(|| {
                eprintln!("--size needs WxH, got {s}");
                std::process::exit(2)
            })
        });
        let shots = args
            .all("--shot")
            .iter()
            .map(|s| {
                s.split_once(':')
                    .and_then(|(f, p)| Some((f.parse().ok()?, p.to_string())))
                    .unwrap_or_else(|| {
                        eprintln!("--shot needs FRAME:PATH, got {s}");
                        std::process::exit(2)
                    })
            })
            .collect();
        let frames = args.text("--frames").map(|_| args.num("--frames", 0u32));
        Self {
            frames,
            headless: args.flag("--headless"),
            size,
            shots,
            script: args.flag("--script"),
            warmup: args.num("--warmup", 120),
            lite: args.flag("--lite"),
            no_sleep: args.flag("--no-sleep"),
            sleep_speed: args
                .text("--sleep-speed")
                .map(|_| args.num("--sleep-speed", 0.0)),
            msaa: args.text("--msaa").map(|_| match args.num("--msaa", 0u32) {
                m @ (1 | 2 | 4) => m,
                m => {
                    eprintln!("--msaa takes 1, 2 or 4, got {m}");
                    std::process::exit(2)
                }
            }),
            pause: args.flag("--pause"),
            profile: args.flag("--profile"),
            webgpu_limits: args.flag("--webgpu-limits"),
        }
    }
}

/// The camera the scene is seen through (a headless run points it at an image).
#[derive(Component)]
pub struct SceneCamera;

/// The headless target image.
#[derive(Resource)]
struct TargetImage(Handle<Image>);

/// Frame counter and frame-time samples.
#[derive(Resource, Default)]
pub struct Frames {
    /// Frames run (the first is 1).
    pub count: u32,
    last: Option<Instant>,
    times: Vec<f64>,
}

/// The app: Bevy's default plugins for a window or a headless image target, the tissue
/// plugin with `settings`, and this module's frame handling.
pub fn app(args: &SceneArgs, title: &str, mut settings: TissueSettings) -> App {
    let mut app = App::new();
    let window = Window {
        title: title.into(),
        resolution: WindowResolution::new(args.size.x, args.size.y),
        ..default()
    };
    let render = bevy::render::RenderPlugin {
        render_creation: bevy::render::settings::RenderCreation::Automatic(Box::new(
            bevy::render::settings::WgpuSettings {
                constrained_limits: args
                    .webgpu_limits
                    .then(bevy::render::settings::WgpuLimits::default),
                ..default()
            },
        )),
        ..default()
    };
    if args.headless {
        app.add_plugins(
            DefaultPlugins
                .set(WindowPlugin {
                    primary_window: None,
                    exit_condition: ExitCondition::DontExit,
                    ..default()
                })
                .set(render)
                .disable::<bevy::winit::WinitPlugin>(),
        )
        .add_plugins(bevy::app::ScheduleRunnerPlugin::run_loop(Duration::ZERO));
    } else {
        app.add_plugins(
            DefaultPlugins
                .set(WindowPlugin {
                    primary_window: Some(window),
                    ..default()
                })
                .set(render),
        );
    }
    if args.script {
        // One step per frame: the script's timeline is in frames, whatever the frame rate.
        settings.max_steps_per_frame = 1;
    }
    app.add_plugins(TissuePlugin { settings });
    if args.no_sleep || args.sleep_speed.is_some() {
        app.insert_resource(TissueSleep {
            speed: if args.no_sleep {
                0.0
            } else {
                args.sleep_speed.unwrap_or_default()
            },
            ..default()
        });
    }
    app.insert_resource(args.clone())
        .init_resource::<Frames>()
        .add_systems(PreStartup, make_target)
        .add_systems(Update, (aim_camera, count_frames, lite_lights))
        .add_systems(Last, finish);
    if args.script {
        app.add_systems(Startup, |mut clock: ResMut<TissueClock>| {
            clock.fixed_steps_per_frame = Some(1);
        });
    }
    if args.pause {
        app.add_systems(Startup, |mut clock: ResMut<TissueClock>| {
            clock.paused = true
        });
    }
    if args.profile {
        profile::add(&mut app);
    }
    app
}

fn make_target(args: Res<SceneArgs>, mut images: ResMut<Assets<Image>>, mut commands: Commands) {
    if args.headless {
        let image = Image::new_target_texture(
            args.size.x,
            args.size.y,
            TextureFormat::Rgba8UnormSrgb,
            None,
        );
        commands.insert_resource(TargetImage(images.add(image)));
    }
}

/// Points a headless scene's camera at the target image.
fn aim_camera(
    target: Option<Res<TargetImage>>,
    cameras: Query<Entity, Added<SceneCamera>>,
    mut commands: Commands,
) {
    let Some(target) = target else { return };
    for e in &cameras {
        commands
            .entity(e)
            .insert(RenderTarget::Image(target.0.clone().into()));
    }
}

/// MSAA samples the adapter can take for the scenes' targets: 4 when it multisamples
/// their colour formats (sRGB for the window or image, `Rgba16Float` for HDR) and the
/// depth format 4x — every WebGPU adapter must, lavapipe included — else 1. 2 is not
/// offered: WebGPU does not guarantee it and lavapipe refuses it.
pub fn adapter_msaa(adapter: Option<&bevy::render::renderer::RenderAdapter>) -> u32 {
    let Some(adapter) = adapter else {
        return 1;
    };
    let four = [
        TextureFormat::Rgba8UnormSrgb,
        TextureFormat::Bgra8UnormSrgb,
        TextureFormat::Rgba16Float,
        TextureFormat::Depth32Float,
    ]
    .iter()
    .all(|f| {
        adapter
            .get_texture_format_features(*f)
            .flags
            .sample_count_supported(4)
    });
    if four { 4 } else { 1 }
}

/// `--lite`: directional lights cast no shadows and the camera takes one sample a pixel;
/// `--msaa`: the camera's samples (default: [`adapter_msaa`]).
fn lite_lights(
    args: Res<SceneArgs>,
    adapter: Option<Res<bevy::render::renderer::RenderAdapter>>,
    mut lights: Query<&mut DirectionalLight, Added<DirectionalLight>>,
    cameras: Query<Entity, Added<SceneCamera>>,
    mut commands: Commands,
) {
    if args.lite {
        for mut l in &mut lights {
            l.shadow_maps_enabled = false;
        }
    }
    if cameras.is_empty() {
        return;
    }
    let samples = args
        .msaa
        .unwrap_or_else(|| adapter_msaa(adapter.as_deref()));
    let msaa = match (args.lite, samples) {
        (true, _) | (false, 1) => Msaa::Off,
        (false, 4) => Msaa::Sample4,
        _ => Msaa::Sample2,
    };
    if args.msaa.is_none() {
        eprintln!("MSAA: {samples} samples (what the adapter supports; --msaa N to choose)");
    }
    for e in &cameras {
        commands.entity(e).insert(msaa);
    }
}

fn count_frames(mut frames: ResMut<Frames>) {
    frames.count += 1;
    let now = Instant::now();
    if let Some(last) = frames.last {
        let dt = (now - last).as_secs_f64() * 1e3;
        frames.times.push(dt);
    }
    frames.last = Some(now);
}

/// Whether this is the last frame (`--frames`, and a few frames more than the last shot,
/// so that the PNGs are written).
fn at_end(args: &SceneArgs, frames: &Frames) -> bool {
    let Some(limit) = args.frames else {
        return false;
    };
    let last_shot = args.shots.iter().map(|s| s.0).max().unwrap_or(0);
    frames.count >= limit.max(last_shot + 5)
}

/// PNG frames, the frame limit and the frame-rate report.
// A Bevy system: its arguments are the resources and queries it reads.
#[allow(clippy::too_many_arguments)]
fn finish(
    args: Res<SceneArgs>,
    frames: Res<Frames>,
    target: Option<Res<TargetImage>>,
    clock: Res<TissueClock>,
    store: Option<Res<bevy::diagnostic::DiagnosticsStore>>,
    bodies: Query<(Has<Sleeping>, &BodyMotion), With<SoftBody>>,
    mut commands: Commands,
    mut exit: MessageWriter<AppExit>,
) {
    let n = frames.count;
    for (f, path) in &args.shots {
        if *f == n {
            let shot = match &target {
                Some(t) => Screenshot::image(t.0.clone()),
                None => Screenshot::primary_window(),
            };
            commands.spawn(shot).observe(save_to_disk(path.clone()));
        }
    }
    if !at_end(&args, &frames) {
        return;
    }
    let times = &frames.times[(args.warmup as usize).min(frames.times.len())..];
    if !times.is_empty() {
        let mut sorted = times.to_vec();
        sorted.sort_by(f64::total_cmp);
        let mean = times.iter().sum::<f64>() / times.len() as f64;
        let median = sorted[sorted.len() / 2];
        println!(
            "frames {n} (after {} warm-up): mean {mean:.3} ms/frame = {:.1} fps, median {median:.3} ms = {:.1} fps, slowest {:.3} ms; {} steps",
            args.warmup,
            1e3 / mean,
            1e3 / median,
            sorted[sorted.len() - 1],
            clock.steps
        );
    }
    let mut awake: Vec<f32> = bodies
        .iter()
        .filter(|(asleep, _)| !asleep)
        .map(|(_, m)| m.max_speed)
        .collect();
    awake.sort_by(f32::total_cmp);
    println!(
        "bodies asleep at exit: {} of {}; fastest particle of the awake ones, m/s: {:?}",
        bodies.iter().filter(|(asleep, _)| *asleep).count(),
        bodies.iter().count(),
        awake
            .iter()
            .map(|v| (v * 1e3).round() / 1e3)
            .collect::<Vec<_>>()
    );
    // GPU time per render pass (with RenderDiagnosticsPlugin, which the panel adds).
    if let Some(store) = store {
        let mut passes: Vec<(String, f64)> = store
            .iter()
            .filter(|d| {
                let p = d.path().as_str();
                p.starts_with("render/") && p.ends_with("/elapsed_gpu")
            })
            .filter_map(|d| Some((d.path().to_string(), d.smoothed()?)))
            .collect();
        passes.sort_by(|a, b| b.1.total_cmp(&a.1));
        if args.profile {
            let cpu: f64 = store
                .iter()
                .filter(|d| d.path().as_str().ends_with("/elapsed_cpu"))
                .filter_map(|d| d.smoothed())
                .sum();
            let gpu: f64 = store
                .iter()
                .filter(|d| {
                    let p = d.path().as_str();
                    // Spans nest (`tissue` holds `tissue/<kernel>`): count the outer ones.
                    p.ends_with("/elapsed_gpu") && p.matches('/').count() == 2
                })
                .filter_map(|d| d.smoothed())
                .sum();
            println!(
                "render passes (smoothed): CPU {cpu:.3} ms encoding, GPU {gpu:.3} ms in outer spans"
            );
        }
        if !passes.is_empty() {
            let list: Vec<String> = passes
                .iter()
                .take(16)
                .map(|(p, ms)| format!("{} {ms:.3}", &p[7..p.len() - 12]))
                .collect();
            println!(
                "GPU ms per pass (smoothed; `tissue` is all of the frame's tissue work, \
                 `tissue/<kernel>` its first dispatch): {}",
                list.join(", ")
            );
        }
    }
    exit.write(AppExit::Success);
}

/// The camera the scene is seen through, and a directional light with shadows that
/// shines from `sun` toward the origin (`illuminance` in lux).
///
/// Drawing is kept cheap where it costs the look little, because an H100 or H200 (where
/// the frame rates in BENCHMARKS.md, "Scenes", are measured) rasterises on few units and
/// pays for every pixel and every shadow-map texel: the shadow map is one cascade of
/// 1024² reaching twice the camera's distance to `target` (these scenes are small and
/// seen from one side; Bevy's default is four cascades of 2048² out to 150 m), filtered
/// with one hardware 2×2 lookup, and the camera takes 4 samples a pixel where the adapter
/// can (`--msaa`).
pub fn spawn_view(commands: &mut Commands, eye: Vec3, target: Vec3, sun: Vec3, illuminance: f32) {
    commands.spawn((
        SceneCamera,
        Camera3d::default(),
        bevy::light::ShadowFilteringMethod::Hardware2x2,
        Transform::from_translation(eye).looking_at(target, Vec3::Y),
    ));
    commands.insert_resource(bevy::light::DirectionalLightShadowMap { size: 1024 });
    let reach = 2.0 * eye.distance(target);
    commands.spawn((
        DirectionalLight {
            shadow_maps_enabled: true,
            illuminance,
            ..default()
        },
        bevy::light::CascadeShadowConfigBuilder {
            num_cascades: 1,
            minimum_distance: 0.01 * reach,
            maximum_distance: reach,
            ..default()
        }
        .build(),
        Transform::from_translation(sun).looking_at(Vec3::ZERO, Vec3::Y),
    ));
}

/// What a script needs to drive the pointer: with a window, its cursor and mouse-button
/// messages (the path a real mouse takes); headless, [`TissuePointer`] directly.
#[derive(SystemParam)]
pub struct ScriptPointer<'w, 's> {
    camera: Query<'w, 's, (&'static Camera, &'static GlobalTransform), With<SceneCamera>>,
    window: Query<'w, 's, (Entity, &'static mut Window), With<PrimaryWindow>>,
    buttons: Res<'w, ButtonInput<MouseButton>>,
    mouse: MessageWriter<'w, MouseButtonInput>,
    pointer: ResMut<'w, TissuePointer>,
}

impl ScriptPointer<'_, '_> {
    /// Puts the cursor over the world point `at` (m) and the left button down or up.
    pub fn drive(&mut self, at: Vec3, pressed: bool) {
        let Ok((camera, eye)) = self.camera.single() else {
            return;
        };
        let screen = camera.world_to_viewport(eye, at).ok();
        if let Ok((entity, mut w)) = self.window.single_mut() {
            if screen.is_some() {
                w.set_cursor_position(screen);
            }
            if pressed != self.buttons.pressed(MouseButton::Left) {
                self.mouse.write(MouseButtonInput {
                    button: MouseButton::Left,
                    state: if pressed {
                        ButtonState::Pressed
                    } else {
                        ButtonState::Released
                    },
                    window: entity,
                });
            }
        } else {
            if screen.is_some() {
                self.pointer.position = screen;
            }
            self.pointer.pressed = pressed;
        }
    }
}

/// `--profile`: where a frame's time goes. The main world's update (`First` to `Last`),
/// and the render world's stages (Bevy's `RenderSystems`: extract commands to the end of
/// bind-group preparation, the render graph — encoding and submitting every pass, the
/// tissue kernels included —, and cleanup, where the tissue plugin paces a CPU running
/// ahead of the GPU) and its frame-to-frame time.
mod profile {
    use super::{Frames, SceneArgs, at_end};
    use bevy::diagnostic::DiagnosticsStore;
    use bevy::prelude::*;
    use bevy::render::diagnostic::RenderDiagnosticsPlugin;
    use bevy::render::{Render, RenderApp, RenderSystems};
    use bevy_tissue::prelude::TissueDiagnostics;
    use std::sync::{Arc, Mutex};
    use std::time::Instant;

    /// Samples (ms) shared by both worlds.
    #[derive(Default)]
    struct Samples {
        main_start: Option<Instant>,
        main: Vec<f64>,
        /// Per frame, the plugin's main-world diagnostics measured in it (ms, 0 when
        /// not): step, contacts, skin.
        tissue: Vec<[f64; 3]>,
        marks: [Option<Instant>; 4],
        last_frame: Option<Instant>,
        prepare: Vec<f64>,
        graph: Vec<f64>,
        cleanup: Vec<f64>,
        render_frame: Vec<f64>,
    }

    #[derive(Resource, Clone, Default)]
    struct Shared(Arc<Mutex<Samples>>);

    fn ms(a: Instant, b: Instant) -> f64 {
        (b - a).as_secs_f64() * 1e3
    }

    pub fn add(app: &mut App) {
        if !app.is_plugin_added::<RenderDiagnosticsPlugin>() {
            app.add_plugins(RenderDiagnosticsPlugin);
        }
        let shared = Shared::default();
        app.insert_resource(shared.clone())
            .add_systems(First, main_start)
            .add_systems(Last, (main_end, report.before(super::finish)));
        if let Some(render) = app.get_sub_app_mut(RenderApp) {
            render.insert_resource(shared).add_systems(
                Render,
                (
                    mark::<0>.in_set(RenderSystems::ExtractCommands),
                    mark::<1>
                        .after(RenderSystems::PrepareBindGroups)
                        .before(RenderSystems::Render),
                    mark::<2>
                        .after(RenderSystems::Render)
                        .before(RenderSystems::Cleanup),
                    mark::<3>.in_set(RenderSystems::PostCleanup),
                ),
            );
        }
    }

    fn main_start(shared: Res<Shared>) {
        if let Ok(mut s) = shared.0.lock() {
            s.main_start = Some(Instant::now());
        }
    }

    fn main_end(shared: Res<Shared>, store: Res<DiagnosticsStore>) {
        if let Ok(mut s) = shared.0.lock()
            && let Some(t) = s.main_start
        {
            s.main.push(ms(t, Instant::now()));
            let this_frame = TissueDiagnostics::ALL.map(|p| {
                store
                    .get_measurement(&p)
                    .filter(|m| m.time >= t)
                    .map_or(0.0, |m| m.value)
            });
            s.tissue.push(this_frame);
        }
    }

    fn mark<const I: usize>(shared: Res<Shared>) {
        let now = Instant::now();
        let Ok(mut s) = shared.0.lock() else { return };
        s.marks[I] = Some(now);
        if I == 0 {
            if let Some(l) = s.last_frame {
                s.render_frame.push(ms(l, now));
            }
            s.last_frame = Some(now);
        }
        if I == 3
            && let [Some(a), Some(b), Some(c), Some(d)] = s.marks
        {
            s.prepare.push(ms(a, b));
            s.graph.push(ms(b, c));
            s.cleanup.push(ms(c, d));
            s.marks = [None; 4];
        }
    }

    fn report(args: Res<SceneArgs>, frames: Res<Frames>, shared: Res<Shared>) {
        if !at_end(&args, &frames) {
            return;
        }
        let Ok(s) = shared.0.lock() else { return };
        let mean = |v: &[f64]| {
            let v = &v[(args.warmup as usize).min(v.len())..];
            if v.is_empty() {
                return f64::NAN;
            }
            v.iter().sum::<f64>() / v.len() as f64
        };
        let part = |i: usize| mean(&s.tissue.iter().map(|t| t[i]).collect::<Vec<_>>());
        println!(
            "profile, mean ms per frame after the warm-up: the plugin's main-world work: \
             steps {:.3} (on the GPU: submit, wait, read back), contact search {:.3}, \
             skinning {:.3}",
            part(0),
            part(1),
            part(2)
        );
        println!(
            "profile, mean ms after the warm-up: main world update {:.3}; render world: \
             frame-to-frame {:.3}, prepare {:.3}, render graph (encode + submit) {:.3}, \
             cleanup (with the tissue plugin's frame pacing) {:.3}",
            mean(&s.main),
            mean(&s.render_frame),
            mean(&s.prepare),
            mean(&s.graph),
            mean(&s.cleanup)
        );
    }
}
