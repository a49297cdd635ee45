//! `umesh dataset generate | merge | stats`.

use super::grid::GridArgs;
use super::input::{InputArgs, LoadInput};
use anyhow::{Context, Result};
use std::path::PathBuf;
use umesh_core::dataset::{DatasetConfig, ShardSelection, run_generate_checked, run_merge, run_stats};
use umesh_core::loads::FixedChoice;
use umesh_core::segmentation::Segmentation;
use umesh_workflow::options::DatasetOptions;

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
    pub config: DatasetOptions,
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
    /// Run the job even when the pre-flight check projects an acceptance below 90 % or
    /// samples reaching less than 75 % of their target displacement.
    #[arg(long)]
    pub force: bool,
}

impl PreflightArgs {
    pub fn settings(&self) -> Result<umesh_core::dataset::PreflightSettings> {
        let s = umesh_core::dataset::PreflightSettings { samples: self.preflight_samples, ..Default::default() };
        s.validate().context("--preflight-samples")?;
        Ok(s)
    }
}

/// Print the pre-flight figures (stderr, so `--json` output stays one document); a refused
/// job's error carries the likely cause, a forced one gets it as a warning.
pub fn print_preflight(p: &umesh_core::dataset::Preflight, forced: bool) {
    eprintln!("{}", p.summary());
    if let (true, Some(cause)) = (forced, &p.cause) {
        eprintln!("warning: run with --force; likely cause of the low acceptance or displacement: {cause}");
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

impl GenerateArgs {
    pub fn config(&self, seg: &Segmentation) -> Result<(DatasetConfig, FixedChoice)> {
        Ok(self.config.config(seg, self.grid.settings(), self.samples, self.seed, self.shard_size)?)
    }
}

pub fn run(a: Args) -> Result<()> {
    match a.command {
        Sub::Generate(g) => generate(*g),
        Sub::Merge(m) => {
            let r = run_merge(&m.inputs, &m.out)?;
            if m.json {
                super::output::print_json(&serde_json::to_value(&r)?);
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
                super::output::print_json(&serde_json::to_value(&st)?);
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
                let f: Vec<String> = st
                    .materials
                    .iter()
                    .map(|(k, n, a, lo, hi)| format!("{} {a}/{n} (Poisson {lo:.3}-{hi:.3})", k.name()))
                    .collect();
                println!("  materials (accepted/samples): {}", f.join(", "));
            }
            if let (n @ 1.., Some(f)) = (st.strain_limited, &st.strain_limited_factor) {
                println!(
                    "  targets lowered by the strain limit ({} % at the 95th percentile of the linear solution): {n}, to {:.2} of the drawn target in the median (min {:.2})",
                    st.max_strain * 100.0,
                    f.median,
                    f.min
                );
            }
            if st.below_target > 0 {
                println!(
                    "  accepted below their target (the converged state nearest an unreachable target): {}",
                    st.below_target
                );
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
                ("rejected: solve (ms)", &st.rejected_solve_ms),
            ] {
                if let Some(d) = d {
                    println!(
                        "  {name:24} {:>8.2} {:>8.2} {:>8.2} {:>8.2} {:>8.2} {:>8.2}",
                        d.min, d.p5, d.median, d.mean, d.p95, d.max
                    );
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
    // Ten million samples would take years here; the bound keeps every count and shard
    // index far from overflow.
    anyhow::ensure!(
        (1..=umesh_core::dataset::MAX_SAMPLES).contains(&a.samples),
        "--samples {}: between 1 and {}",
        a.samples,
        umesh_core::dataset::MAX_SAMPLES
    );
    let seg = a.input.load()?;
    let (config, fixed) = a.config(&seg)?;
    if !a.json {
        eprintln!("fixed region: {}", fixed.description);
    }
    let (pb, progress) = super::output::progress_bar("samples");
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
    let report =
        run_generate_checked(&seg, &a.out, &config, selection, Some(&check), &progress, &super::output::cancel());
    pb.finish_and_clear();
    let report = report.with_context(|| format!("generating the dataset in {}", a.out.display()))?;
    let stats = run_stats(&a.out).ok();
    if a.json {
        super::output::print_json(&serde_json::to_value(&report)?);
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
