//! `umesh screenshot`: render a named scene of the app headless (EGL or Vulkan, no window).

use anyhow::{Result, bail};
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// phantom, grid, probes or rehearsal.
    #[arg(long)]
    pub scene: String,
    #[arg(long)]
    pub out: PathBuf,
    /// WIDTHxHEIGHT in pixels.
    #[arg(long, default_value = "1280x800")]
    pub size: String,
    /// Frames rendered before the capture.
    #[arg(long, default_value_t = 6)]
    pub warmup: u32,
}

pub fn parse_size(s: &str) -> Result<(u32, u32)> {
    let Some((w, h)) = s.split_once(['x', 'X']) else { bail!("size {s:?}: WIDTHxHEIGHT expected") };
    Ok((w.trim().parse()?, h.trim().parse()?))
}

pub fn run(a: Args) -> Result<()> {
    let (w, h) = parse_size(&a.size)?;
    crate::app::screenshot::render_scene(&a.scene, w, h, &a.out, a.warmup)?;
    println!("{}", a.out.display());
    exit_now()
}

/// Leave at once, the PNG written (atomically) and stdout flushed: Mesa's GL teardown at
/// process exit corrupted the heap in about 1 of 26 headless renders ("corrupted size vs.
/// prev_size"), after the image was complete.
#[allow(unsafe_code)]
fn exit_now() -> ! {
    use std::io::Write;
    let _ = std::io::stdout().flush();
    let _ = std::io::stderr().flush();
    // SAFETY: _exit only ends the process; nothing of ours is left to run or flush.
    unsafe { libc::_exit(0) }
}
