//! Orbit camera: right-drag rotates, middle-drag (or shift + right-drag) pans, the wheel
//! zooms, F frames the organ. Input that egui takes is ignored.

use crate::app::shell::convert::bevy_from_world;
use crate::app::state::Organ;
use bevy::input::mouse::{AccumulatedMouseMotion, AccumulatedMouseScroll, MouseScrollUnit};
use bevy::prelude::*;
use bevy_egui::input::{egui_wants_any_keyboard_input, egui_wants_any_pointer_input};

#[derive(Resource, Clone, Debug)]
pub struct OrbitCamera {
    pub focus: Vec3,
    pub yaw: f32,
    pub pitch: f32,
    pub distance: f32,
    /// Organ generation the camera was last framed on.
    framed: u64,
}

impl Default for OrbitCamera {
    fn default() -> Self {
        // Looking at the patient's anterior side (from +y RAS = -z Bevy), slightly from above.
        Self { focus: Vec3::ZERO, yaw: 0.0, pitch: -0.35, distance: 6.0, framed: 0 }
    }
}

impl OrbitCamera {
    pub fn transform(&self) -> Transform {
        let rot = Quat::from_euler(EulerRot::YXZ, self.yaw, self.pitch, 0.0);
        // Camera looks along its -z; place it on the -z side of the focus (anterior).
        let offset = rot * Vec3::new(0.0, 0.0, -self.distance);
        Transform::from_translation(self.focus + offset).looking_at(self.focus, Vec3::Y)
    }

    /// Fit the organ's bounds in view.
    /// A saved view, kept for the organ of `organ_generation` (not reframed).
    pub fn set_view(&mut self, focus: Vec3, yaw: f32, pitch: f32, distance: f32, organ_generation: u64) {
        *self = Self { focus, yaw, pitch, distance, framed: organ_generation };
    }

    pub fn frame(&mut self, organ: &Organ) {
        if let Some(d) = &organ.data
            && let Some((lo, hi)) = d.surface.bounds()
        {
            let (a, b) = (bevy_from_world(&lo), bevy_from_world(&hi));
            self.focus = (a + b) * 0.5;
            self.distance = (a - b).length() * 1.9;
        }
        self.framed = organ.generation;
    }
}

#[derive(Component)]
pub struct MainCamera;

fn orbit(
    mut cam: ResMut<OrbitCamera>,
    motion: Res<AccumulatedMouseMotion>,
    scroll: Res<AccumulatedMouseScroll>,
    buttons: Res<ButtonInput<MouseButton>>,
    keys: Res<ButtonInput<KeyCode>>,
) {
    let d = motion.delta;
    let shift = keys.pressed(KeyCode::ShiftLeft) || keys.pressed(KeyCode::ShiftRight);
    if buttons.pressed(MouseButton::Middle) || (buttons.pressed(MouseButton::Right) && shift) {
        let t = cam.transform();
        let s = cam.distance * 0.0015;
        let pan = t.right() * -d.x * s + t.up() * d.y * s;
        cam.focus += pan;
    } else if buttons.pressed(MouseButton::Right) {
        cam.yaw -= d.x * 0.008;
        cam.pitch = (cam.pitch - d.y * 0.008).clamp(-1.5, 1.5);
    }
    let wheel = match scroll.unit {
        MouseScrollUnit::Line => scroll.delta.y,
        MouseScrollUnit::Pixel => scroll.delta.y / 40.0,
    };
    if wheel != 0.0 {
        cam.distance = (cam.distance * (1.0 - 0.1 * wheel)).clamp(0.2, 200.0);
    }
}

fn frame_key(mut cam: ResMut<OrbitCamera>, keys: Res<ButtonInput<KeyCode>>, organ: Res<Organ>) {
    if keys.just_pressed(KeyCode::KeyF) || cam.framed != organ.generation {
        cam.frame(&organ);
    }
}

fn apply(cam: Res<OrbitCamera>, mut q: Query<&mut Transform, With<MainCamera>>) {
    if cam.is_changed() {
        for mut t in &mut q {
            *t = cam.transform();
        }
    }
}

pub struct OrbitCameraPlugin;

impl Plugin for OrbitCameraPlugin {
    fn build(&self, app: &mut App) {
        app.init_resource::<OrbitCamera>().add_systems(
            Update,
            (
                orbit.run_if(not(egui_wants_any_pointer_input)),
                frame_key.run_if(not(egui_wants_any_keyboard_input)),
                apply,
            )
                .chain(),
        );
    }
}
