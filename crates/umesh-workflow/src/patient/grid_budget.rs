//! The grid a patient's job can train within its hour: a large organ's cells grow until its
//! grid holds at most `PrepareSettings::max_grid_nodes` nodes.

use super::folder::PrepareSettings;
use umesh_core::grid::ImmersedGrid;
use umesh_core::segmentation::Segmentation;
use umesh_core::{Cancel, Progress};
use umesh_net::NetError;

/// The cell size grows by whole millimetres: the 2.15 l SOFA liver's 9 mm (4925 nodes) is
/// measured within the hour; its 8.5 mm (5703 nodes, the same padded grid) is not.
const CELL_STEP_MM: f64 = 1.0;

/// Cells beyond this are not tried: the grid stays as large as that makes it.
const MAX_CELL_MM: f64 = 30.0;

/// `settings` with the cell size the hour affords: as asked when the organ's grid has at most
/// `max_grid_nodes` nodes (or the limit is 0), else the smallest whole-millimetre step above it whose
/// grid fits; `grid_description` says which and why.
pub fn fit_grid_to_budget(
    seg: &Segmentation,
    settings: &PrepareSettings,
    cancel: &Cancel,
) -> Result<PrepareSettings, NetError> {
    let mask = seg.organ_mask();
    let nodes = |cell_size_mm: f64| -> Result<usize, NetError> {
        let grid = umesh_core::grid::GridSettings { cell_size_mm, ..settings.dataset.grid.clone() };
        let g = ImmersedGrid::from_mask(&mask, &grid, &Progress::none(), cancel)
            .map_err(|e| NetError::Dataset(umesh_core::dataset::DatasetError::Grid(e)))?;
        Ok(g.node_count())
    };
    let asked = settings.dataset.grid.cell_size_mm;
    let first = nodes(asked)?;
    let limit = settings.max_grid_nodes;
    let mut out = settings.clone();
    if limit == 0 || first <= limit {
        out.grid_description = format!("{asked} mm cells: {first} nodes");
        return Ok(out);
    }
    let mut cell = asked;
    let mut n = first;
    while n > limit && cell + CELL_STEP_MM <= MAX_CELL_MM {
        cancel.check()?;
        cell += CELL_STEP_MM;
        n = nodes(cell)?;
    }
    out.dataset.grid.cell_size_mm = cell;
    out.grid_description = format!(
        "{cell} mm cells: {n} nodes (at {asked} mm the grid had {first}, over the {limit} a patient's hour trains; --max-grid-nodes 0 keeps the cell size asked)"
    );
    Ok(out)
}
