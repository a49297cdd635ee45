//! Force probes: a click on the organ surface places one (mesh ray cast), dragging sets its
//! direction and magnitude (arrow gizmo); probes are edited in the inspector. Rehearsal
//! mode: the dragged probes deform the organ live through the network.

use crate::app::model::compute::deformation;
use crate::app::shell::camera::MainCamera;
use crate::app::shell::convert::{bevy_dir_from_world, bevy_from_world, world_dir_from_bevy, world_from_bevy};
use crate::app::shell::tasks::{JobOutput, Jobs};
use crate::app::shell::view3d::View3d;
use crate::app::state::*;
use anyhow::Context;
use bevy::prelude::*;
use bevy::window::PrimaryWindow;
use bevy_egui::input::egui_wants_any_pointer_input;
use nalgebra::Vector3;
use std::sync::{Arc, Mutex};
use umesh_core::dataset::DatasetContext;
use umesh_core::fem::BoundaryConditions;
use umesh_core::fem::solver::SolveMethod;
use umesh_core::simulate::{SimulationSettings, solve_bc};

/// A pick ray in world RAS millimetres.
#[derive(Message, Clone, Debug)]
pub struct ProbeRay {
    pub origin_mm: Vector3<f64>,
    pub direction: Vector3<f64>,
}

#[derive(Resource, Clone, Debug)]
pub struct ProbeSettings {
    /// Force per millimetre of mouse drag (N/mm).
    pub newtons_per_mm: f64,
    /// Force of a probe placed without dragging (N), pushing inward.
    pub default_force_n: f64,
}

impl Default for ProbeSettings {
    fn default() -> Self {
        Self { newtons_per_mm: 0.01, default_force_n: 0.15 }
    }
}

/// Where a ray meets the organ: a new probe pushing inward, or None when it misses.
pub fn probe_from_ray(organ: &OrganData, ray: &ProbeRay, settings: &ProbeSettings) -> Option<Probe> {
    let hit = organ.surface.ray_cast(&ray.origin_mm, &ray.direction)?;
    Some(Probe { point_mm: hit.point, normal: hit.normal, force_n: -hit.normal * settings.default_force_n })
}

fn place_probes(
    mut rays: MessageReader<ProbeRay>,
    organ: Res<Organ>,
    settings: Res<ProbeSettings>,
    mut probes: ResMut<Probes>,
    mut messages: ResMut<UiMessages>,
) {
    for ray in rays.read() {
        let Some(data) = &organ.data else {
            messages.error("no organ loaded: open a segmentation first");
            continue;
        };
        match probe_from_ray(data, ray, &settings) {
            Some(p) => {
                let i = probes.add(p);
                probes.dragging = Some(i);
            }
            None => probes.selected = None,
        }
    }
}

fn cursor_ray(window: &Window, view: &View3d, camera: &Camera, tf: &GlobalTransform) -> Option<Ray3d> {
    let size = camera.physical_target_size()?;
    let pos = view.viewport_position(window.cursor_position()?, size)?;
    camera.viewport_to_world(tf, pos).ok()
}

/// Mouse: left press on the organ places a probe; dragging pulls it.
fn mouse_probes(
    buttons: Res<ButtonInput<MouseButton>>,
    window: Query<&Window, With<PrimaryWindow>>,
    cam: Query<(&Camera, &GlobalTransform), With<MainCamera>>,
    mut rays: MessageWriter<ProbeRay>,
    mut probes: ResMut<Probes>,
    settings: Res<ProbeSettings>,
    view: Res<View3d>,
) {
    let (Ok(window), Ok((camera, tf))) = (window.single(), cam.single()) else { return };
    let Some(ray) = cursor_ray(window, &view, camera, tf) else { return };
    if buttons.just_pressed(MouseButton::Left) {
        rays.write(ProbeRay { origin_mm: world_from_bevy(ray.origin), direction: world_dir_from_bevy(*ray.direction) });
        return;
    }
    if buttons.just_released(MouseButton::Left) {
        probes.dragging = None;
        return;
    }
    let Some(i) = probes.dragging else { return };
    if !buttons.pressed(MouseButton::Left) || i >= probes.list.len() {
        return;
    }
    // Intersect with the plane through the probe facing the camera.
    let p = bevy_from_world(&probes.list[i].point_mm);
    let n = tf.forward();
    let Some(t) = ray.intersect_plane(p, InfinitePlane3d::new(*n)) else { return };
    let drag_mm = world_from_bevy(ray.get_point(t)) - probes.list[i].point_mm;
    if drag_mm.norm() > 1.0 {
        let f = drag_mm * settings.newtons_per_mm;
        if (probes.list[i].force_n - f).norm() > 1e-6 {
            probes.list[i].force_n = f;
            probes.generation += 1;
        }
    }
}

fn draw_probes(probes: Res<Probes>, mut gizmos: Gizmos, settings: Res<ProbeSettings>) {
    for (i, p) in probes.list.iter().enumerate() {
        let a = bevy_from_world(&p.point_mm);
        let len_mm = (p.force_n.norm() / settings.newtons_per_mm).max(5.0);
        let dir = bevy_dir_from_world(&p.force_n.normalize());
        let b = a + dir * (len_mm as f32) * crate::app::shell::convert::UNITS_PER_MM;
        let color = if probes.selected == Some(i) { Color::srgb(1.0, 0.9, 0.1) } else { Color::srgb(0.1, 0.9, 1.0) };
        // The arrow ends on the surface: the force pushes along it.
        gizmos.arrow(b, a, color);
        gizmos.sphere(Isometry3d::from_translation(a), 0.04, color);
    }
}

/// Rehearsal: the network deforms the organ from the probes every frame.
#[derive(Resource, Default)]
pub struct Rehearsal {
    pub enabled: bool,
    pub model: Option<Arc<Mutex<RehearsalModel>>>,
    /// Gaussian radius over which a dragged probe moves the visible surface (mm).
    pub radius_mm: f64,
    pub shown_generation: u64,
    pub last_predict_ms: f64,
}

pub struct RehearsalModel {
    pub predictor: umesh_net::inference::Predictor,
    pub ctx: DatasetContext,
    pub field: Vec<f32>,
    /// The network input: a camera view of the probed surface, or u_s.
    pub encoder: umesh_net::inference::InputEncoder,
    /// Points of the rest surface the dataset's camera sees (what a view of the probes samples).
    pub view_rest_mm: Vec<Vector3<f64>>,
}

impl RehearsalModel {
    /// Load a model and rebuild its grid from the organ's segmentation (they must match).
    pub fn load(dir: &std::path::Path, organ: &OrganData) -> anyhow::Result<Self> {
        Self::load_checkpoint(dir, "model.safetensors", organ)
    }

    /// Load one checkpoint of a model folder (`model.safetensors`, `last.safetensors`).
    pub fn load_checkpoint(dir: &std::path::Path, file: &str, organ: &OrganData) -> anyhow::Result<Self> {
        let predictor =
            umesh_net::inference::Predictor::load_checkpoint(dir, file).with_context(|| dir.display().to_string())?;
        let config = umesh_workflow::input::model_dataset_config(Some(&predictor.info), &organ.seg);
        let ctx = DatasetContext::prepare(&organ.seg, &config, &umesh_core::Cancel::new())?;
        predictor
            .info
            .check_grid(&ctx.grid_hash(), ctx.grid.padded_shape())
            .with_context(|| dir.display().to_string())?;
        let encoder = umesh_net::inference::InputEncoder::new(&predictor.info, &ctx.grid, &ctx.surface)
            .with_context(|| dir.display().to_string())?;
        let seen = umesh_core::mesh::TriMesh {
            positions: ctx.surface.positions.clone(),
            triangles: ctx
                .surface
                .triangles
                .iter()
                .zip(&ctx.visible.visible)
                .filter(|(_, v)| **v)
                .map(|(t, _)| *t)
                .collect(),
        };
        let view_rest_mm =
            umesh_core::observation::dense_surface_points(&seen, 0.05).into_iter().map(|p| p.0).collect();
        Ok(Self { predictor, ctx, field: Vec::new(), encoder, view_rest_mm })
    }

    /// The probes' displacement (each probe's force over the drag stiffness, spread with a
    /// Gaussian of `radius_mm`) at `p`.
    fn probe_displacement(probes: &[Probe], newtons_per_mm: f64, radius_mm: f64, p: &Vector3<f64>) -> Vector3<f64> {
        probes
            .iter()
            .map(|q| {
                q.force_n / newtons_per_mm * (-(p - q.point_mm).norm_squared() / (2.0 * radius_mm * radius_mm)).exp()
            })
            .sum()
    }

    /// The network input for the probes: a camera view of the surface they move (models
    /// trained on camera views) or u_s.
    pub fn network_input(&mut self, probes: &[Probe], newtons_per_mm: f64, radius_mm: f64) -> anyhow::Result<Vec<f32>> {
        if self.encoder.takes_points() {
            let pts: Vec<Vector3<f64>> = self
                .view_rest_mm
                .iter()
                .map(|p| p + Self::probe_displacement(probes, newtons_per_mm, radius_mm, p))
                .collect();
            self.encoder.input(Some(&pts), None).map_err(anyhow::Error::from)
        } else {
            Ok(self.surface_input(probes, newtons_per_mm, radius_mm))
        }
    }

    /// u_s from the probes: each probe's displacement (its force over the drag stiffness)
    /// spread over the visible nodes with a Gaussian of `radius_mm`.
    pub fn surface_input(&self, probes: &[Probe], newtons_per_mm: f64, radius_mm: f64) -> Vec<f32> {
        let g = &self.ctx.grid;
        let [x, y, z] = g.padded_shape();
        let cells = x * y * z;
        let mut u_s = vec![0f32; 3 * cells];
        for &n in &self.ctx.visible_nodes {
            let u = Self::probe_displacement(probes, newtons_per_mm, radius_mm, &g.node_position(n));
            let d = g.dense_index(n);
            for c in 0..3 {
                u_s[c * cells + d] = u[c] as f32;
            }
        }
        u_s
    }

    pub fn nodal(&self, field: &[f32]) -> Vec<Vector3<f64>> {
        let g = &self.ctx.grid;
        let [x, y, z] = g.padded_shape();
        let cells = x * y * z;
        (0..g.node_count())
            .map(|n| {
                let d = g.dense_index(n);
                Vector3::new(field[d] as f64, field[cells + d] as f64, field[2 * cells + d] as f64)
            })
            .collect()
    }
}

fn rehearse(
    mut reh: ResMut<Rehearsal>,
    probes: Res<Probes>,
    organ: Res<Organ>,
    settings: Res<ProbeSettings>,
    mut sim: ResMut<Simulation>,
    mut messages: ResMut<UiMessages>,
) {
    if !reh.enabled || reh.shown_generation == probes.generation {
        return;
    }
    let (Some(model), Some(data)) = (reh.model.clone(), &organ.data) else { return };
    reh.shown_generation = probes.generation;
    let Ok(mut m) = model.lock() else { return };
    let t = std::time::Instant::now();
    let input = m.network_input(&probes.list, settings.newtons_per_mm, reh.radius_mm.max(1.0));
    let shape = m.ctx.grid.padded_shape();
    let field =
        match input.and_then(|x| m.predictor.predict(&x, shape).map(|f| f.to_vec()).map_err(anyhow::Error::from)) {
            Ok(f) => f,
            Err(e) => {
                messages.error(format!("prediction failed: {e:#}"));
                reh.enabled = false;
                return;
            }
        };
    let u = m.nodal(&field);
    m.field = field;
    reh.last_predict_ms = t.elapsed().as_secs_f64() * 1e3;
    let d = deformation(&m.ctx.grid, data, &u, Vec::new(), reh.last_predict_ms, "U-Net");
    sim.check = None;
    sim.set(d);
}

/// Compare the rehearsal prediction with the SVK solution for the same surface displacement.
pub fn start_fe_check(
    jobs: &mut Jobs,
    reh: &Rehearsal,
    probes: &Probes,
    organ: &Organ,
    settings: &ProbeSettings,
) -> anyhow::Result<()> {
    let model = reh.model.clone().context("load a model first")?;
    let data = organ.data.clone().context("no organ")?;
    let list = probes.list.clone();
    let (k, r) = (settings.newtons_per_mm, reh.radius_mm.max(1.0));
    jobs.spawn("FE check", move |progress, cancel| {
        let m = model.lock().map_err(|_| anyhow::anyhow!("model lock poisoned"))?;
        let u_s = m.surface_input(&list, k, r);
        let g = &m.ctx.grid;
        let [x, y, z] = g.padded_shape();
        let cells = x * y * z;
        let mut bc = BoundaryConditions::new(g.node_count());
        bc.fixed = m.ctx.fixed.clone();
        bc.prescribed_mm = m
            .ctx
            .visible_nodes
            .iter()
            .filter(|&&n| !bc.fixed[n])
            .map(|&n| {
                let d = g.dense_index(n);
                (n, Vector3::new(u_s[d] as f64, u_s[cells + d] as f64, u_s[2 * cells + d] as f64))
            })
            .collect();
        let settings = SimulationSettings {
            material: Default::default(),
            solver: Default::default(),
            method: SolveMethod::Newton,
            fixed: Vec::new(),
            forces: Vec::new(),
        };
        let t = std::time::Instant::now();
        let sol = solve_bc(g, &bc, &settings, progress, cancel)?;
        let fe = deformation(g, &data, &sol.displacement_mm, Vec::new(), t.elapsed().as_secs_f64() * 1e3, "SVK check");
        let net = deformation(g, &data, &m.nodal(&m.field), Vec::new(), 0.0, "U-Net");
        let diffs: Vec<f64> =
            fe.surface.positions.iter().zip(&net.surface.positions).map(|(a, b)| (a - b).norm()).collect();
        let mean = diffs.iter().sum::<f64>() / diffs.len().max(1) as f64;
        let max = diffs.iter().copied().fold(0.0, f64::max);
        Ok(JobOutput::Checked { fe, mean_mm: mean, max_mm: max })
    });
    Ok(())
}

pub struct ProbesPlugin;

impl Plugin for ProbesPlugin {
    fn build(&self, app: &mut App) {
        app.add_message::<ProbeRay>()
            .init_resource::<ProbeSettings>()
            .insert_resource(Rehearsal { radius_mm: 25.0, ..default() })
            .init_resource::<ModelToLoad>()
            .add_systems(Update, ((place_probes, rehearse).chain(), load_chosen_model));
    }
}

/// A model chosen elsewhere (the jobs view's dashboard) becomes the rehearsal's, on this organ.
fn load_chosen_model(mut to_load: ResMut<ModelToLoad>, organ: Res<Organ>, mut jobs: ResMut<Jobs>) {
    if let Some(m) = to_load.0.take()
        && let Some(d) = &organ.data
    {
        jobs.spawn("load model", load_model_job(m.dir, m.checkpoint, d.clone()));
    }
}

/// The interactive half (needs a window, a camera and gizmos).
pub struct ProbeInputPlugin;

impl Plugin for ProbeInputPlugin {
    fn build(&self, app: &mut App) {
        app.add_systems(
            Update,
            (mouse_probes.run_if(not(egui_wants_any_pointer_input)).before(place_probes), draw_probes)
                .run_if(in_state(Mode::Model)),
        );
    }
}

/// Load a model's checkpoint for rehearsal in the background; once loaded, rehearsal is on.
pub fn load_model_job(
    dir: std::path::PathBuf,
    file: String,
    organ: OrganData,
) -> impl FnOnce(&umesh_core::Progress, &umesh_core::Cancel) -> anyhow::Result<JobOutput> + Send + 'static {
    move |_, _| {
        let m = RehearsalModel::load_checkpoint(&dir, &file, &organ)?;
        Ok(JobOutput::Apply(Box::new(move |world| {
            let mut r = world.resource_mut::<Rehearsal>();
            r.model = Some(std::sync::Arc::new(std::sync::Mutex::new(m)));
            r.enabled = true;
            r.shown_generation = u64::MAX;
            Ok("model loaded: rehearsal on (drag the probes)".to_string())
        })))
    }
}
