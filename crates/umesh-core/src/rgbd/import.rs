//! A RealSense recording (`.bag`, `.db3`) turned into a recording folder (see
//! [`super::recording`]): depth aligned to colour in the device's own depth units, colour,
//! the colour camera's intrinsics, the frame rate, and each frame's device frame number and
//! timestamp (`frames.json`); frames the camera dropped (gaps in its frame counter) are
//! counted.

use super::realsense::{RealSenseRequest, RealSenseSource, next_frame};
use super::recording::{RecordingMeta, write_frame};
use super::stream::FrameSource;
use super::{Intrinsics, RgbdError, invalid};
use std::path::{Path, PathBuf};

/// One imported frame: its file stem, the camera's frame number and timestamp.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ImportedFrame {
    pub frame: String,
    pub device_frame: Option<u64>,
    pub timestamp_s: f64,
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ImportReport {
    pub source: PathBuf,
    pub frames: usize,
    /// Frames missing from the recording (gaps in the camera's frame counter).
    pub dropped: u64,
    pub frames_without_color: usize,
    pub intrinsics: Intrinsics,
    /// Raw depth units per metre, as the device recorded them (1000: millimetres).
    pub depth_scale: f64,
    pub fps: f64,
    pub duration_s: f64,
    /// What the camera said of itself (streams, rate, depth units).
    pub camera: Vec<String>,
    pub warnings: Vec<String>,
}

/// The recording's frame rate from its timestamps (the median step); None with one frame.
fn fps_of(times: &[f64]) -> Option<f64> {
    let mut steps: Vec<f64> = times.windows(2).map(|w| w[1] - w[0]).filter(|d| d.is_finite() && *d > 0.0).collect();
    if steps.is_empty() {
        return None;
    }
    steps.sort_by(f64::total_cmp);
    Some(1.0 / steps[steps.len() / 2])
}

/// Read the RealSense recording `file` whole and write it as a recording folder into `out`
/// (an empty folder the caller swaps in when this returns Ok).
pub fn run_rgbd_import(
    file: &Path,
    out: &Path,
    progress: &crate::Progress,
    cancel: &crate::Cancel,
) -> Result<ImportReport, RgbdError> {
    let mut src = RealSenseSource::open(&RealSenseRequest::recording(file))?;
    let io = |p: PathBuf| move |e: std::io::Error| RgbdError::Io { path: p, source: e };
    let mut frames: Vec<ImportedFrame> = Vec::new();
    let mut intrinsics: Option<Intrinsics> = None;
    let mut said = Vec::new();
    let mut without_color = 0;
    let mut depth_scale = None;
    while let Some(frame) = next_frame(&mut src, cancel).map_err(|e| match e {
        RgbdError::Stream(reason) => invalid(file, reason),
        other => other,
    })? {
        said.extend(src.take_log());
        let k = *intrinsics.get_or_insert(frame.intrinsics);
        if frame.intrinsics != k {
            return Err(invalid(
                file,
                format!(
                    "frame {} is {}x{} (fx {}), the frames before it {}x{} (fx {}): one recording, one camera setting",
                    frames.len(),
                    frame.intrinsics.width,
                    frame.intrinsics.height,
                    frame.intrinsics.fx,
                    k.width,
                    k.height,
                    k.fx
                ),
            ));
        }
        let scale = *depth_scale.get_or_insert(src.depth_scale().unwrap_or(1000.0));
        let stem = format!("{:05}", frames.len());
        write_frame(out, &stem, &frame, scale)?;
        without_color += frame.color.is_none() as usize;
        frames.push(ImportedFrame { frame: stem, device_frame: frame.device_frame, timestamp_s: frame.timestamp_s });
        progress.report(frames.len() as u64, 0, &format!("{} frames", frames.len()));
    }
    said.extend(src.take_log());
    let (warnings, camera): (Vec<String>, Vec<String>) = said.into_iter().partition(|l| l.starts_with("warning:"));
    let Some(intrinsics) = intrinsics else {
        return Err(invalid(file, "the recording holds no depth frame"));
    };
    let times: Vec<f64> = frames.iter().map(|f| f.timestamp_s).collect();
    // To the microhertz: 5.000000000000001 is 5.
    let fps = (fps_of(&times).unwrap_or(30.0) * 1e6).round() / 1e6;
    let depth_scale = depth_scale.unwrap_or(1000.0);
    let w = |name: &str, value: serde_json::Result<String>| -> Result<(), RgbdError> {
        let p = out.join(name);
        let text = value.map_err(|e| invalid(&p, format!("cannot serialise: {e}")))?;
        crate::write_atomic(&p, text.as_bytes()).map_err(io(p.clone()))
    };
    w("intrinsics.json", Ok(intrinsics.to_open3d_json()))?;
    w("recording.json", serde_json::to_string_pretty(&RecordingMeta { depth_scale, fps }))?;
    w("frames.json", serde_json::to_string_pretty(&frames))?;
    let report = ImportReport {
        source: file.to_path_buf(),
        frames: frames.len(),
        dropped: src.dropped(),
        frames_without_color: without_color,
        intrinsics,
        depth_scale,
        fps,
        duration_s: times.last().copied().unwrap_or(0.0) - times.first().copied().unwrap_or(0.0),
        camera,
        warnings,
    };
    w("import.json", serde_json::to_string_pretty(&report))?;
    Ok(report)
}
