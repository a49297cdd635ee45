//! What the app shows and edits: plain resources, free of rendering (tested headless).

use bevy::prelude::*;
use nalgebra::Vector3;
use std::path::PathBuf;
use std::sync::Arc;
use umesh_core::fem::FixedRegion;
use umesh_core::grid::{GridSettings, GridStats, ImmersedGrid};
use umesh_core::mesh::TriMesh;
use umesh_core::segmentation::Segmentation;

/// The loaded organ: segmentation, surface and internal structures (world RAS, mm).
#[derive(Clone)]
pub struct OrganData {
    pub seg: Arc<Segmentation>,
    pub surface: Arc<TriMesh>,
    pub structures: Vec<StructureMesh>,
    /// Where it came from (file name or "bundled phantom").
    pub source: String,
    /// The scan under the segmentation, when one was opened with it.
    pub ct: Option<Arc<CtImage>>,
    /// How to open it again (sessions).
    pub opened: OrganSource,
}

/// A scan, with its world bounds (voxel centres, mm).
pub struct CtImage {
    pub volume: umesh_core::volume::Volume,
    pub source: PathBuf,
    pub lo_mm: Vector3<f64>,
    pub hi_mm: Vector3<f64>,
    /// Values in Hounsfield units (air near -1000): the CT presets apply; else the image's range.
    pub hounsfield: bool,
}

/// Where the organ came from, enough to open it again.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize, Default)]
#[serde(tag = "kind", rename_all = "kebab-case")]
pub enum OrganSource {
    #[default]
    Phantom,
    File {
        path: PathBuf,
        organ_labels: Vec<i64>,
        structure_labels: Vec<i64>,
    },
    Patient {
        dir: PathBuf,
    },
}

#[derive(Clone)]
pub struct StructureMesh {
    pub label: i64,
    pub name: String,
    pub color: [u8; 3],
    pub mesh: Arc<TriMesh>,
}

#[derive(Resource, Default)]
pub struct Organ {
    pub data: Option<OrganData>,
    /// Bumped on every change, so that the scene rebuilds its meshes.
    pub generation: u64,
}

impl Organ {
    pub fn set(&mut self, data: OrganData) {
        self.data = Some(data);
        self.generation += 1;
    }
}

#[derive(Resource)]
pub struct GridState {
    pub settings: GridSettings,
    pub grid: Option<Arc<ImmersedGrid>>,
    pub stats: Option<GridStats>,
    pub show: bool,
    pub generation: u64,
    /// Volume of the voxel mask the grid approximates (mm^3).
    pub voxel_volume_mm3: f64,
}

impl Default for GridState {
    fn default() -> Self {
        Self {
            settings: GridSettings::default(),
            grid: None,
            stats: None,
            show: true,
            generation: 0,
            voxel_volume_mm3: 0.0,
        }
    }
}

/// A force probe on the organ surface.
#[derive(Clone, Debug, PartialEq)]
pub struct Probe {
    pub point_mm: Vector3<f64>,
    pub normal: Vector3<f64>,
    pub force_n: Vector3<f64>,
}

#[derive(Resource, Default)]
pub struct Probes {
    pub list: Vec<Probe>,
    pub selected: Option<usize>,
    /// The probe being dragged with the mouse.
    pub dragging: Option<usize>,
    pub generation: u64,
}

impl Probes {
    pub fn add(&mut self, p: Probe) -> usize {
        self.list.push(p);
        self.selected = Some(self.list.len() - 1);
        self.generation += 1;
        self.list.len() - 1
    }
    pub fn remove(&mut self, i: usize) {
        if i < self.list.len() {
            self.list.remove(i);
            self.selected = None;
            self.dragging = None;
            self.generation += 1;
        }
    }
}

/// Which nodes the simulation and the dataset hold fixed.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "kind", content = "with", rename_all = "kebab-case")]
pub enum FixedChoice {
    /// The CLI's default: near the vena cava / hepatic veins when the segmentation names them,
    /// else the posterior fifth (`umesh_core::loads::default_fixed`).
    Auto { distance_mm: f64 },
    /// Nodes within `distance_mm` of a label.
    Label { label: i64, distance_mm: f64 },
    /// The posterior slab of the organ, `fraction` of its depth.
    Posterior { fraction: f64 },
    /// A region given elsewhere (an opened patient's), with its description.
    Region(FixedRegion, String),
}

impl Default for FixedChoice {
    fn default() -> Self {
        FixedChoice::Auto { distance_mm: 6.0 }
    }
}

impl FixedChoice {
    pub fn region(&self, seg: &Segmentation) -> FixedRegion {
        self.describe(seg).0
    }
    /// The region and how it was chosen (as `umesh dataset generate` prints it).
    pub fn describe(&self, seg: &Segmentation) -> (FixedRegion, String) {
        match self {
            FixedChoice::Auto { distance_mm } => {
                let c = umesh_core::loads::default_fixed(seg, None, *distance_mm);
                (c.region, c.description)
            }
            FixedChoice::Label { label, distance_mm } => {
                let c = umesh_core::loads::default_fixed(seg, Some(*label), *distance_mm);
                (c.region, c.description)
            }
            FixedChoice::Posterior { fraction } => {
                let (lo, hi) = seg.organ_mask().world_bounds().unwrap_or_default();
                let region = FixedRegion::Plane {
                    normal: [0.0, 1.0, 0.0],
                    offset_mm: lo.y,
                    thickness_mm: fraction * (hi.y - lo.y),
                };
                (region, format!("the posterior {:.0} % of the organ", fraction * 100.0))
            }
            FixedChoice::Region(r, d) => (r.clone(), d.clone()),
        }
    }
}

/// A displacement field over the grid and the meshes it deforms.
#[derive(Clone)]
pub struct Deformation {
    /// Per surface vertex: displacement magnitude (mm), for the colour map.
    pub surface_displacement_mm: Vec<f32>,
    pub surface: Arc<TriMesh>,
    pub structures: Vec<Arc<TriMesh>>,
    pub max_mm: f64,
    pub mean_mm: f64,
    /// Newton history: (iteration, relative residual).
    pub history: Vec<(usize, f64)>,
    pub solve_ms: f64,
    /// What produced it: "SVK", "U-Net", ...
    pub source: String,
}

#[derive(Resource, Default)]
pub struct Simulation {
    pub fixed: FixedChoice,
    pub result: Option<Deformation>,
    pub show_deformed: bool,
    /// The rest shape as a faint ghost behind the deformed organ.
    pub show_ghost: bool,
    pub generation: u64,
    /// FE check of a rehearsal prediction: (mean, max) difference at the surface (mm).
    pub check: Option<(f64, f64)>,
}

impl Simulation {
    pub fn set(&mut self, d: Deformation) {
        self.result = Some(d);
        self.show_deformed = true;
        self.generation += 1;
    }
    pub fn clear(&mut self) {
        self.result = None;
        self.check = None;
        self.generation += 1;
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Level {
    Info,
    Error,
}

/// Messages for the status bar and the error window: errors are shown, never panicked on.
#[derive(Resource, Default)]
pub struct UiMessages {
    pub list: Vec<(Level, String)>,
    /// Errors not yet dismissed.
    pub unread_errors: usize,
}

impl UiMessages {
    pub fn info(&mut self, m: impl Into<String>) {
        let m = m.into();
        info!("{m}");
        self.list.push((Level::Info, m));
    }
    pub fn error(&mut self, m: impl Into<String>) {
        let m = m.into();
        warn!("{m}");
        self.list.push((Level::Error, m));
        self.unread_errors += 1;
    }
    pub fn last(&self) -> Option<&(Level, String)> {
        self.list.last()
    }
}

/// What to open: a NIfTI with its labels, or a closed mesh.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct OpenRequest {
    pub path: Option<PathBuf>,
    pub organ_labels: Vec<i64>,
    pub structure_labels: Vec<i64>,
    /// The scan the segmentation was made from, shown as slices under the model.
    pub ct: Option<PathBuf>,
}

/// A file picked in File > Open, waiting for the user's choice of labels.
#[derive(Clone, Debug)]
pub struct PendingOpen {
    pub path: PathBuf,
    /// (value, name, voxels, role): role 0 none, 1 organ, 2 structure.
    pub labels: Vec<(i64, String, usize, u8)>,
}

impl PendingOpen {
    /// Guess roles from the names: "liver" is the organ; vessels and tumours are structures.
    pub fn new(path: PathBuf, labels: Vec<(i64, String, usize)>) -> Self {
        let labels = labels
            .into_iter()
            .map(|(v, name, n)| {
                let l = name.to_lowercase();
                let role = if l.contains("liver") {
                    1
                } else if ["vein", "cava", "tumo", "lesion", "vessel", "portal"].iter().any(|k| l.contains(k)) {
                    2
                } else {
                    0
                };
                (v, name, n, role)
            })
            .collect();
        Self { path, labels }
    }
    pub fn request(&self) -> OpenRequest {
        OpenRequest {
            path: Some(self.path.clone()),
            organ_labels: self.labels.iter().filter(|l| l.3 == 1).map(|l| l.0).collect(),
            structure_labels: self.labels.iter().filter(|l| l.3 == 2).map(|l| l.0).collect(),
            ct: None,
        }
    }
}

#[derive(Resource, Default)]
pub struct PendingOpenRes(pub Option<PendingOpen>);

/// The model the QA browser and the AR view use: a model folder and one of its checkpoints
/// (the bundled model by default; the training dashboard changes it).
#[derive(Resource, Clone, Debug)]
pub struct ActiveModel {
    pub dir: std::path::PathBuf,
    pub checkpoint: String,
}

impl Default for ActiveModel {
    fn default() -> Self {
        Self { dir: umesh_workflow::input::bundled_model(), checkpoint: "model.safetensors".into() }
    }
}

/// A model to load into the rehearsal on the organ open now (chosen in the jobs view).
#[derive(Resource, Default)]
pub struct ModelToLoad(pub Option<ActiveModel>);

/// What the window shows: the organ and its simulation, the jobs, the dataset browser or
/// the AR view. A bevy state: systems of one view run `in_state` of it; each view says what
/// it shows in its registry entry (`shell::views`).
#[derive(States, Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Mode {
    #[default]
    Model,
    Jobs,
    Qa,
    Ar,
}

/// A path relative to the working directory when it lies inside it (shorter to read, and
/// the same on every checkout).
pub fn short_path(p: &std::path::Path) -> String {
    std::env::current_dir()
        .ok()
        .and_then(|d| p.strip_prefix(d).ok().map(|r| r.display().to_string()))
        .unwrap_or_else(|| p.display().to_string())
}

/// The patient folder opened (File > Open patient, `umesh gui PATIENT/`) and its figures.
#[derive(Resource, Default)]
pub struct OpenPatient(pub Option<umesh_workflow::patient::PatientFigures>);

/// The sample truth the QA view shows, for the views that outline it (the scan's slices): its
/// surface and the QA view's generation it belongs to.
#[derive(Resource, Default)]
pub struct QaTruth {
    pub generation: u64,
    pub surface: Option<Arc<TriMesh>>,
}
