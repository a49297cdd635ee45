#!/usr/bin/env python3
"""The peer of `umesh bench net`: the same U-Net (3 steps, padded 3x3x3 convolutions + ReLU,
2x2x2 max pooling, 2x2x2 stride-2 transposed convolutions, concatenation, 1x1x1 head) in
JAX/XLA on the CPU, batch of one, on the phantom's padded grid 32 x 24 x 24, random weights.

    pip install jax            # CPU build
    python3 scripts/jax_unet_bench.py [--channels 8 --in-channels 4] [--repeat 30]

Prints one JSON line: the median and p95 of the jitted forward pass in ms. Run it right after
`umesh bench net --json` on the same idle machine to compare (XLA uses every core by default;
`taskset -c 0,1` pins both to the same two).
"""
import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np


def conv(x, w, b, pad):
    # x [N, C, X, Y, Z], w [O, I, kx, ky, kz] (burn's and PyTorch's layout)
    y = jax.lax.conv_general_dilated(x, w, (1, 1, 1), [(pad, pad)] * 3, dimension_numbers=("NCDHW", "OIDHW", "NCDHW"))
    return y + b[None, :, None, None, None]


def up(x, w, b):
    # 2x2x2 stride-2 transposed convolution, w [I, O, 2, 2, 2]: each input voxel writes a 2^3 block.
    n, c, d, h, ww = x.shape
    o = w.shape[1]
    y = jnp.einsum("ncdhw,ioxyz->nodxhywz", x, w).reshape(n, o, 2 * d, 2 * h, 2 * ww)
    return y + b[None, :, None, None, None]


def pool(x):
    n, c, d, h, w = x.shape
    return x.reshape(n, c, d // 2, 2, h // 2, 2, w // 2, 2).max(axis=(3, 5, 7))


def init(key, steps, ch, cin, cout):
    p = {"down": [], "up": [], "dec": []}

    def conv_p(key, i, o, k=3):
        k1, k2 = jax.random.split(key)
        s = 1.0 / np.sqrt(i * k**3)
        return (jax.random.uniform(k1, (o, i, k, k, k), minval=-s, maxval=s), jax.random.uniform(k2, (o,), minval=-s, maxval=s))

    keys = iter(jax.random.split(key, 64))
    c = cin
    for s in range(steps):
        p["down"].append((conv_p(next(keys), c, ch << s), conv_p(next(keys), ch << s, ch << s)))
        c = ch << s
    p["bottom"] = (conv_p(next(keys), c, ch << steps), conv_p(next(keys), ch << steps, ch << steps))
    for s in reversed(range(steps)):
        hi, lo = ch << (s + 1), ch << s
        k1, k2 = jax.random.split(next(keys))
        sc = 1.0 / np.sqrt(hi * 8)
        p["up"].append((jax.random.uniform(k1, (hi, lo, 2, 2, 2), minval=-sc, maxval=sc), jax.random.uniform(k2, (lo,), minval=-sc, maxval=sc)))
        p["dec"].append((conv_p(next(keys), 2 * lo, lo), conv_p(next(keys), lo, lo)))
    p["head"] = conv_p(next(keys), ch, cout, k=1)
    return p


def forward(p, x):
    def double(x, d):
        (wa, ba), (wb, bb) = d
        return jax.nn.relu(conv(jax.nn.relu(conv(x, wa, ba, 1)), wb, bb, 1))

    skips = []
    for d in p["down"]:
        f = double(x, d)
        skips.append(f)
        x = pool(f)
    x = double(x, p["bottom"])
    for (wu, bu), d in zip(p["up"], p["dec"]):
        u = up(x, wu, bu)
        x = double(jnp.concatenate([u, skips.pop()], axis=1), d)
    w, b = p["head"]
    return conv(x, w, b, 0)


def main():
    a = argparse.ArgumentParser()
    a.add_argument("--channels", type=int, default=8)
    a.add_argument("--in-channels", type=int, default=4)
    a.add_argument("--steps", type=int, default=3)
    a.add_argument("--shape", type=int, nargs=3, default=[32, 24, 24])
    a.add_argument("--repeat", type=int, default=30)
    args = a.parse_args()
    p = init(jax.random.PRNGKey(0), args.steps, args.channels, args.in_channels, 3)
    f = jax.jit(forward)
    x = jax.random.uniform(jax.random.PRNGKey(1), (1, args.in_channels, *args.shape))
    f(p, x).block_until_ready()  # compile
    times = []
    for i in range(args.repeat):
        x = jax.random.uniform(jax.random.PRNGKey(2 + i), (1, args.in_channels, *args.shape))
        x.block_until_ready()
        t = time.perf_counter()
        f(p, x).block_until_ready()
        times.append((time.perf_counter() - t) * 1e3)
    times.sort()
    print(json.dumps({
        "peer": f"JAX {jax.__version__} (XLA CPU)", "channels": args.channels, "in_channels": args.in_channels,
        "shape": args.shape, "inference_ms_median": times[len(times) // 2],
        "inference_ms_p95": times[round((len(times) - 1) * 0.95)], "devices": str(jax.devices()),
    }))


if __name__ == "__main__":
    main()
