//! Benchmark results as files and the page made from them: every `umesh bench ... --json` (and
//! `umesh prepare ... --json`) result carries the command that measured it, the machine, the date
//! and a one-line summary; `umesh bench page` renders a folder of such files as
//! `docs/BENCHMARKS.md`, so each figure the docs quote has one source.

use anyhow::{Context, Result, bail};
use serde_json::{Value, json};
use std::path::Path;

/// One row of the page: what was measured, the figure, and what it compares with.
pub struct Row {
    pub what: String,
    pub figure: String,
    pub reference: String,
}

/// `value` with `run` (the command, machine, date and program version) and `summary` (the rows
/// the page shows) added.
pub fn stamped(kind: &str, mut value: Value) -> Value {
    let rows = summary(kind, &value);
    if let Value::Object(m) = &mut value {
        m.insert(
            "run".into(),
            json!({
                "kind": kind,
                "command": command_line(),
                "date": today_utc(),
                "machine": machine(),
                "version": env!("CARGO_PKG_VERSION"),
            }),
        );
        m.insert(
            "summary".into(),
            rows.iter().map(|r| json!({ "what": r.what, "figure": r.figure, "reference": r.reference })).collect(),
        );
    }
    value
}

/// The command as typed, the program named `umesh` whatever its path.
fn command_line() -> String {
    let quote = |a: String| if a.contains([' ', '"', '\'']) { format!("'{a}'") } else { a };
    std::iter::once("umesh".to_string()).chain(std::env::args().skip(1).map(quote)).collect::<Vec<_>>().join(" ")
}

/// Today's date (UTC) as YYYY-MM-DD, from the days since 1970 (Hinnant's civil calendar).
fn today_utc() -> String {
    let secs = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs());
    civil_date(secs / 86_400)
}

fn civil_date(days: u64) -> String {
    let z = days as i64 + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!("{year:04}-{month:02}-{day:02}")
}

/// The processor, its cores and the memory, from /proc where it exists.
fn machine() -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|m| m.replace("(R)", "").replace("(TM)", "").trim().to_string())
        })
        .unwrap_or_else(|| std::env::consts::ARCH.to_string());
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let memory = std::fs::read_to_string("/proc/meminfo").ok().and_then(|s| {
        let kb: f64 = s.lines().find(|l| l.starts_with("MemTotal:"))?.split_whitespace().nth(1)?.parse().ok()?;
        Some(format!(", {:.0} GiB", kb / (1024.0 * 1024.0)))
    });
    format!("{cpu}, {cores} cores{}", memory.unwrap_or_default())
}

fn f(v: &Value, key: &str) -> f64 {
    v[key].as_f64().unwrap_or(f64::NAN)
}

/// The range of `values` as "a-b" (or "a" when they agree at this precision).
fn range(values: &[f64], decimals: usize) -> String {
    let lo = values.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let (a, b) = (format!("{lo:.decimals$}"), format!("{hi:.decimals$}"));
    if values.is_empty() {
        "none".into()
    } else if a == b {
        a
    } else {
        format!("{a}-{b}")
    }
}

/// "the patient ct" for a patient folder's model, else "ORGAN, model MODEL" (the bundled phantom
/// and model by name).
fn organ_and_model(organ: &str, model: &str) -> String {
    let model_path = Path::new(model);
    // The bundled organ's model is never a patient's (its relative path `assets/model` sits
    // beside `assets/phantom.nii.gz`).
    if !organ.ends_with("(bundled)")
        && model_path.file_name().is_some_and(|n| n == "model")
        && let Some(patient) =
            model_path.parent().filter(|p| p.join("patient.json").exists() || organ.starts_with(&*p.to_string_lossy()))
    {
        return format!("the patient {}", file_name(&patient.display().to_string()));
    }
    let organ = if organ.ends_with("(bundled)") { "the bundled phantom".to_string() } else { file_name(organ) };
    format!(
        "{organ}, model {}",
        if model.ends_with("assets/model") { "the bundled one".to_string() } else { file_name(model) }
    )
}

fn file_name(path: &str) -> String {
    Path::new(path).file_name().map_or_else(|| path.to_string(), |n| n.to_string_lossy().into_owned())
}

/// The rows a result of `kind` shows on the page.
fn summary(kind: &str, v: &Value) -> Vec<Row> {
    let row = |what: String, figure: String, reference: &str| Row { what, figure, reference: reference.to_string() };
    match kind {
        "grid" => vec![row(
            format!("grid of a 512 x 512 x 110 CT label volume ({} cells, {} nodes)", v["cells"], v["nodes"]),
            format!("{:.0} ms", f(v, "grid_ms")),
            "target: under 2 s",
        )],
        "fe" => vec![row(
            format!("SVK solve of the phantom ({} nodes, {} forces)", v["nodes"], v["forces"]),
            format!(
                "{:.0} ms median of {} load cases ({:.0} Newton iterations)",
                f(v, "svk_solve_ms"),
                v["load_cases"],
                f(v, "svk_newton_iterations")
            ),
            "the paper's Pardiso: 1550 ms",
        )],
        "dataset" => vec![row(
            "training samples on the phantom, default mixture of loads".into(),
            format!(
                "{:.0} a minute, {} of {} accepted, achieved / target {:.2}",
                f(v, "samples_per_minute"),
                v["accepted"],
                v["samples"],
                f(v, "achieved_over_target_mean")
            ),
            &format!(
                "earlier versions' uncalibrated loads, same run: {:.0} a minute",
                f(&v["energy_scale_3mm"], "samples_per_minute")
            ),
        )],
        "sweep" => {
            let configs = v["configs"].as_array().cloned().unwrap_or_default();
            let all = configs.iter().filter(|c| c["accepted"] == c["samples"] && c["error"].is_null()).count();
            let accepted: u64 = configs.iter().filter_map(|c| c["accepted"].as_u64()).sum();
            let samples: u64 = configs.iter().filter_map(|c| c["samples"].as_u64()).sum();
            vec![row(
                format!(
                    "{} organ, attachment and camera set-ups (phantom scaled and squashed, real livers), {} samples each",
                    configs.len(),
                    v["samples_per_config"]
                ),
                format!("{all} of {} set-ups accept every sample ({accepted} of {samples} samples)", configs.len()),
                "each set-up at least 97 % accepted",
            )]
        }
        "net" => {
            let [x, y, z] = [0, 1, 2].map(|i| v["padded_shape"][i].as_u64().unwrap_or(0));
            vec![row(
                format!("network inference on a {x} x {y} x {z} grid"),
                match v.get("inference_ms_median_cpu_nodes").and_then(|n| n.as_f64()) {
                    // What registration runs: only the voxels whose values reach the grid's nodes.
                    Some(nodes) => format!(
                        "{nodes:.1} ms median at the organ's {} nodes ({:.1} ms for the whole grid)",
                        v["nodes"],
                        f(v, "inference_ms_median")
                    ),
                    None => format!("{:.1} ms median", f(v, "inference_ms_median")),
                },
                &format!(
                    "burn's own pass, same run: {:.1} ms; the paper: 3 ms on a GPU",
                    f(v, "inference_ms_median_cpu_burn")
                ),
            )]
        }
        "ui" => vec![row(
            format!("app frame while a training job runs ({} rendering)", v["backend"].as_str().unwrap_or("default")),
            format!(
                "{:.0} ms median, p95 {:.0} ms",
                f(&v["during_training_jobs_view"], "median_ms"),
                f(&v["during_training_jobs_view"], "p95_ms")
            ),
            "target: under 50 ms",
        )],
        "register" => {
            let rows = v["recordings"].as_array().cloned().unwrap_or_default();
            let col = |k: &str| rows.iter().filter_map(|r| r[k].as_f64()).collect::<Vec<_>>();
            let families: Vec<String> =
                rows.iter().filter_map(|r| r["family"].as_str().map(String::from)).fold(Vec::new(), |mut a, f| {
                    if !a.contains(&f) {
                        a.push(f);
                    }
                    a
                });
            // Families the model never trained on are benchmarked against the wider bar.
            let held_out: Vec<&str> = families
                .iter()
                .filter(|f| rows.iter().any(|r| r["family"].as_str() == Some(f.as_str()) && r["held_out"] == true))
                .map(String::as_str)
                .collect();
            let (bar, reference) = match held_out.len() {
                0 => {
                    ("within 2.0 mm and 20 % of rigid", "each draw within 2.0 mm and 20 % of rigid; frame within 33 ms")
                }
                n if n == families.len() => (
                    "within 3.0 mm and 30 % of rigid",
                    "each draw of a family held out of training within 3.0 mm and 30 % of rigid; frame within 33 ms",
                ),
                _ => (
                    "within their bar",
                    "each draw within 2.0 mm and 20 % of rigid, 3.0 mm and 30 % when its family was held out of training; frame within 33 ms",
                ),
            };
            let held = if held_out.is_empty() {
                String::new()
            } else {
                format!(" (held out of training: {})", held_out.join(", "))
            };
            vec![row(
                format!(
                    "{} new draws on {}: {}{held}, SVK and Neo-Hookean truth, {} mm of motion asked, {} correction, overlay drawn",
                    rows.len(),
                    organ_and_model(v["organ"].as_str().unwrap_or(""), v["model"].as_str().unwrap_or("")),
                    families.join(", "),
                    v["motion_mm_asked"],
                    v["correction_form"].as_str().unwrap_or("")
                ),
                format!(
                    "{} {bar} ({} mm, {} % of rigid); frame {} ms median{}; network alone {} mm",
                    v["within_bar"].as_str().unwrap_or(""),
                    range(&col("corrected_mm"), 2),
                    range(&col("corrected_share_of_rigid").iter().map(|s| 100.0 * s).collect::<Vec<_>>(), 0),
                    range(&col("frame_ms_median"), 1),
                    // Results saved before the 95th percentile was kept have none.
                    match col("frame_ms_p95") {
                        p if p.is_empty() => String::new(),
                        p => format!(", {} ms 95th percentile", range(&p, 0)),
                    },
                    range(&col("network_mm"), 2)
                ),
                reference,
            )]
        }
        "prepare" => vec![row(
            format!(
                "a patient from a segmentation to a checked model, loads calibrated to {} mm",
                v["target_displacement_mm"]
            ),
            format!(
                "{:.1} min; {} of {} samples; validation TRE {:.2} mm at {:.2} mm of motion; {}",
                f(v, "job_seconds") / 60.0,
                v["accepted"],
                v["samples"],
                f(v, "val_tre_mean_mm"),
                f(v, "val_marker_displacement_mean_mm"),
                if v["verdict"]["ready"] == true { "verdict: ready" } else { "verdict: not ready" }
            ),
            "within the hour",
        )],
        _ => Vec::new(),
    }
}

/// The order kinds appear on the page: the pipeline's order.
const ORDER: [&str; 8] = ["grid", "fe", "dataset", "sweep", "prepare", "net", "register", "ui"];

fn cell(s: &str) -> String {
    s.replace('|', "\\|").replace('\n', " ")
}

/// The page for every result in `dir` (`*.json` with `run` and `summary`), then `dir/notes.md`
/// (figures measured by commands that write no result file, each with its command and date).
pub fn render(dir: &Path) -> Result<String> {
    let mut files: Vec<_> = std::fs::read_dir(dir)
        .with_context(|| format!("--results {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "json"))
        .collect();
    files.sort();
    let mut results = Vec::new();
    for path in files {
        let text = std::fs::read_to_string(&path).with_context(|| format!("{}", path.display()))?;
        let v: Value = serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?;
        let run = &v["run"];
        let Some(kind) = run["kind"].as_str() else {
            bail!(
                "{}: no \"run\" record (write it with `umesh bench ... --json` or `umesh prepare ... --json`)",
                path.display()
            );
        };
        let rank = ORDER.iter().position(|k| *k == kind).unwrap_or(ORDER.len());
        results.push((rank, path, v.clone()));
    }
    results.sort_by(|a, b| (a.0, &a.1).cmp(&(b.0, &b.1)));
    let mut page = String::from(
        "# Benchmarks\n\n\
         Generated by `umesh bench page --results docs/benchmarks --out docs/BENCHMARKS.md` from the\n\
         result files in [benchmarks/](benchmarks/), each written by the command in its row with\n\
         `--json`. To measure again, run the command on your machine; to update this page, save the\n\
         result there and regenerate. How the figures changed over time is in\n\
         [CHANGELOG.md](../CHANGELOG.md).\n\n\
         | what | figure | compared with | command | machine, date |\n|---|---|---|---|---|\n",
    );
    for (_, path, v) in &results {
        let run = &v["run"];
        for r in v["summary"].as_array().into_iter().flatten() {
            page += &format!(
                "| {} | {} | {} | `{}` ([result]({})) | {}, {} |\n",
                cell(r["what"].as_str().unwrap_or("")),
                cell(r["figure"].as_str().unwrap_or("")),
                cell(r["reference"].as_str().unwrap_or("")),
                cell(run["command"].as_str().unwrap_or("")),
                cell(&format!("benchmarks/{}", file_name(&path.display().to_string()))),
                cell(run["machine"].as_str().unwrap_or("")),
                run["date"].as_str().unwrap_or("")
            );
        }
    }
    let notes = dir.join("notes.md");
    if notes.exists() {
        let text = std::fs::read_to_string(&notes).with_context(|| format!("{}", notes.display()))?;
        page += "\n";
        page += text.trim_end();
        page += "\n";
    }
    Ok(page)
}

/// `umesh bench page`: write the page (atomically), or with `check` say whether it is current.
pub fn run(dir: &Path, out: &Path, check: bool) -> Result<()> {
    let page = render(dir)?;
    if check {
        let old = std::fs::read_to_string(out).with_context(|| format!("--out {}", out.display()))?;
        if old != page {
            bail!(
                "{} is not the page the results in {} make: regenerate it with `umesh bench page --results {} --out {}`",
                out.display(),
                dir.display(),
                dir.display(),
                out.display()
            );
        }
        return Ok(());
    }
    umesh_core::write_atomic(out, page.as_bytes()).with_context(|| format!("--out {}", out.display()))?;
    eprintln!("wrote {}", out.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    #[test]
    fn civil_dates_agree_with_the_calendar() {
        assert_eq!(super::civil_date(0), "1970-01-01");
        assert_eq!(super::civil_date(11_016), "2000-02-29");
        assert_eq!(super::civil_date(20_793), "2026-12-06");
    }

    /// A register result whose rows are families held out of training states them and the
    /// wider bar; with none held out, the bar is the trained families'.
    #[test]
    fn a_register_result_names_the_families_held_out_of_training_and_their_bar() {
        let result = |held_out: bool| {
            let draw = |family: &str, mm: f64| {
                serde_json::json!({ "family": family, "held_out": held_out, "corrected_mm": mm,
                    "corrected_share_of_rigid": mm / 12.0, "frame_ms_median": 30.0, "network_mm": 4.0 })
            };
            serde_json::json!({ "organ": "o.nii.gz", "model": "m", "motion_mm_asked": 12.0,
                "correction_form": "subspace", "within_bar": "2 / 2",
                "recordings": [draw("gravity", 1.0), draw("gravity", 2.5)] })
        };
        let held = &super::summary("register", &result(true))[0];
        assert!(held.what.contains("gravity (held out of training: gravity)"), "{}", held.what);
        assert!(held.figure.starts_with("2 / 2 within 3.0 mm and 30 % of rigid"), "{}", held.figure);
        assert!(held.reference.contains("held out of training within 3.0 mm and 30 %"), "{}", held.reference);
        let trained = &super::summary("register", &result(false))[0];
        assert!(!trained.what.contains("held out"), "{}", trained.what);
        assert!(trained.figure.starts_with("2 / 2 within 2.0 mm and 20 % of rigid"), "{}", trained.figure);
    }
}
