//! The linear solve of a Newton step: the last factorisation reused as a preconditioner of
//! conjugate gradients while they converge fast, refreshed in single precision when they slow.

use super::*;

impl FeSolver<'_> {
    /// Solve K du = r for the Newton step. The stiffness at rest is factorised once and
    /// reused; later iterations first try conjugate gradients preconditioned by the last
    /// factorisation (an inexact Newton step, relative tolerance |r|/|r0| / 2 clamped to
    /// [5e-4, 0.05], which keeps the fast local rate until the last digits), and refresh the
    /// factorisation in single precision when CG converges slowly.
    pub(super) fn linear_step(
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
    pub(super) fn pcg(&mut self, b: &[f64], tol: f64, max_iter: usize) -> Option<(Mat<f64>, usize)> {
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

    pub(super) fn matvec(&self, x: &[f64], y: &mut [f64]) {
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
}
