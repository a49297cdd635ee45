//! The organ model a dataset job solves on: grid, fixed region, visible surface, observation
//! set-up and the rest solver, built once from a segmentation and a configuration.

use super::config::{DatasetConfig, MIN_VISIBLE_FRACTION, fnv_hex, sample_material, segmentation_hash};
use super::error::{DatasetError, invalid};
use crate::fem::solver::{FeSolver, SolveMethod};
use crate::fem::{BoundaryConditions, FixedRegion, MaterialParams};
use crate::grid::ImmersedGrid;
use crate::loads::{self, LoadCalibration, LoadFamily, PointForce};
use crate::mesh::TriMesh;
use crate::npz::{Array, ArrayData, encode_npz_with};
use crate::progress::{Cancel, Progress};
use crate::rng::SplitMix64;
use crate::segmentation::Segmentation;
use crate::surface::{SurfaceSettings, extract_surface};
use crate::visible::{VisibilitySettings, VisibleSurface, sample_points, visible_surface};
use nalgebra::Vector3;

/// Everything shared by the samples of a dataset.
#[derive(Debug)]
pub struct DatasetContext {
    pub grid: ImmersedGrid,
    pub surface: TriMesh,
    pub visible: VisibleSurface,
    /// Grid nodes whose displacement the camera observes (u_s is non-zero there).
    pub visible_nodes: Vec<usize>,
    pub fixed: Vec<bool>,
    /// Per surface triangle: visible and not held (each corner and its centre lie in a cell
    /// with a free node). Probes land only here: one that presses a held part moves nothing.
    pub pressable: Vec<bool>,
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
        return Err(invalid(
            &seg_path,
            format!("the camera at {:?} mm is inside the organ", visible.camera.position_mm),
        ));
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

/// The organ's surface as a dataset of `surface_step` builds it (and registration reads it
/// back): marching every `surface_step`-th voxel of the organ's mask.
pub fn organ_surface(mask: &crate::volume::Mask, surface_step: usize) -> TriMesh {
    extract_surface(mask, &SurfaceSettings { step: surface_step.max(1), ..Default::default() })
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
        // The surface's marching step in voxels: beyond 16 a liver is a handful of triangles
        // (100000 asked for petabytes).
        if !(1..=16).contains(&config.surface_step) {
            return Err(invalid(&seg_path, format!("surface_step {}: 1 to 16 voxels", config.surface_step)));
        }
        let mask = seg.organ_mask();
        let grid = ImmersedGrid::from_mask(&mask, &config.grid, &Progress::none(), cancel)?;
        let surface = organ_surface(&mask, config.surface_step);
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
        grid_arrays.push((
            "visible_nodes",
            Array::i64(vec![visible_nodes.len()], visible_nodes.iter().map(|&v| v as i64).collect()),
        ));
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
            Array::i64(
                vec![surface.triangles.len(), 3],
                surface.triangles.iter().flat_map(|t| t.map(|v| v as i64)).collect(),
            ),
        ));
        grid_arrays.push((
            "surface_visible",
            Array::new(
                vec![surface.triangles.len()],
                ArrayData::U8(visible.visible.iter().map(|&v| v as u8).collect()),
            ),
        ));
        let grid_npz =
            encode_npz_with(&grid_arrays, true).map_err(|e| DatasetError::Io { path: "grid.npz".into(), source: e })?;
        let pressable = pressable_triangles(&grid, &surface, &visible.visible, &fixed);
        if !pressable.contains(&true) {
            return Err(invalid(
                &seg.source,
                "every surface triangle the camera sees is held by the fixed region: no probe could move the organ; \
                 hold less of it or choose another camera",
            ));
        }
        Ok(Self {
            grid,
            surface,
            visible,
            visible_nodes,
            fixed,
            pressable,
            grid_npz,
            segmentation_hash: segmentation_hash(seg),
            material: config.material,
        })
    }

    /// The probes' forces on the grid, each spread over its contact patch on the surface
    /// (`ForceSettings::patch_radius_mm`): the one load model of samples and recordings.
    pub fn apply_probes(
        &self,
        bc: &mut BoundaryConditions,
        config: &DatasetConfig,
        forces: &[PointForce],
    ) -> Result<(), crate::Invalid> {
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
    ) -> Result<(), crate::Invalid> {
        match family.contact_radius_mm(config.forces.patch_radius_mm) {
            Some(r) => loads::apply_forces(&self.grid, bc, &loads::spread_forces(&self.surface, forces, r)),
            None => loads::apply_forces(&self.grid, bc, forces),
        }
    }

    /// Scale `forces` so that their linear mean displacement (over the nodes the configuration
    /// averages) is `target_mm`: the calibration of samples, for any load. Returns how hard
    /// that linear solution strains the organ.
    pub fn calibrate_forces(
        &self,
        solver: &mut FeSolver,
        config: &DatasetConfig,
        forces: &mut [PointForce],
        target_mm: f64,
        family: LoadFamily,
    ) -> Result<LinearStrain, crate::Invalid> {
        let mut bc = BoundaryConditions::new(self.grid.node_count());
        bc.fixed = self.fixed.clone();
        self.apply_load(&mut bc, config, forces, family)?;
        let lin =
            solver.solve(&bc, SolveMethod::Linear, &Progress::none(), &Cancel::new()).map_err(|e| e.to_string())?;
        let scale =
            loads::scale_forces(forces, config.forces.mean_over.mean_mm(&lin.displacement_mm, &self.fixed), target_mm)?;
        let at = |q| scale * crate::fem::element::compression_quantile(&self.grid, &lin.displacement_mm, q);
        Ok(LinearStrain { p95: at(STRAIN_QUANTILE), max: at(1.0) })
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
        let pts = sample_points(&self.surface, &self.pressable, loads::family_points(family, &config.forces), &mut rng);
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
    /// sample's target times `load_scale` (one solve with the cached rest factor), lowered
    /// where that strains the organ beyond `max_strain`. Returns the forces, the target (mm;
    /// for `energy-scale`, the configured value) and, when the strain limit lowered it, the
    /// target drawn.
    pub fn calibrated_forces(
        &self,
        solver: &mut FeSolver,
        config: &DatasetConfig,
        index: usize,
        load_scale: f64,
    ) -> Result<(Vec<PointForce>, f64, Option<f64>), crate::Invalid> {
        let (mut forces, target) = self.sample_forces(config, index);
        if config.forces.calibration == LoadCalibration::EnergyScale {
            let _ = loads::scale_forces(&mut forces, 1.0, load_scale);
            return Ok((forces, config.forces.target_displacement_mm * load_scale, None));
        }
        let drawn = target * load_scale;
        let strain = self.calibrate_forces(solver, config, &mut forces, drawn, self.sample_family(config, index))?;
        let limit = config.forces.max_strain;
        let factor = strain.limit_factor(limit);
        if factor < 1.0 {
            // Linear: forces, displacement and strain scale together.
            let lowered = drawn * factor;
            loads::scale_forces(&mut forces, drawn, lowered)?;
            return Ok((forces, lowered, Some(drawn)));
        }
        Ok((forces, drawn, None))
    }
}

/// The visible triangles free nodes move: each corner and the centre embed in a cell with a
/// free node (a non-zero weight); a triangle on the edge of the hold is left out, so that a
/// point inside it cannot land in a held cell.
fn pressable_triangles(grid: &ImmersedGrid, surface: &TriMesh, visible: &[bool], fixed: &[bool]) -> Vec<bool> {
    surface
        .triangles
        .iter()
        .zip(visible)
        .map(|(tri, &seen)| {
            seen && {
                let c = tri.iter().map(|&i| surface.positions[i as usize]).sum::<Vector3<f64>>() / 3.0;
                tri.iter().map(|&i| surface.positions[i as usize]).chain([c]).all(|p| {
                    grid.embed(&p)
                        .is_none_or(|e| e.nodes.iter().zip(e.weights).any(|(n, w)| w > 1e-9 && !fixed[*n as usize]))
                })
            }
        })
        .collect()
}

/// How hard a calibrated linear solution compresses the organ (`element::compression_quantile`):
/// over the organ (its 95th percentile) and at its most compressed cell (under a contact).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LinearStrain {
    pub p95: f64,
    pub max: f64,
}

impl LinearStrain {
    /// The factor (at most 1) that brings the compression within `limit` over the organ and,
    /// for an organ compressed beyond it, `LOCAL_STRAIN_FACTOR` times it at the most compressed
    /// cell as well; 1 for no limit (0). A contact alone is not limited: on a freely moving
    /// organ it converges (the MR liver's contact cells reach 0.38; a local limit lowered 236
    /// of its 1000 samples to half their target).
    pub fn limit_factor(&self, limit: f64) -> f64 {
        if !(limit > 0.0 && self.p95 > limit) {
            return 1.0;
        }
        let f = |strain: f64, cap: f64| if strain > cap { cap / strain } else { 1.0 };
        f(self.p95, limit).min(f(self.max, LOCAL_STRAIN_FACTOR * limit))
    }
}

/// On an organ compressed beyond `ForceSettings::max_strain`, the most compressed cell may
/// take this many times it (0.30 at the default): an instrument pressing the phantom held at
/// its core (0.48 once the organ is within the limit) did not converge, at 0.30 6 of 7 did.
pub const LOCAL_STRAIN_FACTOR: f64 = 2.5;

/// The volume quantile of `ForceSettings::max_strain`: the contact cells of a probe are
/// compressed far more than the organ (a few percent of its volume); they have their own limit.
pub const STRAIN_QUANTILE: f64 = 0.95;
