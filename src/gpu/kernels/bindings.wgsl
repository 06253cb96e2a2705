// The "world" bind group (group 0) shared by every simulation kernel; a kernel's source
// is common.wgsl + this file + its own file, so every binding is declared once.
// Layout and packing: src/gpu/buffers.rs.

const MAX_COLLIDERS: u32 = 128u;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<uniform> colliders: array<Collider, MAX_COLLIDERS>;
@group(0) @binding(2) var<storage, read_write> x: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> v: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> p: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> p2: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read> rest: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read> pinfo: array<vec4<u32>>;
@group(0) @binding(8) var<storage, read> lists: array<u32>;
@group(0) @binding(9) var<storage, read> crest: array<ClusterRest>;
@group(0) @binding(10) var<storage, read> bodies: array<Body>;
@group(0) @binding(11) var<storage, read_write> cstate: array<ClusterState>;
@group(0) @binding(12) var<storage, read_write> corr: array<vec4<f32>>;
@group(0) @binding(13) var<storage, read> pins: array<vec4<f32>>;
@group(0) @binding(14) var<storage, read_write> coldp: array<vec4<f32>>;
@group(0) @binding(15) var<storage, read_write> contacts: array<u32>;
@group(0) @binding(16) var<storage, read_write> scan: array<atomic<u32>>;
@group(0) @binding(17) var<storage, read_write> cursor: array<atomic<u32>>;
@group(0) @binding(18) var<storage, read_write> sorted: array<vec4<f32>>;
@group(0) @binding(19) var<storage, read_write> cell_of: array<u32>;
@group(0) @binding(20) var<storage, read_write> forces: array<vec4<f32>>;
@group(0) @binding(21) var<storage, read_write> fgrad: array<vec4<f32>>;
@group(0) @binding(22) var<storage, read> vinf: array<vec4<u32>>;
@group(0) @binding(23) var<storage, read> vwt: array<vec4<f32>>;
@group(0) @binding(24) var<storage, read> vrest: array<vec4<f32>>;
@group(0) @binding(25) var<storage, read> adj: array<u32>;
@group(0) @binding(26) var<storage, read> draw: array<DrawBody>;
@group(0) @binding(27) var<storage, read_write> knn_out: array<u32>;
@group(0) @binding(28) var<storage, read_write> status: array<atomic<u32>>;
@group(0) @binding(29) var<storage, read_write> bounds: array<vec4<f32>>;
@group(0) @binding(30) var<storage, read> hier: array<u32>;
@group(0) @binding(31) var<storage, read_write> grab: array<vec4<f32>>;
@group(0) @binding(32) var<storage, read_write> spare: array<u32>;

const GRASPER: u32 = 4u;

// Where grasper-held particle i must be (xyz) and the grasper (w; −1: free). `grab[i]` is
// the offset in the grasper's frame (xyz, m) and the grasper's index + 1 (w; 0: free).
// CPU twin: core::colliders::grab_target.
fn grab_target(i: u32) -> vec4<f32> {
    let g = grab[i];
    if (g.w < 0.5) {
        return vec4<f32>(0.0, 0.0, 0.0, -1.0);
    }
    let k = u32(g.w) - 1u;
    let c = colliders[k];
    return vec4<f32>(c.pos.xyz + quat_rotate(c.rot, g.xyz), f32(k));
}

// Whether particle (or cluster) i belongs to a sleeping body (plugin::sleep).
fn asleep(i: u32) -> bool {
    return bodies[pinfo[i].x].asleep != 0u;
}

// Whether body b was near another at the last contact refresh (broad.wgsl; the flags
// follow the 2 n_bodies boxes in `bounds`): only then can its particles have contacts.
fn near_body(b: u32) -> bool {
    return bounds[2u * params.n_bodies + b].x != 0.0;
}

// Other bodies listed per body for the contact search's per-particle test (knn.wgsl,
// `knn_contacts`): after the flags, NEAR_SLOTS / 4 vec4 per body, the indices as bits.
// A body with more near ones (`y` of its flag entry above NEAR_SLOTS) is not listed and
// its particles all search.
const NEAR_SLOTS: u32 = 32u;

// Whether the contact search of particle i (at q, of near body b) can find anything:
// q lies within `params.contact_reach` of the bounding box of one of the bodies near b
// (the reach bound is at least any particle's search radius, so a particle outside all
// of them has no candidate within its reach and its list is empty, as a full search's).
// True when b has more near bodies than the list holds.
fn may_touch(b: u32, q: vec3<f32>) -> bool {
    let nb = params.n_bodies;
    let count = u32(bounds[2u * nb + b].y);
    if (count > NEAR_SLOTS) {
        return true;
    }
    let r = vec3<f32>(params.contact_reach);
    let base = 3u * nb + b * (NEAR_SLOTS / 4u);
    for (var k = 0u; k < count; k = k + 1u) {
        let c = bitcast<u32>(bounds[base + k / 4u][k % 4u]);
        let l = bounds[2u * c].xyz - r;
        let h = bounds[2u * c + 1u].xyz + r;
        if (all(l <= q) && all(q <= h)) {
            return true;
        }
    }
    return false;
}

// Whether the cluster and gather kernels leave particle (or cluster) i alone: its body
// sleeps, or body.wgsl solves it.
fn passed_over(b: Body) -> bool {
    return b.asleep != 0u || b.in_wg != 0u;
}

// Inverse mass (1/kg) of particle i: 0 when pinned. Both loads are issued at once.
fn inv_mass(i: u32) -> f32 {
    return select(1.0 / rest[i].w, 0.0, pinfo[i].y != NONE);
}

// Grid cell of a point (unbounded integer coordinates) and its hash bucket.
fn cell_coords(q: vec3<f32>, cell: f32) -> vec3<i32> {
    return vec3<i32>(floor(q / cell));
}

fn cell_hash(c: vec3<i32>) -> u32 {
    let h = (u32(c.x) * 73856093u) ^ (u32(c.y) * 19349663u) ^ (u32(c.z) * 83492791u);
    return h & (params.grid_table - 1u);
}
