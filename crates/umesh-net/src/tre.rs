//! Target registration error at virtual markers.

use nalgebra::Vector3;
use umesh_core::grid::ImmersedGrid;
use umesh_core::phantom::SplitMix64;

/// `count` marker points inside the organ (in fully inside cells), fixed by `seed`.
pub fn markers(grid: &ImmersedGrid, count: usize, seed: u64) -> Vec<Vector3<f64>> {
    let inside: Vec<usize> = (0..grid.cells.len()).filter(|&c| grid.cells[c].kind == umesh_core::grid::CellKind::Inside).collect();
    let cells = if inside.is_empty() { (0..grid.cells.len()).collect() } else { inside };
    let mut rng = SplitMix64(seed);
    (0..count)
        .map(|_| {
            let c = cells[(rng.next_u64() % cells.len() as u64) as usize];
            let [i, j, k] = grid.cells[c].ijk;
            let off = Vector3::new(i as f64 + rng.next_f64(), j as f64 + rng.next_f64(), k as f64 + rng.next_f64());
            grid.origin_mm + off * grid.cell_size_mm
        })
        .collect()
}

/// Displacement at a world point from a dense [3, X, Y, Z] field, through the grid embedding.
pub fn displacement_at(grid: &ImmersedGrid, field: &[f32], p: &Vector3<f64>) -> Vector3<f64> {
    let [x, y, z] = grid.padded_shape();
    let cells = x * y * z;
    let Some(e) = grid.embed(p) else { return Vector3::zeros() };
    let mut d = Vector3::zeros();
    for (n, w) in e.nodes.iter().zip(e.weights) {
        let idx = grid.dense_index(*n as usize);
        for c in 0..3 {
            d[c] += w * field[c * cells + idx] as f64;
        }
    }
    d
}

/// Per-marker errors |predicted - true| (mm) and true displacements |true| (mm).
pub fn marker_errors(grid: &ImmersedGrid, markers: &[Vector3<f64>], predicted: &[f32], truth: &[f32]) -> (Vec<f64>, Vec<f64>) {
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
