// Pass B (gather: every particle sums the affine corrections of the clusters that
// contain it) and pass C (particle contacts, colliders, pins) of a Jacobi iteration.
// CPU twins: core::solver (Jacobi passes B and C), core::constraints::solve_contact,
// core::colliders::project_collider.

// Signed distance (w) and outward normal (xyz, world) of collider k at p.
fn collider_distance(k: u32, pw: vec3<f32>) -> vec4<f32> {
    return collider_sdf(colliders[k], pw);
}

// Macklin et al. 2014 eq. 24 friction; returns the correction of p.
fn project_collider(k: u32, pp: vec3<f32>, xx: vec3<f32>, radius: f32) -> vec3<f32> {
    return collider_push(colliders[k], pp, xx, radius, params.h);
}

// Pins, graspers and colliders for particle j at q; records the collider correction.
fn boundary(j: u32, q0: vec3<f32>) -> vec3<f32> {
    let info = pinfo[j];
    if (info.y != NONE) {
        return rest[params.pin_base + info.y].xyz;
    }
    // No colliders: no grasper holds anything (predict's update_grab let go), and the
    // grab and x reads below are skipped (a gather is memory-bound).
    if (params.n_colliders == 0u) {
        return q0;
    }
    let held = grab_target(j);
    if (held.w >= 0.0) {
        let old = aux[params.coldp_base + j];
        aux[params.coldp_base + j] = vec4<f32>(old.xyz + held.xyz - q0, held.w);
        return held.xyz;
    }
    var q = q0;
    let r = bodies[info.x].radius;
    var id = NONE;
    var total = vec3<f32>(0.0);
    let xj = x[j].xyz;
    for (var k = 0u; k < params.n_colliders; k = k + 1u) {
        let dp = project_collider(k, q, xj, r);
        if (any(dp != vec3<f32>(0.0))) {
            q = q + dp;
            total = total + dp;
            id = k;
        }
    }
    if (id != NONE) {
        let old = aux[params.coldp_base + j];
        aux[params.coldp_base + j] = vec4<f32>(old.xyz + total, f32(id));
    }
    return q;
}

// Shape matching's a (R X + t) (xyz) and a (w) for a correction stored as the unit
// quaternion q of R and (a t, a): X rotated as X + 2w (q × X) + 2 q × (q × X).
fn rigid_part(q: vec4<f32>, ta: vec4<f32>, xr: vec3<f32>) -> vec4<f32> {
    let u = 2.0 * cross(q.xyz, xr);
    let rx = xr + q.w * u + cross(q.xyz, u);
    return vec4<f32>(ta.w * rx + ta.xyz, ta.w);
}

// LANES threads share a particle: each applies every LANES-th cluster correction to the
// particle (shape matching: a quaternion rotation, 32 B read; hyperelastic: an affine
// map, 48 B), the partial sums are combined in lane order and lane 0 finishes. Four
// lanes measured fastest (against 8 and 16, from 37,982 to 1M particles; BENCHMARKS.md).
const LANES: u32 = 4u;
var<workgroup> part: array<vec4<f32>, 128>;

@compute @workgroup_size(128)
fn gather(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let local = (wid.x + wid.y * nwg.x) * (128u / LANES) + lid / LANES;
    let j = range.first + local;
    let lane = lid % LANES;
    let valid = local < range.count;
    // Σ over the clusters of Δx + a p (xyz) and Σ a (w).
    var acc = vec4<f32>(0.0);
    var xr = vec3<f32>(0.0);
    var mine = true;
    if (valid) {
        let info = pinfo[j];
        let s0 = info.z;
        let s1r = pinfo[j + 1u].z;
        xr = rest[j].xyz;
        // The first two correction indices are loaded before the body record is used,
        // so that the two loads overlap instead of following each other.
        var s = s0 + lane;
        let base = params.inv_offset;
        var n0 = 0u;
        var n1 = 0u;
        if (s + LANES < s1r) {
            n0 = lists[base + s];
            n1 = lists[base + s + LANES];
        }
        let body = bodies[info.x];
        // A sleeping body's particles gather nothing (its clusters were skipped).
        let s1 = select(s1r, s0, passed_over(body));
        // body.wgsl wrote this particle already.
        mine = body.in_wg == 0u;
        if (body.kind == 0u) {
            // Two corrections at a time (both loads in flight before either is used),
            // added in the same order as one at a time. The next two indices are loaded
            // with the current two corrections.
            loop {
                if (s + LANES >= s1) {
                    break;
                }
                let o0 = n0 * CORR_STRIDE;
                let o1 = n1 * CORR_STRIDE;
                let sn = s + 2u * LANES;
                if (sn + LANES < s1) {
                    n0 = lists[base + sn];
                    n1 = lists[base + sn + LANES];
                }
                let q0 = corr[o0];
                let ta0 = corr[o0 + 1u];
                let q1 = corr[o1];
                let ta1 = corr[o1 + 1u];
                acc = acc + rigid_part(q0, ta0, xr);
                acc = acc + rigid_part(q1, ta1, xr);
                s = sn;
            }
            if (s < s1) {
                let o = lists[base + s] * CORR_STRIDE;
                acc = acc + rigid_part(corr[o], corr[o + 1u], xr);
            }
        } else {
            for (; s < s1; s = s + LANES) {
                let o = lists[base + s] * CORR_STRIDE;
                let c0 = corr[o];
                let c1 = corr[o + 1u];
                let c2 = corr[o + 2u];
                let d = c0.xyz * xr.x + c1.xyz * xr.y + c2.xyz * xr.z
                    + vec3<f32>(c0.w, c1.w, c2.w);
                acc = acc + vec4<f32>(d, 0.0);
            }
        }
    }
    part[lid] = acc;
    workgroupBarrier();
    if (!valid || !mine || lane != 0u) {
        return;
    }
    for (var l = 1u; l < LANES; l = l + 1u) {
        acc = acc + part[lid + l];
    }
    store_gathered(j, x[params.p_base + j].xyz, acc, pinfo[j].x);
}

// A particle at pj moved by its gathered corrections `acc` (Σ a (R X + t), Σ a): the
// Jacobi average pj + Σ a (R X + t − pj). Shared by the gather and body.wgsl.
fn gathered(pj: vec3<f32>, acc: vec4<f32>) -> vec3<f32> {
    return pj + (acc.xyz - acc.w * pj);
}

// Particle j at pj moved by its gathered corrections `acc`: to p after its pins and
// colliders, or to p2 when the contact pass follows (`range.flag`, a body near another).
fn store_gathered(j: u32, pj: vec3<f32>, acc: vec4<f32>, body: u32) {
    let out = gathered(pj, acc);
    if (range.flag == 0u || !near_body(body)) {
        x[params.p_base + j] = vec4<f32>(boundary(j, out), 0.0);
    } else {
        // w: the particle's contact radius, so that the contact pass reads it with the
        // position instead of through the body record.
        aux[range.half * params.n + j] = vec4<f32>(out, bodies[body].radius);
    }
}

// What candidate i (at qi, its radius in w, inverse mass wi) asks of particle j (at pj,
// radius rj, inverse mass wj): j's share of their overlap (xyz) and 1 (w), or zero when
// they do not overlap. CPU twin: core::constraints::solve_contact (pass C).
fn contact_move(pj: vec3<f32>, rj: f32, wj: f32, qi: vec4<f32>, wi: f32) -> vec4<f32> {
    let dist = qi.w + rj;
    let delta = pj - qi.xyz;
    let l2 = dot(delta, delta);
    let w = wj + wi;
    if (l2 < dist * dist && l2 > 1.0e-24 && w > 0.0) {
        let l = sqrt(l2);
        let dc = delta * ((dist - l) / l * wj / w);
        if (any(dc != vec3<f32>(0.0))) {
            return vec4<f32>(dc, 1.0);
        }
    }
    return vec4<f32>(0.0);
}

// Candidate slot s of particle j's list (`first` = j · contact_k), NONE past the list.
fn candidate(first: u32, s: u32, kk: u32) -> u32 {
    if (s < kk) {
        return contacts[first + s];
    }
    return NONE;
}

// The contact pass of particle j (a body near another: pass B left it in half `half` of
// p2, its candidates too, each with its radius in w): its position after the contacts,
// pins and colliders. Candidates are taken four at a time: their positions, pins and
// masses loaded together, and the next four's indices with them, so that four
// candidates cost one round trip to memory; they are added in list order (as the CPU
// twin does) up to the first empty slot.
fn contact_position(j: u32, half: u32) -> vec3<f32> {
    let h = half * params.n;
    let own = aux[h + j];
    let pj = own.xyz;
    let rj = own.w;
    var q = pj;
    let wj = inv_mass(j);
    var acc = vec4<f32>(0.0);
    let kk = params.contact_k;
    let first = j * kk;
    var ids = vec4<u32>(
        candidate(first, 0u, kk),
        candidate(first, 1u, kk),
        candidate(first, 2u, kk),
        candidate(first, 3u, kk),
    );
    for (var s = 0u; s < kk; s = s + 4u) {
        if (ids.x == NONE) {
            break;
        }
        // An empty slot loads particle j itself (in bounds; never used).
        let a = select(ids, vec4<u32>(j), ids == vec4<u32>(NONE));
        let q0 = aux[h + a.x];
        let q1 = aux[h + a.y];
        let q2 = aux[h + a.z];
        let q3 = aux[h + a.w];
        let w0 = inv_mass(a.x);
        let w1 = inv_mass(a.y);
        let w2 = inv_mass(a.z);
        let w3 = inv_mass(a.w);
        let cur = ids;
        ids = vec4<u32>(
            candidate(first, s + 4u, kk),
            candidate(first, s + 5u, kk),
            candidate(first, s + 6u, kk),
            candidate(first, s + 7u, kk),
        );
        acc = acc + contact_move(pj, rj, wj, q0, w0);
        if (cur.y == NONE) {
            break;
        }
        acc = acc + contact_move(pj, rj, wj, q1, w1);
        if (cur.z == NONE) {
            break;
        }
        acc = acc + contact_move(pj, rj, wj, q2, w2);
        if (cur.w == NONE) {
            break;
        }
        acc = acc + contact_move(pj, rj, wj, q3, w3);
    }
    if (acc.w > 0.0) {
        q = q + acc.xyz / acc.w * params.contact_omega;
    }
    return boundary(j, q);
}

// Pass C: every particle of a body near another (a body near no other has no contacts,
// and pass B wrote its particles to p), except, with `range.skip`, those of body.wgsl's
// bodies, whose next body_iteration runs their contacts first.
@compute @workgroup_size(128)
fn contact(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = gid.x;
    if (j >= params.n) {
        return;
    }
    let bj = pinfo[j].x;
    if (!near_body(bj) || (range.skip != 0u && bodies[bj].in_wg != 0u)) {
        return;
    }
    x[params.p_base + j] = vec4<f32>(contact_position(j, range.half), 0.0);
}
