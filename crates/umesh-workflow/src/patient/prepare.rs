//! One patient from segmentation to checked model: grid, dataset (the paper's protocol),
//! training, evaluation and a synthetic-recording registration check, as one resumable job.
//!
//! The patient folder holds `patient.json` (inputs and their hashes, every setting, stage
//! status and timings), `segmentation.nii.gz` (the label volume the job used, so later
//! commands need not find the original files), `dataset/`, `model/`, `eval.json`,
//! `check/recording/` and `check/register.json`, and `report.html`. Every stage resumes from
//! what is on disk; a folder made from other inputs or settings is refused.

use super::folder::{
    CheckReport, FORMAT, FORMAT_VERSION, Patient, PrepareReport, PrepareSettings, Stage, Verdict, hash_inputs,
    model_dir, read_json, read_metrics, same_as_stored, settings_differences, write_json,
};
use std::path::{Path, PathBuf};
use std::time::Instant;
use umesh_core::dataset::{DatasetConfig, DatasetContext, DatasetStats, ShardSelection, run_generate, run_stats};
use umesh_core::register::RegistrationContext;
use umesh_core::register::correction::{CorrectionChoice, CorrectionForm, FormFigures};
use umesh_core::register::pipeline::{DisplacementModel, GroundTruth, RegisterReport, RegisterSettings, run_register};
use umesh_core::rgbd::recording::Recording;
use umesh_core::rgbd::stream::RecordingSource;
use umesh_core::segmentation::Segmentation;
use umesh_core::synth::{SynthReport, run_rgbd_synth};
use umesh_core::{Cancel, Progress};
use umesh_net::inference::Predictor;
use umesh_net::training::{EpochMetrics, run_train};
use umesh_net::{NetError, eval};

/// Estimated cost of each stage (arbitrary units ~ 10 ms on 2 cores), for one progress bar.
fn stage_weights(s: &PrepareSettings) -> [u64; 6] {
    let samples = s.dataset.samples as u64;
    let train = (samples * 4 / 5).max(1);
    [
        samples * 75,
        s.train.epochs as u64 * train * 8,
        (samples / 5).max(1) * 3,
        s.check.frames as u64 * 100,
        s.check.frames as u64 * 10,
        10,
    ]
}

/// A progress callback for one stage, mapped into the job's total.
fn stage_progress(global: &Progress, offset: u64, width: u64, total: u64, stage: Stage) -> Progress {
    let g = global.clone();
    Progress::new(move |done, t, msg| {
        let frac = if t > 0 { (done as f64 / t as f64).clamp(0.0, 1.0) } else { 0.0 };
        // The stage's own count in the message: the figures after it are the job's units
        // (a log read "samples: 5475/205810" for sample 73 of 1000).
        let msg = if t > 0 {
            format!("{}: {msg} {done} of {t}; job", stage.name())
        } else {
            format!("{}: {msg}", stage.name())
        };
        g.report(offset + (frac * width as f64) as u64, total, &msg);
    })
}

/// Run (or resume) the whole job for `seg` into `out`. `inputs` are the files the
/// segmentation was read from (hashed and stored); nothing is written before every input
/// and setting has been checked.
pub fn run_prepare(
    seg: &Segmentation,
    inputs: &[PathBuf],
    out: &Path,
    settings: &PrepareSettings,
    preflight: Option<&umesh_core::dataset::PreflightCheck>,
    progress: &Progress,
    cancel: &Cancel,
) -> Result<PrepareReport, NetError> {
    let start = Instant::now();
    // The cell size the hour affords, before anything is built on the grid.
    let settings = &super::grid_budget::fit_grid_to_budget(seg, settings, cancel)?;
    // The surface step a registration frame affords, before the dataset is built on it.
    let settings = &super::surface_budget::fit_surface_to_budget(seg, settings, cancel)?;
    let settings = &super::prior::resolve_prior(settings)?;
    // Checks first: labels, grid, fixed region, camera (all raise before anything is written).
    let ctx = DatasetContext::prepare(seg, &settings.dataset, cancel)?;
    check_job(seg, settings, &ctx)?;
    let mut patient = new_patient(seg, inputs, settings)?;
    resume_or_start(out, settings, &mut patient)?;
    preflight_new(out, settings, &ctx, preflight, progress, cancel)?;
    drop(ctx);
    std::fs::create_dir_all(out).map_err(|e| NetError::Io { path: out.to_path_buf(), source: e })?;
    store_segmentation(seg, out, &mut patient)?;
    patient.write(out)?;

    // What earlier runs of this job spent (a resumed job's time budget counts it).
    let earlier_s: f64 = patient.stages.values().map(|r| r.seconds).sum();
    let weights = stage_weights(settings);
    let total: u64 = weights.iter().sum();
    let offset = |s: Stage| weights[..Stage::ALL.iter().position(|x| *x == s).unwrap_or(0)].iter().sum::<u64>();
    let width = |s: Stage| weights[Stage::ALL.iter().position(|x| *x == s).unwrap_or(0)];
    let sp = |s: Stage| stage_progress(progress, offset(s), width(s), total, s);
    let run_stage = |patient: &mut Patient,
                     s: Stage,
                     f: &mut dyn FnMut(&Progress) -> Result<(), NetError>|
     -> Result<(), NetError> {
        if patient.done(s) {
            progress.report(offset(s) + width(s), total, &format!("{}: done before", s.name()));
            return Ok(());
        }
        let t = Instant::now();
        let r = f(&sp(s));
        let rec = patient.stages.entry(s).or_default();
        rec.seconds += t.elapsed().as_secs_f64();
        rec.done = r.is_ok();
        patient.write(out)?;
        r
    };

    let ds_dir = out.join("dataset");
    let model = model_dir(out);
    let mut samples_per_minute = None;
    run_stage(&mut patient, Stage::Dataset, &mut |p| {
        let r =
            run_generate(seg, &ds_dir, &settings.dataset, ShardSelection::all(), p, cancel).map_err(|e| match e {
                umesh_core::dataset::DatasetError::Cancelled(c) => NetError::Cancelled(c),
                e => e.into(),
            })?;
        if r.samples_computed > 0 {
            samples_per_minute = Some(r.samples_per_minute);
        }
        Ok(())
    })?;
    let stats = run_stats(&ds_dir)?;
    let train_settings = training_settings(settings, earlier_s + start.elapsed().as_secs_f64());
    let mut stopped_early = None;
    run_stage(&mut patient, Stage::Train, &mut |p| {
        let r = run_train(&ds_dir, &model, &train_settings, true, p, &|_| {}, cancel)?;
        stopped_early = r.stopped_early;
        Ok(())
    })?;
    if let Some(why) = stopped_early {
        patient.stages.entry(Stage::Train).or_default().note = Some(why);
        patient.write(out)?;
    }
    let eval_path = out.join("eval.json");
    run_stage(&mut patient, Stage::Eval, &mut |p| {
        p.report(0, 1, "validation TRE");
        let r = eval::run_eval(&model, &ds_dir, settings.eval_markers)?;
        write_json(&eval_path, &r)
    })?;
    let eval: eval::EvalReport = read_json(&eval_path)?;
    let rec_dir = out.join("check").join("recording");
    let synth_path = out.join("check").join("recording.json");
    let synth_failed_path = out.join("check").join("recording-failed.json");
    run_stage(&mut patient, Stage::Recording, &mut |p| {
        make_check_recording(seg, settings, &stats, &rec_dir, (&synth_path, &synth_failed_path), p, cancel)
    })?;
    let check_path = out.join("check").join("register.json");
    run_stage(&mut patient, Stage::Register, &mut |p| {
        check_registration(seg, settings, &model, &rec_dir, (&synth_failed_path, &check_path), p, cancel)
    })?;
    let check: CheckReport = read_json(&check_path)?;
    let synth: Option<SynthReport> = read_json(&synth_path).ok();
    let metrics = read_metrics(&model);
    let verdict = write_report(out, &mut patient, settings, &stats, &metrics, &eval, synth.as_ref(), &check)?;
    let stopped_early = patient.stages.get(&Stage::Train).and_then(|r| r.note.clone());
    progress.report(total, total, "done");
    Ok(PrepareReport {
        out: out.into(),
        grid: settings.grid_description.clone(),
        surface: settings.surface_description.clone(),
        prior: settings.prior_description.clone(),
        stages: Stage::ALL
            .iter()
            .map(|s| (*s, patient.stages.get(s).map(|r| r.seconds).unwrap_or(0.0), patient.done(*s)))
            .collect(),
        dataset: stats,
        dataset_samples_per_minute: samples_per_minute,
        final_epoch: metrics.last().cloned(),
        training_stopped_early: stopped_early,
        eval,
        check_recording: synth,
        check,
        verdict,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// The network fits the organ's grid, and the job has samples to split and epochs to run.
fn check_job(seg: &Segmentation, settings: &PrepareSettings, ctx: &DatasetContext) -> Result<(), NetError> {
    settings
        .train
        .network()
        .check_shape([
            1,
            settings.train.network().in_channels,
            ctx.grid.padded_shape()[0],
            ctx.grid.padded_shape()[1],
            ctx.grid.padded_shape()[2],
        ])
        .map_err(|e| NetError::Invalid(format!("{}: {e}", seg.source.display())))?;
    if settings.dataset.samples < 10 {
        return Err(NetError::Invalid(format!(
            "{} samples: at least 10 are needed for a train/validation split",
            settings.dataset.samples
        )));
    }
    if settings.train.epochs == 0 {
        return Err(NetError::Invalid("0 epochs: at least one is needed".into()));
    }
    Ok(())
}

/// A folder holding this patient's earlier run: its stages (and, when finished, its time
/// budget) carried over. Refused: another segmentation, other label names, other settings, or a
/// folder that is not empty and holds no patient.
fn resume_or_start(out: &Path, settings: &PrepareSettings, patient: &mut Patient) -> Result<(), NetError> {
    let seg_hash = &patient.segmentation_hash;
    if out.join("patient.json").exists() {
        let old = Patient::read(out)?;
        if old.segmentation_hash != *seg_hash {
            return Err(NetError::Invalid(format!(
                "{}: holds a patient prepared from another segmentation (segmentation hash {} vs {seg_hash}); choose an empty folder",
                out.display(),
                old.segmentation_hash
            )));
        }
        // The same voxels under other names are another patient's segmentation: its structures
        // would be drawn under the wrong names, or dropped by `register --patient`.
        if (&old.organ_labels, &old.structures) != (&patient.organ_labels, &patient.structures) {
            return Err(NetError::Invalid(format!(
                "{}: holds a patient whose label names differ (organ {:?}, structures {:?}; now organ {:?}, structures {:?}); choose an empty folder",
                out.display(),
                old.organ_labels,
                old.structures,
                patient.organ_labels,
                patient.structures
            )));
        }
        if !same_as_stored(&old.settings, settings)? {
            return Err(NetError::Invalid(format!(
                "{}: holds a patient prepared with other settings (same segmentation): {}; choose an empty folder or the same options",
                out.display(),
                settings_differences(&old.settings, settings).join(", ")
            )));
        }
        // A resumed job's budget counts the time its earlier runs spent; a finished job run
        // again only rewrites its report, and keeps the budget its work was done under.
        let finished = Stage::ALL.iter().all(|s| *s == Stage::Report || old.done(*s));
        patient.settings.time_budget_s = if finished { old.settings.time_budget_s } else { settings.time_budget_s };
        patient.stages = old.stages;
        patient.stored_segmentation_hash = old.stored_segmentation_hash;
    } else if out.exists() && std::fs::read_dir(out).map(|mut d| d.next().is_some()).unwrap_or(false) {
        return Err(NetError::Invalid(format!(
            "{}: the folder is not empty and holds no patient.json; choose an empty folder",
            out.display()
        )));
    }
    Ok(())
}

/// The label volume the job uses, with its names, kept in the folder (and its hash, so an edit
/// later is seen).
fn store_segmentation(seg: &Segmentation, out: &Path, patient: &mut Patient) -> Result<(), NetError> {
    let seg_path = out.join("segmentation.nii.gz");
    if !seg_path.exists() {
        let mut vol = seg.volume.clone();
        // Names travel with the labels so that `Patient::segmentation` finds them again.
        for &l in seg.organ_labels.iter().chain(&seg.structure_labels) {
            vol.label_names.entry(l).or_insert_with(|| seg.label_name(l));
        }
        umesh_core::nifti_io::write_volume(&seg_path, &vol, umesh_core::nifti_io::WriteType::I16)
            .map_err(|e| NetError::Io { path: seg_path.to_path_buf(), source: e })?;
    }
    if patient.stored_segmentation_hash.is_none() {
        let stored = patient.read_segmentation(out)?;
        patient.stored_segmentation_hash = Some(umesh_core::dataset::segmentation_hash(&stored));
    }
    Ok(())
}

/// The check's synthetic recording: its load within what the dataset's samples reached, lighter
/// when the organ does not converge; when none converges the reason is written instead (the job
/// then ends with its model and a warning, never fails after training).
#[allow(clippy::too_many_arguments)]
fn make_check_recording(
    seg: &Segmentation,
    settings: &PrepareSettings,
    stats: &DatasetStats,
    rec_dir: &Path,
    (synth_path, synth_failed_path): (&Path, &Path),
    p: &Progress,
    cancel: &Cancel,
) -> Result<(), NetError> {
    // The check's load starts within what the dataset's samples reached, and an organ whose
    // load still does not converge (an element inverts) is checked at lighter loads; if none
    // converges the job ends with its model and a warning, never fails after training.
    let mut check = settings.check.clone();
    if let Some(reach) = stats.achieved_over_target.as_ref().map(|d| d.median)
        && reach < 1.0 - umesh_core::dataset::CALIBRATION_TOLERANCE / 2.0
    {
        check.load_scale *= reach;
    }
    let mut failures = Vec::new();
    // A failure recorded by an interrupted earlier run is not this run's.
    let _ = std::fs::remove_file(synth_failed_path);
    for _ in 0..3 {
        let _ = std::fs::remove_dir_all(rec_dir);
        match run_rgbd_synth(seg, &settings.dataset, &check, rec_dir, p, cancel) {
            Ok(r) => return write_json(synth_path, &r),
            Err(umesh_core::rgbd::RgbdError::Cancelled(c)) => return Err(c.into()),
            Err(umesh_core::rgbd::RgbdError::Io { path, source }) => return Err(NetError::Io { path, source }),
            Err(e) => failures.push(format!("at load scale {:.2}: {e}", check.load_scale)),
        }
        check.load_scale *= 0.6;
    }
    let _ = std::fs::remove_dir_all(rec_dir);
    write_json(synth_failed_path, &format!("the check recording could not be made: {}", failures.join("; ")))
}

/// The verdict, and `report.html` written with it (on every run: its timings change).
#[allow(clippy::too_many_arguments)]
fn write_report(
    out: &Path,
    patient: &mut Patient,
    settings: &PrepareSettings,
    stats: &DatasetStats,
    metrics: &[EpochMetrics],
    eval: &eval::EvalReport,
    synth: Option<&SynthReport>,
    check: &CheckReport,
) -> Result<Verdict, NetError> {
    // The report is rewritten on every run (its timings change).
    let t = Instant::now();
    patient.stages.entry(Stage::Report).or_default().done = true;
    let stopped_early = patient.stages.get(&Stage::Train).and_then(|r| r.note.clone());
    let verdict = super::judge(metrics, settings.train.epochs, stopped_early.as_deref(), eval, check, out);
    let html = super::page::patient_html(
        patient,
        &verdict,
        stats,
        metrics,
        eval,
        synth,
        check,
        &out.join("dataset").join("grid.npz"),
    );
    umesh_core::write_atomic(&out.join("report.html"), html.as_bytes())
        .map_err(|e| NetError::Io { path: out.to_path_buf(), source: e })?;
    let rec = patient.stages.entry(Stage::Report).or_default();
    rec.done = true;
    rec.seconds = t.elapsed().as_secs_f64();
    patient.write(out)?;
    Ok(verdict)
}

/// The record of a new job on this segmentation: its inputs' hashes, names and settings.
fn new_patient(seg: &Segmentation, inputs: &[PathBuf], settings: &PrepareSettings) -> Result<Patient, NetError> {
    let hashed = hash_inputs(inputs)?;
    let seg_hash = umesh_core::dataset::segmentation_hash(seg);
    let names = |ls: &[i64]| ls.iter().map(|&l| seg.label_name(l)).collect::<Vec<_>>();
    Ok(Patient {
        format: FORMAT.into(),
        format_version: FORMAT_VERSION,
        program_version: env!("CARGO_PKG_VERSION").into(),
        inputs: hashed,
        segmentation_hash: seg_hash.clone(),
        organ_labels: names(&seg.organ_labels),
        structures: names(&seg.structure_labels),
        stored_segmentation_hash: None,
        settings: settings.clone(),
        stages: Default::default(),
    })
}

/// The check: the recording registered with the new model (each correction form, the chosen
/// one written into the model folder), or why it did not run.
fn check_registration(
    seg: &Segmentation,
    settings: &PrepareSettings,
    model: &Path,
    rec_dir: &Path,
    (synth_failed_path, check_path): (&Path, &Path),
    p: &Progress,
    cancel: &Cancel,
) -> Result<(), NetError> {
    let r = match read_json::<String>(synth_failed_path) {
        Ok(reason) => CheckReport::not_run(reason),
        Err(_) => match registration_check(seg, &settings.dataset, model, rec_dir, p, cancel) {
            Ok(r) => r,
            Err(NetError::Cancelled(c)) => return Err(c.into()),
            Err(e) => CheckReport::not_run(format!("the registration check failed: {e}")),
        },
    };
    write_json(check_path, &r)
}

/// The training's settings with its share of the job's time budget: what the stages before it
/// left (`spent` seconds so far, earlier runs included), less what the stages after it take.
fn training_settings(settings: &PrepareSettings, spent: f64) -> umesh_net::TrainSettings {
    // The job's time budget: training gets what the stages before it left, less what the
    // stages after it take (an estimate: the evaluation and the check's frames).
    let mut train = settings.train.clone();
    if settings.time_budget_s > 0.0 {
        let after = 60.0 + 5.0 * settings.check.frames as f64;
        // At least one epoch runs whatever the budget: a model is the job's point.
        train.time_budget_s = (settings.time_budget_s - spent - after).max(1e-3);
    }
    train
}

/// A new patient's dataset checked before the folder exists: a job that would store too few
/// samples stops here with its likely cause.
fn preflight_new(
    out: &Path,
    settings: &PrepareSettings,
    ctx: &DatasetContext,
    preflight: Option<&umesh_core::dataset::PreflightCheck>,
    progress: &Progress,
    cancel: &Cancel,
) -> Result<(), NetError> {
    // A new patient's dataset is checked before the folder exists: a job that would store too
    // few samples stops here with its likely cause.
    if let Some(check) = preflight
        && !out.join("patient.json").exists()
        && settings.dataset.samples > check.settings.samples
    {
        let p = ctx.preflight(&settings.dataset, &check.settings, progress, cancel).map_err(|e| match e {
            umesh_core::dataset::DatasetError::Cancelled(c) => NetError::Cancelled(c),
            e => e.into(),
        })?;
        check.judge(p).map_err(|e| NetError::Invalid(e.to_string()))?;
    }
    Ok(())
}

/// Register the check recording with the patient's model, once with each correction form
/// (`CorrectionForm`): TRE against the recording's truth; the form chosen on it is written into
/// the model folder (`CorrectionChoice`) and its registration is the check's figure.
/// Register every frame of the recording in `dir` from its first camera pose, against its
/// ground truth, reporting frames done out of the recording's; an error when no frame could
/// be registered.
pub fn register_recording(
    dir: &Path,
    ctx: &RegistrationContext,
    model: &mut dyn DisplacementModel,
    settings: &RegisterSettings,
    progress: &Progress,
    cancel: &Cancel,
) -> Result<RegisterReport, NetError> {
    let invalid = |e: String| NetError::Invalid(e);
    let truth = GroundTruth::read(&dir.join("ground_truth.json")).map_err(|e| invalid(e.to_string()))?;
    let rec = Recording::open(dir, None).map_err(|e| invalid(e.to_string()))?;
    let pose = rec
        .trajectory
        .as_ref()
        .and_then(|t| t.first().copied())
        .ok_or_else(|| invalid(format!("{}: no camera pose", dir.display())))?;
    // The recording's length is known: frames done out of it (a live source reports none).
    let frames = rec.len() as u64;
    let p = progress.clone();
    let progress = Progress::new(move |done, _, msg| p.report(done, frames, msg));
    let mut source = RecordingSource::new(rec);
    let r = run_register(&mut source, ctx, model, pose, Some(&truth), settings, &mut |_| Ok(()), &progress, cancel)
        .map_err(|e| match e {
            umesh_core::rgbd::RgbdError::Cancelled(c) => NetError::Cancelled(c),
            e => invalid(e.to_string()),
        })?;
    if r.summary.frames == 0 {
        return Err(invalid(format!("{}: no frame could be registered: {}", dir.display(), r.log.join("; "))));
    }
    Ok(r)
}

pub fn registration_check(
    seg: &Segmentation,
    config: &DatasetConfig,
    model: &Path,
    recording: &Path,
    progress: &Progress,
    cancel: &Cancel,
) -> Result<CheckReport, NetError> {
    let mut net = Predictor::load(model)?;
    let dctx = DatasetContext::prepare(seg, config, cancel)?;
    net.info.check_grid(&dctx.grid_hash(), dctx.grid.padded_shape())?;
    let ctx = RegistrationContext::new(dctx, seg).map_err(|e| NetError::Invalid(e.into()))?;
    // Each form as it runs at surgery, the overlay drawn: its frame time is what the choice
    // for a frame budget reads. The two forms near the budget run twice, alternated, and keep
    // the quicker median: this machine's noise only ever adds time, and one busy minute made
    // the coarse tracking form read 34 ms where registering again read 23. The tracking form
    // costs several frames' time and runs once.
    let forms = [CorrectionForm::Subspace, CorrectionForm::CoarseTracking, CorrectionForm::Tracking];
    let repeated = [0, 1];
    let n = (forms.len() + repeated.len()) as u64;
    let mut run = |k: usize, form: CorrectionForm| {
        let settings = RegisterSettings { overlay: true, correction: form.settings(), ..Default::default() };
        let p = progress.clone();
        let (k, name) = (k as u64, form.name());
        let inner = Progress::new(move |done, total, msg| {
            p.report(k * total + done, n * total, &format!("{name} correction: {msg}"))
        });
        register_recording(recording, &ctx, &mut net, &settings, &inner, cancel)
    };
    let mut runs = Vec::with_capacity(forms.len());
    for (k, &form) in forms.iter().enumerate() {
        runs.push(run(k, form)?);
    }
    let mut frame_ms: Vec<f64> = runs.iter().map(|r| r.summary.frame_ms_median).collect();
    // The runs are deterministic: the repeats are read for their time alone.
    for (k, &i) in repeated.iter().enumerate() {
        let r = run(forms.len() + k, forms[i])?;
        frame_ms[i] = frame_ms[i].min(r.summary.frame_ms_median);
    }
    let figures: Vec<Option<FormFigures>> = runs
        .iter()
        .zip(&frame_ms)
        .map(|(r, &ms)| r.form_figures().map(|f| FormFigures { frame_ms_median: ms, ..f }))
        .collect();
    let choice = match (figures[0], figures[2]) {
        (Some(s), Some(t)) => {
            let c = CorrectionChoice::decide_among(s, figures[1], t, recording);
            c.write(model).map_err(|e| NetError::Invalid(e.0))?;
            Some(c)
        }
        _ => None,
    };
    let chosen = choice.as_ref().map_or(CorrectionForm::Subspace, |c| c.form);
    let r = &runs[forms.iter().position(|f| *f == chosen).unwrap_or(0)];
    let last = r.frames.last();
    Ok(CheckReport {
        summary: (&r.summary).into(),
        last_frame_tre_mm: last.and_then(|f| f.tre_mean_mm),
        last_frame_tre_rigid_mm: last.and_then(|f| f.tre_rigid_mean_mm),
        last_frame_marker_displacement_mm: last.and_then(|f| f.marker_displacement_mean_mm),
        log: r.log.clone(),
        warning: None,
        correction: choice,
    })
}
