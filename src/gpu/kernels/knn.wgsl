// Exact K nearest neighbours on the hashed grid: shells (Chebyshev rings) of cells
// around the query's cell until the K-th best distance is below the distance to every
// cell not yet visited; candidates ordered by (squared distance, index), so ties break
// by the smaller index and the result equals the CPU's bit for bit. Cells whose box lies
// farther than the K-th best candidate found so far are skipped.
// Mode 0: K nearest of all other particles (knn_out, stride knn_k) — CPU twin
// core::knn::knn_all. Mode 1: contact candidates, the contact_k nearest particles of
// other bodies within 2 (r_i + r_max) (contacts) — CPU twin
// core::solver::Solver::refresh_contacts.

const MAX_K: u32 = 64u;
const MAX_RING: i32 = 64;

fn knn_query(i: u32, mode: u32) {
    var bd: array<f32, 64>;
    var bi: array<u32, 64>;
    var cnt = 0u;
    let q = x[i].xyz;
    var k = params.knn_k;
    var max2 = 3.4028235e38;
    var reach = 3.4028235e38;
    let body_i = pinfo[i].x;
    if (mode == 1u) {
        k = params.contact_k;
        reach = 2.0 * (bodies[body_i].radius + params.max_radius);
        max2 = reach * reach;
    }
    k = min(k, MAX_K);
    var cell = params.knn_cell;
    if (mode == 1u) {
        cell = params.grid_cell;
    }
    let c = cell_coords(q, cell);
    let rel = q / cell;
    // Rounding slack of the cell-box distance (m): a few ulps of the coordinates.
    let slack = 1.0e-6 * (max(max(abs(q.x), abs(q.y)), abs(q.z)) + cell);
    for (var r = 0; r <= MAX_RING; r = r + 1) {
        for (var dz = -r; dz <= r; dz = dz + 1) {
            let zr = dz == -r || dz == r;
            for (var dy = -r; dy <= r; dy = dy + 1) {
                let yr = zr || dy == -r || dy == r;
                var dx = -r;
                loop {
                    if (dx > r) { break; }
                    if (!yr && dx != -r && dx != r) {
                        dx = r;
                        continue;
                    }
                    let cc = c + vec3<i32>(dx, dy, dz);
                    // Skip a cell whose every point is farther than the K-th best so far
                    // (or than the contact reach): the box distance less a rounding
                    // slack, so that no point that could enter the list is skipped and
                    // the result stays the CPU's exactly.
                    var cut = max2;
                    if (cnt == k && k > 0u) {
                        cut = min(cut, bd[k - 1u]);
                    }
                    if (cut < 3.4028235e38) {
                        let lo = vec3<f32>(cc) * cell;
                        let gap = max(max(lo - q, q - lo - vec3<f32>(cell)), vec3<f32>(0.0));
                        let m = length(gap) - slack;
                        if (m > 0.0 && m * m > cut) {
                            dx = dx + 1;
                            continue;
                        }
                    }
                    let h = cell_hash(cc);
                    let s0 = atomicLoad(&scan[h]);
                    let s1 = atomicLoad(&scan[h + 1u]);
                    for (var s = s0; s < s1; s = s + 1u) {
                        let e = sorted[s];
                        let j = bitcast<u32>(e.w);
                        if (j == i) { continue; }
                        if (any(cell_coords(e.xyz, cell) != cc)) { continue; }
                        if (mode == 1u && pinfo[j].x == body_i) { continue; }
                        let d2 = dist2(q, e.xyz);
                        if (d2 > max2) { continue; }
                        // insert into the sorted list (by d2, then index)
                        if (cnt == k) {
                            let ld = bd[k - 1u];
                            if (!(d2 < ld || (d2 == ld && j < bi[k - 1u]))) {
                                continue;
                            }
                        }
                        var pos = min(cnt, k - 1u);
                        if (cnt < k) { cnt = cnt + 1u; }
                        loop {
                            if (pos == 0u) { break; }
                            let pd = bd[pos - 1u];
                            if (d2 < pd || (d2 == pd && j < bi[pos - 1u])) {
                                bd[pos] = pd;
                                bi[pos] = bi[pos - 1u];
                                pos = pos - 1u;
                            } else {
                                break;
                            }
                        }
                        bd[pos] = d2;
                        bi[pos] = j;
                    }
                    dx = dx + 1;
                }
            }
        }
        if (f32(r) * cell >= reach + cell) {
            break;
        }
        if (cnt == k && k > 0u) {
            var bound = 3.4028235e38;
            for (var a = 0; a < 3; a = a + 1) {
                bound = min(bound, rel[a] - f32(c[a] - r));
                bound = min(bound, f32(c[a] + r + 1) - rel[a]);
            }
            let b = max(bound, 0.0) * cell;
            if (bd[k - 1u] < b * b) {
                break;
            }
        }
    }
    if (mode == 1u) {
        let stride = params.contact_k;
        for (var s = 0u; s < stride; s = s + 1u) {
            var o = NONE;
            if (s < cnt) { o = bi[s]; }
            contacts[i * stride + s] = o;
        }
    } else {
        let stride = params.knn_k;
        for (var s = 0u; s < stride; s = s + 1u) {
            var o = NONE;
            if (s < cnt) { o = bi[s]; }
            knn_out[i * stride + s] = o;
        }
    }
}

@compute @workgroup_size(128)
fn knn_all(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x < params.n) {
        knn_query(gid.x, 0u);
    }
}

@compute @workgroup_size(128)
fn knn_contacts(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x < params.n) {
        knn_query(gid.x, 1u);
    }
}
