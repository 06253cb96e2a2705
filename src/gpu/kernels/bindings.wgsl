// Helpers shared by the simulation kernels over the world's bindings. A kernel's source
// is common.wgsl + the binding declarations (made from the one binding table,
// src/gpu/kernels/bindings.rs) + this file + its own files. Buffers that hold several
// arrays are indexed from the region bases in `params`: `x` holds the positions, then
// from `p_base` the predicted positions; `rest` the rest positions and masses, then
// from `pin_base` the pin targets; `aux` the two halves of the contact pass's
// positions (from 0), then from their bases the collider displacements, the grabs,
// the per-body boxes and flags, and the grid's sorted points.

const MAX_COLLIDERS: u32 = 128u;


const GRASPER: u32 = 4u;

// Where grasper-held particle i must be (xyz) and the grasper (w; −1: free). `grab[i]` is
// the offset in the grasper's frame (xyz, m) and the grasper's index + 1 (w; 0: free).
// CPU twin: core::colliders::grab_target.
fn grab_target(i: u32) -> vec4<f32> {
    let g = aux[params.grab_base + i];
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
// follow the 2 body_cap boxes in `bounds`): only then can its particles have contacts.
fn near_body(b: u32) -> bool {
    return aux[params.bounds_base + 2u * params.body_cap + b].x != 0.0;
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
    let nb = params.body_cap;
    let count = u32(aux[params.bounds_base + 2u * nb + b].y);
    if (count > NEAR_SLOTS) {
        return true;
    }
    let r = vec3<f32>(params.contact_reach);
    let base = 3u * nb + b * (NEAR_SLOTS / 4u);
    for (var k = 0u; k < count; k = k + 1u) {
        let c = bitcast<u32>(aux[params.bounds_base + base + k / 4u][k % 4u]);
        let l = aux[params.bounds_base + 2u * c].xyz - r;
        let h = aux[params.bounds_base + 2u * c + 1u].xyz + r;
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
