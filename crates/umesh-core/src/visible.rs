//! The part of the organ surface a camera sees: front-facing, inside the field of view and
//! not occluded (a depth buffer over the surface mesh), capped at a fraction of the area.

use crate::mesh::TriMesh;
use nalgebra::{Matrix3, Vector3};

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Camera {
    pub position_mm: [f64; 3],
    /// Viewing direction (need not be unit).
    pub direction: [f64; 3],
    pub fov_deg: f64,
}

impl Camera {
    /// Looking at the anterior face (from +y, RAS) of a mesh from 2.5 organ sizes away.
    pub fn anterior(mesh: &TriMesh) -> Self {
        let (lo, hi) = mesh.bounds().unwrap_or((Vector3::zeros(), Vector3::zeros()));
        let c = (lo + hi) * 0.5;
        let size = (hi - lo).max().max(1.0);
        Self { position_mm: [c.x, c.y + 2.5 * size, c.z], direction: [0.0, -1.0, 0.0], fov_deg: 50.0 }
    }

    /// The laparoscope views by name, from 2.5 organ sizes away: `anterior` (from +y, RAS),
    /// `posterior`, `right` (from +x), `left`, `superior` (from +z), `inferior`, or two of them
    /// joined by `-` for an oblique view (`anterior-inferior`). `lo`, `hi`: the organ's bounds.
    pub fn named(view: &str, lo: &Vector3<f64>, hi: &Vector3<f64>) -> Result<Self, crate::Invalid> {
        let axis = |name: &str| -> Option<Vector3<f64>> {
            Some(match name {
                "anterior" => Vector3::y(),
                "posterior" => -Vector3::y(),
                "right" => Vector3::x(),
                "left" => -Vector3::x(),
                "superior" => Vector3::z(),
                "inferior" => -Vector3::z(),
                _ => return None,
            })
        };
        let mut from = Vector3::zeros();
        for part in view.trim().to_lowercase().split('-') {
            from += axis(part).ok_or_else(|| {
                format!("unknown camera view {view:?}: anterior, posterior, right, left, superior, inferior, or two joined by '-'")
            })?;
        }
        if from.norm() < 1e-9 {
            return Err(crate::Invalid(format!("camera view {view:?}: opposite directions cancel")));
        }
        let c = (lo + hi) * 0.5;
        let size = (hi - lo).max().max(1.0);
        let eye = c + from.normalize() * 2.5 * size;
        Ok(Self::look_at(&eye, &c, 50.0))
    }

    pub fn look_at(from_mm: &Vector3<f64>, to_mm: &Vector3<f64>, fov_deg: f64) -> Self {
        let d = to_mm - from_mm;
        Self { position_mm: (*from_mm).into(), direction: d.into(), fov_deg }
    }

    /// Rotation whose rows are the camera's right, up and forward axes.
    fn frame(&self) -> Option<Matrix3<f64>> {
        let f = Vector3::from(self.direction);
        if f.norm() == 0.0 || !f.iter().all(|v| v.is_finite()) {
            return None;
        }
        let f = f.normalize();
        let up0 = if f.z.abs() < 0.9 { Vector3::z() } else { Vector3::y() };
        let r = f.cross(&up0).normalize();
        let u = r.cross(&f);
        Some(Matrix3::from_rows(&[r.transpose(), u.transpose(), f.transpose()]))
    }
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct VisibilitySettings {
    pub camera: Option<Camera>,
    /// At most this fraction of the total surface area is visible (the paper: one half).
    pub max_fraction: f64,
    /// Depth-buffer resolution (pixels per side).
    pub resolution: usize,
}

impl Default for VisibilitySettings {
    fn default() -> Self {
        Self { camera: None, max_fraction: 0.5, resolution: 512 }
    }
}

#[derive(Clone, Debug)]
pub struct VisibleSurface {
    pub camera: Camera,
    /// Per triangle: visible.
    pub visible: Vec<bool>,
    pub visible_area_mm2: f64,
    pub total_area_mm2: f64,
}

impl VisibleSurface {
    pub fn fraction(&self) -> f64 {
        self.visible_area_mm2 / self.total_area_mm2.max(1e-30)
    }
}

/// Which triangles of `mesh` the camera sees.
pub fn visible_surface(mesh: &TriMesh, settings: &VisibilitySettings) -> Result<VisibleSurface, crate::Invalid> {
    let camera = settings.camera.clone().unwrap_or_else(|| Camera::anterior(mesh));
    let frame = camera.frame().ok_or("the camera direction is zero or not finite")?;
    if !(settings.fov_ok(&camera)) {
        return Err(crate::Invalid(format!("field of view {} deg must lie in (0, 170)", camera.fov_deg)));
    }
    let eye = Vector3::from(camera.position_mm);
    let res = settings.resolution.clamp(16, 4096);
    let tan_half = (camera.fov_deg.to_radians() * 0.5).tan();
    // Camera coordinates -> pixel coordinates and depth.
    let project = |p: &Vector3<f64>| -> Option<(f64, f64, f64)> {
        let c = frame * (p - eye);
        if c.z <= 1e-6 {
            return None;
        }
        let x = (c.x / (c.z * tan_half) * 0.5 + 0.5) * res as f64;
        let y = (c.y / (c.z * tan_half) * 0.5 + 0.5) * res as f64;
        Some((x, y, c.z))
    };
    let mut depth = vec![f64::INFINITY; res * res];
    let proj: Vec<Option<(f64, f64, f64)>> = mesh.positions.iter().map(project).collect();
    for t in &mesh.triangles {
        let (Some(a), Some(b), Some(c)) = (proj[t[0] as usize], proj[t[1] as usize], proj[t[2] as usize]) else {
            continue;
        };
        let x0 = a.0.min(b.0).min(c.0).floor().max(0.0) as usize;
        let x1 = (a.0.max(b.0).max(c.0).ceil() as usize).min(res - 1);
        let y0 = a.1.min(b.1).min(c.1).floor().max(0.0) as usize;
        let y1 = (a.1.max(b.1).max(c.1).ceil() as usize).min(res - 1);
        let area = (b.0 - a.0) * (c.1 - a.1) - (c.0 - a.0) * (b.1 - a.1);
        if area.abs() < 1e-12 || x0 > x1 || y0 > y1 {
            continue;
        }
        for py in y0..=y1 {
            for px in x0..=x1 {
                let (qx, qy) = (px as f64 + 0.5, py as f64 + 0.5);
                let w0 = ((b.0 - qx) * (c.1 - qy) - (c.0 - qx) * (b.1 - qy)) / area;
                let w1 = ((c.0 - qx) * (a.1 - qy) - (a.0 - qx) * (c.1 - qy)) / area;
                let w2 = 1.0 - w0 - w1;
                if w0 >= 0.0 && w1 >= 0.0 && w2 >= 0.0 {
                    let z = w0 * a.2 + w1 * b.2 + w2 * c.2;
                    let d = &mut depth[py * res + px];
                    if z < *d {
                        *d = z;
                    }
                }
            }
        }
    }
    let size = mesh.bounds().map(|(lo, hi)| (hi - lo).norm()).unwrap_or(1.0);
    let tol = 0.01 * size;
    let mut visible = vec![false; mesh.triangles.len()];
    let mut total = 0.0;
    // (angle from the view axis, triangle, area) of visible candidates.
    let mut cand: Vec<(f64, usize, f64)> = Vec::new();
    for (ti, t) in mesh.triangles.iter().enumerate() {
        let (n, area) = mesh.triangle_normal_area(ti);
        total += area;
        let cen = t.iter().map(|&i| mesh.positions[i as usize]).sum::<Vector3<f64>>() / 3.0;
        let to_eye = eye - cen;
        if n.dot(&to_eye) <= 0.0 {
            continue;
        }
        let Some((x, y, z)) = project(&cen) else { continue };
        if x < 0.0 || y < 0.0 || x >= res as f64 || y >= res as f64 {
            continue;
        }
        if z <= depth[(y as usize) * res + x as usize] + tol {
            let fwd = frame.row(2).transpose();
            let ang = (-to_eye.normalize()).dot(&fwd).clamp(-1.0, 1.0).acos();
            cand.push((ang, ti, area));
        }
    }
    // Keep the most central triangles up to the area cap.
    cand.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let cap = settings.max_fraction.clamp(0.0, 1.0) * total;
    let mut area = 0.0;
    for (_, ti, a) in cand {
        if area + a > cap {
            break;
        }
        area += a;
        visible[ti] = true;
    }
    Ok(VisibleSurface { camera, visible, visible_area_mm2: area, total_area_mm2: total })
}

impl VisibilitySettings {
    fn fov_ok(&self, c: &Camera) -> bool {
        c.fov_deg > 0.0 && c.fov_deg < 170.0 && c.position_mm.iter().all(|v| v.is_finite())
    }
}

/// `n` points uniformly distributed by area over the visible triangles, with their normals.
pub fn sample_points(
    mesh: &TriMesh,
    visible: &[bool],
    n: usize,
    rng: &mut crate::rng::SplitMix64,
) -> Vec<(Vector3<f64>, Vector3<f64>)> {
    let mut cum = Vec::new();
    let mut ids = Vec::new();
    let mut acc = 0.0;
    for (ti, &v) in visible.iter().enumerate() {
        if v {
            acc += mesh.triangle_normal_area(ti).1;
            cum.push(acc);
            ids.push(ti);
        }
    }
    if ids.is_empty() {
        return Vec::new();
    }
    (0..n)
        .map(|_| {
            let r = rng.next_f64() * acc;
            let k = cum.partition_point(|&c| c < r).min(ids.len() - 1);
            let t = mesh.triangles[ids[k]];
            let [a, b, c] = t.map(|i| mesh.positions[i as usize]);
            let (s1, s2) = (rng.next_f64().sqrt(), rng.next_f64());
            let p = a * (1.0 - s1) + b * (s1 * (1.0 - s2)) + c * (s1 * s2);
            (p, mesh.triangle_normal_area(ids[k]).0)
        })
        .collect()
}
