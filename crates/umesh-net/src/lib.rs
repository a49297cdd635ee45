//! umesh-net: the U-Mesh 3-D U-Net on burn (CPU `flex` backend by default): model, data,
//! training, evaluation by target registration error, and inference.

pub mod data;
mod error;
pub mod eval;
pub mod fast;
pub mod inference;
pub mod info;
pub mod model;
pub mod training;
pub mod tre;

pub use burn;
pub use error::NetError;
pub use info::{LrSchedule, ModelInfo, TrainSettings};
pub use model::{UNet, UNetConfig};
