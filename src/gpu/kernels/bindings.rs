//! The one binding table of the simulation kernels ([`TABLE`]), grouped by lifetime, and
//! what is made from it: the WGSL declarations every module starts with
//! ([`compose`]), and each entry point's bind group layouts, holding only the bindings
//! its shader uses (found by naga's analysis of the module, [`Analysis::uses`]).
//!
//! A binding's group is its [`Lifetime`]: per-frame parameters and colliders (group 0),
//! particle state and solver work (group 1), the static model (group 2), and per-dispatch
//! ranges (group 3, uniform windows chosen with a dynamic offset, and the draw path's
//! vertex slab). Its binding number is its position among the table's entries of the
//! same group.
//!
//! Buffers that hold several arrays are indexed from region bases in `Params` (see
//! `bindings.wgsl`), so that no kernel binds more than WebGPU's guaranteed 8 storage
//! buffers per stage (the workgroup-per-body kernels excepted, which are made only where
//! the adapter allows them).

use bevy::render::render_resource::{
    BindGroupLayoutEntry, BindingType, BufferBindingType, ShaderStages,
};

/// How a kernel sees a binding.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Access {
    /// A uniform buffer bound whole.
    Uniform,
    /// A uniform buffer window chosen per dispatch (dynamic offset).
    Dynamic,
    /// A storage buffer the kernels only read.
    Read,
    /// A storage buffer the kernels write.
    ReadWrite,
}

/// How long a binding's buffer lives, which is also its bind group.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Lifetime {
    /// Written every frame: parameters, colliders, draw records (group 0).
    Frame,
    /// Particle state and solver work, changed by every step (group 1).
    State,
    /// The static model: rest data, lists, per-body constants (group 2).
    Model,
    /// Chosen per dispatch: ranges and the vertex slab (group 3).
    Dispatch,
}

impl Lifetime {
    /// Every lifetime, in group order.
    pub const ALL: [Lifetime; 4] = [
        Lifetime::Frame,
        Lifetime::State,
        Lifetime::Model,
        Lifetime::Dispatch,
    ];

    /// The bind group index.
    pub const fn group(self) -> u32 {
        match self {
            Lifetime::Frame => 0,
            Lifetime::State => 1,
            Lifetime::Model => 2,
            Lifetime::Dispatch => 3,
        }
    }
}

/// One binding: its WGSL name and type, its access, its lifetime.
#[derive(Debug, Clone, Copy)]
pub struct Binding {
    /// Variable name in WGSL.
    pub name: &'static str,
    /// WGSL type.
    pub ty: &'static str,
    /// Access.
    pub access: Access,
    /// Lifetime (bind group).
    pub lifetime: Lifetime,
}

const fn b(name: &'static str, ty: &'static str, access: Access, lifetime: Lifetime) -> Binding {
    Binding {
        name,
        ty,
        access,
        lifetime,
    }
}

use Access::{Dynamic, Read, ReadWrite, Uniform};
use Lifetime::{Dispatch, Frame, Model, State};

/// The binding table of the simulation and draw kernels (layout and packing:
/// `src/gpu/buffers.rs` and [`crate::gpu::GpuWorld`]).
pub const TABLE: &[Binding] = &[
    b("params", "Params", Uniform, Frame),
    b(
        "colliders",
        "array<Collider, MAX_COLLIDERS>",
        Uniform,
        Frame,
    ),
    b("draw", "array<DrawBody>", Read, Frame),
    // Positions, then from `p_base` the predicted positions (every level's particles).
    b("x", "array<vec4<f32>>", ReadWrite, State),
    b("v", "array<vec4<f32>>", ReadWrite, State),
    // The contact pass's two halves of positions, then collider displacements, grabs,
    // per-body boxes and flags, grid-sorted points (bases in `params`).
    b("aux", "array<vec4<f32>>", ReadWrite, State),
    b("cstate", "array<ClusterState>", ReadWrite, State),
    b("corr", "array<vec4<f32>>", ReadWrite, State),
    b("contacts", "array<u32>", ReadWrite, State),
    b("scan", "array<atomic<u32>>", ReadWrite, State),
    b("cursor", "array<atomic<u32>>", ReadWrite, State),
    b("cell_of", "array<u32>", ReadWrite, State),
    b("forces", "array<vec4<f32>>", ReadWrite, State),
    b("fgrad", "array<vec4<f32>>", ReadWrite, State),
    b("knn_out", "array<u32>", ReadWrite, State),
    b("status", "array<atomic<u32>>", ReadWrite, State),
    b("spare", "array<u32>", ReadWrite, State),
    // Rest positions and masses, then from `pin_base` the pin targets.
    b("rest", "array<vec4<f32>>", Read, Model),
    b("pinfo", "array<vec4<u32>>", Read, Model),
    b("lists", "array<u32>", Read, Model),
    b("crest", "array<ClusterRest>", Read, Model),
    b("bodies", "array<Body>", Read, Model),
    b("hier", "array<u32>", Read, Model),
    b("vinf", "array<vec4<u32>>", Read, Model),
    b("vwt", "array<vec4<f32>>", Read, Model),
    b("vrest", "array<vec4<f32>>", Read, Model),
    b("adj", "array<u32>", Read, Model),
    b("range", "Range", Dynamic, Dispatch),
    b("level", "ScanLevel", Dynamic, Dispatch),
    b("slab", "array<f32>", ReadWrite, Dispatch),
    b("span", "SkinRange", Dynamic, Dispatch),
];

/// Group and binding number of the table's entry `index`.
pub fn location(index: usize) -> (u32, u32) {
    let me = &TABLE[index];
    let binding = TABLE[..index]
        .iter()
        .filter(|o| o.lifetime == me.lifetime)
        .count() as u32;
    (me.lifetime.group(), binding)
}

/// Index in [`TABLE`] of the binding called `name`.
pub fn index_of(name: &str) -> Option<usize> {
    TABLE.iter().position(|b| b.name == name)
}

/// The WGSL declarations of every binding of [`TABLE`].
pub fn declarations() -> String {
    let mut s = String::from("\n// Bindings (src/gpu/kernels/bindings.rs, TABLE).\n");
    for (i, b) in TABLE.iter().enumerate() {
        let (group, binding) = location(i);
        let space = match b.access {
            Access::Uniform | Access::Dynamic => "uniform",
            Access::Read => "storage, read",
            Access::ReadWrite => "storage, read_write",
        };
        s.push_str(&format!(
            "@group({group}) @binding({binding}) var<{space}> {}: {};\n",
            b.name, b.ty
        ));
    }
    s
}

/// A module's WGSL: `common.wgsl`, the declarations, `bindings.wgsl`, then `parts`.
pub fn compose(parts: &[&str]) -> String {
    let mut s = String::from(include_str!("common.wgsl"));
    s.push_str(&declarations());
    s.push_str(include_str!("bindings.wgsl"));
    for p in parts {
        s.push('\n');
        s.push_str(p);
    }
    s
}

/// naga's analysis of a WGSL module: which bindings each entry point uses.
pub struct Analysis {
    module: naga::Module,
    info: naga::valid::ModuleInfo,
}

impl Analysis {
    /// Parses and validates `source`; the message names the problem where it fails.
    pub fn new(source: &str) -> Result<Self, String> {
        let module = naga::front::wgsl::parse_str(source).map_err(|e| e.emit_to_string(source))?;
        let info = naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::all(),
        )
        .validate(&module)
        .map_err(|e| e.emit_to_string(source))?;
        Ok(Self { module, info })
    }

    fn entry(&self, entry: &str) -> Result<(usize, &naga::EntryPoint), String> {
        self.module
            .entry_points
            .iter()
            .enumerate()
            .find(|(_, ep)| ep.name == entry)
            .ok_or_else(|| format!("no entry point {entry}"))
    }

    /// The [`TABLE`] entries the entry point `entry` uses (statically, through any
    /// function it calls), in table order.
    pub fn uses(&self, entry: &str) -> Result<Vec<usize>, String> {
        let (i, _) = self.entry(entry)?;
        let uses = self.info.get_entry_point(i);
        let mut out = Vec::new();
        for (h, g) in self.module.global_variables.iter() {
            if g.binding.is_none() || uses[h].is_empty() {
                continue;
            }
            let name = g.name.as_deref().unwrap_or("");
            out.push(index_of(name).ok_or_else(|| format!("{entry} binds {name}, not in TABLE"))?);
        }
        out.sort_unstable();
        Ok(out)
    }

    /// Workgroup memory (bytes) the entry point `entry` uses.
    pub fn workgroup_bytes(&self, entry: &str) -> Result<u32, String> {
        let (i, _) = self.entry(entry)?;
        let uses = self.info.get_entry_point(i);
        Ok(self
            .module
            .global_variables
            .iter()
            .filter(|(h, g)| g.space == naga::AddressSpace::WorkGroup && !uses[*h].is_empty())
            .map(|(_, g)| self.module.types[g.ty].inner.size(self.module.to_ctx()))
            .sum())
    }

    /// Invocations per workgroup of the entry point `entry`.
    pub fn invocations(&self, entry: &str) -> Result<u32, String> {
        Ok(self.entry(entry)?.1.workgroup_size.iter().product())
    }
}

/// Storage buffers among the table entries `uses`.
pub fn storage_count(uses: &[usize]) -> u32 {
    uses.iter()
        .filter(|&&i| matches!(TABLE[i].access, Access::Read | Access::ReadWrite))
        .count() as u32
}

/// The layout entry of the table's entry `index`.
pub fn layout_entry(index: usize) -> BindGroupLayoutEntry {
    let b = &TABLE[index];
    let ty = match b.access {
        Access::Uniform | Access::Dynamic => BindingType::Buffer {
            ty: BufferBindingType::Uniform,
            has_dynamic_offset: b.access == Access::Dynamic,
            min_binding_size: None,
        },
        Access::Read | Access::ReadWrite => BindingType::Buffer {
            ty: BufferBindingType::Storage {
                read_only: b.access == Access::Read,
            },
            has_dynamic_offset: false,
            min_binding_size: None,
        },
    };
    BindGroupLayoutEntry {
        binding: location(index).1,
        visibility: ShaderStages::COMPUTE,
        ty,
        count: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_binding_has_one_place() {
        let mut seen = std::collections::HashSet::new();
        for (i, b) in TABLE.iter().enumerate() {
            assert!(seen.insert(location(i)), "{} shares a place", b.name);
            assert_eq!(index_of(b.name), Some(i), "{} twice", b.name);
        }
        assert_eq!(location(index_of("params").unwrap()), (0, 0));
        assert_eq!(location(index_of("x").unwrap()), (1, 0));
        assert_eq!(location(index_of("rest").unwrap()), (2, 0));
        assert_eq!(location(index_of("range").unwrap()), (3, 0));
    }
}
