//! The sparse regular hexahedral grid with an immersed boundary.
//!
//! The grid is axis-aligned in the world frame (RAS mm) and does not follow the organ's
//! surface: cells are classified inside / boundary / outside by sampling the organ, outside
//! cells are dropped, and each boundary cell is integrated over the inside part of its
//! recursive subdivision into 8 sub-cells (`subdivisions` levels; 1 as in the paper).
//! Node numbering covers the kept cells only; hexahedra use VTK's corner order.

use crate::npz::{Array, ArrayData, Npz, NpzError};
use crate::progress::{Cancel, Progress};
use crate::volume::Mask;
use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

/// Corner offsets of a hexahedron in VTK order.
pub const HEX_CORNERS: [[usize; 3]; 8] =
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]];

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GridSettings {
    /// Edge length of a cell (mm). 7 mm gives about the paper's 32 x 40 x 16 padded grid
    /// for an adult liver.
    pub cell_size_mm: f64,
    /// Levels of recursive subdivision of boundary cells into 8 sub-cells.
    pub subdivisions: u32,
    /// Inside samples per axis in each finest sub-cell (its volume fraction estimate).
    pub samples_per_leaf_axis: u32,
    /// Pooling steps of the U-Net: the padded shape is a multiple of 2^k on each axis.
    pub pooling_steps: u32,
}

impl Default for GridSettings {
    fn default() -> Self {
        Self { cell_size_mm: 7.0, subdivisions: 1, samples_per_leaf_axis: 2, pooling_steps: 3 }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum GridError {
    #[error("the organ mask is empty (no voxel has the organ label)")]
    EmptyMask,
    #[error(
        "no cell of {cell_size_mm} mm holds a sample inside the organ (its box is {:.0} x {:.0} x {:.0} mm): use a smaller --cell-size-mm",
        extent_mm[0], extent_mm[1], extent_mm[2]
    )]
    CellsTooLarge { cell_size_mm: f64, extent_mm: [f64; 3] },
    #[error("invalid grid settings: {0}")]
    Settings(String),
    #[error(
        "the grid would have {cells} cells in its bounding box, more than the limit of {limit}; use a larger --cell-size-mm"
    )]
    TooLarge { cells: usize, limit: usize },
    #[error(
        "the immersed boundary would take {samples} inside tests (box cells x (2^subdivisions x samples per leaf axis)^3), more than the limit of {limit}; use a larger --cell-size-mm or fewer --subdivisions"
    )]
    TooMuchWork { samples: u64, limit: u64 },
    #[error(transparent)]
    Cancelled(#[from] crate::Cancelled),
    #[error(transparent)]
    Npz(#[from] NpzError),
    #[error("{0}")]
    BadFile(String),
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub enum CellKind {
    Inside = 1,
    Boundary = 2,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Cell {
    pub ijk: [usize; 3],
    pub nodes: [u32; 8],
    pub kind: CellKind,
    /// Inside volume / cell volume.
    pub volume_fraction: f64,
}

/// A quadrature point: reference coordinates in [-1, 1]^3 of its cell, physical weight (mm^3).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct QuadPoint {
    pub cell: u32,
    pub xi: [f64; 3],
    pub weight_mm3: f64,
}

#[derive(Clone, Debug, PartialEq)]
pub struct ImmersedGrid {
    /// World position (mm) of node lattice index (0, 0, 0).
    pub origin_mm: Vector3<f64>,
    pub cell_size_mm: f64,
    /// Cells of the bounding lattice on each axis (nodes: +1).
    pub cell_dims: [usize; 3],
    pub cells: Vec<Cell>,
    /// Lattice index of each node.
    pub node_ijk: Vec<[usize; 3]>,
    /// Quadrature points, grouped by cell: those of cell c are `qp_offsets[c]..qp_offsets[c+1]`.
    pub quadrature: Vec<QuadPoint>,
    pub qp_offsets: Vec<usize>,
    pub pooling_steps: u32,
    /// Cell lattice index -> cell number, u32::MAX when dropped.
    cell_lookup: Vec<u32>,
    /// Node lattice index -> node number, u32::MAX when absent.
    node_lookup: Vec<u32>,
}

/// Where a world point sits in the grid: the enclosing (or nearest) cell and trilinear weights.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Embedding {
    pub cell: u32,
    pub nodes: [u32; 8],
    pub weights: [f64; 8],
}

#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct GridStats {
    pub cells: usize,
    pub nodes: usize,
    pub inside_cells: usize,
    pub boundary_cells: usize,
    pub quadrature_points: usize,
    pub cell_size_mm: f64,
    pub grid_volume_mm3: f64,
    pub node_dims: [usize; 3],
    pub padded_shape: [usize; 3],
}

/// Trilinear shape functions at reference coordinates, VTK corner order.
pub fn shape_functions(xi: [f64; 3]) -> [f64; 8] {
    std::array::from_fn(|a| {
        let c = HEX_CORNERS[a];
        (0..3).map(|d| 0.5 * (1.0 + if c[d] == 1 { xi[d] } else { -xi[d] })).product()
    })
}

/// Grids whose box holds more cells are refused before any work: their FE model could not be
/// solved in the time a dataset has (a 2 l liver at 7 mm has 41 k; 2 mm cells on it, 640 k).
const MAX_LATTICE_CELLS: usize = 2_000_000;
/// The displacement at an embedded point from per-node displacements.
pub fn interpolate_nodes(e: &Embedding, u: &[Vector3<f64>]) -> Vector3<f64> {
    e.nodes.iter().zip(e.weights).map(|(&n, w)| u[n as usize] * w).sum()
}

/// Inside tests of the immersed boundary (box cells x samples per cell) over this are refused:
/// hours of classification (1 mm cells with 4 subdivisions on the phantom: 6e10).
const MAX_INSIDE_SAMPLES: u64 = 200_000_000;

impl ImmersedGrid {
    pub fn node_dims(&self) -> [usize; 3] {
        self.cell_dims.map(|d| d + 1)
    }

    pub fn padded_shape(&self) -> [usize; 3] {
        let m = 1usize << self.pooling_steps;
        self.node_dims().map(|d| d.div_ceil(m) * m)
    }

    pub fn node_count(&self) -> usize {
        self.node_ijk.len()
    }

    pub fn node_position(&self, n: usize) -> Vector3<f64> {
        let [i, j, k] = self.node_ijk[n];
        self.origin_mm + Vector3::new(i as f64, j as f64, k as f64) * self.cell_size_mm
    }

    pub fn node_positions(&self) -> Vec<Vector3<f64>> {
        (0..self.node_count()).map(|n| self.node_position(n)).collect()
    }

    pub fn cell_volume_mm3(&self) -> f64 {
        self.cell_size_mm.powi(3)
    }

    pub fn volume_mm3(&self) -> f64 {
        self.quadrature.iter().map(|q| q.weight_mm3).sum()
    }

    /// Cell number at a cell-lattice index.
    pub fn cell_at(&self, ijk: [usize; 3]) -> Option<usize> {
        let [nx, ny, nz] = self.cell_dims;
        if ijk[0] >= nx || ijk[1] >= ny || ijk[2] >= nz {
            return None;
        }
        let c = self.cell_lookup[ijk[0] + nx * (ijk[1] + ny * ijk[2])];
        (c != u32::MAX).then_some(c as usize)
    }

    /// Node number at a node-lattice index.
    pub fn node_at(&self, ijk: [usize; 3]) -> Option<usize> {
        let [nx, ny, nz] = self.node_dims();
        if ijk[0] >= nx || ijk[1] >= ny || ijk[2] >= nz {
            return None;
        }
        let n = self.node_lookup[ijk[0] + nx * (ijk[1] + ny * ijk[2])];
        (n != u32::MAX).then_some(n as usize)
    }

    /// Index of a node in the padded dense grid (C order over [X, Y, Z]).
    pub fn dense_index(&self, node: usize) -> usize {
        let [_, py, pz] = self.padded_shape();
        let [i, j, k] = self.node_ijk[node];
        (i * py + j) * pz + k
    }

    /// The same organ on cells `factor` times as large, on the same lattice (coarse cell
    /// `ijk / factor`, node `I` at fine node `factor * I`): a coarse cell whose fine cells are
    /// all whole is whole (2x2x2 Gauss), any other carries its fine cells' quadrature points
    /// moved into it, so the organ's volume and where it lies are integrated as on this grid.
    pub fn coarsened(&self, factor: usize) -> ImmersedGrid {
        let f = factor.max(1);
        let cell_dims = self.cell_dims.map(|d| d.div_ceil(f));
        let h = self.cell_size_mm * f as f64;
        // Per coarse cell (by lattice index): whole fine cells, inside volume, fine quadrature.
        let mut acc: std::collections::BTreeMap<[usize; 3], (usize, f64, Vec<QuadPoint>)> = Default::default();
        for (c, cell) in self.cells.iter().enumerate() {
            let cc = cell.ijk.map(|v| v / f);
            let e = acc.entry([cc[2], cc[1], cc[0]]).or_default();
            e.0 += (cell.kind == CellKind::Inside) as usize;
            e.1 += cell.volume_fraction * self.cell_volume_mm3();
            for q in &self.quadrature[self.qp_offsets[c]..self.qp_offsets[c + 1]] {
                // Fine reference point -> lattice coordinate -> coarse reference point.
                let xi = [0, 1, 2].map(|a| {
                    let fine = cell.ijk[a] as f64 + 0.5 * (q.xi[a] + 1.0);
                    2.0 * (fine / f as f64 - cc[a] as f64) - 1.0
                });
                e.2.push(QuadPoint { cell: 0, xi, weight_mm3: q.weight_mm3 });
            }
        }
        let g = 1.0 / 3f64.sqrt();
        let (mut occupied, mut quadrature) = (Vec::with_capacity(acc.len()), Vec::new());
        for (k, (zyx, (whole, volume_mm3, qps))) in acc.into_iter().enumerate() {
            let ijk = [zyx[2], zyx[1], zyx[0]];
            let is_whole = whole == f * f * f;
            let kind = if is_whole { CellKind::Inside } else { CellKind::Boundary };
            occupied.push((ijk, kind, if is_whole { 1.0 } else { volume_mm3 / (h * h * h) }));
            if is_whole {
                quadrature.extend(HEX_CORNERS.map(|c| QuadPoint {
                    cell: k as u32,
                    xi: c.map(|v| if v == 1 { g } else { -g }),
                    weight_mm3: h * h * h / 8.0,
                }));
            } else {
                quadrature.extend(qps.into_iter().map(|q| QuadPoint { cell: k as u32, ..q }));
            }
        }
        assemble_grid(self.origin_mm, h, cell_dims, occupied, quadrature, self.pooling_steps)
    }

    pub fn stats(&self) -> GridStats {
        let boundary = self.cells.iter().filter(|c| c.kind == CellKind::Boundary).count();
        GridStats {
            cells: self.cells.len(),
            nodes: self.node_count(),
            inside_cells: self.cells.len() - boundary,
            boundary_cells: boundary,
            quadrature_points: self.quadrature.len(),
            cell_size_mm: self.cell_size_mm,
            grid_volume_mm3: self.volume_mm3(),
            node_dims: self.node_dims(),
            padded_shape: self.padded_shape(),
        }
    }

    /// Embed a world point: the enclosing kept cell, or the nearest one for points just
    /// outside the grid (local coordinates clamped to the cell).
    pub fn embed(&self, p: &Vector3<f64>) -> Option<Embedding> {
        let c = (p - self.origin_mm) / self.cell_size_mm;
        let base = [0, 1, 2].map(|a| (c[a].floor().max(0.0) as usize).min(self.cell_dims[a] - 1));
        let cell = if let Some(cell) = self.cell_at(base) {
            cell
        } else {
            // Nearest kept cell in a growing neighbourhood.
            let mut best: Option<(f64, usize)> = None;
            for r in 1..=4i64 {
                for dk in -r..=r {
                    for dj in -r..=r {
                        for di in -r..=r {
                            let ijk = [base[0] as i64 + di, base[1] as i64 + dj, base[2] as i64 + dk];
                            if ijk.iter().any(|&v| v < 0) {
                                continue;
                            }
                            let ijk = ijk.map(|v| v as usize);
                            if let Some(cell) = self.cell_at(ijk) {
                                let lo = Vector3::new(ijk[0] as f64, ijk[1] as f64, ijk[2] as f64);
                                let q = Vector3::new(
                                    c.x.clamp(lo.x, lo.x + 1.0),
                                    c.y.clamp(lo.y, lo.y + 1.0),
                                    c.z.clamp(lo.z, lo.z + 1.0),
                                );
                                let d = (q - c).norm_squared();
                                if best.is_none_or(|(bd, _)| d < bd) {
                                    best = Some((d, cell));
                                }
                            }
                        }
                    }
                }
                if best.is_some() {
                    break;
                }
            }
            best?.1
        };
        let ijk = self.cells[cell].ijk;
        let xi = [0, 1, 2].map(|a| 2.0 * (c[a] - ijk[a] as f64).clamp(0.0, 1.0) - 1.0);
        Some(Embedding { cell: cell as u32, nodes: self.cells[cell].nodes, weights: shape_functions(xi) })
    }

    /// Build the grid of a mask.
    pub fn from_mask(
        mask: &Mask,
        settings: &GridSettings,
        progress: &Progress,
        cancel: &Cancel,
    ) -> Result<Self, GridError> {
        let (lo, hi) = mask.world_bounds().ok_or(GridError::EmptyMask)?;
        let sampler = mask.world_sampler();
        build(lo, hi, |p| sampler.inside(p), settings, progress, cancel)
    }

    /// Serialise to NPZ (documented in the README).
    pub fn to_npz_arrays(&self) -> Vec<(&'static str, Array)> {
        let n = self.node_count();
        let m = self.cells.len();
        let q = self.quadrature.len();
        let nodes: Vec<f64> = self.node_positions().iter().flat_map(|p| [p.x, p.y, p.z]).collect();
        vec![
            ("nodes", Array::f64(vec![n, 3], nodes)),
            ("node_ijk", Array::i64(vec![n, 3], self.node_ijk.iter().flatten().map(|&v| v as i64).collect())),
            ("hexes", Array::i64(vec![m, 8], self.cells.iter().flat_map(|c| c.nodes.map(|v| v as i64)).collect())),
            ("cell_ijk", Array::i64(vec![m, 3], self.cells.iter().flat_map(|c| c.ijk.map(|v| v as i64)).collect())),
            ("cell_fraction", Array::f64(vec![m], self.cells.iter().map(|c| c.volume_fraction).collect())),
            ("cell_kind", Array::new(vec![m], ArrayData::U8(self.cells.iter().map(|c| c.kind as u8).collect()))),
            ("qp_cell", Array::i64(vec![q], self.quadrature.iter().map(|p| p.cell as i64).collect())),
            ("qp_xi", Array::f64(vec![q, 3], self.quadrature.iter().flat_map(|p| p.xi).collect())),
            ("qp_w", Array::f64(vec![q], self.quadrature.iter().map(|p| p.weight_mm3).collect())),
            ("origin_mm", Array::f64(vec![3], self.origin_mm.iter().copied().collect())),
            ("cell_size_mm", Array::scalar_f64(self.cell_size_mm)),
            ("cell_dims", Array::i64(vec![3], self.cell_dims.map(|v| v as i64).to_vec())),
            ("padded_shape", Array::i64(vec![3], self.padded_shape().map(|v| v as i64).to_vec())),
            ("pooling_steps", Array::i64(vec![], vec![self.pooling_steps as i64])),
        ]
    }

    /// Read a grid written by [`Self::to_npz_arrays`].
    pub fn from_npz(npz: &Npz) -> Result<Self, GridError> {
        let bad = |s: String| GridError::BadFile(format!("{}: {s}", npz.path.display()));
        let (_, origin) = npz.f64_with_shape("origin_mm", &[Some(3)])?;
        let (_, h) = npz.f64_with_shape("cell_size_mm", &[])?;
        let (_, dims) = npz.f64_with_shape("cell_dims", &[Some(3)])?;
        let (_, k) = npz.f64_with_shape("pooling_steps", &[])?;
        let (sh, cell_ijk) = npz.f64_with_shape("cell_ijk", &[None, Some(3)])?;
        let m = sh[0];
        let (_, frac) = npz.f64_with_shape("cell_fraction", &[Some(m)])?;
        let (_, kind) = npz.f64_with_shape("cell_kind", &[Some(m)])?;
        let (_, qp_cell) = npz.f64_with_shape("qp_cell", &[None])?;
        let q = qp_cell.len();
        let (_, qp_xi) = npz.f64_with_shape("qp_xi", &[Some(q), Some(3)])?;
        let (_, qp_w) = npz.f64_with_shape("qp_w", &[Some(q)])?;
        let h = h[0];
        if !(h > 0.0 && h.is_finite()) {
            return Err(bad(format!("cell size {h} is not positive")));
        }
        let cell_dims = [dims[0] as usize, dims[1] as usize, dims[2] as usize];
        if cell_dims.iter().product::<usize>() > MAX_LATTICE_CELLS {
            return Err(bad("cell_dims too large".into()));
        }
        let occupied: Vec<([usize; 3], CellKind, f64)> = (0..m)
            .map(|c| {
                let ijk = [0, 1, 2].map(|a| cell_ijk[3 * c + a] as usize);
                if (0..3).any(|a| ijk[a] >= cell_dims[a]) {
                    return Err(bad(format!("cell {c} lies outside cell_dims")));
                }
                let kind = if kind[c] == 1.0 { CellKind::Inside } else { CellKind::Boundary };
                Ok((ijk, kind, frac[c]))
            })
            .collect::<Result<_, _>>()?;
        let mut quadrature = Vec::with_capacity(q);
        for i in 0..q {
            let cell = qp_cell[i] as usize;
            if cell >= m {
                return Err(bad(format!("quadrature point {i} refers to cell {cell} of {m}")));
            }
            quadrature.push(QuadPoint {
                cell: cell as u32,
                xi: [qp_xi[3 * i], qp_xi[3 * i + 1], qp_xi[3 * i + 2]],
                weight_mm3: qp_w[i],
            });
        }
        if quadrature.windows(2).any(|w| w[1].cell < w[0].cell) {
            return Err(bad("quadrature points are not grouped by cell".into()));
        }
        Ok(assemble_grid(Vector3::from_column_slice(&origin), h, cell_dims, occupied, quadrature, k[0] as u32))
    }
}

/// Number the nodes of the kept cells and index everything. `occupied` is (cell lattice
/// index, kind, volume fraction) per cell; `quadrature` refers to cells by their position
/// in `occupied` and must be grouped by cell.
pub fn assemble_grid(
    origin_mm: Vector3<f64>,
    cell_size_mm: f64,
    cell_dims: [usize; 3],
    occupied: Vec<([usize; 3], CellKind, f64)>,
    quadrature: Vec<QuadPoint>,
    pooling_steps: u32,
) -> ImmersedGrid {
    let [cx, cy, cz] = cell_dims;
    let [nx, ny, nz] = [cx + 1, cy + 1, cz + 1];
    let mut node_lookup = vec![u32::MAX; nx * ny * nz];
    let mut cell_lookup = vec![u32::MAX; cx * cy * cz];
    for (idx, (ijk, _, _)) in occupied.iter().enumerate() {
        cell_lookup[ijk[0] + cx * (ijk[1] + cy * ijk[2])] = idx as u32;
        for c in HEX_CORNERS {
            node_lookup[(ijk[0] + c[0]) + nx * ((ijk[1] + c[1]) + ny * (ijk[2] + c[2]))] = 0;
        }
    }
    let mut node_ijk = Vec::new();
    for (lin, slot) in node_lookup.iter_mut().enumerate() {
        if *slot == 0 {
            *slot = node_ijk.len() as u32;
            node_ijk.push([lin % nx, (lin / nx) % ny, lin / (nx * ny)]);
        }
    }
    let cells: Vec<Cell> = occupied
        .into_iter()
        .map(|(ijk, kind, volume_fraction)| Cell {
            ijk,
            nodes: HEX_CORNERS.map(|c| node_lookup[(ijk[0] + c[0]) + nx * ((ijk[1] + c[1]) + ny * (ijk[2] + c[2]))]),
            kind,
            volume_fraction,
        })
        .collect();
    let mut qp_offsets = vec![0usize; cells.len() + 1];
    for q in &quadrature {
        qp_offsets[q.cell as usize + 1] += 1;
    }
    for c in 0..cells.len() {
        qp_offsets[c + 1] += qp_offsets[c];
    }
    ImmersedGrid {
        origin_mm,
        cell_size_mm,
        cell_dims,
        cells,
        node_ijk,
        quadrature,
        qp_offsets,
        pooling_steps,
        cell_lookup,
        node_lookup,
    }
}

/// Build the grid over the world box [lo, hi] from an inside test.
pub fn build(
    lo: Vector3<f64>,
    hi: Vector3<f64>,
    inside: impl Fn(&Point3<f64>) -> bool + Sync,
    settings: &GridSettings,
    progress: &Progress,
    cancel: &Cancel,
) -> Result<ImmersedGrid, GridError> {
    let h = settings.cell_size_mm;
    if !(h.is_finite() && h > 0.0) {
        return Err(GridError::Settings(format!("cell size {h} mm must be positive")));
    }
    if settings.subdivisions > 4 || settings.samples_per_leaf_axis == 0 || settings.samples_per_leaf_axis > 8 {
        return Err(GridError::Settings("subdivisions must be 0..4 and samples per leaf axis 1..8".into()));
    }
    if settings.pooling_steps > 6 {
        return Err(GridError::Settings("pooling steps must be 0..6".into()));
    }
    let extent = hi - lo;
    let cell_dims = [0, 1, 2].map(|a| ((extent[a] / h).ceil() as usize).max(1));
    let total: usize = cell_dims.iter().try_fold(1usize, |acc, &d| acc.checked_mul(d)).unwrap_or(usize::MAX);
    if total > MAX_LATTICE_CELLS {
        return Err(GridError::TooLarge { cells: total, limit: MAX_LATTICE_CELLS });
    }
    let per_cell = ((1u64 << settings.subdivisions) * settings.samples_per_leaf_axis as u64).pow(3);
    let samples = (total as u64).saturating_mul(per_cell);
    if samples > MAX_INSIDE_SAMPLES {
        return Err(GridError::TooMuchWork { samples, limit: MAX_INSIDE_SAMPLES });
    }
    // Centre the lattice on the organ's box.
    let origin = lo - (Vector3::new(cell_dims[0] as f64, cell_dims[1] as f64, cell_dims[2] as f64) * h - extent) * 0.5;
    let levels = settings.subdivisions;
    let leaves_per_axis = 1usize << levels;
    let s = settings.samples_per_leaf_axis as usize;
    let n = leaves_per_axis * s; // fine samples per cell axis
    let [cx, cy, _] = cell_dims;
    let done = std::sync::atomic::AtomicU64::new(0);

    // Each cell -> (kind, fraction, quadrature) in parallel over z-slabs of cells.
    let per_slab: Vec<Vec<([usize; 3], CellKind, f64, Vec<([f64; 3], f64)>)>> = (0..cell_dims[2])
        .into_par_iter()
        .map(|k| {
            if cancel.is_cancelled() {
                return Vec::new();
            }
            let mut out = Vec::new();
            let mut samples = vec![false; n * n * n];
            for j in 0..cy {
                for i in 0..cx {
                    let cell_lo = origin + Vector3::new(i as f64, j as f64, k as f64) * h;
                    if let Some((kind, fraction, qps)) = classify_cell(cell_lo, h, levels, s, &inside, &mut samples) {
                        out.push(([i, j, k], kind, fraction, qps));
                    }
                }
            }
            let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            progress.report(d, cell_dims[2] as u64, "classifying cells");
            out
        })
        .collect();
    cancel.check()?;
    let mut occupied = Vec::new();
    let mut quadrature = Vec::new();
    // Slabs are in k order and cells inside in (j, i) order: cell numbers follow the lattice.
    for (ijk, kind, fraction, qps) in per_slab.into_iter().flatten() {
        let cell = occupied.len() as u32;
        occupied.push((ijk, kind, fraction));
        quadrature.extend(qps.into_iter().map(|(xi, weight_mm3)| QuadPoint { cell, xi, weight_mm3 }));
    }
    if occupied.is_empty() {
        // The organ is there, but no cell's samples fall inside it: cells larger than the organ.
        return Err(GridError::CellsTooLarge { cell_size_mm: h, extent_mm: [extent.x, extent.y, extent.z] });
    }
    Ok(assemble_grid(origin, h, cell_dims, occupied, quadrature, settings.pooling_steps))
}

/// One cell of the lattice from its corner: None when no sample of it is inside; else its kind,
/// inside fraction and quadrature points (2x2x2 Gauss inside, one point per finest sub-cell
/// with inside samples on the boundary). `samples` is scratch for the n^3 inside flags.
#[allow(clippy::type_complexity)]
fn classify_cell(
    cell_lo: Vector3<f64>,
    h: f64,
    levels: u32,
    s: usize,
    inside: &(impl Fn(&Point3<f64>) -> bool + Sync),
    samples: &mut [bool],
) -> Option<(CellKind, f64, Vec<([f64; 3], f64)>)> {
    let leaves_per_axis = 1usize << levels;
    let n = leaves_per_axis * s;
    let mut count = 0usize;
    for c in 0..n {
        for b in 0..n {
            for a in 0..n {
                let p = cell_lo + Vector3::new(a as f64 + 0.5, b as f64 + 0.5, c as f64 + 0.5) * (h / n as f64);
                let v = inside(&Point3::from(p));
                samples[a + n * (b + n * c)] = v;
                count += v as usize;
            }
        }
    }
    if count == 0 {
        return None;
    }
    let fraction = count as f64 / (n * n * n) as f64;
    let cell_vol = h * h * h;
    let mut qps = Vec::new();
    let kind = if count == n * n * n {
        // Regular cell: 2x2x2 Gauss.
        let g = 1.0 / 3f64.sqrt();
        for c in HEX_CORNERS {
            qps.push((c.map(|v| if v == 1 { g } else { -g }), cell_vol / 8.0));
        }
        CellKind::Inside
    } else {
        // Boundary cell: one point at the centre of each finest sub-cell with inside
        // samples, weighted by that sub-cell's inside fraction.
        let leaf_vol = cell_vol / (leaves_per_axis.pow(3)) as f64;
        for lc in 0..leaves_per_axis {
            for lb in 0..leaves_per_axis {
                for la in 0..leaves_per_axis {
                    let mut inside_count = 0;
                    for c in 0..s {
                        for b in 0..s {
                            for a in 0..s {
                                inside_count += samples[(la * s + a) + n * ((lb * s + b) + n * (lc * s + c))] as usize;
                            }
                        }
                    }
                    if inside_count > 0 {
                        let xi = [la, lb, lc].map(|l| -1.0 + (2 * l + 1) as f64 / leaves_per_axis as f64);
                        qps.push((xi, leaf_vol * inside_count as f64 / (s * s * s) as f64));
                    }
                }
            }
        }
        CellKind::Boundary
    };
    Some((kind, fraction, qps))
}

/// The grid of a segmentation's organ, with the figures `umesh grid` reports.
#[derive(Debug)]
pub struct GridOutput {
    pub grid: ImmersedGrid,
    pub stats: GridStats,
    /// Organ voxels x voxel volume.
    pub segmentation_volume_mm3: f64,
}

pub fn run_grid(
    seg: &crate::segmentation::Segmentation,
    settings: &GridSettings,
    progress: &Progress,
    cancel: &Cancel,
) -> Result<GridOutput, GridError> {
    let mask = seg.organ_mask();
    let segmentation_volume_mm3 = mask.volume_mm3();
    let grid = ImmersedGrid::from_mask(&mask, settings, progress, cancel)?;
    let stats = grid.stats();
    Ok(GridOutput { grid, stats, segmentation_volume_mm3 })
}

/// The grid as a VTK unstructured grid (hexahedra with kind and volume fraction).
pub fn grid_vtu(grid: &ImmersedGrid) -> crate::vtk::Vtu {
    use crate::vtk::{VTK_HEXAHEDRON, VtkData, Vtu};
    Vtu {
        points: grid.node_positions(),
        cells: grid.cells.iter().map(|c| (c.nodes.iter().map(|&n| n as usize).collect(), VTK_HEXAHEDRON)).collect(),
        point_data: vec![],
        cell_data: vec![
            VtkData::Scalars("volume_fraction".into(), grid.cells.iter().map(|c| c.volume_fraction).collect()),
            VtkData::Scalars(
                "boundary".into(),
                grid.cells.iter().map(|c| (c.kind == CellKind::Boundary) as u8 as f64).collect(),
            ),
        ],
    }
}
