//! The trained U-Net's forward pass for inference, without burn: the same layers on
//! channel-last f32 buffers, direct 3x3x3 convolutions vectorised over the output channels
//! (AVX2 + FMA when the CPU has them), split over the first grid axis with rayon. Training
//! stays on burn; this is what runs per frame at surgery (a batch of one, small channel counts,
//! where a general convolution's im2col and layout changes cost more than the arithmetic).

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

impl FastUNet {
    /// The weights of `model`, repacked.
    pub fn from_model(model: &UNet) -> Result<Self, String> {
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
        let ok = net.down.iter().chain(&net.dec).chain(std::iter::once(&net.bottom)).all(|(a, b)| a.taps == 27 && b.taps == 27)
            && net.head.taps == 1
            && net.up.len() == net.down.len();
        if !ok {
            return Err("the network's layers are not the U-Net's 3x3x3 convolutions".into());
        }
        // Beyond 64 channels a layer is a large matrix product, where burn's convolution is
        // faster (the paper preset: 2421 ms here against burn's 1637 ms, `umesh bench net`).
        if net.bottom.1.cout > 64 {
            return Err(format!("{} channels at the bottom: burn runs this network faster", net.bottom.1.cout));
        }
        Ok(Self { in_channels, out_channels, ..net })
    }

    /// Input [C, X, Y, Z] (network units) -> output [C_out, X, Y, Z], channel-first as burn's.
    pub fn forward(&self, input: &[f32], dims: [usize; 3], out: &mut Vec<f32>) {
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
            let f = conv(&conv(&x, a, true), b, true);
            x = pool(&f);
            skips.push(f);
        }
        x = conv(&conv(&x, &self.bottom.0, true), &self.bottom.1, true);
        for (u, (a, b)) in self.up.iter().zip(&self.dec) {
            let up = transpose(&x, u);
            let skip = skips.pop().unwrap_or_else(|| Map { dims: up.dims, c: 0, v: Vec::new() });
            x = conv(&conv(&concat(&up, &skip), a, true), b, true);
        }
        let y = conv(&x, &self.head, false);
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

/// A padded convolution (3x3x3, or 1x1x1 for the head), with ReLU when `relu`.
fn conv(x: &Map, k: &Conv, relu: bool) -> Map {
    let [a, b, c] = x.dims;
    let cout = k.cout;
    let mut v = vec![0.0; a * b * c * cout];
    let slab = b * c * cout;
    v.par_chunks_mut(slab).enumerate().for_each(|(i, out)| {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU has AVX2 and FMA (checked above); the function is safe Rust
            // compiled for those features.
            #[allow(unsafe_code)]
            unsafe {
                slab_avx2(x, k, relu, i, out)
            };
            return;
        }
        slab_body::<false>(x, k, relu, i, out);
    });
    Map { dims: x.dims, c: cout, v }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn slab_avx2(x: &Map, k: &Conv, relu: bool, i: usize, out: &mut [f32]) {
    slab_body::<true>(x, k, relu, i, out);
}

/// One x-slab of the output. `FMA`: fused multiply-adds (only where the CPU has them; a
/// software fma would be far slower than a multiply and an add).
#[inline(always)]
fn slab_body<const FMA: bool>(x: &Map, k: &Conv, relu: bool, i: usize, out: &mut [f32]) {
    // Voxels per block measured best on 2 cores (AVX2): more for fewer channels, until the
    // accumulators no longer fit in the registers.
    match k.cout {
        3 => slab_fixed::<3, 4, FMA>(x, k, relu, i, out),
        8 => slab_fixed::<8, 4, FMA>(x, k, relu, i, out),
        16 => slab_fixed::<16, 2, FMA>(x, k, relu, i, out),
        32 => slab_fixed::<32, 1, FMA>(x, k, relu, i, out),
        64 => slab_fixed::<64, 1, FMA>(x, k, relu, i, out),
        _ => slab_any::<FMA>(x, k, relu, i, out),
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
fn slab_fixed<const C: usize, const B: usize, const FMA: bool>(x: &Map, k: &Conv, relu: bool, i: usize, out: &mut [f32]) {
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
fn slab_any<const FMA: bool>(x: &Map, k: &Conv, relu: bool, i: usize, out: &mut [f32]) {
    let [a, b, c] = x.dims;
    let (cin, cout) = (k.cin, k.cout);
    let kernel = if k.taps == 1 { 1 } else { 3 };
    let (x0, x1) = window(i, a, kernel);
    for j in 0..b {
        let (y0, y1) = window(j, b, kernel);
        for l in 0..c {
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
