//! Training with Adam on the mean squared error of Eq. 1, per-epoch validation loss and TRE,
//! safetensors checkpoints, resume, metrics as JSON lines; optionally a cosine learning rate,
//! a stop on a validation plateau and a time budget (the epochs that fit, planned after each).

use crate::data::{Normalization, SampleSet};
use crate::info::{ModelInfo, TrainSettings};
use crate::model::{UNet, UNetConfig};
use crate::model::{load_weights, save_weights};
use crate::{NetError, tre};
use burn::optim::{AdamConfig, GradientsParams};
use burn::prelude::*;
use std::path::{Path, PathBuf};
use std::time::Instant;
use umesh_core::rng::SplitMix64;
use umesh_core::{Cancel, Progress};

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EpochMetrics {
    pub epoch: usize,
    pub train_loss: f64,
    pub val_loss: f64,
    pub val_tre_mean_mm: f64,
    pub val_tre_max_mm: f64,
    pub seconds: f64,
    pub train_samples_per_s: f64,
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct TrainReport {
    pub out: PathBuf,
    pub epochs: Vec<EpochMetrics>,
    pub train_samples: usize,
    pub val_samples: usize,
    pub best_epoch: usize,
    /// Why training ended before the epochs asked (a plateau, the time budget), if it did.
    pub stopped_early: Option<String>,
}

/// When to stop before the epochs asked, and how far the learning-rate schedule plans.
struct EpochPlan {
    asked: usize,
    patience: usize,
    budget_s: f64,
    /// Training seconds of this run so far, and its epochs.
    spent_s: f64,
    run_epochs: usize,
}

impl EpochPlan {
    /// The last epoch this run will reach: the epochs asked, or fewer when the budget stops it
    /// (each epoch taken to cost the mean of this run's so far).
    fn last_epoch(&self, done: usize) -> usize {
        if self.budget_s <= 0.0 || self.run_epochs == 0 {
            return self.asked;
        }
        let per_epoch = self.spent_s / self.run_epochs as f64;
        // `as usize` saturates (a budget of 1e30 s); the sum must not wrap either.
        let more = ((self.budget_s - self.spent_s) / per_epoch).floor().max(0.0) as usize;
        done.saturating_add(more).min(self.asked)
    }

    /// Why to stop after epoch `done` (`best_epoch` the best so far), if so.
    fn stop(&self, done: usize, best_epoch: usize) -> Option<String> {
        if done >= self.asked {
            return None;
        }
        if self.patience > 0 && done >= best_epoch.saturating_add(self.patience) {
            return Some(format!(
                "validation plateau: no better validation loss in the {} epochs after epoch {best_epoch}; stopped after epoch {done} of {}",
                self.patience, self.asked
            ));
        }
        if self.last_epoch(done) <= done {
            return Some(format!(
                "time budget: another epoch (about {:.0} s) would end after {:.0} s of training; stopped after epoch {done} of {}",
                self.spent_s / self.run_epochs.max(1) as f64,
                self.budget_s,
                self.asked
            ));
        }
        None
    }
}

pub(crate) fn batch(set: &[Vec<f32>], ids: &[usize], shape: [usize; 3], scale: f32, device: &Device) -> Tensor<5> {
    let cells = shape[0] * shape[1] * shape[2];
    let channels = ids.first().map(|&k| set[k].len() / cells.max(1)).unwrap_or(3);
    let mut data = Vec::with_capacity(ids.len() * channels * cells);
    for &k in ids {
        data.extend(set[k].iter().map(|v| v / scale));
    }
    Tensor::from_data(TensorData::new(data, [ids.len(), channels, shape[0], shape[1], shape[2]]), device)
}

/// The targets of `ids`: u_v, or zero for a sample seen at rest this epoch.
fn target_batch(set: &SampleSet, ids: &[usize], rest: &[bool], scale: f32, device: &Device) -> Tensor<5> {
    let [x, y, z] = set.shape;
    let n = 3 * x * y * z;
    let mut data = Vec::with_capacity(ids.len() * n);
    for &k in ids {
        if rest[k] {
            data.resize(data.len() + n, 0.0);
        } else {
            data.extend(set.u_v[k].iter().map(|v| v / scale));
        }
    }
    Tensor::from_data(TensorData::new(data, [ids.len(), 3, x, y, z]), device)
}

/// The settings of the app's job that made a folder (written there before the job runs).
pub use umesh_core::JOB_FILE;

/// Copy the files (not folders) of `from` into `to`: a resumed model continues in its staging copy.
fn copy_files(from: &Path, to: &Path) -> Result<(), NetError> {
    let entries = std::fs::read_dir(from).map_err(|e| NetError::Io { path: from.to_path_buf(), source: e })?;
    for e in entries.flatten() {
        if e.file_type().is_ok_and(|t| t.is_file()) {
            let dst = to.join(e.file_name());
            std::fs::copy(e.path(), &dst).map_err(|err| NetError::Io { path: dst.clone(), source: err })?;
        }
    }
    Ok(())
}

/// Validation loss and per-sample mean TRE over `ids`.
pub(crate) fn validate(
    model: &UNet,
    set: &SampleSet,
    ids: &[usize],
    norm: &Normalization,
    markers: &[nalgebra::Vector3<f64>],
    device: &Device,
) -> (f64, Vec<f64>, Vec<f64>) {
    let mut loss = 0.0;
    let mut tres = Vec::new();
    let mut moved = Vec::new();
    for &k in ids {
        let x = batch(&set.u_s, &[k], set.shape, norm.input_scale_mm, device);
        let y = batch(&set.u_v, &[k], set.shape, norm.output_scale_mm, device);
        let p = model.forward(x);
        loss += (p.clone() - y).square().mean().into_scalar::<f32>() as f64;
        let pred: Vec<f32> =
            p.into_data().try_to_vec::<f32>().unwrap_or_default().iter().map(|v| v * norm.output_scale_mm).collect();
        let (err, disp) = tre::marker_errors(&set.grid, markers, &pred, &set.u_v[k]);
        tres.extend(err);
        moved.extend(disp);
    }
    (loss / ids.len().max(1) as f64, tres, moved)
}

/// Train on the dataset in `dataset`, writing the model folder `out`.
pub fn run_train(
    dataset: &Path,
    out: &Path,
    settings: &TrainSettings,
    resume: bool,
    progress: &Progress,
    on_epoch: &(dyn Fn(&EpochMetrics) + Sync),
    cancel: &Cancel,
) -> Result<TrainReport, NetError> {
    check_settings(settings)?;
    check_out_apart(dataset, out, settings)?;
    let mut set = SampleSet::load_inputs(dataset, settings.observation.as_ref())?;
    let mut rest = vec![false; set.len()];
    let refresher = match (&settings.observation, settings.fresh_views) {
        (Some(o), true) => Some(crate::data::ViewRefresher::new(dataset, o)?),
        _ => None,
    };
    let (train, val) = split(&set, dataset)?;
    let cfg = &settings.network();
    cfg.check_shape([1, set.channels, set.shape[0], set.shape[1], set.shape[2]])
        .map_err(|e| NetError::Invalid(format!("{}: {e}", dataset.display())))?;
    let final_out = out;
    let staged = stage(final_out, resume)?;
    let out = staged.path();
    let device = Device::flex();
    device.seed(settings.seed);
    let ad = device.clone().autodiff();
    let mut norm = Normalization::fit(&set, &train);
    let mut model = cfg.init(&ad);
    let metrics_path = out.join("metrics.jsonl");
    let manifest = umesh_core::dataset::Manifest::read(dataset).ok();
    let start = Start { dataset, out, resume, manifest: manifest.as_ref() };
    let mut epochs = start.load(settings, set.shape, &mut model, &mut norm, &metrics_path)?;
    let markers = tre::markers(&set.grid, settings.markers, settings.seed ^ 0x5EED);
    write_info(out, dataset, settings, (&set, &train, &val), norm, manifest)?;
    let mut optim = AdamConfig::new().init();
    let mut best = epochs.iter().map(|e| e.val_loss).fold(f64::INFINITY, f64::min);
    let mut best_epoch = epochs.iter().min_by(|a, b| a.val_loss.total_cmp(&b.val_loss)).map(|e| e.epoch).unwrap_or(0);
    let total_batches = settings.epochs.saturating_mul(train.len().div_ceil(settings.batch_size.max(1)));
    let mut done_batches = epochs.len() * train.len().div_ceil(settings.batch_size.max(1));
    let mut plan = EpochPlan {
        asked: settings.epochs,
        patience: settings.patience,
        budget_s: settings.time_budget_s,
        spent_s: 0.0,
        run_epochs: 0,
    };
    let mut stopped_early = epochs.last().and_then(|e| plan.stop(e.epoch, best_epoch));
    for epoch in epochs.len() + 1..=settings.epochs {
        if stopped_early.is_some() {
            break;
        }
        let t = Instant::now();
        let learning_rate = settings.lr_schedule.rate(settings.learning_rate, epoch, plan.last_epoch(epoch - 1));
        let order = shuffled(&train, settings.seed.wrapping_add(epoch as u64));
        if let Some(r) = &refresher
            && epoch > 1
        {
            progress.report(
                done_batches as u64,
                total_batches as u64,
                &format!("epoch {epoch}/{}: new camera views", settings.epochs),
            );
            r.refresh(&mut set, &train, epoch, settings.rest_views, &mut rest)
                .map_err(|e| NetError::Invalid(format!("{}: {e}", dataset.display())))?;
        }
        let batches: Vec<&[usize]> = order.chunks(settings.batch_size.max(1)).collect();
        let steps = Steps { learning_rate, epoch, epochs: settings.epochs, total_batches };
        let train_loss;
        (model, train_loss) = train_batches(
            model,
            &mut optim,
            &batches,
            (&set, &rest, &norm),
            &ad,
            &steps,
            &mut done_batches,
            progress,
            cancel,
        )?;
        let train_secs = t.elapsed().as_secs_f64();
        let valid = model.valid();
        let (val_loss, tres, _) = validate(&valid, &set, &val, &norm, &markers, &device);
        let (tre_mean, _, tre_max) = tre::summary(&tres);
        let m = EpochMetrics {
            epoch,
            train_loss,
            val_loss,
            val_tre_mean_mm: tre_mean,
            val_tre_max_mm: tre_max,
            seconds: t.elapsed().as_secs_f64(),
            train_samples_per_s: train.len() as f64 / train_secs.max(1e-9),
        };
        // The last weights (for --resume) and the best so far (the model).
        save_weights(&valid, &out.join("last.safetensors"))?;
        if val_loss < best {
            (best, best_epoch) = (val_loss, epoch);
            save_weights(&valid, &out.join("model.safetensors"))?;
        }
        append_metrics(&metrics_path, &m)?;
        plan.spent_s += m.seconds;
        plan.run_epochs += 1;
        stopped_early = plan.stop(epoch, best_epoch);
        on_epoch(&m);
        epochs.push(m);
    }
    check_usable(out, best, &epochs, settings, final_out)?;
    // The calibration ends the training: its views are reported as the training's last step
    // (every batch counted), not as a count from zero, which a job's progress read as the
    // stage starting over (a prepare's log went from 201368 of 205810 units back to 75640, an
    // hour and a half "left").
    let calibrating = {
        let (p, all) = (progress.clone(), total_batches as u64);
        Progress::new(move |view, views, msg| p.report(all, all, &format!("{msg} (view {view} of {views}), batches")))
    };
    calibrate_confidence(out, dataset, settings, &calibrating)?;
    staged.commit().map_err(|e| NetError::Io { path: final_out.to_path_buf(), source: e })?;
    Ok(TrainReport {
        out: final_out.into(),
        epochs,
        train_samples: train.len(),
        val_samples: val.len(),
        best_epoch,
        stopped_early,
    })
}

/// The model (and its staging folder beside it) is not written into a dataset or a model it
/// reads.
fn check_out_apart(dataset: &Path, out: &Path, settings: &TrainSettings) -> Result<(), NetError> {
    // The model (and its staging folder beside it) must not be written into a dataset or a
    // model it reads. Fine-tuning a model in place (`--init-from M --out M`) is safe: its
    // weights are read before the new folder is swapped in, and only when training succeeds.
    let mut inputs: Vec<(&str, &Path)> = vec![("--dataset", dataset)];
    if let Some(prior) = &settings.prior {
        inputs.push(("--prior", prior.as_path()));
    }
    if let Some(init) = &settings.init_from {
        let same = matches!((init.canonicalize(), out.canonicalize()), (Ok(a), Ok(b)) if a == b);
        if !same {
            inputs.push(("--init-from", init.as_path()));
        }
    }
    umesh_core::check_apart(out, &inputs).map_err(|e| NetError::Invalid(e.0))
}

/// The staging folder the model is written in.
fn stage(final_out: &Path, resume: bool) -> Result<umesh_core::StagedDir, NetError> {
    // Training runs in a staging folder beside `out`, kept on failure or cancel (so `resume`
    // continues there) and swapped in whole at the end: a failed or cancelled run never leaves
    // `out` half-overwritten, and no file of an earlier model survives in the new one.
    let pending = umesh_core::StagedDir::pending_path(final_out);
    let continue_pending = resume && pending.join("last.safetensors").exists();
    let staged = umesh_core::StagedDir::resumable(
        final_out,
        umesh_core::OutputKind::Model,
        &["model.json", "metrics.jsonl", JOB_FILE],
        continue_pending,
    )
    .map_err(|e| NetError::Io { path: final_out.to_path_buf(), source: e })?;
    let out = staged.path();
    if resume && !continue_pending && final_out.join("last.safetensors").exists() {
        copy_files(final_out, out)?;
        // The correction form was chosen for the weights before: the resumed model has none
        // until it is checked again (`umesh choose-correction`, or prepare's check).
        let _ = std::fs::remove_file(out.join(umesh_core::register::correction::CorrectionChoice::FILE));
    }
    // The app records a job's settings in the folder before it runs: they travel with the model.
    let job = final_out.join(JOB_FILE);
    if job.is_file() {
        std::fs::copy(&job, out.join(JOB_FILE)).map_err(|e| NetError::Io { path: job.to_path_buf(), source: e })?;
    }
    Ok(staged)
}

/// Swapped in only when usable: a run whose validation loss was never finite (diverged) leaves
/// the folder it would replace as it was.
fn check_usable(
    out: &Path,
    best: f64,
    epochs: &[EpochMetrics],
    settings: &TrainSettings,
    final_out: &Path,
) -> Result<(), NetError> {
    if !out.join("model.safetensors").exists() || !best.is_finite() {
        let last = epochs.last().map(|m| m.val_loss).unwrap_or(f64::NAN);
        return Err(NetError::Invalid(format!(
            "training produced no usable weights (validation loss {last} at the last epoch, never finite: the learning rate {} is too large for this dataset?); {} left as it was",
            settings.learning_rate,
            final_out.display()
        )));
    }
    Ok(())
}

/// The training and validation samples (80/20), refused when either would be empty.
fn split(set: &SampleSet, dataset: &Path) -> Result<(Vec<usize>, Vec<usize>), NetError> {
    let (train, val) = set.split();
    if train.is_empty() || val.is_empty() {
        return Err(NetError::Invalid(format!(
            "{}: {} samples are too few for an 80/20 split",
            dataset.display(),
            set.len()
        )));
    }
    Ok((train, val))
}

/// `model.json` (and the grid beside it: registration needs its visible nodes and surface).
fn write_info(
    out: &Path,
    dataset: &Path,
    settings: &TrainSettings,
    (set, train, val): (&SampleSet, &[usize], &[usize]),
    norm: Normalization,
    manifest: Option<umesh_core::dataset::Manifest>,
) -> Result<(), NetError> {
    // The grid travels with the model: registration needs its visible nodes and surface.
    let grid_src = dataset.join("grid.npz");
    if let Ok(bytes) = std::fs::read(&grid_src) {
        umesh_core::write_atomic(&out.join("grid.npz"), &bytes)
            .map_err(|e| NetError::Io { path: out.to_path_buf(), source: e })?;
    }
    let info = ModelInfo {
        config: settings.network(),
        normalization: norm,
        padded_shape: set.shape,
        dataset: dataset.display().to_string(),
        train_indices: train.iter().map(|&k| set.indices[k]).collect(),
        val_indices: val.iter().map(|&k| set.indices[k]).collect(),
        settings: settings.clone(),
        grid_hash: manifest.as_ref().map(|m| m.grid_hash.clone()),
        dataset_config: manifest.map(|m| m.config),
    };
    info.write(out)
}

/// The training samples in an epoch's order: a Fisher-Yates shuffle from the epoch's seed.
fn shuffled(train: &[usize], seed: u64) -> Vec<usize> {
    let mut order = train.to_vec();
    let mut rng = SplitMix64(seed);
    for i in (1..order.len()).rev() {
        order.swap(i, (rng.next_u64() % (i as u64 + 1)) as usize);
    }
    order
}

/// Where a training starts: the dataset, the staging folder, whether it resumes, the dataset's
/// manifest.
struct Start<'a> {
    dataset: &'a Path,
    out: &'a Path,
    resume: bool,
    manifest: Option<&'a umesh_core::dataset::Manifest>,
}

impl Start<'_> {
    /// With --init-from, the network and its scales come from that model; a resumed run keeps
    /// the scales and continues from its own last weights and epochs (returned).
    fn load(
        &self,
        settings: &TrainSettings,
        shape: [usize; 3],
        model: &mut UNet,
        norm: &mut Normalization,
        metrics_path: &Path,
    ) -> Result<Vec<EpochMetrics>, NetError> {
        if let Some(init) = &settings.init_from {
            let from = check_init_from(init, &settings.network(), shape, self.manifest, self.dataset)?;
            if !(self.resume && self.out.join("last.safetensors").exists()) {
                load_weights(model, &init.join("model.safetensors"))?;
            }
            // The weights expect the scales they were trained with.
            *norm = from.normalization;
        }
        if let Some(prior) = &settings.prior {
            let from = check_prior(prior, settings)?;
            if !(self.resume && self.out.join("last.safetensors").exists()) {
                load_weights(model, &prior.join("model.safetensors"))?;
            }
            *norm = from.normalization;
        }
        if self.resume && self.out.join("last.safetensors").exists() {
            check_resume(self.out, self.manifest, &settings.network(), self.dataset)?;
            load_weights(model, &self.out.join("last.safetensors"))?;
            if let Ok(text) = std::fs::read_to_string(metrics_path) {
                return Ok(text.lines().filter_map(|l| serde_json::from_str(l).ok()).collect());
            }
        }
        Ok(Vec::new())
    }
}

/// What registration compares each frame's fit with (camera-view models only).
fn calibrate_confidence(
    out: &Path,
    dataset: &Path,
    settings: &TrainSettings,
    progress: &Progress,
) -> Result<(), NetError> {
    if settings.observation.is_some() && out.join("model.safetensors").exists() {
        let r = crate::eval::calibrate_confidence(out, dataset, progress)?;
        crate::eval::write_confidence(out, &r)?;
    }
    Ok(())
}

/// Where an epoch stands in the training: its learning rate, its number, and the batches of
/// the whole run (for progress).
struct Steps {
    learning_rate: f64,
    epoch: usize,
    epochs: usize,
    total_batches: usize,
}

/// One epoch's batches, each a forward pass, a backward pass and an Adam step: the model and
/// the mean training loss.
#[allow(clippy::too_many_arguments)]
fn train_batches(
    mut model: UNet,
    optim: &mut burn::optim::ModuleOptimizer,
    batches: &[&[usize]],
    (set, rest, norm): (&SampleSet, &[bool], &Normalization),
    ad: &Device,
    steps: &Steps,
    done_batches: &mut usize,
    progress: &Progress,
    cancel: &Cancel,
) -> Result<(UNet, f64), NetError> {
    let mut train_loss = 0.0;
    for ids in batches {
        cancel.check()?;
        let x = batch(&set.u_s, ids, set.shape, norm.input_scale_mm, ad);
        let y = target_batch(set, ids, rest, norm.output_scale_mm, ad);
        let loss = (model.forward(x) - y).square().mean();
        train_loss += loss.clone().into_scalar::<f32>() as f64;
        let grads = GradientsParams::from_grads(loss.backward(), &model);
        model = optim.step(steps.learning_rate, model, grads);
        *done_batches += 1;
        progress.report(
            *done_batches as u64,
            steps.total_batches as u64,
            &format!("epoch {}/{}", steps.epoch, steps.epochs),
        );
    }
    Ok((model, train_loss / batches.len().max(1) as f64))
}

/// The settings a training can run with, each refused naming its option.
fn check_settings(settings: &TrainSettings) -> Result<(), NetError> {
    if !(settings.rest_views.is_finite() && (0.0..=0.5).contains(&settings.rest_views)) {
        return Err(NetError::Invalid(format!("rest_views must be in [0, 0.5], got {}", settings.rest_views)));
    }
    if !(settings.time_budget_s.is_finite() && settings.time_budget_s >= 0.0) {
        return Err(NetError::Invalid(format!(
            "the time budget must be a finite number of seconds >= 0, got {}",
            settings.time_budget_s
        )));
    }
    // Adam's step: above 1 the weights leave any useful range at the first batch; 0 or less
    // (or NaN) learns nothing. Either would end without usable weights.
    if !(settings.learning_rate.is_finite() && settings.learning_rate > 0.0 && settings.learning_rate <= 1.0) {
        return Err(NetError::Invalid(format!(
            "--learning-rate {}: a finite rate above 0 and at most 1",
            umesh_core::shown(settings.learning_rate)
        )));
    }
    if settings.epochs == 0 || settings.epochs > 100_000 {
        return Err(NetError::Invalid(format!(
            "--epochs {}: 1 to 100000 (a model needs trained weights; 100000 epochs of the smallest dataset take weeks here)",
            settings.epochs
        )));
    }
    if settings.batch_size == 0 {
        return Err(NetError::Invalid("--batch-size 0: at least one sample a batch".into()));
    }
    settings.network().check_size().map_err(|e| NetError::Invalid(e.0))?;
    Ok(())
}

/// The model `--init-from` names, if it has this network on this grid.
fn check_init_from(
    init: &Path,
    cfg: &UNetConfig,
    shape: [usize; 3],
    manifest: Option<&umesh_core::dataset::Manifest>,
    dataset: &Path,
) -> Result<ModelInfo, NetError> {
    let from = ModelInfo::read(init)?;
    if from.config != *cfg || from.padded_shape != shape {
        return Err(NetError::Invalid(format!(
            "--init-from {}: its network {:?} on grid {:?} differs from this one's {:?} on {:?}",
            init.display(),
            from.config,
            from.padded_shape,
            cfg,
            shape
        )));
    }
    if let (Some(h), Some(m)) = (&from.grid_hash, manifest)
        && *h != m.grid_hash
    {
        return Err(NetError::Invalid(format!(
            "--init-from {}: it was trained on another grid than {}",
            init.display(),
            dataset.display()
        )));
    }
    Ok(from)
}

/// The model `--prior` names, if it has this network and input (its grid may be another organ's).
pub fn check_prior(prior: &Path, settings: &TrainSettings) -> Result<ModelInfo, NetError> {
    if settings.init_from.is_some() {
        return Err(NetError::Invalid(format!(
            "--prior {}: a training starts from one model, --init-from or --prior, not both",
            prior.display()
        )));
    }
    let from = ModelInfo::read(prior)?;
    if !from.fits_as_prior(settings) {
        return Err(NetError::Invalid(format!(
            "--prior {}: its network {:?} on input {:?} differs from this one's {:?} on {:?}",
            prior.display(),
            from.config,
            from.settings.observation,
            settings.network(),
            settings.observation
        )));
    }
    Ok(from)
}

/// Resuming into a model trained on another dataset or network would mix both.
fn check_resume(
    out: &Path,
    manifest: Option<&umesh_core::dataset::Manifest>,
    cfg: &UNetConfig,
    dataset: &Path,
) -> Result<(), NetError> {
    // Resuming into a model trained on another dataset would mix both.
    if let Ok(old) = ModelInfo::read(out) {
        let same = manifest.is_some_and(|m| {
            old.grid_hash.as_deref() == Some(m.grid_hash.as_str()) && old.dataset_config.as_ref() == Some(&m.config)
        });
        if !same || old.config != *cfg {
            return Err(NetError::Invalid(format!(
                "{}: --resume: the model there was trained on another dataset or network configuration than {} (start in an empty folder)",
                out.display(),
                dataset.display()
            )));
        }
    }
    Ok(())
}

/// One epoch's line of `metrics.jsonl`.
fn append_metrics(path: &Path, m: &EpochMetrics) -> Result<(), NetError> {
    use std::io::Write;
    let mut line = serde_json::to_string(m).map_err(|e| NetError::Invalid(format!("{}: {e}", path.display())))?;
    line.push('\n');
    std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .and_then(|mut f| f.write_all(line.as_bytes()))
        .map_err(|e| NetError::Io { path: path.to_path_buf(), source: e })
}

#[cfg(test)]
mod tests {
    use super::EpochPlan;
    use crate::LrSchedule;

    #[test]
    fn the_cosine_rate_starts_at_the_base_and_ends_at_five_percent_of_it_on_the_last_planned_epoch() {
        let s = LrSchedule::Cosine;
        assert!((s.rate(1e-3, 1, 20) - 1e-3).abs() < 1e-15);
        assert!((s.rate(1e-3, 20, 20) - 5e-5).abs() < 1e-15);
        // Halfway: the mean of both ends (tolerance 1e-15).
        assert!((s.rate(1e-3, 11, 21) - 0.5 * (1e-3 + 5e-5)).abs() < 1e-15);
        // Past the plan (a budget that shrank the plan after the rate was set): the floor.
        assert!((s.rate(1e-3, 30, 20) - 5e-5).abs() < 1e-15);
        assert_eq!(LrSchedule::Constant.rate(1e-3, 20, 20), 1e-3);
    }

    #[test]
    fn a_plan_stops_on_a_plateau_or_before_an_epoch_the_budget_cannot_hold() {
        let mut p = EpochPlan { asked: 20, patience: 3, budget_s: 0.0, spent_s: 0.0, run_epochs: 0 };
        assert_eq!(p.last_epoch(0), 20);
        assert!(p.stop(5, 3).is_none(), "2 epochs without improvement, patience 3");
        assert!(p.stop(6, 3).unwrap().contains("plateau"));
        assert!(p.stop(20, 3).is_none(), "the last epoch asked is not an early stop");
        // 100 s a mean epoch, 350 s budget: after 3 epochs (300 s), a 4th would end at 400 s.
        p = EpochPlan { asked: 20, patience: 0, budget_s: 350.0, spent_s: 300.0, run_epochs: 3 };
        assert_eq!(p.last_epoch(3), 3);
        assert!(p.stop(3, 3).unwrap().contains("time budget"));
        p.spent_s = 200.0;
        p.run_epochs = 2;
        assert_eq!(p.last_epoch(2), 3);
        assert!(p.stop(2, 2).is_none());
    }
}
