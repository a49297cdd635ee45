//! Grid preview: the sparse hexahedral grid drawn over the organ, inside cells faint green,
//! boundary cells orange with an opacity that follows their inside volume fraction.

use crate::app::shell::convert::{UNITS_PER_MM, bevy_from_world};
use crate::app::state::GridState;
use bevy::prelude::*;
use nalgebra::Vector3;

fn draw_grid(grid: Res<GridState>, mut gizmos: Gizmos) {
    let (true, Some(g)) = (grid.show, &grid.grid) else { return };
    let h = g.cell_size_mm;
    for c in &g.cells {
        let [i, j, k] = c.ijk;
        let centre = g.origin_mm + Vector3::new(i as f64 + 0.5, j as f64 + 0.5, k as f64 + 0.5) * h;
        let color = match c.kind {
            umesh_core::grid::CellKind::Inside => Color::srgba(0.3, 0.9, 0.4, 0.18),
            _ => Color::srgba(1.0, 0.55, 0.1, 0.25 + 0.75 * c.volume_fraction as f32),
        };
        gizmos.cube(
            Transform::from_translation(bevy_from_world(&centre)).with_scale(Vec3::splat(h as f32 * UNITS_PER_MM)),
            color,
        );
    }
}

pub struct GridPreviewPlugin;

impl Plugin for GridPreviewPlugin {
    fn build(&self, app: &mut App) {
        app.add_systems(Update, draw_grid.run_if(in_state(crate::app::state::Mode::Model)));
    }
}
