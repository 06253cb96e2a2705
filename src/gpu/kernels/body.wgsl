// Jacobi iterations (passes A and B) of every small shape-matching body, a workgroup per
// body: the body's predicted positions and rest records are read once into workgroup
// memory, every cluster is solved from there (its members' reads are workgroup-memory
// hits instead of L2 round trips), the corrections stay in workgroup memory, and every
// particle gathers them. A body near no other (broad.wgsl; or any body without particle
// contacts) runs all iterations of a substep in one workgroup (nothing outside the body
// acts on it between two iterations, so its positions and cluster rotations stay in the
// workgroup): in `body_substep` without particle contacts, with them in the substep's
// first `body_iteration` dispatch, beside the other bodies' first block of iterations
// (measured faster even with every body touching: BENCHMARKS.md, "The 1,000-body step
// as the plugin runs it"); a body with contact candidates runs one iteration
// per dispatch (`body_iteration`), which starts with the previous iteration's contact
// pass for the body's particles (iterations alternate between two halves of p2).
// The arithmetic is the cluster and gather kernels' (the gather adds a particle's
// corrections in inverse-list order, as the CPU twin does, instead of in four lanes).
// CPU twin: core::solver (Jacobi passes A and B) with
// core::constraints::solve_shape_matching. Used for the bodies with shape matching and
// at most BODY_MAX particles (`Body.in_wg`; world.rs, `set_body_kernel`); the cluster and
// gather kernels skip them.

const BODY_MAX: u32 = 511u;
const BODY_WG: u32 = 512u;

var<workgroup> sp: array<vec4<f32>, BODY_MAX>;   // the body's predicted positions p
var<workgroup> sr: array<vec4<f32>, BODY_MAX>;   // its rest records (X, m)
var<workgroup> sq: array<vec4<f32>, BODY_MAX>;   // per cluster: rotation (quaternion)
var<workgroup> st: array<vec4<f32>, BODY_MAX>;   // per cluster: (a t, a)
var<workgroup> wg_flag: u32;                      // whether it solves the body's substep whole

// Members j.x..j.w (local indices) added in that order.
fn add_four_local(t: MomentSums, j: vec4<u32>, origin: vec3<f32>, com: vec3<f32>) -> MomentSums {
    var u = add_member(t, sp[j.x].xyz, sr[j.x], origin, com);
    u = add_member(u, sp[j.y].xyz, sr[j.y], origin, com);
    u = add_member(u, sp[j.z].xyz, sr[j.z], origin, com);
    return add_member(u, sp[j.w].xyz, sr[j.w], origin, com);
}

// What a particle's passes A and B read besides positions and corrections: the same in
// every iteration, so `body_substep` loads it once per substep.
struct LocalConst {
    start: u32,              // its cluster's members: lists[start..end]
    end: u32,
    s0: u32,                 // the clusters that contain it: lists[s0..s1]
    s1: u32,
    com_mass: vec4<f32>,     // its cluster's rest centre (m) and mass (kg)
    alpha: f32,              // the cluster's Jacobi stiffness k_iter ω / s_c
    origin: u32,             // the cluster's first member (body-local)
};

fn local_const(body: Body, t: u32) -> LocalConst {
    let c = body.first + t;
    let i0 = pinfo[c];
    let i1 = pinfo[c + 1u];
    return LocalConst(
        i0.w,
        i1.w,
        params.inv_offset + i0.z,
        params.inv_offset + i1.z,
        crest[c].com_mass,
        body.k_iter * params.omega * crest[c].weight.x,
        lists[i0.w] - body.first,
    );
}

// The first indices of a particle's two lists: its cluster's first two rounds of four
// members and the first four clusters that contain it (zero where a list is shorter).
// The same in every iteration: `run_substep` loads them once and keeps them over all its
// iterations (measured faster with 1,000 bodies apart); `body_iteration` loads them at
// the head of each pass (loading them, with the rest of `LocalConst`, before the
// contact pass measured slower with 1,000 touching bodies; BENCHMARKS.md).
struct ListHead {
    jn: vec4<u32>,
    jm: vec4<u32>,
    on: vec4<u32>,
};

fn list_head(k: LocalConst) -> ListHead {
    var h = ListHead(vec4<u32>(0u), vec4<u32>(0u), vec4<u32>(0u));
    if (k.start + 4u <= k.end) {
        h.jn = lists4(k.start);
    }
    if (k.start + 8u <= k.end) {
        h.jm = lists4(k.start + 4u);
    }
    if (k.s0 + 4u <= k.s1) {
        h.on = lists4(k.s0);
    }
    return h;
}

// Cluster moments (members in list order, as moments_from) from workgroup memory;
// `first` is the body's first particle.
fn local_moments(k: LocalConst, first: u32, head: ListHead) -> Moments {
    let end = k.end;
    let com = k.com_mass.xyz;
    let origin = sp[k.origin].xyz;
    let z = vec3<f32>(0.0);
    var t = MomentSums(z, z, z, z, z);
    var s = k.start;
    let f4 = vec4<u32>(first);
    // The indices of the next two rounds of four are loaded while this round is added
    // (the first two by `list_head`, before the pass).
    var jn = head.jn;
    var jm = head.jm;
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
    return moments_of(t, origin, k.com_mass);
}

// Pass A for cluster first + t: its rotation (warm-started from `rot`) and correction
// to workgroup memory; returns the rotation.
fn solve_local_cluster(k: LocalConst, first: u32, t: u32, rot: vec4<f32>, head: ListHead) -> vec4<f32> {
    let mo = local_moments(k, first, head);
    let q = extract_rotation(mo.apq, rot, params.rot_iters);
    let r = quat_mat(q);
    sq[t] = q;
    st[t] = vec4<f32>((mo.com - r * mo.rest_com) * k.alpha, k.alpha);
    return q;
}

// Pass B for particle first + t: Σ over the clusters that contain it of a (R X + t)
// (xyz) and a (w), in inverse-list order (the CPU's).
fn gather_local(k: LocalConst, first: u32, t: u32, head: ListHead) -> vec4<f32> {
    let xr = sr[t].xyz;
    var acc = vec4<f32>(0.0);
    let base = k.s0;
    let n = k.s1 - k.s0;
    let f4 = vec4<u32>(first);
    // Four indices at a time, the next four loaded while these are added (the first
    // four by `list_head`).
    var on = head.on;
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
    return acc;
}

// Loads body b's positions and rest records into workgroup memory.
fn load_body(body: Body, lid: u32) {
    let count = min(body.count, BODY_MAX);
    for (var t = lid; t < count; t = t + BODY_WG) {
        sp[t] = x[params.p_base + body.first + t];
        sr[t] = rest[body.first + t];
    }
}

// The same for body b near another after an iteration whose contact pass left it (a
// dispatch fewer per iteration): its positions are that pass's results for its particles,
// from the other half of p2, where the previous body_iteration (or gather) left every
// particle near another.
fn load_body_after_contacts(body: Body, lid: u32) {
    let count = min(body.count, BODY_MAX);
    for (var t = lid; t < count; t = t + BODY_WG) {
        let j = body.first + t;
        sp[t] = vec4<f32>(contact_position(j, 1u - range.half), 0.0);
        sr[t] = rest[j];
    }
}

// Whether a body with particle contacts has candidates now (broad.wgsl): then its
// iterations are dispatched one at a time (body_iteration).
fn in_contact(b: u32) -> bool {
    return range.flag != 0u && near_body(b);
}

// `range.iters` iterations of the bodies near another (in the substep's first block, the
// others' whole substep, `run_substep`): the previous dispatch's contact pass for the body's particles first (`range.prev`),
// then the iterations, pins and colliders after each but the last, whose result goes to
// p2 for the contact pass (particle contacts every `contact_every` iterations).
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
    // The flag's load is issued before the body record's, so that the two overlap.
    let contact = in_contact(b);
    let body = bodies[b];
    // The first block of a substep also solves the bodies near no other, all their
    // iterations at once (`body_substep`'s work, which is then not dispatched): those
    // bodies meet none of the others in this substep, and in this dispatch their
    // workgroups run beside the others' instead of in a lightly loaded dispatch of
    // their own before it.
    if (range.prev == 0u) {
        if (lid == 0u) {
            wg_flag = u32(solves_substep(body, b));
        }
        if (workgroupUniformLoad(&wg_flag) != 0u) {
            run_substep(body, lid);
            return;
        }
    }
    // A sleeping body, one the cluster and gather kernels solve, or one near no other
    // (solved whole above, or by body_substep), is left alone (every thread still meets
    // the barriers).
    let awake = contact && body.asleep == 0u && body.in_wg != 0u;
    let count = min(body.count, BODY_MAX);
    if (awake) {
        if (range.prev != 0u) {
            load_body_after_contacts(body, lid);
        } else {
            load_body(body, lid);
        }
    }
    workgroupBarrier();
    for (var it = 1u; it <= range.iters; it = it + 1u) {
        let final_it = it == range.iters;
        // Pass A: every cluster (one per particle) from the same positions.
        for (var t = lid; t < count; t = t + BODY_WG) {
            if (awake) {
                let c = body.first + t;
                let k = local_const(body, t);
                let rot = solve_local_cluster(k, body.first, t, cstate[c].rot, list_head(k));
                cstate[c].rot = rot;
            }
        }
        workgroupBarrier();
        // Pass B: every particle adds the corrections of the clusters that contain it.
        for (var t = lid; t < count; t = t + BODY_WG) {
            if (awake) {
                let k = local_const(body, t);
                let acc = gather_local(k, body.first, t, list_head(k));
                let c = body.first + t;
                if (final_it) {
                    store_gathered(c, sp[t].xyz, acc, b);
                } else {
                    // An iteration without contacts: pins and colliders at once (pass B
                    // reads only its own position, so it may be replaced now).
                    sp[t] = vec4<f32>(boundary(c, gathered(sp[t].xyz, acc)), 0.0);
                }
            }
        }
        workgroupBarrier();
    }
}

// All `params.iterations` iterations of a substep for every awake body it solves, when
// particle contacts are off (with them, `body_iteration`'s first block does this for the
// bodies near no other; world.rs dispatches this kernel only without them): positions and rotations stay
// in the workgroup between iterations, each particle's pins and colliders applied after
// every iteration as `store_gathered` does; p and the rotations written at the end. The
// same arithmetic as `body_iteration` dispatched `iterations` times.
@compute @workgroup_size(512)
fn body_substep(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let b = wid.x + wid.y * nwg.x;
    if (b >= params.n_bodies) {
        return;
    }
    let body = bodies[b];
    if (lid == 0u) {
        wg_flag = u32(solves_substep(body, b));
    }
    if (workgroupUniformLoad(&wg_flag) == 0u) {
        return;
    }
    run_substep(body, lid);
}

// Whether body b's substep is solved whole in one workgroup (`run_substep`): awake, one
// of this file's bodies, and near no other (or without particle contacts).
fn solves_substep(body: Body, b: u32) -> bool {
    return body.asleep == 0u && body.in_wg != 0u && !in_contact(b);
}

// All `params.iterations` iterations of a substep of `body` in this workgroup (every
// thread calls it, in uniform control flow).
fn run_substep(body: Body, lid: u32) {
    load_body(body, lid);
    // BODY_WG > BODY_MAX: thread t owns cluster and particle t (the last thread none).
    let t = lid;
    let mine = t < min(body.count, BODY_MAX);
    let c = body.first + t;
    var rot = vec4<f32>(0.0, 0.0, 0.0, 1.0);
    var k: LocalConst;
    var head: ListHead;
    if (mine) {
        rot = cstate[c].rot;
        k = local_const(body, t);
        head = list_head(k);
    }
    workgroupBarrier();
    for (var it = 0u; it < params.iterations; it = it + 1u) {
        if (mine) {
            rot = solve_local_cluster(k, body.first, t, rot, head);
        }
        workgroupBarrier();
        if (mine) {
            let acc = gather_local(k, body.first, t, head);
            let pj = sp[t].xyz;
            // Pass B reads only its own position, so it may be replaced at once.
            sp[t] = vec4<f32>(boundary(c, gathered(pj, acc)), 0.0);
        }
        // The next pass A reads the new positions and overwrites the corrections.
        workgroupBarrier();
    }
    if (mine) {
        x[params.p_base + c] = sp[t];
        cstate[c].rot = rot;
    }
}
