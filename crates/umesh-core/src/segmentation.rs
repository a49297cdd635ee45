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
            return Err(SegmentationError::Invalid {
                path: self.source.clone(),
                reason: "no organ label chosen".into(),
            });
        }
        // An organ made only of labels named as vessels or tumours (`--organ-label 63`, the vena
        // cava) would run a whole job on the wrong tissue: said before any stage runs.
        let named: Vec<(i64, String)> = self.organ_labels.iter().map(|&l| (l, self.label_name(l))).collect();
        if named.iter().all(|(_, n)| matches!(name_role(n), Some(Role::Anchor | Role::Structure))) {
            let organ: Vec<String> = counts
                .keys()
                .filter(|&&l| name_role(&self.label_name(l)) == Some(Role::Organ))
                .map(|l| format!("{l} ({})", self.label_name(*l)))
                .collect();
            return Err(SegmentationError::Invalid {
                path: self.source.clone(),
                reason: format!(
                    "the organ labels {named:?} are named as vessels or structures, not an organ: choose the organ with --organ-label{}",
                    if organ.is_empty() { String::new() } else { format!(" (here: {})", organ.join(", ")) }
                ),
            });
        }
        // Structures may lie inside the organ (the phantom's tumours are organ labels too), but
        // an organ made only of structure labels would draw the whole organ as a structure.
        if self.organ_labels.iter().all(|l| self.structure_labels.contains(l)) {
            return Err(SegmentationError::Invalid {
                path: self.source.clone(),
                reason: format!(
                    "the organ labels {:?} are all also structure labels {:?}: a structure cannot be the whole organ",
                    self.organ_labels, self.structure_labels
                ),
            });
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
    with_labels(path, read_volume(path, options)?, organ_labels.to_vec(), structure_labels.to_vec())
}

fn with_labels(
    path: &Path,
    volume: Volume,
    organ_labels: Vec<i64>,
    structure_labels: Vec<i64>,
) -> Result<Segmentation, SegmentationError> {
    let seg = Segmentation { source: path.into(), volume, organ_labels, structure_labels };
    seg.validate()?;
    Ok(seg)
}

/// Load a NIfTI label volume; labels not chosen are taken by name (`labels_by_name`), else
/// the organ is label 1 with no structures.
pub fn load_nifti_labels(
    path: &Path,
    organ_labels: &[i64],
    structure_labels: &[i64],
    options: &ReadOptions,
) -> Result<Segmentation, SegmentationError> {
    let volume = read_volume(path, options)?;
    let by_name = labels_by_name(&volume);
    let organ = if !organ_labels.is_empty() {
        organ_labels.to_vec()
    } else {
        by_name.as_ref().map(|b| b.0.clone()).unwrap_or_else(|| vec![1])
    };
    let structures = if !structure_labels.is_empty() || !organ_labels.is_empty() {
        structure_labels.to_vec()
    } else {
        by_name.map(|b| b.1).unwrap_or_default()
    };
    // Labels chosen by default: the structures the organ encloses are part of it, as in a
    // folder of masks and the bundled phantom (the same file is the same organ however given).
    let mut organ = organ;
    if organ_labels.is_empty() {
        let mut inside: Vec<i64> = structures.iter().copied().filter(|l| !organ.contains(l)).collect();
        inside.sort_unstable();
        for l in inside {
            let voxels: Vec<bool> = volume.data.iter().map(|&v| v.round() as i64 == l).collect();
            if enclosed_by_organ(&volume, &voxels, &organ) {
                organ.push(l);
            }
        }
    }
    with_labels(path, volume, organ, structures)
}

/// The one rule for structures inside the organ, in every input path: a structure is part of
/// the organ volume when more than half of the voxels bordering it (6-neighbours, the volume's
/// edge counted as background) are organ voxels: a tumour or an intrahepatic vessel, not the
/// extrahepatic portal vein. `structure`: the structure's voxels.
fn enclosed_by_organ(volume: &Volume, structure: &[bool], organ_labels: &[i64]) -> bool {
    let [nx, ny, nz] = volume.dims;
    let (mut border, mut border_organ) = (0usize, 0usize);
    for (idx, _) in structure.iter().enumerate().filter(|(_, h)| **h) {
        let (i, j, k) = (idx % nx, (idx / nx) % ny, idx / (nx * ny));
        for (di, dj, dk) in [(-1i64, 0i64, 0i64), (1, 0, 0), (0, -1, 0), (0, 1, 0), (0, 0, -1), (0, 0, 1)] {
            let (a, b, c) = (i as i64 + di, j as i64 + dj, k as i64 + dk);
            if a < 0 || b < 0 || c < 0 || a >= nx as i64 || b >= ny as i64 || c >= nz as i64 {
                border += 1;
                continue;
            }
            let n = a as usize + nx * (b as usize + ny * c as usize);
            if !structure[n] {
                border += 1;
                let v = volume.data[n];
                border_organ += (v != 0.0 && organ_labels.contains(&(v.round() as i64))) as usize;
            }
        }
    }
    border_organ * 2 > border
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
pub fn load_meshes(
    organ: &Path,
    structures: &[PathBuf],
    spacing_mm: f64,
    scale_to_mm: f64,
) -> Result<Segmentation, SegmentationError> {
    let read = |p: &Path| -> Result<TriMesh, SegmentationError> {
        let mut m = read_closed_mesh(p)?;
        for v in &mut m.positions {
            *v *= scale_to_mm;
        }
        Ok(m)
    };
    let organ_mesh = read(organ)?;
    let invalid = |reason: String| SegmentationError::Invalid { path: organ.into(), reason };
    let mask = organ_mesh
        .voxelize(spacing_mm)
        .ok_or_else(|| invalid(format!("the mesh is too large to voxelise at {spacing_mm} mm")))?;
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

/// Names (lower case) that mark a label as the organ, as a vein that anchors it, or as an
/// internal structure drawn in the overlay: TotalSegmentator's and 3D Slicer's usual names.
pub fn name_role(name: &str) -> Option<Role> {
    let n = name.trim().to_lowercase().replace([' ', '-'], "_");
    let n = n.strip_suffix(".nii.gz").or_else(|| n.strip_suffix(".nii")).unwrap_or(&n).to_string();
    if n == "liver" {
        return Some(Role::Organ);
    }
    if ["inferior_vena_cava", "vena_cava", "ivc", "hepatic_vein", "hepatic_veins"].iter().any(|a| n == *a) {
        return Some(Role::Anchor);
    }
    let structure = ["portal_vein", "hepatic_vessel", "liver_vessel", "tumor", "tumour", "lesion", "hepatic_artery"];
    structure.iter().any(|s| n.contains(s)).then_some(Role::Structure)
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Role {
    Organ,
    Anchor,
    Structure,
}

/// Organ and structure labels of a named multi-label volume when none are chosen: the label
/// named "liver", and the vessels and tumours named as such. None without a "liver" label.
pub fn labels_by_name(volume: &Volume) -> Option<(Vec<i64>, Vec<i64>)> {
    let counts = volume.label_counts();
    let present = |l: &i64| counts.contains_key(l);
    let organ: Vec<i64> = volume
        .label_names
        .iter()
        .filter(|(l, n)| present(l) && name_role(n) == Some(Role::Organ))
        .map(|x| *x.0)
        .collect();
    if organ.is_empty() {
        return None;
    }
    let structures = volume
        .label_names
        .iter()
        .filter(|(l, n)| present(l) && name_role(n) == Some(Role::Structure))
        .map(|x| *x.0)
        .collect();
    Some((organ, structures))
}

/// One mask file of a multi-file segmentation and what it is.
#[derive(Clone, Debug)]
pub struct MaskFile {
    pub name: String,
    pub path: PathBuf,
    pub role: Role,
}

/// What assembling per-structure masks did, for the user to read.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct AssemblyNotes {
    /// Files whose lattice differs from the organ's (resampled, nearest voxel).
    pub resampled: Vec<String>,
    /// Files in a folder that were not used (not a known organ, vein or structure name).
    pub ignored: Vec<String>,
    /// Anchor veins drawn mostly inside the organ mask (some livers are segmented with the
    /// intrahepatic vena cava): their voxels were taken from the organ so the organ can be held there.
    pub carved: Vec<String>,
}

/// The mask files of a folder of per-structure NIfTI masks (TotalSegmentator's default
/// output): `liver.nii.gz` is the organ; the vena cava and hepatic veins anchor it; portal
/// vein, hepatic vessels and tumours are structures. Other files are listed as ignored.
pub fn mask_folder(dir: &Path) -> Result<MaskFolder, SegmentationError> {
    let bad = |reason: String| SegmentationError::Invalid { path: dir.into(), reason };
    let entries = std::fs::read_dir(dir).map_err(|e| bad(format!("cannot list the folder: {e}")))?;
    let mut files = Vec::new();
    let mut ignored = Vec::new();
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(stem) = name.strip_suffix(".nii.gz").or_else(|| name.strip_suffix(".nii")) else { continue };
        match name_role(stem) {
            Some(role) => files.push(MaskFile { name: stem.to_string(), path: e.path(), role }),
            None => ignored.push(name),
        }
    }
    files.sort_by(|a, b| a.name.cmp(&b.name).then_with(|| a.path.cmp(&b.path)));
    // liver.nii beside liver.nii.gz: which one is meant cannot be told.
    if let Some(w) = files.windows(2).find(|w| w[0].name == w[1].name) {
        return Err(bad(format!(
            "{} and {} are masks of the same structure; keep one",
            w[0].path.file_name().unwrap_or_default().to_string_lossy(),
            w[1].path.file_name().unwrap_or_default().to_string_lossy()
        )));
    }
    ignored.sort();
    if !files.iter().any(|f| f.role == Role::Organ) {
        return Err(bad("no liver.nii.gz (or liver.nii) mask in the folder".into()));
    }
    Ok(MaskFolder { files, ignored })
}

/// The masks found in a folder, and the names of the files that are none of them.
#[derive(Clone, Debug)]
pub struct MaskFolder {
    pub files: Vec<MaskFile>,
    pub ignored: Vec<String>,
}

/// Per-structure binary masks (any non-zero voxel is inside) assembled into one label volume
/// on the organ mask's lattice: organ = 1, then the other files 2, 3, ... in the order given,
/// named after them. Masks on other lattices are resampled (nearest voxel) and reported; a
/// mask with voxels but none on the organ's lattice is an error. Structures enclosed by the
/// organ (most voxels around them are organ) become part of it, as tumours and vessels in the
/// phantom; anchors and other structures never take voxels from the organ.
pub fn assemble_masks(
    files: &[MaskFile],
    options: &ReadOptions,
) -> Result<(Segmentation, AssemblyNotes), SegmentationError> {
    let organ_file = files
        .iter()
        .find(|f| f.role == Role::Organ)
        .ok_or_else(|| SegmentationError::Invalid { path: PathBuf::from("."), reason: "no organ mask given".into() })?;
    let organ = read_volume(&organ_file.path, options)?;
    let mut volume = Volume::new(organ.dims, organ.world_from_voxel);
    let mut organ_count = 0;
    for (v, &o) in volume.data.iter_mut().zip(&organ.data) {
        if o.round() != 0.0 {
            *v = 1.0;
            organ_count += 1;
        }
    }
    if organ_count == 0 {
        return Err(SegmentationError::EmptyMask { path: organ_file.path.clone() });
    }
    volume.label_names.insert(1, organ_file.name.clone());
    let mut notes = AssemblyNotes::default();
    let mut organ_labels = vec![1];
    let mut structure_labels = Vec::new();
    let to_index = volume.world_from_voxel;
    for (label, f) in (2i64..).zip(files.iter().filter(|f| f.role != Role::Organ)) {
        let m = read_volume(&f.path, options)?;
        let mask = Mask {
            dims: m.dims,
            data: m.data.iter().map(|v| v.round() != 0.0).collect(),
            world_from_voxel: m.world_from_voxel,
        };
        if mask.count() == 0 {
            return Err(SegmentationError::EmptyMask { path: f.path.clone() });
        }
        let same = m.dims == volume.dims && (m.world_from_voxel - volume.world_from_voxel).abs().max() < 1e-4;
        let sampler = mask.world_sampler();
        let [nx, ny, _] = volume.dims;
        let hits: Vec<bool> = (0..volume.data.len())
            .map(|idx| {
                if same {
                    mask.data[idx]
                } else {
                    let p = to_index.transform_point(&nalgebra::Point3::new(
                        (idx % nx) as f64,
                        ((idx / nx) % ny) as f64,
                        (idx / (nx * ny)) as f64,
                    ));
                    sampler.inside(&p)
                }
            })
            .collect();
        let count = hits.iter().filter(|&&h| h).count();
        let enclosed = f.role == Role::Structure && enclosed_by_organ(&volume, &hits, &organ_labels);
        // An anchor vein lying mostly inside the organ mask would otherwise keep only a few
        // voxels (or none) and the organ would silently lose its attachment: it takes its
        // voxels from the organ instead, and the notes say so.
        let inside = hits.iter().zip(&volume.data).filter(|&(&h, &v)| h && v == 1.0).count();
        let carve = f.role == Role::Anchor && inside * 2 > count;
        if carve {
            notes.carved.push(format!(
                "{}: {inside} of its {count} voxels lie inside {}; they are the vein's, not the organ's",
                f.path.display(),
                organ_file.path.display()
            ));
        }
        for (idx, &h) in hits.iter().enumerate() {
            // Only an enclosed structure takes voxels from the organ (and becomes part of it);
            // an anchor vein outside the organ or an extrahepatic structure never carves it.
            if h && (enclosed || carve || volume.data[idx] != 1.0) {
                volume.data[idx] = label as f32;
            }
        }
        if count == 0 {
            return Err(SegmentationError::Invalid {
                path: f.path.clone(),
                reason: format!(
                    "its {} voxels do not overlap the lattice of {}",
                    mask.count(),
                    organ_file.path.display()
                ),
            });
        }
        if !same {
            notes.resampled.push(format!("{} (resampled onto the organ's lattice, nearest voxel)", f.path.display()));
        }
        volume.label_names.insert(label, f.name.clone());
        if f.role == Role::Structure {
            structure_labels.push(label);
            if enclosed {
                organ_labels.push(label);
            }
        }
    }
    let seg = Segmentation { source: organ_file.path.clone(), volume, organ_labels, structure_labels };
    seg.validate()?;
    Ok((seg, notes))
}
