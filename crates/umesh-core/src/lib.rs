//! umesh-core: the computation behind umesh, free of any GUI or ML dependency.
//!
//! Units everywhere: millimetres for lengths (`_mm`), newtons for forces (`_n`),
//! pascals for stresses and moduli (`_pa`). The world frame is RAS (x: right,
//! y: anterior, z: superior), as NIfTI's scanner frame.

pub mod dataset;
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
pub mod visible;
pub mod volume;
pub mod vtk;

pub use progress::{Cancel, Progress};

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
