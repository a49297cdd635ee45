//! Background work: every heavy computation runs as a task on bevy's async compute pool,
//! polled each frame (bevy's `async_tasks` pattern), with progress and cancellation.

use super::state::*;
use bevy::prelude::*;
use bevy::tasks::{AsyncComputeTaskPool, Task, futures::check_ready};
use nalgebra::Vector3;
use std::sync::{Arc, Mutex};
use std::time::Instant;
use umesh_core::fem::solver::SolveMethod;
use umesh_core::grid::ImmersedGrid;
use umesh_core::loads::{PointForce, deform_mesh};
use umesh_core::simulate::{SimulationSettings, run_simulate};
use umesh_core::surface::{SurfaceSettings, extract_surface};
use umesh_core::{Cancel, Progress};

pub enum JobOutput {
    Loaded(OrganData),
    /// The grid and the voxel volume of the organ mask it approximates (mm^3).
    Grid(Arc<ImmersedGrid>, f64),
    /// Labels of a NIfTI file, to choose from before loading: (value, name, voxels).
    Inspected(std::path::PathBuf, Vec<(i64, String, usize)>),
    Simulated(Deformation),
    /// An FE check of a rehearsal prediction: the FE result and the surface difference.
    Checked {
        fe: Deformation,
        mean_mm: f64,
        max_mm: f64,
    },
    /// A network ready for rehearsal.
    Model(Arc<Mutex<super::probes::RehearsalModel>>),
    /// A synthetic RGB-D recording written to this folder.
    Synthesized(std::path::PathBuf, String),
    /// A session's organ (as `Loaded` or `Patient`), the session to apply once it is in place,
    /// and its file.
    Session(Box<JobOutput>, Box<super::session::Session>, std::path::PathBuf),
    /// A scan to show under the loaded organ.
    Ct(Arc<CtImage>),
    /// A patient folder: its organ and what it holds.
    Patient(OrganData, Box<umesh_net::patient::PatientFigures>),
}

#[derive(Clone, Debug, Default)]
pub struct JobProgress {
    pub done: u64,
    pub total: u64,
    pub message: String,
}

pub struct Job {
    pub id: u64,
    pub label: String,
    pub progress: Arc<Mutex<JobProgress>>,
    pub cancel: Cancel,
    pub started: Instant,
    task: Task<Result<JobOutput, String>>,
}

#[derive(Resource, Default)]
pub struct Jobs {
    pub running: Vec<Job>,
    next_id: u64,
    /// Finished jobs: (label, outcome, seconds).
    pub finished: Vec<(String, String, f64)>,
}

impl Jobs {
    /// Start `work` in the background; it receives a progress sink and a cancel flag.
    pub fn spawn(
        &mut self,
        label: impl Into<String>,
        work: impl FnOnce(&Progress, &Cancel) -> Result<JobOutput, String> + Send + 'static,
    ) -> u64 {
        let progress = Arc::new(Mutex::new(JobProgress::default()));
        let cancel = Cancel::new();
        let (p2, c2) = (progress.clone(), cancel.clone());
        let task = AsyncComputeTaskPool::get().spawn(async move {
            let sink = Progress::new(move |done, total, msg| {
                if let Ok(mut p) = p2.lock() {
                    *p = JobProgress { done, total, message: msg.to_string() };
                }
            });
            // Leave a core to the UI and the (software) renderer: the solvers' rayon loops run
            // in a pool one thread smaller than the machine, at a lower priority, so that the
            // renderer's threads win whenever they have work.
            let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(2).saturating_sub(1).max(1);
            match rayon::ThreadPoolBuilder::new().num_threads(threads).start_handler(|_| lower_thread_priority()).build() {
                Ok(pool) => pool.install(|| work(&sink, &c2)),
                Err(_) => work(&sink, &c2),
            }
        });
        self.next_id += 1;
        self.running.push(Job { id: self.next_id, label: label.into(), progress, cancel, started: Instant::now(), task });
        self.next_id
    }

    pub fn cancel(&self, id: u64) {
        if let Some(j) = self.running.iter().find(|j| j.id == id) {
            j.cancel.cancel();
        }
    }

    pub fn is_running(&self, label_prefix: &str) -> bool {
        self.running.iter().any(|j| j.label.starts_with(label_prefix))
    }
}

/// The state an opened patient sets besides the organ.
#[derive(bevy::ecs::system::SystemParam)]
pub struct PatientState<'w> {
    setup: ResMut<'w, super::setup::ObservationSetup>,
    session: ResMut<'w, super::session::PendingSession>,
    active: ResMut<'w, ActiveModel>,
    open: ResMut<'w, OpenPatient>,
}

/// Poll the tasks; apply finished results to the app state.
pub fn poll_jobs(
    mut jobs: ResMut<Jobs>,
    mut organ: ResMut<Organ>,
    mut grid: ResMut<GridState>,
    mut sim: ResMut<Simulation>,
    mut probes: ResMut<Probes>,
    mut messages: ResMut<UiMessages>,
    mut pending: ResMut<PendingOpenRes>,
    mut rehearsal: ResMut<super::probes::Rehearsal>,
    mut ar: ResMut<super::ar::Ar>,
    mut patient: PatientState,
) {
    let mut i = 0;
    while i < jobs.running.len() {
        let Some(result) = check_ready(&mut jobs.running[i].task) else {
            i += 1;
            continue;
        };
        let job = jobs.running.remove(i);
        let secs = job.started.elapsed().as_secs_f64();
        // A session opens its organ as any other; the rest is applied after (`session::apply_pending`).
        let result = match result {
            Ok(JobOutput::Session(inner, s, path)) => {
                patient.session.0 = Some((*s, path));
                Ok(*inner)
            }
            r => r,
        };
        let outcome = match result {
            Ok(JobOutput::Loaded(data)) => {
                let msg = format!("loaded {} ({} structures)", data.source, data.structures.len());
                organ.set(data);
                grid.grid = None;
                grid.stats = None;
                probes.list.clear();
                probes.generation += 1;
                sim.clear();
                messages.info(msg.clone());
                msg
            }
            Ok(JobOutput::Patient(data, figures)) => {
                let dir = figures.dir.clone();
                let settings = &figures.patient.settings;
                organ.set(data);
                grid.grid = None;
                grid.stats = None;
                grid.settings = settings.dataset.grid.clone();
                probes.list.clear();
                probes.generation += 1;
                sim.clear();
                sim.fixed = FixedChoice::Region(settings.dataset.fixed.clone(), settings.fixed_description.clone());
                patient.setup.adopt(&settings.dataset.visibility);
                let model = if figures.has_model {
                    *patient.active = ActiveModel { dir: umesh_net::patient::model_dir(&dir), checkpoint: "model.safetensors".into() };
                    "its model is active"
                } else {
                    "no trained model yet (run umesh prepare again to continue)"
                };
                patient.open.0 = Some(*figures);
                let msg = format!("patient {}: {model}", dir.display());
                messages.info(msg.clone());
                msg
            }
            Ok(JobOutput::Ct(ct)) => match organ.data.as_mut() {
                Some(d) => {
                    let msg = format!("scan {} under the organ ({:?} voxels)", ct.source.display(), ct.volume.dims);
                    d.ct = Some(ct);
                    messages.info(msg.clone());
                    msg
                }
                None => {
                    let msg = "open a segmentation before its scan".to_string();
                    messages.error(msg.clone());
                    msg
                }
            },
            Ok(JobOutput::Model(m)) => {
                rehearsal.model = Some(m);
                rehearsal.enabled = true;
                rehearsal.shown_generation = u64::MAX;
                let msg = "model loaded: rehearsal on (drag the probes)".to_string();
                messages.info(msg.clone());
                msg
            }
            Ok(JobOutput::Synthesized(dir, summary)) => {
                let msg = format!("synthetic recording in {}: {summary}; press Open recording", dir.display());
                ar.source_text = dir.display().to_string();
                messages.info(msg.clone());
                msg
            }
            Ok(JobOutput::Inspected(path, labels)) => {
                let msg = format!("{}: {} labels", path.display(), labels.len());
                pending.0 = Some(PendingOpen::new(path, labels));
                msg
            }
            Ok(JobOutput::Grid(g, voxel_volume)) => {
                let s = g.stats();
                let msg = format!("grid: {} cells, {} nodes, padded {:?}", s.cells, s.nodes, s.padded_shape);
                grid.voxel_volume_mm3 = voxel_volume;
                grid.stats = Some(s);
                grid.grid = Some(g);
                grid.generation += 1;
                // The cells would hide the organ and its deformation: off once built (G shows them).
                grid.show = false;
                sim.clear();
                messages.info(msg.clone());
                msg
            }
            Ok(JobOutput::Simulated(d)) => {
                let msg = format!("{}: max displacement {:.1} mm in {:.0} ms", d.source, d.max_mm, d.solve_ms);
                sim.set(d);
                messages.info(msg.clone());
                msg
            }
            Ok(JobOutput::Checked { fe, mean_mm, max_mm }) => {
                let msg = format!("FE check: U-Net vs SVK surface difference {mean_mm:.2} mm mean, {max_mm:.2} mm max");
                let _ = fe;
                sim.check = Some((mean_mm, max_mm));
                messages.info(msg.clone());
                msg
            }
            // Unwrapped above; a session inside a session is no organ to open.
            Ok(JobOutput::Session(..)) => {
                let msg = format!("{}: no organ in the session", job.label);
                messages.error(msg.clone());
                msg
            }
            Err(e) if job.cancel.is_cancelled() => {
                let msg = format!("{} cancelled", job.label);
                let _ = e;
                messages.info(msg.clone());
                msg
            }
            Err(e) => {
                let msg = format!("{} failed: {e}", job.label);
                messages.error(msg.clone());
                msg
            }
        };
        jobs.finished.push((job.label, outcome, secs));
    }
}

/// A synthetic RGB-D recording of the organ deformed by the FE model (`umesh rgbd synth`).
pub fn synth_job(
    organ: OrganData,
    model_dir: std::path::PathBuf,
    out: std::path::PathBuf,
    frames: usize,
) -> impl FnOnce(&Progress, &Cancel) -> Result<JobOutput, String> + Send + 'static {
    move |progress, cancel| {
        let info = umesh_net::ModelInfo::read(&model_dir).ok();
        let config = crate::cli::input::model_dataset_config(info.as_ref(), &organ.seg);
        let settings = umesh_core::rgbd::synth::SynthSettings { frames, ..Default::default() };
        let r = umesh_core::rgbd::synth::run_rgbd_synth(&organ.seg, &config, &settings, &out, progress, cancel)
            .map_err(|e| format!("{}: {e}", out.display()))?;
        let summary = format!("{} frames, markers move {:.1} mm by the last", r.frames, r.mean_marker_displacement_mm);
        Ok(JobOutput::Synthesized(out, summary))
    }
}

/// Nice the calling thread (Linux: priorities are per thread) so background work yields to the UI.
#[allow(unsafe_code)]
pub fn lower_thread_priority() {
    #[cfg(target_os = "linux")]
    // SAFETY: setpriority only reads its integer arguments; who = 0 is the calling thread.
    unsafe {
        libc::setpriority(libc::PRIO_PROCESS, 0, 10);
    }
}

/// Load a segmentation (or the bundled phantom) and extract its surfaces.
pub fn load_job(req: OpenRequest) -> impl FnOnce(&Progress, &Cancel) -> Result<JobOutput, String> + Send + 'static {
    move |progress, cancel| {
        progress.report(0, 3, "reading");
        let input = crate::cli::input::InputArgs {
            seg: req.path.clone(),
            organ_labels: req.organ_labels.clone(),
            structure_labels: req.structure_labels.clone(),
            structure_files: Vec::new(),
            structure_meshes: Vec::new(),
            mesh_scale_mm: 1.0,
            mesh_voxel_mm: 1.0,
            max_voxels: umesh_core::nifti_io::DEFAULT_MAX_VOXELS,
        };
        let seg = input.load().map_err(|e| format!("{e:#}"))?;
        if cancel.is_cancelled() {
            return Err("cancelled".into());
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
            data.ct = Some(Arc::new(super::ct::read_ct(ct, data.surface.bounds())?));
        }
        Ok(JobOutput::Loaded(data))
    }
}

/// The organ's display surfaces.
pub fn organ_data(seg: umesh_core::segmentation::Segmentation, source: String) -> Result<OrganData, String> {
    // Sampled every 3 mm (6 mm on software rasterisers: every second / fourth voxel of the
    // phantom's 1.5 mm): 68k (17k) triangles instead of 272k on the phantom, plenty for display
    // and picking. In millimetres, so that a 3 mm CT is not sampled every 12 mm.
    let spacing_mm = 1.5 * super::view3d::display_surface_step() as f64;
    let voxel_mm = (0..3).map(|c| seg.volume.world_from_voxel.fixed_view::<3, 1>(0, c).norm()).fold(f64::INFINITY, f64::min);
    let step = (spacing_mm / voxel_mm.max(1e-3)).round().clamp(1.0, 8.0) as usize;
    // Blurred over about half the sampling step before it is sampled: a smooth surface, whose
    // normals follow the field rather than the voxel faces.
    let settings = SurfaceSettings { step, sigma_voxels: (0.5 * step as f64).max(1.0), ..Default::default() };
    let surface = extract_surface(&seg.organ_mask(), &settings);
    if surface.triangles.is_empty() {
        return Err(format!("{}: the organ labels give an empty surface", seg.source.display()));
    }
    let structures = umesh_core::register::structure_surfaces(&seg)
        .into_iter()
        .map(|(label, name, color, mesh)| StructureMesh { label, name, color, mesh: Arc::new(mesh) })
        .collect();
    Ok(OrganData { seg: Arc::new(seg), surface: Arc::new(surface), structures, source, ct: None, opened: Default::default() })
}

/// Open a patient folder made by `umesh prepare`: its segmentation and figures.
pub fn open_patient_job(dir: std::path::PathBuf) -> impl FnOnce(&Progress, &Cancel) -> Result<JobOutput, String> + Send + 'static {
    move |progress, _| {
        progress.report(0, 2, "reading the patient");
        let figures = umesh_net::patient::read_figures(&dir).map_err(|e| e.to_string())?;
        let seg = figures.patient.segmentation(&dir).map_err(|e| e.to_string())?;
        progress.report(1, 2, "organ surface");
        let mut organ = organ_data(seg, format!("patient {}", dir.display()))?;
        organ.opened = OrganSource::Patient { dir: std::fs::canonicalize(&dir).unwrap_or_else(|_| dir.clone()) };
        // The scan, when the folder holds one (`umesh prepare --ct`).
        let ct = umesh_net::patient::ct_path(&dir);
        if ct.is_file() {
            organ.ct = Some(Arc::new(super::ct::read_ct(&ct, organ.surface.bounds())?));
        }
        Ok(JobOutput::Patient(organ, Box::new(figures)))
    }
}

pub fn grid_job(
    seg: Arc<umesh_core::segmentation::Segmentation>,
    settings: umesh_core::grid::GridSettings,
) -> impl FnOnce(&Progress, &Cancel) -> Result<JobOutput, String> + Send + 'static {
    move |progress, cancel| {
        let mask = seg.organ_mask();
        let g = ImmersedGrid::from_mask(&mask, &settings, progress, cancel).map_err(|e| e.to_string())?;
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
    let disp: Vec<f32> = surface.positions.iter().zip(&organ.surface.positions).map(|(a, b)| (a - b).norm() as f32).collect();
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
        let near: Vec<&Vector3<f64>> = surface.positions.iter().filter(|v| (*v - p.point_mm).norm() <= radius_mm).collect();
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
) -> impl FnOnce(&Progress, &Cancel) -> Result<JobOutput, String> + Send + 'static {
    move |progress, cancel| {
        if probes.is_empty() {
            return Err("place at least one force probe (click on the organ)".into());
        }
        let settings = SimulationSettings {
            material: Default::default(),
            solver: Default::default(),
            method: SolveMethod::Newton,
            fixed: vec![fixed.region(&organ.seg)],
            forces: spread_probes(&organ.surface, &probes, PROBE_TIP_RADIUS_MM),
        };
        let t = Instant::now();
        let out = run_simulate(&grid, Some(&organ.seg.volume), &settings, progress, cancel).map_err(|e| e.to_string())?;
        let history = out.solution.history.iter().enumerate().map(|(i, h)| (i + 1, h.residual)).collect();
        Ok(JobOutput::Simulated(deformation(&grid, &organ, &out.solution.displacement_mm, history, t.elapsed().as_secs_f64() * 1e3, "SVK")))
    }
}

/// Read a NIfTI's labels (names and voxel counts) so the user can choose organ and structures.
pub fn inspect_job(path: std::path::PathBuf) -> impl FnOnce(&Progress, &Cancel) -> Result<JobOutput, String> + Send + 'static {
    move |_, _| {
        if umesh_core::segmentation::is_mesh_path(&path) {
            return Ok(JobOutput::Inspected(path, Vec::new()));
        }
        let v = umesh_core::nifti_io::read_volume(&path, &Default::default()).map_err(|e| e.to_string())?;
        let labels = v
            .label_counts()
            .into_iter()
            .filter(|&(l, _)| l != 0)
            .map(|(l, n)| (l, v.label_names.get(&l).cloned().unwrap_or_default(), n))
            .collect::<Vec<_>>();
        if labels.is_empty() {
            return Err(format!("{}: no non-zero label: not a segmentation", path.display()));
        }
        Ok(JobOutput::Inspected(path, labels))
    }
}

pub struct JobsPlugin;

impl Plugin for JobsPlugin {
    fn build(&self, app: &mut App) {
        app.init_resource::<Jobs>()
            .init_resource::<Organ>()
            .init_resource::<GridState>()
            .init_resource::<Probes>()
            .init_resource::<Simulation>()
            .init_resource::<UiMessages>()
            .init_resource::<PendingOpenRes>()
            .add_systems(Update, poll_jobs);
    }
}

/// A scan read in the background and attached to the loaded organ.
pub fn load_ct_job(
    path: std::path::PathBuf,
    organ_bounds: Option<(Vector3<f64>, Vector3<f64>)>,
) -> impl FnOnce(&umesh_core::Progress, &umesh_core::Cancel) -> Result<JobOutput, String> + Send + 'static {
    move |progress, _| {
        progress.report(0, 1, "reading the scan");
        Ok(JobOutput::Ct(Arc::new(super::ct::read_ct(&path, organ_bounds)?)))
    }
}
