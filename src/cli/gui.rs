//! `umesh gui`: the desktop app (also what `umesh` with no command opens when a display
//! exists).

use anyhow::{Result, bail};

#[derive(clap::Args, Debug, Default)]
pub struct Args {
    /// A patient folder made by `umesh prepare`: opens its organ, model, camera and fixed
    /// region, with its figures in the Jobs view.
    pub patient: Option<std::path::PathBuf>,
}

pub fn has_display() -> bool {
    std::env::var_os("DISPLAY").is_some() || std::env::var_os("WAYLAND_DISPLAY").is_some()
}

pub fn run(a: Args) -> Result<()> {
    // Checked before a window opens, so that a wrong folder is one clear error.
    if let Some(dir) = &a.patient {
        umesh_net::patient::Patient::read(dir)?;
    }
    if !has_display() {
        bail!("no display (DISPLAY / WAYLAND_DISPLAY unset): the app needs one; `umesh screenshot` renders headless");
    }
    match crate::app::run_gui(a.patient) {
        bevy::app::AppExit::Success => Ok(()),
        bevy::app::AppExit::Error(code) => bail!("the app exited with code {code}"),
    }
}
