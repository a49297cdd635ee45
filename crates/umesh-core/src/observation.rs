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
        if !(self.rest_density_per_mm2.is_finite() && self.rest_density_per_mm2 > 0.0 && self.rest_density_per_mm2 <= 10.0) {
            return Err(crate::Invalid(format!("rest sampling density {} per mm^2: above 0 and at most 10", self.rest_density_per_mm2)));
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
    buckets: Buckets,
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
    pub fn new(grid: &ImmersedGrid, rest_surface: &TriMesh, settings: ObservationSettings) -> Result<Self, crate::Invalid> {
        if !(settings.band_mm > 0.0 && settings.band_mm.is_finite()) {
            return Err(crate::Invalid(format!("observation band {} mm: must be positive", settings.band_mm)));
        }
        if !(settings.rest_density_per_mm2 > 0.0 && settings.rest_density_per_mm2.is_finite()) {
            return Err(crate::Invalid(format!("rest sampling density {} per mm^2: must be positive", settings.rest_density_per_mm2)));
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
            buckets: Buckets::default(),
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
            let w =
                (if di == 1 { t.x } else { 1.0 - t.x }) * (if dj == 1 { t.y } else { 1.0 - t.y }) * (if dk == 1 { t.z } else { 1.0 - t.z });
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

const MAX_BUCKETS: f64 = (1 << 20) as f64;

/// Points bucketed on a uniform grid of cells half the `band` wide, for nearest-point queries
/// searched in shells: a query near a point stops after 27 cells of band/2, an eighth of the
/// volume of the 27 band-wide cells it scanned before (the physics correction's closest-sample
/// search was a quarter of its time).
#[derive(Default)]
pub(crate) struct Buckets {
    origin: Vector3<f64>,
    size: f64,
    dims: [usize; 3],
    start: Vec<u32>,
    points: Vec<Vector3<f64>>,
    /// Index of each bucketed point in the filled slice.
    index: Vec<u32>,
    /// The points of the filled slice the box left out (non-finite or beyond the band).
    outside: Vec<u32>,
}

impl Buckets {
    pub(crate) fn fill(&mut self, points: &[Vector3<f64>], lattice_origin: Vector3<f64>, band: f64, shape: [usize; 3], h: f64) -> usize {
        // The lattice's box grown by the band: points beyond cannot be nearest to a node.
        self.origin = lattice_origin - Vector3::repeat(band);
        let extent = Vector3::new(shape[0] as f64, shape[1] as f64, shape[2] as f64) * h + Vector3::repeat(2.0 * band);
        // Cells of half the band, but at most about MAX_BUCKETS of them (a small band on a
        // large organ): the shell search finds the same nearest point with any cell size.
        self.size = (0.5 * band).max((extent.x * extent.y * extent.z / MAX_BUCKETS).cbrt());
        self.dims = [0, 1, 2].map(|a| ((extent[a] / self.size).ceil() as usize).max(1));
        let n = self.dims.iter().product::<usize>();
        // A counting sort: counts, their running sums as each cell's end, then each point
        // placed by counting down from its cell's end, which leaves the starts.
        let keys: Vec<u32> = points.iter().map(|p| self.cell_of(p).map_or(u32::MAX, |b| b as u32)).collect();
        let mut start = std::mem::take(&mut self.start);
        start.clear();
        start.resize(n + 1, 0);
        for &b in keys.iter().filter(|&&b| b != u32::MAX) {
            start[b as usize + 1] += 1;
        }
        for b in 0..n {
            start[b + 1] += start[b];
        }
        let used = start[n] as usize;
        self.outside.clear();
        self.outside.extend(keys.iter().enumerate().filter(|(_, b)| **b == u32::MAX).map(|(i, _)| i as u32));
        self.points.clear();
        self.points.resize(used, Vector3::zeros());
        self.index.clear();
        self.index.resize(used, 0);
        for (i, (p, &b)) in points.iter().zip(&keys).enumerate().rev() {
            if b != u32::MAX {
                let end = &mut start[b as usize + 1];
                *end -= 1;
                self.points[*end as usize] = *p;
                self.index[*end as usize] = i as u32;
            }
        }
        // Each cell's end counted down to its start; shift back so start[b]..start[b + 1] is b.
        for b in 0..n {
            start[b] = start[b + 1];
        }
        start[n] = used as u32;
        self.start = start;
        used
    }

    /// The bucket of `p`; None outside the grown lattice's box or not finite.
    fn cell_of(&self, p: &Vector3<f64>) -> Option<usize> {
        let l = (p - self.origin) / self.size;
        if !(l.iter().all(|v| v.is_finite() && *v >= 0.0)) {
            return None;
        }
        let (i, j, k) = (l.x as usize, l.y as usize, l.z as usize);
        (i < self.dims[0] && j < self.dims[1] && k < self.dims[2]).then(|| (i * self.dims[1] + j) * self.dims[2] + k)
    }

    /// Whether a fill would bucket `p`.
    pub(crate) fn holds(&self, p: &Vector3<f64>) -> bool {
        self.cell_of(p).is_some()
    }

    /// The nearest point within `band` of `x` once the bucketed points have moved to `now`
    /// (indexed as filled) by at most `moved` each, given that one of them is now within
    /// `reach` of `x` and inside the box (`band` when none is known): the same point as
    /// `nearest` on buckets filled with `now`, without the fill. The nearest is now within
    /// `reach`, so it was within `reach + moved` when filled: only the buckets that far are
    /// looked at.
    pub(crate) fn nearest_moved(&self, x: &Vector3<f64>, now: &[Vector3<f64>], reach: f64, moved: f64, band: f64) -> Option<usize> {
        // A micrometre's slack for the rounding of the positions keeps every candidate.
        let r = reach.min(band) + moved + 1e-3;
        if !(self.size > 0.0 && r.is_finite() && x.iter().all(|v| v.is_finite())) {
            return None;
        }
        let range = |a: usize| {
            let lo = ((x[a] - r - self.origin[a]) / self.size).floor().max(0.0) as usize;
            let hi = ((x[a] + r - self.origin[a]) / self.size).floor();
            (lo, if hi < 0.0 { None } else { Some((hi as usize).min(self.dims[a] - 1)) })
        };
        let mut best: Option<(f64, usize, Vector3<f64>)> = None;
        let mut consider = |idx: usize| {
            let q = now[idx];
            let d2 = (q - x).norm_squared();
            // A fresh fill would not hold a point moved out of the box.
            if d2 > band * band || !self.holds(&q) {
                return;
            }
            // `nearest`'s order: distance, then coordinates, then index.
            let better = match best {
                None => true,
                Some((bd, bi, bq)) => d2 < bd || (d2 == bd && (q.x, q.y, q.z, idx) < (bq.x, bq.y, bq.z, bi)),
            };
            if better {
                best = Some((d2, idx, q));
            }
        };
        if let [(i0, Some(i1)), (j0, Some(j1)), (k0, Some(k1))] = [range(0), range(1), range(2)] {
            for i in i0..=i1 {
                for j in j0..=j1 {
                    let row = (i * self.dims[1] + j) * self.dims[2];
                    for b in row + k0..=row + k1 {
                        for s in self.start[b] as usize..self.start[b + 1] as usize {
                            if (self.points[s] - x).norm_squared() <= r * r {
                                consider(self.index[s] as usize);
                            }
                        }
                    }
                }
            }
        }
        // Those the box left out may have moved in.
        for &idx in &self.outside {
            consider(idx as usize);
        }
        best.map(|(_, i, _)| i)
    }

    /// The nearest bucketed point within `band` of `x`: its index in the filled slice and
    /// position. Ties go to the smaller coordinates, then the smaller index, so the result does
    /// not depend on the order of the search.
    pub(crate) fn nearest(&self, x: &Vector3<f64>, band: f64) -> Option<(usize, Vector3<f64>)> {
        if self.size <= 0.0 {
            return None;
        }
        let l = (x - self.origin) / self.size;
        let c = [l.x.floor() as i64, l.y.floor() as i64, l.z.floor() as i64];
        // Queries use the band the buckets were filled with (2 shells) or less; 64 bounds a
        // query's work should one ask for far more.
        let reach = (band / self.size).ceil().clamp(1.0, 64.0) as i64;
        let mut best: Option<(f64, usize, Vector3<f64>)> = None;
        let visit = |i: i64, j: i64, k: i64, best: &mut Option<(f64, usize, Vector3<f64>)>| {
            if i < 0 || j < 0 || k < 0 || i >= self.dims[0] as i64 || j >= self.dims[1] as i64 || k >= self.dims[2] as i64 {
                return;
            }
            let b = (i as usize * self.dims[1] + j as usize) * self.dims[2] + k as usize;
            for s in self.start[b] as usize..self.start[b + 1] as usize {
                let (q, idx) = (&self.points[s], self.index[s] as usize);
                let d2 = (q - x).norm_squared();
                let better = match *best {
                    None => true,
                    Some((bd, bi, bq)) => d2 < bd || (d2 == bd && (q.x, q.y, q.z, idx) < (bq.x, bq.y, bq.z, bi)),
                };
                if better {
                    *best = Some((d2, idx, *q));
                }
            }
        };
        for shell in 0..=reach {
            for di in -shell..=shell {
                for dj in -shell..=shell {
                    // Inside the shell's cube only its two k faces are new.
                    let stride = if di.abs() == shell || dj.abs() == shell { 1 } else { 2 * shell as usize };
                    for dk in (-shell..=shell).step_by(stride.max(1)) {
                        visit(c[0] + di, c[1] + dj, c[2] + dk, &mut best);
                    }
                }
            }
            // Every point of the next shell is at least `shell` whole cells away: a nearer one
            // (or a tie) cannot be there.
            let r = shell as f64 * self.size;
            if best.is_some_and(|(d2, _, _)| d2 < r * r) {
                break;
            }
        }
        best.filter(|(d2, _, _)| *d2 <= band * band).map(|(_, i, q)| (i, q))
    }
}

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
        let finite = [self.jitter_mm, self.jitter_deg, self.min_fraction, self.max_fraction, self.noise_mm, self.dropout];
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
    let holes: Vec<(Vector3<f64>, f64)> =
        if seen.is_empty() { Vec::new() } else { (0..n_holes).map(|_| (pick(rng), 8.0 + 12.0 * rng.next_f64())).collect() };
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
    let (mut s, mut t) = if den > 1e-12 { ((bb * ee - cc * dd) / den, (aa * ee - bb * dd) / den) } else { (0.0, ee / cc.max(1e-12)) };
    s = s.clamp(0.0, 1.0);
    t = t.clamp(0.0, 1.0);
    ((a + u * s) - (e + v * t)).norm()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A sphere's surface (radius 30 mm about (40, 40, 40)) sampled about every 1-2 mm, with
    /// exact duplicates of the first 50 at the end (ties by index).
    fn sphere_points(r: &mut impl FnMut(f64) -> f64) -> Vec<Vector3<f64>> {
        let mut points: Vec<Vector3<f64>> = (0..4000)
            .map(|_| {
                let (z, a) = (r(2.0) - 1.0, r(std::f64::consts::TAU));
                let s = (1.0 - z * z).sqrt();
                Vector3::new(40.0 + 30.0 * s * a.cos(), 40.0 + 30.0 * s * a.sin(), 40.0 + 30.0 * z)
            })
            .collect();
        points.extend(points[..50].to_vec());
        points
    }

    #[test]
    fn buckets_find_the_same_nearest_point_within_the_band_as_a_brute_force_search() {
        let mut rng = crate::rng::SplitMix64(7);
        let mut r = |s: f64| s * rng.next_f64();
        let points = sphere_points(&mut r);
        // 0.05 mm on an 80 mm lattice: cells far larger than half the band (about 2^20 of them at most).
        for (band, h) in [(2.0, 4.0), (5.0, 4.0), (10.0, 4.0), (0.05, 4.0)] {
            let mut b = Buckets::default();
            assert_eq!(b.fill(&points, Vector3::zeros(), band, [20, 20, 20], h), points.len());
            // Each axis rounds its count up: a few per cent over.
            assert!(b.start.len() <= (1 << 20) * 11 / 10, "{} cells for a {band} mm band", b.start.len());
            for k in 0..2000 {
                // Anywhere in the box, or near a point (within the band).
                let q = if k % 2 == 0 {
                    Vector3::new(r(90.0) - 5.0, r(90.0) - 5.0, r(90.0) - 5.0)
                } else {
                    let p = points[(r(1.0) * points.len() as f64) as usize % points.len()];
                    p + Vector3::new(r(band) - 0.5 * band, r(band) - 0.5 * band, r(band) - 0.5 * band) * 0.5
                };
                let brute =
                    points.iter().enumerate().map(|(i, p)| ((p - q).norm_squared(), i)).filter(|(d2, _)| *d2 <= band * band).min_by(
                        |a, b| {
                            a.0.total_cmp(&b.0).then_with(|| {
                                (points[a.1].x, points[a.1].y, points[a.1].z, a.1)
                                    .partial_cmp(&(points[b.1].x, points[b.1].y, points[b.1].z, b.1))
                                    .unwrap()
                            })
                        },
                    );
                let got = b.nearest(&q, band).map(|(i, _)| i);
                assert_eq!(got, brute.map(|(_, i)| i), "band {band} mm, query {q:?}");
            }
        }
    }

    #[test]
    fn buckets_find_after_a_move_the_same_nearest_point_as_buckets_filled_anew() {
        let mut rng = crate::rng::SplitMix64(11);
        let mut r = |s: f64| s * rng.next_f64();
        let filled = sphere_points(&mut r);
        let band = 10.0;
        // Moves small and large against the band, some points crossing the box's side.
        for moved in [0.3, 2.0, 8.0] {
            let mut now: Vec<Vector3<f64>> =
                filled.iter().map(|p| p + Vector3::new(r(2.0) - 1.0, r(2.0) - 1.0, r(2.0) - 1.0).normalize() * r(moved)).collect();
            // The duplicates moved alike (ties by index after the move).
            for i in 0..50 {
                now[4000 + i] = now[i];
            }
            // The box ends at x = 50 + 10 mm: the sphere (x up to 70) reaches beyond it.
            let shape = [10, 20, 20];
            let mut old = Buckets::default();
            old.fill(&filled, Vector3::zeros(), band, shape, 4.0);
            let mut fresh = Buckets::default();
            fresh.fill(&now, Vector3::zeros(), band, shape, 4.0);
            let left = now.iter().zip(&filled).filter(|(n, f)| old.holds(f) != old.holds(n)).count();
            assert!(moved < 1.0 || left > 0, "no point crossed the box's side at {moved} mm");
            for k in 0..2000 {
                let q = if k % 2 == 0 {
                    Vector3::new(r(90.0) - 5.0, r(90.0) - 5.0, r(90.0) - 5.0)
                } else {
                    now[(r(1.0) * now.len() as f64) as usize % now.len()] + Vector3::new(r(4.0) - 2.0, r(4.0) - 2.0, r(4.0) - 2.0)
                };
                // A known point's distance bounds the nearest's, as the previous match does.
                let known = now[(r(1.0) * now.len() as f64) as usize % now.len()];
                let reach = if k % 3 == 0 || !fresh.holds(&known) { band } else { (known - q).norm() };
                let expect = fresh.nearest(&q, band).map(|(i, _)| i);
                assert_eq!(old.nearest_moved(&q, &now, reach, moved, band), expect, "moved {moved} mm, query {q:?}");
            }
        }
    }
}
