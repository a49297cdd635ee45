//! Training data: random force probes on the visible surface, SVK solves, and sharded,
//! deterministic, resumable dataset folders.
//!
//! A dataset folder holds `manifest.json` (configuration, hashes, per-sample statistics),
//! `grid.npz` (the grid, the visible-surface nodes, the surface mesh) and `shard_NNNNNN.npz`
//! files, each covering `shard_size` consecutive sample indices. Sample i depends only on
//! (seed, i), so shards computed anywhere merge into exactly the single-run dataset.

use crate::fem::solver::{FeSolver, FemError, MeanSolve, SolveMethod, SolverSettings};
use crate::fem::{BoundaryConditions, FixedRegion, MaterialParams};
use crate::grid::{GridError, GridSettings, ImmersedGrid};
use crate::loads::{self, ForceSettings, LoadCalibration, LoadFamily, PointForce};
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

mod preflight;
pub use preflight::{Preflight, PreflightSettings, run_preflight};

pub const FORMAT: &str = "umesh-dataset";
/// 2: shards carry each sample's simulated camera view (`obs_points`, `obs_count`).
pub const FORMAT_VERSION: u32 = 2;
/// Each calibrated sample's SVK mean nodal displacement lands within this fraction of its target.
pub const CALIBRATION_TOLERANCE: f64 = 0.2;
/// The first load factor of the reference solves, relative to the forces whose *linear* mean
/// is the target: SVK is softer than linear elasticity at these strains.
const FIRST_LOAD_FACTOR: f64 = 0.8;
/// A camera that sees less of the organ than this cannot drive a registration.
pub const MIN_VISIBLE_FRACTION: f64 = 0.02;

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
    /// The simulated depth-camera view stored with each sample (configurations written
    /// before it get the defaults).
    #[serde(default)]
    pub view: crate::observation::ViewSettings,
    /// The material drawn per sample around `material` (absent: every sample is `material`;
    /// configurations made before read so, their hash unchanged).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub material_variation: Option<crate::fem::material::MaterialVariation>,
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
            // A sample that needs many load cuts is going to invert: it is rejected after a
            // budget of Newton iterations (about two plain solves) rather than ground through.
            solver: SolverSettings {
                max_iterations: 15,
                max_halvings: 3,
                max_total_iterations: Some(24),
                reject_indefinite: true,
                ..SolverSettings::default()
            },
            forces: ForceSettings::default(),
            visibility: VisibilitySettings::default(),
            fixed,
            surface_step: 2,
            view: Default::default(),
            material_variation: None,
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
    /// The pre-flight check projects too low an acceptance (the message names the likely cause).
    #[error("{message}")]
    Refused { message: String, preflight: Box<Preflight> },
    #[error("cancelled")]
    Cancelled,
}

/// Sets faer's process-wide parallelism to sequential while alive (each sample's solve runs
/// on one core, the samples in parallel, so results do not depend on scheduling).
struct SequentialFaer(faer::Par);

impl SequentialFaer {
    fn new() -> Self {
        let previous = faer::get_global_parallelism();
        faer::set_global_parallelism(faer::Par::Seq);
        Self(previous)
    }
}

impl Drop for SequentialFaer {
    fn drop(&mut self) {
        faer::set_global_parallelism(self.0);
    }
}

/// A pre-flight check before a long dataset job (see `preflight`).
pub struct PreflightCheck<'a> {
    pub settings: PreflightSettings,
    /// Run the job even when the check refuses it.
    pub force: bool,
    /// Called with the check's figures before the job goes on or is refused.
    pub report: &'a (dyn Fn(&Preflight) + Sync),
}

impl PreflightCheck<'_> {
    /// Report the check's figures, then refuse the job when it would store too little (unless forced).
    pub fn judge(&self, p: Preflight) -> Result<Preflight, DatasetError> {
        (self.report)(&p);
        match p.refusal(self.settings.min_acceptance) {
            Some(message) if !self.force => Err(DatasetError::Refused { message, preflight: Box::new(p) }),
            _ => Ok(p),
        }
    }
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
    /// The material the samples are solved with (registration's physics correction uses it).
    pub material: MaterialParams,
}

/// What a dataset's camera sees and which nodes its fixed region holds, checked as
/// generation checks them (camera outside the organ, enough of the surface seen, a fixed
/// region that holds some nodes but not all). The app previews exactly this.
pub struct ObservationSetup {
    pub visible: VisibleSurface,
    /// Grid nodes under the visible triangles (the network's observed nodes).
    pub visible_nodes: Vec<usize>,
    /// Per grid node: held fixed.
    pub fixed: Vec<bool>,
}

pub fn observation_setup(
    seg: &Segmentation,
    grid: &ImmersedGrid,
    surface: &TriMesh,
    visibility: &VisibilitySettings,
    fixed: &FixedRegion,
) -> Result<ObservationSetup, DatasetError> {
    let seg_path = seg.source.clone();
    let visible = visible_surface(surface, visibility).map_err(|r| invalid(&seg_path, r))?;
    let eye = nalgebra::Point3::from(Vector3::from(visible.camera.position_mm));
    if seg.organ_mask().world_sampler().inside(&eye) {
        return Err(invalid(&seg_path, format!("the camera at {:?} mm is inside the organ", visible.camera.position_mm)));
    }
    if visible.fraction() < MIN_VISIBLE_FRACTION {
        return Err(invalid(
            &seg_path,
            format!(
                "the camera at {:?} mm looking along {:?} sees {:.1} % of the organ surface (at least {:.0} % needed)",
                visible.camera.position_mm,
                visible.camera.direction,
                visible.fraction() * 100.0,
                MIN_VISIBLE_FRACTION * 100.0
            ),
        ));
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
    let label_mask = match fixed {
        FixedRegion::Label { label, .. } => Some(seg.volume.mask(&[*label])),
        _ => None,
    };
    bc.fix_region(grid, fixed, label_mask.as_ref()).map_err(|r| invalid(&seg_path, r))?;
    if bc.fixed_count() == 0 {
        return Err(invalid(&seg_path, format!("the fixed region {fixed:?} holds no grid node")));
    }
    if bc.fixed_count() == grid.node_count() {
        return Err(invalid(&seg_path, format!("the fixed region {fixed:?} holds every grid node: nothing can move")));
    }
    Ok(ObservationSetup { visible, visible_nodes, fixed: bc.fixed })
}

impl DatasetContext {
    pub fn prepare(seg: &Segmentation, config: &DatasetConfig, cancel: &Cancel) -> Result<Self, DatasetError> {
        let seg_path = seg.source.clone();
        if config.samples == 0 || config.shard_size == 0 {
            return Err(invalid(&seg_path, "samples and shard size must be positive"));
        }
        config.material.validate().map_err(|r| invalid(&seg_path, r))?;
        if let Some(v) = &config.material_variation {
            v.validate().map_err(|r| invalid(&seg_path, r))?;
        }
        config.forces.validate().map_err(|r| invalid(&seg_path, r))?;
        let mask = seg.organ_mask();
        let grid = ImmersedGrid::from_mask(&mask, &config.grid, &Progress::none(), cancel)?;
        let surface = extract_surface(&mask, &SurfaceSettings { step: config.surface_step.max(1), ..Default::default() });
        let ObservationSetup { visible, visible_nodes, fixed } =
            observation_setup(seg, &grid, &surface, &config.visibility, &config.fixed)?;
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
        let fixed_list: Vec<i64> = (0..grid.node_count()).filter(|&n| fixed[n]).map(|n| n as i64).collect();
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
        Ok(Self {
            grid,
            surface,
            visible,
            visible_nodes,
            fixed,
            grid_npz,
            segmentation_hash: segmentation_hash(seg),
            material: config.material,
        })
    }

    /// The probes' forces on the grid, each spread over its contact patch on the surface
    /// (`ForceSettings::patch_radius_mm`): the one load model of samples and recordings.
    pub fn apply_probes(&self, bc: &mut BoundaryConditions, config: &DatasetConfig, forces: &[PointForce]) -> Result<(), String> {
        self.apply_load(bc, config, forces, LoadFamily::Pressing)
    }

    /// The forces of a load family on the grid: contacts spread over the family's contact
    /// radius (`LoadFamily::contact_radius_mm`), body forces as they are.
    pub fn apply_load(
        &self,
        bc: &mut BoundaryConditions,
        config: &DatasetConfig,
        forces: &[PointForce],
        family: LoadFamily,
    ) -> Result<(), String> {
        match family.contact_radius_mm(config.forces.patch_radius_mm) {
            Some(r) => loads::apply_forces(&self.grid, bc, &loads::spread_forces(&self.surface, forces, r)),
            None => loads::apply_forces(&self.grid, bc, forces),
        }
    }

    /// Scale `forces` so that their linear mean displacement (over the nodes the configuration
    /// averages) is `target_mm`: the calibration of samples, for any load.
    pub fn calibrate_forces(
        &self,
        solver: &mut FeSolver,
        config: &DatasetConfig,
        forces: &mut [PointForce],
        target_mm: f64,
        family: LoadFamily,
    ) -> Result<(), String> {
        let mut bc = BoundaryConditions::new(self.grid.node_count());
        bc.fixed = self.fixed.clone();
        self.apply_load(&mut bc, config, forces, family)?;
        let lin = solver.solve(&bc, SolveMethod::Linear, &Progress::none(), &Cancel::new()).map_err(|e| e.to_string())?;
        loads::scale_forces(forces, config.forces.mean_over.mean_mm(&lin.displacement_mm, &self.fixed), target_mm)?;
        Ok(())
    }

    pub fn grid_hash(&self) -> String {
        fnv_hex(&self.grid_npz)
    }

    /// Probes and force pattern of sample `index`, and its target mean displacement (mm):
    /// a function of (seed, index) only.
    pub fn sample_forces(&self, config: &DatasetConfig, index: usize) -> (Vec<PointForce>, f64) {
        let mut rng = SplitMix64(config.seed ^ (index as u64).wrapping_mul(0xD1B5_4A32_D192_ED03));
        rng.next_u64();
        let family = self.sample_family(config, index);
        let pts = sample_points(&self.surface, &self.visible.visible, loads::family_points(family, &config.forces), &mut rng);
        let forces = loads::family_forces(family, &pts, &self.grid, &config.material, &config.forces, &mut rng);
        (forces, config.forces.sample_target_mm(&mut rng) * family.target_factor())
    }

    /// The material of sample `index`: the configuration's, or one drawn from
    /// `material_variation` with the sample's own random stream (a function of (seed, index)).
    pub fn sample_material(&self, config: &DatasetConfig, index: usize) -> MaterialParams {
        sample_material(config, index)
    }

    /// The load family of sample `index` (`ForceSettings::family_of`).
    pub fn sample_family(&self, config: &DatasetConfig, index: usize) -> LoadFamily {
        config.forces.family_of(config.seed, index)
    }

    /// The forces of sample `index` as they are solved: with `mean-displacement` calibration,
    /// the pattern scaled so that its linear (small-strain) mean nodal displacement is the
    /// sample's target times `load_scale` (one solve with the cached rest factor). Returns the
    /// forces and the target (mm; for `energy-scale`, the configured value).
    pub fn calibrated_forces(
        &self,
        solver: &mut FeSolver,
        config: &DatasetConfig,
        index: usize,
        load_scale: f64,
    ) -> Result<(Vec<PointForce>, f64), String> {
        let (mut forces, target) = self.sample_forces(config, index);
        if config.forces.calibration == LoadCalibration::EnergyScale {
            let _ = loads::scale_forces(&mut forces, 1.0, load_scale);
            return Ok((forces, config.forces.target_displacement_mm * load_scale));
        }
        self.calibrate_forces(solver, config, &mut forces, target * load_scale, self.sample_family(config, index))?;
        Ok((forces, target * load_scale))
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
    /// The mean nodal displacement the forces were calibrated for (mm).
    pub target_mm: f64,
    pub displacement_mm: Option<Vec<Vector3<f64>>>,
    /// The simulated camera view of the deformed organ (accepted samples).
    pub observed_mm: Vec<[f32; 3]>,
    pub rejection: Option<(Rejection, String)>,
    pub newton_iterations: usize,
    pub solve_ms: f64,
}

impl SampleResult {
    /// Maximum and mean displacement norm (mm); the mean over the nodes the calibration uses.
    fn max_mean(&self, ctx: &DatasetContext, config: &DatasetConfig) -> (f64, f64) {
        match &self.displacement_mm {
            Some(u) => {
                let max = u.iter().map(|v| v.norm()).fold(0.0, f64::max);
                (max, config.forces.mean_over.mean_mm(u, &ctx.fixed))
            }
            None => (0.0, 0.0),
        }
    }
}

/// A sample's forces as solved, its target, and the outcome.
#[derive(Clone, Debug)]
pub struct SolvedLoad {
    pub forces: Vec<PointForce>,
    pub target_mm: f64,
    /// The factor applied to the linearly calibrated forces (1 for `energy-scale`).
    pub load_factor: f64,
    pub solution: Result<crate::fem::solver::Solution, (Rejection, String)>,
}

impl DatasetContext {
    /// Solve the load of sample `index` (scaled by `load_scale`) on the SVK model. With
    /// `mean-displacement` calibration the forces are first scaled so that the linear mean
    /// nodal displacement is the target, then the load factor that gives the target on the
    /// hyperelastic model (within `CALIBRATION_TOLERANCE`) is found by continuation from
    /// `first_lambda`: the two responses differ (SVK softens under the probes' compression,
    /// by a factor 1.1 on a real liver and up to 3 on the phantom).
    pub fn solve_sample(
        &self,
        solver: &mut FeSolver,
        config: &DatasetConfig,
        index: usize,
        load_scale: f64,
        first_lambda: f64,
        cancel: &Cancel,
    ) -> SolvedLoad {
        if let Err(e) = solver.set_material(self.sample_material(config, index)) {
            let (forces, target_mm) = self.sample_forces(config, index);
            return SolvedLoad { forces, target_mm, load_factor: 1.0, solution: Err((Rejection::Failed, e.to_string())) };
        }
        let (forces, target_mm) = match self.calibrated_forces(solver, config, index, load_scale) {
            Ok(x) => x,
            Err(e) => {
                let (forces, _) = self.sample_forces(config, index);
                let target_mm = config.forces.target_displacement_mm * load_scale;
                let solution = Err((Rejection::Failed, format!("load calibration: {e}")));
                return SolvedLoad { forces, target_mm, load_factor: 1.0, solution };
            }
        };
        self.solve_calibrated(solver, config, forces, target_mm, self.sample_family(config, index), first_lambda, cancel)
    }

    /// Solve calibrated forces (`calibrate_forces`) on the SVK model: the load factor that
    /// gives `target_mm` found by continuation from `first_lambda`; the forces applied as
    /// `family`'s (`apply_load`).
    #[allow(clippy::too_many_arguments)]
    pub fn solve_calibrated(
        &self,
        solver: &mut FeSolver,
        config: &DatasetConfig,
        mut forces: Vec<PointForce>,
        target_mm: f64,
        family: LoadFamily,
        first_lambda: f64,
        cancel: &Cancel,
    ) -> SolvedLoad {
        let classify = |e: FemError| match e {
            FemError::NotConverged { reason, .. } if reason.contains("invert") => (Rejection::Inverted, reason),
            FemError::NotConverged { reason, .. } => (Rejection::NotConverged, reason),
            other => (Rejection::Failed, other.to_string()),
        };
        let mut bc = BoundaryConditions::new(self.grid.node_count());
        bc.fixed = self.fixed.clone();
        if let Err(e) = self.apply_load(&mut bc, config, &forces, family) {
            return SolvedLoad { forces, target_mm, load_factor: 1.0, solution: Err((Rejection::Failed, e)) };
        }
        if config.forces.calibration == LoadCalibration::EnergyScale {
            let solution = solver.solve(&bc, SolveMethod::Newton, &Progress::none(), cancel).map_err(classify);
            return SolvedLoad { forces, target_mm, load_factor: 1.0, solution };
        }
        let over = config.forces.mean_over;
        match solver.solve_to_mean_displacement(&bc, target_mm, CALIBRATION_TOLERANCE, first_lambda, over, cancel) {
            // A state kept below an unreachable target shows in the manifest as achieved / target.
            Ok(MeanSolve { solution, lambda, .. }) => {
                let _ = loads::scale_forces(&mut forces, 1.0, lambda);
                SolvedLoad { forces, target_mm, load_factor: lambda, solution: Ok(solution) }
            }
            Err(e) => SolvedLoad { forces, target_mm, load_factor: first_lambda, solution: Err(classify(e)) },
        }
    }

    /// `solve_sample` with the first load factor from the collapse scale `softening_mm`.
    pub fn solve_sample_softening(
        &self,
        solver: &mut FeSolver,
        config: &DatasetConfig,
        index: usize,
        load_scale: f64,
        softening_mm: f64,
        cancel: &Cancel,
    ) -> SolvedLoad {
        let target = self.sample_forces(config, index).1 * load_scale;
        self.solve_sample(solver, config, index, load_scale, first_load_factor(target, softening_mm), cancel)
    }

    /// How much softer than linear the organ responds at the dataset's target: the collapse
    /// scale D (mm) of `fem::solver::softening_factor`, the lower quartile over eight reference
    /// patterns (not samples of the dataset). Each sample's first load factor is then
    /// 1 / (1 + target / D), so that most land within the tolerance at the first solve.
    /// Infinite for `energy-scale` or a response no softer than linear.
    pub fn reference_softening_mm(&self, config: &DatasetConfig, cancel: &Cancel) -> Result<f64, DatasetError> {
        if config.forces.calibration == LoadCalibration::EnergyScale {
            return Ok(f64::INFINITY);
        }
        use rayon::prelude::*;
        let settings = SolverSettings { max_total_iterations: Some(80), max_halvings: 8, ..config.solver.clone() };
        let mut reference = config.clone();
        reference.forces.target_spread = 0.0;
        // Patterns differ a lot in how much they soften (on the phantom D spans 4-15 mm), so
        // the median needs several; they run in parallel, each solve single-threaded.
        let results: Vec<Result<Option<f64>, String>> = (0..REFERENCE_PATTERNS)
            .into_par_iter()
            .map(|k| {
                let mut solver = FeSolver::new(&self.grid, config.material, &self.fixed, settings.clone()).map_err(|e| e.to_string())?;
                let r = self.solve_sample(&mut solver, &reference, REFERENCE_INDEX + k, 1.0, FIRST_LOAD_FACTOR, cancel);
                let mean = |sol: &crate::fem::solver::Solution| config.forces.mean_over.mean_mm(&sol.displacement_mm, &self.fixed);
                Ok(r.solution.ok().map(|sol| crate::fem::solver::softening_scale_mm(r.target_mm, r.load_factor, mean(&sol))))
            })
            .collect();
        if cancel.is_cancelled() {
            return Err(DatasetError::Cancelled);
        }
        let mut scales = Vec::new();
        for r in results {
            if let Some(d) = r.map_err(|e| invalid(Path::new("."), e))? {
                scales.push(d);
            }
        }
        scales.sort_by(f64::total_cmp);
        // The lower quartile, not the median: a first probe that overshoots heads for a
        // collapsed state and is abandoned, one that undershoots costs a cheap second probe.
        // No reference converged: assume strong softening (the continuation corrects it).
        Ok(scales.get(scales.len() / 4).copied().unwrap_or(config.forces.target_displacement_mm))
    }
}

/// The first load factor for a target under a collapse scale D (see `reference_softening_mm`).
pub fn first_load_factor(target_mm: f64, softening_mm: f64) -> f64 {
    if softening_mm.is_finite() && softening_mm > 0.0 { 1.0 / (1.0 + target_mm / softening_mm) } else { 1.0 }
}

/// Sample indices of the reference patterns (far beyond any dataset's samples).
const REFERENCE_INDEX: usize = 1 << 40;
/// How many reference patterns set the collapse scale.
const REFERENCE_PATTERNS: usize = 8;

/// Solve one sample with a solver built for the context's fixed nodes; `softening_mm` from
/// `DatasetContext::reference_softening_mm`.
pub fn generate_sample(
    ctx: &DatasetContext,
    solver: &mut FeSolver,
    config: &DatasetConfig,
    index: usize,
    softening_mm: f64,
    cancel: &Cancel,
) -> Result<SampleResult, DatasetError> {
    let t = Instant::now();
    let r = ctx.solve_sample_softening(solver, config, index, 1.0, softening_mm, cancel);
    if cancel.is_cancelled() {
        return Err(DatasetError::Cancelled);
    }
    let (forces, target_mm) = (r.forces, r.target_mm);
    // What the camera sees of this deformation: decided on the deformed shape, with its own
    // random stream so that the loads do not depend on the view settings.
    let solution = r.solution.and_then(|sol| {
        let deformed = loads::deform_mesh(&ctx.grid, &ctx.surface, &sol.displacement_mm);
        let mut rng = SplitMix64(config.seed ^ (index as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0x0B5E_4F1E_77E0_0001);
        match crate::observation::simulated_view(&deformed, &ctx.visible.camera, &config.view, &mut rng) {
            Ok(v) if v.len() >= 10 => Ok((sol, v)),
            Ok(v) => Err((Rejection::Failed, format!("the simulated camera view holds {} points", v.len()))),
            Err(e) => Err((Rejection::Failed, format!("simulated camera view: {e}"))),
        }
    });
    let solve_ms = t.elapsed().as_secs_f64() * 1e3;
    Ok(match solution {
        Ok((sol, view)) => SampleResult {
            index,
            forces,
            target_mm,
            newton_iterations: sol.iterations,
            displacement_mm: Some(sol.displacement_mm),
            observed_mm: view.iter().map(|p| [p.x as f32, p.y as f32, p.z as f32]).collect(),
            rejection: None,
            solve_ms,
        },
        Err(r) => SampleResult {
            index,
            forces,
            target_mm,
            displacement_mm: None,
            observed_mm: Vec::new(),
            rejection: Some(r),
            newton_iterations: 0,
            solve_ms,
        },
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
    /// The mean displacement the sample's forces were calibrated for (mm).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target_displacement_mm: Option<f64>,
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
        let m: Manifest = serde_json::from_str(&text).map_err(|e| invalid(&path, format!("not a umesh dataset manifest: {e}")))?;
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

/// A sample's family as the manifest records it: None for pressing-only datasets (as before
/// families existed).
/// See `DatasetContext::sample_material`.
pub fn sample_material(config: &DatasetConfig, index: usize) -> MaterialParams {
    match &config.material_variation {
        None => config.material,
        Some(v) => {
            let mut rng = SplitMix64(config.seed ^ 0x3A7E_41A1_0000_0001 ^ (index as u64).wrapping_mul(0xBF58_476D_1CE4_E5B9));
            let (a, b) = (rng.next_f64(), rng.next_f64());
            v.draw(config.material, a, b)
        }
    }
}

fn recorded_material(config: &DatasetConfig, index: usize) -> Option<MaterialParams> {
    config.material_variation.is_some().then(|| sample_material(config, index))
}

fn recorded_family(config: &DatasetConfig, index: usize) -> Option<LoadFamily> {
    config.forces.mixes_families().then(|| config.forces.family_of(config.seed, index))
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
    let stats: Vec<(f64, f64)> = results.iter().map(|r| r.max_mean(ctx, config)).collect();
    let arrays = vec![
        ("sample_index", Array::i64(vec![n], results.iter().map(|r| r.index as i64).collect())),
        ("accepted", Array::new(vec![n], ArrayData::U8(results.iter().map(|r| r.rejection.is_none() as u8).collect()))),
        (
            "rejection",
            Array::new(vec![n], ArrayData::U8(results.iter().map(|r| r.rejection.as_ref().map(|x| x.0 as u8).unwrap_or(0)).collect())),
        ),
        ("max_displacement_mm", Array::f32(vec![n], stats.iter().map(|s| s.0 as f32).collect())),
        ("mean_displacement_mm", Array::f32(vec![n], stats.iter().map(|s| s.1 as f32).collect())),
        ("target_displacement_mm", Array::f32(vec![n], results.iter().map(|r| r.target_mm as f32).collect())),
        ("newton_iterations", Array::new(vec![n], ArrayData::I32(results.iter().map(|r| r.newton_iterations as i32).collect()))),
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
    /// The pre-flight check, when one ran (a fresh job with more samples than the check).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub preflight: Option<Preflight>,
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
    run_generate_checked(seg, out, config, selection, None, progress, cancel)
}

/// `run_generate` with a pre-flight check: a fresh job with more samples than the check first
/// solves a few of its samples in parallel and, when their acceptance is below the check's
/// threshold, stops with `DatasetError::Refused` before anything is written (unless forced).
pub fn run_generate_checked(
    seg: &Segmentation,
    out: &Path,
    config: &DatasetConfig,
    selection: ShardSelection,
    preflight: Option<&PreflightCheck>,
    progress: &Progress,
    cancel: &Cancel,
) -> Result<GenerateReport, DatasetError> {
    let start = Instant::now();
    let ctx = DatasetContext::prepare(seg, config, cancel)?;
    let fresh = !out.join("manifest.json").exists();
    let _seq = SequentialFaer::new();
    // Each reference solve single-threaded like the samples, so every machine finds the same factor.
    progress.report(0, config.samples as u64, "calibrating the load");
    let mut softening: Option<f64> = None;
    let mut checked = None;
    if let Some(check) = preflight
        && fresh
        && config.samples > check.settings.samples
    {
        let d = ctx.reference_softening_mm(config, cancel)?;
        softening = Some(d);
        checked = Some(check.judge(preflight::preflight_with(&ctx, config, &check.settings, d, start, progress, cancel)?)?);
    }
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
    let mut manifest = base_manifest(seg, config, &ctx);
    // Shard file -> content hash, as the manifest on disk recorded them when they were written.
    let mut recorded: BTreeMap<String, String> = BTreeMap::new();
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
        recorded = old.shards.into_iter().map(|s| (s.file, s.hash)).collect();
    } else if (0..config.shard_count()).any(|s| out.join(shard_file_name(s)).exists())
        || std::fs::read_dir(out).map(|d| d.flatten().any(|e| e.file_name().to_string_lossy().starts_with("shard_"))).unwrap_or(false)
    {
        // The manifest is written before the first shard: shards without one are left over from
        // another run (or its manifest was deleted), and their settings cannot be checked.
        return Err(invalid(
            out,
            "holds shard files but no manifest.json, so what made them cannot be checked; choose an empty folder (or restore its manifest.json)",
        ));
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
        // A shard is adopted only when its bytes are the ones this dataset's manifest recorded:
        // a file copied in from another dataset (another seed, same grid) is recomputed.
        let bytes = if path.exists() { std::fs::read(&path).ok() } else { None };
        if let Some(bytes) = bytes
            && recorded.get(&shard_file_name(shard)) == Some(&fnv_hex(&bytes))
            && let Ok((records, accepted)) = read_shard_records(&path, config, shard, padded)
        {
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
    // Parallel over samples; each solve single-threaded (`_seq`) so results do not depend on scheduling.
    let softening = match softening {
        Some(d) => d,
        None if todo.is_empty() => f64::INFINITY,
        None => ctx.reference_softening_mm(config, cancel)?,
    };
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
                    let result = match generate_sample(&ctx, &mut solver, config, index, softening, cancel) {
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
        preflight: checked,
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
        let (max, mean) = r.max_mean(ctx, config);
        m.samples.push(SampleRecord {
            index: r.index,
            accepted: r.rejection.is_none(),
            rejection: r.rejection.as_ref().map(|x| x.0),
            reason: r.rejection.as_ref().map(|x| x.1.clone()),
            max_displacement_mm: max,
            mean_displacement_mm: mean,
            target_displacement_mm: Some(r.target_mm),
            family: recorded_family(config, r.index),
            material: recorded_material(config, r.index),
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
            out.push(pts[3 * at..3 * (at + c)].chunks_exact(3).map(|p| Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64)).collect());
            at += c;
        }
        Ok(out)
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
    let same = |m: &Manifest| m.config_hash == m0.config_hash && m.grid_hash == m0.grid_hash && m.segmentation_hash == m0.segmentation_hash;
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
    let staged = crate::StagedDir::new(out, &["manifest.json"]).map_err(|source| DatasetError::Io { path: out.into(), source })?;
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

fn merge_into(
    m0: &Manifest,
    sources: &[PathBuf],
    first: &Path,
    stage: &Path,
    same: impl Fn(&Manifest) -> bool,
) -> Result<Manifest, DatasetError> {
    std::fs::create_dir_all(stage).map_err(|source| DatasetError::Io { path: stage.into(), source })?;
    let grid = std::fs::read(first.join("grid.npz")).map_err(|source| DatasetError::Io { path: first.join("grid.npz"), source })?;
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
    crate::write_atomic(&stage.join("grid.npz"), &grid).map_err(|source| DatasetError::Io { path: stage.join("grid.npz"), source })?;
    finalize(&mut merged);
    merged.write(stage)?;
    Ok(merged)
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
    /// The configured target of the mean nodal displacement (mm) and how it was used.
    pub target_displacement_mm: f64,
    pub calibration: LoadCalibration,
    /// Per accepted sample: achieved mean displacement / its calibrated target.
    pub achieved_over_target: Option<Distribution>,
    /// Which nodes the mean displacement averages over (free: what can move).
    pub mean_over: crate::fem::solver::MeanOver,
    /// Accepted samples whose target was out of reach and whose converged state nearest it
    /// was kept (achieved / target below 1 - `CALIBRATION_TOLERANCE`, at least
    /// `fem::solver::MIN_REACHED_FRACTION`).
    pub below_target: usize,
    /// Per load family (datasets of more than one): (family, samples, accepted).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub families: Vec<(LoadFamily, usize, usize)>,
    /// Per material kind (datasets that draw one per sample): (kind, samples, accepted,
    /// smallest and largest Poisson's ratio drawn).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub materials: Vec<(crate::fem::MaterialKind, usize, usize, f64, f64)>,
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
    let mut families: Vec<(LoadFamily, usize, usize)> = Vec::new();
    for s in &m.samples {
        let Some(f) = s.family else { continue };
        match families.iter_mut().find(|e| e.0 == f) {
            Some(e) => {
                e.1 += 1;
                e.2 += s.accepted as usize;
            }
            None => families.push((f, 1, s.accepted as usize)),
        }
    }
    families.sort_by_key(|e| LoadFamily::ALL.iter().position(|f| *f == e.0));
    let mut materials: Vec<(crate::fem::MaterialKind, usize, usize, f64, f64)> = Vec::new();
    for s in &m.samples {
        let Some(mat) = s.material else { continue };
        match materials.iter_mut().find(|e| e.0 == mat.kind) {
            Some(e) => {
                e.1 += 1;
                e.2 += s.accepted as usize;
                e.3 = e.3.min(mat.poisson);
                e.4 = e.4.max(mat.poisson);
            }
            None => materials.push((mat.kind, 1, s.accepted as usize, mat.poisson, mat.poisson)),
        }
    }
    materials.sort_by_key(|e| e.0.name());
    Ok(DatasetStats {
        families,
        materials,
        samples: m.samples.len(),
        accepted: acc.len(),
        rejected,
        flagged: m.samples.iter().filter(|s| s.flagged).count(),
        complete: m.complete,
        max_displacement_mm: max_d,
        mean_displacement_mm: Distribution::of(acc.iter().map(|s| s.mean_displacement_mm).collect()),
        target_displacement_mm: m.config.forces.target_displacement_mm,
        calibration: m.config.forces.calibration,
        achieved_over_target: Distribution::of(
            acc.iter().filter_map(|s| s.target_displacement_mm.filter(|t| *t > 0.0).map(|t| s.mean_displacement_mm / t)).collect(),
        ),
        newton_iterations: its,
        solve_ms: Distribution::of(acc.iter().filter_map(|s| s.solve_ms).collect()),
        mean_over: m.config.forces.mean_over,
        below_target: acc
            .iter()
            .filter(|s| s.target_displacement_mm.is_some_and(|t| s.mean_displacement_mm < (1.0 - CALIBRATION_TOLERANCE) * t * (1.0 - 1e-9)))
            .count(),
        outliers,
    })
}
