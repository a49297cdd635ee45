//! Organ geometry input: a label volume (NIfTI) with the organ and internal-structure
//! labels chosen by number, or closed surface meshes voxelised into such a volume.

use crate::mesh::TriMesh;
use crate::mesh_io::{MeshIoError, read_closed_mesh};
use crate::nifti_io::{NiftiError, ReadOptions, read_volume, read_volume_bytes};
use crate::volume::{Mask, Volume};
use std::path::{Path, PathBuf};

/// The bundled phantom, embedded so every command works with no input.
pub const BUNDLED_PHANTOM_NAME: &str = "assets/phantom.nii.gz (bundled)";

#[derive(Debug, thiserror::Error)]
pub enum SegmentationError {
    #[error(transparent)]
    Nifti(#[from] NiftiError),
    #[error(transparent)]
    Mesh(#[from] MeshIoError),
    #[error("{path}: label {label} is not in the volume (labels present: {present})")]
    MissingLabel { path: PathBuf, label: i64, present: String },
    #[error("{path}: the organ mask is empty")]
    EmptyMask { path: PathBuf },
    #[error("{path}: {reason}")]
    Invalid { path: PathBuf, reason: String },
}

/// A label volume with the labels that make the organ and those drawn as internal structures.
#[derive(Clone, Debug)]
pub struct Segmentation {
    pub source: PathBuf,
    pub volume: Volume,
    pub organ_labels: Vec<i64>,
    pub structure_labels: Vec<i64>,
}

impl Segmentation {
    pub fn organ_mask(&self) -> Mask {
        self.volume.mask(&self.organ_labels)
    }

    pub fn label_name(&self, label: i64) -> String {
        self.volume.label_names.get(&label).cloned().unwrap_or_else(|| format!("label {label}"))
    }

    /// Check that every chosen label exists and the organ is not empty.
    pub fn validate(&self) -> Result<(), SegmentationError> {
        let counts = self.volume.label_counts();
        for &l in self.organ_labels.iter().chain(&self.structure_labels) {
            if !counts.contains_key(&l) {
                let present = counts.keys().map(|k| k.to_string()).collect::<Vec<_>>().join(", ");
                return Err(SegmentationError::MissingLabel {
                    path: self.source.clone(),
                    label: l,
                    present: if present.is_empty() { "none".into() } else { present },
                });
            }
        }
        if self.organ_labels.is_empty() {
            return Err(SegmentationError::Invalid { path: self.source.clone(), reason: "no organ label chosen".into() });
        }
        Ok(())
    }
}

/// Load a NIfTI label volume and choose labels.
pub fn load_nifti(
    path: &Path,
    organ_labels: &[i64],
    structure_labels: &[i64],
    options: &ReadOptions,
) -> Result<Segmentation, SegmentationError> {
    let volume = read_volume(path, options)?;
    let seg =
        Segmentation { source: path.into(), volume, organ_labels: organ_labels.to_vec(), structure_labels: structure_labels.to_vec() };
    seg.validate()?;
    Ok(seg)
}

/// The bundled phantom with its default labels.
pub fn bundled_phantom(bytes: &[u8]) -> Result<Segmentation, SegmentationError> {
    let path = PathBuf::from(BUNDLED_PHANTOM_NAME);
    let volume = read_volume_bytes(&path, bytes, &ReadOptions::default())?;
    let seg = Segmentation {
        source: path,
        volume,
        organ_labels: crate::phantom::ORGAN_LABELS.to_vec(),
        structure_labels: crate::phantom::STRUCTURE_LABELS.to_vec(),
    };
    seg.validate()?;
    Ok(seg)
}

/// Closed meshes (organ first, then internal structures) voxelised into a label volume:
/// organ = 1, structures = 2, 3, ... `scale_to_mm` converts the files' units.
pub fn load_meshes(organ: &Path, structures: &[PathBuf], spacing_mm: f64, scale_to_mm: f64) -> Result<Segmentation, SegmentationError> {
    let read = |p: &Path| -> Result<TriMesh, SegmentationError> {
        let mut m = read_closed_mesh(p)?;
        for v in &mut m.positions {
            *v *= scale_to_mm;
        }
        Ok(m)
    };
    let organ_mesh = read(organ)?;
    let invalid = |reason: String| SegmentationError::Invalid { path: organ.into(), reason };
    let mask = organ_mesh.voxelize(spacing_mm).ok_or_else(|| invalid(format!("the mesh is too large to voxelise at {spacing_mm} mm")))?;
    if mask.count() == 0 {
        return Err(SegmentationError::EmptyMask { path: organ.into() });
    }
    let mut volume = Volume::new(mask.dims, mask.world_from_voxel);
    for (v, &m) in volume.data.iter_mut().zip(&mask.data) {
        *v = if m { 1.0 } else { 0.0 };
    }
    volume.label_names.insert(1, file_stem(organ));
    let mut structure_labels = Vec::new();
    for (i, sp) in structures.iter().enumerate() {
        let label = 2 + i as i64;
        let m = read(sp)?;
        // Voxelise on the organ's lattice by ray parity, through a mesh-local mask resampled.
        let sm = m
            .voxelize(spacing_mm)
            .ok_or_else(|| SegmentationError::Invalid { path: sp.clone(), reason: "too large to voxelise".into() })?;
        let sampler = sm.world_sampler();
        for (idx, v) in volume.data.iter_mut().enumerate() {
            let [nx, ny, _] = volume.dims;
            let p = volume.world_from_voxel.transform_point(&nalgebra::Point3::new(
                (idx % nx) as f64,
                ((idx / nx) % ny) as f64,
                (idx / (nx * ny)) as f64,
            ));
            if sampler.inside(&p) {
                *v = label as f32;
            }
        }
        volume.label_names.insert(label, file_stem(sp));
        structure_labels.push(label);
    }
    let mut organ_labels = vec![1];
    organ_labels.extend(&structure_labels);
    let seg = Segmentation { source: organ.into(), volume, organ_labels, structure_labels };
    seg.validate()?;
    Ok(seg)
}

fn file_stem(p: &Path) -> String {
    p.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default()
}

/// Is this path a mesh file (by extension)?
pub fn is_mesh_path(p: &Path) -> bool {
    matches!(p.extension().map(|e| e.to_string_lossy().to_lowercase()).as_deref(), Some("obj" | "ply" | "stl"))
}
