//! `umesh rgbd import` (a RealSense recording to a recording folder) and `umesh rgbd
//! realsense` (a RealSense camera or recording served over umesh's stream protocol, with a
//! tracked pose from a file or a tracker socket).

use anyhow::{Context, Result, bail};
use nalgebra::Matrix4;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use umesh_core::rgbd::import::run_rgbd_import;
use umesh_core::rgbd::realsense::{RealSenseRequest, RealSenseSource, list_devices};
use umesh_core::rgbd::recording::read_trajectory_log;
use umesh_core::rgbd::stream::{FrameSource, Poll, write_frame};

#[derive(clap::Args, Debug)]
pub struct ImportArgs {
    /// A RealSense recording: .db3 (librealsense 2.56 and later) or .bag (before).
    pub file: PathBuf,
    /// The recording folder to write (depth aligned to colour, colour, intrinsics, frames.json).
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long)]
    pub json: bool,
}

/// Import `file` into the folder `out`, swapped in whole at the end.
pub fn import_to(file: &Path, out: &Path) -> Result<umesh_core::rgbd::import::ImportReport> {
    umesh_core::check_apart(out, &[("FILE", file)])?;
    let staged = umesh_core::StagedDir::new(out, umesh_core::OutputKind::Recording, &["import.json", "frames.json"])
        .with_context(|| format!("--out {}", out.display()))?;
    let (pb, progress) = super::output::progress_bar("importing");
    let r = run_rgbd_import(file, staged.path(), &progress, &super::output::cancel());
    pb.finish_and_clear();
    let r = r?;
    staged.commit().with_context(|| format!("replacing {}", out.display()))?;
    Ok(r)
}

pub fn import(a: ImportArgs) -> Result<()> {
    let r = import_to(&a.file, &a.out)?;
    for w in &r.warnings {
        eprintln!("{w}");
    }
    if a.json {
        let mut v = serde_json::to_value(&r)?;
        v["out"] = serde_json::json!(a.out);
        super::output::print_json(&v);
    } else {
        let k = r.intrinsics;
        println!(
            "{} frames into {} ({}x{}, fx {:.1}, {:.1} fps, {:.0} depth units a metre); {} dropped by the camera{}",
            r.frames,
            a.out.display(),
            k.width,
            k.height,
            k.fx,
            r.fps,
            r.depth_scale,
            r.dropped,
            if r.frames_without_color > 0 {
                format!(", {} without colour", r.frames_without_color)
            } else {
                String::new()
            }
        );
    }
    Ok(())
}

#[derive(clap::Args, Debug)]
pub struct RealSenseArgs {
    /// List the connected RealSense cameras and exit.
    #[arg(long)]
    pub list: bool,
    /// Serve a recording (.db3 or .bag) instead of a camera.
    #[arg(long, conflicts_with = "serial")]
    pub file: Option<PathBuf>,
    /// With --file: play at the recording's own rate (default: as fast as the client takes
    /// frames).
    #[arg(long, requires = "file")]
    pub realtime: bool,
    /// The camera's serial number (default: the first one connected).
    #[arg(long)]
    pub serial: Option<String>,
    #[arg(long, default_value_t = RealSenseRequest::default().width)]
    pub width: usize,
    #[arg(long, default_value_t = RealSenseRequest::default().height)]
    pub height: usize,
    #[arg(long, default_value_t = RealSenseRequest::default().fps)]
    pub fps: u32,
    #[arg(long, default_value = "127.0.0.1:7878")]
    pub listen: String,
    /// Also record what the camera streams to this .db3 (for later review: `umesh rgbd import`
    /// or `umesh register --recording FILE.db3`).
    #[arg(long, conflicts_with = "file")]
    pub record: Option<PathBuf>,
    /// Tracked camera poses, one per frame in order (Open3D .log, world_from_camera, metres);
    /// the last is kept once they run out.
    #[arg(long, conflicts_with = "pose_socket")]
    pub pose_file: Option<PathBuf>,
    /// A tracker at host:port sending one pose a line: 16 numbers, row-major, mm
    /// (world_from_marker of the marker on the camera); the newest is used.
    #[arg(long)]
    pub pose_socket: Option<String>,
    /// Hand-eye calibration: marker_from_camera (Open3D .log with one pose), so that
    /// world_from_camera = world_from_marker * marker_from_camera. Default: identity (the
    /// tracker already reports the camera).
    #[arg(long)]
    pub hand_eye: Option<PathBuf>,
}

fn check_rigid(m: &Matrix4<f64>, what: &str) -> Result<()> {
    umesh_core::rgbd::check_rigid(m).map_err(|e| anyhow::anyhow!("{what}: {e}"))
}

/// Where each served frame's pose comes from.
enum PoseSource {
    None,
    File(Vec<Matrix4<f64>>),
    Socket(Arc<Mutex<(Option<Matrix4<f64>>, Option<String>)>>),
}

impl PoseSource {
    fn open(a: &RealSenseArgs) -> Result<(Self, Matrix4<f64>)> {
        let hand_eye = match &a.hand_eye {
            Some(p) => {
                // read_trajectory_log refuses a pose that is not rigid.
                *read_trajectory_log(p)?.first().with_context(|| format!("--hand-eye {}: no pose", p.display()))?
            }
            None => Matrix4::identity(),
        };
        let src = match (&a.pose_file, &a.pose_socket) {
            (Some(p), _) => {
                let poses = read_trajectory_log(p).with_context(|| format!("--pose-file {}", p.display()))?;
                if poses.is_empty() {
                    bail!("--pose-file {}: no pose", p.display());
                }
                PoseSource::File(poses)
            }
            (None, Some(addr)) => {
                let sock = std::net::TcpStream::connect(addr)
                    .with_context(|| format!("--pose-socket {addr}: cannot connect"))?;
                let state: Arc<Mutex<(Option<Matrix4<f64>>, Option<String>)>> = Arc::default();
                let st = state.clone();
                let addr = addr.clone();
                std::thread::spawn(move || {
                    for line in BufReader::new(sock).lines() {
                        let parsed = line.map_err(|e| e.to_string()).and_then(|l| {
                            let v: Vec<f64> = l
                                .split([' ', ',', '\t'])
                                .filter(|s| !s.is_empty())
                                .filter_map(|s| s.parse().ok())
                                .collect();
                            if v.len() != 16 {
                                return Err(format!("a line of {} numbers, 16 expected", v.len()));
                            }
                            let m = Matrix4::from_row_slice(&v);
                            check_rigid(&m, "the pose").map_err(|e| e.to_string())?;
                            Ok(m)
                        });
                        let Ok(mut s) = st.lock() else { return };
                        match parsed {
                            Ok(m) => *s = (Some(m), None),
                            Err(e) => {
                                s.1 = Some(format!("--pose-socket {addr}: {e}"));
                                return;
                            }
                        }
                    }
                    if let Ok(mut s) = st.lock() {
                        s.1 = Some(format!("--pose-socket {addr}: the tracker closed the connection"));
                    }
                });
                PoseSource::Socket(state)
            }
            (None, None) => PoseSource::None,
        };
        Ok((src, hand_eye))
    }

    fn pose(&self, index: usize) -> Result<Option<Matrix4<f64>>> {
        Ok(match self {
            PoseSource::None => None,
            PoseSource::File(p) => Some(p[index.min(p.len() - 1)]),
            PoseSource::Socket(s) => {
                let s = s.lock().map_err(|_| anyhow::anyhow!("the tracker thread failed"))?;
                if let Some(e) = &s.1 {
                    bail!("{e}");
                }
                s.0
            }
        })
    }
}

pub fn realsense(a: RealSenseArgs) -> Result<()> {
    if a.list {
        let devices = list_devices()?;
        if devices.is_empty() {
            println!("no RealSense camera is connected");
        }
        for d in devices {
            println!(
                "{}  serial {}  firmware {}  USB {}",
                d.name.unwrap_or_default(),
                d.serial.unwrap_or_default(),
                d.firmware.unwrap_or_default(),
                d.usb.unwrap_or_default()
            );
        }
        return Ok(());
    }
    let request = RealSenseRequest {
        file: a.file.clone(),
        serial: a.serial.clone(),
        width: a.width,
        height: a.height,
        fps: a.fps,
        realtime: a.realtime,
        record: a.record.clone(),
    };
    request.validate().map_err(|e| anyhow::anyhow!("{e}"))?;
    let (poses, hand_eye) = PoseSource::open(&a)?;
    let listener = std::net::TcpListener::bind(&a.listen).with_context(|| format!("listening on {}", a.listen))?;
    eprintln!("serving {} on {}", request.describe(), a.listen);
    let (mut sock, peer) = listener.accept()?;
    sock.set_nodelay(true).ok();
    eprintln!("client {peer}");
    // The camera starts once a client is there: its first frames are not dropped waiting.
    let mut src = RealSenseSource::open(&request)?;
    let t0 = Instant::now();
    let mut sent = 0usize;
    loop {
        for l in src.take_log() {
            eprintln!("{l}");
        }
        match src.poll(Duration::from_millis(200)) {
            Poll::Frame(mut f) => {
                if let Some(p) = poses.pose(sent)? {
                    f.world_from_camera = Some(p * hand_eye);
                }
                if let Err(e) = write_frame(&mut sock, &f, src.depth_scale().unwrap_or(1000.0)) {
                    eprintln!("client gone after {sent} frames: {e}");
                    return Ok(());
                }
                sent += 1;
            }
            Poll::Pending => {}
            Poll::Ended(reason) => {
                for l in src.take_log() {
                    eprintln!("{l}");
                }
                let secs = t0.elapsed().as_secs_f64();
                eprintln!(
                    "{sent} frames sent in {secs:.1} s; {} dropped (the camera's gaps and frames the client was late for)",
                    src.dropped()
                );
                return match reason {
                    None => Ok(()),
                    Some(r) => bail!("{}: {r}", request.describe()),
                };
            }
        }
    }
}
