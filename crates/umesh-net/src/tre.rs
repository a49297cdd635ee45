//! Target registration error at virtual markers.

use nalgebra::Vector3;
use umesh_core::grid::ImmersedGrid;
use umesh_core::rng::SplitMix64;

/// `count` marker points inside the organ (in fully inside cells), fixed by `seed`.
pub fn markers(grid: &ImmersedGrid, count: usize, seed: u64) -> Vec<Vector3<f64>> {
    umesh_core::register::inside_markers(grid, count, &mut SplitMix64(seed))
}

/// Displacement at a world point from a dense [3, X, Y, Z] field, through the grid embedding.
pub fn displacement_at(grid: &ImmersedGrid, field: &[f32], p: &Vector3<f64>) -> Vector3<f64> {
    grid.embed(p).map(|e| umesh_core::register::displacement_at(grid, field, &e)).unwrap_or_else(Vector3::zeros)
}

/// Per-marker errors |predicted - true| (mm) and true displacements |true| (mm).
pub fn marker_errors(
    grid: &ImmersedGrid,
    markers: &[Vector3<f64>],
    predicted: &[f32],
    truth: &[f32],
) -> (Vec<f64>, Vec<f64>) {
    markers
        .iter()
        .map(|m| {
            let t = displacement_at(grid, truth, m);
            ((displacement_at(grid, predicted, m) - t).norm(), t.norm())
        })
        .unzip()
}

/// mean, standard deviation, max.
pub fn summary(v: &[f64]) -> (f64, f64, f64) {
    if v.is_empty() {
        return (0.0, 0.0, 0.0);
    }
    let mean = v.iter().sum::<f64>() / v.len() as f64;
    let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / v.len() as f64;
    (mean, var.sqrt(), v.iter().copied().fold(0.0, f64::max))
}
