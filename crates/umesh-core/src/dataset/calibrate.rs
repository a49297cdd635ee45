//! One sample: its force pattern, the load calibration to the target displacement (mean over
//! the free nodes) and the SVK continuation, or the converged state nearest an unreachable target.

use super::config::{CALIBRATION_TOLERANCE, DatasetConfig, FIRST_LOAD_FACTOR};
use super::context::DatasetContext;
use super::error::{DatasetError, invalid};
use crate::fem::BoundaryConditions;
use crate::fem::solver::{FeSolver, FemError, MeanSolve, SolveMethod, SolverSettings};
use crate::loads::{self, LoadCalibration, LoadFamily, PointForce};
use crate::progress::{Cancel, Progress};
use crate::rng::SplitMix64;
use nalgebra::Vector3;
use std::path::Path;
use std::time::Instant;

/// Why a sample was rejected.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Rejection {
    NotConverged = 1,
    Inverted = 2,
    Failed = 3,
}

#[derive(Clone, Debug)]
pub struct SampleResult {
    pub index: usize,
    pub forces: Vec<PointForce>,
    /// The mean nodal displacement the forces were calibrated for (mm).
    pub target_mm: f64,
    /// The target drawn, when the strain limit lowered it to `target_mm`.
    pub drawn_target_mm: Option<f64>,
    pub displacement_mm: Option<Vec<Vector3<f64>>>,
    /// The simulated camera view of the deformed organ (accepted samples).
    pub observed_mm: Vec<[f32; 3]>,
    pub rejection: Option<(Rejection, String)>,
    pub newton_iterations: usize,
    pub solve_ms: f64,
}

impl SampleResult {
    /// Maximum and mean displacement norm (mm); the mean over the nodes the calibration uses.
    pub(super) fn max_mean(&self, ctx: &DatasetContext, config: &DatasetConfig) -> (f64, f64) {
        match &self.displacement_mm {
            Some(u) => {
                let max = u.iter().map(|v| v.norm()).fold(0.0, f64::max);
                (max, config.forces.mean_over.mean_mm(u, &ctx.fixed))
            }
            None => (0.0, 0.0),
        }
    }
}

/// A sample's forces as solved, its target, and the outcome.
#[derive(Clone, Debug)]
pub struct SolvedLoad {
    pub forces: Vec<PointForce>,
    pub target_mm: f64,
    /// The target drawn, when the strain limit (`ForceSettings::max_strain`) lowered it.
    pub drawn_target_mm: Option<f64>,
    /// The factor applied to the linearly calibrated forces (1 for `energy-scale`).
    pub load_factor: f64,
    pub solution: Result<crate::fem::solver::Solution, (Rejection, String)>,
}

impl DatasetContext {
    /// Solve the load of sample `index` (scaled by `load_scale`) on the SVK model. With
    /// `mean-displacement` calibration the forces are first scaled so that the linear mean
    /// nodal displacement is the target, then the load factor that gives the target on the
    /// hyperelastic model (within `CALIBRATION_TOLERANCE`) is found by continuation from
    /// `first_lambda`: the two responses differ (SVK softens under the probes' compression,
    /// by a factor 1.1 on a real liver and up to 3 on the phantom).
    pub fn solve_sample(
        &self,
        solver: &mut FeSolver,
        config: &DatasetConfig,
        index: usize,
        load_scale: f64,
        first_lambda: f64,
        cancel: &Cancel,
    ) -> SolvedLoad {
        if let Err(e) = solver.set_material(self.sample_material(config, index)) {
            let (forces, target_mm) = self.sample_forces(config, index);
            return SolvedLoad {
                forces,
                target_mm,
                drawn_target_mm: None,
                load_factor: 1.0,
                solution: Err((Rejection::Failed, e.to_string())),
            };
        }
        let (forces, target_mm, drawn_target_mm) = match self.calibrated_forces(solver, config, index, load_scale) {
            Ok(x) => x,
            Err(e) => {
                let (forces, _) = self.sample_forces(config, index);
                let target_mm = config.forces.target_displacement_mm * load_scale;
                let solution = Err((Rejection::Failed, format!("load calibration: {e}")));
                return SolvedLoad { forces, target_mm, drawn_target_mm: None, load_factor: 1.0, solution };
            }
        };
        let solved = self.solve_calibrated(
            solver,
            config,
            forces,
            target_mm,
            self.sample_family(config, index),
            first_lambda,
            cancel,
        );
        SolvedLoad { drawn_target_mm, ..solved }
    }

    /// Solve calibrated forces (`calibrate_forces`) on the SVK model: the load factor that
    /// gives `target_mm` found by continuation from `first_lambda`; the forces applied as
    /// `family`'s (`apply_load`).
    #[allow(clippy::too_many_arguments)]
    pub fn solve_calibrated(
        &self,
        solver: &mut FeSolver,
        config: &DatasetConfig,
        mut forces: Vec<PointForce>,
        target_mm: f64,
        family: LoadFamily,
        first_lambda: f64,
        cancel: &Cancel,
    ) -> SolvedLoad {
        let classify = |e: FemError| match e {
            FemError::NotConverged { reason, .. } if reason.contains("invert") => (Rejection::Inverted, reason),
            FemError::NotConverged { reason, .. } => (Rejection::NotConverged, reason),
            other => (Rejection::Failed, other.to_string()),
        };
        let mut bc = BoundaryConditions::new(self.grid.node_count());
        bc.fixed = self.fixed.clone();
        if let Err(e) = self.apply_load(&mut bc, config, &forces, family) {
            return SolvedLoad {
                forces,
                target_mm,
                drawn_target_mm: None,
                load_factor: 1.0,
                solution: Err((Rejection::Failed, e.into())),
            };
        }
        if config.forces.calibration == LoadCalibration::EnergyScale {
            let solution = solver.solve(&bc, SolveMethod::Newton, &Progress::none(), cancel).map_err(classify);
            return SolvedLoad { forces, target_mm, drawn_target_mm: None, load_factor: 1.0, solution };
        }
        let over = config.forces.mean_over;
        match solver.solve_to_mean_displacement(&bc, target_mm, CALIBRATION_TOLERANCE, first_lambda, over, cancel) {
            // A state kept below an unreachable target shows in the manifest as achieved / target.
            Ok(MeanSolve { solution, lambda, .. }) => {
                let _ = loads::scale_forces(&mut forces, 1.0, lambda);
                SolvedLoad { forces, target_mm, drawn_target_mm: None, load_factor: lambda, solution: Ok(solution) }
            }
            Err(e) => SolvedLoad {
                forces,
                target_mm,
                drawn_target_mm: None,
                load_factor: first_lambda,
                solution: Err(classify(e)),
            },
        }
    }

    /// `solve_sample` with the first load factor from the collapse scale `softening_mm`.
    pub fn solve_sample_softening(
        &self,
        solver: &mut FeSolver,
        config: &DatasetConfig,
        index: usize,
        load_scale: f64,
        softening_mm: f64,
        cancel: &Cancel,
    ) -> SolvedLoad {
        let target = self.sample_forces(config, index).1 * load_scale;
        self.solve_sample(solver, config, index, load_scale, first_load_factor(target, softening_mm), cancel)
    }

    /// How much softer than linear the organ responds at the dataset's target: the collapse
    /// scale D (mm) of `fem::solver::softening_factor`, the lower quartile over eight reference
    /// patterns (not samples of the dataset). Each sample's first load factor is then
    /// 1 / (1 + target / D), so that most land within the tolerance at the first solve.
    /// Infinite for `energy-scale` or a response no softer than linear.
    pub fn reference_softening_mm(&self, config: &DatasetConfig, cancel: &Cancel) -> Result<f64, DatasetError> {
        if config.forces.calibration == LoadCalibration::EnergyScale {
            return Ok(f64::INFINITY);
        }
        use rayon::prelude::*;
        let settings = SolverSettings { max_total_iterations: Some(80), max_halvings: 8, ..config.solver.sequential() };
        let mut reference = config.clone();
        reference.forces.target_spread = 0.0;
        // Patterns differ a lot in how much they soften (on the phantom D spans 4-15 mm), so
        // the median needs several; they run in parallel, each solve single-threaded.
        let results: Vec<Result<Option<f64>, crate::fem::solver::FemError>> = (0..REFERENCE_PATTERNS)
            .into_par_iter()
            .map(|k| {
                let mut solver = FeSolver::new(&self.grid, config.material, &self.fixed, settings.clone())?;
                let r = self.solve_sample(&mut solver, &reference, REFERENCE_INDEX + k, 1.0, FIRST_LOAD_FACTOR, cancel);
                let mean = |sol: &crate::fem::solver::Solution| {
                    config.forces.mean_over.mean_mm(&sol.displacement_mm, &self.fixed)
                };
                Ok(r.solution
                    .ok()
                    .map(|sol| crate::fem::solver::softening_scale_mm(r.target_mm, r.load_factor, mean(&sol))))
            })
            .collect();
        cancel.check()?;
        let mut scales = Vec::new();
        for r in results {
            if let Some(d) = r.map_err(|e| invalid(Path::new("."), e.to_string()))? {
                scales.push(d);
            }
        }
        scales.sort_by(f64::total_cmp);
        // The lower quartile, not the median: a first probe that overshoots heads for a
        // collapsed state and is abandoned, one that undershoots costs a cheap second probe.
        // No reference converged: assume strong softening (the continuation corrects it).
        Ok(scales.get(scales.len() / 4).copied().unwrap_or(config.forces.target_displacement_mm))
    }
}

/// The first load factor for a target under a collapse scale D (see `reference_softening_mm`).
pub fn first_load_factor(target_mm: f64, softening_mm: f64) -> f64 {
    if softening_mm.is_finite() && softening_mm > 0.0 { 1.0 / (1.0 + target_mm / softening_mm) } else { 1.0 }
}

/// Sample indices of the reference patterns (far beyond any dataset's samples).
pub(super) const REFERENCE_INDEX: usize = 1 << 40;
/// How many reference patterns set the collapse scale.
pub(super) const REFERENCE_PATTERNS: usize = 8;

/// Solve one sample with a solver built for the context's fixed nodes; `softening_mm` from
/// `DatasetContext::reference_softening_mm`.
pub fn generate_sample(
    ctx: &DatasetContext,
    solver: &mut FeSolver,
    config: &DatasetConfig,
    index: usize,
    softening_mm: f64,
    cancel: &Cancel,
) -> Result<SampleResult, DatasetError> {
    let t = Instant::now();
    let r = ctx.solve_sample_softening(solver, config, index, 1.0, softening_mm, cancel);
    cancel.check()?;
    let (forces, target_mm, drawn_target_mm) = (r.forces, r.target_mm, r.drawn_target_mm);
    // What the camera sees of this deformation: decided on the deformed shape, with its own
    // random stream so that the loads do not depend on the view settings.
    let solution = r.solution.and_then(|sol| {
        let deformed = loads::deform_mesh(&ctx.grid, &ctx.surface, &sol.displacement_mm);
        let mut rng =
            SplitMix64(config.seed ^ (index as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0x0B5E_4F1E_77E0_0001);
        match crate::observation::simulated_view(&deformed, &ctx.visible.camera, &config.view, &mut rng) {
            Ok(v) if v.len() >= 10 => Ok((sol, v)),
            Ok(v) => Err((Rejection::Failed, format!("the simulated camera view holds {} points", v.len()))),
            Err(e) => Err((Rejection::Failed, format!("simulated camera view: {e}"))),
        }
    });
    let solve_ms = t.elapsed().as_secs_f64() * 1e3;
    Ok(match solution {
        Ok((sol, view)) => SampleResult {
            index,
            forces,
            target_mm,
            drawn_target_mm,
            newton_iterations: sol.iterations,
            displacement_mm: Some(sol.displacement_mm),
            observed_mm: view.iter().map(|p| [p.x as f32, p.y as f32, p.z as f32]).collect(),
            rejection: None,
            solve_ms,
        },
        Err(r) => SampleResult {
            index,
            forces,
            target_mm,
            drawn_target_mm,
            displacement_mm: None,
            observed_mm: Vec::new(),
            rejection: Some(r),
            newton_iterations: 0,
            solve_ms,
        },
    })
}
