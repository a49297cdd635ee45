//! umesh-net: the U-Mesh 3-D U-Net on burn (CPU `flex` backend by default): model, data,
//! training, evaluation by target registration error, and inference.

pub mod data;
pub mod eval;
pub mod fast;
pub mod inference;
pub mod model;
pub mod patient;
pub mod report;
pub mod training;
pub mod tre;

pub use burn;
pub use model::{UNet, UNetConfig};

use std::path::Path;

#[derive(Debug, thiserror::Error)]
pub enum NetError {
    #[error(transparent)]
    Dataset(#[from] umesh_core::dataset::DatasetError),
    #[error("{0}")]
    Invalid(String),
    #[error("{0}")]
    Io(String),
    #[error("weights: {0}")]
    Store(String),
    #[error("cancelled")]
    Cancelled,
}

/// What a model folder holds besides its weights (`model.json`).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ModelInfo {
    pub config: UNetConfig,
    pub normalization: data::Normalization,
    pub padded_shape: [usize; 3],
    pub dataset: String,
    pub train_indices: Vec<usize>,
    pub val_indices: Vec<usize>,
    pub settings: training::TrainSettings,
    /// Hash of the dataset's `grid.npz` (copied beside the weights): a model only fits its grid.
    #[serde(default)]
    pub grid_hash: Option<String>,
    /// The dataset's configuration (grid, loads, visibility), so that registration rebuilds
    /// the same grid and visible nodes from the segmentation.
    #[serde(default)]
    pub dataset_config: Option<umesh_core::dataset::DatasetConfig>,
}

impl ModelInfo {
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
        let text = std::fs::read_to_string(&p).map_err(|e| NetError::Io(format!("{}: {e}", p.display())))?;
        let info: Self =
            serde_json::from_str(&text).map_err(|e| NetError::Invalid(format!("{}: not a umesh model description: {e}", p.display())))?;
        info.validate().map_err(|e| NetError::Invalid(format!("{}: {e}", p.display())))?;
        Ok(info)
    }

    /// The one check of a model description, wherever a model is loaded (`eval`, `register`,
    /// the app's rehearsal, QA and AR view, `prepare`'s check): normalisation, grid size and
    /// observation settings finite and within bounds.
    pub fn validate(&self) -> Result<(), String> {
        let n = &self.normalization;
        for (name, v) in [("input_scale_mm", n.input_scale_mm), ("output_scale_mm", n.output_scale_mm)] {
            if !(v.is_finite() && (1e-6..=1e6).contains(&v)) {
                return Err(format!("normalization {name} = {v}: must lie in [1e-6, 1e6] mm"));
            }
        }
        let cells = self.padded_shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
        if self.padded_shape.contains(&0) || cells.is_none_or(|c| c > 1 << 26) {
            return Err(format!("padded grid {:?}: empty or over 2^26 cells", self.padded_shape));
        }
        if let Some(o) = &self.settings.observation {
            o.validate()?;
        }
        Ok(())
    }
    pub fn write(&self, dir: &Path) -> Result<(), NetError> {
        let p = dir.join("model.json");
        let text = serde_json::to_string_pretty(self).map_err(|e| NetError::Invalid(e.to_string()))?;
        umesh_core::write_atomic(&p, text.as_bytes()).map_err(|e| NetError::Io(format!("{}: {e}", p.display())))
    }
}
