//! Rigid initialisation: point-to-plane ICP of the observed cloud onto the preoperative
//! surface (whose normals are exact), from an initial pose.

use crate::nn::PointIndex;
use crate::rgbd::transform_point;
use nalgebra::{Matrix4, Matrix6, Rotation3, Vector3, Vector6};

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct IcpSettings {
    pub max_iterations: usize,
    /// Pairs further apart than this are not correspondences (mm).
    pub max_correspondence_mm: f64,
    /// Stop when the update moves points less than this (mm).
    pub tolerance_mm: f64,
    /// Share of the points that steers the fit: those that fit the surface best at the initial
    /// pose (1: all, Huber-weighted; below 1: trimmed, so that a deformed part does not pull).
    #[serde(default = "one")]
    pub trim: f64,
    /// The fit may move the cloud by at most this much RMS from the initial pose (mm): a
    /// refinement of a tracked pose, never a slide.
    #[serde(default)]
    pub max_motion_mm: Option<f64>,
}

fn one() -> f64 {
    1.0
}

impl Default for IcpSettings {
    fn default() -> Self {
        Self { max_iterations: 50, max_correspondence_mm: 20.0, tolerance_mm: 1e-3, trim: 1.0, max_motion_mm: None }
    }
}

impl IcpSettings {
    /// The refinement of a tracked pose: the best-fitting half of the points, within
    /// 10 mm, moving the cloud by at most `bound_mm` RMS.
    pub fn tracked(bound_mm: f64) -> Self {
        Self { max_correspondence_mm: 10.0, trim: 0.5, max_motion_mm: Some(bound_mm), ..Self::default() }
    }

    pub fn validate(&self) -> Result<(), crate::Invalid> {
        if !(self.trim > 0.0 && self.trim <= 1.0) {
            return Err(crate::Invalid(format!("ICP trim {}: above 0 and at most 1", self.trim)));
        }
        if let Some(b) = self.max_motion_mm
            && !(b.is_finite() && (0.0..=1000.0).contains(&b))
        {
            return Err(crate::Invalid(format!("pose bound {b} mm: between 0 and 1000 mm")));
        }
        if !(self.max_correspondence_mm.is_finite() && self.max_correspondence_mm > 0.0) || self.max_iterations > 10_000
        {
            return Err(crate::Invalid::from(
                "ICP: the correspondence distance must be finite and positive, at most 10000 iterations",
            ));
        }
        Ok(())
    }
}

#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct IcpReport {
    /// target_from_source.
    #[serde(skip)]
    pub transform: Matrix4<f64>,
    /// Fraction of source points with a correspondence.
    pub fitness: f64,
    /// RMS point-to-plane distance of the correspondences (mm).
    pub rms_mm: f64,
    pub iterations: usize,
    pub converged: bool,
    /// How far the fit moved the cloud from the initial pose (RMS over its points, mm).
    pub moved_mm: f64,
    /// The fit stopped at `max_motion_mm`.
    pub bounded: bool,
}

/// The target surface: points with unit normals.
#[derive(Debug)]
pub struct IcpTarget {
    grid: PointIndex,
    normals: Vec<Vector3<f64>>,
}

impl IcpTarget {
    pub fn new(points: Vec<Vector3<f64>>, normals: Vec<Vector3<f64>>, spacing_mm: f64) -> Self {
        Self { grid: PointIndex::new(&points, spacing_mm.max(0.5) * 2.0), normals }
    }
}

/// Find `target_from_source` that puts `source` on the target surface, starting from `initial`.
pub fn icp_point_to_plane(
    source: &[Vector3<f64>],
    target: &IcpTarget,
    initial: &Matrix4<f64>,
    s: &IcpSettings,
) -> IcpReport {
    let mut t = *initial;
    let mut report = IcpReport {
        transform: t,
        fitness: 0.0,
        rms_mm: f64::INFINITY,
        iterations: 0,
        converged: false,
        moved_mm: 0.0,
        bounded: false,
    };
    if source.is_empty() {
        return report;
    }
    // The motion from the initial pose, measured on at most 500 of the points.
    let probe: Vec<Vector3<f64>> = source.iter().step_by(source.len().div_ceil(500)).copied().collect();
    let start: Vec<Vector3<f64>> = probe.iter().map(|p| transform_point(initial, p)).collect();
    let moved = |m: &Matrix4<f64>| {
        let sq: f64 = probe.iter().zip(&start).map(|(p, q)| (transform_point(m, p) - q).norm_squared()).sum();
        (sq / probe.len() as f64).sqrt()
    };
    // Trimmed: the share of the points that fits the surface best at the initial pose steers
    // the fit, chosen once (re-chosen each step, the subset would follow the slide it causes).
    let subset: Vec<Vector3<f64>>;
    let mut source = source;
    let mut matched_share = None;
    if s.trim < 1.0 {
        let (best, share) = best_fitting(source, target, &t, s);
        matched_share = Some(share);
        subset = best;
        source = &subset;
        if source.is_empty() {
            report.fitness = 0.0;
            return report;
        }
    }
    let mut pairs: Vec<(f64, Vector6<f64>)> = Vec::with_capacity(source.len());
    // Shrink the correspondence distance as the fit improves, never below a few mm.
    let mut max_d = s.max_correspondence_mm;
    for it in 0..s.max_iterations.max(1) {
        let mut ata = Matrix6::<f64>::zeros();
        let mut atb = Vector6::<f64>::zeros();
        pairs.clear();
        for p in source {
            let q = transform_point(&t, p);
            let Some((j, on)) = target.grid.nearest(&q, max_d) else { continue };
            let n = target.normals[j];
            let r = n.dot(&(q - on));
            let c = q.cross(&n);
            pairs.push((r, Vector6::new(c.x, c.y, c.z, n.x, n.y, n.z)));
        }
        let count = pairs.len();
        let mut sq = 0.0;
        for (r, a) in &pairs {
            // Huber weight: noisy or deformed parts do not pull the rigid fit.
            let w = if r.abs() <= 2.0 { 1.0 } else { 2.0 / r.abs() };
            ata += w * a * a.transpose();
            atb += -w * r * a;
            sq += r * r;
        }
        report.iterations = it + 1;
        report.fitness = matched_share.unwrap_or(count as f64 / source.len() as f64);
        report.rms_mm = if count > 0 { (sq / count as f64).sqrt() } else { f64::INFINITY };
        if count < 6 {
            break;
        }
        let Some(x) = (ata + Matrix6::identity() * 1e-9).cholesky().map(|c| c.solve(&atb)) else { break };
        let step_by = |f: f64| {
            let rot = Rotation3::from_scaled_axis(Vector3::new(x[0], x[1], x[2]) * f);
            let mut d = Matrix4::identity();
            d.fixed_view_mut::<3, 3>(0, 0).copy_from(rot.matrix());
            d.fixed_view_mut::<3, 1>(0, 3).copy_from(&(Vector3::new(x[3], x[4], x[5]) * f));
            d * t
        };
        let next = step_by(1.0);
        if let Some(bound) = s.max_motion_mm
            && moved(&next) > bound
        {
            // Stop on the bound: the largest share of this step that stays within it.
            let (mut lo, mut hi) = (0.0, 1.0);
            for _ in 0..30 {
                let mid = 0.5 * (lo + hi);
                if moved(&step_by(mid)) > bound {
                    hi = mid;
                } else {
                    lo = mid;
                }
            }
            t = step_by(lo);
            report.bounded = true;
            break;
        }
        t = next;
        let step = Vector3::new(x[0], x[1], x[2]).norm() * 100.0 + Vector3::new(x[3], x[4], x[5]).norm();
        max_d = (max_d * 0.8).max(3.0 * report.rms_mm).max(5.0).min(s.max_correspondence_mm);
        if step < s.tolerance_mm {
            report.converged = true;
            break;
        }
    }
    report.transform = t;
    report.moved_mm = moved(&t);
    report
}

/// The trimmed fit's points: the share `s.trim` of those within reach of the target that lie
/// nearest its surface (along its normal) at pose `t`, and the share of all that were within
/// reach.
fn best_fitting(
    source: &[Vector3<f64>],
    target: &IcpTarget,
    t: &Matrix4<f64>,
    s: &IcpSettings,
) -> (Vec<Vector3<f64>>, f64) {
    let mut fit: Vec<(f64, usize)> = source
        .iter()
        .enumerate()
        .filter_map(|(i, p)| {
            let q = transform_point(t, p);
            let (j, p) = target.grid.nearest(&q, s.max_correspondence_mm)?;
            Some((target.normals[j].dot(&(q - p)).abs(), i))
        })
        .collect();
    let share = fit.len() as f64 / source.len() as f64;
    let keep = ((fit.len() as f64 * s.trim).ceil() as usize).min(fit.len());
    if keep > 0 {
        fit.select_nth_unstable_by(keep - 1, |a, b| a.0.total_cmp(&b.0));
    }
    (fit[..keep].iter().map(|&(_, i)| source[i]).collect(), share)
}
