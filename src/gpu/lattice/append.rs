//! Appending a lattice body into the room of a [`GpuLattice`] in two parts: packing it
//! against a snapshot of the world ([`AppendBasis::prepare`], plain CPU work that any
//! thread can do while the world steps on), and writing what was packed
//! ([`GpuLattice::commit_append`]: copies from one staging buffer in one submission,
//! and the new plan), which is all a frame pays for a new body where the packing ran
//! on a worker thread.

use super::layout::{Buf, Layout, Writes};
use super::{Dispatch, GpuLattice, PassRecord, Shape, pass_bytes, passes_of, shape_of};
use crate::core::TissueError;
use crate::core::model::{Discretisation, Material, Model};
use crate::core::multigrid::{BodyLevels, LatticeMultigrid};
use crate::core::solver::{SolverSettings, State};
use bevy::render::render_resource::{Buffer, BufferInitDescriptor, BufferUsages};
use bevy::render::renderer::{RenderDevice, RenderQueue};

/// What packing a body into a [`GpuLattice`] needs of the world: where everything is in
/// its buffers and how much room is left, the shape of its step, and the generation
/// they belong to (every append and every change of steps makes a new one). Owned and
/// `Send`: a worker thread packs against it while the world steps.
#[derive(Debug, Clone)]
pub struct AppendBasis {
    world: u64,
    generation: u64,
    layout: Layout,
    shape: Shape,
    newton: u32,
    pass_room: usize,
    pair_capacity: usize,
}

/// A body packed into one generation of a world, ready to be written there by
/// [`GpuLattice::commit_append`].
#[derive(Debug)]
pub struct PreparedAppend {
    world: u64,
    generation: u64,
    layout: Layout,
    shape: Shape,
    dispatches: Vec<Dispatch>,
    pass_index: Vec<u32>,
    records: Vec<PassRecord>,
    /// Each level's Chebyshev `1/θ` and `ρ²` for the body alone.
    chebyshev: Vec<[f32; 2]>,
    /// Every write, back to back (u32 words).
    staged: Vec<u32>,
    /// Each write: its buffer, where there (words), where in `staged`, how long.
    copies: Vec<(Buf, u32, usize, usize)>,
    /// `staged` on the device, once made ([`PreparedAppend::stage`]).
    staging: Option<Buffer>,
}

impl AppendBasis {
    /// Packs `model`'s body (one hyperelastic lattice body, its own model, in `state`;
    /// `levels` its hierarchy from [`BodyLevels::new`]) as the world's next body, for
    /// [`GpuLattice::commit_append`]. `Ok(None)` where it does not fit the room, or the
    /// world has no particle-contact lists and `settings` asks for particle contacts;
    /// an error for a model that is not one such body.
    pub fn prepare(
        &self,
        model: &Model,
        levels: &BodyLevels,
        state: &State,
        settings: &SolverSettings,
    ) -> Result<Option<PreparedAppend>, TissueError> {
        let lattice = model.bodies.len() == 1
            && model.bodies[0].discretisation == Discretisation::Lattice
            && matches!(model.bodies[0].material, Material::Hyperelastic { .. });
        let fine = levels.levels.first();
        if !lattice
            || fine.is_none_or(|f| {
                f.nodes != model.particle_count() || f.elements.len() != model.elements.len()
            })
            || state.x.len() != model.particle_count()
            || state.element_rot.len() != model.elements.len()
        {
            return Err(TissueError::InvalidParameter {
                name: "appended body",
                value: format!("{} bodies", model.bodies.len()),
                expected: "one hyperelastic lattice body with its own levels and state",
            });
        }
        if self.pair_capacity == 0 && settings.particle_contacts {
            return Ok(None);
        }
        let depth = self.layout.levels();
        let mut mg = if levels.chebyshev.len() >= depth.min(levels.levels.len()) {
            let mut mg = LatticeMultigrid::join(&[levels], depth);
            mg.chebyshev = levels.chebyshev.clone();
            mg
        } else {
            LatticeMultigrid::joined(&[levels], depth)
        };
        mg.smoother = self.shape.smoother;
        let mut layout = self.layout.clone();
        let mut writes = Writes::default();
        if !layout.pack_all(model, &mg, state, &mut writes) {
            return Ok(None);
        }
        let mut shape = shape_of(
            &layout,
            self.shape.smoother,
            self.shape.pairs,
            self.shape.cycles,
            self.shape.sweeps,
            self.shape.fused_coarsest,
            self.shape.one_thread_rows_from,
        );
        shape.factor_kept = self.shape.factor_kept;
        let (dispatches, records, pass_index) = passes_of(&shape, self.newton);
        if records.len() > self.pass_room {
            return Ok(None);
        }
        let words = writes.0.iter().map(|w| w.2.len()).sum();
        let mut staged: Vec<u32> = Vec::with_capacity(words);
        let mut copies = Vec::with_capacity(writes.0.len());
        for (b, at, data) in &writes.0 {
            copies.push((*b, *at, staged.len(), data.len()));
            staged.extend_from_slice(data);
        }
        Ok(Some(PreparedAppend {
            world: self.world,
            generation: self.generation,
            layout,
            shape,
            dispatches,
            pass_index,
            records,
            chebyshev: mg.chebyshev,
            staged,
            copies,
            staging: None,
        }))
    }

    /// The basis of the world once `prepared` (packed against this basis) is committed:
    /// to pack another body behind it before it is.
    pub fn after(&self, prepared: &PreparedAppend) -> AppendBasis {
        AppendBasis {
            generation: self.generation + 1,
            layout: prepared.layout.clone(),
            shape: prepared.shape.clone(),
            ..self.clone()
        }
    }
}

impl PreparedAppend {
    /// Puts the packed data on the device now (any thread), so that the commit only
    /// records the copies.
    pub fn stage(&mut self, device: &RenderDevice) {
        if self.staging.is_none() && !self.staged.is_empty() {
            self.staging = Some(device.create_buffer_with_data(&BufferInitDescriptor {
                label: Some("tissue lattice append"),
                contents: bytemuck::cast_slice(&self.staged),
                usage: BufferUsages::COPY_SRC,
            }));
        }
    }

    /// Bytes the commit copies into the world's buffers.
    pub fn bytes(&self) -> usize {
        4 * self.staged.len()
    }
}

impl GpuLattice {
    /// What a body appended now would be packed against ([`AppendBasis::prepare`]).
    pub fn append_basis(&self) -> AppendBasis {
        AppendBasis {
            world: self.id,
            generation: self.generation,
            layout: self.layout.clone(),
            shape: self.shape.clone(),
            newton: self.newton,
            pass_room: self.pass_room,
            pair_capacity: self.pair_capacity,
        }
    }

    /// Writes a body packed by [`AppendBasis::prepare`] against this world as it is now:
    /// its data into the room (one submission), each level's Chebyshev estimate the
    /// larger of the world's and the body's, and the new plan and parameters. False,
    /// with nothing changed, where it was packed for another world, or this world has
    /// changed since the basis was taken (another append, new steps): pack it again.
    pub fn commit_append(
        &mut self,
        device: &RenderDevice,
        queue: &RenderQueue,
        mut prepared: PreparedAppend,
    ) -> bool {
        if (prepared.world, prepared.generation) != (self.id, self.generation) {
            return false;
        }
        prepared.stage(device);
        if let Some(staging) = &prepared.staging {
            let mut enc = device.create_command_encoder(&Default::default());
            for &(b, at, from, len) in &prepared.copies {
                let buffer = match b {
                    Buf::Elems => &self.elems,
                    Buf::Kmat => &self.kmat,
                    Buf::Topo => &self.topo,
                    Buf::Nodes => &self.nodes,
                    Buf::Mats => &self.mats,
                    Buf::Rot => &self.rot,
                    Buf::Pos => &self.pos,
                    Buf::Ccol => &self.ccol,
                    Buf::Bodyt => &self.bodyt,
                };
                enc.copy_buffer_to_buffer(
                    staging,
                    4 * from as u64,
                    buffer,
                    4 * at as u64,
                    4 * len as u64,
                );
            }
            queue.submit([enc.finish()]);
        }
        // The larger largest eigenvalue (the smaller 1/θ).
        for (c, new) in self.cheb.iter_mut().zip(&prepared.chebyshev) {
            if new[0] < c[0] {
                *c = *new;
            }
        }
        queue.write_buffer(
            &self.passes,
            0,
            &pass_bytes(&prepared.records, self.pass_room),
        );
        self.layout = prepared.layout;
        self.shape = prepared.shape;
        self.dispatches = prepared.dispatches;
        self.pass_index = prepared.pass_index;
        self.generation += 1;
        self.write_params(queue);
        true
    }

    /// Appends `model`'s body (one hyperelastic lattice body, its own model, in
    /// `state`; `levels` its hierarchy from [`BodyLevels::new`]) as the world's next
    /// body, into the room the world was made with ([`super::LatticeOptions::room`]):
    /// its particles and elements numbered on from the world's, every other body's
    /// state left as it is. Each level's Chebyshev estimate becomes the larger of the
    /// world's and the body's own ([`BodyLevels::chebyshev`], made with its levels).
    /// `Ok(false)` (nothing changed) where the room is too small, or the world has no
    /// particle-contact lists and `settings` asks for particle contacts (make the world
    /// again then); an error for a model that is not one such body. The packing and the
    /// writes in one call: [`GpuLattice::append_basis`], [`AppendBasis::prepare`] and
    /// [`GpuLattice::commit_append`] split them across threads.
    pub fn append(
        &mut self,
        device: &RenderDevice,
        queue: &RenderQueue,
        model: &Model,
        levels: &BodyLevels,
        state: &State,
        settings: &SolverSettings,
    ) -> Result<bool, TissueError> {
        match self
            .append_basis()
            .prepare(model, levels, state, settings)?
        {
            Some(prepared) => Ok(self.commit_append(device, queue, prepared)),
            None => Ok(false),
        }
    }
}
