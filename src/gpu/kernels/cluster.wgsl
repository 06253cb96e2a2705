// Pass A of a Jacobi iteration: every cluster solved from the same predicted positions
// `p`; its correction stored as an affine map of the rest positions (`corr`).
// CPU twin: core::solver (Jacobi pass A) with core::constraints::{solve_shape_matching,
// solve_hyperelastic}.

fn sym_from(l0: vec4<f32>, l1: vec4<f32>) -> mat3x3<f32> {
    return mat3x3<f32>(
        vec3<f32>(l0.y, l1.x, l1.y),
        vec3<f32>(l1.x, l0.z, l1.z),
        vec3<f32>(l1.y, l1.z, l0.w),
    );
}

// Every component finite (`is_finite_f` of each).
fn vec_finite(v: vec3<f32>) -> bool {
    return all(v == v) && all(abs(v) <= vec3<f32>(3.4028235e38));
}

// Every entry finite (columns written out: a matrix indexed in a loop may be kept in
// per-thread memory rather than registers).
fn mat_finite(m: mat3x3<f32>) -> bool {
    return vec_finite(m[0]) && vec_finite(m[1]) && vec_finite(m[2]);
}

// Hyperelastic: Δx = M X + t.
fn store_affine(c: u32, m: mat3x3<f32>, t: vec3<f32>) {
    let o = c * CORR_STRIDE;
    corr[o] = vec4<f32>(m[0], t.x);
    corr[o + 1u] = vec4<f32>(m[1], t.y);
    corr[o + 2u] = vec4<f32>(m[2], t.z);
}

// One thread per cluster: its moments summed over the members in list order (the CPU
// twin's order), then its solve. Threads sharing a cluster (8, 4 or 2 lanes summing
// every LANES-th member, one lane solving) measured slower on large ranges
// (BENCHMARKS.md, "GPU"), as the solve then runs on one lane in LANES. Small ranges use
// solve_clusters_lanes below (world.rs, LANE_CLUSTERS_BELOW).
@compute @workgroup_size(128)
fn solve_clusters(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let local = (wid.x + wid.y * nwg.x) * 128u + lid;
    let c = range.first + local;
    if (local >= range.count) {
        return;
    }
    // A sleeping body's clusters are skipped (their corrections are read only by its own
    // particles, which skip gathering). The moments' first loads are issued before the
    // sleep flag is known, so that its two dependent loads (particle record, then body)
    // overlap them instead of preceding them.
    let body = pinfo[c].x;
    let ms = moments_start(c);
    if (passed_over(bodies[body])) {
        return;
    }
    solve_cluster(c, moments_from(ms, true));
}

// The same for small ranges (the hierarchy's coarse levels, small worlds): LANES threads
// share a cluster, each sums every LANES-th member, the partial sums are combined in lane
// order (deterministic) and lane 0 solves. Eight times the threads hide the latency of
// the member reads where a thread per cluster would leave the GPU mostly idle (measured
// on the hierarchy's coarse passes: BENCHMARKS.md, "Hierarchy").
const LANES: u32 = 8u;
var<workgroup> part: array<array<vec4<f32>, 4>, 128>;

@compute @workgroup_size(128)
fn solve_clusters_lanes(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let local = (wid.x + wid.y * nwg.x) * (128u / LANES) + lid / LANES;
    let c = range.first + local;
    let lane = lid % LANES;
    // A sleeping body's clusters are skipped (their corrections are read only by its own
    // particles, which skip gathering).
    let valid = local < range.count && !passed_over(bodies[pinfo[c].x]);
    let z = vec3<f32>(0.0);
    var t = MomentSums(z, z, z, z, z);
    var origin = vec3<f32>(0.0);
    var com = vec3<f32>(0.0);
    if (valid) {
        let start = pinfo[c].w;
        let end = pinfo[c + 1u].w;
        com = crest[c].com_mass.xyz;
        origin = x[params.p_base + lists[start]].xyz;
        // Four of the lane's members at a time (their loads in flight together), added
        // in the lane's order (a small gain on the coarse passes: on a small level the
        // solve after the sums is most of a dispatch).
        var s = start + lane;
        loop {
            if (s + 3u * LANES >= end) {
                break;
            }
            let j = vec4<u32>(lists[s], lists[s + LANES], lists[s + 2u * LANES], lists[s + 3u * LANES]);
            t = add_four(t, j, true, origin, com);
            s = s + 4u * LANES;
        }
        for (; s < end; s = s + LANES) {
            let j = lists[s];
            t = add_member(t, x[params.p_base + j].xyz, rest[j], origin, com);
        }
    }
    part[lid] = array<vec4<f32>, 4>(vec4<f32>(t.mp, t.a0.x), vec4<f32>(t.mq, t.a0.y), vec4<f32>(t.a1, t.a0.z), vec4<f32>(t.a2, 0.0));
    workgroupBarrier();
    if (!valid || lane != 0u) {
        return;
    }
    for (var l = 1u; l < LANES; l = l + 1u) {
        let o = part[lid + l];
        let other = MomentSums(o[0].xyz, o[1].xyz, vec3<f32>(o[0].w, o[1].w, o[2].w), o[2].xyz, o[3].xyz);
        t = add_sums(t, other);
    }
    let mo = moments_of(t, origin, crest[c].com_mass);
    solve_cluster(c, mo);
}

fn solve_cluster(c: u32, mo: Moments) {
    let info = pinfo[c];
    let body = bodies[info.x];
    if (body.kind == 0u) {
        // Shape matching (Müller et al. 2005), averaged with the cluster weight. Reads
        // and writes only the fields it uses (the rest record is 192 B, the state 48 B).
        let alpha = body.k_iter * params.omega * crest[c].weight.x;
        let rot = extract_rotation(mo.apq, cstate[c].rot, params.rot_iters);
        let r = quat_mat(rot);
        let o = c * CORR_STRIDE;
        corr[o] = rot;
        corr[o + 1u] = vec4<f32>((mo.com - r * mo.rest_com) * alpha, alpha);
        cstate[c].rot = rot;
        return;
    }
    let cr = crest[c];
    var st = cstate[c];
    // Fixed-corotated XPBD on F with split masses (core::constraints::solve_hyperelastic).
    let f = mo.apq * cr.aqq;
    let vol = cr.values_vol.w;
    let coord = max(max(abs(mo.com.x), abs(mo.com.y)), abs(mo.com.z));
    let band = 16.0 * 1.1920929e-7 * (coord + body.spacing) / body.spacing;
    let scale = params.omega;
    var g = mat3x3<f32>(vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
    var f2 = f;
    let alpha_h = 1.0 / (body.lambda * vol * params.h2);
    if (is_finite_f(alpha_h)) {
        var c_h = determinant(f) - 1.0;
        if (abs(c_h) <= band) {
            c_h = 0.0;
        }
        let ph = cofactor(f);
        let r = -c_h - alpha_h * st.lam0.x;
        if (r != 0.0) {
            let a = frob(ph * cr.w, ph);
            let dl = scale * r / (a + alpha_h);
            if (is_finite_f(dl)) {
                st.lam0.x = st.lam0.x + dl;
                g = g + ph * dl;
                f2 = f2 + ph * cr.w * dl;
            }
        }
    }
    let alpha_d = 1.0 / (2.0 * body.mu * vol * params.h2);
    if (is_finite_f(alpha_d)) {
        st.rot = extract_rotation(f2, st.rot, params.rot_iters);
        let r = quat_mat(st.rot);
        let rtf = transpose(r) * f2;
        var e = (rtf + transpose(rtf)) * 0.5 - mat3x3<f32>(vec3<f32>(1.0, 0.0, 0.0), vec3<f32>(0.0, 1.0, 0.0), vec3<f32>(0.0, 0.0, 1.0));
        if (frob(e, e) <= band * band) {
            e = mat3x3<f32>(vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
        }
        let lam_d = sym_from(st.lam0, st.lam1);
        let rhs = (e * -1.0) - lam_d * alpha_d;
        let nz = any(rhs[0] != vec3<f32>(0.0)) || any(rhs[1] != vec3<f32>(0.0)) || any(rhs[2] != vec3<f32>(0.0));
        if (nz) {
            let q = cr.basis;
            let rp = transpose(q) * rhs * q;
            let wv = cr.values_vol.xyz;
            // Entry (a, b): scale rp_ab / (½ (w_a + w_b) + α), a column at a time.
            var dl = mat3x3<f32>(
                scale * rp[0] / (0.5 * (wv + vec3<f32>(wv.x)) + alpha_d),
                scale * rp[1] / (0.5 * (wv + vec3<f32>(wv.y)) + alpha_d),
                scale * rp[2] / (0.5 * (wv + vec3<f32>(wv.z)) + alpha_d),
            );
            dl = q * dl * transpose(q);
            dl = (dl + transpose(dl)) * 0.5;
            if (mat_finite(dl)) {
                let nl = lam_d + dl;
                st.lam0 = vec4<f32>(st.lam0.x, nl[0].x, nl[1].y, nl[2].z);
                st.lam1 = vec4<f32>(nl[0].y, nl[0].z, nl[1].z, 0.0);
                var gd = r * dl;
                let det = determinant(f);
                if (abs(det) > 1.0e-3) {
                    let k = gd * transpose(f);
                    let skew = (k - transpose(k)) * 0.5;
                    gd = gd - skew * (cofactor(f) * (1.0 / det));
                }
                g = g + gd;
            }
        }
    }
    cstate[c] = st;
    let gz = all(g[0] == vec3<f32>(0.0)) && all(g[1] == vec3<f32>(0.0)) && all(g[2] == vec3<f32>(0.0));
    if (gz) {
        store_affine(c, g, vec3<f32>(0.0));
        return;
    }
    let m = g * cr.aqq;
    store_affine(c, m, -(m * mo.rest_com));
}
