//! Newton-Raphson with adaptive load increments and a backtracking line search, and the one
//! linear solve.

use super::*;

impl FeSolver<'_> {
    pub(super) fn residual(&self, asmd: &Assembled, f_ext: &[Vector3<f64>], load: f64) -> (Vec<f64>, f64) {
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

    pub(super) fn apply_prescribed(&self, u: &mut [Vector3<f64>], bc: &BoundaryConditions, load: f64) {
        for &(node, d) in &bc.prescribed_mm {
            u[node] = d * load;
        }
        for (nd, fixed) in bc.fixed.iter().enumerate() {
            if *fixed && !bc.prescribed_mm.iter().any(|p| p.0 == nd) {
                u[nd] = Vector3::zeros();
            }
        }
    }

    pub(super) fn add_free(&self, u: &mut [Vector3<f64>], du: &Mat<f64>, alpha: f64) {
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

    pub(super) fn solve_linear(&mut self, bc: &BoundaryConditions) -> Result<Solution, FemError> {
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

    pub(super) fn solve_incremental(
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
                    reason: format!(
                        "gave up after {budget} Newton iterations at load factor {done:.3} (iteration budget)"
                    ),
                    history,
                });
            }
            match self.newton(
                &mut trial,
                bc,
                model,
                load,
                increments + 1,
                &mut history,
                &mut timings,
                progress,
                cancel,
            )? {
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
    pub(super) fn newton(
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
                return Ok(Err(crate::Invalid::from(
                    "the tangent stiffness is indefinite (the material collapses under this load)",
                )));
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
            let potential = |a: &Assembled, u: &[Vector3<f64>]| {
                a.energy - load * u.iter().zip(&bc.forces_n).map(|(x, f)| x.dot(f)).sum::<f64>()
            };
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
                                ElementModel::Hyperelastic(_) if slope0 > 0.0 && pi.is_finite() => {
                                    pi <= pi0 - 1e-4 * alpha * slope0
                                }
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
