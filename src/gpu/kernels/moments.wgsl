// Cluster moments and the polar rotation shared by the cluster and deform kernels.
// CPU twins: core::constraints::{cluster_moments, extract_rotation}.

struct Moments {
    com: vec3<f32>,          // current centre of mass x_cm, m
    apq: mat3x3<f32>,        // A_pq = Σ m (p − x_cm) qᵀ
    rest_com: vec3<f32>,     // rest centre as the f32 members average to, m
};

// Running sums of the moments over a cluster's members.
struct MomentSums {
    mp: vec3<f32>,           // Σ m (p − origin)
    mq: vec3<f32>,           // Σ m q
    a0: vec3<f32>,           // columns of Σ m (p − origin) qᵀ
    a1: vec3<f32>,
    a2: vec3<f32>,
};

// Adds member (position pj, rest record r = (X, m)) to the sums, in the CPU twin's order.
fn add_member(t: MomentSums, pj: vec3<f32>, r: vec4<f32>, origin: vec3<f32>, com: vec3<f32>) -> MomentSums {
    let m = r.w;
    let md = (pj - origin) * m;
    let q = r.xyz - com;
    return MomentSums(t.mp + md, t.mq + q * m, t.a0 + md * q.x, t.a1 + md * q.y, t.a2 + md * q.z);
}

// Two partial sums added (a's then b's terms, the order the lane reduction needs).
fn add_sums(a: MomentSums, b: MomentSums) -> MomentSums {
    return MomentSums(a.mp + b.mp, a.mq + b.mq, a.a0 + b.a0, a.a1 + b.a1, a.a2 + b.a2);
}

// The moments from the member sums: centre of mass, A_pq about it, and the rest centre
// (`com_mass`: the cluster's rest centre and total mass).
fn moments_of(t: MomentSums, origin: vec3<f32>, com_mass: vec4<f32>) -> Moments {
    let inv_m = 1.0 / com_mass.w;
    let c_rel = t.mp * inv_m;
    let a = mat3x3<f32>(t.a0, t.a1, t.a2) - outer(c_rel, t.mq);
    return Moments(origin + c_rel, a, com_mass.xyz + t.mq * inv_m);
}

fn member_pos(j: u32, use_p: bool) -> vec3<f32> {
    if (use_p) {
        return x[params.p_base + j].xyz;
    }
    return x[j].xyz;
}

// Adds members j.x, j.y, j.z, j.w in that order, all their loads issued before any is
// used (one round of memory latency for four members).
fn add_four(t: MomentSums, j: vec4<u32>, use_p: bool, origin: vec3<f32>, com: vec3<f32>) -> MomentSums {
    let y0 = member_pos(j.x, use_p);
    let y1 = member_pos(j.y, use_p);
    let y2 = member_pos(j.z, use_p);
    let y3 = member_pos(j.w, use_p);
    let r0 = rest[j.x];
    let r1 = rest[j.y];
    let r2 = rest[j.z];
    let r3 = rest[j.w];
    var u = add_member(t, y0, r0, origin, com);
    u = add_member(u, y1, r1, origin, com);
    u = add_member(u, y2, r2, origin, com);
    return add_member(u, y3, r3, origin, com);
}

// The first loads of a cluster's moments: its member range, rest centre and mass, and
// the indices of its first members (the first two rounds of four and the origin member).
struct MemberScan {
    start: u32,
    end: u32,
    com_mass: vec4<f32>,     // only the rest record's first field (not all 192 bytes)
    first: u32,
    jn: vec4<u32>,
    jm: vec4<u32>,
};

// Entries s..s+3 of `lists`.
fn lists4(s: u32) -> vec4<u32> {
    return vec4<u32>(lists[s], lists[s + 1u], lists[s + 2u], lists[s + 3u]);
}

// Issues the loads of a MemberScan. Nothing here waits on them, so a caller can issue
// other loads (the body's sleep flag) before it uses any.
fn moments_start(c: u32) -> MemberScan {
    let start = pinfo[c].w;
    let end = pinfo[c + 1u].w;
    var jn = vec4<u32>(0u);
    var jm = vec4<u32>(0u);
    if (start + 4u <= end) {
        jn = lists4(start);
    }
    if (start + 8u <= end) {
        jm = lists4(start + 4u);
    }
    return MemberScan(start, end, crest[c].com_mass, lists[start], jn, jm);
}

fn cluster_moments(c: u32, use_p: bool) -> Moments {
    return moments_from(moments_start(c), use_p);
}

// `pos` is x or p (chosen by `use_p`). Members are read four at a time (all their loads
// issued before any is used, so a thread waits for one round of memory latency per four
// members instead of per member) and added in list order, as the CPU twin does.
fn moments_from(ms: MemberScan, use_p: bool) -> Moments {
    let end = ms.end;
    let com_mass = ms.com_mass;
    let com = com_mass.xyz;
    let origin = member_pos(ms.first, use_p);
    let z = vec3<f32>(0.0);
    var t = MomentSums(z, z, z, z, z);
    var s = ms.start;
    // The indices of the next two rounds of four are loaded while the current four
    // members' positions are, so the index loads leave the chain of memory round trips
    // (one ahead measured no gain, two ahead a small one; BENCHMARKS.md).
    var jn = ms.jn;
    var jm = ms.jm;
    loop {
        if (s + 4u > end) {
            break;
        }
        let j = jn;
        jn = jm;
        let sm = s + 8u;
        if (sm + 4u <= end) {
            jm = lists4(sm);
        }
        t = add_four(t, j, use_p, origin, com);
        s = s + 4u;
    }
    for (; s < end; s = s + 1u) {
        let j = lists[s];
        t = add_member(t, member_pos(j, use_p), rest[j], origin, com);
    }
    return moments_of(t, origin, com_mass);
}
