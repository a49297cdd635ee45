//! `umesh train` and `umesh eval`.

use anyhow::{Context, Result};
use std::path::PathBuf;
use umesh_net::TrainSettings;
use umesh_net::UNetConfig;
use umesh_net::training::run_train;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Dataset folder written by `umesh dataset generate`.
    #[arg(long)]
    pub dataset: PathBuf,
    /// Model folder (model.json, model.safetensors, last.safetensors, metrics.jsonl).
    #[arg(long, default_value = "out/model")]
    pub out: PathBuf,
    /// Network size: "cpu" (3 steps, 8 channels) or "paper" (3 steps, 128 channels).
    #[arg(long, default_value = "cpu")]
    pub preset: String,
    /// Override the first layer's channels.
    #[arg(long)]
    pub channels: Option<usize>,
    #[arg(long)]
    pub steps: Option<usize>,
    #[arg(long, default_value_t = TrainSettings::default().epochs)]
    pub epochs: usize,
    #[arg(long, default_value_t = TrainSettings::default().batch_size)]
    pub batch_size: usize,
    #[arg(long, default_value_t = TrainSettings::default().learning_rate)]
    pub learning_rate: f64,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Continue from `last.safetensors` and `metrics.jsonl` in --out.
    #[arg(long)]
    pub resume: bool,
    /// Network input: "exact" (the visible nodes' displacement u_s), or the dataset's simulated
    /// camera views encoded by "nearest" (nearest-point normal offsets) or "corner" (cell-corner
    /// mean offsets), as registration encodes each frame.
    #[arg(long, default_value = "corner")]
    pub input: String,
    /// Train on the stored camera view of each sample only (default: a new simulated view of
    /// each training sample every epoch after the first).
    #[arg(long)]
    pub stored_views: bool,
    /// With new views each epoch: the fraction of training samples seen undeformed, with a
    /// zero target, so the network learns that an organ at rest has not moved (0 to 0.5).
    #[arg(long, default_value_t = TrainSettings::default().rest_views)]
    pub rest_views: f64,
    /// Start from this model folder's weights and normalisation (fine-tuning; the same network,
    /// input and grid).
    #[arg(long)]
    pub init_from: Option<PathBuf>,
    /// Start from the weights of a model of another organ (a prior; the same network and
    /// input, any grid), e.g. the bundled `assets/model`.
    #[arg(long, conflicts_with = "init_from")]
    pub prior: Option<PathBuf>,
    /// Stop before an epoch that would end after this many minutes of training (0: no limit);
    /// the best epoch's weights are the model either way.
    #[arg(long, default_value_t = 0.0)]
    pub time_budget_min: f64,
    #[command(flatten)]
    pub schedule: ScheduleArgs,
    #[arg(long)]
    pub json: bool,
}

/// When training stops and how its learning rate moves (shared by `train` and `prepare`).
#[derive(clap::Args, Debug, Clone)]
pub struct ScheduleArgs {
    /// The learning rate over the epochs: "constant", or "cosine" (down to 5 % of it at the
    /// last planned epoch: the epochs asked, or the last that fits the time budget).
    #[arg(long, default_value = "constant")]
    pub lr_schedule: String,
    /// Stop when the validation loss has not improved for this many epochs (0: never).
    #[arg(long, default_value_t = 0)]
    pub patience: usize,
}

impl ScheduleArgs {
    pub fn apply(&self, settings: &mut TrainSettings) -> Result<()> {
        settings.lr_schedule = umesh_net::LrSchedule::parse(&self.lr_schedule).context("--lr-schedule")?;
        settings.patience = self.patience;
        Ok(())
    }
}

/// `--time-budget-min` (of `train` and `prepare`) in seconds; 0: none.
pub fn budget_seconds(minutes: f64) -> Result<f64> {
    anyhow::ensure!(minutes.is_finite() && minutes >= 0.0, "--time-budget-min {minutes}: a number of minutes >= 0");
    Ok(minutes * 60.0)
}

#[derive(clap::Args, Debug)]
pub struct EvalArgs {
    /// Model folder (default: the bundled phantom model).
    #[arg(long, default_value = "assets/model")]
    pub model: PathBuf,
    #[arg(long)]
    pub dataset: PathBuf,
    #[arg(long, default_value_t = 10)]
    pub markers: usize,
    /// Also write the report as JSON to this file.
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Also measure the confidence figures on the validation views and write them to the
    /// model folder (`confidence.json`, what registration compares every frame with; training
    /// writes it too).
    #[arg(long)]
    pub calibrate: bool,
    #[arg(long)]
    pub json: bool,
}

/// `--input`: "exact" (u_s) or an observation encoding.
pub fn parse_input(s: &str) -> Result<Option<umesh_core::observation::ObservationSettings>> {
    Ok(match s {
        "exact" => None,
        e => Some(umesh_core::observation::ObservationSettings {
            encoding: umesh_core::observation::Encoding::parse(e)
                .map_err(|m| anyhow::anyhow!("--input: {m} (or exact)"))?,
            ..Default::default()
        }),
    })
}

pub fn run(a: Args) -> Result<()> {
    umesh_workflow::patient::check_model_out(&a.out, &a.dataset).map_err(|e| anyhow::anyhow!("--out {e}"))?;
    let mut model = match a.preset.as_str() {
        "cpu" => UNetConfig::cpu(),
        "paper" => UNetConfig::paper(),
        p => anyhow::bail!("unknown preset {p:?} (cpu, paper)"),
    };
    if let Some(c) = a.channels {
        model.channels = c;
    }
    if let Some(s) = a.steps {
        model.steps = s;
    }
    let observation = parse_input(&a.input)?;
    let mut settings = TrainSettings {
        model,
        epochs: a.epochs,
        batch_size: a.batch_size,
        learning_rate: a.learning_rate,
        seed: a.seed,
        observation,
        fresh_views: !a.stored_views,
        rest_views: a.rest_views,
        init_from: a.init_from.clone(),
        prior: a.prior.clone(),
        ..Default::default()
    };
    a.schedule.apply(&mut settings)?;
    settings.time_budget_s = budget_seconds(a.time_budget_min)?;
    let (pb, progress) = super::output::progress_bar("training");
    let quiet = a.json;
    let pb2 = pb.clone();
    let on_epoch = move |m: &umesh_net::training::EpochMetrics| {
        if !quiet {
            pb2.println(format!(
                "epoch {:3}: train loss {:.4e}, val loss {:.4e}, val TRE mean {:.2} mm (max {:.2}), {:.1} s",
                m.epoch, m.train_loss, m.val_loss, m.val_tre_mean_mm, m.val_tre_max_mm, m.seconds
            ));
        }
    };
    let report = run_train(&a.dataset, &a.out, &settings, a.resume, &progress, &on_epoch, &super::output::cancel());
    pb.finish_and_clear();
    let report = report.with_context(|| format!("training on {}", a.dataset.display()))?;
    if a.json {
        super::output::print_json(&serde_json::to_value(&report)?);
    } else {
        println!(
            "model in {} (best epoch {}; {} train / {} validation samples)",
            report.out.display(),
            report.best_epoch,
            report.train_samples,
            report.val_samples
        );
        if let Some(why) = &report.stopped_early {
            println!("stopped early: {why}");
        }
    }
    Ok(())
}

pub fn eval(a: EvalArgs) -> Result<()> {
    let r = umesh_net::eval::run_eval(&a.model, &a.dataset, a.markers)
        .with_context(|| format!("evaluating {}", a.model.display()))?;
    let mut v = serde_json::json!({
        "samples": r.samples, "markers_per_sample": r.markers_per_sample, "tre_mean_mm": r.tre_mean_mm, "tre_std_mm": r.tre_std_mm,
        "tre_max_mm": r.tre_max_mm, "marker_displacement_mean_mm": r.marker_displacement_mean_mm,
    });
    if a.calibrate {
        let (pb, progress) = super::output::progress_bar("confidence");
        let c = umesh_net::eval::calibrate_confidence(&a.model, &a.dataset, &progress);
        pb.finish_and_clear();
        let c = c.with_context(|| format!("calibrating the confidence of {}", a.model.display()))?;
        umesh_net::eval::write_confidence(&a.model, &c)?;
        if !a.json {
            println!(
                "confidence range          residual p95 <= {:.2} mm, mean <= {:.2} mm, coverage >= {:.1} %, surface motion <= {:.1} mm ({} views): {}",
                c.residual_p95_mm,
                c.residual_mean_mm,
                100.0 * c.coverage_min,
                c.displacement_max_mm,
                c.views,
                a.model.join(umesh_core::register::confidence::ConfidenceReference::FILE).display()
            );
        }
        v["confidence"] = serde_json::to_value(&c)?;
    }
    if let Some(p) = &a.report {
        umesh_core::write_atomic(p, serde_json::to_string_pretty(&r)?.as_bytes())
            .with_context(|| format!("--report {}", p.display()))?;
    }
    if a.json {
        super::output::print_json(&v);
    } else {
        println!("validation samples        {}", r.samples);
        println!("TRE (mm)                  {:.2} +/- {:.2}, max {:.2}", r.tre_mean_mm, r.tre_std_mm, r.tre_max_mm);
        println!("marker displacement (mm)  {:.2} mean", r.marker_displacement_mean_mm);
    }
    Ok(())
}
