//! RGB-D frames: pinhole intrinsics (Open3D JSON), depth and colour images, depth to points,
//! projection, recordings on disk, live sources and the organ's segmentation in the frame.
//!
//! Camera frame: OpenCV's (x right, y down, z forward), in millimetres.

pub mod import;
pub mod realsense;
pub mod recording;
pub mod segment;
pub mod stream;

use nalgebra::{Matrix4, Vector3};
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum RgbdError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: {reason}")]
    Invalid { path: PathBuf, reason: String },
    #[error("stream: {0}")]
    Stream(String),
    /// The system refused what a stream needs (a connection, a thread, a process), its error kept.
    #[error("stream: {what}")]
    StreamIo { what: String, source: std::io::Error },
    /// Inputs that do not belong together (a ground truth of another organ, say).
    #[error(transparent)]
    Mismatch(#[from] crate::Invalid),
    #[error(transparent)]
    Cancelled(#[from] crate::Cancelled),
}

pub(crate) fn invalid(path: &Path, reason: impl Into<String>) -> RgbdError {
    RgbdError::Invalid { path: path.to_path_buf(), reason: reason.into() }
}

/// Pinhole intrinsics in pixels.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Intrinsics {
    pub width: usize,
    pub height: usize,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

/// Open3D's `PinholeCameraIntrinsic` JSON (column-major `intrinsic_matrix`).
#[derive(serde::Serialize, serde::Deserialize)]
struct Open3dIntrinsic {
    width: usize,
    height: usize,
    intrinsic_matrix: Vec<f64>,
}

/// Refuse frames larger than this (16 Mpixel): a corrupt header must not allocate gigabytes.
pub const MAX_PIXELS: usize = 1 << 24;

impl Intrinsics {
    pub fn validate(&self) -> Result<(), crate::Invalid> {
        if self.width == 0 || self.height == 0 || self.width.saturating_mul(self.height) > MAX_PIXELS {
            return Err(crate::Invalid(format!(
                "image size {}x{} is zero or larger than {MAX_PIXELS} pixels",
                self.width, self.height
            )));
        }
        for (name, v) in [("fx", self.fx), ("fy", self.fy)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(crate::Invalid(format!("focal length {name} = {v} must be finite and positive")));
            }
        }
        if !(self.cx.is_finite() && self.cy.is_finite()) {
            return Err(crate::Invalid(format!("principal point ({}, {}) is not finite", self.cx, self.cy)));
        }
        Ok(())
    }

    pub fn from_open3d_json(text: &str, path: &Path) -> Result<Self, RgbdError> {
        let j: Open3dIntrinsic = serde_json::from_str(text).map_err(|e| {
            invalid(path, format!("not an Open3D PinholeCameraIntrinsic JSON (width, height, intrinsic_matrix): {e}"))
        })?;
        if j.intrinsic_matrix.len() != 9 {
            return Err(invalid(path, format!("intrinsic_matrix has {} values, 9 expected", j.intrinsic_matrix.len())));
        }
        let m = &j.intrinsic_matrix;
        // Column-major: [fx, 0, 0, 0, fy, 0, cx, cy, 1].
        let k = Self { width: j.width, height: j.height, fx: m[0], fy: m[4], cx: m[6], cy: m[7] };
        k.validate().map_err(|r| invalid(path, r))?;
        Ok(k)
    }

    pub fn read(path: &Path) -> Result<Self, RgbdError> {
        let text = std::fs::read_to_string(path).map_err(|e| RgbdError::Io { path: path.into(), source: e })?;
        Self::from_open3d_json(&text, path)
    }

    pub fn to_open3d_json(&self) -> String {
        let j = Open3dIntrinsic {
            width: self.width,
            height: self.height,
            intrinsic_matrix: vec![self.fx, 0.0, 0.0, 0.0, self.fy, 0.0, self.cx, self.cy, 1.0],
        };
        serde_json::to_string_pretty(&j).unwrap_or_default()
    }

    /// Camera-frame point of pixel (u, v) (pixel centres at integers) at depth z.
    pub fn unproject(&self, u: f64, v: f64, z_mm: f64) -> Vector3<f64> {
        Vector3::new((u - self.cx) * z_mm / self.fx, (v - self.cy) * z_mm / self.fy, z_mm)
    }

    /// Pixel coordinates and depth of a camera-frame point, None behind the camera.
    pub fn project(&self, p: &Vector3<f64>) -> Option<(f64, f64, f64)> {
        if p.z <= 1e-9 {
            return None;
        }
        Some((self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy, p.z))
    }
}

/// Depth in millimetres, 0 where the sensor has no data.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthImage {
    pub width: usize,
    pub height: usize,
    pub depth_mm: Vec<f32>,
}

impl DepthImage {
    pub fn at(&self, u: usize, v: usize) -> f32 {
        self.depth_mm[v * self.width + u]
    }

    /// Depth at a sub-pixel position: bilinear over the valid neighbours, None in a hole or
    /// across a depth edge (neighbours further apart than `edge_mm`).
    pub fn sample(&self, u: f64, v: f64, edge_mm: f32) -> Option<f32> {
        if !(u >= 0.0 && v >= 0.0) {
            return None;
        }
        let (u0, v0) = (u.floor() as usize, v.floor() as usize);
        if u0 + 1 >= self.width || v0 + 1 >= self.height {
            return None;
        }
        let (fu, fv) = ((u - u0 as f64) as f32, (v - v0 as f64) as f32);
        let mut acc = 0.0;
        let mut wsum = 0.0;
        let (mut lo, mut hi) = (f32::INFINITY, 0.0f32);
        for (du, dv, w) in
            [(0, 0, (1.0 - fu) * (1.0 - fv)), (1, 0, fu * (1.0 - fv)), (0, 1, (1.0 - fu) * fv), (1, 1, fu * fv)]
        {
            let d = self.at(u0 + du, v0 + dv);
            if d > 0.0 && w > 0.0 {
                acc += w * d;
                wsum += w;
                lo = lo.min(d);
                hi = hi.max(d);
            }
        }
        (wsum > 0.25 && hi - lo <= edge_mm).then(|| acc / wsum)
    }
}

/// 8-bit RGB.
#[derive(Clone, Debug, PartialEq)]
pub struct ColorImage {
    pub width: usize,
    pub height: usize,
    pub rgb: Vec<u8>,
}

impl ColorImage {
    pub fn new(width: usize, height: usize, rgb: [u8; 3]) -> Self {
        Self { width, height, rgb: rgb.repeat(width * height) }
    }

    pub fn read(path: &Path) -> Result<Self, RgbdError> {
        let img =
            image::open(path).map_err(|e| invalid(path, format!("cannot decode the colour image: {e}")))?.to_rgb8();
        let (w, h) = img.dimensions();
        Ok(Self { width: w as usize, height: h as usize, rgb: img.into_raw() })
    }

    pub fn encode_png(&self) -> Result<Vec<u8>, crate::Invalid> {
        let mut out = Vec::new();
        image::codecs::png::PngEncoder::new(&mut out)
            .write_image(&self.rgb, self.width as u32, self.height as u32, image::ExtendedColorType::Rgb8)
            .map_err(|e| e.to_string())?;
        Ok(out)
    }

    pub fn blend(&mut self, u: usize, v: usize, rgb: [u8; 3], alpha: f32) {
        let i = 3 * (v * self.width + u);
        blend_pixel(&mut self.rgb[i..i + 3], rgb, alpha);
    }
}

/// `rgb` blended at `alpha` over one pixel's three bytes.
pub fn blend_pixel(px: &mut [u8], rgb: [u8; 3], alpha: f32) {
    for (d, s) in px.iter_mut().zip(rgb) {
        *d = (*d as f32 * (1.0 - alpha) + s as f32 * alpha).round().clamp(0.0, 255.0) as u8;
    }
}

use image::ImageEncoder;

/// Read a 16-bit single-channel depth PNG; `depth_scale` raw units per metre (1000:
/// millimetres, 5000: TUM). 8-bit images are refused: at most 255 mm (or 51 mm at 5000 per
/// metre) cannot hold an organ's depth, and they are usually a visualisation, not the data.
pub fn read_depth_png(path: &Path, depth_scale: f64) -> Result<DepthImage, RgbdError> {
    if !(depth_scale.is_finite() && depth_scale > 0.0) {
        return Err(invalid(path, format!("depth scale {depth_scale} must be finite and positive")));
    }
    let img = image::open(path).map_err(|e| invalid(path, format!("cannot decode the depth image: {e}")))?;
    let gray = match img {
        image::DynamicImage::ImageLuma16(g) => g,
        image::DynamicImage::ImageLuma8(_) => {
            return Err(invalid(
                path,
                "the depth image is 8-bit: depth needs a 16-bit single-channel PNG (8 bits hold at most 255 raw units, \
                 a visualisation rather than the camera's depth)",
            ));
        }
        other => {
            return Err(invalid(path, format!("depth must be a single-channel 16-bit PNG, found {:?}", other.color())));
        }
    };
    let (w, h) = gray.dimensions();
    let to_mm = (1000.0 / depth_scale) as f32;
    Ok(DepthImage {
        width: w as usize,
        height: h as usize,
        depth_mm: gray.into_raw().into_iter().map(|d| d as f32 * to_mm).collect(),
    })
}

/// Encode depth (mm) as a 16-bit PNG with `depth_scale` units per metre.
pub fn encode_depth_png(depth: &DepthImage, depth_scale: f64) -> Result<Vec<u8>, crate::Invalid> {
    let k = (depth_scale / 1000.0) as f32;
    let raw: Vec<u8> =
        depth.depth_mm.iter().flat_map(|&d| ((d * k).round().clamp(0.0, 65535.0) as u16).to_ne_bytes()).collect();
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new(&mut out)
        .write_image(&raw, depth.width as u32, depth.height as u32, image::ExtendedColorType::L16)
        .map_err(|e| e.to_string())?;
    Ok(out)
}

/// One RGB-D frame.
#[derive(Clone, Debug)]
pub struct Frame {
    pub index: usize,
    pub timestamp_s: f64,
    pub intrinsics: Intrinsics,
    pub depth: DepthImage,
    pub color: Option<ColorImage>,
    /// Organ pixels, when the recording has masks.
    pub mask: Option<Vec<bool>>,
    /// Camera pose (world_from_camera, mm), when the recording has a trajectory.
    pub world_from_camera: Option<Matrix4<f64>>,
    /// The camera's own point cloud (camera frame, mm) when the source gives points rather
    /// than depth; `depth` is then their splat, for display and segmentation only.
    pub points: Option<Vec<Vector3<f64>>>,
    /// The camera's own frame counter, when the source gives one (a gap is a frame the camera
    /// or its bridge dropped).
    pub device_frame: Option<u64>,
    /// When the camera's bridge took the frame from the camera (Unix time, s): the start of
    /// the end-to-end latency (bridge, transport, queue, registration) on the same machine.
    pub host_time_s: Option<f64>,
}

/// Refuse clouds larger than this (4 M points): a corrupt count must not allocate gigabytes.
pub const MAX_POINTS: usize = 1 << 22;

impl Frame {
    /// Check that the images agree with the intrinsics and with each other.
    pub fn validate(&self) -> Result<(), crate::Invalid> {
        self.intrinsics.validate()?;
        let (w, h) = (self.intrinsics.width, self.intrinsics.height);
        if (self.depth.width, self.depth.height) != (w, h) || self.depth.depth_mm.len() != w * h {
            return Err(crate::Invalid(format!(
                "depth is {}x{}, the intrinsics say {w}x{h}",
                self.depth.width, self.depth.height
            )));
        }
        if let Some(c) = &self.color
            && ((c.width, c.height) != (w, h) || c.rgb.len() != 3 * w * h)
        {
            return Err(crate::Invalid(format!("colour is {}x{}, depth is {w}x{h}", c.width, c.height)));
        }
        if let Some(m) = &self.mask
            && m.len() != w * h
        {
            return Err(crate::Invalid(format!("the mask has {} pixels, depth has {}", m.len(), w * h)));
        }
        if let Some(p) = &self.points {
            if p.len() > MAX_POINTS {
                return Err(crate::Invalid(format!("the point cloud has {} points, at most {MAX_POINTS}", p.len())));
            }
            if p.iter().any(|q| !q.iter().all(|v| v.is_finite())) {
                return Err(crate::Invalid::from("a point of the cloud is not finite"));
            }
        }
        Ok(())
    }

    /// The organ's points (camera frame, mm): the frame's own cloud when it has one, each
    /// point kept when its pixel is an organ pixel (`keep`, from `segment_frame`) and used
    /// whole; else every `stride`-th organ pixel of the depth image.
    pub fn organ_points(&self, keep: &[bool], stride: usize) -> Vec<Vector3<f64>> {
        let k = &self.intrinsics;
        match &self.points {
            Some(cloud) => cloud
                .iter()
                .filter(|p| {
                    k.project(p).is_some_and(|(u, v, _)| {
                        let (u, v) = (u.round(), v.round());
                        u >= 0.0
                            && v >= 0.0
                            && (u as usize) < k.width
                            && (v as usize) < k.height
                            && keep.get(v as usize * k.width + u as usize).copied().unwrap_or(false)
                    })
                })
                .copied()
                .collect(),
            None => depth_to_points(&self.depth, k, Some(keep), stride),
        }
    }
}

/// Camera-frame points of the pixels selected by `keep` with valid depth, every `stride` pixels.
pub fn depth_to_points(depth: &DepthImage, k: &Intrinsics, keep: Option<&[bool]>, stride: usize) -> Vec<Vector3<f64>> {
    let stride = stride.max(1);
    let mut pts = Vec::new();
    for v in (0..depth.height).step_by(stride) {
        for u in (0..depth.width).step_by(stride) {
            let i = v * depth.width + u;
            let d = depth.depth_mm[i];
            if d > 0.0 && d.is_finite() && keep.is_none_or(|m| m[i]) {
                pts.push(k.unproject(u as f64, v as f64, d as f64));
            }
        }
    }
    pts
}

pub fn transform_point(m: &Matrix4<f64>, p: &Vector3<f64>) -> Vector3<f64> {
    m.fixed_view::<3, 3>(0, 0) * p + m.fixed_view::<3, 1>(0, 3)
}

/// A camera pose must be rigid: its rotation orthonormal with determinant 1 (to 1e-3, what a
/// pose printed to six decimals keeps) and its last row 0 0 0 1. A sheared or scaled "pose"
/// would place the organ anywhere.
pub fn check_rigid(m: &Matrix4<f64>) -> Result<(), crate::Invalid> {
    if !m.iter().all(|v| v.is_finite()) {
        return Err(crate::Invalid::from("the pose holds a value that is not finite"));
    }
    let r = m.fixed_view::<3, 3>(0, 0);
    let off = (r.transpose() * r - nalgebra::Matrix3::identity()).abs().max();
    let det = r.determinant();
    if off > 1e-3 || (det - 1.0).abs() > 1e-3 {
        return Err(crate::Invalid(format!(
            "not a rigid pose: its rotation is off orthonormal by {off:.2e} with determinant {det:.4} (sheared, scaled or mirrored)"
        )));
    }
    if m[(3, 0)].abs() + m[(3, 1)].abs() + m[(3, 2)].abs() + (m[(3, 3)] - 1.0).abs() > 1e-9 {
        return Err(crate::Invalid::from("not a rigid pose: its last row must be 0 0 0 1"));
    }
    Ok(())
}

/// Inverse of a rigid transform.
pub fn rigid_inverse(m: &Matrix4<f64>) -> Matrix4<f64> {
    let r = m.fixed_view::<3, 3>(0, 0).transpose();
    let t = -(r * m.fixed_view::<3, 1>(0, 3));
    let mut out = Matrix4::identity();
    out.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    out.fixed_view_mut::<3, 1>(0, 3).copy_from(&t);
    out
}
