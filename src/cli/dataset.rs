//! `umesh dataset generate | merge | stats`.

use super::grid::GridArgs;
use super::input::InputArgs;
use anyhow::{Context, Result};
use nalgebra::Vector3;
use std::path::PathBuf;
use umesh_core::dataset::{DatasetConfig, ShardSelection, run_generate_checked, run_merge, run_stats};
use umesh_core::fem::{FixedRegion, MaterialParams};
use umesh_core::grid::GridSettings;
use umesh_core::loads::{FixedChoice, ForceSettings, LoadCalibration};
use umesh_core::segmentation::Segmentation;
use umesh_core::visible::Camera;

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(subcommand)]
    pub command: Sub,
}

#[derive(clap::Subcommand, Debug)]
pub enum Sub {
    /// Generate (or resume) a dataset: random forces on the visible surface -> SVK solves.
    Generate(Box<GenerateArgs>),
    /// Join datasets made with the same configuration (e.g. shards from several machines).
    Merge(MergeArgs),
    /// Distributions, rejections and outliers of a dataset.
    Stats(StatsArgs),
}

#[derive(clap::Args, Debug)]
pub struct GenerateArgs {
    #[command(flatten)]
    pub input: InputArgs,
    #[command(flatten)]
    pub grid: GridArgs,
    #[arg(long, default_value_t = 1000)]
    pub samples: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Compute only shard files j with j % N == k ("k/N"), for clusters.
    #[arg(long)]
    pub shard: Option<String>,
    #[arg(long, default_value_t = 50)]
    pub shard_size: usize,
    #[command(flatten)]
    pub config: ConfigArgs,
    #[command(flatten)]
    pub preflight: PreflightArgs,
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long)]
    pub json: bool,
}

/// The pre-flight check before a long dataset job (`dataset generate`, `prepare`).
#[derive(clap::Args, Debug, Clone)]
pub struct PreflightArgs {
    /// Samples of the job solved in parallel before it starts, to project its acceptance and
    /// time; jobs with no more samples than this start without the check.
    #[arg(long, default_value_t = umesh_core::dataset::PreflightSettings::default().samples)]
    pub preflight_samples: usize,
    /// Run the job even when the pre-flight check projects an acceptance below 90 %.
    #[arg(long)]
    pub force: bool,
}

impl PreflightArgs {
    pub fn settings(&self) -> Result<umesh_core::dataset::PreflightSettings> {
        let s = umesh_core::dataset::PreflightSettings { samples: self.preflight_samples, ..Default::default() };
        s.validate().map_err(|e| anyhow::anyhow!("--preflight-samples: {e}"))?;
        Ok(s)
    }
}

/// Print the pre-flight figures (stderr, so `--json` output stays one document); a refused
/// job's error carries the likely cause, a forced one gets it as a warning.
pub fn print_preflight(p: &umesh_core::dataset::Preflight, forced: bool) {
    eprintln!("{}", p.summary());
    if forced && p.acceptance < umesh_core::dataset::PreflightSettings::default().min_acceptance {
        eprintln!("warning: run with --force; likely cause of the low acceptance: {}", p.cause.as_deref().unwrap_or("unknown"));
    }
}

#[derive(clap::Args, Debug)]
pub struct MergeArgs {
    /// Dataset folders to join.
    #[arg(required = true)]
    pub inputs: Vec<PathBuf>,
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
pub struct StatsArgs {
    pub dir: PathBuf,
    #[arg(long)]
    pub json: bool,
}

/// The loads, material, fixed region and camera of a dataset (shared by `dataset generate`
/// and `prepare`).
#[derive(clap::Args, Debug, Clone)]
pub struct ConfigArgs {
    /// Force probes per sample.
    #[arg(long, default_value_t = ForceSettings::default().probes)]
    pub probes: usize,
    /// Mean nodal displacement each sample's forces are calibrated for (mm), by one linear
    /// solve per sample; each sample's target is this times a factor uniform in
    /// [1 - spread, 1 + spread].
    #[arg(long, default_value_t = ForceSettings::default().target_displacement_mm)]
    pub target_displacement_mm: f64,
    #[arg(long, default_value_t = ForceSettings::default().target_spread)]
    pub target_spread: f64,
    /// Contact radius of each probe (mm): its force is spread over the surface within it
    /// (0: point loads, as datasets made before).
    #[arg(long, default_value_t = ForceSettings::default().patch_radius_mm)]
    pub probe_radius_mm: f64,
    /// Load families the samples are drawn from, each sample one of them: `mixture` (all four)
    /// or a comma-separated list of pressing (many probes), instrument (1-3 local contacts),
    /// grasp (1-2 contacts pulled) and gravity (a body force in a random direction).
    #[arg(long, default_value = "mixture")]
    pub loads: String,
    /// How forces are scaled: mean-displacement (calibrated per sample, the default) or
    /// energy-scale (F = E L D / N, as datasets made before calibration).
    #[arg(long, default_value = "mean-displacement", value_parser = ["mean-displacement", "energy-scale"])]
    pub calibration: String,
    /// Largest visible fraction of the organ surface.
    #[arg(long, default_value_t = 0.5)]
    pub visible_fraction: f64,
    #[arg(long, default_value_t = MaterialParams::default().young_pa)]
    pub young_pa: f64,
    #[arg(long, default_value_t = MaterialParams::default().poisson)]
    pub poisson: f64,
    /// Draw each sample's Poisson's ratio uniformly in MIN,MAX (for example 0.45,0.49)
    /// instead of --poisson for all; recorded per sample in the manifest.
    #[arg(long, value_delimiter = ',', value_name = "MIN,MAX")]
    pub poisson_range: Vec<f64>,
    /// The share of samples solved with a Neo-Hookean material (the others SVK).
    #[arg(long, default_value_t = 0.0)]
    pub neo_hookean_fraction: f64,
    /// Fix the nodes within --fix-distance-mm of this label. Default: the inferior vena cava
    /// or hepatic veins when the segmentation names them (TotalSegmentator's 63 next to its
    /// liver 5), else the posterior fifth of the organ.
    #[arg(long)]
    pub fix_label: Option<i64>,
    #[arg(long, default_value_t = 6.0)]
    pub fix_distance_mm: f64,
    /// Fix the nodes inside a box: xmin,ymin,zmin,xmax,ymax,zmax (world mm).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub fix_box: Vec<f64>,
    /// Fix the nodes on the negative side of a plane: nx,ny,nz,offset_mm,thickness_mm.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub fix_plane: Vec<f64>,
    /// Laparoscope view: anterior, posterior, right, left, superior, inferior, or two joined by
    /// '-' (anterior-inferior); from 2.5 organ sizes away, looking at the organ's centre.
    #[arg(long, conflicts_with = "camera_from")]
    pub camera: Option<String>,
    /// Camera position x,y,z (world mm), with --camera-to.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true, requires = "camera_to")]
    pub camera_from: Vec<f64>,
    /// Point the camera looks at, x,y,z (world mm).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true, requires = "camera_from")]
    pub camera_to: Vec<f64>,
    #[arg(long, default_value_t = 50.0)]
    pub fov_deg: f64,
    /// Newton iterations a sample may take over all its load increments before it is
    /// rejected (a sample that keeps cutting its load is about to invert).
    #[arg(long, default_value_t = DatasetConfig::paper(FixedRegion::Nodes { nodes: vec![] }).solver.max_total_iterations.unwrap_or(24))]
    pub max_newton_iterations: usize,
}

impl Default for ConfigArgs {
    /// The command line's defaults (what `umesh dataset generate` uses with no option).
    fn default() -> Self {
        #[derive(clap::Parser)]
        struct Wrapper {
            #[command(flatten)]
            c: ConfigArgs,
        }
        <Wrapper as clap::Parser>::parse_from(["umesh"]).c
    }
}

impl ConfigArgs {
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
        opt("target-displacement-mm", self.target_displacement_mm != d.target_displacement_mm, self.target_displacement_mm.to_string());
        opt("target-spread", self.target_spread != d.target_spread, self.target_spread.to_string());
        opt("probe-radius-mm", self.probe_radius_mm != d.probe_radius_mm, self.probe_radius_mm.to_string());
        opt("loads", self.loads != d.loads, self.loads.clone());
        opt("calibration", self.calibration != d.calibration, self.calibration.clone());
        opt("visible-fraction", self.visible_fraction != d.visible_fraction, self.visible_fraction.to_string());
        opt("young-pa", self.young_pa != d.young_pa, self.young_pa.to_string());
        opt("poisson", self.poisson != d.poisson, self.poisson.to_string());
        opt("poisson-range", !self.poisson_range.is_empty(), list(&self.poisson_range));
        opt("neo-hookean-fraction", self.neo_hookean_fraction != d.neo_hookean_fraction, self.neo_hookean_fraction.to_string());
        opt("fix-label", self.fix_label.is_some(), self.fix_label.map(|l| l.to_string()).unwrap_or_default());
        opt("fix-distance-mm", self.fix_distance_mm != d.fix_distance_mm, self.fix_distance_mm.to_string());
        opt("fix-box", !self.fix_box.is_empty(), list(&self.fix_box));
        opt("fix-plane", !self.fix_plane.is_empty(), list(&self.fix_plane));
        opt("camera", self.camera.is_some(), self.camera.clone().unwrap_or_default());
        opt("camera-from", !self.camera_from.is_empty(), list(&self.camera_from));
        opt("camera-to", !self.camera_to.is_empty(), list(&self.camera_to));
        opt("fov-deg", self.fov_deg != d.fov_deg, self.fov_deg.to_string());
        opt("max-newton-iterations", self.max_newton_iterations != d.max_newton_iterations, self.max_newton_iterations.to_string());
        out.join(" ")
    }

    /// The fixed region: the options given, else core's default for this segmentation.
    pub fn fixed(&self, seg: &Segmentation) -> Result<FixedChoice> {
        let finite = |v: &[f64], opt: &str| -> Result<()> {
            anyhow::ensure!(v.iter().all(|x| x.is_finite()), "{opt}: every number must be finite");
            Ok(())
        };
        if !self.fix_box.is_empty() {
            anyhow::ensure!(self.fix_box.len() == 6, "--fix-box: expected xmin,ymin,zmin,xmax,ymax,zmax (6 numbers)");
            finite(&self.fix_box, "--fix-box")?;
            let b = &self.fix_box;
            anyhow::ensure!((0..3).all(|a| b[a] < b[a + 3]), "--fix-box: each minimum must be below its maximum");
            return Ok(FixedChoice {
                region: FixedRegion::Box { min_mm: [b[0], b[1], b[2]], max_mm: [b[3], b[4], b[5]] },
                description: format!("nodes in the box {:?}..{:?} mm (chosen)", &b[..3], &b[3..]),
            });
        }
        if !self.fix_plane.is_empty() {
            anyhow::ensure!(self.fix_plane.len() == 5, "--fix-plane: expected nx,ny,nz,offset_mm,thickness_mm (5 numbers)");
            finite(&self.fix_plane, "--fix-plane")?;
            let p = &self.fix_plane;
            anyhow::ensure!(p[4] >= 0.0, "--fix-plane: the thickness must be >= 0");
            return Ok(FixedChoice {
                region: FixedRegion::Plane { normal: [p[0], p[1], p[2]], offset_mm: p[3], thickness_mm: p[4] },
                description: format!("nodes with n.x < {} mm for n = {:?} (chosen)", p[3] + p[4], &p[..3]),
            });
        }
        anyhow::ensure!(
            self.fix_distance_mm > 0.0 && self.fix_distance_mm < 1000.0,
            "--fix-distance-mm {}: must be positive and below 1 m",
            self.fix_distance_mm
        );
        if let Some(l) = self.fix_label {
            anyhow::ensure!(
                seg.volume.label_counts().contains_key(&l),
                "--fix-label {l}: {} has no voxel of that label",
                seg.source.display()
            );
        }
        Ok(umesh_core::loads::default_fixed(seg, self.fix_label, self.fix_distance_mm))
    }

    pub fn camera(&self, seg: &Segmentation) -> Result<Option<Camera>> {
        anyhow::ensure!(self.fov_deg > 0.0 && self.fov_deg < 170.0, "--fov-deg {}: must lie in (0, 170)", self.fov_deg);
        if !self.camera_from.is_empty() {
            anyhow::ensure!(
                self.camera_from.len() == 3 && self.camera_to.len() == 3,
                "--camera-from and --camera-to: x,y,z (3 numbers each)"
            );
            let (f, t) = (Vector3::from_column_slice(&self.camera_from), Vector3::from_column_slice(&self.camera_to));
            anyhow::ensure!(f.iter().chain(t.iter()).all(|v| v.is_finite()), "--camera-from/--camera-to: numbers must be finite");
            anyhow::ensure!((f - t).norm() > 1e-6, "--camera-from and --camera-to are the same point");
            return Ok(Some(Camera::look_at(&f, &t, self.fov_deg)));
        }
        let Some(view) = &self.camera else { return Ok(None) };
        let (lo, hi) = seg.organ_mask().world_bounds().context("the organ mask is empty")?;
        let mut c = Camera::named(view, &lo, &hi).map_err(|e| anyhow::anyhow!("--camera: {e}"))?;
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
    ) -> Result<(DatasetConfig, FixedChoice)> {
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
            calibration: if self.calibration == "energy-scale" { LoadCalibration::EnergyScale } else { LoadCalibration::MeanDisplacement },
            // The uncalibrated scale knows only pressing: its default is that, not the mixture.
            families: if self.calibration == "energy-scale" && self.loads == Self::default().loads {
                vec![umesh_core::loads::LoadFamily::Pressing]
            } else {
                ForceSettings::parse_families(&self.loads).map_err(|e| anyhow::anyhow!("--loads {}: {e}", self.loads))?
            },
            ..Default::default()
        };
        c.forces
            .validate()
            .map_err(|e| anyhow::anyhow!("--probes/--target-displacement-mm/--target-spread/--probe-radius-mm/--loads: {e}"))?;
        anyhow::ensure!(
            self.visible_fraction > 0.0 && self.visible_fraction <= 1.0,
            "--visible-fraction {}: must lie in (0, 1]",
            self.visible_fraction
        );
        c.visibility.max_fraction = self.visible_fraction;
        c.visibility.camera = self.camera(seg)?;
        c.material = MaterialParams { young_pa: self.young_pa, poisson: self.poisson, ..Default::default() };
        anyhow::ensure!(self.max_newton_iterations >= 1, "--max-newton-iterations must be at least 1");
        c.solver.max_total_iterations = Some(self.max_newton_iterations);
        c.material.validate().map_err(|e| anyhow::anyhow!("--young-pa/--poisson: {e}"))?;
        if !self.poisson_range.is_empty() || self.neo_hookean_fraction != 0.0 {
            let (lo, hi) = match self.poisson_range.as_slice() {
                [lo, hi] => (*lo, *hi),
                [] => (self.poisson, self.poisson),
                v => anyhow::bail!("--poisson-range takes two values MIN,MAX, got {}", v.len()),
            };
            let v = umesh_core::fem::material::MaterialVariation {
                poisson_min: lo,
                poisson_max: hi,
                neo_hookean_fraction: self.neo_hookean_fraction,
            };
            v.validate().map_err(|e| anyhow::anyhow!("--poisson-range/--neo-hookean-fraction: {e}"))?;
            c.material_variation = Some(v);
        }
        Ok((c, fixed))
    }
}

/// The default fixed region of a segmentation (core's rule), for callers without options.
pub fn default_fixed(seg: &Segmentation, fix_label: Option<i64>, distance_mm: f64) -> FixedRegion {
    umesh_core::loads::default_fixed(seg, fix_label, distance_mm).region
}

impl GenerateArgs {
    pub fn config(&self, seg: &Segmentation) -> Result<(DatasetConfig, FixedChoice)> {
        self.config.config(seg, self.grid.settings(), self.samples, self.seed, self.shard_size)
    }
}

pub fn run(a: Args) -> Result<()> {
    match a.command {
        Sub::Generate(g) => generate(*g),
        Sub::Merge(m) => {
            let r = run_merge(&m.inputs, &m.out)?;
            if m.json {
                super::print_json(&serde_json::to_value(&r)?);
            } else {
                println!(
                    "merged {} shards ({} samples, {} accepted) into {}; complete: {}",
                    r.shards,
                    r.samples,
                    r.accepted,
                    r.out.display(),
                    r.complete
                );
            }
            Ok(())
        }
        Sub::Stats(s) => {
            let st = run_stats(&s.dir).with_context(|| format!("reading the dataset {}", s.dir.display()))?;
            if s.json {
                super::print_json(&serde_json::to_value(&st)?);
                return Ok(());
            }
            println!(
                "{}: {} samples, {} accepted, {} flagged, complete: {}",
                s.dir.display(),
                st.samples,
                st.accepted,
                st.flagged,
                st.complete
            );
            for (why, n) in &st.rejected {
                println!("  rejected ({why}): {n}");
            }
            if !st.families.is_empty() {
                let f: Vec<String> = st.families.iter().map(|(f, n, a)| format!("{} {a}/{n}", f.name())).collect();
                println!("  load families (accepted/samples): {}", f.join(", "));
            }
            if !st.materials.is_empty() {
                let f: Vec<String> =
                    st.materials.iter().map(|(k, n, a, lo, hi)| format!("{} {a}/{n} (Poisson {lo:.3}-{hi:.3})", k.name())).collect();
                println!("  materials (accepted/samples): {}", f.join(", "));
            }
            if st.below_target > 0 {
                println!("  accepted below their target (the converged state nearest an unreachable target): {}", st.below_target);
            }
            println!("  {:24} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8}", "", "min", "p5", "median", "mean", "p95", "max");
            println!(
                "  target mean displacement {} mm ({:?}, over {} nodes)",
                st.target_displacement_mm,
                st.calibration,
                if st.mean_over.is_all() { "all" } else { "the free" }
            );
            for (name, d) in [
                ("max displacement (mm)", &st.max_displacement_mm),
                ("mean displacement (mm)", &st.mean_displacement_mm),
                ("achieved / target", &st.achieved_over_target),
                ("Newton iterations", &st.newton_iterations),
                ("solve time (ms)", &st.solve_ms),
            ] {
                if let Some(d) = d {
                    println!("  {name:24} {:>8.2} {:>8.2} {:>8.2} {:>8.2} {:>8.2} {:>8.2}", d.min, d.p5, d.median, d.mean, d.p95, d.max);
                }
            }
            if st.outliers.is_empty() {
                println!("  no outliers");
            }
            for (i, why) in &st.outliers {
                println!("  outlier: sample {i}: {why}");
            }
            Ok(())
        }
    }
}

fn generate(a: GenerateArgs) -> Result<()> {
    let selection = match &a.shard {
        Some(s) => ShardSelection::parse(s).with_context(|| format!("--shard {s:?}: expected k/N with 0 <= k < N"))?,
        None => ShardSelection::all(),
    };
    anyhow::ensure!(a.samples > 0, "--samples must be positive");
    let seg = a.input.load()?;
    let (config, fixed) = a.config(&seg)?;
    if !a.json {
        eprintln!("fixed region: {}", fixed.description);
    }
    let (pb, progress) = super::progress_bar("samples");
    pb.set_style(
        indicatif::ProgressStyle::with_template("{spinner} {msg} [{bar:30}] {pos}/{len} ({per_sec}, eta {eta})")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    let check = umesh_core::dataset::PreflightCheck {
        settings: a.preflight.settings()?,
        force: a.preflight.force,
        report: &|p: &umesh_core::dataset::Preflight| {
            pb.suspend(|| print_preflight(p, a.preflight.force));
        },
    };
    let report = run_generate_checked(&seg, &a.out, &config, selection, Some(&check), &progress, &super::cancel());
    pb.finish_and_clear();
    let report = report.with_context(|| format!("generating the dataset in {}", a.out.display()))?;
    let stats = run_stats(&a.out).ok();
    if a.json {
        super::print_json(&serde_json::to_value(&report)?);
    } else {
        println!(
            "{}: {} samples computed ({} reused), {} accepted in total, rejected {:?}; {:.1} samples/min; complete: {}",
            report.out.display(),
            report.samples_computed,
            report.samples_reused,
            report.accepted,
            report.rejected,
            report.samples_per_minute,
            report.complete
        );
        if let Some(m) = stats.as_ref().and_then(|s| s.mean_displacement_mm.clone()) {
            println!(
                "mean displacement of the free nodes {:.2} mm on average (p5 {:.2}, p95 {:.2}) for a target of {} mm",
                m.mean, m.p5, m.p95, config.forces.target_displacement_mm
            );
        }
    }
    Ok(())
}
