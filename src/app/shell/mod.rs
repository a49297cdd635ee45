//! The services every view uses, knowing none of them: the view registry (`views`), the
//! offscreen 3-D view and its orbit camera, core <-> Bevy conversions, the background task
//! runner, the shortcut keys' modifier.

pub mod camera;
pub mod convert;
pub mod tasks;
pub mod view3d;
pub mod views;

use bevy::prelude::{ButtonInput, KeyCode};

/// Held, or pressed and released within this frame (a fast chord, a slow frame).
pub fn ctrl_held(keys: &ButtonInput<KeyCode>) -> bool {
    let ctrl_keys = [KeyCode::ControlLeft, KeyCode::ControlRight];
    keys.any_pressed(ctrl_keys) || keys.any_just_pressed(ctrl_keys) || keys.any_just_released(ctrl_keys)
}
