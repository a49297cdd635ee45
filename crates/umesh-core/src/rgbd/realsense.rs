//! Intel RealSense cameras and recordings (`.bag` before librealsense 2.56, `.db3` since).
//!
//! Read through librealsense's own Python wrapper (`pyrealsense2`): one library reads live
//! devices and both recording formats, applies the device's intrinsics and depth units as the
//! camera does, and needs no native build here. A small bridge script (embedded in umesh,
//! `realsense_bridge.py`) runs under that Python and writes frames in umesh's stream protocol
//! on its standard output, depth aligned to colour; this module runs it and reads them as a
//! [`FrameSource`].
//!
//! The Python used: `UMESH_PYTHON` when set, else the environment `scripts/setup.sh` makes
//! (`~/.cache/umesh-python`), else `python3`.

use super::stream::{FrameReader, FrameSource, Poll};
use super::{Frame, RgbdError};
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::Duration;

const BRIDGE: &str = include_str!("realsense_bridge.py");

/// The Python interpreter that has `pyrealsense2`.
pub fn python() -> PathBuf {
    if let Some(p) = std::env::var_os("UMESH_PYTHON") {
        return PathBuf::from(p);
    }
    if let Some(home) = std::env::var_os("HOME") {
        let venv = Path::new(&home).join(".cache/umesh-python/bin/python");
        if venv.is_file() {
            return venv;
        }
    }
    PathBuf::from("python3")
}

/// What to open: a recording file, or a connected camera (by serial, or the first one).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RealSenseRequest {
    pub file: Option<PathBuf>,
    pub serial: Option<String>,
    pub width: usize,
    pub height: usize,
    pub fps: u32,
    /// A recording played at its own rate (frames the reader is late for are dropped, as a
    /// live camera's would be) instead of as fast as it is read.
    pub realtime: bool,
    /// A connected camera: also record what it streams to this .db3 (librealsense's recorder).
    #[serde(default)]
    pub record: Option<PathBuf>,
}

impl Default for RealSenseRequest {
    fn default() -> Self {
        Self { file: None, serial: None, width: 640, height: 480, fps: 30, realtime: false, record: None }
    }
}

impl RealSenseRequest {
    pub fn recording(file: &Path) -> Self {
        Self { file: Some(file.to_path_buf()), ..Default::default() }
    }

    pub fn validate(&self) -> Result<(), crate::Invalid> {
        if self.file.is_some() && self.record.is_some() {
            return Err(crate::Invalid::from(
                "recording to a file is for a connected camera, not a recording played back",
            ));
        }
        if let Some(r) = &self.record
            && r.extension().is_none_or(|e| e != "db3")
        {
            return Err(crate::Invalid(format!("{}: librealsense records to a .db3 file", r.display())));
        }
        if let Some(f) = &self.file {
            if !f.is_file() {
                return Err(crate::Invalid(format!(
                    "{}: no such file (a RealSense recording, .bag or .db3)",
                    f.display()
                )));
            }
        } else {
            if !(1..=4096).contains(&self.width) || !(1..=4096).contains(&self.height) {
                return Err(crate::Invalid(format!(
                    "camera size {}x{}: each side 1 to 4096 pixels",
                    self.width, self.height
                )));
            }
            if !(1..=300).contains(&self.fps) {
                return Err(crate::Invalid(format!("camera rate {} fps: 1 to 300", self.fps)));
            }
        }
        Ok(())
    }

    pub fn describe(&self) -> String {
        match (&self.file, &self.serial) {
            (Some(f), _) => format!("RealSense recording {}", f.display()),
            (None, Some(s)) => format!("RealSense {s} ({}x{}, {} fps)", self.width, self.height, self.fps),
            (None, None) => format!("RealSense camera ({}x{}, {} fps)", self.width, self.height, self.fps),
        }
    }

    fn args(&self) -> Vec<String> {
        let mut a = vec!["stream".to_string()];
        match &self.file {
            Some(f) => {
                a.extend(["--file".into(), f.to_string_lossy().into_owned()]);
                if self.realtime {
                    a.push("--realtime".into());
                }
            }
            None => {
                if let Some(s) = &self.serial {
                    a.extend(["--serial".into(), s.clone()]);
                }
                if let Some(r) = &self.record {
                    a.extend(["--record".into(), r.to_string_lossy().into_owned()]);
                }
                a.extend([
                    "--width".into(),
                    self.width.to_string(),
                    "--height".into(),
                    self.height.to_string(),
                    "--fps".into(),
                    self.fps.to_string(),
                ]);
            }
        }
        a
    }
}

/// A connected camera, as `list_devices` finds it.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DeviceInfo {
    pub name: Option<String>,
    pub serial: Option<String>,
    pub firmware: Option<String>,
    pub usb: Option<String>,
}

/// What the bridge said on its standard error, one JSON object a line.
#[derive(Debug, Default)]
struct Messages {
    log: Vec<String>,
    error: Option<String>,
    summary: Option<serde_json::Value>,
}

impl Messages {
    fn take(&mut self, line: &str) {
        match serde_json::from_str::<serde_json::Value>(line) {
            Ok(v) if v.get("error").is_some() => self.error = v["error"].as_str().map(str::to_string),
            Ok(v) if v.get("summary").is_some() => self.summary = Some(v["summary"].clone()),
            Ok(v) if v.get("warning").is_some() => {
                self.log.push(format!("warning: {}", v["warning"].as_str().unwrap_or_default()))
            }
            Ok(v) if v.get("info").is_some() => self.log.push(v["info"].as_str().unwrap_or_default().to_string()),
            // librealsense's own log lines.
            _ if !line.trim().is_empty() => self.log.push(line.trim().to_string()),
            _ => {}
        }
    }
}

fn spawn(args: &[String]) -> Result<Child, RgbdError> {
    let py = python();
    Command::new(&py).arg("-c").arg(BRIDGE).args(args).stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().map_err(
        |e| {
            RgbdError::Stream(format!(
                "cannot run {} for the RealSense bridge ({e}): run scripts/setup.sh, or set UMESH_PYTHON to a Python with pyrealsense2",
                py.display()
            ))
        },
    )
}

/// The connected RealSense cameras (empty when none is plugged in).
pub fn list_devices() -> Result<Vec<DeviceInfo>, RgbdError> {
    let out = spawn(&["list".into()])?
        .wait_with_output()
        .map_err(|source| RgbdError::StreamIo { what: "the RealSense bridge".into(), source })?;
    let mut m = Messages::default();
    for l in String::from_utf8_lossy(&out.stderr).lines() {
        m.take(l);
    }
    if !out.status.success() {
        return Err(RgbdError::Stream(
            m.error.unwrap_or_else(|| format!("the RealSense bridge exited with {}", out.status)),
        ));
    }
    serde_json::from_slice(&out.stdout)
        .map_err(|e| RgbdError::Stream(format!("the RealSense bridge's device list: {e}")))
}

/// A RealSense camera or recording as a frame source. Live, the newest frame is kept (frames
/// the consumer is late for are dropped and counted); a recording played as fast as read
/// (`realtime: false`) loses none. The camera's own dropped frames (gaps in its frame
/// counter) are counted too.
pub struct RealSenseSource {
    request: RealSenseRequest,
    reader: FrameReader,
    child: Arc<Mutex<Child>>,
    messages: Arc<Mutex<Messages>>,
}

impl std::fmt::Debug for RealSenseSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RealSenseSource").field("request", &self.request).finish()
    }
}

impl RealSenseSource {
    pub fn open(request: &RealSenseRequest) -> Result<Self, RgbdError> {
        request.validate().map_err(|e| RgbdError::Stream(e.0))?;
        let mut child = spawn(&request.args())?;
        let (Some(stdout), Some(stderr)) = (child.stdout.take(), child.stderr.take()) else {
            let _ = child.kill();
            return Err(RgbdError::Stream("the RealSense bridge has no output pipes".into()));
        };
        let messages: Arc<Mutex<Messages>> = Arc::default();
        let m = messages.clone();
        let errors = std::thread::Builder::new()
            .name("umesh-realsense-log".into())
            .spawn(move || {
                for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                    if let Ok(mut m) = m.lock() {
                        m.take(&line);
                    }
                }
            })
            .map_err(|source| RgbdError::StreamIo { what: "cannot start the bridge's log reader".into(), source })?;
        let child = Arc::new(Mutex::new(child));
        let (c, m) = (child.clone(), messages.clone());
        let keep_all = request.file.is_some() && !request.realtime;
        let on_end = move |protocol_error: Option<String>| -> Option<String> {
            // The bridge's last word (its standard error closes when it exits).
            if protocol_error.is_some()
                && let Ok(mut c) = c.lock()
            {
                let _ = c.kill();
            }
            let _ = errors.join();
            // Waited for without holding the lock long: dropping the source kills it meanwhile.
            let mut status = None;
            for _ in 0..500 {
                match c.lock().map(|mut c| c.try_wait()) {
                    Ok(Ok(Some(s))) => {
                        status = Some(s);
                        break;
                    }
                    Ok(Ok(None)) => std::thread::sleep(Duration::from_millis(10)),
                    _ => break,
                }
            }
            let said = m.lock().ok().and_then(|m| m.error.clone());
            match (status, said, protocol_error) {
                (_, Some(e), _) => Some(e),
                (_, None, Some(p)) => Some(format!("the RealSense bridge sent a bad frame: {p}")),
                (Some(s), None, None) if s.success() => None,
                (Some(s), None, None) => Some(format!("the RealSense bridge stopped ({s}) without a message")),
                (None, None, None) => Some("the RealSense bridge could not be waited for".into()),
            }
        };
        let reader =
            FrameReader::spawn(BufReader::with_capacity(1 << 20, stdout), "umesh-realsense", keep_all, on_end)?;
        Ok(Self { request: request.clone(), reader, child, messages })
    }

    pub fn received(&self) -> u64 {
        self.reader.received()
    }

    /// Raw depth units per metre of the frames so far (1000: millimetres).
    pub fn depth_scale(&self) -> Option<f64> {
        self.reader.depth_scale()
    }

    /// The bridge's closing figures of a recording (frames, dropped, depth without colour).
    pub fn summary(&self) -> Option<serde_json::Value> {
        self.messages.lock().ok().and_then(|m| m.summary.clone())
    }
}

impl Drop for RealSenseSource {
    fn drop(&mut self) {
        if let Ok(mut c) = self.child.lock() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

impl FrameSource for RealSenseSource {
    fn describe(&self) -> String {
        self.request.describe()
    }
    fn poll(&mut self, timeout: Duration) -> Poll {
        self.reader.poll(timeout)
    }
    fn dropped(&self) -> u64 {
        self.reader.dropped()
    }
    fn take_log(&mut self) -> Vec<String> {
        self.messages.lock().map(|mut m| std::mem::take(&mut m.log)).unwrap_or_default()
    }
}

/// Every frame of a source until it ends: for reading a recording whole.
pub(crate) fn next_frame(src: &mut RealSenseSource, cancel: &crate::Cancel) -> Result<Option<Frame>, RgbdError> {
    loop {
        cancel.check()?;
        match src.poll(Duration::from_millis(200)) {
            Poll::Frame(f) => return Ok(Some(*f)),
            Poll::Pending => {}
            Poll::Ended(None) => return Ok(None),
            Poll::Ended(Some(reason)) => return Err(RgbdError::Stream(reason)),
        }
    }
}
