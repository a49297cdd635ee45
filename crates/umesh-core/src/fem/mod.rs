//! Finite elements on the immersed-boundary grid: materials, the hexahedral element,
//! parallel assembly into a fixed sparse pattern, and the nonlinear / linear /
//! co-rotational static solvers.
//!
//! Units: lengths in mm, forces in N, so stresses and moduli are N/mm^2 (MPa) inside the
//! solver; public settings take moduli in Pa (`young_pa`).

pub mod assembly;
pub mod bc;
pub mod element;
pub mod material;
pub mod problem_io;
pub mod solver;

pub use bc::{BoundaryConditions, FixedRegion};
pub use material::{HyperelasticMaterial, Material, MaterialKind, MaterialParams};
pub use solver::{FemError, IterationRecord, Solution, SolveMethod, SolverSettings, solve};
