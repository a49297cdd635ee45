//! The jobs view: the dataset / training / patient queue and its dashboard.

pub mod panel;
pub mod queue;
pub mod view;
