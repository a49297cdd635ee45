//! `umesh gui`: the desktop app (also what `umesh` with no command opens when a display
//! exists).

use anyhow::{Result, bail};

#[derive(clap::Args, Debug, Default)]
pub struct Args {}

pub fn has_display() -> bool {
    std::env::var_os("DISPLAY").is_some() || std::env::var_os("WAYLAND_DISPLAY").is_some()
}

pub fn run(_a: Args) -> Result<()> {
    if !has_display() {
        bail!("no display (DISPLAY / WAYLAND_DISPLAY unset): the app needs one; `umesh screenshot` renders headless");
    }
    match crate::app::run_gui() {
        bevy::app::AppExit::Success => Ok(()),
        bevy::app::AppExit::Error(code) => bail!("the app exited with code {code}"),
    }
}
