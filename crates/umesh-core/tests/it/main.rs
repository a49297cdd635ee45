//! umesh-core's integration tests, one binary with a module per area (each module's doc says
//! what it checks).

mod dataset;
mod fem;
mod grid;
mod io;
mod observation;
mod real_data;
mod rgbd;
