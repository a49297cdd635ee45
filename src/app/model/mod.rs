//! The model view: the organ and its structures, the grid preview, force probes and
//! rehearsal, the scan's slices, sessions, the
//! background computations behind them, and its panels.

pub mod compute;
pub mod grid_preview;
pub mod panel;
pub mod probes;
pub mod scene;
pub mod session;
pub mod view;
