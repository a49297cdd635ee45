//! Dataset generation and training as queued background jobs, with the CLI's settings and
//! the CLI's output files. One job runs at a time (the solver and the trainer each use every
//! core they get); the others wait in the queue. Two jobs may not write the same folder.

use crate::app::shell::tasks::{JobProgress, lower_thread_priority};
use crate::app::state::UiMessages;
use anyhow::Context;
use bevy::prelude::*;
use bevy::tasks::{AsyncComputeTaskPool, Task, futures::check_ready};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Instant;
use umesh_core::dataset::{DatasetConfig, ShardSelection, run_generate_checked};
use umesh_core::segmentation::Segmentation;
use umesh_core::{Cancel, Progress};
use umesh_net::TrainSettings;
use umesh_net::training::{EpochMetrics, run_train};
use umesh_workflow::patient::{PrepareSettings, run_prepare};

pub enum WorkKind {
    Dataset {
        seg: Arc<Segmentation>,
        config: Box<DatasetConfig>,
    },
    Train {
        dataset: PathBuf,
        settings: TrainSettings,
        resume: bool,
    },
    /// `umesh prepare`: the whole job into a patient folder.
    Prepare {
        seg: Arc<Segmentation>,
        inputs: Vec<PathBuf>,
        settings: Box<PrepareSettings>,
    },
}

impl WorkKind {
    pub fn label(&self) -> &'static str {
        match self {
            WorkKind::Dataset { .. } => "dataset",
            WorkKind::Train { .. } => "training",
            WorkKind::Prepare { .. } => "patient",
        }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub enum WorkStatus {
    Queued,
    Running,
    Done(String),
    Failed(String),
    Cancelled,
}

impl WorkStatus {
    pub fn is_active(&self) -> bool {
        matches!(self, WorkStatus::Queued | WorkStatus::Running)
    }
}

pub struct WorkItem {
    pub id: u64,
    pub label: &'static str,
    pub out: PathBuf,
    /// The settings as saved beside the outputs (`umesh-job.json`).
    pub settings: serde_json::Value,
    /// The equivalent command line.
    pub command: String,
    pub status: WorkStatus,
    pub progress: Arc<Mutex<JobProgress>>,
    pub log: Arc<Mutex<Vec<String>>>,
    /// Training only: one entry per finished epoch, as they come.
    pub metrics: Arc<Mutex<Vec<EpochMetrics>>>,
    pub cancel: Cancel,
    pub started: Option<Instant>,
    pub seconds: Option<f64>,
    kind: Option<WorkKind>,
    task: Option<Task<anyhow::Result<String>>>,
}

impl WorkItem {
    /// (fraction done, items per second, seconds left) of a running job.
    pub fn rate(&self) -> (f32, Option<f64>, Option<f64>) {
        let p = self.progress.lock().map(|p| p.clone()).unwrap_or_default();
        let frac = if p.total > 0 { p.done as f32 / p.total as f32 } else { 0.0 };
        if self.started.is_none() {
            return (frac, None, None);
        }
        let now = Instant::now();
        (frac, p.eta.rate_per_s(p.done, now), p.eta.seconds_left(p.done, p.total, now))
    }
}

#[derive(Resource, Default)]
pub struct WorkQueue {
    pub items: Vec<WorkItem>,
    next_id: u64,
}

/// A folder path made comparable: absolute, and canonical where it exists.
pub fn normalize(p: &Path) -> PathBuf {
    let joined = if p.is_absolute() {
        p.to_path_buf()
    } else {
        std::env::current_dir().map(|d| d.join(p)).unwrap_or_else(|_| p.into())
    };
    // Lexically first: "a/x/.." is "a" even when "a/x" does not exist.
    let mut abs = PathBuf::new();
    for c in joined.components() {
        match c {
            std::path::Component::ParentDir => {
                abs.pop();
            }
            std::path::Component::CurDir => {}
            c => abs.push(c),
        }
    }
    // Canonicalise the longest existing ancestor, keep the rest as written.
    let mut head = abs.clone();
    let mut tail = Vec::new();
    while !head.exists() {
        match (head.file_name().map(|s| s.to_os_string()), head.parent()) {
            (Some(name), Some(parent)) => {
                tail.push(name);
                head = parent.to_path_buf();
            }
            _ => return abs,
        }
    }
    let mut out = head.canonicalize().unwrap_or(head);
    for t in tail.into_iter().rev() {
        out.push(t);
    }
    out
}

impl WorkQueue {
    /// Queue a job writing into `out`. Refused when a queued or running job writes there.
    pub fn submit(&mut self, kind: WorkKind, out: PathBuf) -> anyhow::Result<u64> {
        if out.as_os_str().is_empty() {
            anyhow::bail!("choose an output folder");
        }
        let norm = normalize(&out);
        if let Some(other) = self.items.iter().find(|i| i.status.is_active() && normalize(&i.out) == norm) {
            anyhow::bail!(
                "{}: job #{} ({}) already writes there; wait for it or choose another folder",
                out.display(),
                other.id,
                other.label
            );
        }
        if let WorkKind::Train { dataset, .. } = &kind
            && normalize(dataset) == norm
        {
            anyhow::bail!("{}: the model folder must differ from the dataset folder", out.display());
        }
        if let WorkKind::Train { dataset, .. } = &kind {
            umesh_workflow::patient::check_model_out(&out, dataset)?;
        }
        let (settings, command) = describe(&kind, &out);
        self.next_id += 1;
        let id = self.next_id;
        self.items.push(WorkItem {
            id,
            label: kind.label(),
            out,
            settings,
            command,
            status: WorkStatus::Queued,
            progress: Default::default(),
            log: Default::default(),
            metrics: Default::default(),
            cancel: Cancel::new(),
            started: None,
            seconds: None,
            kind: Some(kind),
            task: None,
        });
        Ok(id)
    }

    pub fn cancel(&mut self, id: u64) {
        if let Some(i) = self.items.iter_mut().find(|i| i.id == id) {
            match i.status {
                WorkStatus::Queued => i.status = WorkStatus::Cancelled,
                WorkStatus::Running => i.cancel.cancel(),
                _ => {}
            }
        }
    }

    pub fn running(&self) -> Option<&WorkItem> {
        self.items.iter().find(|i| i.status == WorkStatus::Running)
    }
}

/// The settings as JSON and the equivalent CLI command.
fn describe(kind: &WorkKind, out: &Path) -> (serde_json::Value, String) {
    match kind {
        WorkKind::Dataset { seg, config } => {
            let c = config;
            let src = seg.source.display().to_string();
            let input =
                if src.contains("phantom") && !Path::new(&src).exists() { String::new() } else { format!("{src} ") };
            let command = format!(
                "umesh dataset generate {input}--samples {} --seed {} --shard-size {} {} --out {}",
                c.samples,
                c.seed,
                c.shard_size,
                dataset_options(c),
                out.display()
            );
            (serde_json::json!({ "kind": "dataset", "segmentation": src, "config": c }), command)
        }
        WorkKind::Train { dataset, settings, resume } => {
            let s = settings;
            let command = format!(
                "umesh train --dataset {} --out {} --input {} --channels {} --steps {} --epochs {} --batch-size {} --learning-rate {} --seed {}{}{}{}",
                dataset.display(),
                out.display(),
                s.observation.as_ref().map(|o| o.encoding.name()).unwrap_or("exact"),
                s.model.channels,
                s.model.steps,
                s.epochs,
                s.batch_size,
                s.learning_rate,
                s.seed,
                if s.observation.is_some() && !s.fresh_views { " --stored-views" } else { "" },
                if s.observation.is_some() && s.fresh_views {
                    format!(" --rest-views {}", s.rest_views)
                } else {
                    String::new()
                },
                if *resume { " --resume" } else { "" }
            );
            (serde_json::json!({ "kind": "training", "dataset": dataset, "settings": s, "resume": resume }), command)
        }
        WorkKind::Prepare { inputs, settings, .. } => {
            let c = &settings.dataset;
            let input = inputs.iter().map(|p| format!("{} ", p.display())).collect::<String>();
            let command = format!(
                "umesh prepare {input}--samples {} --epochs {} --preset {} --input {} {} --out {}",
                c.samples,
                settings.train.epochs,
                if settings.train.model == umesh_net::UNetConfig::paper() { "paper" } else { "cpu" },
                settings.train.observation.as_ref().map(|o| o.encoding.name()).unwrap_or("exact"),
                dataset_options(c),
                out.display()
            );
            (serde_json::json!({ "kind": "patient", "inputs": inputs, "settings": settings }), command)
        }
    }
}

/// The loads, material, grid, camera and fixed-region options of a configuration (shared by
/// `dataset generate` and `prepare`).
fn dataset_options(c: &DatasetConfig) -> String {
    format!(
        "--probes {} --target-displacement-mm {} --visible-fraction {} --young-pa {} --poisson {} --cell-size-mm {} --subdivisions {}{}",
        c.forces.probes,
        c.forces.target_displacement_mm,
        c.visibility.max_fraction,
        c.material.young_pa,
        c.material.poisson,
        c.grid.cell_size_mm,
        c.grid.subdivisions,
        camera_and_fixed_options(c)
    )
}

/// The camera and fixed-region options of a configuration, as typed on the command line
/// (a region no option spells is named as such).
fn camera_and_fixed_options(c: &DatasetConfig) -> String {
    use umesh_core::fem::FixedRegion;
    let list = |v: &[f64]| v.iter().map(|x| format!("{x:.1}")).collect::<Vec<_>>().join(",");
    let mut out = String::new();
    if let Some(cam) = &c.visibility.camera {
        let to: Vec<f64> = (0..3).map(|i| cam.position_mm[i] + cam.direction[i]).collect();
        out +=
            &format!(" --camera-from {} --camera-to {} --fov-deg {}", list(&cam.position_mm), list(&to), cam.fov_deg);
    }
    out += &match &c.fixed {
        FixedRegion::Label { label, distance_mm } => format!(" --fix-label {label} --fix-distance-mm {distance_mm}"),
        FixedRegion::Box { min_mm, max_mm } => format!(" --fix-box {},{}", list(min_mm), list(max_mm)),
        FixedRegion::Plane { normal, offset_mm, thickness_mm } => {
            format!(" --fix-plane {},{offset_mm:.1},{thickness_mm:.1}", list(normal))
        }
        other => format!(" (fixed region {other:?} as chosen in the app)"),
    };
    out
}

fn start(item: &mut WorkItem) {
    let Some(kind) = item.kind.take() else { return };
    let (p2, log, metrics, cancel, out) =
        (item.progress.clone(), item.log.clone(), item.metrics.clone(), item.cancel.clone(), item.out.clone());
    let record = serde_json::json!({ "settings": item.settings, "command": item.command });
    item.status = WorkStatus::Running;
    item.started = Some(Instant::now());
    if let Ok(mut p) = item.progress.lock() {
        *p = JobProgress::default();
    }
    item.task = Some(AsyncComputeTaskPool::get().spawn(async move {
        let sink = progress_sink(p2, log.clone());
        // A patient folder records its own settings (patient.json) and refuses foreign files.
        if !matches!(kind, WorkKind::Prepare { .. }) {
            std::fs::create_dir_all(&out).with_context(|| out.display().to_string())?;
            let job_file = out.join(umesh_net::training::JOB_FILE);
            umesh_core::write_atomic(&job_file, serde_json::to_string_pretty(&record).unwrap_or_default().as_bytes())
                .with_context(|| job_file.display().to_string())?;
        }
        let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(2);
        let pool =
            rayon::ThreadPoolBuilder::new().num_threads(threads).start_handler(|_| lower_thread_priority()).build()?;
        // The pre-flight figures go to the job's log; a job it refuses ends at once with the
        // likely cause as its error.
        let report_preflight = |p: &umesh_core::dataset::Preflight| {
            if let Ok(mut l) = log.lock() {
                l.push(p.summary());
            }
        };
        let check = umesh_core::dataset::PreflightCheck {
            settings: Default::default(),
            force: false,
            report: &report_preflight,
        };
        pool.install(|| run_work(kind, &out, &check, &sink, &cancel, &log, &metrics))
    }));
}

/// The job's progress, its messages also appended to its log (the last 500 lines kept).
fn progress_sink(progress: Arc<Mutex<JobProgress>>, log: Arc<Mutex<Vec<String>>>) -> Progress {
    let push = move |line: String| {
        if let Ok(mut l) = log.lock() {
            l.push(line);
            let n = l.len();
            if n > 500 {
                l.drain(..n - 500);
            }
        }
    };
    let last_msg = Mutex::new(String::new());
    Progress::new(move |done, total, msg| {
        if let Ok(mut p) = progress.lock() {
            p.update(done, total, msg);
        }
        if let Ok(mut m) = last_msg.lock()
            && *m != msg
        {
            *m = msg.to_string();
            push(msg.to_string());
        }
    })
}

/// Run one job on the current thread pool; its summary line, or why it failed.
fn run_work(
    kind: WorkKind,
    out: &std::path::Path,
    check: &umesh_core::dataset::PreflightCheck,
    sink: &Progress,
    cancel: &Cancel,
    log: &Mutex<Vec<String>>,
    metrics: &Mutex<Vec<EpochMetrics>>,
) -> anyhow::Result<String> {
    match kind {
        WorkKind::Dataset { seg, config } => {
            let r = run_generate_checked(&seg, out, &config, ShardSelection::all(), Some(check), sink, cancel)?;
            Ok(format!(
                "{} samples computed ({} reused), {} accepted; {:.1} samples/min",
                r.samples_computed, r.samples_reused, r.accepted, r.samples_per_minute
            ))
        }
        WorkKind::Prepare { seg, inputs, settings } => {
            let r = run_prepare(&seg, &inputs, out, &settings, Some(check), sink, cancel)?;
            Ok(format!(
                "{} / {} samples accepted, validation TRE {:.2} mm; {}; report.html written",
                r.dataset.accepted,
                r.dataset.samples,
                r.eval.tre_mean_mm,
                match &r.check.warning {
                    Some(w) => format!("warning: {w}"),
                    None => format!(
                        "check TRE {} mm (rigid {})",
                        r.check.last_frame_tre_mm.map(|v| format!("{v:.2}")).unwrap_or_else(|| "-".into()),
                        r.check.last_frame_tre_rigid_mm.map(|v| format!("{v:.2}")).unwrap_or_else(|| "-".into())
                    ),
                },
            ))
        }
        WorkKind::Train { dataset, settings, resume } => {
            let on_epoch = |m: &EpochMetrics| {
                if let Ok(mut v) = metrics.lock() {
                    v.push(m.clone());
                }
                if let Ok(mut l) = log.lock() {
                    l.push(format!(
                        "epoch {}: train loss {:.3e}, val loss {:.3e}, val TRE {:.2} mm (max {:.2}), {:.0} s",
                        m.epoch, m.train_loss, m.val_loss, m.val_tre_mean_mm, m.val_tre_max_mm, m.seconds
                    ));
                }
            };
            let r = run_train(&dataset, out, &settings, resume, sink, &on_epoch, cancel)?;
            Ok(format!(
                "best epoch {} of {}; {} train / {} validation samples",
                r.best_epoch,
                r.epochs.len(),
                r.train_samples,
                r.val_samples
            ))
        }
    }
}

/// Poll the running job; start the next queued one.
pub fn run_queue(mut q: ResMut<WorkQueue>, mut messages: ResMut<UiMessages>) {
    for item in q.items.iter_mut().filter(|i| i.status == WorkStatus::Running) {
        let Some(task) = &mut item.task else { continue };
        let Some(result) = check_ready(task) else { continue };
        item.task = None;
        item.seconds = item.started.map(|t| t.elapsed().as_secs_f64());
        item.status = match result {
            Ok(msg) => {
                messages.info(format!("{} job #{} finished: {msg}", item.label, item.id));
                WorkStatus::Done(msg)
            }
            Err(_) if item.cancel.is_cancelled() => {
                messages.info(format!(
                    "{} job #{} cancelled (what was written is kept; run it again to resume)",
                    item.label, item.id
                ));
                WorkStatus::Cancelled
            }
            Err(e) => {
                messages.error(format!("{} job #{} ({}) failed: {e:#}", item.label, item.id, item.out.display()));
                WorkStatus::Failed(format!("{e:#}"))
            }
        };
        if let Ok(mut l) = item.log.lock() {
            l.push(format!("{:?}", item.status));
        }
    }
    if q.running().is_none()
        && let Some(next) = q.items.iter_mut().find(|i| i.status == WorkStatus::Queued)
    {
        start(next);
    }
}

/// Training metrics of a model folder (`metrics.jsonl`), for the dashboard; a training still
/// running (or cancelled) into that folder writes them in its staging folder beside it.
pub fn read_metrics(dir: &Path) -> anyhow::Result<Vec<EpochMetrics>> {
    let pending = umesh_core::StagedDir::pending_path(dir).join("metrics.jsonl");
    let path = if pending.exists() { pending } else { dir.join("metrics.jsonl") };
    let text = std::fs::read_to_string(&path).with_context(|| path.display().to_string())?;
    text.lines()
        .filter(|l| !l.trim().is_empty())
        .enumerate()
        .map(|(i, l)| serde_json::from_str(l).with_context(|| format!("{} line {}", path.display(), i + 1)))
        .collect()
}

pub struct WorkflowPlugin;

impl Plugin for WorkflowPlugin {
    fn build(&self, app: &mut App) {
        app.init_resource::<WorkQueue>().add_systems(Update, run_queue);
    }
}
