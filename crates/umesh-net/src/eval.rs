//! Evaluation: TRE at virtual markers over the validation split, against the FE ground truth.

use crate::data::SampleSet;
use crate::inference::Predictor;
use crate::{NetError, tre};
use std::path::Path;

#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct EvalReport {
    pub samples: usize,
    pub markers_per_sample: usize,
    pub tre_mean_mm: f64,
    pub tre_std_mm: f64,
    pub tre_max_mm: f64,
    pub marker_displacement_mean_mm: f64,
    pub per_sample_tre_mm: Vec<(usize, f64)>,
    /// Every marker's error (mm), for histograms.
    #[serde(default)]
    pub per_marker_tre_mm: Vec<f64>,
}

pub fn run_eval(model_dir: &Path, dataset: &Path, markers_per_sample: usize) -> Result<EvalReport, NetError> {
    // The TRE needs markers; each one is interpolated in every validation sample.
    if !(1..=10_000).contains(&markers_per_sample) {
        return Err(NetError::Invalid(format!("--markers {markers_per_sample}: between 1 and 10000 a sample")));
    }
    let mut predictor = Predictor::load(model_dir)?;
    let set = SampleSet::load_inputs(dataset, predictor.info.settings.observation.as_ref())?;
    if set.shape != predictor.info.padded_shape {
        return Err(NetError::Invalid(format!(
            "{}: grid {:?} differs from the model's {:?} ({})",
            dataset.display(),
            set.shape,
            predictor.info.padded_shape,
            model_dir.display()
        )));
    }
    let (_, val) = set.split();
    let markers = tre::markers(&set.grid, markers_per_sample, predictor.info.settings.seed ^ 0x5EED);
    let (mut all, mut moved, mut per) = (Vec::new(), Vec::new(), Vec::new());
    for &k in &val {
        let pred = predictor.predict(&set.u_s[k], set.shape)?.to_vec();
        let (e, d) = tre::marker_errors(&set.grid, &markers, &pred, &set.u_v[k]);
        per.push((set.indices[k], tre::summary(&e).0));
        all.extend(e);
        moved.extend(d);
    }
    if val.is_empty() {
        return Err(NetError::Invalid(format!(
            "{}: no validation sample to evaluate (indices i with i mod 5 = 4)",
            dataset.display()
        )));
    }
    let (mean, std, max) = tre::summary(&all);
    if !(mean.is_finite() && max.is_finite()) {
        return Err(NetError::Invalid(format!(
            "{}: the predictions are not finite (corrupt weights or normalisation)",
            model_dir.display()
        )));
    }
    Ok(EvalReport {
        samples: val.len(),
        markers_per_sample,
        tre_mean_mm: mean,
        tre_std_mm: std,
        tre_max_mm: max,
        marker_displacement_mean_mm: tre::summary(&moved).0,
        per_sample_tre_mm: per,
        per_marker_tre_mm: all.clone(),
    })
}

/// Markers per view for the calibration's TRE (cheap: interpolation only).
const CALIBRATION_MARKERS: usize = 100;

/// The range of the confidence figures on the model's validation views: each stored view
/// (what the dataset's camera saw of the true deformation) against the surface the model
/// predicts from it, and the largest surface displacement of the training targets. The
/// residuals are taken over the views the model registers within CORRECT_TRE_MM (their marker
/// TRE against the truth): over all views, a network wrong on many of them set a limit its
/// wrong frames stayed under (the CT patient: 2 of 23 frames above 2 mm flagged). Written to
/// the model folder as `confidence.json`, read by registration to flag frames outside it.
pub fn calibrate_confidence(
    model_dir: &Path,
    dataset: &Path,
    progress: &umesh_core::Progress,
) -> Result<umesh_core::register::confidence::ConfidenceReference, NetError> {
    use umesh_core::dataset::Dataset;
    use umesh_core::register::confidence::{CORRECT_TRE_MM, ConfidenceReference, frame_coverage, surface_residual};
    let mut predictor = Predictor::load(model_dir)?;
    let Some(observation) = predictor.info.settings.observation.clone() else {
        return Err(NetError::Invalid(format!(
            "{}: the model takes the exact surface displacement, not camera views: there is no view to calibrate its confidence on",
            model_dir.display()
        )));
    };
    let set = SampleSet::load_inputs(dataset, Some(&observation))?;
    if set.shape != predictor.info.padded_shape {
        return Err(NetError::Invalid(format!(
            "{}: grid {:?} differs from the model's {:?}",
            dataset.display(),
            set.shape,
            predictor.info.padded_shape
        )));
    }
    let ds = Dataset::open(dataset)?;
    let npz = umesh_core::dataset::read_grid_npz(dataset, &ds.manifest)?;
    let surface = crate::data::rest_surface(&npz)
        .map_err(|e| NetError::Invalid(format!("{}: {e}", dataset.join("grid.npz").display())))?;
    let (train, val) = set.split();
    let val_index: std::collections::BTreeMap<usize, usize> = val.iter().map(|&k| (set.indices[k], k)).collect();
    let mut r = ConfidenceReference {
        residual_p95_mm: 0.0,
        residual_mean_mm: 0.0,
        coverage_min: 1.0,
        displacement_max_mm: 0.0,
        views: 0,
        correct_tre_mm: None,
        correct_views: 0,
    };
    let markers = tre::markers(&set.grid, CALIBRATION_MARKERS, predictor.info.settings.seed ^ 0x5EED);
    // (view's TRE, residual mean, residual p95)
    let (mut residuals, mut coverages) = (Vec::new(), Vec::new());
    for &k in &train {
        let moved = umesh_core::loads::deform_mesh(
            &set.grid,
            &surface,
            &crate::data::node_displacements(&set.grid, &set.u_v[k]),
        );
        let d = moved.positions.iter().zip(&surface.positions).map(|(a, b)| (a - b).norm()).fold(0.0, f64::max);
        r.displacement_max_mm = r.displacement_max_mm.max(d);
    }
    for shard in &ds.manifest.shards {
        let (idx, _, _) = ds.load_shard(shard)?;
        let views = ds.load_views(shard)?;
        for (j, i) in idx.into_iter().enumerate() {
            let Some(&k) = val_index.get(&i) else { continue };
            let points = &views[j];
            if points.is_empty() {
                continue;
            }
            let pred = predictor.predict(&set.u_s[k], set.shape)?.to_vec();
            let predicted =
                umesh_core::loads::deform_mesh(&set.grid, &surface, &crate::data::node_displacements(&set.grid, &pred));
            let (mean, p95) = surface_residual(points, &predicted);
            let (errors, _) = tre::marker_errors(&set.grid, &markers, &pred, &set.u_v[k]);
            residuals.push((tre::summary(&errors).0, mean, p95));
            // Coverage as registration measures it: the points against the predicted surface.
            coverages.push(frame_coverage(&predicted, points));
            r.views += 1;
            progress.report(r.views as u64, val.len() as u64, "confidence range on the validation views");
        }
    }
    if r.views == 0 {
        return Err(NetError::Invalid(format!("{}: no validation sample has a stored camera view", dataset.display())));
    }
    // The range of most views, not of the single worst one.
    let pct = |v: &mut Vec<f64>, p: f64| {
        v.sort_by(f64::total_cmp);
        v[((v.len() - 1) as f64 * p).round() as usize]
    };
    // The views registered within the bar; when too few are, the best quarter (its worst TRE
    // stated), so that the limit still comes from the model's better predictions.
    residuals.sort_by(|a, b| a.0.total_cmp(&b.0));
    let within = residuals.iter().take_while(|v| v.0 <= CORRECT_TRE_MM).count();
    let enough = (residuals.len() / 10).max(10).min(residuals.len());
    let used = if within >= enough { within } else { (residuals.len() / 4).max(enough) };
    let right = &residuals[..used];
    r.correct_tre_mm = Some(if within >= enough { CORRECT_TRE_MM } else { right[used - 1].0 });
    r.correct_views = used;
    r.residual_p95_mm = pct(&mut right.iter().map(|v| v.2).collect(), 0.95);
    r.residual_mean_mm = pct(&mut right.iter().map(|v| v.1).collect(), 0.95);
    r.coverage_min = pct(&mut coverages, 0.05);
    Ok(r)
}

/// Write `reference` into the model folder (atomically).
pub fn write_confidence(
    model_dir: &Path,
    reference: &umesh_core::register::confidence::ConfidenceReference,
) -> Result<(), NetError> {
    let path = model_dir.join(umesh_core::register::confidence::ConfidenceReference::FILE);
    let text = serde_json::to_string_pretty(reference).map_err(|e| NetError::Invalid(e.to_string()))?;
    umesh_core::write_atomic(&path, text.as_bytes()).map_err(|e| NetError::Io { path: path.to_path_buf(), source: e })
}
