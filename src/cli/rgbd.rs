//! `umesh rgbd synth` (synthetic recordings with ground truth), `umesh rgbd serve` (stream a
//! recording folder over the TCP frame protocol, as a camera bridge would), and the RealSense
//! commands `import` and `realsense` (in `camera.rs`).

use super::input::{InputArgs, LoadInput, bundled_model, model_dataset_config};
use anyhow::{Context, Result};
use std::path::PathBuf;
use std::time::{Duration, Instant};
use umesh_core::rgbd::recording::Recording;
use umesh_core::rgbd::stream::{FrameSource, Poll, RecordingSource, write_frame};
use umesh_core::synth::{SynthSettings, run_rgbd_synth};

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(subcommand)]
    command: Sub,
}

#[derive(clap::Subcommand, Debug)]
enum Sub {
    /// Deform the organ with the FE model over a short sequence and render a recording.
    Synth(Box<SynthArgs>),
    /// Serve a recording's frames on a TCP port in umesh's stream protocol.
    Serve(ServeArgs),
    /// Turn a RealSense recording (.db3, .bag) into a recording folder: depth aligned to
    /// colour, the device's intrinsics and depth units, frame numbers and timestamps.
    Import(super::camera::ImportArgs),
    /// Serve a connected RealSense camera (or a RealSense recording) on a TCP port in umesh's
    /// stream protocol, depth aligned to colour, with a tracked pose from a file or a tracker.
    Realsense(super::camera::RealSenseArgs),
}

#[derive(clap::Args, Debug)]
pub struct SynthArgs {
    #[command(flatten)]
    pub input: InputArgs,
    /// Use this model's grid and camera (default: the bundled model's).
    #[arg(long)]
    pub model: Option<PathBuf>,
    #[arg(long, default_value_t = SynthSettings::default().frames)]
    pub frames: usize,
    #[arg(long, default_value_t = SynthSettings::default().fps)]
    pub fps: f64,
    #[arg(long, default_value_t = SynthSettings::default().width)]
    pub width: usize,
    #[arg(long, default_value_t = SynthSettings::default().height)]
    pub height: usize,
    #[arg(long, default_value_t = SynthSettings::default().focal_px)]
    pub focal_px: f64,
    /// Depth noise, standard deviation (mm).
    #[arg(long, default_value_t = SynthSettings::default().noise_mm)]
    pub noise_mm: f64,
    /// Holes (no depth) per frame.
    #[arg(long, default_value_t = SynthSettings::default().holes)]
    pub holes: usize,
    /// Markers inside the organ (as many again on the internal structures).
    #[arg(long, default_value_t = SynthSettings::default().markers)]
    pub markers: usize,
    /// Scale of the final load relative to the dataset's random forces.
    #[arg(long, default_value_t = SynthSettings::default().load_scale)]
    pub load_scale: f64,
    #[arg(long, default_value_t = SynthSettings::default().seed)]
    pub seed: u64,
    /// The camera moves sideways by this much over the sequence (mm); the trajectory records it.
    #[arg(long, default_value_t = 0.0)]
    pub camera_motion_mm: f64,
    /// The camera turns by this much over the sequence (degrees).
    #[arg(long, default_value_t = 0.0)]
    pub camera_motion_deg: f64,
    /// Instrument shafts occluding the organ.
    #[arg(long, default_value_t = 0)]
    pub instruments: usize,
    /// The load family of the truth: pressing (the dataset's own pattern), instrument (1-3
    /// local contacts pushing), grasp (1-2 contacts pulled outward and sideways) or gravity (a
    /// body force in a random direction).
    #[arg(long, default_value = "pressing")]
    pub loads: String,
    /// The share of the final load already on at the first frame (0: starts at rest; 0.5: the
    /// sequence starts half deformed).
    #[arg(long, default_value_t = 0.0)]
    pub first_load: f64,
    /// Write each frame as a cloud of this many organ points (points/*.ply, camera frame)
    /// instead of a depth image (0: depth images).
    #[arg(long, default_value_t = 0)]
    pub cloud_points: usize,
    /// Move the truth's attachment by x,y,z (mm) from the one the model assumes (for example
    /// 0,15,0: 1.5 cm anterior), a test off the training distribution; rounded to whole cells.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true, value_name = "X,Y,Z")]
    pub attachment_shift_mm: Vec<f64>,
    /// The truth's material (svk, neo-hookean, linear; default: the dataset's), a test off the
    /// training distribution.
    #[arg(long)]
    pub material: Option<String>,
    /// The truth's Poisson ratio (with --material; default: the dataset's).
    #[arg(long)]
    pub poisson: Option<f64>,
    /// The truth's Young's modulus (Pa; with --material; default: the dataset's).
    #[arg(long)]
    pub young_pa: Option<f64>,
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
pub struct ServeArgs {
    #[arg(long)]
    pub recording: PathBuf,
    /// Intrinsics JSON (default: found in the recording).
    #[arg(long)]
    pub intrinsics: Option<PathBuf>,
    #[arg(long, default_value = "127.0.0.1:7878")]
    pub listen: String,
    /// Frames per second (default: the recording's).
    #[arg(long)]
    pub fps: Option<f64>,
    /// Play the recording this many times (0: forever).
    #[arg(long, default_value_t = 1)]
    pub loops: usize,
}

pub fn run(a: Args) -> Result<()> {
    match a.command {
        Sub::Synth(s) => synth(*s),
        Sub::Serve(s) => serve(s),
        Sub::Import(s) => super::camera::import(s),
        Sub::Realsense(s) => super::camera::realsense(s),
    }
}

fn synth(a: SynthArgs) -> Result<()> {
    let seg = a.input.load()?;
    let model_dir = a.model.clone().unwrap_or_else(bundled_model);
    let info = umesh_net::ModelInfo::read(&model_dir).ok();
    if a.model.is_some() && info.is_none() {
        anyhow::bail!("{}: not a model folder (model.json)", model_dir.display());
    }
    let config = model_dataset_config(info.as_ref(), &seg);
    let material = match (&a.material, a.poisson, a.young_pa) {
        (None, None, None) => None,
        (m, p, e) => {
            let kind = match m {
                Some(m) => umesh_core::fem::MaterialKind::parse(m)
                    .with_context(|| format!("--material {m}: expected svk, neo-hookean or linear"))?,
                None => config.material.kind,
            };
            Some(umesh_core::fem::MaterialParams {
                kind,
                poisson: p.unwrap_or(config.material.poisson),
                young_pa: e.unwrap_or(config.material.young_pa),
            })
        }
    };
    let loads = umesh_core::loads::LoadFamily::parse(&a.loads).context("--loads")?;
    let settings = SynthSettings {
        loads,
        first_load: a.first_load,
        cloud_points: a.cloud_points,
        attachment_shift_mm: match a.attachment_shift_mm.as_slice() {
            [] => None,
            [x, y, z] if [x, y, z].iter().all(|v| v.is_finite() && v.abs() <= 200.0) => Some([*x, *y, *z]),
            v => anyhow::bail!("--attachment-shift-mm {v:?}: three finite values x,y,z within 200 mm"),
        },
        camera_motion_mm: a.camera_motion_mm,
        camera_motion_deg: a.camera_motion_deg,
        instruments: a.instruments,
        material,
        frames: a.frames,
        fps: a.fps,
        width: a.width,
        height: a.height,
        focal_px: a.focal_px,
        noise_mm: a.noise_mm,
        holes: a.holes,
        markers: a.markers,
        load_scale: a.load_scale,
        seed: a.seed,
        ..Default::default()
    };
    let (pb, progress) = super::output::progress_bar("synthetic recording");
    // Written beside --out and swapped in whole: no frame of an earlier recording survives.
    let mut inputs = a.input.paths();
    inputs.push(("--model", model_dir.as_path()));
    umesh_core::check_apart(&a.out, &inputs)?;
    let staged =
        umesh_core::StagedDir::new(&a.out, umesh_core::OutputKind::Recording, &["synth.json", "ground_truth.json"])
            .with_context(|| format!("--out {}", a.out.display()))?;
    let r = run_rgbd_synth(&seg, &config, &settings, staged.path(), &progress, &super::output::cancel());
    pb.finish_and_clear();
    let mut r = r.with_context(|| format!("writing the recording {}", a.out.display()))?;
    staged.commit().with_context(|| format!("replacing {}", a.out.display()))?;
    r.out = a.out.clone();
    if a.json {
        super::output::print_json(&serde_json::to_value(&r)?);
    } else {
        println!(
            "{} frames in {} ({} markers; mean marker displacement at the last frame {:.2} mm, max {:.2} mm; FE {:.1} s)",
            r.frames,
            r.out.display(),
            r.markers,
            r.mean_marker_displacement_mm,
            r.max_marker_displacement_mm,
            r.solve_ms_total / 1e3
        );
        if r.load_reached < 1.0 {
            println!(
                "the truth took {:.0} % of the final load and no more (the later frames hold that state)",
                100.0 * r.load_reached
            );
        }
        if let Some(s) = r.attachment_shift_mm {
            println!(
                "attachment moved by {:.1},{:.1},{:.1} mm: {} nodes held (the model assumes {})",
                s[0], s[1], s[2], r.fixed_nodes, r.dataset_fixed_nodes
            );
        }
    }
    Ok(())
}

fn serve(a: ServeArgs) -> Result<()> {
    let rec = Recording::open(&a.recording, a.intrinsics.as_deref())?;
    let fps = a.fps.unwrap_or(rec.meta.fps).max(0.1);
    let depth_scale = rec.meta.depth_scale;
    let listener = std::net::TcpListener::bind(&a.listen).with_context(|| format!("listening on {}", a.listen))?;
    eprintln!("serving {} ({} frames at {fps} fps) on {}", a.recording.display(), rec.len(), a.listen);
    let (mut sock, peer) = listener.accept()?;
    eprintln!("client {peer}");
    let mut played = 0;
    let mut index = 0usize;
    loop {
        let mut src = RecordingSource::new(rec.clone());
        let start = Instant::now();
        let mut n = 0u32;
        loop {
            match src.poll(Duration::ZERO) {
                Poll::Frame(mut f) => {
                    f.timestamp_s = index as f64 / fps;
                    index += 1;
                    if let Err(e) = write_frame(&mut sock, &f, depth_scale) {
                        eprintln!("client gone: {e}");
                        return Ok(());
                    }
                    n += 1;
                    let due = start + Duration::from_secs_f64(n as f64 / fps);
                    std::thread::sleep(due.saturating_duration_since(Instant::now()));
                }
                Poll::Pending => continue,
                Poll::Ended(_) => break,
            }
            for l in src.take_log() {
                eprintln!("{l}");
            }
        }
        played += 1;
        if a.loops != 0 && played >= a.loops {
            return Ok(());
        }
    }
}
