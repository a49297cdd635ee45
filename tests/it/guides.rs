//! The guides' command blocks run as written (sizes made small), so a newcomer following them
//! from a fresh clone meets no command that fails.

use std::path::PathBuf;
use std::process::Command;

/// Every `umesh ...` line of the ```sh blocks of `doc`, in order.
fn command_lines(doc: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut inside = false;
    for line in doc.lines() {
        let t = line.trim();
        if t.starts_with("```") {
            inside = !inside && t == "```sh";
            continue;
        }
        if inside && t.starts_with("umesh ") {
            out.push(t.split(" #").next().unwrap_or(t).trim().to_string());
        }
    }
    out
}

#[test]
fn every_command_of_the_research_guide_runs_on_the_bundled_phantom() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let doc = std::fs::read_to_string(root.join("docs/RESEARCH.md")).expect("read docs/RESEARCH.md");
    let lines = command_lines(&doc);
    assert!(lines.len() >= 7, "the guide's command blocks: {lines:?}");
    // The sizes written for users, and the small ones CI runs; each must occur, so that a
    // changed guide cannot make this test run an hour-long job.
    let small = [("--samples 1000", "--samples 12"), ("--epochs 20", "--epochs 1"), ("--frames 20", "--frames 3")];
    for (big, _) in small {
        assert!(lines.iter().any(|l| l.contains(big)), "no command of the guide has {big}: {lines:?}");
    }
    let dir = std::env::temp_dir().join(format!("umesh-guide-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    for line in &lines {
        let mut l = line.clone();
        for (big, little) in small {
            l = l.replace(big, little);
        }
        if l.starts_with("umesh bench register") {
            l.push_str(&format!(" --recordings {}", dir.join("bench-recordings").display()));
        }
        let args: Vec<&str> = l.split_whitespace().skip(1).collect();
        let out = Command::new(env!("CARGO_BIN_EXE_umesh")).args(&args).current_dir(&dir).output().expect("run umesh");
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "`{l}` (from `{line}`) failed:\n{stderr}");
        if args.contains(&"--json") {
            let v: serde_json::Value =
                serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("`{l}`: not JSON ({e})"));
            assert!(v.is_object() || v.is_array(), "`{l}`: {v}");
        }
    }
    // What the steps leave, as the guide says.
    for f in [
        "data/phantom/manifest.json",
        "models/phantom/model.json",
        "rec/grasp/ground_truth.json",
        "out/grasp/report.json",
    ] {
        assert!(dir.join(f).is_file(), "{f} missing after the guide's commands");
    }
}

/// `docs/BENCHMARKS.md` is the page `umesh bench page` makes from the result files in
/// `docs/benchmarks/` (nobody edited a figure by hand), and every figure the README's "How well
/// it works" table gives appears in it, word for word.
#[test]
fn the_benchmarks_page_is_made_from_its_results_and_holds_every_figure_of_the_readme() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let results = root.join("docs/benchmarks");
    let page_path = root.join("docs/BENCHMARKS.md");
    let (ok, _, err) = crate::support::umesh(&[
        "bench",
        "page",
        "--results",
        results.to_str().unwrap(),
        "--out",
        page_path.to_str().unwrap(),
        "--check",
    ]);
    assert!(ok, "{err}");
    let page = std::fs::read_to_string(&page_path).unwrap();
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    let section = readme.split("## How well it works").nth(1).expect("README: no \"How well it works\"");
    let section = section.split("\n## ").next().unwrap_or(section);
    let rows: Vec<Vec<&str>> = section
        .lines()
        .filter(|l| l.starts_with('|') && !l.starts_with("|---"))
        .skip(1)
        .map(|l| l.trim_matches('|').split(" | ").map(str::trim).collect())
        .collect();
    assert!(rows.len() >= 5, "the README's table has {} rows", rows.len());
    for row in rows {
        let figure = row.get(1).copied().unwrap_or("");
        assert!(page.contains(figure), "the README's figure {figure:?} is not in docs/BENCHMARKS.md");
    }
    // A figure a command measured on this machine, its machine and date beside it.
    assert!(page.lines().filter(|l| l.starts_with("| ") && l.contains("`umesh ")).count() >= 5, "{page}");
}
