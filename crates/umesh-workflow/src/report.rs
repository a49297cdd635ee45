//! `report.html` of a patient folder: one self-contained page (inline SVG, no script, no
//! external file) with the grid, the dataset, the training, the TRE and the registration check.

use crate::patient::{CheckReport, Patient, Stage};
use std::fmt::Write;
use std::path::Path;
use umesh_core::dataset::{DatasetStats, Distribution};
use umesh_core::synth::{SynthReport, SynthSettings};
use umesh_net::eval::EvalReport;
use umesh_net::training::EpochMetrics;

fn esc(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

const W: f64 = 420.0;
const H: f64 = 220.0;
const L: f64 = 48.0;
const B: f64 = 34.0;

fn nice(v: f64) -> String {
    if v.abs() >= 100.0 {
        format!("{v:.0}")
    } else if v.abs() >= 10.0 {
        format!("{v:.1}")
    } else {
        format!("{v:.2}")
    }
}

fn axes(svg: &mut String, x0: f64, x1: f64, y0: f64, y1: f64, xlabel: &str, ylabel: &str) {
    let _ = write!(
        svg,
        r##"<line x1="{L}" y1="{yb}" x2="{W}" y2="{yb}" stroke="#333"/><line x1="{L}" y1="8" x2="{L}" y2="{yb}" stroke="#333"/>"##,
        yb = H - B
    );
    for k in 0..=4 {
        let f = k as f64 / 4.0;
        let x = L + f * (W - L - 8.0);
        let y = H - B - f * (H - B - 8.0);
        let _ = write!(
            svg,
            r##"<text x="{x}" y="{ty}" font-size="10" text-anchor="middle">{}</text><text x="{tx}" y="{y2}" font-size="10" text-anchor="end">{}</text>"##,
            nice(x0 + f * (x1 - x0)),
            nice(y0 + f * (y1 - y0)),
            ty = H - B + 13.0,
            tx = L - 4.0,
            y2 = y + 3.0
        );
    }
    let _ = write!(
        svg,
        r##"<text x="{cx}" y="{by}" font-size="11" text-anchor="middle">{}</text><text x="12" y="{cy}" font-size="11" text-anchor="middle" transform="rotate(-90 12 {cy})">{}</text>"##,
        esc(xlabel),
        esc(ylabel),
        cx = (L + W) / 2.0,
        by = H - 4.0,
        cy = (H - B) / 2.0
    );
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
pub fn histogram_svg(values: &[f64], bins: usize, xlabel: &str, mark: Option<(f64, &str)>) -> String {
    let v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    let mut svg = format!(r#"<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" viewBox="0 0 {W} {H}">"#);
    if v.is_empty() {
        svg.push_str(r#"<text x="20" y="40">no values</text></svg>"#);
        return svg;
    }
    let (lo, hi, counts) = histogram_bins(&v, bins, mark.map(|m| m.0));
    let bins = counts.len();
    // Whole counts on the four y ticks.
    let cmax = (*counts.iter().max().unwrap_or(&1)).div_ceil(4).max(1) as f64 * 4.0;
    axes(&mut svg, lo, hi, 0.0, cmax, xlabel, "samples");
    let pw = W - L - 8.0;
    let ph = H - B - 8.0;
    for (b, &c) in counts.iter().enumerate() {
        let x = L + pw * b as f64 / bins as f64;
        let h = ph * c as f64 / cmax;
        let _ = write!(
            svg,
            r##"<rect x="{x:.1}" y="{y:.1}" width="{w:.1}" height="{h:.1}" fill="#4c78a8"/>"##,
            y = H - B - h,
            w = pw / bins as f64 - 1.0
        );
    }
    if let Some((m, label)) = mark {
        let x = L + pw * (m - lo) / (hi - lo);
        let _ = write!(
            svg,
            r##"<line x1="{x:.1}" y1="8" x2="{x:.1}" y2="{yb}" stroke="#d62728" stroke-width="2" stroke-dasharray="4 3"/><text x="{tx:.1}" y="20" font-size="11" fill="#d62728">{}</text>"##,
            esc(label),
            yb = H - B,
            tx = x + 4.0
        );
    }
    svg.push_str("</svg>");
    svg
}

/// Lines over epochs; `log` plots log10 of the values.
pub fn lines_svg(series: &[(&str, &str, Vec<(f64, f64)>)], xlabel: &str, ylabel: &str, log: bool) -> String {
    let mut svg = format!(r#"<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" viewBox="0 0 {W} {H}">"#);
    let tf = |y: f64| if log { y.max(1e-30).log10() } else { y };
    let pts: Vec<(f64, f64)> = series.iter().flat_map(|s| s.2.iter().map(|&(x, y)| (x, tf(y)))).filter(|p| p.1.is_finite()).collect();
    if pts.is_empty() {
        svg.push_str(r#"<text x="20" y="40">no values</text></svg>"#);
        return svg;
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
    axes(&mut svg, x0, x1, y0, y1, xlabel, &yl);
    let pw = W - L - 8.0;
    let ph = H - B - 8.0;
    for (k, (name, color, s)) in series.iter().enumerate() {
        let path: Vec<String> = s
            .iter()
            .map(|&(x, y)| (x, tf(y)))
            .filter(|p| p.1.is_finite())
            .map(|(x, y)| format!("{:.1},{:.1}", L + pw * (x - x0) / (x1 - x0), H - B - ph * (y - y0) / (y1 - y0)))
            .collect();
        let _ = write!(svg, r#"<polyline fill="none" stroke="{color}" stroke-width="2" points="{}"/>"#, path.join(" "));
        let _ = write!(
            svg,
            r#"<text x="{x}" y="{y}" font-size="11" fill="{color}">{}</text>"#,
            esc(name),
            x = W - 130.0,
            y = 20.0 + 14.0 * k as f64
        );
    }
    svg.push_str("</svg>");
    svg
}

/// The grid seen from the camera's side (anterior, x right and z up): every node a dot,
/// fixed nodes red, nodes the camera observes green.
pub fn grid_svg(grid_npz: &Path) -> String {
    let Ok(npz) = umesh_core::npz::Npz::read(grid_npz) else {
        return "<p>grid.npz could not be read</p>".into();
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
    let mut out = String::new();
    for (title, ax, ay, depth, flip) in views {
        let sx = hi[ax] - lo[ax];
        let sy = hi[ay] - lo[ay];
        let scale = 320.0 / sx.max(sy).max(1e-9);
        let (w, h) = (sx * scale + 20.0, sy * scale + 20.0);
        let _ = write!(out, r#"<figure><svg xmlns="http://www.w3.org/2000/svg" width="{w:.0}" height="{h:.0}">"#);
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
            let _ = write!(out, r#"<circle cx="{x:.1}" cy="{y:.1}" r="{r}" fill="{c}"/>"#);
        }
        let _ = write!(out, "</svg><figcaption>{}</figcaption></figure>", esc(title));
    }
    out
}

fn dist_row(name: &str, d: &Option<Distribution>) -> String {
    match d {
        Some(d) => format!(
            "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
            esc(name),
            nice(d.min),
            nice(d.p5),
            nice(d.median),
            nice(d.mean),
            nice(d.p95),
            nice(d.max)
        ),
        None => format!("<tr><td>{}</td><td colspan=6>none</td></tr>", esc(name)),
    }
}

fn opt(v: Option<f64>) -> String {
    v.map(|x| format!("{x:.2}")).unwrap_or_else(|| "-".into())
}

/// The whole page.
pub fn patient_html(
    patient: &Patient,
    stats: &DatasetStats,
    metrics: &[EpochMetrics],
    eval: &EvalReport,
    synth: Option<&SynthReport>,
    check: &CheckReport,
    grid_npz: &Path,
) -> String {
    let mut h = String::new();
    let s = &patient.settings;
    let _ = write!(
        h,
        r#"<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>umesh patient report</title><style>
body{{font-family:sans-serif;max-width:1100px;margin:1em auto;padding:0 1em;color:#222}}
table{{border-collapse:collapse;margin:.5em 0}}td,th{{border:1px solid #ccc;padding:3px 8px;text-align:right}}
td:first-child,th:first-child{{text-align:left}}figure{{display:inline-block;margin:.5em 1em .5em 0;vertical-align:top}}
figcaption{{font-size:12px;color:#555}}pre{{background:#f5f5f5;padding:.5em;overflow:auto;font-size:11px}}
.ok{{color:#2ca02c}}.bad{{color:#d62728}}</style></head><body>
<h1>umesh patient report</h1><p>umesh {} &middot; organ: {} &middot; structures: {} &middot; segmentation hash {}</p>"#,
        esc(&patient.program_version),
        esc(&patient.organ_labels.join(", ")),
        esc(&if patient.structures.is_empty() { "none".to_string() } else { patient.structures.join(", ") }),
        esc(&patient.segmentation_hash)
    );
    h.push_str("<h2>Inputs</h2><table><tr><th>file</th><th>bytes</th><th>hash (FNV-1a 64)</th></tr>");
    for f in &patient.inputs {
        let _ = write!(h, "<tr><td>{}</td><td>{}</td><td>{}</td></tr>", esc(&f.path), f.bytes, esc(&f.hash));
    }
    h.push_str("</table><h2>Stages</h2><table><tr><th>stage</th><th>done</th><th>time (s)</th></tr>");
    let mut total = 0.0;
    for st in Stage::ALL {
        let r = patient.stages.get(&st).cloned().unwrap_or_default();
        total += r.seconds;
        let _ = write!(
            h,
            "<tr><td>{}</td><td class={}>{}</td><td>{:.1}</td></tr>",
            st.name(),
            if r.done { "ok" } else { "bad" },
            if r.done { "yes" } else { "no" },
            r.seconds
        );
    }
    let _ = write!(h, "<tr><td>total</td><td></td><td>{total:.1}</td></tr></table>");

    h.push_str("<h2>Grid, fixed region and camera</h2>");
    let _ = write!(
        h,
        "<p>Fixed region: {}.<br>Camera: {}. Cells of {} mm, {} boundary level(s).</p>",
        esc(&s.fixed_description),
        esc(&match &s.dataset.visibility.camera {
            Some(c) => format!("at {:?} mm looking along {:?}, {}&deg; field of view", c.position_mm, c.direction, c.fov_deg),
            None => "anterior (default: from 2.5 organ sizes, 50&deg;)".into(),
        })
        .replace("&amp;deg;", "&deg;"),
        s.dataset.grid.cell_size_mm,
        s.dataset.grid.subdivisions
    );
    h.push_str(&grid_svg(grid_npz));
    h.push_str("<p><span style=color:#d62728>&#9679;</span> fixed nodes &nbsp; <span style=color:#2ca02c>&#9679;</span> nodes the camera observes &nbsp; <span style=color:#9aa3ad>&#9679;</span> other nodes</p>");

    h.push_str("<h2>Dataset</h2>");
    let rejected: Vec<String> = stats.rejected.iter().map(|(k, v)| format!("{v} {k}")).collect();
    let _ = write!(
        h,
        "<p>{} samples, <b>{} accepted ({:.1} %)</b>; rejected: {}. Loads calibrated to a mean nodal displacement of {} mm (each sample's target uniform in {:.0}-{:.0} % of it).</p>",
        stats.samples,
        stats.accepted,
        100.0 * stats.accepted as f64 / stats.samples.max(1) as f64,
        if rejected.is_empty() { "none".into() } else { esc(&rejected.join(", ")) },
        nice(stats.target_displacement_mm),
        100.0 * (1.0 - s.dataset.forces.target_spread),
        100.0 * (1.0 + s.dataset.forces.target_spread)
    );
    h.push_str("<table><tr><th></th><th>min</th><th>p5</th><th>median</th><th>mean</th><th>p95</th><th>max</th></tr>");
    for (n, d) in [
        ("mean nodal displacement (mm)", &stats.mean_displacement_mm),
        ("max nodal displacement (mm)", &stats.max_displacement_mm),
        ("achieved / calibrated target", &stats.achieved_over_target),
        ("Newton iterations", &stats.newton_iterations),
        ("solve time (ms)", &stats.solve_ms),
    ] {
        h.push_str(&dist_row(n, d));
    }
    h.push_str("</table>");
    let (means, maxes) = dataset_values(patient, grid_npz);
    let _ = write!(
        h,
        "<figure>{}<figcaption>mean nodal displacement per sample (target dashed)</figcaption></figure><figure>{}<figcaption>max nodal displacement per sample</figcaption></figure>",
        histogram_svg(&means, 30, "mean displacement (mm)", Some((stats.target_displacement_mm, "target"))),
        histogram_svg(&maxes, 30, "max displacement (mm)", None)
    );

    h.push_str("<h2>Training</h2>");
    let ep = |f: &dyn Fn(&EpochMetrics) -> f64| metrics.iter().map(|m| (m.epoch as f64, f(m))).collect::<Vec<_>>();
    let _ = write!(
        h,
        "<figure>{}<figcaption>loss (MSE, normalised units)</figcaption></figure><figure>{}<figcaption>validation TRE per epoch</figcaption></figure>",
        lines_svg(&[("train", "#4c78a8", ep(&|m| m.train_loss)), ("validation", "#f58518", ep(&|m| m.val_loss))], "epoch", "loss", true),
        lines_svg(
            &[("mean", "#4c78a8", ep(&|m| m.val_tre_mean_mm)), ("max", "#d62728", ep(&|m| m.val_tre_max_mm))],
            "epoch",
            "TRE (mm)",
            false
        )
    );
    if let Some(m) = metrics.last() {
        let _ = write!(
            h,
            "<p>{} epochs; last: validation TRE {:.2} mm mean, {:.2} mm max; {:.1} training samples/s.</p>",
            metrics.len(),
            m.val_tre_mean_mm,
            m.val_tre_max_mm,
            m.train_samples_per_s
        );
    }

    h.push_str("<h2>Target registration error (validation split, FE truth)</h2>");
    let _ = write!(
        h,
        "<p>{} samples &times; {} markers: <b>TRE {:.2} &plusmn; {:.2} mm</b>, max {:.2} mm, at a mean marker displacement of {:.2} mm.</p><figure>{}<figcaption>per-marker TRE</figcaption></figure>",
        eval.samples,
        eval.markers_per_sample,
        eval.tre_mean_mm,
        eval.tre_std_mm,
        eval.tre_max_mm,
        eval.marker_displacement_mean_mm,
        histogram_svg(&eval.per_marker_tre_mm, 30, "TRE (mm)", None)
    );

    h.push_str("<h2>Registration check (synthetic RGB-D recording)</h2>");
    if let Some(r) = synth {
        let _ = write!(
            h,
            "<p>{} frames, {} markers; mean marker displacement at the last frame {:.2} mm (max over frames {:.2} mm); load scale {:.2}{}.</p>",
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
        );
    }
    if let Some(w) = &check.warning {
        let _ = write!(h, "<p class=\"warn\"><b>The check did not run:</b> {}. The model is trained and usable.</p>", esc(w));
    }
    let c = &check.summary;
    let _ = write!(
        h,
        "<table><tr><th></th><th>value</th></tr><tr><td>frames registered / skipped</td><td>{} / {}</td></tr><tr><td>frame time, median (ms)</td><td>{:.1}</td></tr><tr><td>TRE, mean over frames (mm)</td><td>{}</td></tr><tr><td>TRE rigid only, mean over frames (mm)</td><td>{}</td></tr><tr><td>last frame: TRE / rigid only / marker motion (mm)</td><td>{} / {} / {}</td></tr></table>",
        c.frames,
        c.skipped,
        c.frame_ms_median,
        opt(c.tre_mean_mm),
        opt(c.tre_rigid_mean_mm),
        opt(check.last_frame_tre_mm),
        opt(check.last_frame_tre_rigid_mm),
        opt(check.last_frame_marker_displacement_mm)
    );
    if !check.log.is_empty() {
        let _ = write!(h, "<pre>{}</pre>", esc(&check.log.join("\n")));
    }
    let _ = write!(h, "<h2>Settings</h2><pre>{}</pre></body></html>", esc(&serde_json::to_string_pretty(s).unwrap_or_default()));
    h
}

/// Per accepted sample: mean and max displacement, from the dataset's manifest.
fn dataset_values(_patient: &Patient, grid_npz: &Path) -> (Vec<f64>, Vec<f64>) {
    let dir = grid_npz.parent().unwrap_or(Path::new("."));
    match umesh_core::dataset::Manifest::read(dir) {
        Ok(m) => m.accepted().map(|s| (s.mean_displacement_mm, s.max_displacement_mm)).unzip(),
        Err(_) => (Vec::new(), Vec::new()),
    }
}
