//! Benchmarks as commands, so they run on any machine with the release binary.

use super::input::PHANTOM_BYTES;
use anyhow::Result;
use nalgebra::{Matrix4, Vector3};
use std::time::Instant;
use umesh_core::fem::solver::FeSolver;
use umesh_core::fem::{MaterialParams, SolveMethod, SolverSettings};
use umesh_core::grid::{GridSettings, ImmersedGrid, run_grid};
use umesh_core::loads::{self, ForceSettings};
use umesh_core::segmentation::{Segmentation, bundled_phantom};
use umesh_core::simulate::{SimulationSettings, boundary_conditions};
use umesh_core::surface::{SurfaceSettings, extract_surface};
use umesh_core::volume::Volume;
use umesh_core::{Cancel, Progress};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// What to measure: grid or fe.
    pub what: String,
    /// Repetitions (the median is reported).
    #[arg(long, default_value_t = 3)]
    pub repeat: usize,
    #[arg(long)]
    pub json: bool,
}

/// Peak resident memory of this process (MB), from /proc.
pub fn peak_memory_mb() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

pub fn run(a: Args) -> Result<()> {
    let repeat = a.repeat.max(1);
    let value = match a.what.as_str() {
        "grid" => bench_grid(repeat)?,
        "fe" => bench_fe(repeat)?,
        w => anyhow::bail!("unknown benchmark {w:?} (grid, fe)"),
    };
    if a.json {
        super::print_json(&value);
    } else if let serde_json::Value::Object(m) = &value {
        for (k, v) in m {
            println!("{k:28} {v}");
        }
    }
    Ok(())
}

/// Grid construction from a 512 x 512 x 110 label volume (0.7 x 0.7 x 2.0 mm, a typical CT).
fn bench_grid(repeat: usize) -> Result<serde_json::Value> {
    let dims = [512, 512, 110];
    let spacing = Vector3::new(0.7, 0.7, 2.0);
    let mut m = Matrix4::new_nonuniform_scaling(&spacing);
    let centre = Vector3::new(dims[0] as f64, dims[1] as f64, dims[2] as f64).component_mul(&spacing) * 0.5;
    for i in 0..3 {
        m[(i, 3)] = -centre[i];
    }
    let mut vol = Volume::new(dims, m);
    let [nx, ny, _] = dims;
    use rayon::prelude::*;
    vol.data.par_chunks_mut(nx * ny).enumerate().for_each(|(k, slab)| {
        for j in 0..ny {
            for i in 0..nx {
                let p = m.transform_point(&nalgebra::Point3::new(i as f64, j as f64, k as f64)).coords;
                slab[i + nx * j] = if umesh_core::phantom::liver_sdf(p) < 0.0 { 1.0 } else { 0.0 };
            }
        }
    });
    let seg = Segmentation { source: "bench".into(), volume: vol, organ_labels: vec![1], structure_labels: vec![] };
    let mut times = Vec::new();
    let mut last = None;
    for _ in 0..repeat {
        let t = Instant::now();
        let out = run_grid(&seg, &GridSettings::default(), &Progress::none(), &Cancel::new())?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
        last = Some(out);
    }
    let out = last.ok_or_else(|| anyhow::anyhow!("no run"))?;
    Ok(serde_json::json!({
        "volume_dims": dims, "cells": out.stats.cells, "nodes": out.stats.nodes,
        "grid_ms": median(times), "threads": rayon::current_num_threads(), "peak_memory_mb": peak_memory_mb(),
    }))
}

pub struct FeScenario {
    pub seg: Segmentation,
    pub grid: ImmersedGrid,
    pub settings: SimulationSettings,
}

/// The paper-size scenario: the bundled phantom, the default grid, 100 random forces on the
/// visible (anterior) surface, nodes near the vena cava fixed.
pub fn fe_scenario(seed: u64) -> Result<FeScenario> {
    let seg = bundled_phantom(PHANTOM_BYTES)?;
    let grid = run_grid(&seg, &GridSettings::default(), &Progress::none(), &Cancel::new())?.grid;
    let material = MaterialParams::default();
    let organ = extract_surface(&seg.organ_mask(), &SurfaceSettings { step: 2, ..Default::default() });
    let forces = loads::visible_random_forces(&organ, &grid, &material, &ForceSettings::default(), &Default::default(), seed)
        .map_err(anyhow::Error::msg)?;
    let fixed = vec![loads::default_fixed_region(&grid, Some(umesh_core::phantom::VENA_CAVA), 6.0)];
    let settings = SimulationSettings { material, solver: SolverSettings::default(), method: SolveMethod::Newton, fixed, forces };
    Ok(FeScenario { seg, grid, settings })
}

fn bench_fe(repeat: usize) -> Result<serde_json::Value> {
    let sc = fe_scenario(1)?;
    let bc = boundary_conditions(&sc.grid, Some(&sc.seg.volume), &sc.settings)?;
    let t = Instant::now();
    let mut solver = FeSolver::new(&sc.grid, sc.settings.material, &bc.fixed, sc.settings.solver.clone())?;
    let setup_ms = t.elapsed().as_secs_f64() * 1e3;
    let mut run = |method| -> Result<Vec<umesh_core::fem::Solution>> {
        // One warm-up solve computes the symbolic factorisation, as dataset generation does once.
        solver.solve(&bc, method, &Progress::none(), &Cancel::new())?;
        (0..repeat).map(|_| Ok(solver.solve(&bc, method, &Progress::none(), &Cancel::new())?)).collect()
    };
    let svk = run(SolveMethod::Newton)?;
    let lin = run(SolveMethod::Linear)?;
    let cor = run(SolveMethod::Corotational)?;
    let med = |v: &[umesh_core::fem::Solution], f: &dyn Fn(&umesh_core::fem::Solution) -> f64| median(v.iter().map(f).collect());
    let s0 = &svk[0];
    let stats = sc.grid.stats();
    Ok(serde_json::json!({
        "cells": stats.cells, "nodes": stats.nodes, "padded_shape": stats.padded_shape,
        "free_dofs": solver.free_dofs(), "nnz": solver.nnz(), "fixed_nodes": bc.fixed_count(), "forces": sc.settings.forces.len(),
        "setup_ms": setup_ms,
        "svk_solve_ms": med(&svk, &|s| s.timings.total_ms),
        "svk_assembly_ms": med(&svk, &|s| s.timings.assembly_ms),
        "svk_factorization_ms": med(&svk, &|s| s.timings.factorization_ms),
        "svk_linear_solve_ms": med(&svk, &|s| s.timings.solve_ms),
        "svk_newton_iterations": s0.iterations, "svk_increments": s0.increments,
        "svk_max_displacement_mm": s0.max_displacement_mm(),
        "corotational_solve_ms": med(&cor, &|s| s.timings.total_ms),
        "corotational_iterations": cor[0].iterations,
        "linear_solve_ms": med(&lin, &|s| s.timings.total_ms),
        "linear_max_displacement_mm": lin[0].max_displacement_mm(),
        "corotational_max_displacement_mm": cor[0].max_displacement_mm(),
        "threads": rayon::current_num_threads(),
        "peak_memory_mb": peak_memory_mb(),
    }))
}
