//! The U-Net of the paper: k encoder steps (two padded 3x3x3 convolutions with ReLU, then a
//! 2x2x2 max pooling, channels doubling), two 3x3x3 convolutions at the bottom, k decoder steps
//! (2x2x2 transposed convolution, concatenation with the encoder features of the same level,
//! two 3x3x3 convolutions), and a final 1x1x1 convolution to 3 channels.

use crate::NetError;
use burn::nn::PaddingConfig3d;
use burn::nn::conv::{Conv3d, Conv3dConfig, ConvTranspose3d, ConvTranspose3dConfig};
use burn::prelude::*;
use burn::store::{ModuleSnapshot, SafetensorsStore};
use burn::tensor::activation::relu;
use std::path::Path;

/// Architecture, saved beside the weights as JSON.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct UNetConfig {
    /// Encoder (and decoder) steps k; the input's spatial sizes must be multiples of 2^k.
    pub steps: usize,
    /// Channels of the first layer; doubled at each step.
    pub channels: usize,
    /// Input channels: 3 displacement components (+1 with the visibility mask).
    pub in_channels: usize,
    pub out_channels: usize,
}

/// Bounds of `UNetConfig::channels` and `steps` (see `check_shape`).
pub const MAX_CHANNELS: usize = 256;
pub const MAX_STEPS: usize = 6;

impl UNetConfig {
    /// The paper's setting: 3 steps, 128 channels in the first layer.
    pub fn paper() -> Self {
        Self { steps: 3, channels: 128, in_channels: 3, out_channels: 3 }
    }
    /// Small enough for real-time inference on 2 CPU cores.
    pub fn cpu() -> Self {
        Self { steps: 3, channels: 8, in_channels: 3, out_channels: 3 }
    }

    pub fn init(&self, device: &Device) -> UNet {
        let conv = |i: usize, o: usize| {
            Conv3dConfig::new([i, o], [3, 3, 3]).with_padding(PaddingConfig3d::Explicit(1, 1, 1)).init(device)
        };
        let double = |i: usize, o: usize| DoubleConv { a: conv(i, o), b: conv(o, o) };
        let c = self.channels;
        let mut down = Vec::new();
        let mut ch = self.in_channels;
        for s in 0..self.steps {
            down.push(double(ch, c << s));
            ch = c << s;
        }
        let bottom = double(ch, c << self.steps);
        let mut up = Vec::new();
        let mut dec = Vec::new();
        for s in (0..self.steps).rev() {
            let (hi, lo) = (c << (s + 1), c << s);
            up.push(ConvTranspose3dConfig::new([hi, lo], [2, 2, 2]).with_stride([2, 2, 2]).init(device));
            dec.push(double(2 * lo, lo));
        }
        let head = Conv3dConfig::new([c, self.out_channels], [1, 1, 1]).init(device);
        UNet { down, bottom, up, dec, head, steps: self.steps }
    }

    /// Check an input shape [B, C, X, Y, Z]; the error says what is wrong.
    /// The network's width and depth within what can be allocated: the widest layer has
    /// channels x 2^steps channels (the paper's 128 x 2^3 is about what 24 GiB trains).
    pub fn check_size(&self) -> Result<(), umesh_core::Invalid> {
        if !(1..=MAX_CHANNELS).contains(&self.channels) {
            return Err(umesh_core::Invalid(format!(
                "--channels {}: between 1 and {MAX_CHANNELS} (the paper uses 128)",
                self.channels
            )));
        }
        if !(1..=MAX_STEPS).contains(&self.steps) {
            return Err(umesh_core::Invalid(format!(
                "--steps {}: between 1 and {MAX_STEPS} (the paper uses 3)",
                self.steps
            )));
        }
        Ok(())
    }

    pub fn check_shape(&self, shape: [usize; 5]) -> Result<(), umesh_core::Invalid> {
        self.check_size()?;
        let m = 1usize << self.steps;
        if shape[1] != self.in_channels {
            return Err(umesh_core::Invalid(format!(
                "the input has {} channels, the network expects {}",
                shape[1], self.in_channels
            )));
        }
        if let Some(a) = (2..5).find(|&a| shape[a] == 0 || !shape[a].is_multiple_of(m)) {
            return Err(umesh_core::Invalid(format!(
                "the grid {:?} is not divisible by 2^{} = {m} along axis {} (pad the grid to a multiple of {m})",
                &shape[2..],
                self.steps,
                a - 2
            )));
        }
        Ok(())
    }
}

#[derive(Module, Debug)]
pub struct DoubleConv {
    pub(crate) a: Conv3d,
    pub(crate) b: Conv3d,
}

impl DoubleConv {
    fn forward(&self, x: Tensor<5>) -> Tensor<5> {
        relu(self.b.forward(relu(self.a.forward(x))))
    }
}

#[derive(Module, Debug)]
pub struct UNet {
    pub(crate) down: Vec<DoubleConv>,
    pub(crate) bottom: DoubleConv,
    pub(crate) up: Vec<ConvTranspose3d>,
    pub(crate) dec: Vec<DoubleConv>,
    pub(crate) head: Conv3d,
    steps: usize,
}

/// 2x2x2 max pooling as a reshape plus a max over the pooled axes (burn 0.22 has no 3-D pool).
pub fn max_pool_2x2x2(x: Tensor<5>) -> Tensor<5> {
    let [b, c, d, h, w] = x.dims();
    x.reshape([b * c, d / 2, 2, h / 2, 2, w / 2, 2]).max_dims(&[2, 4, 6]).reshape([b, c, d / 2, h / 2, w / 2])
}

impl UNet {
    /// [B, C_in, X, Y, Z] -> [B, C_out, X, Y, Z]; X, Y, Z multiples of 2^steps.
    pub fn forward(&self, x: Tensor<5>) -> Tensor<5> {
        let mut skips = Vec::with_capacity(self.steps);
        let mut x = x;
        for d in &self.down {
            let f = d.forward(x);
            x = max_pool_2x2x2(f.clone());
            skips.push(f);
        }
        x = self.bottom.forward(x);
        for (u, d) in self.up.iter().zip(&self.dec) {
            let up = u.forward(x);
            let skip = skips.pop().unwrap_or_else(|| up.clone());
            x = d.forward(Tensor::cat(vec![up, skip], 1));
        }
        self.head.forward(x)
    }
}

pub fn save_weights(model: &UNet, path: &Path) -> Result<(), NetError> {
    let mut store = SafetensorsStore::from_file(path).overwrite(true);
    model.save_into(&mut store).map_err(|source| NetError::Weights { path: path.into(), source })
}

pub fn load_weights(model: &mut UNet, path: &Path) -> Result<(), NetError> {
    let mut store = SafetensorsStore::from_file(path);
    model.load_from(&mut store).map(|_| ()).map_err(|source| NetError::Weights { path: path.into(), source })
}
