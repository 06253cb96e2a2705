// Shared declarations of every bevy_tissue kernel (prepended to each kernel's source).
// The layouts mirror `src/gpu/buffers.rs`; the math mirrors `src/core` (the CPU twin).

const NONE: u32 = 0xffffffffu;
const WG: u32 = 128u;

struct Params {
    gravity: vec4<f32>,      // xyz m/s², w unused
    n: u32,                  // particles
    n_colliders: u32,
    rot_iters: u32,
    contacts: u32,           // 1: particle contacts on (pass C separate)
    h: f32,                  // substep, s
    h2: f32,                 // h², s²
    keep: f32,               // velocity kept after damping, max(0, 1 − damping·h)
    omega: f32,              // Jacobi relaxation
    inv_offset: u32,         // start of the inverse lists in `lists`
    contact_k: u32,          // contact neighbours per particle (list stride)
    n_vertices: u32,         // render vertices
    inv_substeps: f32,       // 1 / substeps
    grid_cell: f32,          // grid cell edge, m
    grid_table: u32,         // hash buckets (power of two)
    max_speed: f32,          // a particle faster than this (m/s) counts as diverged
    max_radius: f32,         // largest particle radius of any body, m
    knn_k: u32,              // K of the unfiltered search (knn_out stride)
    n_bodies: u32,
    knn_cell: f32,           // grid cell edge of the all-particle search, m
    spare_stride: u32,       // entries per particle in `spare` (neighbour search)
    iterations: u32,         // Jacobi iterations per substep (body.wgsl's body_substep)
    contact_reach: f32,      // broad phase: core::knn::contact_reach_bound(max_radius), m
    contact_omega: f32,      // Jacobi relaxation of the particle contacts
    p_base: u32,             // first predicted position in `x` (all levels' particles)
    pin_base: u32,           // first pin target in `rest`
    coldp_base: u32,         // first collider displacement in `aux`
    grab_base: u32,          // first grab in `aux`
    bounds_base: u32,        // first per-body box in `aux`
    sorted_base: u32,        // first grid-sorted point in `aux`
    body_cap: u32,           // bodies the per-body arrays have room for (bounds layout)
    vertex_cap: u32,         // render vertices the vertex arrays have room for (adj layout)
    _pad: u32,
};

// Per body, per frame: world → entity-local affine map for drawing, and where the
// body's render vertices start in the mesh slab (in floats) and in the vertex arrays.
struct DrawBody {
    m0: vec4<f32>,           // rows of the 3×4 map
    m1: vec4<f32>,
    m2: vec4<f32>,
    vbase: u32,              // first float of the body's vertices in the slab
    vfirst: u32,             // first render vertex of the body (global)
    stride: u32,             // floats per vertex in the slab
    _pad: u32,
};

struct Body {
    kind: u32,               // 0 shape matching, 1 hyperelastic
    first: u32,
    count: u32,
    asleep: u32,             // 1: the body sleeps, its particles and clusters are skipped
    k_iter: f32,             // shape matching: per-iteration stiffness
    mu: f32,                 // Pa
    lambda: f32,             // Pa
    spacing: f32,            // m
    radius: f32,             // m
    in_wg: u32,              // 1: level 0 solved by body.wgsl (the cluster and gather
                             // kernels skip the body)
    _pad2: f32,
    _pad3: f32,
};

struct ClusterRest {
    com_mass: vec4<f32>,     // rest centre of mass (body frame, m), total mass (kg)
    aqq: mat3x3<f32>,        // A_qq⁻¹
    w: mat3x3<f32>,          // split-mass metric W
    basis: mat3x3<f32>,      // eigenvectors of W
    values_vol: vec4<f32>,   // eigenvalues of W, cluster volume (m³)
    weight: vec4<f32>,       // x: Jacobi weight 1/s_c
};

struct ClusterState {
    rot: vec4<f32>,          // warm-start rotation (quaternion xyzw)
    lam0: vec4<f32>,         // λ_H, Λxx, Λyy, Λzz
    lam1: vec4<f32>,         // Λxy, Λxz, Λyz, -
};

// A cluster's correction of its members, three vec4 per cluster in `corr` (48 B; the
// gather reads it once per member, so its size is the gather's memory traffic):
// - shape matching: Δx = a (R X + t) − a p, stored as [R as a quaternion xyzw],
//   [a t, a] (32 B read);
// - hyperelastic: Δx = M X + t, stored as the columns of M with t in w (48 B read).
const CORR_STRIDE: u32 = 3u;

struct Collider {
    kind_fr: vec4<f32>,      // x: kind (0 plane, 1 sphere, 2 capsule, 3 box, 4 grasper),
                             // y: friction, z: grasper mode (0 open, 1 capture, 2 hold)
    pos: vec4<f32>,          // m
    rot: vec4<f32>,          // quaternion
    shape: vec4<f32>,        // sphere, grasper: r; capsule: half length, r; box: half extents
    vel: vec4<f32>,          // m/s
};

fn quat_mat(q: vec4<f32>) -> mat3x3<f32> {
    // glam's Mat3::from_quat.
    let x2 = q.x + q.x; let y2 = q.y + q.y; let z2 = q.z + q.z;
    let xx = q.x * x2; let xy = q.x * y2; let xz = q.x * z2;
    let yy = q.y * y2; let yz = q.y * z2; let zz = q.z * z2;
    let wx = q.w * x2; let wy = q.w * y2; let wz = q.w * z2;
    return mat3x3<f32>(
        vec3<f32>(1.0 - (yy + zz), xy + wz, xz - wy),
        vec3<f32>(xy - wz, 1.0 - (xx + zz), yz + wx),
        vec3<f32>(xz + wy, yz - wx, 1.0 - (xx + yy)),
    );
}

fn quat_mul(a: vec4<f32>, b: vec4<f32>) -> vec4<f32> {
    return vec4<f32>(
        a.w * b.x + a.x * b.w + a.y * b.z - a.z * b.y,
        a.w * b.y - a.x * b.z + a.y * b.w + a.z * b.x,
        a.w * b.z + a.x * b.y - a.y * b.x + a.z * b.w,
        a.w * b.w - a.x * b.x - a.y * b.y - a.z * b.z,
    );
}

fn quat_rotate(q: vec4<f32>, v: vec3<f32>) -> vec3<f32> {
    return quat_mat(q) * v;
}

fn quat_inv_rotate(q: vec4<f32>, v: vec3<f32>) -> vec3<f32> {
    return transpose(quat_mat(q)) * v;
}

fn outer(a: vec3<f32>, b: vec3<f32>) -> mat3x3<f32> {
    return mat3x3<f32>(a * b.x, a * b.y, a * b.z);
}

fn frob(a: mat3x3<f32>, b: mat3x3<f32>) -> f32 {
    return dot(a[0], b[0]) + dot(a[1], b[1]) + dot(a[2], b[2]);
}

fn is_finite_f(x: f32) -> bool {
    return x == x && abs(x) <= 3.4028235e38;
}

fn dist2(a: vec3<f32>, b: vec3<f32>) -> f32 {
    let d = a - b;
    return d.x * d.x + d.y * d.y + d.z * d.z;
}

// Cofactor matrix cof F = det(F) F⁻ᵀ (core::constraints::cofactor).
fn cofactor(f: mat3x3<f32>) -> mat3x3<f32> {
    return mat3x3<f32>(cross(f[1], f[2]), cross(f[2], f[0]), cross(f[0], f[1]));
}

// Müller et al. 2016, warm-started from q (first-order update below 0.25 rad).
fn extract_rotation(a: mat3x3<f32>, q0: vec4<f32>, iterations: u32) -> vec4<f32> {
    var q = q0;
    for (var it = 0u; it < iterations; it = it + 1u) {
        let r = quat_mat(q);
        let num = cross(r[0], a[0]) + cross(r[1], a[1]) + cross(r[2], a[2]);
        let den = abs(dot(r[0], a[0]) + dot(r[1], a[1]) + dot(r[2], a[2])) + 1.0e-9;
        let om = num / den;
        let w = length(om);
        if (!(w == w) || w < 1.0e-6) {
            break;
        }
        var s: vec4<f32>;
        if (w < 0.25) {
            s = vec4<f32>(0.5 * om, 1.0);
        } else {
            let half = 0.5 * w;
            s = vec4<f32>(om / w * sin(half), cos(half));
        }
        let qn = quat_mul(s, q);
        q = qn * (1.0 / length(qn));
    }
    return q;
}

fn sdf_sphere(l: vec3<f32>, r: f32) -> vec4<f32> {
    let len = length(l);
    var n = vec3<f32>(0.0, 1.0, 0.0);
    if (len > 1.0e-12) {
        n = l / len;
    }
    return vec4<f32>(n, len - r);
}

fn sdf_box(l: vec3<f32>, he: vec3<f32>) -> vec4<f32> {
    let q = abs(l) - he;
    let outside = max(q, vec3<f32>(0.0));
    let ol = length(outside);
    if (ol > 0.0) {
        return vec4<f32>(outside * sign(l) / ol, ol);
    }
    var axis = 2;
    if (q.x >= q.y && q.x >= q.z) {
        axis = 0;
    } else if (q.y >= q.z) {
        axis = 1;
    }
    var n = vec3<f32>(0.0);
    if (l[axis] >= 0.0) { n[axis] = 1.0; } else { n[axis] = -1.0; }
    return vec4<f32>(n, q[axis]);
}

// Signed distance (w) and outward normal (xyz, world) of collider c at p
// (core::colliders::Collider::distance).
fn collider_sdf(c: Collider, pw: vec3<f32>) -> vec4<f32> {
    let l = quat_inv_rotate(c.rot, pw - c.pos.xyz);
    let kind = u32(c.kind_fr.x);
    var r: vec4<f32>;
    if (kind == 0u) {
        r = vec4<f32>(0.0, 1.0, 0.0, l.y);
    } else if (kind == 1u) {
        r = sdf_sphere(l, c.shape.x);
    } else if (kind == 2u) {
        let y = clamp(l.y, -c.shape.x, c.shape.x);
        r = sdf_sphere(l - vec3<f32>(0.0, y, 0.0), c.shape.y);
    } else if (kind == 3u) {
        r = sdf_box(l, c.shape.xyz);
    } else {
        r = vec4<f32>(0.0, 1.0, 0.0, 3.4e38); // grasper: touches nothing
    }
    return vec4<f32>(quat_rotate(c.rot, r.xyz), r.w);
}

// The correction pushing a particle of `radius` at pp (at xx at the substep's start) out
// of collider c, with Macklin et al. 2014 eq. 24 friction over a substep of h seconds
// (core::colliders::project_collider).
fn collider_push(c: Collider, pp: vec3<f32>, xx: vec3<f32>, radius: f32, h: f32) -> vec3<f32> {
    let dn = collider_sdf(c, pp);
    let depth = radius - dn.w;
    if (!(depth == depth) || depth <= 0.0) {
        return vec3<f32>(0.0);
    }
    let n = dn.xyz;
    var dp = n * depth;
    let mu = c.kind_fr.y;
    if (mu > 0.0) {
        let rel = (pp + dp - xx) - c.vel.xyz * h;
        let tangential = rel - n * dot(rel, n);
        let t = length(tangential);
        if (t > 0.0) {
            if (t <= mu * depth) {
                dp = dp - tangential;
            } else {
                dp = dp - tangential * (mu * depth / t);
            }
        }
    }
    return dp;
}

// The per-dispatch range of the cluster, gather and hierarchy kernels (one
// 256-byte uniform record per range, bound with a dynamic offset; `GpuRange` in
// src/gpu/buffers.rs): level 0's particles or a coarse level's, or a run of records.

struct Range {
    first: u32,     // first particle, cluster or record
    count: u32,
    base: u32,      // prolong, transfer: start of the records in `hier`;
                    // level_in: 1 zeroes the level's multipliers (the coarsest level)
    flag: u32,      // gather: 1 leaves contacts and the boundary to the contact pass
    half: u32,      // level 0 with contacts: the half of p2 (0, 1) this iteration's pass B
                    // writes and its contact pass reads
    prev: u32,      // body_iteration: 1 runs the previous iteration's contact pass for
                    // its particles first (from the other half of p2)
    skip: u32,      // contact: 1 leaves the particles of body.wgsl's bodies to the next
                    // body_iteration
    iters: u32,     // body_iteration: Jacobi iterations in this dispatch (contacts only
                    // before the first, from the dispatch before; SolverSettings::contact_every)
};

// One level of the grid's prefix sum (`GpuScanLevel`), per dispatch.
struct ScanLevel {
    offset: u32,             // first element of this level in `scan`
    count: u32,              // elements at this level
    sums: u32,               // where this level's block sums go (next level's offset)
    cell: f32,               // grid cell edge of this build (grid_count, grid_scatter), m
};

// The render-vertex span of one skinning dispatch (`GpuSkinRange`).
struct SkinRange {
    begin: u32,
    end: u32,
    _pad0: u32,
    _pad1: u32,
};
