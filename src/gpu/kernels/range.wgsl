// The per-dispatch range of the cluster, gather and hierarchy kernels (group 1, one
// 256-byte uniform record per range, bound with a dynamic offset; `GpuRange` in
// src/gpu/buffers.rs): level 0's particles or a coarse level's, or a run of records.

struct Range {
    first: u32,     // first particle, cluster or record
    count: u32,
    base: u32,      // prolong, transfer: start of the records in `hier`;
                    // level_in: 1 zeroes the level's multipliers (the coarsest level)
    flag: u32,      // gather: 1 leaves contacts and the boundary to the contact pass
};

@group(1) @binding(0) var<uniform> range: Range;
