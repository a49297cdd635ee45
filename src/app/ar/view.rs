//! The AR view's registry entry: the source, playback and alignment left, the overlaid camera
//! image in the middle, the frame's figures right (no 3-D view).

use crate::app::ar::Ar;
use crate::app::shell::tasks::Jobs;
use crate::app::shell::views::{View, ViewEntry};
use crate::app::state::{ActiveModel, Mode, Organ, UiMessages};
use bevy::prelude::*;
use bevy_egui::egui;

pub struct ArView;

impl View for ArView {
    fn entry(world: &mut World) -> ViewEntry {
        ViewEntry {
            mode: Mode::Ar,
            name: "AR view",
            shows_3d: false,
            keys: &[],
            panels: world.register_system(panels),
            shortcuts: None,
            scale: None,
        }
    }
}

#[derive(bevy::ecs::system::SystemParam)]
struct ArState<'w> {
    ar: ResMut<'w, Ar>,
    organ: Res<'w, Organ>,
    active: Res<'w, ActiveModel>,
    messages: ResMut<'w, UiMessages>,
    jobs: ResMut<'w, Jobs>,
    proxy: Option<Res<'w, bevy::winit::EventLoopProxyWrapper>>,
}

fn panels(InMut(root): InMut<egui::Ui>, mut s: ArState, mut texture: Local<Option<egui::TextureHandle>>) {
    // Frames arriving wake the event loop (the window updates only on events otherwise).
    let waker = s.proxy.as_ref().map(|p| {
        let p = (**p).clone();
        Box::new(move || {
            let _ = p.send_event(bevy::winit::WinitUserEvent::WakeUp);
        }) as crate::app::ar::Waker
    });
    let mut synth = false;
    egui::Panel::left("ar_left").default_size(290.0).show(root, |ui| {
        egui::ScrollArea::vertical().show(ui, |ui| {
            synth = crate::app::ar::panel::left_panel(ui, &mut s.ar, &s.organ, &s.active, &mut s.messages, waker)
        });
    });
    egui::Panel::right("ar_right").default_size(250.0).show(root, |ui| {
        egui::ScrollArea::vertical().show(ui, |ui| crate::app::ar::panel::right_panel(ui, &s.ar));
    });
    egui::CentralPanel::default().show(root, |ui| crate::app::ar::panel::central(ui, &mut s.ar, &mut texture));
    if synth {
        match &s.organ.data {
            Some(d) if !s.jobs.is_running("synthetic") => {
                let job = crate::app::ar::panel::synth_job(
                    d.clone(),
                    s.active.dir.clone(),
                    crate::app::ar::panel::synthetic_recording_dir(),
                    20,
                );
                s.jobs.spawn("synthetic recording", job);
            }
            Some(_) => {}
            None => s.messages.error("load an organ first"),
        }
    }
}
