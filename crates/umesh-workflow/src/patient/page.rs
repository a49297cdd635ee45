//! A patient's `report.html`: the verdict, the grid, the dataset, the training, the TRE and
//! the registration check, on one page made with `report`'s builder and charts.

use super::{CheckReport, Patient, Stage, Verdict};
use crate::report::{El, STYLE, el, figure, grid_svg, histogram_svg, lines_svg, nice, p, table};
use std::path::Path;
use umesh_core::dataset::{DatasetStats, Distribution};
use umesh_core::synth::{SynthReport, SynthSettings};
use umesh_net::eval::EvalReport;
use umesh_net::training::EpochMetrics;

fn dist_row(name: &str, d: &Option<Distribution>) -> Vec<String> {
    match d {
        Some(d) => vec![name.into(), nice(d.min), nice(d.p5), nice(d.median), nice(d.mean), nice(d.p95), nice(d.max)],
        None => vec![name.into(), "none".into()],
    }
}

fn opt(v: Option<f64>) -> String {
    v.map(|x| format!("{x:.2}")).unwrap_or_else(|| "-".into())
}

fn dot(color: &str) -> El {
    el("span").attr("style", format!("color:{color}")).text("\u{25CF}")
}

/// The whole page.
pub fn patient_html(
    patient: &Patient,
    verdict: &Verdict,
    stats: &DatasetStats,
    metrics: &[EpochMetrics],
    eval: &EvalReport,
    synth: Option<&SynthReport>,
    check: &CheckReport,
    grid_npz: &Path,
) -> String {
    let s = &patient.settings;
    let head = el("head")
        .child(el("meta").attr("charset", "utf-8"))
        .child(el("title").text("umesh patient report"))
        .child(el("style").static_text(STYLE));
    let body = el("body").child(el("h1").text("umesh patient report")).child(p(format!(
        "umesh {} \u{b7} organ: {} \u{b7} structures: {} \u{b7} segmentation hash {}",
        patient.program_version,
        patient.organ_labels.join(", "),
        if patient.structures.is_empty() { "none".to_string() } else { patient.structures.join(", ") },
        patient.segmentation_hash
    )));
    let body = verdict_section(body, verdict);
    let body = stages_section(body, patient);
    let body = grid_section(body, patient, grid_npz);
    let body = dataset_section(body, patient, stats, grid_npz);
    let body = training_section(body, metrics);
    let body = tre_section(body, eval);
    let body = check_section(body, synth, check);
    let body = body
        .child(el("h2").text("Settings"))
        .child(el("pre").text(serde_json::to_string_pretty(s).unwrap_or_default()));
    let mut page = String::from("<!DOCTYPE html>");
    el("html").attr("lang", "en").child(head).child(body).write(&mut page);
    page
}

/// The verdict: what a reader needs before any figure.
fn verdict_section(body: El, verdict: &Verdict) -> El {
    let mut body = body;
    // The verdict first: what a reader needs before any figure.
    body = body.child(el("h2").text(if verdict.ready { "Verdict: ready" } else { "Verdict: not ready" }));
    for problem in &verdict.problems {
        body = body.child(el("p").attr("class", "problem").text(problem));
    }
    for note in &verdict.notes {
        body = body.child(p(note.clone()));
    }
    body
}

/// The inputs, and each stage's state and time.
fn stages_section(body: El, patient: &Patient) -> El {
    let mut body = body;
    body = body.child(el("h2").text("Inputs")).child(table(
        &["file", "bytes", "hash (FNV-1a 64)"],
        patient.inputs.iter().map(|f| vec![f.path.clone(), f.bytes.to_string(), f.hash.clone()]),
    ));
    let mut stages = el("table").child(el("tr").children(["stage", "done", "time (s)"].map(|h| el("th").text(h))));
    let mut total = 0.0;
    for st in Stage::ALL {
        let r = patient.stages.get(&st).cloned().unwrap_or_default();
        total += r.seconds;
        let done = el("td").attr("class", if r.done { "ok" } else { "bad" }).text(if r.done { "yes" } else { "no" });
        stages = stages.child(
            el("tr").child(el("td").text(st.name())).child(done).child(el("td").text(format!("{:.1}", r.seconds))),
        );
    }
    stages = stages
        .child(el("tr").child(el("td").text("total")).child(el("td")).child(el("td").text(format!("{total:.1}"))));
    body = body.child(el("h2").text("Stages")).child(stages);
    if !patient.settings.prior_description.is_empty() {
        body = body.child(p(format!("Training started from {}.", patient.settings.prior_description)));
    }
    if let Some(note) = patient.stages.get(&Stage::Train).and_then(|r| r.note.as_ref()) {
        body = body.child(p(format!("Training {note}.")));
    }
    body
}

/// The grid's slices with the fixed and observed nodes, the fixed region and the camera.
fn grid_section(body: El, patient: &Patient, grid_npz: &Path) -> El {
    let mut body = body;
    let s = &patient.settings;
    let camera = match &s.dataset.visibility.camera {
        Some(c) => {
            format!("at {:?} mm looking along {:?}, {}\u{b0} field of view", c.position_mm, c.direction, c.fov_deg)
        }
        None => "anterior (default: from 2.5 organ sizes, 50\u{b0})".into(),
    };
    body = body
        .child(el("h2").text("Grid, fixed region and camera"))
        .child(el("p").text(format!("Fixed region: {}.", s.fixed_description)).child(el("br")).text(format!(
            "Camera: {camera}. Cells of {} mm, {} boundary level(s){}.",
            s.dataset.grid.cell_size_mm,
            s.dataset.grid.subdivisions,
            if s.grid_description.is_empty() { String::new() } else { format!(": {}", s.grid_description) }
        )))
        .children((!s.surface_description.is_empty()).then(|| p(format!("Organ surface: {}.", s.surface_description))))
        .children(grid_svg(grid_npz))
        .child(
            el("p")
                .child(dot("#d62728"))
                .text(" fixed nodes \u{a0} ")
                .child(dot("#2ca02c"))
                .text(" nodes the camera observes \u{a0} ")
                .child(dot("#9aa3ad"))
                .text(" other nodes"),
        );
    body
}

/// The dataset: acceptance, the distributions of its samples, their displacements.
fn dataset_section(body: El, patient: &Patient, stats: &DatasetStats, grid_npz: &Path) -> El {
    let mut body = body;
    let s = &patient.settings;
    let rejected: Vec<String> = stats.rejected.iter().map(|(k, v)| format!("{v} {k}")).collect();
    let (means, maxes) = dataset_values(patient, grid_npz);
    body = body
        .child(el("h2").text("Dataset"))
        .child(
            el("p")
                .text(format!("{} samples, ", stats.samples))
                .child(el("b").text(format!(
                    "{} accepted ({:.1} %)",
                    stats.accepted,
                    100.0 * stats.accepted as f64 / stats.samples.max(1) as f64
                )))
                .text(format!(
                    "; rejected: {}. Loads calibrated to a mean nodal displacement of {} mm (each sample's target uniform in {:.0}-{:.0} % of it).",
                    if rejected.is_empty() { "none".into() } else { rejected.join(", ") },
                    nice(stats.target_displacement_mm),
                    100.0 * (1.0 - s.dataset.forces.target_spread),
                    100.0 * (1.0 + s.dataset.forces.target_spread)
                )),
        )
        .child(table(
            &["", "min", "p5", "median", "mean", "p95", "max"],
            [
                ("mean nodal displacement (mm)", &stats.mean_displacement_mm),
                ("max nodal displacement (mm)", &stats.max_displacement_mm),
                ("achieved / calibrated target", &stats.achieved_over_target),
                ("Newton iterations", &stats.newton_iterations),
                ("solve time (ms)", &stats.solve_ms),
                ("rejected samples' solve time (ms)", &stats.rejected_solve_ms),
            ]
            .map(|(n, d)| dist_row(n, d)),
        ))
        .child(figure(
            histogram_svg(&means, 30, "mean displacement (mm)", Some((stats.target_displacement_mm, "target"))),
            "mean nodal displacement per sample (target dashed)",
        ))
        .child(figure(histogram_svg(&maxes, 30, "max displacement (mm)", None), "max nodal displacement per sample"));
    body
}

/// The training curves and the last epoch.
fn training_section(body: El, metrics: &[EpochMetrics]) -> El {
    let mut body = body;
    let ep = |f: &dyn Fn(&EpochMetrics) -> f64| metrics.iter().map(|m| (m.epoch as f64, f(m))).collect::<Vec<_>>();
    body = body
        .child(el("h2").text("Training"))
        .child(figure(
            lines_svg(
                &[("train", "#4c78a8", ep(&|m| m.train_loss)), ("validation", "#f58518", ep(&|m| m.val_loss))],
                "epoch",
                "loss",
                true,
            ),
            "loss (MSE, normalised units)",
        ))
        .child(figure(
            lines_svg(
                &[("mean", "#4c78a8", ep(&|m| m.val_tre_mean_mm)), ("max", "#d62728", ep(&|m| m.val_tre_max_mm))],
                "epoch",
                "TRE (mm)",
                false,
            ),
            "validation TRE per epoch",
        ));
    if let Some(m) = metrics.last() {
        body = body.child(p(format!(
            "{} epochs; last: validation TRE {:.2} mm mean, {:.2} mm max; {:.1} training samples/s.",
            metrics.len(),
            m.val_tre_mean_mm,
            m.val_tre_max_mm,
            m.train_samples_per_s
        )));
    }
    body
}

/// The validation split's TRE.
fn tre_section(body: El, eval: &EvalReport) -> El {
    let mut body = body;
    body = body
        .child(el("h2").text("Target registration error (validation split, FE truth)"))
        .child(
            el("p")
                .text(format!("{} samples \u{d7} {} markers: ", eval.samples, eval.markers_per_sample))
                .child(el("b").text(format!("TRE {:.2} \u{b1} {:.2} mm", eval.tre_mean_mm, eval.tre_std_mm)))
                .text(format!(
                    ", max {:.2} mm, at a mean marker displacement of {:.2} mm.",
                    eval.tre_max_mm, eval.marker_displacement_mean_mm
                )),
        )
        .child(figure(histogram_svg(&eval.per_marker_tre_mm, 30, "TRE (mm)", None), "per-marker TRE"));
    body
}

/// The registration check on the synthetic recording and the correction form it chose.
fn check_section(body: El, synth: Option<&SynthReport>, check: &CheckReport) -> El {
    let mut body = body;
    body = body.child(el("h2").text("Registration check (synthetic RGB-D recording)"));
    if let Some(r) = synth {
        body = body.child(p(format!(
            "{} frames, {} markers; mean marker displacement at the last frame {:.2} mm (max over frames {:.2} mm); load scale {:.2}{}.",
            r.frames,
            r.markers,
            r.mean_marker_displacement_mm,
            r.max_marker_displacement_mm,
            r.load_scale,
            if r.load_scale > 0.0 && r.load_scale < SynthSettings::default().load_scale - 1e-9 {
                " (lighter than the default: the organ did not converge at the default load)"
            } else {
                ""
            }
        )));
    }
    if let Some(w) = &check.warning {
        body = body.child(
            el("p")
                .attr("class", "warn")
                .child(el("b").text("The check did not run:"))
                .text(format!(" {w}. The model is trained and usable.")),
        );
    }
    let c = &check.summary;
    body = body.child(table(
        &["", "value"],
        [
            ["frames registered / skipped".to_string(), format!("{} / {}", c.frames, c.skipped)],
            ["frame time, median (ms)".into(), format!("{:.1}", c.frame_ms_median)],
            ["TRE, mean over frames (mm)".into(), opt(c.tre_mean_mm)],
            ["TRE rigid only, mean over frames (mm)".into(), opt(c.tre_rigid_mean_mm)],
            [
                "last frame: TRE / rigid only / marker motion (mm)".into(),
                format!(
                    "{} / {} / {}",
                    opt(check.last_frame_tre_mm),
                    opt(check.last_frame_tre_rigid_mm),
                    opt(check.last_frame_marker_displacement_mm)
                ),
            ],
        ],
    ));
    if let Some(ch) = &check.correction {
        body = body.child(el("p").text(format!(
            "The figures above are the {} (written into the model folder; `register` and the AR view use it unless told otherwise).",
            ch.describe()
        )));
    }
    if !check.log.is_empty() {
        body = body.child(el("pre").text(check.log.join("\n")));
    }
    body
}

/// Per accepted sample: mean and max displacement, from the dataset's manifest.
fn dataset_values(_patient: &Patient, grid_npz: &Path) -> (Vec<f64>, Vec<f64>) {
    let dir = grid_npz.parent().unwrap_or(Path::new("."));
    match umesh_core::dataset::Manifest::read(dir) {
        Ok(m) => m.accepted().map(|s| (s.mean_displacement_mm, s.max_displacement_mm)).unzip(),
        Err(_) => (Vec::new(), Vec::new()),
    }
}
