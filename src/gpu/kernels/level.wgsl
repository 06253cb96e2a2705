// A small coarse level's Jacobi iterations in one workgroup (hierarchical PBD, Müller
// 2008): every iteration solves all the level's clusters (pass A, `solve_cluster`), then
// after a barrier gathers every particle's corrections (pass B, `gather_sum`), then
// another barrier, all in one dispatch instead of two dispatches per iteration. The same
// arithmetic as the one-thread cluster kernel and a one-lane gather, in the CPU twin's
// order (core::solver::Solver::solve_levels). On a small level a dispatch's latency, not
// its work, is the cost: the 972-particle level of the 50,000-particle bar took about
// 10 µs per dispatch (BENCHMARKS.md, "Hierarchy").
// `range` is the level's particle range; params.coarse_iterations the iteration count.

const LEVEL_WG: u32 = LEVEL_WG_VALUEu;

@compute @workgroup_size(LEVEL_WG)
fn solve_level(@builtin(local_invocation_index) lid: u32) {
    for (var it = 0u; it < params.coarse_iterations; it = it + 1u) {
        for (var l = lid; l < range.count; l = l + LEVEL_WG) {
            let c = range.first + l;
            if (!asleep(c)) {
                solve_cluster(c, cluster_moments(c, true));
            }
        }
        storageBarrier();
        workgroupBarrier();
        for (var l = lid; l < range.count; l = l + LEVEL_WG) {
            let j = range.first + l;
            gather_finish(j, gather_sum(j, 0u, 1u));
        }
        storageBarrier();
        workgroupBarrier();
    }
}
