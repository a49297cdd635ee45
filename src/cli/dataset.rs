//! `umesh dataset generate | merge | stats`.

use super::grid::GridArgs;
use super::input::InputArgs;
use anyhow::{Context, Result};
use std::path::PathBuf;
use umesh_core::dataset::{DatasetConfig, ShardSelection, run_generate, run_merge, run_stats};
use umesh_core::fem::{FixedRegion, MaterialParams};
use umesh_core::loads::ForceSettings;
use umesh_core::segmentation::Segmentation;

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
    /// Force probes per sample.
    #[arg(long, default_value_t = ForceSettings::default().probes)]
    pub probes: usize,
    /// Scale of the random forces (small-strain displacement they aim at, mm).
    #[arg(long, default_value_t = ForceSettings::default().target_displacement_mm)]
    pub target_displacement_mm: f64,
    /// Largest visible fraction of the organ surface.
    #[arg(long, default_value_t = 0.5)]
    pub visible_fraction: f64,
    #[arg(long, default_value_t = MaterialParams::default().young_pa)]
    pub young_pa: f64,
    #[arg(long, default_value_t = MaterialParams::default().poisson)]
    pub poisson: f64,
    /// Fix the nodes within --fix-distance-mm of this label (phantom default: 2, the vena cava;
    /// otherwise the posterior tenth of the organ is fixed).
    #[arg(long)]
    pub fix_label: Option<i64>,
    #[arg(long, default_value_t = 6.0)]
    pub fix_distance_mm: f64,
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long)]
    pub json: bool,
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

pub fn default_fixed(seg: &Segmentation, fix_label: Option<i64>, distance_mm: f64) -> FixedRegion {
    let label = fix_label.or_else(|| {
        let phantom = seg.source.to_string_lossy().contains("phantom");
        (phantom && seg.volume.label_counts().contains_key(&umesh_core::phantom::VENA_CAVA)).then_some(umesh_core::phantom::VENA_CAVA)
    });
    if let Some(label) = label {
        return FixedRegion::Label { label, distance_mm };
    }
    let (lo, hi) = seg.organ_mask().world_bounds().unwrap_or_default();
    FixedRegion::Plane { normal: [0.0, 1.0, 0.0], offset_mm: lo.y, thickness_mm: 0.1 * (hi.y - lo.y) }
}

impl GenerateArgs {
    pub fn config(&self, seg: &Segmentation) -> DatasetConfig {
        let mut c = DatasetConfig::paper(default_fixed(seg, self.fix_label, self.fix_distance_mm));
        c.samples = self.samples;
        c.seed = self.seed;
        c.shard_size = self.shard_size.max(1);
        c.grid = self.grid.settings();
        c.forces = ForceSettings { probes: self.probes, target_displacement_mm: self.target_displacement_mm, ..Default::default() };
        c.visibility.max_fraction = self.visible_fraction;
        c.material = MaterialParams { young_pa: self.young_pa, poisson: self.poisson, ..Default::default() };
        c
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
            println!("  {:24} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8}", "", "min", "p5", "median", "mean", "p95", "max");
            for (name, d) in [
                ("max displacement (mm)", &st.max_displacement_mm),
                ("mean displacement (mm)", &st.mean_displacement_mm),
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
    let config = a.config(&seg);
    let (pb, progress) = super::progress_bar("samples");
    pb.set_style(
        indicatif::ProgressStyle::with_template("{spinner} {msg} [{bar:30}] {pos}/{len} ({per_sec}, eta {eta})")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    let report = run_generate(&seg, &a.out, &config, selection, &progress, &super::cancel());
    pb.finish_and_clear();
    let report = report.with_context(|| format!("generating the dataset in {}", a.out.display()))?;
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
    }
    Ok(())
}
