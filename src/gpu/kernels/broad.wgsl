// Broad phase of the particle contacts, at each contact refresh: per body, whether its
// bounding box (bounds[2b], bounds[2b + 1], from `body_bounds` on the same positions)
// grown by the contact reach bound (`params.contact_reach`) overlaps another body's box. Written to
// bounds[2 n_bodies + b].x (1: near, 0: near no other). A body near no other gets empty
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

// One workgroup per body; its threads test every BROAD_WG-th other body.
@compute @workgroup_size(64)
fn near_bodies(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let b = wid.x + wid.y * 65535u;
    if (b >= params.n_bodies) {
        return;
    }
    if (lid == 0u) {
        atomicStore(&near_hit, u32(params.n_bodies > BROAD_MAX_BODIES));
    }
    workgroupBarrier();
    let reach = params.contact_reach;
    let lo = bounds[2u * b].xyz - vec3<f32>(reach);
    let hi = bounds[2u * b + 1u].xyz + vec3<f32>(reach);
    let tested = select(params.n_bodies, 0u, params.n_bodies > BROAD_MAX_BODIES);
    for (var c = lid; c < tested; c = c + BROAD_WG) {
        if (c != b) {
            let l = bounds[2u * c].xyz;
            let h = bounds[2u * c + 1u].xyz;
            if (all(lo <= h) && all(l <= hi)) {
                atomicOr(&near_hit, 1u);
            }
        }
    }
    workgroupBarrier();
    if (lid == 0u) {
        bounds[2u * params.n_bodies + b] = vec4<f32>(f32(atomicLoad(&near_hit)), 0.0, 0.0, 0.0);
    }
}
