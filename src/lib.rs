//! umesh: physics-based deep network for augmented reality in liver surgery.
//!
//! The binary (`main.rs`) is a thin shell over [`cli`]; the desktop app lives in [`app`].

pub mod app;
pub mod cli;
