use super::grid::GridArgs;
use super::input::{InputArgs, LoadInput};
use anyhow::{Context, Result, bail};
use nalgebra::Vector3;
use std::path::{Path, PathBuf};
use umesh_core::fem::problem_io::{read_problem, write_problem};
use umesh_core::fem::{FixedRegion, MaterialKind, MaterialParams, SolveMethod, SolverSettings};
use umesh_core::grid::{ImmersedGrid, grid_vtu, run_grid};
use umesh_core::loads::{self, ForceSettings, PointForce};
use umesh_core::npz::{Array, Npz, write_npz};
use umesh_core::segmentation::Segmentation;
use umesh_core::simulate::{SimulationSettings, boundary_conditions, solve_bc};
use umesh_core::surface::{SurfaceSettings, extract_surface};
use umesh_core::vtk::VtkData;

#[derive(clap::Args, Debug, Clone)]
pub struct FeArgs {
    /// Material: svk, linear or neo-hookean.
    #[arg(long, default_value = "svk")]
    pub material: String,
    /// Young's modulus (Pa).
    #[arg(long, default_value_t = MaterialParams::default().young_pa)]
    pub young_pa: f64,
    /// Poisson's ratio.
    #[arg(long, default_value_t = MaterialParams::default().poisson)]
    pub poisson: f64,
    /// Solver: newton, linear or corotational.
    #[arg(long, default_value = "newton")]
    pub method: String,
    /// Initial number of load increments (halved adaptively on failure), 1 to 1000.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=1000))]
    pub increments: u32,
    #[arg(long, default_value_t = SolverSettings::default().max_iterations)]
    pub max_iterations: usize,
}

impl FeArgs {
    pub fn material(&self) -> Result<MaterialParams> {
        let kind = MaterialKind::parse(&self.material)
            .with_context(|| format!("unknown material {:?} (svk, linear, neo-hookean)", self.material))?;
        let m = MaterialParams { kind, young_pa: self.young_pa, poisson: self.poisson };
        m.validate()?;
        Ok(m)
    }
    pub fn method(&self) -> Result<SolveMethod> {
        Ok(match self.method.as_str() {
            "newton" | "svk" => SolveMethod::Newton,
            "linear" => SolveMethod::Linear,
            "corotational" | "co-rotational" => SolveMethod::Corotational,
            m => bail!("unknown method {m:?} (newton, linear, corotational)"),
        })
    }
    pub fn solver(&self) -> SolverSettings {
        SolverSettings {
            initial_increments: self.increments as usize,
            max_iterations: self.max_iterations,
            ..Default::default()
        }
    }
}

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(flatten)]
    pub input: InputArgs,
    #[command(flatten)]
    pub grid: GridArgs,
    #[command(flatten)]
    pub fe: FeArgs,
    /// A grid written by `umesh grid` (instead of building one).
    #[arg(long)]
    pub grid_file: Option<PathBuf>,
    /// Solve a problem file written by --export-problem (or by another program).
    #[arg(long)]
    pub problem: Option<PathBuf>,
    /// Fix the nodes within --fix-distance-mm of this label (phantom default: 2, the vena cava).
    #[arg(long)]
    pub fix_label: Option<i64>,
    #[arg(long, default_value_t = 6.0)]
    pub fix_distance_mm: f64,
    /// Fix the nodes in a box: xmin,ymin,zmin,xmax,ymax,zmax (mm).
    #[arg(long, value_delimiter = ',', num_args = 6)]
    pub fix_box: Vec<f64>,
    /// Fix the nodes below a plane: nx,ny,nz,offset_mm,thickness_mm.
    #[arg(long, value_delimiter = ',', num_args = 5)]
    pub fix_plane: Vec<f64>,
    /// Fix these node numbers.
    #[arg(long, value_delimiter = ',')]
    pub fix_nodes: Vec<usize>,
    /// JSON file of forces: [{"point_mm": [x,y,z], "force_n": [fx,fy,fz]}, ...].
    #[arg(long)]
    pub forces: Option<PathBuf>,
    /// Without --forces: this many random forces on the visible surface.
    #[arg(long, default_value_t = 100)]
    pub random_forces: usize,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// With random forces: the mean displacement of the free nodes a linear solve of them gives
    /// (mm); each is spread over the datasets' probe contact radius and the set scaled to it.
    #[arg(long, default_value_t = 3.0)]
    pub target_displacement_mm: f64,
    /// Output folder: displacement.npz, result.vtu, deformed structure meshes, history.json.
    #[arg(long, default_value = "out/simulate")]
    pub out: PathBuf,
    /// Also write the discrete problem (see the README) to this NPZ file.
    #[arg(long)]
    pub export_problem: Option<PathBuf>,
    #[arg(long)]
    pub json: bool,
}

fn read_forces(path: &Path) -> Result<Vec<PointForce>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let v: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?;
    let list = v.get("forces").cloned().unwrap_or(v);
    let forces: Vec<PointForce> = serde_json::from_value(list).with_context(|| {
        format!("{}: expected a list of {{\"point_mm\": [x,y,z], \"force_n\": [fx,fy,fz]}}", path.display())
    })?;
    anyhow::ensure!(
        forces.iter().all(|f| f.point_mm.iter().chain(&f.force_n).all(|x| x.is_finite())),
        "{}: a force has a non-finite value",
        path.display()
    );
    Ok(forces)
}

pub fn fixed_regions(a: &Args, seg: &Segmentation) -> Vec<FixedRegion> {
    let mut regions = Vec::new();
    if let Some(l) = a.fix_label {
        regions.push(FixedRegion::Label { label: l, distance_mm: a.fix_distance_mm });
    }
    if a.fix_box.len() == 6 {
        regions.push(FixedRegion::Box {
            min_mm: [a.fix_box[0], a.fix_box[1], a.fix_box[2]],
            max_mm: [a.fix_box[3], a.fix_box[4], a.fix_box[5]],
        });
    }
    if a.fix_plane.len() == 5 {
        let p = &a.fix_plane;
        regions.push(FixedRegion::Plane { normal: [p[0], p[1], p[2]], offset_mm: p[3], thickness_mm: p[4] });
    }
    if !a.fix_nodes.is_empty() {
        regions.push(FixedRegion::Nodes { nodes: a.fix_nodes.clone() });
    }
    if regions.is_empty() {
        regions.push(loads::default_fixed(seg, None, a.fix_distance_mm).region);
    }
    regions
}

pub fn run(a: Args) -> Result<()> {
    let cancel = super::output::cancel();
    let method = a.fe.method()?;
    // Outputs go to a staging folder swapped in whole at the end (a failure leaves the last
    // run's folder as it was); made first, so a folder umesh did not write is refused before any work.
    let mut inputs = a.input.paths();
    inputs.extend(a.problem.iter().map(|p| ("--problem", p.as_path())));
    inputs.extend(a.forces.iter().map(|p| ("--forces", p.as_path())));
    umesh_core::check_apart(&a.out, &inputs)?;
    let staged = umesh_core::StagedDir::new(&a.out, umesh_core::OutputKind::Simulation, &["displacement.npz"])
        .with_context(|| format!("--out {}", a.out.display()))?;
    if let Some(p) = &a.problem {
        return run_problem(&a, p, method, staged);
    }
    let material = a.fe.material()?;
    let seg = a.input.load()?;
    let grid = match &a.grid_file {
        Some(g) => ImmersedGrid::from_npz(&Npz::read(g)?)?,
        None => run_grid(&seg, &a.grid.settings(), &umesh_core::Progress::none(), &cancel)?.grid,
    };
    let organ = extract_surface(&seg.organ_mask(), &SurfaceSettings { step: 2, ..Default::default() });
    let mut settings = SimulationSettings {
        material,
        solver: a.fe.solver(),
        method,
        fixed: fixed_regions(&a, &seg),
        forces: Vec::new(),
    };
    // The fixed region once: the random forces are calibrated on it, then loaded onto it.
    let mut bc = boundary_conditions(&grid, Some(&seg.volume), &settings)?;
    let mut calibration = None;
    settings.forces = match &a.forces {
        Some(f) => read_forces(f)?,
        None => {
            let (forces, scale) = umesh_core::simulate::calibrated_random_forces(
                &grid,
                &organ,
                &bc,
                &settings,
                a.random_forces,
                a.target_displacement_mm,
                a.seed,
                &cancel,
            )
            .context("--random-forces/--target-displacement-mm")?;
            calibration = Some(scale);
            forces
        }
    };
    loads::apply_forces(&grid, &mut bc, &settings.forces)
        .map_err(|e| umesh_core::simulate::SimulateError::Boundary(e.into()))?;
    if let Some(s) = calibration
        && !a.json
    {
        eprintln!(
            "{} random forces on the visible surface, spread over {} mm contacts and scaled x{s:.3e} for a {} mm mean linear displacement of the free nodes",
            a.random_forces,
            ForceSettings::default().patch_radius_mm,
            a.target_displacement_mm
        );
    }
    if let Some(p) = &a.export_problem {
        write_problem(p, &grid, &material, &bc, settings.solver.stabilization)?;
    }
    let (pb, progress) = super::output::progress_bar("solving");
    let sol = solve_bc(&grid, &bc, &settings, &progress, &cancel);
    pb.finish_and_clear();
    let sol = sol?;
    let dir = staged.path();
    let u = &sol.displacement_mm;
    write_npz(
        &dir.join("displacement.npz"),
        &[
            (
                "nodes",
                Array::f64(vec![u.len(), 3], grid.node_positions().iter().flat_map(|p| [p.x, p.y, p.z]).collect()),
            ),
            ("displacement_mm", Array::f64(vec![u.len(), 3], u.iter().flat_map(|d| [d.x, d.y, d.z]).collect())),
            ("forces_n", Array::f64(vec![u.len(), 3], bc.forces_n.iter().flat_map(|d| [d.x, d.y, d.z]).collect())),
            (
                "fixed",
                Array::i64(
                    vec![bc.fixed_count()],
                    bc.fixed.iter().enumerate().filter(|x| *x.1).map(|x| x.0 as i64).collect(),
                ),
            ),
        ],
    )?;
    let mut vtu = grid_vtu(&grid);
    vtu.point_data.push(VtkData::Vectors("displacement_mm".into(), u.clone()));
    vtu.point_data.push(VtkData::Vectors("force_n".into(), bc.forces_n.clone()));
    vtu.point_data.push(VtkData::Scalars("fixed".into(), bc.fixed.iter().map(|&f| f as u8 as f64).collect()));
    vtu.write(&dir.join("result.vtu")).with_context(|| format!("writing result.vtu for {}", a.out.display()))?;
    umesh_core::mesh_io::write_mesh(&dir.join("organ_deformed.obj"), &loads::deform_mesh(&grid, &organ, u))?;
    for &l in &seg.structure_labels {
        let m = extract_surface(&seg.volume.mask(&[l]), &SurfaceSettings::default());
        let name = seg.label_name(l).replace([' ', '/'], "_");
        umesh_core::mesh_io::write_mesh(&dir.join(format!("{name}_deformed.obj")), &loads::deform_mesh(&grid, &m, u))?;
    }
    umesh_core::write_atomic(&dir.join("history.json"), serde_json::to_string_pretty(&sol.history)?.as_bytes())
        .with_context(|| format!("writing history.json for {}", a.out.display()))?;
    staged.commit().with_context(|| format!("replacing {}", a.out.display()))?;
    report(&a.out, a.json, &sol, grid.node_count(), grid.cells.len(), bc.fixed_count());
    Ok(())
}

fn report(out: &Path, json: bool, sol: &umesh_core::fem::Solution, nodes: usize, cells: usize, fixed: usize) {
    if json {
        super::output::print_json(&serde_json::json!({
            "converged": true, "newton_iterations": sol.iterations, "increments": sol.increments,
            "max_displacement_mm": sol.max_displacement_mm(), "mean_displacement_mm": sol.mean_displacement_mm(),
            "solve_ms": sol.timings.total_ms, "assembly_ms": sol.timings.assembly_ms,
            "factorization_ms": sol.timings.factorization_ms, "linear_solve_ms": sol.timings.solve_ms,
            "nodes": nodes, "cells": cells, "fixed_nodes": fixed, "out": out,
        }));
        return;
    }
    println!(
        "{:>4} {:>4} {:>6} {:>11} {:>11} {:>6} {:>9} {:>9} {:>8}",
        "inc", "it", "load", "residual", "correction", "step", "asm ms", "fact ms", "solve ms"
    );
    for r in &sol.history {
        println!(
            "{:>4} {:>4} {:>6.3} {:>11.3e} {:>11.3e} {:>6.3} {:>9.1} {:>9.1} {:>8.1}",
            r.increment,
            r.iteration,
            r.load_factor,
            r.residual,
            r.correction,
            r.step_length,
            r.assembly_ms,
            r.factorization_ms,
            r.solve_ms
        );
    }
    println!(
        "converged: {} increments, {} iterations, {:.0} ms; {} nodes, {} cells, {} fixed",
        sol.increments, sol.iterations, sol.timings.total_ms, nodes, cells, fixed
    );
    println!(
        "displacement: max {:.2} mm, mean {:.2} mm; results in {}",
        sol.max_displacement_mm(),
        sol.mean_displacement_mm(),
        out.display()
    );
}

fn run_problem(a: &Args, path: &Path, method: SolveMethod, staged: umesh_core::StagedDir) -> Result<()> {
    let p = read_problem(path)?;
    // The file's stabilisation, not the command line's: the file is the whole problem.
    let solver = umesh_core::fem::solver::SolverSettings { stabilization: p.stabilization, ..a.fe.solver() };
    let settings = SimulationSettings { material: p.material, solver, method, fixed: vec![], forces: vec![] };
    let (pb, progress) = super::output::progress_bar("solving");
    let sol = solve_bc(&p.grid, &p.bc, &settings, &progress, &super::output::cancel());
    pb.finish_and_clear();
    let sol = sol?;
    // Displacements in the file's node order.
    let u: Vec<Vector3<f64>> = p.node_map.iter().map(|&g| sol.displacement_mm[g]).collect();
    write_npz(
        &staged.path().join("displacement.npz"),
        &[("displacement_mm", Array::f64(vec![u.len(), 3], u.iter().flat_map(|d| [d.x, d.y, d.z]).collect()))],
    )?;
    staged.commit().with_context(|| format!("replacing {}", a.out.display()))?;
    report(&a.out, a.json, &sol, p.grid.node_count(), p.grid.cells.len(), p.bc.fixed_count());
    Ok(())
}
