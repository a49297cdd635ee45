//! Static solvers: Newton-Raphson with adaptive load increments and a backtracking line
//! search (hyperelastic), one linear solve, and co-rotational iterations. Linear systems
//! use faer's sparse Cholesky, whose symbolic factorisation is computed once per pattern
//! and reused; LU takes over when the tangent is not positive definite.
//!
//! One concern a file: `ordering` (nested dissection), `factorization` (the cached Cholesky /
//! LU factors), `step` (a Newton step's linear solve: factor reuse and PCG), `newton` (load
//! increments and Newton iterations), `calibration` (the solve to a mean displacement) and
//! `fit` (the registration's FE fit).

use super::assembly::{Assembled, Assembler, ElementModel, NONE};
use super::bc::BoundaryConditions;
use super::material::{MaterialKind, MaterialParams};
use crate::grid::ImmersedGrid;
use crate::progress::{Cancel, Progress};
use faer::{Mat, Par};
use nalgebra::Vector3;
use std::time::Instant;

mod calibration;
mod factorization;
pub mod fit;
mod newton;
mod ordering;
mod outcome;
mod step;

pub use calibration::{softening_factor, softening_scale_mm};
use factorization::Factorizer;
pub use ordering::nested_dissection;
pub use outcome::{FactorizationError, FemError, IterationRecord, MeanSolve, Solution, Timings};

#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SolveMethod {
    /// Newton-Raphson on the chosen hyperelastic material.
    Newton,
    /// One solve of the small-strain problem.
    Linear,
    /// Co-rotational linear elasticity, iterated to equilibrium.
    Corotational,
}

/// How many threads one solve's factorisations and triangular solves use. Carried in the
/// settings and passed to faer with every call, never set process-wide: dataset generation
/// solves its samples in parallel, each on one core, while an app solve next to it keeps
/// every core.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Parallelism {
    /// rayon's threads (faer's own default).
    #[default]
    Threads,
    /// One thread: results independent of scheduling and of the machine's core count.
    Sequential,
}

impl Parallelism {
    pub fn par(self) -> Par {
        match self {
            Self::Threads => Par::rayon(0),
            Self::Sequential => Par::Seq,
        }
    }
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SolverSettings {
    pub max_iterations: usize,
    /// Converged when |r| <= residual_tol * |reference force| ...
    pub residual_tol: f64,
    /// ... and the last correction |du| <= correction_tol * |u|.
    pub correction_tol: f64,
    /// Load increments to start with; halved on failure.
    pub initial_increments: usize,
    /// How many times an increment may be halved before giving up.
    pub max_halvings: usize,
    pub line_search: bool,
    /// Reuse factorisations as CG preconditioners between Newton iterations.
    pub reuse_factorization: bool,
    /// Relative stiffness of the fictitious part of boundary cells (finite cell method).
    pub stabilization: f64,
    /// Give up after this many Newton iterations over all increments (a sample that keeps
    /// cutting its load is going to invert; dataset generation rejects it early).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_total_iterations: Option<usize>,
    /// Treat an indefinite tangent (the material collapsing under the load, which SVK does in
    /// strong compression) as a failed increment instead of factorising it by LU: dataset
    /// generation rejects such a load in a few iterations rather than grinding for a minute.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub reject_indefinite: bool,
    /// Threads for this solve's linear algebra; not part of a dataset's configuration (the
    /// result does not depend on it beyond rounding).
    #[serde(skip)]
    pub parallelism: Parallelism,
}

impl Default for SolverSettings {
    fn default() -> Self {
        Self {
            max_iterations: 25,
            residual_tol: 1e-6,
            correction_tol: 1e-5,
            initial_increments: 1,
            max_halvings: 8,
            line_search: true,
            reuse_factorization: true,
            stabilization: 1e-2,
            max_total_iterations: None,
            reject_indefinite: false,
            parallelism: Parallelism::Threads,
        }
    }
}

impl SolverSettings {
    /// The same settings on one thread (each dataset sample: the samples run in parallel).
    pub fn sequential(&self) -> Self {
        Self { parallelism: Parallelism::Sequential, ..self.clone() }
    }
}

/// Which nodes a calibrated mean displacement averages over.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MeanOver {
    /// Every grid node, fixed ones included (datasets made before the free-node measure): a
    /// large fixed region then pushes the free part towards collapse to reach the target.
    All,
    /// The nodes that can move (not fixed): the same target means the same motion of what
    /// moves, whatever the size of the attachment.
    Free,
}

impl MeanOver {
    /// Datasets written before the field existed averaged over every node.
    pub fn legacy() -> Self {
        Self::All
    }
    pub fn is_all(&self) -> bool {
        *self == Self::All
    }
    /// The mean displacement norm (mm) over the chosen nodes; `fixed[n]`: node n is held.
    pub fn mean_mm(self, u: &[Vector3<f64>], fixed: &[bool]) -> f64 {
        let (sum, count) = u
            .iter()
            .enumerate()
            .filter(|(n, _)| self == Self::All || !fixed.get(*n).copied().unwrap_or(false))
            .fold((0.0, 0usize), |(s, c), (_, v)| (s + v.norm(), c + 1));
        sum / count.max(1) as f64
    }
}

/// A calibrated solve that cannot reach its target keeps its converged state nearest the target
/// when that moves at least this fraction of it (and at most `MAX_REACHED_FRACTION`); otherwise
/// the sample is rejected. A state short of its target is still an equilibrium of the forces
/// stored with it: the work is kept rather than redrawn. 0.5 rejected 8 of the MR liver's 1000
/// samples (at 0.35-0.46 of their targets) and the instruments on stiffly held tissue; 0.25
/// still rejected 3 of the robustness sweep's 936 samples (instruments whose first loads
/// inverted a contact cell, at 0.12-0.24, and one stalled at 0.11).
pub const MIN_REACHED_FRACTION: f64 = 0.1;
/// The largest multiple of the target a kept state may move (probes past twice the target are
/// abandoned as heading for a collapse).
pub const MAX_REACHED_FRACTION: f64 = 1.5;

/// A reusable solver for one grid, material and set of constrained nodes: the sparse
/// pattern, scatter maps and symbolic factorisation are kept between solves.
pub struct FeSolver<'g> {
    pub grid: &'g ImmersedGrid,
    pub material: MaterialParams,
    pub settings: SolverSettings,
    asm: Assembler<'g>,
    fact: Factorizer,
    pub(crate) constrained_nodes: Vec<bool>,
    /// While probing a load factor: give up on the probe once the iterate's mean nodal
    /// displacement passes this (mm), as it is heading for a collapsed state.
    overshoot_mm: Option<(f64, MeanOver)>,
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

impl<'g> FeSolver<'g> {
    /// `constrained[n]`: node n is fixed or has a prescribed displacement.
    pub fn new(
        grid: &'g ImmersedGrid,
        material: MaterialParams,
        constrained: &[bool],
        settings: SolverSettings,
    ) -> Result<Self, FemError> {
        material.validate().map_err(|e| FemError::InvalidInput(e.into()))?;
        if constrained.len() != grid.node_count() {
            return Err(FemError::InvalidInput(format!(
                "{} constraint flags for {} nodes",
                constrained.len(),
                grid.node_count()
            )));
        }
        if !constrained.iter().any(|&c| c) {
            return Err(FemError::InvalidInput("no node is fixed: the problem has rigid-body modes".into()));
        }
        // The assembler numbers cell-matrix entries (576 per cell) in 32 bits.
        if grid.cells.len() > super::assembly::MAX_CELLS {
            return Err(FemError::InvalidInput(format!(
                "the grid has {} cells, more than the {} the assembler handles; use larger cells (--cell-size-mm)",
                grid.cells.len(),
                super::assembly::MAX_CELLS
            )));
        }
        let dofs: Vec<bool> = constrained.iter().flat_map(|&c| [c; 3]).collect();
        let lin = MaterialParams { kind: MaterialKind::Linear, ..material }.material();
        let asm = Assembler::new(grid, &dofs, lin, settings.stabilization);
        let fact = Factorizer::new(&grid.node_ijk, &asm.dofs.free_of);
        Ok(Self { grid, material, settings, asm, fact, constrained_nodes: constrained.to_vec(), overshoot_mm: None })
    }

    /// Another material between solves (a dataset draws one per sample). The rest factor is
    /// dropped when the small-strain stiffness changes (Young's modulus or Poisson's ratio).
    pub fn set_material(&mut self, material: MaterialParams) -> Result<(), FemError> {
        material.validate().map_err(|e| FemError::InvalidInput(e.into()))?;
        if (material.young_pa, material.poisson) != (self.material.young_pa, self.material.poisson) {
            self.fact.rest_values = None;
            self.fact.current = None;
            self.asm.set_linear_material(MaterialParams { kind: MaterialKind::Linear, ..material }.material());
        }
        self.material = material;
        Ok(())
    }

    pub fn free_dofs(&self) -> usize {
        self.asm.dofs.n_free
    }

    pub fn nnz(&self) -> usize {
        self.asm.nnz()
    }

    /// The tangent stiffness (N/mm) of the free dofs at the node displacements `u_mm`, with the
    /// solver's material and stabilisation: the matrix a Newton step factorises, as CSC with both
    /// triangles stored, (n, col_ptr, row_idx, values). Free dofs are numbered node-major over
    /// the unconstrained nodes.
    pub fn tangent_csc(&mut self, u_mm: &[Vector3<f64>]) -> (usize, Vec<usize>, Vec<usize>, Vec<f64>) {
        self.asm.assemble(ElementModel::Hyperelastic(self.material.material()), u_mm, true);
        let m = self.asm.matrix();
        (m.nrows(), m.symbolic().col_ptr().to_vec(), m.symbolic().row_idx().to_vec(), m.val().to_vec())
    }

    /// Time (ms) one numeric Cholesky factorisation of the tangent at `u_mm`, on the symbolic
    /// factorisation the solver keeps (computed first if needed, not timed): the floor of a
    /// Newton step.
    pub fn time_factorization(&mut self, u_mm: &[Vector3<f64>]) -> Result<f64, FemError> {
        self.asm.assemble(ElementModel::Hyperelastic(self.material.material()), u_mm, true);
        self.fact.factorize(&self.asm, false, self.settings.parallelism.par())?;
        let t = Instant::now();
        self.fact.factorize(&self.asm, false, self.settings.parallelism.par())?;
        Ok(ms(t))
    }

    /// Solve the static problem for `bc`, whose constrained nodes must be those given to `new`.
    pub fn solve(
        &mut self,
        bc: &BoundaryConditions,
        method: SolveMethod,
        progress: &Progress,
        cancel: &Cancel,
    ) -> Result<Solution, FemError> {
        let n = self.grid.node_count();
        if bc.forces_n.len() != n || bc.fixed.len() != n {
            return Err(FemError::InvalidInput("boundary conditions do not match the grid".into()));
        }
        let mut constrained = bc.fixed.clone();
        for &(node, d) in &bc.prescribed_mm {
            if node >= n || !d.iter().all(|v| v.is_finite()) {
                return Err(FemError::InvalidInput(format!("bad prescribed displacement on node {node}")));
            }
            constrained[node] = true;
        }
        if constrained != self.constrained_nodes {
            return Err(FemError::InvalidInput(
                "the constrained nodes differ from those the solver was built for".into(),
            ));
        }
        if bc.forces_n.iter().any(|f| !f.iter().all(|v| v.is_finite())) {
            return Err(FemError::InvalidInput("a force is not finite".into()));
        }
        let start = Instant::now();
        let mut out = match method {
            SolveMethod::Linear => self.solve_linear(bc)?,
            SolveMethod::Newton => {
                let model = ElementModel::Hyperelastic(self.material.material());
                self.solve_incremental(bc, model, progress, cancel)?
            }
            SolveMethod::Corotational => self.solve_incremental(bc, ElementModel::Corotational, progress, cancel)?,
        };
        out.timings.total_ms = ms(start);
        Ok(out)
    }
}

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}

/// One-shot solve: builds a solver for the constraints of `bc` and solves.
pub fn solve(
    grid: &ImmersedGrid,
    material: &MaterialParams,
    bc: &BoundaryConditions,
    method: SolveMethod,
    settings: &SolverSettings,
    progress: &Progress,
    cancel: &Cancel,
) -> Result<Solution, FemError> {
    let mut constrained = bc.fixed.clone();
    if constrained.len() != grid.node_count() {
        return Err(FemError::InvalidInput(format!(
            "{} fixed flags for {} nodes",
            constrained.len(),
            grid.node_count()
        )));
    }
    for &(n, _) in &bc.prescribed_mm {
        if n >= constrained.len() {
            return Err(FemError::InvalidInput(format!("prescribed node {n} does not exist")));
        }
        constrained[n] = true;
    }
    let mut solver = FeSolver::new(grid, *material, &constrained, settings.clone())?;
    solver.solve(bc, method, progress, cancel)
}
