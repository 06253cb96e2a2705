//! An independent finite-element reference for static, small-strain, linear isotropic
//! elasticity (f64 throughout, SI units: metres, pascals, kilograms, newtons).
//!
//! It shares no code with the particle simulator: it exists to measure the simulator's
//! accuracy against a converged answer (cantilever deflection, Poisson ratio, volume
//! change, an organ under gravity).
//!
//! * [`TetMesh`] — linear tetrahedra: structured boxes (Kuhn/Freudenthal split), Gmsh
//!   MSH 1 and MSH 2 ASCII files, 1→8 red refinement, outward boundary triangles.
//! * [`Fem`] — 10-node (quadratic) tetrahedra built on a [`TetMesh`] (straight edges,
//!   mid-edge nodes shared), the stiffness ∫ Bᵀ D B dV integrated exactly with the 4-point
//!   degree-2 rule, Dirichlet constraints and consistent body loads.
//! * [`SparseMatrix`] and [`pcg`] — a generic CSR matrix and a block-Jacobi preconditioned
//!   conjugate gradient solver with Dirichlet degrees of freedom (DOF = 3·node + component).
//! * [`Solution`] — nodal displacements with exact volume integrals (mean displacement,
//!   relative volume change) and pointwise interpolation.
//!
//! References: Zienkiewicz, Taylor & Zhu, *The Finite Element Method: Its Basis and
//! Fundamentals* (7th ed.), quadratic tetrahedron shape functions and the tetrahedral
//! integration formula ∫ L₁ᵃ L₂ᵇ L₃ᶜ L₄ᵈ dV = a! b! c! d! 3! V / (a+b+c+d+3)!;
//! Hammer, Marlowe & Stroud (1956), 4-point degree-2 rule for the tetrahedron;
//! Bey, "Tetrahedral grid refinement", Computing 55 (1995), red refinement;
//! Saad, *Iterative Methods for Sparse Linear Systems* (2nd ed.), Algorithm 9.1
//! (preconditioned conjugate gradient).
//!
//! ```
//! use bevy_tissue::core::fem::{Fem, TetMesh};
//! use glam::DVec3;
//! // A 0.24 × 0.03 × 0.03 m cantilever clamped at x = 0, sagging under its own weight.
//! let mesh = TetMesh::box_mesh(DVec3::ZERO, DVec3::new(0.24, 0.03, 0.03), [8, 1, 1]).unwrap();
//! let mut fem = Fem::new(&mesh, 100e3, 0.3).unwrap();
//! fem.fix_nodes(|p| p.x <= 0.0, [true; 3], DVec3::ZERO);
//! fem.gravity(1000.0, DVec3::new(0.0, -0.2, 0.0));
//! let solution = fem.solve(1e-8).unwrap();
//! let tip = solution.mean_over(|p| p.x >= 0.24).unwrap();
//! assert!(tip.y < -0.009 && tip.y > -0.012);
//! ```

use glam::{DMat3, DVec3};
use std::collections::HashMap;
use std::fmt;
use std::sync::OnceLock;

// ---------------------------------------------------------------------------------------
// Errors
// ---------------------------------------------------------------------------------------

/// What went wrong while reading a mesh, building the finite-element model or solving it.
#[derive(Debug, Clone, PartialEq)]
pub enum FemError {
    /// A mesh file could not be read.
    Parse {
        /// 1-based line number of the problem (one past the last line at end of file).
        line: usize,
        /// What was expected or found.
        message: String,
    },
    /// The mesh has no nodes or no tetrahedra.
    EmptyMesh,
    /// A node coordinate is NaN or infinite.
    NonFiniteNode {
        /// Index of the first bad node.
        node: usize,
    },
    /// A tetrahedron refers to a node that does not exist.
    IndexOutOfRange {
        /// Index of the tetrahedron.
        tet: usize,
        /// The offending node index.
        index: u32,
        /// Number of nodes.
        nodes: usize,
    },
    /// A tetrahedron with (relatively) zero volume or repeated vertices.
    DegenerateTet {
        /// Index of the tetrahedron.
        tet: usize,
        /// Its signed volume (m³).
        volume: f64,
    },
    /// A tetrahedron with negative signed volume where positive orientation is required
    /// (see [`TetMesh::orient`]).
    InvertedTet {
        /// Index of the tetrahedron.
        tet: usize,
        /// Its signed volume (m³).
        volume: f64,
    },
    /// A parameter outside its valid range (also NaN or infinite inputs).
    BadParameter {
        /// Which parameter.
        name: &'static str,
        /// The value given (for vectors: the first bad entry).
        value: f64,
        /// The valid range, in words.
        expected: &'static str,
    },
    /// A vector or index does not fit the system size.
    DimensionMismatch {
        /// Which input.
        what: &'static str,
        /// The size required.
        expected: usize,
        /// The size given.
        found: usize,
    },
    /// No degree of freedom is constrained: the elastic problem has rigid-body modes.
    NoConstraints,
    /// A free degree of freedom has a zero, negative or non-finite diagonal entry: the
    /// matrix is not positive definite.
    NonPositiveDiagonal {
        /// The degree of freedom.
        dof: usize,
        /// Its diagonal entry.
        value: f64,
    },
    /// Conjugate gradient broke down (pᵀ A p ≤ 0 or non-finite): the system restricted
    /// to the free degrees of freedom is singular or indefinite.
    Singular {
        /// The iteration at which it broke down.
        iteration: usize,
    },
    /// Conjugate gradient reached its iteration limit.
    NotConverged {
        /// Iterations done.
        iterations: usize,
        /// Relative residual reached (see [`pcg`]).
        residual: f64,
    },
}

impl fmt::Display for FemError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            FemError::Parse { line, message } => write!(f, "line {line}: {message}"),
            FemError::EmptyMesh => write!(f, "mesh is empty: no nodes or no tetrahedra"),
            FemError::NonFiniteNode { node } => {
                write!(f, "node {node} has a NaN or infinite coordinate")
            }
            FemError::IndexOutOfRange { tet, index, nodes } => write!(
                f,
                "tetrahedron {tet} refers to node {index}, but there are only {nodes} nodes"
            ),
            FemError::DegenerateTet { tet, volume } => write!(
                f,
                "tetrahedron {tet} is degenerate (volume {volume:e} m³ or repeated vertices)"
            ),
            FemError::InvertedTet { tet, volume } => write!(
                f,
                "tetrahedron {tet} is inverted (signed volume {volume:e} m³)"
            ),
            FemError::BadParameter {
                name,
                value,
                expected,
            } => write!(f, "{name} = {value} is invalid: expected {expected}"),
            FemError::DimensionMismatch {
                what,
                expected,
                found,
            } => write!(f, "{what} has size {found}, expected {expected}"),
            FemError::NoConstraints => write!(
                f,
                "no degree of freedom is constrained: the problem has rigid-body modes"
            ),
            FemError::NonPositiveDiagonal { dof, value } => write!(
                f,
                "diagonal entry of free DOF {dof} is {value}: the matrix is not positive definite"
            ),
            FemError::Singular { iteration } => write!(
                f,
                "conjugate gradient broke down at iteration {iteration}: \
                 the constrained system is singular or indefinite"
            ),
            FemError::NotConverged {
                iterations,
                residual,
            } => write!(
                f,
                "conjugate gradient did not converge in {iterations} iterations \
                 (relative residual {residual:e})"
            ),
        }
    }
}

impl std::error::Error for FemError {}

// ---------------------------------------------------------------------------------------
// Linear tetrahedral mesh
// ---------------------------------------------------------------------------------------

/// A mesh of linear tetrahedra (m). After [`TetMesh::new`], [`TetMesh::orient`] or any
/// constructor of this module, every tetrahedron `[a, b, c, d]` is positively oriented:
/// (b − a) · ((c − a) × (d − a)) > 0.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct TetMesh {
    /// Node positions (m).
    pub nodes: Vec<DVec3>,
    /// Node indices of each tetrahedron.
    pub tets: Vec<[u32; 4]>,
}

/// Signed volume (m³) of the tetrahedron `a b c d`: (b − a) · ((c − a) × (d − a)) / 6.
fn signed_volume(a: DVec3, b: DVec3, c: DVec3, d: DVec3) -> f64 {
    (b - a).dot((c - a).cross(d - a)) / 6.0
}

/// Longest edge (m) of the tetrahedron `p`.
fn longest_edge(p: &[DVec3; 4]) -> f64 {
    let mut longest = 0.0_f64;
    for (i, a) in p.iter().enumerate() {
        for b in &p[i + 1..] {
            longest = longest.max(a.distance(*b));
        }
    }
    longest
}

/// Relative volume below which a tetrahedron counts as degenerate: |6V| ≤ this · ℓ³,
/// with ℓ its longest edge (a regular tetrahedron has 6V/ℓ³ = 1/√2).
const DEGENERATE_RELATIVE_VOLUME: f64 = 1e-12;

/// The six edges of a tetrahedron, as local vertex pairs; also the order of the
/// mid-edge nodes 4..10 of a quadratic tetrahedron.
const TET_EDGES: [[usize; 2]; 6] = [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]];

/// The faces of a positively oriented tetrahedron, outward (counter-clockwise seen from
/// outside), as local vertex triples: face k is opposite vertex k.
const TET_FACES: [[usize; 3]; 4] = [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]];

fn edge_key(a: u32, b: u32) -> (u32, u32) {
    if a < b { (a, b) } else { (b, a) }
}

/// Coordinate `i` of `n` grid intervals between `min` and `max` (exact at both ends).
fn grid_coord(min: f64, max: f64, i: usize, n: usize) -> f64 {
    if i == n {
        max
    } else {
        min + (max - min) * (i as f64 / n as f64)
    }
}

impl TetMesh {
    /// A mesh from nodes (m) and tetrahedra, checked (finite nodes, indices in range, no
    /// degenerate tetrahedron) and positively oriented (see [`TetMesh::orient`]).
    pub fn new(nodes: Vec<DVec3>, tets: Vec<[u32; 4]>) -> Result<TetMesh, FemError> {
        let mut mesh = TetMesh { nodes, tets };
        mesh.orient()?;
        Ok(mesh)
    }

    fn tet_points(&self, tet: &[u32; 4]) -> [DVec3; 4] {
        tet.map(|i| self.nodes[i as usize])
    }

    /// Checks the mesh and returns the signed volume of every tetrahedron (m³).
    fn checked_volumes(&self) -> Result<Vec<f64>, FemError> {
        if self.nodes.is_empty() || self.tets.is_empty() {
            return Err(FemError::EmptyMesh);
        }
        if let Some(node) = self.nodes.iter().position(|p| !p.is_finite()) {
            return Err(FemError::NonFiniteNode { node });
        }
        let mut volumes = Vec::with_capacity(self.tets.len());
        for (t, tet) in self.tets.iter().enumerate() {
            if let Some(&index) = tet.iter().find(|&&i| i as usize >= self.nodes.len()) {
                return Err(FemError::IndexOutOfRange {
                    tet: t,
                    index,
                    nodes: self.nodes.len(),
                });
            }
            let p = self.tet_points(tet);
            let volume = signed_volume(p[0], p[1], p[2], p[3]);
            let scale = longest_edge(&p);
            let repeated = (0..4).any(|i| (i + 1..4).any(|j| tet[i] == tet[j]));
            if repeated || 6.0 * volume.abs() <= DEGENERATE_RELATIVE_VOLUME * scale.powi(3) {
                return Err(FemError::DegenerateTet { tet: t, volume });
            }
            volumes.push(volume);
        }
        Ok(volumes)
    }

    /// Makes every tetrahedron positively oriented, swapping its last two vertices where
    /// the signed volume is negative; returns how many were swapped. Fails on an empty
    /// mesh, non-finite nodes, indices out of range or a degenerate tetrahedron (named).
    pub fn orient(&mut self) -> Result<usize, FemError> {
        let volumes = self.checked_volumes()?;
        let mut swapped = 0;
        for (tet, volume) in self.tets.iter_mut().zip(volumes) {
            if volume < 0.0 {
                tet.swap(2, 3);
                swapped += 1;
            }
        }
        Ok(swapped)
    }

    /// Checks that the mesh is usable as it is: non-empty, finite, indices in range and
    /// every tetrahedron positively oriented and non-degenerate.
    pub fn validate(&self) -> Result<(), FemError> {
        let volumes = self.checked_volumes()?;
        match volumes.iter().position(|&v| v < 0.0) {
            Some(tet) => Err(FemError::InvertedTet {
                tet,
                volume: volumes[tet],
            }),
            None => Ok(()),
        }
    }

    /// A structured mesh of the box `min`..`max` (m) with `cells` cubes (cuboids) along x,
    /// y and z, each split into 6 tetrahedra around its main diagonal from the `min`
    /// corner to the `max` corner (Kuhn/Freudenthal triangulation; every cell uses the same
    /// diagonal direction, so the mesh is conforming). Nodes are numbered x fastest, then
    /// y, then z, and lie exactly on the box faces.
    pub fn box_mesh(min: DVec3, max: DVec3, cells: [usize; 3]) -> Result<TetMesh, FemError> {
        if !min.is_finite() || !max.is_finite() {
            return Err(FemError::BadParameter {
                name: "box corner",
                value: f64::NAN,
                expected: "finite coordinates",
            });
        }
        for axis in 0..3 {
            if max[axis] <= min[axis] {
                return Err(FemError::BadParameter {
                    name: "box extent",
                    value: max[axis] - min[axis],
                    expected: "max > min on every axis",
                });
            }
            if cells[axis] == 0 {
                return Err(FemError::BadParameter {
                    name: "box cells",
                    value: 0.0,
                    expected: "at least one cell on every axis",
                });
            }
        }
        let [nx, ny, nz] = cells;
        let node_count = (nx + 1)
            .checked_mul(ny + 1)
            .and_then(|n| n.checked_mul(nz + 1))
            .filter(|&n| n <= u32::MAX as usize);
        let too_many = FemError::BadParameter {
            name: "box cells",
            value: (nx as f64 + 1.0) * (ny as f64 + 1.0) * (nz as f64 + 1.0),
            expected: "at most 2^32 - 1 nodes and tetrahedra",
        };
        let node_count = node_count.ok_or(too_many.clone())?;
        let tet_count = nx
            .checked_mul(ny)
            .and_then(|n| n.checked_mul(nz))
            .and_then(|n| n.checked_mul(6))
            .ok_or(too_many)?;
        let index = |i: usize, j: usize, k: usize| (i + (nx + 1) * (j + (ny + 1) * k)) as u32;
        let mut nodes = Vec::with_capacity(node_count);
        for k in 0..=nz {
            for j in 0..=ny {
                for i in 0..=nx {
                    nodes.push(DVec3::new(
                        grid_coord(min.x, max.x, i, nx),
                        grid_coord(min.y, max.y, j, ny),
                        grid_coord(min.z, max.z, k, nz),
                    ));
                }
            }
        }
        const PERMUTATIONS: [[usize; 3]; 6] = [
            [0, 1, 2],
            [0, 2, 1],
            [1, 0, 2],
            [1, 2, 0],
            [2, 0, 1],
            [2, 1, 0],
        ];
        let mut tets = Vec::with_capacity(tet_count);
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    for perm in PERMUTATIONS {
                        // Walk from the cell's min corner to its max corner, one axis at a time.
                        let mut corner = [i, j, k];
                        let mut tet = [index(i, j, k); 4];
                        for (step, &axis) in perm.iter().enumerate() {
                            corner[axis] += 1;
                            tet[step + 1] = index(corner[0], corner[1], corner[2]);
                        }
                        tets.push(tet);
                    }
                }
            }
        }
        TetMesh::new(nodes, tets)
    }

    /// Reads a Gmsh mesh: MSH version 1 (`$NOD`/`$ENDNOD`, `$ELM`/`$ENDELM`) or MSH 2 ASCII
    /// (`$MeshFormat`, `$Nodes`, `$Elements`). Only 4-node tetrahedra (element type 4) are
    /// kept; other elements (lines, triangles, ...) and unknown sections are skipped. Node
    /// numbers are arbitrary labels, mapped to indices in file order; coordinates are taken
    /// as metres. Tetrahedra are then oriented (see [`TetMesh::orient`]). Errors name the
    /// line (1-based).
    pub fn from_gmsh_v1(text: &str) -> Result<TetMesh, FemError> {
        gmsh::parse(text)
    }

    /// Red refinement (Bey 1995): every tetrahedron becomes 8 by its edge midpoints — 4
    /// corner tetrahedra and 4 around the shortest diagonal of the inner octahedron. The
    /// midpoint nodes are shared between neighbouring tetrahedra (appended after the
    /// existing nodes), so a conforming mesh stays conforming; the volume is unchanged and
    /// the children are positively oriented. Tetrahedra with node indices out of range
    /// (possible only by editing the fields directly) are left out.
    pub fn refine(&self) -> TetMesh {
        let mut nodes = self.nodes.clone();
        let mut midpoints: HashMap<(u32, u32), u32> = HashMap::new();
        let mut tets = Vec::with_capacity(self.tets.len() * 8);
        let in_range = |tet: &&[u32; 4]| tet.iter().all(|&i| (i as usize) < self.nodes.len());
        for tet in self.tets.iter().filter(in_range) {
            let mut m = [0u32; 6];
            for (slot, [a, b]) in m.iter_mut().zip(TET_EDGES) {
                let (a, b) = (tet[a], tet[b]);
                *slot = *midpoints.entry(edge_key(a, b)).or_insert_with(|| {
                    let p = (nodes[a as usize] + nodes[b as usize]) * 0.5;
                    nodes.push(p);
                    (nodes.len() - 1) as u32
                });
            }
            let [m01, m02, m03, m12, m13, m23] = m;
            let [v0, v1, v2, v3] = *tet;
            let mut children = [
                [v0, m01, m02, m03],
                [m01, v1, m12, m13],
                [m02, m12, v2, m23],
                [m03, m13, m23, v3],
                [0; 4],
                [0; 4],
                [0; 4],
                [0; 4],
            ];
            // Opposite vertex pairs of the inner octahedron: the three candidate diagonals.
            let pairs = [(m01, m23), (m02, m13), (m03, m12)];
            let length = |(a, b): (u32, u32)| nodes[a as usize].distance(nodes[b as usize]);
            let mut diagonal = 0;
            for k in 1..3 {
                if length(pairs[k]) < length(pairs[diagonal]) {
                    diagonal = k;
                }
            }
            let (a, b) = pairs[diagonal];
            let (p, q) = pairs[(diagonal + 1) % 3];
            let (r, s) = pairs[(diagonal + 2) % 3];
            // p, r, q, s is a cycle around the diagonal (opposite vertices are not adjacent).
            for (child, [c, d]) in children[4..]
                .iter_mut()
                .zip([[p, r], [r, q], [q, s], [s, p]])
            {
                *child = [a, b, c, d];
            }
            for child in &mut children {
                let p = child.map(|i| nodes[i as usize]);
                if signed_volume(p[0], p[1], p[2], p[3]) < 0.0 {
                    child.swap(2, 3);
                }
            }
            tets.extend_from_slice(&children);
        }
        TetMesh { nodes, tets }
    }

    /// The boundary: faces used by exactly one tetrahedron, each oriented outward
    /// (counter-clockwise seen from outside) for a positively oriented mesh, in the order
    /// the tetrahedra list them.
    pub fn boundary_triangles(&self) -> Vec<[u32; 3]> {
        let mut faces: Vec<([u32; 3], u32)> = Vec::new();
        let mut slots: HashMap<[u32; 3], usize> = HashMap::new();
        for tet in &self.tets {
            for face in TET_FACES {
                let face = face.map(|i| tet[i]);
                let mut key = face;
                key.sort_unstable();
                match slots.get(&key) {
                    Some(&slot) => faces[slot].1 += 1,
                    None => {
                        slots.insert(key, faces.len());
                        faces.push((face, 1));
                    }
                }
            }
        }
        faces
            .into_iter()
            .filter(|&(_, uses)| uses == 1)
            .map(|(face, _)| face)
            .collect()
    }

    /// Total volume (m³): the sum of the signed tetrahedron volumes, which is the volume
    /// for a positively oriented mesh. Tetrahedra with indices out of range count zero.
    pub fn volume(&self) -> f64 {
        self.tets
            .iter()
            .filter(|tet| tet.iter().all(|&i| (i as usize) < self.nodes.len()))
            .map(|tet| {
                let p = self.tet_points(tet);
                signed_volume(p[0], p[1], p[2], p[3])
            })
            .sum()
    }

    /// Axis-aligned bounds (m) of the nodes, `(min, max)`; `(0, 0)` for no nodes.
    pub fn bounds(&self) -> (DVec3, DVec3) {
        if self.nodes.is_empty() {
            return (DVec3::ZERO, DVec3::ZERO);
        }
        self.nodes.iter().fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(lo, hi), &p| (lo.min(p), hi.max(p)),
        )
    }

    /// A copy with every node mapped to `p · scale + translation` (m). A negative scale
    /// mirrors the mesh, so the tetrahedra are re-oriented (last two vertices swapped).
    pub fn transformed(&self, scale: f64, translation: DVec3) -> TetMesh {
        let nodes = self
            .nodes
            .iter()
            .map(|&p| p * scale + translation)
            .collect();
        let mut tets = self.tets.clone();
        if scale < 0.0 {
            for tet in &mut tets {
                tet.swap(2, 3);
            }
        }
        TetMesh { nodes, tets }
    }
}

/// Gmsh MSH 1 and MSH 2 ASCII reader.
mod gmsh {
    use super::{FemError, TetMesh};
    use glam::DVec3;
    use std::collections::HashMap;

    /// Non-blank lines with their 1-based numbers.
    struct Lines<'a> {
        inner: std::iter::Enumerate<std::str::Lines<'a>>,
        last: usize,
    }

    impl<'a> Lines<'a> {
        fn next(&mut self) -> Option<(usize, &'a str)> {
            for (i, line) in self.inner.by_ref() {
                self.last = i + 1;
                let line = line.trim();
                if !line.is_empty() {
                    return Some((i + 1, line));
                }
            }
            None
        }

        /// The next line, or an error naming the line after the last one.
        fn expect(&mut self, what: &str) -> Result<(usize, &'a str), FemError> {
            self.next().ok_or_else(|| FemError::Parse {
                line: self.last + 1,
                message: format!("unexpected end of file: expected {what}"),
            })
        }

        /// Reads the section end marker `end`.
        fn expect_end(&mut self, end: &str) -> Result<(), FemError> {
            let (line, text) = self.expect(end)?;
            if text.eq_ignore_ascii_case(end) {
                Ok(())
            } else {
                Err(error(line, format!("expected {end}, found '{text}'")))
            }
        }
    }

    fn error(line: usize, message: String) -> FemError {
        FemError::Parse { line, message }
    }

    fn parse_field<T: std::str::FromStr>(
        line: usize,
        token: Option<&str>,
        what: &str,
    ) -> Result<T, FemError> {
        let token = token.ok_or_else(|| error(line, format!("missing {what}")))?;
        token
            .parse()
            .map_err(|_| error(line, format!("invalid {what} '{token}'")))
    }

    /// A tetrahedron as node labels, with the line it was read from.
    struct RawTet {
        labels: [u64; 4],
        line: usize,
    }

    pub(super) fn parse(text: &str) -> Result<TetMesh, FemError> {
        let mut lines = Lines {
            inner: text.lines().enumerate(),
            last: 0,
        };
        let mut nodes: Vec<DVec3> = Vec::new();
        let mut labels: HashMap<u64, u32> = HashMap::new();
        let mut raw_tets: Vec<RawTet> = Vec::new();
        while let Some((line, header)) = lines.next() {
            match header {
                "$MeshFormat" => {
                    let (line, text) = lines.expect("the MSH version line")?;
                    let mut fields = text.split_whitespace();
                    let version: f64 = parse_field(line, fields.next(), "MSH version")?;
                    let file_type: u32 = parse_field(line, fields.next(), "MSH file type")?;
                    if !(2.0..3.0).contains(&version) {
                        return Err(error(
                            line,
                            format!("MSH version {version} is not supported (only 1 and 2)"),
                        ));
                    }
                    if file_type != 0 {
                        return Err(error(line, "binary MSH files are not supported".into()));
                    }
                    skip_section(&mut lines, "MeshFormat")?;
                }
                "$NOD" | "$Nodes" => {
                    let end = if header == "$NOD" {
                        "$ENDNOD"
                    } else {
                        "$EndNodes"
                    };
                    read_nodes(&mut lines, end, &mut nodes, &mut labels)?;
                }
                "$ELM" | "$Elements" => {
                    let version1 = header == "$ELM";
                    let end = if version1 { "$ENDELM" } else { "$EndElements" };
                    read_elements(&mut lines, end, version1, &mut raw_tets)?;
                }
                other if other.starts_with('$') && !other.contains(char::is_whitespace) => {
                    skip_section(&mut lines, &other[1..])?;
                }
                other => {
                    return Err(error(
                        line,
                        format!("expected a section header such as $NOD or $ELM, found '{other}'"),
                    ));
                }
            }
        }
        if nodes.is_empty() || raw_tets.is_empty() {
            return Err(FemError::EmptyMesh);
        }
        let mut tets = Vec::with_capacity(raw_tets.len());
        for raw in raw_tets {
            let mut tet = [0u32; 4];
            for (slot, label) in tet.iter_mut().zip(raw.labels) {
                *slot = *labels.get(&label).ok_or_else(|| {
                    error(
                        raw.line,
                        format!("tetrahedron refers to undefined node {label}"),
                    )
                })?;
            }
            tets.push(tet);
        }
        TetMesh::new(nodes, tets)
    }

    /// Skips an unknown section up to `$End<name>` (case-insensitive).
    fn skip_section(lines: &mut Lines<'_>, name: &str) -> Result<(), FemError> {
        let end = format!("$End{name}");
        loop {
            let (_, text) = lines.expect(&end)?;
            if text.eq_ignore_ascii_case(&end) {
                return Ok(());
            }
        }
    }

    fn read_count(lines: &mut Lines<'_>, what: &str) -> Result<usize, FemError> {
        let (line, text) = lines.expect(what)?;
        parse_field(line, Some(text), what)
    }

    fn read_nodes(
        lines: &mut Lines<'_>,
        end: &str,
        nodes: &mut Vec<DVec3>,
        labels: &mut HashMap<u64, u32>,
    ) -> Result<(), FemError> {
        let count = read_count(lines, "the number of nodes")?;
        nodes.reserve(count.min(1 << 20));
        for k in 0..count {
            let (line, text) = lines.expect(&format!("node {} of {count}", k + 1))?;
            let mut fields = text.split_whitespace();
            let label: u64 = parse_field(line, fields.next(), "node number")?;
            let mut p = DVec3::ZERO;
            for axis in 0..3 {
                p[axis] = parse_field(line, fields.next(), "node coordinate")?;
            }
            if !p.is_finite() {
                return Err(error(
                    line,
                    format!("node {label} has a non-finite coordinate"),
                ));
            }
            if nodes.len() >= u32::MAX as usize {
                return Err(error(line, "too many nodes".into()));
            }
            if labels.insert(label, nodes.len() as u32).is_some() {
                return Err(error(line, format!("node number {label} is defined twice")));
            }
            nodes.push(p);
        }
        lines.expect_end(end)
    }

    fn read_elements(
        lines: &mut Lines<'_>,
        end: &str,
        version1: bool,
        tets: &mut Vec<RawTet>,
    ) -> Result<(), FemError> {
        const TETRAHEDRON: u32 = 4;
        let count = read_count(lines, "the number of elements")?;
        for k in 0..count {
            let (line, text) = lines.expect(&format!("element {} of {count}", k + 1))?;
            let fields: Vec<&str> = text.split_whitespace().collect();
            let field =
                |i: usize, what: &str| parse_field::<u64>(line, fields.get(i).copied(), what);
            field(0, "element number")?;
            let kind = field(1, "element type")?;
            // MSH 1: number type physical elementary node-count nodes...
            // MSH 2: number type tag-count tags... nodes...
            let first_node = if version1 {
                let node_count = field(4, "number of element nodes")? as usize;
                if fields.len() != 5 + node_count {
                    return Err(error(
                        line,
                        format!(
                            "element lists {} nodes, its header says {node_count}",
                            fields.len().saturating_sub(5)
                        ),
                    ));
                }
                5
            } else {
                3 + field(2, "number of element tags")? as usize
            };
            if kind != u64::from(TETRAHEDRON) {
                continue;
            }
            if fields.len() != first_node + 4 {
                return Err(error(
                    line,
                    format!(
                        "a tetrahedron (type 4) needs 4 nodes, found {}",
                        fields.len().saturating_sub(first_node)
                    ),
                ));
            }
            let mut labels = [0u64; 4];
            for (i, label) in labels.iter_mut().enumerate() {
                *label = field(first_node + i, "node number")?;
            }
            tets.push(RawTet { labels, line });
        }
        lines.expect_end(end)
    }
}

// ---------------------------------------------------------------------------------------
// Sparse matrix and preconditioned conjugate gradient
// ---------------------------------------------------------------------------------------

/// A square sparse matrix in compressed sparse row (CSR) form: f64 values, u32 column
/// indices sorted and unique within each row.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct SparseMatrix {
    n: usize,
    row_ptr: Vec<usize>,
    cols: Vec<u32>,
    vals: Vec<f64>,
}

/// Worker threads for [`SparseMatrix::mul`] (queried once: the query reads cgroup files).
fn worker_threads() -> usize {
    static THREADS: OnceLock<usize> = OnceLock::new();
    *THREADS.get_or_init(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
}

/// Below this many stored entries a product runs on the calling thread only.
const PARALLEL_MIN_NNZ: usize = 200_000;

impl SparseMatrix {
    /// An n × n matrix from (row, column, value) triplets; duplicates are summed. Fails
    /// if the three slices differ in length, an index is ≥ n, n does not fit u32, or a
    /// value is not finite.
    pub fn from_triplets(
        n: usize,
        rows: &[u32],
        cols: &[u32],
        vals: &[f64],
    ) -> Result<SparseMatrix, FemError> {
        if n > u32::MAX as usize {
            return Err(FemError::DimensionMismatch {
                what: "matrix size",
                expected: u32::MAX as usize,
                found: n,
            });
        }
        for (what, len) in [
            ("triplet columns", cols.len()),
            ("triplet values", vals.len()),
        ] {
            if len != rows.len() {
                return Err(FemError::DimensionMismatch {
                    what,
                    expected: rows.len(),
                    found: len,
                });
            }
        }
        if let Some(&bad) = rows.iter().chain(cols).find(|&&i| i as usize >= n) {
            return Err(FemError::DimensionMismatch {
                what: "triplet index",
                expected: n,
                found: bad as usize,
            });
        }
        if let Some(&bad) = vals.iter().find(|v| !v.is_finite()) {
            return Err(FemError::BadParameter {
                name: "triplet value",
                value: bad,
                expected: "a finite number",
            });
        }
        // Counting sort by row, then sort and merge each row by column.
        let mut start = vec![0usize; n + 1];
        for &r in rows {
            start[r as usize + 1] += 1;
        }
        for i in 0..n {
            start[i + 1] += start[i];
        }
        let mut next = start.clone();
        let mut entries = vec![(0u32, 0.0f64); rows.len()];
        for ((&r, &c), &v) in rows.iter().zip(cols).zip(vals) {
            let slot = &mut next[r as usize];
            entries[*slot] = (c, v);
            *slot += 1;
        }
        let mut row_ptr = Vec::with_capacity(n + 1);
        let mut out_cols = Vec::with_capacity(entries.len());
        let mut out_vals = Vec::with_capacity(entries.len());
        row_ptr.push(0);
        for i in 0..n {
            let row = &mut entries[start[i]..start[i + 1]];
            row.sort_unstable_by_key(|&(c, _)| c);
            for &(c, v) in row.iter() {
                if out_cols.len() > row_ptr[i] && out_cols.last() == Some(&c) {
                    *out_vals.last_mut().expect("a value per column") += v;
                } else {
                    out_cols.push(c);
                    out_vals.push(v);
                }
            }
            row_ptr.push(out_cols.len());
        }
        Ok(SparseMatrix {
            n,
            row_ptr,
            cols: out_cols,
            vals: out_vals,
        })
    }

    /// Number of rows (= columns).
    pub fn n(&self) -> usize {
        self.n
    }

    /// Number of stored entries.
    pub fn nnz(&self) -> usize {
        self.vals.len()
    }

    /// The stored columns and values of row `i` (empty past the last row).
    pub fn row(&self, i: usize) -> (&[u32], &[f64]) {
        if i >= self.n {
            return (&[], &[]);
        }
        let range = self.row_ptr[i]..self.row_ptr[i + 1];
        (&self.cols[range.clone()], &self.vals[range])
    }

    /// Entry (i, j); zero where nothing is stored or out of range.
    pub fn get(&self, i: usize, j: usize) -> f64 {
        let (cols, vals) = self.row(i);
        u32::try_from(j)
            .ok()
            .and_then(|j| cols.binary_search(&j).ok())
            .map_or(0.0, |k| vals[k])
    }

    /// The diagonal entries.
    pub fn diagonal(&self) -> Vec<f64> {
        (0..self.n).map(|i| self.get(i, i)).collect()
    }

    /// y = A x, for rows `first..first + y.len()`.
    fn mul_rows(&self, first: usize, x: &[f64], y: &mut [f64]) {
        for (i, yi) in (first..).zip(y.iter_mut()) {
            let range = self.row_ptr[i]..self.row_ptr[i + 1];
            *yi = self.cols[range.clone()]
                .iter()
                .zip(&self.vals[range])
                .map(|(&c, &v)| v * x[c as usize])
                .sum();
        }
    }

    /// y = A x. Large matrices are split into row chunks of about equal stored entries,
    /// one per available core (scoped threads); the result does not depend on the split.
    ///
    /// # Panics
    /// If `x` or `y` does not have length n.
    pub fn mul(&self, x: &[f64], y: &mut [f64]) {
        assert_eq!(x.len(), self.n, "SparseMatrix::mul: x has the wrong length");
        assert_eq!(y.len(), self.n, "SparseMatrix::mul: y has the wrong length");
        let threads = worker_threads().min(self.n.max(1));
        if threads < 2 || self.nnz() < PARALLEL_MIN_NNZ {
            self.mul_rows(0, x, y);
            return;
        }
        let per_thread = self.nnz().div_ceil(threads);
        std::thread::scope(|scope| {
            let mut rest = y;
            let mut first = 0;
            for t in 1..=threads {
                let end = if t == threads {
                    self.n
                } else {
                    self.row_ptr
                        .partition_point(|&p| p < t * per_thread)
                        .clamp(first, self.n)
                };
                let (chunk, tail) = rest.split_at_mut(end - first);
                rest = tail;
                if t == threads {
                    self.mul_rows(first, x, chunk);
                } else {
                    let start = first;
                    scope.spawn(move || self.mul_rows(start, x, chunk));
                }
                first = end;
            }
        });
    }
}

/// A symmetric positive definite linear operator for [`pcg`], assembled or not. Degrees
/// of freedom are grouped by node: DOF = 3 · node + component.
pub trait SymOperator {
    /// Number of degrees of freedom n.
    fn dofs(&self) -> usize;

    /// y = A x, overwriting `y`; both have length n.
    fn apply(&self, x: &[f64], y: &mut [f64]);

    /// The 3 × 3 diagonal blocks of A, row-major: block k holds A[3k + r][3k + s] at
    /// index 3r + s, for k in 0..⌈n/3⌉ (entries past n are ignored). Used by the
    /// block-Jacobi preconditioner of [`pcg`].
    fn block_diagonal(&self) -> Vec<[f64; 9]>;
}

impl SymOperator for SparseMatrix {
    fn dofs(&self) -> usize {
        self.n
    }

    fn apply(&self, x: &[f64], y: &mut [f64]) {
        self.mul(x, y);
    }

    fn block_diagonal(&self) -> Vec<[f64; 9]> {
        (0..self.n.div_ceil(3))
            .map(|k| {
                let mut block = [0.0; 9];
                for (index, entry) in block.iter_mut().enumerate() {
                    *entry = self.get(3 * k + index / 3, 3 * k + index % 3);
                }
                block
            })
            .collect()
    }
}

/// Block-Jacobi preconditioner: the inverse of each 3 × 3 node block of the operator
/// (rows and columns of fixed DOFs replaced by the identity), or of its diagonal where a
/// block is not safely positive definite. Fixed DOFs map to zero.
struct BlockJacobi {
    /// One inverse per node block (DOFs 3k..3k+3, the last one possibly partial).
    blocks: Vec<DMat3>,
}

impl BlockJacobi {
    fn new<A: SymOperator + ?Sized>(a: &A, fixed: &[bool]) -> Result<BlockJacobi, FemError> {
        let n = a.dofs();
        let diagonal = a.block_diagonal();
        if diagonal.len() != n.div_ceil(3) {
            return Err(FemError::DimensionMismatch {
                what: "block diagonal",
                expected: n.div_ceil(3),
                found: diagonal.len(),
            });
        }
        let mut blocks = Vec::with_capacity(diagonal.len());
        for (k, entries) in diagonal.iter().enumerate() {
            // Fixed DOFs and the padding past n take no part.
            let held = [0, 1, 2].map(|i| fixed.get(3 * k + i).is_none_or(|&f| f));
            let mut m = DMat3::IDENTITY;
            for i in 0..3 {
                for j in 0..3 {
                    if !held[i] && !held[j] {
                        m.col_mut(j)[i] = entries[3 * i + j];
                    }
                }
            }
            // Sylvester's criterion with relative margins.
            let (a00, a11, a22) = (m.x_axis.x, m.y_axis.y, m.z_axis.z);
            let minor2 = a00 * a11 - m.y_axis.x * m.x_axis.y;
            let det = m.determinant();
            let positive = a00 > 0.0
                && a11 > 0.0
                && a22 > 0.0
                && minor2 > 1e-12 * a00 * a11
                && det > 1e-12 * a00 * a11 * a22
                && det.is_finite();
            let mut inverse = if positive {
                m.inverse()
            } else {
                // Scalar Jacobi for this block.
                let mut scaled = DVec3::ZERO;
                for i in (0..3).filter(|&i| !held[i]) {
                    let d = m.col(i)[i];
                    if !(d > 0.0 && d.is_finite()) {
                        return Err(FemError::NonPositiveDiagonal {
                            dof: 3 * k + i,
                            value: d,
                        });
                    }
                    scaled[i] = 1.0 / d;
                }
                DMat3::from_diagonal(scaled)
            };
            for i in (0..3).filter(|&i| held[i]) {
                for j in 0..3 {
                    inverse.col_mut(j)[i] = 0.0;
                    inverse.col_mut(i)[j] = 0.0;
                }
            }
            blocks.push(inverse);
        }
        Ok(BlockJacobi { blocks })
    }

    /// z = M⁻¹ r.
    fn apply(&self, r: &[f64], z: &mut [f64]) {
        for ((block, r), z) in self.blocks.iter().zip(r.chunks(3)).zip(z.chunks_mut(3)) {
            let mut v = DVec3::ZERO;
            for (i, r) in r.iter().enumerate() {
                v[i] = *r;
            }
            let w = (*block * v).to_array();
            z.copy_from_slice(&w[..z.len()]);
        }
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn zero_fixed(v: &mut [f64], fixed: &[bool]) {
    for (v, _) in v.iter_mut().zip(fixed).filter(|(_, f)| **f) {
        *v = 0.0;
    }
}

/// Solves A x = b for a symmetric positive definite `a` (a [`SparseMatrix`] or any
/// [`SymOperator`]) by the preconditioned conjugate gradient method (Saad, *Iterative
/// Methods for Sparse Linear Systems*, Algorithm 9.1) with a block-Jacobi preconditioner:
/// the inverted 3 × 3 diagonal block of each node (DOFs 3k, 3k+1, 3k+2), or scalar Jacobi
/// where a block is not safely positive definite.
///
/// DOFs with `fixed[i]` are Dirichlet: they keep the value `x[i]` has on entry, and their
/// equations are dropped (lifting: r = b − A x with the fixed entries of r and of every
/// search direction zeroed). The free entries of `x` are the initial guess and receive
/// the solution.
///
/// Converges when ‖r‖ ≤ `tol` · ‖b_f − A_fd x_d‖, the norm of the right-hand side of the
/// system reduced to the free DOFs (which is ‖b_free‖ when the prescribed values are
/// zero). Returns the number of iterations; calls `progress(iteration, relative residual)`
/// after each one. Errors: mismatched lengths, `tol` not positive, non-finite input, a
/// non-positive diagonal entry of a free DOF, breakdown (singular or indefinite system),
/// or `max_iter` reached.
pub fn pcg<A: SymOperator + ?Sized>(
    a: &A,
    b: &[f64],
    x: &mut [f64],
    fixed: &[bool],
    tol: f64,
    max_iter: usize,
    mut progress: Option<&mut dyn FnMut(usize, f64)>,
) -> Result<usize, FemError> {
    let n = a.dofs();
    for (what, len) in [("b", b.len()), ("x", x.len()), ("fixed", fixed.len())] {
        if len != n {
            return Err(FemError::DimensionMismatch {
                what,
                expected: n,
                found: len,
            });
        }
    }
    if !(tol > 0.0 && tol.is_finite()) {
        return Err(FemError::BadParameter {
            name: "tol",
            value: tol,
            expected: "a finite number > 0",
        });
    }
    for (name, v) in [("b", b), ("x", &*x)] {
        if let Some(&bad) = v.iter().find(|v| !v.is_finite()) {
            return Err(FemError::BadParameter {
                name,
                value: bad,
                expected: "finite entries",
            });
        }
    }
    let preconditioner = BlockJacobi::new(a, fixed)?;
    let mut r = vec![0.0; n];
    let mut q = vec![0.0; n];

    // The reduced right-hand side b_f − A_fd x_d sets the scale of the residual.
    let lifted: Vec<f64> = x
        .iter()
        .zip(fixed)
        .map(|(&x, &f)| if f { x } else { 0.0 })
        .collect();
    a.apply(&lifted, &mut q);
    for ((q, b), f) in q.iter_mut().zip(b).zip(fixed) {
        *q = if *f { 0.0 } else { b - *q };
    }
    let reference = dot(&q, &q).sqrt();
    if reference == 0.0 {
        // The reduced system is A_ff x_f = 0: its solution is zero.
        x.copy_from_slice(&lifted);
        return Ok(0);
    }

    a.apply(x, &mut q);
    for ((r, b), q) in r.iter_mut().zip(b).zip(&q) {
        *r = b - q;
    }
    zero_fixed(&mut r, fixed);
    let mut residual = dot(&r, &r).sqrt();
    if residual <= tol * reference {
        return Ok(0);
    }
    let mut z = vec![0.0; n];
    preconditioner.apply(&r, &mut z);
    let mut p = z.clone();
    let mut rz = dot(&r, &z);
    for iteration in 1..=max_iter {
        a.apply(&p, &mut q);
        zero_fixed(&mut q, fixed);
        let curvature = dot(&p, &q);
        if !(curvature > 0.0 && curvature.is_finite()) {
            return Err(FemError::Singular { iteration });
        }
        let alpha = rz / curvature;
        for ((x, r), (p, q)) in x.iter_mut().zip(&mut r).zip(p.iter().zip(&q)) {
            *x += alpha * p;
            *r -= alpha * q;
        }
        residual = dot(&r, &r).sqrt();
        let relative = residual / reference;
        if let Some(progress) = progress.as_mut() {
            progress(iteration, relative);
        }
        if !relative.is_finite() {
            return Err(FemError::Singular { iteration });
        }
        if residual <= tol * reference {
            return Ok(iteration);
        }
        preconditioner.apply(&r, &mut z);
        let rz_next = dot(&r, &z);
        let beta = rz_next / rz;
        rz = rz_next;
        for (p, z) in p.iter_mut().zip(&z) {
            *p = z + beta * *p;
        }
    }
    Err(FemError::NotConverged {
        iterations: max_iter,
        residual: residual / reference,
    })
}

// ---------------------------------------------------------------------------------------
// Quadratic tetrahedra
// ---------------------------------------------------------------------------------------

/// Barycentric coordinates of the 4-point degree-2 rule for the tetrahedron (Hammer,
/// Marlowe & Stroud 1956): a = (5 + 3√5)/20, b = (5 − √5)/20, each point weighted V/4.
const QUADRATURE_A: f64 = 0.585_410_196_624_968_5;
const QUADRATURE_B: f64 = 0.138_196_601_125_010_5;

fn quadrature_points() -> [[f64; 4]; 4] {
    let (a, b) = (QUADRATURE_A, QUADRATURE_B);
    [[a, b, b, b], [b, a, b, b], [b, b, a, b], [b, b, b, a]]
}

/// Gradients (1/m) of the barycentric coordinates L₀..L₃ of a tetrahedron, and its
/// signed volume (m³).
fn barycentric_gradients(p: &[DVec3; 4]) -> ([DVec3; 4], f64) {
    let jacobian = DMat3::from_cols(p[1] - p[0], p[2] - p[0], p[3] - p[0]);
    let volume = jacobian.determinant() / 6.0;
    // Rows of J⁻¹ are ∇L₁, ∇L₂, ∇L₃.
    let inverse_t = jacobian.inverse().transpose();
    let (g1, g2, g3) = (inverse_t.x_axis, inverse_t.y_axis, inverse_t.z_axis);
    ([-(g1 + g2 + g3), g1, g2, g3], volume)
}

/// Values of the 10 quadratic shape functions at barycentric coordinates `l`
/// (Zienkiewicz & Taylor, quadratic tetrahedron): vertices Lᵢ(2Lᵢ − 1), mid-edge nodes
/// 4 Lᵢ Lⱼ in the order of `TET_EDGES`.
fn shape_values(l: [f64; 4]) -> [f64; 10] {
    let mut n = [0.0; 10];
    for i in 0..4 {
        n[i] = l[i] * (2.0 * l[i] - 1.0);
    }
    for (k, [i, j]) in TET_EDGES.into_iter().enumerate() {
        n[4 + k] = 4.0 * l[i] * l[j];
    }
    n
}

/// Gradients (1/m) of the 10 quadratic shape functions at barycentric coordinates `l`:
/// vertices (4Lᵢ − 1)∇Lᵢ, mid-edge nodes 4(Lᵢ∇Lⱼ + Lⱼ∇Lᵢ).
fn shape_gradients(l: [f64; 4], grad_l: &[DVec3; 4]) -> [DVec3; 10] {
    let mut g = [DVec3::ZERO; 10];
    for i in 0..4 {
        g[i] = (4.0 * l[i] - 1.0) * grad_l[i];
    }
    for (k, [i, j]) in TET_EDGES.into_iter().enumerate() {
        g[4 + k] = 4.0 * (l[i] * grad_l[j] + l[j] * grad_l[i]);
    }
    g
}

/// u vᵀ.
fn outer(u: DVec3, v: DVec3) -> DMat3 {
    DMat3::from_cols(u * v.x, u * v.y, u * v.z)
}

/// Stiffness of a quadratic tetrahedron as 10 × 10 node blocks (N/m): K_ab = ∫ B_aᵀ D B_b dV
/// for isotropic D, which in index form is
/// (K_ab)ᵢₖ = ∫ λ ∂ᵢN_a ∂ₖN_b + μ ∂ₖN_a ∂ᵢN_b + μ δᵢₖ ∇N_a·∇N_b dV,
/// integrated exactly (the integrand is quadratic) by the 4-point degree-2 rule.
fn element_stiffness(grad_l: &[DVec3; 4], volume: f64, lambda: f64, mu: f64) -> [[DMat3; 10]; 10] {
    let mut k = [[DMat3::ZERO; 10]; 10];
    let weight = volume / 4.0;
    for l in quadrature_points() {
        let g = shape_gradients(l, grad_l);
        for (row, &ga) in k.iter_mut().zip(&g) {
            for (block, &gb) in row.iter_mut().zip(&g) {
                // Symmetric to rounding: K_ba is computed from the same products as K_abᵀ.
                *block += (outer(ga, gb) * lambda
                    + outer(gb, ga) * mu
                    + DMat3::from_diagonal(DVec3::splat(mu * ga.dot(gb))))
                    * weight;
            }
        }
    }
    k
}

/// Lamé parameters (Pa) from Young's modulus E (Pa) and Poisson's ratio ν:
/// λ = E ν / ((1 + ν)(1 − 2ν)), μ = E / (2(1 + ν)).
fn lame(youngs_modulus: f64, poisson_ratio: f64) -> (f64, f64) {
    let (e, nu) = (youngs_modulus, poisson_ratio);
    (
        e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)),
        e / (2.0 * (1.0 + nu)),
    )
}

/// A static linear-elastic finite-element model on 10-node (quadratic) tetrahedra: the
/// assembled stiffness, the load vector and the Dirichlet constraints.
///
/// Nodes are the mesh vertices (same indices as the [`TetMesh`]) followed by one node at
/// the midpoint of every edge. Mesh nodes used by no tetrahedron are held at zero
/// displacement.
#[derive(Debug, Clone)]
pub struct Fem {
    nodes: Vec<DVec3>,
    elements: Vec<[u32; 10]>,
    gradients: Vec<[DVec3; 4]>,
    volumes: Vec<f64>,
    stiffness: SparseMatrix,
    load: Vec<f64>,
    fixed: Vec<bool>,
    prescribed: Vec<f64>,
    unused: Vec<bool>,
    youngs_modulus: f64,
    poisson_ratio: f64,
}

impl Fem {
    /// Builds the quadratic elements on `mesh` (which must be positively oriented, see
    /// [`TetMesh::orient`]) and assembles the global stiffness for Young's modulus
    /// `youngs_modulus` (Pa, > 0) and Poisson's ratio `poisson_ratio` (in [0, 0.5)).
    /// No constraints, no load.
    pub fn new(mesh: &TetMesh, youngs_modulus: f64, poisson_ratio: f64) -> Result<Fem, FemError> {
        if !(youngs_modulus > 0.0 && youngs_modulus.is_finite()) {
            return Err(FemError::BadParameter {
                name: "youngs_modulus",
                value: youngs_modulus,
                expected: "a finite modulus > 0 Pa",
            });
        }
        if !(0.0..0.5).contains(&poisson_ratio) {
            return Err(FemError::BadParameter {
                name: "poisson_ratio",
                value: poisson_ratio,
                expected: "0 <= ν < 0.5",
            });
        }
        mesh.validate()?;
        let vertex_count = mesh.nodes.len();
        let mut nodes = mesh.nodes.clone();
        let mut edges: HashMap<(u32, u32), u32> = HashMap::new();
        let mut elements = Vec::with_capacity(mesh.tets.len());
        let mut gradients = Vec::with_capacity(mesh.tets.len());
        let mut volumes = Vec::with_capacity(mesh.tets.len());
        for tet in &mesh.tets {
            let mut element = [0u32; 10];
            element[..4].copy_from_slice(tet);
            for (slot, [a, b]) in element[4..].iter_mut().zip(TET_EDGES) {
                let (a, b) = (tet[a], tet[b]);
                *slot = *edges.entry(edge_key(a, b)).or_insert_with(|| {
                    nodes.push((nodes[a as usize] + nodes[b as usize]) * 0.5);
                    (nodes.len() - 1) as u32
                });
            }
            let (grad_l, volume) = barycentric_gradients(&mesh.tet_points(tet));
            elements.push(element);
            gradients.push(grad_l);
            volumes.push(volume);
        }
        let dofs = 3 * nodes.len();
        if dofs > u32::MAX as usize {
            return Err(FemError::BadParameter {
                name: "mesh size",
                value: dofs as f64,
                expected: "at most 2^32 - 1 degrees of freedom",
            });
        }
        let mut unused = vec![true; nodes.len()];
        for element in &elements {
            for &i in element {
                unused[i as usize] = false;
            }
        }
        debug_assert!(unused[vertex_count..].iter().all(|u| !u));

        let (lambda, mu) = lame(youngs_modulus, poisson_ratio);
        let mut assembler = BlockAssembler::new(nodes.len(), &elements);
        for ((element, grad_l), &volume) in elements.iter().zip(&gradients).zip(&volumes) {
            let k = element_stiffness(grad_l, volume, lambda, mu);
            for (a, row) in k.iter().enumerate() {
                for (b, block) in row.iter().enumerate() {
                    assembler.add(element[a], element[b], block);
                }
            }
        }
        Ok(Fem {
            stiffness: assembler.finish(),
            load: vec![0.0; dofs],
            fixed: vec![false; dofs],
            prescribed: vec![0.0; dofs],
            nodes,
            elements,
            gradients,
            volumes,
            unused,
            youngs_modulus,
            poisson_ratio,
        })
    }

    /// Rest positions (m) of all nodes: mesh vertices, then mid-edge nodes.
    pub fn nodes(&self) -> &[DVec3] {
        &self.nodes
    }

    /// Number of degrees of freedom (3 per node).
    pub fn dof_count(&self) -> usize {
        3 * self.nodes.len()
    }

    /// The assembled global stiffness (N/m), DOF = 3 · node + component.
    pub fn stiffness(&self) -> &SparseMatrix {
        &self.stiffness
    }

    /// Young's modulus (Pa) and Poisson's ratio the model was built with.
    pub fn material(&self) -> (f64, f64) {
        (self.youngs_modulus, self.poisson_ratio)
    }

    /// Total volume of the elements (m³).
    pub fn volume(&self) -> f64 {
        self.volumes.iter().sum()
    }

    /// Prescribes displacement `value` (m) on the selected `components` (x, y, z) of every
    /// node — vertex or mid-edge — whose rest position satisfies `pred`. Later calls
    /// override earlier ones on the same DOFs. Returns the number of nodes selected.
    /// A non-finite value is reported by [`Fem::solve`].
    pub fn fix_nodes(
        &mut self,
        pred: impl Fn(DVec3) -> bool,
        components: [bool; 3],
        value: DVec3,
    ) -> usize {
        let mut count = 0;
        for (node, &p) in self.nodes.iter().enumerate() {
            if !pred(p) {
                continue;
            }
            count += 1;
            for (axis, _) in components.iter().enumerate().filter(|(_, c)| **c) {
                self.fixed[3 * node + axis] = true;
                self.prescribed[3 * node + axis] = value[axis];
            }
        }
        count
    }

    /// Removes all Dirichlet constraints.
    pub fn clear_constraints(&mut self) {
        self.fixed.fill(false);
        self.prescribed.fill(0.0);
    }

    /// Adds the consistent nodal load of a uniform body force ρ g (density ρ in kg/m³,
    /// acceleration g in m/s²): Fₐ = ∫ Nₐ ρ g dV, which for a quadratic tetrahedron of
    /// volume V is −ρgV/20 at each vertex and +ρgV/5 at each mid-edge node (tetrahedral
    /// integration formula: ∫Lᵢ² dV = V/10, ∫Lᵢ dV = V/4, ∫LᵢLⱼ dV = V/20). The loads add
    /// up to ρ g V. A non-finite load is reported by [`Fem::solve`].
    pub fn gravity(&mut self, density: f64, g: DVec3) {
        for (element, &volume) in self.elements.iter().zip(&self.volumes) {
            let force = density * volume * g;
            for (a, &node) in element.iter().enumerate() {
                let share = if a < 4 { -force / 20.0 } else { force / 5.0 };
                for axis in 0..3 {
                    self.load[3 * node as usize + axis] += share[axis];
                }
            }
        }
    }

    /// Adds the point force `force` (N) to node `node`.
    pub fn add_load(&mut self, node: usize, force: DVec3) -> Result<(), FemError> {
        if node >= self.nodes.len() {
            return Err(FemError::DimensionMismatch {
                what: "load node",
                expected: self.nodes.len(),
                found: node,
            });
        }
        for axis in 0..3 {
            self.load[3 * node + axis] += force[axis];
        }
        Ok(())
    }

    /// Removes all loads.
    pub fn clear_loads(&mut self) {
        self.load.fill(0.0);
    }

    /// Sum of all nodal loads (N).
    pub fn total_load(&self) -> DVec3 {
        self.load
            .chunks_exact(3)
            .fold(DVec3::ZERO, |sum, f| sum + DVec3::new(f[0], f[1], f[2]))
    }

    /// Solves K u = f for the displacements with [`pcg`] to relative residual `tol`
    /// (at most 20 iterations per DOF, clamped to 100..=200 000).
    pub fn solve(&self, tol: f64) -> Result<Solution, FemError> {
        self.solve_inner(tol, None)
    }

    /// [`Fem::solve`], calling `progress(iteration, relative residual)` after every
    /// conjugate gradient iteration.
    pub fn solve_with_progress(
        &self,
        tol: f64,
        progress: &mut dyn FnMut(usize, f64),
    ) -> Result<Solution, FemError> {
        self.solve_inner(tol, Some(progress))
    }

    fn solve_inner(
        &self,
        tol: f64,
        progress: Option<&mut dyn FnMut(usize, f64)>,
    ) -> Result<Solution, FemError> {
        if !self.fixed.iter().any(|&f| f) {
            return Err(FemError::NoConstraints);
        }
        if let Some(&bad) = self.prescribed.iter().find(|v| !v.is_finite()) {
            return Err(FemError::BadParameter {
                name: "prescribed displacement",
                value: bad,
                expected: "finite values",
            });
        }
        if let Some(&bad) = self.load.iter().find(|v| !v.is_finite()) {
            return Err(FemError::BadParameter {
                name: "load",
                value: bad,
                expected: "finite values",
            });
        }
        let mut fixed = self.fixed.clone();
        let mut x = self.prescribed.clone();
        for (node, _) in self.unused.iter().enumerate().filter(|(_, u)| **u) {
            fixed[3 * node..3 * node + 3].fill(true);
            x[3 * node..3 * node + 3].fill(0.0);
        }
        let dofs = self.dof_count();
        let max_iter = (20 * dofs).clamp(100, 200_000);
        let iterations = pcg(
            &self.stiffness,
            &self.load,
            &mut x,
            &fixed,
            tol,
            max_iter,
            progress,
        )?;
        let displacements = x
            .chunks_exact(3)
            .map(|u| DVec3::new(u[0], u[1], u[2]))
            .collect();
        Ok(Solution::new(
            self.nodes.clone(),
            displacements,
            iterations,
            self.elements.clone(),
            self.gradients.clone(),
            self.volumes.clone(),
        ))
    }
}

/// Assembles 3 × 3 node blocks into a CSR matrix whose sparsity is the node adjacency of
/// the elements (every node couples with every node of every element it belongs to).
struct BlockAssembler {
    /// Node adjacency in CSR form: neighbours of node a are `adjacency[start[a]..start[a+1]]`,
    /// sorted.
    start: Vec<usize>,
    adjacency: Vec<u32>,
    matrix: SparseMatrix,
}

impl BlockAssembler {
    fn new(node_count: usize, elements: &[[u32; 10]]) -> BlockAssembler {
        let mut neighbours: Vec<Vec<u32>> = vec![Vec::new(); node_count];
        for element in elements {
            for &a in element {
                neighbours[a as usize].extend_from_slice(element);
            }
        }
        let mut start = Vec::with_capacity(node_count + 1);
        let mut adjacency = Vec::new();
        start.push(0);
        for list in &mut neighbours {
            list.sort_unstable();
            list.dedup();
            adjacency.extend_from_slice(list);
            start.push(adjacency.len());
            *list = Vec::new();
        }
        let n = 3 * node_count;
        let mut row_ptr = Vec::with_capacity(n + 1);
        let mut cols = Vec::with_capacity(9 * adjacency.len());
        row_ptr.push(0);
        for a in 0..node_count {
            for _ in 0..3 {
                for &b in &adjacency[start[a]..start[a + 1]] {
                    cols.extend_from_slice(&[3 * b, 3 * b + 1, 3 * b + 2]);
                }
                row_ptr.push(cols.len());
            }
        }
        let vals = vec![0.0; cols.len()];
        BlockAssembler {
            start,
            adjacency,
            matrix: SparseMatrix {
                n,
                row_ptr,
                cols,
                vals,
            },
        }
    }

    /// Adds `block` to the rows of node `a` and columns of node `b`.
    fn add(&mut self, a: u32, b: u32, block: &DMat3) {
        let a = a as usize;
        let neighbours = &self.adjacency[self.start[a]..self.start[a + 1]];
        let k = neighbours
            .binary_search(&b)
            .expect("element nodes are adjacent by construction");
        for i in 0..3 {
            let first = self.matrix.row_ptr[3 * a + i] + 3 * k;
            for (j, v) in self.matrix.vals[first..first + 3].iter_mut().enumerate() {
                *v += block.col(j)[i];
            }
        }
    }

    fn finish(self) -> SparseMatrix {
        self.matrix
    }
}

// ---------------------------------------------------------------------------------------
// Solution and queries
// ---------------------------------------------------------------------------------------

/// A uniform grid of buckets listing the elements whose bounding box overlaps each cell.
#[derive(Debug, Clone)]
struct ElementGrid {
    origin: DVec3,
    cell: DVec3,
    dims: [usize; 3],
    start: Vec<u32>,
    elements: Vec<u32>,
}

impl ElementGrid {
    fn new(nodes: &[DVec3], elements: &[[u32; 10]]) -> ElementGrid {
        let boxes: Vec<(DVec3, DVec3)> = elements
            .iter()
            .map(|e| {
                e[..4].iter().fold(
                    (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
                    |(lo, hi), &i| (lo.min(nodes[i as usize]), hi.max(nodes[i as usize])),
                )
            })
            .collect();
        let (lo, hi) = boxes.iter().fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(lo, hi), b| (lo.min(b.0), hi.max(b.1)),
        );
        let extent = (hi - lo).max(DVec3::splat(1e-300));
        // About one cell per element, cells as cubic as the extent allows.
        let target = (elements.len().max(1) as f64).min(4e6);
        let side = (extent.x * extent.y * extent.z / target).cbrt();
        let dims = [0, 1, 2].map(|axis| ((extent[axis] / side).ceil() as usize).clamp(1, 512));
        let cell = DVec3::new(
            extent.x / dims[0] as f64,
            extent.y / dims[1] as f64,
            extent.z / dims[2] as f64,
        );
        let mut grid = ElementGrid {
            origin: lo,
            cell,
            dims,
            start: Vec::new(),
            elements: Vec::new(),
        };
        let cells = dims[0] * dims[1] * dims[2];
        let mut counts = vec![0u32; cells + 1];
        for b in &boxes {
            grid.for_cells(b.0, b.1, |c| counts[c + 1] += 1);
        }
        for c in 0..cells {
            counts[c + 1] += counts[c];
        }
        let mut next = counts.clone();
        let mut list = vec![0u32; counts[cells] as usize];
        for (e, b) in boxes.iter().enumerate() {
            grid.for_cells(b.0, b.1, |c| {
                list[next[c] as usize] = e as u32;
                next[c] += 1;
            });
        }
        grid.start = counts;
        grid.elements = list;
        grid
    }

    fn cell_of(&self, p: DVec3) -> [usize; 3] {
        let q = (p - self.origin) / self.cell;
        [0, 1, 2].map(|axis| (q[axis].max(0.0) as usize).min(self.dims[axis] - 1))
    }

    fn for_cells(&self, lo: DVec3, hi: DVec3, mut f: impl FnMut(usize)) {
        let (a, b) = (self.cell_of(lo), self.cell_of(hi));
        for k in a[2]..=b[2] {
            for j in a[1]..=b[1] {
                for i in a[0]..=b[0] {
                    f(i + self.dims[0] * (j + self.dims[1] * k));
                }
            }
        }
    }

    /// Elements whose bounding box may contain `p` (none for points outside the grid by
    /// more than a relative 1e-9).
    fn candidates(&self, p: DVec3) -> &[u32] {
        let dims = DVec3::new(
            self.dims[0] as f64,
            self.dims[1] as f64,
            self.dims[2] as f64,
        );
        let (lo, hi) = (self.origin, self.origin + self.cell * dims);
        let slack = (hi - lo) * 1e-9;
        if !p.is_finite() || p.cmplt(lo - slack).any() || p.cmpgt(hi + slack).any() {
            return &[];
        }
        let [i, j, k] = self.cell_of(p);
        let c = i + self.dims[0] * (j + self.dims[1] * k);
        &self.elements[self.start[c] as usize..self.start[c + 1] as usize]
    }
}

/// Nodal displacements of a solved [`Fem`] model (m), with queries that interpolate them
/// by the quadratic shape functions.
#[derive(Debug, Clone)]
pub struct Solution {
    /// Rest positions (m) of all nodes of the 10-node mesh: vertices, then mid-edge nodes.
    pub nodes: Vec<DVec3>,
    /// Displacement (m) of each node.
    pub displacements: Vec<DVec3>,
    /// Conjugate gradient iterations the solve took.
    pub iterations: usize,
    elements: Vec<[u32; 10]>,
    gradients: Vec<[DVec3; 4]>,
    volumes: Vec<f64>,
    grid: ElementGrid,
}

/// Barycentric tolerance of [`Solution::displacement_at`] for points on element faces.
const INSIDE_TOLERANCE: f64 = 1e-9;

impl Solution {
    fn new(
        nodes: Vec<DVec3>,
        displacements: Vec<DVec3>,
        iterations: usize,
        elements: Vec<[u32; 10]>,
        gradients: Vec<[DVec3; 4]>,
        volumes: Vec<f64>,
    ) -> Solution {
        let grid = ElementGrid::new(&nodes, &elements);
        Solution {
            nodes,
            displacements,
            iterations,
            elements,
            gradients,
            volumes,
            grid,
        }
    }

    /// Displacement (m) of node `node`; `None` past the last node.
    pub fn displacement(&self, node: usize) -> Option<DVec3> {
        self.displacements.get(node).copied()
    }

    /// Total volume of the elements (m³).
    pub fn volume(&self) -> f64 {
        self.volumes.iter().sum()
    }

    /// Barycentric coordinates of `p` in element `e`.
    fn barycentric(&self, e: usize, p: DVec3) -> [f64; 4] {
        let g = &self.gradients[e];
        let d = p - self.nodes[self.elements[e][0] as usize];
        let (l1, l2, l3) = (g[1].dot(d), g[2].dot(d), g[3].dot(d));
        [1.0 - l1 - l2 - l3, l1, l2, l3]
    }

    /// Displacement (m) at rest position `p` (m), interpolated by the quadratic shape
    /// functions of the element containing `p`; `None` outside the mesh.
    pub fn displacement_at(&self, p: DVec3) -> Option<DVec3> {
        let e = self
            .grid
            .candidates(p)
            .iter()
            .map(|&e| e as usize)
            .find(|&e| {
                self.barycentric(e, p)
                    .iter()
                    .all(|&l| l >= -INSIDE_TOLERANCE)
            })?;
        let n = shape_values(self.barycentric(e, p));
        Some(
            self.elements[e]
                .iter()
                .zip(n)
                .map(|(&node, n)| n * self.displacements[node as usize])
                .sum(),
        )
    }

    /// Volume average of the displacement, ∫ u dV / V (m), exact for the quadratic
    /// interpolation: ∫ N_vertex dV = −V/20 and ∫ N_edge dV = V/5 per element.
    pub fn mean_displacement(&self) -> DVec3 {
        let total: DVec3 = self
            .elements
            .iter()
            .zip(&self.volumes)
            .map(|(element, &volume)| {
                let u = |a: usize| self.displacements[element[a] as usize];
                let vertices: DVec3 = (0..4).map(u).sum();
                let edges: DVec3 = (4..10).map(u).sum();
                volume * (edges / 5.0 - vertices / 20.0)
            })
            .sum();
        total / self.volume()
    }

    /// Plain average (m) of the displacements of the nodes (vertices and mid-edge nodes)
    /// whose rest position satisfies `pred`, e.g. the nodes of a face; `None` if no node
    /// does.
    pub fn mean_over(&self, pred: impl Fn(DVec3) -> bool) -> Option<DVec3> {
        let (sum, count) = self
            .nodes
            .iter()
            .zip(&self.displacements)
            .filter(|(p, _)| pred(**p))
            .fold((DVec3::ZERO, 0usize), |(sum, count), (_, &u)| {
                (sum + u, count + 1)
            });
        (count > 0).then(|| sum / count as f64)
    }

    /// Relative volume change in small strain, ∫ div u dV / V (dimensionless). Exact for
    /// the quadratic interpolation: ∫ ∇N_vertex dV = 0 and ∫ ∇N_ij dV = V (∇Lᵢ + ∇Lⱼ).
    pub fn volume_change(&self) -> f64 {
        let total: f64 = self
            .elements
            .iter()
            .zip(&self.gradients)
            .zip(&self.volumes)
            .map(|((element, g), &volume)| {
                TET_EDGES
                    .iter()
                    .zip(&element[4..])
                    .map(|(&[i, j], &node)| (g[i] + g[j]).dot(self.displacements[node as usize]))
                    .sum::<f64>()
                    * volume
            })
            .sum();
        total / self.volume()
    }

    /// Largest displacement magnitude over the nodes (m).
    pub fn max_displacement(&self) -> f64 {
        self.displacements
            .iter()
            .map(|u| u.length())
            .fold(0.0, f64::max)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Instant;

    /// Deterministic uniform numbers in [0, 1) (64-bit LCG, Knuth's MMIX constants).
    fn uniform(state: &mut u64) -> f64 {
        *state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (*state >> 11) as f64 / (1u64 << 53) as f64
    }

    fn relative(a: f64, b: f64) -> f64 {
        (a - b).abs() / b.abs()
    }

    /// Every directed edge is used once and its reverse once: closed and consistently
    /// oriented.
    fn assert_closed(triangles: &[[u32; 3]]) {
        let mut directed: HashMap<(u32, u32), usize> = HashMap::new();
        for t in triangles {
            for k in 0..3 {
                *directed.entry((t[k], t[(k + 1) % 3])).or_default() += 1;
            }
        }
        for (&(a, b), &uses) in &directed {
            assert_eq!(uses, 1, "edge {a}-{b} used {uses} times in one direction");
            assert_eq!(directed.get(&(b, a)), Some(&1), "edge {a}-{b} has no twin");
        }
    }

    /// Volume enclosed by a triangle surface (divergence theorem); positive if outward.
    fn enclosed_volume(nodes: &[DVec3], triangles: &[[u32; 3]]) -> f64 {
        triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| nodes[i as usize]);
                a.dot(b.cross(c)) / 6.0
            })
            .sum()
    }

    /// A box mesh with its interior nodes moved randomly (still valid), so that tests do
    /// not rely on a regular grid.
    fn distorted_box(cells: [usize; 3], amount: f64, seed: u64) -> TetMesh {
        let mut mesh = TetMesh::box_mesh(DVec3::ZERO, DVec3::ONE, cells).unwrap();
        let mut state = seed;
        let h = 1.0 / cells.iter().copied().max().unwrap() as f64;
        for p in &mut mesh.nodes {
            let interior = (0..3).all(|a| p[a] > 0.0 && p[a] < 1.0);
            if interior {
                let d = DVec3::new(
                    uniform(&mut state),
                    uniform(&mut state),
                    uniform(&mut state),
                );
                *p += (d - 0.5) * amount * h;
            }
        }
        mesh.validate().unwrap();
        mesh
    }

    fn mesh_path(name: &str) -> Option<String> {
        let path = format!("{}/../shared/meshes/{name}", env!("CARGO_MANIFEST_DIR"));
        if std::path::Path::new(&path).exists() {
            return Some(path);
        }
        if std::env::var("CI").is_ok_and(|v| v == "true") {
            panic!("{path} is missing (CI=true: test meshes are required)");
        }
        println!("skipped: {path} is missing");
        None
    }

    #[test]
    fn box_mesh_is_closed_and_oriented() {
        let size = DVec3::new(1.0, 2.0, 3.0);
        let mesh = TetMesh::box_mesh(DVec3::ZERO, size, [3, 2, 4]).unwrap();
        assert_eq!(mesh.nodes.len(), 4 * 3 * 5);
        assert_eq!(mesh.tets.len(), 6 * 3 * 2 * 4);
        mesh.validate().unwrap();
        assert!(relative(mesh.volume(), 6.0) < 1e-14);
        assert_eq!(mesh.bounds(), (DVec3::ZERO, size));
        let boundary = mesh.boundary_triangles();
        assert_eq!(boundary.len(), 2 * 2 * (3 * 2 + 2 * 4 + 3 * 4));
        assert_closed(&boundary);
        assert!(relative(enclosed_volume(&mesh.nodes, &boundary), 6.0) < 1e-14);
    }

    #[test]
    fn refine_preserves_volume_and_boundary() {
        let mesh = distorted_box([2, 3, 2], 0.3, 7);
        let fine = mesh.refine();
        fine.validate().unwrap();
        assert_eq!(fine.tets.len(), 8 * mesh.tets.len());
        assert!(relative(fine.volume(), mesh.volume()) < 1e-13);
        let (coarse_boundary, fine_boundary) =
            (mesh.boundary_triangles(), fine.boundary_triangles());
        assert_eq!(fine_boundary.len(), 4 * coarse_boundary.len());
        assert_closed(&fine_boundary);
        assert!(relative(enclosed_volume(&fine.nodes, &fine_boundary), mesh.volume()) < 1e-13);
        // Vertices + one node per edge.
        let edges: std::collections::HashSet<_> = mesh
            .tets
            .iter()
            .flat_map(|t| TET_EDGES.map(|[a, b]| edge_key(t[a], t[b])))
            .collect();
        assert_eq!(fine.nodes.len(), mesh.nodes.len() + edges.len());
        let twice = fine.refine();
        assert_eq!(twice.boundary_triangles().len(), 16 * coarse_boundary.len());
        assert!(relative(twice.volume(), mesh.volume()) < 1e-13);
    }

    #[test]
    fn transformed_scales_and_translates() {
        let mesh = TetMesh::box_mesh(DVec3::ZERO, DVec3::ONE, [1, 1, 1]).unwrap();
        let moved = mesh.transformed(2.0, DVec3::new(1.0, 0.0, -1.0));
        assert_eq!(
            moved.bounds(),
            (DVec3::new(1.0, 0.0, -1.0), DVec3::new(3.0, 2.0, 1.0))
        );
        assert!(relative(moved.volume(), 8.0) < 1e-14);
        let mirrored = mesh.transformed(-1.0, DVec3::ZERO);
        mirrored.validate().unwrap();
    }

    #[test]
    fn orientation_is_fixed_and_bad_tets_are_named() {
        let nodes = vec![
            DVec3::ZERO,
            DVec3::X,
            DVec3::Y,
            DVec3::Z,
            DVec3::new(1.0, 1.0, 0.0),
        ];
        let mesh = TetMesh::new(nodes.clone(), vec![[0, 1, 3, 2], [0, 1, 2, 3]]).unwrap();
        assert_eq!(mesh.tets[0], [0, 1, 2, 3]);
        assert!(relative(mesh.volume(), 1.0 / 3.0) < 1e-15);
        let flat = TetMesh::new(nodes.clone(), vec![[0, 1, 2, 3], [0, 1, 2, 4]]);
        assert!(matches!(flat, Err(FemError::DegenerateTet { tet: 1, .. })));
        let repeated = TetMesh::new(nodes.clone(), vec![[0, 1, 1, 3]]);
        assert!(matches!(
            repeated,
            Err(FemError::DegenerateTet { tet: 0, .. })
        ));
        let outside = TetMesh::new(nodes.clone(), vec![[0, 1, 2, 3], [0, 1, 2, 9]]);
        assert!(matches!(
            outside,
            Err(FemError::IndexOutOfRange {
                tet: 1,
                index: 9,
                ..
            })
        ));
        let inverted = TetMesh {
            nodes: nodes.clone(),
            tets: vec![[0, 1, 2, 3], [0, 1, 3, 2]],
        };
        assert!(matches!(
            Fem::new(&inverted, 1e3, 0.3),
            Err(FemError::InvertedTet { tet: 1, .. })
        ));
        let mut bad = nodes;
        bad[2].y = f64::NAN;
        assert_eq!(
            TetMesh::new(bad, vec![[0, 1, 2, 3]]),
            Err(FemError::NonFiniteNode { node: 2 })
        );
        assert_eq!(TetMesh::new(vec![], vec![]), Err(FemError::EmptyMesh));
    }

    #[test]
    fn bad_parameters_are_errors() {
        let mesh = TetMesh::box_mesh(DVec3::ZERO, DVec3::ONE, [1, 1, 1]).unwrap();
        for (e, nu) in [
            (0.0, 0.3),
            (-1.0, 0.3),
            (f64::NAN, 0.3),
            (f64::INFINITY, 0.3),
            (1e3, 0.5),
            (1e3, -0.1),
            (1e3, f64::NAN),
        ] {
            assert!(
                matches!(Fem::new(&mesh, e, nu), Err(FemError::BadParameter { .. })),
                "E = {e}, ν = {nu}"
            );
        }
        assert!(TetMesh::box_mesh(DVec3::ZERO, DVec3::ONE, [1, 0, 1]).is_err());
        assert!(TetMesh::box_mesh(DVec3::ONE, DVec3::ZERO, [1, 1, 1]).is_err());
        assert!(TetMesh::box_mesh(DVec3::ZERO, DVec3::splat(f64::NAN), [1, 1, 1]).is_err());

        let mut fem = Fem::new(&mesh, 1e3, 0.3).unwrap();
        fem.gravity(1000.0, DVec3::NEG_Y);
        assert!(matches!(fem.solve(1e-8), Err(FemError::NoConstraints)));
        fem.fix_nodes(|p| p.y == 0.0, [true; 3], DVec3::ZERO);
        assert!(matches!(
            fem.solve(0.0),
            Err(FemError::BadParameter { name: "tol", .. })
        ));
        assert!(fem.add_load(fem.nodes().len(), DVec3::X).is_err());
        fem.gravity(f64::NAN, DVec3::NEG_Y);
        assert!(matches!(
            fem.solve(1e-8),
            Err(FemError::BadParameter { name: "load", .. })
        ));
        fem.clear_loads();
        fem.fix_nodes(|p| p.y == 1.0, [true; 3], DVec3::splat(f64::INFINITY));
        assert!(fem.solve(1e-8).is_err());
        fem.clear_constraints();
        assert!(matches!(fem.solve(1e-8), Err(FemError::NoConstraints)));
    }

    const GMSH_V1: &str = "$NOD
5
10 0 0 0
20 1 0 0
30 0 1 0
40 0 0 1
50 1 1 1
$ENDNOD
$ELM
4
1 1 0 0 2 10 20
2 2 0 0 3 10 20 30
3 4 1 1 4 10 20 30 40
4 4 1 1 4 20 40 30 50
$ENDELM
";

    #[test]
    fn gmsh_v1_inline() {
        let mesh = TetMesh::from_gmsh_v1(GMSH_V1).unwrap();
        assert_eq!(mesh.nodes.len(), 5);
        assert_eq!(mesh.nodes[4], DVec3::ONE);
        // The second tetrahedron was listed inverted and is re-oriented.
        assert_eq!(mesh.tets, vec![[0, 1, 2, 3], [1, 3, 4, 2]]);
        mesh.validate().unwrap();
        assert!(relative(mesh.volume(), 0.5) < 1e-15);
    }

    #[test]
    fn gmsh_errors_name_the_line() {
        let truncated: String = GMSH_V1.lines().take(11).map(|l| format!("{l}\n")).collect();
        let error = TetMesh::from_gmsh_v1(&truncated).unwrap_err();
        assert!(matches!(error, FemError::Parse { line: 12, .. }), "{error}");
        assert!(
            error
                .to_string()
                .starts_with("line 12: unexpected end of file"),
            "{error}"
        );

        let bad = GMSH_V1.replace("40 0 0 1", "40 0 zero 1");
        let error = TetMesh::from_gmsh_v1(&bad).unwrap_err();
        assert!(matches!(error, FemError::Parse { line: 6, .. }), "{error}");

        let undefined = GMSH_V1.replace("20 40 30 50", "20 40 30 99");
        let error = TetMesh::from_gmsh_v1(&undefined).unwrap_err();
        assert!(matches!(error, FemError::Parse { line: 14, .. }), "{error}");
        assert!(error.to_string().contains("99"), "{error}");

        let unterminated = GMSH_V1.replace("$ENDNOD", "$ELM");
        assert!(matches!(
            TetMesh::from_gmsh_v1(&unterminated),
            Err(FemError::Parse { line: 8, .. })
        ));
        let duplicate = GMSH_V1.replace("50 1 1 1", "40 1 1 1");
        assert!(matches!(
            TetMesh::from_gmsh_v1(&duplicate),
            Err(FemError::Parse { line: 7, .. })
        ));
        let flat = GMSH_V1.replace("50 1 1 1", "50 0.5 0.5 0");
        assert!(matches!(
            TetMesh::from_gmsh_v1(&flat),
            Err(FemError::DegenerateTet { tet: 1, .. })
        ));
        assert_eq!(TetMesh::from_gmsh_v1(""), Err(FemError::EmptyMesh));
        assert!(matches!(
            TetMesh::from_gmsh_v1("hello"),
            Err(FemError::Parse { line: 1, .. })
        ));
    }

    #[test]
    fn gmsh_v2_inline() {
        let text = "$MeshFormat
2.2 0 8
$EndMeshFormat
$PhysicalNames
1
3 1 \"body\"
$EndPhysicalNames
$Nodes
4
1 0 0 0
2 1 0 0
3 0 1 0
4 0 0 1
$EndNodes
$Elements
2
1 2 2 0 1 1 2 3
2 4 2 1 1 1 3 2 4
$EndElements
";
        let mesh = TetMesh::from_gmsh_v1(text).unwrap();
        assert_eq!(mesh.nodes.len(), 4);
        assert_eq!(mesh.tets, vec![[0, 2, 3, 1]]);
        assert!(relative(mesh.volume(), 1.0 / 6.0) < 1e-15);
        let version4 = text.replace("2.2 0 8", "4.1 0 8");
        assert!(matches!(
            TetMesh::from_gmsh_v1(&version4),
            Err(FemError::Parse { line: 2, .. })
        ));
    }

    #[test]
    fn liver2_msh() {
        let Some(path) = mesh_path("liver2.msh") else {
            return;
        };
        let text = std::fs::read_to_string(&path).unwrap();
        let mesh = TetMesh::from_gmsh_v1(&text).unwrap();
        assert_eq!(mesh.nodes.len(), 507);
        assert_eq!(mesh.tets.len(), 1493);
        mesh.validate().unwrap();
        let volume = mesh.volume();
        assert!(volume > 0.0);
        let boundary = mesh.boundary_triangles();
        assert_closed(&boundary);
        assert!(relative(enclosed_volume(&mesh.nodes, &boundary), volume) < 1e-12);

        let fine = mesh.refine();
        fine.validate().unwrap();
        assert!(relative(fine.volume(), volume) < 1e-12);
        assert_eq!(fine.boundary_triangles().len(), 4 * boundary.len());

        // Scaled to about 0.2 m across and hanging from its top 10 % under gravity.
        let (lo, hi) = mesh.bounds();
        let scale = 0.2 / (hi - lo).max_element();
        let organ = mesh.transformed(scale, DVec3::ZERO);
        let (lo, hi) = organ.bounds();
        let top = hi.y - 0.1 * (hi.y - lo.y);
        let mut fem = Fem::new(&organ, 20e3, 0.45).unwrap();
        assert!(fem.fix_nodes(|p| p.y >= top, [true; 3], DVec3::ZERO) > 0);
        fem.gravity(1060.0, DVec3::new(0.0, -9.81, 0.0));
        let solution = fem.solve(1e-8).unwrap();
        let mean = solution.mean_displacement();
        println!(
            "liver2: {:.4e} m³ scaled, {} DOFs, {} iterations, mean u_y {:.4e} m, max |u| {:.4e} m",
            organ.volume(),
            fem.dof_count(),
            solution.iterations,
            mean.y,
            solution.max_displacement()
        );
        assert!(mean.y < 0.0 && solution.max_displacement() < 0.25 * (hi - lo).max_element());
    }

    /// Dense Gaussian elimination with partial pivoting (test reference).
    fn dense_solve(mut a: Vec<Vec<f64>>, mut b: Vec<f64>) -> Vec<f64> {
        let n = b.len();
        for col in 0..n {
            let pivot = (col..n)
                .max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))
                .unwrap();
            a.swap(col, pivot);
            b.swap(col, pivot);
            let pivot_row = a[col].clone();
            for row in col + 1..n {
                let factor = a[row][col] / pivot_row[col];
                for (x, p) in a[row][col..].iter_mut().zip(&pivot_row[col..]) {
                    *x -= factor * p;
                }
                b[row] -= factor * b[col];
            }
        }
        let mut x = vec![0.0; n];
        for row in (0..n).rev() {
            let tail: f64 = (row + 1..n).map(|k| a[row][k] * x[k]).sum();
            x[row] = (b[row] - tail) / a[row][row];
        }
        x
    }

    /// A random dense SPD matrix (Mᵀ M + I) and its triplets, each entry split in two
    /// duplicates.
    fn random_spd(n: usize, seed: u64) -> (Vec<Vec<f64>>, SparseMatrix) {
        let mut state = seed;
        let m: Vec<Vec<f64>> = (0..n)
            .map(|_| (0..n).map(|_| uniform(&mut state) - 0.5).collect())
            .collect();
        let mut a = vec![vec![0.0; n]; n];
        let (mut rows, mut cols, mut vals) = (vec![], vec![], vec![]);
        for i in 0..n {
            for j in 0..n {
                a[i][j] = (0..n).map(|k| m[k][i] * m[k][j]).sum::<f64>() + f64::from(i == j);
                let part = uniform(&mut state);
                for v in [part * a[i][j], (1.0 - part) * a[i][j]] {
                    rows.push(i as u32);
                    cols.push(j as u32);
                    vals.push(v);
                }
            }
        }
        (
            a,
            SparseMatrix::from_triplets(n, &rows, &cols, &vals).unwrap(),
        )
    }

    #[test]
    fn sparse_matrix_basics() {
        let a = SparseMatrix::from_triplets(
            3,
            &[0, 2, 0, 1, 2, 0],
            &[0, 2, 2, 1, 2, 0],
            &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
        )
        .unwrap();
        assert_eq!(a.n(), 3);
        assert_eq!(a.nnz(), 4);
        assert_eq!(a.diagonal(), vec![7.0, 4.0, 7.0]);
        assert_eq!(a.get(0, 2), 3.0);
        assert_eq!(a.get(2, 0), 0.0);
        assert_eq!(a.row(0), (&[0u32, 2][..], &[7.0, 3.0][..]));
        let mut y = vec![0.0; 3];
        a.mul(&[1.0, 2.0, 3.0], &mut y);
        assert_eq!(y, vec![16.0, 8.0, 21.0]);
        assert!(SparseMatrix::from_triplets(2, &[0, 2], &[0, 0], &[1.0, 1.0]).is_err());
        assert!(SparseMatrix::from_triplets(2, &[0], &[0, 1], &[1.0]).is_err());
        assert!(SparseMatrix::from_triplets(2, &[0], &[0], &[f64::NAN]).is_err());
    }

    #[test]
    fn parallel_product_matches_serial() {
        let n = 60_000;
        let mut state = 3;
        let (mut rows, mut cols, mut vals) = (vec![], vec![], vec![]);
        for i in 0..n {
            for _ in 0..5 {
                rows.push(i as u32);
                cols.push((uniform(&mut state) * n as f64) as u32);
                vals.push(uniform(&mut state) - 0.5);
            }
        }
        let a = SparseMatrix::from_triplets(n, &rows, &cols, &vals).unwrap();
        assert!(a.nnz() >= PARALLEL_MIN_NNZ);
        let x: Vec<f64> = (0..n).map(|_| uniform(&mut state)).collect();
        let (mut parallel, mut serial) = (vec![0.0; n], vec![0.0; n]);
        a.mul(&x, &mut parallel);
        a.mul_rows(0, &x, &mut serial);
        assert_eq!(parallel, serial);
    }

    #[test]
    fn pcg_matches_dense_solve() {
        let n = 31; // not a multiple of 3: a scalar tail
        let (dense, a) = random_spd(n, 11);
        let mut state = 5;
        let b: Vec<f64> = (0..n).map(|_| uniform(&mut state) - 0.5).collect();
        let exact = dense_solve(dense.clone(), b.clone());
        let mut x = vec![0.0; n];
        let mut calls = 0;
        let mut progress = |_: usize, _: f64| calls += 1;
        let iterations = pcg(
            &a,
            &b,
            &mut x,
            &vec![false; n],
            1e-13,
            1000,
            Some(&mut progress),
        )
        .unwrap();
        assert_eq!(calls, iterations);
        let error = x
            .iter()
            .zip(&exact)
            .map(|(x, e)| (x - e).abs())
            .fold(0.0, f64::max);
        let scale = exact.iter().map(|e| e.abs()).fold(0.0, f64::max);
        assert!(error < 1e-9 * scale, "error {error:e}, scale {scale:e}");

        // Dirichlet DOFs keep their value; the rest solve the reduced system.
        let fixed: Vec<bool> = (0..n).map(|i| i % 4 == 1).collect();
        let mut x: Vec<f64> = (0..n)
            .map(|i| if fixed[i] { i as f64 * 0.1 } else { 0.0 })
            .collect();
        let free: Vec<usize> = (0..n).filter(|&i| !fixed[i]).collect();
        let reduced: Vec<Vec<f64>> = free
            .iter()
            .map(|&i| free.iter().map(|&j| dense[i][j]).collect())
            .collect();
        let rhs: Vec<f64> = free
            .iter()
            .map(|&i| {
                b[i] - (0..n)
                    .filter(|&j| fixed[j])
                    .map(|j| dense[i][j] * x[j])
                    .sum::<f64>()
            })
            .collect();
        let exact = dense_solve(reduced, rhs);
        let before = x.clone();
        pcg(&a, &b, &mut x, &fixed, 1e-13, 1000, None).unwrap();
        for (i, _) in fixed.iter().enumerate().filter(|(_, f)| **f) {
            assert_eq!(x[i], before[i]);
        }
        for (&i, e) in free.iter().zip(&exact) {
            assert!(
                (x[i] - e).abs() < 1e-9 * scale.max(1.0),
                "DOF {i}: {} vs {e}",
                x[i]
            );
        }
    }

    /// A matrix-free operator: the wrapped matrix applied through the trait only.
    struct MatrixFree(SparseMatrix);

    impl SymOperator for MatrixFree {
        fn dofs(&self) -> usize {
            self.0.n()
        }

        fn apply(&self, x: &[f64], y: &mut [f64]) {
            for (i, y) in y.iter_mut().enumerate() {
                let (cols, vals) = self.0.row(i);
                *y = cols.iter().zip(vals).map(|(&c, v)| v * x[c as usize]).sum();
            }
        }

        fn block_diagonal(&self) -> Vec<[f64; 9]> {
            self.0.block_diagonal()
        }
    }

    #[test]
    fn pcg_accepts_any_operator() {
        let n = 30;
        let (_, a) = random_spd(n, 4);
        let b: Vec<f64> = (0..n).map(|i| (i as f64).sin()).collect();
        let fixed: Vec<bool> = (0..n).map(|i| i < 3).collect();
        let (mut x, mut y) = (vec![0.5; n], vec![0.5; n]);
        let assembled = pcg(&a, &b, &mut x, &fixed, 1e-12, 1000, None).unwrap();
        let free = MatrixFree(a);
        let matrix_free = pcg(&free, &b, &mut y, &fixed, 1e-12, 1000, None).unwrap();
        assert_eq!(assembled, matrix_free);
        assert!(x.iter().zip(&y).all(|(x, y)| (x - y).abs() < 1e-12));

        struct Short;
        impl SymOperator for Short {
            fn dofs(&self) -> usize {
                6
            }
            fn apply(&self, x: &[f64], y: &mut [f64]) {
                y.copy_from_slice(x);
            }
            fn block_diagonal(&self) -> Vec<[f64; 9]> {
                vec![[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]]
            }
        }
        let result = pcg(
            &Short,
            &[1.0; 6],
            &mut [0.0; 6],
            &[false; 6],
            1e-9,
            10,
            None,
        );
        assert!(matches!(
            result,
            Err(FemError::DimensionMismatch {
                what: "block diagonal",
                ..
            })
        ));
    }

    #[test]
    fn pcg_reports_singular_systems() {
        // 1-D Neumann Laplacian (constant null space) with an inconsistent right-hand side.
        let n = 30;
        let (mut rows, mut cols, mut vals) = (vec![], vec![], vec![]);
        for i in 0..n - 1 {
            let (i, j) = (i as u32, i as u32 + 1);
            rows.extend([i, j, i, j]);
            cols.extend([i, j, j, i]);
            vals.extend([1.0, 1.0, -1.0, -1.0]);
        }
        let a = SparseMatrix::from_triplets(n, &rows, &cols, &vals).unwrap();
        let mut b = vec![0.0; n];
        b[0] = 1.0;
        let result = pcg(
            &a,
            &b,
            &mut vec![0.0; n],
            &vec![false; n],
            1e-10,
            10 * n,
            None,
        );
        assert!(
            matches!(
                result,
                Err(FemError::Singular { .. } | FemError::NotConverged { .. })
            ),
            "{result:?}"
        );
        // A zero row.
        let zero = SparseMatrix::from_triplets(3, &[0, 1], &[0, 1], &[1.0, 1.0]).unwrap();
        let result = pcg(
            &zero,
            &[1.0; 3],
            &mut [0.0; 3],
            &[false; 3],
            1e-10,
            100,
            None,
        );
        assert!(
            matches!(result, Err(FemError::NonPositiveDiagonal { dof: 2, .. })),
            "{result:?}"
        );
        // ...which is fine once that DOF is fixed.
        let mut x = [0.0, 0.0, 5.0];
        assert_eq!(
            pcg(
                &zero,
                &[1.0; 3],
                &mut x,
                &[false, false, true],
                1e-12,
                100,
                None
            ),
            Ok(1)
        );
        assert_eq!(x, [1.0, 1.0, 5.0]);
        let result = pcg(
            &zero,
            &[1.0; 2],
            &mut [0.0; 3],
            &[false; 3],
            1e-10,
            100,
            None,
        );
        assert!(matches!(
            result,
            Err(FemError::DimensionMismatch { what: "b", .. })
        ));
    }

    #[test]
    fn quadratic_shape_functions_integrate_to_the_consistent_load() {
        // The 4-point rule is exact for the (quadratic) shape functions.
        let p = [
            DVec3::ZERO,
            DVec3::new(2.0, 0.1, 0.0),
            DVec3::new(0.3, 1.0, 0.2),
            DVec3::new(0.1, 0.4, 1.5),
        ];
        let (grad_l, volume) = barycentric_gradients(&p);
        let mut integral = [0.0; 10];
        let mut gradient_integral = [DVec3::ZERO; 10];
        for l in quadrature_points() {
            for (a, (n, g)) in shape_values(l)
                .iter()
                .zip(shape_gradients(l, &grad_l))
                .enumerate()
            {
                integral[a] += n * volume / 4.0;
                gradient_integral[a] += g * volume / 4.0;
            }
            assert!(relative(shape_values(l).iter().sum(), 1.0) < 1e-15);
        }
        for (a, value) in integral.iter().enumerate() {
            let expected = if a < 4 { -volume / 20.0 } else { volume / 5.0 };
            assert!(
                (value - expected).abs() < 1e-14 * volume,
                "node {a}: {value} vs {expected}"
            );
        }
        // ∫∇N_vertex = 0 and ∫∇N_ij = V(∇Lᵢ + ∇Lⱼ), used by volume_change.
        for (a, g) in gradient_integral.iter().enumerate() {
            let expected = if a < 4 {
                DVec3::ZERO
            } else {
                let [i, j] = TET_EDGES[a - 4];
                volume * (grad_l[i] + grad_l[j])
            };
            assert!(
                (*g - expected).length() < 1e-13,
                "node {a}: {g} vs {expected}"
            );
        }
    }

    #[test]
    fn gravity_load_sums_to_the_weight() {
        let mesh = distorted_box([3, 2, 2], 0.3, 1).transformed(0.1, DVec3::new(0.0, 1.0, 0.0));
        let mut fem = Fem::new(&mesh, 1e4, 0.3).unwrap();
        let g = DVec3::new(0.5, -9.81, 0.25);
        fem.gravity(1000.0, g);
        let weight = 1000.0 * mesh.volume() * g;
        assert!((fem.total_load() - weight).length() < 1e-13 * weight.length());
        assert!(relative(fem.volume(), mesh.volume()) < 1e-14);
    }

    #[test]
    fn rigid_translation_has_that_mean() {
        let mesh = distorted_box([2, 2, 3], 0.3, 2);
        let mut fem = Fem::new(&mesh, 1e4, 0.3).unwrap();
        let t = DVec3::new(0.01, -0.02, 0.03);
        assert_eq!(fem.fix_nodes(|_| true, [true; 3], t), fem.nodes().len());
        let solution = fem.solve(1e-10).unwrap();
        assert_eq!(solution.iterations, 0);
        assert!((solution.mean_displacement() - t).length() < 1e-15);
        assert!(solution.volume_change().abs() < 1e-15);
        assert!((solution.displacement_at(DVec3::splat(0.4)).unwrap() - t).length() < 1e-15);
        assert!((solution.mean_over(|p| p.x == 0.0).unwrap() - t).length() < 1e-15);
        assert_eq!(solution.mean_over(|p| p.x > 2.0), None);
        assert_eq!(solution.displacement(0), Some(t));
        assert_eq!(solution.displacement(solution.nodes.len()), None);
    }

    #[test]
    fn patch_test_uniaxial_compression() {
        let side = 0.06;
        let nu = 0.3;
        let mesh = TetMesh::box_mesh(DVec3::ZERO, DVec3::splat(side), [2, 3, 2]).unwrap();
        let mut fem = Fem::new(&mesh, 20e3, nu).unwrap();
        fem.fix_nodes(|p| p.y == 0.0, [false, true, false], DVec3::ZERO);
        fem.fix_nodes(|p| p.x == 0.0, [true, false, false], DVec3::ZERO);
        fem.fix_nodes(|p| p.z == 0.0, [false, false, true], DVec3::ZERO);
        let top = fem.fix_nodes(
            |p| p.y == side,
            [false, true, false],
            DVec3::new(0.0, -0.003, 0.0),
        );
        assert_eq!(top, 5 * 5);
        let solution = fem.solve(1e-14).unwrap();
        let axial = -0.003 / side;
        let lateral_x = solution.mean_over(|p| p.x == side).unwrap().x / side;
        let lateral_z = solution.mean_over(|p| p.z == side).unwrap().z / side;
        assert!(
            relative(lateral_x / axial, -nu) < 1e-9,
            "{}",
            lateral_x / axial
        );
        assert!(
            relative(lateral_z / axial, -nu) < 1e-9,
            "{}",
            lateral_z / axial
        );
        // Homogeneous: every node, and points in between, follow u = ε x.
        let strain = DVec3::new(-nu * axial, axial, -nu * axial);
        for (p, u) in solution.nodes.iter().zip(&solution.displacements) {
            assert!((*u - strain * *p).length() < 1e-11, "{p}: {u}");
        }
        let q = DVec3::new(0.011, 0.037, 0.052);
        assert!((solution.displacement_at(q).unwrap() - strain * q).length() < 1e-11);
        assert!(relative(solution.volume_change(), (1.0 - 2.0 * nu) * axial) < 1e-9);
        assert!((solution.mean_displacement() - strain * side / 2.0).length() < 1e-11);
    }

    /// Mean vertical displacement (m) of the free end of the 0.24 × 0.03 × 0.03 m
    /// cantilever under its own weight, with the DOFs, iterations and seconds it took.
    fn cantilever(cells: [usize; 3]) -> (f64, usize, usize, f64) {
        let length = 0.24;
        let mesh = TetMesh::box_mesh(DVec3::ZERO, DVec3::new(length, 0.03, 0.03), cells).unwrap();
        let start = Instant::now();
        let mut fem = Fem::new(&mesh, 100e3, 0.3).unwrap();
        assert!(fem.fix_nodes(|p| p.x == 0.0, [true; 3], DVec3::ZERO) > 0);
        fem.gravity(1000.0, DVec3::new(0.0, -0.2, 0.0));
        let solution = fem.solve(1e-9).unwrap();
        let tip = solution.mean_over(|p| p.x == length).unwrap().y;
        let seconds = start.elapsed().as_secs_f64();
        println!(
            "cantilever {cells:?}: tip {tip:.6e} m, {} DOFs, {} PCG iterations, {seconds:.2} s",
            fem.dof_count(),
            solution.iterations
        );
        (tip, fem.dof_count(), solution.iterations, seconds)
    }

    /// Converged tip deflection (m) of the cantilever (Richardson extrapolation of the
    /// 32 × 4 × 4 and 64 × 8 × 8 answers); Euler–Bernoulli q L⁴ / (8 E I) gives 11.06e-3.
    const CANTILEVER_TIP: f64 = 11.11e-3;

    #[test]
    fn cantilever_matches_the_converged_deflection() {
        let (coarse, ..) = cantilever([16, 2, 2]);
        assert!(relative(-coarse, CANTILEVER_TIP) < 0.01, "{coarse}");
        let (fine, ..) = cantilever([32, 4, 4]);
        assert!(relative(-fine, CANTILEVER_TIP) < 0.0025, "{fine}");
        // Measured: 0.501 % apart (-11.0355e-3 and -11.0910e-3 m).
        assert!(relative(coarse, fine) < 0.006, "{coarse} vs {fine}");
    }

    #[test]
    #[ignore = "large: 112k DOFs (run with --release --ignored --nocapture)"]
    fn cantilever_64x8x8() {
        let (tip, ..) = cantilever([64, 8, 8]);
        assert!(relative(-tip, CANTILEVER_TIP) < 0.001, "{tip}");
    }

    #[test]
    fn displacement_queries_agree_with_the_exact_integrals() {
        let length = 0.24;
        let mesh =
            TetMesh::box_mesh(DVec3::ZERO, DVec3::new(length, 0.03, 0.03), [8, 1, 1]).unwrap();
        let mut fem = Fem::new(&mesh, 100e3, 0.3).unwrap();
        fem.fix_nodes(|p| p.x == 0.0, [true; 3], DVec3::ZERO);
        fem.gravity(1000.0, DVec3::new(0.0, -0.2, 0.0));
        let solution = fem.solve(1e-12).unwrap();
        // At the nodes, the interpolation returns the nodal values.
        for (p, u) in solution.nodes.iter().zip(&solution.displacements) {
            let at = solution.displacement_at(*p).unwrap();
            assert!(
                (at - *u).length() < 1e-12 * solution.max_displacement(),
                "{p}"
            );
        }
        assert_eq!(solution.displacement_at(DVec3::new(0.3, 0.0, 0.0)), None);
        assert_eq!(solution.displacement_at(DVec3::NAN), None);
        // The 4-point rule on displacement_at (quadratic) reproduces mean_displacement.
        let mut integral = DVec3::ZERO;
        for tet in &mesh.tets {
            let p = tet.map(|i| mesh.nodes[i as usize]);
            let volume = signed_volume(p[0], p[1], p[2], p[3]);
            for l in quadrature_points() {
                let x = p.iter().zip(l).map(|(p, l)| *p * l).sum();
                integral += solution.displacement_at(x).unwrap() * volume / 4.0;
            }
        }
        let mean = solution.mean_displacement();
        assert!((integral / solution.volume() - mean).length() < 1e-12 * mean.length());
        assert!(mean.y < 0.0);
        // Bending is nearly isochoric at the mean: |ΔV/V| far below the strains.
        assert!(solution.volume_change().abs() < 1e-3);
    }
}
