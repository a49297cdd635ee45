//! Confidence of a registered frame without ground truth: how far the observed organ points
//! lie from the predicted surface, how much of the organ they cover, how far the prediction
//! moved the organ, each against the range the model met on its validation views.

use crate::mesh::TriMesh;
use nalgebra::Vector3;
use rayon::prelude::*;

/// At most this many observed points are measured per frame (every n-th point).
const MAX_POINTS: usize = 1000;

/// Bucket size for the points near the surface (mm).
const FINE_BUCKET_MM: f64 = 4.0;

/// A point farther than this from every surface vertex counts as this far (mm).
pub const RESIDUAL_CAP_MM: f64 = 20.0;

/// What one frame's figures are compared with: their range on the model's validation views
/// (written by training or `umesh eval --calibrate`).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ConfidenceReference {
    /// The 95th percentile over the views of each view's 95th percentile of the distance from
    /// its points to the predicted surface; over the views the model got right when
    /// `correct_tre_mm` is set, over all of them in files from before.
    pub residual_p95_mm: f64,
    /// The 95th percentile over the views of that distance's mean.
    pub residual_mean_mm: f64,
    /// The residuals above were measured on the validation views registered within this TRE
    /// (CORRECT_TRE_MM, or the TRE of the best quarter when too few are): a frame is compared
    /// with predictions known to be right, so a weak network does not loosen its own check.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub correct_tre_mm: Option<f64>,
    /// How many views that was.
    #[serde(default)]
    pub correct_views: usize,
    /// The 5th percentile over the views of the surface coverage.
    pub coverage_min: f64,
    /// The largest displacement of a surface vertex in the training targets.
    pub displacement_max_mm: f64,
    /// Views it was measured on.
    pub views: usize,
}

impl ConfidenceReference {
    pub const FILE: &'static str = "confidence.json";

    /// None when the model folder has no such file (an uncalibrated model); an error naming
    /// the file when it is there but unreadable or corrupt.
    pub fn read(model_dir: &std::path::Path) -> Result<Option<Self>, crate::Invalid> {
        let path = model_dir.join(Self::FILE);
        if !path.exists() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&path).map_err(|e| format!("{}: {e}", path.display()))?;
        let r: Self = serde_json::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))?;
        let finite = [
            r.residual_p95_mm,
            r.residual_mean_mm,
            r.coverage_min,
            r.displacement_max_mm,
            r.correct_tre_mm.unwrap_or(0.0),
        ];
        if !finite.iter().all(|v| v.is_finite() && *v >= 0.0) {
            return Err(crate::Invalid(format!(
                "{}: the confidence range holds negative or non-finite values",
                path.display()
            )));
        }
        // Limits a frame cannot reach would silence every warning (1e308, then 1000 mm, were
        // accepted): a residual is measured up to RESIDUAL_CAP_MM; no organ moves 300 mm. A
        // range of zero was measured on nothing and would flag every frame.
        let bounds = [
            ("residual_p95_mm", r.residual_p95_mm, RESIDUAL_CAP_MM),
            ("residual_mean_mm", r.residual_mean_mm, RESIDUAL_CAP_MM),
            ("displacement_max_mm", r.displacement_max_mm, 300.0),
        ];
        if let Some((name, v, max)) = bounds.iter().find(|(_, v, max)| !(*v > 0.0 && v <= max)) {
            return Err(crate::Invalid(format!(
                "{}: {name} = {v} mm: a confidence range lies above 0 and at most {max} mm (what a frame can measure)",
                path.display()
            )));
        }
        if !(r.coverage_min > 0.0 && r.coverage_min <= 1.0) || r.views == 0 {
            return Err(crate::Invalid(format!(
                "{}: coverage_min = {} over {} views: a share above 0 and at most 1, measured on at least one view",
                path.display(),
                r.coverage_min,
                r.views
            )));
        }
        Ok(Some(r))
    }
}

/// One frame's confidence figures and what they say.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct Confidence {
    /// Distance from the observed organ points to the predicted organ surface.
    pub residual_mean_mm: f64,
    pub residual_p95_mm: f64,
    /// The observed share of the organ's surface.
    pub surface_coverage: f64,
    /// The largest displacement of the predicted surface.
    pub displacement_max_mm: f64,
    /// Why the overlay should not be trusted (empty: within the range seen in training, or
    /// no reference to compare with).
    pub warnings: Vec<String>,
    /// A reference was available to compare with.
    pub calibrated: bool,
    /// A warning about the prediction itself (the observed points too far from it, or it moves
    /// beyond the training deformations), not only about how much is seen.
    pub prediction_doubted: bool,
}

impl Confidence {
    pub fn warning(&self) -> bool {
        !self.warnings.is_empty()
    }
}

/// A validation view counts as right when its marker TRE is within this (the registration bar).
pub const CORRECT_TRE_MM: f64 = 2.0;

/// Tolerance over a reference measured on right views: measured on the phantom and the CT
/// patient, it flags every frame beyond 2.6 mm and few below 2.0 (docs/REGISTRATION.md).
const RESIDUAL_SLACK_MM: f64 = 0.5;
/// References from before measured all views, wrong ones too: a wider tolerance (a frame is
/// not held to the single worst view).
const RESIDUAL_MARGIN_ALL_VIEWS: f64 = 1.5;
const DISPLACEMENT_MARGIN: f64 = 1.25;

impl ConfidenceReference {
    /// The residual beyond which a frame warns, for a reference residual `r`.
    fn residual_limit(&self, r: f64) -> f64 {
        match self.correct_tre_mm {
            Some(_) => r + RESIDUAL_SLACK_MM,
            None => r * RESIDUAL_MARGIN_ALL_VIEWS + RESIDUAL_SLACK_MM,
        }
    }

    /// What the residual limits were measured on, for the warnings.
    fn residual_basis(&self) -> String {
        match self.correct_tre_mm {
            Some(t) => format!("seen on the validation views registered within {t:.1} mm"),
            None => "seen in training".to_string(),
        }
    }
}

/// The confidence of a frame: `points` (world, mm) against `predicted` (the organ surface
/// deformed by the prediction) and `rest` (the same mesh undeformed).
pub fn frame_confidence(
    points: &[Vector3<f64>],
    predicted: &TriMesh,
    rest: &TriMesh,
    rings: &VertexRings,
    coverage: f64,
    reference: Option<&ConfidenceReference>,
) -> Confidence {
    let (residual_mean_mm, residual_p95_mm) = surface_residual_with(points, predicted, rings);
    let displacement_max_mm =
        predicted.positions.iter().zip(&rest.positions).map(|(a, b)| (a - b).norm()).fold(0.0, f64::max);
    let mut c = Confidence {
        residual_mean_mm,
        residual_p95_mm,
        surface_coverage: coverage,
        displacement_max_mm,
        warnings: Vec::new(),
        calibrated: reference.is_some(),
        prediction_doubted: false,
    };
    if let Some(r) = reference {
        let p95_limit = r.residual_limit(r.residual_p95_mm);
        if residual_p95_mm > p95_limit {
            c.warnings.push(format!(
                "the observed surface is {residual_p95_mm:.1} mm (95th percentile) from the predicted one, beyond the {p95_limit:.1} mm {}",
                r.residual_basis()
            ));
        }
        let mean_limit = r.residual_limit(r.residual_mean_mm);
        if residual_mean_mm > mean_limit {
            c.warnings.push(format!(
                "the observed surface is {residual_mean_mm:.1} mm (mean) from the predicted one, beyond the {mean_limit:.1} mm {}",
                r.residual_basis()
            ));
        }
        if coverage < r.coverage_min {
            c.warnings.push(format!(
                "{:.0} % of the organ's surface is seen, less than the {:.0} % of 95 % of the validation views",
                100.0 * coverage,
                100.0 * r.coverage_min
            ));
        }
        let d_limit = r.displacement_max_mm * DISPLACEMENT_MARGIN;
        if displacement_max_mm > d_limit {
            c.warnings.push(format!(
                "the predicted surface moves {displacement_max_mm:.1} mm, beyond the {:.1} mm of the training deformations",
                r.displacement_max_mm
            ));
        }
        c.prediction_doubted =
            residual_p95_mm > p95_limit || residual_mean_mm > mean_limit || displacement_max_mm > d_limit;
    }
    c
}

/// A surface point counts as seen when an organ point lies this close (mm), or closer than
/// 1.5 times the cloud's median point spacing when the cloud is sparser (a 500-point cloud
/// covers the area it spans, not 500 discs of 5 mm), at most COVERAGE_RADIUS_MAX_MM.
pub const COVERAGE_RADIUS_MM: f64 = 5.0;
pub const COVERAGE_RADIUS_MAX_MM: f64 = 20.0;
/// The coverage gate takes each point to the rest surface from at most this far beyond the
/// coverage radius: three times the default datasets' 10 mm mean displacement.
pub const DEFORMATION_ALLOWANCE_MM: f64 = 30.0;

/// The coverage radius of a cloud (see COVERAGE_RADIUS_MM): from the nearest-neighbour
/// spacing of at most 500 of its points.
pub fn coverage_radius_mm(points: &[Vector3<f64>]) -> f64 {
    if points.len() < 2 {
        return COVERAGE_RADIUS_MM;
    }
    let grid = crate::nn::PointIndex::new(points, COVERAGE_RADIUS_MM);
    let step = points.len().div_ceil(500);
    let mut d: Vec<f64> = (0..points.len())
        .into_par_iter()
        .step_by(step)
        .map(|i| {
            grid.nearest_except(&points[i], COVERAGE_RADIUS_MAX_MM, i)
                .map_or(COVERAGE_RADIUS_MAX_MM, |(_, q)| (q - points[i]).norm())
        })
        .collect();
    d.sort_by(f64::total_cmp);
    (1.5 * d[d.len() / 2]).clamp(COVERAGE_RADIUS_MM, COVERAGE_RADIUS_MAX_MM)
}

/// The share of `surface` a frame's organ points cover (`surface_coverage` at the cloud's
/// `coverage_radius_mm`); registration measures it on the deformed organ.
pub fn frame_coverage(surface: &TriMesh, points: &[Vector3<f64>]) -> f64 {
    surface_coverage(surface, points, coverage_radius_mm(points))
}

/// The share of `surface`'s vertices (at most about 2000, every n-th) within `radius_mm` of
/// an observed point.
pub fn surface_coverage(surface: &TriMesh, points: &[Vector3<f64>], radius_mm: f64) -> f64 {
    let n = surface.positions.len();
    if n == 0 || points.is_empty() || !(radius_mm > 0.0) {
        return 0.0;
    }
    // Buckets over the points' own box, a radius wide: a probe looks at the 27 around it.
    // (Buckets over the surface's box, half a radius wide, held ten times as many and took
    // longer to fill than the 2000 probes took to search.)
    let b = crate::nn::PointIndex::new(points, radius_mm);
    let step = n.div_ceil(2000);
    let probes: Vec<&Vector3<f64>> = surface.positions.iter().step_by(step).collect();
    let hit = probes.par_iter().filter(|v| b.nearest(v, radius_mm).is_some()).count();
    hit as f64 / probes.len() as f64
}

/// The triangles around each vertex of a mesh (its topology only: built once per organ).
#[derive(Clone, Debug, Default)]
pub struct VertexRings {
    start: Vec<u32>,
    triangles: Vec<u32>,
}

impl VertexRings {
    pub fn new(mesh: &TriMesh) -> Self {
        let n = mesh.positions.len();
        let mut start = vec![0u32; n + 1];
        for t in &mesh.triangles {
            for &v in t {
                start[v as usize + 1] += 1;
            }
        }
        for i in 0..n {
            start[i + 1] += start[i];
        }
        let mut triangles = vec![0u32; start[n] as usize];
        let mut fill = start.clone();
        for (ti, t) in mesh.triangles.iter().enumerate() {
            for &v in t {
                triangles[fill[v as usize] as usize] = ti as u32;
                fill[v as usize] += 1;
            }
        }
        Self { start, triangles }
    }

    fn of(&self, v: usize) -> &[u32] {
        &self.triangles[self.start[v] as usize..self.start[v + 1] as usize]
    }

    fn fits(&self, mesh: &TriMesh) -> bool {
        self.start.len() == mesh.positions.len() + 1
    }
}

/// Mean and 95th percentile of the distance from `points` (at most MAX_POINTS of them, every
/// n-th) to `mesh`: each point's nearest vertex, then the exact distance to that vertex's
/// triangles. Points beyond RESIDUAL_CAP_MM of every vertex count as that far.
pub fn surface_residual(points: &[Vector3<f64>], mesh: &TriMesh) -> (f64, f64) {
    surface_residual_with(points, mesh, &VertexRings::new(mesh))
}

/// As `surface_residual`, with the mesh's vertex rings given (the same topology every frame).
pub fn surface_residual_with(points: &[Vector3<f64>], mesh: &TriMesh, rings: &VertexRings) -> (f64, f64) {
    if points.is_empty() || mesh.positions.is_empty() || mesh.triangles.is_empty() || !rings.fits(mesh) {
        return (0.0, 0.0);
    }
    let band = RESIDUAL_CAP_MM;
    // Small buckets: most points lie within a few mm of the surface, where the search ends
    // in the first shells around them; the rest widen it up to the cap.
    let vertices = crate::nn::PointIndex::new(&mesh.positions, FINE_BUCKET_MM);
    let step = points.len().div_ceil(MAX_POINTS);
    let mut d: Vec<f64> = points
        .iter()
        .step_by(step)
        .map(|p| match vertices.nearest(p, band) {
            None => band,
            Some((v, _)) => rings
                .of(v)
                .iter()
                .map(|&t| {
                    let [a, bb, c] = mesh.triangles[t as usize].map(|i| mesh.positions[i as usize]);
                    (closest_on_triangle(p, &a, &bb, &c) - p).norm()
                })
                .fold(band, f64::min),
        })
        .collect();
    let mean = d.iter().sum::<f64>() / d.len() as f64;
    d.sort_by(f64::total_cmp);
    let p95 = d[((0.95 * (d.len() - 1) as f64).round() as usize).min(d.len() - 1)];
    (mean, p95)
}

/// The closest point to `p` on triangle (a, b, c) (Ericson, Real-Time Collision Detection 5.1.5).
pub fn closest_on_triangle(p: &Vector3<f64>, a: &Vector3<f64>, b: &Vector3<f64>, c: &Vector3<f64>) -> Vector3<f64> {
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(&ap), ac.dot(&ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return *a;
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(&bp), ac.dot(&bp));
    if d3 >= 0.0 && d4 <= d3 {
        return *b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return a + ab * (d1 / (d1 - d3));
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(&cp), ac.dot(&cp));
    if d6 >= 0.0 && d5 <= d6 {
        return *c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return a + ac * (d2 / (d2 - d6));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    }
    let denom = va + vb + vc;
    if denom.abs() < 1e-300 {
        return *a;
    }
    let (v, w) = (vb / denom, vc / denom);
    a + ab * v + ac * w
}

#[cfg(test)]
mod tests {
    use super::*;

    fn square() -> TriMesh {
        // A 40 x 40 mm square in z = 0, split into 2 x 2 x 2 triangles.
        let mut positions = Vec::new();
        for i in 0..3 {
            for j in 0..3 {
                positions.push(Vector3::new(20.0 * i as f64, 20.0 * j as f64, 0.0));
            }
        }
        let mut triangles = Vec::new();
        for i in 0..2u32 {
            for j in 0..2u32 {
                let v = i * 3 + j;
                triangles.push([v, v + 3, v + 1]);
                triangles.push([v + 1, v + 3, v + 4]);
            }
        }
        TriMesh { positions, triangles }
    }

    #[test]
    fn residual_of_points_off_a_plane_is_their_height_within_1e9_mm() {
        let m = square();
        let pts: Vec<_> = (0..100).map(|k| Vector3::new(3.0 + 0.3 * k as f64, 7.0 + 0.2 * k as f64, 2.5)).collect();
        let (mean, p95) = surface_residual(&pts, &m);
        assert!((mean - 2.5).abs() < 1e-9 && (p95 - 2.5).abs() < 1e-9, "{mean} {p95}");
    }

    #[test]
    fn coverage_and_residual_equal_a_search_of_every_vertex_and_triangle() {
        // A 200 x 200 mm sheet of 5 mm triangles, waved in z; points scattered over part of it
        // at heights up to 25 mm (beyond the residual's 20 mm cap), some far outside its box.
        let n = 41;
        let positions: Vec<Vector3<f64>> = (0..n * n)
            .map(|v| {
                let (i, j) = ((v / n) as f64 * 5.0, (v % n) as f64 * 5.0);
                Vector3::new(i, j, 10.0 * (i / 30.0).sin() * (j / 40.0).cos())
            })
            .collect();
        let mut triangles = Vec::new();
        for i in 0..(n - 1) as u32 {
            for j in 0..(n - 1) as u32 {
                let v = i * n as u32 + j;
                triangles.push([v, v + n as u32, v + 1]);
                triangles.push([v + 1, v + n as u32, v + n as u32 + 1]);
            }
        }
        let mesh = TriMesh { positions, triangles };
        let mut rng = crate::rng::SplitMix64(5);
        let mut r = |s: f64| rng.next_f64() * s;
        let mut points: Vec<Vector3<f64>> =
            (0..1500).map(|_| Vector3::new(20.0 + r(90.0), 50.0 + r(120.0), r(50.0) - 25.0)).collect();
        points.extend((0..20).map(|k| Vector3::new(-100.0 - k as f64, 400.0, 0.0)));
        for radius in [5.0, 7.5, 20.0] {
            let step = mesh.positions.len().div_ceil(2000);
            let probes: Vec<_> = mesh.positions.iter().step_by(step).collect();
            let hit = probes.iter().filter(|v| points.iter().any(|p| (*p - **v).norm() <= radius)).count();
            assert_eq!(surface_coverage(&mesh, &points, radius), hit as f64 / probes.len() as f64, "{radius} mm");
        }
        // The residual: each point's distance to the triangles around its nearest vertex, capped.
        let rings = VertexRings::new(&mesh);
        let (mean, p95) = surface_residual_with(&points, &mesh, &rings);
        let step = points.len().div_ceil(MAX_POINTS);
        let mut d: Vec<f64> = points
            .iter()
            .step_by(step)
            .map(|p| {
                let near = (0..mesh.positions.len())
                    .filter(|&v| (mesh.positions[v] - p).norm() <= RESIDUAL_CAP_MM)
                    .min_by(|&a, &b| {
                        let key = |v: usize| {
                            let q = mesh.positions[v];
                            ((q - p).norm_squared(), q.x, q.y, q.z, v)
                        };
                        key(a).partial_cmp(&key(b)).unwrap()
                    });
                near.map_or(RESIDUAL_CAP_MM, |v| {
                    rings
                        .of(v)
                        .iter()
                        .map(|&t| {
                            let [a, b, c] = mesh.triangles[t as usize].map(|i| mesh.positions[i as usize]);
                            (closest_on_triangle(p, &a, &b, &c) - p).norm()
                        })
                        .fold(RESIDUAL_CAP_MM, f64::min)
                })
            })
            .collect();
        let want_mean = d.iter().sum::<f64>() / d.len() as f64;
        d.sort_by(f64::total_cmp);
        let want_p95 = d[((0.95 * (d.len() - 1) as f64).round() as usize).min(d.len() - 1)];
        assert_eq!((mean, p95), (want_mean, want_p95));
    }

    #[test]
    fn closest_point_on_a_triangle_matches_a_dense_search_within_0_01_mm() {
        let (a, b, c) = (Vector3::new(0.0, 0.0, 0.0), Vector3::new(10.0, 0.0, 1.0), Vector3::new(2.0, 8.0, -1.0));
        for p in [
            Vector3::new(-3.0, -2.0, 4.0),
            Vector3::new(12.0, 1.0, 0.0),
            Vector3::new(4.0, 3.0, 5.0),
            Vector3::new(7.0, 7.0, 0.0),
        ] {
            let q = closest_on_triangle(&p, &a, &b, &c);
            let mut best = f64::INFINITY;
            for i in 0..=400 {
                for j in 0..=(400 - i) {
                    let (u, v) = (i as f64 / 400.0, j as f64 / 400.0);
                    best = best.min((a + (b - a) * u + (c - a) * v - p).norm());
                }
            }
            assert!((q - p).norm() <= best + 1e-9 && (q - p).norm() > best - 0.01, "{p:?}");
        }
    }

    #[test]
    fn a_residual_beyond_the_reference_warns_and_one_within_does_not() {
        let m = square();
        let r = ConfidenceReference {
            residual_p95_mm: 1.0,
            residual_mean_mm: 0.8,
            coverage_min: 0.1,
            displacement_max_mm: 10.0,
            views: 1,
            correct_tre_mm: None,
            correct_views: 0,
        };
        let near: Vec<_> = (0..50).map(|k| Vector3::new(1.0 + 0.5 * k as f64, 10.0, 0.5)).collect();
        assert!(!frame_confidence(&near, &m, &m, &VertexRings::new(&m), 0.3, Some(&r)).warning());
        let far: Vec<_> = near.iter().map(|p| p + Vector3::new(0.0, 0.0, 4.0)).collect();
        let c = frame_confidence(&far, &m, &m, &VertexRings::new(&m), 0.05, Some(&r));
        assert_eq!(c.warnings.len(), 3, "{:?}", c.warnings);
        assert!(frame_confidence(&far, &m, &m, &VertexRings::new(&m), 0.05, None).warnings.is_empty());
    }

    #[test]
    fn a_reference_from_right_views_warns_half_a_millimetre_above_it_and_an_old_one_at_one_and_a_half_times() {
        let m = square();
        let at =
            |h: f64| -> Vec<Vector3<f64>> { (0..50).map(|k| Vector3::new(1.0 + 0.5 * k as f64, 10.0, h)).collect() };
        let right = ConfidenceReference {
            residual_p95_mm: 2.0,
            residual_mean_mm: 2.0,
            coverage_min: 0.0,
            displacement_max_mm: 10.0,
            views: 100,
            correct_tre_mm: Some(CORRECT_TRE_MM),
            correct_views: 60,
        };
        let rings = VertexRings::new(&m);
        // Limit 2.5 mm (2.0 + 0.5): 2.4 passes, 2.6 warns on both figures.
        assert!(!frame_confidence(&at(2.4), &m, &m, &rings, 0.3, Some(&right)).warning());
        let c = frame_confidence(&at(2.6), &m, &m, &rings, 0.3, Some(&right));
        assert_eq!(c.warnings.len(), 2, "{:?}", c.warnings);
        assert!(c.warnings[0].contains("registered within 2.0 mm"), "{:?}", c.warnings);
        // The same numbers from all views (a file from before): limit 3.5 mm (2.0 x 1.5 + 0.5).
        let all = ConfidenceReference { correct_tre_mm: None, correct_views: 0, ..right };
        assert!(!frame_confidence(&at(3.4), &m, &m, &rings, 0.3, Some(&all)).warning());
        assert!(frame_confidence(&at(3.6), &m, &m, &rings, 0.3, Some(&all)).warning());
    }
}
