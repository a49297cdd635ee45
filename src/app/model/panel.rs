//! The model view's panels: left (data, scan, grid, laparoscope, simulation, rehearsal) and
//! right (grid statistics, probes, the Newton history). They read and edit the state
//! resources; the work itself is started through `Jobs`.

use crate::app::model::compute::{grid_job, simulate_job};
use crate::app::model::probes::{ProbeSettings, Rehearsal, start_fe_check};
use crate::app::shell::tasks::Jobs;
use crate::app::state::*;
use bevy::prelude::*;
use bevy_egui::egui;
use egui_plot::{Line, Plot, PlotPoints};

#[derive(bevy::ecs::system::SystemParam)]
/// The state the model view (and the menus) read and edit.
pub struct AppState<'w> {
    pub organ: ResMut<'w, Organ>,
    pub grid: ResMut<'w, GridState>,
    pub probes: ResMut<'w, Probes>,
    pub sim: ResMut<'w, Simulation>,
    pub jobs: ResMut<'w, Jobs>,
    pub messages: ResMut<'w, UiMessages>,
    pub pending: ResMut<'w, PendingOpenRes>,
    pub probe_settings: ResMut<'w, ProbeSettings>,
    pub rehearsal: ResMut<'w, Rehearsal>,
    pub setup: ResMut<'w, crate::app::setup::ObservationSetup>,
    pub orbit: Res<'w, crate::app::shell::camera::OrbitCamera>,
    pub ct: ResMut<'w, crate::app::ct::CtView>,
}

pub fn left_panel(ui: &mut egui::Ui, st: &mut AppState) {
    ui.heading("Data");
    match &st.organ.data {
        Some(d) => {
            ui.label(format!("Organ: {}", d.source));
            for s in &d.structures {
                let c = egui::Color32::from_rgb(s.color[0], s.color[1], s.color[2]);
                ui.colored_label(c, format!("■ {} (label {})", s.name, s.label));
            }
        }
        None => {
            ui.label("No organ loaded (File > Open).");
        }
    }
    ui.separator();
    ui.heading("Scan");
    crate::app::ct::ct_ui(ui, &mut st.ct, &st.organ);
    ui.separator();
    ui.heading("Grid");
    let mut h = st.grid.settings.cell_size_mm as f32;
    let r = ui.add(egui::Slider::new(&mut h, 3.0..=15.0).text("cell size (mm)"));
    st.grid.settings.cell_size_mm = h as f64;
    let mut sub = st.grid.settings.subdivisions;
    let r2 = ui.add(egui::Slider::new(&mut sub, 0..=3).text("boundary subdivisions"));
    st.grid.settings.subdivisions = sub;
    let rebuild =
        r.drag_stopped() || r2.drag_stopped() || (r.changed() && !r.dragged()) || (r2.changed() && !r2.dragged());
    if (ui.button("Build grid").clicked() || rebuild)
        && let Some(d) = &st.organ.data
    {
        st.jobs.spawn("grid", grid_job(d.seg.clone(), st.grid.settings.clone()));
    }
    ui.separator();
    ui.heading("Laparoscope (dataset camera)");
    crate::app::setup::camera_ui(ui, &mut st.setup, &st.orbit);
    ui.separator();
    ui.heading("Simulation");
    crate::app::setup::fixed_ui(ui, &mut st.sim.fixed, st.organ.data.as_ref());
    ui.add(
        egui::Slider::new(&mut st.probe_settings.newtons_per_mm, 0.001..=0.1)
            .logarithmic(true)
            .text("N per mm of drag"),
    );
    let can = st.organ.data.is_some()
        && st.grid.grid.is_some()
        && !st.probes.list.is_empty()
        && !st.jobs.is_running("simulate");
    if ui
        .add_enabled(can, egui::Button::new("Simulate (SVK) (S)"))
        .on_disabled_hover_text("needs a grid and at least one probe")
        .clicked()
    {
        start_simulation(st);
    }
    ui.separator();
    ui.heading("Rehearsal");
    if ui.button("Load the bundled model").clicked()
        && let Some(d) = &st.organ.data
    {
        st.jobs.spawn(
            "load model",
            crate::app::model::probes::load_model_job(
                umesh_workflow::input::bundled_model(),
                "model.safetensors".into(),
                d.clone(),
            ),
        );
    }
    let has_model = st.rehearsal.model.is_some();
    ui.add_enabled(has_model, egui::Checkbox::new(&mut st.rehearsal.enabled, "live U-Net deformation"));
    ui.add(egui::Slider::new(&mut st.rehearsal.radius_mm, 5.0..=60.0).text("probe radius (mm)"));
    if ui.add_enabled(has_model && !st.probes.list.is_empty(), egui::Button::new("FE check")).clicked()
        && let Err(e) = start_fe_check(&mut st.jobs, &st.rehearsal, &st.probes, &st.organ, &st.probe_settings)
    {
        st.messages.error(format!("{e:#}"));
    }
    if let Some((mean, max)) = st.sim.check {
        ui.label(format!("U-Net vs SVK: {mean:.2} mm mean, {max:.2} mm max"));
    }
}

/// The SVK solve of the probes' forces, when a grid and a probe exist and none runs.
pub fn start_simulation(st: &mut AppState) {
    if st.probes.list.is_empty() || st.jobs.is_running("simulate") {
        return;
    }
    if let (Some(d), Some(g)) = (&st.organ.data, &st.grid.grid) {
        st.jobs.spawn("simulate", simulate_job(d.clone(), g.clone(), st.sim.fixed.clone(), st.probes.list.clone()));
    }
}

pub fn right_panel(ui: &mut egui::Ui, st: &mut AppState) {
    ui.heading("Inspector");
    if let Some(s) = &st.grid.stats {
        egui::Grid::new("grid_stats").striped(true).show(ui, |ui| {
            ui.label("cells");
            ui.label(format!("{} ({} inside, {} boundary)", s.cells, s.inside_cells, s.boundary_cells));
            ui.end_row();
            ui.label("nodes");
            ui.label(s.nodes.to_string());
            ui.end_row();
            ui.label("volume error");
            let err = 100.0 * (s.grid_volume_mm3 - st.grid.voxel_volume_mm3) / st.grid.voxel_volume_mm3.max(1e-9);
            ui.label(format!("{err:+.2} %"));
            ui.end_row();
            ui.label("padded shape");
            ui.label(format!("{:?}", s.padded_shape));
            ui.end_row();
        });
    } else {
        ui.label("No grid yet.");
    }
    ui.separator();
    ui.label(format!("Probes ({}): click the organ to add, drag to pull", st.probes.list.len()));
    let mut remove = None;
    let mut changed = false;
    let mut selected = st.probes.selected;
    for (i, p) in st.probes.list.iter_mut().enumerate() {
        ui.horizontal(|ui| {
            if ui.selectable_label(selected == Some(i), format!("#{}", i + 1)).clicked() {
                selected = Some(i);
            }
            for c in 0..3 {
                changed |= ui.add(egui::DragValue::new(&mut p.force_n[c]).speed(0.01).max_decimals(3)).changed();
            }
            ui.label("N");
            if ui.small_button("delete").clicked() {
                remove = Some(i);
            }
        });
    }
    st.probes.selected = selected;
    if changed {
        st.probes.generation += 1;
    }
    if let Some(i) = remove {
        st.probes.remove(i);
    }
    if let Some(d) = &st.sim.result {
        ui.separator();
        ui.label(format!("{}: max {:.2} mm, mean {:.2} mm ({:.0} ms)", d.source, d.max_mm, d.mean_mm, d.solve_ms));
        if !d.history.is_empty() {
            let pts: PlotPoints = d.history.iter().map(|&(i, r)| [i as f64, r.max(1e-16).log10()]).collect();
            Plot::new("newton").height(120.0).x_axis_label("iteration").y_axis_label("log10 residual").show(ui, |p| {
                p.line(Line::new("residual", pts));
            });
        }
    }
}
