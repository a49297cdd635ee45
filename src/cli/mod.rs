//! Command-line interface: one file per command; all of them call umesh-core's `run_*`.

pub mod bench;
mod bench_page;
mod bench_register;
mod bench_sweep;
mod camera;
mod choose_correction;
pub mod dataset;
mod demo;
mod grid;
mod gui;
pub mod input;
mod output;
mod phantom;
mod prepare;
mod register;
mod rgbd;
mod screenshot;
mod simulate;
mod surface;
mod train;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

#[derive(Parser, Debug)]
#[command(
    name = "umesh",
    version,
    about = "Physics-based deep network for augmented reality in liver surgery (U-Mesh).\n\nWith no command: open the app on the bundled phantom (or, with no display, run the demo pipeline)."
)]
pub struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Open the desktop app.
    Gui(gui::Args),
    /// Render a named app scene headless to PNG (no window; EGL or Vulkan).
    Screenshot(screenshot::Args),
    /// Run the pipeline on the bundled phantom: grid, surfaces, one SVK simulation.
    Demo(demo::Args),
    /// Write the procedural liver phantom (NIfTI label volume).
    Phantom(phantom::Args),
    /// Build the immersed-boundary hexahedral grid of a segmentation.
    Grid(grid::Args),
    /// Extract label surfaces as triangle meshes (OBJ, PLY, STL).
    Surface(surface::Args),
    /// Solve a static FE problem (SVK Newton, linear or co-rotational).
    Simulate(Box<simulate::Args>),
    /// Training data: generate, merge, stats.
    Dataset(dataset::Args),
    /// Train the U-Net on a dataset (Adam, MSE; checkpoints, resume, metrics).
    Train(Box<train::Args>),
    /// One patient from segmentation to checked model: grid, dataset, training, evaluation,
    /// registration check and report.html in one resumable job.
    Prepare(Box<prepare::Args>),
    /// Target registration error of a model on a dataset's validation split.
    Eval(train::EvalArgs),
    /// Benchmarks: grid construction, FE solves, dataset generation.
    Bench(bench::Args),
    /// RGB-D recordings: synthetic ones with ground truth; serve one over TCP.
    Rgbd(rgbd::Args),
    /// Register RGB-D frames: overlays of the deformed internal structures, latency, TRE.
    Register(Box<register::Args>),
    /// Register a recording with ground truth with each correction form and keep the better
    /// one in the model folder (as `prepare`'s check does).
    ChooseCorrection(Box<choose_correction::Args>),
}

pub fn main() -> ExitCode {
    let cli = Cli::parse();
    let default =
        if gui::has_display() { Command::Gui(gui::Args::default()) } else { Command::Demo(demo::Args::default()) };
    let result = match cli.command.unwrap_or(default) {
        Command::Gui(a) => gui::run(a),
        Command::Screenshot(a) => screenshot::run(a),
        Command::Demo(a) => demo::run(a),
        Command::Phantom(a) => phantom::run(a),
        Command::Grid(a) => grid::run(a),
        Command::Surface(a) => surface::run(a),
        Command::Simulate(a) => simulate::run(*a),
        Command::Dataset(a) => dataset::run(a),
        Command::Train(a) => train::run(*a),
        Command::Eval(a) => train::eval(a),
        Command::Prepare(a) => prepare::run(*a),
        Command::Bench(a) => bench::run(a),
        Command::Rgbd(a) => rgbd::run(a),
        Command::Register(a) => register::run(*a),
        Command::ChooseCorrection(a) => choose_correction::run(*a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", error_line(&e));
            ExitCode::FAILURE
        }
    }
}

/// The error and its causes on one line, each once: a library error that names its source in
/// its own message (`{path}: {source}`) would otherwise print that source twice.
fn error_line(e: &anyhow::Error) -> String {
    let mut line = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if line.contains(&text) {
            continue;
        }
        if !line.is_empty() {
            line.push_str(": ");
        }
        line.push_str(&text);
    }
    line
}
