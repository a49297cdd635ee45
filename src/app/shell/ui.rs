//! The window's layout: the menu bar, the bottom bar (status and jobs), the help and error
//! windows, and the active view's panels (each view's own `panel` module) around the 3-D view.

use crate::app::model::compute::{inspect_job, load_job};
use crate::app::model::panel::{AppState, left_panel, right_panel, start_simulation};
use crate::app::state::*;
use bevy::prelude::*;
use bevy::tasks::{IoTaskPool, Task, futures::check_ready};
use bevy_egui::{EguiContexts, egui};

#[derive(Resource, Default)]
pub struct UiState {
    pub show_help: bool,
    pub frame_ms: f32,
    /// The open file dialogs, at most one per purpose.
    dialogs: Vec<(Dialog, Task<Option<std::path::PathBuf>>)>,
}

/// What a file dialog was opened for: its answer is applied by purpose, in one place.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Dialog {
    Segmentation,
    Patient,
    Scan,
    OpenSession,
    SaveSession,
    ExportPng,
}

impl Dialog {
    /// The native dialog for this purpose, on the I/O pool.
    fn spawn(self) -> Task<Option<std::path::PathBuf>> {
        let pick = |filter: &'static str, ext: &'static [&'static str]| rfd::AsyncFileDialog::new().add_filter(filter, ext);
        let save = |name: &'static str, ext: &'static str| rfd::AsyncFileDialog::new().add_filter(ext, &[ext]).set_file_name(name);
        IoTaskPool::get().spawn(async move {
            let picked = match self {
                Dialog::Segmentation => pick("segmentation / mesh", &["nii", "gz", "hdr", "obj", "ply", "stl"]).pick_file().await,
                Dialog::Patient => rfd::AsyncFileDialog::new().pick_folder().await,
                Dialog::Scan => pick("NIfTI", &["nii", "gz", "hdr"]).pick_file().await,
                Dialog::OpenSession => pick("umesh session", &["json"]).pick_file().await,
                Dialog::SaveSession => save("session.json", "json").save_file().await,
                Dialog::ExportPng => save("view.png", "png").save_file().await,
            };
            picked.map(|f| f.path().to_path_buf())
        })
    }
}

impl UiState {
    /// Open the dialog for `purpose` unless one is already open for it.
    fn open(&mut self, purpose: Dialog) {
        if !self.dialogs.iter().any(|(p, _)| *p == purpose) {
            self.dialogs.push((purpose, purpose.spawn()));
        }
    }

    /// The dialogs answered since the last frame (None: cancelled), removed from the open ones.
    fn answered(&mut self) -> Vec<(Dialog, Option<std::path::PathBuf>)> {
        let mut out = Vec::new();
        self.dialogs.retain_mut(|(purpose, task)| match check_ready(task) {
            Some(picked) => {
                out.push((*purpose, picked));
                false
            }
            None => true,
        });
        out
    }
}

/// The state of the jobs, QA and AR views.
#[derive(bevy::ecs::system::SystemParam)]
pub struct Views<'w> {
    mode: ResMut<'w, Mode>,
    jobs_ui: ResMut<'w, crate::app::jobs::panel::JobsUi>,
    queue: ResMut<'w, crate::app::jobs::queue::WorkQueue>,
    qa: ResMut<'w, crate::app::qa::Qa>,
    ar: ResMut<'w, crate::app::ar::Ar>,
    active: ResMut<'w, ActiveModel>,
    patient: ResMut<'w, OpenPatient>,
    proxy: Option<Res<'w, bevy::winit::EventLoopProxyWrapper>>,
    recent: ResMut<'w, crate::app::model::session::Recent>,
    session_file: Res<'w, crate::app::model::session::SessionFile>,
    save: ResMut<'w, crate::app::model::session::SaveRequest>,
    export: ResMut<'w, crate::app::model::session::PendingExport>,
}

fn menu_bar(
    ui: &mut egui::Ui,
    st: &mut AppState,
    uis: &mut UiState,
    view: &mut crate::app::shell::view3d::View3d,
    views: &mut Views,
    mode: &mut Mode,
) {
    egui::MenuBar::new().ui(ui, |ui| {
        ui.menu_button("File", |ui| {
            if ui.button("Open segmentation or mesh...").clicked() {
                uis.open(Dialog::Segmentation);
            }
            if ui.button("Open patient folder...").on_hover_text("a folder made by umesh prepare (or New patient in Jobs)").clicked() {
                uis.open(Dialog::Patient);
            }
            let has_organ = st.organ.data.is_some();
            if ui
                .add_enabled(has_organ, egui::Button::new("Open CT image..."))
                .on_hover_text("the scan of the loaded segmentation: slices under the model")
                .on_disabled_hover_text("open a segmentation first")
                .clicked()
            {
                uis.open(Dialog::Scan);
            }
            if ui.button("Bundled phantom").clicked() {
                st.jobs.spawn("load phantom", load_job(OpenRequest::default()));
            }
            ui.separator();
            if ui.button("Open session...").clicked() {
                uis.open(Dialog::OpenSession);
            }
            let current = views.session_file.0.clone();
            let label = match &current {
                Some(p) => format!("Save session (Ctrl+S): {}", p.file_name().map(|n| n.to_string_lossy()).unwrap_or_default()),
                None => "Save session (Ctrl+S)...".into(),
            };
            if ui.add_enabled(has_organ, egui::Button::new(label)).clicked() {
                match current {
                    Some(p) => views.save.0 = Some(p),
                    None => uis.open(Dialog::SaveSession),
                }
            }
            if ui.add_enabled(has_organ, egui::Button::new("Save session as...")).clicked() {
                uis.open(Dialog::SaveSession);
            }
            if ui.button("Export view as PNG...").clicked() {
                uis.open(Dialog::ExportPng);
            }
            ui.separator();
            ui.menu_button("Recent", |ui| {
                if views.recent.list.is_empty() {
                    ui.weak("nothing yet");
                }
                let mut open = None;
                for (p, kind) in &views.recent.list {
                    let what = match kind {
                        crate::app::model::session::RecentKind::Session => "session",
                        crate::app::model::session::RecentKind::Patient => "patient",
                        crate::app::model::session::RecentKind::Segmentation => "segmentation",
                    };
                    if ui.button(format!("{} ({what})", p.display())).clicked() {
                        open = Some((p.clone(), *kind));
                    }
                }
                if let Some((p, kind)) = open {
                    open_recent(st, p, kind);
                }
            });
        });
        ui.menu_button("View", |ui| {
            ui.checkbox(&mut st.grid.show, "Grid (G)");
            if ui.checkbox(&mut st.sim.show_deformed, "Deformed (D)").changed() {
                st.sim.generation += 1;
            }
            if ui.checkbox(&mut st.sim.show_ghost, "Rest shape ghost").on_hover_text("behind the deformed organ").changed() {
                st.sim.generation += 1;
            }
            ui.separator();
            let mut q = view.quality.clone();
            ui.add(egui::Slider::new(&mut q.render_scale, 0.25..=1.0).text("3-D resolution"));
            ui.checkbox(&mut q.shadows, "Shadows");
            if let Some((name, software)) = &view.adapter {
                ui.weak(format!("{name}{}", if *software { " (software: quarter resolution, no shadows by default)" } else { "" }));
            }
            if q != view.quality {
                view.quality = q;
                view.quality_locked = true;
            }
        });
        if ui.button("Help (F1)").clicked() {
            uis.show_help = !uis.show_help;
        }
        ui.separator();
        for (m, name) in Mode::ALL {
            ui.selectable_value(mode, m, name);
        }
    });
}

/// The colour map's scale in the 3-D view's lower right corner: 0 to `max_mm`.
fn scale_bar(painter: &egui::Painter, rect: egui::Rect, max_mm: f64, what: &str) {
    let (w, h) = (14.0, (rect.height() * 0.3).clamp(60.0, 180.0));
    let x0 = rect.right() - 70.0;
    let y1 = rect.bottom() - 30.0;
    let bar = egui::Rect::from_min_max(egui::pos2(x0, y1 - h), egui::pos2(x0 + w, y1));
    let steps = 32;
    for i in 0..steps {
        let t = (i as f32 + 0.5) / steps as f32;
        let c = crate::app::shell::convert::colormap_srgb(t);
        let y = bar.bottom() - bar.height() * i as f32 / steps as f32;
        let r = egui::Rect::from_min_max(egui::pos2(bar.left(), y - bar.height() / steps as f32), egui::pos2(bar.right(), y));
        painter.rect_filled(r, 0.0, egui::Color32::from_rgb((c[0] * 255.0) as u8, (c[1] * 255.0) as u8, (c[2] * 255.0) as u8));
    }
    painter.rect_stroke(bar, 0.0, egui::Stroke::new(1.0, egui::Color32::GRAY), egui::StrokeKind::Outside);
    let font = egui::FontId::proportional(12.0);
    let text = egui::Color32::from_gray(230);
    painter.text(egui::pos2(bar.right() + 4.0, bar.top()), egui::Align2::LEFT_CENTER, format!("{max_mm:.1} mm"), font.clone(), text);
    painter.text(egui::pos2(bar.right() + 4.0, bar.bottom()), egui::Align2::LEFT_CENTER, "0", font.clone(), text);
    painter.text(egui::pos2(bar.right() + 8.0, bar.top() - 14.0), egui::Align2::RIGHT_BOTTOM, what, font, text);
}

fn open_recent(st: &mut AppState, p: std::path::PathBuf, kind: crate::app::model::session::RecentKind) {
    use crate::app::model::session::RecentKind;
    match kind {
        RecentKind::Session => st.jobs.spawn("open session", crate::app::model::session::open_job(p)),
        RecentKind::Patient => st.jobs.spawn("open patient", crate::app::model::compute::open_patient_job(p)),
        RecentKind::Segmentation => st.jobs.spawn("inspect", inspect_job(p)),
    };
}

fn bottom_panel(ui: &mut egui::Ui, st: &mut AppState, uis: &UiState) {
    ui.horizontal(|ui| {
        ui.label(format!("{:.1} ms/frame", uis.frame_ms));
        ui.separator();
        if let Some((lvl, m)) = st.messages.last() {
            let c = if *lvl == Level::Error { egui::Color32::LIGHT_RED } else { ui.visuals().text_color() };
            ui.colored_label(c, m);
        }
    });
    let mut cancel = None;
    for j in &st.jobs.running {
        let p = j.progress.lock().map(|p| p.clone()).unwrap_or_default();
        ui.horizontal(|ui| {
            let frac = if p.total > 0 { p.done as f32 / p.total as f32 } else { 0.0 };
            ui.label(&j.label);
            ui.add(egui::ProgressBar::new(frac).desired_width(220.0).text(format!(
                "{} ({:.0} s)",
                p.message,
                j.started.elapsed().as_secs_f64()
            )));
            if ui.button("Cancel").clicked() {
                cancel = Some(j.id);
            }
        });
    }
    if let Some(id) = cancel {
        st.jobs.cancel(id);
    }
}

fn open_window(ctx: &egui::Context, st: &mut AppState) {
    let Some(p) = &mut st.pending.0 else { return };
    let mut open = true;
    let mut go = false;
    egui::Window::new("Open segmentation").open(&mut open).show(ctx, |ui| {
        ui.label(p.path.display().to_string());
        if p.labels.is_empty() {
            ui.label("A closed organ mesh.");
        }
        egui::Grid::new("labels").striped(true).show(ui, |ui| {
            for (v, name, n, role) in &mut p.labels {
                ui.label(format!("{v}"));
                ui.label(if name.is_empty() { "-" } else { name.as_str() });
                ui.label(format!("{n} voxels"));
                ui.radio_value(role, 0, "ignore");
                ui.radio_value(role, 1, "organ");
                ui.radio_value(role, 2, "structure");
                ui.end_row();
            }
        });
        go = ui.button("Open").clicked();
    });
    if go {
        let req = p.request();
        if req.organ_labels.is_empty() && !p.labels.is_empty() {
            st.messages.error("choose at least one organ label");
        } else {
            st.jobs.spawn("load", load_job(req));
            st.pending.0 = None;
        }
    } else if !open {
        st.pending.0 = None;
    }
}

pub fn ui_system(
    mut contexts: EguiContexts,
    mut st: AppState,
    mut uis: ResMut<UiState>,
    keys: Res<ButtonInput<KeyCode>>,
    time: Res<Time>,
    mut view: ResMut<crate::app::shell::view3d::View3d>,
    mut views: Views,
    mut ar_texture: Local<Option<egui::TextureHandle>>,
) -> Result {
    uis.frame_ms = 0.9 * uis.frame_ms + 0.1 * time.delta_secs() * 1e3;
    answer_dialogs(&mut uis, &mut st, &mut views);
    let ctx = contexts.ctx_mut()?.clone();
    let mode = *views.mode;
    if !ctx.egui_wants_keyboard_input() {
        shortcuts(&keys, mode, &mut st, &mut uis, &mut views);
    }
    let mut root = egui::Ui::new(
        ctx.clone(),
        "root".into(),
        egui::UiBuilder::new().layer_id(egui::LayerId::background()).max_rect(ctx.viewport_rect()),
    );
    let mut new_mode = mode;
    egui::Panel::top("menu").show(&mut root, |ui| menu_bar(ui, &mut st, &mut uis, &mut view, &mut views, &mut new_mode));
    egui::Panel::bottom("status").show(&mut root, |ui| bottom_panel(ui, &mut st, &uis));
    view_panels(&mut root, mode, &mut st, &mut views, &mut ar_texture);
    if new_mode != mode {
        *views.mode = new_mode;
    }
    // The 3-D view gets what the panels leave (only where the mode shows it).
    view.active = mode.shows_3d();
    if mode.shows_3d() {
        let rect = root.available_rect_before_wrap();
        view.rect = Some(rect);
        view.pixels_per_point = ctx.pixels_per_point();
        if let Some(tex) = view.texture {
            let uv = egui::Rect::from_min_max(egui::pos2(0.0, 0.0), egui::pos2(1.0, 1.0));
            root.painter().image(tex, rect, uv, egui::Color32::WHITE);
        }
        let scale = match mode {
            Mode::Model => {
                st.sim.result.as_ref().filter(|_| st.sim.show_deformed).map(|d| (d.max_mm, format!("{} displacement", d.source)))
            }
            Mode::Qa => views.qa.sample.as_ref().map(|s| (s.max_mm as f64, "FE displacement; prediction: error".to_string())),
            _ => None,
        };
        if let Some((max_mm, what)) = scale {
            scale_bar(root.painter(), rect, max_mm, &what);
        }
    }
    open_window(&ctx, &mut st);
    help_and_error_windows(&ctx, &mut uis, &mut st);
    Ok(())
}

/// Apply the answers of the file dialogs closed since the last frame.
fn answer_dialogs(uis: &mut UiState, st: &mut AppState, views: &mut Views) {
    for (purpose, picked) in uis.answered() {
        match (purpose, picked) {
            (Dialog::Segmentation, Some(path)) => {
                views.recent.push(&path, crate::app::model::session::RecentKind::Segmentation);
                st.jobs.spawn("inspect", inspect_job(path));
            }
            (Dialog::Patient, Some(dir)) => {
                views.recent.push(&dir, crate::app::model::session::RecentKind::Patient);
                st.jobs.spawn("open patient", crate::app::model::compute::open_patient_job(dir));
            }
            (Dialog::Scan, Some(path)) => {
                let bounds = st.organ.data.as_ref().and_then(|d| d.surface.bounds());
                st.jobs.spawn("scan", crate::app::model::compute::load_ct_job(path, bounds));
            }
            (Dialog::OpenSession, Some(path)) => {
                st.jobs.spawn("open session", crate::app::model::session::open_job(path));
            }
            (Dialog::SaveSession, picked) => views.save.0 = picked,
            (Dialog::ExportPng, picked) => views.export.0 = picked,
            (_, None) => {}
        }
    }
}

/// The keyboard shortcuts (when egui does not want the keyboard).
fn shortcuts(keys: &ButtonInput<KeyCode>, mode: Mode, st: &mut AppState, uis: &mut UiState, views: &mut Views) {
    if keys.just_pressed(KeyCode::F1) {
        uis.show_help = !uis.show_help;
    }
    // Held, or pressed and released within this frame (a fast chord, a slow frame).
    let ctrl_keys = [KeyCode::ControlLeft, KeyCode::ControlRight];
    let ctrl = keys.any_pressed(ctrl_keys) || keys.any_just_pressed(ctrl_keys) || keys.any_just_released(ctrl_keys);
    if ctrl && keys.just_pressed(KeyCode::KeyS) && st.organ.data.is_some() {
        match views.session_file.0.clone() {
            Some(p) => views.save.0 = Some(p),
            None => uis.open(Dialog::SaveSession),
        }
    }
    if mode == Mode::Model && !ctrl && keys.just_pressed(KeyCode::KeyS) {
        start_simulation(st);
    }
    if mode == Mode::Model {
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
    if mode == Mode::Qa {
        if keys.just_pressed(KeyCode::ArrowRight) {
            views.qa.step(1);
        }
        if keys.just_pressed(KeyCode::ArrowLeft) {
            views.qa.step(-1);
        }
        if keys.just_pressed(KeyCode::KeyR) {
            match views.qa.toggle_flag() {
                Ok(m) => st.messages.info(m),
                Err(e) => st.messages.error(e),
            }
        }
    }
}

/// The help window (F1) and the window that shows errors not yet acknowledged.
fn help_and_error_windows(ctx: &egui::Context, uis: &mut UiState, st: &mut AppState) {
    if uis.show_help {
        egui::Window::new("Keyboard and mouse").open(&mut uis.show_help).show(ctx, |ui| {
            egui::Grid::new("keys").show(ui, |ui| {
                for (k, what) in [
                    ("left click", "place a force probe on the organ"),
                    ("left drag", "pull the probe: direction and magnitude"),
                    ("right drag", "rotate the view"),
                    ("middle drag / shift + right drag", "pan"),
                    ("wheel", "zoom"),
                    ("F", "frame the organ"),
                    ("G", "show or hide the grid"),
                    ("D", "show the rest or deformed organ"),
                    ("S", "simulate the probes' forces (SVK)"),
                    ("Ctrl+S", "save the session (organ, probes, fixed region, camera, model, slices)"),
                    ("Delete", "delete the selected probe"),
                    ("F1", "this window"),
                ] {
                    ui.strong(k);
                    ui.label(what);
                    ui.end_row();
                }
            });
        });
    }
    if st.messages.unread_errors > 0 {
        let errors: Vec<String> = st
            .messages
            .list
            .iter()
            .filter(|(l, _)| *l == Level::Error)
            .rev()
            .take(st.messages.unread_errors)
            .map(|(_, m)| m.clone())
            .collect();
        let mut dismiss = false;
        egui::Window::new("Error").collapsible(false).show(ctx, |ui| {
            for e in errors.iter().rev() {
                ui.colored_label(egui::Color32::LIGHT_RED, e);
            }
            dismiss = ui.button("OK").clicked();
        });
        if dismiss {
            st.messages.unread_errors = 0;
        }
    }
}

/// The active view's panels around the 3-D view (or instead of it).
fn view_panels(root: &mut egui::Ui, mode: Mode, st: &mut AppState, views: &mut Views, ar_texture: &mut Option<egui::TextureHandle>) {
    let waker = views.proxy.as_ref().map(|p| {
        let p = (**p).clone();
        Box::new(move || {
            let _ = p.send_event(bevy::winit::WinitUserEvent::WakeUp);
        }) as crate::app::ar::Waker
    });
    let Views { jobs_ui, queue, qa, ar, active, patient, .. } = views;
    match mode {
        Mode::Model => {
            egui::Panel::left("left").default_size(260.0).show(root, |ui| {
                egui::ScrollArea::vertical().show(ui, |ui| left_panel(ui, st));
            });
            egui::Panel::right("right").default_size(280.0).show(root, |ui| {
                egui::ScrollArea::vertical().show(ui, |ui| right_panel(ui, st));
            });
        }
        Mode::Jobs => {
            egui::Panel::left("jobs_left").default_size(300.0).show(root, |ui| {
                egui::ScrollArea::vertical().show(ui, |ui| {
                    crate::app::jobs::panel::forms_panel(ui, jobs_ui, queue, &st.organ, &st.setup, &st.sim.fixed, &mut st.messages)
                });
            });
            let load = egui::CentralPanel::default()
                .show(root, |ui| crate::app::jobs::panel::queue_and_dashboard(ui, jobs_ui, queue, active, patient))
                .inner;
            if let Some((dir, file)) = load {
                **active = ActiveModel { dir: dir.clone(), checkpoint: file.clone() };
                if let Some(d) = &st.organ.data {
                    st.jobs.spawn("load model", crate::app::model::probes::load_model_job(dir, file, d.clone()));
                }
            }
        }
        Mode::Qa => {
            egui::Panel::left("qa_left").default_size(280.0).show(root, |ui| {
                egui::ScrollArea::vertical().show(ui, |ui| crate::app::qa::panel::left_panel(ui, qa, &st.organ, active, &mut st.messages));
            });
            egui::Panel::right("qa_right").default_size(280.0).show(root, |ui| {
                egui::ScrollArea::vertical().show(ui, |ui| {
                    crate::app::qa::panel::right_panel(ui, qa);
                    if st.organ.data.as_ref().is_some_and(|d| d.ct.is_some()) {
                        ui.separator();
                        ui.heading("Scan");
                        ui.weak("yellow: the organ at rest; cyan: the sample's FE deformation");
                        crate::app::model::ct::ct_ui(ui, &mut st.ct, &st.organ);
                    }
                });
            });
        }
        Mode::Ar => {
            let mut synth = false;
            egui::Panel::left("ar_left").default_size(290.0).show(root, |ui| {
                egui::ScrollArea::vertical()
                    .show(ui, |ui| synth = crate::app::ar::panel::left_panel(ui, ar, &st.organ, active, &mut st.messages, waker));
            });
            egui::Panel::right("ar_right").default_size(250.0).show(root, |ui| {
                egui::ScrollArea::vertical().show(ui, |ui| crate::app::ar::panel::right_panel(ui, ar));
            });
            egui::CentralPanel::default().show(root, |ui| crate::app::ar::panel::central(ui, ar, ar_texture));
            if synth {
                match &st.organ.data {
                    Some(d) if !st.jobs.is_running("synthetic") => {
                        st.jobs.spawn(
                            "synthetic recording",
                            crate::app::ar::panel::synth_job(
                                d.clone(),
                                active.dir.clone(),
                                crate::app::ar::panel::synthetic_recording_dir(),
                                20,
                            ),
                        );
                    }
                    Some(_) => {}
                    None => st.messages.error("load an organ first"),
                }
            }
        }
    }
}
