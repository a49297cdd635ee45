//! The jobs view's registry entry: the dataset, patient and training forms left, the queue
//! and the training dashboard in the middle (no 3-D view).

use crate::app::jobs::panel::{JobsUi, forms_panel, queue_and_dashboard};
use crate::app::jobs::queue::WorkQueue;
use crate::app::setup::ObservationSetup;
use crate::app::shell::views::{View, ViewEntry};
use crate::app::state::{ActiveModel, Mode, ModelToLoad, OpenPatient, Organ, Simulation, UiMessages};
use bevy::prelude::*;
use bevy_egui::egui;

pub struct JobsView;

impl View for JobsView {
    fn entry(world: &mut World) -> ViewEntry {
        ViewEntry {
            mode: Mode::Jobs,
            name: "Jobs",
            shows_3d: false,
            keys: &[],
            panels: world.register_system(panels),
            shortcuts: None,
            scale: None,
        }
    }
}

#[derive(bevy::ecs::system::SystemParam)]
struct JobsState<'w> {
    ui: ResMut<'w, JobsUi>,
    queue: ResMut<'w, WorkQueue>,
    organ: Res<'w, Organ>,
    setup: Res<'w, ObservationSetup>,
    sim: Res<'w, Simulation>,
    messages: ResMut<'w, UiMessages>,
    active: ResMut<'w, ActiveModel>,
    patient: ResMut<'w, OpenPatient>,
    to_load: ResMut<'w, ModelToLoad>,
}

fn panels(InMut(root): InMut<egui::Ui>, mut s: JobsState) {
    egui::Panel::left("jobs_left").default_size(300.0).show(root, |ui| {
        egui::ScrollArea::vertical()
            .show(ui, |ui| forms_panel(ui, &mut s.ui, &mut s.queue, &s.organ, &s.setup, &s.sim.fixed, &mut s.messages));
    });
    let load = egui::CentralPanel::default()
        .show(root, |ui| queue_and_dashboard(ui, &mut s.ui, &mut s.queue, &s.active, &mut s.patient))
        .inner;
    if let Some((dir, file)) = load {
        *s.active = ActiveModel { dir: dir.clone(), checkpoint: file.clone() };
        // The rehearsal (model view) loads it onto the organ.
        s.to_load.0 = Some(ActiveModel { dir, checkpoint: file });
    }
}
