//! The dataset's laparoscope pose and fixed region, chosen in the model view and used by the
//! jobs view's forms (state both views share, with its preview systems): the camera's
//! frustum drawn, the surface it sees tinted, the fixed nodes marked. The preview runs in the
//! background through the same core check as generation (`dataset::observation_setup`), so
//! what is shown (and any refusal: camera inside the organ, too little seen, an empty fixed
//! region) is what `umesh dataset generate` and `umesh prepare` will use.

use crate::app::shell::convert::{UNITS_PER_MM, bevy_from_world, world_from_bevy};
use crate::app::state::{FixedChoice, GridState, Organ, OrganData, Simulation};
use bevy::prelude::*;
use bevy::tasks::{AsyncComputeTaskPool, Task, futures::check_ready};
use bevy_egui::egui;
use nalgebra::Vector3;
use std::sync::Arc;
use umesh_core::fem::FixedRegion;
use umesh_core::segmentation::Segmentation;
use umesh_core::visible::{Camera, VisibilitySettings};
use umesh_workflow::options::DatasetOptions;

/// The named laparoscope views offered (the CLI's `--camera`).
pub const VIEWS: [&str; 9] = [
    "anterior",
    "anterior-inferior",
    "anterior-superior",
    "anterior-right",
    "anterior-left",
    "inferior",
    "superior",
    "right",
    "left",
];

#[derive(Clone, Debug, PartialEq)]
pub enum CameraChoice {
    /// A named view (`--camera`), looking at the organ's centre from 2.5 organ sizes.
    Named(String),
    /// From a point toward another, world mm (`--camera-from/--camera-to`): set from the 3-D
    /// view or by an opened patient.
    Custom { from_mm: Vector3<f64>, to_mm: Vector3<f64> },
}

#[derive(Resource)]
pub struct ObservationSetup {
    pub camera: CameraChoice,
    pub fov_deg: f64,
    /// Largest visible fraction of the surface (`--visible-fraction`).
    pub max_fraction: f64,
    /// Draw the frustum, the seen surface and the fixed nodes.
    pub show: bool,
    pub preview: Option<Arc<Preview>>,
    /// Why the current choice would be refused.
    pub error: Option<String>,
    pub generation: u64,
    computed: Option<PreviewKey>,
    task: Option<(PreviewKey, Task<anyhow::Result<Preview>>)>,
}

impl Default for ObservationSetup {
    fn default() -> Self {
        Self {
            camera: CameraChoice::Named("anterior".into()),
            fov_deg: 50.0,
            max_fraction: 0.5,
            show: true,
            preview: None,
            error: None,
            generation: 0,
            computed: None,
            task: None,
        }
    }
}

/// What a preview was computed for.
#[derive(Clone, Debug, PartialEq)]
struct PreviewKey {
    organ: u64,
    grid: u64,
    camera: CameraChoice,
    fov_deg: f64,
    max_fraction: f64,
    fixed: FixedChoice,
}

/// What the dataset's camera sees of the displayed surface and which grid nodes are fixed.
pub struct Preview {
    pub organ_generation: u64,
    pub camera: Camera,
    /// Per triangle of the displayed organ surface: seen by the camera.
    pub visible_triangles: Vec<bool>,
    pub visible_fraction: f64,
    pub visible_nodes: usize,
    pub fixed_nodes_mm: Vec<Vector3<f64>>,
    pub fixed_description: String,
    pub nodes: usize,
}

impl ObservationSetup {
    /// The dataset options for this camera and fixed region, on top of `base` (loads,
    /// material): the CLI's, so the GUI's datasets are the CLI's.
    pub fn config_args(&self, fixed: &FixedChoice, base: &DatasetOptions) -> DatasetOptions {
        let mut a = base.clone();
        a.fov_deg = self.fov_deg;
        a.visible_fraction = self.max_fraction;
        a.camera = None;
        a.camera_from.clear();
        a.camera_to.clear();
        match &self.camera {
            // The default view is no option at all (the dataset's own anterior camera).
            CameraChoice::Named(v) if v == "anterior" && self.fov_deg == 50.0 => {}
            CameraChoice::Named(v) => a.camera = Some(v.clone()),
            CameraChoice::Custom { from_mm, to_mm } => {
                a.camera_from = from_mm.iter().copied().collect();
                a.camera_to = to_mm.iter().copied().collect();
            }
        }
        a.fix_label = None;
        a.fix_box.clear();
        a.fix_plane.clear();
        match fixed {
            FixedChoice::Auto { distance_mm } => a.fix_distance_mm = *distance_mm,
            FixedChoice::Label { label, distance_mm } => {
                a.fix_label = Some(*label);
                a.fix_distance_mm = *distance_mm;
            }
            FixedChoice::Posterior { .. } | FixedChoice::Region(..) => {}
        }
        a
    }

    /// The camera and visibility the dataset will use on this organ.
    pub fn visibility(
        &self,
        seg: &Segmentation,
        fixed: &FixedChoice,
    ) -> anyhow::Result<(VisibilitySettings, FixedRegion, String)> {
        let args = self.config_args(fixed, &DatasetOptions::default());
        let camera = args.camera(seg)?;
        let (region, description) = fixed.describe(seg);
        Ok((VisibilitySettings { camera, max_fraction: self.max_fraction, ..Default::default() }, region, description))
    }

    /// Compute the preview now (screenshots: a rendered frame waits for nothing).
    pub fn compute_now(&mut self, organ: &Organ, grid: &GridState, fixed: &FixedChoice) -> anyhow::Result<()> {
        let (Some(data), Some(g)) = (&organ.data, &grid.grid) else { anyhow::bail!("no organ or grid") };
        let vis = self.visibility(&data.seg, fixed)?;
        let p = compute(data.clone(), organ.generation, g.clone(), vis)?;
        self.preview = Some(Arc::new(p));
        self.error = None;
        self.computed = Some(PreviewKey {
            organ: organ.generation,
            grid: grid.generation,
            camera: self.camera.clone(),
            fov_deg: self.fov_deg,
            max_fraction: self.max_fraction,
            fixed: fixed.clone(),
        });
        self.generation += 1;
        Ok(())
    }

    /// Adopt a dataset's camera and visible fraction (an opened patient's).
    pub fn adopt(&mut self, v: &VisibilitySettings) {
        self.max_fraction = v.max_fraction;
        match &v.camera {
            None => {
                self.camera = CameraChoice::Named("anterior".into());
                self.fov_deg = 50.0;
            }
            Some(c) => {
                let from = Vector3::from(c.position_mm);
                self.camera = CameraChoice::Custom { from_mm: from, to_mm: from + Vector3::from(c.direction) };
                self.fov_deg = c.fov_deg;
            }
        }
    }
}

fn compute(
    organ: OrganData,
    organ_generation: u64,
    grid: Arc<umesh_core::grid::ImmersedGrid>,
    setup_vis: (VisibilitySettings, FixedRegion, String),
) -> anyhow::Result<Preview> {
    let (vis, region, fixed_description) = setup_vis;
    let s = umesh_core::dataset::observation_setup(&organ.seg, &grid, &organ.surface, &vis, &region)?;
    let fixed_nodes_mm = (0..grid.node_count()).filter(|&n| s.fixed[n]).map(|n| grid.node_position(n)).collect();
    Ok(Preview {
        organ_generation,
        camera: s.visible.camera.clone(),
        visible_fraction: s.visible.fraction(),
        visible_triangles: s.visible.visible,
        visible_nodes: s.visible_nodes.len(),
        fixed_nodes_mm,
        fixed_description,
        nodes: grid.node_count(),
    })
}

/// Start a preview when the organ, grid, camera or fixed region changed; collect it.
fn update_preview(mut setup: ResMut<ObservationSetup>, organ: Res<Organ>, grid: Res<GridState>, sim: Res<Simulation>) {
    if let Some((key, task)) = &mut setup.task {
        let Some(result) = check_ready(task) else { return };
        let key = key.clone();
        setup.task = None;
        match result {
            Ok(p) => {
                setup.preview = Some(Arc::new(p));
                setup.error = None;
            }
            Err(e) => {
                setup.preview = None;
                setup.error = Some(format!("{e:#}"));
            }
        }
        setup.computed = Some(key);
        setup.generation += 1;
    }
    // Hidden, it costs nothing; shown again, it catches up.
    let (true, Some(data), Some(g)) = (setup.show, &organ.data, &grid.grid) else { return };
    let key = PreviewKey {
        organ: organ.generation,
        grid: grid.generation,
        camera: setup.camera.clone(),
        fov_deg: setup.fov_deg,
        max_fraction: setup.max_fraction,
        fixed: sim.fixed.clone(),
    };
    if setup.computed.as_ref() == Some(&key) {
        return;
    }
    let vis = match setup.visibility(&data.seg, &sim.fixed) {
        Ok(v) => v,
        Err(e) => {
            setup.preview = None;
            setup.error = Some(format!("{e:#}"));
            setup.computed = Some(key);
            setup.generation += 1;
            return;
        }
    };
    let (data, g, gen_) = (data.clone(), g.clone(), organ.generation);
    setup.task = Some((key, AsyncComputeTaskPool::get().spawn(async move { compute(data, gen_, g, vis) })));
}

/// The frustum (to just past the organ; thin lines the UI paints over the view) and the fixed
/// nodes.
fn draw_preview(
    setup: Res<ObservationSetup>,
    organ: Res<Organ>,
    mut gizmos: Gizmos,
    mut lines: ResMut<crate::app::shell::view3d::OverlayLines>,
) {
    let (true, Some(p), Some(d)) = (setup.show, &setup.preview, &organ.data) else { return };
    if p.organ_generation != organ.generation {
        return;
    }
    let c = &p.camera;
    let eye = Vector3::from(c.position_mm);
    let f = Vector3::from(c.direction).normalize();
    let up0 = if f.z.abs() < 0.9 { Vector3::z() } else { Vector3::y() };
    let r = f.cross(&up0).normalize();
    let u = r.cross(&f);
    let (lo, hi) = d.surface.bounds().unwrap_or_default();
    let depth = ((lo + hi) * 0.5 - eye).dot(&f) + 0.5 * (hi - lo).norm();
    let half = (c.fov_deg.to_radians() * 0.5).tan() * depth;
    let colour = Color::srgb(1.0, 0.85, 0.2);
    let corners: Vec<Vec3> = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
        .iter()
        .map(|(a, b)| bevy_from_world(&(eye + f * depth + r * (a * half) + u * (b * half))))
        .collect();
    let e = bevy_from_world(&eye);
    let line = egui::Color32::from_rgb(255, 217, 51);
    for k in 0..4 {
        lines.0.push((e, corners[k], line));
        lines.0.push((corners[k], corners[(k + 1) % 4], line));
    }
    gizmos.sphere(Isometry3d::from_translation(e), 4.0 * UNITS_PER_MM, colour);
    let blue = Color::srgb(0.25, 0.45, 1.0);
    for n in &p.fixed_nodes_mm {
        gizmos.sphere(Isometry3d::from_translation(bevy_from_world(n)), 1.5 * UNITS_PER_MM, blue).resolution(6);
    }
}

/// Per-vertex colours of the organ with the seen part tinted (None without a preview for it).
pub fn seen_colors(setup: &ObservationSetup, organ: &OrganData, organ_generation: u64) -> Option<Vec<[f32; 4]>> {
    let p = setup.preview.as_ref().filter(|p| setup.show && p.organ_generation == organ_generation)?;
    if p.visible_triangles.len() != organ.surface.triangles.len() {
        return None;
    }
    let mut colors = vec![[0.62, 0.25, 0.2, 0.35]; organ.surface.positions.len()];
    for (t, tri) in organ.surface.triangles.iter().enumerate() {
        if p.visible_triangles[t] {
            for &v in tri {
                colors[v as usize] = [0.35, 0.75, 0.35, 0.55];
            }
        }
    }
    Some(colors)
}

/// The camera section of the model view's left panel.
pub fn camera_ui(ui: &mut egui::Ui, setup: &mut ObservationSetup, orbit: &crate::app::shell::camera::OrbitCamera) {
    ui.checkbox(&mut setup.show, "show the camera, seen surface, fixed nodes");
    let current = match &setup.camera {
        CameraChoice::Named(v) => v.clone(),
        CameraChoice::Custom { .. } => "custom position".into(),
    };
    egui::ComboBox::from_label("laparoscope").selected_text(current).show_ui(ui, |ui| {
        for v in VIEWS {
            if ui.selectable_label(setup.camera == CameraChoice::Named(v.into()), v).clicked() {
                setup.camera = CameraChoice::Named(v.into());
            }
        }
    });
    if ui
        .button("Camera from this view")
        .on_hover_text("the laparoscope where the 3-D view's camera is, looking at its focus")
        .clicked()
    {
        let t = orbit.transform();
        setup.camera =
            CameraChoice::Custom { from_mm: world_from_bevy(t.translation), to_mm: world_from_bevy(orbit.focus) };
    }
    let mut fov = setup.fov_deg as f32;
    if ui.add(egui::Slider::new(&mut fov, 20.0..=100.0).text("field of view (deg)")).changed() {
        setup.fov_deg = fov as f64;
    }
    let mut frac = setup.max_fraction as f32;
    if ui.add(egui::Slider::new(&mut frac, 0.05..=1.0).text("largest visible fraction")).changed() {
        setup.max_fraction = frac as f64;
    }
    match (&setup.error, &setup.preview) {
        (Some(e), _) => {
            ui.colored_label(egui::Color32::LIGHT_RED, e);
        }
        (None, Some(p)) => {
            ui.label(format!(
                "sees {:.0} % of the surface, {} of {} nodes",
                100.0 * p.visible_fraction,
                p.visible_nodes,
                p.nodes
            ));
            ui.label(format!("fixed: {} nodes, {}", p.fixed_nodes_mm.len(), p.fixed_description));
        }
        (None, None) => {
            ui.weak(if !setup.show {
                "preview hidden"
            } else if setup.task.is_some() {
                "computing the preview..."
            } else {
                "build a grid to preview"
            });
        }
    }
}

/// The fixed-region choice (shared by the simulation and the dataset).
pub fn fixed_ui(ui: &mut egui::Ui, fixed: &mut FixedChoice, organ: Option<&OrganData>) {
    ui.horizontal(|ui| {
        ui.label("Fixed:");
        if ui
            .radio(matches!(fixed, FixedChoice::Auto { .. }), "default")
            .on_hover_text("near the vena cava / hepatic veins when named, else the posterior fifth")
            .clicked()
        {
            *fixed = FixedChoice::default();
        }
        if ui.radio(matches!(fixed, FixedChoice::Label { .. }), "near a label").clicked() {
            let label = organ
                .and_then(|o| umesh_core::loads::anchor_label(&o.seg))
                .map(|(l, _)| l)
                .unwrap_or(umesh_core::phantom::VENA_CAVA);
            *fixed = FixedChoice::Label { label, distance_mm: 6.0 };
        }
        if ui.radio(matches!(fixed, FixedChoice::Posterior { .. }), "posterior slab").clicked() {
            *fixed = FixedChoice::Posterior { fraction: umesh_core::loads::POSTERIOR_FRACTION };
        }
    });
    match fixed {
        FixedChoice::Auto { distance_mm } => {
            ui.add(egui::Slider::new(distance_mm, 1.0..=20.0).text("within (mm)"));
        }
        FixedChoice::Label { label, distance_mm } => {
            ui.add(egui::DragValue::new(label).prefix("label "));
            ui.add(egui::Slider::new(distance_mm, 1.0..=20.0).text("within (mm)"));
        }
        FixedChoice::Posterior { fraction } => {
            ui.add(egui::Slider::new(fraction, 0.02..=0.5).text("of the depth"));
        }
        FixedChoice::Region(_, d) => {
            ui.weak(d.as_str());
        }
    }
}

pub struct SetupPlugin;

impl Plugin for SetupPlugin {
    fn build(&self, app: &mut App) {
        app.init_resource::<ObservationSetup>().add_systems(Update, update_preview);
    }
}

pub struct SetupViewPlugin;

impl Plugin for SetupViewPlugin {
    fn build(&self, app: &mut App) {
        app.add_systems(Update, draw_preview.run_if(in_state(crate::app::state::Mode::Model)));
    }
}
