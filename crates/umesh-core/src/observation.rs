//! The observation operator: observed 3-D points of the organ surface (world frame, after
//! rigid alignment; no vertex identity) -> the network's input tensor on the rest grid's dense
//! lattice. The same function makes training inputs (points rendered from the deformed FE
//! solution) and runs at surgery (points from the depth camera).
//!
//! Two correspondence-free encodings, both sums over points (so invariant to their order) and
//! local averages or nearest points (so nearly invariant to their density):
//! - `corner` (after DeepPhysX's liver registration): each lattice node takes the
//!   trilinear-weighted mean offset (point - node) of the points in its 8 adjacent cells;
//!   taken relative to the same encoding of the whole rest surface;
//! - `nearest`: each point of a dense, fixed sampling of the rest surface looks for its nearest
//!   observed point within `band_mm`; the normal component of the offset (what a depth camera
//!   measures: tangential sliding is invisible, and dropping it removes the sampling noise) is
//!   spread to the lattice nodes with the rest point's trilinear weights and averaged. Offsets
//!   mostly tangential (a rest point beyond the edge of the seen patch) are ignored.
//!
//! Both are zero where the surface did not move (as the exact surface displacement u_s was)
//! and come with a mask channel: 4 channels [dx, dy, dz, observed] over [X, Y, Z]. The mask
//! holds half the cell size (mm) where observed, so that it scales like the offsets under the
//! network's input normalisation.

use crate::grid::ImmersedGrid;
use crate::mesh::TriMesh;
use crate::nn::PointIndex;
use nalgebra::Vector3;

/// Channels of the encoded observation: offset x, y, z (mm) and the observed mask (0 or h/2).
pub const CHANNELS: usize = 4;

#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Encoding {
    Corner,
    Nearest,
}

impl Encoding {
    pub fn parse(s: &str) -> Result<Self, crate::Invalid> {
        match s {
            "corner" => Ok(Encoding::Corner),
            "nearest" => Ok(Encoding::Nearest),
            other => Err(crate::Invalid(format!("unknown observation encoding {other:?}: corner or nearest"))),
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            Encoding::Corner => "corner",
            Encoding::Nearest => "nearest",
        }
    }
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ObservationSettings {
    pub encoding: Encoding,
    /// `nearest`: nodes farther than this from every observed point are unobserved (mm).
    pub band_mm: f64,
    /// Points sampled per mm^2 of the rest surface for the rest baseline.
    pub rest_density_per_mm2: f64,
}

impl Default for ObservationSettings {
    fn default() -> Self {
        Self { encoding: Encoding::Corner, band_mm: 10.0, rest_density_per_mm2: 0.25 }
    }
}

impl ObservationSettings {
    /// Settings whose work and memory stay bounded (a band of 1e30 mm made the encoder grow
    /// to tens of gigabytes).
    pub fn validate(&self) -> Result<(), crate::Invalid> {
        if !(self.band_mm.is_finite() && self.band_mm > 0.0 && self.band_mm <= 200.0) {
            return Err(crate::Invalid(format!("observation band {} mm: above 0 and at most 200 mm", self.band_mm)));
        }
        if !(self.rest_density_per_mm2.is_finite()
            && self.rest_density_per_mm2 > 0.0
            && self.rest_density_per_mm2 <= 10.0)
        {
            return Err(crate::Invalid(format!(
                "rest sampling density {} per mm^2: above 0 and at most 10",
                self.rest_density_per_mm2
            )));
        }
        Ok(())
    }
}

/// The encoder for one rest grid: the lattice, the rest baseline and reusable scratch.
pub struct Observer {
    pub settings: ObservationSettings,
    origin_mm: Vector3<f64>,
    h_mm: f64,
    shape: [usize; 3],
    /// The dense rest-surface sampling: points and outward normals.
    rest_points: Vec<(Vector3<f64>, Vector3<f64>)>,
    /// `corner`: the rest surface's own encoding ([3, X, Y, Z] offsets, and where defined).
    rest: Vec<f32>,
    rest_defined: Vec<bool>,
    acc: Vec<Vector3<f64>>,
    wsum: Vec<f64>,
    wmax: Vec<f64>,
    buckets: PointIndex,
}

/// What one encoding used.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct ObservationStats {
    pub points: usize,
    /// Points inside the lattice (the others are ignored).
    pub points_used: usize,
    pub nodes_observed: usize,
}

impl Observer {
    pub fn new(
        grid: &ImmersedGrid,
        rest_surface: &TriMesh,
        settings: ObservationSettings,
    ) -> Result<Self, crate::Invalid> {
        if !(settings.band_mm > 0.0 && settings.band_mm.is_finite()) {
            return Err(crate::Invalid(format!("observation band {} mm: must be positive", settings.band_mm)));
        }
        if !(settings.rest_density_per_mm2 > 0.0 && settings.rest_density_per_mm2.is_finite()) {
            return Err(crate::Invalid(format!(
                "rest sampling density {} per mm^2: must be positive",
                settings.rest_density_per_mm2
            )));
        }
        let shape = grid.padded_shape();
        let cells = shape.iter().product::<usize>();
        let mut o = Self {
            origin_mm: grid.origin_mm,
            h_mm: grid.cell_size_mm,
            shape,
            rest_points: Vec::new(),
            rest: vec![0.0; 3 * cells],
            rest_defined: vec![false; cells],
            acc: vec![Vector3::zeros(); cells],
            wsum: vec![0.0; cells],
            wmax: vec![0.0; cells],
            buckets: PointIndex::default(),
            settings,
        };
        o.rest_points = dense_surface_points(rest_surface, o.settings.rest_density_per_mm2);
        if o.rest_points.is_empty() {
            return Err(crate::Invalid::from("the rest surface has no triangle"));
        }
        if o.settings.encoding == Encoding::Corner {
            let pts: Vec<Vector3<f64>> = o.rest_points.iter().map(|p| p.0).collect();
            let mut raw = Vec::new();
            o.raw_encode(&pts, &mut raw);
            for d in 0..cells {
                if raw[3 * cells + d] > 0.0 {
                    o.rest_defined[d] = true;
                    for c in 0..3 {
                        o.rest[c * cells + d] = raw[c * cells + d];
                    }
                }
            }
        } else {
            o.rest_defined.iter_mut().for_each(|v| *v = true);
        }
        Ok(o)
    }

    pub fn shape(&self) -> [usize; 3] {
        self.shape
    }

    /// Encode `points_mm` into `out` ([CHANNELS, X, Y, Z], f32), relative to the rest surface.
    /// Non-finite points are ignored.
    pub fn encode(&mut self, points_mm: &[Vector3<f64>], out: &mut Vec<f32>) -> ObservationStats {
        let cells = self.shape.iter().product::<usize>();
        let used = self.raw_encode(points_mm, out);
        let mut observed = 0;
        for d in 0..cells {
            if out[3 * cells + d] > 0.0 && self.rest_defined[d] {
                observed += 1;
                for c in 0..3 {
                    out[c * cells + d] -= self.rest[c * cells + d];
                }
            } else {
                for c in 0..CHANNELS {
                    out[c * cells + d] = 0.0;
                }
            }
        }
        ObservationStats { points: points_mm.len(), points_used: used, nodes_observed: observed }
    }

    fn node_position(&self, i: usize, j: usize, k: usize) -> Vector3<f64> {
        self.origin_mm + Vector3::new(i as f64, j as f64, k as f64) * self.h_mm
    }

    fn dense(&self, i: usize, j: usize, k: usize) -> usize {
        (i * self.shape[1] + j) * self.shape[2] + k
    }

    /// The encoding without the rest baseline; returns the points inside the lattice.
    fn raw_encode(&mut self, points: &[Vector3<f64>], out: &mut Vec<f32>) -> usize {
        let cells = self.shape.iter().product::<usize>();
        out.clear();
        out.resize(CHANNELS * cells, 0.0);
        match self.settings.encoding {
            Encoding::Corner => self.corner(points, out, cells),
            Encoding::Nearest => self.nearest(points, out, cells),
        }
    }

    fn corner(&mut self, points: &[Vector3<f64>], out: &mut [f32], cells: usize) -> usize {
        self.clear_sums();
        let mut used = 0;
        for p in points.iter().filter(|p| p.iter().all(|v| v.is_finite())) {
            if self.splat(p, |x| p - x) {
                used += 1;
            }
        }
        self.write_means(out, cells);
        used
    }

    fn nearest(&mut self, points: &[Vector3<f64>], out: &mut [f32], cells: usize) -> usize {
        let band = self.settings.band_mm;
        let used = self.buckets.fill(points, self.origin_mm, band, self.shape, self.h_mm);
        if used == 0 {
            return 0;
        }
        self.clear_sums();
        for k in 0..self.rest_points.len() {
            let (r, n) = self.rest_points[k];
            let Some((_, q)) = self.buckets.nearest(&r, band) else { continue };
            let d = q - r;
            let dn = d.dot(&n);
            // Mostly sideways: this rest point lies beyond the seen patch (or in a hole).
            if (d - n * dn).norm() > TANGENTIAL_MM + dn.abs() {
                continue;
            }
            self.splat(&r, |_| n * dn);
        }
        self.write_means(out, cells);
        used
    }

    fn clear_sums(&mut self) {
        self.acc.iter_mut().for_each(|a| *a = Vector3::zeros());
        self.wsum.iter_mut().for_each(|w| *w = 0.0);
        self.wmax.iter_mut().for_each(|w| *w = 0.0);
    }

    /// Add `value(node position)` to the 8 lattice nodes of the cell holding `p`, with p's
    /// trilinear weights; false (nothing added) when p lies outside the lattice.
    fn splat(&mut self, p: &Vector3<f64>, value: impl Fn(Vector3<f64>) -> Vector3<f64>) -> bool {
        let [sx, sy, sz] = self.shape;
        let l = (p - self.origin_mm) / self.h_mm;
        let (fi, fj, fk) = (l.x.floor(), l.y.floor(), l.z.floor());
        if fi < 0.0 || fj < 0.0 || fk < 0.0 || fi + 1.0 >= sx as f64 || fj + 1.0 >= sy as f64 || fk + 1.0 >= sz as f64 {
            return false;
        }
        let (i, j, k) = (fi as usize, fj as usize, fk as usize);
        let t = Vector3::new(l.x - fi, l.y - fj, l.z - fk);
        for a in 0..8 {
            let (di, dj, dk) = (a & 1, (a >> 1) & 1, (a >> 2) & 1);
            let w = (if di == 1 { t.x } else { 1.0 - t.x })
                * (if dj == 1 { t.y } else { 1.0 - t.y })
                * (if dk == 1 { t.z } else { 1.0 - t.z });
            let d = self.dense(i + di, j + dj, k + dk);
            let v = value(self.node_position(i + di, j + dj, k + dk));
            self.acc[d] += v * w;
            self.wsum[d] += w;
            self.wmax[d] = self.wmax[d].max(w);
        }
        true
    }

    /// The weighted means into `out`, with the mask channel.
    fn write_means(&self, out: &mut [f32], cells: usize) {
        for d in 0..cells {
            // A node only seen by points at the far corners of its cells gets a noisy mean: it
            // needs one point with weight 1/8 (the largest weight, not the sum, so that the
            // test does not depend on the points' density).
            if self.wmax[d] >= 0.125 {
                let m = self.acc[d] / self.wsum[d];
                for c in 0..3 {
                    out[c * cells + d] = m[c] as f32;
                }
                out[3 * cells + d] = (0.5 * self.h_mm) as f32;
            }
        }
    }
}

/// `nearest`: an offset whose tangential part exceeds this plus its normal part is ignored (mm).
const TANGENTIAL_MM: f64 = 3.0;

/// A deterministic, even sampling of a surface with the triangles' normals: each triangle's
/// centroid and, for triangles larger than 1/density, a regular barycentric subdivision.
pub fn dense_surface_points(mesh: &TriMesh, density_per_mm2: f64) -> Vec<(Vector3<f64>, Vector3<f64>)> {
    let mut out = Vec::new();
    for (ti, t) in mesh.triangles.iter().enumerate() {
        let [a, b, c] = t.map(|i| mesh.positions[i as usize]);
        let (normal, area) = mesh.triangle_normal_area(ti);
        if !(area > 0.0) {
            continue;
        }
        let n = ((area * density_per_mm2).sqrt().ceil() as usize).max(1);
        for i in 0..n {
            for j in 0..n - i {
                let (u, v) = ((i as f64 + 1.0 / 3.0) / n as f64, (j as f64 + 1.0 / 3.0) / n as f64);
                out.push((a + (b - a) * u + (c - a) * v, normal));
            }
        }
    }
    out
}

/// What a depth camera gives of a deformed organ, for training inputs: the visible part
/// decided on the deformed shape from a jittered camera, a visible area that varies, depth
/// noise, dropped points, holes and occluding instruments.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct ViewSettings {
    /// Points sampled on the seen surface.
    pub points: usize,
    /// Camera position jitter (mm, uniform in a ball) and direction jitter (degrees).
    pub jitter_mm: f64,
    pub jitter_deg: f64,
    /// The seen fraction of the surface area is drawn uniformly in this range.
    pub min_fraction: f64,
    pub max_fraction: f64,
    /// Standard deviation of the depth noise along the viewing ray (mm).
    pub noise_mm: f64,
    /// Fraction of the points dropped at random.
    pub dropout: f64,
    /// Up to this many holes (radius 8-20 mm) and instruments (a 5 mm shaft between the
    /// camera and the organ) per view.
    pub max_holes: usize,
    pub max_instruments: usize,
}

impl Default for ViewSettings {
    fn default() -> Self {
        Self {
            points: 3000,
            jitter_mm: 15.0,
            jitter_deg: 8.0,
            min_fraction: 0.2,
            max_fraction: 0.5,
            noise_mm: 1.0,
            dropout: 0.1,
            max_holes: 3,
            max_instruments: 2,
        }
    }
}

impl ViewSettings {
    pub fn validate(&self) -> Result<(), crate::Invalid> {
        let finite =
            [self.jitter_mm, self.jitter_deg, self.min_fraction, self.max_fraction, self.noise_mm, self.dropout];
        if !finite.iter().all(|v| v.is_finite() && *v >= 0.0) {
            return Err(crate::Invalid(format!("camera view settings must be finite and non-negative: {self:?}")));
        }
        if !(self.min_fraction > 0.0 && self.min_fraction <= self.max_fraction && self.max_fraction <= 1.0) {
            return Err(crate::Invalid(format!(
                "seen fraction range {}..{}: needs 0 < min <= max <= 1",
                self.min_fraction, self.max_fraction
            )));
        }
        if self.dropout >= 1.0 || self.points == 0 || self.points > 1_000_000 {
            return Err(crate::Invalid(format!(
                "{} points with dropout {}: needs 1..1e6 points and dropout below 1",
                self.points, self.dropout
            )));
        }
        Ok(())
    }
}

/// The simulated view of `deformed` from around `camera`; deterministic for a given `rng`.
pub fn simulated_view(
    deformed: &TriMesh,
    camera: &crate::visible::Camera,
    settings: &ViewSettings,
    rng: &mut crate::rng::SplitMix64,
) -> Result<Vec<Vector3<f64>>, crate::Invalid> {
    let mut uniform = |lo: f64, hi: f64| lo + (hi - lo) * rng.next_f64();
    let unit = |rng_f: &mut dyn FnMut(f64, f64) -> f64| loop {
        let v = Vector3::new(rng_f(-1.0, 1.0), rng_f(-1.0, 1.0), rng_f(-1.0, 1.0));
        if v.norm_squared() <= 1.0 && v.norm_squared() > 1e-6 {
            return v;
        }
    };
    let eye = Vector3::from(camera.position_mm) + unit(&mut uniform) * settings.jitter_mm;
    let dir = Vector3::from(camera.direction).normalize();
    let dir = (dir + unit(&mut uniform) * settings.jitter_deg.to_radians()).normalize();
    let fraction = uniform(settings.min_fraction, settings.max_fraction);
    let cam = crate::visible::Camera { position_mm: eye.into(), direction: dir.into(), fov_deg: camera.fov_deg };
    let vis = crate::visible::visible_surface(
        deformed,
        &crate::visible::VisibilitySettings { camera: Some(cam), max_fraction: fraction, resolution: 256 },
    )?;
    let seen = crate::visible::sample_points(deformed, &vis.visible, settings.points, rng);
    let gauss = |rng: &mut crate::rng::SplitMix64| {
        // Box-Muller.
        let (a, b) = (rng.next_f64().max(1e-12), rng.next_f64());
        (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
    };
    let n_holes = (rng.next_u64() % (settings.max_holes as u64 + 1)) as usize;
    let n_tools = (rng.next_u64() % (settings.max_instruments as u64 + 1)) as usize;
    let pick = |rng: &mut crate::rng::SplitMix64| seen[(rng.next_u64() % seen.len().max(1) as u64) as usize].0;
    let holes: Vec<(Vector3<f64>, f64)> = if seen.is_empty() {
        Vec::new()
    } else {
        (0..n_holes).map(|_| (pick(rng), 8.0 + 12.0 * rng.next_f64())).collect()
    };
    // An instrument: a shaft from beside the camera to a seen point (its tip on the organ).
    let tools: Vec<(Vector3<f64>, Vector3<f64>)> = if seen.is_empty() {
        Vec::new()
    } else {
        (0..n_tools)
            .map(|_| {
                let tip = pick(rng);
                let side = Vector3::new(gauss(rng), gauss(rng), gauss(rng)) * 60.0;
                (eye + side, tip)
            })
            .collect()
    };
    let mut out = Vec::with_capacity(seen.len());
    for (p, _) in &seen {
        if rng.next_f64() < settings.dropout || holes.iter().any(|(c, r)| (p - c).norm() < *r) {
            continue;
        }
        if tools.iter().any(|(a, b)| segment_line_distance(a, b, &eye, p) < 5.0 && (p - b).norm() > 5.0) {
            continue;
        }
        let ray = (p - eye).normalize();
        out.push(p + ray * (settings.noise_mm * gauss(rng)));
    }
    Ok(out)
}

/// Distance between the segment [a, b] and the segment from the eye `e` to `p` (the ray to p):
/// whether an instrument hides p.
fn segment_line_distance(a: &Vector3<f64>, b: &Vector3<f64>, e: &Vector3<f64>, p: &Vector3<f64>) -> f64 {
    // Closest points of two segments, sampled finely enough for a 5 mm shaft.
    let (u, v) = (b - a, p - e);
    let w = a - e;
    let (aa, bb, cc, dd, ee) = (u.dot(&u), u.dot(&v), v.dot(&v), u.dot(&w), v.dot(&w));
    let den = aa * cc - bb * bb;
    let (mut s, mut t) =
        if den > 1e-12 { ((bb * ee - cc * dd) / den, (aa * ee - bb * dd) / den) } else { (0.0, ee / cc.max(1e-12)) };
    s = s.clamp(0.0, 1.0);
    t = t.clamp(0.0, 1.0);
    ((a + u * s) - (e + v * t)).norm()
}
