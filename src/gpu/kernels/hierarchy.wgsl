// The coarse levels of hierarchical PBD (Müller 2008): moving positions between level 0
// and a coarse level's own particle range, and prolongation. A level's constraints are
// solved by the cluster and gather kernels run over its range.
// CPU twin: core::solver::Solver::solve_levels.

// The positions at the start of the coarse pass (prolongation reference), kept in the
// level-0 part of p2 (free until level 0's first gather).
@compute @workgroup_size(128)
fn level_snapshot(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= params.n) {
        return;
    }
    aux[i] = x[params.p_base + i];
}

// A level's particles take their level-0 particles' positions. The coarsest level's XPBD
// multipliers start from zero (as level 0's do in predict); the others' were handed down
// by `transfer`.
@compute @workgroup_size(128)
fn level_in(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= range.count) {
        return;
    }
    let g = range.first + gid.x;
    let src = hier[g - params.n];
    x[params.p_base + g] = x[params.p_base + src];
    x[g] = x[src];
    if (range.base == 1u) {
        let st = cstate[g];
        cstate[g] = ClusterState(st.rot, vec4<f32>(0.0), vec4<f32>(0.0));
    }
}

// A level's solved positions go back to their level-0 particles.
@compute @workgroup_size(128)
fn level_out(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= range.count) {
        return;
    }
    let g = range.first + gid.x;
    x[params.p_base + hier[g - params.n]] = x[params.p_base + g];
}

// The finer level's other particles follow their parents: Δx_i = Σ_j w_ij Δx_j, the
// displacements taken since the snapshot. Pinned particles stay at their targets.
@compute @workgroup_size(128)
fn prolong(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= range.count) {
        return;
    }
    let r = range.base + (range.first + gid.x) * 9u;
    let i = hier[r];
    if (pinfo[i].y != NONE) {
        return;
    }
    var d = vec3<f32>(0.0);
    for (var k = 0u; k < 4u; k = k + 1u) {
        let w = bitcast<f32>(hier[r + 5u + k]);
        if (w != 0.0) {
            let j = hier[r + 1u + k];
            d = d + w * (x[params.p_base + j].xyz - aux[j].xyz);
        }
    }
    x[params.p_base + i] = vec4<f32>(aux[i].xyz + d, 0.0);
}

// The finer level's multipliers from this level's: λ_i = Σ_j (w_ij V_i / V_j) λ_j.
@compute @workgroup_size(128)
fn transfer(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= range.count) {
        return;
    }
    let r = range.base + (range.first + gid.x) * 9u;
    let c = hier[r];
    var l0 = vec4<f32>(0.0);
    var l1 = vec4<f32>(0.0);
    for (var k = 0u; k < 4u; k = k + 1u) {
        let w = bitcast<f32>(hier[r + 5u + k]);
        if (w != 0.0) {
            let st = cstate[hier[r + 1u + k]];
            l0 = l0 + w * st.lam0;
            l1 = l1 + w * st.lam1;
        }
    }
    cstate[c] = ClusterState(cstate[c].rot, l0, l1);
}
