//! The AR view's engine: a worker thread owns the source (a recording, a RealSense camera or
//! recording through the bridge, or a live TCP stream), the network and the registrar, and sends overlay frames back; the UI sends it
//! play / pause / step / seek / ICP / pose commands. The UI thread never waits for it.

pub mod panel;
pub mod view;

use crate::app::state::ActiveModel;
use anyhow::Context;
use bevy::prelude::*;
use nalgebra::{Matrix4, Rotation3, Vector3};
use std::path::PathBuf;
use std::sync::mpsc::{Receiver, Sender, TryRecvError, channel};
use std::time::{Duration, Instant};
use umesh_core::dataset::DatasetContext;
use umesh_core::register::RegistrationContext;
use umesh_core::register::correction::{CorrectionForm, CorrectionSettings};
use umesh_core::register::pipeline::{FrameReport, GroundTruth, PosePolicy, RegisterSettings, Registrar, choose_pose};
use umesh_core::rgbd::realsense::{RealSenseRequest, RealSenseSource};
use umesh_core::rgbd::recording::Recording;
use umesh_core::rgbd::segment::segment_frame;
use umesh_core::rgbd::stream::{FrameSource, Peeked, Poll, TcpSource};
use umesh_core::rgbd::{ColorImage, Frame};
use umesh_core::segmentation::Segmentation;

#[derive(Clone, Debug)]
pub enum ArSource {
    Recording(PathBuf),
    Tcp(String),
    /// A RealSense camera, or a RealSense recording played at its own rate, through the bridge.
    RealSense(RealSenseRequest),
}

#[derive(Clone, Debug)]
pub enum ArCommand {
    Play(bool),
    /// Frames forward (positive) or back (negative); recordings only.
    Step(i64),
    Seek(usize),
    /// Redo the rigid alignment on the current frame.
    Icp,
    /// Offset of the initial pose: translation in camera axes (mm) and rotation about the
    /// camera's axes (degrees); the alignment restarts from it.
    PoseOffset([f64; 3], [f64; 3]),
    /// Write each overlay to this folder as PNG (None: stop).
    Record(Option<PathBuf>),
    ShowPoints(bool),
    /// The physics correction after each prediction (`CorrectionSettings::off()`: none).
    Correction(CorrectionSettings),
    /// Where the camera pose comes from (None: as the source carries it, `choose_pose`); the
    /// alignment restarts with it.
    Pose(Option<PosePolicy>),
    Stop,
}

pub struct ArFrame {
    pub index: usize,
    pub image: ColorImage,
    pub report: FrameReport,
    pub received: Instant,
    /// Frames the live source dropped so far (the camera's gaps, frames arriving while one
    /// was registered).
    pub dropped: u64,
}

/// Wakes the UI's event loop from another thread.
pub type Waker = Box<dyn Fn() + Send>;

struct EventSender {
    tx: Sender<ArEvent>,
    wake: Option<Waker>,
}

impl EventSender {
    fn send(&self, e: ArEvent) -> Result<(), std::sync::mpsc::SendError<ArEvent>> {
        let r = self.tx.send(e);
        if let Some(w) = &self.wake {
            w();
        }
        r
    }
}

pub enum ArEvent {
    Opened {
        label: String,
        frames: Option<usize>,
        fps: f64,
        truth: bool,
    },
    /// The pose policy in use and why (`choose_pose`).
    Pose(PosePolicy, String),
    Frame(Box<ArFrame>),
    Log(String),
    Ended(String),
    Failed(String),
}

/// A running AR session: its channels and thread.
pub struct ArSession {
    tx: Sender<ArCommand>,
    rx: std::sync::Mutex<Receiver<ArEvent>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl ArSession {
    /// `wake` is called after each event: the window, updating only on demand, wakes up.
    pub fn start(source: ArSource, seg: std::sync::Arc<Segmentation>, model: ActiveModel, wake: Option<Waker>) -> Self {
        let (tx, crx) = channel();
        let (etx, rx) = channel();
        let etx = EventSender { tx: etx, wake };
        let thread = std::thread::Builder::new()
            .name("ar".into())
            .spawn(move || {
                if let Err(e) = worker(source, &seg, &model, crx, &etx) {
                    let _ = etx.send(ArEvent::Failed(format!("{e:#}")));
                }
            })
            .ok();
        Self { tx, rx: std::sync::Mutex::new(rx), thread }
    }

    pub fn send(&self, c: ArCommand) {
        let _ = self.tx.send(c);
    }
}

impl Drop for ArSession {
    fn drop(&mut self) {
        let _ = self.tx.send(ArCommand::Stop);
        // The worker checks its commands between frames; do not block the UI on it.
        drop(self.thread.take());
    }
}

enum Src {
    Recording(std::sync::Arc<Recording>, usize),
    Live(Box<dyn FrameSource>),
}

fn pose_with_offset(base: &Matrix4<f64>, t_mm: [f64; 3], r_deg: [f64; 3]) -> Matrix4<f64> {
    let r = Rotation3::from_euler_angles(r_deg[0].to_radians(), r_deg[1].to_radians(), r_deg[2].to_radians());
    let mut offset = Matrix4::identity();
    offset.fixed_view_mut::<3, 3>(0, 0).copy_from(r.matrix());
    offset.fixed_view_mut::<3, 1>(0, 3).copy_from(&Vector3::from(t_mm));
    // world_from_camera * offset: the offset is expressed in the camera's frame.
    base * offset
}

/// Tint every fourth segmented pixel: the observed organ points.
fn draw_points(img: &mut ColorImage, frame: &Frame, settings: &RegisterSettings) {
    let Ok(keep) = segment_frame(frame, &settings.segment) else { return };
    let w = frame.depth.width;
    for (i, &k) in keep.iter().enumerate() {
        let (u, v) = (i % w, i / w);
        if k && u % 4 == 0 && v % 4 == 0 && frame.depth.depth_mm[i] > 0.0 {
            img.blend(u, v, [0, 230, 255], 0.9);
        }
    }
}

fn worker(
    source: ArSource,
    seg: &Segmentation,
    am: &ActiveModel,
    rx: Receiver<ArCommand>,
    tx: &EventSender,
) -> anyhow::Result<()> {
    let log = |s: String| {
        let _ = tx.send(ArEvent::Log(s));
    };
    let mut net = umesh_net::inference::Predictor::load_checkpoint(&am.dir, &am.checkpoint)
        .with_context(|| am.dir.display().to_string())?;
    let config = umesh_workflow::input::model_dataset_config(Some(&net.info), seg);
    let dctx = DatasetContext::prepare(seg, &config, &umesh_core::Cancel::new())?;
    net.info
        .check_grid(&dctx.grid_hash(), dctx.grid.padded_shape())
        .with_context(|| format!("the model {} does not fit {}", am.dir.display(), seg.source.display()))?;
    let ctx = RegistrationContext::new(dctx, seg)?;
    // The form the panel starts with (the model's choice), as the panel reads it.
    let form = match umesh_core::register::correction::CorrectionChoice::read(&am.dir) {
        Ok(Some(c)) => c.choose(Some(umesh_core::register::correction::DEFAULT_FRAME_BUDGET_MS)).0,
        _ => CorrectionForm::Subspace,
    };
    let settings = RegisterSettings { overlay: true, ..Default::default() };
    let mut reg = Registrar::new(&ctx, settings.clone(), Matrix4::identity());
    // Its FE models and subspace before the source opens rather than in the first frame (half a
    // second on a 5000-node liver, seconds on a busy machine): a live source's frames would be
    // dropped.
    reg.set_correction(form.settings());
    reg.prepare_correction()?;
    let (mut src, base_pose, truth, label, fps, tracked) = open_source(&source, &ctx, &log)?;
    reg.reset(base_pose);
    let frames = match &src {
        Src::Recording(r, _) => Some(r.len()),
        Src::Live(_) => None,
    };
    let _ = tx.send(ArEvent::Opened { label, frames, fps, truth: truth.is_some() });
    let (pose, why) = choose_pose(None, tracked);
    reg.settings.pose = pose;
    let _ = tx.send(ArEvent::Pose(pose, why));
    let true_pose = truth.as_ref().map(|g| g.pose());
    let rest = truth.as_ref().map(|g| g.markers_rest_mm.as_slice());
    let mut state = Playback {
        playing: false,
        record: None,
        show_points: true,
        next_due: Instant::now(),
        want: Some(0),
        last_index: None,
    };
    // While a recording plays, the next frame's files are decoded on a helper thread during
    // this frame's registration (a few ms of PNG decoding off the frame's path).
    let mut prefetch: Option<(usize, std::thread::JoinHandle<Result<Frame, umesh_core::rgbd::RgbdError>>)> = None;
    loop {
        // Commands: block briefly when idle, so a paused session costs nothing.
        let cmd = if state.playing || state.want.is_some() {
            rx.try_recv().map_err(Some)
        } else {
            rx.recv_timeout(Duration::from_millis(50)).map_err(|_| None)
        };
        match cmd {
            Ok(ArCommand::Stop) | Err(Some(TryRecvError::Disconnected)) => return Ok(()),
            Ok(ArCommand::Pose(p)) => {
                let (pose, why) = choose_pose(p, tracked);
                reg.settings.pose = pose;
                reg.reset(reg.world_from_camera);
                state.want = state.last_index;
                let _ = tx.send(ArEvent::Pose(pose, why));
            }
            Ok(c) => state.apply(c, &mut reg, &src, &base_pose, &log)?,
            Err(_) => {}
        }
        // The frame to process now, if any.
        let frame: Option<Frame> = match &mut src {
            Src::Recording(rec, pos) => recording_frame(&mut state, rec, pos, fps, &mut prefetch, tx, &log),
            Src::Live(s) => live_frame(&mut state, s.as_mut(), tx, &log),
        };
        let Some(frame) = frame else { continue };
        let index = frame.index;
        state.last_index = Some(match &src {
            Src::Recording(_, p) => *p,
            Src::Live(_) => index,
        });
        let gt = truth.as_ref().and_then(|g| g.markers_mm.get(index)).map(|v| v.as_slice());
        match reg.process(&frame, &mut net, gt, rest, true_pose.as_ref()) {
            Ok(out) => {
                let Some(mut image) = out.overlay else { continue };
                if state.show_points {
                    draw_points(&mut image, &frame, &settings);
                }
                record_overlay(&mut state, index, &image, &log);
                let report = out.report;
                let dropped = match &src {
                    Src::Live(s) => s.dropped(),
                    Src::Recording(..) => 0,
                };
                let _ = tx.send(ArEvent::Frame(Box::new(ArFrame {
                    index: state.last_index.unwrap_or(index),
                    image,
                    report,
                    received: Instant::now(),
                    dropped,
                })));
            }
            Err(e) => log(format!("frame {index} skipped: {e:#}")),
        }
    }
}

/// The live source's next frame while playing (its log passed on; its end said and playback
/// stopped).
fn live_frame(state: &mut Playback, s: &mut dyn FrameSource, tx: &EventSender, log: &dyn Fn(String)) -> Option<Frame> {
    state.want = None;
    if !state.playing {
        return None;
    }
    for l in s.take_log() {
        log(l);
    }
    match s.poll(Duration::from_millis(100)) {
        Poll::Frame(f) => Some(*f),
        Poll::Pending => None,
        Poll::Ended(reason) => {
            for l in s.take_log() {
                log(l);
            }
            let _ = tx
                .send(ArEvent::Ended(format!("the live stream ended: {}", reason.unwrap_or_else(|| "closed".into()))));
            state.playing = false;
            None
        }
    }
}

/// While the session records: the overlay of frame `index` as a PNG in its folder (a write that
/// fails stops the recording, said once).
fn record_overlay(state: &mut Playback, index: usize, image: &ColorImage, log: &dyn Fn(String)) {
    let Some(dir) = &state.record else { return };
    let p = dir.join(format!("{index:05}.png"));
    match image.encode_png() {
        Ok(bytes) => {
            if let Err(e) = umesh_core::write_atomic(&p, &bytes) {
                log(format!("{}: {e:#}; recording stopped", p.display()));
                state.record = None;
            }
        }
        Err(e) => log(format!("{}: {e:#}", p.display())),
    }
}

/// A live source, its first frame read ahead: whether it carries a tracked pose, and a
/// source that fails at once (no library, no camera, a bad file) fails here with its reason.
fn open_live(s: Box<dyn FrameSource>, what: &str, log: &dyn Fn(String)) -> anyhow::Result<(Src, bool)> {
    let mut p = Peeked::new(s, Duration::from_secs(15));
    for l in p.take_log() {
        log(l);
    }
    if p.first().is_none() {
        match p.poll(Duration::ZERO) {
            Poll::Ended(Some(reason)) => anyhow::bail!("{what}: {reason}"),
            Poll::Ended(None) => anyhow::bail!("{what}: the source ended before its first frame"),
            _ => anyhow::bail!("{what}: no frame in 15 s"),
        }
    }
    let tracked = p.first().is_some_and(|f| f.world_from_camera.is_some());
    Ok((Src::Live(Box::new(p)), tracked))
}

/// Open the frames' source: a recording (its first tracked pose, ground truth if any, frame
/// rate) or a live one (starting from the training camera unless its frames carry a pose);
/// and whether it tracks the camera on every frame (`choose_pose`).
fn open_source(
    source: &ArSource,
    ctx: &RegistrationContext,
    log: &dyn Fn(String),
) -> anyhow::Result<(Src, Matrix4<f64>, Option<GroundTruth>, String, f64, bool)> {
    Ok(match &source {
        ArSource::Recording(dir) => {
            let rec = Recording::open(dir, None)?;
            for w in &rec.warnings {
                log(format!("warning: {w}"));
            }
            if rec.is_empty() {
                anyhow::bail!("{}: the recording holds no frame", dir.display());
            }
            let pose = rec.trajectory.as_ref().and_then(|t| t.first().copied()).with_context(|| {
                format!(
                    "{}: no trajectory.log, so no initial camera pose; the AR view needs one to start the alignment",
                    dir.display()
                )
            })?;
            let gt_path = dir.join("ground_truth.json");
            let truth = if gt_path.is_file() { Some(GroundTruth::read(&gt_path)?) } else { None };
            // The recording's rate from its timestamps (30 fps when they are missing).
            let fps = rec_fps(&rec).unwrap_or(30.0);
            let tracked = rec.tracks_every_frame();
            (Src::Recording(std::sync::Arc::new(rec), 0), pose, truth, dir.display().to_string(), fps, tracked)
        }
        ArSource::Tcp(addr) => {
            let s = TcpSource::connect(addr, Duration::from_secs(5)).with_context(|| addr.to_string())?;
            let (src, tracked) = open_live(Box::new(s), &format!("tcp://{addr}"), log)?;
            // Without a pose in its frames, start from the phantom's training camera.
            (src, default_pose(ctx), None, format!("tcp://{addr}"), 30.0, tracked)
        }
        ArSource::RealSense(req) => {
            let req = RealSenseRequest { realtime: true, ..req.clone() };
            let s = RealSenseSource::open(&req)?;
            let (src, tracked) = open_live(Box::new(s), &req.describe(), log)?;
            (src, default_pose(ctx), None, req.describe(), req.fps as f64, tracked)
        }
    })
}

/// Where a session's playback stands: what the commands change between frames.
struct Playback {
    playing: bool,
    record: Option<PathBuf>,
    show_points: bool,
    next_due: Instant,
    /// The frame to (re)process now.
    want: Option<usize>,
    last_index: Option<usize>,
}

impl Playback {
    /// Apply one command from the view (other than Stop).
    fn apply(
        &mut self,
        cmd: ArCommand,
        reg: &mut Registrar,
        src: &Src,
        base_pose: &Matrix4<f64>,
        log: &dyn Fn(String),
    ) -> anyhow::Result<()> {
        match cmd {
            ArCommand::Stop => {}
            ArCommand::Play(p) => {
                self.playing = p;
                self.next_due = Instant::now();
            }
            ArCommand::Step(d) => {
                self.playing = false;
                if let Src::Recording(r, _) = src {
                    let cur = self.last_index.unwrap_or(0);
                    self.want = Some((cur as i64 + d).clamp(0, r.len() as i64 - 1) as usize);
                }
            }
            ArCommand::Seek(f) => {
                if let Src::Recording(r, _) = src {
                    self.want = Some(f.min(r.len() - 1));
                }
            }
            ArCommand::Icp => {
                reg.reset(reg.world_from_camera);
                self.want = self.last_index;
                log("rigid alignment (ICP) requested".into());
            }
            ArCommand::PoseOffset(t, r) => {
                reg.reset(pose_with_offset(base_pose, t, r));
                self.want = self.last_index;
            }
            ArCommand::Record(dir) => {
                if let Some(d) = &dir {
                    std::fs::create_dir_all(d).with_context(|| d.display().to_string())?;
                }
                self.record = dir;
            }
            ArCommand::ShowPoints(s) => {
                self.show_points = s;
                self.want = self.last_index;
            }
            ArCommand::Correction(c) => {
                reg.set_correction(c);
                self.want = self.last_index;
            }
            // Resolved by the worker, which knows the source.
            ArCommand::Pose(_) => {}
        }
        Ok(())
    }
}

/// The recording's frame to process now, if any: the one asked for, else the next one due at
/// the recording's rate (skipping frames when processing is slower); the one after it is
/// decoded on a helper thread meanwhile.
fn recording_frame(
    state: &mut Playback,
    rec: &std::sync::Arc<Recording>,
    pos: &mut usize,
    fps: f64,
    prefetch: &mut Option<(usize, std::thread::JoinHandle<Result<Frame, umesh_core::rgbd::RgbdError>>)>,
    tx: &EventSender,
    log: &dyn Fn(String),
) -> Option<Frame> {
    let idx = if let Some(w) = state.want.take() {
        Some(w)
    } else if state.playing && Instant::now() >= state.next_due {
        // Keep the recording's rate: when processing is slower, skip frames.
        let late = state.next_due.elapsed().as_secs_f64();
        let skip = (late * fps).floor() as usize;
        let n = state.last_index.map(|i| i + 1 + skip).unwrap_or(0);
        state.next_due += Duration::from_secs_f64((1 + skip) as f64 / fps);
        if n >= rec.len() {
            state.playing = false;
            let _ = tx.send(ArEvent::Ended("end of the recording".into()));
            None
        } else {
            Some(n)
        }
    } else {
        if state.playing {
            std::thread::sleep(state.next_due.saturating_duration_since(Instant::now()).min(Duration::from_millis(20)));
        }
        None
    };
    match idx {
        Some(i) => {
            *pos = i;
            let read = match prefetch.take() {
                Some((j, h)) if j == i => h.join().unwrap_or_else(|_| rec.read_frame(i)),
                _ => rec.read_frame(i),
            };
            if state.playing && i + 1 < rec.len() {
                let r = rec.clone();
                *prefetch = Some((i + 1, std::thread::spawn(move || r.read_frame(i + 1))));
            }
            match read {
                Ok(f) => Some(f),
                Err(e) => {
                    log(format!("frame {i} skipped: {e:#}"));
                    state.last_index = Some(i);
                    None
                }
            }
        }
        None => None,
    }
}

fn rec_fps(rec: &Recording) -> Option<f64> {
    let n = rec.len();
    if n < 2 {
        return None;
    }
    let (a, b) = (rec.read_frame(0).ok()?.timestamp_s, rec.read_frame(n - 1).ok()?.timestamp_s);
    let fps = (n - 1) as f64 / (b - a);
    (fps.is_finite() && fps > 0.1 && fps < 1000.0).then_some(fps)
}

/// A camera 400 mm in front of the organ's anterior side, looking at it (RAS: from +y).
fn default_pose(ctx: &RegistrationContext) -> Matrix4<f64> {
    let (lo, hi) = ctx.surface.bounds().unwrap_or_default();
    let c = (lo + hi) * 0.5;
    let eye = c + Vector3::new(0.0, 400.0, 0.0);
    let z = (c - eye).normalize();
    let x = Vector3::new(1.0, 0.0, 0.0);
    let y = z.cross(&x);
    let mut m = Matrix4::identity();
    m.fixed_view_mut::<3, 1>(0, 0).copy_from(&x);
    m.fixed_view_mut::<3, 1>(0, 1).copy_from(&y);
    m.fixed_view_mut::<3, 1>(0, 2).copy_from(&z);
    m.fixed_view_mut::<3, 1>(0, 3).copy_from(&eye);
    m
}

/// The AR view's state in the app.
#[derive(Resource, Default)]
pub struct Ar {
    pub session: Option<ArSession>,
    pub source_text: String,
    pub live_text: String,
    pub label: String,
    pub frames: Option<usize>,
    pub fps: f64,
    pub has_truth: bool,
    pub playing: bool,
    pub scrub: usize,
    pub last: Option<ArFrame>,
    /// New image to upload to the UI texture.
    pub image_dirty: bool,
    pub log: Vec<String>,
    /// Display intervals between frames (s), for the shown frame rate.
    pub intervals: std::collections::VecDeque<f64>,
    pub offset_t_mm: [f64; 3],
    pub offset_r_deg: [f64; 3],
    pub record: bool,
    pub record_dir: String,
    pub show_points: bool,
    /// The physics correction after each prediction (on by default).
    pub correction: bool,
    /// ... in this form (each session starts with the model's choice within the default
    /// frame budget).
    pub form: CorrectionForm,
    /// A frame whose prediction the confidence rule doubts is not corrected as the FE fit
    /// (`CorrectionSettings::doubted`, on by default): every frame within the correction's time.
    pub keep_frame_time: bool,
    /// Where the camera pose comes from (None: as the source carries it).
    pub pose: Option<PosePolicy>,
    /// The policy in use and why, as the worker resolved it.
    pub pose_in_use: Option<(PosePolicy, String)>,
    /// The RealSense part of the source choice (`panel::camera_ui`).
    pub camera: CameraChoice,
    pub generation: u64,
}

impl Ar {
    pub fn displayed_fps(&self) -> Option<f64> {
        (self.intervals.len() >= 2).then(|| self.intervals.len() as f64 / self.intervals.iter().sum::<f64>())
    }
}

fn poll_ar(mut ar: ResMut<Ar>, mut messages: ResMut<crate::app::state::UiMessages>) {
    let Some(s) = &ar.session else { return };
    let events: Vec<ArEvent> = s.rx.lock().map(|r| r.try_iter().collect()).unwrap_or_default();
    for e in events {
        match e {
            ArEvent::Opened { label, frames, fps, truth } => {
                messages.info(format!(
                    "AR: {label} opened ({} frames at {fps:.1} fps{})",
                    frames.map(|n| n.to_string()).unwrap_or("live".into()),
                    if truth { ", with ground truth" } else { "" }
                ));
                ar.label = label;
                ar.frames = frames;
                ar.fps = fps;
                ar.has_truth = truth;
            }
            ArEvent::Pose(p, why) => {
                ar.log.push(format!("pose: {why}"));
                ar.pose_in_use = Some((p, why));
            }
            ArEvent::Frame(f) => {
                if let Some(prev) = &ar.last {
                    let dt = f.received.duration_since(prev.received).as_secs_f64();
                    ar.intervals.push_back(dt);
                    if ar.intervals.len() > 30 {
                        ar.intervals.pop_front();
                    }
                }
                ar.scrub = f.index;
                ar.last = Some(*f);
                ar.image_dirty = true;
                ar.generation += 1;
            }
            ArEvent::Log(l) => {
                ar.log.push(l);
                let n = ar.log.len();
                if n > 200 {
                    ar.log.drain(..n - 200);
                }
            }
            ArEvent::Ended(m) => {
                ar.playing = false;
                messages.info(format!("AR: {m}"));
            }
            ArEvent::Failed(e) => {
                ar.playing = false;
                ar.session = None;
                messages.error(format!("AR: {e:#}"));
                break;
            }
        }
    }
}

/// The RealSense cameras found (listed on a helper thread: the bridge takes about a second),
/// the one chosen, and a recording file to play.
#[derive(Default)]
pub struct CameraChoice {
    pub devices: Option<Result<Vec<umesh_core::rgbd::realsense::DeviceInfo>, String>>,
    pub listing: Option<std::sync::Mutex<Receiver<Result<Vec<umesh_core::rgbd::realsense::DeviceInfo>, String>>>>,
    pub chosen: usize,
    pub width: usize,
    pub height: usize,
    pub fps: u32,
    pub file: String,
}

impl CameraChoice {
    /// Start listing the cameras (the answer arrives in `poll`).
    pub fn list(&mut self) {
        let (tx, rx) = channel();
        std::thread::spawn(move || {
            let _ = tx.send(umesh_core::rgbd::realsense::list_devices().map_err(|e| e.to_string()));
        });
        self.listing = Some(std::sync::Mutex::new(rx));
    }

    pub fn poll(&mut self) {
        let got = self.listing.as_ref().and_then(|l| l.lock().ok().and_then(|r| r.try_recv().ok()));
        if let Some(r) = got {
            self.devices = Some(r);
            self.listing = None;
            self.chosen = 0;
        }
    }
}

pub struct ArPlugin;

impl Plugin for ArPlugin {
    fn build(&self, app: &mut App) {
        app.insert_resource(Ar { show_points: true, correction: true, ..Default::default() })
            .add_systems(Update, poll_ar);
    }
}
