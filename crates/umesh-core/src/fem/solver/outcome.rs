//! What a solve returns: its solution and iteration records, or its error.

use nalgebra::Vector3;

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
