//! Rehearsal sessions: what was open (the phantom, a segmentation with its labels, or a patient
//! folder; the scan), the grid settings, probes, fixed region, 3-D camera, active model and
//! slices, as one small JSON file written atomically and reopened; the File menu's recent files;
//! the current view exported as a PNG.

use crate::app::ct::CtView;
use crate::app::shell::camera::OrbitCamera;
use crate::app::shell::tasks::{JobOutput, Jobs};
use crate::app::state::*;
use anyhow::Context;
use bevy::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use umesh_core::slices::Window;
use umesh_core::{Cancel, Progress};

pub const FORMAT: &str = "umesh-session";
pub const FORMAT_VERSION: u32 = 1;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SavedProbe {
    pub point_mm: [f64; 3],
    pub normal: [f64; 3],
    pub force_n: [f64; 3],
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SavedCamera {
    pub focus: [f32; 3],
    pub yaw: f32,
    pub pitch: f32,
    pub distance: f32,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SavedSlices {
    pub show: [bool; 3],
    pub position_mm: [f64; 3],
    pub window: Window,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Session {
    pub format: String,
    pub format_version: u32,
    pub organ: OrganSource,
    /// The scan shown under the organ.
    pub ct: Option<PathBuf>,
    pub cell_size_mm: f64,
    pub subdivisions: u32,
    pub probes: Vec<SavedProbe>,
    pub fixed: FixedChoice,
    pub camera: SavedCamera,
    /// The active model folder and checkpoint; `rehearsal`: its live deformation was on.
    pub model: Option<(PathBuf, String)>,
    pub rehearsal: bool,
    pub slices: Option<SavedSlices>,
}

impl Session {
    /// Check what a hand-edited or damaged file could hold: numbers finite, sizes sane.
    fn validate(&self, path: &Path) -> anyhow::Result<()> {
        let bad = |what: String| Err(anyhow::anyhow!("{}: {what}", path.display()));
        if self.format != FORMAT || self.format_version != FORMAT_VERSION {
            return bad(format!("format {} v{} is not {FORMAT} v{FORMAT_VERSION}", self.format, self.format_version));
        }
        if !(self.cell_size_mm.is_finite() && (1.0..=50.0).contains(&self.cell_size_mm)) || self.subdivisions > 4 {
            return bad(format!(
                "cell size {} mm / {} subdivisions out of range",
                self.cell_size_mm, self.subdivisions
            ));
        }
        if self.probes.len() > 1000 {
            return bad(format!("{} probes (at most 1000)", self.probes.len()));
        }
        for (i, p) in self.probes.iter().enumerate() {
            if !p.point_mm.iter().chain(&p.normal).chain(&p.force_n).all(|v| v.is_finite()) {
                return bad(format!("probe {}: a coordinate or force is not a finite number", i + 1));
            }
        }
        let c = &self.camera;
        if !(c.focus.iter().all(|v| v.is_finite())
            && c.yaw.is_finite()
            && c.pitch.is_finite()
            && c.distance.is_finite()
            && c.distance > 0.0)
        {
            return bad("the camera holds a non-finite or non-positive value".into());
        }
        if let Some(s) = &self.slices
            && !(s.position_mm.iter().all(|v| v.is_finite())
                && s.window.level.is_finite()
                && s.window.width.is_finite()
                && s.window.width > 0.0)
        {
            return bad("the slices hold a non-finite position or window".into());
        }
        Ok(())
    }

    pub fn read(path: &Path) -> anyhow::Result<Session> {
        let text = std::fs::read_to_string(path).with_context(|| path.display().to_string())?;
        let s: Session =
            serde_json::from_str(&text).with_context(|| format!("{}: not a umesh session", path.display()))?;
        s.validate(path)?;
        Ok(s)
    }

    pub fn write(&self, path: &Path) -> anyhow::Result<()> {
        let text = serde_json::to_string_pretty(self)?;
        umesh_core::write_atomic(path, text.as_bytes()).with_context(|| path.display().to_string())
    }
}

/// The session file the app works on: Ctrl+S writes it (`umesh gui --session FILE`, or the last
/// one saved or opened).
#[derive(Resource, Default)]
pub struct SessionFile(pub Option<PathBuf>);

/// A session read with its organ, applied once the organ is in place.
#[derive(Resource, Default)]
pub struct PendingSession(pub Option<(Session, PathBuf)>);

/// The state a session holds.
#[derive(bevy::ecs::system::SystemParam)]
pub struct SessionState<'w> {
    pub organ: ResMut<'w, Organ>,
    pub grid: ResMut<'w, GridState>,
    pub probes: ResMut<'w, Probes>,
    pub sim: ResMut<'w, Simulation>,
    pub camera: ResMut<'w, OrbitCamera>,
    pub active: ResMut<'w, ActiveModel>,
    pub rehearsal: ResMut<'w, crate::app::model::probes::Rehearsal>,
    pub ct: ResMut<'w, CtView>,
    pub jobs: ResMut<'w, Jobs>,
    pub messages: ResMut<'w, UiMessages>,
    pub file: ResMut<'w, SessionFile>,
    pub recent: ResMut<'w, Recent>,
}

/// The session of what is open now.
pub fn capture(st: &SessionState) -> anyhow::Result<Session> {
    let d = st.organ.data.as_ref().context("nothing is open")?;
    let v3 = |v: &nalgebra::Vector3<f64>| [v.x, v.y, v.z];
    let c = &*st.camera;
    Ok(Session {
        format: FORMAT.into(),
        format_version: FORMAT_VERSION,
        organ: d.opened.clone(),
        ct: d.ct.as_ref().map(|c| c.source.clone()),
        cell_size_mm: st.grid.settings.cell_size_mm,
        subdivisions: st.grid.settings.subdivisions,
        probes: st
            .probes
            .list
            .iter()
            .map(|p| SavedProbe { point_mm: v3(&p.point_mm), normal: v3(&p.normal), force_n: v3(&p.force_n) })
            .collect(),
        fixed: st.sim.fixed.clone(),
        camera: SavedCamera { focus: c.focus.to_array(), yaw: c.yaw, pitch: c.pitch, distance: c.distance },
        model: Some((st.active.dir.clone(), st.active.checkpoint.clone())),
        rehearsal: st.rehearsal.enabled && st.rehearsal.model.is_some(),
        slices: d.ct.as_ref().map(|_| SavedSlices {
            show: st.ct.show,
            position_mm: st.ct.position_mm,
            window: st.ct.window,
        }),
    })
}

/// Save what is open to `path` (atomically) and remember it.
pub fn save(st: &mut SessionState, path: PathBuf) {
    match capture(st).and_then(|s| s.write(&path)) {
        Ok(()) => {
            st.messages.info(format!("session saved to {} ({} probes)", path.display(), st.probes.list.len()));
            st.recent.push(&path, RecentKind::Session);
            st.file.0 = Some(path);
        }
        Err(e) => st.messages.error(format!("saving the session: {e:#}")),
    }
}

/// Read a session and open its organ (and scan) in the background; the rest is applied when it
/// has loaded.
pub fn open_job(path: PathBuf) -> impl FnOnce(&Progress, &Cancel) -> anyhow::Result<JobOutput> + Send + 'static {
    move |progress, cancel| {
        let s = Session::read(&path)?;
        let inner = match &s.organ {
            OrganSource::Phantom => {
                crate::app::model::compute::load_job(OpenRequest { ct: s.ct.clone(), ..Default::default() })(
                    progress, cancel,
                )?
            }
            OrganSource::File { path: p, organ_labels, structure_labels } => {
                crate::app::model::compute::load_job(OpenRequest {
                    path: Some(p.clone()),
                    organ_labels: organ_labels.clone(),
                    structure_labels: structure_labels.clone(),
                    ct: s.ct.clone(),
                })(progress, cancel)?
            }
            OrganSource::Patient { dir } => {
                crate::app::model::compute::open_patient_job(dir.clone())(progress, cancel)?
            }
        };
        Ok(JobOutput::Apply(Box::new(move |world| {
            let msg = crate::app::shell::tasks::apply(world, inner)?;
            // Applied after the organ (`apply_pending`, this frame): the probes, camera and
            // slices belong to it.
            world.resource_mut::<PendingSession>().0 = Some((s, path));
            Ok(msg.unwrap_or_default())
        })))
    }
}

/// Apply a session whose organ has just been loaded: grid settings, probes, fixed region,
/// camera, slices, model.
pub fn apply_pending(mut pending: ResMut<PendingSession>, mut st: SessionState) {
    let Some((s, path)) = pending.0.take() else { return };
    let v = |a: &[f64; 3]| nalgebra::Vector3::new(a[0], a[1], a[2]);
    st.grid.settings.cell_size_mm = s.cell_size_mm;
    st.grid.settings.subdivisions = s.subdivisions;
    st.probes.list = s
        .probes
        .iter()
        .map(|p| Probe { point_mm: v(&p.point_mm), normal: v(&p.normal), force_n: v(&p.force_n) })
        .collect();
    st.probes.selected = None;
    st.probes.generation += 1;
    st.sim.fixed = s.fixed.clone();
    let c = &s.camera;
    let generation = st.organ.generation;
    st.camera.set_view(Vec3::from_array(c.focus), c.yaw, c.pitch, c.distance, generation);
    if let (Some(sl), Some(d)) = (&s.slices, &st.organ.data)
        && let Some(ct) = &d.ct
    {
        let ct = ct.clone();
        st.ct.restore(sl.show, sl.position_mm, sl.window, generation, &ct);
    }
    if let (Some((dir, file)), Some(d)) = (&s.model, &st.organ.data) {
        *st.active = ActiveModel { dir: dir.clone(), checkpoint: file.clone() };
        if s.rehearsal {
            st.jobs
                .spawn("load model", crate::app::model::probes::load_model_job(dir.clone(), file.clone(), d.clone()));
        }
    }
    st.messages.info(format!("session {} opened ({} probes)", path.display(), s.probes.len()));
    st.recent.push(&path, RecentKind::Session);
    st.file.0 = Some(path);
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RecentKind {
    Session,
    Segmentation,
    Patient,
}

/// Recently opened files (newest first), kept in the user's configuration folder
/// (`$UMESH_CONFIG_DIR`, else `$XDG_CONFIG_HOME/umesh`, else `~/.config/umesh`).
#[derive(Resource, Default, Serialize, Deserialize)]
pub struct Recent {
    pub list: Vec<(PathBuf, RecentKind)>,
    #[serde(skip)]
    file: Option<PathBuf>,
}

const RECENT_MAX: usize = 10;

impl Recent {
    fn config_file() -> Option<PathBuf> {
        let dir = std::env::var_os("UMESH_CONFIG_DIR").map(PathBuf::from).or_else(|| {
            std::env::var_os("XDG_CONFIG_HOME")
                .map(|d| PathBuf::from(d).join("umesh"))
                .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".config/umesh")))
        })?;
        Some(dir.join("recent.json"))
    }

    /// The list on disk; a missing or damaged one is an empty list (it is only a convenience).
    pub fn load() -> Recent {
        match Self::config_file() {
            Some(f) => Self::at(f),
            None => Recent::default(),
        }
    }

    /// The list kept in `file`.
    pub fn at(file: PathBuf) -> Recent {
        let file = Some(file);
        let mut r: Recent = file
            .as_ref()
            .and_then(|f| std::fs::read_to_string(f).ok())
            .and_then(|t| serde_json::from_str(&t).ok())
            .unwrap_or_default();
        r.list.truncate(RECENT_MAX);
        r.file = file;
        r
    }

    pub fn push(&mut self, path: &Path, kind: RecentKind) {
        let path = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
        self.list.retain(|(p, _)| *p != path);
        self.list.insert(0, (path, kind));
        self.list.truncate(RECENT_MAX);
        if let Some(f) = &self.file {
            if let Some(d) = f.parent() {
                let _ = std::fs::create_dir_all(d);
            }
            if let Ok(t) = serde_json::to_string_pretty(self)
                && let Err(e) = umesh_core::write_atomic(f, t.as_bytes())
            {
                warn!("{}: {e:#}", f.display());
            }
        }
    }
}

/// A save asked for by the menu or Ctrl+S, to this file.
#[derive(Resource, Default)]
pub struct SaveRequest(pub Option<PathBuf>);

fn save_requested(mut req: ResMut<SaveRequest>, mut st: SessionState) {
    if let Some(path) = req.0.take() {
        save(&mut st, path);
    }
}

/// A PNG export of the window asked for by the menu.
#[derive(Resource, Default)]
pub struct PendingExport(pub Option<PathBuf>);

fn export_view(mut commands: Commands, mut pending: ResMut<PendingExport>, mut messages: ResMut<UiMessages>) {
    let Some(path) = pending.0.take() else { return };
    use bevy::render::view::screenshot::{Screenshot, save_to_disk};
    commands.spawn(Screenshot::primary_window()).observe(save_to_disk(path.clone()));
    messages.info(format!("view exported to {}", path.display()));
}

pub struct SessionPlugin;

impl Plugin for SessionPlugin {
    fn build(&self, app: &mut App) {
        app.init_resource::<SessionFile>()
            .init_resource::<PendingSession>()
            .init_resource::<PendingExport>()
            .init_resource::<SaveRequest>()
            .insert_resource(Recent::load())
            .add_systems(
                Update,
                (
                    apply_pending.after(crate::app::shell::tasks::poll_jobs),
                    save_requested.after(apply_pending),
                    export_view,
                ),
            );
    }
}
