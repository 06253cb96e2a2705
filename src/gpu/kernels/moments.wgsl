// Cluster moments and the polar rotation shared by the cluster and deform kernels.
// CPU twins: core::constraints::{cluster_moments, extract_rotation}.

struct Moments {
    com: vec3<f32>,          // current centre of mass x_cm, m
    apq: mat3x3<f32>,        // A_pq = Σ m (p − x_cm) qᵀ
    rest_com: vec3<f32>,     // rest centre as the f32 members average to, m
};

// `pos` is x or p (chosen by `use_p`).
fn cluster_moments(c: u32, use_p: bool) -> Moments {
    let start = pinfo[c].w;
    let end = pinfo[c + 1u].w;
    // Only the record's first field (not the whole 192-byte ClusterRest).
    let com_mass = crest[c].com_mass;
    let com = com_mass.xyz;
    var origin: vec3<f32>;
    if (use_p) { origin = p[lists[start]].xyz; } else { origin = x[lists[start]].xyz; }
    var mp = vec3<f32>(0.0);
    var mq = vec3<f32>(0.0);
    var a0 = vec3<f32>(0.0);
    var a1 = vec3<f32>(0.0);
    var a2 = vec3<f32>(0.0);
    for (var s = start; s < end; s = s + 1u) {
        let j = lists[s];
        var pj: vec3<f32>;
        if (use_p) { pj = p[j].xyz; } else { pj = x[j].xyz; }
        let r = rest[j];
        let m = r.w;
        let md = (pj - origin) * m;
        let q = r.xyz - com;
        mp = mp + md;
        mq = mq + q * m;
        a0 = a0 + md * q.x;
        a1 = a1 + md * q.y;
        a2 = a2 + md * q.z;
    }
    let inv_m = 1.0 / com_mass.w;
    let c_rel = mp * inv_m;
    let a = mat3x3<f32>(a0, a1, a2) - outer(c_rel, mq);
    return Moments(origin + c_rel, a, com + mq * inv_m);
}

// Müller et al. 2016, warm-started from q (first-order update below 0.25 rad).
fn extract_rotation(a: mat3x3<f32>, q0: vec4<f32>, iterations: u32) -> vec4<f32> {
    var q = q0;
    for (var it = 0u; it < iterations; it = it + 1u) {
        let r = quat_mat(q);
        let num = cross(r[0], a[0]) + cross(r[1], a[1]) + cross(r[2], a[2]);
        let den = abs(dot(r[0], a[0]) + dot(r[1], a[1]) + dot(r[2], a[2])) + 1.0e-9;
        let om = num / den;
        let w = length(om);
        if (!(w == w) || w < 1.0e-6) {
            break;
        }
        var s: vec4<f32>;
        if (w < 0.25) {
            s = vec4<f32>(0.5 * om, 1.0);
        } else {
            let half = 0.5 * w;
            s = vec4<f32>(om / w * sin(half), cos(half));
        }
        let qn = quat_mul(s, q);
        q = qn * (1.0 / length(qn));
    }
    return q;
}
