//! Self-contained HTML pages (inline SVG, no script, no external file): the element builder
//! and the charts (histograms, curves, the grid's slices). `patient::page` makes a patient's
//! `report.html` from them; the app's jobs view bins its histograms with `histogram_bins`.

mod html;

pub use html::{El, el, figure, p, table};
use std::path::Path;

const W: f64 = 420.0;
const H: f64 = 220.0;
const L: f64 = 48.0;
const B: f64 = 34.0;

pub const STYLE: &str = "body{font-family:sans-serif;max-width:1100px;margin:1em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}
td:first-child,th:first-child{text-align:left}figure{display:inline-block;margin:.5em 1em .5em 0;vertical-align:top}
figcaption{font-size:12px;color:#555}pre{background:#f5f5f5;padding:.5em;overflow:auto;font-size:11px}
.ok{color:#2ca02c}.bad{color:#d62728}.problem{color:#d62728;font-weight:bold}";

pub fn nice(v: f64) -> String {
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
    el("text")
        .attr("x", format!("{x:.1}"))
        .attr("y", format!("{y:.1}"))
        .attr("font-size", size)
        .attr("text-anchor", anchor)
        .text(text)
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
    let pts: Vec<(f64, f64)> =
        series.iter().flat_map(|s| s.2.iter().map(|&(x, y)| (x, tf(y)))).filter(|p| p.1.is_finite()).collect();
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
            .child(
                el("polyline")
                    .attr("fill", "none")
                    .attr("stroke", color)
                    .attr("stroke-width", 2)
                    .attr("points", path.join(" ")),
            )
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
    let list = |name: &str| {
        npz.f64_with_shape(name, &[None])
            .map(|x| x.1.iter().map(|&v| v as usize).collect::<Vec<_>>())
            .unwrap_or_default()
    };
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
    let views = [
        ("anterior (x right, z up)", 0usize, 2usize, 1usize, false),
        ("right side (y anterior left, z up)", 1, 2, 0, true),
    ];
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
            picture = picture.child(
                el("circle").attr("cx", format!("{x:.1}")).attr("cy", format!("{y:.1}")).attr("r", r).attr("fill", c),
            );
        }
        out.push(figure(picture, title));
    }
    out
}
