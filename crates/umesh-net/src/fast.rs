//! The trained U-Net's forward pass for inference, without burn: the same layers on
//! channel-last f32 buffers, split over the first grid axis with rayon. Narrow layers (the
//! shipped network) are direct 3x3x3 convolutions vectorised over the output channels
//! (compiled for AVX-512 and for AVX2 with FMA, chosen at run time by what the CPU has): a
//! batch of one with few channels, where a general convolution's im2col and layout changes
//! cost more than the arithmetic. Wide layers (the paper's 128
//! channels and up) are 27 shifted matrix products on a zero-padded copy of the input (faer's
//! matmul, no im2col): the padded layout makes every tap's input window a contiguous block of
//! columns. Training stays on burn.

use crate::model::UNet;
use burn::prelude::*;
use rayon::prelude::*;

/// A 3x3x3 padded convolution (or a 1x1x1 one), repacked as [offset][in][out].
struct Conv {
    cin: usize,
    cout: usize,
    taps: usize,
    w: Vec<f32>,
    b: Vec<f32>,
}

/// A 2x2x2 stride-2 transposed convolution, repacked as [sub-voxel][in][out].
struct Up {
    cin: usize,
    cout: usize,
    w: Vec<f32>,
    b: Vec<f32>,
}

/// A feature map: [X][Y][Z][C].
struct Map {
    dims: [usize; 3],
    c: usize,
    v: Vec<f32>,
}

pub struct FastUNet {
    down: Vec<(Conv, Conv)>,
    bottom: (Conv, Conv),
    up: Vec<Up>,
    dec: Vec<(Conv, Conv)>,
    head: Conv,
    in_channels: usize,
    out_channels: usize,
}

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().convert::<f32>().try_to_vec::<f32>().unwrap_or_default()
}

fn conv_of(c: &burn::nn::conv::Conv3d) -> Conv {
    let [cout, cin, kx, ky, kz] = c.weight.val().dims();
    let raw = values(c.weight.val());
    let taps = kx * ky * kz;
    // burn: [out][in][kx][ky][kz] -> [tap][in][out]
    let mut w = vec![0.0; raw.len()];
    for o in 0..cout {
        for i in 0..cin {
            for t in 0..taps {
                w[(t * cin + i) * cout + o] = raw[(o * cin + i) * taps + t];
            }
        }
    }
    let b = c.bias.as_ref().map(|b| values(b.val())).unwrap_or_else(|| vec![0.0; cout]);
    Conv { cin, cout, taps, w, b }
}

fn up_of(c: &burn::nn::conv::ConvTranspose3d) -> Up {
    let [cin, cout, ..] = c.weight.val().dims();
    let raw = values(c.weight.val());
    // burn: [in][out][2][2][2] -> [sub][in][out]
    let mut w = vec![0.0; raw.len()];
    for i in 0..cin {
        for o in 0..cout {
            for s in 0..8 {
                w[(s * cin + i) * cout + o] = raw[(i * cout + o) * 8 + s];
            }
        }
    }
    let b = c.bias.as_ref().map(|b| values(b.val())).unwrap_or_else(|| vec![0.0; cout]);
    Up { cin, cout, w, b }
}

/// A weight beyond this is no trained network's: the file is corrupt (flipped exponent bits).
pub const MAX_WEIGHT: f32 = 1e4;

impl FastUNet {
    /// Every weight and bias finite and at most `MAX_WEIGHT` in magnitude (NaN weights give
    /// finite, wrong predictions through the ReLU's `max`, so the output check cannot see them).
    pub fn check_weights(&self) -> Result<(), umesh_core::Invalid> {
        let convs = self.down.iter().chain(&self.dec).chain(std::iter::once(&self.bottom)).flat_map(|(a, b)| [a, b]);
        let all = convs
            .flat_map(|c| c.w.iter().chain(&c.b))
            .chain(self.head.w.iter().chain(&self.head.b))
            .chain(self.up.iter().flat_map(|u| u.w.iter().chain(&u.b)));
        for v in all {
            if !(v.is_finite() && v.abs() <= MAX_WEIGHT) {
                return Err(umesh_core::Invalid(format!(
                    "a weight is {v} (not finite or over {MAX_WEIGHT}): the weights are corrupt"
                )));
            }
        }
        Ok(())
    }

    /// The weights of `model`, repacked.
    pub fn from_model(model: &UNet) -> Result<Self, umesh_core::Invalid> {
        let dc = |d: &crate::model::DoubleConv| (conv_of(&d.a), conv_of(&d.b));
        let net = Self {
            down: model.down.iter().map(dc).collect(),
            bottom: dc(&model.bottom),
            up: model.up.iter().map(up_of).collect(),
            dec: model.dec.iter().map(dc).collect(),
            head: conv_of(&model.head),
            in_channels: 0,
            out_channels: 0,
        };
        let in_channels = net.down.first().map(|d| d.0.cin).unwrap_or(net.bottom.0.cin);
        let out_channels = net.head.cout;
        let ok = net
            .down
            .iter()
            .chain(&net.dec)
            .chain(std::iter::once(&net.bottom))
            .all(|(a, b)| a.taps == 27 && b.taps == 27)
            && net.head.taps == 1
            && net.up.len() == net.down.len();
        if !ok {
            return Err(umesh_core::Invalid::from("the network's layers are not the U-Net's 3x3x3 convolutions"));
        }
        Ok(Self { in_channels, out_channels, ..net })
    }

    /// Input [C, X, Y, Z] (network units) -> output [C_out, X, Y, Z], channel-first as burn's.
    pub fn forward(&self, input: &[f32], dims: [usize; 3], out: &mut Vec<f32>) {
        self.forward_at(input, dims, None, out);
    }

    /// As `forward`, computing the outputs only where `needed` asks (`Needed::new`, for these
    /// dims): the decoder's convolutions skip the voxels whose values reach none of them, and
    /// every other output is 0. The outputs asked for are the same bits as `forward`'s.
    pub fn forward_at(&self, input: &[f32], dims: [usize; 3], needed: Option<&Needed>, out: &mut Vec<f32>) {
        let needed = needed.filter(|m| m.dims == dims && m.levels.len() == self.dec.len());
        let n = dims[0] * dims[1] * dims[2];
        let c = self.in_channels;
        let mut x = Map { dims, c, v: vec![0.0; n * c] };
        for ch in 0..c {
            for (p, &v) in input[ch * n..(ch + 1) * n].iter().enumerate() {
                x.v[p * c + ch] = v;
            }
        }
        let mut skips = Vec::with_capacity(self.down.len());
        for (a, b) in &self.down {
            let f = conv(&conv(&x, a, true, None), b, true, None);
            x = pool(&f);
            skips.push(f);
        }
        x = conv(&conv(&x, &self.bottom.0, true, None), &self.bottom.1, true, None);
        // The decoder runs from the deepest level; `Needed` holds the finest first.
        let levels = self.dec.len();
        for (d, (u, (a, b))) in self.up.iter().zip(&self.dec).enumerate() {
            let up = transpose(&x, u);
            let skip = skips.pop().unwrap_or_else(|| Map { dims: up.dims, c: 0, v: Vec::new() });
            let masks = needed.map(|m| &m.levels[levels - 1 - d]);
            let h = conv(&concat(&up, &skip), a, true, masks.map(|m| m.0.as_slice()));
            x = conv(&h, b, true, masks.map(|m| m.1.as_slice()));
        }
        let y = conv(&x, &self.head, false, needed.and_then(|m| m.levels.first()).map(|m| m.1.as_slice()));
        let co = self.out_channels;
        out.clear();
        out.resize(n * co, 0.0);
        for p in 0..n {
            for ch in 0..co {
                out[ch * n + p] = y.v[p * co + ch];
            }
        }
    }
}

/// The voxels of each decoder level whose values reach the outputs a caller reads (the organ's
/// grid nodes, about a third of the padded box): a level's last convolution is needed at
/// those, the one before at them dilated by a voxel, and the upsampling into them reads the
/// next coarser level's voxels under its dilation by two. The encoder feeds the pooling of
/// every voxel and stays whole.
#[derive(Clone, Debug, PartialEq)]
pub struct Needed {
    dims: [usize; 3],
    /// Per decoder level, finest first: (the first convolution's voxels, the second's).
    levels: Vec<(Vec<bool>, Vec<bool>)>,
}

impl Needed {
    /// For outputs read at `voxels` (dense indices into `dims`, X-major as the field's channels)
    /// of a network with `steps` pooling steps; None when an index is outside `dims` or `dims`
    /// does not halve `steps` times.
    pub fn new(dims: [usize; 3], steps: usize, voxels: &[usize]) -> Option<Self> {
        let n = dims.iter().product::<usize>();
        if dims.iter().any(|&d| d == 0 || d % (1 << steps) != 0) || voxels.iter().any(|&v| v >= n) {
            return None;
        }
        let mut need = vec![false; n];
        voxels.iter().for_each(|&v| need[v] = true);
        let mut level_dims = dims;
        let mut levels = Vec::with_capacity(steps);
        for _ in 0..steps {
            let first = dilate(&need, level_dims);
            let inputs = dilate(&first, level_dims);
            levels.push((first, std::mem::take(&mut need)));
            let coarse = level_dims.map(|d| d / 2);
            need = vec![false; coarse.iter().product()];
            let [_, b, c] = level_dims;
            for (p, _) in inputs.iter().enumerate().filter(|(_, x)| **x) {
                let (i, j, k) = (p / (b * c), (p / c) % b, p % c);
                need[((i / 2) * coarse[1] + j / 2) * coarse[2] + k / 2] = true;
            }
            level_dims = coarse;
        }
        Some(Self { dims, levels })
    }
}

/// The voxels within one (3x3x3) of `mask`'s.
fn dilate(mask: &[bool], [a, b, c]: [usize; 3]) -> Vec<bool> {
    let mut out = vec![false; mask.len()];
    for (p, _) in mask.iter().enumerate().filter(|(_, x)| **x) {
        let (i, j, k) = (p / (b * c), (p / c) % b, p % c);
        for x in i.saturating_sub(1)..(i + 2).min(a) {
            for y in j.saturating_sub(1)..(j + 2).min(b) {
                for z in k.saturating_sub(1)..(k + 2).min(c) {
                    out[(x * b + y) * c + z] = true;
                }
            }
        }
    }
    out
}

fn pool(x: &Map) -> Map {
    let [a, b, c] = x.dims;
    let d = [a / 2, b / 2, c / 2];
    let ch = x.c;
    let mut v = vec![f32::NEG_INFINITY; d[0] * d[1] * d[2] * ch];
    for i in 0..d[0] * 2 {
        for j in 0..d[1] * 2 {
            for k in 0..d[2] * 2 {
                let src = &x.v[((i * b + j) * c + k) * ch..][..ch];
                let dst = &mut v[(((i / 2) * d[1] + j / 2) * d[2] + k / 2) * ch..][..ch];
                for (o, s) in dst.iter_mut().zip(src) {
                    *o = o.max(*s);
                }
            }
        }
    }
    Map { dims: d, c: ch, v }
}

fn concat(a: &Map, b: &Map) -> Map {
    let n = a.dims[0] * a.dims[1] * a.dims[2];
    let c = a.c + b.c;
    let mut v = Vec::with_capacity(n * c);
    for p in 0..n {
        v.extend_from_slice(&a.v[p * a.c..(p + 1) * a.c]);
        v.extend_from_slice(&b.v[p * b.c..(p + 1) * b.c]);
    }
    Map { dims: a.dims, c, v }
}

fn transpose(x: &Map, u: &Up) -> Map {
    if wide(u.cin, u.cout) {
        return transpose_gemm(x, u);
    }
    let [a, b, c] = x.dims;
    let d = [2 * a, 2 * b, 2 * c];
    let (cin, cout) = (u.cin, u.cout);
    let mut v = vec![0.0; d[0] * d[1] * d[2] * cout];
    let slab = d[1] * d[2] * cout;
    v.par_chunks_mut(slab).enumerate().for_each(|(xo, out)| {
        let (i, si) = (xo / 2, xo % 2);
        for yo in 0..d[1] {
            let (j, sj) = (yo / 2, yo % 2);
            for zo in 0..d[2] {
                let (k, sk) = (zo / 2, zo % 2);
                let s = (si * 2 + sj) * 2 + sk;
                let inp = &x.v[((i * b + j) * c + k) * cin..][..cin];
                let acc = &mut out[(yo * d[2] + zo) * cout..][..cout];
                acc.copy_from_slice(&u.b);
                let w = &u.w[s * cin * cout..][..cin * cout];
                for (ci, &val) in inp.iter().enumerate() {
                    for (o, wv) in acc.iter_mut().zip(&w[ci * cout..(ci + 1) * cout]) {
                        *o += val * wv;
                    }
                }
            }
        }
    });
    Map { dims: d, c: cout, v }
}

/// Whether a layer runs as matrix products. The direct kernels are tuned for the shipped
/// network's channel counts and win below 64 x 64 (measured with `umesh bench net` on 2 cores:
/// the shipped network 7.6-7.8 ms with its 64 x 64 bottom layer as products, 7.6-9.4 ms with
/// it direct, 8.0-10.1 ms with the 32 x 64 layers as products too).
fn wide(cin: usize, cout: usize) -> bool {
    !matches!(cout, 3 | 8 | 16 | 32 | 64) || cin * cout >= 64 * 64
}

/// A padded convolution (3x3x3, or 1x1x1 for the head), with ReLU when `relu`; where `mask`
/// is given (by voxel) the direct kernels compute only its voxels and leave the rest 0 (the
/// matrix products compute all).
fn conv(x: &Map, k: &Conv, relu: bool, mask: Option<&[bool]>) -> Map {
    if wide(k.cin, k.cout) {
        return conv_gemm(x, k, relu);
    }
    let [a, b, c] = x.dims;
    let cout = k.cout;
    let mut v = vec![0.0; a * b * c * cout];
    let slab = b * c * cout;
    let isa = Isa::detect();
    v.par_chunks_mut(slab).enumerate().for_each(|(i, out)| match isa {
        // SAFETY (both): `Isa::detect` found the features these functions are compiled for;
        // they are safe Rust otherwise.
        #[cfg(target_arch = "x86_64")]
        #[allow(unsafe_code)]
        Isa::Avx512 => unsafe { slab_avx512(x, k, relu, mask, i, out) },
        #[cfg(target_arch = "x86_64")]
        #[allow(unsafe_code)]
        Isa::Avx2 => unsafe { slab_avx2(x, k, relu, mask, i, out) },
        Isa::Plain => slab_body::<false>(x, k, relu, mask, i, out),
    });
    Map { dims: x.dims, c: cout, v }
}

/// The instruction set the direct kernels run with, the widest the CPU has.
#[derive(Clone, Copy)]
enum Isa {
    #[cfg(target_arch = "x86_64")]
    Avx512,
    #[cfg(target_arch = "x86_64")]
    Avx2,
    Plain,
}

impl Isa {
    fn detect() -> Self {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("fma") {
            if std::arch::is_x86_feature_detected!("avx512f") {
                return Isa::Avx512;
            }
            if std::arch::is_x86_feature_detected!("avx2") {
                return Isa::Avx2;
            }
        }
        Isa::Plain
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn slab_avx2(x: &Map, k: &Conv, relu: bool, mask: Option<&[bool]>, i: usize, out: &mut [f32]) {
    slab_body::<true>(x, k, relu, mask, i, out);
}

/// The same kernels compiled for AVX-512 (16-lane registers for the 16- to 64-channel layers):
/// the shipped network 9.8-11.9 ms against 10.9-13.5 ms with AVX2 in alternating runs of
/// `umesh bench net` on an AMD EPYC with AVX-512.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
fn slab_avx512(x: &Map, k: &Conv, relu: bool, mask: Option<&[bool]>, i: usize, out: &mut [f32]) {
    slab_body::<true>(x, k, relu, mask, i, out);
}

/// One x-slab of the output. `FMA`: fused multiply-adds (only where the CPU has them; a
/// software fma would be far slower than a multiply and an add).
#[inline(always)]
fn slab_body<const FMA: bool>(x: &Map, k: &Conv, relu: bool, mask: Option<&[bool]>, i: usize, out: &mut [f32]) {
    // Voxels per block measured best on 2 cores (AVX2): more for fewer channels, until the
    // accumulators no longer fit in the registers.
    match k.cout {
        3 => slab_fixed::<3, 4, FMA>(x, k, relu, mask, i, out),
        8 => slab_fixed::<8, 4, FMA>(x, k, relu, mask, i, out),
        16 => slab_fixed::<16, 2, FMA>(x, k, relu, mask, i, out),
        32 => slab_fixed::<32, 1, FMA>(x, k, relu, mask, i, out),
        64 => slab_fixed::<64, 1, FMA>(x, k, relu, mask, i, out),
        _ => slab_any::<FMA>(x, k, relu, mask, i, out),
    }
}

#[inline(always)]
fn madd<const FMA: bool>(acc: f32, a: f32, b: f32) -> f32 {
    if FMA { a.mul_add(b, acc) } else { acc + a * b }
}

/// The in-grid range of a 3-tap window centred on `i` along an axis of length `n`: the taps
/// lo..hi (input index i + tap - 1).
#[inline(always)]
fn window(i: usize, n: usize, kernel: usize) -> (usize, usize) {
    if kernel == 1 {
        return (1, 2);
    }
    (if i == 0 { 1 } else { 0 }, if i + 1 >= n { 2 } else { 3 })
}

/// `C` output channels (held in registers), `B` consecutive voxels along z computed together
/// so that each weight row loaded serves B of them.
#[inline(always)]
fn slab_fixed<const C: usize, const B: usize, const FMA: bool>(
    x: &Map,
    k: &Conv,
    relu: bool,
    mask: Option<&[bool]>,
    i: usize,
    out: &mut [f32],
) {
    let [a, b, c] = x.dims;
    let cin = k.cin;
    let kernel = if k.taps == 1 { 1 } else { 3 };
    let bias: [f32; C] = k.b[..C].try_into().unwrap_or([0.0; C]);
    let (x0, x1) = window(i, a, kernel);
    for j in 0..b {
        let (y0, y1) = window(j, b, kernel);
        let mut l = 0;
        while l < c {
            let (z0, z1) = window(l, c, kernel);
            // B voxels at once where all of them see the same window along z.
            let block = l + B <= c && window(l + B - 1, c, kernel) == (z0, z1);
            let m_count = if block { B } else { 1 };
            if let Some(mask) = mask
                && !mask[(i * b + j) * c + l..][..m_count].iter().any(|m| *m)
            {
                l += m_count;
                continue;
            }
            let mut acc = [bias; B];
            for dx in x0..x1 {
                for dy in y0..y1 {
                    for dz in z0..z1 {
                        let p = ((i + dx - 1) * b + (j + dy - 1)) * c + (l + dz - 1);
                        let t = if kernel == 1 { 0 } else { (dx * 3 + dy) * 3 + dz };
                        let w = &k.w[t * cin * C..(t + 1) * cin * C];
                        if block {
                            let inp = &x.v[p * cin..(p + B) * cin];
                            for (ci, wr) in w.chunks_exact(C).enumerate() {
                                for m in 0..B {
                                    let val = inp[m * cin + ci];
                                    for o in 0..C {
                                        acc[m][o] = madd::<FMA>(acc[m][o], val, wr[o]);
                                    }
                                }
                            }
                        } else {
                            let inp = &x.v[p * cin..(p + 1) * cin];
                            for (val, wr) in inp.iter().zip(w.chunks_exact(C)) {
                                for o in 0..C {
                                    acc[0][o] = madd::<FMA>(acc[0][o], *val, wr[o]);
                                }
                            }
                        }
                    }
                }
            }
            for (m, am) in acc.iter().enumerate().take(m_count) {
                // A block's voxels outside the mask stay 0, as the skipped blocks' do.
                if mask.is_some_and(|mask| !mask[(i * b + j) * c + l + m]) {
                    continue;
                }
                let dst = &mut out[(j * c + l + m) * C..(j * c + l + m + 1) * C];
                for o in 0..C {
                    dst[o] = if relu { am[o].max(0.0) } else { am[o] };
                }
            }
            l += m_count;
        }
    }
}

#[inline(always)]
fn slab_any<const FMA: bool>(x: &Map, k: &Conv, relu: bool, mask: Option<&[bool]>, i: usize, out: &mut [f32]) {
    let [a, b, c] = x.dims;
    let (cin, cout) = (k.cin, k.cout);
    let kernel = if k.taps == 1 { 1 } else { 3 };
    let (x0, x1) = window(i, a, kernel);
    for j in 0..b {
        let (y0, y1) = window(j, b, kernel);
        for l in 0..c {
            if mask.is_some_and(|m| !m[(i * b + j) * c + l]) {
                continue;
            }
            let (z0, z1) = window(l, c, kernel);
            let acc = &mut out[(j * c + l) * cout..(j * c + l + 1) * cout];
            acc.copy_from_slice(&k.b);
            for dx in x0..x1 {
                for dy in y0..y1 {
                    for dz in z0..z1 {
                        let p = ((i + dx - 1) * b + (j + dy - 1)) * c + (l + dz - 1);
                        let t = if kernel == 1 { 0 } else { (dx * 3 + dy) * 3 + dz };
                        let inp = &x.v[p * cin..(p + 1) * cin];
                        let w = &k.w[t * cin * cout..(t + 1) * cin * cout];
                        for (val, wr) in inp.iter().zip(w.chunks_exact(cout)) {
                            for (o, wv) in acc.iter_mut().zip(wr) {
                                *o = madd::<FMA>(*o, *val, *wv);
                            }
                        }
                    }
                }
            }
            if relu {
                acc.iter_mut().for_each(|v| *v = v.max(0.0));
            }
        }
    }
}

/// A padded convolution as one matrix product per tap. The input is copied into a zero-padded
/// lattice (X+2, Y+2, Z+2) stored as a column-major [C_in x voxels] matrix with one spare
/// column at each end; an output voxel at padded index p reads tap (dx, dy, dz) at
/// p + (dx-1) sx + (dy-1) sy + (dz-1), so for a run of consecutive output columns every tap's
/// input is a contiguous block, and out[:, run] += W_tap [C_out x C_in] * in[:, run + offset].
/// Runs cover whole x-slabs (with the z halo, a few percent of wasted columns); a run's
/// accumulator stays in cache over its 27 products.
fn conv_gemm(x: &Map, k: &Conv, relu: bool) -> Map {
    use faer::linalg::matmul::matmul;
    use faer::{Accum, MatMut, MatRef, Par};
    let [a, b, c] = x.dims;
    let (cin, cout) = (k.cin, k.cout);
    let (sy, sx) = (c + 2, (b + 2) * (c + 2));
    // xp column q = 1 + padded index; x-slab pi of the padded lattice starts at column 1 + pi sx.
    let mut xp = vec![0f32; ((a + 2) * sx + 2) * cin];
    xp[cin..(1 + (a + 1) * sx) * cin].par_chunks_mut(sx * cin).enumerate().skip(1).for_each(|(pi, slab)| {
        let i = pi - 1;
        for j in 0..b {
            let src = &x.v[((i * b + j) * c) * cin..][..c * cin];
            slab[((j + 1) * sy + 1) * cin..][..c * cin].copy_from_slice(src);
        }
    });
    let taps: Vec<(usize, isize)> = if k.taps == 1 {
        vec![(0, 0)]
    } else {
        (0..27)
            .map(|t| {
                let (dx, dy, dz) = (t / 9, (t / 3) % 3, t % 3);
                (t, (dx as isize - 1) * sx as isize + (dy as isize - 1) * sy as isize + dz as isize - 1)
            })
            .collect()
    };
    // Small weights: one run per x-slab (many runs to share out, each in cache). Large ones
    // (the deep levels): one run per thread, so the weights are streamed once per thread.
    let weight_bytes = k.w.len() * 4;
    let groups = if weight_bytes <= 8 << 20 { a } else { a.min(rayon::current_num_threads().max(1)) };
    let per = a.div_ceil(groups);
    let mut v = vec![0.0; a * b * c * cout];
    v.par_chunks_mut(per * b * c * cout).enumerate().for_each(|(g, out)| {
        let (i0, i1) = (g * per, (g * per + per).min(a));
        let p0 = (i0 + 1) * sx + sy;
        let n = (i1 - i0 - 1) * sx + b * sy;
        let mut acc = vec![0f32; cout * n];
        for col in acc.chunks_exact_mut(cout) {
            col.copy_from_slice(&k.b);
        }
        {
            let mut dst = MatMut::from_column_major_slice_mut(&mut acc, cout, n);
            for &(t, off) in &taps {
                let w = MatRef::from_column_major_slice(&k.w[t * cin * cout..(t + 1) * cin * cout], cout, cin);
                let q = (1 + p0 as isize + off) as usize;
                let inp = MatRef::from_column_major_slice(&xp[q * cin..(q + n) * cin], cin, n);
                matmul(dst.as_mut(), Accum::Add, w, inp, 1.0f32, Par::Seq);
            }
        }
        for i in i0..i1 {
            for j in 0..b {
                for l in 0..c {
                    let col = (i - i0) * sx + j * sy + l + 1;
                    let src = &acc[col * cout..(col + 1) * cout];
                    let dst = &mut out[(((i - i0) * b + j) * c + l) * cout..][..cout];
                    if relu {
                        for (d, s) in dst.iter_mut().zip(src) {
                            *d = s.max(0.0);
                        }
                    } else {
                        dst.copy_from_slice(src);
                    }
                }
            }
        }
    });
    Map { dims: x.dims, c: cout, v }
}

/// The 2x2x2 stride-2 transposed convolution as eight matrix products, one per sub-voxel:
/// y_s = W_s [C_out x C_in] * x [C_in x voxels], then each input voxel's eight columns are
/// scattered to its 2^3 block.
fn transpose_gemm(x: &Map, u: &Up) -> Map {
    use faer::linalg::matmul::matmul;
    use faer::{Accum, MatMut, MatRef, Par};
    let [a, b, c] = x.dims;
    let (cin, cout) = (u.cin, u.cout);
    let n = a * b * c;
    let mut ys = vec![0f32; 8 * cout * n];
    let xin = MatRef::from_column_major_slice(&x.v, cin, n);
    ys.par_chunks_mut(cout * n).enumerate().for_each(|(s, y)| {
        let w = MatRef::from_column_major_slice(&u.w[s * cin * cout..(s + 1) * cin * cout], cout, cin);
        matmul(MatMut::from_column_major_slice_mut(y, cout, n), Accum::Replace, w, xin, 1.0f32, Par::Seq);
    });
    let d = [2 * a, 2 * b, 2 * c];
    let mut v = vec![0.0; d[0] * d[1] * d[2] * cout];
    v.par_chunks_mut(d[1] * d[2] * cout).enumerate().for_each(|(xo, out)| {
        let (i, si) = (xo / 2, xo % 2);
        for yo in 0..d[1] {
            let (j, sj) = (yo / 2, yo % 2);
            for zo in 0..d[2] {
                let (l, sl) = (zo / 2, zo % 2);
                let s = (si * 2 + sj) * 2 + sl;
                let src = &ys[(s * n + (i * b + j) * c + l) * cout..][..cout];
                let dst = &mut out[(yo * d[2] + zo) * cout..][..cout];
                for ((o, v), bias) in dst.iter_mut().zip(src).zip(&u.b) {
                    *o = v + bias;
                }
            }
        }
    });
    Map { dims: d, c: cout, v }
}
