//! The command line as a user drives it: JSON summaries, exit codes, errors naming files.

use std::path::PathBuf;
use std::process::Command;

use crate::support::{json, umesh};

fn tmp(name: &str) -> PathBuf {
    crate::support::scratch("cli", name)
}

#[test]
fn every_command_has_help() {
    for cmd in [
        vec!["--help"],
        vec!["demo", "--help"],
        vec!["phantom", "--help"],
        vec!["grid", "--help"],
        vec!["surface", "--help"],
        vec!["simulate", "--help"],
        vec!["bench", "--help"],
        vec!["rgbd", "synth", "--help"],
        vec!["rgbd", "serve", "--help"],
        vec!["register", "--help"],
        vec!["choose-correction", "--help"],
        vec!["screenshot", "--help"],
        vec!["gui", "--help"],
    ] {
        let (ok, out, _) = umesh(&cmd);
        assert!(ok && out.contains("Usage"), "{cmd:?}");
    }
}

#[test]
fn grid_json_reports_the_documented_keys() {
    let out_file = tmp("grid.npz");
    let (ok, out, err) = umesh(&["grid", "--json", "--out", out_file.to_str().unwrap()]);
    assert!(ok, "{err}");
    let v = json(&out);
    for key in ["cells", "nodes", "boundary_cells", "grid_volume_mm3", "segmentation_volume_mm3", "padded_shape"] {
        assert!(v.get(key).is_some(), "missing {key}: {v}");
    }
    let seg = v["segmentation_volume_mm3"].as_f64().unwrap();
    let grid = v["grid_volume_mm3"].as_f64().unwrap();
    assert!((grid - seg).abs() / seg < 0.01);
    let p: Vec<u64> = serde_json::from_value(v["padded_shape"].clone()).unwrap();
    assert!(p.iter().all(|d| d % 8 == 0));
    assert!(out_file.exists() && out_file.with_extension("vtu").exists());
    let vtu = std::fs::read_to_string(out_file.with_extension("vtu")).unwrap();
    assert!(vtu.contains("UnstructuredGrid") && vtu.contains("volume_fraction"));
}

#[test]
fn the_bundled_phantom_and_its_file_given_as_a_path_are_the_same_organ_and_grid() {
    let file = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("assets/phantom.nii.gz");
    let (ok, bundled, err) = umesh(&["grid", "--json"]);
    assert!(ok, "{err}");
    let (ok, given, err) = umesh(&["grid", file.to_str().unwrap(), "--json"]);
    assert!(ok, "{err}");
    let (bundled, given) = (json(&bundled), json(&given));
    // The vein and tumours the liver encloses are part of the organ either way.
    assert_eq!(bundled["organ_labels"], serde_json::json!([1, 3, 4, 5, 6]), "{bundled}");
    for key in ["organ_labels", "cells", "nodes", "grid_hash"] {
        assert_eq!(bundled[key], given[key], "{key}: bundled {bundled}, given {given}");
    }
}

#[test]
fn bad_inputs_fail_with_one_clear_error_and_a_nonzero_exit() {
    let (ok, _, err) = umesh(&["grid", "/nonexistent/seg.nii.gz"]);
    assert!(!ok && err.contains("/nonexistent/seg.nii.gz"), "{err}");
    let corrupt = tmp("corrupt.nii.gz");
    std::fs::write(&corrupt, b"\x1f\x8b\x08\x00garbage").unwrap();
    let (ok, _, err) = umesh(&["grid", corrupt.to_str().unwrap()]);
    assert!(!ok && err.contains("corrupt.nii.gz"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    let (ok, _, err) = umesh(&["grid", "--organ-label", "99"]);
    assert!(!ok && err.contains("label 99"), "{err}");
    let (ok, _, err) = umesh(&["grid", "--cell-size-mm", "0"]);
    assert!(!ok && err.contains("cell size"), "{err}");
    let open = tmp("open.obj");
    std::fs::write(&open, "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n").unwrap();
    let (ok, _, err) = umesh(&["grid", open.to_str().unwrap()]);
    assert!(!ok && err.contains("open.obj") && err.contains("not closed"), "{err}");
    let forces = tmp("forces.json");
    std::fs::write(&forces, "{not json").unwrap();
    let (ok, _, err) = umesh(&["simulate", "--forces", forces.to_str().unwrap()]);
    assert!(!ok && err.contains("forces.json"), "{err}");
    let (ok, _, err) = umesh(&["simulate", "--material", "rubber"]);
    assert!(!ok && err.contains("rubber"), "{err}");
    // A force 1 m away from the organ: refused, not moved onto the grid's edge.
    std::fs::write(&forces, r#"[{"point_mm": [1000, 0, 0], "force_n": [0, 0, -0.1]}]"#).unwrap();
    let (ok, _, err) =
        umesh(&["simulate", "--forces", forces.to_str().unwrap(), "--out", tmp("far-force").to_str().unwrap()]);
    assert!(!ok && err.contains("outside the organ"), "{err}");
    // Training's schedule and budget, refused before the dataset is read.
    let (ok, _, err) = umesh(&["train", "--dataset", "/nonexistent/ds", "--time-budget-min", "nan"]);
    assert!(!ok && err.contains("--time-budget-min") && !err.contains("/nonexistent/ds"), "{err}");
    let (ok, _, err) = umesh(&["train", "--dataset", "/nonexistent/ds", "--lr-schedule", "step"]);
    assert!(!ok && err.contains("--lr-schedule") && err.contains("cosine"), "{err}");
}

#[test]
fn simulate_writes_results_and_an_exported_problem_solves_to_the_same_answer() {
    let dir = tmp("sim");
    let problem = tmp("problem.npz");
    let forces = tmp("f.json");
    std::fs::write(
        &forces,
        r#"[{"point_mm": [30, 60, 10], "force_n": [0, -0.05, 0]}, {"point_mm": [-40, 50, 20], "force_n": [0.01, -0.03, 0]}]"#,
    )
    .unwrap();
    let (ok, out, err) = umesh(&[
        "simulate",
        "--json",
        "--forces",
        forces.to_str().unwrap(),
        "--out",
        dir.to_str().unwrap(),
        "--export-problem",
        problem.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let v = json(&out);
    for key in ["converged", "newton_iterations", "max_displacement_mm", "solve_ms"] {
        assert!(v.get(key).is_some(), "missing {key}: {v}");
    }
    assert_eq!(v["converged"], true);
    let max = v["max_displacement_mm"].as_f64().unwrap();
    assert!(max > 0.1 && max < 100.0, "{max}");
    for f in ["displacement.npz", "result.vtu", "organ_deformed.obj", "history.json", "tumour_1_deformed.obj"] {
        assert!(dir.join(f).exists(), "{f}");
    }
    let dir2 = tmp("sim2");
    let (ok, out2, err) =
        umesh(&["simulate", "--json", "--problem", problem.to_str().unwrap(), "--out", dir2.to_str().unwrap()]);
    assert!(ok, "{err}");
    let v2 = json(&out2);
    let max2 = v2["max_displacement_mm"].as_f64().unwrap();
    assert!((max - max2).abs() < 1e-6 * max, "{max} vs {max2}");
    let a = umesh_npz(&dir.join("displacement.npz"));
    let b = umesh_npz(&dir2.join("displacement.npz"));
    assert_eq!(a.len(), b.len());
    let diff = a.iter().zip(&b).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max);
    assert!(diff < 1e-6, "{diff}");
}

/// The displacement array of an NPZ, read by hand (a zip of one .npy) to stay independent.
fn umesh_npz(path: &std::path::Path) -> Vec<f64> {
    let bytes = std::fs::read(path).unwrap();
    let key = b"displacement_mm.npy";
    let start = bytes.windows(key.len()).position(|w| w == key).unwrap() + key.len();
    let npy = &bytes[start..];
    let hlen = u16::from_le_bytes([npy[8], npy[9]]) as usize;
    let header = std::str::from_utf8(&npy[10..10 + hlen]).unwrap();
    assert!(header.contains("'<f8'"));
    let shape = &header[header.find("'shape': (").unwrap() + 10..];
    let n: usize = shape.split(',').next().unwrap().trim().parse().unwrap();
    npy[10 + hlen..10 + hlen + n * 24].chunks_exact(8).map(|c| f64::from_le_bytes(c.try_into().unwrap())).collect()
}

/// `simulate --random-forces 5 --target-displacement-mm 8` moved the phantom by 110 mm on
/// average (linear) or inverted it after minutes (SVK): the forces were scaled by energy, not by
/// a solve. They are now spread and calibrated as dataset samples are. The linear mean over all
/// nodes is the target times the free fraction (1e-6 relative); SVK's within 25 %.
#[test]
fn simulate_with_a_few_random_forces_moves_the_organ_by_the_asked_displacement() {
    for m in ["linear", "svk"] {
        let out_dir = tmp(&format!("few-forces-{m}"));
        let (ok, out, err) = umesh(&[
            "simulate",
            "--json",
            "--method",
            m,
            "--random-forces",
            "3",
            "--target-displacement-mm",
            "6",
            "--out",
            out_dir.to_str().unwrap(),
        ]);
        assert!(ok, "{m}: {err}");
        let v = json(&out);
        assert_eq!(v["converged"], true, "{v}");
        let (nodes, fixed) = (v["nodes"].as_f64().unwrap(), v["fixed_nodes"].as_f64().unwrap());
        let expected = 6.0 * (nodes - fixed) / nodes;
        let mean = v["mean_displacement_mm"].as_f64().unwrap();
        let tolerance = if m == "linear" { 1e-6 * expected } else { 0.25 * expected };
        assert!((mean - expected).abs() <= tolerance, "{m}: mean {mean} mm, expected {expected} mm");
    }
    let (ok, _, err) = umesh(&[
        "simulate",
        "--random-forces",
        "3",
        "--target-displacement-mm=-1",
        "--out",
        tmp("few-bad").to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("--random-forces") && err.contains("target displacement"), "{err}");
}

#[test]
fn linear_and_corotational_methods_run_and_phantom_and_surfaces_are_written() {
    for m in ["linear", "corotational"] {
        let (ok, out, err) = umesh(&["simulate", "--json", "--method", m, "--out", tmp(m).to_str().unwrap()]);
        assert!(ok, "{m}: {err}");
        assert_eq!(json(&out)["converged"], true);
    }
    let p = tmp("ph.nii.gz");
    let (ok, out, err) = umesh(&["phantom", "--json", "--spacing-mm", "4", "--out", p.to_str().unwrap()]);
    assert!(ok, "{err}");
    assert!(json(&out)["labels"]["liver"]["volume_mm3"].as_f64().unwrap() > 1e6);
    let (ok, out, err) = umesh(&[
        "surface",
        "--json",
        p.to_str().unwrap(),
        "--organ-label",
        "1,3,4,5,6",
        "--structure-label",
        "4",
        "--format",
        "stl",
        "--out",
        tmp("surf").to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let v = json(&out);
    for s in v["surfaces"].as_array().unwrap() {
        assert_eq!(s["watertight"], true, "{s}");
    }
}

fn dataset_args<'a>(out: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
    let mut v = vec![
        "dataset",
        "generate",
        "--samples",
        "6",
        "--seed",
        "5",
        "--shard-size",
        "1",
        "--cell-size-mm",
        "14",
        "--probes",
        "20",
        "--out",
        out,
    ];
    v.extend_from_slice(extra);
    v
}

#[test]
fn dataset_killed_midway_and_resumed_equals_an_uninterrupted_run() {
    let full = tmp("ds-full");
    let _ = std::fs::remove_dir_all(&full);
    let (ok, out, err) = umesh(&dataset_args(full.to_str().unwrap(), &["--json"]));
    assert!(ok, "{err}");
    let v = json(&out);
    assert_eq!(v["complete"], true);

    let killed = tmp("ds-killed");
    let _ = std::fs::remove_dir_all(&killed);
    let mut child = Command::new(env!("CARGO_BIN_EXE_umesh"))
        .args(dataset_args(killed.to_str().unwrap(), &[]))
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    // Kill as soon as the first shard is on disk (or after a time limit).
    let start = std::time::Instant::now();
    while !killed.join("shard_000000.npz").exists()
        && !killed.join("shard_000001.npz").exists()
        && start.elapsed().as_secs() < 120
    {
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    child.kill().unwrap();
    let _ = child.wait();
    let shards_before = std::fs::read_dir(&killed)
        .unwrap()
        .filter(|e| e.as_ref().unwrap().file_name().to_string_lossy().starts_with("shard_"))
        .count();
    assert!(shards_before < 6, "the run finished before it could be killed");
    let (ok, out, err) = umesh(&dataset_args(killed.to_str().unwrap(), &["--json"]));
    assert!(ok, "{err}");
    let v = json(&out);
    assert_eq!(v["complete"], true);
    assert!(v["samples_reused"].as_u64().unwrap() >= (shards_before as u64), "{v}");
    for k in 0..6 {
        let name = format!("shard_{k:06}.npz");
        assert_eq!(std::fs::read(full.join(&name)).unwrap(), std::fs::read(killed.join(&name)).unwrap(), "{name}");
    }
    // No temporary files are left behind.
    assert!(std::fs::read_dir(&killed).unwrap().all(|e| !e.unwrap().file_name().to_string_lossy().ends_with(".tmp")));
    // Stats read the result.
    let (ok, out, err) = umesh(&["dataset", "stats", "--json", killed.to_str().unwrap()]);
    assert!(ok, "{err}");
    let s = json(&out);
    assert_eq!(s["samples"], 6);
    assert!(s["max_displacement_mm"]["median"].as_f64().unwrap() > 0.0);
}

#[test]
fn numpy_loads_the_grid_and_dataset_files() {
    let has_numpy = Command::new("python3").args(["-c", "import numpy"]).status().map(|s| s.success()).unwrap_or(false);
    if !has_numpy {
        assert!(std::env::var_os("CI").is_none(), "numpy is missing in CI: scripts/setup.sh should have installed it");
        eprintln!("SKIPPED: python3 with numpy not found; the NPZ interop check did not run");
        return;
    }
    let dir = tmp("ds-numpy");
    let _ = std::fs::remove_dir_all(&dir);
    let (ok, _, err) = umesh(&[
        "dataset",
        "generate",
        "--samples",
        "2",
        "--shard-size",
        "2",
        "--cell-size-mm",
        "14",
        "--probes",
        "10",
        "--out",
        dir.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let script = r#"
import json, sys, numpy as np
d = sys.argv[1]
m = json.load(open(d + "/manifest.json"))
g = np.load(d + "/grid.npz")
s = np.load(d + "/shard_000000.npz")
X, Y, Z = m["padded_shape"]
a = int(s["accepted"].sum())
assert s["u_v"].shape == (a, 3, X, Y, Z) and s["u_v"].dtype == np.float32, s["u_v"].shape
assert s["u_s"].shape == (a, 3, X, Y, Z)
assert g["nodes"].shape == (m["nodes"], 3) and g["hexes"].shape[1] == 8
assert g["visible_mask"].shape == (X, Y, Z) and g["visible_mask"].sum() == m["visible_nodes"]
assert np.all(s["u_s"][:, :, g["visible_mask"] == 0] == 0)
print("ok", a)
"#;
    let out = Command::new("python3").args(["-c", script, dir.to_str().unwrap()]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(String::from_utf8_lossy(&out.stdout).starts_with("ok"));
}

#[test]
fn register_on_a_synthetic_recording_reports_latency_and_tre_per_frame() {
    let rec = tmp("synth-rec");
    let _ = std::fs::remove_dir_all(&rec);
    // At 1.5 x the bundled model's target (13 mm mean nodal displacement), the markers move
    // 11 mm: the issue's 10 mm or more, within the dataset's range.
    let (ok, out, err) = umesh(&[
        "rgbd",
        "synth",
        "--frames",
        "4",
        "--noise-mm",
        "1",
        "--load-scale",
        "1.5",
        "--json",
        "--out",
        rec.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let s = json(&out);
    assert_eq!(s["frames"], 4);
    for f in [
        "intrinsics.json",
        "recording.json",
        "trajectory.log",
        "ground_truth.json",
        "depth/00003.png",
        "color/00003.png",
        "mask/00003.png",
    ] {
        assert!(rec.join(f).exists(), "{f}");
    }
    let reg = tmp("synth-reg");
    let (ok, out, err) =
        umesh(&["register", "--recording", rec.to_str().unwrap(), "--out", reg.to_str().unwrap(), "--json"]);
    assert!(ok, "{err}");
    let r = json(&out);
    assert_eq!(r["frames"], 4, "{r}");
    for k in ["frame_ms_median", "frame_ms_p95", "tre_mean_mm", "tre_max_mm"] {
        assert!(r[k].as_f64().is_some_and(|v| v.is_finite() && v >= 0.0), "{k}: {r}");
    }
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(reg.join("report.json")).unwrap()).unwrap();
    let frames = report["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 4);
    for f in frames {
        assert!(f["tre_mean_mm"].as_f64().is_some(), "TRE per frame: {f}");
    }
    // Threshold: the paper's ex vivo TRE (2.92 mm) on 1 mm depth noise, over the frames and at
    // the last one, where the recording moves the markers by the dataset's scale (measured with
    // the bundled model: 10.96 mm of motion, 0.53 mm TRE, 11.00 mm rigid only).
    let tre = r["tre_mean_mm"].as_f64().unwrap();
    eprintln!("synthetic registration: {r}");
    assert!(tre < 2.92, "TRE {tre} mm");
    let (last, rigid, moved) = (
        r["last_tre_mm"].as_f64().unwrap(),
        r["last_tre_rigid_mm"].as_f64().unwrap(),
        r["last_marker_displacement_mm"].as_f64().unwrap(),
    );
    assert!(moved >= 10.0, "the recording moves the markers {moved} mm (the issue's recordings: 10 or more)");
    assert!(last < 2.92 && last < 0.25 * rigid, "last frame: TRE {last} mm, rigid only {rigid} mm");
    assert!(reg.join("overlay/00003.png").exists());
    // Confidence without ground truth: the bundled model is calibrated (confidence.json), and
    // this recording, at the dataset's scale, stays within its range on every frame.
    assert_eq!(r["confidence_calibrated"], true, "{r}");
    assert_eq!(r["frames_with_warning"], 0, "{r}");
    for f in frames {
        let c = &f["confidence"];
        let p95 = c["residual_p95_mm"].as_f64().unwrap();
        assert!(p95.is_finite() && p95 > 0.0 && p95 < 5.0, "residual p95 {p95} mm: {c}");
    }
    // The tracking correction on the same recording: the same bar (measured: 0.44 mm against
    // the default's 0.53), and each frame reports how far its correction moved the prediction.
    let reg_t = tmp("synth-reg-tracking");
    let (ok, out, err) = umesh(&[
        "register",
        "--recording",
        rec.to_str().unwrap(),
        "--out",
        reg_t.to_str().unwrap(),
        "--no-overlay",
        "--correction-form",
        "tracking",
        "--json",
    ]);
    assert!(ok, "{err}");
    let t = json(&out);
    let last_t = t["last_tre_mm"].as_f64().unwrap();
    eprintln!("tracking correction: {t}");
    assert!(last_t < 2.92 && last_t < 0.25 * rigid, "tracking: last frame TRE {last_t} mm, rigid only {rigid} mm");
    let report_t: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(reg_t.join("report.json")).unwrap()).unwrap();
    let moved = |f: &serde_json::Value| f["correction"]["moved_rms_mm"].as_f64().unwrap();
    let last_frame = |r: &serde_json::Value| r["frames"].as_array().unwrap().last().unwrap().clone();
    assert!(moved(&last_frame(&report_t)) > 0.0 && moved(&last_frame(&report)) > 0.0, "{t}");
    assert_eq!(t["correction_form"], "tracking", "{t}");
    assert_eq!(r["correction_form"], "subspace", "the bundled model has no choice: {r}");
    // The choice on this recording, kept in a copy of the model: the rule (tracking at 75 % of
    // the subspace's late TRE or less) applied to the figures it reports, and `register`
    // follows it unless told otherwise.
    let model = tmp("choice-model");
    let _ = std::fs::remove_dir_all(&model);
    std::fs::create_dir_all(&model).unwrap();
    for e in std::fs::read_dir(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("assets/model")).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), model.join(e.file_name())).unwrap();
    }
    let (ok, out, err) = umesh(&[
        "choose-correction",
        "--model",
        model.to_str().unwrap(),
        "--recording",
        rec.to_str().unwrap(),
        "--json",
    ]);
    assert!(ok, "{err}");
    let c = json(&out);
    // Each form measured; the choice is the rule's (tested in core) within the default budget.
    let choice: umesh_core::register::correction::CorrectionChoice = serde_json::from_value(c.clone()).unwrap();
    let want = choice.choose(Some(umesh_core::register::correction::DEFAULT_FRAME_BUDGET_MS)).0.name();
    assert_eq!(c["form"], want, "{c}");
    assert!(model.join("correction.json").is_file());
    let reg_c = tmp("synth-reg-chosen");
    let args = [
        "register",
        "--model",
        model.to_str().unwrap(),
        "--recording",
        rec.to_str().unwrap(),
        "--out",
        reg_c.to_str().unwrap(),
        "--no-overlay",
        "--json",
    ];
    let (ok, out, err) = umesh(&args);
    assert!(ok, "{err}");
    assert_eq!(json(&out)["correction_form"], want, "{err}");
    assert!(err.contains("correction: ") && err.contains("on the check recording"), "{err}");
    assert!(
        json(&out)["correction_reason"]
            .as_str()
            .is_some_and(|r| r.contains("within 33 ms") || r.contains("no form met")),
        "{out}"
    );
    // No frame budget: the most accurate form whatever its time; a budget that is no time is refused.
    let mut unlimited = args.to_vec();
    unlimited.extend(["--frame-budget-ms", "0"]);
    let (ok, out, err) = umesh(&unlimited);
    assert!(ok, "{err}");
    assert_eq!(json(&out)["correction_form"], choice.choose(None).0.name(), "{err}");
    for bad in ["-1", "NaN", "1e300"] {
        let opt = format!("--frame-budget-ms={bad}");
        let mut a = args.to_vec();
        a.push(&opt);
        let (ok, _, err) = umesh(&a);
        assert!(!ok && err.contains("--frame-budget-ms"), "{bad}: {err}");
    }
    // A damaged choice: one error naming the file, nothing registered.
    std::fs::write(model.join("correction.json"), "{\"form\": 3").unwrap();
    let (ok, _, err) = umesh(&args);
    assert!(!ok && err.contains("correction.json") && err.contains("not a correction choice"), "{err}");
    // A recording without its truth cannot choose.
    let (ok, _, err) =
        umesh(&["choose-correction", "--model", model.to_str().unwrap(), "--recording", model.to_str().unwrap()]);
    assert!(!ok && err.contains("no ground_truth.json"), "{err}");
    // A recording without intrinsics: one clear error naming the folder.
    std::fs::remove_file(rec.join("intrinsics.json")).unwrap();
    let (ok, _, err) = umesh(&["register", "--recording", rec.to_str().unwrap(), "--out", reg.to_str().unwrap()]);
    assert!(!ok && err.contains("no intrinsics") && err.contains("synth-rec"), "{err}");
}

/// `register --compare-fe` wrote the FE overlays into the input recording's folder (a shadowed
/// name): they belong in --out, and the recording is read, never written.
#[test]
fn register_compare_fe_writes_its_overlays_into_out_and_leaves_the_recording_as_it_was() {
    let rec = tmp("fe-rec");
    let _ = std::fs::remove_dir_all(&rec);
    let (ok, _, err) = umesh(&["rgbd", "synth", "--frames", "2", "--out", rec.to_str().unwrap()]);
    assert!(ok, "{err}");
    let listing = |d: &std::path::Path| {
        let mut v: Vec<String> = walk(d).iter().map(|p| p.strip_prefix(d).unwrap().display().to_string()).collect();
        v.sort();
        v
    };
    let before = listing(&rec);
    let reg = tmp("fe-reg");
    let (ok, out, err) = umesh(&[
        "register",
        "--recording",
        rec.to_str().unwrap(),
        "--compare-fe",
        "--json",
        "--out",
        reg.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    assert!(json(&out)["fe"].is_object(), "{out}");
    assert_eq!(listing(&rec), before, "the recording's folder changed");
    assert!(reg.join("overlay_fe/00001.png").exists() && reg.join("overlay/00001.png").exists());
}

/// Every file under a folder.
fn walk(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

#[test]
fn a_tracked_pose_is_kept_on_a_sequence_that_starts_deformed_and_sparse_clouds_are_used_whole() {
    // A tracked, moving camera; the instrument already pushing at the first frame (70 % of the
    // final load); each frame a cloud of 500 organ points, no depth image. Measured: 5.8 mm of
    // marker motion at the first frame, 9.9 at the last; tracked: the refinement stops at its
    // 1.5 mm bound, last-frame TRE 1.29 mm against 8.89 rigid (15 %); icp-first slides the
    // organ by 10.5 mm.
    let rec = tmp("tracked-clouds");
    let _ = std::fs::remove_dir_all(&rec);
    let r = rec.to_str().unwrap();
    let (ok, _, err) = umesh(&[
        "rgbd",
        "synth",
        "--frames",
        "6",
        "--first-load",
        "0.7",
        "--cloud-points",
        "500",
        "--camera-motion-mm",
        "20",
        "--camera-motion-deg",
        "5",
        "--loads",
        "instrument",
        "--load-scale",
        "2.6",
        "--seed",
        "1",
        "--out",
        r,
    ]);
    assert!(ok, "{err}");
    assert!(rec.join("points/00000.ply").is_file() && !rec.join("depth").exists());
    let truth: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(rec.join("ground_truth.json")).unwrap()).unwrap();
    let point = |v: &serde_json::Value| [0, 1, 2].map(|i| v[i].as_f64().unwrap());
    let rest: Vec<[f64; 3]> = truth["markers_rest_mm"].as_array().unwrap().iter().map(point).collect();
    let first: Vec<[f64; 3]> = truth["markers_mm"][0].as_array().unwrap().iter().map(point).collect();
    let motion0 =
        first.iter().zip(&rest).map(|(a, b)| (0..3).map(|i| (a[i] - b[i]).powi(2)).sum::<f64>().sqrt()).sum::<f64>()
            / rest.len() as f64;
    assert!(motion0 >= 5.0, "the first frame is deformed by {motion0} mm (5 mm or more wanted)");
    let register = |pose: &str| {
        let out = tmp(&format!("tracked-clouds-{pose}"));
        let (ok, stdout, err) = umesh(&[
            "register",
            "--recording",
            r,
            "--pose",
            pose,
            "--no-overlay",
            "--json",
            "--out",
            out.to_str().unwrap(),
        ]);
        assert!(ok, "{err}");
        let report: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
        (json(&stdout), report)
    };
    // No --pose: the recording's trajectory holds a pose for every frame, so it is followed.
    let (v, report) = register("auto");
    assert_eq!(v["pose"], "tracked", "{v}");
    assert!(v["pose_reason"].as_str().unwrap().contains("every frame"), "{v}");
    assert_eq!((v["frames"].as_u64(), v["skipped"].as_u64()), (Some(6), Some(0)), "every frame registered: {v}");
    for f in report["frames"].as_array().unwrap() {
        assert_eq!(f["observed_points"], 500, "the cloud is used whole: {}", f["observed_points"]);
    }
    let moved = v["pose_moved_max_mm"].as_f64().unwrap();
    assert!(moved < 2.0, "ICP moved the tracked pose by {moved} mm");
    let (last, rigid) = (v["last_tre_mm"].as_f64().unwrap(), v["last_tre_rigid_mm"].as_f64().unwrap());
    assert!(last <= 0.3 * rigid, "last frame: TRE {last} mm, rigid {rigid} mm");
    // The full first-frame ICP slides the organ further than the bounded refinement.
    let (v, _) = register("icp-first");
    assert!(v["pose_moved_max_mm"].as_f64().unwrap() > moved, "{v}");
    // The output folder is replaced whole or not at all: a run that registers no frame (the
    // organ outside the depth range) leaves the last run's folder as it was, stray file and
    // all; a run that succeeds replaces it, stray file gone.
    let out = tmp("tracked-clouds-auto");
    let before = std::fs::read(out.join("report.json")).unwrap();
    std::fs::write(out.join("stray.txt"), "an earlier run's file").unwrap();
    let o = out.to_str().unwrap();
    let (ok, _, err) =
        umesh(&["register", "--recording", r, "--depth-min-mm", "5000", "--depth-max-mm", "6000", "--out", o]);
    assert!(!ok && err.contains("no frame could be registered"), "{err}");
    assert_eq!(std::fs::read(out.join("report.json")).unwrap(), before);
    assert!(out.join("stray.txt").is_file());
    register("auto");
    assert!(!out.join("stray.txt").exists(), "a stale file survived the new run");
    let parent = out.parent().unwrap();
    let leftovers: Vec<_> = std::fs::read_dir(parent)
        .unwrap()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().contains("tracked-clouds-auto.staging"))
        .collect();
    assert!(leftovers.is_empty(), "staging folders left behind: {leftovers:?}");
    let (ok, _, err) =
        umesh(&["register", "--recording", r, "--pose", "gps", "--out", tmp("tracked-bad").to_str().unwrap()]);
    assert!(!ok && err.contains("--pose") && err.contains("tracked"), "{err}");
    // Absurd correction work: one error naming the option, before anything is built.
    // (1000 patches did not finish in 5 minutes; 100 updates of 1000 iterations neither.)
    for (flag, value) in [
        ("--doubted-updates", "500"),
        ("--doubted-carried-updates", "5"),
        ("--doubted-carried-updates", "0"),
        ("--doubted-carried-stop-mm", "NaN"),
        ("--doubted-carried-stop-mm", "60"),
        ("--correction-subspace", "5000"),
        ("--correction-subspace", "1000"),
        ("--correction-cg", "1000"),
        ("--doubted-coarsening", "9"),
        ("--doubted-coarsening", "0"),
    ] {
        let (ok, _, err) =
            umesh(&["register", "--recording", r, flag, value, "--out", tmp("tracked-bad").to_str().unwrap()]);
        assert!(!ok && err.contains(flag) && err.lines().count() == 1, "{flag} {value}: {err}");
    }
    // The doubted frames' correction asked for with the correction off: said, not ignored.
    let (ok, _, err) = umesh(&[
        "register",
        "--recording",
        r,
        "--correction-updates",
        "0",
        "--doubted-updates",
        "4",
        "--out",
        tmp("tracked-bad").to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("--doubted-updates") && err.lines().count() == 1, "{err}");
    // A shorter recording written over this one replaces it whole: no frame of the old one left.
    let (ok, _, err) = umesh(&["rgbd", "synth", "--frames", "2", "--cloud-points", "50", "--out", r]);
    assert!(ok, "{err}");
    assert!(rec.join("points/00001.ply").is_file() && !rec.join("points/00002.ply").exists(), "a stale frame survived");
}

#[test]
fn a_corrupt_model_is_refused_with_a_reason_and_never_reports_a_tre() {
    let rec = tmp("corrupt-model-rec");
    let _ = std::fs::remove_dir_all(&rec);
    let (ok, _, err) = umesh(&[
        "rgbd",
        "synth",
        "--frames",
        "2",
        "--width",
        "320",
        "--height",
        "240",
        "--focal-px",
        "262.5",
        "--out",
        rec.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let bundled = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("assets/model");
    let copy = |name: &str| {
        let d = tmp(name);
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        for e in std::fs::read_dir(&bundled).unwrap().flatten() {
            std::fs::copy(e.path(), d.join(e.file_name())).unwrap();
        }
        d
    };
    let register = |model: &PathBuf| {
        umesh(&[
            "register",
            "--model",
            model.to_str().unwrap(),
            "--recording",
            rec.to_str().unwrap(),
            "--no-overlay",
            "--json",
            "--out",
            tmp("corrupt-model-out").to_str().unwrap(),
        ])
    };
    // Absurd settings in model.json: refused on reading, naming the file and the value.
    for (key, path, value) in [
        ("band", "/settings/observation/band_mm", serde_json::json!(1e30)),
        ("scale", "/normalization/output_scale_mm", serde_json::json!(1e38)),
        // Each asked for hours or petabytes when the organ model was rebuilt.
        ("surface-step", "/dataset_config/surface_step", serde_json::json!(100000)),
        ("fixed-distance", "/dataset_config/fixed/distance_mm", serde_json::json!(1e308)),
    ] {
        let d = copy(&format!("corrupt-model-{key}"));
        let mut info: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(d.join("model.json")).unwrap()).unwrap();
        *info.pointer_mut(path).unwrap() = serde_json::json!(value);
        std::fs::write(d.join("model.json"), info.to_string()).unwrap();
        let (ok, out, err) = register(&d);
        assert!(!ok && out.is_empty() && err.contains("model.json"), "{key}: {err}");
    }
    // A confidence range no frame reaches (it would silence every warning: 1e308, 1000 mm, or
    // above the 20 mm a residual is measured to) or one of zero (measured on nothing):
    // refused, named.
    for (key, value) in
        [("residual_p95_mm", 1e308), ("residual_p95_mm", 1000.0), ("residual_mean_mm", 25.0), ("residual_p95_mm", 0.0)]
    {
        let d = copy("corrupt-model-confidence");
        let mut c: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(d.join("confidence.json")).unwrap()).unwrap();
        c[key] = serde_json::json!(value);
        std::fs::write(d.join("confidence.json"), c.to_string()).unwrap();
        let (ok, out, err) = register(&d);
        assert!(!ok && out.is_empty() && err.contains("confidence.json") && err.contains(key), "{key} {value}: {err}");
    }
    // NaN weights (a run of bytes overwritten in the middle of the weights file; through the
    // ReLU they gave finite, wrong predictions and a TRE) and huge finite ones: refused on
    // loading, naming the weights file, no TRE reported.
    for (key, byte) in [("nan", 0xFFu8), ("huge", 0x7Eu8)] {
        let d = copy(&format!("corrupt-model-weights-{key}"));
        let mut w = std::fs::read(d.join("model.safetensors")).unwrap();
        let mid = w.len() / 2;
        w[mid..mid + 4096].fill(byte);
        std::fs::write(d.join("model.safetensors"), w).unwrap();
        let (ok, out, err) = register(&d);
        assert!(!ok && out.is_empty(), "{key}: {out}");
        assert!(err.contains("corrupt") && err.contains("model.safetensors"), "{key}: {err}");
    }
}

#[test]
fn surface_of_a_one_voxel_organ_is_refused_with_a_reason_not_written_empty() {
    let p = tmp("one-voxel.nii.gz");
    let mut data = vec![0.0f32; 512];
    data[4 + 8 * (4 + 8 * 4)] = 1.0;
    let vol = umesh_core::volume::Volume {
        dims: [8, 8, 8],
        data,
        world_from_voxel: nalgebra::Matrix4::identity(),
        label_names: Default::default(),
    };
    umesh_core::nifti_io::write_volume(&p, &vol, umesh_core::nifti_io::WriteType::U8).unwrap();
    let out = tmp("one-voxel-surfaces");
    let _ = std::fs::remove_dir_all(&out);
    let (ok, _, err) = umesh(&["surface", p.to_str().unwrap(), "--organ-label", "1", "--out", out.to_str().unwrap()]);
    assert!(!ok && err.contains("one-voxel.nii.gz") && err.contains("1 voxel"), "{err}");
    assert!(!out.join("organ.obj").exists());
}

#[test]
fn output_folders_are_replaced_whole_and_a_folder_umesh_did_not_write_is_never_emptied() {
    let ph = tmp("replace-ph.nii.gz");
    let (ok, _, err) = umesh(&["phantom", "--spacing-mm", "4", "--out", ph.to_str().unwrap()]);
    assert!(ok, "{err}");
    let ph = ph.to_str().unwrap();
    // surface: a second run leaves no file of the first (stale.obj) and carries the marker.
    let surf = tmp("replace-surf");
    let _ = std::fs::remove_dir_all(&surf);
    let (ok, _, err) = umesh(&["surface", ph, "--out", surf.to_str().unwrap()]);
    assert!(ok, "{err}");
    std::fs::write(surf.join("stale.obj"), "from an earlier run").unwrap();
    let (ok, _, err) = umesh(&["surface", ph, "--out", surf.to_str().unwrap()]);
    assert!(ok, "{err}");
    assert!(surf.join("organ.obj").exists() && !surf.join("stale.obj").exists());
    assert!(surf.join(umesh_core::OUTPUT_MARKER).exists());
    // A run that fails half-way (label 99 after the organ) leaves the last folder byte for byte.
    let before = std::fs::read(surf.join("organ.obj")).unwrap();
    std::fs::write(surf.join("organ.obj"), b"last run's mesh").unwrap();
    let (ok, _, err) = umesh(&["surface", ph, "--label", "1,99", "--out", surf.to_str().unwrap()]);
    assert!(!ok && err.contains("99"), "{err}");
    assert_eq!(std::fs::read(surf.join("organ.obj")).unwrap(), b"last run's mesh");
    assert!(!before.is_empty());
    let parent = surf.parent().unwrap();
    let leftovers: Vec<_> = std::fs::read_dir(parent)
        .unwrap()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().starts_with(".replace-surf."))
        .collect();
    assert!(leftovers.is_empty(), "staging folders left: {leftovers:?}");
    // simulate into a folder of the user's own files: refused before any work, files intact.
    let mine = tmp("replace-mine");
    std::fs::create_dir_all(&mine).unwrap();
    std::fs::write(mine.join("notes.txt"), "mine").unwrap();
    let (ok, _, err) = umesh(&["simulate", "--out", mine.to_str().unwrap()]);
    assert!(!ok && err.contains("replace-mine") && err.contains("did not write"), "{err}");
    assert_eq!(std::fs::read_to_string(mine.join("notes.txt")).unwrap(), "mine");
    let (ok, _, err) = umesh(&["surface", ph, "--out", mine.to_str().unwrap()]);
    assert!(!ok && err.contains("did not write"), "{err}");
    // simulate into its own earlier output: replaced, the stale file gone.
    let sim = tmp("replace-sim");
    let _ = std::fs::remove_dir_all(&sim);
    std::fs::create_dir_all(&sim).unwrap();
    std::fs::write(sim.join("displacement.npz"), "an earlier run").unwrap();
    std::fs::write(sim.join("tumour_9_deformed.obj"), "an earlier run").unwrap();
    let forces = tmp("replace-forces.json");
    std::fs::write(&forces, r#"[{"point_mm": [30, 60, 10], "force_n": [0, -0.05, 0]}]"#).unwrap();
    let (ok, _, err) = umesh(&["simulate", "--forces", forces.to_str().unwrap(), "--out", sim.to_str().unwrap()]);
    assert!(ok, "{err}");
    assert!(sim.join("result.vtu").exists() && !sim.join("tumour_9_deformed.obj").exists());
}

#[test]
fn a_recordings_load_the_organ_cannot_take_is_made_smaller_and_said_not_refused() {
    // The bundled phantom pressed by instrument seed 3 at 2.0 x the dataset's target (26 mm):
    // SVK collapses under it (refused before: "the recording's instrument load: an element
    // inverted"); at 0.7 of it the organ takes the load.
    let rec = tmp("too-large-load");
    let (ok, out, err) = umesh(&[
        "rgbd",
        "synth",
        "--frames",
        "2",
        "--loads",
        "instrument",
        "--load-scale",
        "2.0",
        "--seed",
        "3",
        "--json",
        "--out",
        rec.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let r = json(&out);
    assert_eq!(r["load_scale_asked"].as_f64(), Some(2.0), "{r}");
    let made = r["load_scale"].as_f64().unwrap();
    assert!((0.5 * 2.0 - 1e-9..2.0).contains(&made), "{r}");
    assert!(r["mean_marker_displacement_mm"].as_f64().unwrap() > 1.0, "{r}");
}

#[test]
fn confidence_warns_on_a_deformation_far_beyond_the_datasets_scale() {
    // Gravity at three times the dataset's target (made at 0.7 of it, the organ could not take
    // more): 21.4 mm of marker motion against the dataset's 5-15 mm (measured with the bundled
    // mixture model: last-frame TRE 8.4 mm, the points 8.3 mm from the predicted surface at the
    // 95th percentile against 3.1 mm allowed: 2.6 on the validation views registered within
    // 2 mm, plus 0.5).
    let rec = tmp("far-rec");
    let _ = std::fs::remove_dir_all(&rec);
    let (ok, _, err) = umesh(&[
        "rgbd",
        "synth",
        "--frames",
        "3",
        "--loads",
        "gravity",
        "--load-scale",
        "3",
        "--seed",
        "6",
        "--json",
        "--out",
        rec.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let reg = tmp("far-reg");
    let (ok, out, err) =
        umesh(&["register", "--recording", rec.to_str().unwrap(), "--out", reg.to_str().unwrap(), "--json"]);
    assert!(ok, "{err}");
    let r = json(&out);
    assert!(r["last_marker_displacement_mm"].as_f64().unwrap() > 20.0, "{r}");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(reg.join("report.json")).unwrap()).unwrap();
    let frames = report["frames"].as_array().unwrap();
    let (first, last) = (&frames[0]["confidence"], &frames[frames.len() - 1]["confidence"]);
    // The undeformed first frame is trusted, the far one is not, and says why.
    assert_eq!(first["warnings"].as_array().unwrap().len(), 0, "{first}");
    let w = last["warnings"].as_array().unwrap();
    assert!(!w.is_empty() && w.iter().any(|m| m.as_str().unwrap().contains("registered within 2.0 mm")), "{last}");
    assert!(r["frames_with_warning"].as_u64().unwrap() >= 1, "{r}");
}

fn shared_data() -> Option<PathBuf> {
    let d = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data");
    if d.is_dir() {
        Some(d)
    } else {
        eprintln!("SKIPPED: {} not found; the real-patient prepare checks did not run", d.display());
        None
    }
}

/// A short `prepare` (few samples, one epoch, a 3-frame check): the folder, the report and
/// the JSON summary.
fn short_prepare(seg: Option<&str>, out: &std::path::Path, extra: &[&str]) -> serde_json::Value {
    let mut args = vec!["prepare"];
    if let Some(s) = seg {
        args.push(s);
    }
    args.extend([
        "--samples",
        "10",
        "--shard-size",
        "5",
        "--epochs",
        "1",
        "--check-frames",
        "3",
        "--json",
        "--out",
        out.to_str().unwrap(),
    ]);
    args.extend(extra);
    let (ok, stdout, stderr) = umesh(&args);
    assert!(ok, "prepare failed: {stderr}");
    let v = json(&stdout);
    for f in [
        "patient.json",
        "segmentation.nii.gz",
        "dataset/manifest.json",
        "model/model.json",
        "eval.json",
        "check/register.json",
        "report.html",
    ] {
        assert!(out.join(f).is_file(), "{} missing", f);
    }
    let html = std::fs::read_to_string(out.join("report.html")).unwrap();
    for needle in ["<svg", "Dataset", "Training", "Registration check", "Fixed region"] {
        assert!(html.contains(needle), "report.html lacks {needle}");
    }
    assert!(!html.contains("http://") || !html.contains("src=\"http"), "report.html loads an external resource");
    v
}

/// `register --patient` on the patient's own check recording.
fn register_patient_check(patient: &std::path::Path, name: &str) -> (bool, String, String) {
    let rec = patient.join("check/recording");
    let reg = tmp(name);
    umesh(&[
        "register",
        "--patient",
        patient.to_str().unwrap(),
        "--recording",
        rec.to_str().unwrap(),
        "--no-overlay",
        "--json",
        "--out",
        reg.to_str().unwrap(),
    ])
}

#[test]
fn prepare_runs_every_stage_resumes_and_refuses_a_folder_of_another_patient() {
    let out = tmp("patient");
    let _ = std::fs::remove_dir_all(&out);
    let v = short_prepare(None, &out, &[]);
    assert_eq!(v["samples"], 10);
    assert!(v["accepted"].as_u64().unwrap() >= 9, "{v}");
    let ratio = v["achieved_over_target"]["mean"].as_f64().unwrap();
    assert!((0.75..=1.25).contains(&ratio), "achieved / target {ratio}");
    assert!(v["val_tre_mean_mm"].as_f64().unwrap().is_finite());
    assert!(v["check"]["summary"]["frames"].as_u64().unwrap() >= 2, "{v}");
    // The check registered its recording with the three correction forms and kept the choice
    // in the model folder.
    let form = v["check"]["correction"]["form"].as_str().unwrap_or_default().to_string();
    assert!(["subspace", "coarse-tracking", "tracking"].contains(&form.as_str()), "{v}");
    assert!(v["check"]["correction"]["coarse_tracking"]["frame_ms_median"].as_f64().is_some(), "{v}");
    let kept: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("model/correction.json")).unwrap()).unwrap();
    assert_eq!(kept["form"], form.as_str());
    // Run again: every stage was done, nothing is recomputed.
    let (ok, stdout, stderr) = umesh(&[
        "prepare",
        "--samples",
        "10",
        "--shard-size",
        "5",
        "--epochs",
        "1",
        "--check-frames",
        "3",
        "--json",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(ok, "{stderr}");
    let again = json(&stdout);
    assert!(again["seconds"].as_f64().unwrap() < 0.5 * v["seconds"].as_f64().unwrap() + 5.0, "{again}");
    assert!(again["dataset_samples_per_minute"].is_null(), "samples were recomputed: {again}");
    // Other settings in the same folder: refused, the folder left as it was.
    let before = std::fs::read(out.join("patient.json")).unwrap();
    let (ok, _, stderr) = umesh(&["prepare", "--samples", "12", "--epochs", "1", "--out", out.to_str().unwrap()]);
    assert!(!ok && stderr.contains("other settings") && stderr.contains("samples: 10 -> 12"), "{stderr}");
    assert_eq!(before, std::fs::read(out.join("patient.json")).unwrap());
    // The patient's model is trained only on the patient's own dataset: another dataset's
    // training into it is refused before any work, the model left as it was.
    let weights = std::fs::read(out.join("model/model.json")).unwrap();
    let other = tmp("patient-other-dataset");
    let (ok, _, stderr) =
        umesh(&["train", "--dataset", other.to_str().unwrap(), "--out", out.join("model").to_str().unwrap()]);
    assert!(!ok && stderr.contains("patient") && stderr.contains("its own dataset"), "{stderr}");
    assert_eq!(weights, std::fs::read(out.join("model/model.json")).unwrap());
    // The same voxels under other label names: another patient, refused naming the names.
    let mut renamed: serde_json::Value = serde_json::from_slice(&before).unwrap();
    renamed["structures"] = serde_json::json!(["renamed"]);
    std::fs::write(out.join("patient.json"), renamed.to_string()).unwrap();
    let (ok, _, stderr) = umesh(&[
        "prepare",
        "--samples",
        "10",
        "--shard-size",
        "5",
        "--epochs",
        "1",
        "--check-frames",
        "3",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!ok && stderr.contains("label names differ") && stderr.contains("renamed"), "{stderr}");
    std::fs::write(out.join("patient.json"), &before).unwrap();
    // A finished patient keeps its scan: the same job with one scan stores it, with another
    // one it is refused and the stored scan stays.
    let ct1 = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("assets/phantom.nii.gz");
    let vol =
        umesh_core::nifti_io::read_volume(&ct1, &umesh_core::nifti_io::ReadOptions { max_voxels: 1 << 30 }).unwrap();
    let ct2 = tmp("other-scan.nii.gz");
    umesh_core::nifti_io::write_volume(&ct2, &vol, umesh_core::nifti_io::WriteType::F32).unwrap();
    let with_ct = |ct: &PathBuf| {
        umesh(&[
            "prepare",
            "--samples",
            "10",
            "--shard-size",
            "5",
            "--epochs",
            "1",
            "--check-frames",
            "3",
            "--ct",
            ct.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
    };
    let (ok, _, stderr) = with_ct(&ct1);
    assert!(ok, "{stderr}");
    let (ok, _, stderr) = with_ct(&ct2);
    assert!(!ok && stderr.contains("another scan"), "{stderr}");
    assert_eq!(std::fs::read(out.join("ct.nii.gz")).unwrap(), std::fs::read(&ct1).unwrap());
    // The patient folder drives registration.
    let (ok, stdout, stderr) = register_patient_check(&out, "patient-reg");
    assert!(ok, "{stderr}");
    assert!(json(&stdout)["frames"].as_u64().unwrap() >= 2);
    // A structure renamed in patient.json would vanish from the overlay: refused, naming it.
    let before = std::fs::read(out.join("patient.json")).unwrap();
    let mut renamed: serde_json::Value = serde_json::from_slice(&before).unwrap();
    renamed["structures"] = serde_json::json!(["renamed"]);
    std::fs::write(out.join("patient.json"), renamed.to_string()).unwrap();
    let (ok, _, stderr) = register_patient_check(&out, "patient-reg-renamed");
    assert!(!ok && stderr.contains("renamed") && stderr.contains("not labels"), "{stderr}");
    std::fs::write(out.join("patient.json"), &before).unwrap();
    // Voxels edited in the stored segmentation: not what the model learnt, refused.
    let seg_path = out.join("segmentation.nii.gz");
    let seg_bytes = std::fs::read(&seg_path).unwrap();
    let mut seg = umesh_core::nifti_io::read_volume(&seg_path, &Default::default()).unwrap();
    let i = seg.data.iter().position(|&v| v != 0.0).unwrap();
    seg.data[i] = 0.0;
    umesh_core::nifti_io::write_volume(&seg_path, &seg, umesh_core::nifti_io::WriteType::I16).unwrap();
    let (ok, _, stderr) = register_patient_check(&out, "patient-reg-edited");
    assert!(!ok && stderr.contains("not the segmentation this patient was prepared from"), "{stderr}");
    std::fs::write(&seg_path, &seg_bytes).unwrap();
}

#[test]
fn a_patient_prepared_from_a_mesh_registers_with_its_own_model() {
    // A closed organ surface whose coordinates are not exact in float32 (the phantom's, moved
    // by a fraction of a millimetre): the segmentation saved in the patient folder must give
    // back the grid the model was trained on.
    let dir = tmp("mesh-organ");
    let _ = std::fs::remove_dir_all(&dir);
    let (ok, _, err) = umesh(&["surface", "--out", dir.to_str().unwrap(), "--step", "2"]);
    assert!(ok, "{err}");
    let obj = std::fs::read_to_string(dir.join("organ.obj")).unwrap();
    let moved: String = obj
        .lines()
        .map(|l| match l.strip_prefix("v ") {
            Some(v) => {
                let c: Vec<f64> = v.split_whitespace().map(|x| x.parse::<f64>().unwrap() + 0.123456789).collect();
                format!("v {:.9} {:.9} {:.9}\n", c[0], c[1], c[2])
            }
            None => format!("{l}\n"),
        })
        .collect();
    let mesh = dir.join("liver.obj");
    std::fs::write(&mesh, moved).unwrap();
    let out = tmp("mesh-patient");
    let _ = std::fs::remove_dir_all(&out);
    let v = short_prepare(Some(mesh.to_str().unwrap()), &out, &[]);
    assert!(v["accepted"].as_u64().unwrap() >= 8, "{v}");
    let (ok, stdout, stderr) = register_patient_check(&out, "mesh-patient-reg");
    assert!(ok, "the patient's own model refused: {stderr}");
    assert!(json(&stdout)["frames"].as_u64().unwrap() >= 2);
}

#[test]
fn a_check_recording_that_cannot_converge_ends_the_job_with_the_model_and_a_warning() {
    // 50 times the dataset's target (then 30 and 18): no load of the check converges. The
    // model is trained before; the job ends with it, and the JSON and report say why the check
    // is missing.
    let out = tmp("check-fails");
    let _ = std::fs::remove_dir_all(&out);
    let v = short_prepare(None, &out, &["--check-load-scale", "50"]);
    let w = v["check"]["warning"].as_str().unwrap_or_default();
    assert!(w.contains("could not be made") && w.contains("load scale 50.00"), "{v}");
    assert!(out.join("model/model.safetensors").is_file());
    let html = std::fs::read_to_string(out.join("report.html")).unwrap();
    assert!(html.contains("The check did not run"), "the report does not say the check is missing");
    let (ok, _, err) = umesh(&["prepare", "--check-load-scale", "0", "--out", tmp("check-bad").to_str().unwrap()]);
    assert!(!ok && err.contains("--check-load-scale"), "{err}");
}

#[test]
fn gui_refuses_a_folder_that_is_no_patient_before_opening_a_window() {
    let dir = tmp("not-a-patient");
    std::fs::create_dir_all(&dir).unwrap();
    let (ok, _, stderr) = umesh(&["gui", dir.to_str().unwrap()]);
    assert!(!ok, "exit 0 for a folder without patient.json");
    assert!(stderr.contains("patient.json") && stderr.contains(&dir.display().to_string()), "{stderr}");
}

#[test]
fn prepare_refuses_bad_input_before_writing_anything() {
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (vec!["--organ-label", "77"], "label 77"),
        (vec!["--fix-box", "9000,9000,9000,9001,9001,9001"], "holds no grid node"),
        (vec!["--fix-label", "42"], "--fix-label 42"),
        (vec!["--camera", "sideways"], "unknown camera view"),
        (vec!["--camera-from", "0,0,0", "--camera-to", "0,0,0"], "same point"),
        (vec!["--camera-from", "0,5000,0", "--camera-to", "0,9000,0"], "of the organ surface"),
        (vec!["--target-displacement-mm", "nan"], "target displacement"),
        (vec!["--samples", "3"], "at least 10"),
        // The phantom's vena cava as the organ; cells larger than the organ.
        (vec!["--organ-label", "2"], "named as vessels or structures"),
        (vec!["--cell-size-mm", "500"], "use a smaller --cell-size-mm"),
        (vec!["--time-budget-min", "inf"], "--time-budget-min inf"),
        (vec!["--lr-schedule", "zigzag"], "--lr-schedule"),
    ];
    for (extra, needle) in cases {
        let out = tmp(&format!("bad-patient-{}", needle.len()));
        let _ = std::fs::remove_dir_all(&out);
        let mut args = vec!["prepare", "--out", out.to_str().unwrap()];
        args.extend(&extra);
        let (ok, _, stderr) = umesh(&args);
        assert!(!ok, "{extra:?} succeeded");
        assert!(stderr.contains(needle), "{extra:?}: {stderr}");
        assert_eq!(stderr.matches("error:").count(), 1, "{stderr}");
        assert!(!out.exists(), "{extra:?} left {}", out.display());
    }
}

#[test]
fn prepare_on_the_real_ct_and_mr_livers_accepts_the_samples_at_the_target() {
    let Some(d) = shared_data() else { return };
    for (file, ivc) in
        [("totalsegmentator/example_seg.nii.gz", "label 63"), ("totalsegmentator/example_seg_mr.nii.gz", "label 24")]
    {
        let out = tmp(&format!("real-{}", file.len()));
        let _ = std::fs::remove_dir_all(&out);
        let seg = d.join(file);
        let v = short_prepare(Some(seg.to_str().unwrap()), &out, &[]);
        eprintln!("{file}: {v}");
        assert!(v["accepted"].as_u64().unwrap() >= 9, "{file}: {v}");
        let ratio = v["achieved_over_target"]["mean"].as_f64().unwrap();
        assert!((0.75..=1.25).contains(&ratio), "{file}: achieved / target {ratio}");
        let patient = std::fs::read_to_string(out.join("patient.json")).unwrap();
        assert!(
            patient.contains("inferior_vena_cava") && patient.contains(ivc),
            "{file}: fixed region not the vena cava"
        );
        assert!(patient.contains("portal_vein_and_splenic_vein"), "{file}: the portal vein is not a structure");
    }
}

#[test]
fn the_live_path_without_masks_registers_every_frame() {
    let rec = tmp("live-rec");
    let _ = std::fs::remove_dir_all(&rec);
    let (ok, _, err) = umesh(&["rgbd", "synth", "--frames", "4", "--instruments", "1", "--out", rec.to_str().unwrap()]);
    assert!(ok, "{err}");
    // A recording's frames without its masks: the organ found from depth and colour.
    let reg = tmp("live-nomask");
    let (ok, out, err) = umesh(&[
        "register",
        "--recording",
        rec.to_str().unwrap(),
        "--no-mask",
        "--no-overlay",
        "--json",
        "--out",
        reg.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let r = json(&out);
    assert_eq!((r["frames"].as_u64(), r["skipped"].as_u64()), (Some(4), Some(0)), "{r}");
    // A camera bridge on loopback (no masks on the wire), slow enough that no frame is dropped.
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let addr = format!("127.0.0.1:{port}");
    let log = tmp("live-serve.log");
    let mut serve = Command::new(env!("CARGO_BIN_EXE_umesh"))
        .args(["rgbd", "serve", "--recording", rec.to_str().unwrap(), "--listen", &addr, "--fps", "1"])
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let t0 = std::time::Instant::now();
    while !std::fs::read_to_string(&log).unwrap_or_default().contains("serving") {
        assert!(
            t0.elapsed().as_secs() < 30,
            "the server did not start: {}",
            std::fs::read_to_string(&log).unwrap_or_default()
        );
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let live = tmp("live-source");
    // No --initial-pose: the stream carries each frame's tracked pose, which --pose tracked keeps.
    let (ok, out, err) = umesh(&[
        "register",
        "--source",
        &addr,
        "--pose",
        "tracked",
        "--no-overlay",
        "--json",
        "--out",
        live.to_str().unwrap(),
    ]);
    let _ = serve.wait();
    assert!(ok, "{err}");
    let r = json(&out);
    assert_eq!((r["frames"].as_u64(), r["skipped"].as_u64()), (Some(4), Some(0)), "{r}");
}

#[test]
fn bench_fe_exports_the_newton_tangent_as_a_symmetric_csc_matrix_numpy_reads() {
    let has_numpy = Command::new("python3").args(["-c", "import numpy"]).status().map(|s| s.success()).unwrap_or(false);
    if !has_numpy {
        assert!(std::env::var_os("CI").is_none(), "numpy is missing in CI: scripts/setup.sh should have installed it");
        eprintln!("SKIPPED: python3 with numpy not found");
        return;
    }
    let dir = tmp("export-matrix");
    std::fs::create_dir_all(&dir).unwrap();
    let k = dir.join("K.npz");
    let (ok, out, err) = umesh(&["bench", "fe", "--repeat", "1", "--export-matrix", k.to_str().unwrap(), "--json"]);
    assert!(ok, "{err}");
    let v = json(&out);
    let n = v["free_dofs"].as_u64().unwrap();
    for key in ["factorization_ms", "svk_solve_ms", "corotational_update_ms"] {
        assert!(v[key].as_f64().is_some_and(|x| x > 0.0 && x.is_finite()), "{key}: {}", v[key]);
    }
    // Symmetric to rounding, positive diagonal, the documented shape; rhs on the same dofs.
    let script = r#"
import sys, numpy as np
z = np.load(sys.argv[1]); n = int(sys.argv[2])
p, i, v = z["indptr"], z["indices"], z["data"]
assert tuple(z["shape"]) == (n, n) and len(p) == n + 1 and p[-1] == len(v) == len(i) and z["rhs"].shape == (n,)
c = np.repeat(np.arange(n), np.diff(p))
a, b = np.lexsort((i, c)), np.lexsort((c, i))
assert np.array_equal(c[a], i[b]) and np.array_equal(i[a], c[b]), "pattern not symmetric"
assert np.abs(v[a] - v[b]).max() <= 1e-12 * np.abs(v).max(), "values not symmetric"
assert (v[c == i] > 0).all() and (c == i).sum() == n
print("ok")
"#;
    let o = Command::new("python3").args(["-c", script, k.to_str().unwrap(), &n.to_string()]).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

#[test]
fn gui_refuses_a_bad_scan_or_session_before_opening_a_window() {
    let dir = tmp("gui-bad");
    std::fs::create_dir_all(&dir).unwrap();
    let bad = dir.join("ct.nii.gz");
    std::fs::write(&bad, b"not a nifti").unwrap();
    let (ok, _, stderr) = umesh(&["gui", "--ct", bad.to_str().unwrap(), "does-not-exist.nii.gz"]);
    assert!(!ok && stderr.contains("does-not-exist.nii.gz"), "{stderr}");
    let session = dir.join("s.json");
    std::fs::write(&session, "{\"format\": \"umesh-session\"").unwrap();
    let (ok, _, stderr) = umesh(&["gui", "--session", session.to_str().unwrap()]);
    assert!(!ok && stderr.contains("s.json") && stderr.contains("--session"), "{stderr}");
}

#[test]
fn bench_register_presses_each_family_to_the_motion_asked_and_reuses_its_recordings() {
    let dir = tmp("bench-register");
    let rec = dir.to_str().unwrap();
    let args =
        ["bench", "register", "--loads", "gravity", "--frames", "3", "--motion-mm", "8", "--recordings", rec, "--json"];
    let (ok, out, err) = umesh(&args);
    assert!(ok, "{err}");
    let v = json(&out);
    let rows = v["recordings"].as_array().unwrap();
    // One recording per truth material, each pressed to the motion asked within 25 % (the
    // probe scales the load in proportion; the material is not linear).
    assert_eq!(rows.iter().map(|r| r["truth"].as_str().unwrap()).collect::<Vec<_>>(), ["svk", "neo-hookean"], "{v}");
    for r in rows {
        let f = |k: &str| r[k].as_f64().unwrap_or(f64::NAN);
        assert!((f("motion_mm") - 8.0).abs() <= 2.0, "{r}");
        // Registration recovers most of the motion; the figures are the report's own.
        assert!(f("rigid_mm") > 5.0 && f("corrected_mm") < 0.5 * f("rigid_mm") && f("network_mm").is_finite(), "{r}");
        assert!((f("corrected_share_of_rigid") - f("corrected_mm") / f("rigid_mm")).abs() < 1e-9, "{r}");
        assert!(f("frame_ms_median") > 0.0 && f("network_frame_ms_median") > 0.0, "{r}");
        // At 8 mm of motion no recording meets a bar stated at 10 mm or more.
        assert_eq!(r["meets_bar"], false, "{r}");
        // The bundled model trained on every family: none is held out, the bar is 2 mm.
        assert!(r["held_out"] == false && f("bar_mm") == 2.0, "{r}");
    }
    assert_eq!(v["trained_families"].as_array().map(Vec::len), Some(4), "{v}");
    assert_eq!(v["within_bar"], "0 / 2", "{v}");
    assert_eq!(v["correction_form"], "subspace", "{v}");
    // A second run registers the same recordings again, made once (their files untouched).
    let made = || -> Vec<(PathBuf, std::time::SystemTime)> {
        // One folder for the organ and model, the recordings in it.
        let folders: Vec<_> = std::fs::read_dir(&dir).unwrap().filter_map(|e| e.ok()).collect();
        assert_eq!(folders.len(), 1, "{folders:?}");
        let mut v: Vec<_> = std::fs::read_dir(folders[0].path())
            .unwrap()
            .filter_map(|e| e.ok())
            .map(|e| e.path().join("ground_truth.json"))
            .filter(|p| p.is_file())
            .map(|p| {
                let t = std::fs::metadata(&p).unwrap().modified().unwrap();
                (p, t)
            })
            .collect();
        v.sort();
        v
    };
    let before = made();
    assert_eq!(before.len(), 4, "two probes and two recordings: {before:?}");
    let (ok, out2, err) = umesh(&args);
    assert!(ok, "{err}");
    let v2 = json(&out2);
    for (a, b) in rows.iter().zip(v2["recordings"].as_array().unwrap()) {
        assert_eq!(a["motion_mm"], b["motion_mm"], "{a} {b}");
        assert_eq!(a["name"], b["name"], "{a} {b}");
    }
    assert_eq!(made(), before, "the recordings were made again");
    // Bad options: one error naming the option, nothing made.
    for (bad, name) in
        [(["--motion-mm", "0"], "--motion-mm"), (["--frames", "1"], "--frames"), (["--loads", "twist"], "--loads")]
    {
        let mut a: Vec<&str> = vec!["bench", "register", "--recordings", rec];
        a.extend(bad);
        let (ok, _, err) = umesh(&a);
        assert!(!ok && err.contains(name), "{bad:?}: {err}");
    }
}

#[test]
fn an_error_names_its_cause_once() {
    // A missing patient folder: the file and the system's reason, said once each.
    let (ok, _, err) = umesh(&[
        "register",
        "--patient",
        "/nonexistent-umesh-patient",
        "--recording",
        "/nonexistent",
        "--out",
        "/tmp/umesh-never-written",
    ]);
    assert!(!ok, "{err}");
    assert!(err.contains("/nonexistent-umesh-patient/patient.json"), "{err}");
    assert_eq!(err.matches("No such file or directory").count(), 1, "{err}");
}

/// Every file under `dir` with its bytes, to compare before and after a refused run.
fn snapshot(dir: &std::path::Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut v: Vec<(PathBuf, Vec<u8>)> =
        walk(dir).into_iter().map(|p| (p.clone(), std::fs::read(&p).unwrap())).collect();
    v.sort();
    v
}

#[test]
fn an_output_never_replaces_an_input_or_an_output_of_another_kind() {
    let rec = tmp("kinds-rec");
    let _ = std::fs::remove_dir_all(&rec);
    let r = rec.to_str().unwrap();
    let (ok, _, err) = umesh(&[
        "rgbd",
        "synth",
        "--frames",
        "1",
        "--width",
        "160",
        "--height",
        "120",
        "--focal-px",
        "130",
        "--out",
        r,
    ]);
    assert!(ok, "{err}");
    let marker = std::fs::read_to_string(rec.join(umesh_core::OUTPUT_MARKER)).unwrap();
    assert!(marker.contains("kind: recording"), "{marker}");
    let before = snapshot(&rec);
    // The recording as register's output, or a folder holding it: refused before any work,
    // naming both paths.
    for out in [rec.clone(), rec.parent().unwrap().to_path_buf(), rec.join("reg")] {
        let (ok, _, err) = umesh(&["register", "--recording", r, "--out", out.to_str().unwrap()]);
        assert!(
            !ok && err.contains("--recording") && err.contains(&out.display().to_string()),
            "{}: {err}",
            out.display()
        );
    }
    // Other commands' outputs of another kind: a recording is not surfaces or a simulation.
    let ph = "assets/phantom.nii.gz";
    let (ok, _, err) = umesh(&["surface", ph, "--out", r]);
    assert!(!ok && err.contains("holds a recording") && err.contains("surfaces"), "{err}");
    let (ok, _, err) = umesh(&["simulate", "--out", r]);
    assert!(!ok && err.contains("holds a recording"), "{err}");
    assert_eq!(snapshot(&rec), before, "a refused run changed the recording");
    // A model (marked as one) is not a recording's output.
    let model = tmp("kinds-model");
    let _ = std::fs::remove_dir_all(&model);
    std::fs::create_dir_all(&model).unwrap();
    std::fs::write(model.join("model.json"), "{}").unwrap();
    std::fs::write(model.join(umesh_core::OUTPUT_MARKER), "written by umesh\nkind: model\n").unwrap();
    let (ok, _, err) = umesh(&["rgbd", "synth", "--frames", "1", "--out", model.to_str().unwrap()]);
    assert!(!ok && err.contains("holds a model"), "{err}");
    assert!(model.join("model.json").is_file());
    // A recording written over by a recording: the same kind, replaced.
    let (ok, _, err) = umesh(&[
        "rgbd",
        "synth",
        "--frames",
        "1",
        "--width",
        "160",
        "--height",
        "120",
        "--focal-px",
        "130",
        "--out",
        r,
    ]);
    assert!(ok, "{err}");
    // A ground truth of another organ (its markers 400 mm away): no TRE of tens of mm that
    // describes nothing, from register or choose-correction; the model is not written.
    let truth_path = rec.join("ground_truth.json");
    let mut truth: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&truth_path).unwrap()).unwrap();
    for m in truth["markers_rest_mm"].as_array_mut().unwrap() {
        m[0] = serde_json::json!(m[0].as_f64().unwrap() + 400.0);
    }
    std::fs::write(&truth_path, truth.to_string()).unwrap();
    let (ok, _, err) = umesh(&["register", "--recording", r, "--out", tmp("kinds-other-organ").to_str().unwrap()]);
    assert!(!ok && err.contains("not of this organ"), "{err}");
    let model_copy = tmp("kinds-model-copy");
    let _ = std::fs::remove_dir_all(&model_copy);
    std::fs::create_dir_all(&model_copy).unwrap();
    for e in std::fs::read_dir("assets/model").unwrap().flatten() {
        std::fs::copy(e.path(), model_copy.join(e.file_name())).unwrap();
    }
    let before = snapshot(&model_copy);
    let (ok, _, err) = umesh(&["choose-correction", "--model", model_copy.to_str().unwrap(), "--recording", r]);
    assert!(!ok && err.contains("not of this organ"), "{err}");
    assert_eq!(snapshot(&model_copy), before, "choose-correction changed the model on a recording of another organ");
}

#[test]
fn training_options_that_give_no_usable_model_are_refused_and_the_old_model_stays() {
    let model = tmp("train-bad");
    let _ = std::fs::remove_dir_all(&model);
    std::fs::create_dir_all(&model).unwrap();
    std::fs::write(model.join("model.json"), "an earlier model").unwrap();
    std::fs::write(model.join(umesh_core::OUTPUT_MARKER), "written by umesh\nkind: model\n").unwrap();
    let before = snapshot(&model);
    let m = model.to_str().unwrap();
    for (flag, value) in [
        ("--learning-rate", "NaN"),
        ("--learning-rate", "inf"),
        ("--learning-rate", "1e30"),
        ("--learning-rate", "0"),
        ("--learning-rate", "-0.001"),
        ("--epochs", "0"),
    ] {
        let (ok, _, err) = umesh(&["train", "--dataset", "no-such-dataset", "--out", m, &format!("{flag}={value}")]);
        assert!(!ok && err.contains(flag), "{flag} {value}: {err}");
        assert_eq!(snapshot(&model), before, "{flag} {value} changed the model folder");
    }
}

#[test]
fn counts_and_sizes_no_run_can_afford_are_refused_naming_the_option() {
    let out = tmp("absurd-out");
    let _ = std::fs::remove_dir_all(&out);
    let o = out.to_str().unwrap();
    let u64max = "18446744073709551615";
    // (command, what the message must name); each refused before any work, within seconds.
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (vec!["train", "--dataset", "no-such-dataset", "--out", o, "--channels", "0"], "--channels 0"),
        (vec!["train", "--dataset", "no-such-dataset", "--out", o, "--channels", "100000"], "--channels 100000"),
        (vec!["train", "--dataset", "no-such-dataset", "--out", o, "--steps", "40"], "--steps 40"),
        (vec!["train", "--dataset", "no-such-dataset", "--out", o, "--batch-size", "0"], "--batch-size 0"),
        (
            vec!["train", "--dataset", "no-such-dataset", "--out", "no-such-dataset/model"],
            "lies inside the input --dataset",
        ),
        (vec!["surface", "--step", "0", "--out", o], "--step 0"),
        (vec!["surface", "--step", "100000", "--out", o], "--step 100000"),
        (vec!["eval", "--dataset", "no-such-dataset", "--markers", "0"], "--markers 0"),
        (vec!["eval", "--dataset", "no-such-dataset", "--markers", u64max], "--markers"),
        (vec!["rgbd", "synth", "--markers", "0", "--out", o], "0 markers"),
        (vec!["rgbd", "synth", "--markers", u64max, "--out", o], "markers: between 1"),
        (vec!["rgbd", "synth", "--young-pa", "1e308", "--out", o], "Young's modulus 1e308"),
        (vec!["dataset", "generate", "--samples", u64max, "--out", o], "--samples"),
        (vec!["simulate", "--increments", "0", "--out", o], "--increments"),
        (vec!["register", "--recording", "no-such-recording", "--depth-min-mm", "1e308", "--out", o], "--depth-min-mm"),
        (vec!["register", "--recording", "no-such-recording", "--pose", "sideways", "--out", o], "--pose"),
    ];
    for (args, needle) in cases {
        let t = std::time::Instant::now();
        let (ok, _, err) = umesh(&args);
        assert!(!ok && err.contains(needle) && !err.contains("panicked"), "{args:?}: {err}");
        assert!(t.elapsed().as_secs_f64() < 30.0, "{args:?} took {:?} to refuse", t.elapsed());
        assert!(!out.exists(), "{args:?} wrote {}", out.display());
    }
    // A folder that holds something else never receives a dataset's shards.
    let foreign = tmp("absurd-foreign");
    let _ = std::fs::remove_dir_all(&foreign);
    std::fs::create_dir_all(&foreign).unwrap();
    std::fs::write(foreign.join("model.json"), "a user's file").unwrap();
    let before = snapshot(&foreign);
    let (ok, _, err) = umesh(&["dataset", "generate", "--samples", "2", "--out", foreign.to_str().unwrap()]);
    assert!(!ok && err.contains("model.json") && err.contains("no dataset"), "{err}");
    assert_eq!(snapshot(&foreign), before);
}

#[test]
fn a_recording_made_on_another_organs_grid_is_refused_by_register_and_choose_correction() {
    let rec = tmp("other-grid-rec");
    let _ = std::fs::remove_dir_all(&rec);
    let r = rec.to_str().unwrap();
    let (ok, _, err) = umesh(&[
        "rgbd",
        "synth",
        "--frames",
        "2",
        "--width",
        "160",
        "--height",
        "120",
        "--focal-px",
        "130",
        "--out",
        r,
    ]);
    assert!(ok, "{err}");
    // The truth names the grid it was made on; another hash is another organ (a scaled copy of
    // this one keeps its markers within this organ's bounds, so the bounds check cannot see it).
    let gt = rec.join("ground_truth.json");
    let mut v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&gt).unwrap()).unwrap();
    assert!(v["grid_hash"].is_string(), "a synthetic truth records its grid: {}", v["grid_hash"]);
    v["grid_hash"] = serde_json::json!("0123456789abcdef");
    std::fs::write(&gt, v.to_string()).unwrap();
    let model = tmp("other-grid-model");
    let _ = std::fs::remove_dir_all(&model);
    std::fs::create_dir_all(&model).unwrap();
    for e in std::fs::read_dir(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("assets/model")).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), model.join(e.file_name())).unwrap();
    }
    let before = snapshot(&model);
    let out = tmp("other-grid-reg");
    let (ok, _, err) = umesh(&[
        "register",
        "--model",
        model.to_str().unwrap(),
        "--recording",
        r,
        "--no-overlay",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("another organ's grid") && err.contains("0123456789abcdef"), "{err}");
    let (ok, _, err) = umesh(&["choose-correction", "--model", model.to_str().unwrap(), "--recording", r]);
    assert!(!ok && err.contains("another organ's grid"), "{err}");
    assert_eq!(snapshot(&model), before, "the model folder changed");
    assert!(!out.exists());
}
