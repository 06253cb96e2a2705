//! Allocation: the world's buffers by bind group (frame, particle state, static model:
//! the lifetimes of [`kernels::bindings::TABLE`]), their room for bodies appended later
//! ([`Capacity`]), where the arrays that share a buffer start ([`Regions`]), each
//! kernel's bind groups over them ([`KernelBind`]), the adapter-limit checks, and
//! staged uploads.

use crate::core::TissueError;
use crate::core::model::Model;
use crate::core::solver::{SolverSettings, State};
use crate::gpu::buffers::*;
use crate::gpu::kernels;
use bevy::render::render_resource::{
    BindGroup, BindGroupEntry, BindingResource, Buffer, BufferBinding, BufferDescriptor,
    BufferUsages,
};
use bevy::render::renderer::{RenderDevice, RenderQueue};

/// One kernel's bind groups in a world: groups 0–2 (up to the last it uses, empty where
/// it uses nothing), and group 3 where it reads the world's range or scan-level records.
pub struct KernelBind {
    pub(super) fixed: Vec<BindGroup>,
    pub(super) window: Option<BindGroup>,
}

impl KernelBind {
    /// `kernel`'s bind groups over the world's buffers `b` and records.
    pub(super) fn new(
        device: &RenderDevice,
        kernel: &kernels::Kernel,
        b: &Buffers,
        scan_buf: &Buffer,
        lrec_buf: &Buffer,
    ) -> Self {
        let window = |name: &str| -> Option<BindingResource<'_>> {
            let (buffer, size) = match name {
                "level" => (scan_buf, size_of::<u32>() as u64 * 4),
                // The WGSL `Range`: 8 words.
                "range" => (lrec_buf, size_of::<u32>() as u64 * 8),
                _ => return b.named(name).map(|buf| buf.as_entire_binding()),
            };
            Some(BindingResource::Buffer(BufferBinding {
                buffer,
                offset: 0,
                size: std::num::NonZeroU64::new(size),
            }))
        };
        let mut fixed = Vec::new();
        let mut own = None;
        for (g, (layout, uses)) in kernel.groups.iter().enumerate() {
            if g < 3 {
                fixed.push(bind_group(device, kernel.name, layout, uses, &window));
            } else if uses
                .iter()
                .all(|&i| window(kernels::bindings::TABLE[i].name).is_some())
            {
                // Group 3 from the world's own records; the draw kernels' comes with the
                // slab ([`GpuWorld::slab_group`](super::GpuWorld::slab_group)).
                own = Some(bind_group(device, kernel.name, layout, uses, &window));
            }
        }
        Self { fixed, window: own }
    }
}

/// A bind group of `layout` with each of the table entries `uses` bound to the resource
/// `resource` names for it (entries it has none for are left out, and the group is
/// then invalid: a defect the device reports).
pub(super) fn bind_group<'a>(
    device: &RenderDevice,
    label: &str,
    layout: &bevy::render::render_resource::BindGroupLayout,
    uses: &[usize],
    resource: &dyn Fn(&str) -> Option<BindingResource<'a>>,
) -> BindGroup {
    let entries: Vec<BindGroupEntry> = uses
        .iter()
        .filter_map(|&i| {
            let (_, binding) = kernels::bindings::location(i);
            Some(BindGroupEntry {
                binding,
                resource: resource(kernels::bindings::TABLE[i].name)?,
            })
        })
        .collect();
    device.create_bind_group(label, layout, &entries)
}

/// The bind groups that let the draw kernels write into one vertex slab (one per kernel
/// that writes it); made by [`GpuWorld::slab_group`](super::GpuWorld::slab_group).
pub struct SlabGroup {
    pub(super) skin: BindGroup,
    pub(super) normals: BindGroup,
}

/// Storage usage of the world's own buffers (copied between worlds, written by uploads).
const STORAGE: BufferUsages = BufferUsages::STORAGE
    .union(BufferUsages::COPY_DST)
    .union(BufferUsages::COPY_SRC);

/// A buffer holding `bytes` (at least 16 bytes: empty arrays still bind).
pub(super) fn init(
    device: &RenderDevice,
    label: &str,
    bytes: &[u8],
    usage: BufferUsages,
) -> Buffer {
    let mut data = bytes.to_vec();
    if data.len() < 16 {
        data.resize(16, 0);
    }
    device.create_buffer_with_data(&bevy::render::render_resource::BufferInitDescriptor {
        label: Some(label),
        contents: &data,
        usage,
    })
}

/// A zeroed buffer of `bytes` (at least 16).
pub(super) fn zeroed(
    device: &RenderDevice,
    label: &str,
    bytes: u64,
    usage: BufferUsages,
) -> Buffer {
    device.create_buffer(&BufferDescriptor {
        label: Some(label),
        size: bytes.max(16),
        usage,
        mapped_at_creation: false,
    })
}

/// Group 0, written every frame: the parameters, the colliders and the draw records.
pub(super) struct FrameBuffers {
    pub(super) params: Buffer,
    pub(super) colliders: Buffer,
    pub(super) draw: Buffer,
}

impl FrameBuffers {
    /// Room for `bodies` draw records.
    pub(super) fn new(device: &RenderDevice, bodies: u32) -> Self {
        let uniform = BufferUsages::UNIFORM | BufferUsages::COPY_DST;
        Self {
            params: zeroed(
                device,
                "tissue params",
                size_of::<GpuParams>() as u64,
                uniform,
            ),
            colliders: zeroed(
                device,
                "tissue colliders",
                (MAX_COLLIDERS * size_of::<GpuCollider>()) as u64,
                uniform,
            ),
            draw: zeroed(
                device,
                "tissue draw",
                bodies as u64 * size_of::<GpuDrawBody>() as u64,
                STORAGE,
            ),
        }
    }
}

/// What group 1 starts from: the state arrays, with room for appended bodies.
pub(super) struct StateArrays {
    /// Positions, then the predicted positions (the same at the start).
    pub(super) x: Vec<[f32; 4]>,
    /// Velocities.
    pub(super) v: Vec<[f32; 4]>,
    /// The shared scratch ([`Regions`]), grabs included.
    pub(super) aux: Vec<[f32; 4]>,
    /// Cluster states (every level's).
    pub(super) cstate: Vec<GpuClusterState>,
}

impl StateArrays {
    /// `state` of `model` (packed as `packed`) in arrays with room for `particles`
    /// level-0 particles and `total` of all levels, the scratch laid out as `regions`.
    pub(super) fn new(
        model: &Model,
        packed: &Packed,
        state: &State,
        particles: u32,
        total: u64,
        regions: &Regions,
    ) -> Self {
        let (mut x, mut v, mut cstate) = pack_state(state);
        for &src in &packed.hier[..packed.records_base as usize] {
            x.push(x[src as usize]);
        }
        // Room for appended bodies (level 0 only: a world with levels has none).
        x.resize(total as usize, [0.0; 4]);
        v.resize(particles as usize, [0.0; 4]);
        for lv in &model.levels {
            for &b in &lv.model.particle_body {
                cstate.push(GpuClusterState {
                    rot: lv.model.bodies[b as usize].rotation.to_array(),
                    ..Default::default()
                });
            }
        }
        cstate.resize(total as usize, GpuClusterState::default());
        // Grabs: offset in the grasper's frame (m) and the grasper + 1 (0: free), all
        // levels.
        let mut grab: Vec<[f32; 4]> = state.grab.iter().map(grab_record).collect();
        grab.resize(total as usize, [0.0; 4]);
        // The contact pass's two halves of level 0's particles (iterations alternate
        // between them when particle contacts are on), at least every level's (the
        // hierarchy's snapshot); collider displacements; grabs; per-body boxes, flags and
        // near lists (broad.wgsl); grid-sorted points.
        let mut aux = x.clone();
        aux.resize(regions.grab_base as usize, [0.0; 4]);
        aux.extend_from_slice(&grab);
        aux.resize(regions.aux_len as usize, [0.0; 4]);
        let mut xp = x.clone();
        xp.extend_from_slice(&x);
        Self {
            x: xp,
            v,
            aux,
            cstate,
        }
    }
}

/// The sizes of group 1's scratch.
pub(super) struct StateSizes {
    /// Level-0 particles the per-particle scratch has room for.
    pub(super) particles: u64,
    /// Particles of all levels.
    pub(super) total: u64,
    /// Bodies.
    pub(super) bodies: u64,
    /// Contact candidates per particle.
    pub(super) contact_k: u32,
    /// All-particle neighbours per particle.
    pub(super) knn_k: u32,
    /// Candidate store entries per particle.
    pub(super) spare_stride: u32,
    /// Elements of the prefix sum.
    pub(super) scan_len: u32,
    /// Hash buckets.
    pub(super) table: u32,
    /// Entries of the shared scratch (`Regions::aux_len`).
    pub(super) aux: u64,
}

/// A grab as the kernels read it: offset in the grasper's frame (m) and the grasper + 1
/// (0: free).
pub(super) fn grab_record(g: &crate::core::colliders::Grab) -> [f32; 4] {
    let id = if g.collider == u32::MAX {
        0.0
    } else {
        g.collider as f32 + 1.0
    };
    g.offset.extend(id).to_array()
}

/// Group 1, the particle state the steps write.
pub(super) struct StateBuffers {
    pub(super) x: Buffer,
    pub(super) v: Buffer,
    pub(super) aux: Buffer,
    pub(super) cstate: Buffer,
    pub(super) corr: Buffer,
    pub(super) contacts: Buffer,
    pub(super) scan: Buffer,
    pub(super) cursor: Buffer,
    pub(super) cell_of: Buffer,
    pub(super) forces: Buffer,
    pub(super) fgrad: Buffer,
    pub(super) knn_out: Buffer,
    pub(super) status: Buffer,
    pub(super) spare: Buffer,
}

impl StateBuffers {
    /// The buffers holding `a` (or zeroed, of the sizes `z` names, without it: their
    /// contents are copied in afterwards).
    pub(super) fn new(device: &RenderDevice, a: Option<&StateArrays>, z: &StateSizes) -> Self {
        let st = STORAGE;
        let p = z.particles;
        let make = |label: &str, data: Option<&[u8]>, bytes: u64| match data {
            Some(d) => init(device, label, d, st),
            None => zeroed(device, label, bytes, st),
        };
        Self {
            x: make(
                "tissue x",
                a.map(|a| bytemuck::cast_slice(&a.x)),
                2 * z.total * 16,
            ),
            v: make("tissue v", a.map(|a| bytemuck::cast_slice(&a.v)), p * 16),
            aux: make(
                "tissue aux",
                a.map(|a| bytemuck::cast_slice(&a.aux)),
                z.aux * 16,
            ),
            cstate: make(
                "tissue cstate",
                a.map(|a| bytemuck::cast_slice(&a.cstate)),
                z.total * size_of::<GpuClusterState>() as u64,
            ),
            corr: zeroed(device, "tissue corr", z.total * CORR_BYTES, st),
            contacts: unknown_lists(device, "tissue contacts", p * z.contact_k.max(1) as u64, st),
            scan: zeroed(device, "tissue scan", z.scan_len as u64 * 4, st),
            cursor: zeroed(device, "tissue cursor", z.table as u64 * 4, st),
            cell_of: zeroed(device, "tissue cell_of", p * 4, st),
            forces: zeroed(
                device,
                "tissue forces",
                (MAX_COLLIDERS as u64) * (FORCE_GROUPS as u64 + 1) * 16,
                st,
            ),
            fgrad: zeroed(device, "tissue fgrad", p * 48, st),
            knn_out: unknown_lists(device, "tissue knn", p * z.knn_k.max(1) as u64, st),
            status: zeroed(device, "tissue status", z.bodies * 4, st),
            spare: zeroed(
                device,
                "tissue knn spare",
                p * z.spare_stride as u64 * 4,
                st,
            ),
        }
    }
}

/// What group 2 holds: the static model's arrays, with room for appended bodies.
pub(super) struct ModelArrays {
    /// Rest records, then from the pin base the pin targets.
    pub(super) rest: Vec<[f32; 4]>,
    /// Per particle: body, pin slot, inverse-list and member-list starts (and the
    /// sentinel row after the last; the rest of the rows are written by `append`).
    pub(super) pinfo: Vec<[u32; 4]>,
    /// Members from 0, inverse lists from the member room.
    pub(super) lists: Vec<u32>,
    /// Cluster rest data.
    pub(super) crest: Vec<GpuClusterRest>,
    /// Bodies.
    pub(super) bodies: Vec<GpuBody>,
    /// Skin influences, weights and rest vertices.
    pub(super) vinf: Vec<[u32; 4]>,
    pub(super) vwt: Vec<[f32; 4]>,
    pub(super) vrest: Vec<[f32; 4]>,
    /// Normal adjacency: starts (and sentinel) per render vertex of room, then from
    /// `vertex_cap + 1` the triangles' corners.
    pub(super) adj: Vec<u32>,
}

impl ModelArrays {
    /// `packed` (with `state`'s pin targets and the GPU's `bodies`) in arrays with room
    /// for `cap`, `total` particles of all levels.
    pub(super) fn new(
        packed: &Packed,
        state: &State,
        cap: Capacity,
        total: u64,
        bodies: Vec<GpuBody>,
    ) -> Self {
        let mut pins: Vec<[f32; 4]> = state
            .pin_targets
            .iter()
            .map(|p| p.extend(0.0).to_array())
            .collect();
        pins.resize(cap.particles as usize, [0.0; 4]);
        let mut rest = packed.rest.clone();
        rest.resize(total as usize, [0.0; 4]);
        rest.extend_from_slice(&pins);
        let mut pinfo = packed.pinfo.clone();
        pinfo.resize(total as usize + 1, [0; 4]);
        let members = cap.members as usize;
        let mut lists = packed.lists[..packed.inv_offset as usize].to_vec();
        lists.resize(members, 0);
        lists.extend_from_slice(&packed.lists[packed.inv_offset as usize..]);
        lists.resize(2 * members, 0);
        let mut crest = packed.crest.clone();
        crest.resize(total as usize, GpuClusterRest::default());
        let vcap = cap.vertices as usize;
        let (mut vinf, mut vwt, mut vrest) = (
            packed.vinf.clone(),
            packed.vwt.clone(),
            packed.vrest.clone(),
        );
        vinf.resize(vcap, [0; 4]);
        vwt.resize(vcap, [0.0; 4]);
        vrest.resize(vcap, [0.0; 4]);
        let nv = packed.vertex_count();
        let mut adj = packed.adj[..nv + 1].to_vec();
        adj.resize(vcap + 1, 0);
        adj.extend_from_slice(&packed.adj[nv + 1..]);
        adj.resize(vcap + 1 + 3 * cap.triangles as usize, 0);
        Self {
            rest,
            pinfo,
            lists,
            crest,
            bodies,
            vinf,
            vwt,
            vrest,
            adj,
        }
    }
}

/// Group 2, the static model (written once, and where bodies are appended).
pub(super) struct ModelBuffers {
    pub(super) rest: Buffer,
    pub(super) pinfo: Buffer,
    pub(super) lists: Buffer,
    pub(super) crest: Buffer,
    pub(super) bodies: Buffer,
    pub(super) hier: Buffer,
    pub(super) vinf: Buffer,
    pub(super) vwt: Buffer,
    pub(super) vrest: Buffer,
    pub(super) adj: Buffer,
}

/// Entries of group 2's arrays, for buffers made empty (their contents copied in).
pub(super) struct ModelSizes {
    /// Particles (level 0 and the rest of the levels).
    pub(super) total: u64,
    /// Level-0 particles (the pin region).
    pub(super) particles: u64,
    /// Cluster memberships (each of the two list regions).
    pub(super) members: u64,
    /// Bodies.
    pub(super) bodies: u64,
    /// Render vertices.
    pub(super) vertices: u64,
    /// Adjacency triangles.
    pub(super) triangles: u64,
}

impl ModelBuffers {
    /// Empty buffers of the sizes `z` names (no hierarchy tables).
    pub(super) fn zeroed(device: &RenderDevice, z: &ModelSizes) -> Self {
        let st = STORAGE;
        Self {
            rest: zeroed(device, "tissue rest", (z.total + z.particles) * 16, st),
            pinfo: zeroed(device, "tissue pinfo", (z.total + 1) * 16, st),
            lists: zeroed(device, "tissue lists", 2 * z.members * 4, st),
            crest: zeroed(
                device,
                "tissue crest",
                z.total * size_of::<GpuClusterRest>() as u64,
                st,
            ),
            bodies: zeroed(
                device,
                "tissue bodies",
                z.bodies * size_of::<GpuBody>() as u64,
                st,
            ),
            hier: zeroed(device, "tissue hierarchy", 16, st),
            vinf: zeroed(device, "tissue vinf", z.vertices * 16, st),
            vwt: zeroed(device, "tissue vwt", z.vertices * 16, st),
            vrest: zeroed(device, "tissue vrest", z.vertices * 16, st),
            adj: zeroed(
                device,
                "tissue adj",
                (z.vertices + 1 + 3 * z.triangles) * 4,
                st,
            ),
        }
    }

    /// The model's arrays and the hierarchy's tables `hier`.
    pub(super) fn new(device: &RenderDevice, a: &ModelArrays, hier: &[u32]) -> Self {
        let st = STORAGE;
        Self {
            rest: init(device, "tissue rest", bytemuck::cast_slice(&a.rest), st),
            pinfo: init(device, "tissue pinfo", bytemuck::cast_slice(&a.pinfo), st),
            lists: init(device, "tissue lists", bytemuck::cast_slice(&a.lists), st),
            crest: init(device, "tissue crest", bytemuck::cast_slice(&a.crest), st),
            bodies: init(device, "tissue bodies", bytemuck::cast_slice(&a.bodies), st),
            hier: init(device, "tissue hierarchy", bytemuck::cast_slice(hier), st),
            vinf: init(device, "tissue vinf", bytemuck::cast_slice(&a.vinf), st),
            vwt: init(device, "tissue vwt", bytemuck::cast_slice(&a.vwt), st),
            vrest: init(device, "tissue vrest", bytemuck::cast_slice(&a.vrest), st),
            adj: init(device, "tissue adj", bytemuck::cast_slice(&a.adj), st),
        }
    }
}

/// Group 3's records of the world: the prefix sum's levels and grid builds, the ranges,
/// the skinning spans.
pub(super) struct DispatchBuffers {
    pub(super) scan: Buffer,
    pub(super) ranges: Buffer,
    pub(super) spans: Buffer,
}

impl DispatchBuffers {
    pub(super) fn new(device: &RenderDevice, scan: &[GpuScanLevel], ranges: &[GpuRange]) -> Self {
        let uniform = BufferUsages::UNIFORM | BufferUsages::COPY_DST;
        Self {
            scan: init(
                device,
                "tissue scan levels",
                bytemuck::cast_slice(scan),
                uniform,
            ),
            ranges: init(
                device,
                "tissue level ranges",
                bytemuck::cast_slice(ranges),
                uniform,
            ),
            spans: zeroed(
                device,
                "tissue skin ranges",
                (super::MAX_SKIN_RUNS * size_of::<GpuSkinRange>()) as u64,
                uniform,
            ),
        }
    }
}

/// The world's buffers by bind group ([`kernels::bindings::TABLE`]'s lifetimes).
pub(super) struct Buffers {
    pub(super) frame: FrameBuffers,
    pub(super) state: StateBuffers,
    pub(super) model: ModelBuffers,
}

impl Buffers {
    /// The buffer bound as the table's `name` (groups 0–2).
    pub(super) fn named(&self, name: &str) -> Option<&Buffer> {
        let (f, s, m) = (&self.frame, &self.state, &self.model);
        Some(match name {
            "params" => &f.params,
            "colliders" => &f.colliders,
            "draw" => &f.draw,
            "x" => &s.x,
            "v" => &s.v,
            "aux" => &s.aux,
            "cstate" => &s.cstate,
            "corr" => &s.corr,
            "contacts" => &s.contacts,
            "scan" => &s.scan,
            "cursor" => &s.cursor,
            "cell_of" => &s.cell_of,
            "forces" => &s.forces,
            "fgrad" => &s.fgrad,
            "knn_out" => &s.knn_out,
            "status" => &s.status,
            "spare" => &s.spare,
            "rest" => &m.rest,
            "pinfo" => &m.pinfo,
            "lists" => &m.lists,
            "crest" => &m.crest,
            "bodies" => &m.bodies,
            "hier" => &m.hier,
            "vinf" => &m.vinf,
            "vwt" => &m.vwt,
            "vrest" => &m.vrest,
            "adj" => &m.adj,
            _ => return None,
        })
    }
}

/// Where the arrays that share a buffer start (in `vec4` entries; the kernels read the
/// same bases from `Params`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(super) struct Regions {
    /// Predicted positions in `x` (after every level's positions).
    pub(super) p_base: u32,
    /// Pin targets in `rest`.
    pub(super) pin_base: u32,
    /// Collider displacements in `aux` (after the contact pass's two halves).
    pub(super) coldp_base: u32,
    /// Grabs in `aux`.
    pub(super) grab_base: u32,
    /// Per-body boxes, flags and near lists in `aux`.
    pub(super) bounds_base: u32,
    /// Grid-sorted points in `aux`.
    pub(super) sorted_base: u32,
    /// Entries of `aux`.
    pub(super) aux_len: u32,
}

impl Regions {
    /// The regions of a world of `n` level-0 particles, `total` particles of all levels,
    /// `rest` rest records and `bodies` bodies.
    pub(super) fn new(n: u32, total: u32, rest: u32, bodies: u32) -> Self {
        let halves = total.max(2 * n);
        let coldp_base = halves;
        let grab_base = coldp_base + total;
        let bounds_base = grab_base + total;
        let sorted_base = bounds_base + bodies * BOUNDS_PER_BODY;
        Self {
            p_base: total,
            pin_base: rest,
            coldp_base,
            grab_base,
            bounds_base,
            sorted_base,
            aux_len: sorted_base + n,
        }
    }

    /// Writes the region bases, and the room they are laid out for (`cap`: the inverse
    /// lists' start, the per-body and per-vertex layouts), into `p`.
    pub(super) fn write_bases(&self, p: &mut GpuParams, cap: Capacity) {
        p.p_base = self.p_base;
        p.pin_base = self.pin_base;
        p.coldp_base = self.coldp_base;
        p.grab_base = self.grab_base;
        p.bounds_base = self.bounds_base;
        p.sorted_base = self.sorted_base;
        p.inv_offset = cap.members;
        p.body_cap = cap.bodies;
        p.vertex_cap = cap.vertices;
    }
}

/// `vec4` entries per body in the bounds region: min and max, the broad phase's flag,
/// then the near list (`NEAR_SLOTS` indices, four to an entry).
pub(super) const BOUNDS_PER_BODY: u32 = 3 + kernels::broad::NEAR_SLOTS / 4;

/// What a world's buffers have room for. A world made by [`GpuWorld::new`](super::GpuWorld::new) has room for
/// its model and no more; [`GpuWorld::with_room`](super::GpuWorld::with_room) and [`GpuWorld::with_capacity`](super::GpuWorld::with_capacity) leave
/// room for bodies appended later ([`GpuWorld::append`](super::GpuWorld::append)) without a new allocation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Capacity {
    /// Particles (a world with hierarchy levels has room for its own only).
    pub particles: u32,
    /// Bodies.
    pub bodies: u32,
    /// Render vertices.
    pub vertices: u32,
    /// Cluster memberships (entries of the member lists; the inverse lists have as many).
    pub members: u32,
    /// Triangles of the normal adjacency (a render vertex's triangles, three corners each).
    pub triangles: u32,
}

impl Capacity {
    /// The larger of each count.
    pub fn max(self, o: Capacity) -> Capacity {
        Capacity {
            particles: self.particles.max(o.particles),
            bodies: self.bodies.max(o.bodies),
            vertices: self.vertices.max(o.vertices),
            members: self.members.max(o.members),
            triangles: self.triangles.max(o.triangles),
        }
    }

    /// Whether `self` plus `more` fits in `cap`.
    pub(super) fn fits(self, more: Capacity, cap: Capacity) -> bool {
        let fit = |a: u32, b: u32, c: u32| a.checked_add(b).is_some_and(|s| s <= c);
        fit(self.particles, more.particles, cap.particles)
            && fit(self.bodies, more.bodies, cap.bodies)
            && fit(self.vertices, more.vertices, cap.vertices)
            && fit(self.members, more.members, cap.members)
            && fit(self.triangles, more.triangles, cap.triangles)
    }

    pub(super) fn add(self, o: Capacity) -> Capacity {
        Capacity {
            particles: self.particles + o.particles,
            bodies: self.bodies + o.bodies,
            vertices: self.vertices + o.vertices,
            members: self.members + o.members,
            triangles: self.triangles + o.triangles,
        }
    }

    /// `growth` times each count (rounded up), and at least `extra` more.
    pub(super) fn grown(self, growth: f32, extra: Capacity) -> Capacity {
        let g = |a: u32| {
            ((a as f64) * growth.max(1.0) as f64)
                .ceil()
                .min(u32::MAX as f64) as u32
        };
        Capacity {
            particles: g(self.particles),
            bodies: g(self.bodies),
            vertices: g(self.vertices),
            members: g(self.members),
            triangles: g(self.triangles),
        }
        .max(self.add(extra))
    }
}

/// What the packed arrays of a model use, in all and for its largest body.
pub(super) fn packed_use(model: &Model, packed: &Packed) -> (Capacity, Capacity) {
    let nv = packed.vertex_count();
    let mut largest = Capacity::default();
    for (i, b) in model.bodies.iter().enumerate() {
        let (p0, p1) = (b.first as usize, (b.first + b.count) as usize);
        let v0 = packed.vfirst[i] as usize;
        let v1 = v0 + b.skin.rest_vertices.len();
        largest = largest.max(Capacity {
            particles: b.count,
            bodies: 1,
            vertices: (v1 - v0) as u32,
            members: packed.pinfo[p1][3] - packed.pinfo[p0][3],
            triangles: packed.adj[v1] - packed.adj[v0],
        });
    }
    let used = Capacity {
        particles: packed.n0,
        bodies: model.bodies.len() as u32,
        vertices: nv as u32,
        members: packed.inv_offset,
        triangles: packed.adj[nv],
    };
    (used, largest)
}

/// How a new world sizes its buffers.
#[derive(Debug, Clone, Copy)]
pub(super) enum Sizing {
    /// Room for the model only.
    Exact,
    /// `growth` times what the model needs, and at least one more of its largest body.
    Grow(f32),
    /// At least this much.
    AtLeast(Capacity),
}

/// A buffer of `entries` neighbour-list entries, all NONE (no previous search: the
/// first search of each particle starts without a bound).
pub(super) fn unknown_lists(
    device: &RenderDevice,
    label: &str,
    entries: u64,
    usage: BufferUsages,
) -> Buffer {
    let buffer = device.create_buffer(&BufferDescriptor {
        label: Some(label),
        size: (entries * 4).max(16),
        usage,
        mapped_at_creation: true,
    });
    buffer.slice(..).get_mapped_range_mut().slice(..).fill(0xff);
    buffer.unmap();
    buffer
}

/// Checks that arrays of `total` particles (all levels), `n0` level-0 particles, `nv`
/// render vertices, `lists` cluster-list entries and `bodies` bodies fit a device with
/// `limits`: every buffer binding and the per-particle dispatch size.
pub(super) fn check_counts(
    limits: &bevy::render::render_resource::WgpuLimits,
    [n, n0, nv, lists, bodies]: [u64; 5],
    settings: &SolverSettings,
) -> Result<(), TissueError> {
    let contact_k = (settings.contact_neighbours as u64).min(MAX_GPU_K as u64);
    let aux = n.max(2 * n0) + 2 * n + bodies * BOUNDS_PER_BODY as u64 + n0;
    let checks: [(&'static str, u64); 8] = [
        ("positions and predicted positions", 2 * n * 16),
        (
            "particle scratch (contact pass, colliders, grabs, bounds, grid)",
            aux * 16,
        ),
        ("cluster rest data", n * size_of::<GpuClusterRest>() as u64),
        ("cluster corrections", n * CORR_BYTES),
        ("cluster lists", lists * 4),
        ("contact lists", n * contact_k.max(1) * 4),
        (
            "neighbour search candidate store",
            n * (contact_k + SPARE_EXTRA as u64) * 4,
        ),
        ("render vertices", nv * 32),
    ];
    for (what, bytes) in checks {
        check_binding(limits, what, bytes)?;
    }
    let max_groups = limits.max_compute_workgroups_per_dimension as u64;
    let needed = n.div_ceil(WORKGROUP as u64);
    if needed > max_groups {
        return Err(TissueError::GpuLimit {
            what: "workgroups per dispatch (particles / 128)",
            needed,
            limit: max_groups,
        });
    }
    Ok(())
}

/// Buffer writes gathered into one staging buffer and copied in one submission (one
/// mapping instead of one per write).
#[derive(Default)]
pub(super) struct Uploads<'a> {
    pub(super) data: Vec<u8>,
    /// Destination, its byte offset, the source's byte offset, bytes.
    pub(super) copies: Vec<(&'a Buffer, u64, u64, u64)>,
}

impl<'a> Uploads<'a> {
    /// `bytes` (a multiple of 4) to `buffer` at byte `offset`.
    pub(super) fn add(&mut self, buffer: &'a Buffer, offset: u64, bytes: &[u8]) {
        if bytes.is_empty() {
            return;
        }
        self.copies
            .push((buffer, offset, self.data.len() as u64, bytes.len() as u64));
        self.data.extend_from_slice(bytes);
    }

    /// `bytes` to element `index` of `buffer`, whose elements are `stride` bytes.
    pub(super) fn put(&mut self, buffer: &'a Buffer, index: u32, bytes: &[u8], stride: usize) {
        self.add(buffer, index as u64 * stride as u64, bytes);
    }

    pub(super) fn submit(self, device: &RenderDevice, queue: &RenderQueue) {
        if self.copies.is_empty() {
            return;
        }
        let staging =
            device.create_buffer_with_data(&bevy::render::render_resource::BufferInitDescriptor {
                label: Some("tissue append"),
                contents: &self.data,
                usage: BufferUsages::COPY_SRC,
            });
        let mut enc = device.create_command_encoder(&Default::default());
        for (dst, at, from, bytes) in self.copies {
            enc.copy_buffer_to_buffer(&staging, from, dst, at, bytes);
        }
        queue.submit([enc.finish()]);
    }
}

/// A [`TissueError::GpuLimit`] where a buffer of `bytes` cannot be bound on a device
/// with `limits`.
pub(super) fn check_binding(
    limits: &bevy::render::render_resource::WgpuLimits,
    what: &'static str,
    bytes: u64,
) -> Result<(), TissueError> {
    let limit = limits
        .max_storage_buffer_binding_size
        .min(limits.max_buffer_size);
    if bytes > limit {
        return Err(TissueError::GpuLimit {
            what,
            needed: bytes,
            limit,
        });
    }
    Ok(())
}
