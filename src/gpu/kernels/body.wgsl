// One Jacobi iteration (passes A and B) of every small shape-matching body, a workgroup
// per body: the body's predicted positions and rest records are read once into
// workgroup memory, every cluster is solved from there (its members' reads are
// workgroup-memory hits instead of L2 round trips), the corrections stay in workgroup
// memory, and every particle gathers them. One dispatch per iteration instead of two.
// The arithmetic is the cluster and gather kernels' (the gather adds a particle's
// corrections in inverse-list order, as the CPU twin does, instead of in four lanes).
// CPU twin: core::solver (Jacobi passes A and B) with
// core::constraints::solve_shape_matching. Used for the bodies with shape matching and
// at most BODY_MAX particles (`Body.in_wg`; world.rs, `set_body_kernel`); the cluster and
// gather kernels skip them.

const BODY_MAX: u32 = 512u;
const BODY_WG: u32 = 512u;

var<workgroup> sp: array<vec4<f32>, BODY_MAX>;   // the body's predicted positions p
var<workgroup> sr: array<vec4<f32>, BODY_MAX>;   // its rest records (X, m)
var<workgroup> sq: array<vec4<f32>, BODY_MAX>;   // per cluster: rotation (quaternion)
var<workgroup> st: array<vec4<f32>, BODY_MAX>;   // per cluster: (a t, a)

// Members j.x..j.w (local indices) added in that order.
fn add_four_local(t: MomentSums, j: vec4<u32>, origin: vec3<f32>, com: vec3<f32>) -> MomentSums {
    var u = add_member(t, sp[j.x].xyz, sr[j.x], origin, com);
    u = add_member(u, sp[j.y].xyz, sr[j.y], origin, com);
    u = add_member(u, sp[j.z].xyz, sr[j.z], origin, com);
    return add_member(u, sp[j.w].xyz, sr[j.w], origin, com);
}

// Cluster c's moments (members in list order, as moments_from) from workgroup memory,
// its first loads issued by moments_start; `first` is the body's first particle.
fn local_moments(c: u32, first: u32) -> Moments {
    let ms = moments_start(c);
    let end = ms.end;
    let com = ms.com_mass.xyz;
    let origin = sp[ms.first - first].xyz;
    let z = vec3<f32>(0.0);
    var t = MomentSums(z, z, z, z, z);
    var s = ms.start;
    let f4 = vec4<u32>(first);
    // The indices of the next two rounds of four are loaded while this round is added.
    var jn = ms.jn;
    var jm = ms.jm;
    loop {
        if (s + 4u > end) {
            break;
        }
        let j = jn - f4;
        jn = jm;
        let sm = s + 8u;
        if (sm + 4u <= end) {
            jm = lists4(sm);
        }
        t = add_four_local(t, j, origin, com);
        s = s + 4u;
    }
    for (; s < end; s = s + 1u) {
        let j = lists[s] - first;
        t = add_member(t, sp[j].xyz, sr[j], origin, com);
    }
    return moments_of(t, origin, ms.com_mass);
}

@compute @workgroup_size(512)
fn body_iteration(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let b = wid.x + wid.y * nwg.x;
    if (b >= params.n_bodies) {
        return;
    }
    let body = bodies[b];
    // A sleeping body, or one the cluster and gather kernels solve, is left alone (every
    // thread still meets the barriers).
    let awake = body.asleep == 0u && body.in_wg != 0u;
    let first = body.first;
    let count = min(body.count, BODY_MAX);
    for (var t = lid; t < count; t = t + BODY_WG) {
        sp[t] = p[first + t];
        sr[t] = rest[first + t];
    }
    workgroupBarrier();
    // Pass A: every cluster (one per particle) from the same positions.
    for (var t = lid; t < count; t = t + BODY_WG) {
        if (awake) {
            let c = first + t;
            let mo = local_moments(c, first);
            let alpha = body.k_iter * params.omega * crest[c].weight.x;
            let rot = extract_rotation(mo.apq, cstate[c].rot, params.rot_iters);
            let r = quat_mat(rot);
            sq[t] = rot;
            st[t] = vec4<f32>((mo.com - r * mo.rest_com) * alpha, alpha);
            cstate[c].rot = rot;
        }
    }
    workgroupBarrier();
    // Pass B: every particle adds the corrections of the clusters that contain it.
    for (var t = lid; t < count; t = t + BODY_WG) {
        if (awake) {
            let j = first + t;
            let s0 = pinfo[j].z;
            let s1 = pinfo[j + 1u].z;
            let xr = sr[t].xyz;
            var acc = vec4<f32>(0.0);
            let base = params.inv_offset + s0;
            let n = s1 - s0;
            let f4 = vec4<u32>(first);
            // Four indices at a time, the next four loaded while these are added.
            var on = vec4<u32>(0u);
            if (n >= 4u) {
                on = lists4(base);
            }
            var s = 0u;
            loop {
                if (s + 4u > n) {
                    break;
                }
                let o = on - f4;
                let sn = base + s + 4u;
                if (s + 8u <= n) {
                    on = lists4(sn);
                }
                acc = acc + rigid_part(sq[o.x], st[o.x], xr);
                acc = acc + rigid_part(sq[o.y], st[o.y], xr);
                acc = acc + rigid_part(sq[o.z], st[o.z], xr);
                acc = acc + rigid_part(sq[o.w], st[o.w], xr);
                s = s + 4u;
            }
            for (; s < n; s = s + 1u) {
                let o = lists[base + s] - first;
                acc = acc + rigid_part(sq[o], st[o], xr);
            }
            store_gathered(j, sp[t].xyz, acc);
        }
    }
}
