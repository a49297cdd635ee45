//! The model view's registry entry: the organ, its grid, probes and simulation in the 3-D view,
//! with the data and simulation panels either side.

use crate::app::model::panel::{AppState, left_panel, right_panel, start_simulation};
use crate::app::shell::views::{View, ViewEntry};
use crate::app::state::{Mode, Simulation};
use bevy::prelude::*;
use bevy_egui::egui;

pub struct ModelView;

impl View for ModelView {
    fn entry(world: &mut World) -> ViewEntry {
        ViewEntry {
            mode: Mode::Model,
            name: "Model",
            shows_3d: true,
            keys: &[
                ("left click", "place a force probe on the organ"),
                ("left drag", "pull the probe: direction and magnitude"),
                ("G", "show or hide the grid"),
                ("D", "show the rest or deformed organ"),
                ("S", "simulate the probes' forces (SVK)"),
                ("Delete", "delete the selected probe"),
            ],
            panels: world.register_system(panels),
            shortcuts: Some(world.register_system(shortcuts)),
            scale: Some(world.register_system(scale)),
        }
    }
}

fn panels(InMut(root): InMut<egui::Ui>, mut st: AppState) {
    egui::Panel::left("left").default_size(260.0).show(root, |ui| {
        egui::ScrollArea::vertical().show(ui, |ui| left_panel(ui, &mut st));
    });
    egui::Panel::right("right").default_size(280.0).show(root, |ui| {
        egui::ScrollArea::vertical().show(ui, |ui| right_panel(ui, &mut st));
    });
}

fn shortcuts(keys: Res<ButtonInput<KeyCode>>, mut st: AppState) {
    // Ctrl+S saves the session (the shell's); S alone simulates.
    if !crate::app::shell::ctrl_held(&keys) && keys.just_pressed(KeyCode::KeyS) {
        start_simulation(&mut st);
    }
    if keys.just_pressed(KeyCode::KeyG) {
        st.grid.show = !st.grid.show;
    }
    if keys.just_pressed(KeyCode::KeyD) {
        st.sim.show_deformed = !st.sim.show_deformed;
        st.sim.generation += 1;
    }
    if keys.just_pressed(KeyCode::Delete)
        && let Some(i) = st.probes.selected
    {
        st.probes.remove(i);
    }
}

fn scale(sim: Res<Simulation>) -> Option<(f64, String)> {
    sim.result.as_ref().filter(|_| sim.show_deformed).map(|d| (d.max_mm, format!("{} displacement", d.source)))
}
