//! Panels of the AR view: the source and playback controls, the alignment controls and
//! recording (left); latency, TRE and log (right); the overlay image (centre).

use crate::app::ar::{Ar, ArCommand, ArSession, ArSource};
use crate::app::shell::tasks::JobOutput;
use crate::app::state::{ActiveModel, Organ, OrganData, UiMessages};
use anyhow::Context;
use bevy_egui::egui;
use std::path::PathBuf;
use umesh_core::register::correction::{CorrectionChoice, CorrectionForm, CorrectionSettings};
use umesh_core::register::pipeline::PosePolicy;
use umesh_core::rgbd::realsense::RealSenseRequest;
use umesh_core::{Cancel, Progress};

/// Default recording folder of the synthetic sequence the AR view offers to generate.
pub fn synthetic_recording_dir() -> PathBuf {
    PathBuf::from("out/ar-synthetic")
}

pub fn left_panel(
    ui: &mut egui::Ui,
    ar: &mut Ar,
    organ: &Organ,
    model: &ActiveModel,
    messages: &mut UiMessages,
    waker: Option<crate::app::ar::Waker>,
) -> bool {
    let want_synth = source_ui(ui, ar, organ, model, messages, waker);
    ui.weak(format!("model: {} ({})", crate::app::state::short_path(&model.dir), model.checkpoint));
    // Held outside `ar` while the sections below edit it; put back unless closed.
    let Some(s) = ar.session.take() else {
        ui.label(
            "Open a recording (Open3D layout: color/, depth/, intrinsics, trajectory.log) or connect to a live stream.",
        );
        return want_synth;
    };
    playback_ui(ui, ar, &s);
    alignment_ui(ui, ar, &s);
    display_ui(ui, ar, &s);
    if ui.button("Close").clicked() {
        ar.playing = false;
    } else {
        ar.session = Some(s);
    }
    want_synth
}

/// Where the frames come from: a recording, a synthetic one made now, or a live stream.
fn source_ui(
    ui: &mut egui::Ui,
    ar: &mut Ar,
    organ: &Organ,
    model: &ActiveModel,
    messages: &mut UiMessages,
    waker: Option<crate::app::ar::Waker>,
) -> bool {
    let mut want_synth = false;
    ui.heading("AR view");
    if ar.source_text.is_empty() {
        ar.source_text = synthetic_recording_dir().display().to_string();
    }
    if ar.live_text.is_empty() {
        ar.live_text = "127.0.0.1:5599".into();
    }
    if ar.record_dir.is_empty() {
        ar.record_dir = "out/ar-overlay".into();
    }
    ui.horizontal(|ui| {
        ui.label("recording");
        ui.add(egui::TextEdit::singleline(&mut ar.source_text).desired_width(150.0));
    });
    let mut start = None;
    ui.horizontal(|ui| {
        if ui.button("Open recording").clicked() {
            start = Some(ArSource::Recording(PathBuf::from(ar.source_text.trim())));
        }
        if ui
            .button("Make a synthetic one")
            .on_hover_text("umesh rgbd synth on the bundled phantom, into out/ar-synthetic")
            .clicked()
        {
            want_synth = true;
        }
    });
    ui.horizontal(|ui| {
        ui.label("live (TCP)");
        ui.add(egui::TextEdit::singleline(&mut ar.live_text).desired_width(110.0));
        if ui.button("Connect").clicked() {
            start = Some(ArSource::Tcp(ar.live_text.trim().to_string()));
        }
    });
    if let Some(s) = camera_ui(ui, ar) {
        start = Some(s);
    }
    if let Some(src) = start {
        // Each session starts with the model's correction form; the box changes it for this session.
        ar.form = model_correction_form(&model.dir, messages);
        match &organ.data {
            Some(o) => {
                let s = ArSession::start(src.clone(), o.seg.clone(), model.clone(), waker);
                s.send(ArCommand::ShowPoints(ar.show_points));
                s.send(ArCommand::Correction(correction_settings(ar)));
                s.send(ArCommand::Pose(ar.pose));
                ar.session = Some(s);
                ar.last = None;
                ar.frames = None;
                ar.intervals.clear();
                ar.pose_in_use = None;
                ar.playing = matches!(src, ArSource::Tcp(_) | ArSource::RealSense(_));
                if ar.playing
                    && let Some(s) = &ar.session
                {
                    s.send(ArCommand::Play(true));
                }
            }
            None => messages.error("load the organ (segmentation) the recording shows first"),
        }
    }
    want_synth
}

/// A RealSense camera (listed by the bridge) or a RealSense recording played at its own rate.
fn camera_ui(ui: &mut egui::Ui, ar: &mut Ar) -> Option<ArSource> {
    let c = &mut ar.camera;
    c.poll();
    if c.width == 0 {
        let d = RealSenseRequest::default();
        (c.width, c.height, c.fps) = (d.width, d.height, d.fps);
    }
    let mut start = None;
    ui.horizontal(|ui| {
        ui.label("RealSense");
        if c.listing.is_some() {
            ui.spinner();
        } else if ui
            .button("Find cameras")
            .on_hover_text("asks librealsense (pyrealsense2) for the connected cameras")
            .clicked()
        {
            c.list();
        }
    });
    match &c.devices {
        Some(Err(e)) => {
            ui.colored_label(egui::Color32::from_rgb(235, 90, 60), egui::RichText::new(e).small());
        }
        Some(Ok(d)) if d.is_empty() => {
            ui.weak("no RealSense camera is connected");
        }
        Some(Ok(d)) => {
            let label = |i: usize| {
                let x = &d[i];
                format!("{} {}", x.name.as_deref().unwrap_or("camera"), x.serial.as_deref().unwrap_or(""))
            };
            ui.horizontal(|ui| {
                egui::ComboBox::from_id_salt("ar_camera").selected_text(label(c.chosen.min(d.len() - 1))).show_ui(
                    ui,
                    |ui| {
                        for i in 0..d.len() {
                            ui.selectable_value(&mut c.chosen, i, label(i));
                        }
                    },
                );
            });
            ui.horizontal(|ui| {
                ui.add(egui::DragValue::new(&mut c.width).range(1..=4096));
                ui.label("x");
                ui.add(egui::DragValue::new(&mut c.height).range(1..=4096));
                ui.add(egui::DragValue::new(&mut c.fps).range(1..=300));
                ui.label("fps");
                if ui.button("Start").clicked() {
                    start = Some(ArSource::RealSense(RealSenseRequest {
                        serial: d.get(c.chosen).and_then(|x| x.serial.clone()),
                        width: c.width,
                        height: c.height,
                        fps: c.fps,
                        ..Default::default()
                    }));
                }
            });
        }
        None => {}
    }
    ui.horizontal(|ui| {
        ui.label("RealSense file");
        ui.add(egui::TextEdit::singleline(&mut c.file).hint_text(".db3 or .bag").desired_width(110.0));
        if ui
            .button("Play")
            .on_hover_text("played at its own rate through the RealSense bridge, as a camera would be")
            .clicked()
        {
            start = Some(ArSource::RealSense(RealSenseRequest::recording(std::path::Path::new(c.file.trim()))));
        }
    });
    start
}

/// Play, pause, step and scrub.
fn playback_ui(ui: &mut egui::Ui, ar: &mut Ar, s: &ArSession) {
    ui.separator();
    ui.label(&ar.label);
    ui.horizontal(|ui| {
        let play = if ar.playing { "⏸ Pause" } else { "▶ Play" };
        if ui.button(play).clicked() {
            ar.playing = !ar.playing;
            s.send(ArCommand::Play(ar.playing));
        }
        if ar.frames.is_some() {
            if ui.button("◀ step").clicked() {
                ar.playing = false;
                s.send(ArCommand::Step(-1));
            }
            if ui.button("step ▶").clicked() {
                ar.playing = false;
                s.send(ArCommand::Step(1));
            }
        }
    });
    if let Some(n) = ar.frames {
        let mut f = ar.scrub;
        if ui.add(egui::Slider::new(&mut f, 0..=n.saturating_sub(1)).text("frame")).changed() {
            ar.scrub = f;
            s.send(ArCommand::Seek(f));
        }
        ui.weak(format!("recorded at {:.1} fps", ar.fps));
    }
}

/// The camera pose policy, ICP on demand and the initial pose offset.
fn alignment_ui(ui: &mut egui::Ui, ar: &mut Ar, s: &ArSession) {
    ui.separator();
    ui.strong("Rigid alignment");
    let before = ar.pose;
    ui.horizontal(|ui| {
        ui.label("pose").on_hover_text(
            "auto: tracked when the source carries a tracked camera pose for every frame, else icp-first; \
             tracked: keep the recording's or stream's camera pose, refined on the first frame by at most 1.5 mm; \
             icp-first: full ICP on the first frame; icp-every-frame: full ICP on each frame",
        );
        egui::ComboBox::from_id_salt("ar_pose").selected_text(ar.pose.map_or("auto", PosePolicy::name)).show_ui(
            ui,
            |ui| {
                ui.selectable_value(&mut ar.pose, None, "auto");
                for p in PosePolicy::ALL {
                    ui.selectable_value(&mut ar.pose, Some(p), p.name());
                }
            },
        );
    });
    if ar.pose != before {
        s.send(ArCommand::Pose(ar.pose));
    }
    if let Some((_, why)) = &ar.pose_in_use {
        ui.weak(format!("in use: {why}"));
    }
    if ui.button("ICP on this frame").clicked() {
        s.send(ArCommand::Icp);
    }
    if let Some(icp) = ar.last.as_ref().and_then(|f| f.report.icp.as_ref()) {
        ui.label(format!(
            "last ICP: fitness {:.2}, RMS {:.2} mm, {} iterations, moved the points {:.2} mm{}",
            icp.fitness,
            icp.rms_mm,
            icp.iterations,
            icp.moved_mm,
            if icp.bounded { " (at the bound)" } else { "" }
        ));
    }
    ui.label("initial pose offset (drag the values; camera axes):");
    let mut changed = false;
    egui::Grid::new("pose").num_columns(4).show(ui, |ui| {
        ui.label("mm");
        for v in &mut ar.offset_t_mm {
            changed |= ui.add(egui::DragValue::new(v).speed(0.5).range(-200.0..=200.0)).changed();
        }
        ui.end_row();
        ui.label("deg");
        for v in &mut ar.offset_r_deg {
            changed |= ui.add(egui::DragValue::new(v).speed(0.2).range(-90.0..=90.0)).changed();
        }
        ui.end_row();
    });
    if ui.button("reset offset").clicked() {
        ar.offset_t_mm = [0.0; 3];
        ar.offset_r_deg = [0.0; 3];
        changed = true;
    }
    if changed {
        s.send(ArCommand::PoseOffset(ar.offset_t_mm, ar.offset_r_deg));
    }
}

/// The correction form a model asks for: its registration check's choice within the default
/// frame budget (said in the messages, with why), else the subspace form; a damaged choice is
/// shown as an error.
pub fn model_correction_form(model_dir: &std::path::Path, messages: &mut UiMessages) -> CorrectionForm {
    match CorrectionChoice::read(model_dir) {
        Ok(Some(c)) => {
            let (form, why) = c.choose(Some(umesh_core::register::correction::DEFAULT_FRAME_BUDGET_MS));
            messages.info(format!("in use: {why}"));
            form
        }
        Ok(None) => CorrectionForm::Subspace,
        Err(e) => {
            messages.error(format!("{e}; the subspace correction is used"));
            CorrectionForm::Subspace
        }
    }
}

/// The correction the panel asks for.
fn correction_settings(ar: &Ar) -> CorrectionSettings {
    let settings = if ar.correction { ar.form.settings() } else { CorrectionSettings::off() };
    if ar.keep_frame_time { CorrectionSettings { doubted_updates: 0, ..settings } } else { settings }
}

/// What is drawn (observed points), the physics correction and recording the overlays.
fn display_ui(ui: &mut egui::Ui, ar: &mut Ar, s: &ArSession) {
    ui.separator();
    if ui.checkbox(&mut ar.show_points, "observed organ points").changed() {
        s.send(ArCommand::ShowPoints(ar.show_points));
    }
    let mut changed = ui
        .checkbox(&mut ar.correction, "physics correction")
        .on_hover_text(
            "After the network, two FE fit updates pull the prediction onto the observed points (about 8 ms a frame on the phantom); a frame whose prediction the confidence check doubts is corrected as the FE fit instead, on cells twice as large (from rest: 4 updates at the first doubted frame, about 55 ms on the CT patient; each next one starts from the fit before and takes one update, two when the organ moved fast, about 30 ms)",
        )
        .changed();
    ui.add_enabled_ui(ar.correction, |ui| {
        ui.horizontal(|ui| {
            ui.label("form");
            for (form, hover) in [
                (CorrectionForm::Subspace, "Each prediction corrected in a basis of smooth surface loads: the fastest; good where the network is good"),
                (
                    CorrectionForm::CoarseTracking,
                    "The FE fit carried from frame to frame on cells twice as large, moved by the network's prediction, one update a frame: about the subspace form's frame; the network's error where the surface does not show it stays out",
                ),
                (
                    CorrectionForm::Tracking,
                    "The correction carried from frame to frame, its elastic energy from rest, by conjugate gradients over the whole grid (the FE fit): the most accurate where the network is weak, 5-10 times the frame",
                ),
            ] {
                changed |= ui.radio_value(&mut ar.form, form, form.name()).on_hover_text(hover).changed();
            }
        });
        changed |= ui
            .checkbox(&mut ar.keep_frame_time, "keep the frame time")
            .on_hover_text(
                "Do not correct a frame whose prediction the confidence check doubts as the FE fit (about 55 ms for the first of a run on the CT patient and 30 ms for each next, more on a larger liver): every frame within the correction's time, the doubted ones less accurate",
            )
            .changed();
    });
    if changed {
        s.send(ArCommand::Correction(correction_settings(ar)));
    }
    ui.horizontal(|ui| {
        if ui.checkbox(&mut ar.record, "record overlays to").changed() {
            s.send(ArCommand::Record(ar.record.then(|| PathBuf::from(ar.record_dir.trim()))));
        }
        ui.add(egui::TextEdit::singleline(&mut ar.record_dir).desired_width(110.0));
    });
}

pub fn right_panel(ui: &mut egui::Ui, ar: &Ar) {
    ui.heading("Frame");
    let Some(f) = &ar.last else {
        ui.label("No frame yet.");
        return;
    };
    let r = &f.report;
    let l = &r.latency;
    egui::Grid::new("latency").num_columns(2).show(ui, |ui| {
        ui.label("frame");
        ui.label(f.index.to_string());
        ui.end_row();
        ui.label("organ points");
        ui.label(r.observed_points.to_string());
        ui.end_row();
        for (k, v) in [
            ("points (ms)", l.points_ms),
            ("ICP (ms)", l.icp_ms),
            ("u_s (ms)", l.surface_ms),
            ("network (ms)", l.predict_ms),
            ("correction (ms)", l.correction_ms),
            ("overlay (ms)", l.overlay_ms),
            ("total (ms)", l.total_ms),
        ] {
            ui.label(k);
            ui.label(format!("{v:.1}"));
            ui.end_row();
        }
        if let Some(c) = &r.correction {
            ui.label("correction moved");
            let how = if c.doubted { ", as the FE fit (prediction doubted)" } else { "" };
            ui.label(format!("{:.2} mm RMS{how}", c.moved_rms_mm));
            ui.end_row();
        }
        if let Some(e) = r.end_to_end_ms {
            ui.label("camera to overlay (ms)");
            ui.label(format!("{e:.1}"));
            ui.end_row();
        }
        if f.dropped > 0 {
            ui.label("frames dropped");
            ui.label(f.dropped.to_string());
            ui.end_row();
        }
        if let Some(fps) = ar.displayed_fps() {
            ui.label("shown");
            ui.label(format!("{fps:.1} frames/s"));
            ui.end_row();
        }
        if let (Some(t), Some(m)) = (r.tre_mean_mm, r.tre_max_mm) {
            ui.label("TRE");
            ui.strong(format!("{t:.2} mm (max {m:.2})"));
            ui.end_row();
        }
        if let Some(t) = r.tre_rigid_mean_mm {
            ui.label("TRE, rigid only");
            ui.label(format!("{t:.2} mm"));
            ui.end_row();
        }
        if let Some(d) = r.marker_displacement_mean_mm {
            ui.label("markers moved");
            ui.label(format!("{d:.2} mm"));
            ui.end_row();
        }
    });
    if !ar.has_truth {
        ui.weak("No ground truth: TRE needs ground_truth.json in the recording.");
    }
    ui.separator();
    confidence_panel(ui, &r.confidence);
    ui.separator();
    ui.strong("Log");
    for l in ar.log.iter().rev().take(10) {
        ui.label(egui::RichText::new(l).small());
    }
}

/// How far the overlay can be trusted, without ground truth: the fit of the prediction to the
/// observed points and the seen share of the organ, against the range seen in training.
fn confidence_panel(ui: &mut egui::Ui, c: &umesh_core::register::confidence::Confidence) {
    let (colour, state) = if !c.calibrated {
        (egui::Color32::GRAY, "not calibrated")
    } else if c.warning() {
        (egui::Color32::from_rgb(235, 90, 60), "do not trust the overlay")
    } else {
        (egui::Color32::from_rgb(90, 200, 110), "within the training range")
    };
    ui.horizontal(|ui| {
        ui.strong("Confidence");
        ui.colored_label(colour, egui::RichText::new(state).strong());
    });
    egui::Grid::new("confidence").num_columns(2).show(ui, |ui| {
        ui.label("points to surface");
        ui.label(format!("{:.2} mm mean, {:.2} p95", c.residual_mean_mm, c.residual_p95_mm));
        ui.end_row();
        ui.label("surface seen");
        ui.label(format!("{:.0} %", 100.0 * c.surface_coverage));
        ui.end_row();
        ui.label("largest motion");
        ui.label(format!("{:.1} mm", c.displacement_max_mm));
        ui.end_row();
    });
    for w in &c.warnings {
        ui.colored_label(colour, egui::RichText::new(w).small());
    }
    if !c.calibrated {
        ui.weak("The model has no confidence.json: `umesh eval --calibrate --model M --dataset D` writes it.");
    }
}

/// The overlay, fitted into the central area.
pub fn central(ui: &mut egui::Ui, ar: &mut Ar, texture: &mut Option<egui::TextureHandle>) {
    if ar.image_dirty
        && let Some(f) = &ar.last
    {
        let img = egui::ColorImage::from_rgb([f.image.width, f.image.height], &f.image.rgb);
        match texture {
            Some(t) => t.set(img, egui::TextureOptions::LINEAR),
            None => *texture = Some(ui.ctx().load_texture("ar-overlay", img, egui::TextureOptions::LINEAR)),
        }
        ar.image_dirty = false;
    }
    let rect = ui.available_rect_before_wrap();
    match (texture.as_ref(), ar.last.as_ref()) {
        (Some(t), Some(f)) => {
            let aspect = f.image.width as f32 / f.image.height.max(1) as f32;
            let mut size = rect.size();
            if size.x / size.y > aspect {
                size.x = size.y * aspect;
            } else {
                size.y = size.x / aspect;
            }
            let r = egui::Rect::from_center_size(rect.center(), size);
            ui.painter().image(
                t.id(),
                r,
                egui::Rect::from_min_max(egui::pos2(0.0, 0.0), egui::pos2(1.0, 1.0)),
                egui::Color32::WHITE,
            );
        }
        _ => {
            ui.centered_and_justified(|ui| {
                ui.label(if ar.session.is_some() { "waiting for the first frame..." } else { "no source" })
            });
        }
    }
}

/// The settings of the view's synthetic recording (and the AR scenes'): the bundled pressing
/// load at 1.5 x the dataset's target (13 mm mean nodal displacement), within the range the
/// model trained on: 11.0 mm of marker motion on the phantom.
pub fn synthetic_settings(frames: usize) -> umesh_core::synth::SynthSettings {
    umesh_core::synth::SynthSettings { frames, load_scale: 1.5, ..Default::default() }
}

/// A synthetic RGB-D recording of the organ deformed by the FE model (`umesh rgbd synth`).
pub fn synth_job(
    organ: OrganData,
    model_dir: std::path::PathBuf,
    out: std::path::PathBuf,
    frames: usize,
) -> impl FnOnce(&Progress, &Cancel) -> anyhow::Result<JobOutput> + Send + 'static {
    move |progress, cancel| {
        let info = umesh_net::ModelInfo::read(&model_dir).ok();
        let config = umesh_workflow::input::model_dataset_config(info.as_ref(), &organ.seg);
        let settings = synthetic_settings(frames);
        let r = umesh_core::synth::run_rgbd_synth(&organ.seg, &config, &settings, &out, progress, cancel)
            .with_context(|| out.display().to_string())?;
        let summary = format!("{} frames, markers move {:.1} mm by the last", r.frames, r.mean_marker_displacement_mm);
        Ok(JobOutput::Apply(Box::new(move |world| {
            world.resource_mut::<Ar>().source_text = out.display().to_string();
            Ok(format!("synthetic recording in {}: {summary}; press Open recording", out.display()))
        })))
    }
}
