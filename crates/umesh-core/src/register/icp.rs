//! Rigid initialisation: point-to-plane ICP of the observed cloud onto the preoperative
//! surface (whose normals are exact), from an initial pose.

use super::nn::PointGrid;
use crate::rgbd::transform_point;
use nalgebra::{Matrix4, Matrix6, Rotation3, Vector3, Vector6};

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct IcpSettings {
    pub max_iterations: usize,
    /// Pairs further apart than this are not correspondences (mm).
    pub max_correspondence_mm: f64,
    /// Stop when the update moves points less than this (mm).
    pub tolerance_mm: f64,
}

impl Default for IcpSettings {
    fn default() -> Self {
        Self { max_iterations: 50, max_correspondence_mm: 20.0, tolerance_mm: 1e-3 }
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
}

/// The target surface: points with unit normals.
#[derive(Debug)]
pub struct IcpTarget {
    grid: PointGrid,
    normals: Vec<Vector3<f64>>,
}

impl IcpTarget {
    pub fn new(points: Vec<Vector3<f64>>, normals: Vec<Vector3<f64>>, spacing_mm: f64) -> Self {
        Self { grid: PointGrid::new(points, spacing_mm.max(0.5) * 2.0), normals }
    }
}

/// Find `target_from_source` that puts `source` on the target surface, starting from `initial`.
pub fn icp_point_to_plane(source: &[Vector3<f64>], target: &IcpTarget, initial: &Matrix4<f64>, s: &IcpSettings) -> IcpReport {
    let mut t = *initial;
    let mut report = IcpReport { transform: t, fitness: 0.0, rms_mm: f64::INFINITY, iterations: 0, converged: false };
    if source.is_empty() {
        return report;
    }
    // Shrink the correspondence distance as the fit improves, never below a few mm.
    let mut max_d = s.max_correspondence_mm;
    for it in 0..s.max_iterations.max(1) {
        let mut ata = Matrix6::<f64>::zeros();
        let mut atb = Vector6::<f64>::zeros();
        let (mut count, mut sq) = (0usize, 0.0);
        for p in source {
            let q = transform_point(&t, p);
            let Some((j, _)) = target.grid.nearest(&q, max_d) else { continue };
            let n = target.normals[j];
            let r = n.dot(&(q - target.grid.points[j]));
            // Huber weight: noisy or deformed parts do not pull the rigid fit.
            let w = if r.abs() <= 2.0 { 1.0 } else { 2.0 / r.abs() };
            let c = q.cross(&n);
            let a = Vector6::new(c.x, c.y, c.z, n.x, n.y, n.z);
            ata += w * a * a.transpose();
            atb += -w * r * a;
            count += 1;
            sq += r * r;
        }
        report.iterations = it + 1;
        report.fitness = count as f64 / source.len() as f64;
        report.rms_mm = if count > 0 { (sq / count as f64).sqrt() } else { f64::INFINITY };
        if count < 6 {
            break;
        }
        let Some(x) = (ata + Matrix6::identity() * 1e-9).cholesky().map(|c| c.solve(&atb)) else { break };
        let rot = Rotation3::from_scaled_axis(Vector3::new(x[0], x[1], x[2]));
        let mut d = Matrix4::identity();
        d.fixed_view_mut::<3, 3>(0, 0).copy_from(rot.matrix());
        d.fixed_view_mut::<3, 1>(0, 3).copy_from(&Vector3::new(x[3], x[4], x[5]));
        t = d * t;
        let step = Vector3::new(x[0], x[1], x[2]).norm() * 100.0 + Vector3::new(x[3], x[4], x[5]).norm();
        max_d = (max_d * 0.8).max(3.0 * report.rms_mm).max(5.0).min(s.max_correspondence_mm);
        if step < s.tolerance_mm {
            report.converged = true;
            break;
        }
    }
    report.transform = t;
    report
}
