//! `umesh gui`: the desktop app (also what `umesh` with no command opens when a display
//! exists).

use anyhow::{Context, Result, bail};

#[derive(clap::Args, Debug, Default)]
pub struct Args {
    /// A patient folder made by `umesh prepare`: opens its organ, model, camera and fixed
    /// region, with its figures in the Jobs view.
    pub patient: Option<std::path::PathBuf>,
    /// A scan and its segmentation: `--ct CT.nii.gz SEG.nii.gz` opens the segmentation's organ
    /// (the label named liver) with the scan's slices under it.
    #[arg(long, num_args = 2, value_names = ["CT", "SEG"], conflicts_with = "patient")]
    pub ct: Option<Vec<std::path::PathBuf>>,
    /// A session file: opened when it exists (its organ, scan, probes, fixed region, camera,
    /// model, slices), else created by the first Ctrl+S; Ctrl+S saves to it.
    #[arg(long, value_name = "FILE", conflicts_with_all = ["patient", "ct"])]
    pub session: Option<std::path::PathBuf>,
}

pub fn has_display() -> bool {
    std::env::var_os("DISPLAY").is_some() || std::env::var_os("WAYLAND_DISPLAY").is_some()
}

pub fn run(a: Args) -> Result<()> {
    // Checked before a window opens, so that a wrong folder is one clear error.
    if let Some(dir) = &a.patient {
        umesh_workflow::patient::Patient::read(dir)?;
    }
    let open = match a.ct.as_deref() {
        Some([ct, seg]) => {
            // Both read now: a wrong file is one clear error, not a message in a window.
            let input = umesh_workflow::input::InputSpec {
                seg: Some(seg.clone()),
                mesh_scale_mm: 1.0,
                mesh_voxel_mm: 1.0,
                max_voxels: umesh_core::nifti_io::DEFAULT_MAX_VOXELS,
                ..Default::default()
            };
            let s = crate::cli::input::LoadInput::load(&input)?;
            umesh_core::slices::read_scan(ct, s.organ_mask().world_bounds()).context("--ct")?;
            Some(crate::app::state::OpenRequest { path: Some(seg.clone()), ct: Some(ct.clone()), ..Default::default() })
        }
        _ => None,
    };
    if let Some(s) = &a.session
        && s.exists()
    {
        crate::app::model::session::Session::read(s).context("--session")?;
    }
    if !has_display() {
        bail!("no display (DISPLAY / WAYLAND_DISPLAY unset): the app needs one; `umesh screenshot` renders headless");
    }
    let start = match (open, a.session) {
        (Some(req), _) => crate::app::StartWith::Open(req),
        (None, Some(s)) => crate::app::StartWith::Session(s),
        (None, None) => a.patient.map(crate::app::StartWith::Patient).unwrap_or_default(),
    };
    restart_on_vulkan_if_gl_cannot_present();
    match crate::app::run_gui(start) {
        bevy::app::AppExit::Success => Ok(()),
        bevy::app::AppExit::Error(code) => bail!("the app exited with code {code}"),
    }
}

/// Set when the app was restarted on Vulkan, so it never loops.
const GL_FALLBACK_ENV: &str = "UMESH_GL_FELL_BACK";

/// GL through Mesa's EGL under some X servers (Xvfb) offers no present mode for a window, and
/// bevy then stops with an internal `unreachable` ("Fallback system failed to choose present
/// mode"). That one failure is said plainly and the app restarts on Vulkan; GL still serves
/// the headless `umesh screenshot`.
fn restart_on_vulkan_if_gl_cannot_present() {
    let gl = std::env::var("WGPU_BACKEND")
        .is_ok_and(|b| matches!(b.to_ascii_lowercase().as_str(), "gl" | "gles" | "opengl"));
    if !gl || std::env::var_os(GL_FALLBACK_ENV).is_some() {
        return;
    }
    let default = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let payload = info.payload();
        let msg = payload
            .downcast_ref::<String>()
            .map(String::as_str)
            .or_else(|| payload.downcast_ref::<&str>().copied())
            .unwrap_or("");
        if !msg.contains("failed to choose present mode") {
            return default(info);
        }
        eprintln!(
            "umesh gui: the GL backend (WGPU_BACKEND=gl) offers no present mode for this window; restarting on Vulkan (WGPU_BACKEND=vulkan)"
        );
        #[cfg(unix)]
        if let Ok(exe) = std::env::current_exe() {
            use std::os::unix::process::CommandExt;
            let e = std::process::Command::new(exe)
                .args(std::env::args_os().skip(1))
                .env("WGPU_BACKEND", "vulkan")
                .env(GL_FALLBACK_ENV, "1")
                .exec();
            eprintln!("umesh gui: could not restart on Vulkan: {e}");
        }
        std::process::exit(1);
    }));
}
