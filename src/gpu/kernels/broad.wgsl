// Broad phase of the particle contacts, at each contact refresh: per body, whether its
// bounding box (bounds[2b], bounds[2b + 1], from `body_bounds` on the same positions)
// grown by the contact reach bound (`params.contact_reach`) overlaps another body's box. Written to
// bounds[2 body_cap + b].x (1: near, 0: near no other). A body near no other gets empty
// contact lists without a search (`knn_contacts`), runs all iterations of a substep in
// one dispatch (body.wgsl, `body_substep`) or goes straight to p after the gather
// (`store_gathered`), and the contact pass skips it: the same result, as no particle of
// another body lies within any contact reach of its particles.
// CPU twin: core::knn::near_bodies (with contact_reach_bound).

const BROAD_WG: u32 = 64u;

// Above this many bodies every body counts as near (core::knn::BROAD_MAX_BODIES): the
// pair tests grow with the square of the bodies.
const BROAD_MAX_BODIES: u32 = 2048u;

var<workgroup> near_hit: atomic<u32>;
var<workgroup> near_count: atomic<u32>;
var<workgroup> near_list: array<u32, NEAR_SLOTS>;

// One workgroup per body; its threads test every BROAD_WG-th other body.
@compute @workgroup_size(64)
fn near_bodies(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let b = wid.x + wid.y * 65535u;
    if (b >= params.n_bodies) {
        return;
    }
    if (lid == 0u) {
        let all = params.n_bodies > BROAD_MAX_BODIES;
        atomicStore(&near_hit, u32(all));
        // Without the pair tests no list: every particle searches.
        atomicStore(&near_count, select(0u, NEAR_SLOTS + 1u, all));
    }
    workgroupBarrier();
    let reach = params.contact_reach;
    let lo = aux[params.bounds_base + 2u * b].xyz - vec3<f32>(reach);
    let hi = aux[params.bounds_base + 2u * b + 1u].xyz + vec3<f32>(reach);
    let tested = select(params.n_bodies, 0u, params.n_bodies > BROAD_MAX_BODIES);
    for (var c = lid; c < tested; c = c + BROAD_WG) {
        if (c != b) {
            let l = aux[params.bounds_base + 2u * c].xyz;
            let h = aux[params.bounds_base + 2u * c + 1u].xyz;
            if (all(lo <= h) && all(l <= hi)) {
                atomicOr(&near_hit, 1u);
                let slot = atomicAdd(&near_count, 1u);
                if (slot < NEAR_SLOTS) {
                    near_list[slot] = c;
                }
            }
        }
    }
    workgroupBarrier();
    let count = atomicLoad(&near_count);
    if (lid == 0u) {
        let hit = f32(atomicLoad(&near_hit));
        aux[params.bounds_base + 2u * params.body_cap + b] = vec4<f32>(hit, f32(count), 0.0, 0.0);
    }
    // The list (in no particular order: the per-particle test does not depend on it).
    let base = 3u * params.body_cap + b * (NEAR_SLOTS / 4u);
    if (count <= NEAR_SLOTS && lid < NEAR_SLOTS / 4u) {
        var v = vec4<u32>(0u);
        for (var k = 0u; k < 4u; k = k + 1u) {
            let slot = 4u * lid + k;
            if (slot < count) {
                v[k] = near_list[slot];
            }
        }
        aux[params.bounds_base + base + lid] = bitcast<vec4<f32>>(v);
    }
}
