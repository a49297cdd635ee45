//! `umesh prepare`: from a segmentation to a trained, checked model in a patient folder
//! (grid, dataset, training, evaluation, registration check, report), resumable.

use super::grid::GridArgs;
use super::input::{InputArgs, LoadInput};
use anyhow::{Context, Result};
use std::path::PathBuf;
use umesh_net::UNetConfig;
use umesh_workflow::options::DatasetOptions;
use umesh_workflow::patient::{PrepareSettings, run_prepare};

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(flatten)]
    pub input: InputArgs,
    #[command(flatten)]
    pub grid: GridArgs,
    #[command(flatten)]
    pub config: DatasetOptions,
    /// Training samples (the paper: 1000).
    #[arg(long, default_value_t = 1000)]
    pub samples: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[arg(long, default_value_t = 50)]
    pub shard_size: usize,
    /// Training epochs (at most: see --time-budget-min).
    #[arg(long, default_value_t = 20)]
    pub epochs: usize,
    /// The whole job's time budget in minutes (0: none): training stops before an epoch that
    /// would leave too little of it for the evaluation and the check; the best epoch is the model.
    #[arg(long, default_value_t = 60.0)]
    pub time_budget_min: f64,
    /// The most grid nodes the job trains in its hour (0: keep --cell-size-mm): a larger
    /// organ's cells grow by whole millimetres until its grid fits, and the report says so.
    #[arg(long, default_value_t = umesh_workflow::patient::MAX_GRID_NODES)]
    pub max_grid_nodes: usize,
    /// The most triangles of the organ's surface, which registration judges and draws every
    /// frame (0: keep the step): a larger surface is marched at a coarser step, said in the report.
    #[arg(long, default_value_t = umesh_workflow::patient::MAX_SURFACE_TRIANGLES)]
    pub max_surface_triangles: usize,
    /// Where the network's training starts: "bundled" (the bundled phantom model's weights,
    /// when its network and input are this job's), "none" (random weights) or a model folder of
    /// another organ.
    #[arg(long, default_value = "bundled")]
    pub prior: String,
    #[command(flatten)]
    pub schedule: super::train::ScheduleArgs,
    /// Network size: "cpu" (3 steps, 8 channels) or "paper" (128 channels).
    #[arg(long, default_value = "cpu")]
    pub preset: String,
    /// Network input: "corner" or "nearest" (the simulated camera views, encoded) or "exact"
    /// (the visible nodes' displacement), as `umesh train --input`.
    #[arg(long = "input", default_value = "corner")]
    pub network_input: String,
    /// Frames of the synthetic registration-check recording.
    #[arg(long, default_value_t = 20)]
    pub check_frames: usize,
    /// Load of the check recording, relative to the dataset's target displacement (lowered to
    /// what the dataset reached, and again when it does not converge).
    #[arg(long, default_value_t = umesh_core::synth::SynthSettings::default().load_scale)]
    pub check_load_scale: f64,
    /// The scan the segmentation was made from (NIfTI): checked first, copied into the
    /// folder as `ct.nii.gz` when the job ends, shown under the model by the app.
    #[arg(long, value_name = "FILE")]
    pub ct: Option<PathBuf>,
    #[command(flatten)]
    pub preflight: super::dataset::PreflightArgs,
    /// The patient folder (created; an interrupted job run again continues there).
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: Args) -> Result<()> {
    let seg = a.input.load()?;
    if let Some(ct) = &a.ct {
        umesh_core::slices::read_scan(ct, seg.organ_mask().world_bounds()).context("--ct")?;
        // A finished patient keeps its scan: another one is refused, not copied over it.
        let stored = umesh_workflow::patient::ct_path(&a.out);
        if stored.is_file() {
            let same = std::fs::read(&stored).with_context(|| format!("{}", stored.display()))?
                == std::fs::read(ct).with_context(|| format!("--ct {}", ct.display()))?;
            anyhow::ensure!(
                same,
                "{}: the patient already holds another scan than --ct {}; choose an empty folder",
                stored.display(),
                ct.display()
            );
        }
    }
    let (dataset, fixed) = a.config.config(&seg, a.grid.settings(), a.samples, a.seed, a.shard_size)?;
    let mut settings = PrepareSettings::paper(dataset, fixed.description.clone());
    settings.train.epochs = a.epochs;
    settings.train.model = match a.preset.as_str() {
        "cpu" => UNetConfig::cpu(),
        "paper" => UNetConfig::paper(),
        p => anyhow::bail!("--preset {p:?}: cpu or paper"),
    };
    settings.train.observation = super::train::parse_input(&a.network_input)?;
    a.schedule.apply(&mut settings.train)?;
    settings.time_budget_s = super::train::budget_seconds(a.time_budget_min)?;
    settings.max_grid_nodes = a.max_grid_nodes;
    settings.max_surface_triangles = a.max_surface_triangles;
    settings.prior = umesh_workflow::patient::Prior::parse(&a.prior);
    anyhow::ensure!(
        a.check_frames >= 2 && a.check_frames <= 1000,
        "--check-frames {}: between 2 and 1000",
        a.check_frames
    );
    settings.check.frames = a.check_frames;
    anyhow::ensure!(
        a.check_load_scale.is_finite() && a.check_load_scale > 0.0 && a.check_load_scale <= 100.0,
        "--check-load-scale {}: above 0 and at most 100",
        a.check_load_scale
    );
    settings.check.load_scale = a.check_load_scale;
    if !a.json {
        eprintln!("fixed region: {}", fixed.description);
    }
    let (pb, progress) = super::output::progress_bar("preparing");
    pb.set_style(
        indicatif::ProgressStyle::with_template("{spinner} [{bar:30}] {percent:>3}% ({elapsed}, eta {eta}) {msg}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    let check = umesh_core::dataset::PreflightCheck {
        settings: a.preflight.settings()?,
        force: a.preflight.force,
        report: &|p: &umesh_core::dataset::Preflight| {
            pb.suspend(|| super::dataset::print_preflight(p, a.preflight.force));
        },
    };
    let r = run_prepare(&seg, &a.input.files()?, &a.out, &settings, Some(&check), &progress, &super::output::cancel());
    pb.finish_and_clear();
    let r = r.with_context(|| format!("preparing the patient {}", a.out.display()))?;
    if let Some(ct) = &a.ct {
        let dst = umesh_workflow::patient::ct_path(&a.out);
        let bytes = std::fs::read(ct).with_context(|| format!("--ct {}", ct.display()))?;
        umesh_core::write_atomic(&dst, &bytes).with_context(|| format!("{}", dst.display()))?;
    }
    if let Some(w) = &r.check.warning {
        eprintln!("warning: {w} (the model is trained and usable; the check's figures are missing)");
    }
    if a.json {
        let value = report_json(&r);
        super::output::print_json(&super::bench_page::stamped("prepare", value));
        return Ok(());
    }
    println!("patient folder {} ({:.0} s)", r.out.display(), r.seconds);
    println!("grid: {}", r.grid);
    println!("surface: {}", r.surface);
    println!("training started from {}", r.prior);
    for (s, t, done) in &r.stages {
        println!("  {:20} {:>8.1} s{}", s.name(), t, if *done { "" } else { "  (not done)" });
    }
    let d = &r.dataset;
    println!(
        "dataset: {}/{} accepted ({:.1} %), rejected {:?}; mean displacement {} (target {} mm)",
        d.accepted,
        d.samples,
        100.0 * d.accepted as f64 / d.samples.max(1) as f64,
        d.rejected,
        d.mean_displacement_mm
            .as_ref()
            .map(|m| format!("{:.2} mm mean, {:.2}-{:.2} p5-p95", m.mean, m.p5, m.p95))
            .unwrap_or_default(),
        d.target_displacement_mm
    );
    if let Some(why) = &r.training_stopped_early {
        println!("training {why}");
    }
    println!(
        "validation TRE {:.2} +/- {:.2} mm (max {:.2}) at {:.2} mm mean marker displacement",
        r.eval.tre_mean_mm, r.eval.tre_std_mm, r.eval.tre_max_mm, r.eval.marker_displacement_mean_mm
    );
    let c = &r.check;
    println!(
        "registration check: {} frames, {:.1} ms median; last frame TRE {} mm (rigid only {} mm) at {} mm of marker motion",
        c.summary.frames,
        c.summary.frame_ms_median,
        c.last_frame_tre_mm.map(|v| format!("{v:.2}")).unwrap_or("-".into()),
        c.last_frame_tre_rigid_mm.map(|v| format!("{v:.2}")).unwrap_or("-".into()),
        c.last_frame_marker_displacement_mm.map(|v| format!("{v:.2}")).unwrap_or("-".into())
    );
    if let Some(ch) = &c.correction {
        println!("registration check: {}", ch.describe());
    }
    println!("verdict: {}", r.verdict.line());
    for note in &r.verdict.notes {
        println!("  note: {note}");
    }
    println!("report: {}", r.out.join("report.html").display());
    Ok(())
}

/// The job's figures as `--json` prints them.
fn report_json(r: &umesh_workflow::patient::PrepareReport) -> serde_json::Value {
    serde_json::json!({
        "out": r.out, "seconds": r.seconds, "grid": r.grid, "surface": r.surface, "prior": r.prior,
        // The whole job's time over every run of it (a rerun on a finished folder takes seconds).
        "job_seconds": r.stages.iter().map(|(_, t, _)| t).sum::<f64>(),
        "stages": r.stages.iter().map(|(s, t, d)| serde_json::json!({"stage": s, "seconds": t, "done": d})).collect::<Vec<_>>(),
        "samples": r.dataset.samples, "accepted": r.dataset.accepted, "rejected": r.dataset.rejected,
        "target_displacement_mm": r.dataset.target_displacement_mm,
        "mean_displacement_mm": r.dataset.mean_displacement_mm, "achieved_over_target": r.dataset.achieved_over_target,
        "dataset_samples_per_minute": r.dataset_samples_per_minute, "training_stopped_early": r.training_stopped_early,
        "val_tre_mean_mm": r.eval.tre_mean_mm, "val_tre_max_mm": r.eval.tre_max_mm,
        "val_marker_displacement_mean_mm": r.eval.marker_displacement_mean_mm,
        "check": r.check, "check_recording": r.check_recording,
        "verdict": { "ready": r.verdict.ready, "problems": r.verdict.problems, "notes": r.verdict.notes },
    })
}
