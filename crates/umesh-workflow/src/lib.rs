//! umesh-workflow: the recipes the command line and the app share, over umesh-core and
//! umesh-net and without a front end: `input` (the organ from what a user gives, the bundled
//! model), `options` (a dataset job's options and the configuration they make), `patient` (the
//! `prepare` job, its folder and its `report.html`) and `report` (self-contained HTML pages and
//! their charts).
//! With the `clap` feature, `InputSpec` and `DatasetOptions` are also command-line argument groups.

mod error;
pub mod input;
pub mod options;
pub mod patient;
pub mod report;

pub use error::WorkflowError;
