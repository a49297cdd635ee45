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
