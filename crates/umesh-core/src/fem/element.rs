//! The 8-node hexahedron of the regular grid. Every cell is the same cube, so shape
//! function gradients depend only on the reference point: they are tabulated once per
//! distinct quadrature location (2x2x2 Gauss points and sub-cell centres), not per point.

use crate::grid::{HEX_CORNERS, ImmersedGrid};
use nalgebra::{Matrix3, SMatrix, Vector3};

/// Physical gradients of the 8 shape functions (1/mm) at one reference point.
pub type Gradients = [Vector3<f64>; 8];

/// Shape-function gradients of a cube of edge `h_mm` at reference coordinates `xi`.
pub fn gradients(xi: [f64; 3], h_mm: f64) -> Gradients {
    std::array::from_fn(|a| {
        let s = HEX_CORNERS[a].map(|c| if c == 1 { 1.0 } else { -1.0 });
        let half = |d: usize| 0.5 * (1.0 + s[d] * xi[d]);
        Vector3::new(s[0] * half(1) * half(2), s[1] * half(0) * half(2), s[2] * half(0) * half(1)) / h_mm
    })
}

/// Quadrature of a grid with its gradient table.
#[derive(Clone, Debug)]
pub struct ElementQuadrature {
    pub table: Vec<Gradients>,
    /// Per quadrature point: index into `table`.
    pub qp_table: Vec<u32>,
    pub qp_weight_mm3: Vec<f64>,
    pub qp_offsets: Vec<usize>,
}

impl ElementQuadrature {
    pub fn new(grid: &ImmersedGrid) -> Self {
        let mut keys: Vec<[u64; 3]> = Vec::new();
        let mut table = Vec::new();
        let mut qp_table = Vec::with_capacity(grid.quadrature.len());
        let mut lookup = std::collections::HashMap::new();
        for q in &grid.quadrature {
            let key = q.xi.map(f64::to_bits);
            let id = *lookup.entry(key).or_insert_with(|| {
                keys.push(key);
                table.push(gradients(q.xi, grid.cell_size_mm));
                (table.len() - 1) as u32
            });
            qp_table.push(id);
        }
        Self {
            table,
            qp_table,
            qp_weight_mm3: grid.quadrature.iter().map(|q| q.weight_mm3).collect(),
            qp_offsets: grid.qp_offsets.clone(),
        }
    }
}

/// Deformation gradient F = I + sum_a u_a (x) grad N_a.
#[inline]
pub fn deformation_gradient(u: &[Vector3<f64>; 8], g: &Gradients) -> Matrix3<f64> {
    let mut f = Matrix3::identity();
    for a in 0..8 {
        f += u[a] * g[a].transpose();
    }
    f
}

/// The `q`-quantile (0-1) over the organ's volume of the compression at each cell's centre
/// (minus the smallest principal small strain, 0 where the cell is not compressed): how hard a
/// displacement field squeezes the organ, the strain SVK collapses under (it stiffens in
/// tension). Cells weigh by their inside volume.
pub fn compression_quantile(grid: &ImmersedGrid, u_mm: &[Vector3<f64>], q: f64) -> f64 {
    let g = gradients([0.0; 3], grid.cell_size_mm);
    let mut strains: Vec<(f64, f64)> = grid
        .cells
        .iter()
        .filter(|c| c.volume_fraction > 0.0)
        .map(|c| {
            let ue: [Vector3<f64>; 8] = c.nodes.map(|n| u_mm[n as usize]);
            let h = deformation_gradient(&ue, &g) - Matrix3::identity();
            let eps = (h + h.transpose()) * 0.5;
            (-eps.symmetric_eigenvalues().min().min(0.0), c.volume_fraction)
        })
        .collect();
    strains.sort_by(|a, b| a.0.total_cmp(&b.0));
    let total: f64 = strains.iter().map(|s| s.1).sum();
    let mut seen = 0.0;
    for (e, w) in &strains {
        seen += w;
        if seen >= q.clamp(0.0, 1.0) * total {
            return *e;
        }
    }
    strains.last().map_or(0.0, |s| s.0)
}

/// Small-strain stiffness (24x24, dofs ordered node-major) of a full cube with
/// Lame parameters (N/mm^2), integrated with 2x2x2 Gauss points.
pub fn linear_cube_stiffness(h_mm: f64, lambda: f64, mu: f64) -> SMatrix<f64, 24, 24> {
    let g = 1.0 / 3f64.sqrt();
    let w = h_mm.powi(3) / 8.0;
    let mut k = SMatrix::<f64, 24, 24>::zeros();
    for c in HEX_CORNERS {
        let gr = gradients(c.map(|v| if v == 1 { g } else { -g }), h_mm);
        for a in 0..8 {
            for b in 0..8 {
                for i in 0..3 {
                    for j in 0..3 {
                        // K_ai,bj = lambda ga_i gb_j + mu ga_j gb_i + mu d_ij (ga . gb)
                        let mut v = lambda * gr[a][i] * gr[b][j] + mu * gr[a][j] * gr[b][i];
                        if i == j {
                            v += mu * gr[a].dot(&gr[b]);
                        }
                        k[(3 * a + i, 3 * b + j)] += w * v;
                    }
                }
            }
        }
    }
    k
}
