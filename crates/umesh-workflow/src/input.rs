//! The organ's geometry from what a user gives: a NIfTI segmentation, a folder of masks, closed
//! meshes, or the bundled phantom; the bundled model and a model's dataset configuration.

use crate::WorkflowError;
use std::path::{Path, PathBuf};
use umesh_core::nifti_io::ReadOptions;
use umesh_core::segmentation::{self, Segmentation};

pub const PHANTOM_BYTES: &[u8] = include_bytes!("../../../assets/phantom.nii.gz");

/// Where the organ comes from (the command line's positional SEG and its options; the app fills
/// it from its dialogs).
#[derive(Debug, Clone, Default)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct InputSpec {
    /// Segmentation: a multi-label NIfTI (.nii/.nii.gz/.hdr), a folder of per-structure masks
    /// (TotalSegmentator's output: liver.nii.gz, inferior_vena_cava.nii.gz, ...), the organ's
    /// mask with --structure files, or a closed organ mesh (.obj/.ply/.stl); the bundled
    /// phantom when omitted.
    pub seg: Option<PathBuf>,
    /// More masks, NAME=FILE (repeat): vena cava / hepatic veins anchor the organ, other names
    /// are structures drawn in the overlay. SEG is then the organ's mask.
    #[cfg_attr(feature = "clap", arg(long = "structure", value_name = "NAME=FILE"))]
    pub structure_files: Vec<String>,
    /// Organ label(s) (repeat or comma-separate); default: the label named "liver", else 1
    /// (phantom: liver with its contents).
    #[cfg_attr(feature = "clap", arg(long = "organ-label", value_delimiter = ','))]
    pub organ_labels: Vec<i64>,
    /// Internal-structure labels (tumours, vessels).
    #[cfg_attr(feature = "clap", arg(long = "structure-label", value_delimiter = ','))]
    pub structure_labels: Vec<i64>,
    /// Internal-structure meshes, with a mesh organ.
    #[cfg_attr(feature = "clap", arg(long = "structure-mesh"))]
    pub structure_meshes: Vec<PathBuf>,
    /// Millimetres per unit of mesh files.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 1.0))]
    pub mesh_scale_mm: f64,
    /// Voxel size used to voxelise meshes (mm).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 1.0))]
    pub mesh_voxel_mm: f64,
    /// Refuse volumes with more voxels than this (checked before allocating).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = umesh_core::nifti_io::DEFAULT_MAX_VOXELS))]
    pub max_voxels: u64,
}

impl InputSpec {
    /// The files and folders this organ is read from, with the option naming each (for
    /// `umesh_core::check_apart`).
    pub fn paths(&self) -> Vec<(&'static str, &std::path::Path)> {
        let mut v: Vec<(&'static str, &std::path::Path)> = self.seg.iter().map(|p| ("SEG", p.as_path())).collect();
        v.extend(self.structure_meshes.iter().map(|p| ("--structure-mesh", p.as_path())));
        v
    }

    /// Reads the segmentation; notes on how masks were combined go to `notes`.
    pub fn load_with_notes(&self, notes: &mut Vec<String>) -> Result<Segmentation, WorkflowError> {
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
        if !(self.mesh_voxel_mm >= 0.05 && self.mesh_voxel_mm <= 50.0) {
            return Err(WorkflowError::option(
                format!("--mesh-voxel-mm {}", self.mesh_voxel_mm),
                "must lie in [0.05, 50]",
            ));
        }
        if !(self.mesh_scale_mm > 0.0 && self.mesh_scale_mm.is_finite()) {
            return Err(WorkflowError::option(
                format!("--mesh-scale-mm {}", self.mesh_scale_mm),
                "must be positive and finite",
            ));
        }
        let options = ReadOptions { max_voxels: self.max_voxels };
        let files = if path.is_dir() {
            let segmentation::MaskFolder { files, ignored } = segmentation::mask_folder(path)?;
            if !ignored.is_empty() {
                notes.push(format!(
                    "{}: {} files not used (not liver, vena cava, hepatic veins, portal vein, vessels or tumours)",
                    path.display(),
                    ignored.len()
                ));
            }
            Some(files)
        } else if !self.structure_files.is_empty() {
            let mut files = vec![segmentation::MaskFile {
                name: path
                    .file_name()
                    .map(|n| n.to_string_lossy().trim_end_matches(".gz").trim_end_matches(".nii").to_string())
                    .unwrap_or_default(),
                path: path.clone(),
                role: segmentation::Role::Organ,
            }];
            for s in &self.structure_files {
                let (name, file) = s
                    .split_once('=')
                    .ok_or_else(|| WorkflowError::option(format!("--structure {s:?}"), "expected NAME=FILE"))?;
                if name.trim().is_empty() {
                    return Err(WorkflowError::option(format!("--structure {s:?}"), "the name is empty"));
                }
                let role = match segmentation::name_role(name) {
                    Some(segmentation::Role::Anchor) => segmentation::Role::Anchor,
                    _ => segmentation::Role::Structure,
                };
                files.push(segmentation::MaskFile { name: name.trim().to_string(), path: PathBuf::from(file), role });
            }
            Some(files)
        } else {
            None
        };
        if let Some(files) = files {
            if !(self.organ_labels.is_empty() && self.structure_labels.is_empty()) {
                return Err(WorkflowError::option(
                    "--organ-label/--structure-label",
                    "apply to a multi-label file, not to separate masks",
                ));
            }
            let (seg, assembly) = segmentation::assemble_masks(&files, &options)?;
            notes.extend(assembly.resampled.iter().chain(&assembly.carved).cloned());
            return Ok(seg);
        }
        if segmentation::is_mesh_path(path) {
            return Ok(segmentation::load_meshes(
                path,
                &self.structure_meshes,
                self.mesh_voxel_mm,
                self.mesh_scale_mm,
            )?);
        }
        Ok(segmentation::load_nifti_labels(path, &self.organ_labels, &self.structure_labels, &options)?)
    }
}

impl InputSpec {
    /// The files the segmentation is read from (hashed into a patient folder).
    pub fn files(&self) -> Result<Vec<PathBuf>, WorkflowError> {
        let Some(path) = &self.seg else { return Ok(Vec::new()) };
        let mut files = Vec::new();
        if path.is_dir() {
            files.extend(segmentation::mask_folder(path)?.files.into_iter().map(|f| f.path));
        } else {
            files.push(path.clone());
            let s = path.to_string_lossy();
            if let Some(stem) = s.strip_suffix(".hdr") {
                files.push(PathBuf::from(format!("{stem}.img")));
            }
        }
        for s in &self.structure_files {
            if let Some((_, f)) = s.split_once('=') {
                files.push(PathBuf::from(f));
            }
        }
        files.extend(self.structure_meshes.iter().cloned());
        Ok(files)
    }
}

/// The bundled model folder: `assets/model` under the working directory, else under a folder
/// holding the binary (`target/release/umesh` in a checkout), else beside the sources this
/// binary was built from (a path fixed at build time: a build directory shared between two
/// checkouts may name the other one, or none that still exists).
pub fn bundled_model() -> PathBuf {
    let local = PathBuf::from("assets/model");
    if local.join("model.json").is_file() {
        return local;
    }
    let exe = std::env::current_exe().ok();
    if let Some(found) = exe
        .iter()
        .flat_map(|e| e.ancestors().skip(1).take(4))
        .map(|d| d.join("assets/model"))
        .find(|m| m.join("model.json").is_file())
    {
        return found;
    }
    let crate_dir = Path::new(env!("CARGO_MANIFEST_DIR"));
    crate_dir.parent().and_then(Path::parent).unwrap_or(crate_dir).join("assets/model")
}

/// The dataset configuration of a model (its grid, loads and camera), or the paper's
/// default for `seg` when the model predates that record.
pub fn model_dataset_config(
    info: Option<&umesh_net::ModelInfo>,
    seg: &Segmentation,
) -> umesh_core::dataset::DatasetConfig {
    info.and_then(|i| i.dataset_config.clone()).unwrap_or_else(|| {
        umesh_core::dataset::DatasetConfig::paper(umesh_core::loads::default_fixed(seg, None, 6.0).region)
    })
}
