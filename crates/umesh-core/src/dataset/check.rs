//! Running the pre-flight check: a small batch of the job's own samples solved in parallel,
//! the likely cause of a low acceptance, and the judgement before a long job.

use super::calibrate::{Rejection, SampleResult, generate_sample};
use super::config::CALIBRATION_TOLERANCE;
use super::config::DatasetConfig;
use super::context::DatasetContext;
use super::error::DatasetError;
use super::error::invalid;
use super::preflight::{Preflight, PreflightSettings};

use crate::fem::solver::FeSolver;
use crate::progress::{Cancel, Progress};
use std::collections::BTreeMap;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

/// A pre-flight check before a long dataset job (see `preflight`).
pub struct PreflightCheck<'a> {
    pub settings: PreflightSettings,
    /// Run the job even when the check refuses it.
    pub force: bool,
    /// Called with the check's figures before the job goes on or is refused.
    pub report: &'a (dyn Fn(&Preflight) + Sync),
}

impl PreflightCheck<'_> {
    /// Report the check's figures, then refuse the job when it would store too little (unless forced).
    pub fn judge(&self, p: Preflight) -> Result<Preflight, DatasetError> {
        (self.report)(&p);
        match p.refusal(&self.settings) {
            Some(message) if !self.force => Err(DatasetError::Refused { message, preflight: Box::new(p) }),
            _ => Ok(p),
        }
    }
}

/// The likely cause of a low acceptance, from the set-up and how the samples failed.
fn likely_cause(ctx: &DatasetContext, config: &DatasetConfig, results: &[SampleResult], fixed_fraction: f64) -> String {
    let visible = ctx.visible.fraction();
    let fixed_nodes = ctx.fixed.iter().filter(|&&f| f).count();
    let inverted = results.iter().filter(|r| matches!(r.rejection, Some((Rejection::Inverted, _)))).count();
    let failed = results.iter().filter(|r| matches!(r.rejection, Some((Rejection::Failed, _)))).count();
    if failed * 2 > results.len() {
        let why =
            results.iter().find_map(|r| r.rejection.as_ref().filter(|x| x.0 == Rejection::Failed).map(|x| x.1.clone()));
        return format!("the samples fail before solving ({})", why.unwrap_or_default());
    }
    if visible < 0.08 {
        return format!(
            "the camera sees {:.1} % of the organ surface, so every sample's {} probes press a small patch until elements invert; \
             choose a camera that sees more (--camera, --camera-from/--camera-to, --fov-deg) or lower --target-displacement-mm (now {} mm)",
            visible * 100.0,
            config.forces.probes,
            config.forces.target_displacement_mm
        );
    }
    if fixed_fraction > 0.6 {
        return format!(
            "the fixed region holds {:.0} % of the grid nodes, so the part that can move must strain hard to reach the target; \
             fix less (--fix-box, --fix-plane, --fix-label/--fix-distance-mm) or lower --target-displacement-mm (now {} mm)",
            fixed_fraction * 100.0,
            config.forces.target_displacement_mm
        );
    }
    if fixed_fraction < 0.01 {
        return format!(
            "the fixed region holds only {fixed_nodes} of {} grid nodes, so the organ swings about it and strains it until it inverts; \
             hold more (a larger --fix-box or --fix-distance-mm) or lower --target-displacement-mm (now {} mm)",
            ctx.grid.node_count(),
            config.forces.target_displacement_mm
        );
    }
    let reached: Vec<f64> =
        results.iter().filter(|r| r.rejection.is_none()).map(|r| r.max_mean(ctx, config).1).collect();
    let reached = if reached.is_empty() {
        "no sample converged".to_string()
    } else {
        format!("the accepted samples moved {:.1} mm on average", reached.iter().sum::<f64>() / reached.len() as f64)
    };
    // With the strain limit off, the first thing to say is that it exists.
    let limit = if config.forces.max_strain > 0.0 {
        String::new()
    } else {
        format!(", or limit the strain (--max-strain {}, the default)", crate::loads::DEFAULT_MAX_STRAIN)
    };
    format!(
        "the target mean displacement of {} mm (up to x{:.1}) is beyond what this organ, held as it is, takes without collapsing \
         ({inverted} inverted, {} not converged; {reached}); lower --target-displacement-mm or hold the organ elsewhere \
         (--fix-label, --fix-box, --fix-plane){limit}",
        config.forces.target_displacement_mm,
        1.0 + config.forces.target_spread,
        results.iter().filter(|r| matches!(r.rejection, Some((Rejection::NotConverged, _)))).count()
    )
}

/// Solve `settings.samples` of the job's samples in parallel (one single-threaded solver per
/// worker, as generation runs them) with the collapse scale `softening_mm` the job will use.
pub(super) fn preflight_with(
    ctx: &DatasetContext,
    config: &DatasetConfig,
    settings: &PreflightSettings,
    softening_mm: f64,
    started: Instant,
    progress: &Progress,
    cancel: &Cancel,
) -> Result<Preflight, DatasetError> {
    settings.validate().map_err(|r| invalid(&std::path::PathBuf::from("pre-flight"), r))?;
    let n = settings.samples.min(config.samples).max(1);
    // Spread over the job's indices: the samples it will compute, not a separate family.
    let indices: Vec<usize> = (0..n).map(|k| k * config.samples / n).collect();
    let next = AtomicUsize::new(0);
    let done = AtomicUsize::new(0);
    let out: Mutex<Vec<Result<SampleResult, DatasetError>>> = Mutex::new(Vec::new());
    progress.report(0, n as u64, "pre-flight check");
    let threads = rayon::current_num_threads().max(1);
    std::thread::scope(|scope| {
        for _ in 0..threads.min(n) {
            scope.spawn(|| {
                let push = |r| {
                    if let Ok(mut o) = out.lock() {
                        o.push(r);
                    }
                };
                let mut solver = match FeSolver::new(&ctx.grid, config.material, &ctx.fixed, config.solver.sequential())
                {
                    Ok(s) => s,
                    Err(e) => return push(Err(invalid(&std::path::PathBuf::from("pre-flight"), e.to_string()))),
                };
                loop {
                    let q = next.fetch_add(1, Ordering::Relaxed);
                    if q >= n || cancel.is_cancelled() {
                        break;
                    }
                    let r = generate_sample(ctx, &mut solver, config, indices[q], softening_mm, cancel);
                    let failed = r.is_err();
                    push(r);
                    if failed {
                        break;
                    }
                    let d = done.fetch_add(1, Ordering::Relaxed) + 1;
                    progress.report(d as u64, n as u64, "pre-flight check");
                }
            });
        }
    });
    cancel.check()?;
    let mut results: Vec<SampleResult> = out
        .into_inner()
        .map_err(|_| invalid(&std::path::PathBuf::from("pre-flight"), "a worker panicked"))?
        .into_iter()
        .collect::<Result<_, _>>()?;
    results.sort_by_key(|r| r.index);
    let accepted: Vec<&SampleResult> = results.iter().filter(|r| r.rejection.is_none()).collect();
    let ratios: Vec<f64> =
        accepted.iter().filter(|r| r.target_mm > 0.0).map(|r| r.max_mean(ctx, config).1 / r.target_mm).collect();
    let below_target = ratios.iter().filter(|&&q| q < 1.0 - CALIBRATION_TOLERANCE).count();
    let mut limited: Vec<f64> =
        results.iter().filter_map(|r| Some(r.target_mm / r.drawn_target_mm.filter(|d| *d > 0.0)?)).collect();
    limited.sort_by(f64::total_cmp);
    let mut rejected = BTreeMap::new();
    for r in &results {
        if let Some((why, _)) = &r.rejection {
            *rejected.entry(format!("{why:?}").to_lowercase()).or_insert(0) += 1;
        }
    }
    let mut secs: Vec<f64> = results.iter().map(|r| r.solve_ms / 1e3).collect();
    secs.sort_by(f64::total_cmp);
    let mean_secs = secs.iter().sum::<f64>() / secs.len().max(1) as f64;
    let fixed_nodes = ctx.fixed.iter().filter(|&&f| f).count();
    let fixed_fraction = fixed_nodes as f64 / ctx.grid.node_count().max(1) as f64;
    let acceptance = accepted.len() as f64 / results.len().max(1) as f64;
    let mut p = Preflight {
        samples: results.len(),
        accepted: accepted.len(),
        below_target,
        strain_limited: limited.len(),
        strain_limited_factor: limited.get(limited.len() / 2).copied(),
        rejected,
        acceptance,
        achieved_over_target: (!ratios.is_empty()).then(|| ratios.iter().sum::<f64>() / ratios.len() as f64),
        sample_seconds: secs.get(secs.len() / 2).copied().unwrap_or(0.0),
        threads,
        projected_minutes: config.samples as f64 * mean_secs / threads as f64 / 60.0,
        seconds: started.elapsed().as_secs_f64(),
        visible_fraction: ctx.visible.fraction(),
        fixed_fraction,
        fixed_nodes,
        nodes: ctx.grid.node_count(),
        cause: None,
    };
    if acceptance < settings.min_acceptance || p.is_doomed(settings) {
        p.cause = Some(likely_cause(ctx, config, &results, fixed_fraction));
    }
    Ok(p)
}

impl DatasetContext {
    /// The pre-flight check on a prepared context: the load calibration (as generation finds
    /// it) and `settings.samples` of the job's samples, each solve single-threaded.
    pub fn preflight(
        &self,
        config: &DatasetConfig,
        settings: &PreflightSettings,
        progress: &Progress,
        cancel: &Cancel,
    ) -> Result<Preflight, DatasetError> {
        let started = Instant::now();
        let softening = self.reference_softening_mm(config, cancel)?;
        preflight_with(self, config, settings, softening, started, progress, cancel)
    }
}

/// The pre-flight check alone (the app shows it before it queues a job): the grid, the load
/// calibration and `settings.samples` of the job's samples.
pub fn run_preflight(
    seg: &crate::segmentation::Segmentation,
    config: &DatasetConfig,
    settings: &PreflightSettings,
    progress: &Progress,
    cancel: &Cancel,
) -> Result<Preflight, DatasetError> {
    DatasetContext::prepare(seg, config, cancel)?.preflight(config, settings, progress, cancel)
}
