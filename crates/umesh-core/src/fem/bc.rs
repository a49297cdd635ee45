//! Boundary conditions and loads: fixed nodes, prescribed displacements, point forces.

use crate::grid::ImmersedGrid;
use crate::volume::Mask;
use nalgebra::Vector3;

/// A region whose nodes are fixed (all three displacement components zero).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "type", rename_all = "kebab-case")]
pub enum FixedRegion {
    /// Nodes within `distance_mm` of a voxel of this label (e.g. the vena cava).
    Label { label: i64, distance_mm: f64 },
    /// Nodes inside an axis-aligned box (world mm).
    Box { min_mm: [f64; 3], max_mm: [f64; 3] },
    /// Nodes on the negative side of a plane (n . x < offset) or within `thickness_mm` of it.
    Plane { normal: [f64; 3], offset_mm: f64, thickness_mm: f64 },
    /// Explicit node numbers.
    Nodes { nodes: Vec<usize> },
}

/// The farthest a node may be from a label to be fixed by it (`FixedRegion::Label`).
pub const MAX_FIX_DISTANCE_MM: f64 = 30.0;

/// Everything the static solve needs besides the grid and the material.
#[derive(Clone, Debug, Default)]
pub struct BoundaryConditions {
    /// Per node: all three components fixed.
    pub fixed: Vec<bool>,
    /// Prescribed displacements (mm) of chosen nodes; these nodes are also constrained.
    pub prescribed_mm: Vec<(usize, Vector3<f64>)>,
    /// External force on each node (N).
    pub forces_n: Vec<Vector3<f64>>,
}

impl BoundaryConditions {
    pub fn new(nodes: usize) -> Self {
        Self { fixed: vec![false; nodes], prescribed_mm: Vec::new(), forces_n: vec![Vector3::zeros(); nodes] }
    }

    pub fn fixed_count(&self) -> usize {
        self.fixed.iter().filter(|&&f| f).count()
    }

    /// Fix the nodes of a region; returns how many nodes it fixed.
    pub fn fix_region(
        &mut self,
        grid: &ImmersedGrid,
        region: &FixedRegion,
        label_mask: Option<&Mask>,
    ) -> Result<usize, crate::Invalid> {
        let before = self.fixed_count();
        match region {
            FixedRegion::Label { label, distance_mm } => {
                let mask = label_mask.ok_or_else(|| format!("fixing by label {label} needs the segmentation"))?;
                let sampler = mask.world_sampler();
                let spacing = mask.world_from_voxel.fixed_view::<3, 3>(0, 0).column(0).norm().max(1e-6);
                let r = *distance_mm;
                // The search visits (2r / voxel)^3 voxels a node: beyond 30 mm it takes minutes
                // a grid (1e308 never ended) and holds most of a liver still.
                if !(r.is_finite() && (0.0..=MAX_FIX_DISTANCE_MM).contains(&r)) {
                    return Err(crate::Invalid(format!(
                        "fixed distance {r} mm from label {label}: between 0 and {MAX_FIX_DISTANCE_MM} mm"
                    )));
                }
                let steps = (r / spacing).ceil() as i64;
                for n in 0..grid.node_count() {
                    let p = grid.node_position(n);
                    'search: for dk in -steps..=steps {
                        for dj in -steps..=steps {
                            for di in -steps..=steps {
                                let d = Vector3::new(di as f64, dj as f64, dk as f64) * spacing;
                                if d.norm() <= r + 1e-9 && sampler.inside(&(p + d).into()) {
                                    self.fixed[n] = true;
                                    break 'search;
                                }
                            }
                        }
                    }
                }
            }
            FixedRegion::Box { min_mm, max_mm } => {
                for n in 0..grid.node_count() {
                    let p = grid.node_position(n);
                    if (0..3).all(|a| p[a] >= min_mm[a] && p[a] <= max_mm[a]) {
                        self.fixed[n] = true;
                    }
                }
            }
            FixedRegion::Plane { normal, offset_mm, thickness_mm } => {
                let nrm = Vector3::from(*normal);
                if nrm.norm() == 0.0 {
                    return Err(crate::Invalid::from("the plane's normal is zero"));
                }
                let nrm = nrm.normalize();
                for n in 0..grid.node_count() {
                    let d = nrm.dot(&grid.node_position(n)) - offset_mm;
                    if d < *thickness_mm {
                        self.fixed[n] = true;
                    }
                }
            }
            FixedRegion::Nodes { nodes } => {
                for &n in nodes {
                    if n >= grid.node_count() {
                        return Err(crate::Invalid(format!(
                            "node {n} does not exist (the grid has {})",
                            grid.node_count()
                        )));
                    }
                    self.fixed[n] = true;
                }
            }
        }
        Ok(self.fixed_count() - before)
    }

    /// Apply a point force at a world point, spread over the enclosing cell's nodes with the
    /// trilinear weights (this conserves the total force).
    pub fn add_point_force(
        &mut self,
        grid: &ImmersedGrid,
        point_mm: &Vector3<f64>,
        force_n: &Vector3<f64>,
    ) -> Result<(), crate::Invalid> {
        if !(point_mm.iter().chain(force_n.iter()).all(|v| v.is_finite())) {
            return Err(crate::Invalid(format!(
                "a force of {force_n:?} N at {point_mm:?} mm: every number must be finite"
            )));
        }
        let e = grid.embed(point_mm).ok_or_else(|| format!("the point {point_mm:?} is not near the grid"))?;
        // `embed` clamps a point outside the grid into the nearest cell: beyond one cell the
        // force is not on the organ, and moving it there silently would be another load.
        let at: Vector3<f64> = e.nodes.iter().zip(e.weights).map(|(&n, w)| grid.node_position(n as usize) * w).sum();
        let off = (at - point_mm).norm();
        if off > grid.cell_size_mm {
            return Err(crate::Invalid(format!(
                "the force at [{:.1}, {:.1}, {:.1}] mm lies {off:.1} mm outside the organ's grid (more than one {} mm cell): not on the organ",
                point_mm.x, point_mm.y, point_mm.z, grid.cell_size_mm
            )));
        }
        for (n, w) in e.nodes.iter().zip(e.weights) {
            self.forces_n[*n as usize] += force_n * w;
        }
        Ok(())
    }
}
