//! Dataset statistics: acceptance, achieved displacement, materials and families.

use super::calibrate::Rejection;
use super::config::CALIBRATION_TOLERANCE;
use super::error::DatasetError;
use super::store::{Dataset, SampleRecord};
use crate::loads::{LoadCalibration, LoadFamily};
use std::collections::BTreeMap;
use std::path::Path;

#[derive(Clone, Debug, serde::Serialize)]
pub struct Distribution {
    pub min: f64,
    pub p5: f64,
    pub median: f64,
    pub mean: f64,
    pub p95: f64,
    pub max: f64,
}

impl Distribution {
    pub fn of(mut v: Vec<f64>) -> Option<Self> {
        if v.is_empty() {
            return None;
        }
        v.sort_by(f64::total_cmp);
        let q = |f: f64| v[((v.len() - 1) as f64 * f).round() as usize];
        Some(Self {
            min: v[0],
            p5: q(0.05),
            median: q(0.5),
            mean: v.iter().sum::<f64>() / v.len() as f64,
            p95: q(0.95),
            max: v[v.len() - 1],
        })
    }
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct DatasetStats {
    pub samples: usize,
    pub accepted: usize,
    pub rejected: BTreeMap<String, usize>,
    pub flagged: usize,
    pub complete: bool,
    pub max_displacement_mm: Option<Distribution>,
    pub mean_displacement_mm: Option<Distribution>,
    /// The configured target of the mean nodal displacement (mm) and how it was used.
    pub target_displacement_mm: f64,
    pub calibration: LoadCalibration,
    /// Per accepted sample: achieved mean displacement / its calibrated target.
    pub achieved_over_target: Option<Distribution>,
    /// Which nodes the mean displacement averages over (free: what can move).
    pub mean_over: crate::fem::solver::MeanOver,
    /// Accepted samples whose target was out of reach and whose converged state nearest it
    /// was kept (achieved / target below 1 - `CALIBRATION_TOLERANCE`, at least
    /// `fem::solver::MIN_REACHED_FRACTION`).
    pub below_target: usize,
    /// Samples whose drawn target the strain limit lowered (`ForceSettings::max_strain`), and
    /// the distribution of lowered / drawn over them.
    pub strain_limited: usize,
    pub strain_limited_factor: Option<Distribution>,
    /// The configuration's strain limit (0: none).
    pub max_strain: f64,
    /// Per load family (datasets of more than one): (family, samples, accepted).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub families: Vec<(LoadFamily, usize, usize)>,
    /// Per material kind (datasets that draw one per sample): (kind, samples, accepted,
    /// smallest and largest Poisson's ratio drawn).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub materials: Vec<(crate::fem::MaterialKind, usize, usize, f64, f64)>,
    pub newton_iterations: Option<Distribution>,
    pub solve_ms: Option<Distribution>,
    /// The rejected samples' solve time (ms): the work a rejection wastes, against `solve_ms`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rejected_solve_ms: Option<Distribution>,
    /// (index, why) of samples far from the rest.
    pub outliers: Vec<(usize, String)>,
}

pub fn run_stats(dir: &Path) -> Result<DatasetStats, DatasetError> {
    let ds = Dataset::open(dir)?;
    let m = &ds.manifest;
    let acc: Vec<&SampleRecord> = m.accepted().collect();
    let mut rejected = BTreeMap::new();
    for s in m.samples.iter().filter(|s| !s.accepted) {
        *rejected.entry(format!("{:?}", s.rejection.unwrap_or(Rejection::Failed)).to_lowercase()).or_insert(0) += 1;
    }
    let max_d = Distribution::of(acc.iter().map(|s| s.max_displacement_mm).collect());
    let its = Distribution::of(acc.iter().map(|s| s.newton_iterations as f64).collect());
    // Outliers: beyond median + 4 x (p95 - median) of the maximum displacement or iterations.
    let mut outliers = Vec::new();
    if let (Some(d), Some(i)) = (&max_d, &its) {
        for s in &acc {
            if s.max_displacement_mm > d.median + 4.0 * (d.p95 - d.median).max(1e-9) {
                outliers.push((
                    s.index,
                    format!("max displacement {:.1} mm (median {:.1})", s.max_displacement_mm, d.median),
                ));
            }
            if s.newton_iterations as f64 > i.median + 4.0 * (i.p95 - i.median).max(1.0) {
                outliers.push((s.index, format!("{} Newton iterations (median {:.0})", s.newton_iterations, i.median)));
            }
        }
    }
    let mut families: Vec<(LoadFamily, usize, usize)> = Vec::new();
    for s in &m.samples {
        let Some(f) = s.family else { continue };
        match families.iter_mut().find(|e| e.0 == f) {
            Some(e) => {
                e.1 += 1;
                e.2 += s.accepted as usize;
            }
            None => families.push((f, 1, s.accepted as usize)),
        }
    }
    families.sort_by_key(|e| LoadFamily::ALL.iter().position(|f| *f == e.0));
    let mut materials: Vec<(crate::fem::MaterialKind, usize, usize, f64, f64)> = Vec::new();
    for s in &m.samples {
        let Some(mat) = s.material else { continue };
        match materials.iter_mut().find(|e| e.0 == mat.kind) {
            Some(e) => {
                e.1 += 1;
                e.2 += s.accepted as usize;
                e.3 = e.3.min(mat.poisson);
                e.4 = e.4.max(mat.poisson);
            }
            None => materials.push((mat.kind, 1, s.accepted as usize, mat.poisson, mat.poisson)),
        }
    }
    materials.sort_by_key(|e| e.0.name());
    Ok(DatasetStats {
        families,
        materials,
        samples: m.samples.len(),
        accepted: acc.len(),
        rejected,
        flagged: m.samples.iter().filter(|s| s.flagged).count(),
        complete: m.complete,
        max_displacement_mm: max_d,
        mean_displacement_mm: Distribution::of(acc.iter().map(|s| s.mean_displacement_mm).collect()),
        target_displacement_mm: m.config.forces.target_displacement_mm,
        calibration: m.config.forces.calibration,
        achieved_over_target: Distribution::of(
            acc.iter()
                .filter_map(|s| s.target_displacement_mm.filter(|t| *t > 0.0).map(|t| s.mean_displacement_mm / t))
                .collect(),
        ),
        newton_iterations: its,
        solve_ms: Distribution::of(acc.iter().filter_map(|s| s.solve_ms).collect()),
        rejected_solve_ms: Distribution::of(
            m.samples.iter().filter(|s| !s.accepted).filter_map(|s| s.solve_ms).collect(),
        ),
        mean_over: m.config.forces.mean_over,
        below_target: acc
            .iter()
            .filter(|s| {
                s.target_displacement_mm
                    .is_some_and(|t| s.mean_displacement_mm < (1.0 - CALIBRATION_TOLERANCE) * t * (1.0 - 1e-9))
            })
            .count(),
        max_strain: m.config.forces.max_strain,
        strain_limited: m.samples.iter().filter(|s| s.drawn_target_mm.is_some()).count(),
        strain_limited_factor: Distribution::of(
            m.samples
                .iter()
                .filter_map(|s| Some(s.target_displacement_mm? / s.drawn_target_mm.filter(|d| *d > 0.0)?))
                .collect(),
        ),
        outliers,
    })
}
