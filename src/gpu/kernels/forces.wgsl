// Force each collider takes from the tissue over a substep: the momentum its projections
// removed, `F = −Σ_i m_i Δp_i / h²`, summed deterministically (fixed-shape tree
// reduction, no float atomics). CPU twin: core::solver::Solver::step ("Collider forces").

const FORCE_GROUPS: u32 = 64u;
const FWG: u32 = 256u;

var<workgroup> red: array<vec3<f32>, 256>;

// forces[k * FORCE_GROUPS + g]: partial sum of group g for collider k.
@compute @workgroup_size(256)
fn force_partial(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let g = wid.x;
    let k = wid.y;
    var acc = vec3<f32>(0.0);
    let stride = FORCE_GROUPS * FWG;
    for (var i = g * FWG + lid.x; i < params.n; i = i + stride) {
        let d = aux[params.coldp_base + i];
        if (d.w == f32(k)) {
            acc = acc - d.xyz * (rest[i].w / params.h2);
        }
    }
    red[lid.x] = acc;
    workgroupBarrier();
    for (var s = FWG / 2u; s > 0u; s = s >> 1u) {
        if (lid.x < s) {
            red[lid.x] = red[lid.x] + red[lid.x + s];
        }
        workgroupBarrier();
    }
    if (lid.x == 0u) {
        forces[k * FORCE_GROUPS + g] = vec4<f32>(red[0], 0.0);
    }
}

var<workgroup> lo_red: array<vec3<f32>, 256>;
var<workgroup> speed_red: array<f32, 256>;

// Each body's bounding box (bounds[2b] = min, bounds[2b + 1] = max, m, world frame): one
// workgroup per body, a fixed-shape tree reduction. Read back a frame later for culling.
@compute @workgroup_size(256)
fn body_bounds(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let b = wid.x + wid.y * 65535u;
    if (b >= params.n_bodies) {
        return;
    }
    let body = bodies[b];
    var lo = vec3<f32>(3.4e38);
    var hi = vec3<f32>(-3.4e38);
    var fast = 0.0;
    for (var i = lid.x; i < body.count; i = i + FWG) {
        let q = x[body.first + i].xyz;
        lo = min(lo, q);
        hi = max(hi, q);
        fast = max(fast, length(v[body.first + i].xyz));
    }
    lo_red[lid.x] = lo;
    red[lid.x] = hi;
    speed_red[lid.x] = fast;
    workgroupBarrier();
    for (var s = FWG / 2u; s > 0u; s = s >> 1u) {
        if (lid.x < s) {
            lo_red[lid.x] = min(lo_red[lid.x], lo_red[lid.x + s]);
            red[lid.x] = max(red[lid.x], red[lid.x + s]);
            speed_red[lid.x] = max(speed_red[lid.x], speed_red[lid.x + s]);
        }
        workgroupBarrier();
    }
    if (lid.x == 0u) {
        // w of the minimum carries the body's divergence flag (so one small readback
        // serves culling and the warning).
        aux[params.bounds_base + 2u * b] = vec4<f32>(lo_red[0], f32(atomicLoad(&status[b])));
        // w of the maximum: the fastest particle's speed, m/s (for sleeping).
        aux[params.bounds_base + 2u * b + 1u] = vec4<f32>(red[0], speed_red[0]);
    }
}

// Zeroes the totals at the start of a step.
@compute @workgroup_size(128)
fn force_clear(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x < params.n_colliders) {
        forces[params.n_colliders * FORCE_GROUPS + gid.x] = vec4<f32>(0.0);
    }
}

// Totals after the partials: forces[n_colliders * FORCE_GROUPS + k] += Σ_g partial / substeps.
@compute @workgroup_size(64)
fn force_total(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = gid.x;
    if (k >= params.n_colliders) {
        return;
    }
    var acc = vec3<f32>(0.0);
    for (var g = 0u; g < FORCE_GROUPS; g = g + 1u) {
        acc = acc + forces[k * FORCE_GROUPS + g].xyz;
    }
    let o = params.n_colliders * FORCE_GROUPS + k;
    forces[o] = vec4<f32>(forces[o].xyz + acc * params.inv_substeps, 0.0);
}
