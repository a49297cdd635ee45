//! `umesh choose-correction`: register a recording with ground truth once with each correction
//! form and keep the one that registers it better in the model folder (`correction.json`),
//! as `umesh prepare`'s registration check does; `register` and the AR view then use it.

use super::input::{InputArgs, LoadInput, model_dataset_config, patient_model};
use anyhow::{Context, Result, bail};
use std::path::PathBuf;

#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    #[command(flatten)]
    pub input: InputArgs,
    /// Model folder; its correction.json is replaced (the bundled model is not written to
    /// unless named: copy it first).
    #[arg(long, conflicts_with = "patient", required_unless_present = "patient")]
    pub model: Option<PathBuf>,
    /// A patient folder from `umesh prepare`: its segmentation and model.
    #[arg(long, conflicts_with = "seg")]
    pub patient: Option<PathBuf>,
    /// A recording with its ground truth (`umesh rgbd synth`; ground_truth.json), best of
    /// loads the model did not train on and 10 mm or more of motion.
    #[arg(long)]
    pub recording: PathBuf,
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: Args) -> Result<()> {
    let (model_dir, seg) = match &a.patient {
        Some(p) => patient_model(p)?,
        None => (a.model.clone().context("give --model DIR or --patient DIR")?, a.input.load()?),
    };
    if !a.recording.join("ground_truth.json").is_file() {
        bail!(
            "--recording {}: no ground_truth.json (the choice is made on the TRE against the truth)",
            a.recording.display()
        );
    }
    let info =
        umesh_net::ModelInfo::read(&model_dir).with_context(|| format!("loading the model {}", model_dir.display()))?;
    let config = model_dataset_config(Some(&info), &seg);
    let (pb, progress) = super::output::progress_bar("registering with each correction form");
    let r = umesh_workflow::patient::registration_check(
        &seg,
        &config,
        &model_dir,
        &a.recording,
        &progress,
        &super::output::cancel(),
    );
    pb.finish_and_clear();
    let r = r.with_context(|| format!("--recording {}", a.recording.display()))?;
    let Some(choice) = &r.correction else {
        bail!(
            "--recording {}: fewer than two frames with a TRE; nothing chosen, {} left as it was",
            a.recording.display(),
            model_dir.display()
        )
    };
    if a.json {
        super::output::print_json(&serde_json::to_value(choice)?);
    } else {
        println!("{}", choice.describe());
        println!("written to {}", model_dir.join(umesh_core::register::correction::CorrectionChoice::FILE).display());
    }
    Ok(())
}
