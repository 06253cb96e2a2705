//! Typed errors of the simulation core. Every failure names the problem and, where it
//! helps, counts it; no library function panics on bad input.

use std::fmt;

/// What is wrong with an input surface mesh.
#[derive(Debug, Clone, PartialEq)]
pub enum MeshError {
    /// No vertices or no triangles.
    Empty,
    /// The index buffer length is not a multiple of three.
    NotTriangles {
        /// Number of indices found.
        indices: usize,
    },
    /// A vertex coordinate is NaN or infinite.
    NonFinite {
        /// Index of the first bad vertex.
        vertex: usize,
        /// How many vertices are bad.
        count: usize,
    },
    /// An index points past the vertex array.
    IndexOutOfRange {
        /// The offending index value.
        index: u32,
        /// Number of vertices.
        vertices: usize,
    },
    /// Triangles with (near) zero area or repeated vertices.
    DegenerateTriangles {
        /// How many triangles are degenerate.
        count: usize,
    },
    /// Edges used by only one triangle: the surface has holes.
    NotClosed {
        /// Number of boundary edges.
        boundary_edges: usize,
    },
    /// Edges shared by more than two triangles (or duplicate faces).
    NonManifold {
        /// Number of non-manifold edges.
        edges: usize,
    },
    /// Neighbouring triangles disagree about which side is outside.
    InconsistentOrientation {
        /// Number of edges traversed twice in the same direction.
        edges: usize,
    },
    /// The enclosed volume is zero (flat surface).
    ZeroVolume,
}

impl fmt::Display for MeshError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            MeshError::Empty => write!(f, "mesh is empty: no vertices or no triangles"),
            MeshError::NotTriangles { indices } => {
                write!(
                    f,
                    "index count {indices} is not a multiple of 3 (triangle list expected)"
                )
            }
            MeshError::NonFinite { vertex, count } => write!(
                f,
                "{count} vertex position(s) are NaN or infinite (first: vertex {vertex})"
            ),
            MeshError::IndexOutOfRange { index, vertices } => write!(
                f,
                "triangle index {index} is out of range ({vertices} vertices)"
            ),
            MeshError::DegenerateTriangles { count } => {
                write!(
                    f,
                    "{count} degenerate triangle(s) (zero area or repeated vertex)"
                )
            }
            MeshError::NotClosed { boundary_edges } => {
                write!(f, "surface not closed: {boundary_edges} boundary edges")
            }
            MeshError::NonManifold { edges } => write!(
                f,
                "surface not manifold: {edges} edges shared by more than two triangles"
            ),
            MeshError::InconsistentOrientation { edges } => write!(
                f,
                "triangle orientation inconsistent: {edges} edges traversed twice in the same direction"
            ),
            MeshError::ZeroVolume => write!(f, "surface encloses zero volume"),
        }
    }
}

impl std::error::Error for MeshError {}

/// Any error of model building or simulation.
#[derive(Debug, Clone, PartialEq)]
pub enum TissueError {
    /// The surface mesh cannot become a soft body.
    Mesh(MeshError),
    /// A parameter is outside its valid range.
    InvalidParameter {
        /// Parameter name as it appears in the API.
        name: &'static str,
        /// The rejected value, formatted.
        value: String,
        /// What is allowed.
        expected: &'static str,
    },
    /// The neighbour count K is not smaller than the number of particles.
    TooFewParticles {
        /// Particles sampled in the body.
        particles: usize,
        /// Requested neighbour count K.
        neighbours: usize,
    },
    /// The requested resolution would create more particles than allowed.
    TooManyParticles {
        /// Particles the request would create (estimate).
        requested: usize,
        /// The limit.
        limit: usize,
    },
    /// The model does not fit the GPU: a buffer or a dispatch would exceed the adapter's
    /// limits.
    GpuLimit {
        /// What exceeds the limit (a buffer or a dispatch, by name).
        what: &'static str,
        /// What the model needs (bytes or count).
        needed: u64,
        /// What the adapter allows.
        limit: u64,
    },
    /// The adapter cannot run the simulation's kernels at all, whatever the model: a
    /// limit of the device is below what they need.
    GpuUnsupported {
        /// The device limit, by name.
        what: &'static str,
        /// What the kernels need.
        needed: u64,
        /// What the adapter allows.
        limit: u64,
    },
    /// A kernel's shader could not be analysed for its bindings (a defect of this crate,
    /// not of the model or the adapter).
    GpuShader {
        /// The shader module.
        module: &'static str,
        /// What went wrong.
        message: String,
    },
    /// The simulation produced NaN/inf or exploded; the state was restored to before the step.
    Diverged {
        /// Step counter at which it happened.
        step: u64,
        /// The body it happened in (index into `Model::bodies`).
        body: usize,
        /// The offending particle: the first non-finite one, else the fastest.
        particle: usize,
        /// Where in its body, in words (which faces or corner of its rest bounding box
        /// the particle's rest position is near, and that position from the body's
        /// centre in m).
        region: String,
        /// What was detected.
        reason: DivergenceKind,
        /// The likely cause and the remedy, in words.
        advice: String,
    },
}

/// Why a step was rejected as diverged.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DivergenceKind {
    /// A position or velocity became NaN or infinite.
    NonFinite,
    /// A speed exceeded the configured limit (m/s).
    Exploding {
        /// The speed found, m/s.
        speed: f32,
    },
}

impl fmt::Display for TissueError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            TissueError::Mesh(e) => write!(f, "invalid mesh: {e}"),
            TissueError::InvalidParameter {
                name,
                value,
                expected,
            } => write!(
                f,
                "invalid parameter `{name}` = {value}: expected {expected}"
            ),
            TissueError::TooFewParticles {
                particles,
                neighbours,
            } => write!(
                f,
                "neighbour count K = {neighbours} must be smaller than the body's particle count ({particles}); lower K or raise the resolution"
            ),
            TissueError::TooManyParticles { requested, limit } => write!(
                f,
                "resolution would create about {requested} particles, more than the limit of {limit}"
            ),
            TissueError::GpuLimit {
                what,
                needed,
                limit,
            } => write!(
                f,
                "model too big for the GPU: {what} needs {needed}, the adapter allows {limit}; lower the resolution or split the body"
            ),
            TissueError::GpuUnsupported {
                what,
                needed,
                limit,
            } => write!(
                f,
                "the adapter cannot run the simulation's kernels: {what} needs {needed}, the adapter allows {limit}"
            ),
            TissueError::GpuShader { module, message } => write!(
                f,
                "the {module} kernels' bindings could not be analysed (please report this): {message}"
            ),
            TissueError::Diverged {
                step,
                body,
                particle,
                region,
                reason,
                advice,
            } => {
                match reason {
                    DivergenceKind::NonFinite => write!(
                        f,
                        "body {body} diverged at step {step}: particle {particle} ({region}) became NaN/infinite"
                    )?,
                    DivergenceKind::Exploding { speed } => write!(
                        f,
                        "body {body} exploded at step {step}: particle {particle} ({region}) reached {speed:.3e} m/s"
                    )?,
                }
                write!(f, " (state restored). {advice}")
            }
        }
    }
}

impl std::error::Error for TissueError {}

impl From<MeshError> for TissueError {
    fn from(e: MeshError) -> Self {
        TissueError::Mesh(e)
    }
}

/// Checks that `value` is finite and strictly positive.
pub(crate) fn positive(name: &'static str, value: f32) -> Result<f32, TissueError> {
    if value.is_finite() && value > 0.0 {
        Ok(value)
    } else {
        Err(TissueError::InvalidParameter {
            name,
            value: format!("{value}"),
            expected: "a finite value > 0",
        })
    }
}

/// Checks that `value` is finite and within `[lo, hi]`.
pub(crate) fn in_range(
    name: &'static str,
    value: f32,
    lo: f32,
    hi: f32,
    expected: &'static str,
) -> Result<f32, TissueError> {
    if value.is_finite() && value >= lo && value <= hi {
        Ok(value)
    } else {
        Err(TissueError::InvalidParameter {
            name,
            value: format!("{value}"),
            expected,
        })
    }
}
