// The per-dispatch range of the cluster, gather and hierarchy kernels (group 1, one
// 256-byte uniform record per range, bound with a dynamic offset; `GpuRange` in
// src/gpu/buffers.rs): level 0's particles or a coarse level's, or a run of records.

struct Range {
    first: u32,     // first particle, cluster or record
    count: u32,
    base: u32,      // prolong, transfer: start of the records in `hier`;
                    // level_in: 1 zeroes the level's multipliers (the coarsest level)
    flag: u32,      // gather: 1 leaves contacts and the boundary to the contact pass
    half: u32,      // level 0 with contacts: the half of p2 (0, 1) this iteration's pass B
                    // writes and its contact pass reads
    prev: u32,      // body_iteration: 1 runs the previous iteration's contact pass for
                    // its particles first (from the other half of p2)
    skip: u32,      // contact: 1 leaves the particles of body.wgsl's bodies to the next
                    // body_iteration
    iters: u32,     // body_iteration: Jacobi iterations in this dispatch (contacts only
                    // before the first, from the dispatch before; SolverSettings::contact_every)
};

@group(1) @binding(0) var<uniform> range: Range;
