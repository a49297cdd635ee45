//! Cached factorisations of the stiffness: Cholesky on a symbolic factorisation computed
//! once per pattern, LU when the tangent is not positive definite, single precision for
//! preconditioning.

use super::ordering::nested_dissection;
use super::outcome::{FactorizationError, FemError};
use crate::fem::assembly::{Assembler, NONE};
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::perm::PermRef;
use faer::sparse::linalg::cholesky::{LltRef, SymbolicCholesky, SymmetricOrdering, factorize_symbolic_cholesky};
use faer::sparse::linalg::lu::{LuRef, NumericLu, SymbolicLu, factorize_symbolic_lu};
use faer::{Mat, Par, Side};

/// Cached factorisations for one sparsity pattern: Cholesky with a nested-dissection
/// ordering of the grid (symbolic part computed once), LU when the tangent is not
/// positive definite.
pub(super) struct Factorizer {
    pub(super) perm_fwd: Vec<usize>,
    pub(super) perm_inv: Vec<usize>,
    pub(super) llt_symbolic: Option<SymbolicCholesky<usize>>,
    pub(super) l_values: Vec<f64>,
    pub(super) mem: Option<MemBuffer>,
    pub(super) lu_symbolic: Option<SymbolicLu<usize>>,
    pub(super) lu_values: NumericLu<usize, f64>,
    pub(super) lu_mem: Option<MemBuffer>,
    pub(super) current: Option<Factor>,
    /// Cholesky values of the stiffness at rest (u = 0), the same for every load on this
    /// grid, material and constraints: the first iteration of each solve reuses it.
    pub(super) rest_values: Option<Vec<f64>>,
    /// Single-precision factor of a refreshed tangent: only ever a CG preconditioner, where
    /// f32 halves the factorisation and triangular-solve cost at no loss in the result.
    pub(super) l32: Vec<f32>,
    pub(super) a32: Vec<f32>,
}

#[derive(Clone, Copy, PartialEq, Eq)]
pub(super) enum FactorKind {
    Llt,
    Lu,
}

pub(super) enum Factor {
    Llt,
    Llt32,
    Rest,
    Lu,
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
    sym.factorize_numeric_llt(
        values,
        mat,
        Side::Lower,
        LltRegularization::default(),
        par,
        MemStack::new(mem),
        Default::default(),
    )
    .map(|_| ())
}

fn factorization_error(stage: &'static str) -> impl Fn(FactorizationError) -> FemError {
    move |source| FemError::Factorization { stage, source }
}

impl Factorizer {
    pub(super) fn new(node_ijk: &[[usize; 3]], free_of: &[u32]) -> Self {
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
    pub(super) fn factorize(&mut self, asm: &Assembler, at_rest: bool, par: Par) -> Result<FactorKind, FemError> {
        if at_rest && self.rest_values.is_some() {
            self.current = Some(Factor::Rest);
            return Ok(FactorKind::Llt);
        }
        let mat = asm.matrix();
        if self.llt_symbolic.is_none() {
            let perm = PermRef::new_checked(&self.perm_fwd, &self.perm_inv, self.perm_fwd.len());
            let sym = factorize_symbolic_cholesky(
                mat.symbolic(),
                Side::Lower,
                SymmetricOrdering::Custom(perm),
                Default::default(),
            )
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
            let sym = factorize_symbolic_lu(mat.symbolic(), Default::default())
                .map_err(|e| factorization_error("symbolic LU")(e.into()))?;
            let req = sym
                .factorize_numeric_lu_scratch::<f64>(par, Default::default())
                .or(sym.solve_in_place_scratch::<f64>(1, par));
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
    pub(super) fn factorize32(&mut self, asm: &Assembler, par: Par) -> bool {
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
    pub(super) fn solve(&mut self, rhs: &mut Mat<f64>, par: Par) {
        match (&self.current, &self.llt_symbolic, &mut self.mem) {
            (Some(Factor::Llt), Some(sym), Some(mem)) => {
                LltRef::new(sym, &self.l_values).solve_in_place_with_conj(
                    faer::Conj::No,
                    rhs.as_mut(),
                    par,
                    MemStack::new(mem),
                );
            }
            (Some(Factor::Llt32), Some(sym), Some(mem)) => {
                let mut r32 = Mat::<f32>::from_fn(rhs.nrows(), 1, |i, _| rhs[(i, 0)] as f32);
                LltRef::new(sym, &self.l32).solve_in_place_with_conj(
                    faer::Conj::No,
                    r32.as_mut(),
                    par,
                    MemStack::new(mem),
                );
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
    pub(super) fn name(self) -> &'static str {
        match self {
            FactorKind::Llt => "cholesky",
            FactorKind::Lu => "lu",
        }
    }
}
