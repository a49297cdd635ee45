"""Write a genuine RealSense recording (.db3, or .bag where librealsense still writes it) from a
umesh recording folder, with librealsense's software_device and recorder: no camera needed.
Used by the tests (tests/it/camera.rs); also a way to hand a synthetic recording to other
RealSense tools.

  python make_recording.py SRC_DIR OUT.db3 [--frames N] [--fps F] [--color-only] [--no-color]
                           [--resize-depth-at N]

--fps: the frame rate (default: the folder's recording.json); the frames' timestamps follow it.

--color-only: no depth stream; --no-color: no colour stream; --resize-depth-at N: from frame N
on, depth comes in a second, half-size depth stream (a recording that changes size mid-file).
Frame numbers start at 1 (librealsense drops a frame numbered 0).
"""
import json
import os
import sys
import threading
import time

import numpy as np
import pyrealsense2 as rs
from PIL import Image


def main():
    a = sys.argv[1:]
    if len(a) < 2:
        sys.exit(__doc__)
    src, out = a[0], a[1]
    opt = lambda k: a[a.index(k) + 1] if k in a else None  # noqa: E731
    color_only, no_color = "--color-only" in a, "--no-color" in a
    resize_at = int(opt("--resize-depth-at")) if opt("--resize-depth-at") else None
    j = json.load(open(os.path.join(src, "intrinsics.json")))
    w, h, m = j["width"], j["height"], j["intrinsic_matrix"]
    meta_path = os.path.join(src, "recording.json")
    meta = json.load(open(meta_path)) if os.path.exists(meta_path) else {"depth_scale": 1000.0, "fps": 20.0}
    fps = float(opt("--fps")) if opt("--fps") else meta["fps"]
    stems = sorted(f[:-4] for f in os.listdir(os.path.join(src, "depth")) if f.endswith(".png"))
    if opt("--frames"):
        stems = stems[: int(opt("--frames"))]

    def intr(width, height, scale):
        k = rs.intrinsics()
        k.width, k.height = width, height
        k.fx, k.fy, k.ppx, k.ppy = m[0] * scale, m[4] * scale, (m[6] + 0.5) * scale - 0.5, (m[7] + 0.5) * scale - 0.5
        k.model, k.coeffs = rs.distortion.none, [0.0] * 5
        return k

    def video(kind, uid, width, height, fmt, bpp, k):
        s = rs.video_stream()
        s.type, s.index, s.uid, s.width, s.height, s.fps, s.bpp, s.fmt, s.intrinsics = kind, 0, uid, width, height, max(1, int(round(fps))), bpp, fmt, k
        return s

    dev = rs.software_device()
    dev.register_info(rs.camera_info.name, "umesh synthetic camera")
    dev.register_info(rs.camera_info.serial_number, "000000000001")
    ds = None if color_only else dev.add_sensor("Stereo Module")
    cs = None if no_color else dev.add_sensor("RGB Camera")
    dp = dp2 = cp = None
    if ds:
        dp = ds.add_video_stream(video(rs.stream.depth, 0, w, h, rs.format.z16, 2, intr(w, h, 1.0)))
        if resize_at is not None:
            dp2 = ds.add_video_stream(video(rs.stream.depth, 2, w // 2, h // 2, rs.format.z16, 2, intr(w // 2, h // 2, 0.5)))
        ds.add_read_only_option(rs.option.depth_units, 1.0 / meta["depth_scale"])
    if cs:
        cp = cs.add_video_stream(video(rs.stream.color, 1, w, h, rs.format.rgb8, 3, intr(w, h, 1.0)))
    if dp and cp:
        e = rs.extrinsics()
        e.rotation, e.translation = [1, 0, 0, 0, 1, 0, 0, 0, 1], [0, 0, 0]
        dp.register_extrinsics_to(cp, e)
    dev.create_matcher(rs.matchers.default)
    rec = rs.recorder(out, dev)
    # Each frame waited for at the sensor's callback, so the recorder has it in order.
    seen = {"n": 0}
    cv = threading.Condition()

    def cb(_f):
        with cv:
            seen["n"] += 1
            cv.notify_all()

    def wait_for(n):
        with cv:
            if not cv.wait_for(lambda: seen["n"] >= n, timeout=10):
                sys.exit(f"frame {n} was not taken by the recorder in 10 s")
    if ds:
        ds.open([p for p in (dp, dp2) if p])
        ds.start(cb)
    if cs:
        cs.open(cp)
        cs.start(cb)
    sent = 0
    for i, stem in enumerate(stems):
        n, ts = i + 1, (i + 1) * 1000.0 / fps
        if ds:
            d = np.array(Image.open(os.path.join(src, "depth", stem + ".png")), dtype=np.uint16)
            prof = dp
            if resize_at is not None and i >= resize_at:
                d, prof = np.ascontiguousarray(d[::2, ::2]), dp2
            f = rs.software_video_frame()
            f.pixels, f.bpp, f.stride, f.timestamp, f.frame_number = d, 2, 2 * d.shape[1], ts, n
            f.domain, f.profile = rs.timestamp_domain.hardware_clock, prof.as_video_stream_profile()
            ds.on_video_frame(f)
            sent += 1
        if cs:
            cpath = os.path.join(src, "color", stem + ".png")
            c = np.array(Image.open(cpath).convert("RGB"), dtype=np.uint8) if os.path.exists(cpath) else np.zeros((h, w, 3), np.uint8)
            f = rs.software_video_frame()
            f.pixels, f.bpp, f.stride, f.timestamp, f.frame_number = np.ascontiguousarray(c), 3, 3 * w, ts, n
            f.domain, f.profile = rs.timestamp_domain.hardware_clock, cp.as_video_stream_profile()
            cs.on_video_frame(f)
            sent += 1
        wait_for(sent)
    for s in (ds, cs):
        if s:
            s.stop()
            s.close()
    del rec
    print(json.dumps({"frames": len(stems), "out": out}))


main()
