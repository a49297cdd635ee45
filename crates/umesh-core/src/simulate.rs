//! One static simulation on a grid: boundary conditions from regions, point forces, solve.

use crate::fem::solver::{FeSolver, FemError, Solution, SolveMethod, SolverSettings};
use crate::fem::{BoundaryConditions, FixedRegion, MaterialParams};
use crate::grid::ImmersedGrid;
use crate::loads::{ForceSettings, PointForce, apply_forces};
use crate::mesh::TriMesh;
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
        bc.fix_region(grid, region, mask.as_ref()).map_err(|e| SimulateError::Boundary(e.into()))?;
    }
    if bc.fixed_count() == 0 {
        return Err(SimulateError::Boundary("no node is fixed by the given regions".into()));
    }
    apply_forces(grid, &mut bc, &settings.forces).map_err(|e| SimulateError::Boundary(e.into()))?;
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

/// `probes` random forces on the visible part of `surface`, loaded as dataset samples are: each
/// spread over the default probe contact radius, then scaled so that one linear solve moves the
/// free nodes by `target_mm` on average. Returns the forces (already spread) and the factor the
/// linear solve asked for. (Unscaled, a few concentrated forces moved the phantom by ten times
/// the asked displacement and inverted its boundary cells.)
pub fn calibrated_random_forces(
    grid: &ImmersedGrid,
    surface: &TriMesh,
    bc: &BoundaryConditions,
    settings: &SimulationSettings,
    probes: usize,
    target_mm: f64,
    seed: u64,
    cancel: &Cancel,
) -> Result<(Vec<PointForce>, f64), SimulateError> {
    if !(target_mm > 0.0 && target_mm <= 1000.0) {
        return Err(SimulateError::Boundary(format!("target displacement {target_mm} mm: must lie in (0, 1000]")));
    }
    let force_settings = ForceSettings { probes, target_displacement_mm: target_mm, ..ForceSettings::default() };
    let drawn = crate::loads::visible_random_forces(
        surface,
        grid,
        &settings.material,
        &force_settings,
        &Default::default(),
        seed,
    )
    .map_err(|e| SimulateError::Boundary(e.into()))?;
    let mut forces = crate::loads::spread_forces(surface, &drawn, force_settings.patch_radius_mm);
    let mut trial = bc.clone();
    apply_forces(grid, &mut trial, &forces).map_err(|e| SimulateError::Boundary(e.into()))?;
    let linear = SimulationSettings { method: SolveMethod::Linear, ..settings.clone() };
    let lin = solve_bc(grid, &trial, &linear, &Progress::none(), cancel)?;
    let mean = force_settings.mean_over.mean_mm(&lin.displacement_mm, &bc.fixed);
    let scale =
        crate::loads::scale_forces(&mut forces, mean, target_mm).map_err(|e| SimulateError::Boundary(e.into()))?;
    Ok((forces, scale))
}
