//! A dataset job's options as a user states them (loads, material, fixed region, camera), and
//! the dataset configuration they make: the command line's `dataset generate` / `prepare`
//! options and the app's forms are this one struct (with the `clap` feature it is also the
//! command line's argument group).

use crate::error::{WorkflowError, require};
use nalgebra::Vector3;
use umesh_core::dataset::DatasetConfig;
use umesh_core::fem::{FixedRegion, MaterialParams};
use umesh_core::grid::GridSettings;
use umesh_core::loads::{FixedChoice, ForceSettings, LoadCalibration};
use umesh_core::segmentation::Segmentation;
use umesh_core::visible::Camera;

/// The loads, material, fixed region and camera of a dataset (shared by `dataset generate`
/// and `prepare`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct DatasetOptions {
    /// Force probes per sample.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DatasetOptions::default().probes))]
    pub probes: usize,
    /// Mean nodal displacement each sample's forces are calibrated for (mm), by one linear
    /// solve per sample; each sample's target is this times a factor uniform in
    /// [1 - spread, 1 + spread].
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DatasetOptions::default().target_displacement_mm))]
    pub target_displacement_mm: f64,
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DatasetOptions::default().target_spread))]
    pub target_spread: f64,
    /// Contact radius of each probe (mm): its force is spread over the surface within it
    /// (0: point loads, as datasets made before).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DatasetOptions::default().probe_radius_mm))]
    pub probe_radius_mm: f64,
    /// Strain limit: a sample whose calibrated linear solution strains the organ beyond this
    /// (95th percentile over its volume of the largest principal strain) has its target
    /// lowered to it; an organ held at its core or pressed against its hold otherwise collapses
    /// (SVK) before its target. 0: no limit.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DatasetOptions::default().max_strain))]
    #[serde(default = "default_max_strain")]
    pub max_strain: f64,
    /// Load families the samples are drawn from, each sample one of them: `mixture` (all four)
    /// or a comma-separated list of pressing (many probes), instrument (1-3 local contacts),
    /// grasp (1-2 contacts pulled) and gravity (a body force in a random direction).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DatasetOptions::default().loads))]
    pub loads: String,
    /// How forces are scaled: mean-displacement (calibrated per sample, the default) or
    /// energy-scale (F = E L D / N, as datasets made before calibration).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DatasetOptions::default().calibration, value_parser = ["mean-displacement", "energy-scale"]))]
    pub calibration: String,
    /// Largest visible fraction of the organ surface.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DatasetOptions::default().visible_fraction))]
    pub visible_fraction: f64,
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DatasetOptions::default().young_pa))]
    pub young_pa: f64,
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DatasetOptions::default().poisson))]
    pub poisson: f64,
    /// Draw each sample's Poisson's ratio uniformly in MIN,MAX (for example 0.45,0.49)
    /// instead of --poisson for all; recorded per sample in the manifest.
    #[cfg_attr(feature = "clap", arg(long, value_delimiter = ',', value_name = "MIN,MAX"))]
    pub poisson_range: Vec<f64>,
    /// The share of samples solved with a Neo-Hookean material (the others SVK).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DatasetOptions::default().neo_hookean_fraction))]
    pub neo_hookean_fraction: f64,
    /// Fix the nodes within --fix-distance-mm of this label. Default: the inferior vena cava
    /// or hepatic veins when the segmentation names them (TotalSegmentator's 63 next to its
    /// liver 5), else the posterior fifth of the organ.
    #[cfg_attr(feature = "clap", arg(long))]
    pub fix_label: Option<i64>,
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DatasetOptions::default().fix_distance_mm))]
    pub fix_distance_mm: f64,
    /// Fix the nodes inside a box: xmin,ymin,zmin,xmax,ymax,zmax (world mm).
    #[cfg_attr(feature = "clap", arg(long, value_delimiter = ',', allow_hyphen_values = true))]
    pub fix_box: Vec<f64>,
    /// Fix the nodes on the negative side of a plane: nx,ny,nz,offset_mm,thickness_mm.
    #[cfg_attr(feature = "clap", arg(long, value_delimiter = ',', allow_hyphen_values = true))]
    pub fix_plane: Vec<f64>,
    /// Laparoscope view: anterior, posterior, right, left, superior, inferior, or two joined by
    /// '-' (anterior-inferior); from 2.5 organ sizes away, looking at the organ's centre.
    #[cfg_attr(feature = "clap", arg(long, conflicts_with = "camera_from"))]
    pub camera: Option<String>,
    /// Camera position x,y,z (world mm), with --camera-to.
    #[cfg_attr(feature = "clap", arg(long, value_delimiter = ',', allow_hyphen_values = true, requires = "camera_to"))]
    pub camera_from: Vec<f64>,
    /// Point the camera looks at, x,y,z (world mm).
    #[cfg_attr(
        feature = "clap",
        arg(long, value_delimiter = ',', allow_hyphen_values = true, requires = "camera_from")
    )]
    pub camera_to: Vec<f64>,
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DatasetOptions::default().fov_deg))]
    pub fov_deg: f64,
    /// Newton iterations a sample may take over all its load increments before it is
    /// rejected (a sample that keeps cutting its load is about to invert).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DatasetOptions::default().max_newton_iterations))]
    pub max_newton_iterations: usize,
}

fn default_max_strain() -> f64 {
    umesh_core::loads::DEFAULT_MAX_STRAIN
}

impl Default for DatasetOptions {
    /// The defaults of `umesh dataset generate` with no option (the command line's defaults are these).
    fn default() -> Self {
        Self {
            probes: ForceSettings::default().probes,
            target_displacement_mm: ForceSettings::default().target_displacement_mm,
            target_spread: ForceSettings::default().target_spread,
            probe_radius_mm: ForceSettings::default().patch_radius_mm,
            max_strain: default_max_strain(),
            loads: "mixture".into(),
            calibration: "mean-displacement".into(),
            visible_fraction: 0.5,
            young_pa: MaterialParams::default().young_pa,
            poisson: MaterialParams::default().poisson,
            poisson_range: Vec::new(),
            neo_hookean_fraction: 0.0,
            fix_label: None,
            fix_distance_mm: 6.0,
            fix_box: Vec::new(),
            fix_plane: Vec::new(),
            camera: None,
            camera_from: Vec::new(),
            camera_to: Vec::new(),
            fov_deg: 50.0,
            max_newton_iterations: DatasetConfig::paper(FixedRegion::Nodes { nodes: vec![] })
                .solver
                .max_total_iterations
                .unwrap_or(40),
        }
    }
}

impl DatasetOptions {
    /// The options that differ from the defaults, as they are typed on the command line.
    pub fn command_line(&self) -> String {
        let d = Self::default();
        let list = |v: &[f64]| v.iter().map(|x| format!("{x}")).collect::<Vec<_>>().join(",");
        let mut out = Vec::new();
        let mut opt = |name: &str, differs: bool, value: String| {
            if differs {
                out.push(format!("--{name} {value}"));
            }
        };
        opt("probes", self.probes != d.probes, self.probes.to_string());
        opt(
            "target-displacement-mm",
            self.target_displacement_mm != d.target_displacement_mm,
            self.target_displacement_mm.to_string(),
        );
        opt("target-spread", self.target_spread != d.target_spread, self.target_spread.to_string());
        opt("probe-radius-mm", self.probe_radius_mm != d.probe_radius_mm, self.probe_radius_mm.to_string());
        opt("max-strain", self.max_strain != d.max_strain, self.max_strain.to_string());
        opt("loads", self.loads != d.loads, self.loads.clone());
        opt("calibration", self.calibration != d.calibration, self.calibration.clone());
        opt("visible-fraction", self.visible_fraction != d.visible_fraction, self.visible_fraction.to_string());
        opt("young-pa", self.young_pa != d.young_pa, self.young_pa.to_string());
        opt("poisson", self.poisson != d.poisson, self.poisson.to_string());
        opt("poisson-range", !self.poisson_range.is_empty(), list(&self.poisson_range));
        opt(
            "neo-hookean-fraction",
            self.neo_hookean_fraction != d.neo_hookean_fraction,
            self.neo_hookean_fraction.to_string(),
        );
        opt("fix-label", self.fix_label.is_some(), self.fix_label.map(|l| l.to_string()).unwrap_or_default());
        opt("fix-distance-mm", self.fix_distance_mm != d.fix_distance_mm, self.fix_distance_mm.to_string());
        opt("fix-box", !self.fix_box.is_empty(), list(&self.fix_box));
        opt("fix-plane", !self.fix_plane.is_empty(), list(&self.fix_plane));
        opt("camera", self.camera.is_some(), self.camera.clone().unwrap_or_default());
        opt("camera-from", !self.camera_from.is_empty(), list(&self.camera_from));
        opt("camera-to", !self.camera_to.is_empty(), list(&self.camera_to));
        opt("fov-deg", self.fov_deg != d.fov_deg, self.fov_deg.to_string());
        opt(
            "max-newton-iterations",
            self.max_newton_iterations != d.max_newton_iterations,
            self.max_newton_iterations.to_string(),
        );
        out.join(" ")
    }

    /// The fixed region: the options given, else core's default for this segmentation.
    pub fn fixed(&self, seg: &Segmentation) -> Result<FixedChoice, WorkflowError> {
        let finite = |v: &[f64], opt: &str| -> Result<(), WorkflowError> {
            require(v.iter().all(|x| x.is_finite()), || format!("{opt}: every number must be finite"))
        };
        if !self.fix_box.is_empty() {
            require(self.fix_box.len() == 6, || {
                "--fix-box: expected xmin,ymin,zmin,xmax,ymax,zmax (6 numbers)".into()
            })?;
            finite(&self.fix_box, "--fix-box")?;
            let b = &self.fix_box;
            require((0..3).all(|a| b[a] < b[a + 3]), || "--fix-box: each minimum must be below its maximum".into())?;
            return Ok(FixedChoice {
                region: FixedRegion::Box { min_mm: [b[0], b[1], b[2]], max_mm: [b[3], b[4], b[5]] },
                description: format!("nodes in the box {:?}..{:?} mm (chosen)", &b[..3], &b[3..]),
            });
        }
        if !self.fix_plane.is_empty() {
            require(self.fix_plane.len() == 5, || {
                "--fix-plane: expected nx,ny,nz,offset_mm,thickness_mm (5 numbers)".into()
            })?;
            finite(&self.fix_plane, "--fix-plane")?;
            let p = &self.fix_plane;
            require(p[4] >= 0.0, || "--fix-plane: the thickness must be >= 0".into())?;
            return Ok(FixedChoice {
                region: FixedRegion::Plane { normal: [p[0], p[1], p[2]], offset_mm: p[3], thickness_mm: p[4] },
                description: format!("nodes with n.x < {} mm for n = {:?} (chosen)", p[3] + p[4], &p[..3]),
            });
        }
        require(self.fix_distance_mm > 0.0 && self.fix_distance_mm < 1000.0, || {
            format!("--fix-distance-mm {}: must be positive and below 1 m", self.fix_distance_mm)
        })?;
        if let Some(l) = self.fix_label {
            require(seg.volume.label_counts().contains_key(&l), || {
                format!("--fix-label {l}: {} has no voxel of that label", seg.source.display())
            })?;
        }
        Ok(umesh_core::loads::default_fixed(seg, self.fix_label, self.fix_distance_mm))
    }

    pub fn camera(&self, seg: &Segmentation) -> Result<Option<Camera>, WorkflowError> {
        require(self.fov_deg > 0.0 && self.fov_deg < 170.0, || {
            format!("--fov-deg {}: must lie in (0, 170)", self.fov_deg)
        })?;
        if !self.camera_from.is_empty() {
            require(self.camera_from.len() == 3 && self.camera_to.len() == 3, || {
                "--camera-from and --camera-to: x,y,z (3 numbers each)".into()
            })?;
            let (f, t) = (Vector3::from_column_slice(&self.camera_from), Vector3::from_column_slice(&self.camera_to));
            require(f.iter().chain(t.iter()).all(|v| v.is_finite()), || {
                "--camera-from/--camera-to: numbers must be finite".into()
            })?;
            require((f - t).norm() > 1e-6, || "--camera-from and --camera-to are the same point".into())?;
            return Ok(Some(Camera::look_at(&f, &t, self.fov_deg)));
        }
        let Some(view) = &self.camera else { return Ok(None) };
        let (lo, hi) = seg
            .organ_mask()
            .world_bounds()
            .ok_or_else(|| WorkflowError::option_message("the organ mask is empty".to_string()))?;
        let mut c =
            Camera::named(view, &lo, &hi).map_err(|e| WorkflowError::option_message(format!("--camera: {e}")))?;
        c.fov_deg = self.fov_deg;
        Ok(Some(c))
    }

    /// The dataset configuration (paper protocol) with these options.
    pub fn config(
        &self,
        seg: &Segmentation,
        grid: GridSettings,
        samples: usize,
        seed: u64,
        shard_size: usize,
    ) -> Result<(DatasetConfig, FixedChoice), WorkflowError> {
        let fixed = self.fixed(seg)?;
        let mut c = DatasetConfig::paper(fixed.region.clone());
        c.samples = samples;
        c.seed = seed;
        c.shard_size = shard_size.max(1);
        c.grid = grid;
        c.forces = ForceSettings {
            probes: self.probes,
            target_displacement_mm: self.target_displacement_mm,
            target_spread: self.target_spread,
            patch_radius_mm: self.probe_radius_mm,
            calibration: if self.calibration == "energy-scale" {
                LoadCalibration::EnergyScale
            } else {
                LoadCalibration::MeanDisplacement
            },
            // The uncalibrated scale knows only pressing: its default is that, not the mixture.
            families: if self.calibration == "energy-scale" && self.loads == Self::default().loads {
                vec![umesh_core::loads::LoadFamily::Pressing]
            } else {
                ForceSettings::parse_families(&self.loads)
                    .map_err(|e| WorkflowError::option_message(format!("--loads {}: {e}", self.loads)))?
            },
            // The uncalibrated scale has no linear solution to limit (and its hash stays).
            max_strain: if self.calibration == "energy-scale" { 0.0 } else { self.max_strain },
            ..Default::default()
        };
        c.forces.validate().map_err(|e| {
            WorkflowError::option_message(format!(
                "--probes/--target-displacement-mm/--target-spread/--probe-radius-mm/--max-strain/--loads: {e}"
            ))
        })?;
        require(self.visible_fraction > 0.0 && self.visible_fraction <= 1.0, || {
            format!("--visible-fraction {}: must lie in (0, 1]", self.visible_fraction)
        })?;
        c.visibility.max_fraction = self.visible_fraction;
        c.visibility.camera = self.camera(seg)?;
        c.material = MaterialParams { young_pa: self.young_pa, poisson: self.poisson, ..Default::default() };
        require(self.max_newton_iterations >= 1, || "--max-newton-iterations must be at least 1".into())?;
        c.solver.max_total_iterations = Some(self.max_newton_iterations);
        c.material.validate().map_err(|e| WorkflowError::option_message(format!("--young-pa/--poisson: {e}")))?;
        if !self.poisson_range.is_empty() || self.neo_hookean_fraction != 0.0 {
            let (lo, hi) = match self.poisson_range.as_slice() {
                [lo, hi] => (*lo, *hi),
                [] => (self.poisson, self.poisson),
                v => {
                    return Err(WorkflowError::option_message(format!(
                        "--poisson-range takes two values MIN,MAX, got {}",
                        v.len()
                    )));
                }
            };
            let v = umesh_core::fem::material::MaterialVariation {
                poisson_min: lo,
                poisson_max: hi,
                neo_hookean_fraction: self.neo_hookean_fraction,
            };
            v.validate()
                .map_err(|e| WorkflowError::option_message(format!("--poisson-range/--neo-hookean-fraction: {e}")))?;
            c.material_variation = Some(v);
        }
        Ok((c, fixed))
    }
}
