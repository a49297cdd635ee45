//! The organ's pixels in a frame: the recording's mask when it has one, else a depth range
//! and a colour rule: a colour threshold set by the user, or by default the tissue rule (red
//! well above green and blue: liver parenchyma, not the grey of instruments or the green or
//! blue of drapes), keeping the largest connected region.

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
    /// Without a mask or a colour target: keep tissue-coloured pixels, largest region only.
    #[serde(default = "yes")]
    pub tissue_color: bool,
}

fn yes() -> bool {
    true
}

/// Red over green and over blue for the tissue rule, and the darkest red kept (0-255).
const TISSUE_RATIO: f32 = 1.4;
const TISSUE_MIN_RED: u8 = 35;

impl Default for SegmentSettings {
    fn default() -> Self {
        Self {
            use_mask: true,
            depth_min_mm: 100.0,
            depth_max_mm: 3000.0,
            color_rgb: None,
            color_tolerance: 60.0,
            tissue_color: true,
        }
    }
}

/// Per pixel: organ. Errors when nothing is left (the caller skips the frame).
pub fn segment_frame(frame: &Frame, s: &SegmentSettings) -> Result<Vec<bool>, crate::Invalid> {
    let n = frame.depth.depth_mm.len();
    let masked = frame.mask.is_some() && s.use_mask;
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
    if let (false, None, true, Some(c)) = (masked, s.color_rgb, s.tissue_color, &frame.color) {
        for (i, k) in keep.iter_mut().enumerate() {
            if *k {
                let [r, g, b] = [c.rgb[3 * i], c.rgb[3 * i + 1], c.rgb[3 * i + 2]];
                let rf = r as f32;
                *k = r >= TISSUE_MIN_RED && rf > TISSUE_RATIO * g as f32 && rf > TISSUE_RATIO * b as f32;
            }
        }
        // A sparse cloud's splats do not touch: each would be a region of its own.
        if frame.points.is_none() {
            keep_largest_region(&mut keep, frame.depth.width, frame.depth.height);
        }
    }
    let count = keep.iter().filter(|&&k| k).count();
    if count == 0 {
        return Err(crate::Invalid(format!(
            "frame {}: no organ pixel (mask, depth range {}-{} mm, colour threshold)",
            frame.index, s.depth_min_mm, s.depth_max_mm
        )));
    }
    Ok(keep)
}

/// Keep only the largest 4-connected region of `keep` (specks of tissue colour elsewhere go).
fn keep_largest_region(keep: &mut [bool], w: usize, h: usize) {
    if keep.len() != w * h {
        return;
    }
    let mut label = vec![0u32; keep.len()];
    let (mut best, mut best_size, mut next) = (0u32, 0usize, 0u32);
    let mut stack = Vec::new();
    for start in 0..keep.len() {
        if !keep[start] || label[start] != 0 {
            continue;
        }
        next += 1;
        label[start] = next;
        stack.push(start);
        let mut size = 0;
        while let Some(i) = stack.pop() {
            size += 1;
            let (x, y) = (i % w, i / w);
            let mut visit = |j: usize| {
                if keep[j] && label[j] == 0 {
                    label[j] = next;
                    stack.push(j);
                }
            };
            if x > 0 {
                visit(i - 1);
            }
            if x + 1 < w {
                visit(i + 1);
            }
            if y > 0 {
                visit(i - w);
            }
            if y + 1 < h {
                visit(i + w);
            }
        }
        if size > best_size {
            (best, best_size) = (next, size);
        }
    }
    for (k, l) in keep.iter_mut().zip(&label) {
        *k = *k && *l == best;
    }
}
