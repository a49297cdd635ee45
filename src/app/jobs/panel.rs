//! Panels of the jobs view: the dataset and training forms (the CLI's settings), the queue
//! with progress, rate, ETA, log and cancel, and the training dashboard.

use crate::app::jobs::queue::{WorkKind, WorkQueue, WorkStatus, read_metrics};
use crate::app::setup::ObservationSetup;
use crate::app::state::{ActiveModel, Organ, UiMessages};
use crate::app::state::{FixedChoice, OpenPatient};
use bevy::prelude::*;
use bevy_egui::egui;
use egui_plot::{Legend, Line, Plot, PlotPoints};
use std::path::PathBuf;
use umesh_core::dataset::DatasetConfig;
use umesh_core::fem::MaterialParams;
use umesh_core::loads::ForceSettings;
use umesh_core::segmentation::Segmentation;
use umesh_net::TrainSettings;
use umesh_net::UNetConfig;
use umesh_net::training::EpochMetrics;
use umesh_workflow::options::DatasetOptions;
use umesh_workflow::patient::{PatientFigures, PrepareSettings};

#[derive(Clone, Debug)]
pub struct DatasetForm {
    pub out: String,
    pub samples: usize,
    pub seed: u64,
    pub shard_size: usize,
    pub probes: usize,
    pub target_displacement_mm: f64,
    pub young_pa: f64,
    pub poisson: f64,
    pub cell_size_mm: f64,
    pub subdivisions: u32,
}

impl Default for DatasetForm {
    fn default() -> Self {
        let f = ForceSettings::default();
        let m = MaterialParams::default();
        let g = umesh_core::grid::GridSettings::default();
        Self {
            out: "out/gui-dataset".into(),
            samples: 40,
            seed: 0,
            shard_size: 10,
            probes: f.probes,
            target_displacement_mm: f.target_displacement_mm,
            young_pa: m.young_pa,
            poisson: m.poisson,
            cell_size_mm: g.cell_size_mm,
            subdivisions: g.subdivisions,
        }
    }
}

impl DatasetForm {
    /// The CLI options of these values with the model view's camera and fixed region.
    pub fn config_args(&self, setup: &ObservationSetup, fixed: &FixedChoice) -> DatasetOptions {
        let base = DatasetOptions {
            probes: self.probes,
            target_displacement_mm: self.target_displacement_mm,
            young_pa: self.young_pa,
            poisson: self.poisson,
            ..DatasetOptions::default()
        };
        setup.config_args(fixed, &base)
    }

    /// The configuration `umesh dataset generate` builds from the same values (its checks
    /// too), with the camera and fixed region chosen in the model view.
    pub fn config_with(
        &self,
        seg: &Segmentation,
        setup: &ObservationSetup,
        fixed: &FixedChoice,
    ) -> anyhow::Result<DatasetConfig> {
        let grid = umesh_core::grid::GridSettings {
            cell_size_mm: self.cell_size_mm,
            subdivisions: self.subdivisions,
            ..Default::default()
        };
        let (mut c, _) =
            self.config_args(setup, fixed).config(seg, grid, self.samples.max(1), self.seed, self.shard_size)?;
        // Regions the options cannot spell (a posterior slab, a patient's region) are set as they are.
        c.fixed = fixed.region(seg);
        Ok(c)
    }

    /// With the default camera and fixed region.
    pub fn config(&self, seg: &Segmentation) -> anyhow::Result<DatasetConfig> {
        self.config_with(seg, &ObservationSetup::default(), &FixedChoice::default())
    }
}

/// `umesh prepare` from the jobs view: the dataset form's loads, the model view's camera and
/// fixed region, the paper's protocol.
#[derive(Clone, Debug)]
pub struct PatientForm {
    pub out: String,
    pub samples: usize,
    pub epochs: usize,
    pub paper_preset: bool,
    /// The whole job's time budget (min; 0: none), as `umesh prepare --time-budget-min`.
    pub time_budget_min: f64,
}

impl Default for PatientForm {
    fn default() -> Self {
        Self { out: "patients/new".into(), samples: 1000, epochs: 20, paper_preset: false, time_budget_min: 60.0 }
    }
}

impl PatientForm {
    pub fn settings(
        &self,
        dataset: &DatasetForm,
        seg: &Segmentation,
        setup: &ObservationSetup,
        fixed: &FixedChoice,
    ) -> anyhow::Result<PrepareSettings> {
        let form = DatasetForm { samples: self.samples, shard_size: 50, ..dataset.clone() };
        let config = form.config_with(seg, setup, fixed)?;
        let mut s = PrepareSettings::paper(config, fixed.describe(seg).1);
        s.train.epochs = self.epochs.max(1);
        s.train.model = if self.paper_preset { UNetConfig::paper() } else { UNetConfig::cpu() };
        s.time_budget_s = self.time_budget_min.max(0.0) * 60.0;
        Ok(s)
    }
}

#[derive(Clone, Debug)]
pub struct TrainForm {
    pub dataset: String,
    pub out: String,
    pub paper_preset: bool,
    pub epochs: usize,
    pub batch_size: usize,
    pub learning_rate: f64,
    pub seed: u64,
    pub resume: bool,
    /// The network input: "corner", "nearest" (encoded camera views) or "exact" (u_s).
    pub input: &'static str,
}

/// The network inputs the training form offers (`umesh train --input`).
pub const TRAIN_INPUTS: [&str; 3] = ["corner", "nearest", "exact"];

/// The observation settings of a `--input` name (None: exact u_s).
pub fn observation_of(input: &str) -> Option<umesh_core::observation::ObservationSettings> {
    umesh_core::observation::Encoding::parse(input)
        .ok()
        .map(|encoding| umesh_core::observation::ObservationSettings { encoding, ..Default::default() })
}

impl Default for TrainForm {
    fn default() -> Self {
        let t = TrainSettings::default();
        Self {
            dataset: "out/gui-dataset".into(),
            out: "out/gui-model".into(),
            paper_preset: false,
            epochs: 5,
            batch_size: t.batch_size,
            learning_rate: t.learning_rate,
            seed: 0,
            resume: false,
            input: "corner",
        }
    }
}

impl TrainForm {
    pub fn settings(&self) -> TrainSettings {
        TrainSettings {
            model: if self.paper_preset { UNetConfig::paper() } else { UNetConfig::cpu() },
            epochs: self.epochs.max(1),
            batch_size: self.batch_size.max(1),
            learning_rate: self.learning_rate,
            seed: self.seed,
            observation: observation_of(self.input),
            ..Default::default()
        }
    }
}

/// What the dashboard plots: a training job of the queue, or a model folder.
#[derive(Clone, Debug, PartialEq)]
pub enum DashSource {
    Job(u64),
    Folder(PathBuf),
}

#[derive(Resource, Default)]
pub struct JobsUi {
    pub dataset: DatasetForm,
    pub patient: PatientForm,
    pub train: TrainForm,
    pub dash: Option<DashSource>,
    /// The patient job whose figures were last loaded.
    pub patient_shown: Option<u64>,
    pub folder_text: String,
    /// Metrics read from a folder (re-read every second while shown).
    folder_metrics: Option<(Vec<EpochMetrics>, f64)>,
    pub use_last_checkpoint: bool,
    pub expanded: Option<u64>,
}

fn path_field(ui: &mut egui::Ui, label: &str, s: &mut String) {
    ui.horizontal(|ui| {
        ui.label(label);
        ui.add(egui::TextEdit::singleline(s).desired_width(170.0));
    });
}

/// Left panel: the two forms.
pub fn forms_panel(
    ui: &mut egui::Ui,
    f: &mut JobsUi,
    q: &mut WorkQueue,
    organ: &Organ,
    setup: &ObservationSetup,
    fixed: &FixedChoice,
    messages: &mut UiMessages,
) {
    dataset_form(ui, f, q, organ, setup, fixed, messages);
    ui.separator();
    patient_form(ui, f, q, organ, setup, fixed, messages);
    ui.separator();
    training_form(ui, f, q, messages);
}

/// Dataset generation: the paper's protocol with these loads and material, the model view's camera and fixed region.
fn dataset_form(
    ui: &mut egui::Ui,
    f: &mut JobsUi,
    q: &mut WorkQueue,
    organ: &Organ,
    setup: &ObservationSetup,
    fixed: &FixedChoice,
    messages: &mut UiMessages,
) {
    ui.heading("Dataset generation");
    let d = &mut f.dataset;
    egui::Grid::new("dataset_form").num_columns(2).show(ui, |ui| {
        ui.label("samples");
        ui.add(egui::DragValue::new(&mut d.samples).range(1..=100_000));
        ui.end_row();
        ui.label("seed");
        ui.add(egui::DragValue::new(&mut d.seed));
        ui.end_row();
        ui.label("shard size");
        ui.add(egui::DragValue::new(&mut d.shard_size).range(1..=1000));
        ui.end_row();
        ui.label("probes per sample");
        ui.add(egui::DragValue::new(&mut d.probes).range(1..=1000));
        ui.end_row();
        ui.label("target displacement (mm)");
        ui.add(egui::DragValue::new(&mut d.target_displacement_mm).range(0.1..=50.0).speed(0.1));
        ui.end_row();
        ui.label("Young's modulus (Pa)");
        ui.add(egui::DragValue::new(&mut d.young_pa).range(100.0..=1e7).speed(100.0));
        ui.end_row();
        ui.label("Poisson ratio");
        ui.add(egui::DragValue::new(&mut d.poisson).range(0.0..=0.499).speed(0.001));
        ui.end_row();
        ui.label("cell size (mm)");
        ui.add(egui::DragValue::new(&mut d.cell_size_mm).range(2.0..=30.0).speed(0.1));
        ui.end_row();
        ui.label("boundary subdivisions");
        ui.add(egui::DragValue::new(&mut d.subdivisions).range(0..=3));
        ui.end_row();
    });
    path_field(ui, "output folder", &mut d.out);
    let organ_name = organ.data.as_ref().map(|o| o.source.clone());
    ui.weak(format!("organ: {}", organ_name.as_deref().unwrap_or("none loaded")));
    ui.weak(match (&setup.preview, &setup.error) {
        (_, Some(e)) => format!("camera and fixed region (model view): {e:#}"),
        (Some(p), None) => format!(
            "camera and fixed region as in the model view: {:.0} % of the surface seen, {} fixed nodes",
            100.0 * p.visible_fraction,
            p.fixed_nodes_mm.len()
        ),
        (None, None) => "camera and fixed region as chosen in the model view".into(),
    });
    if ui.add_enabled(organ.data.is_some(), egui::Button::new("Queue dataset generation")).clicked()
        && let Some(o) = &organ.data
    {
        let submitted = d.config_with(&o.seg, setup, fixed).and_then(|config| {
            q.submit(WorkKind::Dataset { seg: o.seg.clone(), config: Box::new(config) }, PathBuf::from(d.out.trim()))
        });
        match submitted {
            Ok(id) => {
                messages.info(format!("dataset job #{id} queued"));
                f.train.dataset = d.out.clone();
            }
            Err(e) => messages.error(format!("{e:#}")),
        }
    }
}

/// New patient: `umesh prepare` on the loaded organ.
fn patient_form(
    ui: &mut egui::Ui,
    f: &mut JobsUi,
    q: &mut WorkQueue,
    organ: &Organ,
    setup: &ObservationSetup,
    fixed: &FixedChoice,
    messages: &mut UiMessages,
) {
    ui.heading("New patient");
    ui.weak("umesh prepare: grid, dataset (these loads, the model view's camera and fixed region), training, evaluation, registration check, report.html; resumable");
    let pf = &mut f.patient;
    path_field(ui, "patient folder", &mut pf.out);
    egui::Grid::new("patient_form").num_columns(2).show(ui, |ui| {
        ui.label("samples");
        ui.add(egui::DragValue::new(&mut pf.samples).range(10..=100_000));
        ui.end_row();
        ui.label("epochs");
        ui.add(egui::DragValue::new(&mut pf.epochs).range(1..=10_000));
        ui.end_row();
        ui.label("time budget (min)")
            .on_hover_text("the whole job; training stops before an epoch that would not fit (0: none)");
        ui.add(egui::DragValue::new(&mut pf.time_budget_min).range(0.0..=10_000.0));
        ui.end_row();
        ui.label("network");
        ui.horizontal(|ui| {
            ui.radio_value(&mut pf.paper_preset, false, "cpu");
            ui.radio_value(&mut pf.paper_preset, true, "paper");
        });
        ui.end_row();
    });
    if ui.add_enabled(organ.data.is_some(), egui::Button::new("Queue new patient")).clicked()
        && let Some(o) = &organ.data
    {
        let inputs: Vec<PathBuf> = Some(o.seg.source.clone()).filter(|p| p.is_file()).into_iter().collect();
        let submitted = pf.settings(&f.dataset, &o.seg, setup, fixed).and_then(|settings| {
            q.submit(
                WorkKind::Prepare { seg: o.seg.clone(), inputs, settings: Box::new(settings) },
                PathBuf::from(pf.out.trim()),
            )
        });
        match submitted {
            Ok(id) => messages.info(format!("patient job #{id} queued")),
            Err(e) => messages.error(format!("{e:#}")),
        }
    }
}

/// Training on a dataset folder.
fn training_form(ui: &mut egui::Ui, f: &mut JobsUi, q: &mut WorkQueue, messages: &mut UiMessages) {
    ui.heading("Training");
    let t = &mut f.train;
    path_field(ui, "dataset folder", &mut t.dataset);
    path_field(ui, "model folder", &mut t.out);
    egui::Grid::new("train_form").num_columns(2).show(ui, |ui| {
        ui.label("network");
        ui.horizontal(|ui| {
            ui.radio_value(&mut t.paper_preset, false, "cpu");
            ui.radio_value(&mut t.paper_preset, true, "paper");
        });
        ui.end_row();
        ui.label("input").on_hover_text("corner / nearest: the simulated camera views, encoded as registration encodes each frame; exact: the visible nodes' displacement (u_s), which a camera cannot give");
        ui.horizontal(|ui| {
            for i in TRAIN_INPUTS {
                ui.radio_value(&mut t.input, i, i);
            }
        });
        ui.end_row();
        ui.label("epochs");
        ui.add(egui::DragValue::new(&mut t.epochs).range(1..=10_000));
        ui.end_row();
        ui.label("batch size");
        ui.add(egui::DragValue::new(&mut t.batch_size).range(1..=256));
        ui.end_row();
        ui.label("learning rate");
        ui.add(egui::DragValue::new(&mut t.learning_rate).range(1e-6..=1.0).speed(1e-4));
        ui.end_row();
        ui.label("seed");
        ui.add(egui::DragValue::new(&mut t.seed));
        ui.end_row();
    });
    ui.checkbox(&mut t.resume, "resume from last.safetensors");
    if ui.button("Queue training").clicked() {
        let kind =
            WorkKind::Train { dataset: PathBuf::from(t.dataset.trim()), settings: t.settings(), resume: t.resume };
        match q.submit(kind, PathBuf::from(t.out.trim())) {
            Ok(id) => {
                messages.info(format!("training job #{id} queued"));
                f.dash = Some(DashSource::Job(id));
            }
            Err(e) => messages.error(format!("{e:#}")),
        }
    }
}

fn fmt_secs(s: f64) -> String {
    if s >= 3600.0 {
        format!("{:.0} h {:02.0} min", (s / 3600.0).floor(), (s % 3600.0) / 60.0)
    } else if s >= 60.0 {
        format!("{:.0} min {:02.0} s", (s / 60.0).floor(), s % 60.0)
    } else {
        format!("{s:.0} s")
    }
}

/// Central area: the queue, then the dashboard. Returns a model to load: (folder, checkpoint file).
pub fn queue_and_dashboard(
    ui: &mut egui::Ui,
    f: &mut JobsUi,
    q: &mut WorkQueue,
    active: &ActiveModel,
    patient: &mut OpenPatient,
) -> Option<(PathBuf, String)> {
    // A finished patient job shows its figures (as File > Open patient would, without the organ).
    if let Some(item) = q.items.iter().rev().find(|i| i.label == "patient" && matches!(i.status, WorkStatus::Done(_)))
        && f.patient_shown != Some(item.id)
    {
        f.patient_shown = Some(item.id);
        if let Ok(fig) = umesh_workflow::patient::read_figures(&item.out) {
            patient.0 = Some(fig);
        }
    }
    if let Some(fig) = &patient.0 {
        egui::CollapsingHeader::new(format!("Patient {}", fig.dir.display())).default_open(true).show(ui, |ui| {
            if let Some(show) = patient_figures(ui, fig) {
                f.dash = Some(DashSource::Folder(show));
            }
        });
        ui.separator();
    }
    ui.heading("Jobs");
    if q.items.is_empty() {
        ui.label("No jobs yet: queue a dataset generation or a training on the left.");
    }
    let mut cancel = None;
    egui::ScrollArea::vertical().id_salt("queue").max_height(ui.available_height() * 0.42).show(ui, |ui| {
        for item in q.items.iter().rev() {
            ui.horizontal(|ui| {
                let open = f.expanded == Some(item.id);
                if ui.small_button(if open { "-" } else { "+" }).clicked() {
                    f.expanded = if open { None } else { Some(item.id) };
                }
                ui.strong(format!("#{} {}", item.id, item.label));
                ui.label(item.out.display().to_string());
                match &item.status {
                    WorkStatus::Queued => {
                        ui.weak("queued");
                    }
                    WorkStatus::Running => {
                        let (frac, rate, eta) = item.rate();
                        let msg = item.progress.lock().map(|p| p.message.clone()).unwrap_or_default();
                        let unit = if item.label == "training" { "batches" } else { "samples" };
                        let mut text = msg;
                        if let Some(r) = rate {
                            text += &format!(" · {:.2} {unit}/s", r);
                        }
                        if let Some(e) = eta {
                            text += &format!(" · ETA {}", fmt_secs(e));
                        }
                        ui.add(egui::ProgressBar::new(frac).desired_width(300.0).text(text));
                    }
                    WorkStatus::Done(m) => {
                        ui.colored_label(
                            egui::Color32::LIGHT_GREEN,
                            format!("done in {}: {m}", fmt_secs(item.seconds.unwrap_or(0.0))),
                        );
                    }
                    WorkStatus::Failed(e) => {
                        ui.colored_label(egui::Color32::LIGHT_RED, format!("failed: {e:#}"));
                    }
                    WorkStatus::Cancelled => {
                        ui.weak("cancelled");
                    }
                }
                if item.status.is_active() && ui.button("Cancel").clicked() {
                    cancel = Some(item.id);
                }
                if item.label == "training" && ui.small_button("plot").clicked() {
                    f.dash = Some(DashSource::Job(item.id));
                }
            });
            if f.expanded == Some(item.id) {
                ui.indent(item.id, |ui| {
                    ui.label(egui::RichText::new(&item.command).monospace().small());
                    if let Ok(log) = item.log.lock() {
                        for l in log.iter().rev().take(12).rev() {
                            ui.label(egui::RichText::new(l).small());
                        }
                    }
                });
            }
        }
    });
    if let Some(id) = cancel {
        q.cancel(id);
    }
    ui.separator();
    dashboard(ui, f, q, active)
}

fn dashboard(ui: &mut egui::Ui, f: &mut JobsUi, q: &WorkQueue, active: &ActiveModel) -> Option<(PathBuf, String)> {
    ui.horizontal(|ui| {
        ui.heading("Training dashboard");
        ui.label("model folder:");
        ui.add(egui::TextEdit::singleline(&mut f.folder_text).desired_width(200.0));
        if ui.button("Show").clicked() {
            f.folder_metrics = None;
            f.dash =
                (!f.folder_text.trim().is_empty()).then(|| DashSource::Folder(PathBuf::from(f.folder_text.trim())));
        }
    });
    let (metrics, folder): (Vec<EpochMetrics>, Option<PathBuf>) = match &f.dash {
        None => {
            ui.label("Queue a training, or type a model folder (for example assets/model) and press Show.");
            return None;
        }
        Some(DashSource::Job(id)) => match q.items.iter().find(|i| i.id == *id) {
            Some(item) => (item.metrics.lock().map(|m| m.clone()).unwrap_or_default(), Some(item.out.clone())),
            None => (Vec::new(), None),
        },
        Some(DashSource::Folder(dir)) => {
            let now = ui.ctx().input(|i| i.time);
            let stale = f.folder_metrics.as_ref().is_none_or(|(_, t)| now - t > 1.0);
            if stale {
                match read_metrics(dir) {
                    Ok(m) => f.folder_metrics = Some((m, now)),
                    Err(e) => {
                        ui.colored_label(egui::Color32::LIGHT_RED, format!("{e:#}"));
                        return None;
                    }
                }
            }
            (f.folder_metrics.as_ref().map(|m| m.0.clone()).unwrap_or_default(), Some(dir.clone()))
        }
    };
    if metrics.is_empty() {
        ui.label("No epoch finished yet.");
    } else if let Some(last) = metrics.last() {
        let best = metrics.iter().min_by(|a, b| a.val_loss.total_cmp(&b.val_loss)).map(|m| m.epoch).unwrap_or(0);
        ui.label(format!(
            "{} epochs; last: val TRE {:.2} mm (max {:.2}), {:.1} samples/s; best validation loss at epoch {best}",
            metrics.len(),
            last.val_tre_mean_mm,
            last.val_tre_max_mm,
            last.train_samples_per_s
        ));
    }
    let pts =
        |g: &dyn Fn(&EpochMetrics) -> f64| -> PlotPoints { metrics.iter().map(|m| [m.epoch as f64, g(m)]).collect() };
    let h = (ui.available_height() - 40.0).max(120.0);
    let w = ui.available_width() / 2.0 - 8.0;
    ui.horizontal(|ui| {
        Plot::new("loss")
            .width(w)
            .height(h)
            .legend(Legend::default())
            .x_axis_label("epoch")
            .y_axis_label("log10 loss")
            .show(ui, |p| {
                p.line(Line::new("train loss", pts(&|m| m.train_loss.max(1e-12).log10())));
                p.line(Line::new("validation loss", pts(&|m| m.val_loss.max(1e-12).log10())));
            });
        Plot::new("tre")
            .width(w)
            .height(h)
            .legend(Legend::default())
            .x_axis_label("epoch")
            .y_axis_label("validation TRE (mm)")
            .show(ui, |p| {
                p.line(Line::new("mean", pts(&|m| m.val_tre_mean_mm)));
                p.line(Line::new("max", pts(&|m| m.val_tre_max_mm)));
            });
    });
    let mut load = None;
    if let Some(dir) = folder {
        ui.horizontal(|ui| {
            ui.label("checkpoint:");
            ui.radio_value(&mut f.use_last_checkpoint, false, "best (model.safetensors)");
            ui.radio_value(&mut f.use_last_checkpoint, true, "last (last.safetensors)");
            let file = if f.use_last_checkpoint { "last.safetensors" } else { "model.safetensors" };
            let exists = dir.join(file).is_file() && dir.join("model.json").is_file();
            if ui
                .add_enabled(exists, egui::Button::new("Load as the active model"))
                .on_disabled_hover_text("no such checkpoint yet")
                .clicked()
            {
                load = Some((dir.clone(), file.to_string()));
            }
            ui.weak(format!("active: {} ({})", crate::app::state::short_path(&active.dir), active.checkpoint));
        });
    }
    load
}

/// The report's figures for a patient folder: stages, dataset acceptance and displacement
/// against target, validation TRE, the registration check. Returns the model folder when
/// its learning curves are asked for.
pub fn patient_figures(ui: &mut egui::Ui, fig: &PatientFigures) -> Option<PathBuf> {
    use egui_plot::{Bar, BarChart};
    let mut show_curves = None;
    let p = &fig.patient;
    ui.label(format!(
        "organ {} · structures {} · fixed: {}",
        p.organ_labels.join(", "),
        p.structures.join(", "),
        p.settings.fixed_description
    ));
    ui.horizontal_wrapped(|ui| {
        for s in umesh_workflow::patient::Stage::ALL {
            let r = p.stages.get(&s);
            let done = r.is_some_and(|r| r.done);
            let text = format!("{} {}", s.name(), r.map(|r| fmt_secs(r.seconds)).unwrap_or_else(|| "-".into()));
            ui.colored_label(if done { egui::Color32::LIGHT_GREEN } else { egui::Color32::GRAY }, text);
        }
    });
    if let Some(d) = &fig.dataset {
        let rejected: Vec<String> = d.rejected.iter().map(|(k, v)| format!("{v} {k}")).collect();
        ui.label(format!(
            "dataset: {} / {} accepted{}; mean nodal displacement {} for a target of {} mm",
            d.accepted,
            d.samples,
            if rejected.is_empty() { String::new() } else { format!(" ({})", rejected.join(", ")) },
            d.mean_displacement_mm
                .as_ref()
                .map(|m| format!("{:.2} mm (p5 {:.1}, p95 {:.1})", m.mean, m.p5, m.p95))
                .unwrap_or_else(|| "-".into()),
            d.target_displacement_mm
        ));
    }
    // The report's binning: (bar centre, width, count).
    let hist = |values: &[f64], bins: usize| -> Vec<(f64, f64, f64)> {
        let (lo, hi, counts) = umesh_workflow::report::histogram_bins(values, bins, None);
        let w = (hi - lo) / counts.len() as f64;
        counts.into_iter().enumerate().map(|(i, c)| (lo + (i as f64 + 0.5) * w, w, c as f64)).collect()
    };
    ui.columns(2, |cols| {
        let achieved: Vec<f64> = fig.mean_vs_target_mm.iter().map(|x| x.0).collect();
        cols[0].label("achieved mean displacement (mm)");
        let bars: Vec<Bar> = hist(&achieved, 20).into_iter().map(|(x, w, c)| Bar::new(x, c).width(w * 0.95)).collect();
        Plot::new("patient_disp").height(140.0).x_axis_label("mm").y_axis_label("samples").show(&mut cols[0], |pl| {
            pl.bar_chart(BarChart::new("samples", bars));
        });
        cols[1].label("validation TRE per marker (mm)");
        let tre = fig.eval.as_ref().map(|e| e.per_marker_tre_mm.clone()).unwrap_or_default();
        let bars: Vec<Bar> = hist(&tre, 20).into_iter().map(|(x, w, c)| Bar::new(x, c).width(w * 0.95)).collect();
        Plot::new("patient_tre").height(140.0).x_axis_label("mm").y_axis_label("markers").show(&mut cols[1], |pl| {
            pl.bar_chart(BarChart::new("markers", bars));
        });
    });
    if let Some(e) = &fig.eval {
        ui.label(format!(
            "validation TRE {:.2} mm mean, {:.2} max, at a mean marker displacement of {:.2} mm",
            e.tre_mean_mm, e.tre_max_mm, e.marker_displacement_mean_mm
        ));
    }
    if let Some(w) = fig.check.as_ref().and_then(|c| c.warning.as_ref()) {
        ui.colored_label(egui::Color32::from_rgb(230, 160, 40), format!("registration check did not run: {w}"));
    } else if let Some(c) = &fig.check {
        let o = |v: Option<f64>| v.map(|v| format!("{v:.2}")).unwrap_or_else(|| "-".into());
        ui.label(format!(
            "registration check, last frame: TRE {} mm, rigid only {}, marker motion {} ({} frames, {:.0} ms median)",
            o(c.last_frame_tre_mm),
            o(c.last_frame_tre_rigid_mm),
            o(c.last_frame_marker_displacement_mm),
            c.summary.frames,
            c.summary.frame_ms_median
        ));
        if let Some(ch) = &c.correction {
            ui.weak(ch.describe());
        }
    }
    ui.horizontal(|ui| {
        if !fig.metrics.is_empty() && ui.button("Learning curves").clicked() {
            show_curves = Some(umesh_workflow::patient::model_dir(&fig.dir));
        }
        let report = fig.dir.join("report.html");
        if report.is_file() {
            ui.weak(format!("report: {}", report.display()));
        }
    });
    show_curves
}
