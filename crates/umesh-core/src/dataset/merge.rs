//! Merging shards computed on several machines into the single-run dataset.

use super::config::fnv_hex;
use super::error::{DatasetError, invalid};
use super::generate::finalize;
use super::store::Manifest;
use std::path::{Path, PathBuf};

#[derive(Clone, Debug, serde::Serialize)]
pub struct MergeReport {
    pub out: PathBuf,
    pub shards: usize,
    pub samples: usize,
    pub accepted: usize,
    pub complete: bool,
}

/// Join datasets made with the same configuration (e.g. `--shard k/N` runs) into `out`.
pub fn run_merge(inputs: &[PathBuf], out: &Path) -> Result<MergeReport, DatasetError> {
    let first = inputs.first().ok_or_else(|| invalid(out, "no input dataset"))?;
    let m0 = Manifest::read(first)?;
    let same = |m: &Manifest| {
        m.config_hash == m0.config_hash && m.grid_hash == m0.grid_hash && m.segmentation_hash == m0.segmentation_hash
    };
    // The target: absent, empty, or the same dataset (its shards then join the merge).
    let mut sources: Vec<PathBuf> = inputs.to_vec();
    let non_empty = std::fs::read_dir(out).map(|mut d| d.next().is_some()).unwrap_or(false);
    if non_empty {
        match Manifest::read(out) {
            Ok(m) if same(&m) => {
                if !inputs.iter().any(|i| crate::same_path(i, out)) {
                    sources.push(out.to_path_buf());
                }
            }
            Ok(_) => {
                return Err(invalid(
                    out,
                    format!(
                        "holds another dataset than {} (other configuration, grid or segmentation); choose an empty folder",
                        first.display()
                    ),
                ));
            }
            Err(_) => return Err(invalid(out, "is not empty and holds no dataset manifest; choose an empty folder")),
        }
    }
    // Everything is written into a staging folder beside the target, which replaces it only at
    // the end: a merge that fails leaves the target as it was.
    let staged = crate::StagedDir::new(out, crate::OutputKind::Dataset, &["manifest.json"])
        .map_err(|source| DatasetError::Io { path: out.into(), source })?;
    let merged = merge_into(&m0, &sources, first, staged.path(), same)?;
    if out.exists() {
        // Other files of the target (a job record, notes) move along.
        for e in std::fs::read_dir(out).map_err(|source| DatasetError::Io { path: out.into(), source })?.flatten() {
            let dst = staged.path().join(e.file_name());
            if e.path().is_file() && !dst.exists() && std::fs::copy(e.path(), &dst).is_err() {
                return Err(invalid(&e.path(), "could not be carried over into the merged dataset"));
            }
        }
    }
    staged.commit().map_err(|source| DatasetError::Io { path: out.into(), source })?;
    Ok(MergeReport {
        out: out.into(),
        shards: merged.shards.len(),
        samples: merged.samples.len(),
        accepted: merged.accepted().count(),
        complete: merged.complete,
    })
}

pub(super) fn merge_into(
    m0: &Manifest,
    sources: &[PathBuf],
    first: &Path,
    stage: &Path,
    same: impl Fn(&Manifest) -> bool,
) -> Result<Manifest, DatasetError> {
    std::fs::create_dir_all(stage).map_err(|source| DatasetError::Io { path: stage.into(), source })?;
    let grid = std::fs::read(first.join("grid.npz"))
        .map_err(|source| DatasetError::Io { path: first.join("grid.npz"), source })?;
    let mut merged = Manifest { shards: Vec::new(), samples: Vec::new(), ..m0.clone() };
    let mut have = std::collections::BTreeSet::new();
    for dir in sources {
        let m = Manifest::read(dir)?;
        if !same(&m) {
            return Err(invalid(dir, format!("was made with another configuration than {}", first.display())));
        }
        for s in &m.shards {
            if !have.insert(s.first) {
                continue;
            }
            let src = dir.join(&s.file);
            let bytes = std::fs::read(&src).map_err(|source| DatasetError::Io { path: src.clone(), source })?;
            if fnv_hex(&bytes) != s.hash {
                return Err(invalid(&src, "is corrupted or truncated (its hash differs from the manifest's)"));
            }
            let dst = stage.join(&s.file);
            crate::write_atomic(&dst, &bytes).map_err(|source| DatasetError::Io { path: dst, source })?;
            merged.shards.push(s.clone());
            merged.samples.extend(m.samples.iter().filter(|r| r.shard == s.file).cloned());
        }
    }
    crate::write_atomic(&stage.join("grid.npz"), &grid)
        .map_err(|source| DatasetError::Io { path: stage.join("grid.npz"), source })?;
    finalize(&mut merged);
    merged.write(stage)?;
    Ok(merged)
}
