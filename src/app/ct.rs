//! The scan under the model: the CT (or MR) the segmentation was made from, as axial,
//! coronal and sagittal slices in the 3-D view of the model and QA views, each toggled and
//! moved, windowed by preset, with the organ's rest outline and the shown deformation's
//! outline drawn on it (core's `slices`).

use crate::app::shell::convert::{bevy_dir_from_world, bevy_from_world};
use crate::app::state::{CtImage, Mode, Organ, QaTruth, Simulation};
use bevy::asset::RenderAssetUsages;
use bevy::mesh::{Indices, PrimitiveTopology};
use bevy::prelude::*;
use bevy::render::render_resource::{Extent3d, TextureDimension, TextureFormat};
use bevy_egui::egui;
use nalgebra::Vector3;
use std::path::Path;
use std::sync::Arc;
use umesh_core::slices::{self, SliceAxis, Window};

/// The rest outline (organ at rest) and the deformed one, on the slices.
const REST_RGB: [u8; 3] = [255, 205, 40];
const DEFORMED_RGB: [u8; 3] = [40, 230, 255];
/// The longer side of a slice image at most (pixels).
const MAX_SIDE_PX: usize = 512;

/// Read a scan and check that it lies where the organ is (`organ_bounds`, world mm).
pub fn read_ct(path: &Path, organ_bounds: Option<(Vector3<f64>, Vector3<f64>)>) -> anyhow::Result<CtImage> {
    let volume = slices::read_scan(path, organ_bounds)?;
    let (lo_mm, hi_mm) = slices::world_bounds(&volume);
    let hounsfield = volume.data.iter().copied().filter(|v| v.is_finite()).fold(f32::INFINITY, f32::min) < -500.0;
    Ok(CtImage { volume, source: path.to_path_buf(), lo_mm, hi_mm, hounsfield })
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Preset {
    Abdomen,
    Liver,
    /// The image's 1st..99th percentile (MR, or a CT not in HU).
    Range,
    Custom,
}

impl Preset {
    const ALL: [(Preset, &'static str); 3] = [
        (Preset::Abdomen, "abdomen (W 400, L 40)"),
        (Preset::Liver, "liver (W 150, L 60)"),
        (Preset::Range, "image range"),
    ];
}

/// Which slices show, where, and how they are windowed.
#[derive(Resource)]
pub struct CtView {
    /// Per axis, in `SliceAxis::ALL` order.
    pub show: [bool; 3],
    pub position_mm: [f64; 3],
    pub window: Window,
    pub preset: Preset,
    pub outlines: bool,
    pub generation: u64,
    /// The organ generation and scan the positions were set for.
    seen: (u64, usize),
}

impl Default for CtView {
    fn default() -> Self {
        Self {
            show: [true, true, true],
            position_mm: [0.0; 3],
            window: Window::LIVER,
            preset: Preset::Liver,
            outlines: true,
            generation: 0,
            seen: (u64::MAX, 0),
        }
    }
}

impl CtView {
    /// Slices through the organ's centre, the window for the kind of image.
    pub fn reset(&mut self, ct: &CtImage, organ_centre_mm: Vector3<f64>) {
        for (i, a) in SliceAxis::ALL.iter().enumerate() {
            let n = a.normal_axis();
            self.position_mm[i] = organ_centre_mm[n].clamp(ct.lo_mm[n], ct.hi_mm[n]);
        }
        self.set_preset(if ct.hounsfield { Preset::Liver } else { Preset::Range }, ct);
        self.generation += 1;
    }

    /// Saved slices for the organ of `organ_generation` and its scan `ct` (not reset).
    pub fn restore(
        &mut self,
        show: [bool; 3],
        position_mm: [f64; 3],
        window: Window,
        organ_generation: u64,
        ct: &Arc<CtImage>,
    ) {
        self.show = show;
        self.position_mm = position_mm;
        self.window = window;
        self.preset = Preset::Custom;
        self.seen = (organ_generation, Arc::as_ptr(ct) as usize);
        self.generation += 1;
    }

    pub fn set_preset(&mut self, p: Preset, ct: &CtImage) {
        self.preset = p;
        self.window = match p {
            Preset::Abdomen => Window::ABDOMEN,
            Preset::Liver => Window::LIVER,
            Preset::Range => Window::auto(&ct.volume),
            Preset::Custom => self.window,
        };
        self.generation += 1;
    }
}

/// The scan's panel: source, one row per slice (toggle and position), window, outlines.
pub fn ct_ui(ui: &mut egui::Ui, view: &mut CtView, organ: &Organ) {
    let Some(ct) = organ.data.as_ref().and_then(|d| d.ct.clone()) else {
        ui.weak("No scan (File > Open CT image...: the scan of this segmentation).");
        return;
    };
    let name = ct.source.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    ui.label(format!("{name}: {:?} voxels", ct.volume.dims)).on_hover_text(ct.source.display().to_string());
    let mut changed = false;
    for (i, a) in SliceAxis::ALL.iter().enumerate() {
        let n = a.normal_axis();
        ui.horizontal(|ui| {
            changed |= ui.checkbox(&mut view.show[i], a.name()).changed();
            let r =
                egui::Slider::new(&mut view.position_mm[i], ct.lo_mm[n]..=ct.hi_mm[n]).suffix(" mm").max_decimals(0);
            changed |= ui.add_enabled(view.show[i], r).changed();
        });
    }
    let mut preset = view.preset;
    egui::ComboBox::from_label("window")
        .selected_text(Preset::ALL.iter().find(|p| p.0 == preset).map(|p| p.1).unwrap_or("custom"))
        .show_ui(ui, |ui| {
            for (p, label) in Preset::ALL {
                ui.selectable_value(&mut preset, p, label);
            }
        });
    if preset != view.preset {
        view.set_preset(preset, &ct);
    }
    ui.horizontal(|ui| {
        let (mut l, mut w) = (view.window.level, view.window.width);
        let rl = ui.add(egui::DragValue::new(&mut l).speed(2.0).prefix("L "));
        let rw = ui.add(egui::DragValue::new(&mut w).speed(2.0).range(1.0..=10000.0).prefix("W "));
        if rl.changed() || rw.changed() {
            view.window = Window { level: l, width: w.max(1.0) };
            view.preset = Preset::Custom;
            changed = true;
        }
    });
    changed |= ui
        .checkbox(&mut view.outlines, "outlines")
        .on_hover_text("yellow: the organ at rest; cyan: as shown deformed")
        .changed();
    if changed {
        view.generation += 1;
    }
}

#[derive(Component)]
struct SliceMesh;

/// What a slice image was made from: rebuilt only when this changes.
#[derive(Clone, PartialEq)]
struct SliceKey {
    organ: u64,
    view: u64,
    deformed: (u8, u64),
    position_bits: u64,
}

/// The deformed surface to outline: the shown simulation or rehearsal in the model view, the
/// sample's FE truth in the QA view. With its identity, to rebuild only on change.
fn deformed_surface<'a>(
    mode: Mode,
    sim: &'a Simulation,
    qa: &'a QaTruth,
) -> Option<((u8, u64), &'a umesh_core::mesh::TriMesh)> {
    match mode {
        Mode::Model => {
            sim.result.as_ref().filter(|_| sim.show_deformed).map(|d| ((1, sim.generation), d.surface.as_ref()))
        }
        Mode::Qa => qa.surface.as_deref().map(|s| ((2, qa.generation), s)),
        _ => None,
    }
}

#[allow(clippy::too_many_arguments)]
fn sync(
    mut commands: Commands,
    mut view: ResMut<CtView>,
    organ: Res<Organ>,
    sim: Res<Simulation>,
    qa: Res<QaTruth>,
    mode: Res<State<Mode>>,
    mut shown: Local<[Option<(SliceKey, Entity)>; 3]>,
    mut meshes: ResMut<Assets<Mesh>>,
    mut images: ResMut<Assets<Image>>,
    mut materials: ResMut<Assets<StandardMaterial>>,
) {
    let ct = organ.data.as_ref().and_then(|d| d.ct.clone());
    let seen = (organ.generation, ct.as_ref().map(|c| Arc::as_ptr(c) as usize).unwrap_or(0));
    if let (Some(ct), true) = (&ct, view.seen != seen) {
        let centre =
            organ.data.as_ref().and_then(|d| d.surface.bounds()).map(|(lo, hi)| (lo + hi) * 0.5).unwrap_or_default();
        view.reset(ct, centre);
        view.seen = seen;
    }
    let mode = *mode.get();
    let in_view = matches!(mode, Mode::Model | Mode::Qa);
    let deformed = deformed_surface(mode, &sim, &qa);
    for (i, axis) in SliceAxis::ALL.iter().enumerate() {
        let want = ct.as_ref().filter(|_| in_view && view.show[i]).map(|_| SliceKey {
            organ: organ.generation,
            view: view.generation,
            deformed: deformed.map(|d| d.0).unwrap_or_default(),
            position_bits: view.position_mm[i].to_bits(),
        });
        if shown[i].as_ref().map(|s| &s.0) == want.as_ref() {
            continue;
        }
        if let Some((_, e)) = shown[i].take() {
            commands.entity(e).despawn();
        }
        let (Some(key), Some(ct), Some(data)) = (want, &ct, &organ.data) else { continue };
        let mut s = match slices::slice(&ct.volume, *axis, view.position_mm[i], view.window, MAX_SIDE_PX) {
            Ok(s) => s,
            Err(e) => {
                warn!("{} slice: {e:#}", axis.name());
                continue;
            }
        };
        if view.outlines {
            s.draw_section(&data.surface, REST_RGB, 2.0);
            if let Some((_, m)) = deformed {
                s.draw_section(m, DEFORMED_RGB, 2.0);
            }
        }
        let e = commands.spawn((
            Mesh3d(meshes.add(slice_quad(&s))),
            MeshMaterial3d(materials.add(StandardMaterial {
                base_color_texture: Some(images.add(slice_image(&s))),
                unlit: true,
                alpha_mode: AlphaMode::Mask(0.5),
                cull_mode: None,
                double_sided: true,
                ..default()
            })),
            SliceMesh,
        ));
        shown[i] = Some((key, e.id()));
    }
}

fn slice_image(s: &slices::Slice) -> Image {
    Image::new(
        Extent3d { width: s.width as u32, height: s.height as u32, depth_or_array_layers: 1 },
        TextureDimension::D2,
        s.rgba.clone(),
        TextureFormat::Rgba8UnormSrgb,
        RenderAssetUsages::RENDER_WORLD,
    )
}

/// The slice's rectangle in the scene, texture row 0 along its (u min, v min) edge.
fn slice_quad(s: &slices::Slice) -> Mesh {
    let c = s.corners_mm();
    let mut nrm = Vector3::zeros();
    nrm[s.axis.normal_axis()] = 1.0;
    let n = bevy_dir_from_world(&nrm).to_array();
    let mut mesh = Mesh::new(PrimitiveTopology::TriangleList, RenderAssetUsages::default());
    mesh.insert_attribute(
        Mesh::ATTRIBUTE_POSITION,
        c.iter().map(|p| bevy_from_world(p).to_array()).collect::<Vec<_>>(),
    );
    mesh.insert_attribute(Mesh::ATTRIBUTE_NORMAL, vec![n; 4]);
    mesh.insert_attribute(Mesh::ATTRIBUTE_UV_0, vec![[0.0f32, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]);
    mesh.insert_indices(Indices::U32(vec![0, 1, 2, 0, 2, 3]));
    mesh
}

pub struct CtPlugin;

impl Plugin for CtPlugin {
    fn build(&self, app: &mut App) {
        app.init_resource::<CtView>().add_systems(PostUpdate, sync);
    }
}
