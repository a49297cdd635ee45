//! Frame sources: recordings and live streams behind one trait.
//!
//! # TCP stream protocol (version 1)
//!
//! A camera bridge serves frames on a TCP port; umesh connects and reads. Each frame:
//!
//! ```text
//! magic        8 bytes  "UMRGBD01"
//! header_len   u32, little endian, at most 65536
//! header       header_len bytes of UTF-8 JSON:
//!              {"width": 640, "height": 480, "fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5,
//!               "timestamp_s": 12.345, "depth_scale": 1000.0, "color": true}
//! depth        width * height u16, little endian, `depth_scale` units per metre, 0 = no data
//! color        width * height * 3 u8 RGB, only when "color" is true
//! points       "points" * 3 f32, little endian, camera frame in mm (x, y, z per point),
//!              only when the header has "points" (a camera that gives a cloud)
//! ```
//!
//! Optional header fields: `"frame_number": N` (the camera's own frame counter; a gap is a
//! frame the camera or bridge dropped, counted as such), `"host_time_s": T` (Unix time at
//! which the bridge took the frame from the camera: the start of the end-to-end latency a
//! consumer on the same machine reports), `"points": N` (a cloud follows; registration uses it whole and the
//! depth image, which may be all zeros, only for display) and `"world_from_camera": [16
//! numbers]` (the tracked camera pose, row-major, mm), which `--pose tracked` keeps.
//!
//! A reader thread keeps only the newest complete frame: frames the consumer is too slow
//! for are dropped (and counted), never queued. A stream that stops mid-frame, or sends
//! nothing for `stall_timeout`, ends with an error message instead of stalling the pipeline.

use super::recording::Recording;
use super::{ColorImage, DepthImage, Frame, Intrinsics, MAX_PIXELS, MAX_POINTS, RgbdError};
use std::io::{Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

pub const MAGIC: &[u8; 8] = b"UMRGBD01";
const MAX_HEADER: u32 = 65536;

/// What a source gives when polled.
#[derive(Debug)]
pub enum Poll {
    Frame(Box<Frame>),
    /// No new frame yet.
    Pending,
    /// The source has ended; with the reason when it ended badly.
    Ended(Option<String>),
}

pub trait FrameSource: Send {
    /// A name for logs and the UI.
    fn describe(&self) -> String;
    /// Wait up to `timeout` for the next frame.
    fn poll(&mut self, timeout: Duration) -> Poll;
    /// Frames skipped because the consumer was late, or unreadable.
    fn dropped(&self) -> u64;
    /// Log lines (unreadable frames and the like) since the last call.
    fn take_log(&mut self) -> Vec<String> {
        Vec::new()
    }
}

/// A recording played back frame by frame (as fast as polled; pacing is the caller's).
#[derive(Debug)]
pub struct RecordingSource {
    pub recording: Recording,
    next: usize,
    dropped: u64,
    log: Vec<String>,
}

impl RecordingSource {
    pub fn new(recording: Recording) -> Self {
        let log = recording.warnings.clone();
        Self { recording, next: 0, dropped: 0, log }
    }
    pub fn seek(&mut self, frame: usize) {
        self.next = frame;
    }
}

impl FrameSource for RecordingSource {
    fn describe(&self) -> String {
        format!("recording {} ({} frames)", self.recording.dir.display(), self.recording.len())
    }
    fn poll(&mut self, _timeout: Duration) -> Poll {
        while self.next < self.recording.len() {
            let i = self.next;
            self.next += 1;
            match self.recording.read_frame(i) {
                Ok(f) => return Poll::Frame(Box::new(f)),
                Err(e) => {
                    self.dropped += 1;
                    self.log.push(format!("frame {i} skipped: {e}"));
                }
            }
        }
        Poll::Ended(None)
    }
    fn dropped(&self) -> u64 {
        self.dropped
    }
    fn take_log(&mut self) -> Vec<String> {
        std::mem::take(&mut self.log)
    }
}

/// A source whose first frame is read ahead, to see what the source carries (a tracked
/// pose, say), and then given first.
pub struct Peeked {
    first: Option<Box<Frame>>,
    ended: Option<Option<String>>,
    inner: Box<dyn FrameSource>,
}

impl Peeked {
    /// Wait up to `timeout` for the first frame.
    pub fn new(mut inner: Box<dyn FrameSource>, timeout: Duration) -> Self {
        let t0 = std::time::Instant::now();
        let (mut first, mut ended) = (None, None);
        while first.is_none() && ended.is_none() && t0.elapsed() < timeout {
            match inner.poll(timeout.saturating_sub(t0.elapsed()).max(Duration::from_millis(1))) {
                Poll::Frame(f) => first = Some(f),
                Poll::Ended(r) => ended = Some(r),
                Poll::Pending => {}
            }
        }
        Self { first, ended, inner }
    }

    pub fn first(&self) -> Option<&Frame> {
        self.first.as_deref()
    }
}

impl FrameSource for Peeked {
    fn describe(&self) -> String {
        self.inner.describe()
    }
    fn poll(&mut self, timeout: Duration) -> Poll {
        if let Some(f) = self.first.take() {
            return Poll::Frame(f);
        }
        if let Some(r) = self.ended.take() {
            return Poll::Ended(r);
        }
        self.inner.poll(timeout)
    }
    fn dropped(&self) -> u64 {
        self.inner.dropped()
    }
    fn take_log(&mut self) -> Vec<String> {
        self.inner.take_log()
    }
}

#[derive(serde::Serialize, serde::Deserialize)]
struct Header {
    width: usize,
    height: usize,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    timestamp_s: f64,
    depth_scale: f64,
    color: bool,
    #[serde(default, skip_serializing_if = "is_zero")]
    points: usize,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    world_from_camera: Option<[f64; 16]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    frame_number: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    host_time_s: Option<f64>,
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

/// Write one frame in the stream protocol.
pub fn write_frame<W: Write>(w: &mut W, frame: &Frame, depth_scale: f64) -> std::io::Result<()> {
    let k = frame.intrinsics;
    let h = Header {
        width: k.width,
        height: k.height,
        fx: k.fx,
        fy: k.fy,
        cx: k.cx,
        cy: k.cy,
        timestamp_s: frame.timestamp_s,
        depth_scale,
        color: frame.color.is_some(),
        points: frame.points.as_ref().map_or(0, Vec::len),
        world_from_camera: frame.world_from_camera.map(|m| {
            let mut a = [0.0; 16];
            a.copy_from_slice(m.transpose().as_slice());
            a
        }),
        frame_number: frame.device_frame,
        host_time_s: frame.host_time_s,
    };
    let header = serde_json::to_vec(&h).map_err(std::io::Error::other)?;
    let mut buf = Vec::with_capacity(12 + header.len() + k.width * k.height * 5);
    buf.extend_from_slice(MAGIC);
    buf.extend_from_slice(&(header.len() as u32).to_le_bytes());
    buf.extend_from_slice(&header);
    let s = (depth_scale / 1000.0) as f32;
    for &d in &frame.depth.depth_mm {
        buf.extend_from_slice(&((d * s).round().clamp(0.0, 65535.0) as u16).to_le_bytes());
    }
    if let Some(c) = &frame.color {
        buf.extend_from_slice(&c.rgb);
    }
    for p in frame.points.iter().flatten() {
        for v in p.iter() {
            buf.extend_from_slice(&(*v as f32).to_le_bytes());
        }
    }
    w.write_all(&buf)
}

/// Read one frame; Ok(None) on a clean end of stream (between frames).
pub fn read_frame<R: Read>(r: &mut R, index: usize) -> Result<Option<Frame>, crate::Invalid> {
    Ok(read_frame_scaled(r, index)?.map(|(f, _)| f))
}

/// [`read_frame`] with the frame's raw depth units per metre (`depth_scale` of its header).
pub fn read_frame_scaled<R: Read>(r: &mut R, index: usize) -> Result<Option<(Frame, f64)>, crate::Invalid> {
    let mut magic = [0u8; 8];
    match r.read(&mut magic[..1]) {
        Ok(0) => return Ok(None),
        Ok(_) => {}
        Err(e) => return Err(crate::Invalid(format!("read: {e}"))),
    }
    let cut = |e: std::io::Error, what: &str| format!("the stream stopped inside a frame ({what}): {e}");
    r.read_exact(&mut magic[1..]).map_err(|e| cut(e, "magic"))?;
    if &magic != MAGIC {
        return Err(crate::Invalid(format!("bad magic {magic:?}: not a umesh RGB-D stream (UMRGBD01)")));
    }
    let mut len = [0u8; 4];
    r.read_exact(&mut len).map_err(|e| cut(e, "header length"))?;
    let len = u32::from_le_bytes(len);
    if len == 0 || len > MAX_HEADER {
        return Err(crate::Invalid(format!("header length {len} outside 1..={MAX_HEADER}")));
    }
    let mut header = vec![0u8; len as usize];
    r.read_exact(&mut header).map_err(|e| cut(e, "header"))?;
    let h: Header = serde_json::from_slice(&header).map_err(|e| format!("bad frame header: {e}"))?;
    let k = Intrinsics { width: h.width, height: h.height, fx: h.fx, fy: h.fy, cx: h.cx, cy: h.cy };
    k.validate().map_err(|e| format!("frame header: {e}"))?;
    if !(h.depth_scale.is_finite() && h.depth_scale > 0.0) {
        return Err(crate::Invalid(format!("frame header: depth_scale {} must be finite and positive", h.depth_scale)));
    }
    debug_assert!(k.width * k.height <= MAX_PIXELS);
    if h.points > MAX_POINTS {
        return Err(crate::Invalid(format!("frame header: {} points, at most {MAX_POINTS}", h.points)));
    }
    let world_from_camera = match h.world_from_camera {
        Some(m) if m.iter().all(|v| v.is_finite()) => Some(nalgebra::Matrix4::from_row_slice(&m)),
        Some(_) => {
            return Err(crate::Invalid::from("frame header: world_from_camera holds a value that is not finite"));
        }
        None => None,
    };
    let n = k.width * k.height;
    let mut raw = vec![0u8; 2 * n];
    r.read_exact(&mut raw).map_err(|e| cut(e, "depth"))?;
    let to_mm = (1000.0 / h.depth_scale) as f32;
    let depth_mm = raw.chunks_exact(2).map(|b| u16::from_le_bytes([b[0], b[1]]) as f32 * to_mm).collect();
    let color = if h.color {
        let mut rgb = vec![0u8; 3 * n];
        r.read_exact(&mut rgb).map_err(|e| cut(e, "colour"))?;
        Some(ColorImage { width: k.width, height: k.height, rgb })
    } else {
        None
    };
    let points = if h.points > 0 {
        let mut raw = vec![0u8; 12 * h.points];
        r.read_exact(&mut raw).map_err(|e| cut(e, "points"))?;
        let f = |b: &[u8]| f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64;
        let pts: Vec<nalgebra::Vector3<f64>> =
            raw.chunks_exact(12).map(|b| nalgebra::Vector3::new(f(&b[0..4]), f(&b[4..8]), f(&b[8..12]))).collect();
        if pts.iter().any(|p| !p.iter().all(|v| v.is_finite())) {
            return Err(crate::Invalid::from("a point of the frame's cloud is not finite"));
        }
        Some(pts)
    } else {
        None
    };
    // A cloud with an empty depth image: its splat, so that segmentation and display see it.
    let mut depth = DepthImage { width: k.width, height: k.height, depth_mm };
    if let Some(p) = &points
        && depth.depth_mm.iter().all(|&d| d == 0.0)
    {
        depth = super::recording::splat_points(p, &k);
    }
    if !h.timestamp_s.is_finite() {
        return Err(crate::Invalid(format!("frame header: timestamp_s {} is not finite", h.timestamp_s)));
    }
    let frame = Frame {
        index,
        timestamp_s: h.timestamp_s,
        intrinsics: k,
        depth,
        color,
        mask: None,
        world_from_camera,
        points,
        device_frame: h.frame_number,
        host_time_s: h.host_time_s.filter(|t| t.is_finite()),
    };
    Ok(Some((frame, h.depth_scale)))
}

/// What a reader thread hands its source: the newest frame (or, keeping all, the next ones).
#[derive(Default)]
struct Shared {
    frames: std::collections::VecDeque<Frame>,
    ended: Option<Option<String>>,
    received: u64,
    dropped: u64,
    depth_scale: Option<f64>,
    last_device_frame: Option<u64>,
    /// The source was dropped: a reader waiting for room stops.
    closed: bool,
}

/// A thread reading frames in the stream protocol from `reader` into a shared slot.
/// `keep_all`: every frame is kept (at most 4 waiting; the reader then waits for the consumer,
/// so a recording played as fast as it is read loses nothing); otherwise only the newest,
/// the ones replaced counted as dropped. Gaps in the frames' `frame_number` count as dropped.
/// `on_end` is called once the stream ends and gives the reason when it ended badly (a
/// bridge process's exit status and last message, say).
pub(crate) struct FrameReader {
    shared: Arc<(Mutex<Shared>, Condvar)>,
    ended_reported: bool,
}

const KEEP_ALL_DEPTH: usize = 4;

impl FrameReader {
    pub(crate) fn spawn<R, E>(mut reader: R, name: &str, keep_all: bool, on_end: E) -> Result<Self, RgbdError>
    where
        R: Read + Send + 'static,
        E: FnOnce(Option<String>) -> Option<String> + Send + 'static,
    {
        let shared: Arc<(Mutex<Shared>, Condvar)> = Arc::default();
        let sh = shared.clone();
        std::thread::Builder::new()
            .name(name.into())
            .spawn(move || {
                let mut index = 0;
                let mut on_end = Some(on_end);
                loop {
                    let r = read_frame_scaled(&mut reader, index);
                    let (lock, cv) = &*sh;
                    let (f, scale) = match r {
                        Ok(Some(fs)) => fs,
                        Ok(None) | Err(_) => {
                            // The end's reason (a bridge's exit status, say) is found unlocked.
                            let reason = match r {
                                Err(e) => Some(on_end.take().and_then(|f| f(Some(e.0.clone()))).unwrap_or(e.0)),
                                _ => on_end.take().and_then(|e| e(None)),
                            };
                            if let Ok(mut s) = lock.lock() {
                                s.ended = Some(reason);
                            }
                            cv.notify_all();
                            return;
                        }
                    };
                    let Ok(mut s) = lock.lock() else { return };
                    index += 1;
                    s.received += 1;
                    s.depth_scale = Some(scale);
                    if let (Some(prev), Some(n)) = (s.last_device_frame, f.device_frame)
                        && n > prev + 1
                    {
                        s.dropped += n - prev - 1;
                    }
                    s.last_device_frame = f.device_frame.or(s.last_device_frame);
                    if keep_all {
                        while s.frames.len() >= KEEP_ALL_DEPTH {
                            if s.closed {
                                return;
                            }
                            match cv.wait(s) {
                                Ok(g) => s = g,
                                Err(_) => return,
                            }
                        }
                    } else if s.frames.pop_front().is_some() {
                        s.dropped += 1;
                    }
                    s.frames.push_back(f);
                    drop(s);
                    cv.notify_all();
                }
            })
            .map_err(|source| RgbdError::StreamIo { what: "cannot start the reader thread".into(), source })?;
        Ok(Self { shared, ended_reported: false })
    }

    pub(crate) fn poll(&mut self, timeout: Duration) -> Poll {
        let (lock, cv) = &*self.shared;
        let Ok(guard) = lock.lock() else { return Poll::Ended(Some("reader thread failed".into())) };
        let Ok((mut s, _)) = cv.wait_timeout_while(guard, timeout, |s| s.frames.is_empty() && s.ended.is_none()) else {
            return Poll::Ended(Some("reader thread failed".into()));
        };
        if let Some(f) = s.frames.pop_front() {
            drop(s);
            // A reader waiting for room (keep_all) goes on.
            cv.notify_all();
            return Poll::Frame(Box::new(f));
        }
        match &s.ended {
            Some(reason) if !self.ended_reported => {
                self.ended_reported = true;
                Poll::Ended(reason.clone())
            }
            Some(_) => Poll::Ended(None),
            None => Poll::Pending,
        }
    }

    pub(crate) fn received(&self) -> u64 {
        self.shared.0.lock().map(|s| s.received).unwrap_or(0)
    }

    pub(crate) fn dropped(&self) -> u64 {
        self.shared.0.lock().map(|s| s.dropped).unwrap_or(0)
    }

    /// Raw depth units per metre of the last frame read.
    pub(crate) fn depth_scale(&self) -> Option<f64> {
        self.shared.0.lock().ok().and_then(|s| s.depth_scale)
    }
}

impl Drop for FrameReader {
    fn drop(&mut self) {
        if let Ok(mut s) = self.shared.0.lock() {
            s.closed = true;
        }
        self.shared.1.notify_all();
    }
}

/// A live TCP source (see the module docs for the protocol).
pub struct TcpSource {
    addr: String,
    reader: FrameReader,
    stream: TcpStream,
}

impl std::fmt::Debug for TcpSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TcpSource").field("addr", &self.addr).finish()
    }
}

impl TcpSource {
    /// Connect to a bridge at `addr` ("host:port"). A stream silent for `stall_timeout` ends.
    pub fn connect(addr: &str, stall_timeout: Duration) -> Result<Self, RgbdError> {
        let sock = addr
            .to_socket_addrs()
            .map_err(|source| RgbdError::StreamIo { what: addr.into(), source })?
            .next()
            .ok_or_else(|| RgbdError::Stream(format!("{addr}: no address")))?;
        let stream = TcpStream::connect_timeout(&sock, Duration::from_secs(5))
            .map_err(|source| RgbdError::StreamIo { what: format!("{addr}: cannot connect"), source })?;
        let io = |what: &str| {
            let what = format!("{addr}: {what}");
            move |source| RgbdError::StreamIo { what, source }
        };
        stream.set_read_timeout(Some(stall_timeout)).map_err(io("the read timeout"))?;
        let reader = std::io::BufReader::with_capacity(1 << 20, stream.try_clone().map_err(io("a second handle"))?);
        let reader = FrameReader::spawn(reader, "umesh-tcp-source", false, |reason| reason)?;
        Ok(Self { addr: addr.to_string(), reader, stream })
    }

    pub fn received(&self) -> u64 {
        self.reader.received()
    }
}

impl Drop for TcpSource {
    fn drop(&mut self) {
        let _ = self.stream.shutdown(std::net::Shutdown::Both);
    }
}

impl FrameSource for TcpSource {
    fn describe(&self) -> String {
        format!("tcp://{}", self.addr)
    }
    fn poll(&mut self, timeout: Duration) -> Poll {
        self.reader.poll(timeout)
    }
    fn dropped(&self) -> u64 {
        self.reader.dropped()
    }
}
