//! Recorded RGB-D sequences on disk, in the layout Open3D and most datasets use:
//!
//! ```text
//! DIR/color/NNNNN.png|jpg     colour frames (optional)
//! DIR/depth/NNNNN.png         16-bit depth, 0 = no data
//! DIR/mask/NNNNN.png          organ masks, non-zero = organ (optional)
//! DIR/points/NNNNN.ply        point clouds in the camera frame, mm (instead of depth; used whole)
//! DIR/trajectory.log          world_from_camera per frame, Open3D/Redwood .log, metres (optional)
//! DIR/intrinsics.json         Open3D PinholeCameraIntrinsic (or any such JSON in DIR or its parent)
//! DIR/recording.json          {"depth_scale": 1000, "fps": 20} (optional)
//! DIR/ground_truth.json       true marker positions per frame (synthetic recordings)
//! ```

use super::{ColorImage, DepthImage, Frame, Intrinsics, RgbdError, invalid, read_depth_png};
use nalgebra::{Matrix4, Vector3};
use std::path::{Path, PathBuf};

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RecordingMeta {
    /// Raw depth units per metre: 1000 for millimetres, 5000 for TUM.
    pub depth_scale: f64,
    pub fps: f64,
}

impl Default for RecordingMeta {
    fn default() -> Self {
        Self { depth_scale: 1000.0, fps: 20.0 }
    }
}

#[derive(Clone, Debug)]
struct FrameFiles {
    stem: String,
    depth: Option<PathBuf>,
    points: Option<PathBuf>,
    color: Option<PathBuf>,
    mask: Option<PathBuf>,
}

/// An opened recording: the frame list and its metadata; frames are read on demand.
#[derive(Clone, Debug)]
pub struct Recording {
    pub dir: PathBuf,
    pub meta: RecordingMeta,
    pub intrinsics: Intrinsics,
    pub intrinsics_path: PathBuf,
    /// world_from_camera (mm) per frame, when the recording has a trajectory.
    pub trajectory: Option<Vec<Matrix4<f64>>>,
    /// What is missing or odd but does not stop the recording (each also logged by callers).
    pub warnings: Vec<String>,
    frames: Vec<FrameFiles>,
}

fn list(dir: &Path, exts: &[&str]) -> Result<Vec<(String, PathBuf)>, RgbdError> {
    if !dir.is_dir() {
        return Ok(Vec::new());
    }
    let rd = std::fs::read_dir(dir).map_err(|e| RgbdError::Io { path: dir.into(), source: e })?;
    let mut out: Vec<(String, PathBuf)> = rd
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| {
            p.is_file() && p.extension().is_some_and(|e| exts.contains(&e.to_string_lossy().to_lowercase().as_str()))
        })
        .filter_map(|p| Some((p.file_stem()?.to_string_lossy().into_owned(), p)))
        .collect();
    out.sort();
    Ok(out)
}

/// The intrinsics JSON of a recording: `intrinsics.json`, `camera_intrinsic.json`, or the
/// first JSON in the folder or its parent that parses as one.
pub fn find_intrinsics(dir: &Path) -> Option<PathBuf> {
    for name in ["intrinsics.json", "camera_intrinsic.json"] {
        if dir.join(name).is_file() {
            return Some(dir.join(name));
        }
    }
    for d in [Some(dir), dir.parent()].into_iter().flatten() {
        let Ok(mut files) = list(d, &["json"]) else { continue };
        files.retain(|(s, _)| s != "recording" && s != "ground_truth");
        for (_, p) in files {
            if std::fs::read_to_string(&p).is_ok_and(|t| Intrinsics::from_open3d_json(&t, &p).is_ok()) {
                return Some(p);
            }
        }
    }
    None
}

/// Open3D/Redwood `.log` trajectory: per frame a line of three integers and a 4x4 matrix
/// (camera to world, metres). Returned in millimetres.
pub fn read_trajectory_log(path: &Path) -> Result<Vec<Matrix4<f64>>, RgbdError> {
    let text = std::fs::read_to_string(path).map_err(|e| RgbdError::Io { path: path.into(), source: e })?;
    let lines: Vec<&str> = text.lines().map(str::trim).filter(|l| !l.is_empty()).collect();
    if !lines.len().is_multiple_of(5) {
        return Err(invalid(path, format!("{} non-empty lines: a .log trajectory has 5 per frame", lines.len())));
    }
    let mut out = Vec::new();
    for (f, block) in lines.chunks(5).enumerate() {
        let mut m = Matrix4::zeros();
        for r in 0..4 {
            let vals: Vec<f64> = block[r + 1].split_whitespace().filter_map(|v| v.parse().ok()).collect();
            if vals.len() != 4 || !vals.iter().all(|v| v.is_finite()) {
                return Err(invalid(path, format!("frame {f}, row {r}: four finite numbers expected")));
            }
            for c in 0..4 {
                m[(r, c)] = vals[c];
            }
        }
        super::check_rigid(&m).map_err(|e| invalid(path, format!("frame {f}: {e}")))?;
        for r in 0..3 {
            m[(r, 3)] *= 1000.0;
        }
        out.push(m);
    }
    Ok(out)
}

pub fn write_trajectory_log(poses_mm: &[Matrix4<f64>]) -> String {
    let mut s = String::new();
    for (i, m) in poses_mm.iter().enumerate() {
        s.push_str(&format!("{i} {i} {}\n", i + 1));
        for r in 0..4 {
            let k = if r < 3 { 1e-3 } else { 1.0 };
            s.push_str(&format!("{} {} {} {}\n", m[(r, 0)], m[(r, 1)], m[(r, 2)], m[(r, 3)] * k));
        }
    }
    s
}

impl Recording {
    /// Open a recording folder. `intrinsics` overrides the JSON search.
    pub fn open(dir: &Path, intrinsics: Option<&Path>) -> Result<Self, RgbdError> {
        if !dir.is_dir() {
            return Err(invalid(dir, "not a folder (a recording has depth/ or points/ and an intrinsics JSON)"));
        }
        let meta_path = dir.join("recording.json");
        let meta = if meta_path.is_file() {
            let t = std::fs::read_to_string(&meta_path)
                .map_err(|e| RgbdError::Io { path: meta_path.clone(), source: e })?;
            let m: RecordingMeta = serde_json::from_str(&t)
                .map_err(|e| invalid(&meta_path, format!("not a recording description: {e}")))?;
            if !(m.depth_scale.is_finite() && m.depth_scale > 0.0 && m.fps.is_finite() && m.fps > 0.0) {
                return Err(invalid(&meta_path, "depth_scale and fps must be finite and positive"));
            }
            m
        } else {
            RecordingMeta::default()
        };
        let intrinsics_path = match intrinsics {
            Some(p) => p.to_path_buf(),
            None => find_intrinsics(dir).ok_or_else(|| {
                invalid(dir, "no intrinsics: put an Open3D PinholeCameraIntrinsic JSON (intrinsics.json) in the folder or pass one")
            })?,
        };
        let k = Intrinsics::read(&intrinsics_path)?;
        let depth = list(&dir.join("depth"), &["png"])?;
        let points = list(&dir.join("points"), &["ply"])?;
        let color = list(&dir.join("color"), &["png", "jpg", "jpeg"])?;
        let mask = list(&dir.join("mask"), &["png"])?;
        let mut warnings = Vec::new();
        // Sorted by stem (`list`): a binary search per frame.
        let find = |v: &[(String, PathBuf)], stem: &str| {
            v.binary_search_by(|(s, _)| s.as_str().cmp(stem)).ok().map(|k| v[k].1.clone())
        };
        if depth.is_empty() && points.is_empty() {
            return Err(invalid(dir, "no frames: depth/*.png or points/*.ply expected"));
        }
        // The ground truth and the trajectory are indexed by frame position: a frame whose depth
        // file is missing (its colour or mask still there, or its number skipped) keeps its
        // place, and is skipped with a message when read, rather than shifting every later
        // frame onto the truth of the one before.
        let mut stems: std::collections::BTreeSet<String> =
            depth.iter().chain(&points).chain(&color).chain(&mask).map(|(s, _)| s.clone()).collect();
        let width = stems.first().map(|s| s.len()).unwrap_or(0);
        let numbered: Option<Vec<u64>> =
            stems.iter().map(|s| if s.len() == width { s.parse::<u64>().ok() } else { None }).collect();
        if let Some(n) = numbered
            && let (Some(&lo), Some(&hi)) = (n.iter().min(), n.iter().max())
            && hi - lo < 1_000_000
        {
            stems.extend((lo..=hi).map(|i| format!("{i:0width$}")));
        }
        let mut frames: Vec<FrameFiles> = stems
            .into_iter()
            .map(|s| FrameFiles {
                depth: find(&depth, &s),
                points: if depth.is_empty() { find(&points, &s) } else { None },
                stem: s,
                color: None,
                mask: None,
            })
            .collect();
        for f in &mut frames {
            f.color = find(&color, &f.stem);
            f.mask = find(&mask, &f.stem);
            if f.color.is_none() && !color.is_empty() {
                warnings.push(format!("frame {}: no colour image in color/", f.stem));
            }
            if f.mask.is_none() && !mask.is_empty() {
                warnings.push(format!("frame {}: no mask in mask/", f.stem));
            }
        }
        let traj_path = dir.join("trajectory.log");
        let trajectory = if traj_path.is_file() {
            let t = read_trajectory_log(&traj_path)?;
            if t.len() < frames.len() {
                warnings.push(format!(
                    "trajectory.log has {} poses for {} frames; the last pose is repeated",
                    t.len(),
                    frames.len()
                ));
            }
            Some(t)
        } else {
            None
        };
        Ok(Self { dir: dir.to_path_buf(), meta, intrinsics: k, intrinsics_path, trajectory, warnings, frames })
    }

    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// Its trajectory holds a pose for every frame (tracked), not one initial pose (of a
    /// recording longer than a frame).
    pub fn tracks_every_frame(&self) -> bool {
        self.trajectory.as_ref().is_some_and(|t| t.len() >= 2 && t.len() >= self.frames.len())
    }

    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    pub fn frame_name(&self, i: usize) -> &str {
        &self.frames[i].stem
    }

    /// Read frame `i`; a bad file gives an error naming it (callers skip the frame).
    pub fn read_frame(&self, i: usize) -> Result<Frame, RgbdError> {
        let f = self
            .frames
            .get(i)
            .ok_or_else(|| invalid(&self.dir, format!("frame {i} out of range (0..{})", self.frames.len())))?;
        let k = self.intrinsics;
        let mut cloud = None;
        let depth = match (&f.depth, &f.points) {
            (Some(p), _) => {
                let d = read_depth_png(p, self.meta.depth_scale)?;
                if (d.width, d.height) != (k.width, k.height) {
                    return Err(invalid(
                        p,
                        format!("depth is {}x{}, the intrinsics say {}x{}", d.width, d.height, k.width, k.height),
                    ));
                }
                d
            }
            (None, Some(p)) => {
                let pts = crate::mesh_io::read_point_cloud(p).map_err(|e| invalid(p, e.to_string()))?;
                if pts.len() > super::MAX_POINTS {
                    return Err(invalid(p, format!("{} points, at most {}", pts.len(), super::MAX_POINTS)));
                }
                let d = splat_points(&pts, &k);
                // The points themselves go to registration; the splat is for display.
                cloud = Some(pts);
                d
            }
            (None, None) => {
                return Err(invalid(
                    &self.dir,
                    format!("frame {}: its depth image (or point cloud) is missing", f.stem),
                ));
            }
        };
        let color = match &f.color {
            Some(p) => {
                let c = ColorImage::read(p)?;
                if (c.width, c.height) != (k.width, k.height) {
                    return Err(invalid(
                        p,
                        format!("colour is {}x{}, depth is {}x{}", c.width, c.height, k.width, k.height),
                    ));
                }
                Some(c)
            }
            None => None,
        };
        let mask = match &f.mask {
            Some(p) => {
                let m = image::open(p).map_err(|e| invalid(p, format!("cannot decode the mask: {e}")))?.to_luma8();
                if (m.width() as usize, m.height() as usize) != (k.width, k.height) {
                    return Err(invalid(
                        p,
                        format!("mask is {}x{}, depth is {}x{}", m.width(), m.height(), k.width, k.height),
                    ));
                }
                let m: Vec<bool> = m.into_raw().into_iter().map(|v| v > 0).collect();
                if !m.iter().any(|&v| v) {
                    return Err(invalid(p, "the organ mask is empty"));
                }
                Some(m)
            }
            None => None,
        };
        let world_from_camera = self.trajectory.as_ref().and_then(|t| t.get(i.min(t.len().saturating_sub(1))).copied());
        Ok(Frame {
            index: i,
            timestamp_s: i as f64 / self.meta.fps,
            intrinsics: k,
            depth,
            color,
            mask,
            world_from_camera,
            points: cloud,
            device_frame: None,
            host_time_s: None,
        })
    }
}

/// A camera-frame point cloud as a depth image (nearest point per pixel, 3x3 splats so that
/// sparse clouds leave no pinholes).
pub fn splat_points(points: &[Vector3<f64>], k: &Intrinsics) -> DepthImage {
    let mut d = vec![0f32; k.width * k.height];
    for p in points {
        let Some((u, v, z)) = k.project(p) else { continue };
        let (u, v) = (u.round() as i64, v.round() as i64);
        for dv in -1..=1 {
            for du in -1..=1 {
                let (x, y) = (u + du, v + dv);
                if x >= 0 && y >= 0 && (x as usize) < k.width && (y as usize) < k.height {
                    let c = &mut d[y as usize * k.width + x as usize];
                    if *c == 0.0 || (z as f32) < *c {
                        *c = z as f32;
                    }
                }
            }
        }
    }
    DepthImage { width: k.width, height: k.height, depth_mm: d }
}

/// Write one frame of a recording (depth 16-bit PNG, colour PNG, mask PNG), each atomically.
pub fn write_frame(dir: &Path, stem: &str, frame: &Frame, depth_scale: f64) -> Result<(), RgbdError> {
    let io = |path: PathBuf| move |e: std::io::Error| RgbdError::Io { path, source: e };
    let p = dir.join("depth").join(format!("{stem}.png"));
    let bytes = super::encode_depth_png(&frame.depth, depth_scale).map_err(|r| invalid(&p, r))?;
    crate::write_atomic(&p, &bytes).map_err(io(p.clone()))?;
    if let Some(c) = &frame.color {
        let p = dir.join("color").join(format!("{stem}.png"));
        let bytes = c.encode_png().map_err(|r| invalid(&p, r))?;
        crate::write_atomic(&p, &bytes).map_err(io(p.clone()))?;
    }
    if let Some(m) = &frame.mask {
        let p = dir.join("mask").join(format!("{stem}.png"));
        let img = image::GrayImage::from_raw(
            frame.depth.width as u32,
            frame.depth.height as u32,
            m.iter().map(|&v| if v { 255 } else { 0 }).collect(),
        )
        .ok_or_else(|| invalid(&p, "mask size does not match"))?;
        let mut bytes = Vec::new();
        img.write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)
            .map_err(|e| invalid(&p, e.to_string()))?;
        crate::write_atomic(&p, &bytes).map_err(io(p.clone()))?;
    }
    Ok(())
}
