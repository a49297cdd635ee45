//! The dataset folder on disk: manifest, shard encoding and decoding, the reader.

use super::calibrate::{Rejection, SampleResult};
use super::config::{DatasetConfig, FORMAT, FORMAT_VERSION, fnv_hex, recorded_family, recorded_material};
use super::context::DatasetContext;
use super::error::{DatasetError, invalid};
use crate::fem::MaterialParams;
use crate::loads::LoadFamily;
use crate::npz::{Array, ArrayData, Npz, encode_npz_with};
use nalgebra::Vector3;
use std::path::{Path, PathBuf};

/// Per-sample record of the manifest.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SampleRecord {
    pub index: usize,
    pub accepted: bool,
    pub rejection: Option<Rejection>,
    pub reason: Option<String>,
    pub max_displacement_mm: f64,
    pub mean_displacement_mm: f64,
    /// The mean displacement the sample's forces were calibrated for (mm).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target_displacement_mm: Option<f64>,
    /// The target drawn, when the strain limit (`ForceSettings::max_strain`) lowered it to
    /// `target_displacement_mm`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub drawn_target_mm: Option<f64>,
    /// The sample's load family (datasets of more than one family).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub family: Option<LoadFamily>,
    /// The sample's material (datasets that draw one per sample).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub material: Option<MaterialParams>,
    pub newton_iterations: usize,
    /// Wall time of the solve (absent for shards adopted from an interrupted run).
    pub solve_ms: Option<f64>,
    pub shard: String,
    /// Set by the QA browser: training skips flagged samples.
    #[serde(default)]
    pub flagged: bool,
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ShardRecord {
    pub file: String,
    pub first: usize,
    pub count: usize,
    pub accepted: usize,
    pub hash: String,
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Manifest {
    pub format: String,
    pub format_version: u32,
    pub program_version: String,
    pub config: DatasetConfig,
    pub config_hash: String,
    pub grid_hash: String,
    pub segmentation: String,
    pub segmentation_hash: String,
    pub padded_shape: [usize; 3],
    pub nodes: usize,
    pub visible_nodes: usize,
    pub shards: Vec<ShardRecord>,
    pub samples: Vec<SampleRecord>,
    /// True when every shard of the configuration is present.
    pub complete: bool,
}

impl Manifest {
    pub fn read(dir: &Path) -> Result<Self, DatasetError> {
        let path = dir.join("manifest.json");
        let text = std::fs::read_to_string(&path).map_err(|source| DatasetError::Io { path: path.clone(), source })?;
        let m: Manifest =
            serde_json::from_str(&text).map_err(|e| invalid(&path, format!("not a umesh dataset manifest: {e}")))?;
        if m.format != FORMAT {
            return Err(invalid(&path, format!("format {} is not {FORMAT}", m.format)));
        }
        if m.format_version != FORMAT_VERSION {
            return Err(invalid(
                &path,
                format!(
                    "dataset format v{} (this umesh reads v{FORMAT_VERSION}: its samples carry the simulated camera view); \
                     regenerate it with `umesh dataset generate SEG --samples {} --seed {} --out NEW_FOLDER`",
                    m.format_version, m.config.samples, m.config.seed
                ),
            ));
        }
        m.check_samples().map_err(|reason| invalid(&path, reason))?;
        Ok(m)
    }

    /// The sample list agrees with the shards and holds figures a solve can give: every sample
    /// once, in a listed shard, within its range; each shard's accepted count that of its
    /// samples; displacements finite and non-negative. A manifest edited by hand (or damaged)
    /// was read as it was: `dataset stats`, `train` and `eval` went on with what it claimed.
    fn check_samples(&self) -> Result<(), String> {
        let mut seen = std::collections::HashSet::new();
        let mut accepted = std::collections::HashMap::<&str, usize>::new();
        for s in &self.samples {
            if !seen.insert(s.index) {
                return Err(format!("sample {} is listed twice", s.index));
            }
            let Some(shard) = self.shards.iter().find(|r| r.file == s.shard) else {
                return Err(format!(
                    "sample {} names the shard {}, which the manifest does not list",
                    s.index, s.shard
                ));
            };
            if !(shard.first..shard.first + shard.count).contains(&s.index) {
                return Err(format!(
                    "sample {} lies outside its shard {} (samples {}..{})",
                    s.index,
                    s.shard,
                    shard.first,
                    shard.first + shard.count
                ));
            }
            let figures = [s.max_displacement_mm, s.mean_displacement_mm].into_iter().chain(s.target_displacement_mm);
            if s.accepted && !figures.clone().all(|v| v.is_finite() && v >= 0.0) {
                return Err(format!("sample {}: a displacement figure is negative or not finite", s.index));
            }
            *accepted.entry(s.shard.as_str()).or_default() += s.accepted as usize;
        }
        for r in &self.shards {
            let listed = self.samples.iter().filter(|s| s.shard == r.file).count();
            if listed != r.count || accepted.get(r.file.as_str()).copied().unwrap_or(0) != r.accepted {
                return Err(format!(
                    "{} holds {} samples, {} accepted, but the sample list gives it {listed}, {} accepted",
                    r.file,
                    r.count,
                    r.accepted,
                    accepted.get(r.file.as_str()).copied().unwrap_or(0)
                ));
            }
        }
        Ok(())
    }

    pub fn write(&self, dir: &Path) -> Result<(), DatasetError> {
        let path = dir.join("manifest.json");
        let text = serde_json::to_string_pretty(self).map_err(|e| invalid(&path, e.to_string()))?;
        crate::write_atomic(&path, text.as_bytes()).map_err(|source| DatasetError::Io { path, source })
    }
    pub fn accepted(&self) -> impl Iterator<Item = &SampleRecord> {
        self.samples.iter().filter(|s| s.accepted)
    }
}

pub fn shard_file_name(shard: usize) -> String {
    format!("shard_{shard:06}.npz")
}

/// Encode one shard: deterministic arrays only (no timings).
pub(super) fn encode_shard(
    ctx: &DatasetContext,
    config: &DatasetConfig,
    results: &[SampleResult],
) -> std::io::Result<Vec<u8>> {
    let [x, y, z] = ctx.grid.padded_shape();
    let cells = x * y * z;
    let p = config.forces.probes;
    let accepted: Vec<&SampleResult> = results.iter().filter(|r| r.displacement_mm.is_some()).collect();
    let a = accepted.len();
    let mut u_s = vec![0f32; a * 3 * cells];
    let mut u_v = vec![0f32; a * 3 * cells];
    let mut probes = vec![0f32; a * p * 3];
    let mut forces = vec![0f32; a * p * 3];
    for (s, r) in accepted.iter().enumerate() {
        let u = r.displacement_mm.as_deref().unwrap_or(&[]);
        for n in 0..ctx.grid.node_count() {
            let d = ctx.grid.dense_index(n);
            for c in 0..3 {
                u_v[(s * 3 + c) * cells + d] = u[n][c] as f32;
            }
        }
        for &n in &ctx.visible_nodes {
            let d = ctx.grid.dense_index(n);
            for c in 0..3 {
                u_s[(s * 3 + c) * cells + d] = u[n][c] as f32;
            }
        }
        for (k, f) in r.forces.iter().enumerate().take(p) {
            for c in 0..3 {
                probes[(s * p + k) * 3 + c] = f.point_mm[c] as f32;
                forces[(s * p + k) * 3 + c] = f.force_n[c] as f32;
            }
        }
    }
    let n = results.len();
    let stats: Vec<(f64, f64)> = results.iter().map(|r| r.max_mean(ctx, config)).collect();
    let arrays = vec![
        ("sample_index", Array::i64(vec![n], results.iter().map(|r| r.index as i64).collect())),
        ("accepted", Array::new(vec![n], ArrayData::U8(results.iter().map(|r| r.rejection.is_none() as u8).collect()))),
        (
            "rejection",
            Array::new(
                vec![n],
                ArrayData::U8(results.iter().map(|r| r.rejection.as_ref().map(|x| x.0 as u8).unwrap_or(0)).collect()),
            ),
        ),
        ("max_displacement_mm", Array::f32(vec![n], stats.iter().map(|s| s.0 as f32).collect())),
        ("mean_displacement_mm", Array::f32(vec![n], stats.iter().map(|s| s.1 as f32).collect())),
        ("target_displacement_mm", Array::f32(vec![n], results.iter().map(|r| r.target_mm as f32).collect())),
        (
            "newton_iterations",
            Array::new(vec![n], ArrayData::I32(results.iter().map(|r| r.newton_iterations as i32).collect())),
        ),
        ("index", Array::i64(vec![a], accepted.iter().map(|r| r.index as i64).collect())),
        ("u_s", Array::f32(vec![a, 3, x, y, z], u_s)),
        ("u_v", Array::f32(vec![a, 3, x, y, z], u_v)),
        ("probes_mm", Array::f32(vec![a, p, 3], probes)),
        ("forces_n", Array::f32(vec![a, p, 3], forces)),
        ("obs_count", Array::i64(vec![a], accepted.iter().map(|r| r.observed_mm.len() as i64).collect())),
        (
            "obs_points",
            Array::f32(
                vec![accepted.iter().map(|r| r.observed_mm.len()).sum(), 3],
                accepted.iter().flat_map(|r| r.observed_mm.iter().flatten().copied()).collect(),
            ),
        ),
    ];
    encode_npz_with(&arrays, true)
}

/// Read a shard's per-sample statistics, checking its arrays against the configuration.
pub fn read_shard_records(
    path: &Path,
    config: &DatasetConfig,
    shard: usize,
    padded: [usize; 3],
) -> Result<(Vec<SampleRecord>, usize), DatasetError> {
    let npz = Npz::read(path)?;
    let range = config.shard_range(shard);
    let n = range.len();
    let (_, idx) = npz.f64_with_shape("sample_index", &[Some(n)])?;
    if idx.iter().zip(range.clone()).any(|(a, b)| *a as usize != b) {
        return Err(invalid(path, format!("holds samples other than {range:?}")));
    }
    let (_, acc) = npz.f64_with_shape("accepted", &[Some(n)])?;
    let (_, rej) = npz.f64_with_shape("rejection", &[Some(n)])?;
    let (_, mx) = npz.f64_with_shape("max_displacement_mm", &[Some(n)])?;
    let (_, mean) = npz.f64_with_shape("mean_displacement_mm", &[Some(n)])?;
    let (_, it) = npz.f64_with_shape("newton_iterations", &[Some(n)])?;
    let target = npz.f64_with_shape("target_displacement_mm", &[Some(n)]).ok().map(|t| t.1);
    let a = acc.iter().filter(|&&v| v == 1.0).count();
    let [x, y, z] = padded;
    npz.f64_with_shape("u_v", &[Some(a), Some(3), Some(x), Some(y), Some(z)])?;
    npz.f64_with_shape("u_s", &[Some(a), Some(3), Some(x), Some(y), Some(z)])?;
    let (_, counts) = npz.f64_with_shape("obs_count", &[Some(a)])?;
    if counts.iter().any(|c| !(*c >= 0.0)) {
        return Err(invalid(path, "obs_count holds a negative count"));
    }
    npz.f64_with_shape("obs_points", &[Some(counts.iter().sum::<f64>() as usize), Some(3)])?;
    let file = shard_file_name(shard);
    let records = (0..n)
        .map(|k| SampleRecord {
            index: range.start + k,
            accepted: acc[k] == 1.0,
            rejection: match rej[k] as u8 {
                1 => Some(Rejection::NotConverged),
                2 => Some(Rejection::Inverted),
                3 => Some(Rejection::Failed),
                _ => None,
            },
            reason: None,
            max_displacement_mm: mx[k],
            mean_displacement_mm: mean[k],
            target_displacement_mm: target.as_ref().map(|t| t[k]),
            // Kept by the manifest (`known` in `run_generate`), not by the shard.
            drawn_target_mm: None,
            family: recorded_family(config, range.start + k),
            material: recorded_material(config, range.start + k),
            newton_iterations: it[k] as usize,
            solve_ms: None,
            shard: file.clone(),
            flagged: false,
        })
        .collect();
    Ok((records, a))
}

/// A dataset opened for reading, its shards checked against the manifest's hashes.
#[derive(Debug)]
pub struct Dataset {
    pub dir: PathBuf,
    pub manifest: Manifest,
}

/// A dataset's `grid.npz`, checked against its manifest's grid hash: another dataset's grid, or
/// a damaged one, is refused wherever the grid is read (a foreign one made `train` panic on a
/// tensor shape and passed `stats`).
pub fn read_grid_npz(dir: &Path, manifest: &Manifest) -> Result<Npz, DatasetError> {
    let path = dir.join("grid.npz");
    let bytes = std::fs::read(&path).map_err(|source| DatasetError::Io { path: path.clone(), source })?;
    if fnv_hex(&bytes) != manifest.grid_hash {
        return Err(invalid(
            &path,
            "does not belong to this dataset (its hash differs from the manifest's grid hash): another dataset's grid, or a damaged one",
        ));
    }
    Ok(Npz::from_bytes(&path, &bytes)?)
}

impl Dataset {
    pub fn open(dir: &Path) -> Result<Self, DatasetError> {
        let manifest = Manifest::read(dir)?;
        read_grid_npz(dir, &manifest)?;
        for s in &manifest.shards {
            let path = dir.join(&s.file);
            let bytes = std::fs::read(&path).map_err(|source| DatasetError::Io { path: path.clone(), source })?;
            if fnv_hex(&bytes) != s.hash {
                return Err(invalid(&path, "is corrupted or truncated (its hash differs from the manifest's)"));
            }
            let npz = Npz::from_bytes(&path, &bytes)?;
            let [x, y, z] = manifest.padded_shape;
            npz.f64_with_shape("u_v", &[Some(s.accepted), Some(3), Some(x), Some(y), Some(z)])?;
        }
        Ok(Self { dir: dir.into(), manifest })
    }

    /// (u_s, u_v) of the accepted samples of one shard, flattened [A, 3, X, Y, Z], with their indices.
    pub fn load_shard(&self, shard: &ShardRecord) -> Result<(Vec<usize>, Vec<f32>, Vec<f32>), DatasetError> {
        let npz = Npz::read(&self.dir.join(&shard.file))?;
        let idx = match &npz.get("index")?.data {
            ArrayData::I64(v) => v.iter().map(|&i| i as usize).collect(),
            _ => return Err(invalid(&self.dir.join(&shard.file), "'index' is not int64")),
        };
        let f = |name: &str| -> Result<Vec<f32>, DatasetError> {
            match &npz.get(name)?.data {
                ArrayData::F32(v) => Ok(v.clone()),
                _ => Err(invalid(&self.dir.join(&shard.file), format!("'{name}' is not float32"))),
            }
        };
        Ok((idx, f("u_s")?, f("u_v")?))
    }

    /// The simulated camera views of the accepted samples of one shard (world mm), in the
    /// order of `load_shard`'s indices.
    pub fn load_views(&self, shard: &ShardRecord) -> Result<Vec<Vec<Vector3<f64>>>, DatasetError> {
        let path = self.dir.join(&shard.file);
        let npz = Npz::read(&path)?;
        let counts: Vec<usize> = match &npz.get("obs_count")?.data {
            ArrayData::I64(v) if v.iter().all(|&c| c >= 0) => v.iter().map(|&c| c as usize).collect(),
            _ => return Err(invalid(&path, "'obs_count' is not a non-negative int64 array")),
        };
        let pts = match &npz.get("obs_points")?.data {
            ArrayData::F32(v) if v.len() == 3 * counts.iter().sum::<usize>() => v.clone(),
            _ => return Err(invalid(&path, "'obs_points' is not float32 [sum(obs_count), 3]")),
        };
        let mut out = Vec::with_capacity(counts.len());
        let mut at = 0;
        for c in counts {
            out.push(
                pts[3 * at..3 * (at + c)]
                    .chunks_exact(3)
                    .map(|p| Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64))
                    .collect(),
            );
            at += c;
        }
        Ok(out)
    }
}
