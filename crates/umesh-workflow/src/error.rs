//! The one error of the workflow recipes.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum WorkflowError {
    /// An option or setting the user gave is out of range or malformed; the message names it.
    #[error("{0}")]
    Option(String),
    #[error(transparent)]
    Segmentation(#[from] umesh_core::segmentation::SegmentationError),
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
}

impl WorkflowError {
    pub(crate) fn option_message(message: String) -> Self {
        Self::Option(message)
    }

    pub(crate) fn option(option: impl std::fmt::Display, reason: &str) -> Self {
        Self::Option(format!("{option}: {reason}"))
    }
}

/// An option error with the message unless the condition holds (the message is made only then).
pub(crate) fn require(holds: bool, message: impl FnOnce() -> String) -> Result<(), WorkflowError> {
    if holds { Ok(()) } else { Err(WorkflowError::Option(message())) }
}
