//! The main job on the bundled data: phantom -> grid -> surfaces -> one SVK simulation.

use super::bench::fe_scenario;
use anyhow::{Context, Result};
use std::path::PathBuf;
use umesh_core::grid::grid_vtu;
use umesh_core::loads;
use umesh_core::mesh_io::write_mesh;
use umesh_core::simulate::{boundary_conditions, solve_bc};
use umesh_core::surface::{SurfaceSettings, extract_surface};
use umesh_core::vtk::VtkData;
use umesh_core::{Cancel, npz};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Output folder.
    #[arg(long, default_value = "out/demo")]
    pub out: PathBuf,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
}

impl Default for Args {
    fn default() -> Self {
        Self { out: "out/demo".into(), seed: 1, json: false }
    }
}

pub fn run(a: Args) -> Result<()> {
    eprintln!("umesh demo on the bundled phantom -> {}", a.out.display());
    let sc = fe_scenario(a.seed)?;
    let s = sc.grid.stats();
    let say = |line: String| {
        if !a.json {
            println!("{line}");
        }
    };
    say(format!(
        "grid: {} cells ({} boundary), {} nodes, padded {:?}, volume {:.0} mm^3 vs segmentation {:.0} mm^3",
        s.cells,
        s.boundary_cells,
        s.nodes,
        s.padded_shape,
        s.grid_volume_mm3,
        sc.seg.organ_mask().volume_mm3()
    ));
    npz::write_npz(&a.out.join("grid.npz"), &sc.grid.to_npz_arrays())?;
    let organ = extract_surface(&sc.seg.organ_mask(), &SurfaceSettings::default());
    write_mesh(&a.out.join("organ.obj"), &organ)?;
    let bc = boundary_conditions(&sc.grid, Some(&sc.seg.volume), &sc.settings)?;
    let (pb, progress) = super::output::progress_bar("SVK solve");
    let sol = solve_bc(&sc.grid, &bc, &sc.settings, &progress, &Cancel::new());
    pb.finish_and_clear();
    let sol = sol?;
    say(format!(
        "SVK solve: {} forces, {} fixed nodes, {} increments, {} Newton iterations, {:.0} ms; displacement max {:.1} mm, mean {:.1} mm",
        sc.settings.forces.len(),
        bc.fixed_count(),
        sol.increments,
        sol.iterations,
        sol.timings.total_ms,
        sol.max_displacement_mm(),
        sol.mean_displacement_mm()
    ));
    let u = &sol.displacement_mm;
    let mut vtu = grid_vtu(&sc.grid);
    vtu.point_data.push(VtkData::Vectors("displacement_mm".into(), u.clone()));
    vtu.write(&a.out.join("result.vtu")).with_context(|| format!("writing {}", a.out.join("result.vtu").display()))?;
    write_mesh(&a.out.join("organ_deformed.obj"), &loads::deform_mesh(&sc.grid, &organ, u))?;
    for &l in &sc.seg.structure_labels {
        let m = extract_surface(&sc.seg.volume.mask(&[l]), &SurfaceSettings::default());
        let name = sc.seg.label_name(l);
        write_mesh(&a.out.join(format!("{name}.obj")), &m)?;
        write_mesh(&a.out.join(format!("{name}_deformed.obj")), &loads::deform_mesh(&sc.grid, &m, u))?;
    }
    say(format!(
        "wrote grid.npz, result.vtu (open in ParaView) and rest/deformed surfaces (OBJ) to {}",
        a.out.display()
    ));
    if a.json {
        super::output::print_json(&serde_json::json!({
            "cells": s.cells, "nodes": s.nodes, "boundary_cells": s.boundary_cells, "padded_shape": s.padded_shape,
            "grid_volume_mm3": s.grid_volume_mm3, "forces": sc.settings.forces.len(), "fixed_nodes": bc.fixed_count(),
            "converged": true, "newton_iterations": sol.iterations, "solve_ms": sol.timings.total_ms,
            "max_displacement_mm": sol.max_displacement_mm(), "mean_displacement_mm": sol.mean_displacement_mm(), "out": a.out,
        }));
    }
    Ok(())
}
