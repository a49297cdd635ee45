//! One static simulation on a grid: boundary conditions from regions, point forces, solve.

use crate::fem::solver::{FeSolver, FemError, Solution, SolveMethod, SolverSettings};
use crate::fem::{BoundaryConditions, FixedRegion, MaterialParams};
use crate::grid::ImmersedGrid;
use crate::loads::{PointForce, apply_forces};
use crate::progress::{Cancel, Progress};
use crate::volume::Volume;

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SimulationSettings {
    pub material: MaterialParams,
    pub solver: SolverSettings,
    pub method: SolveMethod,
    pub fixed: Vec<FixedRegion>,
    pub forces: Vec<PointForce>,
}

#[derive(Debug, thiserror::Error)]
pub enum SimulateError {
    #[error("boundary conditions: {0}")]
    Boundary(String),
    #[error(transparent)]
    Fem(#[from] FemError),
}

#[derive(Debug)]
pub struct SimulationOutput {
    pub bc: BoundaryConditions,
    pub solution: Solution,
}

/// Build the boundary conditions of `settings` on `grid` (labels are looked up in `labels`).
pub fn boundary_conditions(
    grid: &ImmersedGrid,
    labels: Option<&Volume>,
    settings: &SimulationSettings,
) -> Result<BoundaryConditions, SimulateError> {
    let mut bc = BoundaryConditions::new(grid.node_count());
    for region in &settings.fixed {
        let mask = match region {
            FixedRegion::Label { label, .. } => labels.map(|v| v.mask(&[*label])),
            _ => None,
        };
        if let (FixedRegion::Label { label, .. }, Some(m)) = (region, &mask)
            && m.count() == 0
        {
            return Err(SimulateError::Boundary(format!("the fixing label {label} has no voxel")));
        }
        bc.fix_region(grid, region, mask.as_ref()).map_err(SimulateError::Boundary)?;
    }
    if bc.fixed_count() == 0 {
        return Err(SimulateError::Boundary("no node is fixed by the given regions".into()));
    }
    apply_forces(grid, &mut bc, &settings.forces).map_err(SimulateError::Boundary)?;
    Ok(bc)
}

pub fn run_simulate(
    grid: &ImmersedGrid,
    labels: Option<&Volume>,
    settings: &SimulationSettings,
    progress: &Progress,
    cancel: &Cancel,
) -> Result<SimulationOutput, SimulateError> {
    let bc = boundary_conditions(grid, labels, settings)?;
    let solution = solve_bc(grid, &bc, settings, progress, cancel)?;
    Ok(SimulationOutput { bc, solution })
}

pub fn solve_bc(
    grid: &ImmersedGrid,
    bc: &BoundaryConditions,
    settings: &SimulationSettings,
    progress: &Progress,
    cancel: &Cancel,
) -> Result<Solution, SimulateError> {
    let mut constrained = bc.fixed.clone();
    for &(n, _) in &bc.prescribed_mm {
        if n < constrained.len() {
            constrained[n] = true;
        }
    }
    let mut solver = FeSolver::new(grid, settings.material, &constrained, settings.solver.clone())?;
    Ok(solver.solve(bc, settings.method, progress, cancel)?)
}
