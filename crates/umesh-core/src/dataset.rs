//! Training data: random force probes on the visible surface, SVK solves, and sharded,
//! deterministic, resumable dataset folders.
//!
//! A dataset folder holds `manifest.json` (configuration, hashes, per-sample statistics),
//! `grid.npz` (the grid, the visible-surface nodes, the surface mesh) and `shard_NNNNNN.npz`
//! files, each covering `shard_size` consecutive sample indices. Sample i depends only on
//! (seed, i), so shards computed anywhere merge into exactly the single-run dataset.

use crate::fem::solver::{FeSolver, FemError, SolveMethod, SolverSettings};
use crate::fem::{BoundaryConditions, FixedRegion, MaterialParams};
use crate::grid::{GridError, GridSettings, ImmersedGrid};
use crate::loads::{self, ForceSettings, PointForce};
use crate::mesh::TriMesh;
use crate::npz::{Array, ArrayData, Npz, NpzError, encode_npz_with};
use crate::phantom::SplitMix64;
use crate::progress::{Cancel, Progress};
use crate::segmentation::Segmentation;
use crate::surface::{SurfaceSettings, extract_surface};
use crate::visible::{VisibilitySettings, VisibleSurface, sample_points, visible_surface};
use nalgebra::Vector3;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::Instant;

pub const FORMAT: &str = "umesh-dataset";
pub const FORMAT_VERSION: u32 = 1;

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DatasetConfig {
    pub samples: usize,
    pub seed: u64,
    /// Samples per shard file.
    pub shard_size: usize,
    pub grid: GridSettings,
    pub material: MaterialParams,
    pub solver: SolverSettings,
    pub forces: ForceSettings,
    pub visibility: VisibilitySettings,
    /// Nodes held fixed in every sample.
    pub fixed: FixedRegion,
    /// Voxel step of the surface mesh used for visibility and probe sampling.
    pub surface_step: usize,
}

impl DatasetConfig {
    /// The paper's protocol on a segmentation: 1000 samples, 100 probes, SVK, Poisson 0.49.
    pub fn paper(fixed: FixedRegion) -> Self {
        Self {
            samples: 1000,
            seed: 0,
            shard_size: 50,
            grid: GridSettings::default(),
            material: MaterialParams::default(),
            // A sample that needs many load cuts is rejected early rather than ground through.
            solver: SolverSettings { max_iterations: 20, max_halvings: 3, ..SolverSettings::default() },
            forces: ForceSettings::default(),
            visibility: VisibilitySettings::default(),
            fixed,
            surface_step: 2,
        }
    }
    pub fn shard_count(&self) -> usize {
        self.samples.div_ceil(self.shard_size.max(1))
    }
    pub fn shard_range(&self, shard: usize) -> std::ops::Range<usize> {
        let s = self.shard_size.max(1);
        (shard * s)..((shard + 1) * s).min(self.samples)
    }
    pub fn hash(&self) -> String {
        fnv_hex(serde_json::to_string(self).unwrap_or_default().as_bytes())
    }
}

#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("{path}: {reason}")]
    Invalid { path: PathBuf, reason: String },
    #[error("{path}: cannot read or write: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error(transparent)]
    Npz(#[from] NpzError),
    #[error(transparent)]
    Grid(#[from] GridError),
    #[error("cancelled")]
    Cancelled,
}

fn invalid(path: &Path, reason: impl Into<String>) -> DatasetError {
    DatasetError::Invalid { path: path.into(), reason: reason.into() }
}

/// FNV-1a 64-bit, hex: a cheap content hash for change and corruption detection.
pub fn fnv_hex(bytes: &[u8]) -> String {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    format!("{h:016x}")
}

pub fn segmentation_hash(seg: &Segmentation) -> String {
    let mut bytes = Vec::with_capacity(seg.volume.data.len() * 4 + 256);
    for v in &seg.volume.data {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    for v in seg.volume.world_from_voxel.iter() {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    bytes.extend(format!("{:?}{:?}{:?}", seg.volume.dims, seg.organ_labels, seg.structure_labels).bytes());
    fnv_hex(&bytes)
}

/// Everything shared by the samples of a dataset.
#[derive(Debug)]
pub struct DatasetContext {
    pub grid: ImmersedGrid,
    pub surface: TriMesh,
    pub visible: VisibleSurface,
    /// Grid nodes whose displacement the camera observes (u_s is non-zero there).
    pub visible_nodes: Vec<usize>,
    pub fixed: Vec<bool>,
    pub grid_npz: Vec<u8>,
    pub segmentation_hash: String,
}

impl DatasetContext {
    pub fn prepare(seg: &Segmentation, config: &DatasetConfig, cancel: &Cancel) -> Result<Self, DatasetError> {
        let seg_path = seg.source.clone();
        if config.samples == 0 || config.shard_size == 0 {
            return Err(invalid(&seg_path, "samples and shard size must be positive"));
        }
        config.material.validate().map_err(|r| invalid(&seg_path, r))?;
        let mask = seg.organ_mask();
        let grid = ImmersedGrid::from_mask(&mask, &config.grid, &Progress::none(), cancel)?;
        let surface = extract_surface(&mask, &SurfaceSettings { step: config.surface_step.max(1), ..Default::default() });
        let visible = visible_surface(&surface, &config.visibility).map_err(|r| invalid(&seg_path, r))?;
        if visible.visible_area_mm2 <= 0.0 {
            return Err(invalid(&seg_path, "the camera sees none of the organ surface"));
        }
        let mut is_visible = vec![false; grid.node_count()];
        for (t, tri) in surface.triangles.iter().enumerate() {
            if !visible.visible[t] {
                continue;
            }
            let c = tri.iter().map(|&i| surface.positions[i as usize]).sum::<Vector3<f64>>() / 3.0;
            for p in tri.iter().map(|&i| surface.positions[i as usize]).chain([c]) {
                if let Some(e) = grid.embed(&p) {
                    for (n, w) in e.nodes.iter().zip(e.weights) {
                        if w > 1e-9 {
                            is_visible[*n as usize] = true;
                        }
                    }
                }
            }
        }
        let visible_nodes: Vec<usize> = (0..grid.node_count()).filter(|&n| is_visible[n]).collect();
        let mut bc = BoundaryConditions::new(grid.node_count());
        let label_mask = match &config.fixed {
            FixedRegion::Label { label, .. } => Some(seg.volume.mask(&[*label])),
            _ => None,
        };
        bc.fix_region(&grid, &config.fixed, label_mask.as_ref()).map_err(|r| invalid(&seg_path, r))?;
        if bc.fixed_count() == 0 {
            return Err(invalid(&seg_path, format!("the fixed region {:?} holds no grid node", config.fixed)));
        }
        let mut grid_arrays = grid.to_npz_arrays();
        let [x, y, z] = grid.padded_shape();
        let mut vmask = vec![0u8; x * y * z];
        let mut omask = vec![0u8; x * y * z];
        for n in 0..grid.node_count() {
            omask[grid.dense_index(n)] = 1;
        }
        for &n in &visible_nodes {
            vmask[grid.dense_index(n)] = 1;
        }
        grid_arrays.push(("visible_nodes", Array::i64(vec![visible_nodes.len()], visible_nodes.iter().map(|&v| v as i64).collect())));
        grid_arrays.push(("visible_mask", Array::new(vec![x, y, z], ArrayData::U8(vmask))));
        grid_arrays.push(("node_mask", Array::new(vec![x, y, z], ArrayData::U8(omask))));
        let fixed_list: Vec<i64> = (0..grid.node_count()).filter(|&n| bc.fixed[n]).map(|n| n as i64).collect();
        grid_arrays.push(("fixed_nodes", Array::i64(vec![fixed_list.len()], fixed_list)));
        grid_arrays.push((
            "surface_vertices",
            Array::f32(
                vec![surface.positions.len(), 3],
                surface.positions.iter().flat_map(|p| [p.x as f32, p.y as f32, p.z as f32]).collect(),
            ),
        ));
        grid_arrays.push((
            "surface_triangles",
            Array::i64(vec![surface.triangles.len(), 3], surface.triangles.iter().flat_map(|t| t.map(|v| v as i64)).collect()),
        ));
        grid_arrays.push((
            "surface_visible",
            Array::new(vec![surface.triangles.len()], ArrayData::U8(visible.visible.iter().map(|&v| v as u8).collect())),
        ));
        let grid_npz = encode_npz_with(&grid_arrays, true).map_err(|e| DatasetError::Io { path: "grid.npz".into(), source: e })?;
        Ok(Self { grid, surface, visible, visible_nodes, fixed: bc.fixed, grid_npz, segmentation_hash: segmentation_hash(seg) })
    }

    pub fn grid_hash(&self) -> String {
        fnv_hex(&self.grid_npz)
    }

    /// Probes and forces of sample `index`: a function of (seed, index) only.
    pub fn sample_forces(&self, config: &DatasetConfig, index: usize) -> Vec<PointForce> {
        let mut rng = SplitMix64(config.seed ^ (index as u64).wrapping_mul(0xD1B5_4A32_D192_ED03));
        rng.next_u64();
        let pts = sample_points(&self.surface, &self.visible.visible, config.forces.probes, &mut rng);
        loads::random_forces(&pts, loads::organ_size_mm(&self.grid), &config.material, &config.forces, &mut rng)
    }
}

/// Why a sample was rejected.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Rejection {
    NotConverged = 1,
    Inverted = 2,
    Failed = 3,
}

#[derive(Clone, Debug)]
pub struct SampleResult {
    pub index: usize,
    pub forces: Vec<PointForce>,
    pub displacement_mm: Option<Vec<Vector3<f64>>>,
    pub rejection: Option<(Rejection, String)>,
    pub newton_iterations: usize,
    pub solve_ms: f64,
}

impl SampleResult {
    fn max_mean(&self) -> (f64, f64) {
        match &self.displacement_mm {
            Some(u) => {
                let max = u.iter().map(|v| v.norm()).fold(0.0, f64::max);
                (max, u.iter().map(|v| v.norm()).sum::<f64>() / u.len().max(1) as f64)
            }
            None => (0.0, 0.0),
        }
    }
}

/// Solve one sample with a solver built for the context's fixed nodes.
pub fn generate_sample(
    ctx: &DatasetContext,
    solver: &mut FeSolver,
    config: &DatasetConfig,
    index: usize,
    cancel: &Cancel,
) -> Result<SampleResult, DatasetError> {
    let forces = ctx.sample_forces(config, index);
    let mut bc = BoundaryConditions::new(ctx.grid.node_count());
    bc.fixed = ctx.fixed.clone();
    let t = Instant::now();
    let applied = loads::apply_forces(&ctx.grid, &mut bc, &forces);
    let out = applied.map_err(|e| (Rejection::Failed, e)).and_then(|_| {
        solver.solve(&bc, SolveMethod::Newton, &Progress::none(), cancel).map_err(|e| match e {
            FemError::NotConverged { reason, .. } if reason.contains("invert") => (Rejection::Inverted, reason),
            FemError::NotConverged { reason, .. } => (Rejection::NotConverged, reason),
            other => (Rejection::Failed, other.to_string()),
        })
    });
    if cancel.is_cancelled() {
        return Err(DatasetError::Cancelled);
    }
    let solve_ms = t.elapsed().as_secs_f64() * 1e3;
    Ok(match out {
        Ok(sol) => SampleResult {
            index,
            forces,
            newton_iterations: sol.iterations,
            displacement_mm: Some(sol.displacement_mm),
            rejection: None,
            solve_ms,
        },
        Err(r) => SampleResult { index, forces, displacement_mm: None, rejection: Some(r), newton_iterations: 0, solve_ms },
    })
}

/// Per-sample record of the manifest.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SampleRecord {
    pub index: usize,
    pub accepted: bool,
    pub rejection: Option<Rejection>,
    pub reason: Option<String>,
    pub max_displacement_mm: f64,
    pub mean_displacement_mm: f64,
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
        let m: Manifest = serde_json::from_str(&text).map_err(|e| invalid(&path, format!("not a umesh dataset manifest: {e}")))?;
        if m.format != FORMAT || m.format_version != FORMAT_VERSION {
            return Err(invalid(&path, format!("format {} v{} is not {FORMAT} v{FORMAT_VERSION}", m.format, m.format_version)));
        }
        Ok(m)
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
fn encode_shard(ctx: &DatasetContext, config: &DatasetConfig, results: &[SampleResult]) -> std::io::Result<Vec<u8>> {
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
    let stats: Vec<(f64, f64)> = results.iter().map(SampleResult::max_mean).collect();
    let arrays = vec![
        ("sample_index", Array::i64(vec![n], results.iter().map(|r| r.index as i64).collect())),
        ("accepted", Array::new(vec![n], ArrayData::U8(results.iter().map(|r| r.rejection.is_none() as u8).collect()))),
        (
            "rejection",
            Array::new(vec![n], ArrayData::U8(results.iter().map(|r| r.rejection.as_ref().map(|x| x.0 as u8).unwrap_or(0)).collect())),
        ),
        ("max_displacement_mm", Array::f32(vec![n], stats.iter().map(|s| s.0 as f32).collect())),
        ("mean_displacement_mm", Array::f32(vec![n], stats.iter().map(|s| s.1 as f32).collect())),
        ("newton_iterations", Array::new(vec![n], ArrayData::I32(results.iter().map(|r| r.newton_iterations as i32).collect()))),
        ("index", Array::i64(vec![a], accepted.iter().map(|r| r.index as i64).collect())),
        ("u_s", Array::f32(vec![a, 3, x, y, z], u_s)),
        ("u_v", Array::f32(vec![a, 3, x, y, z], u_v)),
        ("probes_mm", Array::f32(vec![a, p, 3], probes)),
        ("forces_n", Array::f32(vec![a, p, 3], forces)),
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
    let a = acc.iter().filter(|&&v| v == 1.0).count();
    let [x, y, z] = padded;
    npz.f64_with_shape("u_v", &[Some(a), Some(3), Some(x), Some(y), Some(z)])?;
    npz.f64_with_shape("u_s", &[Some(a), Some(3), Some(x), Some(y), Some(z)])?;
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
            newton_iterations: it[k] as usize,
            solve_ms: None,
            shard: file.clone(),
            flagged: false,
        })
        .collect();
    Ok((records, a))
}

/// Which shard files a run computes: all, or those with `j % count == k`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ShardSelection {
    pub k: usize,
    pub count: usize,
}

impl ShardSelection {
    pub fn all() -> Self {
        Self { k: 0, count: 1 }
    }
    pub fn parse(s: &str) -> Option<Self> {
        let (a, b) = s.split_once('/')?;
        let (k, count) = (a.trim().parse().ok()?, b.trim().parse().ok()?);
        (count > 0 && k < count).then_some(Self { k, count })
    }
    pub fn includes(&self, shard: usize) -> bool {
        shard % self.count == self.k
    }
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct GenerateReport {
    pub out: PathBuf,
    pub samples_total: usize,
    pub samples_computed: usize,
    pub samples_reused: usize,
    pub accepted: usize,
    pub rejected: BTreeMap<String, usize>,
    pub shards_written: usize,
    pub seconds: f64,
    pub samples_per_minute: f64,
    pub complete: bool,
}

fn base_manifest(seg: &Segmentation, config: &DatasetConfig, ctx: &DatasetContext) -> Manifest {
    Manifest {
        format: FORMAT.into(),
        format_version: FORMAT_VERSION,
        program_version: env!("CARGO_PKG_VERSION").into(),
        config: config.clone(),
        config_hash: config.hash(),
        grid_hash: ctx.grid_hash(),
        segmentation: seg.source.display().to_string(),
        segmentation_hash: ctx.segmentation_hash.clone(),
        padded_shape: ctx.grid.padded_shape(),
        nodes: ctx.grid.node_count(),
        visible_nodes: ctx.visible_nodes.len(),
        shards: Vec::new(),
        samples: Vec::new(),
        complete: false,
    }
}

fn finalize(m: &mut Manifest) {
    m.shards.sort_by_key(|s| s.first);
    m.shards.dedup_by_key(|s| s.first);
    m.samples.sort_by_key(|s| s.index);
    m.samples.dedup_by_key(|s| s.index);
    m.complete = m.shards.len() == m.config.shard_count();
}

/// Generate (or resume) a dataset in `out`.
pub fn run_generate(
    seg: &Segmentation,
    out: &Path,
    config: &DatasetConfig,
    selection: ShardSelection,
    progress: &Progress,
    cancel: &Cancel,
) -> Result<GenerateReport, DatasetError> {
    let start = Instant::now();
    std::fs::create_dir_all(out).map_err(|source| DatasetError::Io { path: out.into(), source })?;
    // Temporary files of an interrupted run are never data.
    if let Ok(entries) = std::fs::read_dir(out) {
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            if name.starts_with('.') && name.ends_with(".tmp") {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
    let ctx = DatasetContext::prepare(seg, config, cancel)?;
    let mut manifest = base_manifest(seg, config, &ctx);
    if out.join("manifest.json").exists() {
        let old = Manifest::read(out)?;
        if old.config_hash != manifest.config_hash
            || old.grid_hash != manifest.grid_hash
            || old.segmentation_hash != manifest.segmentation_hash
        {
            return Err(invalid(out, "holds a dataset made with another configuration or segmentation; choose an empty folder"));
        }
        // Keep what the old manifest knows (timings, reasons) for shards still on disk.
        manifest.samples = old.samples;
    }
    let grid_path = out.join("grid.npz");
    crate::write_atomic(&grid_path, &ctx.grid_npz).map_err(|source| DatasetError::Io { path: grid_path.clone(), source })?;

    // Shards already on disk and sound are adopted; the rest are computed.
    let padded = ctx.grid.padded_shape();
    let mut todo: Vec<usize> = Vec::new();
    let known: BTreeMap<usize, SampleRecord> = manifest.samples.drain(..).map(|s| (s.index, s)).collect();
    let mut reused = 0;
    for shard in 0..config.shard_count() {
        let path = out.join(shard_file_name(shard));
        if path.exists()
            && let Ok((records, accepted)) = read_shard_records(&path, config, shard, padded)
        {
            let bytes = std::fs::read(&path).map_err(|source| DatasetError::Io { path: path.clone(), source })?;
            let range = config.shard_range(shard);
            manifest.shards.push(ShardRecord {
                file: shard_file_name(shard),
                first: range.start,
                count: range.len(),
                accepted,
                hash: fnv_hex(&bytes),
            });
            for r in records {
                let kept = known.get(&r.index).filter(|k| k.shard == r.shard).cloned();
                manifest.samples.push(kept.unwrap_or(r));
            }
            if selection.includes(shard) {
                reused += range.len();
            }
            continue;
        }
        if selection.includes(shard) {
            todo.push(shard);
        }
    }
    finalize(&mut manifest);
    manifest.write(out)?;

    let total: usize = todo.iter().map(|&s| config.shard_range(s).len()).sum();
    let queue: Vec<usize> = todo.iter().flat_map(|&s| config.shard_range(s)).collect();
    let next = std::sync::atomic::AtomicUsize::new(0);
    let done = std::sync::atomic::AtomicUsize::new(0);
    let pending: Mutex<BTreeMap<usize, Vec<SampleResult>>> = Mutex::new(BTreeMap::new());
    let manifest = Mutex::new(manifest);
    let first_error: Mutex<Option<DatasetError>> = Mutex::new(None);
    let shards_written = std::sync::atomic::AtomicUsize::new(0);
    // Parallel over samples; each solve single-threaded so results do not depend on scheduling.
    let previous_par = faer::get_global_parallelism();
    faer::set_global_parallelism(faer::Par::Seq);
    let threads = rayon::current_num_threads().max(1).min(queue.len().max(1));
    std::thread::scope(|scope| {
        for _ in 0..threads {
            scope.spawn(|| {
                let mut solver = match FeSolver::new(&ctx.grid, config.material, &ctx.fixed, config.solver.clone()) {
                    Ok(s) => s,
                    Err(e) => {
                        record_error(&first_error, invalid(out, e.to_string()));
                        cancel.cancel();
                        return;
                    }
                };
                loop {
                    let q = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    if q >= queue.len() || cancel.is_cancelled() {
                        break;
                    }
                    let index = queue[q];
                    let result = match generate_sample(&ctx, &mut solver, config, index, cancel) {
                        Ok(r) => r,
                        Err(e) => {
                            if !matches!(e, DatasetError::Cancelled) {
                                record_error(&first_error, e);
                            }
                            cancel.cancel();
                            break;
                        }
                    };
                    let shard = index / config.shard_size;
                    let complete = {
                        let Ok(mut p) = pending.lock() else { break };
                        let v = p.entry(shard).or_default();
                        v.push(result);
                        if v.len() == config.shard_range(shard).len() { p.remove(&shard) } else { None }
                    };
                    if let Some(mut results) = complete {
                        results.sort_by_key(|r| r.index);
                        if let Err(e) = write_shard(out, &ctx, config, shard, &results, &manifest) {
                            record_error(&first_error, e);
                            cancel.cancel();
                            break;
                        }
                        shards_written.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    }
                    let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
                    progress.report(d as u64, total as u64, "samples");
                }
            });
        }
    });
    faer::set_global_parallelism(previous_par);
    if let Ok(Some(e)) = first_error.into_inner() {
        return Err(e);
    }
    if cancel.is_cancelled() {
        return Err(DatasetError::Cancelled);
    }
    let manifest = manifest.into_inner().map_err(|_| invalid(out, "a worker panicked"))?;
    let secs = start.elapsed().as_secs_f64();
    let mut rejected = BTreeMap::new();
    for s in manifest.samples.iter().filter(|s| !s.accepted) {
        *rejected.entry(format!("{:?}", s.rejection.unwrap_or(Rejection::Failed)).to_lowercase()).or_insert(0) += 1;
    }
    let computed = done.into_inner();
    Ok(GenerateReport {
        out: out.into(),
        samples_total: config.samples,
        samples_computed: computed,
        samples_reused: reused,
        accepted: manifest.accepted().count(),
        rejected,
        shards_written: shards_written.into_inner(),
        seconds: secs,
        samples_per_minute: if secs > 0.0 { computed as f64 * 60.0 / secs } else { 0.0 },
        complete: manifest.complete,
    })
}

fn record_error(slot: &Mutex<Option<DatasetError>>, e: DatasetError) {
    if let Ok(mut g) = slot.lock()
        && g.is_none()
    {
        *g = Some(e);
    }
}

fn write_shard(
    out: &Path,
    ctx: &DatasetContext,
    config: &DatasetConfig,
    shard: usize,
    results: &[SampleResult],
    manifest: &Mutex<Manifest>,
) -> Result<(), DatasetError> {
    let file = shard_file_name(shard);
    let path = out.join(&file);
    let bytes = encode_shard(ctx, config, results).map_err(|source| DatasetError::Io { path: path.clone(), source })?;
    crate::write_atomic(&path, &bytes).map_err(|source| DatasetError::Io { path: path.clone(), source })?;
    let mut m = manifest.lock().map_err(|_| invalid(out, "manifest lock poisoned"))?;
    let range = config.shard_range(shard);
    m.shards.push(ShardRecord {
        file: file.clone(),
        first: range.start,
        count: range.len(),
        accepted: results.iter().filter(|r| r.rejection.is_none()).count(),
        hash: fnv_hex(&bytes),
    });
    for r in results {
        let (max, mean) = r.max_mean();
        m.samples.push(SampleRecord {
            index: r.index,
            accepted: r.rejection.is_none(),
            rejection: r.rejection.as_ref().map(|x| x.0),
            reason: r.rejection.as_ref().map(|x| x.1.clone()),
            max_displacement_mm: max,
            mean_displacement_mm: mean,
            newton_iterations: r.newton_iterations,
            solve_ms: Some(r.solve_ms),
            shard: file.clone(),
            flagged: false,
        });
    }
    finalize(&mut m);
    m.write(out)
}

/// A dataset opened for reading, its shards checked against the manifest's hashes.
#[derive(Debug)]
pub struct Dataset {
    pub dir: PathBuf,
    pub manifest: Manifest,
}

impl Dataset {
    pub fn open(dir: &Path) -> Result<Self, DatasetError> {
        let manifest = Manifest::read(dir)?;
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
}

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
    std::fs::create_dir_all(out).map_err(|source| DatasetError::Io { path: out.into(), source })?;
    let grid = std::fs::read(first.join("grid.npz")).map_err(|source| DatasetError::Io { path: first.join("grid.npz"), source })?;
    let mut merged = Manifest { shards: Vec::new(), samples: Vec::new(), ..m0.clone() };
    let mut have = std::collections::BTreeSet::new();
    for dir in inputs {
        let m = Manifest::read(dir)?;
        if m.config_hash != m0.config_hash || m.grid_hash != m0.grid_hash || m.segmentation_hash != m0.segmentation_hash {
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
            let dst = out.join(&s.file);
            crate::write_atomic(&dst, &bytes).map_err(|source| DatasetError::Io { path: dst, source })?;
            merged.shards.push(s.clone());
            merged.samples.extend(m.samples.iter().filter(|r| r.shard == s.file).cloned());
        }
    }
    crate::write_atomic(&out.join("grid.npz"), &grid).map_err(|source| DatasetError::Io { path: out.join("grid.npz"), source })?;
    finalize(&mut merged);
    merged.write(out)?;
    Ok(MergeReport {
        out: out.into(),
        shards: merged.shards.len(),
        samples: merged.samples.len(),
        accepted: merged.accepted().count(),
        complete: merged.complete,
    })
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct Distribution {
    pub min: f64,
    pub p5: f64,
    pub median: f64,
    pub mean: f64,
    pub p95: f64,
    pub max: f64,
}

impl Distribution {
    pub fn of(mut v: Vec<f64>) -> Option<Self> {
        if v.is_empty() {
            return None;
        }
        v.sort_by(f64::total_cmp);
        let q = |f: f64| v[((v.len() - 1) as f64 * f).round() as usize];
        Some(Self {
            min: v[0],
            p5: q(0.05),
            median: q(0.5),
            mean: v.iter().sum::<f64>() / v.len() as f64,
            p95: q(0.95),
            max: v[v.len() - 1],
        })
    }
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct DatasetStats {
    pub samples: usize,
    pub accepted: usize,
    pub rejected: BTreeMap<String, usize>,
    pub flagged: usize,
    pub complete: bool,
    pub max_displacement_mm: Option<Distribution>,
    pub mean_displacement_mm: Option<Distribution>,
    pub newton_iterations: Option<Distribution>,
    pub solve_ms: Option<Distribution>,
    /// (index, why) of samples far from the rest.
    pub outliers: Vec<(usize, String)>,
}

pub fn run_stats(dir: &Path) -> Result<DatasetStats, DatasetError> {
    let ds = Dataset::open(dir)?;
    let m = &ds.manifest;
    let acc: Vec<&SampleRecord> = m.accepted().collect();
    let mut rejected = BTreeMap::new();
    for s in m.samples.iter().filter(|s| !s.accepted) {
        *rejected.entry(format!("{:?}", s.rejection.unwrap_or(Rejection::Failed)).to_lowercase()).or_insert(0) += 1;
    }
    let max_d = Distribution::of(acc.iter().map(|s| s.max_displacement_mm).collect());
    let its = Distribution::of(acc.iter().map(|s| s.newton_iterations as f64).collect());
    // Outliers: beyond median + 4 x (p95 - median) of the maximum displacement or iterations.
    let mut outliers = Vec::new();
    if let (Some(d), Some(i)) = (&max_d, &its) {
        for s in &acc {
            if s.max_displacement_mm > d.median + 4.0 * (d.p95 - d.median).max(1e-9) {
                outliers.push((s.index, format!("max displacement {:.1} mm (median {:.1})", s.max_displacement_mm, d.median)));
            }
            if s.newton_iterations as f64 > i.median + 4.0 * (i.p95 - i.median).max(1.0) {
                outliers.push((s.index, format!("{} Newton iterations (median {:.0})", s.newton_iterations, i.median)));
            }
        }
    }
    Ok(DatasetStats {
        samples: m.samples.len(),
        accepted: acc.len(),
        rejected,
        flagged: m.samples.iter().filter(|s| s.flagged).count(),
        complete: m.complete,
        max_displacement_mm: max_d,
        mean_displacement_mm: Distribution::of(acc.iter().map(|s| s.mean_displacement_mm).collect()),
        newton_iterations: its,
        solve_ms: Distribution::of(acc.iter().filter_map(|s| s.solve_ms).collect()),
        outliers,
    })
}
