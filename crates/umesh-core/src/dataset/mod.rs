//! Training data: random force probes on the visible surface, SVK solves, and sharded,
//! deterministic, resumable dataset folders.
//!
//! A dataset folder holds `manifest.json` (configuration, hashes, per-sample statistics),
//! `grid.npz` (the grid, the visible-surface nodes, the surface mesh) and `shard_NNNNNN.npz`
//! files, each covering `shard_size` consecutive sample indices. Sample i depends only on
//! (seed, i), so shards computed anywhere merge into exactly the single-run dataset.
//!
//! By concern: `config` (what a job asks for), `context` (the organ model it solves on),
//! `calibrate` (one sample), `preflight` and `check` (the pre-flight check), `generate` (the job),
//! `store` (manifest, shards, reader), `merge`, `stats`; `error` is the one error type.

mod calibrate;
mod check;
mod config;
mod context;
mod error;
mod generate;
mod merge;
mod preflight;
mod stats;
mod store;

pub use calibrate::{Rejection, SampleResult, SolvedLoad, first_load_factor, generate_sample};
pub use check::{PreflightCheck, run_preflight};
pub use config::{
    CALIBRATION_TOLERANCE, DatasetConfig, FORMAT, FORMAT_VERSION, MAX_SAMPLES, MIN_VISIBLE_FRACTION, fnv_hex,
    sample_material, segmentation_hash,
};
pub use context::{
    DatasetContext, LOCAL_STRAIN_FACTOR, LinearStrain, ObservationSetup, STRAIN_QUANTILE, observation_setup,
    organ_surface,
};
pub use error::DatasetError;
pub use generate::{GenerateReport, ShardSelection, run_generate, run_generate_checked};
pub use merge::{MergeReport, run_merge};
pub use preflight::{Preflight, PreflightSettings, wilson_upper};
pub use stats::{DatasetStats, Distribution, run_stats};
pub use store::{Dataset, Manifest, SampleRecord, ShardRecord, read_grid_npz, read_shard_records, shard_file_name};
