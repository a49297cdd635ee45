//! Assembly of internal forces and the tangent stiffness into a sparse matrix whose
//! pattern (over the free degrees of freedom) is computed once per grid and boundary
//! conditions; each iteration only refills the values.

use super::element::{ElementQuadrature, deformation_gradient, linear_cube_stiffness};
use super::material::{HyperelasticMaterial, Material, MaterialKind};
use crate::grid::ImmersedGrid;
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};
use nalgebra::{Matrix3, SMatrix, Vector3};
use rayon::prelude::*;

pub const NONE: u32 = u32::MAX;
/// Cells whose 576 element-matrix entries each can be numbered in a u32 (the gather map).
pub const MAX_CELLS: usize = (u32::MAX / 576) as usize;
type Ke = SMatrix<f64, 24, 24>;

/// Free-dof numbering: constrained components get `NONE`.
#[derive(Clone, Debug)]
pub struct DofMap {
    pub free_of: Vec<u32>,
    pub n_free: usize,
}

impl DofMap {
    pub fn new(constrained: &[bool]) -> Self {
        let mut n_free = 0;
        let free_of = constrained
            .iter()
            .map(|&c| {
                if c {
                    NONE
                } else {
                    n_free += 1;
                    (n_free - 1) as u32
                }
            })
            .collect();
        Self { free_of, n_free }
    }
}

/// How elements produce forces and stiffness.
#[derive(Clone, Copy, Debug)]
pub enum ElementModel {
    /// Total Lagrangian hyperelasticity (SVK, Neo-Hookean, linear).
    Hyperelastic(Material),
    /// Co-rotational linear elasticity: the small-strain stiffness of each cell rotated by
    /// the rotation of its deformation gradient at the centre.
    Corotational,
}

/// Results of one assembly.
#[derive(Clone, Debug)]
pub struct Assembled {
    /// Internal force on every node (N).
    pub f_int: Vec<Vector3<f64>>,
    /// Smallest det F over the quadrature points (<= 0 means an inverted element).
    pub min_det_f: f64,
    /// Stored elastic energy (N mm), for the line search.
    pub energy: f64,
}

pub struct Assembler<'g> {
    pub grid: &'g ImmersedGrid,
    quad: ElementQuadrature,
    pub dofs: DofMap,
    symbolic: SymbolicSparseColMat<usize>,
    pub values: Vec<f64>,
    scatter: Vec<u32>,
    /// The scatter inverted: matrix entry m is the sum of the cell-matrix entries
    /// `gather_src[gather_ptr[m]..gather_ptr[m + 1]]` (cell * 576 + column-major index), in
    /// the order the sequential scatter adds them, so the entries are filled in parallel and
    /// bit for bit as before.
    gather_ptr: Vec<u32>,
    gather_src: Vec<u32>,
    /// Per-cell scale of the stabilising ersatz stiffness (alpha * (1 - volume fraction)).
    stab_scale: Vec<f64>,
    k_stab: Ke,
    /// Each cell's small-strain stiffness with its stabilisation (k_lin + k_stab * stab), built
    /// on first co-rotational use, as an index into the distinct ones: the grid's whole cells
    /// share one matrix, so a co-rotational product reads a few hundred matrices, not one per
    /// cell (the product is memory-bound).
    k_of: Vec<u32>,
    k_unique: Vec<Ke>,
    linear_material: Material,
    ke: Vec<Ke>,
    fe: Vec<SMatrix<f64, 24, 1>>,
    /// Each cell's rotation at the last co-rotational assembly.
    rot: Vec<Matrix3<f64>>,
}

impl std::fmt::Debug for Assembler<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Assembler").field("free_dofs", &self.dofs.n_free).field("nnz", &self.values.len()).finish()
    }
}

impl<'g> Assembler<'g> {
    /// Another small-strain material (a dataset draws one per sample): the stabilising
    /// stiffness follows it, the co-rotational cell stiffnesses are rebuilt on next use.
    pub fn set_linear_material(&mut self, linear_material: Material) {
        if (linear_material.lambda, linear_material.mu) != (self.linear_material.lambda, self.linear_material.mu) {
            self.k_stab = linear_cube_stiffness(self.grid.cell_size_mm, linear_material.lambda, linear_material.mu);
            self.k_of.clear();
            self.k_unique.clear();
            self.linear_material = linear_material;
        }
    }

    /// `constrained_dofs[3 n + c]` marks component c of node n as fixed or prescribed.
    /// `stabilization` is the relative stiffness of the fictitious (outside) part of boundary
    /// cells, as in the finite cell method; it removes spurious zero-energy modes of cells
    /// with few inside sub-cells.
    /// Panics with more than `MAX_CELLS` cells (`FeSolver::new` refuses such grids first).
    pub fn new(
        grid: &'g ImmersedGrid,
        constrained_dofs: &[bool],
        linear_material: Material,
        stabilization: f64,
    ) -> Self {
        assert!(grid.cells.len() <= MAX_CELLS, "{} cells: more than the assembler's {MAX_CELLS}", grid.cells.len());
        let quad = ElementQuadrature::new(grid);
        let dofs = DofMap::new(constrained_dofs);
        let n_nodes = grid.node_count();
        // Node adjacency through shared cells.
        let mut adj: Vec<Vec<u32>> = vec![Vec::new(); n_nodes];
        for c in &grid.cells {
            for &a in &c.nodes {
                adj[a as usize].extend_from_slice(&c.nodes);
            }
        }
        adj.par_iter_mut().for_each(|v| {
            v.sort_unstable();
            v.dedup();
        });
        let mut col_ptr = Vec::with_capacity(dofs.n_free + 1);
        let mut row_idx = Vec::new();
        col_ptr.push(0usize);
        for n in 0..n_nodes {
            for c in 0..3 {
                if dofs.free_of[3 * n + c] == NONE {
                    continue;
                }
                for &m in &adj[n] {
                    for d in 0..3 {
                        let r = dofs.free_of[3 * m as usize + d];
                        if r != NONE {
                            row_idx.push(r as usize);
                        }
                    }
                }
                col_ptr.push(row_idx.len());
            }
        }
        let scatter: Vec<u32> = grid
            .cells
            .par_iter()
            .flat_map_iter(|cell| {
                let g: [u32; 24] = std::array::from_fn(|r| {
                    let (a, i) = (r / 3, r % 3);
                    dofs.free_of[3 * cell.nodes[a] as usize + i]
                });
                let (col_ptr, row_idx) = (&col_ptr, &row_idx);
                (0..576).map(move |rc| {
                    let (r, c) = (rc / 24, rc % 24);
                    if g[r] == NONE || g[c] == NONE {
                        return NONE;
                    }
                    let col = g[c] as usize;
                    let rows = &row_idx[col_ptr[col]..col_ptr[col + 1]];
                    rows.binary_search(&(g[r] as usize)).map(|p| (col_ptr[col] + p) as u32).unwrap_or(NONE)
                })
            })
            .collect();
        let nnz = row_idx.len();
        let mut gather_ptr = vec![0u32; nnz + 1];
        for &m in scatter.iter().filter(|&&m| m != NONE) {
            gather_ptr[m as usize + 1] += 1;
        }
        for i in 0..nnz {
            gather_ptr[i + 1] += gather_ptr[i];
        }
        let mut next: Vec<u32> = gather_ptr[..nnz].to_vec();
        let mut gather_src = vec![0u32; gather_ptr[nnz] as usize];
        for (k, &m) in scatter.iter().enumerate() {
            if m != NONE {
                // nalgebra is column-major: element (r, col) of cell c sits at col * 24 + r.
                let (c, rc) = (k / 576, k % 576);
                gather_src[next[m as usize] as usize] = (576 * c + (rc % 24) * 24 + rc / 24) as u32;
                next[m as usize] += 1;
            }
        }
        let symbolic = SymbolicSparseColMat::new_checked(dofs.n_free, dofs.n_free, col_ptr, None, row_idx);
        let k_stab = linear_cube_stiffness(grid.cell_size_mm, linear_material.lambda, linear_material.mu);
        let stab_scale = grid.cells.iter().map(|c| stabilization * (1.0 - c.volume_fraction).max(0.0)).collect();
        let m = grid.cells.len();
        Self {
            grid,
            quad,
            dofs,
            symbolic,
            values: vec![0.0; nnz],
            scatter,
            gather_ptr,
            gather_src,
            stab_scale,
            k_stab,
            k_of: Vec::new(),
            k_unique: Vec::new(),
            linear_material,
            ke: vec![Ke::zeros(); m],
            fe: vec![SMatrix::zeros(); m],
            rot: vec![Matrix3::identity(); m],
        }
    }

    pub fn matrix(&self) -> SparseColMatRef<'_, usize, f64> {
        SparseColMatRef::new(self.symbolic.as_ref(), &self.values)
    }

    pub fn nnz(&self) -> usize {
        self.values.len()
    }

    /// Add `v` to the matrix entry of cell `cell`'s local dofs (`r`, `c`) (0..24, node-major),
    /// when both are free.
    pub fn add_to_cell_entry(&mut self, cell: usize, r: usize, c: usize, v: f64) {
        let m = self.scatter[576 * cell + 24 * r + c];
        if m != NONE {
            self.values[m as usize] += v;
        }
    }

    fn ensure_linear_stiffness(&mut self) {
        if !self.k_of.is_empty() {
            return;
        }
        let mat = self.linear_material;
        let quad = &self.quad;
        let (k_stab, stab) = (&self.k_stab, &self.stab_scale);
        let k_cells: Vec<Ke> = (0..self.grid.cells.len())
            .into_par_iter()
            .map(|c| {
                let mut k = Ke::zeros();
                for q in quad.qp_offsets[c]..quad.qp_offsets[c + 1] {
                    let g = &quad.table[quad.qp_table[q] as usize];
                    let w = quad.qp_weight_mm3[q];
                    for a in 0..8 {
                        for b in 0..8 {
                            for i in 0..3 {
                                for j in 0..3 {
                                    let mut v = mat.lambda * g[a][i] * g[b][j] + mat.mu * g[a][j] * g[b][i];
                                    if i == j {
                                        v += mat.mu * g[a].dot(&g[b]);
                                    }
                                    k[(3 * a + i, 3 * b + j)] += w * v;
                                }
                            }
                        }
                    }
                }
                k + k_stab * stab[c]
            })
            .collect();
        // Equal bit for bit, so every product is what it was with one matrix per cell.
        let mut seen: std::collections::HashMap<u64, Vec<u32>> = std::collections::HashMap::new();
        self.k_unique.clear();
        self.k_of = k_cells
            .into_iter()
            .map(|k| {
                let hash = k.iter().fold(0xcbf29ce484222325u64, |h, v| (h ^ v.to_bits()).wrapping_mul(0x100000001b3));
                let same = seen.entry(hash).or_default();
                if let Some(&i) = same.iter().find(|&&i| self.k_unique[i as usize] == k) {
                    return i;
                }
                let i = self.k_unique.len() as u32;
                self.k_unique.push(k);
                same.push(i);
                i
            })
            .collect();
    }

    /// Assemble internal forces at displacement `u` (mm per node) and, if `tangent`, the
    /// stiffness of the free dofs into `self.values`.
    pub fn assemble(&mut self, model: ElementModel, u: &[Vector3<f64>], tangent: bool) -> Assembled {
        if matches!(model, ElementModel::Corotational) {
            self.ensure_linear_stiffness();
        }
        let grid = self.grid;
        let quad = &self.quad;
        let k_stab = &self.k_stab;
        let stab = &self.stab_scale;
        let (k_of, k_unique) = (&self.k_of, &self.k_unique);
        let per_cell = self
            .ke
            .par_iter_mut()
            .zip(self.fe.par_iter_mut())
            .enumerate()
            .map(|(c, (ke, fe))| {
                let cell = &grid.cells[c];
                let ue: [Vector3<f64>; 8] = cell.nodes.map(|n| u[n as usize]);
                let ue_flat = SMatrix::<f64, 24, 1>::from_fn(|r, _| ue[r / 3][r % 3]);
                let mut min_det = f64::INFINITY;
                let mut energy = 0.0;
                let mut rot = Matrix3::identity();
                match model {
                    ElementModel::Hyperelastic(mat) => {
                        *fe = k_stab * ue_flat * stab[c];
                        energy += 0.5 * ue_flat.dot(fe);
                        if tangent {
                            *ke = k_stab * stab[c];
                        }
                        let svk = mat.kind == MaterialKind::StVenantKirchhoff;
                        for q in quad.qp_offsets[c]..quad.qp_offsets[c + 1] {
                            let g = &quad.table[quad.qp_table[q] as usize];
                            let w = quad.qp_weight_mm3[q];
                            let f = deformation_gradient(&ue, g);
                            min_det = min_det.min(f.determinant());
                            energy += w * mat.energy_density(&f);
                            if tangent && svk {
                                let s = mat.pk2(&f);
                                add_force(fe, &(f * s), g, w);
                                add_svk_tangent_upper(ke, &f, &s, g, w, mat.lambda, mat.mu);
                            } else if tangent {
                                let (p, a) = mat.pk1_and_tangent(&f);
                                add_force(fe, &p, g, w);
                                add_tangent(ke, &a, g, w);
                            } else {
                                add_force(fe, &mat.pk1(&f), g, w);
                            }
                        }
                        if tangent && svk {
                            mirror_upper_blocks(ke);
                        }
                    }
                    ElementModel::Corotational => {
                        let g0 = super::element::gradients([0.0; 3], grid.cell_size_mm);
                        let f = deformation_gradient(&ue, &g0);
                        min_det = f.determinant();
                        let r = rotation_of(&f);
                        rot = r;
                        let h = grid.cell_size_mm;
                        let x0: [Vector3<f64>; 8] =
                            crate::grid::HEX_CORNERS.map(|c| Vector3::new(c[0] as f64, c[1] as f64, c[2] as f64) * h);
                        let xc = (0..8).map(|a| x0[a] + ue[a]).sum::<Vector3<f64>>() / 8.0;
                        let xc0 = x0.iter().sum::<Vector3<f64>>() / 8.0;
                        let mut ul = SMatrix::<f64, 24, 1>::zeros();
                        for a in 0..8 {
                            let d = r.transpose() * (x0[a] + ue[a] - xc) - (x0[a] - xc0);
                            ul.fixed_rows_mut::<3>(3 * a).copy_from(&d);
                        }
                        let kc = &k_unique[k_of[c] as usize];
                        let fl = kc * ul;
                        energy += 0.5 * ul.dot(&fl);
                        for a in 0..8 {
                            let v = r * fl.fixed_rows::<3>(3 * a);
                            fe.fixed_rows_mut::<3>(3 * a).copy_from(&v);
                        }
                        if tangent {
                            // R_blk K R_blk^T, block by block.
                            for a in 0..8 {
                                for b in 0..8 {
                                    let blk: Matrix3<f64> = kc.fixed_view::<3, 3>(3 * a, 3 * b).into_owned();
                                    ke.fixed_view_mut::<3, 3>(3 * a, 3 * b).copy_from(&(r * blk * r.transpose()));
                                }
                            }
                        }
                    }
                }
                (min_det, energy, rot)
            })
            .collect::<Vec<(f64, f64, Matrix3<f64>)>>();
        if matches!(model, ElementModel::Corotational) {
            self.rot = per_cell.iter().map(|x| x.2).collect();
        }
        // Summed in cell order, so the energy does not depend on thread scheduling.
        let min_det = per_cell.iter().map(|x| x.0).fold(f64::INFINITY, f64::min);
        let energy: f64 = per_cell.iter().map(|x| x.1).sum();

        let mut f_int = vec![Vector3::zeros(); grid.node_count()];
        for (c, cell) in grid.cells.iter().enumerate() {
            for a in 0..8 {
                f_int[cell.nodes[a] as usize] += self.fe[c].fixed_rows::<3>(3 * a);
            }
        }
        if tangent {
            let (ke, ptr, src) = (&self.ke, &self.gather_ptr, &self.gather_src);
            self.values.par_chunks_mut(4096).enumerate().for_each(|(chunk, vals)| {
                for (j, v) in vals.iter_mut().enumerate() {
                    let m = chunk * 4096 + j;
                    let mut sum = 0.0;
                    for &k in &src[ptr[m] as usize..ptr[m + 1] as usize] {
                        sum += ke[k as usize / 576].as_slice()[k as usize % 576];
                    }
                    *v = sum;
                }
            });
        }
        Assembled { f_int, min_det_f: min_det, energy }
    }
}

#[inline]
fn add_force(fe: &mut SMatrix<f64, 24, 1>, p: &Matrix3<f64>, g: &super::element::Gradients, w: f64) {
    for a in 0..8 {
        let v = p * g[a] * w;
        fe[3 * a] += v.x;
        fe[3 * a + 1] += v.y;
        fe[3 * a + 2] += v.z;
    }
}

#[inline]
fn add_tangent(ke: &mut Ke, a: &super::material::Tangent, g: &super::element::Gradients, w: f64) {
    // T_b[(iJ), k] = sum_L A[(iJ), (kL)] g_b[L]; K[(a i), (b k)] += w sum_J g_a[J] T_b[(iJ), k]
    for b in 0..8 {
        let gb = g[b];
        let mut t = [[0.0f64; 3]; 9];
        for ij in 0..9 {
            for k in 0..3 {
                t[ij][k] = a[(ij, 3 * k)] * gb.x + a[(ij, 3 * k + 1)] * gb.y + a[(ij, 3 * k + 2)] * gb.z;
            }
        }
        for aa in 0..8 {
            let ga = g[aa];
            for i in 0..3 {
                for k in 0..3 {
                    let v = ga.x * t[3 * i][k] + ga.y * t[3 * i + 1][k] + ga.z * t[3 * i + 2][k];
                    ke[(3 * aa + i, 3 * b + k)] += w * v;
                }
            }
        }
    }
}

/// Saint Venant-Kirchhoff's element tangent in closed form, node block by node block:
/// K_ab = w [(g_a . S g_b) I + lambda (F g_a)(F g_b)^T + mu (F g_b)(F g_a)^T + mu (g_a . g_b) F F^T]
/// (the contraction of its dP/dF with the shape gradients, about a third of the generic
/// path's work), only for b >= a: the tangent is symmetric, `mirror_upper_blocks` fills the rest.
#[inline]
fn add_svk_tangent_upper(
    ke: &mut Ke,
    f: &Matrix3<f64>,
    s: &Matrix3<f64>,
    g: &super::element::Gradients,
    w: f64,
    lambda: f64,
    mu: f64,
) {
    let v: [Vector3<f64>; 8] = std::array::from_fn(|a| f * g[a]);
    let sg: [Vector3<f64>; 8] = std::array::from_fn(|a| s * g[a]);
    let ff = f * f.transpose() * (w * mu);
    let (wl, wm) = (w * lambda, w * mu);
    for b in 0..8 {
        for a in 0..=b {
            let geo = w * g[a].dot(&sg[b]);
            let d = g[a].dot(&g[b]);
            for k in 0..3 {
                for i in 0..3 {
                    let mut x = wl * v[a][i] * v[b][k] + wm * v[b][i] * v[a][k] + d * ff[(i, k)];
                    if i == k {
                        x += geo;
                    }
                    ke[(3 * a + i, 3 * b + k)] += x;
                }
            }
        }
    }
}

/// Copy the blocks a <= b of a symmetric element matrix to b < a.
fn mirror_upper_blocks(ke: &mut Ke) {
    for b in 0..8 {
        for a in 0..b {
            for i in 0..3 {
                for k in 0..3 {
                    ke[(3 * b + k, 3 * a + i)] = ke[(3 * a + i, 3 * b + k)];
                }
            }
        }
    }
}

impl Assembler<'_> {
    /// y = K x on the free dofs for the co-rotational stiffness at the last co-rotational
    /// assembly (each cell's rest stiffness turned by its rotation, R K R^T), without forming
    /// the matrix: the operator of a registration update, a few milliseconds per product.
    pub fn corotational_matvec(&mut self, x: &[f64], y: &mut [f64]) {
        self.ensure_linear_stiffness();
        let free = &self.dofs.free_of;
        let (grid, k_of, k_unique, rot) = (self.grid, &self.k_of, &self.k_unique, &self.rot);
        self.fe.par_iter_mut().enumerate().for_each(|(c, fe)| {
            let cell = &grid.cells[c];
            let r = rot[c];
            let mut xl = SMatrix::<f64, 24, 1>::zeros();
            for a in 0..8 {
                let mut v = Vector3::zeros();
                for i in 0..3 {
                    let f = free[3 * cell.nodes[a] as usize + i];
                    if f != NONE {
                        v[i] = x[f as usize];
                    }
                }
                xl.fixed_rows_mut::<3>(3 * a).copy_from(&(r.transpose() * v));
            }
            let yl = k_unique[k_of[c] as usize] * xl;
            for a in 0..8 {
                let v = r * yl.fixed_rows::<3>(3 * a);
                fe.fixed_rows_mut::<3>(3 * a).copy_from(&v);
            }
        });
        y.iter_mut().for_each(|v| *v = 0.0);
        for (c, cell) in grid.cells.iter().enumerate() {
            for a in 0..8 {
                for i in 0..3 {
                    let f = free[3 * cell.nodes[a] as usize + i];
                    if f != NONE {
                        y[f as usize] += self.fe[c][3 * a + i];
                    }
                }
            }
        }
    }

    /// Cell `c`'s rotation at the last co-rotational assembly (identity before any).
    pub fn cell_rotation(&self, c: usize) -> Matrix3<f64> {
        self.rot[c]
    }

    /// Each node's rotation: the rotation of the mean of its cells' rotations at the last
    /// co-rotational assembly (stiffness warping turns the rest factor's solves with these).
    pub fn nodal_rotations(&self) -> Vec<Matrix3<f64>> {
        let mut sum = vec![Matrix3::zeros(); self.grid.node_count()];
        for (c, cell) in self.grid.cells.iter().enumerate() {
            for &n in &cell.nodes {
                sum[n as usize] += self.rot[c];
            }
        }
        sum.par_iter().map(|m| if *m == Matrix3::zeros() { Matrix3::identity() } else { rotation_of(m) }).collect()
    }
}

/// The rotation of the polar decomposition F = R U.
pub fn rotation_of(f: &Matrix3<f64>) -> Matrix3<f64> {
    let svd = f.svd(true, true);
    let (Some(u), Some(vt)) = (svd.u, svd.v_t) else { return Matrix3::identity() };
    let mut r = u * vt;
    if r.determinant() < 0.0 {
        let mut u2 = u;
        // Flip the axis of the smallest singular value.
        let (imin, _) =
            svd.singular_values.iter().enumerate().fold((0, f64::MAX), |b, (i, &s)| if s < b.1 { (i, s) } else { b });
        u2.column_mut(imin).neg_mut();
        r = u2 * vt;
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn svk_closed_form_element_tangent_equals_the_generic_contraction_to_1e_12() {
        let mat = Material { kind: MaterialKind::StVenantKirchhoff, lambda: 0.07, mu: 0.0015 };
        let g = super::super::element::gradients([0.2, -0.4, 0.7], 5.0);
        let mut r = crate::rng::SplitMix64(7);
        for _ in 0..5 {
            let f = Matrix3::identity() + Matrix3::from_fn(|_, _| 0.6 * (r.next_f64() - 0.5));
            let (_, a) = mat.pk1_and_tangent(&f);
            let (mut generic, mut fast) = (Ke::zeros(), Ke::zeros());
            add_tangent(&mut generic, &a, &g, 1.7);
            add_svk_tangent_upper(&mut fast, &f, &mat.pk2(&f), &g, 1.7, mat.lambda, mat.mu);
            mirror_upper_blocks(&mut fast);
            let err = (generic - fast).abs().max();
            assert!(err <= 1e-12 * generic.abs().max(), "largest difference {err:e} of {:e}", generic.abs().max());
        }
    }
}
