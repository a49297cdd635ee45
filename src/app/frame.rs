//! The window's layout: the menu bar (with a tab per registered view), the bottom bar (status
//! and jobs), the help and error windows; the active view's panels (its registry entry,
//! `shell::views`) around the 3-D view, which gets what they leave.

use crate::app::model::compute::{inspect_job, load_job};
use crate::app::model::panel::AppState;
use crate::app::shell::ctrl_held;
use crate::app::shell::views::ViewRegistry;
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
        let pick =
            |filter: &'static str, ext: &'static [&'static str]| rfd::AsyncFileDialog::new().add_filter(filter, ext);
        let save = |name: &'static str, ext: &'static str| {
            rfd::AsyncFileDialog::new().add_filter(ext, &[ext]).set_file_name(name)
        };
        IoTaskPool::get().spawn(async move {
            let picked = match self {
                Dialog::Segmentation => {
                    pick("segmentation / mesh", &["nii", "gz", "hdr", "obj", "ply", "stl"]).pick_file().await
                }
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

/// The session's files and the recent list, which the File menu and its dialogs edit.
#[derive(bevy::ecs::system::SystemParam)]
pub struct SessionFiles<'w> {
    recent: ResMut<'w, crate::app::model::session::Recent>,
    session_file: Res<'w, crate::app::model::session::SessionFile>,
    save: ResMut<'w, crate::app::model::session::SaveRequest>,
    export: ResMut<'w, crate::app::model::session::PendingExport>,
}

/// The File menu: organs, patients, scans and sessions.
fn file_menu(ui: &mut egui::Ui, st: &mut AppState, uis: &mut UiState, files: &mut SessionFiles) {
    if ui.button("Open segmentation or mesh...").clicked() {
        uis.open(Dialog::Segmentation);
    }
    if ui
        .button("Open patient folder...")
        .on_hover_text("a folder made by umesh prepare (or New patient in Jobs)")
        .clicked()
    {
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
    let current = files.session_file.0.clone();
    let label = match &current {
        Some(p) => format!("Save session (Ctrl+S): {}", p.file_name().map(|n| n.to_string_lossy()).unwrap_or_default()),
        None => "Save session (Ctrl+S)...".into(),
    };
    if ui.add_enabled(has_organ, egui::Button::new(label)).clicked() {
        match current {
            Some(p) => files.save.0 = Some(p),
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
        if files.recent.list.is_empty() {
            ui.weak("nothing yet");
        }
        let mut open = None;
        for (p, kind) in &files.recent.list {
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
}

fn menu_bar(
    ui: &mut egui::Ui,
    st: &mut AppState,
    uis: &mut UiState,
    view: &mut crate::app::shell::view3d::View3d,
    files: &mut SessionFiles,
    tabs: (&ViewRegistry, &mut Mode),
) {
    egui::MenuBar::new().ui(ui, |ui| {
        ui.menu_button("File", |ui| file_menu(ui, st, uis, files));
        ui.menu_button("View", |ui| {
            ui.checkbox(&mut st.grid.show, "Grid (G)");
            if ui.checkbox(&mut st.sim.show_deformed, "Deformed (D)").changed() {
                st.sim.generation += 1;
            }
            if ui
                .checkbox(&mut st.sim.show_ghost, "Rest shape ghost")
                .on_hover_text("behind the deformed organ")
                .changed()
            {
                st.sim.generation += 1;
            }
            ui.separator();
            let mut q = view.quality.clone();
            ui.add(egui::Slider::new(&mut q.render_scale, 0.25..=1.0).text("3-D resolution"));
            ui.checkbox(&mut q.shadows, "Shadows");
            if let Some((name, software)) = &view.adapter {
                ui.weak(format!(
                    "{name}{}",
                    if *software { " (software: quarter resolution, no shadows by default)" } else { "" }
                ));
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
        let (registry, mode) = tabs;
        for v in registry.iter() {
            ui.selectable_value(mode, v.mode, v.name);
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
        let r = egui::Rect::from_min_max(
            egui::pos2(bar.left(), y - bar.height() / steps as f32),
            egui::pos2(bar.right(), y),
        );
        painter.rect_filled(
            r,
            0.0,
            egui::Color32::from_rgb((c[0] * 255.0) as u8, (c[1] * 255.0) as u8, (c[2] * 255.0) as u8),
        );
    }
    painter.rect_stroke(bar, 0.0, egui::Stroke::new(1.0, egui::Color32::GRAY), egui::StrokeKind::Outside);
    let font = egui::FontId::proportional(12.0);
    let text = egui::Color32::from_gray(230);
    painter.text(
        egui::pos2(bar.right() + 4.0, bar.top()),
        egui::Align2::LEFT_CENTER,
        format!("{max_mm:.1} mm"),
        font.clone(),
        text,
    );
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

/// The frame's layout: the shell's bars, then the active view's shortcuts and panels (its
/// registry entry's systems), then the 3-D view in what they leave and the windows on top.
pub fn ui_system(world: &mut World) -> Result {
    // No context before egui's first pass: nothing to draw yet.
    let Some(ctx) = world.run_system_cached(egui_context)? else { return Ok(()) };
    let wants_keyboard = ctx.egui_wants_keyboard_input();
    let mode = *world.resource::<State<Mode>>().get();
    let entry = world.resource::<ViewRegistry>().get(mode).cloned();
    world.run_system_cached_with(shell_input, wants_keyboard)?;
    if let Some(shortcuts) = entry.as_ref().and_then(|e| e.shortcuts).filter(|_| !wants_keyboard) {
        world.run_system(shortcuts)?;
    }
    let mut root = egui::Ui::new(
        ctx.clone(),
        "root".into(),
        egui::UiBuilder::new().layer_id(egui::LayerId::background()).max_rect(ctx.viewport_rect()),
    );
    world.run_system_cached_with(shell_bars, &mut root)?;
    let mut frame = CentralFrame { root, shows_3d: false, scale: None };
    if let Some(e) = &entry {
        world.run_system_with(e.panels, &mut frame.root)?;
        frame.shows_3d = e.shows_3d;
        if let Some(scale) = e.scale {
            frame.scale = world.run_system(scale)?;
        }
    }
    world.run_system_cached_with(shell_central, &mut frame)?;
    Ok(())
}

fn egui_context(mut contexts: EguiContexts) -> Option<egui::Context> {
    contexts.ctx_mut().ok().cloned()
}

/// What the active view leaves to the 3-D view, and its colour scale.
pub struct CentralFrame {
    root: egui::Ui,
    shows_3d: bool,
    scale: Option<(f64, String)>,
}

/// The frame time, the file dialogs' answers and the shell's keys.
fn shell_input(
    In(wants_keyboard): In<bool>,
    mut st: AppState,
    mut uis: ResMut<UiState>,
    keys: Res<ButtonInput<KeyCode>>,
    time: Res<Time>,
    mut files: SessionFiles,
) {
    uis.frame_ms = 0.9 * uis.frame_ms + 0.1 * time.delta_secs() * 1e3;
    answer_dialogs(&mut uis, &mut st, &mut files);
    if !wants_keyboard {
        shortcuts(&keys, &mut st, &mut uis, &mut files);
    }
}

/// The menu bar (a tab per view) and the status bar.
fn shell_bars(
    InMut(root): InMut<egui::Ui>,
    mut st: AppState,
    mut uis: ResMut<UiState>,
    mut view: ResMut<crate::app::shell::view3d::View3d>,
    mut files: SessionFiles,
    registry: Res<ViewRegistry>,
    mode: Res<State<Mode>>,
    mut next_mode: ResMut<NextState<Mode>>,
) {
    let mut new_mode = *mode.get();
    egui::Panel::top("menu")
        .show(root, |ui| menu_bar(ui, &mut st, &mut uis, &mut view, &mut files, (&registry, &mut new_mode)));
    egui::Panel::bottom("status").show(root, |ui| bottom_panel(ui, &mut st, &uis));
    if new_mode != *mode.get() {
        next_mode.set(new_mode);
        // The new view shows from the next frame: ask for it now.
        root.ctx().request_repaint();
    }
}

/// The 3-D view in what the panels left (when the view shows it), then the windows.
fn shell_central(
    InMut(frame): InMut<CentralFrame>,
    mut st: AppState,
    mut uis: ResMut<UiState>,
    mut view: ResMut<crate::app::shell::view3d::View3d>,
    registry: Res<ViewRegistry>,
    mode: Res<State<Mode>>,
    mut lines: ResMut<crate::app::shell::view3d::OverlayLines>,
    cameras: Query<(&Camera, &GlobalTransform), With<crate::app::shell::camera::MainCamera>>,
) {
    let root = &mut frame.root;
    let ctx = root.ctx().clone();
    view.active = frame.shows_3d;
    if frame.shows_3d {
        let rect = root.available_rect_before_wrap();
        view.rect = Some(rect);
        view.pixels_per_point = ctx.pixels_per_point();
        if let Some(tex) = view.texture {
            let uv = egui::Rect::from_min_max(egui::pos2(0.0, 0.0), egui::pos2(1.0, 1.0));
            root.painter().image(tex, rect, uv, egui::Color32::WHITE);
        }
        if let Ok((camera, at)) = cameras.single() {
            crate::app::shell::view3d::paint_lines(root.painter(), rect, camera, at, &lines.0);
        }
        if let Some((max_mm, what)) = &frame.scale {
            scale_bar(root.painter(), rect, *max_mm, what);
        }
    }
    lines.0.clear();
    open_window(&ctx, &mut st);
    let view_keys = registry.get(*mode.get()).map(|e| e.keys).unwrap_or_default();
    help_and_error_windows(&ctx, &mut uis, &mut st, view_keys);
}

/// Apply the answers of the file dialogs closed since the last frame.
fn answer_dialogs(uis: &mut UiState, st: &mut AppState, files: &mut SessionFiles) {
    for (purpose, picked) in uis.answered() {
        match (purpose, picked) {
            (Dialog::Segmentation, Some(path)) => {
                files.recent.push(&path, crate::app::model::session::RecentKind::Segmentation);
                st.jobs.spawn("inspect", inspect_job(path));
            }
            (Dialog::Patient, Some(dir)) => {
                files.recent.push(&dir, crate::app::model::session::RecentKind::Patient);
                st.jobs.spawn("open patient", crate::app::model::compute::open_patient_job(dir));
            }
            (Dialog::Scan, Some(path)) => {
                let bounds = st.organ.data.as_ref().and_then(|d| d.surface.bounds());
                st.jobs.spawn("scan", crate::app::model::compute::load_ct_job(path, bounds));
            }
            (Dialog::OpenSession, Some(path)) => {
                st.jobs.spawn("open session", crate::app::model::session::open_job(path));
            }
            (Dialog::SaveSession, picked) => files.save.0 = picked,
            (Dialog::ExportPng, picked) => files.export.0 = picked,
            (_, None) => {}
        }
    }
}

/// The shell's keyboard shortcuts (when egui does not want the keyboard); a view's own are
/// its registry entry's.
fn shortcuts(keys: &ButtonInput<KeyCode>, st: &mut AppState, uis: &mut UiState, files: &mut SessionFiles) {
    if keys.just_pressed(KeyCode::F1) {
        uis.show_help = !uis.show_help;
    }
    if ctrl_held(keys) && keys.just_pressed(KeyCode::KeyS) && st.organ.data.is_some() {
        match files.session_file.0.clone() {
            Some(p) => files.save.0 = Some(p),
            None => uis.open(Dialog::SaveSession),
        }
    }
}

/// The help window (F1) and the window that shows errors not yet acknowledged.
fn help_and_error_windows(ctx: &egui::Context, uis: &mut UiState, st: &mut AppState, view_keys: &[(&str, &str)]) {
    if uis.show_help {
        egui::Window::new("Keyboard and mouse").open(&mut uis.show_help).show(ctx, |ui| {
            egui::Grid::new("keys").show(ui, |ui| {
                let shell_keys = [
                    ("right drag", "rotate the view"),
                    ("middle drag / shift + right drag", "pan"),
                    ("wheel", "zoom"),
                    ("F", "frame the organ"),
                    ("Ctrl+S", "save the session (organ, probes, fixed region, camera, model, slices)"),
                    ("F1", "this window"),
                ];
                for &(k, what) in view_keys.iter().chain(shell_keys.iter()) {
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
