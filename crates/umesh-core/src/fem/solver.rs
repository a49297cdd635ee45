//! Static solvers: Newton-Raphson with adaptive load increments and a backtracking line
//! search (hyperelastic), one linear solve, and co-rotational iterations. Linear systems
//! use faer's sparse Cholesky, whose symbolic factorisation is computed once per pattern
//! and reused; LU takes over when the tangent is not positive definite.

use super::assembly::{Assembled, Assembler, ElementModel, NONE};
use super::bc::BoundaryConditions;
use super::material::{MaterialKind, MaterialParams};
use crate::grid::ImmersedGrid;
use crate::progress::{Cancel, Progress};
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::perm::PermRef;
use faer::sparse::linalg::cholesky::{LltRef, SymbolicCholesky, SymmetricOrdering, factorize_symbolic_cholesky};
use faer::sparse::linalg::lu::{LuRef, NumericLu, SymbolicLu, factorize_symbolic_lu};
use faer::{Mat, Par, Side};
use nalgebra::Vector3;
use std::time::Instant;

pub mod fit;

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

/// One Newton (or co-rotational) iteration.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct IterationRecord {
    pub increment: usize,
    pub load_factor: f64,
    pub iteration: usize,
    /// |r| / |reference force| before the step.
    pub residual: f64,
    /// |du| / |u| of the step taken.
    pub correction: f64,
    pub step_length: f64,
    pub assembly_ms: f64,
    pub factorization_ms: f64,
    pub solve_ms: f64,
    pub factorization: &'static str,
}

#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct Timings {
    pub assembly_ms: f64,
    pub factorization_ms: f64,
    pub solve_ms: f64,
    pub total_ms: f64,
}

#[derive(Clone, Debug)]
pub struct Solution {
    pub displacement_mm: Vec<Vector3<f64>>,
    pub history: Vec<IterationRecord>,
    pub increments: usize,
    pub iterations: usize,
    pub timings: Timings,
    pub final_residual: f64,
}

impl Solution {
    pub fn max_displacement_mm(&self) -> f64 {
        self.displacement_mm.iter().map(|u| u.norm()).fold(0.0, f64::max)
    }
    pub fn mean_displacement_mm(&self) -> f64 {
        self.displacement_mm.iter().map(|u| u.norm()).sum::<f64>() / self.displacement_mm.len().max(1) as f64
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

/// The outcome of `FeSolver::solve_to_mean_displacement`.
#[derive(Clone, Debug)]
pub struct MeanSolve {
    pub solution: Solution,
    /// The factor applied to the forces.
    pub lambda: f64,
    /// The mean displacement (mm, over the chosen nodes) of the solution.
    pub mean_mm: f64,
    /// False when the target could not be reached and the largest converged state below it
    /// (at least `MIN_REACHED_FRACTION` of the target) was kept instead.
    pub reached: bool,
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

#[derive(Debug, thiserror::Error)]
pub enum FemError {
    #[error("the solve did not converge: {reason} (after {} iterations)", history.len())]
    NotConverged { reason: String, history: Vec<IterationRecord> },
    #[error("invalid problem: {0}")]
    InvalidInput(String),
    #[error("the linear system could not be factorised ({stage})")]
    Factorization {
        stage: &'static str,
        #[source]
        source: FactorizationError,
    },
    #[error("the solution is not finite (singular stiffness)")]
    Singular,
    #[error(transparent)]
    Cancelled(#[from] crate::Cancelled),
}

/// faer's error, kept as the source of `FemError::Factorization`.
#[derive(Debug, thiserror::Error)]
pub enum FactorizationError {
    #[error(transparent)]
    Faer(#[from] faer::sparse::FaerError),
    #[error(transparent)]
    Lu(#[from] faer::sparse::linalg::LuError),
    #[error("out of memory for the factorisation's workspace")]
    Memory(#[from] faer::dyn_stack::mem::AllocError),
}

/// Cached factorisations for one sparsity pattern: Cholesky with a nested-dissection
/// ordering of the grid (symbolic part computed once), LU when the tangent is not
/// positive definite.
struct Factorizer {
    perm_fwd: Vec<usize>,
    perm_inv: Vec<usize>,
    llt_symbolic: Option<SymbolicCholesky<usize>>,
    l_values: Vec<f64>,
    mem: Option<MemBuffer>,
    lu_symbolic: Option<SymbolicLu<usize>>,
    lu_values: NumericLu<usize, f64>,
    lu_mem: Option<MemBuffer>,
    current: Option<Factor>,
    /// Cholesky values of the stiffness at rest (u = 0), the same for every load on this
    /// grid, material and constraints: the first iteration of each solve reuses it.
    rest_values: Option<Vec<f64>>,
    /// Single-precision factor of a refreshed tangent: only ever a CG preconditioner, where
    /// f32 halves the factorisation and triangular-solve cost at no loss in the result.
    l32: Vec<f32>,
    a32: Vec<f32>,
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum FactorKind {
    Llt,
    Lu,
}

enum Factor {
    Llt,
    Llt32,
    Rest,
    Lu,
}

/// Geometric nested dissection of the node lattice: split the longest axis at a plane of
/// nodes (a separator for the 27-point stencil), order both halves, then the separator.
/// On these grids it leaves about a quarter less fill than AMD and factorises ~2x faster.
pub fn nested_dissection(node_ijk: &[[usize; 3]]) -> Vec<usize> {
    fn rec(nodes: Vec<usize>, ijk: &[[usize; 3]], out: &mut Vec<usize>) {
        if nodes.len() <= 48 {
            out.extend(nodes);
            return;
        }
        let mut lo = [usize::MAX; 3];
        let mut hi = [0; 3];
        for &n in &nodes {
            for a in 0..3 {
                lo[a] = lo[a].min(ijk[n][a]);
                hi[a] = hi[a].max(ijk[n][a]);
            }
        }
        let ax = (0..3).max_by_key(|&a| hi[a] - lo[a]).unwrap_or(0);
        if hi[ax] - lo[ax] < 2 {
            out.extend(nodes);
            return;
        }
        let mid = (lo[ax] + hi[ax]) / 2;
        let (mut l, mut r, mut sep) = (Vec::new(), Vec::new(), Vec::new());
        for n in nodes {
            match ijk[n][ax].cmp(&mid) {
                std::cmp::Ordering::Less => l.push(n),
                std::cmp::Ordering::Greater => r.push(n),
                std::cmp::Ordering::Equal => sep.push(n),
            }
        }
        rec(l, ijk, out);
        rec(r, ijk, out);
        out.extend(sep);
    }
    let mut out = Vec::with_capacity(node_ijk.len());
    rec((0..node_ijk.len()).collect(), node_ijk, &mut out);
    out
}

/// Numeric Cholesky into `values` on the shared symbolic factorisation; faer's error when the
/// matrix is not positive definite (the caller then falls back to LU).
fn numeric_llt<T: faer::traits::ComplexField>(
    sym: &SymbolicCholesky<usize>,
    values: &mut [T],
    mat: faer::sparse::SparseColMatRef<'_, usize, T>,
    mem: &mut MemBuffer,
    par: Par,
) -> Result<(), faer::linalg::solvers::LltError> {
    sym.factorize_numeric_llt(values, mat, Side::Lower, LltRegularization::default(), par, MemStack::new(mem), Default::default())
        .map(|_| ())
}

fn factorization_error(stage: &'static str) -> impl Fn(FactorizationError) -> FemError {
    move |source| FemError::Factorization { stage, source }
}

impl Factorizer {
    fn new(node_ijk: &[[usize; 3]], free_of: &[u32]) -> Self {
        let mut perm_fwd = Vec::new();
        for n in nested_dissection(node_ijk) {
            for c in 0..3 {
                let f = free_of[3 * n + c];
                if f != NONE {
                    perm_fwd.push(f as usize);
                }
            }
        }
        let mut perm_inv = vec![0; perm_fwd.len()];
        for (i, &f) in perm_fwd.iter().enumerate() {
            perm_inv[f] = i;
        }
        Self {
            perm_fwd,
            perm_inv,
            llt_symbolic: None,
            l_values: Vec::new(),
            mem: None,
            lu_symbolic: None,
            lu_values: NumericLu::new(),
            lu_mem: None,
            current: None,
            rest_values: None,
            l32: Vec::new(),
            a32: Vec::new(),
        }
    }

    /// Factorise the assembled matrix; `at_rest` says it is the stiffness at u = 0.
    fn factorize(&mut self, asm: &Assembler, at_rest: bool, par: Par) -> Result<FactorKind, FemError> {
        if at_rest && self.rest_values.is_some() {
            self.current = Some(Factor::Rest);
            return Ok(FactorKind::Llt);
        }
        let mat = asm.matrix();
        if self.llt_symbolic.is_none() {
            let perm = PermRef::new_checked(&self.perm_fwd, &self.perm_inv, self.perm_fwd.len());
            let sym = factorize_symbolic_cholesky(mat.symbolic(), Side::Lower, SymmetricOrdering::Custom(perm), Default::default())
                .map_err(|e| factorization_error("symbolic Cholesky")(e.into()))?;
            let req = sym
                .factorize_numeric_llt_scratch::<f64>(par, Default::default())
                .or(sym.solve_in_place_scratch::<f64>(1, par))
                .or(sym.factorize_numeric_llt_scratch::<f32>(par, Default::default()))
                .or(sym.solve_in_place_scratch::<f32>(1, par));
            self.mem = Some(MemBuffer::try_new(req).map_err(|e| factorization_error("Cholesky workspace")(e.into()))?);
            self.l_values = vec![0.0; sym.len_val()];
            self.llt_symbolic = Some(sym);
        }
        if let (Some(sym), Some(mem)) = (&self.llt_symbolic, &mut self.mem)
            && numeric_llt(sym, &mut self.l_values, mat, mem, par).is_ok()
        {
            if at_rest {
                self.rest_values = Some(self.l_values.clone());
                self.current = Some(Factor::Rest);
            } else {
                self.current = Some(Factor::Llt);
            }
            return Ok(FactorKind::Llt);
        }
        // Not positive definite: LU, its symbolic part also computed once.
        if self.lu_symbolic.is_none() {
            let sym =
                factorize_symbolic_lu(mat.symbolic(), Default::default()).map_err(|e| factorization_error("symbolic LU")(e.into()))?;
            let req = sym.factorize_numeric_lu_scratch::<f64>(par, Default::default()).or(sym.solve_in_place_scratch::<f64>(1, par));
            self.lu_mem = Some(MemBuffer::try_new(req).map_err(|e| factorization_error("LU workspace")(e.into()))?);
            self.lu_symbolic = Some(sym);
        }
        if let (Some(sym), Some(mem)) = (&self.lu_symbolic, &mut self.lu_mem) {
            sym.factorize_numeric_lu(&mut self.lu_values, mat, par, MemStack::new(mem), Default::default())
                .map_err(|e| factorization_error("numeric LU")(e.into()))?;
        }
        self.current = Some(Factor::Lu);
        Ok(FactorKind::Lu)
    }

    /// Single-precision Cholesky of the assembled matrix, for preconditioning. False when the
    /// matrix is not positive definite (or the symbolic factorisation is not there yet).
    fn factorize32(&mut self, asm: &Assembler, par: Par) -> bool {
        let (Some(sym), Some(mem)) = (&self.llt_symbolic, &mut self.mem) else { return false };
        let mat = asm.matrix();
        let (symbolic, vals) = mat.parts();
        self.a32.clear();
        self.a32.extend(vals.iter().map(|&v| v as f32));
        self.l32.resize(sym.len_val(), 0.0);
        let a32 = faer::sparse::SparseColMatRef::new(symbolic, &self.a32);
        let ok = numeric_llt(sym, &mut self.l32, a32, mem, par).is_ok();
        if ok {
            self.current = Some(Factor::Llt32);
        }
        ok
    }

    /// Solve with the last factorisation, in place.
    fn solve(&mut self, rhs: &mut Mat<f64>, par: Par) {
        match (&self.current, &self.llt_symbolic, &mut self.mem) {
            (Some(Factor::Llt), Some(sym), Some(mem)) => {
                LltRef::new(sym, &self.l_values).solve_in_place_with_conj(faer::Conj::No, rhs.as_mut(), par, MemStack::new(mem));
            }
            (Some(Factor::Llt32), Some(sym), Some(mem)) => {
                let mut r32 = Mat::<f32>::from_fn(rhs.nrows(), 1, |i, _| rhs[(i, 0)] as f32);
                LltRef::new(sym, &self.l32).solve_in_place_with_conj(faer::Conj::No, r32.as_mut(), par, MemStack::new(mem));
                for i in 0..rhs.nrows() {
                    rhs[(i, 0)] = r32[(i, 0)] as f64;
                }
            }
            (Some(Factor::Rest), Some(sym), Some(mem)) => {
                if let Some(v) = &self.rest_values {
                    LltRef::new(sym, v).solve_in_place_with_conj(faer::Conj::No, rhs.as_mut(), par, MemStack::new(mem));
                }
            }
            (Some(Factor::Lu), _, _) => {
                if let (Some(sym), Some(mem)) = (&self.lu_symbolic, &mut self.lu_mem) {
                    LuRef::new_unchecked(sym, &self.lu_values).solve_in_place_with_conj(
                        faer::Conj::No,
                        rhs.as_mut(),
                        par,
                        MemStack::new(mem),
                    );
                }
            }
            _ => {}
        }
    }
}

impl FactorKind {
    fn name(self) -> &'static str {
        match self {
            FactorKind::Llt => "cholesky",
            FactorKind::Lu => "lu",
        }
    }
}

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
    pub fn new(grid: &'g ImmersedGrid, material: MaterialParams, constrained: &[bool], settings: SolverSettings) -> Result<Self, FemError> {
        material.validate().map_err(|e| FemError::InvalidInput(e.into()))?;
        if constrained.len() != grid.node_count() {
            return Err(FemError::InvalidInput(format!("{} constraint flags for {} nodes", constrained.len(), grid.node_count())));
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
            return Err(FemError::InvalidInput("the constrained nodes differ from those the solver was built for".into()));
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

    fn residual(&self, asmd: &Assembled, f_ext: &[Vector3<f64>], load: f64) -> (Vec<f64>, f64) {
        let free = &self.asm.dofs.free_of;
        let mut r = vec![0.0; self.asm.dofs.n_free];
        let mut ref2 = 0.0;
        let mut all_int2 = 0.0;
        for (nd, (fi, fe)) in asmd.f_int.iter().zip(f_ext).enumerate() {
            for c in 0..3 {
                let k = free[3 * nd + c];
                all_int2 += fi[c] * fi[c];
                if k != NONE {
                    r[k as usize] = load * fe[c] - fi[c];
                    ref2 += (load * fe[c]).powi(2);
                }
            }
        }
        (r, ref2.max(all_int2).sqrt().max(1e-30))
    }

    fn apply_prescribed(&self, u: &mut [Vector3<f64>], bc: &BoundaryConditions, load: f64) {
        for &(node, d) in &bc.prescribed_mm {
            u[node] = d * load;
        }
        for (nd, fixed) in bc.fixed.iter().enumerate() {
            if *fixed && !bc.prescribed_mm.iter().any(|p| p.0 == nd) {
                u[nd] = Vector3::zeros();
            }
        }
    }

    fn add_free(&self, u: &mut [Vector3<f64>], du: &Mat<f64>, alpha: f64) {
        let free = &self.asm.dofs.free_of;
        for (nd, v) in u.iter_mut().enumerate() {
            for c in 0..3 {
                let k = free[3 * nd + c];
                if k != NONE {
                    v[c] += alpha * du[(k as usize, 0)];
                }
            }
        }
    }

    fn solve_linear(&mut self, bc: &BoundaryConditions) -> Result<Solution, FemError> {
        let mut u = vec![Vector3::zeros(); self.grid.node_count()];
        self.apply_prescribed(&mut u, bc, 1.0);
        let lin = MaterialParams { kind: MaterialKind::Linear, ..self.material }.material();
        let t = Instant::now();
        let a = self.asm.assemble(ElementModel::Hyperelastic(lin), &u, true);
        let assembly_ms = ms(t);
        let (r, refn) = self.residual(&a, &bc.forces_n, 1.0);
        let t = Instant::now();
        // The small-strain stiffness equals the stiffness at rest, whatever u.
        let fac = self.fact.factorize(&self.asm, true, self.settings.parallelism.par())?;
        let factorization_ms = ms(t);
        let t = Instant::now();
        let mut rhs = Mat::from_fn(r.len(), 1, |i, _| r[i]);
        self.fact.solve(&mut rhs, self.settings.parallelism.par());
        let solve_ms = ms(t);
        if !(0..rhs.nrows()).all(|i| rhs[(i, 0)].is_finite()) {
            return Err(FemError::Singular);
        }
        self.add_free(&mut u, &rhs, 1.0);
        let rec = IterationRecord {
            increment: 1,
            load_factor: 1.0,
            iteration: 1,
            residual: norm(&r) / refn,
            correction: 1.0,
            step_length: 1.0,
            assembly_ms,
            factorization_ms,
            solve_ms,
            factorization: fac.name(),
        };
        Ok(Solution {
            displacement_mm: u,
            history: vec![rec],
            increments: 1,
            iterations: 1,
            timings: Timings { assembly_ms, factorization_ms, solve_ms, total_ms: 0.0 },
            final_residual: 0.0,
        })
    }

    /// Solve K du = r for the Newton step. The stiffness at rest is factorised once and
    /// reused; later iterations first try conjugate gradients preconditioned by the last
    /// factorisation (an inexact Newton step, relative tolerance |r|/|r0| / 2 clamped to
    /// [5e-4, 0.05], which keeps the fast local rate until the last digits), and refresh the
    /// factorisation in single precision when CG converges slowly.
    fn linear_step(
        &mut self,
        r: &[f64],
        rel: f64,
        at_rest: bool,
        stale: &mut bool,
    ) -> Result<(Mat<f64>, &'static str, f64, f64), FemError> {
        // Near convergence a few CG steps beat a refactorisation even with a stale preconditioner.
        if !at_rest && (!*stale || rel < 1e-4) && self.settings.reuse_factorization && self.fact.current.is_some() {
            let t = Instant::now();
            let tol = rel.clamp(1e-3, 0.1) * 0.5;
            if let Some((x, iters)) = self.pcg(r, tol, 12) {
                if iters > 6 {
                    *stale = true;
                }
                return Ok((x, "pcg", 0.0, ms(t)));
            }
        }
        *stale = false;
        // A refreshed tangent: factorise in single precision and solve by CG on top of it.
        if !at_rest && self.settings.reuse_factorization && self.fact.llt_symbolic.is_some() {
            let t = Instant::now();
            if self.fact.factorize32(&self.asm, self.settings.parallelism.par()) {
                let factorization_ms = ms(t);
                let t = Instant::now();
                let tol = rel.clamp(1e-3, 0.1) * 0.5;
                if let Some((x, _)) = self.pcg(r, tol, 30) {
                    return Ok((x, "cholesky-f32+pcg", factorization_ms, ms(t)));
                }
            }
        }
        let t = Instant::now();
        let kind = self.fact.factorize(&self.asm, at_rest, self.settings.parallelism.par())?;
        let factorization_ms = ms(t);
        let t = Instant::now();
        let mut du = Mat::from_fn(r.len(), 1, |i, _| r[i]);
        self.fact.solve(&mut du, self.settings.parallelism.par());
        Ok((du, kind.name(), factorization_ms, ms(t)))
    }

    /// Preconditioned conjugate gradients on the assembled matrix; None when it does not
    /// reach |r_k| <= tol |r| in `max_iter` iterations or meets negative curvature.
    fn pcg(&mut self, b: &[f64], tol: f64, max_iter: usize) -> Option<(Mat<f64>, usize)> {
        let n = b.len();
        let bnorm = norm(b);
        let mut x = vec![0.0; n];
        let mut r = b.to_vec();
        let mut z = Mat::from_fn(n, 1, |i, _| r[i]);
        self.fact.solve(&mut z, self.settings.parallelism.par());
        let mut p: Vec<f64> = (0..n).map(|i| z[(i, 0)]).collect();
        let mut rz: f64 = (0..n).map(|i| r[i] * z[(i, 0)]).sum();
        let mut ap = vec![0.0; n];
        for k in 1..=max_iter {
            self.matvec(&p, &mut ap);
            let pap: f64 = p.iter().zip(&ap).map(|(a, b)| a * b).sum();
            if !(pap > 0.0) {
                return None;
            }
            let alpha = rz / pap;
            for i in 0..n {
                x[i] += alpha * p[i];
                r[i] -= alpha * ap[i];
            }
            if norm(&r) <= tol * bnorm {
                return Some((Mat::from_fn(n, 1, |i, _| x[i]), k));
            }
            for i in 0..n {
                z[(i, 0)] = r[i];
            }
            self.fact.solve(&mut z, self.settings.parallelism.par());
            let rz_new: f64 = (0..n).map(|i| r[i] * z[(i, 0)]).sum();
            let beta = rz_new / rz;
            rz = rz_new;
            for i in 0..n {
                p[i] = z[(i, 0)] + beta * p[i];
            }
        }
        None
    }

    fn matvec(&self, x: &[f64], y: &mut [f64]) {
        let m = self.asm.matrix();
        let (sym, val) = m.parts();
        let col_ptr = sym.col_ptr();
        let row_idx = sym.row_idx();
        y.iter_mut().for_each(|v| *v = 0.0);
        for j in 0..x.len() {
            let xj = x[j];
            for p in col_ptr[j]..col_ptr[j + 1] {
                y[row_idx[p]] += val[p] * xj;
            }
        }
    }

    /// Newton on the hyperelastic material with the load scaled to the factor `lambda` at
    /// which the mean nodal displacement is `target_mm` (within `rel_tol`), for forces scaled
    /// so that the *linear* mean displacement at lambda = 1 is the target. A continuation in
    /// the load factor from `first_lambda`: each probe is warm-started from the nearest
    /// converged state below (scaled by the secant through the origin) and solved to a loose
    /// residual; the next factor comes from a softening model fitted to the nearest probe,
    /// m(lambda) = t lambda / (1 - t lambda / D) (D: the displacement scale at which the
    /// material would collapse), kept inside the bracket of probes below and above the target;
    /// the accepted probe is refined to the settings' tolerance. Returns the solution and lambda.
    pub fn solve_to_mean_displacement(
        &mut self,
        bc: &BoundaryConditions,
        target_mm: f64,
        rel_tol: f64,
        first_lambda: f64,
        over: MeanOver,
        cancel: &Cancel,
    ) -> Result<MeanSolve, FemError> {
        let n = self.grid.node_count();
        if bc.forces_n.len() != n || bc.fixed != self.constrained_nodes || !bc.prescribed_mm.is_empty() {
            return Err(FemError::InvalidInput(
                "boundary conditions do not match the solver (fixed nodes only, no prescribed values)".into(),
            ));
        }
        if !(target_mm > 0.0 && target_mm.is_finite() && rel_tol > 0.0 && first_lambda > 0.0) {
            return Err(FemError::InvalidInput(format!("target {target_mm} mm, tolerance {rel_tol}, first factor {first_lambda}")));
        }
        let start = Instant::now();
        let s = self.settings.clone();
        let model = ElementModel::Hyperelastic(self.material.material());
        let fixed = self.constrained_nodes.clone();
        let mean = |u: &[Vector3<f64>]| over.mean_mm(u, &fixed);
        // Converged states (lambda, mean, u), sorted by lambda; the rest state is one.
        let mut states: Vec<(f64, f64, Vec<Vector3<f64>>)> = vec![(0.0, 0.0, vec![Vector3::zeros(); n])];
        let mut failed_above = f64::INFINITY;
        let mut history = Vec::new();
        let mut timings = Timings::default();
        let mut lambda = first_lambda;
        let mut increments = 0;
        let mut failures = 0;
        let mut probes = 0;
        loop {
            cancel.check()?;
            // Probes that converge at once (a warm start already in equilibrium) add no Newton
            // iteration: the probe count bounds the search as well.
            probes += 1;
            if probes > MAX_PROBES || s.max_total_iterations.is_some_and(|budget| history.len() >= budget) {
                let budget = s.max_total_iterations.unwrap_or(history.len());
                if let Some(kept) =
                    self.keep_largest_below(&mut states, bc, model, target_mm, over, &mut history, &mut timings, start, cancel)?
                {
                    return Ok(kept);
                }
                let closest = states.iter().skip(1).map(|x| x.1).min_by(|a, b| (a - target_mm).abs().total_cmp(&(b - target_mm).abs()));
                return Err(FemError::NotConverged {
                    reason: format!(
                        "gave up after {budget} Newton iterations without reaching a mean displacement of {target_mm:.2} mm ({}; iteration budget)",
                        closest.map(|c| format!("closest {c:.2} mm")).unwrap_or_else(|| "no load step converged".into())
                    ),
                    history,
                });
            }
            // Warm start: the nearest converged state below, scaled to the new factor (the secant
            // through the origin); unscaled when the scaled guess would invert an element.
            let (lam0, base) =
                states.iter().rev().find(|x| x.0 < lambda).map(|x| (x.0, x.2.clone())).unwrap_or((0.0, vec![Vector3::zeros(); n]));
            let mut trial = base.clone();
            if lam0 > 0.0 {
                let scaled: Vec<Vector3<f64>> = base.iter().map(|u| u * (lambda / lam0)).collect();
                if self.asm.assemble(model, &scaled, false).min_det_f > 0.0 {
                    trial = scaled;
                }
            }
            // Probing solves stop at a loose residual (the mean displacement is then already
            // right to a fraction of a percent); the accepted one is refined to the settings'.
            let tight = self.settings.clone();
            self.settings.residual_tol = tight.residual_tol.max(1e-3);
            self.settings.correction_tol = tight.correction_tol.max(1e-2);
            self.overshoot_mm = Some((OVERSHOOT * target_mm, over));
            let probe = self.newton(&mut trial, bc, model, lambda, increments + 1, &mut history, &mut timings, &Progress::none(), cancel);
            self.settings = tight;
            self.overshoot_mm = None;
            match probe? {
                Ok(_) => {
                    increments += 1;
                    let m = mean(&trial);
                    if (m - target_mm).abs() <= rel_tol * target_mm {
                        let refined =
                            self.newton(&mut trial, bc, model, lambda, increments, &mut history, &mut timings, &Progress::none(), cancel)?;
                        let res = match refined {
                            Ok((_, res)) => res,
                            Err(reason) => return Err(FemError::NotConverged { reason: reason.into(), history }),
                        };
                        let iterations = history.len();
                        timings.total_ms = ms(start);
                        let mean_mm = mean(&trial);
                        let solution = Solution { displacement_mm: trial, history, increments, iterations, timings, final_residual: res };
                        return Ok(MeanSolve { solution, lambda, mean_mm, reached: true });
                    }
                    let k = states.partition_point(|x| x.0 < lambda);
                    states.insert(k, (lambda, m, trial));
                }
                Err(reason) => {
                    failures += 1;
                    failed_above = failed_above.min(lambda);
                    if failures > s.max_halvings {
                        if let Some(kept) =
                            self.keep_largest_below(&mut states, bc, model, target_mm, over, &mut history, &mut timings, start, cancel)?
                        {
                            return Ok(kept);
                        }
                        let largest = states.iter().map(|x| x.1).fold(0.0, f64::max);
                        return Err(FemError::NotConverged {
                            reason: format!(
                                "{reason}; the load factor failed {failures} times short of the target ({target_mm:.2} mm; the largest converged state moved {largest:.2} mm)"
                            ),
                            history,
                        });
                    }
                }
            }
            // The bracket: the converged states nearest the target from below and above.
            let below = states.iter().filter(|x| x.1 < target_mm).max_by(|a, b| a.0.total_cmp(&b.0));
            let above = states.iter().filter(|x| x.1 > target_mm).min_by(|a, b| a.0.total_cmp(&b.0));
            let nearest = states.iter().filter(|x| x.0 > 0.0).min_by(|a, b| (a.1 - target_mm).abs().total_cmp(&(b.1 - target_mm).abs()));
            let mut next = match nearest {
                Some(&(l, m, _)) => softening_factor(target_mm, l, m),
                None => lambda * 0.5,
            };
            if let (Some(a), Some(b)) = (below, above)
                && !(next > a.0 && next < b.0)
            {
                next = a.0 + (target_mm - a.1) * (b.0 - a.0) / (b.1 - a.1);
            }
            if let (Some(a), None) = (below, above) {
                next = next.min(2.0 * a.0.max(first_lambda));
            }
            // Stay below factors that failed: halfway between the last good one and the failure.
            if next >= failed_above {
                let lo = states.iter().filter(|x| x.0 < failed_above).map(|x| x.0).fold(0.0, f64::max);
                next = 0.5 * (lo + failed_above);
            }
            if !(next > 0.0 && next.is_finite()) {
                next = 0.5 * lambda;
            }
            lambda = next;
        }
    }

    /// The calibrated solve could not reach its target: keep the converged probe with the
    /// largest mean displacement (the states are below the collapse), refined to the settings'
    /// tolerance, when it moves at least `MIN_REACHED_FRACTION` of the target. The work already
    /// done is kept rather than discarded; the caller records it as below its target.
    #[allow(clippy::too_many_arguments)]
    fn keep_largest_below(
        &mut self,
        states: &mut Vec<(f64, f64, Vec<Vector3<f64>>)>,
        bc: &BoundaryConditions,
        model: ElementModel,
        target_mm: f64,
        over: MeanOver,
        history: &mut Vec<IterationRecord>,
        timings: &mut Timings,
        start: Instant,
        cancel: &Cancel,
    ) -> Result<Option<MeanSolve>, FemError> {
        let best = states
            .iter()
            .enumerate()
            .filter(|(_, x)| x.0 > 0.0 && x.1 >= MIN_REACHED_FRACTION * target_mm && x.1 <= MAX_REACHED_FRACTION * target_mm)
            .min_by(|a, b| (a.1.1 - target_mm).abs().total_cmp(&(b.1.1 - target_mm).abs()))
            .map(|(k, _)| k);
        let Some(k) = best else { return Ok(None) };
        let (lambda, _, mut u) = states.swap_remove(k);
        let increments = states.len() + 1;
        // A few iterations from a state already converged to a loose residual.
        let saved = self.settings.max_iterations;
        self.settings.max_iterations = saved.min(8);
        let refined = self.newton(&mut u, bc, model, lambda, increments, history, timings, &Progress::none(), cancel);
        self.settings.max_iterations = saved;
        let res = match refined? {
            Ok((_, res)) => res,
            Err(_) => return Ok(None),
        };
        let mean_mm = over.mean_mm(&u, &self.constrained_nodes);
        timings.total_ms = ms(start);
        let iterations = history.len();
        let solution = Solution {
            displacement_mm: u,
            history: std::mem::take(history),
            increments,
            iterations,
            timings: timings.clone(),
            final_residual: res,
        };
        // Every state within the tolerance was accepted when it converged: this one is not.
        Ok(Some(MeanSolve { solution, lambda, mean_mm, reached: false }))
    }

    fn solve_incremental(
        &mut self,
        bc: &BoundaryConditions,
        model: ElementModel,
        progress: &Progress,
        cancel: &Cancel,
    ) -> Result<Solution, FemError> {
        let s = self.settings.clone();
        let mut u = vec![Vector3::zeros(); self.grid.node_count()];
        let mut history = Vec::new();
        let mut timings = Timings::default();
        let mut done = 0.0f64;
        let mut step = 1.0 / s.initial_increments.max(1) as f64;
        let mut halvings = 0;
        let mut increments = 0;
        let mut final_residual = 0.0;
        while done < 1.0 - 1e-12 {
            cancel.check()?;
            let load = (done + step).min(1.0);
            let mut trial = u.clone();
            self.apply_prescribed(&mut trial, bc, load);
            if let Some(budget) = s.max_total_iterations
                && history.len() >= budget
            {
                return Err(FemError::NotConverged {
                    reason: format!("gave up after {budget} Newton iterations at load factor {done:.3} (iteration budget)"),
                    history,
                });
            }
            match self.newton(&mut trial, bc, model, load, increments + 1, &mut history, &mut timings, progress, cancel)? {
                Ok((iters, res)) => {
                    u = trial;
                    done = load;
                    increments += 1;
                    final_residual = res;
                    halvings = 0;
                    // Easy increments let the next one grow back.
                    if iters <= 4 {
                        step = (step * 2.0).min(1.0);
                    }
                }
                Err(reason) => {
                    halvings += 1;
                    if halvings > s.max_halvings {
                        return Err(FemError::NotConverged {
                            reason: format!(
                                "{reason}; reached load factor {done:.4}, the increment was halved {} times in a row down to {step:.3e}",
                                s.max_halvings
                            ),
                            history,
                        });
                    }
                    step *= 0.5;
                }
            }
        }
        let iterations = history.len();
        Ok(Solution { displacement_mm: u, history, increments, iterations, timings, final_residual })
    }

    /// Newton iterations at one load factor. Outer Err: fatal; inner Err: this increment
    /// failed (too large), with the reason.
    #[allow(clippy::too_many_arguments)]
    fn newton(
        &mut self,
        u: &mut [Vector3<f64>],
        bc: &BoundaryConditions,
        model: ElementModel,
        load: f64,
        increment: usize,
        history: &mut Vec<IterationRecord>,
        timings: &mut Timings,
        progress: &Progress,
        cancel: &Cancel,
    ) -> Result<Result<(usize, f64), crate::Invalid>, FemError> {
        let s = self.settings.clone();
        let t = Instant::now();
        let mut current = self.asm.assemble(model, u, true);
        let mut assembly_ms = ms(t);
        let mut last_correction = f64::INFINITY;
        let mut stale = false;
        for it in 1..=s.max_iterations {
            cancel.check()?;
            if !(current.min_det_f > 0.0) {
                return Ok(Err(crate::Invalid::from("an element inverted (det F <= 0)")));
            }
            let (r, refn) = self.residual(&current, &bc.forces_n, load);
            let rnorm = norm(&r);
            if !rnorm.is_finite() {
                return Ok(Err(crate::Invalid::from("the residual is not finite")));
            }
            let rel = rnorm / refn;
            if rel <= s.residual_tol && (last_correction <= s.correction_tol || rel <= s.residual_tol * 1e-3) {
                return Ok(Ok((it - 1, rel)));
            }
            let at_rest = it == 1 && u.iter().all(|v| *v == Vector3::zeros());
            let (du, fac_name, factorization_ms, solve_ms) = self.linear_step(&r, rel, at_rest, &mut stale)?;
            if s.reject_indefinite && fac_name == "lu" {
                timings.factorization_ms += factorization_ms;
                return Ok(Err(crate::Invalid::from("the tangent stiffness is indefinite (the material collapses under this load)")));
            }
            let du_norm = (0..du.nrows()).map(|i| du[(i, 0)].powi(2)).sum::<f64>().sqrt();
            if !du_norm.is_finite() {
                return Ok(Err(crate::Invalid::from("the Newton correction is not finite")));
            }
            // Backtracking line search. With a descent direction (r . du > 0) the test is
            // Armijo's on the total potential energy Pi = W(u) - load f . u, the quantity Newton
            // minimises; otherwise (indefinite tangent) on the residual norm. Inverted
            // configurations are always rejected.
            let mut alpha = 1.0;
            let t = Instant::now();
            let base: Vec<Vector3<f64>> = u.to_vec();
            let slope0: f64 = r.iter().enumerate().map(|(i, v)| v * du[(i, 0)]).sum();
            let potential =
                |a: &Assembled, u: &[Vector3<f64>]| a.energy - load * u.iter().zip(&bc.forces_n).map(|(x, f)| x.dot(f)).sum::<f64>();
            let pi0 = potential(&current, &base);
            loop {
                u.copy_from_slice(&base);
                self.add_free(u, &du, alpha);
                current = self.asm.assemble(model, u, true);
                let ok = current.min_det_f > 0.0 && {
                    let (r2, _) = self.residual(&current, &bc.forces_n, load);
                    let n2 = norm(&r2);
                    let pi = potential(&current, u);
                    let slope = r2.iter().enumerate().map(|(i, v)| v * du[(i, 0)]).sum::<f64>();
                    n2.is_finite()
                        && (n2 <= refn * s.residual_tol
                            || match model {
                                ElementModel::Hyperelastic(_) if slope0 > 0.0 && pi.is_finite() => pi <= pi0 - 1e-4 * alpha * slope0,
                                // The co-rotational forces are not the exact gradient of an energy:
                                // accept a falling residual or a halved slope along the step.
                                _ => n2 <= (1.0 - 1e-4 * alpha) * rnorm || slope.abs() <= 0.5 * slope0.abs(),
                            })
                };
                if ok || !s.line_search || alpha < 1.0 / 32.0 {
                    break;
                }
                alpha *= 0.5;
            }
            let a_ms = ms(t);
            let unorm = u.iter().map(|v| v.norm_squared()).sum::<f64>().sqrt().max(1e-30);
            last_correction = alpha * du_norm / unorm;
            timings.assembly_ms += assembly_ms;
            timings.factorization_ms += factorization_ms;
            timings.solve_ms += solve_ms;
            history.push(IterationRecord {
                increment,
                load_factor: load,
                iteration: it,
                residual: rel,
                correction: last_correction,
                step_length: alpha,
                assembly_ms,
                factorization_ms,
                solve_ms,
                factorization: fac_name,
            });
            assembly_ms = a_ms;
            progress.report(
                history.len() as u64,
                0,
                &format!("increment {increment} (load {:.0} %), iteration {it}: residual {rel:.2e}", load * 100.0),
            );
            if let Some((limit, over)) = self.overshoot_mm {
                let m = over.mean_mm(u, &self.constrained_nodes);
                if m > limit {
                    timings.assembly_ms += assembly_ms;
                    return Ok(Err(crate::Invalid(format!("the mean displacement passed {limit:.1} mm (overshoot)"))));
                }
            }
        }
        timings.assembly_ms += assembly_ms;
        Ok(Err(crate::Invalid(format!("no convergence in {} iterations at load factor {load:.3}", s.max_iterations))))
    }
}

/// A probe whose iterate's mean displacement passes this multiple of the target is abandoned:
/// on the phantom such iterates were heading for a collapsed state (15 wasted iterations each).
const OVERSHOOT: f64 = 2.0;
/// Load factors a calibrated solve may try before it keeps its nearest state or gives up.
const MAX_PROBES: usize = 24;

/// The load factor at which a softening response through (lambda, m), with the linear slope
/// t per unit factor at the origin, reaches t: m(l) = t l / (1 - t l / D).
pub fn softening_factor(target_mm: f64, lambda: f64, mean_mm: f64) -> f64 {
    let lin = target_mm * lambda;
    if mean_mm > lin * (1.0 + 1e-9) {
        let d = lin / (1.0 - lin / mean_mm);
        1.0 / (1.0 + target_mm / d)
    } else {
        // Stiffening (or linear): the secant through the origin.
        lambda * target_mm / mean_mm.max(1e-12)
    }
}

/// The collapse scale D (mm) of `softening_factor` seen at one converged point; infinite when
/// the response there is not softer than linear.
pub fn softening_scale_mm(target_mm: f64, lambda: f64, mean_mm: f64) -> f64 {
    let lin = target_mm * lambda;
    if mean_mm > lin * (1.0 + 1e-9) { lin / (1.0 - lin / mean_mm) } else { f64::INFINITY }
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
        return Err(FemError::InvalidInput(format!("{} fixed flags for {} nodes", constrained.len(), grid.node_count())));
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
