//! Where every part of a [`super::GpuLattice`] lives in its buffers, with room for
//! bodies appended later, and the packing of one body into that room.
//!
//! Each level's nodes and elements, each level's inverse element lists, each colour's
//! order, each transfer's lists and each reduction table is a segment of its buffer
//! with a capacity of its own. A body is packed segment by segment, at each segment's
//! end, so that a world made with all its bodies and one made with some and appended
//! the rest hold the same data (only at other places). Lists are CSR: a node's list
//! ends where the next slot's begins, and every level's slots end in one spare slot
//! holding the end of the last list, so that the lists of a segment stay contiguous as
//! bodies are appended.

use super::{MAX_BODY_CHUNKS, MAX_LEVELS, WORKGROUP};
use crate::core::element::CubeOperator;
use crate::core::model::Model;
use crate::core::multigrid::{COLOURS, LatticeMultigrid};
use crate::core::solver::State;
use glam::{Mat3, Vec3};
use std::collections::HashMap;

/// A segment: where it starts and how many items it can hold and holds (in the
/// buffer's own items: u32 in `topo`, vec4 records in `elems`, blocks in `kmat`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(super) struct Seg {
    pub start: u32,
    pub cap: u32,
    pub used: u32,
}

impl Seg {
    /// The first free item.
    pub fn end(&self) -> u32 {
        self.start + self.used
    }
}

/// What one body takes of each segment.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(super) struct Extent {
    nodes: Vec<u32>,
    elems: Vec<u32>,
    inv: Vec<u32>,
    order: Vec<[u32; COLOURS]>,
    prol: Vec<u32>,
    restr: Vec<u32>,
    child: Vec<u32>,
    /// Blocks in `kmat`: every set of the body (an upper bound: sets already in the
    /// world are shared), or, as packed, only its new ones.
    kmat: u32,
    chunks: Vec<u32>,
}

impl Extent {
    fn zero(levels: usize) -> Self {
        Self {
            nodes: vec![0; levels],
            elems: vec![0; levels],
            inv: vec![0; levels],
            order: vec![[0; COLOURS]; levels],
            prol: vec![0; levels],
            restr: vec![0; levels],
            child: vec![0; levels],
            kmat: 0,
            chunks: vec![0; levels + 1],
        }
    }

    /// Each count the larger of the two.
    fn max(&mut self, o: &Extent) {
        let m = |a: &mut Vec<u32>, b: &Vec<u32>| {
            a.iter_mut().zip(b).for_each(|(x, y)| *x = (*x).max(*y))
        };
        m(&mut self.nodes, &o.nodes);
        m(&mut self.elems, &o.elems);
        m(&mut self.inv, &o.inv);
        m(&mut self.prol, &o.prol);
        m(&mut self.restr, &o.restr);
        m(&mut self.child, &o.child);
        m(&mut self.chunks, &o.chunks);
        for (a, b) in self.order.iter_mut().zip(&o.order) {
            a.iter_mut().zip(b).for_each(|(x, y)| *x = (*x).max(*y));
        }
        self.kmat = self.kmat.max(o.kmat);
    }

    /// Each count the sum of the two.
    fn add(&mut self, o: &Extent) {
        let a = |a: &mut Vec<u32>, b: &Vec<u32>| a.iter_mut().zip(b).for_each(|(x, y)| *x += *y);
        a(&mut self.nodes, &o.nodes);
        a(&mut self.elems, &o.elems);
        a(&mut self.inv, &o.inv);
        a(&mut self.prol, &o.prol);
        a(&mut self.restr, &o.restr);
        a(&mut self.child, &o.child);
        a(&mut self.chunks, &o.chunks);
        for (x, y) in self.order.iter_mut().zip(&o.order) {
            x.iter_mut().zip(y).for_each(|(p, q)| *p += *q);
        }
        self.kmat += o.kmat;
    }
}

/// Body `b` of a hierarchy as ranges of its joined arrays.
struct BodySlice {
    /// Per level: its nodes.
    nodes: Vec<std::ops::Range<u32>>,
    /// Per level: its elements.
    elems: Vec<std::ops::Range<u32>>,
    /// Per level and colour: its run of the colour order.
    order: Vec<[std::ops::Range<usize>; COLOURS]>,
}

/// Where `mg`'s body `b` lies in its joined arrays.
fn slice(mg: &LatticeMultigrid, b: usize, element_start: &[Vec<u32>]) -> BodySlice {
    let nl = mg.levels.len().min(MAX_LEVELS);
    let mut out = BodySlice {
        nodes: Vec::with_capacity(nl),
        elems: Vec::with_capacity(nl),
        order: Vec::with_capacity(nl),
    };
    for (l, lv) in mg.levels.iter().take(nl).enumerate() {
        let nodes = lv.body_start[b]..lv.body_start[b + 1];
        out.elems.push(element_start[l][b]..element_start[l][b + 1]);
        // Within a colour the order is ascending, and the bodies' nodes come in body
        // order: a body's run is where its node indices are.
        out.order.push(std::array::from_fn(|k| {
            let run = &lv.order[lv.colour_start[k] as usize..lv.colour_start[k + 1] as usize];
            let a = run.partition_point(|&j| j < nodes.start);
            let z = run.partition_point(|&j| j < nodes.end);
            lv.colour_start[k] as usize + a..lv.colour_start[k] as usize + z
        }));
        out.nodes.push(nodes);
    }
    out
}

/// Per level, where each body's elements start (bodies + 1 entries; a body's elements
/// are contiguous).
fn element_starts(mg: &LatticeMultigrid, bodies: usize) -> Vec<Vec<u32>> {
    mg.levels
        .iter()
        .take(MAX_LEVELS)
        .map(|lv| {
            let mut s = vec![0u32; bodies + 1];
            for &b in &lv.body {
                s[b as usize + 1] += 1;
            }
            for i in 0..bodies {
                s[i + 1] += s[i];
            }
            s
        })
        .collect()
}

/// The chunk records of one body's reduction items, the two runs `runs` (first item,
/// item count, body, 0): as few chunks as [`MAX_BODY_CHUNKS`] allows, each a multiple
/// of [`WORKGROUP`] items.
pub(super) fn body_chunks(body: u32, runs: [std::ops::Range<u32>; 2]) -> Vec<[u32; 4]> {
    let items: u32 = runs.iter().map(|r| r.len() as u32).sum();
    let per = (WORKGROUP as usize * MAX_BODY_CHUNKS) as u32;
    let len = WORKGROUP * items.div_ceil(per).max(1);
    let mut records = Vec::new();
    for r in runs {
        let mut at = r.start;
        while at < r.end {
            let count = len.min(r.end - at);
            records.push([at, count, body, 0]);
            at += count;
        }
    }
    records
}

/// What body `b` of `mg` takes of each segment.
fn extent(mg: &LatticeMultigrid, b: usize, s: &BodySlice) -> Extent {
    let nl = s.nodes.len();
    let mut e = Extent::zero(nl);
    for l in 0..nl {
        let lv = &mg.levels[l];
        let nodes = s.nodes[l].clone();
        e.nodes[l] = nodes.len() as u32;
        e.elems[l] = s.elems[l].len() as u32;
        e.inv[l] = lv.inv_start[nodes.end as usize] - lv.inv_start[nodes.start as usize];
        e.order[l] = std::array::from_fn(|k| s.order[l][k].len() as u32);
        if l + 1 < nl && !lv.prolong_start.is_empty() {
            let p = lv.prolong_start[nodes.end as usize] - lv.prolong_start[nodes.start as usize];
            e.prol[l] = 2 * p;
            // Each prolongation weight is a restriction entry of the coarse node.
            e.restr[l + 1] = 2 * p;
        }
        if l > 0 {
            e.kmat += 64 * e.elems[l];
            // The children of this level's elements (lists of the finer level).
            let fine = &mg.levels[l - 1];
            if !fine.child_start.is_empty() {
                let r = &s.elems[l];
                e.child[l] = fine.child_start[r.end as usize] - fine.child_start[r.start as usize];
            }
        }
    }
    if mg.unit_blocks[b].is_some() {
        e.kmat += UNIT_SET;
    }
    // Chunks: the energy's (elements and nodes), then each level's nodes.
    let count = |n: u32| {
        n.div_ceil((WORKGROUP as usize * MAX_BODY_CHUNKS) as u32)
            .max(1)
    };
    let len = |items: u32| WORKGROUP * count(items);
    let energy = e.elems[0] + e.nodes[0];
    let l0 = len(energy);
    e.chunks[0] = e.elems[0].div_ceil(l0) + e.nodes[0].div_ceil(l0);
    for l in 0..nl {
        e.chunks[1 + l] = e.nodes[l].div_ceil(len(e.nodes[l]));
    }
    e
}

/// Where everything is, with room.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Layout {
    /// Per level: node slots (global node index); a level's slots are `cap + 1`, the
    /// last a spare for the end of its lists.
    pub nodes: Vec<Seg>,
    /// Per level: element slots (global element index), likewise.
    pub elems: Vec<Seg>,
    /// Per level: its nodes' inverse element lists in `topo`.
    pub inv: Vec<Seg>,
    /// Per level and colour: its run of the colour order in `topo`.
    pub order: Vec<[Seg; COLOURS]>,
    /// Per level but the coarsest: its nodes' prolongation lists in `topo` (node, weight
    /// bits).
    pub prol: Vec<Seg>,
    /// Per level but the finest: its nodes' restriction lists in `topo` (fine node,
    /// weight bits).
    pub restr: Vec<Seg>,
    /// Per level but the finest: its elements' child lists in `topo` (elements of the
    /// finer level).
    pub child: Vec<Seg>,
    /// Per level: the most nodes one body packed so far has there.
    pub most_nodes: Vec<u32>,
    /// The stiffness blocks in `kmat` (3 vec4 each).
    pub kmat: Seg,
    /// Where each distinct set of 64 blocks packed so far starts in `kmat` (in blocks),
    /// by [`fingerprint`]: an element whose blocks are already there points at them.
    pub shared: HashMap<u128, u32>,
    /// The reductions' tables: their chunk records, from the first chunk.
    pub tables: Vec<Seg>,
    /// Bodies.
    pub bodies: Seg,
    /// Where the prolongation, restriction and child heads start in `topo`.
    pub prol_base: u32,
    pub restr_base: u32,
    pub child_base: u32,
    /// Words of `topo`.
    pub topo_len: u32,
    /// Where the chunk records start in `elems` (vec4), where the per-body chunk starts
    /// start (u32 index into `elems`), and the vec4s of `elems`.
    pub chunk_base: u32,
    pub starts_base: u32,
    pub elems_len: u32,
    /// Where level 0's neighbour records start in `elems` (vec4; [`NBR_RECORD`] a
    /// level-0 node slot, see [`neighbour_record`]).
    pub nbr_base: u32,
}

/// One write of packed data: buffer, where (u32 words), what.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Buf {
    Elems,
    Kmat,
    Topo,
    Nodes,
    Mats,
    Rot,
    Pos,
    Ccol,
    Bodyt,
}

/// Writes of packed data, in order.
#[derive(Debug, Default)]
pub(super) struct Writes(pub Vec<(Buf, u32, Vec<u32>)>);

impl Writes {
    fn put(&mut self, buf: Buf, at: u32, data: Vec<u32>) {
        if !data.is_empty() {
            self.0.push((buf, at, data));
        }
    }

    fn vec4s(&mut self, buf: Buf, at_vec4: u32, data: impl IntoIterator<Item = [f32; 4]>) {
        let words = data.into_iter().flat_map(|v| v.map(f32::to_bits)).collect();
        self.put(buf, 4 * at_vec4, words);
    }
}

/// Vec4s of a level-0 node's neighbour record in `elems` ([`neighbour_record`]).
pub(super) const NBR_RECORD: u32 = 9;

/// No element on that side of a node (a neighbour record's element word).
pub(super) const NBR_NONE: u32 = u32::MAX;

/// Level-0 node `j`'s neighbour record (36 words; the shader's `lattice_terms`): a row
/// of `A x` read from it takes one load for where everything is instead of a chain
/// through the node's element list and each element's corners.
///
/// - Words 0..26: the node slots of its 26 lattice neighbours, the one at offset
///   `(m % 3, m / 3 % 3, m / 9) − 1` for `m` in 0..27 but 13 (the node itself) at word
///   `m` below 13 and `m − 1` above; a neighbour that is a corner of none of its
///   elements is the node itself (a safe load, never used).
/// - Words 26..34: the element slot on each side `s` (x from bit 0, y bit 1, z bit 2:
///   the element's lowest corner is at offset `s − 1` per axis), or [`NBR_NONE`]; the
///   node is that element's corner `7 − s`.
/// - Word 34: the body's unit cube operator (its blocks' base in `kmat`); word 35: the
///   elements' stiffness scale `V / h²` (f32 bits; all of a body's are one).
fn neighbour_record(
    lv: &crate::core::multigrid::MgLevel,
    j: u32,
    nslot: impl Fn(u32) -> u32,
    eslot: impl Fn(u32) -> u32,
    kb: u32,
) -> [u32; 4 * NBR_RECORD as usize] {
    let me = nslot(j);
    let mut w = [me; 4 * NBR_RECORD as usize];
    w[26..34].fill(NBR_NONE);
    w[34] = kb;
    w[35] = 0;
    let list = &lv.inv[lv.inv_start[j as usize] as usize..lv.inv_start[j as usize + 1] as usize];
    for &ec in list {
        let (e, a) = (ec >> 3, (ec & 7) as usize);
        let s = 7 - a;
        debug_assert_eq!(w[26 + s], NBR_NONE, "two elements on one side of node {j}");
        w[26 + s] = eslot(e);
        w[35] = lv.scale[e as usize].to_bits();
        for (c, &q) in lv.elements[e as usize].iter().enumerate() {
            let m = ((s & 1) + (c & 1))
                + 3 * (((s >> 1) & 1) + ((c >> 1) & 1))
                + 9 * ((s >> 2) + (c >> 2));
            if m != 13 {
                w[if m < 13 { m } else { m - 1 }] = nslot(q);
            } else {
                debug_assert_eq!(q, j, "corner {c} of element {e} is not node {j}");
            }
        }
    }
    w
}

/// Vec4s of a body's material record in `mats`: (μ, λ, contact radius, spacing), then
/// its unit cube operator ([`operator_words`] less its padding).
pub(crate) const MAT_RECORD: usize = 6;

fn vec4(v: Vec3) -> [f32; 4] {
    v.extend(0.0).to_array()
}

/// A 128-bit fingerprint of a set of stiffness blocks (of their f32 bits): two 64-bit
/// multiply–xor hashes with independent constants. Elements whose blocks are equal, bit
/// for bit, share one copy in `kmat` (a lattice's interior coarse elements, and every
/// copy of a body, have the same blocks); two different sets collide with a chance of
/// about 2⁻¹²⁸.
fn fingerprint(blocks: &[Mat3]) -> u128 {
    let (mut a, mut b) = (0x243f_6a88_85a3_08d3u64, 0x1319_8a2e_0370_7344u64);
    for m in blocks {
        for v in m.to_cols_array() {
            let w = v.to_bits() as u64;
            a = (a ^ w).wrapping_mul(0x9e37_79b9_7f4a_7c15).rotate_left(27);
            b = (b ^ w.rotate_left(17))
                .wrapping_mul(0xc2b2_ae3d_27d4_eb4f)
                .rotate_left(31);
        }
    }
    let mix = |mut h: u64| {
        h ^= h >> 33;
        h = h.wrapping_mul(0xff51_afd7_ed55_8ccd);
        h ^ (h >> 33)
    };
    ((mix(a) as u128) << 64) | mix(b ^ blocks.len() as u64) as u128
}

/// Blocks of `kmat` a body's unit-cube set takes: its 64 stiffness blocks, then its
/// factored operator (`CubeOperator`, [`operator_words`]) in the room of two.
const UNIT_SET: u32 = 64 + 2;

/// Blocks of `kmat` a set takes: a unit cube's with its operator after it, a coarse
/// element's its 64 blocks.
fn set_room(unit: bool) -> u32 {
    if unit { UNIT_SET } else { 64 }
}

/// A body's unit-cube operator as the six vec4 the lattice kernels read after its unit
/// blocks: μ, λ, the pairs' entries, the triple's, the singles' (`cube_op_row` in
/// lattice.wgsl), zero-padded.
fn operator_words(op: &CubeOperator) -> [[f32; 4]; 6] {
    let [p0, p1, p2] = op.pairs;
    let t = op.triple;
    let s = op.singles;
    [
        [op.mu, op.lambda, p0[0], p0[1]],
        [p0[2], p1[0], p1[1], p1[2]],
        [p2[0], p2[1], p2[2], t[0]],
        [t[1], t[2], t[3], t[4]],
        [t[5], s[0], s[1], s[2]],
        [0.0; 4],
    ]
}

/// Body `b`'s stiffness block sets in packing order: its unit cube's (a lattice body),
/// then each coarse element's, level by level.
fn block_sets<'a>(
    mg: &'a LatticeMultigrid,
    b: usize,
    s: &'a BodySlice,
) -> impl Iterator<Item = &'a [Mat3]> + 'a {
    let unit = mg.unit_blocks[b].as_deref().into_iter();
    let coarse = (1..s.nodes.len()).flat_map(move |l| {
        let lv = &mg.levels[l];
        s.elems[l]
            .clone()
            .map(move |e| &lv.blocks[64 * e as usize..64 * (e as usize + 1)])
    });
    unit.chain(coarse)
}

/// Empty segments of capacities `caps` one after another from 0, each followed by
/// `spare` items; and where the last ends.
fn back_to_back(caps: Vec<u32>, spare: u32) -> (Vec<Seg>, u32) {
    let mut at = 0;
    let segs = caps
        .into_iter()
        .map(|cap| {
            let s = Seg {
                start: at,
                cap,
                used: 0,
            };
            at += cap + spare;
            s
        })
        .collect();
    (segs, at)
}

/// The room a segment of `used` items gets: `room` times as many and `one` more, or
/// exactly `used` where `room` is at most 1.
fn room_for(used: u32, one: u32, room: f32) -> u32 {
    if room > 1.0 {
        ((used as f64 * room as f64).ceil() as u32).max(used) + one
    } else {
        used
    }
}

impl Layout {
    /// A layout for `mg`'s bodies with `room` times their size and one more of their
    /// largest in every segment (exactly their size where `room` is at most 1); the
    /// bodies are not packed yet (nothing used).
    pub fn new(mg: &LatticeMultigrid, room: f32) -> Self {
        let nl = mg.levels.len().clamp(1, MAX_LEVELS);
        let bodies = mg.unit.len();
        let starts = element_starts(mg, bodies);
        let mut total = Extent::zero(nl);
        let mut most = Extent::zero(nl);
        // The distinct block sets: only those take room in `kmat`.
        let mut distinct = HashMap::new();
        for b in 0..bodies {
            let s = slice(mg, b, &starts);
            let e = extent(mg, b, &s);
            total.add(&e);
            most.max(&e);
            let unit = mg.unit_blocks[b].is_some();
            for (i, p) in block_sets(mg, b, &s).map(fingerprint).enumerate() {
                distinct.insert(p, set_room(unit && i == 0));
            }
        }
        total.kmat = distinct.values().sum();
        let caps = |t: &Vec<u32>, m: &Vec<u32>| -> Vec<u32> {
            t.iter()
                .zip(m)
                .map(|(&t, &m)| room_for(t, m, room))
                .collect()
        };
        // Node and element slots, each level's ending in a spare.
        let (nodes, node_slots) = back_to_back(caps(&total.nodes, &most.nodes), 1);
        let (elems, elem_slots) = back_to_back(caps(&total.elems, &most.elems), 1);
        // `topo`: the inverse lists' heads (one per node slot, and one more), lists,
        // colour orders, the transfers' and children's heads and lists.
        let mut at = node_slots + 1;
        let mut seg = |cap: u32| {
            let s = Seg {
                start: at,
                cap,
                used: 0,
            };
            at += cap;
            s
        };
        let inv: Vec<Seg> = caps(&total.inv, &most.inv)
            .into_iter()
            .map(&mut seg)
            .collect();
        let order: Vec<[Seg; COLOURS]> = (0..nl)
            .map(|l| {
                std::array::from_fn(|k| seg(room_for(total.order[l][k], most.order[l][k], room)))
            })
            .collect();
        let prol: Vec<Seg> = caps(&total.prol, &most.prol)
            .into_iter()
            .map(&mut seg)
            .collect();
        let restr: Vec<Seg> = caps(&total.restr, &most.restr)
            .into_iter()
            .map(&mut seg)
            .collect();
        let child: Vec<Seg> = caps(&total.child, &most.child)
            .into_iter()
            .map(&mut seg)
            .collect();
        let fine_slots = nodes[nl - 1].start;
        let coarse_nodes = nodes.get(1).map_or(node_slots, |s| s.start);
        let coarse_elems = elems.get(1).map_or(elem_slots, |s| s.start);
        let prol_base = at;
        let restr_base = prol_base + fine_slots + 1;
        let child_base = restr_base + (node_slots - coarse_nodes) + 1;
        let topo_len = child_base + (elem_slots - coarse_elems) + 1;
        let kmat = Seg {
            start: 0,
            cap: room_for(total.kmat, most.kmat, room),
            used: 0,
        };
        let body_cap = room_for(bodies as u32, 1, room);
        let chunk_base = 3 * elem_slots;
        let (tables, chunks) = back_to_back(caps(&total.chunks, &most.chunks), 0);
        let starts_base = 4 * (chunk_base + chunks);
        let starts_words = tables.len() as u32 * (body_cap + 1);
        let nbr_base = starts_base / 4 + starts_words.div_ceil(4);
        let elems_len = nbr_base + NBR_RECORD * (nodes[0].cap + 1);
        Self {
            nodes,
            elems,
            inv,
            order,
            prol,
            restr,
            child,
            most_nodes: vec![0; nl],
            kmat,
            shared: HashMap::new(),
            tables,
            bodies: Seg {
                start: 0,
                cap: body_cap,
                used: 0,
            },
            prol_base,
            restr_base,
            child_base,
            topo_len,
            chunk_base,
            starts_base,
            elems_len,
            nbr_base,
        }
    }

    /// Levels.
    pub fn levels(&self) -> usize {
        self.nodes.len()
    }

    /// Node slots of level 0 (the stride of the per-particle regions).
    pub fn n_slots(&self) -> u32 {
        self.nodes[0].cap + 1
    }

    /// Node slots of every level (the stride of the per-node regions).
    pub fn node_slots(&self) -> u32 {
        let last = self.nodes[self.levels() - 1];
        last.start + last.cap + 1
    }

    /// Element slots of level 0.
    pub fn ne_slots(&self) -> u32 {
        self.elems[0].cap + 1
    }

    /// Element slots of every level.
    pub fn elem_slots(&self) -> u32 {
        let last = self.elems[self.levels() - 1];
        last.start + last.cap + 1
    }

    /// The most chunks a reduction table can hold.
    pub fn most_chunks(&self) -> u32 {
        self.tables.iter().map(|t| t.cap).max().unwrap_or(0)
    }

    /// Whether body `b` of `mg` fits the room left (same depth or shallower).
    fn fits(&self, e: &Extent) -> bool {
        let nl = self.levels();
        let ok =
            |segs: &[Seg], need: &[u32]| segs.iter().zip(need).all(|(s, &n)| s.used + n <= s.cap);
        e.nodes.len() <= nl
            && self.bodies.used < self.bodies.cap
            && ok(&self.nodes, &e.nodes)
            && ok(&self.elems, &e.elems)
            && ok(&self.inv, &e.inv)
            && ok(&self.prol, &e.prol)
            && ok(&self.restr, &e.restr)
            && ok(&self.child, &e.child)
            && ok(&self.tables, &e.chunks)
            && self.order.iter().zip(&e.order).all(|(s, n)| ok(s, n))
            && self.kmat.used + e.kmat <= self.kmat.cap
    }

    /// Packs every body of `mg` (the hierarchy of `model` in `state`) in order.
    pub fn pack_all(
        &mut self,
        model: &Model,
        mg: &LatticeMultigrid,
        state: &State,
        out: &mut Writes,
    ) -> bool {
        let starts = element_starts(mg, mg.unit.len());
        (0..mg.unit.len()).all(|b| self.pack_body(model, mg, b, &starts, state, out))
    }

    /// Packs body `b` of `mg` (`model`'s hierarchy, `state` its state) as the next
    /// body of the world at the end of every segment, or returns false (nothing
    /// written, nothing used) where it does not fit.
    pub fn pack_body(
        &mut self,
        model: &Model,
        mg: &LatticeMultigrid,
        b: usize,
        element_start: &[Vec<u32>],
        state: &State,
        out: &mut Writes,
    ) -> bool {
        let s = slice(mg, b, element_start);
        let mut ext = extent(mg, b, &s);
        // The body's block sets in packing order; those not in the world yet take room.
        let prints: Vec<u128> = block_sets(mg, b, &s).map(fingerprint).collect();
        let unit = mg.unit_blocks[b].is_some();
        let fresh: HashMap<u128, u32> = prints
            .iter()
            .enumerate()
            .filter(|(_, p)| !self.shared.contains_key(p))
            .map(|(i, &p)| (p, set_room(unit && i == 0)))
            .collect();
        ext.kmat = fresh.values().sum();
        if !self.fits(&ext) {
            return false;
        }
        let nl = s.nodes.len().min(self.levels());
        let body = self.bodies.end();
        // Where each level's nodes and elements go: joined index → slot.
        let node_at: Vec<i64> = (0..nl)
            .map(|l| self.nodes[l].end() as i64 - s.nodes[l].start as i64)
            .collect();
        let elem_at: Vec<i64> = (0..nl)
            .map(|l| self.elems[l].end() as i64 - s.elems[l].start as i64)
            .collect();
        let nslot = |l: usize, j: u32| (j as i64 + node_at[l]) as u32;
        let eslot = |l: usize, e: u32| (e as i64 + elem_at[l]) as u32;
        // Stiffness blocks: the body's unit cube, then its coarse elements', each set
        // written once into the world (`shared`).
        let mut kmat: Vec<[f32; 4]> = Vec::new();
        let kbase = self.kmat.end();
        let shared = &mut self.shared;
        let mut print = prints.into_iter();
        let mut place = |blocks: &[Mat3], op: Option<&CubeOperator>| -> u32 {
            let p = print.next().unwrap_or_else(|| fingerprint(blocks));
            debug_assert_eq!(p, fingerprint(blocks));
            *shared.entry(p).or_insert_with(|| {
                let base = kbase + (kmat.len() / 3) as u32;
                for m in blocks {
                    kmat.extend([vec4(m.x_axis), vec4(m.y_axis), vec4(m.z_axis)]);
                }
                if let Some(op) = op {
                    kmat.extend(operator_words(op));
                }
                base
            })
        };
        let unit_base = match (&mg.unit_blocks[b], &mg.unit_operator[b]) {
            (Some(blocks), Some(op)) => place(blocks, Some(op)),
            _ => kbase,
        };
        for l in 0..nl {
            let lv = &mg.levels[l];
            // Element records.
            let mut recs: Vec<[u32; 4]> = Vec::with_capacity(3 * s.elems[l].len());
            for e in s.elems[l].clone() {
                let c = lv.elements[e as usize].map(|j| nslot(l, j));
                recs.push([c[0], c[1], c[2], c[3]]);
                recs.push([c[4], c[5], c[6], c[7]]);
                if l == 0 {
                    let r = &model.element_rest[e as usize];
                    recs.push([unit_base, body, r.size.to_bits(), r.volume.to_bits()]);
                } else {
                    let base = place(&lv.blocks[64 * e as usize..64 * (e as usize + 1)], None);
                    recs.push([base, body, 0, 0]);
                }
            }
            out.put(
                Buf::Elems,
                4 * 3 * self.elems[l].end(),
                recs.into_iter().flatten().collect(),
            );
            if l == 0 {
                let words: Vec<u32> = s.nodes[0]
                    .clone()
                    .flat_map(|j| {
                        neighbour_record(lv, j, |q| nslot(0, q), |e| eslot(0, e), unit_base)
                    })
                    .collect();
                out.put(
                    Buf::Elems,
                    4 * (self.nbr_base + NBR_RECORD * self.nodes[0].end()),
                    words,
                );
            }
            // Inverse element lists and their heads (the spare after them: their end).
            let nodes = s.nodes[l].clone();
            let mut heads = Vec::with_capacity(nodes.len() + 1);
            let mut lists = Vec::new();
            let at = self.inv[l].end();
            for j in nodes.clone() {
                heads.push(at + lists.len() as u32);
                for &ec in &lv.inv
                    [lv.inv_start[j as usize] as usize..lv.inv_start[j as usize + 1] as usize]
                {
                    lists.push((eslot(l, ec >> 3) << 3) | (ec & 7));
                }
            }
            heads.push(at + lists.len() as u32);
            out.put(Buf::Topo, self.nodes[l].end(), heads);
            out.put(Buf::Topo, at, lists);
            // Colour orders.
            for k in 0..COLOURS {
                let run: Vec<u32> = lv.order[s.order[l][k].clone()]
                    .iter()
                    .map(|&j| nslot(l, j))
                    .collect();
                out.put(Buf::Topo, self.order[l][k].end(), run);
            }
            // Node records: mass, held, reach (level 0: half the spacing), body.
            let recs = nodes.clone().map(|j| {
                let j = j as usize;
                let reach = if l == 0 {
                    0.5 * model.bodies[model.particle_body[j] as usize].spacing
                } else {
                    0.0
                };
                [lv.mass[j], lv.fixed[j] as u32 as f32, reach, body as f32]
            });
            out.vec4s(Buf::Nodes, self.nodes[l].end(), recs);
            // Prolongation lists (to the next level's nodes), their heads, and the
            // restriction lists they make (coarse node → fine nodes, in fine order).
            if l + 1 < nl && !lv.prolong_start.is_empty() {
                let at = self.prol[l].end();
                let mut heads = Vec::with_capacity(nodes.len() + 1);
                let mut lists = Vec::new();
                let coarse = s.nodes[l + 1].clone();
                let mut restr: Vec<Vec<(u32, f32)>> = vec![Vec::new(); coarse.len()];
                for j in nodes.clone() {
                    heads.push(at + lists.len() as u32);
                    for q in lv.prolong_start[j as usize] as usize
                        ..lv.prolong_start[j as usize + 1] as usize
                    {
                        let c = lv.prolong_node[q];
                        let w = lv.prolong_weight[q];
                        lists.extend([nslot(l + 1, c), w.to_bits()]);
                        restr[(c - coarse.start) as usize].push((nslot(l, j), w));
                    }
                }
                heads.push(at + lists.len() as u32);
                out.put(Buf::Topo, self.prol_base + self.nodes[l].end(), heads);
                out.put(Buf::Topo, at, lists);
                let at = self.restr[l + 1].end();
                let mut heads = Vec::with_capacity(coarse.len() + 1);
                let mut lists = Vec::new();
                for r in &restr {
                    heads.push(at + lists.len() as u32);
                    for &(f, w) in r {
                        lists.extend([f, w.to_bits()]);
                    }
                }
                heads.push(at + lists.len() as u32);
                out.put(
                    Buf::Topo,
                    self.restr_base + self.nodes[l + 1].end() - self.nodes[1].start,
                    heads,
                );
                out.put(Buf::Topo, at, lists);
            }
            // Children of this level's elements (the finer level's).
            if l > 0 {
                let fine = &mg.levels[l - 1];
                let at = self.child[l].end();
                let mut heads = Vec::with_capacity(s.elems[l].len() + 1);
                let mut lists = Vec::new();
                if !fine.child_start.is_empty() {
                    for k in s.elems[l].clone() {
                        heads.push(at + lists.len() as u32);
                        for &e in &fine.child[fine.child_start[k as usize] as usize
                            ..fine.child_start[k as usize + 1] as usize]
                        {
                            lists.push(eslot(l - 1, e));
                        }
                    }
                }
                heads.push(at + lists.len() as u32);
                out.put(
                    Buf::Topo,
                    self.child_base + self.elems[l].end() - self.elems[1].start,
                    heads,
                );
                out.put(Buf::Topo, at, lists);
            }
            // Element rotations: level 0's from the state, the coarse ones at rest.
            let rots: Vec<[f32; 4]> = if l == 0 {
                s.elems[0]
                    .clone()
                    .map(|e| state.element_rot[e as usize].to_array())
                    .collect()
            } else {
                vec![[0.0, 0.0, 0.0, 1.0]; s.elems[l].len()]
            };
            out.vec4s(Buf::Rot, self.elems[l].end(), rots);
        }
        debug_assert_eq!(kmat.len() as u32, 3 * ext.kmat);
        out.vec4s(Buf::Kmat, 3 * kbase, kmat);
        // Particle state: positions, velocities, pin targets (w = 1 where pinned), and
        // the collider state (nothing touched, the state's grasps).
        let n = self.n_slots();
        let p0 = s.nodes[0].clone();
        let first = self.nodes[0].end();
        let xs: Vec<[f32; 4]> = p0.clone().map(|i| vec4(state.x[i as usize])).collect();
        out.vec4s(Buf::Pos, first, xs.clone());
        out.vec4s(Buf::Pos, n + first, xs);
        out.vec4s(
            Buf::Pos,
            3 * n + first,
            p0.clone().map(|i| vec4(state.v[i as usize])),
        );
        let mut pins = vec![[0.0f32; 4]; p0.len()];
        for (slot, &i) in model.pinned.iter().enumerate() {
            if p0.contains(&i) {
                let t = state
                    .pin_targets
                    .get(slot)
                    .copied()
                    .unwrap_or(state.x[i as usize]);
                pins[(i - p0.start) as usize] = t.extend(1.0).to_array();
            }
        }
        out.vec4s(Buf::Pos, 4 * n + first, pins);
        let m = p0.len();
        out.vec4s(Buf::Ccol, first, vec![[0.0, 0.0, 0.0, -1.0]; m]);
        out.vec4s(Buf::Ccol, n + first, vec![[-1.0, 0.0, 0.0, 0.0]; m]);
        out.vec4s(
            Buf::Ccol,
            2 * n + first,
            p0.clone().map(|i| {
                let g = state.grab[i as usize];
                if g.collider == u32::MAX {
                    [0.0; 4]
                } else {
                    g.offset.extend(g.collider as f32 + 1.0).to_array()
                }
            }),
        );
        out.vec4s(Buf::Ccol, 3 * n + first, vec![[0.0, 0.0, 0.0, -1.0]; m]);
        // Trust bound 1, no collider step.
        out.put(Buf::Bodyt, body, vec![1.0f32.to_bits()]);
        out.put(Buf::Bodyt, self.bodies.cap + body, vec![0]);
        // The material record.
        let mut rec = vec![[0.0f32; 4]; MAT_RECORD];
        if let (Some(mat), Some(op)) = (&mg.material[b], &mg.unit_operator[b]) {
            let info = &model.bodies[b];
            rec[0] = [mat.mu, mat.lambda, info.radius, info.spacing];
            rec[1..].copy_from_slice(&operator_words(op)[..MAT_RECORD - 1]);
        }
        out.vec4s(Buf::Mats, body * MAT_RECORD as u32, rec);
        // The reductions' chunks: the energy's (elements, then nodes as items past the
        // level-0 element slots), then each level's nodes; and where the body's start.
        let ne = self.ne_slots();
        let n0 = self.nodes[0].end()..self.nodes[0].end() + p0.len() as u32;
        let e0 = self.elems[0].end()..self.elems[0].end() + s.elems[0].len() as u32;
        let mut tables = vec![body_chunks(body, [e0, ne + n0.start..ne + n0.end])];
        for l in 0..self.levels() {
            let r = if l < nl {
                self.nodes[l].end()..self.nodes[l].end() + s.nodes[l].len() as u32
            } else {
                0..0
            };
            tables.push(body_chunks(body, [r, 0..0]));
        }
        for (t, recs) in tables.iter().enumerate() {
            debug_assert_eq!(recs.len() as u32, ext.chunks.get(t).copied().unwrap_or(0));
            let seg = self.tables[t];
            out.put(
                Buf::Elems,
                4 * (self.chunk_base + seg.end()),
                recs.iter().flatten().copied().collect(),
            );
            let i = self.starts_base + t as u32 * (self.bodies.cap + 1) + body;
            out.put(Buf::Elems, i, vec![seg.used, seg.used + recs.len() as u32]);
            self.tables[t].used += recs.len() as u32;
        }
        // Everything written: the segments move on.
        for l in 0..nl {
            self.most_nodes[l] = self.most_nodes[l].max(ext.nodes[l]);
            self.nodes[l].used += ext.nodes[l];
            self.elems[l].used += ext.elems[l];
            self.inv[l].used += ext.inv[l];
            self.prol[l].used += ext.prol[l];
            self.restr[l].used += ext.restr[l];
            self.child[l].used += ext.child[l];
            for k in 0..COLOURS {
                self.order[l][k].used += ext.order[l][k];
            }
        }
        self.kmat.used += ext.kmat;
        self.bodies.used += 1;
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::model::{BodyDesc, Discretisation, Material};
    use crate::core::multigrid::{MAX_LEVELS, MIN_NODES};
    use crate::core::procedural;
    use crate::core::sampling::Resolution;
    use std::collections::HashSet;

    /// Three lattice boxes: two of one material (the second a moved copy of the first),
    /// one stiffer.
    fn boxes() -> Model {
        let mut model = Model::new();
        let mesh = procedural::cuboid(Vec3::new(0.03, 0.02, 0.025), 1);
        for (k, e) in [(0.0f32, 10e3f32), (1.0, 10e3), (2.0, 40e3)] {
            model
                .add_body(
                    &mesh,
                    &BodyDesc {
                        resolution: Resolution::Spacing(0.006),
                        material: Material::Hyperelastic {
                            youngs_modulus: e,
                            poisson_ratio: 0.3,
                        },
                        discretisation: Discretisation::Lattice,
                        translation: Vec3::new(0.2 * k, 0.3, 0.0),
                        ..Default::default()
                    },
                )
                .unwrap();
        }
        model
    }

    /// The packed buffers' words, from the writes.
    fn buffer(w: &Writes, buf: Buf) -> Vec<u32> {
        let mut out = Vec::new();
        for (b, at, data) in &w.0 {
            if *b == buf {
                let end = *at as usize + data.len();
                if out.len() < end {
                    out.resize(end, 0);
                }
                out[*at as usize..end].copy_from_slice(data);
            }
        }
        out
    }

    /// Every level-0 node's neighbour record lists exactly the elements it is a corner
    /// of (found by brute force over the element records), each on the side that makes
    /// the node its corner `7 − side`, and names each of their corners at its lattice
    /// offset; its operator base is its elements', and its scale theirs.
    #[test]
    fn neighbour_records_name_each_nodes_elements_and_corners() {
        let model = boxes();
        let mg = LatticeMultigrid::new(&model, MIN_NODES, MAX_LEVELS);
        let state = State::new(&model);
        let mut layout = Layout::new(&mg, 2.0);
        let mut w = Writes::default();
        assert!(layout.pack_all(&model, &mg, &state, &mut w));
        let elems = buffer(&w, Buf::Elems);
        let n0 = layout.nodes[0];
        let e0 = layout.elems[0];
        let mut owned: HashMap<u32, Vec<(u32, usize)>> = HashMap::new();
        for e in e0.start..e0.end() {
            for c in 0..8 {
                let q = elems[(12 * e) as usize + c];
                owned.entry(q).or_default().push((e, c));
            }
        }
        let mut checked = 0;
        for j in n0.start..n0.end() {
            let o = (4 * (layout.nbr_base + NBR_RECORD * j)) as usize;
            let rec = &elems[o..o + 36];
            let word = |m: usize| {
                if m == 13 {
                    j
                } else {
                    rec[if m < 13 { m } else { m - 1 }]
                }
            };
            let mut found: Vec<(u32, usize)> = Vec::new();
            for s in 0..8 {
                let e = rec[26 + s];
                if e == NBR_NONE {
                    continue;
                }
                found.push((e, 7 - s));
                let info = &elems[(12 * e + 8) as usize..(12 * e + 12) as usize];
                assert_eq!(rec[34], info[0], "node {j}: operator base");
                let (size, vol) = (f32::from_bits(info[2]), f32::from_bits(info[3]));
                let scale = f32::from_bits(rec[35]);
                assert!(
                    (scale - vol / (size * size)).abs() <= 1e-6 * scale,
                    "node {j}: scale"
                );
                for c in 0..8 {
                    let m = ((s & 1) + (c & 1))
                        + 3 * (((s >> 1) & 1) + ((c >> 1) & 1))
                        + 9 * ((s >> 2) + (c >> 2));
                    assert_eq!(
                        word(m),
                        elems[(12 * e) as usize + c],
                        "node {j}, side {s}, corner {c}"
                    );
                }
                checked += 1;
            }
            let mut want = owned.remove(&j).unwrap_or_default();
            want.sort_unstable();
            found.sort_unstable();
            assert_eq!(found, want, "node {j}: its elements");
        }
        assert_eq!(checked, 8 * e0.used as usize);
    }

    /// Equal stiffness block sets are written once and shared: every element (and every
    /// body's unit cube) reads back its own blocks bit for bit, the moved copy adds
    /// nothing, and the world holds fewer blocks than its elements have.
    #[test]
    fn equal_stiffness_blocks_are_stored_once() {
        let model = boxes();
        let mg = LatticeMultigrid::new(&model, MIN_NODES, MAX_LEVELS);
        assert!(mg.levels.len() >= 2, "levels {}", mg.levels.len());
        let state = State::new(&model);
        let mut layout = Layout::new(&mg, 1.0);
        let mut w = Writes::default();
        assert!(layout.pack_all(&model, &mg, &state, &mut w));
        let elems = buffer(&w, Buf::Elems);
        let kmat = buffer(&w, Buf::Kmat);
        let blocks_at = |base: u32| -> Vec<u32> {
            // 64 blocks of 3 vec4 (xyz used).
            (0..64 * 3)
                .flat_map(|v| {
                    let o = 4 * (3 * base as usize + v);
                    kmat[o..o + 3].to_vec()
                })
                .collect()
        };
        let bits = |set: &[Mat3]| -> Vec<u32> {
            set.iter()
                .flat_map(|m| [m.x_axis, m.y_axis, m.z_axis])
                .flat_map(|v| v.to_array().map(f32::to_bits))
                .collect()
        };
        let starts = element_starts(&mg, 3);
        let mut sets = 0;
        for b in 0..3 {
            let s = slice(&mg, b, &starts);
            // Level 0's records name the body's unit cube.
            let e0 = s.elems[0].start as usize;
            let unit = elems[12 * (layout.elems[0].start as usize + e0) + 8];
            assert_eq!(
                blocks_at(unit),
                bits(mg.unit_blocks[b].as_ref().unwrap()),
                "body {b}'s unit cube"
            );
            // Its operator after its blocks.
            let words = operator_words(mg.unit_operator[b].as_ref().unwrap());
            let o = 4 * 3 * (unit as usize + 64);
            let got: Vec<u32> = kmat[o..o + 24].to_vec();
            let want: Vec<u32> = words.iter().flatten().map(|v| v.to_bits()).collect();
            assert_eq!(got, want, "body {b}'s unit operator");
            sets += 1;
            for l in 1..mg.levels.len() {
                for e in s.elems[l].clone() {
                    let slot = layout.elems[l].start as usize + e as usize;
                    let base = elems[12 * slot + 8];
                    let own = &mg.levels[l].blocks[64 * e as usize..64 * (e as usize + 1)];
                    assert_eq!(blocks_at(base), bits(own), "level {l} element {e}");
                    sets += 1;
                }
            }
        }
        let distinct = |b: usize| {
            let s = slice(&mg, b, &starts);
            block_sets(&mg, b, &s)
                .map(fingerprint)
                .collect::<HashSet<_>>()
                .len() as u32
        };
        let (one, stiff) = (distinct(0), distinct(2));
        // The copy shares every set of the first body; the stiffer one shares none. Each
        // has one unit set (with its operator) and coarse sets of 64 blocks.
        assert_eq!(layout.kmat.used, 64 * (one + stiff) + 2 * (UNIT_SET - 64));
        assert!(
            layout.kmat.used < 64 * sets,
            "{} of {}",
            layout.kmat.used,
            64 * sets
        );
        assert_eq!(layout.kmat.used, layout.kmat.cap);
    }
}
