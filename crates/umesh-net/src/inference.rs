//! Inference: surface displacement grid in, volume displacement grid out, batch of one.

use crate::model::load_weights;
use crate::model::{UNet, UNetConfig};
use crate::{ModelInfo, NetError};
use burn::prelude::*;
use std::path::Path;

/// A predicted displacement beyond this (mm) is no organ's: the model is corrupt.
pub const MAX_DISPLACEMENT_MM: f32 = 1000.0;

pub struct Predictor {
    pub info: ModelInfo,
    model: UNet,
    device: Device,
    /// The same weights for the per-frame forward pass (None: the layers are not the
    /// U-Net's, burn runs them).
    fast: Option<crate::fast::FastUNet>,
    /// Run burn's forward pass instead of the fast one (to compare them).
    pub use_burn: bool,
    /// The outputs a caller reads (`read_only_at`), with what the fast pass needs for them.
    read_at: Option<(Vec<usize>, Option<crate::fast::Needed>)>,
    input: Vec<f32>,
    output: Vec<f32>,
    /// `confidence.json` of the model folder, when it has one.
    pub confidence: Option<umesh_core::register::confidence::ConfidenceReference>,
}

impl std::fmt::Debug for Predictor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Predictor").field("config", &self.info.config).finish()
    }
}

impl Predictor {
    /// Load `model.json` and `model.safetensors` from a model folder.
    pub fn load(dir: &Path) -> Result<Self, NetError> {
        Self::load_checkpoint(dir, "model.safetensors")
    }

    /// Load `model.json` and one checkpoint of the folder: `model.safetensors` (the best
    /// validation epoch) or `last.safetensors` (the latest epoch).
    pub fn load_checkpoint(dir: &Path, file: &str) -> Result<Self, NetError> {
        // A checkpoint is a file of the model folder, never a path out of it (a session names it).
        if Path::new(file).file_name().and_then(|n| n.to_str()) != Some(file) || !file.ends_with(".safetensors") {
            return Err(NetError::Invalid(format!(
                "checkpoint {file:?}: expected the name of a .safetensors file in {} (model.safetensors or last.safetensors)",
                dir.display()
            )));
        }
        let info = ModelInfo::read(dir)?;
        let device = Device::flex();
        let mut model = info.config.init(&device);
        load_weights(&mut model, &dir.join(file))?;
        let mut p = Self::from_model(info, model, device);
        if let Some(f) = &p.fast {
            f.check_weights().map_err(|e| NetError::Invalid(format!("{}: {e}", dir.join(file).display())))?;
        }
        p.confidence = umesh_core::register::confidence::ConfidenceReference::read(dir)
            .map_err(|e| NetError::Invalid(e.into()))?;
        Ok(p)
    }

    pub fn from_model(info: ModelInfo, model: UNet, device: Device) -> Self {
        let fast = crate::fast::FastUNet::from_model(&model).ok();
        Self {
            info,
            model,
            device,
            fast,
            use_burn: false,
            read_at: None,
            input: Vec::new(),
            output: Vec::new(),
            confidence: None,
        }
    }

    /// Compute the outputs only at these dense indices of each channel (of the model's padded
    /// shape; the rest are 0): a registration reads the field at the grid's nodes alone, and
    /// the decoder's last level, the widest work, then runs on about half its voxels. Indices
    /// outside the shape leave every output computed.
    pub fn read_only_at(&mut self, voxels: &[usize]) {
        if self.read_at.as_ref().is_some_and(|(v, _)| v == voxels) {
            return;
        }
        let needed = crate::fast::Needed::new(self.info.padded_shape, self.info.config.steps, voxels);
        self.read_at = Some((voxels.to_vec(), needed));
    }

    pub fn config(&self) -> &UNetConfig {
        &self.info.config
    }

    /// Input [C, X, Y, Z] (u_s or the encoded observation, mm) -> u_v [3, X, Y, Z] (mm). The
    /// returned slice is reused by the next call (no per-frame allocation on our side).
    pub fn predict(&mut self, u_s: &[f32], shape: [usize; 3]) -> Result<&[f32], NetError> {
        let c = self.info.config.in_channels;
        self.info.config.check_shape([1, c, shape[0], shape[1], shape[2]]).map_err(|e| NetError::Invalid(e.into()))?;
        let n = c * shape[0] * shape[1] * shape[2];
        if u_s.len() != n {
            return Err(NetError::Invalid(format!(
                "the input holds {} values, the grid {shape:?} x {c} needs {n}",
                u_s.len()
            )));
        }
        let s = self.info.normalization.input_scale_mm;
        self.input.clear();
        self.input.extend(u_s.iter().map(|v| v / s));
        let o = self.info.normalization.output_scale_mm;
        if let (Some(f), false) = (&self.fast, self.use_burn) {
            let needed = self.read_at.as_ref().and_then(|(_, m)| m.as_ref());
            f.forward_at(&self.input, shape, needed, &mut self.output);
            self.output.iter_mut().for_each(|v| *v *= o);
        } else {
            let x = Tensor::<5>::from_data(
                TensorData::new(std::mem::take(&mut self.input), [1, c, shape[0], shape[1], shape[2]]),
                &self.device,
            );
            let y = self.model.forward(x);
            let data = y.into_data().try_to_vec::<f32>().map_err(|e| NetError::Invalid(format!("{e:?}")))?;
            self.output.clear();
            self.output.extend(data.iter().map(|v| v * o));
        }
        // Corrupt weights give NaN or absurd displacements: the frame stops here with a
        // reason, never a "TRE 0.0" or an overflow further on.
        if let Some(v) = self.output.iter().find(|v| !(v.is_finite() && v.abs() <= MAX_DISPLACEMENT_MM)) {
            return Err(NetError::Invalid(format!(
                "the model predicts a displacement of {v} mm (not finite or over {MAX_DISPLACEMENT_MM} mm): its weights or normalisation are corrupt"
            )));
        }
        Ok(&self.output)
    }
}

impl umesh_core::register::pipeline::DisplacementModel for Predictor {
    fn name(&self) -> String {
        format!("U-Net ({} steps, {} channels)", self.info.config.steps, self.info.config.channels)
    }
    fn observation(&self) -> Option<umesh_core::observation::ObservationSettings> {
        self.info.settings.observation.clone()
    }
    fn predict(&mut self, u_s: &[f32], out: &mut Vec<f32>) -> Result<(), umesh_core::ModelError> {
        let shape = self.info.padded_shape;
        let y = Predictor::predict(self, u_s, shape)?;
        out.clear();
        out.extend_from_slice(y);
        Ok(())
    }
    fn confidence_reference(&self) -> Option<umesh_core::register::confidence::ConfidenceReference> {
        self.confidence.clone()
    }
    fn read_only_at(&mut self, voxels: &[usize]) {
        Predictor::read_only_at(self, voxels);
    }
}

/// What a model takes as its input, made from what a caller has: for models trained on camera
/// views, the observed organ points (world, mm) encoded by the observation operator; for
/// models trained on the exact surface displacement, u_s itself.
pub struct InputEncoder {
    observer: Option<umesh_core::observation::Observer>,
}

impl InputEncoder {
    /// For `info`'s input on `grid`, with `rest_surface` the organ's rest surface.
    pub fn new(
        info: &ModelInfo,
        grid: &umesh_core::grid::ImmersedGrid,
        rest_surface: &umesh_core::mesh::TriMesh,
    ) -> Result<Self, NetError> {
        let observer = match &info.settings.observation {
            Some(o) => Some(
                umesh_core::observation::Observer::new(grid, rest_surface, o.clone())
                    .map_err(|e| NetError::Invalid(e.into()))?,
            ),
            None => None,
        };
        Ok(Self { observer })
    }

    /// Whether the model takes observed points (else u_s).
    pub fn takes_points(&self) -> bool {
        self.observer.is_some()
    }

    /// The network input from the observed points `points_mm` or, for an exact-input model,
    /// `u_s` (whichever the model takes must be given).
    pub fn input(
        &mut self,
        points_mm: Option<&[nalgebra::Vector3<f64>]>,
        u_s: Option<&[f32]>,
    ) -> Result<Vec<f32>, NetError> {
        match (&mut self.observer, points_mm, u_s) {
            (Some(o), Some(p), _) => {
                let mut out = Vec::new();
                o.encode(p, &mut out);
                Ok(out)
            }
            (None, _, Some(u)) => Ok(u.to_vec()),
            (Some(_), None, _) => {
                Err(NetError::Invalid("this model takes observed surface points (a camera view)".into()))
            }
            (None, _, None) => Err(NetError::Invalid("this model takes the surface displacement u_s".into())),
        }
    }
}
