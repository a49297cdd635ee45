//! The discrete problem as an NPZ file, so another FE code can solve exactly the same case
//! (and this one can solve theirs). Arrays: `nodes` [N,3] mm, `hexes` [M,8] (VTK order),
//! `qp_cell` [Q], `qp_xi` [Q,3] in [-1,1]^3, `qp_w` [Q] mm^3, `fixed` [F] node indices,
//! `forces` [N,3] N, `young_pa`, `poisson`, `material` (uint8 text: svk, linear,
//! neo-hookean); optional `prescribed_nodes` [P] and `prescribed_mm` [P,3]; the finite-cell
//! stabilisation as `stab_cell` [S] int64 (indices into `hexes`) and `stab_scale` [S] float64:
//! each listed cell adds a small-strain linear-elastic stiffness with the problem's E and nu,
//! integrated over the whole cell with 2x2x2 Gauss points, times `stab_scale` (umesh writes
//! alpha * (1 - the cell's volume fraction) for every cell where that is positive). A file
//! without them has no stabilisation.

use super::bc::BoundaryConditions;
use super::material::{MaterialKind, MaterialParams};
use crate::grid::{CellKind, ImmersedGrid, QuadPoint, assemble_grid};
use crate::npz::{Array, ArrayData, Npz, NpzError};
use nalgebra::Vector3;
use std::path::Path;

#[derive(Debug, thiserror::Error)]
pub enum ProblemError {
    #[error(transparent)]
    Npz(#[from] NpzError),
    #[error("{path}: {reason}")]
    Invalid { path: String, reason: String },
}

pub fn problem_arrays(
    grid: &ImmersedGrid,
    material: &MaterialParams,
    bc: &BoundaryConditions,
    stabilization: f64,
) -> Vec<(&'static str, Array)> {
    let mut arrays: Vec<(&'static str, Array)> = grid
        .to_npz_arrays()
        .into_iter()
        .filter(|(n, _)| matches!(*n, "nodes" | "hexes" | "qp_cell" | "qp_xi" | "qp_w"))
        .collect();
    let fixed: Vec<i64> = bc.fixed.iter().enumerate().filter(|(_, f)| **f).map(|(i, _)| i as i64).collect();
    arrays.push(("fixed", Array::i64(vec![fixed.len()], fixed)));
    arrays.push((
        "forces",
        Array::f64(vec![bc.forces_n.len(), 3], bc.forces_n.iter().flat_map(|f| [f.x, f.y, f.z]).collect()),
    ));
    arrays.push(("young_pa", Array::scalar_f64(material.young_pa)));
    arrays.push(("poisson", Array::scalar_f64(material.poisson)));
    let name = material.kind.name().as_bytes().to_vec();
    arrays.push(("material", Array::new(vec![name.len()], ArrayData::U8(name))));
    let stab: Vec<(i64, f64)> = grid
        .cells
        .iter()
        .enumerate()
        .map(|(c, cell)| (c as i64, stabilization * (1.0 - cell.volume_fraction).max(0.0)))
        .filter(|(_, s)| *s > 0.0)
        .collect();
    if !stab.is_empty() {
        arrays.push(("stab_cell", Array::i64(vec![stab.len()], stab.iter().map(|x| x.0).collect())));
        arrays.push(("stab_scale", Array::f64(vec![stab.len()], stab.iter().map(|x| x.1).collect())));
    }
    if !bc.prescribed_mm.is_empty() {
        let p = &bc.prescribed_mm;
        arrays.push(("prescribed_nodes", Array::i64(vec![p.len()], p.iter().map(|(n, _)| *n as i64).collect())));
        arrays.push((
            "prescribed_mm",
            Array::f64(vec![p.len(), 3], p.iter().flat_map(|(_, d)| [d.x, d.y, d.z]).collect()),
        ));
    }
    arrays
}

pub fn write_problem(
    path: &Path,
    grid: &ImmersedGrid,
    material: &MaterialParams,
    bc: &BoundaryConditions,
    stabilization: f64,
) -> Result<(), NpzError> {
    crate::npz::write_npz(path, &problem_arrays(grid, material, bc, stabilization))
}

/// A problem read from a file: the grid, the material, the conditions, and the map from the
/// file's node numbers to the grid's.
#[derive(Debug)]
pub struct LoadedProblem {
    pub grid: ImmersedGrid,
    pub material: MaterialParams,
    pub bc: BoundaryConditions,
    /// file node index -> grid node index
    pub node_map: Vec<usize>,
    /// The stabilisation factor alpha the file's `stab_scale` encodes (0 without the arrays):
    /// the solver's `SolverSettings::stabilization` for this problem.
    pub stabilization: f64,
}

pub fn read_problem(path: &Path) -> Result<LoadedProblem, ProblemError> {
    let npz = Npz::read(path)?;
    let bad = |reason: String| ProblemError::Invalid { path: path.display().to_string(), reason };
    let (sh, nodes) = npz.f64_with_shape("nodes", &[None, Some(3)])?;
    let n = sh[0];
    let (sh, hexes) = npz.f64_with_shape("hexes", &[None, Some(8)])?;
    let m = sh[0];
    let (_, qp_cell) = npz.f64_with_shape("qp_cell", &[None])?;
    let q = qp_cell.len();
    let (_, qp_xi) = npz.f64_with_shape("qp_xi", &[Some(q), Some(3)])?;
    let (_, qp_w) = npz.f64_with_shape("qp_w", &[Some(q)])?;
    let (_, fixed) = npz.f64_with_shape("fixed", &[None])?;
    let (_, forces) = npz.f64_with_shape("forces", &[Some(n), Some(3)])?;
    let (_, young) = npz.f64_with_shape("young_pa", &[])?;
    let (_, poisson) = npz.f64_with_shape("poisson", &[])?;
    let mat_name = match &npz.get("material")?.data {
        ArrayData::U8(b) => String::from_utf8_lossy(b).into_owned(),
        _ => return Err(bad("'material' must be uint8 text".into())),
    };
    let kind = MaterialKind::parse(mat_name.trim()).ok_or_else(|| bad(format!("unknown material {mat_name:?}")))?;
    let material = MaterialParams { kind, young_pa: young[0], poisson: poisson[0] };
    material.validate().map_err(|e| bad(e.into()))?;
    if n == 0 || m == 0 {
        return Err(bad("no nodes or no hexahedra".into()));
    }
    if nodes.iter().chain(&forces).chain(&qp_xi).chain(&qp_w).any(|v| !v.is_finite()) {
        return Err(bad("non-finite values".into()));
    }
    let node = |i: f64| -> Result<usize, ProblemError> {
        if i < 0.0 || i as usize >= n || i.fract() != 0.0 {
            return Err(bad(format!("node index {i} out of range 0..{n}")));
        }
        Ok(i as usize)
    };
    let pos = |i: usize| Vector3::new(nodes[3 * i], nodes[3 * i + 1], nodes[3 * i + 2]);
    // The lattice: cell size from the first hexahedron's 0-1 edge, origin at the minimum.
    let h0 = node(hexes[0])?;
    let h1 = node(hexes[1])?;
    let h = (pos(h1) - pos(h0)).norm();
    if !(h > 0.0) {
        return Err(bad("the first hexahedron has a zero edge".into()));
    }
    let origin = (0..n).map(pos).fold(Vector3::repeat(f64::INFINITY), |a, p| a.inf(&p));
    let ijk_of = |i: usize| -> Result<[usize; 3], ProblemError> {
        let c = (pos(i) - origin) / h;
        let r = c.map(|v| v.round());
        if (c - r).amax() > 1e-3 {
            return Err(bad(format!("node {i} is not on the regular lattice of spacing {h} mm")));
        }
        Ok([r.x as usize, r.y as usize, r.z as usize])
    };
    let node_ijk: Vec<[usize; 3]> = (0..n).map(ijk_of).collect::<Result<_, _>>()?;
    let cell_dims = [0, 1, 2].map(|a| node_ijk.iter().map(|v| v[a]).max().unwrap_or(0).max(1));
    if cell_dims.iter().product::<usize>() > 50_000_000 {
        return Err(bad("the lattice is too large".into()));
    }
    let occupied = occupied_cells(path, &hexes, &node_ijk, (&qp_cell, &qp_xi, &qp_w), h, &node)?;
    // The grid numbers cells in lattice order; keep the file's order for quadrature grouping.
    let mut order: Vec<usize> = (0..m).collect();
    order.sort_by_key(|&c| {
        let [i, j, k] = occupied[c].0;
        (k, j, i)
    });
    let mut new_of = vec![0usize; m];
    for (newc, &oldc) in order.iter().enumerate() {
        new_of[oldc] = newc;
    }
    let occ_sorted: Vec<_> = order.iter().map(|&c| occupied[c]).collect();
    let mut quadrature: Vec<QuadPoint> = (0..q)
        .map(|i| QuadPoint {
            cell: new_of[qp_cell[i] as usize] as u32,
            xi: [qp_xi[3 * i], qp_xi[3 * i + 1], qp_xi[3 * i + 2]],
            weight_mm3: qp_w[i],
        })
        .collect();
    quadrature.sort_by_key(|p| p.cell);
    let grid = assemble_grid(origin, h, cell_dims, occ_sorted, quadrature, 0);
    let node_map: Vec<usize> = node_ijk.iter().map(|ijk| grid.node_at(*ijk).unwrap_or(usize::MAX)).collect();
    if node_map.contains(&usize::MAX) || grid.node_count() != n {
        return Err(bad("some nodes belong to no hexahedron".into()));
    }
    let mut bc = BoundaryConditions::new(n);
    for &f in &fixed {
        bc.fixed[node_map[node(f)?]] = true;
    }
    for i in 0..n {
        bc.forces_n[node_map[i]] = Vector3::new(forces[3 * i], forces[3 * i + 1], forces[3 * i + 2]);
    }
    if npz.arrays.contains_key("prescribed_nodes") {
        let (_, pn) = npz.f64_with_shape("prescribed_nodes", &[None])?;
        let (_, pd) = npz.f64_with_shape("prescribed_mm", &[Some(pn.len()), Some(3)])?;
        for (k, &p) in pn.iter().enumerate() {
            bc.prescribed_mm.push((node_map[node(p)?], Vector3::new(pd[3 * k], pd[3 * k + 1], pd[3 * k + 2])));
        }
    }
    let stabilization = read_stabilization(&npz, path, &occupied)?;
    Ok(LoadedProblem { grid, material, bc, node_map, stabilization })
}

/// The stabilisation's alpha from `stab_cell` / `stab_scale`, 0 without them. umesh's solver
/// applies alpha * (1 - volume fraction) per cell, so the file's scales must be that for one
/// alpha (any other pattern is refused, not approximated).
fn read_stabilization(npz: &Npz, path: &Path, occupied: &[([usize; 3], CellKind, f64)]) -> Result<f64, ProblemError> {
    let bad = |reason: String| ProblemError::Invalid { path: path.display().to_string(), reason };
    let m = occupied.len();
    if npz.arrays.contains_key("stab_cell") || npz.arrays.contains_key("stab_scale") {
        let (_, sc) = npz.f64_with_shape("stab_cell", &[None])?;
        let (_, ss) = npz.f64_with_shape("stab_scale", &[Some(sc.len())])?;
        let mut per_cell = vec![0.0; m];
        for (&c, &v) in sc.iter().zip(&ss) {
            if c < 0.0 || c.fract() != 0.0 || c as usize >= m {
                return Err(bad(format!("stab_cell {c} out of range 0..{m}")));
            }
            if !(v.is_finite() && v >= 0.0) {
                return Err(bad(format!("stab_scale {v}: must be finite and non-negative")));
            }
            per_cell[c as usize] += v;
        }
        let frac = |c: usize| 1.0 - occupied[c].2.min(1.0);
        let (num, den) = (0..m).fold((0.0, 0.0), |(a, b), c| (a + per_cell[c] * frac(c), b + frac(c) * frac(c)));
        let alpha = if den > 0.0 { num / den } else { 0.0 };
        if let Some(c) = (0..m).find(|&c| (per_cell[c] - alpha * frac(c)).abs() > 1e-9 * (1.0 + alpha)) {
            return Err(bad(format!(
                "stab_scale of hexahedron {c} is {} where alpha (1 - volume fraction) = {}: only that pattern can be solved here",
                per_cell[c],
                alpha * frac(c)
            )));
        }
        return Ok(alpha);
    }
    Ok(0.0)
}

/// Each hexahedron's lattice corner, kind and inside fraction (its quadrature weights over its
/// volume), checked: quadrature points in their cell with non-negative weights, each
/// hexahedron an axis-aligned cube of the lattice in VTK order.
fn occupied_cells(
    path: &Path,
    hexes: &[f64],
    node_ijk: &[[usize; 3]],
    (qp_cell, qp_xi, qp_w): (&[f64], &[f64], &[f64]),
    h: f64,
    node: &impl Fn(f64) -> Result<usize, ProblemError>,
) -> Result<Vec<([usize; 3], CellKind, f64)>, ProblemError> {
    let bad = |reason: String| ProblemError::Invalid { path: path.display().to_string(), reason };
    let m = hexes.len() / 8;
    let mut weight = vec![0.0; m];
    for (i, &c) in qp_cell.iter().enumerate() {
        // Stored as integers or floats: a negative or fractional index is an error, not cell 0.
        if !(c >= 0.0 && c.fract() == 0.0 && (c as usize) < m) {
            return Err(bad(format!("qp_cell[{i}] = {c}: not a hexahedron index in 0..{m}")));
        }
        let xi = &qp_xi[3 * i..3 * i + 3];
        if xi.iter().any(|v| v.abs() > 1.0 + 1e-9) {
            return Err(bad(format!("qp_xi[{i}] = {xi:?}: reference coordinates must lie in [-1, 1]")));
        }
        if qp_w[i] < 0.0 {
            return Err(bad(format!("qp_w[{i}] = {}: a quadrature weight cannot be negative", qp_w[i])));
        }
        weight[c as usize] += qp_w[i];
    }
    let mut occupied = Vec::with_capacity(m);
    for c in 0..m {
        let corner0 = node(hexes[8 * c])?;
        for (k, off) in crate::grid::HEX_CORNERS.iter().enumerate() {
            let nk = node(hexes[8 * c + k])?;
            let expect = [0, 1, 2].map(|a| node_ijk[corner0][a] + off[a]);
            if node_ijk[nk] != expect {
                return Err(bad(format!("hexahedron {c} is not an axis-aligned cube in VTK order")));
            }
        }
        let frac = weight[c] / h.powi(3);
        if frac > 1.0 + 1e-6 {
            return Err(bad(format!(
                "hexahedron {c}: its quadrature weights sum to {:.4} mm^3, more than the cell's volume {:.4} mm^3",
                weight[c],
                h.powi(3)
            )));
        }
        let kind = if (frac - 1.0).abs() < 1e-9 { CellKind::Inside } else { CellKind::Boundary };
        occupied.push((node_ijk[corner0], kind, frac));
    }
    Ok(occupied)
}
