//! What the modules that run the binary share: running it, its JSON line, scratch paths.

use std::path::PathBuf;
use std::process::Command;

/// Run `umesh ARGS`: (exit 0, stdout, stderr).
pub fn umesh(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_umesh")).args(args).output().expect("run umesh");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// The one JSON object a `--json` command prints.
pub fn json(stdout: &str) -> serde_json::Value {
    serde_json::from_str(stdout.trim()).unwrap_or_else(|e| panic!("not one JSON object ({e}): {stdout}"))
}

/// A path in this test process's scratch folder for `area`.
pub fn scratch(area: &str, name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("umesh-{area}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d.join(name)
}
