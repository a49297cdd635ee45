//! Random force probes on the visible surface and default fixed regions.

use crate::fem::solver::MeanOver;
use crate::fem::{BoundaryConditions, FixedRegion, MaterialParams};
use crate::grid::ImmersedGrid;
use crate::mesh::TriMesh;
use crate::rng::SplitMix64;
use crate::segmentation::Segmentation;
use nalgebra::Vector3;

/// How random forces are drawn. Amplitudes are uniform in [0, 2 mean]; directions are the
/// inward normal tilted by a random vector of length `direction_spread` (0: pure pressing,
/// large: nearly isotropic).
///
/// The scale depends on `calibration`:
/// - `mean-displacement` (the default): each sample's forces are scaled after one linear
///   solve so that the small-strain mean nodal displacement equals the sample's target,
///   `target_displacement_mm` times a factor uniform in [1 - spread, 1 + spread]. The SVK
///   solve then lands near it on any organ (the achieved value is what the manifest records).
/// - `energy-scale` (datasets made before calibration existed): the whole load is
///   E * L * target (N) with L the cube root of the organ volume, shared between the probes;
///   what it displaces depends on the organ's shape and fixed region.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ForceSettings {
    pub probes: usize,
    pub target_displacement_mm: f64,
    pub direction_spread: f64,
    #[serde(default = "LoadCalibration::legacy")]
    pub calibration: LoadCalibration,
    /// Relative half-width of the uniform spread of each sample's target (0.5: 0.5-1.5 x).
    #[serde(default)]
    pub target_spread: f64,
    /// The nodes the calibrated mean displacement averages over: `free` (the default) or `all`
    /// (datasets made before; not written then, so their configuration hash is unchanged).
    #[serde(default = "MeanOver::legacy", skip_serializing_if = "MeanOver::is_all")]
    pub mean_over: MeanOver,
    /// Each probe presses a contact of this radius (mm): its force is spread over the surface
    /// within it (`spread_forces`). 0: point loads, as datasets made before (not written then).
    /// A point load of a stiffly held organ's calibrated size inverts the thin boundary cell it
    /// lands on long before the organ reaches its target.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub patch_radius_mm: f64,
    /// The load families samples are drawn from, each sample one of them chosen uniformly
    /// (`family_of`). Datasets made before families existed: pressing only (not written then,
    /// so their configuration hash is unchanged).
    #[serde(default = "pressing_only", skip_serializing_if = "is_pressing_only")]
    pub families: Vec<LoadFamily>,
    /// A sample whose calibrated linear solution compresses the organ beyond this (the 95th
    /// percentile over its volume of the compression, `element::compression_quantile`; its
    /// most compressed cell beyond `dataset::LOCAL_STRAIN_FACTOR` times this) has its target lowered
    /// until it does not: an organ held at its core, or pressed against its hold, reaches
    /// 10 mm of mean displacement only by squeezing its tissue by a third, where SVK collapses
    /// (and tissue would tear). 0: no limit, as datasets made before (not written then, so
    /// their configuration hash is unchanged).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub max_strain: f64,
}

/// The default `ForceSettings::max_strain`: above every sample of the real livers with their
/// default attachment (at most 0.052 over 45 samples of the CT, MR and SOFA livers) and of the
/// phantom's (at most 0.096); under the phantom held at its portal vein (up to 0.3).
pub const DEFAULT_MAX_STRAIN: f64 = 0.12;

fn pressing_only() -> Vec<LoadFamily> {
    vec![LoadFamily::Pressing]
}

fn is_pressing_only(f: &[LoadFamily]) -> bool {
    f == [LoadFamily::Pressing]
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LoadCalibration {
    MeanDisplacement,
    EnergyScale,
}

impl LoadCalibration {
    fn legacy() -> Self {
        Self::EnergyScale
    }
}

impl Default for ForceSettings {
    fn default() -> Self {
        Self {
            probes: 100,
            target_displacement_mm: 10.0,
            direction_spread: 0.8,
            calibration: LoadCalibration::MeanDisplacement,
            target_spread: 0.5,
            mean_over: MeanOver::Free,
            patch_radius_mm: DEFAULT_PATCH_RADIUS_MM,
            families: LoadFamily::ALL.to_vec(),
            max_strain: DEFAULT_MAX_STRAIN,
        }
    }
}

impl ForceSettings {
    /// The uncalibrated scale F = E L D / N (one-off solves and the FE benchmark).
    pub fn energy_scale(probes: usize, target_displacement_mm: f64) -> Self {
        Self {
            probes,
            target_displacement_mm,
            calibration: LoadCalibration::EnergyScale,
            target_spread: 0.0,
            families: pressing_only(),
            max_strain: 0.0,
            ..Self::default()
        }
    }

    pub fn validate(&self) -> Result<(), crate::Invalid> {
        if self.probes == 0 || self.probes > 100_000 {
            return Err(crate::Invalid(format!("{} probes: between 1 and 100000", self.probes)));
        }
        if !(self.target_displacement_mm > 0.0 && self.target_displacement_mm < 1e4) {
            return Err(crate::Invalid(format!(
                "target displacement {} mm: must be positive and below 10 m",
                self.target_displacement_mm
            )));
        }
        if !(self.direction_spread >= 0.0 && self.direction_spread.is_finite()) {
            return Err(crate::Invalid(format!("direction spread {}: must be finite and >= 0", self.direction_spread)));
        }
        if !(0.0..1.0).contains(&self.target_spread) {
            return Err(crate::Invalid(format!("target spread {}: must lie in [0, 1)", self.target_spread)));
        }
        if !(self.patch_radius_mm >= 0.0 && self.patch_radius_mm <= 100.0) {
            return Err(crate::Invalid(format!(
                "probe contact radius {} mm: between 0 and 100 mm",
                self.patch_radius_mm
            )));
        }
        if !(self.max_strain >= 0.0 && self.max_strain <= 1.0) {
            return Err(crate::Invalid(format!("strain limit {}: between 0 (none) and 1", self.max_strain)));
        }
        if self.families.is_empty() {
            return Err(crate::Invalid::from(
                "no load family: give at least one of pressing, instrument, grasp, gravity",
            ));
        }
        if self.families.iter().enumerate().any(|(i, f)| self.families[..i].contains(f)) {
            return Err(crate::Invalid(format!(
                "load families {:?}: each at most once",
                self.families.iter().map(|f| f.name()).collect::<Vec<_>>()
            )));
        }
        if self.calibration == LoadCalibration::EnergyScale && self.mixes_families() {
            return Err(crate::Invalid::from(
                "load families other than pressing need the mean-displacement calibration",
            ));
        }
        Ok(())
    }

    /// Whether samples are drawn from more than pressing (the manifest then records each
    /// sample's family).
    pub fn mixes_families(&self) -> bool {
        !is_pressing_only(&self.families)
    }

    /// The family of sample `index`: uniform over `families`, from its own random stream (a
    /// single family draws nothing, so pressing-only datasets are the ones they always were).
    pub fn family_of(&self, seed: u64, index: usize) -> LoadFamily {
        if self.families.len() <= 1 {
            return self.families.first().copied().unwrap_or(LoadFamily::Pressing);
        }
        let mut rng = SplitMix64(seed ^ 0xFA41_17E5 ^ (index as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
        rng.next_u64();
        self.families[(rng.next_u64() % self.families.len() as u64) as usize]
    }

    /// Parse a comma-separated list of families, or `mixture` (all four).
    pub fn parse_families(s: &str) -> Result<Vec<LoadFamily>, crate::Invalid> {
        if s.trim() == "mixture" {
            return Ok(LoadFamily::ALL.to_vec());
        }
        s.split(',').map(|f| LoadFamily::parse(f.trim())).collect()
    }

    /// The target mean displacement of one sample: the configured target times a factor
    /// uniform in [1 - spread, 1 + spread], drawn from `rng`.
    pub fn sample_target_mm(&self, rng: &mut SplitMix64) -> f64 {
        self.target_displacement_mm * (1.0 + self.target_spread * (2.0 * rng.next_f64() - 1.0))
    }
}

/// Scale forces in place so that their small-strain mean nodal displacement, `linear_mean_mm`
/// for the forces as given, becomes `target_mm`. Errors when the pattern moves nothing.
pub fn scale_forces(forces: &mut [PointForce], linear_mean_mm: f64, target_mm: f64) -> Result<f64, crate::Invalid> {
    if !(linear_mean_mm > 1e-12) || !linear_mean_mm.is_finite() {
        return Err(crate::Invalid(format!(
            "the force pattern displaces the organ by {linear_mean_mm:e} mm: nothing to calibrate"
        )));
    }
    let s = target_mm / linear_mean_mm;
    for f in forces {
        for c in &mut f.force_n {
            *c *= s;
        }
    }
    Ok(s)
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

/// Label names (lower case, `_` for spaces) of the veins that hold the liver in place: the
/// inferior vena cava and the hepatic veins (TotalSegmentator, 3D Slicer and the phantom).
const ANCHOR_NAMES: [&str; 5] = ["inferior_vena_cava", "vena_cava", "ivc", "hepatic_vein", "hepatic_veins"];
/// TotalSegmentator's `total` task: 5 = liver, 63 = inferior vena cava (files without names).
const TOTALSEGMENTATOR_LIVER: i64 = 5;
const TOTALSEGMENTATOR_IVC: i64 = 63;
/// Depth of the fallback region, as a fraction of the organ's antero-posterior extent.
pub const POSTERIOR_FRACTION: f64 = 0.2;

/// The fixed region chosen for an organ and why, as printed and stored.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FixedChoice {
    pub region: FixedRegion,
    pub description: String,
}

/// The label of the vein that anchors the organ, if the segmentation has one: by name
/// (inferior vena cava, hepatic veins), else TotalSegmentator's number 63 next to its liver 5.
pub fn anchor_label(seg: &Segmentation) -> Option<(i64, String)> {
    let counts = seg.volume.label_counts();
    let norm = |s: &str| s.trim().to_lowercase().replace([' ', '-'], "_");
    let mut named: Vec<(usize, i64, String)> = seg
        .volume
        .label_names
        .iter()
        .filter(|(l, n)| {
            counts.contains_key(*l)
                && !seg.organ_labels.contains(l)
                && ANCHOR_NAMES.iter().any(|a| norm(n) == *a || norm(n).ends_with(&format!("_{a}")))
        })
        .map(|(l, n)| (ANCHOR_NAMES.iter().position(|a| norm(n).ends_with(a)).unwrap_or(9), *l, n.clone()))
        .collect();
    named.sort();
    if let Some((_, l, n)) = named.into_iter().next() {
        return Some((l, n));
    }
    (seg.volume.label_names.is_empty()
        && seg.organ_labels.contains(&TOTALSEGMENTATOR_LIVER)
        && counts.contains_key(&TOTALSEGMENTATOR_IVC))
    .then(|| (TOTALSEGMENTATOR_IVC, "inferior vena cava (TotalSegmentator label 63)".to_string()))
}

/// The default fixed region: nodes within `distance_mm` of the label given, else of the
/// organ's anchoring vein (`anchor_label`), else the posterior fifth of the organ (smallest y
/// in RAS; deep enough that the organ cannot swing about a thin strip).
pub fn default_fixed(seg: &Segmentation, fix_label: Option<i64>, distance_mm: f64) -> FixedChoice {
    if let Some(label) = fix_label {
        return FixedChoice {
            region: FixedRegion::Label { label, distance_mm },
            description: format!("nodes within {distance_mm} mm of {} (label {label}, chosen)", seg.label_name(label)),
        };
    }
    if let Some((label, name)) = anchor_label(seg) {
        return FixedChoice {
            region: FixedRegion::Label { label, distance_mm },
            description: format!("nodes within {distance_mm} mm of the {name} (label {label}, found by name)"),
        };
    }
    let (lo, hi) = seg.organ_mask().world_bounds().unwrap_or_default();
    let depth = POSTERIOR_FRACTION * (hi.y - lo.y);
    FixedChoice {
        region: FixedRegion::Plane { normal: [0.0, 1.0, 0.0], offset_mm: lo.y, thickness_mm: depth },
        description: format!(
            "the posterior {:.0} % of the organ (y < {:.1} mm, {depth:.1} mm deep): no vena cava or hepatic vein label found",
            POSTERIOR_FRACTION * 100.0,
            lo.y + depth
        ),
    }
}

/// The default fixed region of a grid alone (no segmentation): the posterior fifth, or the
/// nodes near a vessel label.
pub fn default_fixed_region(grid: &ImmersedGrid, fix_label: Option<i64>, distance_mm: f64) -> FixedRegion {
    if let Some(label) = fix_label {
        return FixedRegion::Label { label, distance_mm };
    }
    let ys: Vec<f64> = (0..grid.node_count()).map(|n| grid.node_position(n).y).collect();
    let (lo, hi) = ys.iter().fold((f64::MAX, f64::MIN), |(a, b), &y| (a.min(y), b.max(y)));
    FixedRegion::Plane { normal: [0.0, 1.0, 0.0], offset_mm: lo, thickness_mm: POSTERIOR_FRACTION * (hi - lo) }
}

/// The contact radius of a probe (mm): about 1 cm², an instrument's tip, over which the
/// force is spread with weights falling linearly to zero at the rim.
pub const DEFAULT_PATCH_RADIUS_MM: f64 = 8.0;

/// Each force spread over the mesh vertices within `radius_mm` of its point, with weights
/// 1 - d / radius normalised to one: the resultant is kept exactly, the moment to within the
/// offset of the patch's weighted centre (small on a smooth surface). A force with no vertex
/// within the radius, or `radius_mm` 0, stays a point force.
pub fn spread_forces(surface: &TriMesh, forces: &[PointForce], radius_mm: f64) -> Vec<PointForce> {
    if radius_mm <= 0.0 {
        return forces.to_vec();
    }
    let mut out = Vec::with_capacity(forces.len() * 16);
    for f in forces {
        let c = Vector3::from(f.point_mm);
        let near: Vec<(Vector3<f64>, f64)> = surface
            .positions
            .iter()
            .filter_map(|v| {
                let d = (v - c).norm();
                (d < radius_mm).then(|| (*v, 1.0 - d / radius_mm))
            })
            .collect();
        let total: f64 = near.iter().map(|x| x.1).sum();
        if !(total > 0.0) {
            out.push(f.clone());
            continue;
        }
        let force = Vector3::from(f.force_n);
        out.extend(
            near.into_iter().map(|(v, w)| PointForce { point_mm: v.into(), force_n: (force * (w / total)).into() }),
        );
    }
    out
}

/// Apply point forces to boundary conditions.
pub fn apply_forces(
    grid: &ImmersedGrid,
    bc: &mut BoundaryConditions,
    forces: &[PointForce],
) -> Result<(), crate::Invalid> {
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
) -> Result<Vec<PointForce>, crate::Invalid> {
    let vis = crate::visible::visible_surface(surface, visibility)?;
    if vis.visible_area_mm2 <= 0.0 {
        return Err(crate::Invalid::from("the camera sees none of the organ surface"));
    }
    let mut rng = SplitMix64(seed);
    let pts = crate::visible::sample_points(surface, &vis.visible, settings.probes, &mut rng);
    Ok(random_forces(&pts, organ_size_mm(grid), material, settings, &mut rng))
}

/// How an organ is loaded. `Pressing` is the datasets' pattern (many probes on the visible
/// surface); the others are deformations a network trained on it has not seen, for test
/// recordings (`rgbd synth --loads`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LoadFamily {
    /// `ForceSettings::probes` probes on the visible surface, pressing (the datasets').
    Pressing,
    /// An instrument pushing locally: 1-3 contacts on the visible surface, nearly along the
    /// inward normal, each spread over the probe contact patch.
    Instrument,
    /// Grasping and pulling: 1-2 contacts pulled outward and sideways.
    Grasp,
    /// A change of support: a body force (the organ's weight turned) in a random direction.
    Gravity,
}

impl LoadFamily {
    pub const ALL: [LoadFamily; 4] = [Self::Pressing, Self::Instrument, Self::Grasp, Self::Gravity];

    pub fn name(&self) -> &'static str {
        match self {
            Self::Pressing => "pressing",
            Self::Instrument => "instrument",
            Self::Grasp => "grasp",
            Self::Gravity => "gravity",
        }
    }

    pub fn parse(s: &str) -> Result<Self, crate::Invalid> {
        Self::ALL.into_iter().find(|f| f.name() == s).ok_or_else(|| {
            crate::Invalid(format!("unknown load family {s:?} (one of {})", Self::ALL.map(|f| f.name()).join(", ")))
        })
    }

    /// The share of the sample's target (the mean displacement of the free organ) this family is
    /// calibrated to. An instrument moves the organ locally: brought to the whole target, one
    /// to three contacts inverted or failed to converge in 48 of 140 phantom samples.
    pub fn target_factor(&self) -> f64 {
        match self {
            Self::Instrument => 0.5,
            _ => 1.0,
        }
    }

    /// The radius its contacts are spread over (`spread_forces`), given the configuration's
    /// probe radius; None for a body force. An instrument's or a grasper's jaw contact is at
    /// least INSTRUMENT_CONTACT_RADIUS_MM: on a point load (the radius of datasets made before
    /// contacts existed) one calibrated contact inverts the cell under it.
    pub fn contact_radius_mm(&self, probe_radius_mm: f64) -> Option<f64> {
        match self {
            Self::Pressing => Some(probe_radius_mm),
            Self::Instrument | Self::Grasp => Some(probe_radius_mm.max(INSTRUMENT_CONTACT_RADIUS_MM)),
            Self::Gravity => None,
        }
    }
}

/// An instrument's contact: 12 mm of radius, about 4.5 cm² ("a few cm²").
pub const INSTRUMENT_CONTACT_RADIUS_MM: f64 = 12.0;

fn random_unit(rng: &mut SplitMix64) -> Vector3<f64> {
    loop {
        let v = Vector3::new(rng.next_f64(), rng.next_f64(), rng.next_f64()) * 2.0 - Vector3::repeat(1.0);
        if v.norm_squared() <= 1.0 && v.norm_squared() > 1e-6 {
            break v.normalize();
        }
    }
}

/// The forces of one load family, before calibration (their scale is arbitrary: they are
/// scaled to a target mean displacement afterwards). `visible_points`: points on the
/// visible surface with outward normals, drawn by the caller; `Pressing` uses them all,
/// `Instrument` the first 1-3, `Grasp` the first 1-2; `Gravity` none (a force on every cell
/// in proportion to its volume).
pub fn family_forces(
    family: LoadFamily,
    visible_points: &[(Vector3<f64>, Vector3<f64>)],
    grid: &ImmersedGrid,
    material: &MaterialParams,
    settings: &ForceSettings,
    rng: &mut SplitMix64,
) -> Vec<PointForce> {
    let contact = |(p, _): &(Vector3<f64>, Vector3<f64>), f: Vector3<f64>| PointForce {
        point_mm: [p.x, p.y, p.z],
        force_n: f.into(),
    };
    match family {
        LoadFamily::Pressing => random_forces(visible_points, organ_size_mm(grid), material, settings, rng),
        LoadFamily::Instrument => {
            let n = 1 + (rng.next_u64() % 3) as usize;
            visible_points
                .iter()
                .take(n)
                .map(|pn| {
                    let dir = (-pn.1 + random_unit(rng) * 0.3).normalize();
                    contact(pn, dir * (0.5 + rng.next_f64()))
                })
                .collect()
        }
        LoadFamily::Grasp => {
            let n = 1 + (rng.next_u64() % 2) as usize;
            visible_points
                .iter()
                .take(n)
                .map(|pn| {
                    let nrm = pn.1;
                    let r = random_unit(rng);
                    let tangent = (r - nrm * r.dot(&nrm))
                        .try_normalize(1e-9)
                        .unwrap_or_else(|| nrm.cross(&Vector3::x()).normalize());
                    let dir = (nrm * 0.6 + tangent).normalize();
                    contact(pn, dir * (0.5 + rng.next_f64()))
                })
                .collect()
        }
        LoadFamily::Gravity => {
            let g = random_unit(rng);
            let h = grid.cell_size_mm;
            grid.cells
                .iter()
                .map(|c| {
                    let [i, j, k] = c.ijk;
                    let centre = grid.origin_mm + Vector3::new(i as f64 + 0.5, j as f64 + 0.5, k as f64 + 0.5) * h;
                    PointForce { point_mm: centre.into(), force_n: (g * c.volume_fraction).into() }
                })
                .collect()
        }
    }
}

/// How many surface points a family draws (`family_forces`'s `visible_points`).
pub fn family_points(family: LoadFamily, settings: &ForceSettings) -> usize {
    match family {
        LoadFamily::Pressing => settings.probes,
        LoadFamily::Instrument => 3,
        LoadFamily::Grasp => 2,
        LoadFamily::Gravity => 0,
    }
}
