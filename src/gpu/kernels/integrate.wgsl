// Predict (`v += h g`, `p = x + h v`, pinned particles at their targets; multipliers and
// collider records reset) and finish (`v = (p − x)/h` with damping, `x = p`).
// CPU twin: core::solver::Solver::step, stages 1 and 3 (where the CPU restores the whole
// state of a diverged step, the GPU holds each diverged particle and flags its body).

@compute @workgroup_size(128)
fn predict(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= params.n) {
        return;
    }
    let vv = v[i].xyz + params.gravity.xyz * params.h;
    v[i] = vec4<f32>(vv, 0.0);
    var pp = x[i].xyz + vv * params.h;
    let slot = pinfo[i].y;
    if (slot != NONE) {
        pp = pins[slot].xyz;
    }
    p[i] = vec4<f32>(pp, 0.0);
    let st = cstate[i];
    cstate[i] = ClusterState(st.rot, vec4<f32>(0.0), vec4<f32>(0.0));
    coldp[i] = vec4<f32>(0.0, 0.0, 0.0, -1.0);
}

@compute @workgroup_size(128)
fn finish(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= params.n) {
        return;
    }
    let pp = p[i].xyz;
    let xx = x[i].xyz;
    let vel = (pp - xx) / params.h * params.keep;
    let speed = length(vel);
    if (!(speed <= params.max_speed)) {
        // Diverged (NaN, infinite or too fast): the particle stays where it was, at rest,
        // and its body is flagged, so nothing non-finite reaches the grid or other bodies.
        v[i] = vec4<f32>(0.0);
        atomicOr(&status[pinfo[i].x], 1u);
        return;
    }
    v[i] = vec4<f32>(vel, 0.0);
    x[i] = vec4<f32>(pp, 0.0);
}
