//! One patient from segmentation to checked model: grid, dataset (the paper's protocol),
//! training, evaluation and a synthetic-recording registration check, as one resumable job.
//!
//! The patient folder holds `patient.json` (inputs and their hashes, every setting, stage
//! status and timings), `segmentation.nii.gz` (the label volume the job used, so later
//! commands need not find the original files), `dataset/`, `model/`, `eval.json`,
//! `check/recording/` and `check/register.json`, and `report.html`. Every stage resumes from
//! what is on disk; a folder made from other inputs or settings is refused.

mod folder;
mod grid_budget;
mod page;
mod prepare;
mod prior;
mod surface_budget;
mod verdict;

pub use folder::{
    CheckReport, FORMAT, FORMAT_VERSION, InputFile, MAX_GRID_NODES, MAX_SURFACE_TRIANGLES, Patient, PatientFigures,
    PrepareReport, PrepareSettings, Prior, Stage, StageRecord, SummaryRecord, Verdict, check_model_out, ct_path,
    hash_inputs, model_dir, read_figures, read_metrics, same_as_stored, settings_differences,
};
pub use grid_budget::fit_grid_to_budget;
pub use prepare::{register_recording, registration_check, run_prepare};
pub use prior::resolve_prior;
pub use surface_budget::fit_surface_to_budget;
pub use verdict::{CHECK_MOTION_MIN_MM, CHECK_RIGID_SHARE_READY, CHECK_TRE_READY_MM, VAL_SHARE_READY, judge};
