//! The shell around the views: menus and the panel layout (`ui`), the offscreen 3-D view and
//! its orbit camera, core <-> Bevy conversions, the background task runner, headless scenes.

pub mod camera;
pub mod convert;
pub mod screenshot;
pub mod tasks;
pub mod ui;
pub mod view3d;
pub mod views;
