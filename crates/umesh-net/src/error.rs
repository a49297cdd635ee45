//! The one error of the network crate.

#[derive(Debug, thiserror::Error)]
pub enum NetError {
    #[error(transparent)]
    Dataset(#[from] umesh_core::dataset::DatasetError),
    #[error("{0}")]
    Invalid(String),
    #[error("{}: {source}", path.display())]
    Io { path: std::path::PathBuf, source: std::io::Error },
    #[error("the weights {}", path.display())]
    Weights { path: std::path::PathBuf, source: burn::store::SafetensorsStoreError },
    #[error(transparent)]
    Cancelled(#[from] umesh_core::Cancelled),
}
