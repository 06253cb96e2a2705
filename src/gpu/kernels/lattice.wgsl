// Newton–multigrid on lattice bodies: one implicit-Euler substep's Newton iterations,
// each a V-cycle (Chebyshev-accelerated block Jacobi or colour-ordered block
// Gauss–Seidel smoothing) and an energy line search.
// CPU twin: core::multigrid (element_forces, element_energy, LatticeMultigrid::prepare,
// vcycle) and the solver's Newton iteration (ElementSolver::Multigrid).
// The bindings are declared by the table in lattice.rs (prepended to this file).

const LWG: u32 = 64u;
const GRASPER: u32 = 4u;
// Line search: α_max 2^-k for k < LINE_CANDIDATES (then 0), the first `part_a()` in
// one pass, the rest in a second pass dispatched only when none of those was taken.
const LINE_CANDIDATES: u32 = 13u;
// First iterate: y = x + s (y − x) for s = 1, ½, ¼, 0.
const FIRST_CANDIDATES: u32 = 4u;
// The first iterate's ties: candidates closer than this fraction of the energy.
const FIRST_TIE: f32 = 1.0e-5;
// Partial sums per workgroup (a reduction's chunk) at the start of `red`.
const RED_STRIDE: u32 = 16u;
// Per-body scalars in `red` (`body_slot`): every step the Newton iteration takes is
// each body's own, so that a body steps as it would alone.
const BODY_SLOTS: u32 = 16u;
const B_ALPHA: u32 = 0u;      // the step chosen by the last `pick`
const B_PENDING: u32 = 1u;    // 1: the line search's second pass decides
const B_CG_ALPHA: u32 = 2u;   // conjugate gradients: the last step α
const B_CG_RZ: u32 = 3u;      // conjugate gradients: the last zᵀ r
const B_CG_BETA: u32 = 4u;    // conjugate gradients: the next direction's β
const B_SHIFT: u32 = 5u;      // + 0..2: the body's translation step (xyz)
const B_MG_ALPHA: u32 = 8u;   // + level: the coarse correction's step
// Indirect dispatches' workgroup counts in `args` (x, y, z each; gpu::lattice's
// `ARGS_*` offsets): the line search's second energy pass, its `pick`, and level 0's
// contact pass (dispatched only where some node has a contact block, a thread a node of
// the list of such nodes, whose length follows).
const ARGS_LINE: u32 = 0u;
const ARGS_PENDING: u32 = 4u;
const ARGS_CONTACT: u32 = 8u;
const ARGS_CONTACT_COUNT: u32 = 12u;

const R_X: u32 = 0u;
const R_Y: u32 = 1u;
const R_T: u32 = 2u;
const R_V: u32 = 3u;
const R_PIN: u32 = 4u;
// Regions of `vecs` (× n_total): right-hand side, correction, residual, prolongated
// coarse correction.
const V_RHS: u32 = 0u;
const V_DELTA: u32 = 1u;
const V_RES: u32 = 2u;
const V_PE: u32 = 3u;
// Material record per body in `mats` (vec4s, MAT_STRIDE of them, from Rust): (μ, λ,
// contact radius, spacing), then the unit cube operator (five vec4, as in `kmat`: see
// `cube_op_row`).
const MAT_OP: u32 = 1u;
// Regions of `ccol` (× n): this substep's collider corrections (xyz, m; w: the last
// collider's index, −1: none); the collider touched in the last substep (x, −1: none),
// this iteration's penalty contacts (y: a bit per collider), at a node's place in it,
// the list of nodes with a contact block that `contacts` makes (z, u32 bits), and
// whether the last particle-contact projection found the node pressed into one of its
// candidates (w, 1 or 0: `pressed_pair`, `pair_hold`).
const C_COL: u32 = 0u;
const C_TOUCH: u32 = 1u;
// Region 2 of `ccol`: the grasp of each node (the offset in the grasper's frame, m; w:
// the grasper's index + 1, 0: free).
const C_GRAB: u32 = 2u;
// Region 3 of `ccol`: the force a node puts on a collider or grasper in this substep
// (xyz, N; w: the collider, −1: none): a grasped node's residual in the last Newton
// iteration, or the reaction of the collider it touches at the substep's end.
const C_NF: u32 = 3u;
// Region 4 of `ccol` (present when the world has particle contacts): per node, where
// its particle-contact candidates (other bodies' nodes) are, as u32 indices into the
// lists after the regions (x..y), and where the nodes whose candidates it is are (z..w).
const C_PAIR: u32 = 4u;
// Penalty stiffness over a particle's own stiffness scale m/h² + (λ + 2μ) s.
const PENALTY: f32 = 1.0e3;
// How far beyond its radius (a fraction of it) a node still touches a collider for the
// collider's force (core::solver's TOUCH_TOLERANCE).
const TOUCH_TOLERANCE: f32 = 0.05;

struct LatticeParams {
    gravity: vec4<f32>,      // m/s²
    h: f32,                  // substep, s
    h2: f32,                 // s²
    keep: f32,               // velocity kept after damping
    rot_iters: u32,
    n: u32,                  // level-0 node slots (the stride of per-particle regions;
                             // the nodes in use end at lv[0].y)
    ne: u32,                 // level-0 element slots (element items of the energy table
                             // are below it, node items from it; in use: lv[0].w)
    levels: u32,
    n_total: u32,            // node slots of all levels (the stride of `vecs` regions)
    order_base: u32,         // start of the colour orders in `topo`
    prol_base: u32,          // start of the prolongation lists in `topo`
    restr_base: u32,         // start of the restriction lists in `topo`
    child_base: u32,         // start of the child element lists in `topo`
    lv: array<vec4<u32>, 8>, // per level: first node, end of its nodes in use, first
                             // element, end of its elements in use (slots past an end are
                             // room for bodies appended later)
    sweeps: vec4<u32>,       // smoothing sweeps: level 0's after the coarse correction,
                             // the levels between, the coarsest; w: the line search's
                             // candidates in its first pass
    colours: array<vec4<u32>, 32>, // per level and colour, where its nodes start and end
                             // in `topo` (16 entries a level)
    misc: vec4<u32>,         // x: colliders; y: substeps; z, w: where the collider
                             // forces' partial sums and totals start in `red`
    cheb: array<vec4<f32>, 8>, // per level: the Chebyshev smoother's 1/θ and ρ²; z: 1 if
                             // the level is smoothed by Chebyshev (else Gauss–Seidel)
    pair: vec4<u32>,         // x: 1 if `ccol` holds particle-contact lists; z: the
                             // contacts' Jacobi relaxation ω_c (f32 bits)
    chunks: vec4<u32>,       // the reductions' chunks: x: where their records start in
                             // `elems`; y: where each table's per-body chunk ranges start
                             // in `elems` (u32s, 4 a vec4); z: body slots (the stride
                             // of per-body regions); w: where the per-body scalars start
                             // in `red`
    count: vec4<u32>,        // x: bodies in use
    nbrs: vec4<u32>,         // x: where level 0's neighbour records start in `elems`
                             // (9 vec4 a level-0 node slot, see `lattice_terms`)
};

// One dispatch's range and mode (a dynamic-offset window of the pass buffer).
struct Pass {
    first: u32,
    count: u32,
    level: u32,
    mode: u32,
};

fn corner_sign(j: u32) -> vec3<f32> {
    return vec3<f32>(
        select(-1.0, 1.0, (j & 1u) != 0u),
        select(-1.0, 1.0, (j & 2u) != 0u),
        select(-1.0, 1.0, (j & 4u) != 0u),
    );
}

fn corner(e: u32, k: u32) -> u32 {
    return elems[3u * e + k / 4u][k % 4u];
}

// Whether node slot j (any level) holds a node, not room for bodies appended later.
fn in_use(j: u32) -> bool {
    var l = 0u;
    for (var k = 1u; k < params.levels; k = k + 1u) {
        if (j >= params.lv[k].x) {
            l = k;
        }
    }
    return j < params.lv[l].y;
}

// Held out of the V-cycle: pinned nodes and nodes outside the lattice.
fn held(j: u32) -> bool {
    return nodes[j].y != 0.0;
}

// Held in this substep: `held`, or grasped.
fn held_now(j: u32) -> bool {
    return held(j) || ccol[C_GRAB * params.n + j].w > 0.5;
}

// Held in the V-cycle: on level 0 `held_now` (grasped particles keep a zero correction,
// as the conjugate gradients keep them; core::multigrid's MgWork::held), above `held`.
fn held_in_cycle(j: u32) -> bool {
    if (j < params.n) {
        return held_now(j);
    }
    return held(j);
}

// Where a grasped node must be (xyz) and whether its grasper exists (w = 1; else 0).
fn grasp_target(j: u32) -> vec4<f32> {
    let g = ccol[C_GRAB * params.n + j];
    if (g.w < 0.5) {
        return vec4<f32>(0.0);
    }
    let k = u32(g.w) - 1u;
    if (k >= params.misc.x) {
        return vec4<f32>(0.0);
    }
    let c = cols[k];
    return vec4<f32>(c.pos.xyz + quat_rotate(c.rot, g.xyz), 1.0);
}

// Node j's particle-contact candidates (x..y) and the nodes that list it (z..w), as
// positions in the lists (empty without particle contacts).
fn pair_range(j: u32) -> vec4<u32> {
    if (params.pair.x == 0u) {
        return vec4<u32>(0u);
    }
    return bitcast<vec4<u32>>(ccol[C_PAIR * params.n + j]);
}

// The node at position s of the particle-contact lists.
fn pair_at(s: u32) -> u32 {
    let v = ccol[(C_PAIR + 1u) * params.n + s / 4u];
    return bitcast<u32>(v[s % 4u]);
}

// Deformation gradient at the centre of a cube of edge `size` (core::element::element_gradient),
// its seven corner terms written out (a small array indexed in a loop is kept in slow
// per-thread memory, not registers).
fn element_gradient(x: array<vec3<f32>, 8>, size: f32) -> mat3x3<f32> {
    let s = 1.0 / (4.0 * size);
    let o = x[0];
    var f = outer(x[1] - o, vec3<f32>(s, -s, -s));
    f = f + outer(x[2] - o, vec3<f32>(-s, s, -s));
    f = f + outer(x[3] - o, vec3<f32>(s, s, -s));
    f = f + outer(x[4] - o, vec3<f32>(-s, -s, s));
    f = f + outer(x[5] - o, vec3<f32>(s, -s, s));
    f = f + outer(x[6] - o, vec3<f32>(-s, s, s));
    f = f + outer(x[7] - o, vec3<f32>(s, s, s));
    return f;
}

fn identity3() -> mat3x3<f32> {
    return mat3x3<f32>(vec3<f32>(1.0, 0.0, 0.0), vec3<f32>(0.0, 1.0, 0.0), vec3<f32>(0.0, 0.0, 1.0));
}

// Element e's elastic energy (J) from its deformation gradient f with rotation r held:
// μ V |sym(Rᵀ F) − I|² + ½ λ V (det F − 1)² (core::multigrid::element_energy without
// the hourglass term).
fn elastic_energy(e: u32, f: mat3x3<f32>, r: mat3x3<f32>) -> f32 {
    let info = elems[3u * e + 2u];
    let lame = mats[info.y * MAT_STRIDE];
    let rtf = transpose(r) * f;
    let s = (rtf + transpose(rtf)) * 0.5 - identity3();
    let ee = dot(s[0], s[0]) + dot(s[1], s[1]) + dot(s[2], s[2]);
    let j = determinant(f) - 1.0;
    return bitcast<f32>(info.w) * (lame.x * ee + 0.5 * lame.y * (j * j));
}

fn load_x(e: u32, region: u32) -> array<vec3<f32>, 8> {
    let o = region * params.n;
    let c0 = elems[3u * e];
    let c1 = elems[3u * e + 1u];
    return array<vec3<f32>, 8>(pos[o + c0.x].xyz, pos[o + c0.y].xyz, pos[o + c0.z].xyz,
                               pos[o + c0.w].xyz, pos[o + c1.x].xyz, pos[o + c1.y].xyz,
                               pos[o + c1.z].xyz, pos[o + c1.w].xyz);
}

// Corner values relative to corner 0.
fn relative8(x: array<vec3<f32>, 8>) -> array<vec3<f32>, 8> {
    let o = x[0];
    return array<vec3<f32>, 8>(o - o, x[1] - o, x[2] - o, x[3] - o, x[4] - o, x[5] - o,
                               x[6] - o, x[7] - o);
}

// The velocity steps of element e's corners (none at a held corner).
fn corner_velocity_steps(e: u32) -> array<vec3<f32>, 8> {
    let c0 = elems[3u * e];
    let c1 = elems[3u * e + 1u];
    return array<vec3<f32>, 8>(free_step(c0.x, velocity_step(c0.x)), free_step(c0.y, velocity_step(c0.y)),
                               free_step(c0.z, velocity_step(c0.z)), free_step(c0.w, velocity_step(c0.w)),
                               free_step(c1.x, velocity_step(c1.x)), free_step(c1.y, velocity_step(c1.y)),
                               free_step(c1.z, velocity_step(c1.z)), free_step(c1.w, velocity_step(c1.w)));
}

// The V-cycle's correction at node j (`direction`'s mode 1), none where it is held now.
fn line_step(j: u32) -> vec3<f32> {
    return free_step(j, vecs[V_DELTA * params.n_total + j].xyz);
}

// The V-cycle's correction at element e's corners (none at a held corner).
fn corner_line_steps(e: u32) -> array<vec3<f32>, 8> {
    let c0 = elems[3u * e];
    let c1 = elems[3u * e + 1u];
    return array<vec3<f32>, 8>(line_step(c0.x), line_step(c0.y), line_step(c0.z), line_step(c0.w),
                               line_step(c1.x), line_step(c1.y), line_step(c1.z), line_step(c1.w));
}

// Search direction of node j: the V-cycle's correction (mode 1) or the step the
// velocity makes, y − x (mode 0).
fn direction(j: u32, mode: u32) -> vec3<f32> {
    if (mode == 0u) {
        return velocity_step(j);
    }
    return vecs[V_DELTA * params.n_total + j].xyz;
}

// The step the velocity makes at node j, y − x (`direction`'s mode 0).
fn velocity_step(j: u32) -> vec3<f32> {
    return pos[R_Y * params.n + j].xyz - pos[R_X * params.n + j].xyz;
}

// Direction d of node j where it moves in this substep, else none (held now).
fn free_step(j: u32, d: vec3<f32>) -> vec3<f32> {
    return select(d, vec3<f32>(0.0), held_now(j));
}

// The first iterate's candidates y + s (y − x), s = 0, −½, −¾, −1, as one vector.
const FIRST_STEPS: vec4<f32> = vec4<f32>(0.0, -0.5, -0.75, -1.0);

fn candidate(k: u32, mode: u32) -> f32 {
    if (mode == 0u) {
        return FIRST_STEPS[k];
    }
    return exp2(-f32(k));
}

// The line search's candidates in its first pass.
fn part_a() -> u32 {
    return min(params.sweeps.w, LINE_CANDIDATES);
}

// Candidates of an energy pass: mode 0 the first iterate's, mode 1 the line search's
// first `part_a()`, mode 2 the rest.
fn candidates(mode: u32) -> u32 {
    if (mode == 0u) {
        return FIRST_CANDIDATES;
    }
    return select(LINE_CANDIDATES - part_a(), part_a(), mode == 1u);
}

// Index of an energy pass's first candidate.
fn first_candidate(mode: u32) -> u32 {
    return select(0u, part_a(), mode == 2u);
}

// A workgroup's partial sums, sum k of thread t at wsum[k][t] (a warp's threads on
// consecutive words: no two of them on one bank).
var<workgroup> wsum: array<array<f32, 64>, 16>;

// The workgroup's sums wsum[·][0] (after a reduction) as one array.
fn wsum_row() -> array<f32, 16> {
    var w: array<f32, 16>;
    for (var k = 0u; k < 16u; k = k + 1u) {
        w[k] = wsum[k][0];
    }
    return w;
}

// Sums `wsum[k][·]` for k < count over the workgroup into partial `wid`.
fn reduce_partials(lid: u32, wid: u32, count: u32) {
    for (var stride = LWG / 2u; stride > 0u; stride = stride / 2u) {
        workgroupBarrier();
        if (lid < stride) {
            for (var k = 0u; k < count; k = k + 1u) {
                wsum[k][lid] = wsum[k][lid] + wsum[k][lid + stride];
            }
        }
    }
    if (lid == 0u) {
        for (var k = 0u; k < count; k = k + 1u) {
            red[wid * RED_STRIDE + k] = wsum[k][0];
        }
    }
}

// Slot k of body b's scalars in `red`.
fn body_slot(b: u32, k: u32) -> u32 {
    return params.chunks.w + b * BODY_SLOTS + k;
}

// The body of node j (any level).
fn node_body(j: u32) -> u32 {
    return u32(nodes[j].w);
}

// Chunk c of the reductions (a run of one body's items of one table): x its first item,
// y its item count, z its body. A reduction's workgroup sums one chunk, so each body's
// sums are its own chunks' (`pick`).
fn chunk(c: u32) -> vec4<u32> {
    return elems[params.chunks.x + c];
}

// The chunks of table t (0: the energy's elements and nodes; 1 + l: level l's nodes)
// that are body b's, as indices from the table's first chunk: x .. y.
fn body_chunks(t: u32, b: u32) -> vec2<u32> {
    let i = params.chunks.y + t * (params.chunks.z + 1u) + b;
    return vec2<u32>(elems[i / 4u][i % 4u], elems[(i + 1u) / 4u][(i + 1u) % 4u]);
}

// Predict: inertial target x̃ = x + h (v + h g) and first iterate y = x + h v (pinned
// nodes: their targets; nodes outside the lattice: x̃).
@compute @workgroup_size(64)
fn predict(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = gid.x;
    if (j >= params.lv[0].y) {
        return;
    }
    let n = params.n;
    let x = pos[R_X * n + j];
    let v = pos[R_V * n + j].xyz;
    let t = x.xyz + (v + params.gravity.xyz * params.h) * params.h;
    var y = x.xyz + v * params.h;
    let pin = pos[R_PIN * n + j];
    if (pin.w != 0.0) {
        y = pin.xyz;
    } else if (held(j)) {
        y = t;
    }
    // Graspers let go and take nodes (core::colliders::update_grab); held nodes start at
    // their targets.
    if (pin.w == 0.0 && params.misc.x > 0u) {
        var g = ccol[C_GRAB * n + j];
        if (g.w > 0.5) {
            let k = u32(g.w) - 1u;
            let keep = k < params.misc.x && u32(cols[k].kind_fr.x) == GRASPER
                && cols[k].kind_fr.z != 0.0;
            if (!keep) {
                g = vec4<f32>(0.0);
            }
        }
        if (g.w < 0.5) {
            for (var k = 0u; k < params.misc.x; k = k + 1u) {
                let c = cols[k];
                if (u32(c.kind_fr.x) == GRASPER && c.kind_fr.z == 1.0
                    && length(x.xyz - c.pos.xyz) <= c.shape.x) {
                    g = vec4<f32>(quat_inv_rotate(c.rot, x.xyz - c.pos.xyz), f32(k + 1u));
                    break;
                }
            }
        }
        ccol[C_GRAB * n + j] = g;
        let gt = grasp_target(j);
        if (gt.w > 0.0) {
            y = gt.xyz;
        }
    }
    pos[R_T * n + j] = vec4<f32>(t, 0.0);
    pos[R_Y * n + j] = vec4<f32>(y, node_tag(j));
    ccol[C_COL * n + j] = vec4<f32>(0.0, 0.0, 0.0, -1.0);
}

// What the particle contacts read of a partner node with its iterate, in the w of its
// `R_Y` slot (set by `predict`, kept by every later write of the substep): its contact
// radius (m), the sign bit set where it is held now (`held_now`, fixed for the substep
// once `predict` has updated the grasps).
fn node_tag(j: u32) -> f32 {
    let r = contact_scale(j).x;
    return select(r, -r, held_now(j));
}

// A node's contact radius (m) from its tag (`node_tag`).
fn tag_radius(w: f32) -> f32 {
    return abs(w);
}

// Whether a node is held now, from its tag (`node_tag`; the sign bit, so a radius of 0
// keeps it).
fn tag_held(w: f32) -> bool {
    return (bitcast<u32>(w) & 0x80000000u) != 0u;
}

// `free_step` from a node's tag: direction d where the node moves in this substep, else
// none.
fn tag_free_step(w: f32, d: vec3<f32>) -> vec3<f32> {
    return select(d, vec3<f32>(0.0), tag_held(w));
}

// The closest distance of two nodes over their straight paths from the step's start to
// candidate a of the first iterate: their offset r1 + t v for t from −1 (the start) to a
// (r1 the offset at the inertial iterate, v the difference of their steps).
fn swept_gap(r1: vec3<f32>, v: vec3<f32>, a: f32) -> f32 {
    let vv = dot(v, v);
    var t = a;
    if (vv > 0.0) {
        t = clamp(-dot(r1, v) / vv, -1.0, a);
    }
    return length(r1 + v * t);
}

// Whether the line search's second pass skips the body at hand (not pending): the body
// of an `energy` workgroup's chunk, or the body a `pick_pending` workgroup sums next.
// Written by thread 0, read through `workgroupUniformLoad` (a uniform branch).
var<workgroup> chunk_idle: u32;

// The first iterate's energy changes: for each of the FIRST_CANDIDATES (4) candidates
// s = 0, −½, −¾, −1 (FIRST_STEPS) its energy's change from the first, each element's
// rotation refined per candidate; then the energy's scale at the first candidate (for
// `pick`'s ties). One partial sum each per chunk of the energy table (items below `ne`
// elements, the rest nodes). A kernel of its own beside the line search's `energy`: its
// four candidates stay in registers.
@compute @workgroup_size(64)
fn energy_first(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wg: vec3<u32>) {
    var acc = vec4<f32>(0.0);
    var scale = 0.0;
    let ch = chunk(pc.first + wg.x);
    let end = ch.x + ch.y;
    for (var i = ch.x + lid; i < end; i = i + LWG) {
        if (i < params.ne) {
            let e = i;
            let y = load_x(e, R_Y);
            let d = corner_velocity_steps(e);
            let info = elems[3u * e + 2u];
            let size = bitcast<f32>(info.z);
            let q0 = rot[e];
            // The first iterate: each candidate's rotation refined from q0 along
            // F(y + a d) = F(y) + a F(d). The hourglass coordinates are linear along
            // the step too, so they are summed once and turned into each candidate's
            // rotation.
            let f0 = element_gradient(y, size);
            let f1 = element_gradient(d, size);
            // The FIRST_CANDIDATES (4) candidates s = 0, −½, −¾, −1 (FIRST_STEPS)
            // written out, so that their rotations and energies stay in registers.
            let fa = f0 + f1 * FIRST_STEPS.x;
            let fb = f0 + f1 * FIRST_STEPS.y;
            let fc = f0 + f1 * FIRST_STEPS.z;
            let fd = f0 + f1 * FIRST_STEPS.w;
            let ra = quat_mat(extract_rotation(fa, q0, params.rot_iters));
            let rb = quat_mat(extract_rotation(fb, q0, params.rot_iters));
            let rc = quat_mat(extract_rotation(fc, q0, params.rot_iters));
            let rd = quat_mat(extract_rotation(fd, q0, params.rot_iters));
            var ea = elastic_energy(e, fa, ra);
            var eb = elastic_energy(e, fb, rb);
            var ec = elastic_energy(e, fc, rc);
            var ed = elastic_energy(e, fd, rd);
            let dy = relative8(y);
            let dd = relative8(d);
            // Hourglass: ½ (V/h²) qᵀ Q q with q = R_aᵀ q(y + a d) in each candidate's
            // own rotation.
            let op = material_op(info.y);
            let hy = hourglass_coords(dy);
            let hd = hourglass_coords(dd);
            let half = 0.5 * bitcast<f32>(info.w) / (size * size);
            let qa = hg_turn(transpose(ra), hg_add(hy, hd, FIRST_STEPS.x));
            let qb = hg_turn(transpose(rb), hg_add(hy, hd, FIRST_STEPS.y));
            let qc = hg_turn(transpose(rc), hg_add(hy, hd, FIRST_STEPS.z));
            let qd = hg_turn(transpose(rd), hg_add(hy, hd, FIRST_STEPS.w));
            ea = ea + half * hg_dot(qa, hourglass_response(op, qa));
            eb = eb + half * hg_dot(qb, hourglass_response(op, qb));
            ec = ec + half * hg_dot(qc, hourglass_response(op, qc));
            ed = ed + half * hg_dot(qd, hourglass_response(op, qd));
            // Each candidate's change from the first (0, or NaN where the energy is
            // not finite).
            acc = acc + vec4<f32>(ea - ea, eb - ea, ec - ea, ed - ea);
            scale = scale + abs(ea);
        } else {
            let j = i - params.ne;
            if (!held_now(j)) {
                let n = params.n;
                let d = velocity_step(j);
                let u = pos[R_Y * n + j].xyz - pos[R_T * n + j].xyz;
                let w = 0.5 * nodes[j].x / params.h2;
                acc = acc + w * FIRST_STEPS * (2.0 * dot(d, u) + FIRST_STEPS * dot(d, d));
                scale = scale + w * dot(u, u);
                // Particle contacts this node holds: ½ k depth² with both nodes moving
                // along the step, each candidate pair's overlap weighed at its closest
                // along the way to each candidate (core::solver's pair_overlap_energy).
                let pr = pair_range(j);
                if (pr.x < pr.y) {
                    let sc = contact_scale(j);
                    let y = pos[R_Y * n + j].xyz;
                    for (var s = pr.x; s < pr.y; s = s + 1u) {
                        let i = pair_at(s);
                        let yi = pos[R_Y * n + i];
                        let reach = sc.x + tag_radius(yi.w);
                        let di = tag_free_step(yi.w, yi.xyz - pos[R_X * n + i].xyz);
                        let r1 = y - yi.xyz;
                        let v = d - di;
                        let o0 = max(reach - swept_gap(r1, v, 0.0), 0.0);
                        let oa = max(vec4<f32>(reach - swept_gap(r1, v, FIRST_STEPS.x),
                                               reach - swept_gap(r1, v, FIRST_STEPS.y),
                                               reach - swept_gap(r1, v, FIRST_STEPS.z),
                                               reach - swept_gap(r1, v, FIRST_STEPS.w)),
                                     vec4<f32>(0.0));
                        acc = acc + 0.5 * sc.y * (oa * oa - o0 * o0);
                    }
                }
            }
        }
    }
    wsum[0][lid] = acc.x;
    wsum[1][lid] = acc.y;
    wsum[2][lid] = acc.z;
    wsum[3][lid] = acc.w;
    wsum[FIRST_CANDIDATES][lid] = scale;
    reduce_partials(lid, wg.x, FIRST_CANDIDATES + 1u);
}

// The line search's candidates 4 blk .. 4 blk + 3 of pass `mode` (`candidate`), as one
// vector (past the pass's last candidate: more halvings, computed and not summed).
fn line_block(blk: u32, mode: u32) -> vec4<f32> {
    let k = first_candidate(mode) + 4u * blk;
    return vec4<f32>(candidate(k, 1u), candidate(k + 1u, 1u), candidate(k + 2u, 1u),
                     candidate(k + 3u, 1u));
}

// An element's energy changes at the step's candidates `av` added to `acc`, from its
// coefficients along the step (rotation held): a (lin + a quad) + ½ λ V ((J_a − 1)² −
// (J_0 − 1)²), J_a = det(F(y) + a F(d)), as a product without cancellation (`vl` is
// ½ λ V).
fn element_line(acc: vec4<f32>, av: vec4<f32>, lin: f32, quad: f32, f0: mat3x3<f32>,
                f1: mat3x3<f32>, j0: f32, vl: f32) -> vec4<f32> {
    let ja = vec4<f32>(determinant(f0 + f1 * av.x), determinant(f0 + f1 * av.y),
                       determinant(f0 + f1 * av.z), determinant(f0 + f1 * av.w));
    let vol_term = vl * ((ja - j0) * (ja + j0 - 2.0));
    return acc + av * (lin + av * quad) + vol_term;
}

// Free node j's energy changes at the step's candidates `av` added to `acc`: its inertia,
// its penalty contacts with the colliders it touches (½ k depth² along the step) and the
// particle contacts it holds (½ k depth² with both nodes moving along the step, the
// pairs in contact at the line search's start, as the Newton iteration's forces).
fn node_line(acc: vec4<f32>, j: u32, av: vec4<f32>) -> vec4<f32> {
    let n = params.n;
    let d = vecs[V_DELTA * params.n_total + j].xyz;
    let y = pos[R_Y * n + j].xyz;
    let u = y - pos[R_T * n + j].xyz;
    let w = 0.5 * nodes[j].x / params.h2;
    var out = acc + w * av * (2.0 * dot(d, u) + av * dot(d, d));
    let mask = bitcast<u32>(ccol[C_TOUCH * n + j].y);
    if (mask != 0u) {
        let sc = contact_scale(j);
        for (var c = 0u; c < params.misc.x; c = c + 1u) {
            if ((mask & (1u << c)) == 0u) {
                continue;
            }
            let col = cols[c];
            let d0 = sc.x - collider_sdf(col, y).w;
            let da = sc.x - vec4<f32>(collider_sdf(col, y + d * av.x).w, collider_sdf(col, y + d * av.y).w,
                                      collider_sdf(col, y + d * av.z).w, collider_sdf(col, y + d * av.w).w);
            out = out + 0.5 * sc.y * (da * da - d0 * d0);
        }
    }
    let pr = pair_range(j);
    if (pr.x < pr.y) {
        let sc = contact_scale(j);
        let hold = pair_hold(j);
        for (var s = pr.x; s < pr.y; s = s + 1u) {
            let i = pair_at(s);
            let yt = pos[R_Y * n + i];
            let yi = yt.xyz;
            let reach = sc.x + tag_radius(yt.w);
            let len0 = length(y - yi);
            if (len0 >= reach * hold || len0 <= 1e-12) {
                continue;
            }
            let di = tag_free_step(yt.w, vecs[V_DELTA * params.n_total + i].xyz);
            let d0 = reach - len0;
            let da = reach - vec4<f32>(length(y + d * av.x - yi - di * av.x), length(y + d * av.y - yi - di * av.y),
                                       length(y + d * av.z - yi - di * av.z), length(y + d * av.w - yi - di * av.w));
            out = out + 0.5 * sc.y * (da * da - d0 * d0);
        }
    }
    return out;
}

// Stores this thread's line-search sums 4 blk .. 4 blk + 3 (those below kc) in wsum.
fn store_block(blk: u32, v: vec4<f32>, kc: u32, lid: u32) {
    for (var c = 0u; c < 4u; c = c + 1u) {
        if (4u * blk + c < kc) {
            wsum[4u * blk + c][lid] = v[c];
        }
    }
}

// The line search's energy changes along the V-cycle's correction (rotations held): mode
// 1 its first `part_a()` candidates, mode 2 the rest, for the bodies whose first
// candidates all failed. One partial sum per candidate and chunk of the energy table.
// The candidates go four at a time, each four in a vector (no array indexed in a loop).
@compute @workgroup_size(64)
fn energy(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wg: vec3<u32>) {
    let mode = pc.mode;
    let kc = candidates(mode);
    let blocks = (kc + 3u) / 4u;
    let a0 = line_block(0u, mode);
    let a1 = line_block(1u, mode);
    let a2 = line_block(2u, mode);
    let a3 = line_block(3u, mode);
    var acc0 = vec4<f32>(0.0);
    var acc1 = vec4<f32>(0.0);
    var acc2 = vec4<f32>(0.0);
    var acc3 = vec4<f32>(0.0);
    let ch = chunk(pc.first + wg.x);
    let end = ch.x + ch.y;
    if (mode == 2u) {
        // The second pass is for the pending bodies only: a chunk of another body leaves
        // at once (its partial sums are not read), however few bodies are pending.
        if (lid == 0u) {
            chunk_idle = u32(red[body_slot(ch.z, B_PENDING)] < 0.5);
        }
        if (workgroupUniformLoad(&chunk_idle) != 0u) {
            return;
        }
    }
    for (var i = ch.x + lid; i < end; i = i + LWG) {
        if (i < params.ne) {
            let e = i;
            let y = load_x(e, R_Y);
            let d = corner_line_steps(e);
            let info = elems[3u * e + 2u];
            let size = bitcast<f32>(info.z);
            // Rotation held: the gradient and the hourglass amplitudes are linear
            // along the step, F(y + a d) = F(y) + a F(d) (likewise c), so each
            // candidate's energy needs no corner loop.
            let r = quat_mat(rot[e]);
            let rt = transpose(r);
            let f0 = element_gradient(y, size);
            let f1 = element_gradient(d, size);
            // Along the step the energy is a polynomial in a: the hourglass term
            // ½ Σ k_m V/h² c_m² and μ V |sym(Rᵀ F) − I|² are quadratic (F and c_m
            // linear in a), det F cubic. Each candidate's change from a = 0 is summed
            // from the coefficients (lin a + quad a², and the volume term apart).
            let vol = bitcast<f32>(info.w);
            let scale = vol / (size * size);
            // Hourglass: ½ (V/h²) qᵀ Q q with q = Rᵀ q(y + a d), linear in a.
            let qy = hg_turn(rt, hourglass_coords(relative8(y)));
            let qd = hg_turn(rt, hourglass_coords(relative8(d)));
            let rd = hourglass_response(material_op(info.y), qd);
            let h1 = scale * hg_dot(qy, rd);
            let h2 = 0.5 * scale * hg_dot(qd, rd);
            let lame = mats[info.y * MAT_STRIDE];
            let rtf0 = rt * f0;
            let rtf1 = rt * f1;
            let s0 = (rtf0 + transpose(rtf0)) * 0.5 - identity3();
            let s1 = (rtf1 + transpose(rtf1)) * 0.5;
            let e01 = dot(s0[0], s1[0]) + dot(s0[1], s1[1]) + dot(s0[2], s1[2]);
            let e11 = dot(s1[0], s1[0]) + dot(s1[1], s1[1]) + dot(s1[2], s1[2]);
            let j0 = determinant(f0);
            let lin = vol * lame.x * 2.0 * e01 + h1;
            let quad = vol * lame.x * e11 + h2;
            let vl = 0.5 * vol * lame.y;
            acc0 = element_line(acc0, a0, lin, quad, f0, f1, j0, vl);
            if (blocks > 1u) {
                acc1 = element_line(acc1, a1, lin, quad, f0, f1, j0, vl);
            }
            if (blocks > 2u) {
                acc2 = element_line(acc2, a2, lin, quad, f0, f1, j0, vl);
            }
            if (blocks > 3u) {
                acc3 = element_line(acc3, a3, lin, quad, f0, f1, j0, vl);
            }
        } else {
            let j = i - params.ne;
            if (!held_now(j)) {
                acc0 = node_line(acc0, j, a0);
                if (blocks > 1u) {
                    acc1 = node_line(acc1, j, a1);
                }
                if (blocks > 2u) {
                    acc2 = node_line(acc2, j, a2);
                }
                if (blocks > 3u) {
                    acc3 = node_line(acc3, j, a3);
                }
            }
        }
    }
    store_block(0u, acc0, kc, lid);
    store_block(1u, acc1, kc, lid);
    store_block(2u, acc2, kc, lid);
    store_block(3u, acc3, kc, lid);
    reduce_partials(lid, wg.x, kc);
}

// Per body (workgroups striding over the bodies): sums the body's chunks' partial sums
// and picks its step. mode 0: the first iterate's s of lowest energy (s = 1 unless
// another is lower); mode 1: the first of the line search's first candidates that does
// not raise the body's energy (else 0, the body pending, and the second pass's
// workgroups, `pc.count`, and its own for mode 4 into `args`); mode 4 (`pick_pending`,
// dispatched only then): for a pending body, the first of the second pass's candidates
// that does not, else 0; mode 3: the
// coarse correction's step of level `pc.level`; conjugate gradients: mode 5 the next
// direction's β, mode 6 the step α along the direction and zᵀ r; mode 7 the body's
// translation step (`translate_terms`); mode 8 the two-direction step's weights
// (`cg_two_terms`).
@compute @workgroup_size(64)
fn pick(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wg: vec3<u32>,
        @builtin(num_workgroups) nwg: vec3<u32>) {
    // The line search's second pass (and its pick) where a body's first candidates all
    // failed; `advance` sets them back to none.
    if (pick_bodies(lid, wg.x, nwg.x, pc.mode) && pc.mode == 1u) {
        atomicStore(&args[ARGS_LINE], pc.count);
        atomicStore(&args[ARGS_PENDING], nwg.x);
    }
}

// `pick`'s mode 4, dispatched (indirectly) only where some body's first line-search
// candidates all failed; a kernel of its own, as an indirect dispatch may not write the
// buffer its count is in.
@compute @workgroup_size(64)
fn pick_pending(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wg: vec3<u32>,
                @builtin(num_workgroups) nwg: vec3<u32>) {
    pick_bodies(lid, wg.x, nwg.x, 4u);
}

// `pick` of workgroup `wid` of `groups` in mode `mode`: whether a body it picked for is
// left pending (mode 1).
fn pick_bodies(lid: u32, wid: u32, groups: u32, mode: u32) -> bool {
    // The sums this mode reads, and their table.
    var used = 2u;
    var table = 0u;
    var pending = false;
    if (mode == 0u) {
        used = FIRST_CANDIDATES + 1u;
    } else if (mode == 1u) {
        used = part_a();
    } else if (mode == 4u) {
        used = LINE_CANDIDATES - part_a();
    } else if (mode == 5u) {
        used = 1u;
        table = 1u;
    } else if (mode == 6u) {
        used = 3u;
        table = 1u;
    } else if (mode == 7u) {
        used = 10u;
        table = 1u;
    } else if (mode == 8u) {
        used = 5u;
    } else {
        table = 1u + pc.level;
    }
    for (var b = wid; b < params.count.x; b = b + groups) {
        let r = body_chunks(table, b);
        // The last body's sums have been read.
        workgroupBarrier();
        if (mode == 4u) {
            // The second pass summed only the pending bodies' chunks.
            if (lid == 0u) {
                chunk_idle = u32(red[body_slot(b, B_PENDING)] < 0.5);
            }
            if (workgroupUniformLoad(&chunk_idle) != 0u) {
                continue;
            }
        }
        // Each sum in its own loop over the chunks (no array indexed at run time). A
        // body of many chunks (a large one: more than four a thread) is read four chunks
        // a thread at a time into four sums, so that the loads are in flight together;
        // up to four a thread, each thread's sum is the plain sum of its chunks.
        for (var k = 0u; k < used; k = k + 1u) {
            var a0 = 0.0;
            var a1 = 0.0;
            var a2 = 0.0;
            var a3 = 0.0;
            var w = r.x + lid;
            if (r.y - r.x > 4u * LWG) {
                for (; w + 3u * LWG < r.y; w = w + 4u * LWG) {
                    a0 = a0 + red[w * RED_STRIDE + k];
                    a1 = a1 + red[(w + LWG) * RED_STRIDE + k];
                    a2 = a2 + red[(w + 2u * LWG) * RED_STRIDE + k];
                    a3 = a3 + red[(w + 3u * LWG) * RED_STRIDE + k];
                }
            }
            for (; w < r.y; w = w + LWG) {
                a0 = a0 + red[w * RED_STRIDE + k];
            }
            wsum[k][lid] = (a0 + a1) + (a2 + a3);
        }
        for (var stride = LWG / 2u; stride > 0u; stride = stride / 2u) {
            workgroupBarrier();
            if (lid < stride) {
                for (var k = 0u; k < used; k = k + 1u) {
                    wsum[k][lid] = wsum[k][lid] + wsum[k][lid + stride];
                }
            }
        }
        if (lid == 0u && pick_body(b, mode)) {
            pending = true;
        }
    }
    return pending;
}

// `pick`'s choice for body b from the sums in wsum[·][0]: whether the body is left pending
// (mode 1: none of the line search's first candidates taken).
fn pick_body(b: u32, mode: u32) -> bool {
    if (mode == 0u) {
        // A candidate is taken only where it lowers the energy by more than FIRST_TIE of
        // its scale; closer, the energies tie to rounding and s = 1 stays
        // (core::solver's first iterate).
        var best = 0u;
        let tie = FIRST_TIE * wsum[FIRST_CANDIDATES][0];
        for (var k = 1u; k < FIRST_CANDIDATES; k = k + 1u) {
            if (wsum[k][0] < wsum[best][0] - tie) {
                best = k;
            }
        }
        red[body_slot(b, B_ALPHA)] = candidate(best, 0u);
    } else if (mode == 1u) {
        // The line search's first candidates; the rest only if none of them is taken.
        var a = 0.0;
        var found = false;
        for (var k = 0u; k < part_a(); k = k + 1u) {
            if (wsum[k][0] <= 0.0) {
                a = candidate(k, 1u);
                found = true;
                break;
            }
        }
        red[body_slot(b, B_ALPHA)] = a;
        red[body_slot(b, B_PENDING)] = select(1.0, 0.0, found);
        return !found;
    } else if (mode == 4u) {
        if (red[body_slot(b, B_PENDING)] > 0.5) {
            var a = 0.0;
            for (var k = 0u; k < LINE_CANDIDATES - part_a(); k = k + 1u) {
                if (wsum[k][0] <= 0.0) {
                    a = candidate(part_a() + k, 1u);
                    break;
                }
            }
            red[body_slot(b, B_ALPHA)] = a;
            red[body_slot(b, B_PENDING)] = 0.0;
        }
    } else if (mode == 5u) {
        let beta = -red[body_slot(b, B_CG_ALPHA)] * wsum[0][0] / red[body_slot(b, B_CG_RZ)];
        red[body_slot(b, B_CG_BETA)] = select(0.0, beta, is_finite_f(beta));
    } else if (mode == 6u) {
        var a = 0.0;
        if (wsum[0][0] > 0.0) {
            a = wsum[1][0] / wsum[0][0];
        }
        red[body_slot(b, B_CG_ALPHA)] = select(0.0, a, is_finite_f(a));
        red[body_slot(b, B_CG_RZ)] = wsum[2][0];
    } else if (mode == 7u) {
        // The translation step (Σ m/h² I + S)⁻¹ Σ r, none for a body with a held node.
        var t = vec3<f32>(0.0);
        if (wsum[9][0] < 0.5) {
            let w = wsum_row();
            let a = mat3x3<f32>(vec3<f32>(w[3], w[6], w[7]), vec3<f32>(w[6], w[4], w[8]),
                                vec3<f32>(w[7], w[8], w[5]));
            t = spd_inverse(a) * vec3<f32>(w[0], w[1], w[2]);
        }
        if (!is_finite_f(t.x) || !is_finite_f(t.y) || !is_finite_f(t.z)) {
            t = vec3<f32>(0.0);
        }
        red[body_slot(b, B_SHIFT)] = t.x;
        red[body_slot(b, B_SHIFT + 1u)] = t.y;
        red[body_slot(b, B_SHIFT + 2u)] = t.z;
    } else if (mode == 8u) {
        // The two-direction step's weights (core::multigrid::two_direction_weights).
        let w = wsum_row();
        let det = w[0] * w[2] - w[1] * w[1];
        var a = 0.0;
        var bw = 0.0;
        if (w[2] > 0.0 && det > 1e-2 * w[0] * w[2]) {
            a = (w[3] * w[2] - w[4] * w[1]) / det;
            bw = (w[0] * w[4] - w[1] * w[3]) / det;
        } else if (w[0] > 0.0) {
            a = w[3] / w[0];
        }
        if (!is_finite_f(a) || !is_finite_f(bw)) {
            a = 0.0;
            bw = 0.0;
        }
        red[body_slot(b, B_CG_ALPHA)] = a;
        red[body_slot(b, B_CG_BETA)] = bw;
    } else {
        red[body_slot(b, B_MG_ALPHA + pc.level)] = correction_step(vec2<f32>(wsum[0][0], wsum[1][0]));
    }
    return false;
}

// y += α d for the free nodes, α their body's step (mode bit 0 as `direction`'s mode;
// nothing at α = 0); resets the bodies' trust bounds and the line search's second
// pass. Mode bit 1: then the node's
// `boundary` (the line search's step where no particle-contact projection comes
// between).
@compute @workgroup_size(64)
fn advance(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = gid.x;
    // The bodies' trust bounds back to 1 and their colliders' steps to 0 for the next
    // iteration (this iteration's `trust_scale` has read them).
    if (j < params.chunks.z) {
        atomicStore(&bodyt[j], bitcast<u32>(1.0));
        atomicStore(&bodyt[params.chunks.z + j], 0u);
    }
    // No second line-search pass until a `pick` asks for one (this iteration's ran).
    if (j == 0u) {
        atomicStore(&args[ARGS_LINE], 0u);
        atomicStore(&args[ARGS_PENDING], 0u);
    }
    if (j >= params.lv[0].y) {
        return;
    }
    let a = red[body_slot(node_body(j), B_ALPHA)];
    if (!held_now(j) && a != 0.0) {
        let y = pos[R_Y * params.n + j];
        pos[R_Y * params.n + j] = vec4<f32>(y.xyz + direction(j, pc.mode & 1u) * a, y.w);
    }
    if ((pc.mode & 2u) != 0u) {
        boundary_node(j, false);
    }
}

// Element forces at the iterate (core::multigrid::element_forces): pc.mode 0, the
// rotations refined; pc.mode 1 (the substep's end, for the colliders' reactions, only
// where there are colliders), the rotations held.
@compute @workgroup_size(64)
fn forces(@builtin(global_invocation_id) gid: vec3<u32>) {
    let e = gid.x;
    if (e >= params.lv[0].w || (pc.mode == 1u && params.misc.x == 0u)) {
        return;
    }
    let x = load_x(e, R_Y);
    let info = elems[3u * e + 2u];
    let b = info.y;
    let size = bitcast<f32>(info.z);
    let volume = bitcast<f32>(info.w);
    let lame = mats[b * MAT_STRIDE];
    let f = element_gradient(x, size);
    var q = rot[e];
    if (pc.mode == 0u) {
        q = extract_rotation(f, q, params.rot_iters);
        rot[e] = q;
    }
    let r = quat_mat(q);
    let rtf = transpose(r) * f;
    let s = (rtf + transpose(rtf)) * 0.5 - identity3();
    let p = r * s * (2.0 * lame.x) + cofactor(f) * (lame.y * (determinant(f) - 1.0));
    let pv = p * volume;
    // Hourglass: −R Σ_α h_α(j) (Q q)_α (V/h²) with q = Rᵀ q(x).
    let scale = volume / (size * size);
    let rq = hourglass_response(material_op(b), hg_turn(transpose(r), hourglass_coords(relative8(x))));
    for (var j = 0u; j < 8u; j = j + 1u) {
        let out = -(pv * (corner_sign(j) / (4.0 * size))) - r * (hourglass_row(j, rq) * scale);
        ef[8u * e + j] = vec4<f32>(out, 0.0);
    }
}

// The Newton residual r = M/h² (x̃ − y) + f(y) (0 on held nodes) as level 0's
// right-hand side, and a zero correction.
@compute @workgroup_size(64)
fn residual(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = gid.x;
    // No contact pass until `contacts` finds a contact block (the last iteration's
    // passes have run).
    if (j == 0u) {
        atomicStore(&args[ARGS_CONTACT], 0u);
        atomicStore(&args[ARGS_CONTACT_COUNT], 0u);
    }
    if (j >= params.lv[0].y) {
        return;
    }
    var f = vec3<f32>(0.0);
    var s = topo[j];
    let end = topo[j + 1u];
    // Four at a time, as `weighted_sum`.
    for (; s + 4u <= end; s = s + 4u) {
        let f0 = ef[8u * (topo[s] >> 3u) + (topo[s] & 7u)].xyz;
        let f1 = ef[8u * (topo[s + 1u] >> 3u) + (topo[s + 1u] & 7u)].xyz;
        let f2 = ef[8u * (topo[s + 2u] >> 3u) + (topo[s + 2u] & 7u)].xyz;
        let f3 = ef[8u * (topo[s + 3u] >> 3u) + (topo[s + 3u] & 7u)].xyz;
        f = f + f0;
        f = f + f1;
        f = f + f2;
        f = f + f3;
    }
    for (; s < end; s = s + 1u) {
        f = f + ef[8u * (topo[s] >> 3u) + (topo[s] & 7u)].xyz;
    }
    let n = params.n;
    var r = (pos[R_T * n + j].xyz - pos[R_Y * n + j].xyz) * (nodes[j].x / params.h2) + f;
    // A grasped node's residual is the tissue's pull on the grasper.
    let g = ccol[C_GRAB * n + j].w;
    var nf = vec4<f32>(0.0, 0.0, 0.0, -1.0);
    if (g > 0.5 && !held(j)) {
        nf = vec4<f32>(r, g - 1.0);
    }
    ccol[C_NF * n + j] = nf;
    if (held_now(j)) {
        r = vec3<f32>(0.0);
    }
    vecs[V_RHS * params.n_total + j] = vec4<f32>(r, 0.0);
    vecs[V_DELTA * params.n_total + j] = vec4<f32>(0.0);
}

// Coarse element e's rotation: the normalised mean of its children's quaternions (signs
// aligned with the first child's).
fn coarsen_rot(e: u32) {
    let c = params.child_base + e - params.lv[1].z;
    let first = rot[topo[topo[c]]];
    var sum = vec4<f32>(0.0);
    var s = topo[c];
    let end = topo[c + 1u];
    // Four at a time, as `weighted_sum`.
    for (; s + 4u <= end; s = s + 4u) {
        let q0 = rot[topo[s]];
        let q1 = rot[topo[s + 1u]];
        let q2 = rot[topo[s + 2u]];
        let q3 = rot[topo[s + 3u]];
        sum = sum + select(q0, -q0, dot(q0, first) < 0.0);
        sum = sum + select(q1, -q1, dot(q1, first) < 0.0);
        sum = sum + select(q2, -q2, dot(q2, first) < 0.0);
        sum = sum + select(q3, -q3, dot(q3, first) < 0.0);
    }
    for (; s < end; s = s + 1u) {
        let q = rot[topo[s]];
        sum = sum + select(q, -q, dot(q, first) < 0.0);
    }
    rot[e] = sum * (1.0 / length(sum));
}

// Level pc.level (1 and below) from the finer one, one thread per node and element: each
// element's rotation (`coarsen_rot`) and each node's extra stiffness (`lump_extra`; none
// where nothing can touch).
@compute @workgroup_size(64)
fn coarsen_level(@builtin(global_invocation_id) gid: vec3<u32>) {
    let lv = params.lv[pc.level];
    if (lv.z + gid.x < lv.w) {
        coarsen_rot(lv.z + gid.x);
    }
    if (contacts_on() && lv.x + gid.x < lv.y) {
        lump_extra(lv.x + gid.x);
    }
}

fn kblock(base: u32, a: u32, b: u32) -> mat3x3<f32> {
    let o = 3u * (base + 8u * a + b);
    return mat3x3<f32>(kmat[o].xyz, kmat[o + 1u].xyz, kmat[o + 2u].xyz);
}

// Stiffness block base and scale of element e (level 0: its body's unit cube scaled by
// V/h²; coarse: its own Galerkin blocks).
fn kinfo(e: u32) -> vec2<f32> {
    let info = elems[3u * e + 2u];
    let size = bitcast<f32>(info.z);
    var sc = 1.0;
    if (size > 0.0) {
        sc = bitcast<f32>(info.w) / (size * size);
    }
    return vec2<f32>(bitcast<f32>(info.x), sc);
}

// Whether a node can have a contact block this step: there are colliders or particle
// contacts. Without, the contact passes are not recorded and every block reads as zero
// (what the buffer holds from before is stale).
fn contacts_on() -> bool {
    return params.misc.x > 0u || params.pair.x != 0u;
}

// Node j's contact stiffness (N/m over h², a level's lumped blocks below level 0; the
// w of its first row is 1 where it is not zero, else 0: `write_extra`).
fn extra_block(j: u32) -> mat3x3<f32> {
    if (!contacts_on()) {
        return mat3x3<f32>(vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
    }
    return extra_rest(j, extra_head(j));
}

// A coarse element's part of (A x)_j: R Σ_b K_ab Rᵀ x_b over its eight corners b from
// its own blocks (the element and corner a packed as `ec`, x at `vecs[off ..]`; level
// 0's rows come from `lattice_terms`). Written out corner by corner, so that the eight
// loads of x are issued together.
fn element_term(ec: u32, off: u32) -> vec3<f32> {
    let e = ec >> 3u;
    let c0 = elems[3u * e];
    let c1 = elems[3u * e + 1u];
    return rotated_row(elems[3u * e + 2u].x, ec & 7u, 1.0, quat_mat(rot[e]),
                       vecs[off + c0.x].xyz, vecs[off + c0.y].xyz, vecs[off + c0.z].xyz,
                       vecs[off + c0.w].xyz, vecs[off + c1.x].xyz, vecs[off + c1.y].xyz,
                       vecs[off + c1.z].xyz, vecs[off + c1.w].xyz);
}

// A body's unit cube operator (see `cube_op_row`).
struct CubeOp {
    k0: vec4<f32>,
    k1: vec4<f32>,
    k2: vec4<f32>,
    k3: vec4<f32>,
    k4: vec4<f32>,
};

// The unit cube operator stored after the 64 unit blocks at `kb`.
fn cube_op(kb: u32) -> CubeOp {
    let o = 3u * (kb + 64u);
    return CubeOp(kmat[o], kmat[o + 1u], kmat[o + 2u], kmat[o + 3u], kmat[o + 4u]);
}

// A unit cube operator's moments of corner values x turned into an element's frame:
// g = Rᵀ Σ_j x_j c_jᵀ and the hourglass coordinates q = Rᵀ q(x) (rt = Rᵀ;
// core::element::CubeOperator::moments).
struct CubeMoments {
    g: mat3x3<f32>,
    q: Hg,
};

fn cube_moments(rt: mat3x3<f32>, x0: vec3<f32>, x1: vec3<f32>, x2: vec3<f32>, x3: vec3<f32>,
                x4: vec3<f32>, x5: vec3<f32>, x6: vec3<f32>, x7: vec3<f32>) -> CubeMoments {
    let s01 = x1 + x0;
    let d01 = x1 - x0;
    let s23 = x3 + x2;
    let d23 = x3 - x2;
    let s45 = x5 + x4;
    let d45 = x5 - x4;
    let s67 = x7 + x6;
    let d67 = x7 - x6;
    let g = rt * mat3x3<f32>((d01 + d23) + (d45 + d67), (s23 - s01) + (s67 - s45),
                             (s45 + s67) - (s01 + s23));
    let q = Hg(rt * ((d23 - d01) + (d67 - d45)), rt * ((s67 - s45) - (s23 - s01)),
               rt * ((d45 + d67) - (d01 + d23)), rt * ((d67 - d45) - (d23 - d01)));
    return CubeMoments(g, q);
}

// The operator's response to moments m (CubeOperator::response): the stress of the
// strain sym(g) / 4 and the hourglass block times the coordinates.
struct CubeResponse {
    sigma: mat3x3<f32>,
    rq: Hg,
};

fn cube_response(op: CubeOp, m: CubeMoments) -> CubeResponse {
    let e = (m.g + transpose(m.g)) * 0.25;
    let tr = e[0].x + e[1].y + e[2].z;
    let lt = 0.5 * op.k0.y * tr;
    let sigma = e * op.k0.x + mat3x3<f32>(vec3<f32>(lt, 0.0, 0.0), vec3<f32>(0.0, lt, 0.0),
                                          vec3<f32>(0.0, 0.0, lt));
    return CubeResponse(sigma, hourglass_response(op, m.q));
}

// vᵀ K u of the unit cube's stiffness K from u's response and v's moments
// (CubeOperator::product): Σ_k σ_k · g_k / 4 + Σ_α (Q q_u)_α · q_v,α.
fn cube_product(u: CubeResponse, v: CubeMoments) -> f32 {
    let s = u.sigma;
    return 0.25 * (dot(s[0], v.g[0]) + dot(s[1], v.g[1]) + dot(s[2], v.g[2])) + hg_dot(v.q, u.rq);
}

// A level-0 element's R K Rᵀ x at corner a (times `scale`, V/h²) from its body's unit
// cube operator `op` (core::element::CubeOperator: the one-point stress and the
// hourglass block's pairs, triple and singles), stored in the five vec4 after the body's
// 64 unit blocks in `kmat`: μ, λ, the pairs' (0,0) (0,1) (1,1), the triple's diagonal
// and (0,1) (1,2) (2,0), the singles.
fn cube_op_row(op: CubeOp, a: u32, scale: f32, r: mat3x3<f32>, x0: vec3<f32>, x1: vec3<f32>,
               x2: vec3<f32>, x3: vec3<f32>, x4: vec3<f32>, x5: vec3<f32>, x6: vec3<f32>,
               x7: vec3<f32>) -> vec3<f32> {
    let u = cube_response(op, cube_moments(transpose(r), x0, x1, x2, x3, x4, x5, x6, x7));
    // Row a (CubeOperator::row).
    let c = corner_sign(a);
    let f = u.sigma * (c * 0.25) + hourglass_row(a, u.rq);
    return r * f * scale;
}

// An element's four hourglass coordinates q_α = Σ_j h_α(c_j) x_j (α = ξη, ηζ, ζξ, ξηζ;
// core::element::hourglass_base), each a vector over the directions.
struct Hg {
    xy: vec3<f32>,
    yz: vec3<f32>,
    zx: vec3<f32>,
    xyz: vec3<f32>,
};

// The hourglass coordinates of corner values x (pass values relative to a corner where
// they are positions: the coordinates do not change, their rounding does).
fn hourglass_coords(x: array<vec3<f32>, 8>) -> Hg {
    let s01 = x[1] + x[0];
    let d01 = x[1] - x[0];
    let s23 = x[3] + x[2];
    let d23 = x[3] - x[2];
    let s45 = x[5] + x[4];
    let d45 = x[5] - x[4];
    let s67 = x[7] + x[6];
    let d67 = x[7] - x[6];
    return Hg((d23 - d01) + (d67 - d45), (s67 - s45) - (s23 - s01), (d45 + d67) - (d01 + d23),
              (d67 - d45) - (d23 - d01));
}

// Hourglass coordinates turned by m (each direction vector times m).
fn hg_turn(m: mat3x3<f32>, q: Hg) -> Hg {
    return Hg(m * q.xy, m * q.yz, m * q.zx, m * q.xyz);
}

fn hg_add(a: Hg, b: Hg, t: f32) -> Hg {
    return Hg(a.xy + b.xy * t, a.yz + b.yz * t, a.zx + b.zx * t, a.xyz + b.xyz * t);
}

fn hg_dot(a: Hg, b: Hg) -> f32 {
    return dot(a.xy, b.xy) + dot(a.yz, b.yz) + dot(a.zx, b.zx) + dot(a.xyz, b.xyz);
}

// The unit cube's hourglass block times coordinates q, Q q: its three pairs, its triple
// and its singles (core::element::CubeOperator::response). ½ qᵀ Q q is a unit cube's
// hourglass energy, Σ_α h_α(a) (Q q)_α its corner a's hourglass force.
fn hourglass_response(op: CubeOp, q: Hg) -> Hg {
    let k0 = op.k0;
    let k1 = op.k1;
    let k2 = op.k2;
    let k3 = op.k3;
    let k4 = op.k4;
    return Hg(
        vec3<f32>(k0.z * q.xy.x + k0.w * q.yz.z, k1.y * q.xy.y + k1.z * q.zx.z,
                  k2.w * q.xy.z + k3.z * q.yz.x + k4.x * q.zx.y),
        vec3<f32>(k3.z * q.xy.z + k3.x * q.yz.x + k3.w * q.zx.y, k2.x * q.yz.y + k2.y * q.zx.x,
                  k0.w * q.xy.x + k1.x * q.yz.z),
        vec3<f32>(k2.y * q.yz.y + k2.z * q.zx.x, k4.x * q.xy.z + k3.w * q.yz.x + k3.y * q.zx.y,
                  k1.z * q.xy.y + k1.w * q.zx.z),
        q.xyz * k4.yzw);
}

// Corner a's hourglass force Σ_α h_α(a) (Q q)_α from the response rq.
fn hourglass_row(a: u32, rq: Hg) -> vec3<f32> {
    let c = corner_sign(a);
    return (rq.xy * (c.x * c.y) + rq.yz * (c.y * c.z)) + (rq.zx * (c.z * c.x) + rq.xyz * (c.x * c.y * c.z));
}

// Body b's unit cube operator, from its material record.
fn material_op(b: u32) -> CubeOp {
    let o = b * MAT_STRIDE + MAT_OP;
    return CubeOp(mats[o], mats[o + 1u], mats[o + 2u], mats[o + 3u], mats[o + 4u]);
}

// R Σ_b K_ab Rᵀ x_b times `scale`: row a of the stiffness blocks from `kb`, turned by r.
fn rotated_row(kb: u32, a: u32, scale: f32, r: mat3x3<f32>, x0: vec3<f32>, x1: vec3<f32>,
               x2: vec3<f32>, x3: vec3<f32>, x4: vec3<f32>, x5: vec3<f32>, x6: vec3<f32>,
               x7: vec3<f32>) -> vec3<f32> {
    let rt = transpose(r);
    var acc = kblock(kb, a, 0u) * (rt * x0);
    acc = acc + kblock(kb, a, 1u) * (rt * x1);
    acc = acc + kblock(kb, a, 2u) * (rt * x2);
    acc = acc + kblock(kb, a, 3u) * (rt * x3);
    acc = acc + kblock(kb, a, 4u) * (rt * x4);
    acc = acc + kblock(kb, a, 5u) * (rt * x5);
    acc = acc + kblock(kb, a, 6u) * (rt * x6);
    acc = acc + kblock(kb, a, 7u) * (rt * x7);
    return r * acc * scale;
}

// (A x)_j with A = M/h² + S + Σ_e R K Rᵀ, x the `vecs` region `region`
// (core::multigrid's apply_row).
fn apply_row(j: u32, region: u32) -> vec3<f32> {
    return apply_row_at(j, region * params.n_total);
}

// (A x)_j with x at `vecs[off ..]`.
fn apply_row_at(j: u32, off: u32) -> vec3<f32> {
    let xj = vecs[off + j].xyz;
    let y = xj * (nodes[j].x / params.h2) + extra_block(j) * xj;
    if (j < params.n) {
        return y + lattice_terms(j, off, xj);
    }
    var k = vec3<f32>(0.0);
    for (var s = topo[j]; s < topo[j + 1u]; s = s + 1u) {
        k = k + element_term(topo[s], off);
    }
    return y + k;
}

// No element on that side of a node (a neighbour record's element word).
const NBR_NONE: u32 = 0xffffffffu;

// Where level-0 node j's neighbour record starts in `elems` (gpu::lattice::layout's
// neighbour_record): words 0..26 its 26 lattice neighbours (offset (m % 3, m / 3 % 3,
// m / 9) − 1 for m in 0..27 but 13, the node itself, at word m below 13 and m − 1
// above), 26..34 the element on each side s (lowest corner at offset s − 1 per axis; the
// node is its corner 7 − s) or NBR_NONE, 34 the body's unit cube operator in `kmat`, 35
// the elements' scale V/h².
fn nbr_record(j: u32) -> u32 {
    return params.nbrs.x + 9u * j;
}

// The element on side s's part of a level-0 row: 0 where there is none.
fn side_term(e: u32, a: u32, op: CubeOp, scale: f32, x0: vec3<f32>, x1: vec3<f32>,
             x2: vec3<f32>, x3: vec3<f32>, x4: vec3<f32>, x5: vec3<f32>, x6: vec3<f32>,
             x7: vec3<f32>) -> vec3<f32> {
    if (e == NBR_NONE) {
        return vec3<f32>(0.0);
    }
    return cube_op_row(op, a, scale, quat_mat(rot[e]), x0, x1, x2, x3, x4, x5, x6, x7);
}

// Level-0 node j's element terms of (A x)_j, Σ_e R K Rᵀ x over its elements in the
// order of their sides (core::multigrid's stiffness_row takes them in that order), x at
// `vecs[off ..]` (xj its own value): every address from the node's record, so that the
// 27 values and 8 rotations are loaded together.
fn lattice_terms(j: u32, off: u32, xj: vec3<f32>) -> vec3<f32> {
    let o = nbr_record(j);
    let r0 = elems[o];
    let r1 = elems[o + 1u];
    let r2 = elems[o + 2u];
    let r3 = elems[o + 3u];
    let r4 = elems[o + 4u];
    let r5 = elems[o + 5u];
    let r6 = elems[o + 6u];
    let r7 = elems[o + 7u];
    let r8 = elems[o + 8u];
    let v0 = vecs[off + r0.x].xyz;
    let v1 = vecs[off + r0.y].xyz;
    let v2 = vecs[off + r0.z].xyz;
    let v3 = vecs[off + r0.w].xyz;
    let v4 = vecs[off + r1.x].xyz;
    let v5 = vecs[off + r1.y].xyz;
    let v6 = vecs[off + r1.z].xyz;
    let v7 = vecs[off + r1.w].xyz;
    let v8 = vecs[off + r2.x].xyz;
    let v9 = vecs[off + r2.y].xyz;
    let v10 = vecs[off + r2.z].xyz;
    let v11 = vecs[off + r2.w].xyz;
    let v12 = vecs[off + r3.x].xyz;
    let v13 = xj;
    let v14 = vecs[off + r3.y].xyz;
    let v15 = vecs[off + r3.z].xyz;
    let v16 = vecs[off + r3.w].xyz;
    let v17 = vecs[off + r4.x].xyz;
    let v18 = vecs[off + r4.y].xyz;
    let v19 = vecs[off + r4.z].xyz;
    let v20 = vecs[off + r4.w].xyz;
    let v21 = vecs[off + r5.x].xyz;
    let v22 = vecs[off + r5.y].xyz;
    let v23 = vecs[off + r5.z].xyz;
    let v24 = vecs[off + r5.w].xyz;
    let v25 = vecs[off + r6.x].xyz;
    let v26 = vecs[off + r6.y].xyz;
    let op = cube_op(r8.z);
    let sc = bitcast<f32>(r8.w);
    var y = side_term(r6.z, 7u, op, sc, v0, v1, v3, v4, v9, v10, v12, v13);
    y = y + side_term(r6.w, 6u, op, sc, v1, v2, v4, v5, v10, v11, v13, v14);
    y = y + side_term(r7.x, 5u, op, sc, v3, v4, v6, v7, v12, v13, v15, v16);
    y = y + side_term(r7.y, 4u, op, sc, v4, v5, v7, v8, v13, v14, v16, v17);
    y = y + side_term(r7.z, 3u, op, sc, v9, v10, v12, v13, v18, v19, v21, v22);
    y = y + side_term(r7.w, 2u, op, sc, v10, v11, v13, v14, v19, v20, v22, v23);
    y = y + side_term(r8.x, 1u, op, sc, v12, v13, v15, v16, v21, v22, v24, v25);
    y = y + side_term(r8.y, 0u, op, sc, v13, v14, v16, v17, v22, v23, v25, v26);
    return y;
}

// Word w of the record at o.
fn record_word(o: u32, w: u32) -> u32 {
    return elems[o + (w >> 2u)][w & 3u];
}

// The value at neighbour m (0..27) of level-0 node j from its record at o.
fn nbr_value(o: u32, j: u32, m: u32, off: u32) -> vec3<f32> {
    var i = j;
    if (m != 13u) {
        i = record_word(o, select(m - 1u, m, m < 13u));
    }
    return vecs[off + i].xyz;
}

// Level-0 node j's element on side s's part of (A x)_j (0 where there is none), x at
// `vecs[off ..]`, from the node's record.
fn lattice_side(j: u32, off: u32, s: u32) -> vec3<f32> {
    let o = nbr_record(j);
    let e = record_word(o, 26u + s);
    if (e == NBR_NONE) {
        return vec3<f32>(0.0);
    }
    let m = (s & 1u) + 3u * ((s >> 1u) & 1u) + 9u * (s >> 2u);
    let r8 = elems[o + 8u];
    return cube_op_row(cube_op(r8.z), 7u - s, bitcast<f32>(r8.w), quat_mat(rot[e]),
                       nbr_value(o, j, m, off), nbr_value(o, j, m + 1u, off),
                       nbr_value(o, j, m + 3u, off), nbr_value(o, j, m + 4u, off),
                       nbr_value(o, j, m + 9u, off), nbr_value(o, j, m + 10u, off),
                       nbr_value(o, j, m + 12u, off), nbr_value(o, j, m + 13u, off));
}

// The inverse of a symmetric positive definite block (of ½ (a + aᵀ)) by its Cholesky
// factor, zero where a pivot is not positive (core::multigrid::spd_inverse: stable where a contact penalty
// makes the block a large rank-one term plus a small one, which cofactors are not).
fn spd_inverse(a: mat3x3<f32>) -> mat3x3<f32> {
    let z = mat3x3<f32>(vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
    if (!(a[0].x > 0.0)) {
        return z;
    }
    let a10 = 0.5 * (a[0].y + a[1].x);
    let a20 = 0.5 * (a[0].z + a[2].x);
    let a21 = 0.5 * (a[1].z + a[2].y);
    let l00 = sqrt(a[0].x);
    let l10 = a10 / l00;
    let l20 = a20 / l00;
    let t11 = a[1].y - l10 * l10;
    if (!(t11 > 0.0)) {
        return z;
    }
    let l11 = sqrt(t11);
    let l21 = (a21 - l20 * l10) / l11;
    let t22 = a[2].z - l20 * l20 - l21 * l21;
    if (!(t22 > 0.0)) {
        return z;
    }
    let l22 = sqrt(t22);
    let i00 = 1.0 / l00;
    let i11 = 1.0 / l11;
    let i22 = 1.0 / l22;
    let i10 = -(l10 * i00) * i11;
    let i21 = -(l21 * i11) * i22;
    let i20 = -(l20 * i00 + l21 * i10) * i22;
    let b00 = i00 * i00 + i10 * i10 + i20 * i20;
    let b10 = i11 * i10 + i21 * i20;
    let b20 = i22 * i20;
    let b11 = i11 * i11 + i21 * i21;
    let b21 = i22 * i21;
    let b22 = i22 * i22;
    return mat3x3<f32>(vec3<f32>(b00, b10, b20), vec3<f32>(b10, b11, b21), vec3<f32>(b20, b21, b22));
}

// Inverted diagonal blocks M/h² + S + Σ_e R K_jj Rᵀ of the nodes pc.first ..
// [.. pc.count] (every level in one dispatch; zero where singular).
@compute @workgroup_size(64)
fn diag(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= pc.count) {
        return;
    }
    let j = pc.first + gid.x;
    if (!in_use(j)) {
        return;
    }
    let m = nodes[j].x / params.h2;
    var d = mat3x3<f32>(vec3<f32>(m, 0.0, 0.0), vec3<f32>(0.0, m, 0.0), vec3<f32>(0.0, 0.0, m));
    d = d + extra_block(j);
    for (var s = topo[j]; s < topo[j + 1u]; s = s + 1u) {
        let ec = topo[s];
        let e = ec >> 3u;
        let a = ec & 7u;
        let ki = kinfo(e);
        let r = quat_mat(rot[e]);
        d = d + r * (kblock(bitcast<u32>(ki.x), a, a) * ki.y) * transpose(r);
    }
    let inv = spd_inverse(d);
    nblk[3u * j] = vec4<f32>(inv[0], 0.0);
    nblk[3u * j + 1u] = vec4<f32>(inv[1], 0.0);
    nblk[3u * j + 2u] = vec4<f32>(inv[2], 0.0);
}

// Gauss–Seidel update of node j: δ_j += D_j⁻¹ (rhs_j − (A δ)_j) (held nodes stay).
fn smooth_node(j: u32) {
    if (held_in_cycle(j)) {
        return;
    }
    let o = 3u * j;
    let dinv = mat3x3<f32>(nblk[o].xyz, nblk[o + 1u].xyz, nblk[o + 2u].xyz);
    let r = vecs[V_RHS * params.n_total + j].xyz - apply_row(j, V_DELTA);
    let dj = V_DELTA * params.n_total + j;
    vecs[dj] = vec4<f32>(vecs[dj].xyz + dinv * r, 0.0);
}

// The residual rhs − A δ of node j (0 on held nodes).
fn fine_residual_node(j: u32) {
    var r = vec3<f32>(0.0);
    if (!held_in_cycle(j)) {
        r = vecs[V_RHS * params.n_total + j].xyz - apply_row(j, V_DELTA);
    }
    vecs[V_RES * params.n_total + j] = vec4<f32>(r, 0.0);
}

// Σ w v_i over the weighted list at `topo[c]` (node, weight bits pairs), v the `vecs`
// values from `base`: four entries at a time, their loads issued together (a list's
// loads one after another are a chain of latencies), the sum in the list's order all
// the same.
fn weighted_sum(c: u32, base: u32) -> vec3<f32> {
    var r = vec3<f32>(0.0);
    var s = topo[c];
    let end = topo[c + 1u];
    for (; s + 8u <= end; s = s + 8u) {
        let v0 = vecs[base + topo[s]].xyz;
        let v1 = vecs[base + topo[s + 2u]].xyz;
        let v2 = vecs[base + topo[s + 4u]].xyz;
        let v3 = vecs[base + topo[s + 6u]].xyz;
        r = r + v0 * bitcast<f32>(topo[s + 1u]);
        r = r + v1 * bitcast<f32>(topo[s + 3u]);
        r = r + v2 * bitcast<f32>(topo[s + 5u]);
        r = r + v3 * bitcast<f32>(topo[s + 7u]);
    }
    for (; s < end; s = s + 2u) {
        r = r + vecs[base + topo[s]].xyz * bitcast<f32>(topo[s + 1u]);
    }
    return r;
}

// Coarse node j's right-hand side (Pᵀ r)_j (0 on held nodes) and a zero correction,
// the finer level's residual r from the `vecs` region `src`.
fn restrict_node(j: u32, src: u32) {
    var r = weighted_sum(params.restr_base + j - params.lv[1].x, src * params.n_total);
    if (held(j)) {
        r = vec3<f32>(0.0);
    }
    vecs[V_RHS * params.n_total + j] = vec4<f32>(r, 0.0);
    vecs[V_DELTA * params.n_total + j] = vec4<f32>(0.0);
}

// The coarse correction prolongated to node j, e_j = (P δ_c)_j; with `add`, added to
// its correction (δ_j += e_j) rather than kept for the step along it.
fn prolong_node(j: u32, add: bool) {
    var e = vec3<f32>(0.0);
    if (!held_in_cycle(j)) {
        e = weighted_sum(params.prol_base + j, V_DELTA * params.n_total);
    }
    if (add) {
        let dj = V_DELTA * params.n_total + j;
        vecs[dj] = vec4<f32>(vecs[dj].xyz + e, 0.0);
    } else {
        vecs[V_PE * params.n_total + j] = vec4<f32>(e, 0.0);
    }
}

// Node j's terms of eᵀ r and eᵀ A e, r from the `vecs` region `src`.
fn alpha_node(j: u32, src: u32) -> vec2<f32> {
    if (held(j)) {
        return vec2<f32>(0.0);
    }
    let e = vecs[V_PE * params.n_total + j].xyz;
    return vec2<f32>(dot(vecs[src * params.n_total + j].xyz, e), dot(apply_row(j, V_PE), e));
}

// Where a pass finds a level's residual: `V_RES`, or with mode 1 (the level not smoothed
// before the coarse correction, so its correction is still zero) its right-hand side,
// which the residual then equals: on held nodes both are 0 (`residual` on level 0 and
// the conjugate gradients' `cg_update` keep them there, `restrict_node` below).
fn residual_region(mode: u32) -> u32 {
    return select(V_RES, V_RHS, mode == 1u);
}

// δ_j += α e_j.
fn correct_node(j: u32, a: f32) {
    let dj = V_DELTA * params.n_total + j;
    vecs[dj] = vec4<f32>(vecs[dj].xyz + vecs[V_PE * params.n_total + j].xyz * a, 0.0);
}

// The coarse correction's step: eᵀ r / eᵀ A e where both are positive, else 0.
fn correction_step(t: vec2<f32>) -> f32 {
    var a = 0.0;
    if (t.y > 0.0 && t.x > 0.0) {
        a = t.x / t.y;
    }
    return select(0.0, a, is_finite_f(a));
}

// A smoothing pass's mode bit: one thread a node, its row's elements in a loop, rather
// than eight threads a node.
const ROW_MODE: u32 = 0x10000u;

// One colour of a Gauss–Seidel sweep: the nodes topo[pc.first ..][.. pc.count], eight
// threads a node (one element each), eight nodes a workgroup; or, with ROW_MODE, one
// thread a node.
@compute @workgroup_size(64)
fn smooth_colour(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    if ((pc.mode & ROW_MODE) != 0u) {
        let i = wg.x * LWG + lid;
        if (i < pc.count) {
            smooth_node(topo[pc.first + i]);
        }
        return;
    }
    smooth_split(pc.first + wg.x * 8u + lid / 8u, pc.first + pc.count, lid);
}

// The residual rhs − A δ of level pc.level's nodes (0 on fixed ones), after sweeps
// before the coarse correction (without them no pass makes it: `residual_region`).
@compute @workgroup_size(64)
fn fine_residual(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x < pc.count) {
        fine_residual_node(pc.first + gid.x);
    }
}

// The next coarser level's right-hand side Pᵀ r (0 on fixed nodes) and a zero
// correction, for its nodes pc.first ..; mode 1: r is the finer level's right-hand side
// (`residual_region`).
@compute @workgroup_size(64)
fn restrict_residual(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x < pc.count) {
        restrict_node(pc.first + gid.x, residual_region(pc.mode));
    }
}

// The coarse correction prolongated to level pc.level's nodes, e = P δ_c; mode 1: added
// to their correction (level 0 takes it whole, and so do the levels between where the
// coarsest level is solved exactly).
@compute @workgroup_size(64)
fn prolong(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x < pc.count) {
        prolong_node(pc.first + gid.x, pc.mode == 1u);
    }
}

// Colour c of level l: its range in `topo` (absolute).
fn colour_range(l: u32, c: u32) -> vec2<u32> {
    let i = l * 16u + 2u * c;
    let v = params.colours[i / 4u];
    return select(v.xy, v.zw, (i % 4u) != 0u);
}

var<workgroup> part: array<vec3<f32>, 64>;

// Part `slot` (0..8) of (A x)_j: one of node j's elements, the mass and extra terms
// in part 0; 0 past its elements.
fn apply_part(j: u32, region: u32, slot: u32) -> vec3<f32> {
    let off = region * params.n_total;
    var y = vec3<f32>(0.0);
    if (slot == 0u) {
        let xj = vecs[off + j].xyz;
        y = xj * (nodes[j].x / params.h2) + extra_block(j) * xj;
    }
    if (j < params.n) {
        return y + lattice_side(j, off, slot);
    }
    let s = topo[j] + slot;
    if (s >= topo[j + 1u]) {
        return y;
    }
    return y + element_term(topo[s], off);
}

// (A x)_j of region `region` split eight ways: thread `lid` adds its part into `part`,
// the node's first thread gets the sum. Every thread of the workgroup calls it (`valid`
// false: no node).
fn split_row(j: u32, valid: bool, region: u32, lid: u32) -> vec3<f32> {
    var p = vec3<f32>(0.0);
    if (valid) {
        p = apply_part(j, region, lid % 8u);
    }
    part[lid] = p;
    for (var st = 4u; st > 0u; st = st / 2u) {
        workgroupBarrier();
        if (lid % 8u < st) {
            part[lid] = part[lid] + part[lid + st];
        }
    }
    workgroupBarrier();
    return part[lid];
}

// Part of a Gauss–Seidel update split eight ways: the node at topo[i] (none past
// `end`), updated by its first thread. Every thread of the workgroup calls it.
fn smooth_split(i: u32, end: u32, lid: u32) {
    var j = 0u;
    if (i < end) {
        j = topo[i];
    }
    let ax = split_row(j, i < end, V_DELTA, lid);
    if (lid % 8u == 0u && i < end) {
        if (!held_in_cycle(j)) {
            let o = 3u * j;
            let dinv = mat3x3<f32>(nblk[o].xyz, nblk[o + 1u].xyz, nblk[o + 2u].xyz);
            let dj = V_DELTA * params.n_total + j;
            let rr = vecs[V_RHS * params.n_total + j].xyz - ax;
            vecs[dj] = vec4<f32>(vecs[dj].xyz + dinv * rr, 0.0);
        }
    }
}

// Chebyshev weight ω_{k+1} of sweep k (core::multigrid::chebyshev_weight).
fn chebyshev_weight(k: u32, rho2: f32) -> f32 {
    var w = 1.0;
    for (var i = 1u; i <= k; i = i + 1u) {
        if (i == 1u) {
            w = 2.0 / (2.0 - rho2);
        } else {
            w = 4.0 / (4.0 - rho2 * w);
        }
    }
    return w;
}

// A Chebyshev sweep's mode bit: the sweep also copies its result to V_RES, for level 0's
// contact pass after it (`contact_smooth`).
const COPY_MODE: u32 = 0x20000u;

// Chebyshev sweep k of level l for node j given ax = (A x_k)_j: x_k is in region
// V_DELTA for even k (V_PE for odd), x_{k+1} replaces x_{k−1} in the other region
// (core::multigrid's smooth_chebyshev), and with `copy` goes to V_RES too. An even
// number of sweeps ends in V_DELTA.
fn chebyshev_node(j: u32, ax: vec3<f32>, l: u32, k: u32, copy: bool) {
    let n = params.n_total;
    let odd = (k & 1u) == 1u;
    let src = select(V_DELTA, V_PE, odd);
    let dst = select(V_PE, V_DELTA, odd);
    let cur = vecs[src * n + j].xyz;
    var next = cur;
    if (!held_in_cycle(j)) {
        let o = 3u * j;
        let dinv = mat3x3<f32>(nblk[o].xyz, nblk[o + 1u].xyz, nblk[o + 2u].xyz);
        let c = params.cheb[l];
        let xh = cur + dinv * (vecs[V_RHS * n + j].xyz - ax) * c.x;
        var prev = cur;
        if (k > 0u) {
            prev = vecs[dst * n + j].xyz;
        }
        next = (xh - prev) * chebyshev_weight(k, c.y) + prev;
    }
    vecs[dst * n + j] = vec4<f32>(next, 0.0);
    if (copy) {
        vecs[V_RES * n + j] = vec4<f32>(next, 0.0);
    }
}

// Chebyshev sweep k of level l for the node at `first + i` (none from `end`), its row
// split eight ways. Every thread of the workgroup calls it.
fn chebyshev_split(i: u32, end: u32, lid: u32, l: u32, k: u32, copy: bool) {
    let ax = split_row(i, i < end, select(V_DELTA, V_PE, (k & 1u) == 1u), lid);
    if (lid % 8u == 0u && i < end) {
        chebyshev_node(i, ax, l, k, copy);
    }
}

// Chebyshev sweep pc.mode of level pc.level over its nodes pc.first ..
// [.. pc.count], eight threads a node (one element each), eight nodes a workgroup,
// the workgroups striding over the level; or, with ROW_MODE in pc.mode, one thread a
// node; with COPY_MODE, the result copied to V_RES as well.
@compute @workgroup_size(64)
fn smooth_chebyshev(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                    @builtin(local_invocation_index) lid: u32) {
    let k = pc.mode & (ROW_MODE - 1u);
    let copy = (pc.mode & COPY_MODE) != 0u;
    if ((pc.mode & ROW_MODE) != 0u) {
        for (var i = wg.x * LWG + lid; i < pc.count; i = i + nwg.x * LWG) {
            let j = pc.first + i;
            chebyshev_node(j, apply_row(j, select(V_DELTA, V_PE, (k & 1u) == 1u)), pc.level, k, copy);
        }
        return;
    }
    for (var base = wg.x * 8u; base < pc.count; base = base + nwg.x * 8u) {
        chebyshev_split(pc.first + base + lid / 8u, pc.first + pc.count, lid, pc.level, k, copy);
    }
}

// Level 0's contact pass after its Chebyshev sweeps (core::multigrid's contact_pass), a
// thread a place of the list `contacts` made (each free node with a contact block, in no
// particular order): the node takes δ_j = x_j + D_j⁻¹ (rhs_j − (A x)_j), x the sweeps'
// result as the last sweep copied it to V_RES (so that every update reads the same x,
// whatever the order); the others keep theirs. The last workgroup's places past the
// list's end hold older entries: a node there is taken only where it has a contact
// block now, and then it is also in the list (the same update, written twice).
@compute @workgroup_size(64)
fn contact_smooth(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= params.lv[0].y) {
        return;
    }
    let j = bitcast<u32>(ccol[C_TOUCH * params.n + gid.x].z);
    if (j >= params.lv[0].y || extra_head(j).w == 0.0) {
        return;
    }
    let n = params.n_total;
    let o = 3u * j;
    let dinv = mat3x3<f32>(nblk[o].xyz, nblk[o + 1u].xyz, nblk[o + 2u].xyz);
    let r = vecs[V_RHS * n + j].xyz - apply_row(j, V_RES);
    vecs[V_DELTA * n + j] = vec4<f32>(vecs[V_RES * n + j].xyz + dinv * r, 0.0);
}

// The fused coarsest solve's row parts (xyz), 256 threads; the node range of the body it
// is on; and that body's two Chebyshev iterates (V_DELTA, then V_PE: xyz of each of
// its at most COARSEST_NODES nodes), kept in workgroup memory between the sweeps.
const COARSEST_NODES: u32 = 128u;
var<workgroup> wide: array<array<f32, 3>, 256>;
var<workgroup> wide_range: vec2<u32>;
var<workgroup> xs: array<f32, 768>;

// Node `local` of the body's iterate `sel` (0: V_DELTA, 1: V_PE) in `xs`.
fn xs_get(sel: u32, local: u32) -> vec3<f32> {
    let o = 3u * (sel * COARSEST_NODES + local);
    return vec3<f32>(xs[o], xs[o + 1u], xs[o + 2u]);
}

fn xs_set(sel: u32, local: u32, v: vec3<f32>) {
    let o = 3u * (sel * COARSEST_NODES + local);
    xs[o] = v.x;
    xs[o + 1u] = v.y;
    xs[o + 2u] = v.z;
}

// Body b's nodes on level l (from its chunks of the level's reduction table, which starts
// at pc.first), at most `most` of them.
fn body_nodes(b: u32, l: u32, most: u32) -> vec2<u32> {
    let r = body_chunks(1u + l, b);
    var range = vec2<u32>(0u, 0u);
    if (r.x < r.y) {
        let last = chunk(pc.first + r.y - 1u);
        range = vec2<u32>(chunk(pc.first + r.x).x, last.x + last.y);
    }
    range.y = min(range.y, range.x + most);
    return range;
}

// What a thread of `smooth_coarsest` keeps of one of its node's elements from sweep to
// sweep: the row's turn r and scale, the blocks' base and the node's corner a, and the
// element's corners as indices into the body's iterates (a corner past `COARSEST_NODES`:
// no element).
struct CoarsestSlot {
    r: mat3x3<f32>,
    scale: f32,
    kb: u32,
    a: u32,
    c0: vec4<u32>,
    c1: vec4<u32>,
};

// Slot s of node j's elements (none past its last, nor where `used` is false), its
// corners local to `base`.
fn coarsest_slot(j: u32, s: u32, base: u32, used: bool) -> CoarsestSlot {
    var out = CoarsestSlot(identity3(), 0.0, 0u, 0u, vec4<u32>(COARSEST_NODES), vec4<u32>(COARSEST_NODES));
    let at = topo[j] + s;
    if (used && at < topo[j + 1u]) {
        let ec = topo[at];
        let e = ec >> 3u;
        let ki = kinfo(e);
        out = CoarsestSlot(quat_mat(rot[e]), ki.y, bitcast<u32>(ki.x), ec & 7u,
                           elems[3u * e] - vec4<u32>(base), elems[3u * e + 1u] - vec4<u32>(base));
    }
    return out;
}

// Slot `t`'s part of (A x) on the body's iterate `sel` in `xs` (0 for no element).
fn coarsest_part(t: CoarsestSlot, sel: u32) -> vec3<f32> {
    if (t.c0.x >= COARSEST_NODES) {
        return vec3<f32>(0.0);
    }
    return rotated_row(t.kb, t.a, t.scale, t.r, xs_get(sel, t.c0.x), xs_get(sel, t.c0.y),
                       xs_get(sel, t.c0.z), xs_get(sel, t.c0.w), xs_get(sel, t.c1.x),
                       xs_get(sel, t.c1.y), xs_get(sel, t.c1.z), xs_get(sel, t.c1.w));
}

// The coarsest level's pc.mode Chebyshev sweeps (level pc.level, its reduction table
// from pc.first) in one dispatch, as that many `smooth_chebyshev` dispatches do them
// (but for the order of a row's sums): a workgroup per body (striding over the bodies).
// A body's coarsest nodes couple only with each other, so its workgroup needs no other.
// All of a body's nodes (at most `COARSEST_NODES`) are swept at once: 8, 4 or 2 threads
// a node (up to 32, 64 or 128 nodes), each with 1, 2 or 4 of its elements; with `most`
// 1, always 8 (bodies of at most 32 nodes). What does not change between sweeps stays in
// registers (each element's turn, blocks and corners; the node's mass, inverse diagonal
// block and right-hand side; the Chebyshev weight), the iterates in workgroup memory
// (read from `vecs` before, written back after). `most` is a constant of each entry
// point, so that one whose threads take one element holds the registers of one.
fn coarsest_sweeps(wg: vec3<u32>, nwg: vec3<u32>, lid: u32, most: u32) {
    let l = pc.level;
    let n = params.n_total;
    for (var b = wg.x; b < params.count.x; b = b + nwg.x) {
        if (lid == 0u) {
            // The plan fuses only levels whose bodies fit `xs`.
            wide_range = body_nodes(b, l, COARSEST_NODES);
        }
        let range = workgroupUniformLoad(&wide_range);
        let nn = range.y - range.x;
        for (var i = range.x + lid; i < range.y; i = i + 256u) {
            xs_set(0u, i - range.x, vecs[V_DELTA * n + i].xyz);
            xs_set(1u, i - range.x, vecs[V_PE * n + i].xyz);
        }
        // Threads a node and elements a thread.
        var per = 8u;
        if (nn > 64u && most > 2u) {
            per = 2u;
        } else if (nn > 32u && most > 1u) {
            per = 4u;
        }
        let slots = 8u / per;
        let local = lid / per;
        let sub = lid % per;
        let valid = local < nn;
        let j = range.x + min(local, max(nn, 1u) - 1u);
        var t: array<CoarsestSlot, 4>;
        for (var q = 0u; q < most; q = q + 1u) {
            t[q] = coarsest_slot(j, sub * slots + q, range.x, valid && q < slots);
        }
        // The node's own terms (its first thread's).
        let mass = nodes[j].x / params.h2;
        let extra = extra_block(j);
        let o = 3u * j;
        let dinv = mat3x3<f32>(nblk[o].xyz, nblk[o + 1u].xyz, nblk[o + 2u].xyz);
        let rhs = vecs[V_RHS * n + j].xyz;
        let fixed = held(j);
        let c = params.cheb[l];
        var w = 1.0;
        workgroupBarrier();
        for (var k = 0u; k < pc.mode; k = k + 1u) {
            let src = select(0u, 1u, (k & 1u) == 1u);
            let dst = 1u - src;
            var p = vec3<f32>(0.0);
            if (valid) {
                if (sub == 0u) {
                    let xj = xs_get(src, local);
                    p = xj * mass + extra * xj;
                }
                for (var q = 0u; q < most; q = q + 1u) {
                    if (q < slots) {
                        p = p + coarsest_part(t[q], src);
                    }
                }
            }
            wide[lid] = array<f32, 3>(p.x, p.y, p.z);
            for (var st = per / 2u; st > 0u; st = st / 2u) {
                workgroupBarrier();
                if (sub < st) {
                    let v = wide[lid + st];
                    wide[lid] = array<f32, 3>(wide[lid][0] + v[0], wide[lid][1] + v[1], wide[lid][2] + v[2]);
                }
            }
            workgroupBarrier();
            // chebyshev_weight(k, ρ²), one sweep at a time.
            if (k == 1u) {
                w = 2.0 / (2.0 - c.y);
            } else if (k > 1u) {
                w = 4.0 / (4.0 - c.y * w);
            }
            if (valid && sub == 0u) {
                let ax = vec3<f32>(wide[lid][0], wide[lid][1], wide[lid][2]);
                let cur = xs_get(src, local);
                var next = cur;
                if (!fixed) {
                    let xh = cur + dinv * (rhs - ax) * c.x;
                    var prev = cur;
                    if (k > 0u) {
                        prev = xs_get(dst, local);
                    }
                    next = (xh - prev) * w + prev;
                }
                xs_set(dst, local, next);
            }
            workgroupBarrier();
        }
        for (var i = range.x + lid; i < range.y; i = i + 256u) {
            vecs[V_DELTA * n + i] = vec4<f32>(xs_get(0u, i - range.x), 0.0);
            vecs[V_PE * n + i] = vec4<f32>(xs_get(1u, i - range.x), 0.0);
        }
        // Every thread has read this body's range and iterates before the next's.
        workgroupBarrier();
    }
}

// `coarsest_sweeps` for bodies of up to `COARSEST_NODES` nodes on the coarsest level.
@compute @workgroup_size(256)
fn smooth_coarsest(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                   @builtin(local_invocation_index) lid: u32) {
    coarsest_sweeps(wg, nwg, lid, 4u);
}

// `coarsest_sweeps` for bodies of up to 32 nodes on the coarsest level: eight threads a
// node, one element each (the same sums as `smooth_coarsest` makes of such a body).
@compute @workgroup_size(256)
fn smooth_coarsest_small(@builtin(workgroup_id) wg: vec3<u32>,
                         @builtin(num_workgroups) nwg: vec3<u32>,
                         @builtin(local_invocation_index) lid: u32) {
    coarsest_sweeps(wg, nwg, lid, 1u);
}

// The exact coarsest solve: a body's system (3 rows a node, its nodes in order) bordered
// by its right-hand side, [[A, .], [bᵀ, .]], as a packed lower triangle (row r, column
// c <= r at `packed(r, c)`; A's m rows first, b as row m), factorised in place into
// A = L D Lᵀ (L unit lower; column k left unscaled, l_ik d_k, the border row becoming
// z = L⁻¹ b); D⁻¹ z, updated into the solution backward; the solution, a node's three
// unknowns at a time.
var<workgroup> chol: array<f32, EXACT_PACKED>;
var<workgroup> exact_y: array<f32, EXACT_ROWS>;
var<workgroup> exact_x: array<f32, EXACT_ROWS>;
var<workgroup> exact_range: vec2<u32>;

fn packed(r: u32, c: u32) -> u32 {
    return r * (r + 1u) / 2u + c;
}

// Adds block `blk` at local nodes (i, k), k <= i (its lower part where i = k).
fn chol_add(i: u32, k: u32, blk: mat3x3<f32>) {
    // Row by row, each column of the block a value of its own (no matrix indexed in a
    // loop: those live in slow memory).
    chol_add_row(3u * i, 3u * k, vec3<f32>(blk[0].x, blk[1].x, blk[2].x));
    chol_add_row(3u * i + 1u, 3u * k, vec3<f32>(blk[0].y, blk[1].y, blk[2].y));
    chol_add_row(3u * i + 2u, 3u * k, vec3<f32>(blk[0].z, blk[1].z, blk[2].z));
}

// Adds v to row `row` of `chol` at columns col .. col + 3 on or below the diagonal.
fn chol_add_row(row: u32, col: u32, v: vec3<f32>) {
    let p = packed(row, col);
    if (col <= row) {
        chol[p] = chol[p] + v.x;
    }
    if (col + 1u <= row) {
        chol[p + 1u] = chol[p + 1u] + v.y;
    }
    if (col + 2u <= row) {
        chol[p + 2u] = chol[p + 2u] + v.z;
    }
}

// Assembles body `range`'s matrix M/h² + S + Σ_e R K Rᵀ on level pc.level into `chol`
// (held nodes' rows and columns the identity's; each node's own terms, then its
// elements' blocks one element slot a round, the lattice giving a node at most eight),
// with room for the border row m, zeroed, where `border` (the caller writes the
// right-hand side there).
fn exact_assemble(lid: u32, range: vec2<u32>, border: bool) {
    let nn = range.y - range.x;
    let m = 3u * nn;
    let rows = select(m, m + 1u, border);
    for (var q = lid; q < rows * (rows + 1u) / 2u; q = q + 256u) {
        chol[q] = 0.0;
    }
    workgroupBarrier();
    if (lid < nn) {
        let j = range.x + lid;
        var d = identity3();
        if (!held(j)) {
            let mass = nodes[j].x / params.h2;
            d = mat3x3<f32>(vec3<f32>(mass, 0.0, 0.0), vec3<f32>(0.0, mass, 0.0),
                            vec3<f32>(0.0, 0.0, mass)) + extra_block(j);
        }
        chol_add(lid, lid, d);
    }
    // Eight threads a node, one a corner of the node's element in this round: within
    // a round each thread adds to its own node's rows at its own corner's columns.
    let local = lid / 8u;
    let cb = lid % 8u;
    let j = range.x + min(local, max(nn, 1u) - 1u);
    let free = local < nn && !held(j);
    for (var s = 0u; s < 8u; s = s + 1u) {
        workgroupBarrier();
        let at = topo[j] + s;
        if (free && at < topo[j + 1u]) {
            let ec = topo[at];
            let e = ec >> 3u;
            let k = corner(e, cb);
            if (k <= j && !held(k)) {
                let ki = kinfo(e);
                let r = quat_mat(rot[e]);
                let blk = r * (kblock(bitcast<u32>(ki.x), ec & 7u, cb) * ki.y) * transpose(r);
                chol_add(local, k - range.x, blk);
            }
        }
    }
}

// The pivot node's own 3 × 3 block at step kb of the elimination, as every thread
// takes it: its diagonal after the steps within it (d0, d1, d2), their inverses (0 for a
// pivot that is not positive) and its entries below the diagonal (a10, a20, and a21
// after step 3 kb).
struct Pivot {
    d: vec3<f32>,
    inv: vec3<f32>,
    a10: f32,
    a20: f32,
    a21: f32,
}

// Step kb's pivot block, eliminated in place (`chol[packed(3 kb + r, 3 kb + c)]` before
// its own steps; after the elimination, as the factor holds it).
fn exact_pivot(kb: u32, eliminated: bool) -> Pivot {
    let k0 = 3u * kb;
    let p1 = packed(k0 + 1u, k0);
    let p2 = packed(k0 + 2u, k0);
    if (!eliminated) {
        return pivot_of(chol[packed(k0, k0)], chol[p1], chol[p1 + 1u], chol[p2], chol[p2 + 1u],
                        chol[p2 + 2u]);
    }
    var v: Pivot;
    v.d.x = chol[packed(k0, k0)];
    v.inv.x = select(0.0, 1.0 / v.d.x, v.d.x > 0.0);
    v.a10 = chol[p1];
    v.a20 = chol[p2];
    v.d.y = chol[p1 + 1u];
    v.inv.y = select(0.0, 1.0 / v.d.y, v.d.y > 0.0);
    v.a21 = chol[p2 + 1u];
    v.d.z = chol[p2 + 2u];
    v.inv.z = select(0.0, 1.0 / v.d.z, v.d.z > 0.0);
    return v;
}

// A pivot block (lower entries a00, a10, a11, a20, a21, a22) eliminated within itself.
fn pivot_of(a00: f32, a10: f32, a11: f32, a20: f32, a21: f32, a22: f32) -> Pivot {
    var v: Pivot;
    v.d.x = a00;
    v.inv.x = select(0.0, 1.0 / v.d.x, v.d.x > 0.0);
    v.a10 = a10;
    v.a20 = a20;
    v.d.y = a11 - v.a10 * (v.a10 * v.inv.x);
    v.inv.y = select(0.0, 1.0 / v.d.y, v.d.y > 0.0);
    v.a21 = a21 - v.a20 * (v.a10 * v.inv.x);
    v.d.z = a22 - v.a20 * (v.a20 * v.inv.x) - v.a21 * (v.a21 * v.inv.y);
    v.inv.z = select(0.0, 1.0 / v.d.z, v.d.z > 0.0);
    return v;
}

// Row i's entries in the pivot columns k0..k0 + 2 after the pivot's own step (the first
// left as it is, l_ik d_k unscaled), as `exact_eliminate` stores them.
fn pivot_row(i: u32, k0: u32, v: Pivot) -> vec3<f32> {
    let p = packed(i, k0);
    let x0 = chol[p];
    let x1 = chol[p + 1u] - x0 * (v.a10 * v.inv.x);
    let x2 = chol[p + 2u] - x0 * (v.a20 * v.inv.x) - x1 * (v.a21 * v.inv.y);
    return vec3<f32>(x0, x1, x2);
}

// Entry a_ij after the step of the pivot node whose columns row i holds as `ci` (as
// `pivot_row` gives them) and row j as `cj` scaled by the pivot's inverses.
fn stepped(a: f32, ci: vec3<f32>, cj: vec3<f32>) -> f32 {
    return a - ci.x * cj.x - ci.y * cj.y - ci.z * cj.z;
}

// Entry (i, j) of `chol` (where j <= i) after the pivot nodes' steps: the first's
// (ci, cj), then the second's (di, dj) where there is a `pair`.
fn trailing_step(i: u32, j: u32, ci: vec3<f32>, di: vec3<f32>, cj: vec3<f32>, dj: vec3<f32>,
                 pair: bool) {
    if (j <= i) {
        let p = packed(i, j);
        var x = stepped(chol[p], ci, cj);
        if (pair) {
            x = stepped(x, di, dj);
        }
        chol[p] = x;
    }
}

// Eliminates `chol` (nn nodes, m = 3 nn rows, and the border row m where `border`) in
// place: every step k applies a_ij -= a_ik (a_jk / d_k) to the rows and columns past k,
// each entry's three updates a node in column order, so the result is the
// column-at-a-time elimination's (core::dense::solve_bordered) in its operations and
// their order. Two nodes (six columns) a phase, between two barriers: every thread
// takes both pivot blocks alike (the second after the first's step; so the result,
// whether every pivot is positive, is the workgroup's); then the six columns below
// them, a row a thread; then the trailing triangle, a pair of nodes (3 × 3 entries) a
// thread, each entry taking both nodes' steps at once. A last odd node takes a phase
// of its own.
fn exact_eliminate(lid: u32, nn: u32, border: bool) -> bool {
    let m = 3u * nn;
    let end = select(m, m + 1u, border);
    var ok = true;
    var kb = 0u;
    loop {
        if (kb >= nn) {
            break;
        }
        workgroupBarrier();
        let k0 = 3u * kb;
        let v = exact_pivot(kb, false);
        ok = ok && all(v.d > vec3<f32>(0.0));
        let pair = kb + 1u < nn;
        // The second pivot node's block after the first's step (every thread alike).
        var w = v;
        var s = array<vec3<f32>, 3>(vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
        var b = array<f32, 6>(0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        let k1 = k0 + 3u;
        if (pair) {
            let r0 = pivot_row(k1, k0, v);
            let r1 = pivot_row(k1 + 1u, k0, v);
            let r2 = pivot_row(k1 + 2u, k0, v);
            s = array<vec3<f32>, 3>(r0 * v.inv, r1 * v.inv, r2 * v.inv);
            b[0] = stepped(chol[packed(k1, k1)], r0, s[0]);
            b[1] = stepped(chol[packed(k1 + 1u, k1)], r1, s[0]);
            b[2] = stepped(chol[packed(k1 + 1u, k1 + 1u)], r1, s[1]);
            b[3] = stepped(chol[packed(k1 + 2u, k1)], r2, s[0]);
            b[4] = stepped(chol[packed(k1 + 2u, k1 + 1u)], r2, s[1]);
            b[5] = stepped(chol[packed(k1 + 2u, k1 + 2u)], r2, s[2]);
            w = pivot_of(b[0], b[1], b[2], b[3], b[4], b[5]);
            ok = ok && all(w.d > vec3<f32>(0.0));
        }
        // The pivot nodes' columns on the rows past them.
        let first_row = select(k0 + 3u, k0 + 6u, pair);
        for (var q = lid; q + first_row < end; q = q + 256u) {
            let i = first_row + q;
            let p = packed(i, k0);
            let x = pivot_row(i, k0, v);
            chol[p + 1u] = x.y;
            chol[p + 2u] = x.z;
            if (pair) {
                let pq = packed(i, k1);
                let y0 = stepped(chol[pq], x, s[0]);
                let y1 = stepped(chol[pq + 1u], x, s[1]) - y0 * (w.a10 * w.inv.x);
                let y2 = stepped(chol[pq + 2u], x, s[2]) - y0 * (w.a20 * w.inv.x) - y1 * (w.a21 * w.inv.y);
                chol[pq] = y0;
                chol[pq + 1u] = y1;
                chol[pq + 2u] = y2;
            }
        }
        workgroupBarrier();
        if (pair && lid < 3u) {
            // The second pivot node's rows in the first's columns (after the barrier:
            // every thread has read them above).
            let p = packed(k1 + lid, k0);
            let x = pivot_row(k1 + lid, k0, v);
            chol[p + 1u] = x.y;
            chol[p + 2u] = x.z;
        }
        if (lid == 0u) {
            chol[packed(k0 + 1u, k0 + 1u)] = v.d.y;
            chol[packed(k0 + 2u, k0 + 1u)] = v.a21;
            chol[packed(k0 + 2u, k0 + 2u)] = v.d.z;
            if (pair) {
                chol[packed(k1, k1)] = b[0];
                chol[packed(k1 + 1u, k1)] = b[1];
                chol[packed(k1 + 2u, k1)] = b[3];
                chol[packed(k1 + 1u, k1 + 1u)] = w.d.y;
                chol[packed(k1 + 2u, k1 + 1u)] = w.a21;
                chol[packed(k1 + 2u, k1 + 2u)] = w.d.z;
            }
        }
        // Node pairs (a, b), b <= a, of the t nodes past the pivot nodes, and with the
        // border (local node t, its one row m) after them; pair q at a (a + 1) / 2 + b.
        let step = select(1u, 2u, pair);
        let t = nn - kb - step;
        let past = k0 + 3u * step;
        let pairs = select(t * (t + 1u) / 2u, (t + 1u) * (t + 2u) / 2u - 1u, border);
        for (var q = lid; q < pairs; q = q + 256u) {
            var a = u32((sqrt(8.0 * f32(q) + 1.0) - 1.0) * 0.5);
            if ((a + 1u) * (a + 2u) / 2u <= q) {
                a = a + 1u;
            }
            if (a * (a + 1u) / 2u > q) {
                a = a - 1u;
            }
            let bq = q - a * (a + 1u) / 2u;
            let jb = past + 3u * bq;
            // The three columns' scaled pivot rows, each a value of its own (no array
            // indexed in a loop: those live in slow memory).
            let pj = packed(jb, k0);
            let pj1 = packed(jb + 1u, k0);
            let pj2 = packed(jb + 2u, k0);
            let cj0 = vec3<f32>(chol[pj], chol[pj + 1u], chol[pj + 2u]) * v.inv;
            let cj1 = vec3<f32>(chol[pj1], chol[pj1 + 1u], chol[pj1 + 2u]) * v.inv;
            let cj2 = vec3<f32>(chol[pj2], chol[pj2 + 1u], chol[pj2 + 2u]) * v.inv;
            var dj0 = vec3<f32>(0.0);
            var dj1 = vec3<f32>(0.0);
            var dj2 = vec3<f32>(0.0);
            if (pair) {
                dj0 = vec3<f32>(chol[pj + 3u], chol[pj + 4u], chol[pj + 5u]) * w.inv;
                dj1 = vec3<f32>(chol[pj1 + 3u], chol[pj1 + 4u], chol[pj1 + 5u]) * w.inv;
                dj2 = vec3<f32>(chol[pj2 + 3u], chol[pj2 + 4u], chol[pj2 + 5u]) * w.inv;
            }
            let rows = select(3u, 1u, a == t);
            for (var r = 0u; r < rows; r = r + 1u) {
                let i = past + 3u * a + r;
                let pi = packed(i, k0);
                let ci = vec3<f32>(chol[pi], chol[pi + 1u], chol[pi + 2u]);
                var di = vec3<f32>(0.0);
                if (pair) {
                    di = vec3<f32>(chol[pi + 3u], chol[pi + 4u], chol[pi + 5u]);
                }
                trailing_step(i, jb, ci, di, cj0, dj0, pair);
                trailing_step(i, jb + 1u, ci, di, cj1, dj1, pair);
                trailing_step(i, jb + 2u, ci, di, cj2, dj2, pair);
            }
        }
        kb = kb + step;
    }
    workgroupBarrier();
    return ok;
}

// Given this thread's entry z of L⁻¹ b (row lid), y = D⁻¹ z, then Lᵀ x = y backward, a
// node at a time (each entry's updates in the column-at-a-time order): every thread
// takes the node's three unknowns alike, then updates the rows before it, a row a
// thread; x into exact_x. `chol` holds the factor.
fn exact_backward(lid: u32, nn: u32, z: f32) {
    let m = 3u * nn;
    var own = 0.0;
    if (lid < m) {
        own = 1.0 / chol[packed(lid, lid)];
        exact_y[lid] = z * own;
    }
    for (var kb = nn; kb > 0u; kb = kb - 1u) {
        let k0 = 3u * (kb - 1u);
        workgroupBarrier();
        let p1 = packed(k0 + 1u, k0);
        let p2 = packed(k0 + 2u, k0);
        let x2 = exact_y[k0 + 2u];
        let x1 = exact_y[k0 + 1u] - chol[p2 + 1u] * (1.0 / chol[p1 + 1u]) * x2;
        let own0 = 1.0 / chol[packed(k0, k0)];
        let x0 = exact_y[k0] - chol[p2] * own0 * x2 - chol[p1] * own0 * x1;
        if (lid < k0) {
            exact_y[lid] = exact_y[lid] - chol[p2 + lid - k0] * own * x2
                - chol[p1 + lid - k0] * own * x1 - chol[packed(k0, lid)] * own * x0;
        }
        if (lid == 0u) {
            exact_x[k0] = x0;
            exact_x[k0 + 1u] = x1;
            exact_x[k0 + 2u] = x2;
        }
    }
    workgroupBarrier();
}

// Writes the solution in exact_x as body `range`'s coarse correction (zero on held nodes,
// and everywhere where `ok` is false); then a barrier before the next body's.
fn exact_write(lid: u32, range: vec2<u32>, ok: bool) {
    let n = params.n_total;
    for (var i = lid; i < range.y - range.x; i = i + 256u) {
        var x = vec3<f32>(exact_x[3u * i], exact_x[3u * i + 1u], exact_x[3u * i + 2u]);
        if (!ok || held(range.x + i)) {
            x = vec3<f32>(0.0);
        }
        vecs[V_DELTA * n + range.x + i] = vec4<f32>(x, 0.0);
    }
    // Every thread has read this body's range and solution before the next's.
    workgroupBarrier();
}

// Node j's right-hand side in the exact solve (0 on held nodes).
fn exact_rhs(j: u32) -> vec3<f32> {
    if (held(j)) {
        return vec3<f32>(0.0);
    }
    return vecs[V_RHS * params.n_total + j].xyz;
}

// Body b's range of nodes on level pc.level (at most EXACT_NODES), the same in every
// thread.
fn exact_body(lid: u32, b: u32) -> vec2<u32> {
    if (lid == 0u) {
        exact_range = body_nodes(b, pc.level, EXACT_NODES);
    }
    return workgroupUniformLoad(&exact_range);
}

// The coarsest level (pc.level, its reduction table from pc.first) solved exactly, a
// workgroup per body (striding over the bodies), as core::multigrid's solve_coarsest
// (core::dense::solve_bordered): the body's matrix (`exact_assemble`) with the
// right-hand side as its last row, eliminated in place (right-looking LDLᵀ, the border
// row's part of it the forward substitution), then solved backward. A body whose matrix
// has a pivot that is not positive keeps a zero correction. The plan takes this kernel
// only where no body has more than EXACT_NODES nodes on the level, and where the world
// keeps no factor between V-cycles (else `factor_coarsest` and `solve_factored`).
@compute @workgroup_size(256)
fn solve_coarsest(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                  @builtin(local_invocation_index) lid: u32) {
    for (var b = wg.x; b < params.count.x; b = b + nwg.x) {
        let range = exact_body(lid, b);
        let nn = range.y - range.x;
        let m = 3u * nn;
        exact_assemble(lid, range, true);
        if (lid < nn) {
            let rhs = exact_rhs(range.x + lid);
            chol[packed(m, 3u * lid)] = rhs.x;
            chol[packed(m, 3u * lid + 1u)] = rhs.y;
            chol[packed(m, 3u * lid + 2u)] = rhs.z;
        }
        let ok = exact_eliminate(lid, nn, true);
        var z = 0.0;
        if (lid < m) {
            z = chol[packed(m, lid)];
        }
        exact_backward(lid, nn, z);
        exact_write(lid, range, ok);
    }
}

// Each body's coarsest-level matrix (as `solve_coarsest` assembles it, without the
// right-hand side) factorised, L D Lᵀ, into `cfac` (body b's packed lower triangle from
// b FACTOR_STRIDE, and last in its stride 1 where every pivot is positive, else 0): once
// a Newton iteration, the matrix being the same in each of its V-cycles.
@compute @workgroup_size(256)
fn factor_coarsest(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                   @builtin(local_invocation_index) lid: u32) {
    for (var b = wg.x; b < params.count.x; b = b + nwg.x) {
        let range = exact_body(lid, b);
        let nn = range.y - range.x;
        let m = 3u * nn;
        exact_assemble(lid, range, false);
        let ok = exact_eliminate(lid, nn, false);
        let base = b * FACTOR_STRIDE;
        for (var q = lid; q < m * (m + 1u) / 2u; q = q + 256u) {
            cfac[base + q] = chol[q];
        }
        if (lid == 0u) {
            cfac[base + FACTOR_STRIDE - 1u] = select(0.0, 1.0, ok);
        }
        workgroupBarrier();
    }
}

// The coarsest level solved exactly from the factor `factor_coarsest` kept: each body's
// right-hand side (held nodes' 0) through L z = b forward, a node at a time (each entry's
// updates in the order and form the bordered elimination gives its border row, so the
// answer is `solve_coarsest`'s), then backward (`exact_backward`).
@compute @workgroup_size(256)
fn solve_factored(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
                  @builtin(local_invocation_index) lid: u32) {
    for (var b = wg.x; b < params.count.x; b = b + nwg.x) {
        let range = exact_body(lid, b);
        let nn = range.y - range.x;
        let m = 3u * nn;
        let base = b * FACTOR_STRIDE;
        for (var q = lid; q < m * (m + 1u) / 2u; q = q + 256u) {
            chol[q] = cfac[base + q];
        }
        let ok = cfac[base + FACTOR_STRIDE - 1u] > 0.5;
        if (lid < nn) {
            let rhs = exact_rhs(range.x + lid);
            exact_y[3u * lid] = rhs.x;
            exact_y[3u * lid + 1u] = rhs.y;
            exact_y[3u * lid + 2u] = rhs.z;
        }
        for (var kb = 0u; kb < nn; kb = kb + 1u) {
            workgroupBarrier();
            let k0 = 3u * kb;
            let v = exact_pivot(kb, true);
            let z0 = exact_y[k0];
            let z1 = exact_y[k0 + 1u] - z0 * (v.a10 * v.inv.x);
            let z2 = exact_y[k0 + 2u] - z0 * (v.a20 * v.inv.x) - z1 * (v.a21 * v.inv.y);
            for (var j = k0 + 3u + lid; j < m; j = j + 256u) {
                let p = packed(j, k0);
                exact_y[j] = exact_y[j] - z0 * (chol[p] * v.inv.x) - z1 * (chol[p + 1u] * v.inv.y)
                    - z2 * (chol[p + 2u] * v.inv.z);
            }
            if (lid == 0u) {
                exact_x[k0] = z0;
                exact_x[k0 + 1u] = z1;
                exact_x[k0 + 2u] = z2;
            }
        }
        workgroupBarrier();
        var z = 0.0;
        if (lid < m) {
            z = exact_x[lid];
        }
        exact_backward(lid, nn, z);
        exact_write(lid, range, ok);
    }
}

// Partial sums of eᵀ r and eᵀ A e over a chunk of level pc.level's nodes (workgroup
// pc.first + wg.x of its table; the coarse correction's energy-minimising step).
@compute @workgroup_size(64)
fn alpha_terms(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wg: vec3<u32>) {
    var num = 0.0;
    var den = 0.0;
    let ch = chunk(pc.first + wg.x);
    let src = residual_region(pc.mode);
    for (var i = ch.x + lid; i < ch.x + ch.y; i = i + LWG) {
        let t = alpha_node(i, src);
        num = num + t.x;
        den = den + t.y;
    }
    wsum[0][lid] = num;
    wsum[1][lid] = den;
    reduce_partials(lid, wg.x, 2u);
}

// Node j's block against a translation of its body: m/h² I plus its contact block.
fn translation_block(j: u32) -> mat3x3<f32> {
    let m = nodes[j].x / params.h2;
    return mat3x3<f32>(vec3<f32>(m, 0.0, 0.0), vec3<f32>(0.0, m, 0.0), vec3<f32>(0.0, 0.0, m))
        + extra_block(j);
}

// Partial sums over a chunk of level 0's nodes (workgroup pc.first + wg.x of its
// table; their residual from `residual_region(pc.mode)`) for each body's translation
// step (core::multigrid's translate_bodies): Σ r, the six entries of Σ (m/h² I + S), and
// the held nodes (whose bodies take none).
@compute @workgroup_size(64)
fn translate_terms(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wg: vec3<u32>) {
    var r = vec3<f32>(0.0);
    var a = mat3x3<f32>(vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
    var fixed = 0.0;
    let ch = chunk(pc.first + wg.x);
    for (var j = ch.x + lid; j < ch.x + ch.y; j = j + LWG) {
        if (held_in_cycle(j)) {
            fixed = fixed + 1.0;
        } else {
            r = r + vecs[residual_region(pc.mode) * params.n_total + j].xyz;
            a = a + translation_block(j);
        }
    }
    wsum[0][lid] = r.x;
    wsum[1][lid] = r.y;
    wsum[2][lid] = r.z;
    wsum[3][lid] = a[0].x;
    wsum[4][lid] = a[1].y;
    wsum[5][lid] = a[2].z;
    wsum[6][lid] = 0.5 * (a[0].y + a[1].x);
    wsum[7][lid] = 0.5 * (a[0].z + a[2].x);
    wsum[8][lid] = 0.5 * (a[1].z + a[2].y);
    wsum[9][lid] = fixed;
    reduce_partials(lid, wg.x, 10u);
}

// Level 0's node j takes its body's translation step t: δ += t and r −= (m/h² I + S) t
// (held nodes: none, and a zero residual; their bodies take none), r read from
// `residual_region(pc.mode)` and written to `V_RES` (mode 1: level 0 was not smoothed
// before, and this pass makes its residual).
@compute @workgroup_size(64)
fn translate(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= pc.count) {
        return;
    }
    let j = pc.first + gid.x;
    let n = params.n_total;
    if (held_in_cycle(j)) {
        vecs[V_RES * n + j] = vec4<f32>(0.0);
        return;
    }
    let b = node_body(j);
    let t = vec3<f32>(red[body_slot(b, B_SHIFT)], red[body_slot(b, B_SHIFT + 1u)],
                      red[body_slot(b, B_SHIFT + 2u)]);
    vecs[V_DELTA * n + j] = vec4<f32>(vecs[V_DELTA * n + j].xyz + t, 0.0);
    let r = vecs[residual_region(pc.mode) * n + j].xyz;
    vecs[V_RES * n + j] = vec4<f32>(r - translation_block(j) * t, 0.0);
}

// δ += α e on level pc.level, α each node's body's.
@compute @workgroup_size(64)
fn correct(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x < pc.count) {
        let j = pc.first + gid.x;
        correct_node(j, red[body_slot(node_body(j), B_MG_ALPHA + pc.level)]);
    }
}

// The trust region, body by body (core::solver's Newton iteration): no free node moves
// more than its reach (half its body's lattice spacing) in one iteration, plus the step
// |v| h of the fastest collider its body touches (`contacts`), plus gravity's step from
// rest |g| h² where it touches nothing. Node j's part of its body's bound for its step d
// (taken by the solve's last update, `cg_update`): the least reach / |δ| of the body's
// nodes (at most 1; 0 where a δ is not finite), into `bodyt` (f32 bits: for
// non-negative floats their order).
fn trust_node(j: u32, d: vec3<f32>) {
    if (held_now(j)) {
        return;
    }
    let b = node_body(j);
    if (!(is_finite_f(d.x) && is_finite_f(d.y) && is_finite_f(d.z))) {
        atomicMin(&bodyt[b], 0u);
    } else {
        let len = length(d);
        // Near something (an active collider contact, or particle-contact candidates):
        // half a spacing; else gravity's step more.
        let pr = pair_range(j);
        let near = contacts_on() && (bitcast<u32>(ccol[C_TOUCH * params.n + j].y) != 0u || pr.x < pr.y);
        let tool = bitcast<f32>(atomicLoad(&bodyt[params.chunks.z + b]));
        let reach = nodes[j].z + tool + select(length(params.gravity.xyz) * params.h2, 0.0, near);
        if (len > reach) {
            atomicMin(&bodyt[b], bitcast<u32>(reach / len));
        }
    }
}

// Each free node's step scaled to its body's trust bound (none at a bound of 0: a body
// with a step that is not finite stays).
@compute @workgroup_size(64)
fn trust_scale(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = gid.x;
    if (j >= params.lv[0].y || held_now(j)) {
        return;
    }
    let t = bitcast<f32>(atomicLoad(&bodyt[node_body(j)]));
    let i = V_DELTA * params.n_total + j;
    var d = vec3<f32>(0.0);
    if (t > 0.0) {
        d = vecs[i].xyz * t;
    }
    vecs[i] = vec4<f32>(d, 0.0);
}

// The force free node j at y puts on the collider it touches (within
// TOUCH_TOLERANCE of its radius; of several, the one it is deepest in), as the node's
// Newton force (core::solver's lattice_reactions): its residual without the contact,
// inertia M/h² (x̃ − y) plus its elements' forces at y (the `forces` pass of mode 1),
// along the collider's normal where it presses on it.
fn reaction(j: u32, y: vec3<f32>) {
    let n = params.n;
    if (params.misc.x == 0u || held(j) || ccol[C_GRAB * n + j].w > 0.5) {
        return;
    }
    let r = mats[u32(nodes[j].w) * MAT_STRIDE].z;
    var best = vec4<f32>(0.0, 0.0, 0.0, r * (1.0 + TOUCH_TOLERANCE));
    var k_best = -1.0;
    for (var k = 0u; k < params.misc.x; k = k + 1u) {
        let dn = collider_sdf(cols[k], y);
        if (dn.w < best.w) {
            best = dn;
            k_best = f32(k);
        }
    }
    if (k_best < 0.0) {
        return;
    }
    var f = (pos[R_T * n + j].xyz - y) * (nodes[j].x / params.h2);
    for (var s = topo[j]; s < topo[j + 1u]; s = s + 1u) {
        let ec = topo[s];
        f = f + ef[8u * (ec >> 3u) + (ec & 7u)].xyz;
    }
    ccol[C_NF * n + j] = vec4<f32>(best.xyz * min(dot(f, best.xyz), 0.0), k_best);
}

// Finish: each touching node's force on its collider (`reaction`); v = (y − x)/h,
// damped; x = y.
@compute @workgroup_size(64)
fn finish(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = gid.x;
    if (j >= params.lv[0].y) {
        return;
    }
    let n = params.n;
    let x = pos[R_X * n + j].xyz;
    let y = pos[R_Y * n + j].xyz;
    reaction(j, y);
    pos[R_V * n + j] = vec4<f32>((y - x) / params.h * params.keep, 0.0);
    pos[R_X * n + j] = vec4<f32>(y, 0.0);
    let t = ccol[C_TOUCH * n + j];
    ccol[C_TOUCH * n + j] = vec4<f32>(ccol[C_COL * n + j].w, t.yzw);
}

// Node j's particle radius (m) and penalty stiffness (N/m).
fn contact_scale(j: u32) -> vec2<f32> {
    let m = mats[u32(nodes[j].w) * MAT_STRIDE];
    let modulus = m.y + 2.0 * m.x;
    return vec2<f32>(m.z, PENALTY * (nodes[j].x / params.h2 + modulus * m.w));
}

// Penalty contacts of node j (core::solver's Newton contacts): with every collider it
// is inside now, and the one it touched in the last substep while within a radius of
// it; and with another body's node closer than their radii (or, where the pair's
// holder was pressed into a candidate at the last projection, within PAIR_HOLD of that:
// `pair_hold`), for the pairs in its own
// candidate list and those in the lists of others (each pair is one contact, held by
// the node whose list has it, with that node's stiffness; a free partner counts it twice
// in its block, the coupling the V-cycle does not see). Adds the penalty forces to its
// right-hand side, sets its extra stiffness k n nᵀ (zero without contacts) and records
// which colliders are in contact. Returns whether it has a contact block (then it is
// free).
fn contact_node(j: u32) -> bool {
    let n = params.n;
    var extra = mat3x3<f32>(vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
    var mask = 0u;
    let pr = pair_range(j);
    if (!held_now(j) && (params.misc.x > 0u || pr.x < pr.y || pr.z < pr.w)) {
        let sc = contact_scale(j);
        let r = sc.x;
        let y = pos[R_Y * n + j].xyz;
        let touched = ccol[C_TOUCH * n + j].x;
        let ri = V_RHS * params.n_total + j;
        var rhs = vecs[ri].xyz;
        for (var k = 0u; k < params.misc.x; k = k + 1u) {
            if (u32(cols[k].kind_fr.x) == GRASPER) {
                continue;
            }
            let dn = collider_sdf(cols[k], y);
            let d = dn.w;
            let on = d < r || (touched == f32(k) && d < 2.0 * r);
            if (!on || !is_finite_f(d)) {
                continue;
            }
            rhs = rhs + dn.xyz * (sc.y * (r - d));
            extra = extra + outer(dn.xyz, dn.xyz) * sc.y;
            mask = mask | (1u << k);
            // The collider's step widens its body's trust region (`trust_node`).
            atomicMax(&bodyt[params.chunks.z + node_body(j)], bitcast<u32>(length(cols[k].vel.xyz) * params.h));
        }
        let hold = pair_hold(j);
        for (var s = pr.x; s < pr.y; s = s + 1u) {
            let i = pair_at(s);
            let yi = pos[R_Y * n + i];
            let d = y - yi.xyz;
            let reach = r + tag_radius(yi.w);
            let len = length(d);
            if (len >= reach * hold || len <= 1e-12) {
                continue;
            }
            let nn = d / len;
            rhs = rhs + nn * (sc.y * (reach - len));
            extra = extra + outer(nn, nn) * (sc.y * select(1.0, 2.0, !tag_held(yi.w)));
        }
        for (var s = pr.z; s < pr.w; s = s + 1u) {
            let i = pair_at(s);
            let yi = pos[R_Y * n + i];
            if (tag_held(yi.w)) {
                continue;
            }
            let d = yi.xyz - y;
            let reach = r + tag_radius(yi.w);
            let len = length(d);
            if (len >= reach * pair_hold(i) || len <= 1e-12) {
                continue;
            }
            let nn = d / len;
            let k = contact_scale(i).y;
            rhs = rhs - nn * (k * (reach - len));
            extra = extra + outer(nn, nn) * (k * 2.0);
        }
        vecs[ri] = vec4<f32>(rhs, 0.0);
    }
    let some = write_extra(j, extra);
    // Only y: z of this region is the list, written by others.
    ccol[C_TOUCH * n + j].y = bitcast<f32>(mask);
    return some;
}

// Every level-0 node's penalty contacts (`contact_node`). The nodes with a contact
// block join the list of level 0's contact pass (`contact_smooth`, a thread a place):
// each takes the next place with an atomic add, and the one that takes the first place
// of a workgroup's worth raises that pass's workgroups to include it.
@compute @workgroup_size(64)
fn contacts(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = gid.x;
    if (j < params.lv[0].y && contact_node(j)) {
        let place = atomicAdd(&args[ARGS_CONTACT_COUNT], 1u);
        if (place % LWG == 0u) {
            atomicMax(&args[ARGS_CONTACT], place / LWG + 1u);
        }
        ccol[C_TOUCH * params.n + place].z = bitcast<f32>(j);
    }
}

// Coarse node j's extra stiffness: its fine nodes' lumped, Σ w S (exact for a uniform
// correction), the blocks that are zero (those away from contacts) skipped after their
// first row (the same sum).
fn lump_extra(j: u32) {
    let c = params.restr_base + j - params.lv[1].x;
    var s = mat3x3<f32>(vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
    var i = topo[c];
    let end = topo[c + 1u];
    // Each fine node's first row first (its w says whether it has a block), four at a
    // time; the other two only where it has.
    for (; i + 8u <= end; i = i + 8u) {
        let a0 = extra_head(topo[i]);
        let a1 = extra_head(topo[i + 2u]);
        let a2 = extra_head(topo[i + 4u]);
        let a3 = extra_head(topo[i + 6u]);
        s = s + weighted_extra(topo[i], a0, topo[i + 1u]);
        s = s + weighted_extra(topo[i + 2u], a1, topo[i + 3u]);
        s = s + weighted_extra(topo[i + 4u], a2, topo[i + 5u]);
        s = s + weighted_extra(topo[i + 6u], a3, topo[i + 7u]);
    }
    for (; i < end; i = i + 2u) {
        s = s + weighted_extra(topo[i], extra_head(topo[i]), topo[i + 1u]);
    }
    write_extra(j, s);
}

// Node j's contact block (its first row `head`) times the weight with bits `w`; zero,
// its other rows not read, where it has none.
fn weighted_extra(j: u32, head: vec4<f32>, w: u32) -> mat3x3<f32> {
    if (head.w == 0.0) {
        return mat3x3<f32>(vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
    }
    return extra_rest(j, head) * bitcast<f32>(w);
}

// Node j's contact block's first row (xyz) and whether it has a block (w: 1, else 0).
fn extra_head(j: u32) -> vec4<f32> {
    return nblk[3u * (params.n_total + j)];
}

// Node j's contact block from its first row `head`.
fn extra_rest(j: u32, head: vec4<f32>) -> mat3x3<f32> {
    let o = 3u * (params.n_total + j);
    return mat3x3<f32>(head.xyz, nblk[o + 1u].xyz, nblk[o + 2u].xyz);
}

// Sets node j's contact block, flagged (w of its first row) where it is not zero;
// returns whether it is not.
fn write_extra(j: u32, s: mat3x3<f32>) -> bool {
    let zero = vec3<f32>(0.0);
    let some = any(s[0] != zero) || any(s[1] != zero) || any(s[2] != zero);
    let o = 3u * (params.n_total + j);
    nblk[o] = vec4<f32>(s[0], select(0.0, 1.0, some));
    nblk[o + 1u] = vec4<f32>(s[1], 0.0);
    nblk[o + 2u] = vec4<f32>(s[2], 0.0);
    return some;
}

// Inverse mass of node j for the particle contacts' projection (0 when pinned).
fn pair_inv_mass(j: u32) -> f32 {
    if (pos[R_PIN * params.n + j].w > 0.5) {
        return 0.0;
    }
    return 1.0 / nodes[j].x;
}

// Particle contacts' projection after a Newton iteration, Jacobi (core::solver's pass
// C): node j moves by ω_c times the mean of the pushes out of its candidates it
// overlaps (core::constraints::solve_contact), from the positions all nodes had before
// this pass; the result goes to `vecs`' residual region for `boundary`.
@compute @workgroup_size(64)
fn pair_project(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = gid.x;
    if (j >= params.lv[0].y) {
        return;
    }
    let n = params.n;
    let y = pos[R_Y * n + j].xyz;
    var q = y;
    let wj = pair_inv_mass(j);
    let pr = pair_range(j);
    var pressed = false;
    if (wj > 0.0 && pr.x < pr.y) {
        let rj = contact_scale(j).x;
        let xj = pos[R_X * n + j].xyz;
        var sum = vec3<f32>(0.0);
        var count = 0u;
        for (var s = pr.x; s < pr.y; s = s + 1u) {
            let i = pair_at(s);
            let yi = pos[R_Y * n + i];
            let delta = y - yi.xyz;
            let dist = rj + tag_radius(yi.w);
            let l2 = dot(delta, delta);
            // (Only a pair within the hold's reach can be pressed: `pressed_pair`.)
            let zone = dist * (1.0 + PAIR_HOLD);
            if (!pressed && l2 < zone * zone) {
                pressed = pressed_pair(xj - pos[R_X * n + i].xyz, delta, dist);
            }
            if (l2 >= dist * dist || l2 <= 1e-24) {
                continue;
            }
            let w = wj + pair_inv_mass(i);
            if (w <= 0.0) {
                continue;
            }
            let l = sqrt(l2);
            sum = sum + delta * ((dist - l) / l * wj / w);
            count = count + 1u;
        }
        if (count > 0u) {
            q = y + sum / f32(count) * bitcast<f32>(params.pair.z);
        }
    }
    vecs[V_RES * params.n_total + j] = vec4<f32>(q, 0.0);
    // Pressed into a candidate: the next Newton iteration holds its pairs PAIR_HOLD past
    // touching (`pair_hold`).
    ccol[C_TOUCH * n + j].w = select(0.0, 1.0, pressed);
}

// Whether a pair `d` apart (`d0` at the substep's start) is closer than `dist` along the
// line between them at the substep's start, within the hold's reach
// (core::solver::pressed_pair).
fn pressed_pair(d0: vec3<f32>, d: vec3<f32>, dist: f32) -> bool {
    let l0 = length(d0);
    let along = select(length(d), dot(d, d0) / l0, l0 > 1e-12);
    let l2 = dot(d, d);
    let zone = dist * (1.0 + PAIR_HOLD);
    return along < dist && l2 > 1e-24 && l2 < zone * zone;
}

// How far node j's own candidates hold it (a factor on their contact distance): a
// little past touching where the last projection found it pressed into one of them.
fn pair_hold(j: u32) -> f32 {
    return select(1.0, 1.0 + PAIR_HOLD, ccol[C_TOUCH * params.n + j].w > 0.5);
}

// The colliders' projection after a Newton iteration (pins already hold their targets),
// from the particle contacts' projection when it ran (pc.mode 1): every free node
// pushed out of each collider it penetrates, with friction (core::solver's boundary),
// the corrections recorded for the touched colliders.
@compute @workgroup_size(64)
fn boundary(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x < params.lv[0].y) {
        boundary_node(gid.x, pc.mode == 1u);
    }
}

// Node j's `boundary` (`projected`: its position from the particle contacts' projection
// in V_RES); also the end of `advance`'s line-search step where no projection comes
// between.
fn boundary_node(j: u32, projected: bool) {
    if (held(j)) {
        return;
    }
    let n = params.n;
    let y = pos[R_Y * n + j];
    let tag = y.w;
    var q = y.xyz;
    if (projected) {
        q = vecs[V_RES * params.n_total + j].xyz;
    }
    if (params.misc.x == 0u) {
        pos[R_Y * n + j] = vec4<f32>(q, tag);
        return;
    }
    let gt = grasp_target(j);
    if (gt.w > 0.0) {
        // A grasped node goes to its target; the correction is the grasper's.
        let old = ccol[C_COL * n + j];
        ccol[C_COL * n + j] = vec4<f32>(old.xyz + gt.xyz - q, ccol[C_GRAB * n + j].w - 1.0);
        pos[R_Y * n + j] = vec4<f32>(gt.xyz, tag);
        return;
    }
    let r = contact_scale(j).x;
    let x = pos[R_X * n + j].xyz;
    var total = vec3<f32>(0.0);
    var id = -1.0;
    for (var k = 0u; k < params.misc.x; k = k + 1u) {
        let dp = collider_push(cols[k], q, x, r, params.h);
        if (any(dp != vec3<f32>(0.0))) {
            q = q + dp;
            total = total + dp;
            id = f32(k);
        }
    }
    if (id >= 0.0) {
        let old = ccol[C_COL * n + j];
        ccol[C_COL * n + j] = vec4<f32>(old.xyz + total, id);
    }
    pos[R_Y * n + j] = vec4<f32>(q, tag);
}

// The forces a node put on the colliders in this substep: its Newton force (the
// reaction of a collider it touches, or a grasped node's pull), and on a grasper −m/h²
// times its correction (core::solver's collider forces).
fn node_force(j: u32, k: f32) -> vec3<f32> {
    let n = params.n;
    var f = vec3<f32>(0.0);
    let c = ccol[C_COL * n + j];
    if (c.w == k && cols[u32(k)].kind_fr.x == 4.0) {
        f = f - c.xyz * (nodes[j].x / params.h2);
    }
    let nf = ccol[C_NF * n + j];
    if (nf.w == k) {
        f = f + nf.xyz;
    }
    return f;
}

var<workgroup> fsum: array<vec3<f32>, 64>;

// Partial sums per collider of the nodes' forces (after finish).
@compute @workgroup_size(64)
fn force_partials(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32,
                  @builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var k = 0u; k < params.misc.x; k = k + 1u) {
        var f = vec3<f32>(0.0);
        for (var j = gid.x; j < params.lv[0].y; j = j + nwg.x * LWG) {
            f = f + node_force(j, f32(k));
        }
        fsum[lid] = f;
        for (var stride = LWG / 2u; stride > 0u; stride = stride / 2u) {
            workgroupBarrier();
            if (lid < stride) {
                fsum[lid] = fsum[lid] + fsum[lid + stride];
            }
        }
        if (lid == 0u) {
            let o = params.misc.z + 4u * (wg.x * 32u + k);
            red[o] = fsum[0].x;
            red[o + 1u] = fsum[0].y;
            red[o + 2u] = fsum[0].z;
        }
        workgroupBarrier();
    }
}

// Adds this substep's force on each collider, over the substeps, to the step's totals
// (thread k: collider k; pc.count partial sums).
@compute @workgroup_size(32)
fn force_total(@builtin(local_invocation_index) k: u32) {
    if (k >= params.misc.x) {
        return;
    }
    var f = vec3<f32>(0.0);
    for (var w = 0u; w < pc.count; w = w + 1u) {
        let o = params.misc.z + 4u * (w * 32u + k);
        f = f + vec3<f32>(red[o], red[o + 1u], red[o + 2u]);
    }
    let o = params.misc.w + 4u * k;
    let inv = 1.0 / f32(params.misc.y);
    red[o] = red[o] + f.x * inv;
    red[o + 1u] = red[o + 1u] + f.y * inv;
    red[o + 2u] = red[o + 2u] + f.z * inv;
}

// Zeroes the step's collider force totals.
@compute @workgroup_size(32)
fn force_clear(@builtin(local_invocation_index) k: u32) {
    let o = params.misc.w + 4u * k;
    red[o] = 0.0;
    red[o + 1u] = 0.0;
    red[o + 2u] = 0.0;
}

// Conjugate gradients on level 0, the V-cycle as preconditioner
// (core::multigrid::LatticeMultigrid::krylov): the iterate x, the direction p and
// q = A p, each n vectors after the V-cycle's regions; the residual r is level 0's
// right-hand side, the preconditioned residual z the V-cycle's correction.
fn cg_at(k: u32) -> u32 {
    return 4u * params.n_total + k * params.n;
}

const CG_X: u32 = 0u;
const CG_P: u32 = 1u;
const CG_Q: u32 = 2u;

// Partial sums of zᵀ q (q of the last direction, 0 on held nodes) over a chunk of level
// 0's nodes (workgroup pc.first + wg.x of its table): the next direction's β.
@compute @workgroup_size(64)
fn cg_dots(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wg: vec3<u32>) {
    var zq = 0.0;
    let ch = chunk(pc.first + wg.x);
    for (var j = ch.x + lid; j < ch.x + ch.y; j = j + LWG) {
        zq = zq + dot(vecs[V_DELTA * params.n_total + j].xyz, vecs[cg_at(CG_Q) + j].xyz);
    }
    wsum[0][lid] = zq;
    reduce_partials(lid, wg.x, 1u);
}

// The direction p = z + β p (mode 0: the first, p = z); on held nodes 0, with w = 1
// (what `cg_matvec` reads).
@compute @workgroup_size(64)
fn cg_direction(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = gid.x;
    if (j >= params.lv[0].y) {
        return;
    }
    var p = vec4<f32>(0.0, 0.0, 0.0, 1.0);
    if (!held_now(j)) {
        var d = vecs[V_DELTA * params.n_total + j].xyz;
        if (pc.mode != 0u) {
            d = d + vecs[cg_at(CG_P) + j].xyz * red[body_slot(node_body(j), B_CG_BETA)];
        }
        p = vec4<f32>(d, 0.0);
    }
    vecs[cg_at(CG_P) + j] = p;
}

// The two-direction step's second direction at node j (core::multigrid::
// LatticeMultigrid::two_direction): the last solve's answer, 0 on held nodes and where it
// is not finite.
fn recycled(j: u32) -> vec3<f32> {
    let x = vecs[cg_at(CG_X) + j].xyz;
    if (held_now(j) || !(is_finite_f(x.x) && is_finite_f(x.y) && is_finite_f(x.z))) {
        return vec3<f32>(0.0);
    }
    return x;
}

// The two-direction step's partial sums over a chunk of the energy table (workgroup
// pc.first + wg.x: a run of one body's elements, then of its level-0 nodes): zᵀ A z,
// pᵀ A z, pᵀ A p, rᵀ z, rᵀ p (z the V-cycle's correction, p `recycled`, both 0 on held
// nodes). Each element adds its stiffness's three products once, from both vectors'
// moments (`cube_product`), and each free node its own terms (M/h² + S and the residual
// r), which together are the rows' sums without evaluating a row.
@compute @workgroup_size(64)
fn cg_two_terms(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wg: vec3<u32>) {
    // The five sums, each a value of its own (no array indexed in a loop).
    var t0 = 0.0;
    var t1 = 0.0;
    var t2 = 0.0;
    var t3 = 0.0;
    var t4 = 0.0;
    let ch = chunk(pc.first + wg.x);
    let zo = V_DELTA * params.n_total;
    for (var i = ch.x + lid; i < ch.x + ch.y; i = i + LWG) {
        if (i < params.ne) {
            let e = i;
            let c0 = elems[3u * e];
            let c1 = elems[3u * e + 1u];
            let k = kinfo(e);
            let op = cube_op(bitcast<u32>(k.x));
            let rt = transpose(quat_mat(rot[e]));
            let mz = cube_moments(rt, vecs[zo + c0.x].xyz, vecs[zo + c0.y].xyz, vecs[zo + c0.z].xyz,
                                  vecs[zo + c0.w].xyz, vecs[zo + c1.x].xyz, vecs[zo + c1.y].xyz,
                                  vecs[zo + c1.z].xyz, vecs[zo + c1.w].xyz);
            let mp = cube_moments(rt, recycled(c0.x), recycled(c0.y), recycled(c0.z), recycled(c0.w),
                                  recycled(c1.x), recycled(c1.y), recycled(c1.z), recycled(c1.w));
            let uz = cube_response(op, mz);
            let up = cube_response(op, mp);
            t0 = t0 + k.y * cube_product(uz, mz);
            t1 = t1 + k.y * cube_product(uz, mp);
            t2 = t2 + k.y * cube_product(up, mp);
        } else {
            let j = i - params.ne;
            if (!held_now(j)) {
                let z = vecs[zo + j].xyz;
                let p = recycled(j);
                let r = vecs[V_RHS * params.n_total + j].xyz;
                let m = nodes[j].x / params.h2;
                let s = extra_block(j);
                let az = z * m + s * z;
                t0 = t0 + dot(z, az);
                t1 = t1 + dot(p, az);
                t2 = t2 + dot(p, p * m + s * p);
                t3 = t3 + dot(r, z);
                t4 = t4 + dot(r, p);
            }
        }
    }
    wsum[0][lid] = t0;
    wsum[1][lid] = t1;
    wsum[2][lid] = t2;
    wsum[3][lid] = t3;
    wsum[4][lid] = t4;
    reduce_partials(lid, wg.x, 5u);
}

// q = A p (0 on held nodes, the direction's w = 1), and partial sums of pᵀ q, rᵀ p and
// rᵀ z, over a chunk of level 0's nodes (workgroup pc.first + wg.x of its table).
@compute @workgroup_size(64)
fn cg_matvec(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wg: vec3<u32>) {
    var t = vec3<f32>(0.0);
    let ch = chunk(pc.first + wg.x);
    for (var j = ch.x + lid; j < ch.x + ch.y; j = j + LWG) {
        let pw = vecs[cg_at(CG_P) + j];
        var q = vec3<f32>(0.0);
        if (pw.w == 0.0) {
            q = apply_row_at(j, cg_at(CG_P));
        }
        vecs[cg_at(CG_Q) + j] = vec4<f32>(q, 0.0);
        let p = pw.xyz;
        let r = vecs[V_RHS * params.n_total + j].xyz;
        t = t + vec3<f32>(dot(p, q), dot(r, p), dot(r, vecs[V_DELTA * params.n_total + j].xyz));
    }
    wsum[0][lid] = t.x;
    wsum[1][lid] = t.y;
    wsum[2][lid] = t.z;
    reduce_partials(lid, wg.x, 3u);
}

// x += α p (mode bit 0 clear, the first iteration: x = α p), r −= α q; then the next
// V-cycle's zero start, or, after the last iteration (mode bit 1), x as the Newton step
// and its node's part of the trust bound (`trust_node`).
// Mode bit 2: the two-direction step instead, x = a z + b p (a, b the body's weights
// in its α and β slots, z the V-cycle's correction, p `recycled`), the residual left as
// it is.
@compute @workgroup_size(64)
fn cg_update(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = gid.x;
    if (j >= params.lv[0].y) {
        return;
    }
    let a = red[body_slot(node_body(j), B_CG_ALPHA)];
    var x = vec3<f32>(0.0);
    if ((pc.mode & 4u) != 0u) {
        let b = red[body_slot(node_body(j), B_CG_BETA)];
        x = vecs[V_DELTA * params.n_total + j].xyz * a + recycled(j) * b;
    } else {
        if ((pc.mode & 1u) != 0u) {
            x = vecs[cg_at(CG_X) + j].xyz;
        }
        x = x + vecs[cg_at(CG_P) + j].xyz * a;
        let ri = V_RHS * params.n_total + j;
        vecs[ri] = vec4<f32>(vecs[ri].xyz - vecs[cg_at(CG_Q) + j].xyz * a, 0.0);
    }
    vecs[cg_at(CG_X) + j] = vec4<f32>(x, 0.0);
    let last = (pc.mode & 2u) != 0u;
    vecs[V_DELTA * params.n_total + j] = vec4<f32>(select(vec3<f32>(0.0), x, last), 0.0);
    if (last) {
        trust_node(j, x);
    }
}
