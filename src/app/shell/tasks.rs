//! Background work: every heavy computation runs as a task on bevy's async compute pool,
//! polled each frame (bevy's `async_tasks` pattern), with progress and cancellation. Results
//! on the shared state (`state`) are applied here; a view's own result comes as a closure
//! (`JobOutput::Apply`) that the view wrote, so this runner depends on no view.

use crate::app::state::*;
use anyhow::Context;
use bevy::prelude::*;
use bevy::tasks::{AsyncComputeTaskPool, Task, futures::check_ready};
use std::sync::{Arc, Mutex};
use std::time::Instant;
use umesh_core::grid::ImmersedGrid;
use umesh_core::{Cancel, Progress};

/// A view's result: applied to the world on the main thread, returning the message to show.
pub type Apply = Box<dyn FnOnce(&mut World) -> anyhow::Result<String> + Send>;

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
    /// A scan to show under the loaded organ.
    Ct(Arc<CtImage>),
    /// What a view does with its result (a network for rehearsal, a recording for the AR view,
    /// a patient folder, a session).
    Apply(Apply),
}

#[derive(Clone, Debug, Default)]
pub struct JobProgress {
    pub done: u64,
    pub total: u64,
    pub message: String,
    /// The rate since the job's first report (a resumed job's earlier work left out).
    pub eta: umesh_core::Eta,
}

impl JobProgress {
    pub fn update(&mut self, done: u64, total: u64, message: &str) {
        self.eta.observe(done, Instant::now());
        (self.done, self.total) = (done, total);
        if self.message != message {
            self.message = message.to_string();
        }
    }
}

pub struct Job {
    pub id: u64,
    pub label: String,
    pub progress: Arc<Mutex<JobProgress>>,
    pub cancel: Cancel,
    pub started: Instant,
    task: Task<anyhow::Result<JobOutput>>,
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
        work: impl FnOnce(&Progress, &Cancel) -> anyhow::Result<JobOutput> + Send + 'static,
    ) -> u64 {
        let progress = Arc::new(Mutex::new(JobProgress::default()));
        let cancel = Cancel::new();
        let (p2, c2) = (progress.clone(), cancel.clone());
        let task = AsyncComputeTaskPool::get().spawn(async move {
            let sink = Progress::new(move |done, total, msg| {
                if let Ok(mut p) = p2.lock() {
                    p.update(done, total, msg);
                }
            });
            // Leave a core to the UI and the (software) renderer: the solvers' rayon loops run
            // in a pool one thread smaller than the machine, at a lower priority, so that the
            // renderer's threads win whenever they have work.
            let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(2).saturating_sub(1).max(1);
            match rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .start_handler(|_| lower_thread_priority())
                .build()
            {
                Ok(pool) => pool.install(|| work(&sink, &c2)),
                Err(_) => work(&sink, &c2),
            }
        });
        self.next_id += 1;
        self.running.push(Job {
            id: self.next_id,
            label: label.into(),
            progress,
            cancel,
            started: Instant::now(),
            task,
        });
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

/// Poll the tasks; apply finished results to the app state.
pub fn poll_jobs(world: &mut World) {
    let mut done = Vec::new();
    {
        let mut jobs = world.resource_mut::<Jobs>();
        let mut i = 0;
        while i < jobs.running.len() {
            match check_ready(&mut jobs.running[i].task) {
                Some(r) => done.push((jobs.running.remove(i), r)),
                None => i += 1,
            }
        }
    }
    for (job, result) in done {
        let secs = job.started.elapsed().as_secs_f64();
        let outcome = match result.and_then(|out| apply(world, out)) {
            Ok(Some(msg)) => {
                world.resource_mut::<UiMessages>().info(msg.clone());
                msg
            }
            Ok(None) => format!("{} done", job.label),
            Err(e) if job.cancel.is_cancelled() => {
                let _ = e;
                let msg = format!("{} cancelled", job.label);
                world.resource_mut::<UiMessages>().info(msg.clone());
                msg
            }
            Err(e) => {
                let msg = format!("{} failed: {e:#}", job.label);
                world.resource_mut::<UiMessages>().error(msg.clone());
                msg
            }
        };
        world.resource_mut::<Jobs>().finished.push((job.label, outcome, secs));
    }
}

/// Apply one result; `Ok(None)`: nothing to say (the labels of a file wait for a choice).
pub fn apply(world: &mut World, out: JobOutput) -> anyhow::Result<Option<String>> {
    Ok(Some(match out {
        JobOutput::Loaded(data) => set_organ(world, data),
        JobOutput::Grid(g, voxel_volume) => {
            let s = g.stats();
            let msg = format!("grid: {} cells, {} nodes, padded {:?}", s.cells, s.nodes, s.padded_shape);
            let mut grid = world.resource_mut::<GridState>();
            grid.voxel_volume_mm3 = voxel_volume;
            grid.stats = Some(s);
            grid.grid = Some(g);
            grid.generation += 1;
            // The cells would hide the organ and its deformation: off once built (G shows them).
            grid.show = false;
            world.resource_mut::<Simulation>().clear();
            msg
        }
        JobOutput::Inspected(path, labels) => {
            world.resource_mut::<PendingOpenRes>().0 = Some(PendingOpen::new(path, labels));
            return Ok(None);
        }
        JobOutput::Simulated(d) => {
            let msg = format!("{}: max displacement {:.1} mm in {:.0} ms", d.source, d.max_mm, d.solve_ms);
            world.resource_mut::<Simulation>().set(d);
            msg
        }
        JobOutput::Checked { fe, mean_mm, max_mm } => {
            let _ = fe;
            world.resource_mut::<Simulation>().check = Some((mean_mm, max_mm));
            format!("FE check: U-Net vs SVK surface difference {mean_mm:.2} mm mean, {max_mm:.2} mm max")
        }
        JobOutput::Ct(ct) => {
            let mut organ = world.resource_mut::<Organ>();
            let d = organ.data.as_mut().context("open a segmentation before its scan")?;
            let msg = format!("scan {} under the organ ({:?} voxels)", ct.source.display(), ct.volume.dims);
            d.ct = Some(ct);
            msg
        }
        JobOutput::Apply(f) => f(world)?,
    }))
}

/// A new organ: the previous one's grid, probes and deformation go.
pub fn set_organ(world: &mut World, data: OrganData) -> String {
    let msg = format!("loaded {} ({} structures)", data.source, data.structures.len());
    world.resource_mut::<Organ>().set(data);
    {
        let mut grid = world.resource_mut::<GridState>();
        grid.grid = None;
        grid.stats = None;
    }
    {
        let mut probes = world.resource_mut::<Probes>();
        probes.list.clear();
        probes.generation += 1;
    }
    world.resource_mut::<Simulation>().clear();
    msg
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
