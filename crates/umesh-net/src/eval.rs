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
        return Err(NetError::Invalid(format!("{}: no validation sample to evaluate (indices i with i mod 5 = 4)", dataset.display())));
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
