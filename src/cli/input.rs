//! The organ input on the command line: the workflow's `InputSpec` (a clap argument group), with
//! its notes printed.

use anyhow::Result;
use umesh_core::segmentation::Segmentation;
pub use umesh_workflow::input::{InputSpec as InputArgs, PHANTOM_BYTES, bundled_model, model_dataset_config};

/// Reading the organ with its notes (masks resampled or carved, files not used) on stderr.
pub trait LoadInput {
    fn load(&self) -> Result<Segmentation>;
}

impl LoadInput for InputArgs {
    fn load(&self) -> Result<Segmentation> {
        let mut notes = Vec::new();
        let seg = self.load_with_notes(&mut notes)?;
        for n in notes {
            eprintln!("note: {n}");
        }
        Ok(seg)
    }
}

/// A patient folder's model and organ (`--patient`), refused until its model is trained.
pub fn patient_model(patient: &std::path::Path) -> Result<(std::path::PathBuf, Segmentation)> {
    let p = umesh_workflow::patient::Patient::read(patient)?;
    anyhow::ensure!(
        p.done(umesh_workflow::patient::Stage::Train),
        "{}: the patient's model is not trained yet (run `umesh prepare` again to finish the job)",
        patient.display()
    );
    Ok((umesh_workflow::patient::model_dir(patient), p.segmentation(patient)?))
}

/// A registration's organ, model and the model's dataset configuration: from `--patient`, or
/// from `--model` (default: the bundled one) and the organ input; the model checked against
/// the organ's grid.
pub struct ModelOnOrgan {
    pub model_dir: std::path::PathBuf,
    pub seg: Segmentation,
    pub net: umesh_net::inference::Predictor,
    pub config: umesh_core::dataset::DatasetConfig,
    pub dctx: umesh_core::dataset::DatasetContext,
}

pub fn model_on_organ(
    patient: Option<&std::path::Path>,
    model: Option<&std::path::Path>,
    input: &InputArgs,
) -> Result<ModelOnOrgan> {
    use anyhow::Context;
    let (model_dir, seg) = match patient {
        Some(p) => patient_model(p)?,
        None => (model.map_or_else(bundled_model, |m| m.to_path_buf()), input.load()?),
    };
    let net = umesh_net::inference::Predictor::load(&model_dir)
        .with_context(|| format!("loading the model {}", model_dir.display()))?;
    let config = model_dataset_config(Some(&net.info), &seg);
    let dctx = umesh_core::dataset::DatasetContext::prepare(&seg, &config, &super::output::cancel())?;
    net.info
        .check_grid(&dctx.grid_hash(), dctx.grid.padded_shape())
        .with_context(|| format!("{} does not fit {}", model_dir.display(), seg.source.display()))?;
    Ok(ModelOnOrgan { model_dir, seg, net, config, dctx })
}
