//! The model view's background computations: loading an organ (with its scan) or a patient
//! folder, building the grid, the SVK solve of the probes, reading a file's labels, a synthetic
//! recording; each returns what `shell::tasks` applies.

use crate::app::shell::tasks::JobOutput;
use crate::app::state::*;
use bevy::prelude::*;
use nalgebra::Vector3;
use std::sync::Arc;
use std::time::Instant;
use umesh_core::fem::solver::SolveMethod;
use umesh_core::grid::ImmersedGrid;
use umesh_core::loads::{PointForce, deform_mesh};
use umesh_core::simulate::{SimulationSettings, run_simulate};
use umesh_core::surface::{SurfaceSettings, extract_surface};
use umesh_core::{Cancel, Progress};

/// Load a segmentation (or the bundled phantom) and extract its surfaces.
pub fn load_job(req: OpenRequest) -> impl FnOnce(&Progress, &Cancel) -> anyhow::Result<JobOutput> + Send + 'static {
    move |progress, cancel| {
        progress.report(0, 3, "reading");
        let input = umesh_workflow::input::InputSpec {
            seg: req.path.clone(),
            organ_labels: req.organ_labels.clone(),
            structure_labels: req.structure_labels.clone(),
            structure_files: Vec::new(),
            structure_meshes: Vec::new(),
            mesh_scale_mm: 1.0,
            mesh_voxel_mm: 1.0,
            max_voxels: umesh_core::nifti_io::DEFAULT_MAX_VOXELS,
        };
        let mut notes = Vec::new();
        let seg = input.load_with_notes(&mut notes)?;
        for n in notes {
            eprintln!("note: {n}");
        }
        if cancel.is_cancelled() {
            anyhow::bail!("cancelled");
        }
        progress.report(1, 3, "organ surface");
        let source = req.path.as_ref().map(|p| p.display().to_string()).unwrap_or_else(|| "bundled phantom".into());
        let mut data = organ_data(seg, source)?;
        if let Some(p) = &req.path {
            data.opened = OrganSource::File {
                path: std::fs::canonicalize(p).unwrap_or_else(|_| p.clone()),
                organ_labels: req.organ_labels.clone(),
                structure_labels: req.structure_labels.clone(),
            };
        }
        if let Some(ct) = &req.ct {
            progress.report(2, 3, "scan");
            data.ct = Some(Arc::new(crate::app::ct::read_ct(ct, data.surface.bounds())?));
        }
        Ok(JobOutput::Loaded(data))
    }
}

/// The organ's display surfaces.
pub fn organ_data(seg: umesh_core::segmentation::Segmentation, source: String) -> anyhow::Result<OrganData> {
    // Sampled every 3 mm (6 mm on software rasterisers: every second / fourth voxel of the
    // phantom's 1.5 mm): 68k (17k) triangles instead of 272k on the phantom, plenty for display
    // and picking. In millimetres, so that a 3 mm CT is not sampled every 12 mm.
    let spacing_mm = 1.5 * crate::app::shell::view3d::display_surface_step() as f64;
    let voxel_mm = seg.volume.min_spacing_mm();
    let step = (spacing_mm / voxel_mm.max(1e-3)).round().clamp(1.0, 8.0) as usize;
    // Blurred over about half the sampling step before it is sampled: a smooth surface, whose
    // normals follow the field rather than the voxel faces.
    let settings = SurfaceSettings { step, sigma_voxels: (0.5 * step as f64).max(1.0), ..Default::default() };
    let surface = extract_surface(&seg.organ_mask(), &settings);
    if surface.triangles.is_empty() {
        anyhow::bail!("{}: the organ labels give an empty surface", seg.source.display());
    }
    let structures = umesh_core::register::structure_surfaces(&seg)
        .into_iter()
        .map(|(label, name, color, mesh)| StructureMesh { label, name, color, mesh: Arc::new(mesh) })
        .collect();
    Ok(OrganData {
        seg: Arc::new(seg),
        surface: Arc::new(surface),
        structures,
        source,
        ct: None,
        opened: Default::default(),
    })
}

/// Open a patient folder made by `umesh prepare`: its segmentation and figures.
pub fn open_patient_job(
    dir: std::path::PathBuf,
) -> impl FnOnce(&Progress, &Cancel) -> anyhow::Result<JobOutput> + Send + 'static {
    move |progress, _| {
        progress.report(0, 2, "reading the patient");
        let figures = umesh_workflow::patient::read_figures(&dir)?;
        let seg = figures.patient.segmentation(&dir)?;
        progress.report(1, 2, "organ surface");
        let mut organ = organ_data(seg, format!("patient {}", dir.display()))?;
        organ.opened = OrganSource::Patient { dir: std::fs::canonicalize(&dir).unwrap_or_else(|_| dir.clone()) };
        // The scan, when the folder holds one (`umesh prepare --ct`).
        let ct = umesh_workflow::patient::ct_path(&dir);
        if ct.is_file() {
            organ.ct = Some(Arc::new(crate::app::ct::read_ct(&ct, organ.surface.bounds())?));
        }
        Ok(JobOutput::Apply(Box::new(move |world| Ok(open_patient(world, organ, figures)))))
    }
}

/// A patient folder opened: its organ, grid settings, fixed region, camera and model.
fn open_patient(world: &mut World, data: OrganData, figures: umesh_workflow::patient::PatientFigures) -> String {
    let dir = figures.dir.clone();
    let settings = figures.patient.settings.clone();
    crate::app::shell::tasks::set_organ(world, data);
    world.resource_mut::<GridState>().settings = settings.dataset.grid.clone();
    world.resource_mut::<Simulation>().fixed =
        FixedChoice::Region(settings.dataset.fixed.clone(), settings.fixed_description.clone());
    world.resource_mut::<crate::app::setup::ObservationSetup>().adopt(&settings.dataset.visibility);
    let model = if figures.has_model {
        *world.resource_mut::<ActiveModel>() =
            ActiveModel { dir: umesh_workflow::patient::model_dir(&dir), checkpoint: "model.safetensors".into() };
        "its model is active"
    } else {
        "no trained model yet (run umesh prepare again to continue)"
    };
    world.resource_mut::<OpenPatient>().0 = Some(figures);
    format!("patient {}: {model}", dir.display())
}

pub fn grid_job(
    seg: Arc<umesh_core::segmentation::Segmentation>,
    settings: umesh_core::grid::GridSettings,
) -> impl FnOnce(&Progress, &Cancel) -> anyhow::Result<JobOutput> + Send + 'static {
    move |progress, cancel| {
        let mask = seg.organ_mask();
        let g = ImmersedGrid::from_mask(&mask, &settings, progress, cancel)?;
        Ok(JobOutput::Grid(Arc::new(g), mask.volume_mm3()))
    }
}

/// A deformation from nodal displacements: the meshes follow through the grid embedding.
pub fn deformation(
    grid: &ImmersedGrid,
    organ: &OrganData,
    u: &[Vector3<f64>],
    history: Vec<(usize, f64)>,
    solve_ms: f64,
    source: &str,
) -> Deformation {
    let surface = deform_mesh(grid, &organ.surface, u);
    let disp: Vec<f32> =
        surface.positions.iter().zip(&organ.surface.positions).map(|(a, b)| (a - b).norm() as f32).collect();
    let max = u.iter().map(|v| v.norm()).fold(0.0, f64::max);
    let mean = u.iter().map(|v| v.norm()).sum::<f64>() / u.len().max(1) as f64;
    Deformation {
        surface_displacement_mm: disp,
        surface: Arc::new(surface),
        structures: organ.structures.iter().map(|s| Arc::new(deform_mesh(grid, &s.mesh, u))).collect(),
        max_mm: max,
        mean_mm: mean,
        history,
        solve_ms,
        source: source.into(),
    }
}

/// Radius of an instrument tip: a probe's force is shared by the surface within it.
pub const PROBE_TIP_RADIUS_MM: f64 = 8.0;

/// Spread each probe's force evenly over the surface vertices within `radius_mm`: a point
/// load on an immersed grid would crush the single (possibly mostly outside) cell under it.
pub fn spread_probes(surface: &umesh_core::mesh::TriMesh, probes: &[Probe], radius_mm: f64) -> Vec<PointForce> {
    let mut out = Vec::new();
    for p in probes {
        let near: Vec<&Vector3<f64>> =
            surface.positions.iter().filter(|v| (*v - p.point_mm).norm() <= radius_mm).collect();
        if near.is_empty() {
            out.push(PointForce { point_mm: p.point_mm.into(), force_n: p.force_n.into() });
            continue;
        }
        let f = p.force_n / near.len() as f64;
        out.extend(near.into_iter().map(|v| PointForce { point_mm: (*v).into(), force_n: f.into() }));
    }
    out
}

pub fn simulate_job(
    organ: OrganData,
    grid: Arc<ImmersedGrid>,
    fixed: FixedChoice,
    probes: Vec<Probe>,
) -> impl FnOnce(&Progress, &Cancel) -> anyhow::Result<JobOutput> + Send + 'static {
    move |progress, cancel| {
        if probes.is_empty() {
            anyhow::bail!("place at least one force probe (click on the organ)");
        }
        let settings = SimulationSettings {
            material: Default::default(),
            solver: Default::default(),
            method: SolveMethod::Newton,
            fixed: vec![fixed.region(&organ.seg)],
            forces: spread_probes(&organ.surface, &probes, PROBE_TIP_RADIUS_MM),
        };
        let t = Instant::now();
        let out = run_simulate(&grid, Some(&organ.seg.volume), &settings, progress, cancel)?;
        let history = out.solution.history.iter().enumerate().map(|(i, h)| (i + 1, h.residual)).collect();
        Ok(JobOutput::Simulated(deformation(
            &grid,
            &organ,
            &out.solution.displacement_mm,
            history,
            t.elapsed().as_secs_f64() * 1e3,
            "SVK",
        )))
    }
}

/// Read a NIfTI's labels (names and voxel counts) so the user can choose organ and structures.
pub fn inspect_job(
    path: std::path::PathBuf,
) -> impl FnOnce(&Progress, &Cancel) -> anyhow::Result<JobOutput> + Send + 'static {
    move |_, _| {
        if umesh_core::segmentation::is_mesh_path(&path) {
            return Ok(JobOutput::Inspected(path, Vec::new()));
        }
        let v = umesh_core::nifti_io::read_volume(&path, &Default::default())?;
        let labels = v
            .label_counts()
            .into_iter()
            .filter(|&(l, _)| l != 0)
            .map(|(l, n)| (l, v.label_names.get(&l).cloned().unwrap_or_default(), n))
            .collect::<Vec<_>>();
        if labels.is_empty() {
            anyhow::bail!("{}: no non-zero label: not a segmentation", path.display());
        }
        Ok(JobOutput::Inspected(path, labels))
    }
}

/// A scan read in the background and attached to the loaded organ.
pub fn load_ct_job(
    path: std::path::PathBuf,
    organ_bounds: Option<(Vector3<f64>, Vector3<f64>)>,
) -> impl FnOnce(&umesh_core::Progress, &umesh_core::Cancel) -> anyhow::Result<JobOutput> + Send + 'static {
    move |progress, _| {
        progress.report(0, 1, "reading the scan");
        Ok(JobOutput::Ct(Arc::new(crate::app::ct::read_ct(&path, organ_bounds)?)))
    }
}
