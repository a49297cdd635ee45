//! umesh-core: the computation behind umesh, free of any GUI or ML dependency.
//!
//! Units everywhere: millimetres for lengths (`_mm`), newtons for forces (`_n`),
//! pascals for stresses and moduli (`_pa`). The world frame is RAS (x: right,
//! y: anterior, z: superior), as NIfTI's scanner frame.

pub mod dataset;
mod error;
pub mod fem;
pub mod grid;
pub mod loads;
pub mod mesh;
pub mod mesh_io;
pub mod nifti_io;
pub mod npz;
pub mod observation;
pub mod phantom;
pub mod progress;
pub mod register;
pub mod rgbd;
pub mod segmentation;
pub mod simulate;
pub mod slices;
pub mod surface;
pub mod synth;
pub mod visible;
pub mod volume;
pub mod vtk;

pub use error::{Cancelled, Invalid, ModelError};
pub use progress::{Cancel, Progress};

/// A folder replaced whole or not at all: a command writes into `path()`, a staging folder
/// beside the target, and `commit` swaps it in; dropped without a commit (a failure), the
/// staging folder goes and the target stays exactly as it was. No stale file of an earlier
/// run survives in the new folder.
#[derive(Debug)]
pub struct StagedDir {
    staging: std::path::PathBuf,
    target: std::path::PathBuf,
    committed: bool,
    keep_on_failure: bool,
}

/// A hidden folder beside `target` named after it: `.NAME.TAG`.
fn beside(target: &std::path::Path, tag: &str) -> std::path::PathBuf {
    let name = target.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "out".into());
    let parent = target.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(std::path::Path::new("."));
    parent.join(format!(".{name}.{tag}"))
}

fn check_replaceable(target: &std::path::Path, recognised: &[&str]) -> std::io::Result<()> {
    if !target.exists() {
        return Ok(());
    }
    if !target.is_dir() {
        return Err(std::io::Error::other(format!("{} exists and is not a folder", target.display())));
    }
    let mut entries = std::fs::read_dir(target)?;
    if entries.next().is_none() || std::iter::once(OUTPUT_MARKER).chain(recognised.iter().copied()).any(|f| target.join(f).exists()) {
        return Ok(());
    }
    Err(std::io::Error::other(format!(
        "{} holds files umesh did not write; it would be replaced whole: choose another output folder or empty it",
        target.display()
    )))
}

/// The file a committed [`StagedDir`] carries, so a later run knows the folder is its own.
pub const OUTPUT_MARKER: &str = ".umesh-output";

impl StagedDir {
    /// Stage a replacement for `target`. An existing, non-empty target is replaced only when
    /// umesh wrote it (it holds [`OUTPUT_MARKER`] or one of `recognised`, the files the command
    /// writes): `--out ~/Documents` must never empty a user's folder.
    pub fn new(target: &std::path::Path, recognised: &[&str]) -> std::io::Result<Self> {
        check_replaceable(target, recognised)?;
        let staging = beside(target, &format!("staging-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&staging);
        std::fs::create_dir_all(&staging)?;
        Ok(Self { staging, target: target.to_path_buf(), committed: false, keep_on_failure: false })
    }

    /// Like [`StagedDir::new`], but the staging folder has a fixed name and survives a failure
    /// or a cancel, so long work (training) can resume in it; `resume` reuses one left by an
    /// earlier run, otherwise it starts empty.
    pub fn resumable(target: &std::path::Path, recognised: &[&str], resume: bool) -> std::io::Result<Self> {
        check_replaceable(target, recognised)?;
        let staging = Self::pending_path(target);
        if !resume {
            let _ = std::fs::remove_dir_all(&staging);
        }
        std::fs::create_dir_all(&staging)?;
        Ok(Self { staging, target: target.to_path_buf(), committed: false, keep_on_failure: true })
    }

    /// Where [`StagedDir::resumable`] stages `target`.
    pub fn pending_path(target: &std::path::Path) -> std::path::PathBuf {
        beside(target, "pending")
    }

    /// Where the command writes.
    pub fn path(&self) -> &std::path::Path {
        &self.staging
    }

    /// Swap the staging folder in for the target (the old target removed after the swap).
    pub fn commit(mut self) -> std::io::Result<()> {
        std::fs::write(self.staging.join(OUTPUT_MARKER), b"written by umesh; replaced whole by the next run\n")?;
        let old = beside(&self.target, &format!("old-{}", std::process::id()));
        if self.target.exists() {
            let _ = std::fs::remove_dir_all(&old);
            std::fs::rename(&self.target, &old)?;
            if let Err(e) = std::fs::rename(&self.staging, &self.target) {
                let _ = std::fs::rename(&old, &self.target);
                return Err(e);
            }
            let _ = std::fs::remove_dir_all(&old);
        } else {
            std::fs::rename(&self.staging, &self.target)?;
        }
        self.committed = true;
        Ok(())
    }
}

impl Drop for StagedDir {
    fn drop(&mut self) {
        if !self.committed && !self.keep_on_failure {
            let _ = std::fs::remove_dir_all(&self.staging);
        }
    }
}

/// Write `bytes` to `path` atomically: a temporary file beside it, then a rename,
/// so a crash never leaves a half-written output.
pub fn write_atomic(path: &std::path::Path, bytes: &[u8]) -> std::io::Result<()> {
    let file_name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "out".into());
    let tmp = path.with_file_name(format!(".{file_name}.{}.tmp", std::process::id()));
    if let Some(dir) = path.parent()
        && !dir.as_os_str().is_empty()
    {
        std::fs::create_dir_all(dir)?;
    }
    // A failed write (a full disk) or rename removes the temporary: nothing is left behind.
    std::fs::write(&tmp, bytes).and_then(|_| std::fs::rename(&tmp, path)).inspect_err(|_| {
        let _ = std::fs::remove_file(&tmp);
    })
}

/// Whether two paths name the same file or folder (canonically, where they exist).
pub fn same_path(a: &std::path::Path, b: &std::path::Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(x), Ok(y)) => x == y,
        _ => a == b,
    }
}
