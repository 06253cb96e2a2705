//! What the Vulkan driver made of each compute kernel: registers per thread and the
//! other statistics it reports through `VK_KHR_pipeline_executable_properties` (NVIDIA
//! reports the register count; it bounds how many workgroups an SM runs at once, see
//! BENCHMARKS.md, "The 1,000-body step as the plugin runs it").
//!
//! Each entry point is translated to SPIR-V by naga with the options wgpu 29 uses on a
//! Vulkan 1.3 device with `robustBufferAccess2` (index bounds checks, loop bounding,
//! native workgroup-memory zeroing) and compiled by the driver in a pipeline of its own,
//! outside wgpu (wgpu does not enable the extension).
//!
//! ```text
//! cargo run --release --example kernel_stats                      # every kernel
//! cargo run --release --example kernel_stats -- --only body       # entry points whose name contains "body"
//! cargo run --release --example kernel_stats -- --wgsl f.wgsl     # a WGSL file's entry points (experiments)
//! cargo run --release --example kernel_stats -- --no-loop-bounding --unchecked
//! ```
//!
//! `--no-loop-bounding` leaves out naga's loop counters, `--unchecked` its index clamps
//! (what wgpu's `ShaderRuntimeChecks` turn off for trusted modules), `--no-zero-init` the
//! zeroing of workgroup memory (`PipelineCompilationOptions::zero_initialize_workgroup_memory`).
//! A driver without the extension (lavapipe has it or not, by version) gets a message
//! and the program exits with 0 after translating every kernel to SPIR-V (so the
//! translation itself is checked).
#[path = "support/bench.rs"]
mod bench;

use ash::vk;
use bevy_tissue::gpu::kernels::{
    body, broad, cluster, forces, gather, grid, hierarchy, integrate, knn, skin,
};
use std::ffi::CString;

/// How naga translates: the options wgpu 29's Vulkan backend passes on such a device.
struct Translate {
    bounds_checks: bool,
    loop_bounding: bool,
    zero_init: bool,
}

impl Translate {
    fn options(&self) -> naga::back::spv::Options<'static> {
        use naga::proc::{BoundsCheckPolicies, BoundsCheckPolicy};
        let index = if self.bounds_checks {
            BoundsCheckPolicy::Restrict
        } else {
            BoundsCheckPolicy::Unchecked
        };
        naga::back::spv::Options {
            lang_version: (1, 6),
            flags: naga::back::spv::WriterFlags::LABEL_VARYINGS
                | naga::back::spv::WriterFlags::FORCE_POINT_SIZE,
            // The identity map (set = group, binding = binding), as wgpu's layouts give.
            fake_missing_bindings: true,
            bounds_check_policies: BoundsCheckPolicies {
                index,
                // robustBufferAccess2 bounds the buffers in hardware.
                buffer: BoundsCheckPolicy::Unchecked,
                image_load: BoundsCheckPolicy::Unchecked,
                binding_array: BoundsCheckPolicy::Unchecked,
            },
            zero_initialize_workgroup_memory: if self.zero_init {
                naga::back::spv::ZeroInitializeWorkgroupMemoryMode::Native
            } else {
                naga::back::spv::ZeroInitializeWorkgroupMemoryMode::None
            },
            force_loop_bounding: self.loop_bounding,
            ..Default::default()
        }
    }
}

/// One module's entry point, translated.
struct Entry {
    module: String,
    entry: String,
    spirv: Vec<u32>,
    /// Descriptor types per group (index: binding), for the pipeline layout.
    groups: Vec<Vec<Option<vk::DescriptorType>>>,
}

fn translate(
    name: &str,
    src: &str,
    t: &Translate,
    only: Option<&str>,
) -> Result<Vec<Entry>, String> {
    let module = naga::front::wgsl::parse_str(src)
        .map_err(|e| format!("{name}: {}", e.emit_to_string(src)))?;
    let info = naga::valid::Validator::new(
        naga::valid::ValidationFlags::all(),
        naga::valid::Capabilities::all(),
    )
    .validate(&module)
    .map_err(|e| format!("{name}: {}", e.emit_to_string(src)))?;
    let mut groups: Vec<Vec<Option<vk::DescriptorType>>> = Vec::new();
    for (_, g) in module.global_variables.iter() {
        let Some(rb) = &g.binding else { continue };
        let ty = match g.space {
            naga::AddressSpace::Uniform if rb.group > 0 => {
                vk::DescriptorType::UNIFORM_BUFFER_DYNAMIC
            }
            naga::AddressSpace::Uniform => vk::DescriptorType::UNIFORM_BUFFER,
            naga::AddressSpace::Storage { .. } => vk::DescriptorType::STORAGE_BUFFER,
            _ => {
                return Err(format!(
                    "{name}: binding {rb:?} is neither a uniform nor a storage buffer"
                ));
            }
        };
        let (gi, bi) = (rb.group as usize, rb.binding as usize);
        if groups.len() <= gi {
            groups.resize(gi + 1, Vec::new());
        }
        if groups[gi].len() <= bi {
            groups[gi].resize(bi + 1, None);
        }
        groups[gi][bi] = Some(ty);
    }
    let options = t.options();
    let mut out = Vec::new();
    for ep in &module.entry_points {
        if only.is_some_and(|o| !ep.name.contains(o) && !name.contains(o)) {
            continue;
        }
        let pipeline = naga::back::spv::PipelineOptions {
            shader_stage: ep.stage,
            entry_point: ep.name.clone(),
        };
        let spirv = naga::back::spv::write_vec(&module, &info, &options, Some(&pipeline))
            .map_err(|e| format!("{name}/{}: {e}", ep.name))?;
        out.push(Entry {
            module: name.to_string(),
            entry: ep.name.clone(),
            spirv,
            groups: groups.clone(),
        });
    }
    Ok(out)
}

/// The crate's kernel modules (name, WGSL source).
fn kernel_sources() -> Vec<(String, String)> {
    let mut v: Vec<(String, String)> = [
        ("integrate", integrate::source()),
        ("grid", grid::source()),
        ("cluster", cluster::source()),
        ("gather", gather::source()),
        ("body", body::source()),
        ("hierarchy", hierarchy::source()),
        ("forces", forces::source()),
        ("broad", broad::source()),
        ("skin", skin::source()),
    ]
    .into_iter()
    .map(|(n, s)| (n.to_string(), s))
    .collect();
    for warm in [false, true] {
        for slots in knn::SLOT_COUNTS {
            let tag = if warm { "warm" } else { "cold" };
            v.push((format!("knn{slots}-{tag}"), knn::source(slots, warm)));
        }
    }
    v
}

/// The driver side: a device with the extension, and a pipeline per entry point.
struct Driver {
    _entry: ash::Entry,
    instance: ash::Instance,
    device: ash::Device,
    exec: ash::khr::pipeline_executable_properties::Device,
    name: String,
}

impl Driver {
    /// A device on the first adapter (a discrete GPU first) that has the extension.
    fn new() -> Result<Self, String> {
        // SAFETY: loads the system's Vulkan loader; the calls below follow the Vulkan
        // spec's valid usage (structures built by ash's builders, handles from this
        // instance), and every object is destroyed before the device and instance.
        unsafe {
            let entry = ash::Entry::load().map_err(|e| format!("no Vulkan loader: {e}"))?;
            let app = vk::ApplicationInfo::default().api_version(vk::API_VERSION_1_3);
            let instance = entry
                .create_instance(
                    &vk::InstanceCreateInfo::default().application_info(&app),
                    None,
                )
                .map_err(|e| format!("vkCreateInstance: {e}"))?;
            let mut pds = instance
                .enumerate_physical_devices()
                .map_err(|e| format!("no adapter: {e}"))?;
            pds.sort_by_key(|&pd| {
                (instance.get_physical_device_properties(pd).device_type
                    != vk::PhysicalDeviceType::DISCRETE_GPU) as u8
            });
            let ext = ash::khr::pipeline_executable_properties::NAME;
            let mut names = Vec::new();
            for pd in pds {
                let props = instance.get_physical_device_properties(pd);
                let name = props
                    .device_name_as_c_str()
                    .map(|c| c.to_string_lossy().into_owned())
                    .unwrap_or_default();
                let has = instance
                    .enumerate_device_extension_properties(pd)
                    .unwrap_or_default()
                    .iter()
                    .any(|e| e.extension_name_as_c_str() == Ok(ext));
                if !has || props.api_version < vk::API_VERSION_1_3 {
                    names.push(name);
                    continue;
                }
                let Some(queue) = instance
                    .get_physical_device_queue_family_properties(pd)
                    .iter()
                    .position(|q| q.queue_flags.contains(vk::QueueFlags::COMPUTE))
                else {
                    continue;
                };
                let mut f13 = vk::PhysicalDeviceVulkan13Features::default();
                let mut f2 = vk::PhysicalDeviceFeatures2::default().push_next(&mut f13);
                instance.get_physical_device_features2(pd, &mut f2);
                let zero = f13.shader_zero_initialize_workgroup_memory;
                let mut want13 = vk::PhysicalDeviceVulkan13Features::default()
                    .shader_zero_initialize_workgroup_memory(zero == vk::TRUE);
                let mut want_exec =
                    vk::PhysicalDevicePipelineExecutablePropertiesFeaturesKHR::default()
                        .pipeline_executable_info(true);
                let prio = [1.0f32];
                let qci = [vk::DeviceQueueCreateInfo::default()
                    .queue_family_index(queue as u32)
                    .queue_priorities(&prio)];
                let exts = [ext.as_ptr()];
                let dci = vk::DeviceCreateInfo::default()
                    .queue_create_infos(&qci)
                    .enabled_extension_names(&exts)
                    .push_next(&mut want13)
                    .push_next(&mut want_exec);
                let device = instance
                    .create_device(pd, &dci, None)
                    .map_err(|e| format!("vkCreateDevice on {name}: {e}"))?;
                let exec =
                    ash::khr::pipeline_executable_properties::Device::new(&instance, &device);
                return Ok(Self {
                    _entry: entry,
                    instance,
                    device,
                    exec,
                    name,
                });
            }
            instance.destroy_instance(None);
            Err(format!(
                "no adapter with Vulkan 1.3 and VK_KHR_pipeline_executable_properties (found: {})",
                names.join(", ")
            ))
        }
    }

    /// The driver's statistics of each executable of `e`'s pipeline, as (name, value).
    fn stats(&self, e: &Entry) -> Result<Vec<(String, String)>, String> {
        // SAFETY: as in `new`; every object created here is destroyed before returning.
        unsafe {
            let d = &self.device;
            let mut set_layouts = Vec::new();
            for g in &e.groups {
                let bindings: Vec<_> = g
                    .iter()
                    .enumerate()
                    .filter_map(|(b, t)| {
                        t.map(|t| {
                            vk::DescriptorSetLayoutBinding::default()
                                .binding(b as u32)
                                .descriptor_type(t)
                                .descriptor_count(1)
                                .stage_flags(vk::ShaderStageFlags::COMPUTE)
                        })
                    })
                    .collect();
                let l = d
                    .create_descriptor_set_layout(
                        &vk::DescriptorSetLayoutCreateInfo::default().bindings(&bindings),
                        None,
                    )
                    .map_err(|err| format!("set layout: {err}"))?;
                set_layouts.push(l);
            }
            let layout = d
                .create_pipeline_layout(
                    &vk::PipelineLayoutCreateInfo::default().set_layouts(&set_layouts),
                    None,
                )
                .map_err(|err| format!("pipeline layout: {err}"))?;
            let module = d
                .create_shader_module(&vk::ShaderModuleCreateInfo::default().code(&e.spirv), None)
                .map_err(|err| format!("shader module: {err}"))?;
            let entry = CString::new(e.entry.clone()).map_err(|err| err.to_string())?;
            let info = vk::ComputePipelineCreateInfo::default()
                .flags(vk::PipelineCreateFlags::CAPTURE_STATISTICS_KHR)
                .stage(
                    vk::PipelineShaderStageCreateInfo::default()
                        .stage(vk::ShaderStageFlags::COMPUTE)
                        .module(module)
                        .name(&entry),
                )
                .layout(layout);
            let result = d.create_compute_pipelines(vk::PipelineCache::null(), &[info], None);
            let mut out = Vec::new();
            let mut err = None;
            match result {
                Ok(pipes) => {
                    let p = pipes[0];
                    let execs = self
                        .exec
                        .get_pipeline_executable_properties(
                            &vk::PipelineInfoKHR::default().pipeline(p),
                        )
                        .unwrap_or_default();
                    for i in 0..execs.len() as u32 {
                        let info = vk::PipelineExecutableInfoKHR::default()
                            .pipeline(p)
                            .executable_index(i);
                        for s in self
                            .exec
                            .get_pipeline_executable_statistics(&info)
                            .unwrap_or_default()
                        {
                            let name = s
                                .name_as_c_str()
                                .map(|c| c.to_string_lossy().into_owned())
                                .unwrap_or_default();
                            let value = match s.format {
                                vk::PipelineExecutableStatisticFormatKHR::BOOL32 => {
                                    (s.value.b32 != 0).to_string()
                                }
                                vk::PipelineExecutableStatisticFormatKHR::INT64 => {
                                    s.value.i64.to_string()
                                }
                                vk::PipelineExecutableStatisticFormatKHR::UINT64 => {
                                    s.value.u64.to_string()
                                }
                                vk::PipelineExecutableStatisticFormatKHR::FLOAT64 => {
                                    format!("{:.3}", s.value.f64)
                                }
                                _ => "?".to_string(),
                            };
                            out.push((name, value));
                        }
                    }
                    d.destroy_pipeline(p, None);
                }
                Err((_, e2)) => err = Some(format!("vkCreateComputePipelines: {e2}")),
            }
            d.destroy_shader_module(module, None);
            d.destroy_pipeline_layout(layout, None);
            for l in set_layouts {
                d.destroy_descriptor_set_layout(l, None);
            }
            match err {
                Some(e) => Err(e),
                None => Ok(out),
            }
        }
    }
}

impl Drop for Driver {
    fn drop(&mut self) {
        // SAFETY: no object of the device is alive (each `stats` call destroys its own).
        unsafe {
            self.device.destroy_device(None);
            self.instance.destroy_instance(None);
        }
    }
}

fn main() {
    let args = bench::Args::new();
    if args.flag("--help") {
        println!(
            "kernel_stats [--only TEXT] [--wgsl FILE]... [--no-loop-bounding] [--unchecked] [--no-zero-init]"
        );
        return;
    }
    let t = Translate {
        bounds_checks: !args.flag("--unchecked"),
        loop_bounding: !args.flag("--no-loop-bounding"),
        zero_init: !args.flag("--no-zero-init"),
    };
    let only = args.text("--only").cloned();
    let files = args.all("--wgsl");
    let sources: Vec<(String, String)> = if files.is_empty() {
        kernel_sources()
    } else {
        files
            .iter()
            .map(|f| match std::fs::read_to_string(f) {
                Ok(s) => (f.clone(), s),
                Err(e) => {
                    eprintln!("{f}: {e}");
                    std::process::exit(2)
                }
            })
            .collect()
    };
    let mut entries = Vec::new();
    for (name, src) in &sources {
        match translate(name, src, &t, only.as_deref()) {
            Ok(mut e) => entries.append(&mut e),
            Err(e) => {
                eprintln!("{e}");
                std::process::exit(1)
            }
        }
    }
    println!(
        "translated {} entry points (bounds checks {}, loop bounding {}, workgroup zeroing {})",
        entries.len(),
        t.bounds_checks,
        t.loop_bounding,
        t.zero_init
    );
    let driver = match Driver::new() {
        Ok(d) => d,
        Err(e) => {
            println!("no statistics: {e}");
            return;
        }
    };
    println!("adapter: {}\n", driver.name);
    println!("| module | entry point | SPIR-V words | driver statistics |");
    println!("|---|---|---|---|");
    for e in &entries {
        let stats = match driver.stats(e) {
            Ok(s) => s
                .iter()
                .map(|(n, v)| format!("{n} {v}"))
                .collect::<Vec<_>>()
                .join("; "),
            Err(err) => err,
        };
        println!(
            "| {} | {} | {} | {} |",
            e.module,
            e.entry,
            e.spirv.len(),
            stats
        );
    }
}
