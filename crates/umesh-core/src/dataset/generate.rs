//! The generation job: shards scheduled over the workers, resumable, each written whole.

use super::calibrate::{Rejection, SampleResult, generate_sample};
use super::check::{PreflightCheck, preflight_with};
use super::config::{DatasetConfig, FORMAT, FORMAT_VERSION, fnv_hex, recorded_family, recorded_material};
use super::context::DatasetContext;
use super::error::{DatasetError, invalid};
use super::preflight::Preflight;
use super::store::{Manifest, SampleRecord, ShardRecord, encode_shard, read_shard_records, shard_file_name};
use crate::fem::solver::FeSolver;
use crate::progress::{Cancel, Progress};
use crate::segmentation::Segmentation;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::Instant;

/// Which shard files a run computes: all, or those with `j % count == k`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ShardSelection {
    pub k: usize,
    pub count: usize,
}

impl ShardSelection {
    pub fn all() -> Self {
        Self { k: 0, count: 1 }
    }
    pub fn parse(s: &str) -> Option<Self> {
        let (a, b) = s.split_once('/')?;
        let (k, count) = (a.trim().parse().ok()?, b.trim().parse().ok()?);
        (count > 0 && k < count).then_some(Self { k, count })
    }
    pub fn includes(&self, shard: usize) -> bool {
        shard % self.count == self.k
    }
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct GenerateReport {
    pub out: PathBuf,
    pub samples_total: usize,
    pub samples_computed: usize,
    pub samples_reused: usize,
    pub accepted: usize,
    pub rejected: BTreeMap<String, usize>,
    pub shards_written: usize,
    pub seconds: f64,
    pub samples_per_minute: f64,
    pub complete: bool,
    /// The pre-flight check, when one ran (a fresh job with more samples than the check).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub preflight: Option<Preflight>,
}

pub(super) fn base_manifest(
    seg: &Segmentation,
    config: &DatasetConfig,
    ctx: &DatasetContext,
) -> Result<Manifest, DatasetError> {
    Ok(Manifest {
        format: FORMAT.into(),
        format_version: FORMAT_VERSION,
        program_version: env!("CARGO_PKG_VERSION").into(),
        config: config.clone(),
        config_hash: config.hash()?,
        grid_hash: ctx.grid_hash(),
        segmentation: seg.source.display().to_string(),
        segmentation_hash: ctx.segmentation_hash.clone(),
        padded_shape: ctx.grid.padded_shape(),
        nodes: ctx.grid.node_count(),
        visible_nodes: ctx.visible_nodes.len(),
        shards: Vec::new(),
        samples: Vec::new(),
        complete: false,
    })
}

pub(super) fn finalize(m: &mut Manifest) {
    m.shards.sort_by_key(|s| s.first);
    m.shards.dedup_by_key(|s| s.first);
    m.samples.sort_by_key(|s| s.index);
    m.samples.dedup_by_key(|s| s.index);
    m.complete = m.shards.len() == m.config.shard_count();
}

/// Generate (or resume) a dataset in `out`.
pub fn run_generate(
    seg: &Segmentation,
    out: &Path,
    config: &DatasetConfig,
    selection: ShardSelection,
    progress: &Progress,
    cancel: &Cancel,
) -> Result<GenerateReport, DatasetError> {
    run_generate_checked(seg, out, config, selection, None, progress, cancel)
}

/// `run_generate` with a pre-flight check: a fresh job with more samples than the check first
/// solves a few of its samples in parallel and, when their acceptance is below the check's
/// threshold, stops with `DatasetError::Refused` before anything is written (unless forced).
/// A new dataset is written into an empty folder: files of anything else there (a model, a
/// recording, a user's documents) would be mixed with the shards, or taken for a dataset by a
/// later run. Shards left without a manifest get their own message further on.
fn check_new_dataset_folder(out: &Path) -> Result<(), DatasetError> {
    let Ok(entries) = std::fs::read_dir(out) else { return Ok(()) };
    let foreign: Vec<String> = entries
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        // The app's job record is written beside its output before the job runs.
        .filter(|n| {
            !(n.starts_with("shard_")
                || n == "grid.npz"
                || n == crate::JOB_FILE
                || (n.starts_with('.') && n.ends_with(".tmp")))
        })
        .collect();
    if foreign.is_empty() {
        return Ok(());
    }
    let shown: Vec<&str> = foreign.iter().take(4).map(String::as_str).collect();
    Err(invalid(
        out,
        format!(
            "holds {} ({} entries) but no dataset (no manifest.json); a dataset is written into an empty folder: choose another --out",
            shown.join(", "),
            foreign.len()
        ),
    ))
}

pub fn run_generate_checked(
    seg: &Segmentation,
    out: &Path,
    config: &DatasetConfig,
    selection: ShardSelection,
    preflight: Option<&PreflightCheck>,
    progress: &Progress,
    cancel: &Cancel,
) -> Result<GenerateReport, DatasetError> {
    let start = Instant::now();
    check_counts(out, config)?;
    let fresh = !out.join("manifest.json").exists();
    if fresh {
        check_new_dataset_folder(out)?;
    }
    let ctx = DatasetContext::prepare(seg, config, cancel)?;
    // Each reference solve single-threaded like the samples, so every machine finds the same factor.
    if fresh {
        progress.report(0, config.samples as u64, "calibrating the load");
    }
    let mut softening: Option<f64> = None;
    let mut checked = None;
    if let Some(check) = preflight
        && fresh
        && config.samples > check.settings.samples
    {
        let d = ctx.reference_softening_mm(config, cancel)?;
        softening = Some(d);
        checked = Some(check.judge(preflight_with(&ctx, config, &check.settings, d, start, progress, cancel)?)?);
    }
    std::fs::create_dir_all(out).map_err(|source| DatasetError::Io { path: out.into(), source })?;
    remove_temporaries(out);
    let mut manifest = base_manifest(seg, config, &ctx)?;
    let recorded = resume_from(out, config, &mut manifest)?;
    let grid_path = out.join("grid.npz");
    crate::write_atomic(&grid_path, &ctx.grid_npz)
        .map_err(|source| DatasetError::Io { path: grid_path.clone(), source })?;

    let (todo, reused) = adopt_shards(out, config, &selection, &ctx, &mut manifest, &recorded);
    finalize(&mut manifest);
    manifest.write(out)?;

    let total: usize = todo.iter().map(|&s| config.shard_range(s).len()).sum();
    // Counted over the whole dataset, the samples kept from an earlier run included: a resumed
    // stage's "samples N of M" and its share of a job's progress then agree with a fresh one's
    // (counting only this run's, a resumed prepare's progress jumped at the stage's end).
    let kept = config.samples.saturating_sub(total) as u64;
    if !fresh {
        progress.report(kept, config.samples as u64, "calibrating the load");
    }

    let queue: Vec<usize> = todo.iter().flat_map(|&s| config.shard_range(s)).collect();
    let next = std::sync::atomic::AtomicUsize::new(0);
    let done = std::sync::atomic::AtomicUsize::new(0);
    let pending: Mutex<BTreeMap<usize, Vec<SampleResult>>> = Mutex::new(BTreeMap::new());
    let manifest = Mutex::new(manifest);
    let first_error: Mutex<Option<DatasetError>> = Mutex::new(None);
    let shards_written = std::sync::atomic::AtomicUsize::new(0);
    // Parallel over samples; each solve single-threaded (`sequential()`) so results do not depend on scheduling.
    let softening = match softening {
        Some(d) => d,
        None if todo.is_empty() => f64::INFINITY,
        None => ctx.reference_softening_mm(config, cancel)?,
    };
    let threads = rayon::current_num_threads().max(1).min(queue.len().max(1));
    std::thread::scope(|scope| {
        for _ in 0..threads {
            scope.spawn(|| {
                let mut solver = match FeSolver::new(&ctx.grid, config.material, &ctx.fixed, config.solver.sequential())
                {
                    Ok(s) => s,
                    Err(e) => {
                        record_error(&first_error, invalid(out, e.to_string()));
                        cancel.cancel();
                        return;
                    }
                };
                loop {
                    let q = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    if q >= queue.len() || cancel.is_cancelled() {
                        break;
                    }
                    let index = queue[q];
                    let result = match generate_sample(&ctx, &mut solver, config, index, softening, cancel) {
                        Ok(r) => r,
                        Err(e) => {
                            if !matches!(e, DatasetError::Cancelled(_)) {
                                record_error(&first_error, e);
                            }
                            cancel.cancel();
                            break;
                        }
                    };
                    let shard = index / config.shard_size;
                    let complete = {
                        let Ok(mut p) = pending.lock() else { break };
                        let v = p.entry(shard).or_default();
                        v.push(result);
                        if v.len() == config.shard_range(shard).len() { p.remove(&shard) } else { None }
                    };
                    if let Some(mut results) = complete {
                        results.sort_by_key(|r| r.index);
                        if let Err(e) = write_shard(out, &ctx, config, shard, &results, &manifest) {
                            record_error(&first_error, e);
                            cancel.cancel();
                            break;
                        }
                        shards_written.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    }
                    let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
                    progress.report(kept + d as u64, config.samples as u64, "samples");
                }
            });
        }
    });
    if let Ok(Some(e)) = first_error.into_inner() {
        return Err(e);
    }
    cancel.check()?;
    let manifest = manifest.into_inner().map_err(|_| invalid(out, "a worker panicked"))?;
    let computed = done.into_inner();
    let shards_written = shards_written.into_inner();
    Ok(generate_report(out, config, &manifest, start, computed, reused, shards_written, checked))
}

/// The sample and shard counts a job can afford.
fn check_counts(out: &Path, config: &DatasetConfig) -> Result<(), DatasetError> {
    if !(1..=super::MAX_SAMPLES).contains(&config.samples) || config.shard_size == 0 {
        return Err(invalid(
            out,
            format!(
                "{} samples in shards of {}: between 1 and {} samples, shards of at least 1",
                config.samples,
                config.shard_size,
                super::MAX_SAMPLES
            ),
        ));
    }
    Ok(())
}

/// Temporary files of an interrupted run are never data.
fn remove_temporaries(out: &Path) {
    // Temporary files of an interrupted run are never data.
    if let Ok(entries) = std::fs::read_dir(out) {
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            if name.starts_with('.') && name.ends_with(".tmp") {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
}

/// What a folder's earlier run left: its samples' records moved into `manifest` and each shard
/// file's recorded hash. Refused when the folder holds another dataset, or shards without a
/// manifest.
fn resume_from(
    out: &Path,
    config: &DatasetConfig,
    manifest: &mut Manifest,
) -> Result<BTreeMap<String, String>, DatasetError> {
    // Shard file -> content hash, as the manifest on disk recorded them when they were written.
    let mut recorded: BTreeMap<String, String> = BTreeMap::new();
    if out.join("manifest.json").exists() {
        let old = Manifest::read(out)?;
        if old.config_hash != manifest.config_hash
            || old.grid_hash != manifest.grid_hash
            || old.segmentation_hash != manifest.segmentation_hash
        {
            return Err(invalid(
                out,
                "holds a dataset made with another configuration or segmentation; choose an empty folder",
            ));
        }
        // Keep what the old manifest knows (timings, reasons) for shards still on disk.
        manifest.samples = old.samples;
        recorded = old.shards.into_iter().map(|s| (s.file, s.hash)).collect();
    } else if (0..config.shard_count()).any(|s| out.join(shard_file_name(s)).exists())
        || std::fs::read_dir(out)
            .map(|d| d.flatten().any(|e| e.file_name().to_string_lossy().starts_with("shard_")))
            .unwrap_or(false)
    {
        // The manifest is written before the first shard: shards without one are left over from
        // another run (or its manifest was deleted), and their settings cannot be checked.
        return Err(invalid(
            out,
            "holds shard files but no manifest.json, so what made them cannot be checked; choose an empty folder (or restore its manifest.json)",
        ));
    }
    Ok(recorded)
}

/// Shards already on disk and sound are adopted into `manifest`: the selected shards left to
/// compute, and how many samples of the selection were adopted.
fn adopt_shards(
    out: &Path,
    config: &DatasetConfig,
    selection: &ShardSelection,
    ctx: &DatasetContext,
    manifest: &mut Manifest,
    recorded: &BTreeMap<String, String>,
) -> (Vec<usize>, usize) {
    // Shards already on disk and sound are adopted; the rest are computed.
    let padded = ctx.grid.padded_shape();
    let mut todo: Vec<usize> = Vec::new();
    let known: BTreeMap<usize, SampleRecord> = manifest.samples.drain(..).map(|s| (s.index, s)).collect();
    let mut reused = 0;
    for shard in 0..config.shard_count() {
        let path = out.join(shard_file_name(shard));
        // A shard is adopted only when its bytes are the ones this dataset's manifest recorded:
        // a file copied in from another dataset (another seed, same grid) is recomputed.
        let bytes = if path.exists() { std::fs::read(&path).ok() } else { None };
        if let Some(bytes) = bytes
            && recorded.get(&shard_file_name(shard)) == Some(&fnv_hex(&bytes))
            && let Ok((records, accepted)) = read_shard_records(&path, config, shard, padded)
        {
            let range = config.shard_range(shard);
            manifest.shards.push(ShardRecord {
                file: shard_file_name(shard),
                first: range.start,
                count: range.len(),
                accepted,
                hash: fnv_hex(&bytes),
            });
            for r in records {
                let kept = known.get(&r.index).filter(|k| k.shard == r.shard).cloned();
                manifest.samples.push(kept.unwrap_or(r));
            }
            if selection.includes(shard) {
                reused += range.len();
            }
            continue;
        }
        if selection.includes(shard) {
            todo.push(shard);
        }
    }
    (todo, reused)
}

/// The job's figures once its samples are in `manifest`.
#[allow(clippy::too_many_arguments)]
fn generate_report(
    out: &Path,
    config: &DatasetConfig,
    manifest: &Manifest,
    start: Instant,
    computed: usize,
    reused: usize,
    shards_written: usize,
    checked: Option<Preflight>,
) -> GenerateReport {
    let secs = start.elapsed().as_secs_f64();
    let mut rejected = BTreeMap::new();
    for s in manifest.samples.iter().filter(|s| !s.accepted) {
        *rejected.entry(format!("{:?}", s.rejection.unwrap_or(Rejection::Failed)).to_lowercase()).or_insert(0) += 1;
    }
    GenerateReport {
        out: out.into(),
        samples_total: config.samples,
        samples_computed: computed,
        samples_reused: reused,
        accepted: manifest.accepted().count(),
        rejected,
        shards_written,
        seconds: secs,
        samples_per_minute: if secs > 0.0 { computed as f64 * 60.0 / secs } else { 0.0 },
        complete: manifest.complete,
        preflight: checked,
    }
}

pub(super) fn record_error(slot: &Mutex<Option<DatasetError>>, e: DatasetError) {
    if let Ok(mut g) = slot.lock()
        && g.is_none()
    {
        *g = Some(e);
    }
}

pub(super) fn write_shard(
    out: &Path,
    ctx: &DatasetContext,
    config: &DatasetConfig,
    shard: usize,
    results: &[SampleResult],
    manifest: &Mutex<Manifest>,
) -> Result<(), DatasetError> {
    let file = shard_file_name(shard);
    let path = out.join(&file);
    let bytes = encode_shard(ctx, config, results).map_err(|source| DatasetError::Io { path: path.clone(), source })?;
    crate::write_atomic(&path, &bytes).map_err(|source| DatasetError::Io { path: path.clone(), source })?;
    let mut m = manifest.lock().map_err(|_| invalid(out, "manifest lock poisoned"))?;
    let range = config.shard_range(shard);
    m.shards.push(ShardRecord {
        file: file.clone(),
        first: range.start,
        count: range.len(),
        accepted: results.iter().filter(|r| r.rejection.is_none()).count(),
        hash: fnv_hex(&bytes),
    });
    for r in results {
        let (max, mean) = r.max_mean(ctx, config);
        m.samples.push(SampleRecord {
            index: r.index,
            accepted: r.rejection.is_none(),
            rejection: r.rejection.as_ref().map(|x| x.0),
            reason: r.rejection.as_ref().map(|x| x.1.clone()),
            max_displacement_mm: max,
            mean_displacement_mm: mean,
            target_displacement_mm: Some(r.target_mm),
            drawn_target_mm: r.drawn_target_mm,
            family: recorded_family(config, r.index),
            material: recorded_material(config, r.index),
            newton_iterations: r.newton_iterations,
            solve_ms: Some(r.solve_ms),
            shard: file.clone(),
            flagged: false,
        });
    }
    finalize(&mut m);
    m.write(out)
}
