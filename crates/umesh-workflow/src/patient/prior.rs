//! Where a patient's network starts: the weights of the bundled phantom model (a prior learned
//! on another liver, with loads deeper than a patient's dataset draws) when its network and input
//! are the job's, else random weights. Fine-tuned on the patient's own dataset, it starts where
//! random weights get after many epochs.

use super::folder::{PrepareSettings, Prior};
use umesh_net::{ModelInfo, NetError};

/// `settings` with the training's starting weights (`train.prior`) resolved from `prior`, and
/// `prior_description` saying which and why.
pub fn resolve_prior(settings: &PrepareSettings) -> Result<PrepareSettings, NetError> {
    let mut out = settings.clone();
    let (path, description) = match &settings.prior {
        Prior::None => (None, "random weights (--prior none)".to_string()),
        Prior::Bundled => {
            let path = crate::input::bundled_model();
            match ModelInfo::read(&path) {
                Ok(info) if info.fits_as_prior(&settings.train) => (
                    Some(path),
                    "the bundled phantom model's weights, fine-tuned on this dataset (--prior none: random weights)"
                        .to_string(),
                ),
                Ok(_) => (None, "random weights: the bundled model's network or input is not this job's".to_string()),
                Err(e) => (
                    None,
                    format!(
                        "random weights: the bundled model is unreadable ({e}); run umesh from its folder, or give --prior with a copy of its assets/model"
                    ),
                ),
            }
        }
        Prior::Model(path) => {
            // Checked as the training will, before the job writes anything.
            umesh_net::training::check_prior(path, &settings.train)?;
            (Some(path.clone()), format!("the weights of {}, fine-tuned on this dataset", path.display()))
        }
    };
    out.train.prior = path;
    out.prior_description = description;
    Ok(out)
}
