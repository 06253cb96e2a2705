//! The GPU memory layout of a batched [`Model`]: `#[repr(C)]` mirrors of the WGSL
//! structs in `kernels/common.wgsl`, and [`Packed`], the host-side arrays an upload
//! copies (built without a device, so the packing is testable on the CPU).
//!
//! Every body of the world lives in the same arrays (one dispatch per kernel for all
//! bodies). Particles keep the core's order: Morton (Z-curve) order inside each
//! body, which is the spatial reordering the kernels' gathers rely on for coherent reads.

use crate::core::TissueError;
use crate::core::colliders::{Collider, ColliderShape, GraspMode};
use crate::core::constraints::iteration_stiffness;
use crate::core::model::{Material, Model};
use crate::core::skin::SKIN_INFLUENCES;
use crate::core::solver::{SolverSettings, State};
use bytemuck::{Pod, Zeroable};
use glam::{Mat3, Quat, Vec3};

/// "No index" marker (`u32::MAX`), as in the kernels.
pub const NONE: u32 = u32::MAX;
/// Most colliders in one world (the size of the collider uniform array).
pub const MAX_COLLIDERS: usize = 128;
/// Workgroups per collider in the first stage of the force reduction.
pub const FORCE_GROUPS: u32 = 64;
/// Threads per workgroup of the per-particle kernels.
pub const WORKGROUP: u32 = 128;
/// Elements per block of the prefix sum.
pub const SCAN_BLOCK: u32 = 1024;
/// Largest K of the GPU neighbour search.
pub const MAX_GPU_K: u32 = 64;
/// Bytes of one cluster's correction in the `corr` buffer (three `vec4<f32>`; layout in
/// `kernels/common.wgsl`, `CORR_STRIDE`).
pub const CORR_BYTES: u64 = 48;

/// Per-step constants (`Params` in WGSL).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, Default)]
pub struct GpuParams {
    /// Gravity, m/s² (xyz).
    pub gravity: [f32; 4],
    /// Particles.
    pub n: u32,
    /// Colliders in use.
    pub n_colliders: u32,
    /// Rotation-extraction iterations.
    pub rot_iters: u32,
    /// 1 when particle contacts run as their own pass.
    pub contacts: u32,
    /// Substep h, s.
    pub h: f32,
    /// h², s².
    pub h2: f32,
    /// Velocity kept after damping, `max(0, 1 − damping·h)`.
    pub keep: f32,
    /// Jacobi relaxation ω.
    pub omega: f32,
    /// Start of the inverse lists in the `lists` buffer.
    pub inv_offset: u32,
    /// Contact candidates per particle.
    pub contact_k: u32,
    /// Render vertices.
    pub n_vertices: u32,
    /// 1 / substeps.
    pub inv_substeps: f32,
    /// Grid cell edge, m.
    pub grid_cell: f32,
    /// Hash buckets (power of two).
    pub grid_table: u32,
    /// A particle faster than this counts as diverged, m/s.
    pub max_speed: f32,
    /// Largest particle radius, m.
    pub max_radius: f32,
    /// K of the unfiltered neighbour search.
    pub knn_k: u32,
    /// Bodies.
    pub n_bodies: u32,
    /// Grid cell edge of the all-particle search, m.
    pub knn_cell: f32,
    /// Entries per particle of the neighbour search's candidate store (`spare`): the
    /// larger of the two searches' K, plus [`SPARE_EXTRA`].
    pub spare_stride: u32,
    /// Jacobi iterations per substep (`body.wgsl`'s `body_substep` runs them all).
    pub iterations: u32,
    /// The contact broad phase's reach, m: [`crate::core::knn::contact_reach_bound`] of
    /// the largest particle radius.
    pub contact_reach: f32,
    /// Jacobi relaxation of the particle contacts
    /// ([`crate::core::solver::SolverSettings::contact_relaxation`]).
    pub contact_omega: f32,
    /// First predicted position in the positions buffer (after every level's positions).
    pub p_base: u32,
    /// First pin target in the rest buffer.
    pub pin_base: u32,
    /// First collider displacement in the `aux` buffer.
    pub coldp_base: u32,
    /// First grab in the `aux` buffer.
    pub grab_base: u32,
    /// First per-body box in the `aux` buffer.
    pub bounds_base: u32,
    /// First grid-sorted point in the `aux` buffer.
    pub sorted_base: u32,
    /// Bodies the per-body arrays have room for (the bounds region's layout in `aux`
    /// depends on it; [`crate::gpu::world::Capacity::bodies`]).
    pub body_cap: u32,
    /// Render vertices the vertex arrays have room for (the normal adjacency's triangle
    /// corners follow its `vertex_cap + 1` starts).
    pub vertex_cap: u32,
    /// Padding to the WGSL struct's 16-byte multiple.
    pub pad: u32,
}

/// Candidates beyond K that a warm neighbour search may set aside before it falls back to
/// inserting while it scans (`knn.wgsl`).
pub const SPARE_EXTRA: u32 = 48;

/// Per-body constants (`Body` in WGSL).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, Default)]
pub struct GpuBody {
    /// 0: shape matching, 1: hyperelastic.
    pub kind: u32,
    /// First particle.
    pub first: u32,
    /// Particles.
    pub count: u32,
    /// 1 while the body sleeps (the kernels skip it), else 0; written by
    /// [`crate::gpu::GpuWorld::set_asleep`].
    pub asleep: u32,
    /// Shape matching: per-iteration stiffness.
    pub k_iter: f32,
    /// Shear modulus μ, Pa.
    pub mu: f32,
    /// Lamé λ, Pa.
    pub lambda: f32,
    /// Lattice spacing, m.
    pub spacing: f32,
    /// Particle radius, m.
    pub radius: f32,
    /// 1 where level 0 of the body is solved by `body.wgsl` (a workgroup per body), which
    /// the cluster and gather kernels then skip; written by [`crate::gpu::GpuWorld`].
    pub in_workgroup: u32,
    /// Padding.
    pub pad1: [f32; 2],
}

/// Per-cluster rest data (`ClusterRest` in WGSL; matrices as three padded columns).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, Default)]
pub struct GpuClusterRest {
    /// Rest centre of mass (m) and total mass (kg).
    pub com_mass: [f32; 4],
    /// `A_qq⁻¹`.
    pub aqq: [[f32; 4]; 3],
    /// Split-mass metric `W`.
    pub w: [[f32; 4]; 3],
    /// Eigenvectors of `W`.
    pub basis: [[f32; 4]; 3],
    /// Eigenvalues of `W` and the cluster volume (m³).
    pub values_vol: [f32; 4],
    /// Jacobi weight `1/s_c` in x.
    pub weight: [f32; 4],
}

/// Per-cluster state (`ClusterState` in WGSL).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, Default)]
pub struct GpuClusterState {
    /// Warm-start rotation (quaternion xyzw).
    pub rot: [f32; 4],
    /// λ_H and the diagonal of Λ.
    pub lam0: [f32; 4],
    /// Off-diagonal of Λ.
    pub lam1: [f32; 4],
}

/// One collider (`Collider` in WGSL).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, Default)]
pub struct GpuCollider {
    /// Kind (0 plane, 1 sphere, 2 capsule, 3 box, 4 grasper), friction, grasper mode (0
    /// open, 1 capture, 2 hold).
    pub kind_fr: [f32; 4],
    /// Position, m.
    pub pos: [f32; 4],
    /// Orientation (quaternion).
    pub rot: [f32; 4],
    /// Shape parameters, m.
    pub shape: [f32; 4],
    /// Velocity, m/s.
    pub vel: [f32; 4],
}

/// `colliders` in their GPU form, or an error naming `what` when there are more than
/// `max` (the size of the kernels' collider array).
pub fn pack_colliders(
    colliders: &[Collider],
    max: usize,
    what: &'static str,
) -> Result<Vec<GpuCollider>, TissueError> {
    if colliders.len() > max {
        return Err(TissueError::InvalidParameter {
            name: "colliders",
            value: colliders.len().to_string(),
            expected: what,
        });
    }
    Ok(colliders.iter().map(GpuCollider::from_core).collect())
}

impl GpuCollider {
    /// The GPU form of a core collider.
    pub fn from_core(c: &Collider) -> Self {
        // Grasper mode: 0 open, 1 capture, 2 hold.
        let (kind, shape, mode) = match c.shape {
            ColliderShape::Plane => (0.0, [0.0; 4], 0.0),
            ColliderShape::Sphere { radius } => (1.0, [radius, 0.0, 0.0, 0.0], 0.0),
            ColliderShape::Capsule {
                half_length,
                radius,
            } => (2.0, [half_length, radius, 0.0, 0.0], 0.0),
            ColliderShape::Cuboid { half_extents } => {
                (3.0, half_extents.extend(0.0).to_array(), 0.0)
            }
            ColliderShape::Grasper { radius, mode } => {
                let mode = match mode {
                    GraspMode::Open => 0.0,
                    GraspMode::Capture => 1.0,
                    GraspMode::Hold => 2.0,
                };
                (4.0, [radius, 0.0, 0.0, 0.0], mode)
            }
        };
        Self {
            kind_fr: [kind, c.friction, mode, 0.0],
            pos: c.position.extend(0.0).to_array(),
            rot: c.rotation.to_array(),
            shape,
            vel: c.velocity.extend(0.0).to_array(),
        }
    }
}

/// Per body, per frame: where and how its surface is drawn (`DrawBody` in WGSL).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, Default)]
pub struct GpuDrawBody {
    /// Rows of the world → entity-local 3×4 affine map.
    pub rows: [[f32; 4]; 3],
    /// First float of the body's vertices in the vertex slab.
    pub vbase: u32,
    /// First render vertex of the body (global).
    pub vfirst: u32,
    /// Floats per vertex in the slab.
    pub stride: u32,
    /// Padding.
    pub pad: u32,
}

impl GpuDrawBody {
    /// Draw record for a body whose entity has the world transform `world_from_local`
    /// (an affine map), with its vertices at float `vbase` of a slab of `stride` floats
    /// per vertex.
    pub fn new(world_from_local: glam::Affine3A, vbase: u32, vfirst: u32, stride: u32) -> Self {
        let inv = world_from_local.inverse();
        let m = Mat3::from(inv.matrix3);
        let t = Vec3::from(inv.translation);
        let rows = [
            [m.x_axis.x, m.y_axis.x, m.z_axis.x, t.x],
            [m.x_axis.y, m.y_axis.y, m.z_axis.y, t.y],
            [m.x_axis.z, m.y_axis.z, m.z_axis.z, t.z],
        ];
        Self {
            rows,
            vbase,
            vfirst,
            stride,
            pad: 0,
        }
    }
}

/// Parameters of one level of the prefix sum (`ScanLevel` in WGSL), padded to 256 bytes
/// (the dynamic-offset alignment).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct GpuScanLevel {
    /// First element of this level in the scan buffer.
    pub offset: u32,
    /// Elements at this level.
    pub count: u32,
    /// Where this level's block sums go.
    pub sums: u32,
    /// Grid cell edge of a build (read by the count and scatter kernels), m.
    pub cell: f32,
    /// Padding.
    pub pad: [u32; 60],
}

/// Vertex range of one skin dispatch (`SkinRange` in WGSL), padded to 256 bytes.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct GpuSkinRange {
    /// First render vertex.
    pub begin: u32,
    /// One past the last.
    pub end: u32,
    /// Padding.
    pub pad: [u32; 62],
}

fn col4(v: Vec3) -> [f32; 4] {
    v.extend(0.0).to_array()
}

fn mat4x3(m: &Mat3) -> [[f32; 4]; 3] {
    [col4(m.x_axis), col4(m.y_axis), col4(m.z_axis)]
}

/// Host-side arrays of a model, in upload order.
#[derive(Debug, Clone, Default)]
pub struct Packed {
    /// Rest position (m) and mass (kg) per particle.
    pub rest: Vec<[f32; 4]>,
    /// `(body, pin slot or NONE, inverse-list start, cluster start)` per particle, plus a
    /// sentinel row.
    pub pinfo: Vec<[u32; 4]>,
    /// Cluster members, then the inverse lists (from [`Packed::inv_offset`]).
    pub lists: Vec<u32>,
    /// Where the inverse lists start in `lists`.
    pub inv_offset: u32,
    /// Cluster rest data.
    pub crest: Vec<GpuClusterRest>,
    /// Per-body constants.
    pub bodies: Vec<GpuBody>,
    /// Skin influences per render vertex (global particle indices).
    pub vinf: Vec<[u32; 4]>,
    /// Skin weights per render vertex.
    pub vwt: Vec<[f32; 4]>,
    /// Rest vertex (body frame, m) with the body index (bits) in w.
    pub vrest: Vec<[f32; 4]>,
    /// Normal adjacency: per render vertex a start (plus sentinel), then triangle corners.
    pub adj: Vec<u32>,
    /// First render vertex of each body.
    pub vfirst: Vec<u32>,
    /// Largest particle radius, m.
    pub max_radius: f32,
    /// Largest lattice spacing, m.
    pub max_spacing: f32,
    /// Particles of level 0 (the coarse levels' particles follow them in the particle
    /// arrays).
    pub n0: u32,
    /// The hierarchy's coarse levels, level 1 first.
    pub levels: Vec<PackedLevel>,
    /// Hierarchy tables: the level-0 index of each coarse particle (coarse particle `g`
    /// at `g − n0`), then the prolongation records from [`Packed::records_base`], 9 words
    /// each: a fine particle's level-0 index, four parents' level-0 indices, four weights
    /// (f32 bits; unused parents have weight 0).
    pub hier: Vec<u32>,
    /// Where the prolongation records start in `hier`.
    pub records_base: u32,
}

/// Where one coarse level lives in the packed arrays.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct PackedLevel {
    /// First particle (and cluster) of the level in the particle arrays.
    pub first: u32,
    /// Particles of the level.
    pub count: u32,
    /// First prolongation record of the level.
    pub rec_first: u32,
    /// Prolongation records of the level (the finer level's particles not on it).
    pub rec_count: u32,
    /// First multiplier-transfer record of the level (same 9-word layout: the finer
    /// cluster, four of this level's clusters, four weights).
    pub tr_first: u32,
    /// Multiplier-transfer records (one per finer-level cluster).
    pub tr_count: u32,
}

/// Words per prolongation record in [`Packed::hier`].
pub const RECORD_WORDS: u32 = 9;

impl Packed {
    /// Packs `model` for the GPU; `settings` fixes the per-iteration stiffness of shape
    /// matching.
    pub fn new(model: &Model, settings: &SolverSettings) -> Self {
        let n = model.particle_count();
        let mut pin_slot = vec![NONE; n];
        for (s, &i) in model.pinned.iter().enumerate() {
            pin_slot[i as usize] = s as u32;
        }
        let rest = model
            .rest
            .iter()
            .zip(&model.mass)
            .map(|(r, &m)| [r.x, r.y, r.z, m])
            .collect();
        let mut pinfo: Vec<[u32; 4]> = (0..n)
            .map(|i| {
                [
                    model.particle_body[i],
                    pin_slot[i],
                    model.inv_start[i],
                    model.cluster_start[i],
                ]
            })
            .collect();
        let members = model.cluster_members.len() as u32;
        pinfo.push([
            0,
            NONE,
            model.inv_start.get(n).copied().unwrap_or(0),
            model.cluster_start.get(n).copied().unwrap_or(0),
        ]);
        let mut lists = model.cluster_members.clone();
        lists.extend_from_slice(&model.inv_clusters);
        let crest = (0..n)
            .map(|c| {
                let r = &model.cluster_rest[c];
                let m = &r.metric_split;
                GpuClusterRest {
                    com_mass: r.com.extend(r.mass).to_array(),
                    aqq: mat4x3(&r.aqq_inv),
                    w: mat4x3(&m.w),
                    basis: mat4x3(&m.basis),
                    values_vol: m.values.extend(model.cluster_volume[c]).to_array(),
                    weight: [model.cluster_weight[c], 0.0, 0.0, 0.0],
                }
            })
            .collect();
        let bodies = model
            .bodies
            .iter()
            .map(|b| {
                let (kind, k_iter, mu, lambda) = match b.material {
                    Material::ShapeMatching { stiffness } => (
                        0,
                        iteration_stiffness(stiffness, settings.iterations),
                        0.0,
                        0.0,
                    ),
                    Material::Hyperelastic {
                        youngs_modulus,
                        poisson_ratio,
                    } => {
                        let h = crate::core::constraints::Hyperelastic::new(
                            youngs_modulus,
                            poisson_ratio,
                        );
                        (1, 0.0, h.mu, h.lambda)
                    }
                };
                GpuBody {
                    kind,
                    first: b.first,
                    count: b.count,
                    asleep: 0,
                    k_iter,
                    mu,
                    lambda,
                    spacing: b.spacing,
                    radius: b.radius,
                    in_workgroup: 0,
                    pad1: [0.0; 2],
                }
            })
            .collect();
        let mut p = Packed {
            rest,
            pinfo,
            lists,
            inv_offset: members,
            crest,
            bodies,
            n0: n as u32,
            ..Default::default()
        };
        p.pack_levels(model, settings);
        // Skin and normal adjacency.
        let mut starts = Vec::new();
        let mut corners = Vec::new();
        for (bi, b) in model.bodies.iter().enumerate() {
            let skin = &b.skin;
            let vfirst = p.vinf.len() as u32;
            p.vfirst.push(vfirst);
            for v in 0..skin.rest_vertices.len() {
                const { assert!(SKIN_INFLUENCES == 4) };
                let inf: [u32; 4] = skin.particles[v];
                let wt: [f32; 4] = skin.weights[v];
                p.vinf.push(inf);
                p.vwt.push(wt);
                let r = skin.rest_vertices[v];
                p.vrest.push([r.x, r.y, r.z, f32::from_bits(bi as u32)]);
            }
            // Representative render vertex of each welded vertex; triangles per welded vertex.
            let mut rep = vec![NONE; skin.welded_count as usize];
            for (v, &w) in skin.weld_map.iter().enumerate() {
                if rep[w as usize] == NONE {
                    rep[w as usize] = v as u32;
                }
            }
            let mut tris_of: Vec<Vec<u32>> = vec![Vec::new(); skin.welded_count as usize];
            for (t, tri) in skin.welded_triangles.iter().enumerate() {
                for &w in tri {
                    tris_of[w as usize].push(t as u32);
                }
            }
            for v in 0..skin.rest_vertices.len() {
                starts.push((corners.len() / 3) as u32);
                for &t in &tris_of[skin.weld_map[v] as usize] {
                    for &w in &skin.welded_triangles[t as usize] {
                        corners.push(vfirst + rep[w as usize]);
                    }
                }
            }
        }
        starts.push((corners.len() / 3) as u32);
        p.adj = starts;
        p.adj.extend_from_slice(&corners);
        p.max_radius = model.bodies.iter().map(|b| b.radius).fold(0.0, f32::max);
        p.max_spacing = model.bodies.iter().map(|b| b.spacing).fold(0.0, f32::max);
        p
    }

    /// Appends the hierarchy's coarse levels after level 0 (Müller 2008; see
    /// [`crate::core::model::Level`]): their particles, clusters and bodies as more of the
    /// same arrays (so the cluster and gather kernels solve a level by running over its
    /// range), and the tables that move positions between levels.
    fn pack_levels(&mut self, model: &Model, settings: &SolverSettings) {
        if model.levels.is_empty() {
            return;
        }
        // Level 0's lists were members then inverse lists; rebuild them as all levels'
        // members, then all levels' inverse lists, so every level's CSR runs on from the
        // previous one and pinfo's sentinel rows line up.
        let n0 = model.particle_count();
        let mut pin_slot = vec![NONE; n0];
        for (s, &i) in model.pinned.iter().enumerate() {
            pin_slot[i as usize] = s as u32;
        }
        let mut members = model.cluster_members.clone();
        let mut inv = model.inv_clusters.clone();
        self.pinfo.pop(); // the sentinel, re-added at the end
        let coarse_iters = SolverSettings {
            iterations: settings.coarse_iterations.max(1),
            ..settings.clone()
        };
        let mut sources = Vec::new();
        let mut records = Vec::new();
        let mut first = n0 as u32;
        for lv in &model.levels {
            let lm = &lv.model;
            let nl = lm.particle_count() as u32;
            let body0 = self.bodies.len() as u32;
            let (m0, i0) = (members.len() as u32, inv.len() as u32);
            for i in 0..nl as usize {
                let r = lm.rest[i];
                self.rest.push([r.x, r.y, r.z, lm.mass[i]]);
                let src = lv.source[i];
                let slot = if lm.pinned.binary_search(&(i as u32)).is_ok() {
                    pin_slot[src as usize]
                } else {
                    NONE
                };
                self.pinfo.push([
                    body0 + lm.particle_body[i],
                    slot,
                    i0 + lm.inv_start[i],
                    m0 + lm.cluster_start[i],
                ]);
                sources.push(src);
            }
            members.extend(lm.cluster_members.iter().map(|j| j + first));
            inv.extend(lm.inv_clusters.iter().map(|c| c + first));
            let lp = Packed::new(lm, &coarse_iters);
            self.crest.extend_from_slice(&lp.crest);
            for mut b in lp.bodies {
                b.first += first;
                self.bodies.push(b);
            }
            let rec_first = (records.len() / RECORD_WORDS as usize) as u32;
            for (f, &i) in lv.fine.iter().enumerate() {
                let (a, b) = (lv.parent_start[f] as usize, lv.parent_start[f + 1] as usize);
                let mut rec = [0u32; RECORD_WORDS as usize];
                rec[0] = i;
                for (k, s) in (a..b).take(4).enumerate() {
                    rec[1 + k] = lv.source[lv.parents[s] as usize];
                    rec[5 + k] = lv.weights[s].to_bits();
                }
                records.extend_from_slice(&rec);
            }
            // Multiplier transfer to the finer level (its clusters in its order).
            let tr_first = (records.len() / RECORD_WORDS as usize) as u32;
            let finer_first = self.levels.last().map_or(0, |l: &PackedLevel| l.first);
            for (t, &c) in lv.transfer_cluster.iter().enumerate() {
                let (a, b) = (
                    lv.transfer_start[t] as usize,
                    lv.transfer_start[t + 1] as usize,
                );
                let mut rec = [0u32; RECORD_WORDS as usize];
                rec[0] = finer_first + c;
                for (k, s) in (a..b).take(4).enumerate() {
                    rec[1 + k] = first + lv.transfer_parents[s];
                    rec[5 + k] = lv.transfer_weights[s].to_bits();
                }
                records.extend_from_slice(&rec);
            }
            self.levels.push(PackedLevel {
                first,
                count: nl,
                rec_first,
                rec_count: lv.fine.len() as u32,
                tr_first,
                tr_count: lv.transfer_cluster.len() as u32,
            });
            first += nl;
        }
        self.pinfo
            .push([0, NONE, inv.len() as u32, members.len() as u32]);
        self.inv_offset = members.len() as u32;
        self.lists = members;
        self.lists.extend_from_slice(&inv);
        self.records_base = sources.len() as u32;
        self.hier = sources;
        self.hier.extend_from_slice(&records);
    }

    /// Particles of all levels (level 0 and the coarse levels).
    pub fn total_particles(&self) -> u32 {
        self.rest.len() as u32
    }

    /// Render vertices of all bodies.
    pub fn vertex_count(&self) -> usize {
        self.vinf.len()
    }
}

/// The time-varying arrays of a [`State`] in GPU form: positions, velocities (vec4) and
/// cluster states.
pub fn pack_state(state: &State) -> (Vec<[f32; 4]>, Vec<[f32; 4]>, Vec<GpuClusterState>) {
    let x = state.x.iter().map(|p| col4(*p)).collect();
    let v = state.v.iter().map(|p| col4(*p)).collect();
    let c = state
        .rot
        .iter()
        .map(|q: &Quat| GpuClusterState {
            rot: q.to_array(),
            ..Default::default()
        })
        .collect();
    (x, v, c)
}

/// A per-dispatch range (group 1 of the cluster, gather and hierarchy kernels; one
/// 256-byte uniform record per range, bound with a dynamic offset).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct GpuRange {
    /// First particle, cluster or record.
    pub first: u32,
    /// How many.
    pub count: u32,
    /// Prolongation and transfer: start of the records in the hierarchy table. Level in:
    /// 1 zeroes the level's multipliers (the coarsest level; the others receive theirs
    /// from the coarser level).
    pub base: u32,
    /// Gather: 1 leaves contacts and the boundary to the contact pass (level 0 with
    /// particle contacts on).
    pub flag: u32,
    /// Level 0 with contacts: the half of p2 (0 or 1) an iteration's pass B writes and
    /// its contact pass reads (iterations alternate, so that `body.wgsl` can run one
    /// iteration's contacts and the next one's passes in one dispatch).
    pub half: u32,
    /// `body_iteration`: 1 runs the previous iteration's contact pass for the body's
    /// particles first (reading the other half of p2).
    pub prev: u32,
    /// Contact pass: 1 leaves the particles of `body.wgsl`'s bodies to the next
    /// `body_iteration`.
    pub skip: u32,
    /// `body_iteration`: the Jacobi iterations it runs (particle contacts only before the
    /// first, the previous dispatch's; [`SolverSettings::contact_every`]).
    ///
    /// [`SolverSettings::contact_every`]: crate::core::solver::SolverSettings::contact_every
    pub iters: u32,
    /// Padding to the uniform offset alignment.
    pub pad: [u32; 56],
}

/// Grid parameters for `n` particles whose largest lattice spacing is `spacing` (m):
/// the contact grid's cell edge (m), the all-particle search's cell edge (m) and the
/// hash buckets (a power of two, ≥ 2n). A contact cell of two spacings covers the contact
/// reach `2 (r_i + r_max)` within one ring. The K-nearest search uses the same edge:
/// of the edges from 1 to 4 spacings, 2 gave the fastest search over a million points
/// and over 1,000 bodies together (BENCHMARKS.md, "GPU").
pub fn grid_params(n: usize, spacing: f32) -> (f32, f32, u32) {
    let table = (2 * n).max(1024).next_power_of_two() as u32;
    let s = spacing.max(1e-6);
    (2.0 * s, 2.0 * s, table)
}

/// Element counts of each level of the prefix sum over `count` elements (level 0 first;
/// the last level fits one block).
pub fn scan_levels(count: u32) -> Vec<u32> {
    let mut levels = vec![count];
    let mut c = count;
    while c > SCAN_BLOCK {
        c = c.div_ceil(SCAN_BLOCK);
        levels.push(c);
    }
    levels
}
