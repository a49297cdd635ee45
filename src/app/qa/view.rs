//! The dataset QA view's registry entry: a sample's FE displacement (and the model's error on
//! it) in the 3-D view, the browser left, the sample's figures and the scan right.

use crate::app::qa::Qa;
use crate::app::shell::views::{View, ViewEntry};
use crate::app::state::{ActiveModel, Mode, Organ, UiMessages};
use bevy::prelude::*;
use bevy_egui::egui;

pub struct QaView;

impl View for QaView {
    fn entry(world: &mut World) -> ViewEntry {
        ViewEntry {
            mode: Mode::Qa,
            name: "Dataset QA",
            shows_3d: true,
            keys: &[("Left / Right", "the previous / next sample"), ("R", "flag or unflag the sample")],
            panels: world.register_system(panels),
            shortcuts: Some(world.register_system(shortcuts)),
            scale: Some(world.register_system(scale)),
        }
    }
}

fn panels(
    InMut(root): InMut<egui::Ui>,
    mut qa: ResMut<Qa>,
    organ: Res<Organ>,
    active: Res<ActiveModel>,
    mut ct: ResMut<crate::app::ct::CtView>,
    mut messages: ResMut<UiMessages>,
) {
    egui::Panel::left("qa_left").default_size(280.0).show(root, |ui| {
        egui::ScrollArea::vertical()
            .show(ui, |ui| crate::app::qa::panel::left_panel(ui, &mut qa, &organ, &active, &mut messages));
    });
    egui::Panel::right("qa_right").default_size(280.0).show(root, |ui| {
        egui::ScrollArea::vertical().show(ui, |ui| {
            crate::app::qa::panel::right_panel(ui, &qa);
            if organ.data.as_ref().is_some_and(|d| d.ct.is_some()) {
                ui.separator();
                ui.heading("Scan");
                ui.weak("yellow: the organ at rest; cyan: the sample's FE deformation");
                crate::app::ct::ct_ui(ui, &mut ct, &organ);
            }
        });
    });
}

fn shortcuts(keys: Res<ButtonInput<KeyCode>>, mut qa: ResMut<Qa>, mut messages: ResMut<UiMessages>) {
    if keys.just_pressed(KeyCode::ArrowRight) {
        qa.step(1);
    }
    if keys.just_pressed(KeyCode::ArrowLeft) {
        qa.step(-1);
    }
    if keys.just_pressed(KeyCode::KeyR) {
        match qa.toggle_flag() {
            Ok(m) => messages.info(m),
            Err(e) => messages.error(format!("{e:#}")),
        }
    }
}

fn scale(qa: Res<Qa>) -> Option<(f64, String)> {
    qa.sample.as_ref().map(|s| (s.max_mm as f64, "FE displacement; prediction: error".to_string()))
}
