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
pub mod nn;
pub mod npz;
pub mod observation;
pub mod phantom;
pub mod progress;
pub mod register;
pub mod rgbd;
pub mod rng;
pub mod segmentation;
pub mod simulate;
pub mod slices;
pub mod surface;
pub mod synth;
pub mod visible;
pub mod volume;
pub mod vtk;

pub use error::{Cancelled, Invalid, ModelError};
pub use progress::{Cancel, Eta, Progress};

/// A folder replaced whole or not at all: a command writes into `path()`, a staging folder
/// beside the target, and `commit` swaps it in; dropped without a commit (a failure), the
/// staging folder goes and the target stays exactly as it was. No stale file of an earlier
/// run survives in the new folder.
#[derive(Debug)]
pub struct StagedDir {
    staging: std::path::PathBuf,
    target: std::path::PathBuf,
    kind: OutputKind,
    committed: bool,
    keep_on_failure: bool,
}

/// A hidden folder beside `target` named after it: `.NAME.TAG`.
fn beside(target: &std::path::Path, tag: &str) -> std::path::PathBuf {
    let name = target.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "out".into());
    let parent = target.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(std::path::Path::new("."));
    parent.join(format!(".{name}.{tag}"))
}

/// What an output folder holds. Its marker ([`OUTPUT_MARKER`]) records it, and a command
/// replaces only a folder of the kind it writes: `register --out` never replaces a recording,
/// `rgbd synth --out` never a model.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OutputKind {
    Recording,
    Model,
    Dataset,
    Registration,
    Surfaces,
    Simulation,
}

impl OutputKind {
    pub const ALL: [OutputKind; 6] = [
        OutputKind::Recording,
        OutputKind::Model,
        OutputKind::Dataset,
        OutputKind::Registration,
        OutputKind::Surfaces,
        OutputKind::Simulation,
    ];

    pub fn name(self) -> &'static str {
        match self {
            OutputKind::Recording => "recording",
            OutputKind::Model => "model",
            OutputKind::Dataset => "dataset",
            OutputKind::Registration => "registration",
            OutputKind::Surfaces => "surfaces",
            OutputKind::Simulation => "simulation",
        }
    }

    /// The kind with its article, for messages: "a model", "surfaces".
    pub fn with_article(self) -> String {
        match self {
            OutputKind::Surfaces => "surfaces".into(),
            k => format!("a {}", k.name()),
        }
    }

    /// The kind a marker names (None: a marker written before markers named their kind).
    fn of_marker(text: &str) -> Option<Self> {
        let k = text.lines().find_map(|l| l.strip_prefix("kind: "))?.trim();
        Self::ALL.into_iter().find(|x| x.name() == k)
    }
}

/// Whether a command writing `kind` may replace `target` (see [`StagedDir::new`]): commands
/// that work long before they stage their output ask first, so a refusal comes before any work.
pub fn check_replaceable(target: &std::path::Path, kind: OutputKind, recognised: &[&str]) -> std::io::Result<()> {
    if !target.exists() {
        return Ok(());
    }
    if !target.is_dir() {
        return Err(std::io::Error::other(format!("{} exists and is not a folder", target.display())));
    }
    let mut entries = std::fs::read_dir(target)?;
    if entries.next().is_none() {
        return Ok(());
    }
    let own = || recognised.iter().any(|f| target.join(f).exists());
    match std::fs::read_to_string(target.join(OUTPUT_MARKER)) {
        Ok(marker) => match OutputKind::of_marker(&marker) {
            Some(k) if k == kind => Ok(()),
            Some(k) => Err(std::io::Error::other(format!(
                "{} holds {} umesh wrote; this command writes {} and would replace it whole: choose another output folder",
                target.display(),
                k.with_article(),
                kind.with_article()
            ))),
            // Marked before markers named their kind: this command's own files say it is its.
            None if own() => Ok(()),
            None => Err(std::io::Error::other(format!(
                "{} holds another kind of umesh output than the {} this command writes; it would be replaced whole: choose another output folder",
                target.display(),
                kind.name()
            ))),
        },
        Err(_) if own() => Ok(()),
        Err(_) => Err(std::io::Error::other(format!(
            "{} holds files umesh did not write; it would be replaced whole: choose another output folder or empty it",
            target.display()
        ))),
    }
}

/// A user's number for a message: large or tiny ones in exponent form (`1e308`, not 309 digits).
pub fn shown(v: f64) -> String {
    if v != 0.0 && v.is_finite() && !(1e-4..1e7).contains(&v.abs()) { format!("{v:e}") } else { format!("{v}") }
}

/// An output folder must stand apart from the command's inputs: not one of them, not inside
/// one (it would change it), not holding one (replacing it would delete it). `inputs`: the
/// option's name and its path. Paths that do not exist yet are compared as written.
pub fn check_apart(out: &std::path::Path, inputs: &[(&str, &std::path::Path)]) -> Result<(), Invalid> {
    fn absolute(p: &std::path::Path) -> std::path::PathBuf {
        if let Ok(c) = std::fs::canonicalize(p) {
            return c;
        }
        // Not there yet: its parent resolved, its name kept.
        match (p.parent().filter(|q| !q.as_os_str().is_empty()), p.file_name()) {
            (Some(parent), Some(name)) => absolute(parent).join(name),
            (None, Some(name)) => std::env::current_dir().map(|d| d.join(name)).unwrap_or_else(|_| p.to_path_buf()),
            _ => p.to_path_buf(),
        }
    }
    let o = absolute(out);
    for (option, input) in inputs {
        let i = absolute(input);
        let how = if o == i {
            "is"
        } else if o.starts_with(&i) {
            "lies inside"
        } else if i.starts_with(&o) {
            "holds"
        } else {
            continue;
        };
        return Err(Invalid(format!(
            "--out {} {how} the input {option} {}: it would be changed or deleted; choose an output folder apart from the inputs",
            out.display(),
            input.display()
        )));
    }
    Ok(())
}

/// The app's record of a job's settings, written beside the job's output before it runs.
pub const JOB_FILE: &str = "umesh-job.json";

/// The file a committed [`StagedDir`] carries, so a later run knows the folder is its own.
pub const OUTPUT_MARKER: &str = ".umesh-output";

impl StagedDir {
    /// Stage a replacement for `target`, an output of `kind`. An existing, non-empty target is
    /// replaced only when umesh wrote it as that kind (its [`OUTPUT_MARKER`] says so; a folder
    /// marked before markers named their kind, or not marked, must hold one of `recognised`,
    /// the files the command writes): `--out ~/Documents` must never empty a user's folder,
    /// nor `register --out` a recording.
    pub fn new(target: &std::path::Path, kind: OutputKind, recognised: &[&str]) -> std::io::Result<Self> {
        check_replaceable(target, kind, recognised)?;
        let staging = beside(target, &format!("staging-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&staging);
        std::fs::create_dir_all(&staging)?;
        Ok(Self { staging, target: target.to_path_buf(), kind, committed: false, keep_on_failure: false })
    }

    /// Like [`StagedDir::new`], but the staging folder has a fixed name and survives a failure
    /// or a cancel, so long work (training) can resume in it; `resume` reuses one left by an
    /// earlier run, otherwise it starts empty.
    pub fn resumable(
        target: &std::path::Path,
        kind: OutputKind,
        recognised: &[&str],
        resume: bool,
    ) -> std::io::Result<Self> {
        check_replaceable(target, kind, recognised)?;
        let staging = Self::pending_path(target);
        if !resume {
            let _ = std::fs::remove_dir_all(&staging);
        }
        std::fs::create_dir_all(&staging)?;
        Ok(Self { staging, target: target.to_path_buf(), kind, committed: false, keep_on_failure: true })
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
        let kind = self.kind.name();
        let marker = format!("written by umesh; replaced whole by the next run that writes a {kind}\nkind: {kind}\n");
        std::fs::write(self.staging.join(OUTPUT_MARKER), marker)?;
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
