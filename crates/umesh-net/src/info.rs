//! What a trained model folder says about itself (`model.json`): the network, the normalisation,
//! the grid it was trained on and the settings of its training.

use crate::NetError;
use crate::data::Normalization;
use crate::model::UNetConfig;
use std::path::{Path, PathBuf};

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TrainSettings {
    pub model: UNetConfig,
    pub epochs: usize,
    pub batch_size: usize,
    pub learning_rate: f64,
    pub seed: u64,
    /// Virtual markers per sample for the validation TRE.
    pub markers: usize,
    /// The network input: None, the exact displacement of the visible nodes (u_s, 3
    /// channels); Some, the encoded simulated camera view of each sample (`observation`,
    /// `observation::CHANNELS` channels), as registration encodes each frame.
    #[serde(default)]
    pub observation: Option<umesh_core::observation::ObservationSettings>,
    /// With `observation`: from the second epoch on, every training sample gets a new
    /// simulated camera view of its deformation each epoch (validation keeps the stored ones).
    #[serde(default)]
    pub fresh_views: bool,
    /// With `fresh_views`: the fraction of training samples whose view each epoch is of the
    /// undeformed organ, with a zero target (0 in models trained before it existed).
    #[serde(default)]
    pub rest_views: f64,
    /// Start from this model folder's weights and normalisation (same network and grid)
    /// instead of random weights: fine-tuning.
    #[serde(default)]
    pub init_from: Option<PathBuf>,
    /// Start from the weights and normalisation of a model of another organ (a prior: the same
    /// network and input, any grid; the network is convolutional throughout) instead of random
    /// weights.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub prior: Option<PathBuf>,
    /// How the learning rate moves over the epochs.
    #[serde(default, skip_serializing_if = "LrSchedule::is_constant")]
    pub lr_schedule: LrSchedule,
    /// Stop when the validation loss has not improved for this many epochs (0: never).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub patience: usize,
    /// Stop before an epoch that would end after this many seconds of training (0: no limit).
    /// The cosine schedule then ends at the last epoch that fits.
    #[serde(default, skip_serializing_if = "is_zero_f64")]
    pub time_budget_s: f64,
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

fn is_zero_f64(x: &f64) -> bool {
    *x == 0.0
}

/// The learning rate over the epochs.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LrSchedule {
    /// `learning_rate` throughout (the paper's protocol).
    #[default]
    Constant,
    /// From `learning_rate` down to 5 % of it at the last planned epoch (the epochs asked, or
    /// fewer when the time budget will stop the run earlier), along half a cosine.
    Cosine,
}

impl LrSchedule {
    pub fn is_constant(&self) -> bool {
        *self == Self::Constant
    }

    pub fn parse(s: &str) -> Result<Self, umesh_core::Invalid> {
        match s {
            "constant" => Ok(Self::Constant),
            "cosine" => Ok(Self::Cosine),
            other => Err(umesh_core::Invalid(format!("learning-rate schedule {other:?}: constant or cosine"))),
        }
    }

    /// The rate of `epoch` (1-based) of a run planned to end at `last_epoch`.
    pub fn rate(self, base: f64, epoch: usize, last_epoch: usize) -> f64 {
        match self {
            Self::Constant => base,
            Self::Cosine => {
                let t = if last_epoch > 1 {
                    ((epoch.saturating_sub(1)) as f64 / (last_epoch - 1) as f64).min(1.0)
                } else {
                    1.0
                };
                let floor = 0.05 * base;
                floor + (base - floor) * 0.5 * (1.0 + (std::f64::consts::PI * t).cos())
            }
        }
    }
}

impl Default for TrainSettings {
    fn default() -> Self {
        Self {
            model: UNetConfig::cpu(),
            epochs: 30,
            batch_size: 4,
            learning_rate: 1e-3,
            seed: 0,
            markers: 10,
            observation: Some(umesh_core::observation::ObservationSettings::default()),
            fresh_views: true,
            rest_views: 0.05,
            init_from: None,
            prior: None,
            lr_schedule: LrSchedule::Constant,
            patience: 0,
            time_budget_s: 0.0,
        }
    }
}

impl TrainSettings {
    /// The network as trained: `model` with the input channels of the chosen input.
    pub fn network(&self) -> UNetConfig {
        let in_channels = if self.observation.is_some() { umesh_core::observation::CHANNELS } else { 3 };
        UNetConfig { in_channels, ..self.model.clone() }
    }
}

/// What a model folder holds besides its weights (`model.json`).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ModelInfo {
    pub config: UNetConfig,
    pub normalization: Normalization,
    pub padded_shape: [usize; 3],
    pub dataset: String,
    pub train_indices: Vec<usize>,
    pub val_indices: Vec<usize>,
    pub settings: TrainSettings,
    /// Hash of the dataset's `grid.npz` (copied beside the weights): a model only fits its grid.
    #[serde(default)]
    pub grid_hash: Option<String>,
    /// The dataset's configuration (grid, loads, visibility), so that registration rebuilds
    /// the same grid and visible nodes from the segmentation.
    #[serde(default)]
    pub dataset_config: Option<umesh_core::dataset::DatasetConfig>,
}

impl ModelInfo {
    /// Whether a training with `settings` can start from this model's weights (a prior): the
    /// same network and input; the grid may be another organ's.
    pub fn fits_as_prior(&self, settings: &TrainSettings) -> bool {
        self.config == settings.network() && self.settings.observation == settings.observation
    }

    /// Refuse a grid this model was not trained on.
    pub fn check_grid(&self, grid_hash: &str, padded_shape: [usize; 3]) -> Result<(), NetError> {
        if padded_shape != self.padded_shape {
            return Err(NetError::Invalid(format!(
                "the model was trained on a {:?} grid, this one is {padded_shape:?}",
                self.padded_shape
            )));
        }
        match &self.grid_hash {
            Some(h) if h != grid_hash => Err(NetError::Invalid(format!(
                "the model was trained on another grid (grid hash {h}, this grid {grid_hash}): generate a dataset and train for it"
            ))),
            _ => Ok(()),
        }
    }

    pub fn read(dir: &Path) -> Result<Self, NetError> {
        let p = dir.join("model.json");
        let text = std::fs::read_to_string(&p).map_err(|e| NetError::Io { path: p.to_path_buf(), source: e })?;
        let info: Self = serde_json::from_str(&text)
            .map_err(|e| NetError::Invalid(format!("{}: not a umesh model description: {e}", p.display())))?;
        info.validate().map_err(|e| NetError::Invalid(format!("{}: {e}", p.display())))?;
        Ok(info)
    }

    /// The one check of a model description, wherever a model is loaded (`eval`, `register`,
    /// the app's rehearsal, QA and AR view, `prepare`'s check): normalisation, grid size and
    /// observation settings finite and within bounds.
    pub fn validate(&self) -> Result<(), umesh_core::Invalid> {
        let n = &self.normalization;
        for (name, v) in [("input_scale_mm", n.input_scale_mm), ("output_scale_mm", n.output_scale_mm)] {
            if !(v.is_finite() && (1e-6..=1e6).contains(&v)) {
                return Err(umesh_core::Invalid(format!("normalization {name} = {v}: must lie in [1e-6, 1e6] mm")));
            }
        }
        let cells = self.padded_shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
        if self.padded_shape.contains(&0) || cells.is_none_or(|c| c > 1 << 26) {
            return Err(umesh_core::Invalid(format!("padded grid {:?}: empty or over 2^26 cells", self.padded_shape)));
        }
        let p = self.padded_shape;
        self.config
            .check_shape([1, self.config.in_channels, p[0], p[1], p[2]])
            .map_err(|e| umesh_core::Invalid(format!("config: {}", e.0)))?;
        if !(1..=16).contains(&self.config.in_channels) || self.config.out_channels != 3 {
            return Err(umesh_core::Invalid(format!(
                "config: {} input and {} output channels (a displacement network has 3 to 16 in, 3 out)",
                self.config.in_channels, self.config.out_channels
            )));
        }
        if let Some(o) = &self.settings.observation {
            o.validate()?;
        }
        // The organ model is rebuilt from these on loading: bounds on what that costs.
        if let Some(c) = &self.dataset_config {
            if !(1..=16).contains(&c.surface_step) {
                return Err(umesh_core::Invalid(format!(
                    "dataset_config.surface_step {}: 1 to 16 voxels",
                    c.surface_step
                )));
            }
            if let umesh_core::fem::FixedRegion::Label { distance_mm, .. } = c.fixed
                && !(distance_mm.is_finite() && (0.0..=umesh_core::fem::bc::MAX_FIX_DISTANCE_MM).contains(&distance_mm))
            {
                return Err(umesh_core::Invalid(format!(
                    "dataset_config.fixed.distance_mm {distance_mm}: between 0 and {} mm",
                    umesh_core::fem::bc::MAX_FIX_DISTANCE_MM
                )));
            }
            c.material.validate().map_err(|e| umesh_core::Invalid(format!("dataset_config.material: {e}")))?;
        }
        Ok(())
    }
    pub fn write(&self, dir: &Path) -> Result<(), NetError> {
        let p = dir.join("model.json");
        let text = serde_json::to_string_pretty(self).map_err(|e| NetError::Invalid(e.to_string()))?;
        umesh_core::write_atomic(&p, text.as_bytes()).map_err(|e| NetError::Io { path: p.to_path_buf(), source: e })
    }
}
