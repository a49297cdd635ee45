//! `umesh register`: RGB-D frames -> rigid ICP -> surface displacement -> network (and,
//! when asked, the co-rotational FE) -> deformed internal structures overlaid on the frames.

use super::input::{InputArgs, ModelOnOrgan, model_on_organ};
use anyhow::{Context, Result, bail};
use nalgebra::Matrix4;
use std::path::{Path, PathBuf};
use std::time::Duration;
use umesh_core::register::RegistrationContext;
use umesh_core::register::correction::{CorrectionChoice, CorrectionForm, CorrectionSettings};
use umesh_core::register::pipeline::{
    FeDisplacementModel, GroundTruth, PosePolicy, RegisterReport, RegisterSettings, Registrar, choose_pose,
    run_registrar,
};
use umesh_core::rgbd::recording::{Recording, read_trajectory_log};
use umesh_core::rgbd::stream::{FrameSource, Peeked, RecordingSource, TcpSource};

#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    #[command(flatten)]
    pub input: InputArgs,
    /// Model folder (default: the bundled phantom model).
    #[arg(long, conflicts_with = "patient")]
    pub model: Option<PathBuf>,
    /// A patient folder from `umesh prepare`: its segmentation and model.
    #[arg(long, conflicts_with = "seg")]
    pub patient: Option<PathBuf>,
    /// Recorded RGB-D folder (color/, depth/, intrinsics JSON; docs/REGISTRATION.md), or a
    /// RealSense recording (.db3, .bag), imported first as `umesh rgbd import` does.
    #[arg(long, conflicts_with = "source")]
    pub recording: Option<PathBuf>,
    /// Live source: a TCP camera bridge "host:port" speaking umesh's frame protocol.
    #[arg(long)]
    pub source: Option<String>,
    /// Intrinsics JSON (default: found in the recording).
    #[arg(long)]
    pub intrinsics: Option<PathBuf>,
    /// Initial camera pose (world_from_camera) as an Open3D .log file (default: the
    /// recording's trajectory.log; a live stream whose frames carry their pose needs none with
    /// --pose tracked).
    #[arg(long)]
    pub initial_pose: Option<PathBuf>,
    /// True marker positions (ground_truth.json of a synthetic recording; default: the
    /// recording folder's), for the TRE of a recording that does not carry them (a RealSense
    /// file made from a synthetic recording, say).
    #[arg(long, conflicts_with = "source")]
    pub ground_truth: Option<PathBuf>,
    /// Overlay PNGs and report.json go here.
    #[arg(long)]
    pub out: PathBuf,
    /// Also register the same organ points with the co-rotational FE fit alone (no network).
    #[arg(long)]
    pub compare_fe: bool,
    /// With --compare-fe: run each frame's FE fit until an update moves the nodes by at most
    /// 0.01 mm RMS (at most 60 updates; seconds to minutes a frame) instead of the fixed
    /// per-frame work.
    #[arg(long)]
    pub fe_converged: bool,
    /// Physics correction after each network prediction: FE fit updates per frame (0: off;
    /// default: the form's, 2 subspace, 2 tracking).
    #[arg(long)]
    pub correction_updates: Option<usize>,
    /// Conjugate-gradient iterations per correction update at most (default: the form's, 6
    /// subspace where they are not used, 10 tracking). Updates x iterations at most 200 a
    /// frame (about 0.6 s on the phantom).
    #[arg(long)]
    pub correction_cg: Option<usize>,
    /// Solve each correction update in a basis of the organ's responses to smooth loads on this
    /// many patches of the seen surface (3 vectors each, built at the first frame) instead of
    /// by conjugate gradients (0; default 64; at most 128: the basis is built before the first
    /// frame, 256 patches took 35 s on the phantom). The tracking form solves by CG.
    #[arg(long)]
    pub correction_subspace: Option<usize>,
    /// The correction's form: auto (the most accurate form within --frame-budget-ms on the
    /// model's registration check, `correction.json`, see `umesh choose-correction`; subspace
    /// when it has none), subspace (each prediction corrected in a basis of smooth surface
    /// loads), coarse-tracking (the FE fit carried from frame to frame on the organ's cells
    /// twice as large, moved by the network's prediction, one update a frame: about the
    /// subspace form's frame), tracking (carried from frame to frame, its elastic energy from
    /// rest, by conjugate gradients over the organ's own grid, 2 updates of 10 iterations:
    /// 5-10 times the frame) or fast-tracking (the tracking form in a basis of free-body
    /// surface-load responses; not yet as accurate as the others on the CT patient's
    /// benchmark; docs/REGISTRATION.md).
    #[arg(long, default_value = "auto")]
    pub correction_form: String,
    /// With --correction-form auto: the frame time the form is chosen within (ms), from the
    /// frame each form took on the model's check; 0: the most accurate whatever its time.
    #[arg(long, default_value_t = umesh_core::register::correction::DEFAULT_FRAME_BUDGET_MS)]
    pub frame_budget_ms: f64,
    /// On a frame whose prediction the confidence rule doubts (the observed points too far from
    /// it, or it moves beyond the training deformations), correct it as the FE fit instead: its
    /// elastic energy from rest, carried over the doubted frames, this many updates (0: as any
    /// other frame; default 4). Needs a model with a confidence reference and the correction on.
    #[arg(long)]
    pub doubted_updates: Option<usize>,
    /// Updates of a doubted frame that follows a doubted frame (its fit starts from the one
    /// carried): 1 to --doubted-updates (default 2). The tracking forms use --doubted-updates.
    #[arg(long)]
    pub doubted_carried_updates: Option<usize>,
    /// Such a frame stops taking updates once one moved the organ's coarse nodes by at most
    /// this (mm RMS; default 2; 0: always --doubted-carried-updates): an organ moving slowly
    /// gets one update a frame, one moving fast the second it needs.
    #[arg(long)]
    pub doubted_carried_stop_mm: Option<f64>,
    /// Conjugate-gradient iterations per update of a doubted frame at most (default 10).
    #[arg(long)]
    pub doubted_cg: Option<usize>,
    /// A doubted frame's fit runs on the organ's cells this many times as large (1: its own
    /// grid; at most 4). The tracking forms fit doubted frames on the organ's own grid.
    #[arg(long)]
    pub doubted_coarsening: Option<usize>,
    /// Network evaluations per frame.
    #[arg(long, default_value_t = RegisterSettings::default().iterations)]
    pub iterations: usize,
    /// Where the camera pose comes from: auto (tracked when the recording or stream carries a
    /// tracked pose for every frame, else icp-first), tracked (keep the recording's or
    /// stream's pose, refined on the first frame by a trimmed ICP within --pose-bound-mm),
    /// icp-first (full ICP on the first frame) or icp-every-frame.
    #[arg(long, default_value = "auto")]
    pub pose: String,
    /// With --pose tracked: the refinement moves the cloud by at most this much (RMS, mm).
    #[arg(long, default_value_t = RegisterSettings::default().pose_bound_mm)]
    pub pose_bound_mm: f64,
    /// Frames whose organ points cover less than this share of the organ's surface (each point
    /// taken to the rest surface from up to 30 mm off it) are not registered.
    #[arg(long, default_value_t = RegisterSettings::default().min_coverage)]
    pub min_coverage: f64,
    /// Depth range of the organ when the recording has no masks (mm).
    #[arg(long, default_value_t = 100.0)]
    pub depth_min_mm: f32,
    #[arg(long, default_value_t = 3000.0)]
    pub depth_max_mm: f32,
    /// Ignore the recording's masks.
    #[arg(long)]
    pub no_mask: bool,
    /// Skip writing overlay PNGs.
    #[arg(long)]
    pub no_overlay: bool,
    #[arg(long)]
    pub json: bool,
}

/// A frame source, its initial pose, its ground truth, and whether it tracks the camera on
/// every frame (`choose_pose`).
struct Opened {
    source: Box<dyn FrameSource>,
    pose: Option<Matrix4<f64>>,
    truth: Option<GroundTruth>,
    tracked: bool,
}

fn open_source(a: &Args, recording: Option<&Path>) -> Result<Opened> {
    match (recording, &a.source) {
        (Some(dir), None) => {
            let rec = Recording::open(dir, a.intrinsics.as_deref())?;
            for w in &rec.warnings {
                eprintln!("warning: {w}");
            }
            let pose = rec.trajectory.as_ref().and_then(|t| t.first().copied());
            let gt_path = a.ground_truth.clone().unwrap_or_else(|| dir.join("ground_truth.json"));
            let truth =
                if a.ground_truth.is_some() || gt_path.is_file() { Some(GroundTruth::read(&gt_path)?) } else { None };
            let tracked = rec.tracks_every_frame();
            Ok(Opened { source: Box::new(RecordingSource::new(rec)), pose, truth, tracked })
        }
        (None, Some(addr)) => {
            // The first frame says whether the stream carries a tracked pose.
            let s = Peeked::new(Box::new(TcpSource::connect(addr, Duration::from_secs(5))?), Duration::from_secs(10));
            let tracked = s.first().is_some_and(|f| f.world_from_camera.is_some());
            Ok(Opened { source: Box::new(s), pose: None, truth: None, tracked })
        }
        _ => bail!("give --recording DIR or --source HOST:PORT"),
    }
}

/// A RealSense recording file (.db3, .bag) is imported into a folder beside --out, removed
/// when the command ends.
struct Imported(Option<PathBuf>);

impl Drop for Imported {
    fn drop(&mut self) {
        if let Some(d) = &self.0 {
            let _ = std::fs::remove_dir_all(d);
        }
    }
}

fn is_realsense_file(p: &Path) -> bool {
    p.is_file() && p.extension().is_some_and(|e| e.eq_ignore_ascii_case("db3") || e.eq_ignore_ascii_case("bag"))
}

/// The frame segmentation the options ask for.
fn segment_settings(a: &Args, s: &RegisterSettings) -> umesh_core::rgbd::segment::SegmentSettings {
    umesh_core::rgbd::segment::SegmentSettings {
        depth_min_mm: a.depth_min_mm,
        depth_max_mm: a.depth_max_mm,
        use_mask: !a.no_mask,
        ..s.segment.clone()
    }
}

/// The files that make a folder a registration's output (see `check_replaceable`).
const REGISTRATION_FILES: &[&str] = &["report.json"];

pub fn run(a: Args) -> Result<()> {
    check_before_work(&a)?;
    // The options that do not depend on the model, checked before it loads (seconds on a big
    // liver); the correction's are checked once the model's form is known.
    let early = RegisterSettings {
        iterations: a.iterations,
        pose_bound_mm: a.pose_bound_mm,
        min_coverage: a.min_coverage,
        ..Default::default()
    };
    let early = RegisterSettings { segment: segment_settings(&a, &early), ..early };
    early.validate()?;
    let requested = match a.pose.as_str() {
        "auto" => None,
        p => Some(PosePolicy::parse(p).context("--pose (or auto)")?),
    };

    let ModelOnOrgan { model_dir, seg, mut net, config, dctx } =
        model_on_organ(a.patient.as_deref(), a.model.as_deref(), &a.input)?;
    let ctx = RegistrationContext::new(dctx, &seg)?;
    // The correction's subspace before the source opens: a live stream would drop the frames
    // that arrive while it is built.
    let budget = (a.frame_budget_ms > 0.0).then_some(a.frame_budget_ms);
    let (form, form_reason) = correction_form(&a.correction_form, &model_dir, budget)?;
    let correction = correction_settings(&a, form.settings())?;
    let mut settings = RegisterSettings {
        iterations: a.iterations,
        pose_bound_mm: a.pose_bound_mm,
        min_coverage: a.min_coverage,
        overlay: !a.no_overlay,
        correction,
        ..Default::default()
    };
    settings.segment = segment_settings(&a, &settings);
    settings.validate()?;
    // The correction's FE models and subspace before the source opens: a live stream would
    // drop the frames that arrive while they are built (half a second to seconds).
    let mut registrar = Registrar::new(&ctx, settings.clone(), Matrix4::identity());
    registrar.prepare_correction()?;
    let imported = import_if_realsense(&a)?;
    let recording = imported.0.as_deref().or(a.recording.as_deref());
    let Opened { mut source, pose: rec_pose, truth, tracked } = open_source(&a, recording)?;
    let (pose_policy, pose_reason) = choose_pose(requested, tracked);
    settings.pose = pose_policy;
    registrar.settings.pose = pose_policy;
    let pose = match (&a.initial_pose, rec_pose) {
        (Some(p), _) => Some(*read_trajectory_log(p)?.first().with_context(|| format!("{}: no pose", p.display()))?),
        (None, Some(p)) => Some(p),
        // A tracked live camera: every frame brings its pose in the stream header.
        (None, None) if a.source.is_some() && pose_policy == PosePolicy::Tracked => None,
        (None, None) => bail!(
            "no initial camera pose: give --initial-pose FILE.log (Open3D trajectory format), or --pose tracked with a stream whose frames carry world_from_camera"
        ),
    };
    // Written beside --out and swapped in at the end: a failed run leaves the old folder as it was.
    let staged = umesh_core::StagedDir::new(&a.out, umesh_core::OutputKind::Registration, REGISTRATION_FILES)
        .with_context(|| format!("--out {}", a.out.display()))?;
    let dir = staged.path().to_path_buf();
    let mut report = register_with(
        &mut *source,
        registrar,
        &mut net,
        pose,
        truth.as_ref(),
        &dir.join("overlay"),
        "registering (U-Net)",
    )?;
    report.pose_reason = pose_reason;
    let fe_report = if a.compare_fe {
        let Some(recording) = recording else {
            bail!("--compare-fe needs a --recording (a live stream cannot be replayed)")
        };
        let mut src = open_source(&Args { source: None, ..a.clone() }, Some(recording))?.source;
        let mut fe = FeDisplacementModel::new(&ctx, config.material)?;
        if a.fe_converged {
            fe = fe.converged(0.01, 60);
        }
        Some(register_with(
            &mut *src,
            Registrar::new(&ctx, settings.clone(), Matrix4::identity()),
            &mut fe,
            pose,
            truth.as_ref(),
            &dir.join("overlay_fe"),
            "registering (FE)",
        )?)
    } else {
        None
    };
    let mut v = summary_json(&report);
    v["correction_form"] = serde_json::json!((correction.updates > 0).then_some(form.name()));
    v["correction_reason"] = serde_json::json!((correction.updates > 0).then_some(&form_reason));
    if let Some(fe) = &fe_report {
        v["fe"] = summary_json(fe);
    }
    let full = serde_json::json!({ "summary": v, "frames": report.frames, "log": report.log, "fe_frames": fe_report.as_ref().map(|r| &r.frames) });
    umesh_core::write_atomic(&dir.join("report.json"), serde_json::to_string_pretty(&full)?.as_bytes())
        .with_context(|| format!("writing {}", a.out.join("report.json").display()))?;
    for l in &report.log {
        eprintln!("{l}");
    }
    if report.summary.frames == 0 {
        bail!("no frame could be registered (see the log lines above); {} left as it was", a.out.display());
    }
    staged.commit().with_context(|| format!("replacing {}", a.out.display()))?;
    if a.json {
        super::output::print_json(&v);
    } else {
        print_table(&report, fe_report.as_ref(), &a.out);
    }
    Ok(())
}

/// What is refused before any work: options that do not go together, an output that is an
/// input or holds something else, a frame budget out of range.
fn check_before_work(a: &Args) -> Result<()> {
    if a.fe_converged && !a.compare_fe {
        bail!("--fe-converged applies to --compare-fe");
    }
    // Before any work: --out apart from every input (a recording, a model, a patient).
    let mut inputs = a.input.paths();
    inputs.extend(a.recording.iter().map(|p| ("--recording", p.as_path())));
    inputs.extend(a.model.iter().map(|p| ("--model", p.as_path())));
    inputs.extend(a.patient.iter().map(|p| ("--patient", p.as_path())));
    inputs.extend(a.ground_truth.iter().map(|p| ("--ground-truth", p.as_path())));
    umesh_core::check_apart(&a.out, &inputs)?;
    umesh_core::check_replaceable(&a.out, umesh_core::OutputKind::Registration, REGISTRATION_FILES)
        .with_context(|| format!("--out {}", a.out.display()))?;

    if !(a.frame_budget_ms.is_finite() && (0.0..=3.6e6).contains(&a.frame_budget_ms)) {
        bail!("--frame-budget-ms {}: between 0 (no limit) and 3600000 (an hour)", umesh_core::shown(a.frame_budget_ms));
    }
    Ok(())
}

/// The form's correction with the options that change it; refused when inconsistent.
fn correction_settings(a: &Args, base: CorrectionSettings) -> Result<CorrectionSettings> {
    let correction = CorrectionSettings {
        updates: a.correction_updates.unwrap_or(base.updates),
        cg_iterations: a.correction_cg.unwrap_or(base.cg_iterations),
        subspace_patches: a.correction_subspace.unwrap_or(base.subspace_patches),
        doubted_updates: a.doubted_updates.unwrap_or(base.doubted_updates),
        doubted_carried_updates: a
            .doubted_carried_updates
            .unwrap_or_else(|| base.doubted_carried_updates.min(a.doubted_updates.unwrap_or(usize::MAX)).max(1)),
        doubted_carried_stop_mm: a.doubted_carried_stop_mm.unwrap_or(base.doubted_carried_stop_mm),
        doubted_cg_iterations: a.doubted_cg.unwrap_or(base.doubted_cg_iterations),
        doubted_coarsening: a.doubted_coarsening.unwrap_or(base.doubted_coarsening),
        ..base
    };
    // A doubted frame is corrected by the correction: asked for with it off, it would be
    // ignored without a word.
    if correction.updates == 0
        && (a.doubted_updates.is_some()
            || a.doubted_carried_updates.is_some()
            || a.doubted_carried_stop_mm.is_some()
            || a.doubted_cg.is_some()
            || a.doubted_coarsening.is_some())
    {
        bail!(
            "--doubted-updates / --doubted-carried-updates / --doubted-carried-stop-mm / --doubted-cg / --doubted-coarsening apply to the physics correction, which --correction-updates 0 turns off"
        );
    }
    correction.validate()?;
    Ok(correction)
}

/// A RealSense file given as `--recording`, imported into a folder beside `--out` (removed
/// with the `Imported` guard).
fn import_if_realsense(a: &Args) -> Result<Imported> {
    Ok(match &a.recording {
        Some(f) if is_realsense_file(f) => {
            let name = a.out.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "out".into());
            let dir = a.out.with_file_name(format!(".{name}.import-{}", std::process::id()));
            let r = super::camera::import_to(f, &dir).with_context(|| format!("--recording {}", f.display()))?;
            eprintln!("imported {} frames of {} ({} dropped by the camera)", r.frames, f.display(), r.dropped);
            Imported(Some(dir))
        }
        _ => Imported(None),
    })
}

/// A registration's summary as `--json` prints it (and `report.json` holds).
fn summary_json(r: &RegisterReport) -> serde_json::Value {
    let s = &r.summary;
    serde_json::json!({
        "model": r.model, "pose": r.pose.name(), "pose_reason": r.pose_reason, "pose_moved_max_mm": s.pose_moved_max_mm, "frames": s.frames, "skipped": s.skipped, "dropped": s.dropped, "frame_ms_median": s.frame_ms_median, "frame_ms_p95": s.frame_ms_p95,
        "end_to_end_ms_median": s.end_to_end_ms_median,
        "tre_mean_mm": s.tre_mean_mm, "tre_max_mm": s.tre_max_mm, "tre_rigid_mean_mm": s.tre_rigid_mean_mm,
        "marker_displacement_mean_mm": s.marker_displacement_mean_mm,
        "last_tre_mm": s.last_tre_mm, "last_tre_rigid_mm": s.last_tre_rigid_mm,
        "last_marker_displacement_mm": s.last_marker_displacement_mm,
        "frames_with_warning": s.frames_with_warning, "frames_corrected_as_fe": s.frames_corrected_as_fe, "residual_p95_median_mm": s.residual_p95_median_mm,
        "confidence_calibrated": r.frames.first().is_some_and(|f| f.confidence.calibrated),
        "latency_ms_median": latency_medians(r),
        "correction_moved_rms_mm_median": correction_moved_median(r),
    })
}

/// The per-frame table and the summary lines printed without `--json`.
fn print_table(report: &RegisterReport, fe_report: Option<&RegisterReport>, out: &std::path::Path) {
    println!(
        "{:>6} {:>9} {:>9} {:>9} {:>9} {:>9} {:>10} {:>10} {:>10}  confidence",
        "frame", "points", "ICP", "u_s", "predict", "overlay", "total ms", "TRE mm", "fit p95"
    );
    for f in &report.frames {
        let l = &f.latency;
        println!(
            "{:>6} {:>9.1} {:>9.1} {:>9.1} {:>9.1} {:>9.1} {:>10.1} {:>10} {:>10.2}  {}",
            f.frame,
            l.points_ms,
            l.icp_ms,
            l.surface_ms,
            l.predict_ms,
            l.overlay_ms,
            l.total_ms,
            f.tre_mean_mm.map(|t| format!("{t:.2}")).unwrap_or_else(|| "-".into()),
            f.confidence.residual_p95_mm,
            if !f.confidence.calibrated {
                "not calibrated".to_string()
            } else if f.confidence.warning() {
                format!("WARNING: {}", f.confidence.warnings.join("; "))
            } else {
                "ok".to_string()
            }
        );
    }
    for r in std::iter::once(report).chain(fe_report) {
        let s = &r.summary;
        println!(
            "{}{}: {} frames ({} skipped, {} with a confidence warning{}), {:.1} ms median, {:.1} ms p95{}",
            r.model,
            match correction_moved_median(r) {
                Some(m) => format!(" + physics correction (moved {m:.2} mm RMS median)"),
                None => String::new(),
            },
            s.frames,
            s.skipped,
            s.frames_with_warning,
            if s.frames_corrected_as_fe > 0 {
                format!(", {} corrected as the FE fit", s.frames_corrected_as_fe)
            } else {
                String::new()
            },
            s.frame_ms_median,
            s.frame_ms_p95,
            match (s.tre_mean_mm, s.tre_max_mm, s.tre_rigid_mean_mm) {
                (Some(m), Some(x), Some(r0)) => format!("; TRE {m:.2} mm mean, {x:.2} mm max (rigid only: {r0:.2} mm)"),
                _ => String::new(),
            }
        );
    }
    match report.summary.pose_moved_max_mm {
        Some(m) => println!("pose: {} (ICP moved the organ points by at most {m:.2} mm RMS)", report.pose_reason),
        None => println!("pose: {}", report.pose_reason),
    }
    if report.summary.dropped > 0 {
        println!(
            "{} frames dropped by the source (the camera's gaps, or frames arriving while one was registered)",
            report.summary.dropped
        );
    }
    if let Some(e) = report.summary.end_to_end_ms_median {
        println!("end-to-end latency (camera bridge to overlay): {e:.1} ms median");
    }
    println!("overlays and report.json in {}", out.display());
}

/// The correction form `--correction-form` names, and why; auto: the model folder's choice for
/// the frame budget (said on stderr), else subspace.
fn correction_form(asked: &str, model_dir: &Path, budget_ms: Option<f64>) -> Result<(CorrectionForm, String)> {
    Ok(match asked {
        "auto" => match CorrectionChoice::read(model_dir)? {
            Some(c) => {
                let (form, why) = c.choose(budget_ms);
                eprintln!("correction: {why}");
                (form, why)
            }
            None => (
                CorrectionForm::Subspace,
                "subspace correction: the model has no registration check (correction.json)".into(),
            ),
        },
        other => {
            (parse_form(other).context("--correction-form")?, format!("{other} correction: asked by --correction-form"))
        }
    })
}

/// A correction form by name.
pub fn parse_form(name: &str) -> Result<CorrectionForm> {
    Ok(match name {
        "subspace" => CorrectionForm::Subspace,
        "tracking" => CorrectionForm::Tracking,
        "fast-tracking" => CorrectionForm::FastTracking,
        "coarse-tracking" => CorrectionForm::CoarseTracking,
        other => bail!("{other:?}: auto, subspace, coarse-tracking, tracking or fast-tracking"),
    })
}

/// The median over the frames of how far the physics correction moved the prediction (mm
/// RMS over the nodes); None when it was off.
fn correction_moved_median(r: &RegisterReport) -> Option<f64> {
    let mut v: Vec<f64> = r.frames.iter().filter_map(|f| f.correction.map(|c| c.moved_rms_mm)).collect();
    v.sort_by(f64::total_cmp);
    (!v.is_empty()).then(|| v[v.len() / 2])
}

fn latency_medians(r: &RegisterReport) -> serde_json::Value {
    let med = |f: &dyn Fn(&umesh_core::register::pipeline::Latency) -> f64| {
        let mut v: Vec<f64> = r.frames.iter().map(|x| f(&x.latency)).collect();
        v.sort_by(f64::total_cmp);
        if v.is_empty() { 0.0 } else { v[v.len() / 2] }
    };
    serde_json::json!({
        "points": med(&|l| l.points_ms), "icp": med(&|l| l.icp_ms), "u_s": med(&|l| l.surface_ms),
        "predict": med(&|l| l.predict_ms), "correction": med(&|l| l.correction_ms), "overlay": med(&|l| l.overlay_ms),
        "total": med(&|l| l.total_ms),
    })
}

/// Register `source`'s frames with `registrar` (its models built, the source's pose policy set).
fn register_with(
    source: &mut dyn FrameSource,
    registrar: Registrar<'_>,
    model: &mut dyn umesh_core::register::pipeline::DisplacementModel,
    pose: Option<Matrix4<f64>>,
    truth: Option<&GroundTruth>,
    overlay_dir: &Path,
    message: &str,
) -> Result<RegisterReport> {
    let (pb, progress) = super::output::progress_bar(message);
    let mut write = |o: &umesh_core::register::pipeline::FrameOutput| -> Result<(), umesh_core::Invalid> {
        if let Some(img) = &o.overlay {
            let p = overlay_dir.join(format!("{:05}.png", o.report.frame));
            let bytes = img.encode_png()?;
            umesh_core::write_atomic(&p, &bytes).map_err(|e| umesh_core::Invalid(format!("{}: {e}", p.display())))?;
        }
        Ok(())
    };
    let r = run_registrar(registrar, source, model, pose, truth, &mut write, &progress, &super::output::cancel());
    pb.finish_and_clear();
    Ok(r?)
}
