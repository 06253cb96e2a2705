// Predict (`v += h g`, `p = x + h v`, pinned particles at their targets, graspers take
// and let go, held particles at their targets; multipliers and collider records reset) and finish (`v = (p − x)/h` with damping, `x = p`).
// CPU twin: core::solver::Solver::step, stages 1 and 3 (where the CPU restores the whole
// state of a diverged step, the GPU holds each diverged particle and flags its body).

// Graspers let go of and take particle i (at x, start of the substep).
// CPU twin: core::colliders::update_grab.
fn update_grab(i: u32) {
    var g = aux[params.grab_base + i];
    if (g.w >= 0.5) {
        let k = u32(g.w) - 1u;
        let keep = k < params.n_colliders && u32(colliders[k].kind_fr.x) == GRASPER
            && colliders[k].kind_fr.z != 0.0;
        if (!keep) {
            g = vec4<f32>(0.0);
        }
    }
    if (g.w < 0.5) {
        let xi = x[i].xyz;
        for (var k = 0u; k < params.n_colliders; k = k + 1u) {
            let c = colliders[k];
            if (u32(c.kind_fr.x) == GRASPER && c.kind_fr.z == 1.0
                && length(xi - c.pos.xyz) <= c.shape.x) {
                g = vec4<f32>(quat_inv_rotate(c.rot, xi - c.pos.xyz), f32(k + 1u));
                break;
            }
        }
    }
    aux[params.grab_base + i] = g;
}

@compute @workgroup_size(128)
fn predict(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x < params.n) {
        predict_one(gid.x);
    }
}

@compute @workgroup_size(128)
fn finish(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x < params.n) {
        finish_one(gid.x);
    }
}

// A substep's finish and the next substep's predict in one dispatch (both per particle),
// between two substeps of one recording (world.rs): one dispatch fewer per substep.
@compute @workgroup_size(128)
fn finish_predict(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x < params.n) {
        finish_one(gid.x);
        predict_one(gid.x);
    }
}

fn predict_one(i: u32) {
    if (asleep(i)) {
        x[params.p_base + i] = x[i];
        return;
    }
    let vv = v[i].xyz + params.gravity.xyz * params.h;
    v[i] = vec4<f32>(vv, 0.0);
    var pp = x[i].xyz + vv * params.h;
    let slot = pinfo[i].y;
    if (slot != NONE) {
        pp = rest[params.pin_base + slot].xyz;
    } else if (params.n_colliders > 0u) {
        update_grab(i);
        let t = grab_target(i);
        if (t.w >= 0.0) {
            pp = t.xyz;
        }
    }
    x[params.p_base + i] = vec4<f32>(pp, 0.0);
    let st = cstate[i];
    cstate[i] = ClusterState(st.rot, vec4<f32>(0.0), vec4<f32>(0.0));
    aux[params.coldp_base + i] = vec4<f32>(0.0, 0.0, 0.0, -1.0);
}

fn finish_one(i: u32) {
    if (asleep(i)) {
        v[i] = vec4<f32>(0.0);
        return;
    }
    let pp = x[params.p_base + i].xyz;
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
