//! The organ's pixels in a frame: the recording's mask when it has one, else a depth range
//! and an optional colour threshold set by the user.

use super::Frame;

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SegmentSettings {
    /// Use the frame's mask when it has one.
    pub use_mask: bool,
    pub depth_min_mm: f32,
    pub depth_max_mm: f32,
    /// Keep pixels whose colour lies within `color_tolerance` (Euclidean, 0-255 units) of this.
    pub color_rgb: Option<[u8; 3]>,
    pub color_tolerance: f32,
}

impl Default for SegmentSettings {
    fn default() -> Self {
        Self { use_mask: true, depth_min_mm: 100.0, depth_max_mm: 3000.0, color_rgb: None, color_tolerance: 60.0 }
    }
}

/// Per pixel: organ. Errors when nothing is left (the caller skips the frame).
pub fn segment_frame(frame: &Frame, s: &SegmentSettings) -> Result<Vec<bool>, String> {
    let n = frame.depth.depth_mm.len();
    let mut keep: Vec<bool> = match (&frame.mask, s.use_mask) {
        (Some(m), true) => m.clone(),
        _ => vec![true; n],
    };
    for (i, k) in keep.iter_mut().enumerate() {
        let d = frame.depth.depth_mm[i];
        *k &= d > 0.0 && d >= s.depth_min_mm && d <= s.depth_max_mm;
    }
    if let (Some(target), Some(c)) = (s.color_rgb, &frame.color) {
        let t = target.map(|v| v as f32);
        let tol2 = s.color_tolerance * s.color_tolerance;
        for (i, k) in keep.iter_mut().enumerate() {
            if *k {
                let p = &c.rgb[3 * i..3 * i + 3];
                let d2: f32 = (0..3).map(|j| (p[j] as f32 - t[j]).powi(2)).sum();
                *k = d2 <= tol2;
            }
        }
    }
    let count = keep.iter().filter(|&&k| k).count();
    if count == 0 {
        return Err(format!(
            "frame {}: no organ pixel (mask, depth range {}-{} mm, colour threshold)",
            frame.index, s.depth_min_mm, s.depth_max_mm
        ));
    }
    Ok(keep)
}
