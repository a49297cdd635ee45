//! Random force probes on the visible surface and default fixed regions.

use crate::fem::{BoundaryConditions, FixedRegion, MaterialParams};
use crate::grid::ImmersedGrid;
use crate::mesh::TriMesh;
use crate::phantom::SplitMix64;
use nalgebra::Vector3;

/// How random forces are drawn. Amplitudes are uniform in [0, 2 mean]; directions are the
/// inward normal tilted by a random vector of length `direction_spread` (0: pure pressing,
/// large: nearly isotropic). The mean amplitude is set so that the whole load would
/// displace a cube of the organ's size by about `target_displacement_mm` in small strain:
/// total force ~ E * L * target (N), shared between the probes.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ForceSettings {
    pub probes: usize,
    pub target_displacement_mm: f64,
    pub direction_spread: f64,
}

impl Default for ForceSettings {
    fn default() -> Self {
        Self { probes: 100, target_displacement_mm: 3.0, direction_spread: 0.8 }
    }
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PointForce {
    pub point_mm: [f64; 3],
    pub force_n: [f64; 3],
}

/// Draw forces at the given surface points (with outward normals).
pub fn random_forces(
    points: &[(Vector3<f64>, Vector3<f64>)],
    organ_size_mm: f64,
    material: &MaterialParams,
    settings: &ForceSettings,
    rng: &mut SplitMix64,
) -> Vec<PointForce> {
    let e = material.young_pa * 1e-6;
    let total = e * organ_size_mm * settings.target_displacement_mm;
    let mean = total / points.len().max(1) as f64;
    points
        .iter()
        .map(|(p, n)| {
            let r = loop {
                let v = Vector3::new(rng.next_f64(), rng.next_f64(), rng.next_f64()) * 2.0 - Vector3::repeat(1.0);
                if v.norm_squared() <= 1.0 && v.norm_squared() > 1e-6 {
                    break v.normalize();
                }
            };
            let dir = (-n + r * settings.direction_spread).normalize();
            let amp = 2.0 * mean * rng.next_f64();
            PointForce { point_mm: [p.x, p.y, p.z], force_n: (dir * amp).into() }
        })
        .collect()
}

/// A characteristic organ size: the cube root of its volume (mm).
pub fn organ_size_mm(grid: &ImmersedGrid) -> f64 {
    grid.volume_mm3().cbrt()
}

/// The default fixed region: nodes within `distance_mm` of a vessel label when there is one,
/// else the posterior tenth of the organ (smallest y in RAS).
pub fn default_fixed_region(grid: &ImmersedGrid, fix_label: Option<i64>, distance_mm: f64) -> FixedRegion {
    if let Some(label) = fix_label {
        return FixedRegion::Label { label, distance_mm };
    }
    let ys: Vec<f64> = (0..grid.node_count()).map(|n| grid.node_position(n).y).collect();
    let (lo, hi) = ys.iter().fold((f64::MAX, f64::MIN), |(a, b), &y| (a.min(y), b.max(y)));
    FixedRegion::Plane { normal: [0.0, 1.0, 0.0], offset_mm: lo, thickness_mm: 0.1 * (hi - lo) }
}

/// Apply point forces to boundary conditions.
pub fn apply_forces(grid: &ImmersedGrid, bc: &mut BoundaryConditions, forces: &[PointForce]) -> Result<(), String> {
    for f in forces {
        bc.add_point_force(grid, &Vector3::from(f.point_mm), &Vector3::from(f.force_n))?;
    }
    Ok(())
}

/// Mesh vertices displaced through their grid embedding.
pub fn deform_mesh(grid: &ImmersedGrid, mesh: &TriMesh, u: &[Vector3<f64>]) -> TriMesh {
    let mut out = mesh.clone();
    for p in &mut out.positions {
        if let Some(e) = grid.embed(p) {
            let d: Vector3<f64> = e.nodes.iter().zip(e.weights).map(|(&n, w)| u[n as usize] * w).sum();
            *p += d;
        }
    }
    out
}

/// `settings.probes` random forces at points sampled uniformly on the visible surface.
pub fn visible_random_forces(
    surface: &TriMesh,
    grid: &ImmersedGrid,
    material: &MaterialParams,
    settings: &ForceSettings,
    visibility: &crate::visible::VisibilitySettings,
    seed: u64,
) -> Result<Vec<PointForce>, String> {
    let vis = crate::visible::visible_surface(surface, visibility)?;
    if vis.visible_area_mm2 <= 0.0 {
        return Err("the camera sees none of the organ surface".into());
    }
    let mut rng = SplitMix64(seed);
    let pts = crate::visible::sample_points(surface, &vis.visible, settings.probes, &mut rng);
    Ok(random_forces(&pts, organ_size_mm(grid), material, settings, &mut rng))
}
