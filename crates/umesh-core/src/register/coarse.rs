//! The organ on cells several times as large (`ImmersedGrid::coarsened`), for the FE fit of a
//! doubted frame (`correction::CoarseFit`): on the organ's own grid that fit costs a few
//! hundred milliseconds (forty conjugate-gradient iterations of triangular solves over every
//! node); cells twice as large have about a sixth of the nodes.

use crate::grid::{Embedding, ImmersedGrid, interpolate_nodes};
use nalgebra::Vector3;

/// The coarsening factors a doubted frame's fit may use (1: the organ's own grid).
pub const MAX_COARSENING: usize = 4;

/// The organ on coarse cells, its held nodes, and the maps between the two grids.
#[derive(Debug)]
pub struct CoarseModel {
    pub grid: ImmersedGrid,
    pub fixed: Vec<bool>,
    /// Each coarse node in the organ's grid: a fine field restricted to the coarse nodes.
    coarse_in_fine: Vec<Embedding>,
    /// Each node of the organ's grid in the coarse grid: a coarse change prolonged.
    pub fine_in_coarse: Vec<Embedding>,
}

impl CoarseModel {
    /// The organ of `fine` (its held nodes `fine_fixed`) on cells `factor` times as large.
    pub fn new(fine: &ImmersedGrid, fine_fixed: &[bool], factor: usize) -> Result<Self, crate::Invalid> {
        debug_assert!((2..=MAX_COARSENING).contains(&factor));
        let grid = fine.coarsened(factor);
        // A coarse node is held where the organ's grid holds the node at its place. On the CT
        // liver, holding every coarse node within a fine cell of a held node instead (a held
        // region grown by half a coarse cell) left the doubted frames of the benchmark's draws
        // at 1.15-2.61 mm against 0.71-1.55. A held region thinner than the coarse lattice's
        // spacing may share no node with it: then the nearest within `factor - 1` fine cells.
        let held_within = |reach: i64| -> Vec<bool> {
            grid.node_ijk
                .iter()
                .map(|ijk| {
                    let centre = ijk.map(|v| (v * factor) as i64);
                    let mut held = false;
                    for dk in -reach..=reach {
                        for dj in -reach..=reach {
                            for di in -reach..=reach {
                                let q = [centre[0] + di, centre[1] + dj, centre[2] + dk];
                                if q.iter().all(|&v| v >= 0)
                                    && let Some(n) = fine.node_at(q.map(|v| v as usize))
                                {
                                    held |= fine_fixed[n];
                                }
                            }
                        }
                    }
                    held
                })
                .collect()
        };
        let fixed = (0..factor as i64)
            .map(held_within)
            .find(|f| f.iter().any(|&h| h))
            .ok_or_else(|| {
                crate::Invalid(format!(
                    "the organ's grid coarsened {factor} times holds no node: its held region is farther than a coarse cell from every coarse node"
                ))
            })?;
        let embed = |g: &ImmersedGrid, p: &Vector3<f64>| {
            g.embed(p).ok_or_else(|| crate::Invalid(format!("point {p:?} lies off the coarse grid")))
        };
        let coarse_in_fine = grid.node_positions().iter().map(|p| embed(fine, p)).collect::<Result<_, _>>()?;
        let fine_in_coarse = fine.node_positions().iter().map(|p| embed(&grid, p)).collect::<Result<_, _>>()?;
        Ok(Self { grid, fixed, coarse_in_fine, fine_in_coarse })
    }

    /// A displacement of the organ's grid (per node) at the coarse nodes; zero where held.
    pub fn restrict(&self, fine: &[Vector3<f64>]) -> Vec<Vector3<f64>> {
        self.coarse_in_fine
            .iter()
            .zip(&self.fixed)
            .map(|(e, &held)| if held { Vector3::zeros() } else { interpolate_nodes(e, fine) })
            .collect()
    }
}
