//! The one error of the dataset jobs.

use super::preflight::Preflight;
use crate::grid::GridError;
use crate::npz::NpzError;
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("{path}: {reason}")]
    Invalid { path: PathBuf, reason: String },
    #[error("{path}: cannot read or write: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error(transparent)]
    Npz(#[from] NpzError),
    /// The configuration could not be written as JSON (for its hash or the manifest).
    #[error("the dataset configuration as JSON")]
    Json(#[from] serde_json::Error),
    #[error(transparent)]
    Grid(#[from] GridError),
    /// The pre-flight check projects too low an acceptance (the message names the likely cause).
    #[error("{message}")]
    Refused { message: String, preflight: Box<Preflight> },
    #[error(transparent)]
    Cancelled(#[from] crate::Cancelled),
}

pub(super) fn invalid(path: &Path, reason: impl Into<String>) -> DatasetError {
    DatasetError::Invalid { path: path.into(), reason: reason.into() }
}
