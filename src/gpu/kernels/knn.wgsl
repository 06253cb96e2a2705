// Exact K nearest neighbours on the hashed grid: shells (Chebyshev rings) of cells
// around the query's cell until the K-th best distance is below the distance to every
// cell not yet visited; candidates ordered by (squared distance, index), so ties break
// by the smaller index and the result equals the CPU's bit for bit. Cells whose box lies
// farther than the K-th best candidate found so far are skipped.
// Mode 0: K nearest of all other particles (knn_out, stride knn_k) — CPU twin
// core::knn::knn_all. Mode 1: contact candidates, the contact_k nearest particles of
// other bodies within 2 (r_i + r_max) (contacts) — CPU twin
// core::solver::Solver::refresh_contacts.
//
// The candidate list lives in registers: LIST_SLOTS scalar pairs (ld_s, lj_s), sorted by
// (squared distance, index), written out by `knn.rs` (`source`) for 32 or 64 slots so
// that every access has a constant index. The list is right-aligned: for K below
// LIST_SLOTS the first LIST_SLOTS − K slots hold a sentinel (−1, 0) that sorts before
// every candidate, so the K-th best is always the last slot. An insertion moves every
// slot at once (slot s takes slot s−1 if the candidate beats slot s−1, else the
// candidate if it beats slot s). A list in a dynamically indexed private array (local
// memory) or in workgroup memory was slower on an H100 (BENCHMARKS.md, "GPU").

const LIST_SLOTS: u32 = LIST_SLOTS_VALUEu;
// The search after the first (see `knn_query`); `knn.rs` compiles both variants.
const WARM: bool = WARM_VALUE;
const MAX_RING: i32 = 64;
const FAR: f32 = 3.4028235e38;

// Whether (d, j) sorts before (e, l): by squared distance, ties by index.
fn before(d: f32, j: u32, e: f32, l: u32) -> bool {
    return d < e || (d == e && j < l);
}

fn knn_query(i: u32, mode: u32) {
    let q = x[i].xyz;
    var k = params.knn_k;
    var max2 = FAR;
    var reach = FAR;
    let body_i = pinfo[i].x;
    if (mode == 1u) {
        k = params.contact_k;
        reach = 2.0 * (bodies[body_i].radius + params.max_radius);
        max2 = reach * reach;
    }
    k = min(k, LIST_SLOTS);
    if (k == 0u) {
        return;
    }
    let pad = LIST_SLOTS - k;
//LIST_DECL
    var stride = params.knn_k;
    if (mode == 1u) {
        stride = params.contact_k;
    }
    // Warm (the variant for searches after the first): this particle's row from the
    // previous search holds K distinct other particles (of other bodies in mode 1), so
    // the largest of their distances now bounds the K-th best from above, and farther
    // candidates need not be inserted nor their cells visited. A row not written yet
    // (NONE) gives no bound. The result is the same.
    var warm = FAR;
    if (WARM) {
        warm = previous_bound(i, mode, i * stride, k, q);
    }
    let bound2 = min(max2, warm);
    // With a bound, the scan only sets aside the candidates within it (about K) in
    // `spare`, and they are inserted afterwards: inserting while scanning makes every
    // thread of a warp wait for any one thread's insertion (about 200 instructions),
    // which happens at almost every candidate. Over K + SPARE_EXTRA of them (a loose
    // bound, the body moved much since the last search): the scan stops there and starts
    // again, inserting. (Inserting whenever K + SPARE_EXTRA had gathered, and restarting
    // with the K-th best of those as the bound, were both slower on an H100:
    // BENCHMARKS.md.)
    var collect = WARM && warm < FAR;
    var count = 0u;
    let spare_at = i * params.spare_stride;
    let spare_cap = k + SPARE_EXTRA;
    var cell = params.knn_cell;
    if (mode == 1u) {
        cell = params.grid_cell;
    }
    let c = cell_coords(q, cell);
    let rel = q / cell;
    // Rounding slack of the cell-box distance (m): a few ulps of the coordinates.
    let slack = 1.0e-6 * (max(max(abs(q.x), abs(q.y)), abs(q.z)) + cell);
    loop {
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
                        let cut = min(bound2, LAST_D);
                        if (cut < FAR) {
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
                            let e = aux[params.sorted_base + s];
                            let j = bitcast<u32>(e.w);
                            if (j == i) { continue; }
                            if (any(cell_coords(e.xyz, cell) != cc)) { continue; }
                            if (mode == 1u && pinfo[j].x == body_i) { continue; }
                            let d2 = dist2(q, e.xyz);
                            if (d2 > bound2) { continue; }
                            if (collect) {
                                if (count == spare_cap) {
                                    count = count + 1u;
                                    break; // too many: stop scanning (see above)
                                }
                                spare[spare_at + count] = j;
                                count = count + 1u;
                                continue;
                            }
                            // Insert into the sorted list unless it is full of better ones.
                            if (!before(d2, j, LAST_D, LAST_J)) {
                                continue;
                            }
//LIST_INSERT
                        }
                        if (count > spare_cap) { break; }
                        dx = dx + 1;
                    }
                    if (count > spare_cap) { break; }
                }
                if (count > spare_cap) { break; }
            }
            if (count > spare_cap || f32(r) * cell >= reach + cell) {
                break;
            }
            let known = min(bound2, LAST_D);
            if (known < FAR) {
                var bound = FAR;
                for (var a = 0; a < 3; a = a + 1) {
                    bound = min(bound, rel[a] - f32(c[a] - r));
                    bound = min(bound, f32(c[a] + r + 1) - rel[a]);
                }
                let b = max(bound, 0.0) * cell;
                if (known < b * b) {
                    break;
                }
            }
        }
        if (!collect) {
            break;
        }
        if (count > spare_cap) {
            collect = false;
            count = 0u;
            continue;
        }
        // The set-aside candidates, four at a time (their loads in flight together).
        let last = spare_at + count - 1u;
        for (var t = 0u; t < count; t = t + 4u) {
            let s = spare_at + t;
            let jj = vec4<u32>(spare[s], spare[min(s + 1u, last)], spare[min(s + 2u, last)], spare[min(s + 3u, last)]);
            let dd = vec4<f32>(dist2(q, x[jj.x].xyz), dist2(q, x[jj.y].xyz), dist2(q, x[jj.z].xyz), dist2(q, x[jj.w].xyz));
            for (var u = 0u; u < 4u; u = u + 1u) {
                if (t + u >= count) {
                    break;
                }
                let j = jj[u];
                let d2 = dd[u];
                if (!before(d2, j, LAST_D, LAST_J)) {
                    continue;
                }
//LIST_INSERT
            }
        }
        break;
    }
    // Slot pad + s is the s-th nearest; unfilled slots (FAR) write NONE.
    let base = i * stride - pad;
//LIST_OUT
}

fn previous(mode: u32, at: u32) -> u32 {
    if (mode == 1u) {
        return contacts[at];
    }
    return knn_out[at];
}

// The largest squared distance from q to the k particles of row `row` of the previous
// search (FAR if the row has a NONE or an index out of range). Four entries at a time,
// all their loads issued before any is used.
fn previous_bound(i: u32, mode: u32, row: u32, k: u32, q: vec3<f32>) -> f32 {
    var worst = 0.0;
    let last = row + k - 1u;
    for (var s = row; s <= last; s = s + 4u) {
        let a = vec4<u32>(
            previous(mode, s),
            previous(mode, min(s + 1u, last)),
            previous(mode, min(s + 2u, last)),
            previous(mode, min(s + 3u, last)),
        );
        if (any(a >= vec4<u32>(params.n)) || any(a == vec4<u32>(i))) {
            return FAR;
        }
        let d = vec4<f32>(dist2(q, x[a.x].xyz), dist2(q, x[a.y].xyz), dist2(q, x[a.z].xyz), dist2(q, x[a.w].xyz));
        worst = max(worst, max(max(d.x, d.y), max(d.z, d.w)));
    }
    // A little above: the scan computes the same distances from the grid's copy of the
    // positions, and a different rounding there must not push a listed particle out.
    return worst * 1.00001;
}

fn put(mode: u32, at: u32, d: f32, j: u32) {
    let o = select(j, NONE, d == FAR);
    if (mode == 1u) {
        contacts[at] = o;
    } else {
        knn_out[at] = o;
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
    let i = gid.x;
    if (i >= params.n) {
        return;
    }
    // Broad phase (broad.wgsl): a body near no other has no candidates, nor has a
    // particle farther than the contact reach from every body near its own.
    let b = pinfo[i].x;
    if (!near_body(b) || !may_touch(b, x[i].xyz)) {
        for (var s = 0u; s < params.contact_k; s = s + 1u) {
            contacts[i * params.contact_k + s] = NONE;
        }
        return;
    }
    knn_query(i, 1u);
}
