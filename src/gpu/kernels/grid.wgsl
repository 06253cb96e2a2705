// Uniform grid by counting sort, with no host round trip: cell counts (atomic), an
// exclusive prefix sum over the buckets (scan_block / scan_add, multi-level), and a
// scatter into bucket order. The grid is hashed (unbounded cell coordinates folded into
// `grid_table` buckets), so it needs no bounding box; the KNN kernel rejects points of
// other cells that share a bucket. CPU twin: core::knn::Grid::build_with_cell.


const SCAN_WG: u32 = 256u;
const SCAN_BLOCK: u32 = 1024u;
var<workgroup> tsum: array<u32, 256>;

// Zeroes the bucket counts and cursors (in the pass, instead of a buffer clear); each
// thread strides over the arrays, so the dispatch stays within 65,535 workgroups for
// any table size (above ~4M particles the table has more than 65,535 × 128 buckets).
@compute @workgroup_size(128)
fn grid_clear(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    let stride = nwg.x * 128u;
    for (var i = gid.x; i < arrayLength(&scan); i = i + stride) {
        atomicStore(&scan[i], 0u);
    }
    for (var i = gid.x; i < arrayLength(&cursor); i = i + stride) {
        atomicStore(&cursor[i], 0u);
    }
}

@compute @workgroup_size(128)
fn grid_count(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= params.n) {
        return;
    }
    let h = cell_hash(cell_coords(x[i].xyz, level.cell));
    cell_of[i] = h;
    atomicAdd(&scan[h], 1u);
}

// Exclusive scan of each 1024-element block in place; block totals to level.sums.
@compute @workgroup_size(256)
fn scan_block(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let base = wid.x * SCAN_BLOCK + lid.x * 4u;
    var vals = array<u32, 4>(0u, 0u, 0u, 0u);
    var local_sum = 0u;
    for (var k = 0u; k < 4u; k = k + 1u) {
        let e = base + k;
        if (e < level.count) {
            vals[k] = atomicLoad(&scan[level.offset + e]);
        }
        local_sum = local_sum + vals[k];
    }
    tsum[lid.x] = local_sum;
    workgroupBarrier();
    // Hillis–Steele inclusive scan of the 256 thread sums.
    for (var s = 1u; s < SCAN_WG; s = s << 1u) {
        var add = 0u;
        if (lid.x >= s) {
            add = tsum[lid.x - s];
        }
        workgroupBarrier();
        tsum[lid.x] = tsum[lid.x] + add;
        workgroupBarrier();
    }
    var run = tsum[lid.x] - local_sum;
    for (var k = 0u; k < 4u; k = k + 1u) {
        let e = base + k;
        if (e < level.count) {
            atomicStore(&scan[level.offset + e], run);
        }
        run = run + vals[k];
    }
    if (lid.x == SCAN_WG - 1u) {
        atomicStore(&scan[level.sums + wid.x], tsum[SCAN_WG - 1u]);
    }
}

// Adds each block's scanned offset (from the level above) to its elements.
@compute @workgroup_size(256)
fn scan_add(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let add = atomicLoad(&scan[level.sums + wid.x]);
    let base = wid.x * SCAN_BLOCK + lid.x * 4u;
    for (var k = 0u; k < 4u; k = k + 1u) {
        let e = base + k;
        if (e < level.count) {
            atomicAdd(&scan[level.offset + e], add);
        }
    }
}

@compute @workgroup_size(128)
fn grid_scatter(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= params.n) {
        return;
    }
    let h = cell_of[i];
    let slot = atomicLoad(&scan[h]) + atomicAdd(&cursor[h], 1u);
    aux[params.sorted_base + slot] = vec4<f32>(x[i].xyz, bitcast<f32>(i));
}
