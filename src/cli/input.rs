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
