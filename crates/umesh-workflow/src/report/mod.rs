//! `report.html` of a patient folder: one self-contained page (inline SVG, no script, no
//! external file) with the grid, the dataset, the training, the TRE and the registration check.

mod html;

use crate::patient::{CheckReport, Patient, Stage};
use html::{El, el, figure, p, table};
use std::path::Path;
use umesh_core::dataset::{DatasetStats, Distribution};
use umesh_core::synth::{SynthReport, SynthSettings};
use umesh_net::eval::EvalReport;
use umesh_net::training::EpochMetrics;

const W: f64 = 420.0;
const H: f64 = 220.0;
const L: f64 = 48.0;
const B: f64 = 34.0;

const STYLE: &str = "body{font-family:sans-serif;max-width:1100px;margin:1em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}
td:first-child,th:first-child{text-align:left}figure{display:inline-block;margin:.5em 1em .5em 0;vertical-align:top}
figcaption{font-size:12px;color:#555}pre{background:#f5f5f5;padding:.5em;overflow:auto;font-size:11px}
.ok{color:#2ca02c}.bad{color:#d62728}.problem{color:#d62728;font-weight:bold}";

fn nice(v: f64) -> String {
    if v.abs() >= 100.0 {
        format!("{v:.0}")
    } else if v.abs() >= 10.0 {
        format!("{v:.1}")
    } else {
        format!("{v:.2}")
    }
}

fn svg(width: f64, height: f64) -> El {
    el("svg")
        .attr("xmlns", "http://www.w3.org/2000/svg")
        .attr("width", format!("{width:.0}"))
        .attr("height", format!("{height:.0}"))
        .attr("viewBox", format!("0 0 {width:.0} {height:.0}"))
}

fn svg_text(x: f64, y: f64, size: u32, anchor: &str, text: impl Into<String>) -> El {
    el("text").attr("x", format!("{x:.1}")).attr("y", format!("{y:.1}")).attr("font-size", size).attr("text-anchor", anchor).text(text)
}

fn line(x1: f64, y1: f64, x2: f64, y2: f64, stroke: &str) -> El {
    el("line")
        .attr("x1", format!("{x1:.1}"))
        .attr("y1", format!("{y1:.1}"))
        .attr("x2", format!("{x2:.1}"))
        .attr("y2", format!("{y2:.1}"))
        .attr("stroke", stroke)
}

/// The axes, four ticks each and their labels.
fn axes(x0: f64, x1: f64, y0: f64, y1: f64, xlabel: &str, ylabel: &str) -> Vec<El> {
    let yb = H - B;
    let mut out = vec![line(L, yb, W, yb, "#333"), line(L, 8.0, L, yb, "#333")];
    for k in 0..=4 {
        let f = k as f64 / 4.0;
        let x = L + f * (W - L - 8.0);
        let y = H - B - f * (H - B - 8.0);
        out.push(svg_text(x, H - B + 13.0, 10, "middle", nice(x0 + f * (x1 - x0))));
        out.push(svg_text(L - 4.0, y + 3.0, 10, "end", nice(y0 + f * (y1 - y0))));
    }
    out.push(svg_text((L + W) / 2.0, H - 4.0, 11, "middle", xlabel));
    let cy = (H - B) / 2.0;
    out.push(svg_text(12.0, cy, 11, "middle", ylabel).attr("transform", format!("rotate(-90 12 {cy})")));
    out
}

fn no_values() -> El {
    svg(W, H).child(el("text").attr("x", 20).attr("y", 40).text("no values"))
}

/// Histogram bins of the finite `values` over [min(0, values, mark), max(values, mark)]:
/// (lo, hi, counts). The report and the app's jobs view bin alike.
pub fn histogram_bins(values: &[f64], bins: usize, mark: Option<f64>) -> (f64, f64, Vec<usize>) {
    let v = values.iter().copied().filter(|x| x.is_finite());
    let mut lo = v.clone().fold(f64::INFINITY, f64::min).min(mark.unwrap_or(f64::INFINITY)).min(0.0);
    let mut hi = v.clone().fold(f64::NEG_INFINITY, f64::max).max(mark.unwrap_or(f64::NEG_INFINITY));
    if !hi.is_finite() {
        (lo, hi) = (0.0, 1.0);
    }
    if hi - lo < 1e-9 {
        hi = lo + 1.0;
    }
    let bins = bins.max(1);
    let mut counts = vec![0usize; bins];
    for x in v {
        let b = (((x - lo) / (hi - lo)) * bins as f64).floor() as usize;
        counts[b.min(bins - 1)] += 1;
    }
    (lo, hi, counts)
}

/// A histogram of `values` with an optional vertical line (a target).
pub fn histogram_svg(values: &[f64], bins: usize, xlabel: &str, mark: Option<(f64, &str)>) -> El {
    let v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return no_values();
    }
    let (lo, hi, counts) = histogram_bins(&v, bins, mark.map(|m| m.0));
    let bins = counts.len();
    // Whole counts on the four y ticks.
    let cmax = (*counts.iter().max().unwrap_or(&1)).div_ceil(4).max(1) as f64 * 4.0;
    let mut out = svg(W, H).children(axes(lo, hi, 0.0, cmax, xlabel, "samples"));
    let pw = W - L - 8.0;
    let ph = H - B - 8.0;
    for (b, &c) in counts.iter().enumerate() {
        let h = ph * c as f64 / cmax;
        out = out.child(
            el("rect")
                .attr("x", format!("{:.1}", L + pw * b as f64 / bins as f64))
                .attr("y", format!("{:.1}", H - B - h))
                .attr("width", format!("{:.1}", pw / bins as f64 - 1.0))
                .attr("height", format!("{h:.1}"))
                .attr("fill", "#4c78a8"),
        );
    }
    if let Some((m, label)) = mark {
        let x = L + pw * (m - lo) / (hi - lo);
        out = out
            .child(line(x, 8.0, x, H - B, "#d62728").attr("stroke-width", 2).attr("stroke-dasharray", "4 3"))
            .child(svg_text(x + 4.0, 20.0, 11, "start", label).attr("fill", "#d62728"));
    }
    out
}

/// Lines over epochs; `log` plots log10 of the values.
pub fn lines_svg(series: &[(&str, &str, Vec<(f64, f64)>)], xlabel: &str, ylabel: &str, log: bool) -> El {
    let tf = |y: f64| if log { y.max(1e-30).log10() } else { y };
    let pts: Vec<(f64, f64)> = series.iter().flat_map(|s| s.2.iter().map(|&(x, y)| (x, tf(y)))).filter(|p| p.1.is_finite()).collect();
    if pts.is_empty() {
        return no_values();
    }
    let (mut x0, mut x1) = pts.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, p| (a.0.min(p.0), a.1.max(p.0)));
    let (mut y0, mut y1) = pts.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, p| (a.0.min(p.1), a.1.max(p.1)));
    if x1 - x0 < 1e-9 {
        x0 -= 0.5;
        x1 += 0.5;
    }
    if !log {
        y0 = y0.min(0.0);
    }
    if y1 - y0 < 1e-9 {
        y1 = y0 + 1.0;
    }
    let yl = if log { format!("log10 {ylabel}") } else { ylabel.to_string() };
    let mut out = svg(W, H).children(axes(x0, x1, y0, y1, xlabel, &yl));
    let pw = W - L - 8.0;
    let ph = H - B - 8.0;
    for (k, (name, color, s)) in series.iter().enumerate() {
        let path: Vec<String> = s
            .iter()
            .map(|&(x, y)| (x, tf(y)))
            .filter(|p| p.1.is_finite())
            .map(|(x, y)| format!("{:.1},{:.1}", L + pw * (x - x0) / (x1 - x0), H - B - ph * (y - y0) / (y1 - y0)))
            .collect();
        out = out
            .child(el("polyline").attr("fill", "none").attr("stroke", color).attr("stroke-width", 2).attr("points", path.join(" ")))
            .child(svg_text(W - 130.0, 20.0 + 14.0 * k as f64, 11, "start", *name).attr("fill", color));
    }
    out
}

/// The grid seen from the camera's side (anterior, x right and z up) and from the right: every
/// node a dot, fixed nodes red, nodes the camera observes green.
pub fn grid_svg(grid_npz: &Path) -> Vec<El> {
    let Ok(npz) = umesh_core::npz::Npz::read(grid_npz) else {
        return vec![p("grid.npz could not be read")];
    };
    let nodes = npz.f64_with_shape("nodes", &[None, Some(3)]).map(|x| x.1).unwrap_or_default();
    let list =
        |name: &str| npz.f64_with_shape(name, &[None]).map(|x| x.1.iter().map(|&v| v as usize).collect::<Vec<_>>()).unwrap_or_default();
    let n = nodes.len() / 3;
    let mut kind = vec![0u8; n];
    for i in list("visible_nodes") {
        if i < n {
            kind[i] = 1;
        }
    }
    for i in list("fixed_nodes") {
        if i < n {
            kind[i] = 2;
        }
    }
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in nodes.chunks(3) {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let views = [("anterior (x right, z up)", 0usize, 2usize, 1usize, false), ("right side (y anterior left, z up)", 1, 2, 0, true)];
    let mut out = Vec::new();
    for (title, ax, ay, depth, flip) in views {
        let sx = hi[ax] - lo[ax];
        let sy = hi[ay] - lo[ay];
        let scale = 320.0 / sx.max(sy).max(1e-9);
        let mut picture = svg(sx * scale + 20.0, sy * scale + 20.0);
        // Far nodes first, so what faces the viewer is drawn on top.
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by(|&a, &b| nodes[3 * a + depth].total_cmp(&nodes[3 * b + depth]));
        if !flip {
            order.reverse();
        }
        for i in order {
            let p = &nodes[3 * i..3 * i + 3];
            let x = if flip { hi[ax] - p[ax] } else { p[ax] - lo[ax] } * scale + 10.0;
            let y = (hi[ay] - p[ay]) * scale + 10.0;
            let (c, r) = match kind[i] {
                2 => ("#d62728", 2.2),
                1 => ("#2ca02c", 1.8),
                _ => ("#9aa3ad", 1.2),
            };
            picture = picture.child(el("circle").attr("cx", format!("{x:.1}")).attr("cy", format!("{y:.1}")).attr("r", r).attr("fill", c));
        }
        out.push(figure(picture, title));
    }
    out
}

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
    verdict: &crate::patient::Verdict,
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
    let mut body = el("body").child(el("h1").text("umesh patient report")).child(p(format!(
        "umesh {} \u{b7} organ: {} \u{b7} structures: {} \u{b7} segmentation hash {}",
        patient.program_version,
        patient.organ_labels.join(", "),
        if patient.structures.is_empty() { "none".to_string() } else { patient.structures.join(", ") },
        patient.segmentation_hash
    )));
    // The verdict first: what a reader needs before any figure.
    body = body.child(el("h2").text(if verdict.ready { "Verdict: ready" } else { "Verdict: not ready" }));
    for problem in &verdict.problems {
        body = body.child(el("p").attr("class", "problem").text(problem));
    }
    for note in &verdict.notes {
        body = body.child(p(note.clone()));
    }

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
        stages = stages.child(el("tr").child(el("td").text(st.name())).child(done).child(el("td").text(format!("{:.1}", r.seconds))));
    }
    stages = stages.child(el("tr").child(el("td").text("total")).child(el("td")).child(el("td").text(format!("{total:.1}"))));
    body = body.child(el("h2").text("Stages")).child(stages);
    if let Some(note) = patient.stages.get(&Stage::Train).and_then(|r| r.note.as_ref()) {
        body = body.child(p(format!("Training {note}.")));
    }

    let camera = match &s.dataset.visibility.camera {
        Some(c) => format!("at {:?} mm looking along {:?}, {}\u{b0} field of view", c.position_mm, c.direction, c.fov_deg),
        None => "anterior (default: from 2.5 organ sizes, 50\u{b0})".into(),
    };
    body = body
        .child(el("h2").text("Grid, fixed region and camera"))
        .child(el("p").text(format!("Fixed region: {}.", s.fixed_description)).child(el("br")).text(format!(
            "Camera: {camera}. Cells of {} mm, {} boundary level(s).",
            s.dataset.grid.cell_size_mm, s.dataset.grid.subdivisions
        )))
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
    body = body.child(el("h2").text("Settings")).child(el("pre").text(serde_json::to_string_pretty(s).unwrap_or_default()));
    let mut page = String::from("<!DOCTYPE html>");
    el("html").attr("lang", "en").child(head).child(body).write(&mut page);
    page
}

/// Per accepted sample: mean and max displacement, from the dataset's manifest.
fn dataset_values(_patient: &Patient, grid_npz: &Path) -> (Vec<f64>, Vec<f64>) {
    let dir = grid_npz.parent().unwrap_or(Path::new("."));
    match umesh_core::dataset::Manifest::read(dir) {
        Ok(m) => m.accepted().map(|s| (s.mean_displacement_mm, s.max_displacement_mm)).unzip(),
        Err(_) => (Vec::new(), Vec::new()),
    }
}
