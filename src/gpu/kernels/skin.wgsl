// The draw path: each particle's own cluster's deformation gradient F at x (deform),
// every render vertex skinned `v = Σ w_i (x_i + F_i (V − X_i))` and written, in the
// entity's local frame, straight into the mesh allocator's vertex slab (skin), then
// area-weighted normals over the welded topology (normals).
// CPU twins: core::solver::Solver::deformation_gradients, core::skin::{skin_positions,
// skin_normals}.


@compute @workgroup_size(128)
fn deform(@builtin(global_invocation_id) gid: vec3<u32>) {
    let c = gid.x;
    if (c >= params.n) {
        return;
    }
    let mo = cluster_moments(c, false);
    let f = mo.apq * crest[c].aqq;
    fgrad[3u * c] = vec4<f32>(f[0], 0.0);
    fgrad[3u * c + 1u] = vec4<f32>(f[1], 0.0);
    fgrad[3u * c + 2u] = vec4<f32>(f[2], 0.0);
}

fn vertex_dst(vtx: u32) -> u32 {
    let d = draw[bitcast<u32>(vrest[vtx].w)];
    return d.vbase + (vtx - d.vfirst) * d.stride;
}

@compute @workgroup_size(128)
fn skin(@builtin(global_invocation_id) gid: vec3<u32>) {
    let vtx = span.begin + gid.x;
    if (vtx >= span.end) {
        return;
    }
    let inf = vinf[vtx];
    let wt = vwt[vtx];
    let vr = vrest[vtx];
    var acc = vec3<f32>(0.0);
    for (var s = 0u; s < 4u; s = s + 1u) {
        let w = wt[s];
        if (w == 0.0) {
            continue;
        }
        let i = inf[s];
        let f = mat3x3<f32>(fgrad[3u * i].xyz, fgrad[3u * i + 1u].xyz, fgrad[3u * i + 2u].xyz);
        acc = acc + w * (x[i].xyz + f * (vr.xyz - rest[i].xyz));
    }
    let d = draw[bitcast<u32>(vr.w)];
    let h = vec4<f32>(acc, 1.0);
    let local = vec3<f32>(dot(d.m0, h), dot(d.m1, h), dot(d.m2, h));
    let o = d.vbase + (vtx - d.vfirst) * d.stride;
    slab[o] = local.x;
    slab[o + 1u] = local.y;
    slab[o + 2u] = local.z;
}

fn slab_pos(vtx: u32) -> vec3<f32> {
    let o = vertex_dst(vtx);
    return vec3<f32>(slab[o], slab[o + 1u], slab[o + 2u]);
}

// adj: [start per render vertex (vertex_cap + 1)] then triangle corners (3 global render
// vertex ids per adjacent triangle of the vertex's welded vertex, in triangle order).
@compute @workgroup_size(128)
fn normals(@builtin(global_invocation_id) gid: vec3<u32>) {
    let vtx = span.begin + gid.x;
    if (vtx >= span.end) {
        return;
    }
    let nv = params.vertex_cap + 1u;
    var n = vec3<f32>(0.0);
    for (var s = adj[vtx]; s < adj[vtx + 1u]; s = s + 1u) {
        let t = nv + 3u * s;
        let a = slab_pos(adj[t]);
        let b = slab_pos(adj[t + 1u]);
        let c = slab_pos(adj[t + 2u]);
        n = n + cross(b - a, c - a);
    }
    let l2 = dot(n, n);
    if (l2 > 0.0) {
        n = n * (1.0 / sqrt(l2));
    } else {
        n = vec3<f32>(0.0);
    }
    let o = vertex_dst(vtx);
    slab[o + 3u] = n.x;
    slab[o + 4u] = n.y;
    slab[o + 5u] = n.z;
}
