//! The application's integration tests, one binary (one link of bevy and burn): a module per
//! area. `app`: the app's logic headless and a live window; `camera`: RealSense recordings and
//! the bridge, without a camera; `cli`: every command as a user runs it; `guides`: the guides' command blocks; `screenshots`: every
//! scene against its reference; `architecture`: the import rules.

mod app;
mod architecture;
mod camera;
mod cli;
mod guides;
mod screenshots;
mod support;
