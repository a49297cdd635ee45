use super::input::{InputArgs, LoadInput};
use anyhow::{Context, Result};
use std::path::PathBuf;
use umesh_core::grid::{GridSettings, grid_vtu, run_grid};

#[derive(clap::Args, Debug, Clone)]
pub struct GridArgs {
    /// Cell edge length (mm).
    #[arg(long, default_value_t = GridSettings::default().cell_size_mm)]
    pub cell_size_mm: f64,
    /// Recursive subdivision levels of boundary cells.
    #[arg(long, default_value_t = GridSettings::default().subdivisions)]
    pub subdivisions: u32,
    /// U-Net pooling steps (the padded shape is a multiple of 2^k).
    #[arg(long, default_value_t = GridSettings::default().pooling_steps)]
    pub pooling_steps: u32,
}

impl GridArgs {
    pub fn settings(&self) -> GridSettings {
        GridSettings {
            cell_size_mm: self.cell_size_mm,
            subdivisions: self.subdivisions,
            pooling_steps: self.pooling_steps,
            ..GridSettings::default()
        }
    }
}

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(flatten)]
    pub input: InputArgs,
    #[command(flatten)]
    pub grid: GridArgs,
    /// Output grid: NPZ (numpy) and a `.vtu` beside it for ParaView.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: Args) -> Result<()> {
    let seg = a.input.load()?;
    let (pb, progress) = super::output::progress_bar("building grid");
    let out = run_grid(&seg, &a.grid.settings(), &progress, &super::output::cancel())
        .with_context(|| format!("building the grid of {}", seg.source.display()))?;
    pb.finish_and_clear();
    let s = &out.stats;
    if let Some(path) = &a.out {
        umesh_core::npz::write_npz(path, &out.grid.to_npz_arrays())?;
        let vtu = path.with_extension("vtu");
        grid_vtu(&out.grid).write(&vtu).with_context(|| format!("writing {}", vtu.display()))?;
    }
    let err = (s.grid_volume_mm3 - out.segmentation_volume_mm3) / out.segmentation_volume_mm3;
    // The grid's own hash (its arrays as written); a dataset's adds its surface and camera.
    let hash = umesh_core::dataset::fnv_hex(&umesh_core::npz::encode_npz_with(&out.grid.to_npz_arrays(), false)?);
    if a.json {
        super::output::print_json(&serde_json::json!({
            "source": seg.source, "cells": s.cells, "nodes": s.nodes, "inside_cells": s.inside_cells,
            "boundary_cells": s.boundary_cells, "quadrature_points": s.quadrature_points,
            "cell_size_mm": s.cell_size_mm, "grid_volume_mm3": s.grid_volume_mm3,
            "segmentation_volume_mm3": out.segmentation_volume_mm3, "volume_error": err,
            "node_dims": s.node_dims, "padded_shape": s.padded_shape, "out": a.out,
            "organ_labels": seg.organ_labels, "grid_hash": hash,
        }));
    } else {
        println!("grid of {} (organ labels {:?})", seg.source.display(), seg.organ_labels);
        println!("  cells            {:>10} ({} inside, {} boundary)", s.cells, s.inside_cells, s.boundary_cells);
        println!("  nodes            {:>10}", s.nodes);
        println!("  grid hash        {hash:>10}");
        println!("  quadrature pts   {:>10}", s.quadrature_points);
        println!("  grid volume      {:>10.0} mm^3", s.grid_volume_mm3);
        println!("  segmentation vol {:>10.0} mm^3 (grid error {:+.2} %)", out.segmentation_volume_mm3, 100.0 * err);
        println!("  node lattice     {:?}, padded {:?}", s.node_dims, s.padded_shape);
        if let Some(p) = &a.out {
            println!("  wrote {} and {}", p.display(), p.with_extension("vtu").display());
        }
    }
    Ok(())
}
