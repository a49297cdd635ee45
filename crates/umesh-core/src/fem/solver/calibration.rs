//! The solve to a target mean displacement: a continuation in the load factor guided by a
//! softening model.

use super::*;

impl FeSolver<'_> {
    /// The probe that landed within the tolerance of the target, refined to the settings'
    /// residual: the solve's result.
    #[allow(clippy::too_many_arguments)]
    fn refine_accepted(
        &mut self,
        mut trial: Vec<Vector3<f64>>,
        bc: &BoundaryConditions,
        model: ElementModel,
        (lambda, increments): (f64, usize),
        over: MeanOver,
        mut history: Vec<IterationRecord>,
        mut timings: Timings,
        start: Instant,
        cancel: &Cancel,
    ) -> Result<MeanSolve, FemError> {
        let refined = self.newton(
            &mut trial,
            bc,
            model,
            lambda,
            increments,
            &mut history,
            &mut timings,
            &Progress::none(),
            cancel,
        )?;
        let res = match refined {
            Ok((_, res)) => res,
            Err(reason) => return Err(FemError::NotConverged { reason: reason.into(), history }),
        };
        let iterations = history.len();
        timings.total_ms = ms(start);
        let mean_mm = over.mean_mm(&trial, &self.constrained_nodes);
        let solution =
            Solution { displacement_mm: trial, history, increments, iterations, timings, final_residual: res };
        Ok(MeanSolve { solution, lambda, mean_mm, reached: true })
    }

    /// The problem a calibrated solve takes: fixed nodes only, a positive target and factor.
    fn check_calibrated(
        &self,
        bc: &BoundaryConditions,
        target_mm: f64,
        rel_tol: f64,
        first_lambda: f64,
    ) -> Result<(), FemError> {
        let n = self.grid.node_count();
        if bc.forces_n.len() != n || bc.fixed != self.constrained_nodes || !bc.prescribed_mm.is_empty() {
            return Err(FemError::InvalidInput(
                "boundary conditions do not match the solver (fixed nodes only, no prescribed values)".into(),
            ));
        }
        if !(target_mm > 0.0 && target_mm.is_finite() && rel_tol > 0.0 && first_lambda > 0.0) {
            return Err(FemError::InvalidInput(format!(
                "target {target_mm} mm, tolerance {rel_tol}, first factor {first_lambda}"
            )));
        }
        Ok(())
    }

    /// One probe of a load factor: Newton to a loose residual (the mean displacement is then
    /// already right to a fraction of a percent; the accepted probe is refined to the settings'),
    /// given up once its iterate passes OVERSHOOT times the target.
    #[allow(clippy::too_many_arguments)]
    fn probe(
        &mut self,
        trial: &mut [Vector3<f64>],
        bc: &BoundaryConditions,
        model: ElementModel,
        lambda: f64,
        increment: usize,
        (target_mm, over): (f64, MeanOver),
        history: &mut Vec<IterationRecord>,
        timings: &mut Timings,
        cancel: &Cancel,
    ) -> Result<Result<(usize, f64), crate::Invalid>, FemError> {
        // Probing solves stop at a loose residual (the mean displacement is then already
        // right to a fraction of a percent); the accepted one is refined to the settings'.
        let tight = self.settings.clone();
        self.settings.residual_tol = tight.residual_tol.max(1e-3);
        self.settings.correction_tol = tight.correction_tol.max(1e-2);
        self.overshoot_mm = Some((OVERSHOOT * target_mm, over));
        let probe = self.newton(trial, bc, model, lambda, increment, history, timings, &Progress::none(), cancel);
        self.settings = tight;
        self.overshoot_mm = None;
        probe
    }

    /// A probe's start: the nearest converged state below `lambda`, scaled to it (the secant
    /// through the origin); unscaled when the scaled guess would invert an element.
    fn warm_start(
        &mut self,
        states: &[(f64, f64, Vec<Vector3<f64>>)],
        lambda: f64,
        model: ElementModel,
    ) -> Vec<Vector3<f64>> {
        let n = self.grid.node_count();
        let (lam0, base) = states
            .iter()
            .rev()
            .find(|x| x.0 < lambda)
            .map(|x| (x.0, x.2.clone()))
            .unwrap_or((0.0, vec![Vector3::zeros(); n]));
        if lam0 > 0.0 {
            let scaled: Vec<Vector3<f64>> = base.iter().map(|u| u * (lambda / lam0)).collect();
            if self.asm.assemble(model, &scaled, false).min_det_f > 0.0 {
                return scaled;
            }
        }
        base
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
        self.check_calibrated(bc, target_mm, rel_tol, first_lambda)?;
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
                if let Some(kept) = self.keep_largest_below(
                    &mut states,
                    bc,
                    model,
                    target_mm,
                    over,
                    &mut history,
                    &mut timings,
                    start,
                    cancel,
                )? {
                    return Ok(kept);
                }
                return Err(gave_up(&states, target_mm, budget, history));
            }
            let mut trial = self.warm_start(&states, lambda, model);
            let probe = self.probe(
                &mut trial,
                bc,
                model,
                lambda,
                increments + 1,
                (target_mm, over),
                &mut history,
                &mut timings,
                cancel,
            );
            match probe? {
                Ok(_) => {
                    increments += 1;
                    let m = mean(&trial);
                    if (m - target_mm).abs() <= rel_tol * target_mm {
                        return self.refine_accepted(
                            trial,
                            bc,
                            model,
                            (lambda, increments),
                            over,
                            history,
                            timings,
                            start,
                            cancel,
                        );
                    }
                    let k = states.partition_point(|x| x.0 < lambda);
                    states.insert(k, (lambda, m, trial));
                }
                Err(reason) => {
                    failures += 1;
                    failed_above = failed_above.min(lambda);
                    if failures > s.max_halvings {
                        if let Some(kept) = self.keep_largest_below(
                            &mut states,
                            bc,
                            model,
                            target_mm,
                            over,
                            &mut history,
                            &mut timings,
                            start,
                            cancel,
                        )? {
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
            lambda = next_factor(&states, target_mm, lambda, first_lambda, failed_above);
        }
    }

    /// The calibrated solve could not reach its target: keep the converged probe with the
    /// largest mean displacement (the states are below the collapse), refined to the settings'
    /// tolerance, when it moves at least `MIN_REACHED_FRACTION` of the target. The work already
    /// done is kept rather than discarded; the caller records it as below its target.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn keep_largest_below(
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
            .filter(|(_, x)| {
                x.0 > 0.0 && x.1 >= MIN_REACHED_FRACTION * target_mm && x.1 <= MAX_REACHED_FRACTION * target_mm
            })
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
}

/// The error of a calibrated solve that spent its iteration budget (or its probes), naming the
/// converged state nearest the target.
fn gave_up(
    states: &[(f64, f64, Vec<Vector3<f64>>)],
    target_mm: f64,
    budget: usize,
    history: Vec<IterationRecord>,
) -> FemError {
    let closest =
        states.iter().skip(1).map(|x| x.1).min_by(|a, b| (a - target_mm).abs().total_cmp(&(b - target_mm).abs()));
    FemError::NotConverged {
        reason: format!(
            "gave up after {budget} Newton iterations without reaching a mean displacement of {target_mm:.2} mm ({}; iteration budget)",
            closest.map(|c| format!("closest {c:.2} mm")).unwrap_or_else(|| "no load step converged".into())
        ),
        history,
    }
}

/// The next load factor to probe: the softening model fitted to the converged state nearest the
/// target, kept inside the bracket of states below and above it (else the secant between them),
/// at most twice the largest factor below when none is above, and halfway below a factor that
/// failed.
fn next_factor(
    states: &[(f64, f64, Vec<Vector3<f64>>)],
    target_mm: f64,
    lambda: f64,
    first_lambda: f64,
    failed_above: f64,
) -> f64 {
    let below = states.iter().filter(|x| x.1 < target_mm).max_by(|a, b| a.0.total_cmp(&b.0));
    let above = states.iter().filter(|x| x.1 > target_mm).min_by(|a, b| a.0.total_cmp(&b.0));
    let nearest =
        states.iter().filter(|x| x.0 > 0.0).min_by(|a, b| (a.1 - target_mm).abs().total_cmp(&(b.1 - target_mm).abs()));
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
    if next >= failed_above {
        let lo = states.iter().filter(|x| x.0 < failed_above).map(|x| x.0).fold(0.0, f64::max);
        next = 0.5 * (lo + failed_above);
    }
    if !(next > 0.0 && next.is_finite()) {
        next = 0.5 * lambda;
    }
    next
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
