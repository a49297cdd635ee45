//! The 3-D view: the main camera renders offscreen into an image, and the UI shows that
//! image in the space the panels leave. The image can be smaller than the view (a render
//! scale): on a software rasteriser (llvmpipe, lavapipe) fragment work dominates the frame,
//! so the view renders there at a quarter of the resolution and without shadows by default.

use bevy::asset::RenderAssetUsages;
use bevy::prelude::*;
use bevy::render::render_resource::{Extent3d, TextureFormat};
use bevy::render::renderer::RenderAdapterInfo;
use bevy_egui::{EguiTextureHandle, EguiUserTextures, egui};
use std::sync::atomic::{AtomicUsize, Ordering};

/// How the 3-D view is rendered; the View menu edits it.
#[derive(Clone, Debug, PartialEq)]
pub struct Quality {
    /// Rendered pixels per displayed pixel along each axis (0.25..=1).
    pub render_scale: f32,
    pub shadows: bool,
}

impl Quality {
    pub const FULL: Quality = Quality { render_scale: 1.0, shadows: true };
    /// Measured with `umesh bench ui` on llvmpipe (1280 x 800, SVK solve running): with the
    /// organ sampled every fourth voxel, 44 ms a frame at this scale, 53 ms at 0.35, 78 ms at
    /// 0.5 with the organ sampled every second voxel.
    pub const SOFTWARE: Quality = Quality { render_scale: 0.25, shadows: false };
}

/// Voxel step of the organ's display surface: llvmpipe's geometry work does not shrink with
/// the render scale, so software rasterisers get a coarser organ (about 17k triangles on the
/// phantom instead of 68k).
static DISPLAY_SURFACE_STEP: AtomicUsize = AtomicUsize::new(2);

pub fn display_surface_step() -> usize {
    DISPLAY_SURFACE_STEP.load(Ordering::Relaxed)
}

#[derive(Resource)]
pub struct View3d {
    pub image: Handle<Image>,
    pub texture: Option<egui::TextureId>,
    /// The view's rectangle in logical window pixels (egui points), set by the UI each frame.
    pub rect: Option<egui::Rect>,
    pub pixels_per_point: f32,
    pub quality: Quality,
    /// The adapter's name and whether it rasterises on the CPU, once known.
    pub adapter: Option<(String, bool)>,
    /// The quality was chosen by a user (or a test); adapter detection leaves it alone.
    pub quality_locked: bool,
    /// Whether the current mode shows the 3-D view (the camera renders only then).
    pub active: bool,
}

impl FromWorld for View3d {
    fn from_world(world: &mut World) -> Self {
        let mut img = Image::new_target_texture(64, 64, TextureFormat::Rgba8UnormSrgb, None);
        img.asset_usage = RenderAssetUsages::default();
        img.data = None;
        // The old contents are redrawn anyway.
        img.copy_on_resize = false;
        // Upscaled by the UI: linear filtering, not blocks.
        img.sampler = bevy::image::ImageSampler::linear();
        let image = world.resource_mut::<Assets<Image>>().add(img);
        // UMESH_QUALITY=full|software overrides the adapter-based choice (benchmarks, tests).
        let forced = match std::env::var("UMESH_QUALITY").as_deref() {
            Ok("full") => Some(Quality::FULL),
            Ok("software") => Some(Quality::SOFTWARE),
            _ => None,
        };
        let quality_locked = forced.is_some();
        let quality = forced.unwrap_or(Quality::FULL);
        Self {
            image,
            texture: None,
            rect: None,
            pixels_per_point: 1.0,
            quality,
            adapter: None,
            quality_locked,
            active: true,
        }
    }
}

impl View3d {
    /// The image size for the current rectangle and render scale (physical pixels).
    pub fn image_size(&self) -> Option<UVec2> {
        let r = self.rect?;
        let s = self.pixels_per_point * self.quality.render_scale.clamp(0.25, 1.0);
        let size = UVec2::new((r.width() * s).round() as u32, (r.height() * s).round() as u32);
        (size.x >= 16 && size.y >= 16).then_some(size)
    }

    /// A cursor position in logical window pixels -> the camera's viewport position (image
    /// pixels), or None outside the view.
    pub fn viewport_position(&self, cursor: Vec2, image_size: UVec2) -> Option<Vec2> {
        let r = self.rect?;
        if !r.contains(egui::pos2(cursor.x, cursor.y)) || r.width() <= 0.0 || r.height() <= 0.0 {
            return None;
        }
        let u = (cursor.x - r.min.x) / r.width();
        let v = (cursor.y - r.min.y) / r.height();
        Some(Vec2::new(u * image_size.x as f32, v * image_size.y as f32))
    }
}

/// Choose the quality from the adapter once it is known: software rasterisers get
/// [`Quality::SOFTWARE`] and a coarser organ surface.
pub fn detect_adapter(info: Option<Res<RenderAdapterInfo>>, mut view: ResMut<View3d>) {
    if view.adapter.is_some() {
        return;
    }
    let Some(info) = info else { return };
    let software = format!("{:?}", info.device_type) == "Cpu"
        || ["llvmpipe", "lavapipe", "softpipe", "swiftshader"].iter().any(|n| info.name.to_lowercase().contains(n));
    info!(
        "render adapter: {} ({:?}, {:?}); software rasteriser: {software}",
        info.name, info.backend, info.device_type
    );
    view.adapter = Some((info.name.clone(), software));
    if software && !view.quality_locked {
        view.quality = Quality::SOFTWARE;
    }
    DISPLAY_SURFACE_STEP.store(if view.quality == Quality::SOFTWARE { 4 } else { 2 }, Ordering::Relaxed);
}

/// Keep the image the size the view needs and registered with egui.
fn resize_image(mut view: ResMut<View3d>, mut images: ResMut<Assets<Image>>, mut textures: ResMut<EguiUserTextures>) {
    if view.texture.is_none() {
        view.texture = Some(textures.add_image(EguiTextureHandle::Strong(view.image.clone())));
    }
    let Some(size) = view.image_size() else { return };
    let Some(img) = images.get(&view.image) else { return };
    if img.size() != size
        && let Some(mut img) = images.get_mut(&view.image)
    {
        img.resize(Extent3d { width: size.x, height: size.y, depth_or_array_layers: 1 });
    }
}

fn apply_shadows(
    view: Res<View3d>,
    mut lights: Query<&mut DirectionalLight>,
    mut cams: Query<&mut Camera, With<crate::app::shell::camera::MainCamera>>,
) {
    if view.is_changed() {
        for mut c in &mut cams {
            if c.is_active != view.active {
                c.is_active = view.active;
            }
        }
        for mut l in &mut lights {
            if l.shadow_maps_enabled != view.quality.shadows {
                l.shadow_maps_enabled = view.quality.shadows;
            }
        }
    }
}

/// Lines over the 3-D view, painted by the UI at the display's resolution: thin and crisp
/// where the view renders at a fraction of it (a 2-pixel gizmo line is 8 pixels wide at a
/// quarter), clipped to the camera's near plane and to the view. Producers set them each
/// frame; the shell paints and clears them.
#[derive(Resource, Default)]
pub struct OverlayLines(pub Vec<(Vec3, Vec3, egui::Color32)>);

/// Paint `lines` (world space) as the main camera sees them, into `rect` (the 3-D view).
pub fn paint_lines(
    painter: &egui::Painter,
    rect: egui::Rect,
    camera: &Camera,
    at: &GlobalTransform,
    lines: &[(Vec3, Vec3, egui::Color32)],
) {
    let view_from_world = at.affine().inverse();
    let clip_from_view = camera.clip_from_view();
    // The near plane's depth (view space looks along -z): points closer are cut off.
    let near = {
        let p = clip_from_view.inverse() * Vec4::new(0.0, 0.0, 1.0, 1.0);
        p.z / p.w
    };
    let painter = painter.with_clip_rect(rect);
    let to_screen = |v: Vec3| {
        let c = clip_from_view * v.extend(1.0);
        let ndc = c.truncate() / c.w;
        egui::pos2(rect.min.x + (ndc.x + 1.0) * 0.5 * rect.width(), rect.min.y + (1.0 - ndc.y) * 0.5 * rect.height())
    };
    for (a, b, colour) in lines {
        let (mut va, mut vb) = (view_from_world.transform_point3(*a), view_from_world.transform_point3(*b));
        let limit = near - 1e-4;
        if va.z > limit && vb.z > limit {
            continue;
        }
        // Cut at the near plane the part of the segment behind it.
        if va.z > limit {
            va = va + (vb - va) * ((va.z - limit) / (va.z - vb.z));
        } else if vb.z > limit {
            vb = vb + (va - vb) * ((vb.z - limit) / (vb.z - va.z));
        }
        painter.line_segment([to_screen(va), to_screen(vb)], egui::Stroke::new(1.5, *colour));
    }
}

pub struct View3dPlugin;

impl Plugin for View3dPlugin {
    fn build(&self, app: &mut App) {
        // PreStartup: before the first organ is loaded, which reads the display step.
        app.init_resource::<View3d>()
            .init_resource::<OverlayLines>()
            .add_systems(PreStartup, detect_adapter)
            .add_systems(Update, (detect_adapter, resize_image, apply_shadows).chain());
    }
}
