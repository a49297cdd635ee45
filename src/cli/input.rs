//! Loading the organ geometry: a NIfTI segmentation, closed meshes, or the bundled phantom.

use anyhow::Result;
use std::path::PathBuf;
use umesh_core::nifti_io::ReadOptions;
use umesh_core::segmentation::{self, Segmentation};

pub const PHANTOM_BYTES: &[u8] = include_bytes!("../../assets/phantom.nii.gz");

#[derive(clap::Args, Debug, Clone, Default)]
pub struct InputArgs {
    /// Segmentation (NIfTI .nii/.nii.gz/.hdr) or closed organ mesh (.obj/.ply/.stl);
    /// the bundled phantom when omitted.
    pub seg: Option<PathBuf>,
    /// Organ label(s) (repeat or comma-separate); default 1 (phantom: liver with its contents).
    #[arg(long = "organ-label", value_delimiter = ',')]
    pub organ_labels: Vec<i64>,
    /// Internal-structure labels (tumours, vessels).
    #[arg(long = "structure-label", value_delimiter = ',')]
    pub structure_labels: Vec<i64>,
    /// Internal-structure meshes, with a mesh organ.
    #[arg(long = "structure-mesh")]
    pub structure_meshes: Vec<PathBuf>,
    /// Millimetres per unit of mesh files.
    #[arg(long, default_value_t = 1.0)]
    pub mesh_scale_mm: f64,
    /// Voxel size used to voxelise meshes (mm).
    #[arg(long, default_value_t = 1.0)]
    pub mesh_voxel_mm: f64,
    /// Refuse volumes with more voxels than this (checked before allocating).
    #[arg(long, default_value_t = umesh_core::nifti_io::DEFAULT_MAX_VOXELS)]
    pub max_voxels: u64,
}

impl InputArgs {
    pub fn load(&self) -> Result<Segmentation> {
        let Some(path) = &self.seg else {
            let mut seg = segmentation::bundled_phantom(PHANTOM_BYTES)?;
            if !self.organ_labels.is_empty() {
                seg.organ_labels = self.organ_labels.clone();
            }
            if !self.structure_labels.is_empty() {
                seg.structure_labels = self.structure_labels.clone();
            }
            seg.validate()?;
            return Ok(seg);
        };
        if segmentation::is_mesh_path(path) {
            return Ok(segmentation::load_meshes(path, &self.structure_meshes, self.mesh_voxel_mm, self.mesh_scale_mm)?);
        }
        let organ = if self.organ_labels.is_empty() { vec![1] } else { self.organ_labels.clone() };
        Ok(segmentation::load_nifti(path, &organ, &self.structure_labels, &ReadOptions { max_voxels: self.max_voxels })?)
    }
}

/// The bundled model folder: `assets/model` under the working directory, else beside the
/// sources this binary was built from.
pub fn bundled_model() -> PathBuf {
    let local = PathBuf::from("assets/model");
    if local.join("model.json").is_file() {
        return local;
    }
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("assets/model")
}

/// The dataset configuration of a model (its grid, loads and camera), or the paper's
/// default for `seg` when the model predates that record.
pub fn model_dataset_config(info: Option<&umesh_net::ModelInfo>, seg: &Segmentation) -> umesh_core::dataset::DatasetConfig {
    info.and_then(|i| i.dataset_config.clone())
        .unwrap_or_else(|| umesh_core::dataset::DatasetConfig::paper(super::dataset::default_fixed(seg, None, 6.0)))
}
