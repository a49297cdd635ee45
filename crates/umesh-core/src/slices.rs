//! Image slices under the model: an axis-aligned plane of the world (axial, coronal, sagittal)
//! through a scalar volume (a CT), sampled trilinearly in the volume's own voxel frame (any
//! affine), windowed to grey levels, with the sections of surface meshes (the organ at rest, a
//! deformed organ) drawn on it as outlines.

use crate::mesh::TriMesh;
use crate::volume::Volume;
use nalgebra::{Point3, Vector3};

#[derive(Debug, thiserror::Error)]
pub enum SliceError {
    #[error("the slice position {0} mm is not a finite number")]
    NotFinite(f64),
    #[error("the image is empty ({0:?} voxels)")]
    Empty([usize; 3]),
    #[error("the window width {0} must be a positive finite number")]
    BadWindow(f32),
    #[error(transparent)]
    Read(#[from] crate::nifti_io::NiftiError),
    #[error("{path}: {reason}")]
    BadScan { path: std::path::PathBuf, reason: String },
}

/// Read a scan to show under an organ and check it: at least 2 voxels along each axis, mostly
/// finite values, and, given the organ's world bounds (mm), lying where the organ is.
pub fn read_scan(
    path: &std::path::Path,
    organ_bounds: Option<(Vector3<f64>, Vector3<f64>)>,
) -> Result<Volume, SliceError> {
    let volume = crate::nifti_io::read_volume(path, &Default::default())?;
    let bad = |reason: String| SliceError::BadScan { path: path.to_path_buf(), reason };
    if volume.dims.iter().any(|&d| d < 2) {
        return Err(bad(format!("{:?} voxels: a scan needs at least 2 voxels along each axis", volume.dims)));
    }
    let finite = volume.data.iter().filter(|v| v.is_finite()).count();
    if finite * 2 < volume.data.len() {
        return Err(bad(format!(
            "{} of {} voxels are not finite numbers",
            volume.data.len() - finite,
            volume.data.len()
        )));
    }
    let (lo, hi) = world_bounds(&volume);
    if let Some((olo, ohi)) = organ_bounds
        && (0..3).any(|c| ohi[c] < lo[c] || olo[c] > hi[c])
    {
        let r = |lo: &Vector3<f64>, hi: &Vector3<f64>| {
            format!("x {:.0}..{:.0}, y {:.0}..{:.0}, z {:.0}..{:.0} mm", lo.x, hi.x, lo.y, hi.y, lo.z, hi.z)
        };
        return Err(bad(format!(
            "the scan ({}) does not overlap the organ ({}): is it the scan of this segmentation?",
            r(&lo, &hi),
            r(&olo, &ohi)
        )));
    }
    Ok(volume)
}

/// Which world plane: axial (constant z, superior), coronal (constant y, anterior), sagittal
/// (constant x, right).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub enum SliceAxis {
    Axial,
    Coronal,
    Sagittal,
}

impl SliceAxis {
    pub const ALL: [SliceAxis; 3] = [SliceAxis::Axial, SliceAxis::Coronal, SliceAxis::Sagittal];

    /// The world axis normal to the plane (0 = x, 1 = y, 2 = z).
    pub fn normal_axis(self) -> usize {
        match self {
            SliceAxis::Axial => 2,
            SliceAxis::Coronal => 1,
            SliceAxis::Sagittal => 0,
        }
    }

    /// The world axes along the image's columns (u) and rows (v).
    pub fn in_plane_axes(self) -> (usize, usize) {
        match self {
            SliceAxis::Axial => (0, 1),
            SliceAxis::Coronal => (0, 2),
            SliceAxis::Sagittal => (1, 2),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            SliceAxis::Axial => "axial",
            SliceAxis::Coronal => "coronal",
            SliceAxis::Sagittal => "sagittal",
        }
    }
}

/// A grey-level window: values `level ± width / 2` map to black..white (Hounsfield units for a CT).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Window {
    pub level: f32,
    pub width: f32,
}

impl Window {
    /// The usual soft-tissue abdomen window (W 400, L 40).
    pub const ABDOMEN: Window = Window { level: 40.0, width: 400.0 };
    /// A narrow liver window (W 150, L 60): parenchyma against vessels and lesions.
    pub const LIVER: Window = Window { level: 60.0, width: 150.0 };

    /// The 1st to 99th percentile of the volume's values: for images that are not in HU (MR).
    pub fn auto(vol: &Volume) -> Window {
        let mut v: Vec<f32> = vol.data.iter().copied().filter(|x| x.is_finite()).step_by(7).collect();
        if v.is_empty() {
            return Window::ABDOMEN;
        }
        v.sort_by(f32::total_cmp);
        let lo = v[v.len() / 100];
        let hi = v[(v.len() * 99) / 100];
        Window { level: 0.5 * (lo + hi), width: (hi - lo).max(1e-3) }
    }

    fn grey(&self, x: f32) -> u8 {
        let t = (x - (self.level - 0.5 * self.width)) / self.width;
        (t.clamp(0.0, 1.0) * 255.0).round() as u8
    }
}

/// A slice image: `width` x `height` RGBA pixels, row 0 at the low end of the v axis, column 0 at
/// the low end of u; pixels outside the volume are transparent.
#[derive(Clone, Debug)]
pub struct Slice {
    pub axis: SliceAxis,
    pub position_mm: f64,
    /// World position of the image's outer corner at (u min, v min).
    pub origin_mm: Vector3<f64>,
    pub pixel_mm: f64,
    pub width: usize,
    pub height: usize,
    pub rgba: Vec<u8>,
}

impl Slice {
    /// The image's four outer corners in the world: (u min, v min), (u max, v min),
    /// (u max, v max), (u min, v max).
    pub fn corners_mm(&self) -> [Vector3<f64>; 4] {
        let (ua, va) = self.axis.in_plane_axes();
        let mut du = Vector3::zeros();
        du[ua] = self.width as f64 * self.pixel_mm;
        let mut dv = Vector3::zeros();
        dv[va] = self.height as f64 * self.pixel_mm;
        let o = self.origin_mm;
        [o, o + du, o + du + dv, o + dv]
    }

    /// The (fractional) pixel coordinates of a world point on the plane.
    fn pixel_of(&self, p: &Vector3<f64>) -> (f64, f64) {
        let (ua, va) = self.axis.in_plane_axes();
        ((p[ua] - self.origin_mm[ua]) / self.pixel_mm, (p[va] - self.origin_mm[va]) / self.pixel_mm)
    }

    /// Draw the section of `mesh` by the slice's plane, `thickness_px` wide, opaque.
    pub fn draw_section(&mut self, mesh: &TriMesh, rgb: [u8; 3], thickness_px: f64) {
        for [a, b] in plane_section(mesh, self.axis, self.position_mm) {
            let (pa, pb) = (self.pixel_of(&a), self.pixel_of(&b));
            self.draw_line(pa, pb, rgb, thickness_px);
        }
    }

    fn draw_line(&mut self, a: (f64, f64), b: (f64, f64), rgb: [u8; 3], thickness_px: f64) {
        let len = ((b.0 - a.0).powi(2) + (b.1 - a.1).powi(2)).sqrt();
        let steps = (len * 2.0).ceil().max(1.0) as usize;
        let r = (thickness_px * 0.5).max(0.5);
        let ri = r.ceil() as i64;
        for s in 0..=steps {
            let t = s as f64 / steps as f64;
            let (x, y) = (a.0 + t * (b.0 - a.0), a.1 + t * (b.1 - a.1));
            for dy in -ri..=ri {
                for dx in -ri..=ri {
                    let (px, py) = ((x - 0.5).round() as i64 + dx, (y - 0.5).round() as i64 + dy);
                    if px < 0 || py < 0 || px >= self.width as i64 || py >= self.height as i64 {
                        continue;
                    }
                    let (cx, cy) = (px as f64 + 0.5 - x, py as f64 + 0.5 - y);
                    if cx * cx + cy * cy <= r * r + 0.25 {
                        let i = 4 * (py as usize * self.width + px as usize);
                        self.rgba[i..i + 4].copy_from_slice(&[rgb[0], rgb[1], rgb[2], 255]);
                    }
                }
            }
        }
    }
}

/// World bounds (mm) of the volume's voxel centres.
pub fn world_bounds(vol: &Volume) -> (Vector3<f64>, Vector3<f64>) {
    let mut lo = Vector3::repeat(f64::INFINITY);
    let mut hi = Vector3::repeat(f64::NEG_INFINITY);
    for c in 0..8 {
        let v = Vector3::new(
            if c & 1 == 0 { 0.0 } else { vol.dims[0].saturating_sub(1) as f64 },
            if c & 2 == 0 { 0.0 } else { vol.dims[1].saturating_sub(1) as f64 },
            if c & 4 == 0 { 0.0 } else { vol.dims[2].saturating_sub(1) as f64 },
        );
        let p = vol.world_point(v).coords;
        lo = lo.inf(&p);
        hi = hi.sup(&p);
    }
    (lo, hi)
}

/// The slice of `vol` at `position_mm` along the axis normal to `axis` (clamped into the volume),
/// windowed by `window`, at half the finest voxel spacing and at most `max_side_px` pixels on its
/// longer side.
pub fn slice(
    vol: &Volume,
    axis: SliceAxis,
    position_mm: f64,
    window: Window,
    max_side_px: usize,
) -> Result<Slice, SliceError> {
    if !position_mm.is_finite() {
        return Err(SliceError::NotFinite(position_mm));
    }
    if vol.dims.contains(&0) || vol.data.len() != vol.dims.iter().product::<usize>() {
        return Err(SliceError::Empty(vol.dims));
    }
    if !(window.width.is_finite() && window.width > 0.0 && window.level.is_finite()) {
        return Err(SliceError::BadWindow(window.width));
    }
    let (lo, hi) = world_bounds(vol);
    let n = axis.normal_axis();
    let (ua, va) = axis.in_plane_axes();
    let position_mm = position_mm.clamp(lo[n], hi[n]);
    let spacing = vol.min_spacing_mm();
    // Half a voxel beyond the outer centres: the image covers the voxels, not their centres.
    let (u0, u1) = (lo[ua] - 0.5 * spacing, hi[ua] + 0.5 * spacing);
    let (v0, v1) = (lo[va] - 0.5 * spacing, hi[va] + 0.5 * spacing);
    let longest = (u1 - u0).max(v1 - v0);
    let pixel_mm = (0.5 * spacing).max(longest / max_side_px.max(1) as f64);
    let width = ((u1 - u0) / pixel_mm).ceil().max(1.0) as usize;
    let height = ((v1 - v0) / pixel_mm).ceil().max(1.0) as usize;
    let mut origin_mm = Vector3::zeros();
    origin_mm[ua] = u0;
    origin_mm[va] = v0;
    origin_mm[n] = position_mm;
    let voxel_from_world = vol.voxel_from_world();
    let [nx, ny, nz] = vol.dims;
    let mut rgba = vec![0u8; 4 * width * height];
    let sample = |q: Vector3<f64>| -> Option<f32> {
        // Within half a voxel of the lattice: clamped to its edge, as the image covers the voxels.
        let lim = |x: f64, d: usize| x >= -0.5 && x <= d as f64 - 0.5;
        if !(lim(q.x, nx) && lim(q.y, ny) && lim(q.z, nz)) {
            return None;
        }
        let c = |x: f64, d: usize| x.clamp(0.0, (d - 1) as f64);
        let (x, y, z) = (c(q.x, nx), c(q.y, ny), c(q.z, nz));
        let (i, j, k) = (
            (x as usize).min(nx.saturating_sub(2)),
            (y as usize).min(ny.saturating_sub(2)),
            (z as usize).min(nz.saturating_sub(2)),
        );
        let (fx, fy, fz) = ((x - i as f64) as f32, (y - j as f64) as f32, (z - k as f64) as f32);
        let at = |a: usize, b: usize, c: usize| {
            vol.data[vol.index((i + a).min(nx - 1), (j + b).min(ny - 1), (k + c).min(nz - 1))]
        };
        let lx = |b: usize, c: usize| at(0, b, c) * (1.0 - fx) + at(1, b, c) * fx;
        let ly = |c: usize| lx(0, c) * (1.0 - fy) + lx(1, c) * fy;
        Some(ly(0) * (1.0 - fz) + ly(1) * fz)
    };
    for py in 0..height {
        for px in 0..width {
            let mut p = origin_mm;
            p[ua] += (px as f64 + 0.5) * pixel_mm;
            p[va] += (py as f64 + 0.5) * pixel_mm;
            let q = voxel_from_world.transform_point(&Point3::from(p)).coords;
            if let Some(v) = sample(q).filter(|v| v.is_finite()) {
                let g = window.grey(v);
                let i = 4 * (py * width + px);
                rgba[i..i + 4].copy_from_slice(&[g, g, g, 255]);
            }
        }
    }
    Ok(Slice { axis, position_mm, origin_mm, pixel_mm, width, height, rgba })
}

/// The segments where the plane (world axis `axis.normal_axis()` = `position_mm`) cuts the
/// triangles of `mesh`; a closed surface gives closed outlines.
pub fn plane_section(mesh: &TriMesh, axis: SliceAxis, position_mm: f64) -> Vec<[Vector3<f64>; 2]> {
    let n = axis.normal_axis();
    let mut out = Vec::new();
    for t in &mesh.triangles {
        let p = t.map(|i| mesh.positions[i as usize]);
        // A vertex exactly on the plane counts as above it: each crossing is found once.
        let d = p.map(|q| q[n] - position_mm);
        let above = d.map(|x| x >= 0.0);
        if above[0] == above[1] && above[1] == above[2] {
            continue;
        }
        let mut pts = Vec::with_capacity(2);
        for (a, b) in [(0, 1), (1, 2), (2, 0)] {
            if above[a] != above[b] {
                let s = d[a] / (d[a] - d[b]);
                pts.push(p[a] + (p[b] - p[a]) * s);
            }
        }
        if let [a, b] = pts[..] {
            out.push([a, b]);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Matrix4;

    /// A 20 x 30 x 10 volume, 2 mm voxels, value = world x (mm) at each voxel centre.
    fn ramp() -> Volume {
        let mut a = Matrix4::identity();
        a[(0, 0)] = 2.0;
        a[(1, 1)] = 2.0;
        a[(2, 2)] = 2.0;
        a[(0, 3)] = -10.0;
        let mut v = Volume::new([20, 30, 10], a);
        for k in 0..10 {
            for j in 0..30 {
                for i in 0..20 {
                    let idx = v.index(i, j, k);
                    v.data[idx] = (2 * i) as f32 - 10.0;
                }
            }
        }
        v
    }

    #[test]
    fn a_slice_samples_the_volume_linearly_within_a_grey_level() {
        let v = ramp();
        let w = Window { level: 9.0, width: 38.0 }; // x in [-10, 28] mm -> 0..255
        let s = slice(&v, SliceAxis::Axial, 7.3, w, 512).unwrap();
        assert_eq!(s.pixel_mm, 1.0);
        assert_eq!((s.width, s.height), (40, 60));
        for py in [3, 30, 55] {
            for px in 1..s.width - 1 {
                let x = s.origin_mm.x + (px as f64 + 0.5);
                let want = ((x + 10.0) / 38.0).clamp(0.0, 1.0) * 255.0;
                let got = s.rgba[4 * (py * s.width + px)] as f64;
                assert!((got - want).abs() <= 1.0, "pixel {px},{py}: {got} vs {want}");
                assert_eq!(s.rgba[4 * (py * s.width + px) + 3], 255);
            }
        }
    }

    /// The box [0, size] as 12 triangles.
    fn box_mesh(size: Vector3<f64>) -> TriMesh {
        let positions = (0..8)
            .map(|c| {
                Vector3::new(size.x * (c & 1) as f64, size.y * ((c >> 1) & 1) as f64, size.z * ((c >> 2) & 1) as f64)
            })
            .collect();
        let quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]];
        let triangles = quads.iter().flat_map(|q: &[u32; 4]| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]).collect();
        TriMesh { positions, triangles }
    }

    #[test]
    fn the_section_of_a_closed_box_is_a_closed_outline_at_the_plane() {
        let b = box_mesh(Vector3::new(10.0, 20.0, 30.0));
        let segs = plane_section(&b, SliceAxis::Coronal, 5.0);
        assert!(!segs.is_empty());
        let len: f64 = segs.iter().map(|[a, b]| (b - a).norm()).sum();
        // The rectangle 10 x 30 in the x-z plane: perimeter 80 mm.
        assert!((len - 80.0).abs() < 1e-9, "perimeter {len}");
        assert!(segs.iter().flatten().all(|p| (p.y - 5.0).abs() < 1e-12));
        assert!(plane_section(&b, SliceAxis::Coronal, 25.0).is_empty());
    }

    #[test]
    fn bad_positions_and_windows_are_errors_and_outside_pixels_are_transparent() {
        let v = ramp();
        assert!(matches!(slice(&v, SliceAxis::Axial, f64::NAN, Window::ABDOMEN, 256), Err(SliceError::NotFinite(_))));
        assert!(matches!(
            slice(&v, SliceAxis::Axial, 0.0, Window { level: 0.0, width: 0.0 }, 256),
            Err(SliceError::BadWindow(_))
        ));
        // An oblique volume (rotated 30° about z): the axis-aligned slice has empty corners.
        let (c, s) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
        let mut r = Matrix4::identity();
        r[(0, 0)] = 2.0 * c;
        r[(0, 1)] = -2.0 * s;
        r[(1, 0)] = 2.0 * s;
        r[(1, 1)] = 2.0 * c;
        let mut o = v.clone();
        o.world_from_voxel = r;
        let sl = slice(&o, SliceAxis::Axial, 4.0, Window::ABDOMEN, 256).unwrap();
        assert_eq!(sl.rgba[3], 0, "the (u min, v min) corner lies outside the rotated volume");
        assert!(sl.rgba.chunks(4).filter(|p| p[3] == 255).count() > sl.width * sl.height / 3);
    }
}
