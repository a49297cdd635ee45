"""umesh's RealSense bridge: frames of a RealSense camera or recording (.bag, .db3) written
on stdout in umesh's stream protocol (UMRGBD01, see rgbd/stream.rs), depth aligned to colour.
Messages go to stderr, one JSON object a line: {"info": ...}, {"warning": ...}, {"error": ...},
{"summary": {...}} at a clean end. umesh runs it (rgbd/realsense.rs); it is not a program of
its own.

  list                                   the connected cameras, JSON on stdout
  stream --file F [--realtime]           a recording: every frame in order, as fast as the
                                         reader takes them (or at the recording's own rate)
  stream [--serial S] [--width W --height H --fps F] [--record OUT.db3]
                                         a connected camera (and its recording)

Why Python: librealsense's own playback reads both recording formats (ROS 1 .bag before
2.56, ROS 2 .db3 since) and the live devices with one API; its wheel needs only libusb.
"""
import json
import os
import queue
import struct
import sys
import threading
import time


def say(**kw):
    sys.stderr.write(json.dumps(kw) + "\n")
    sys.stderr.flush()


def fail(msg, code=2):
    say(error=msg)
    end(code)


def end(code):
    # os._exit: librealsense's threads must not hold the process open at interpreter exit.
    try:
        sys.stdout.flush()
    except Exception:
        pass
    os._exit(code)


try:
    import numpy as np
    import pyrealsense2 as rs
except ImportError as e:
    fail(
        f"pyrealsense2 is not usable by {sys.executable} ({e}): run scripts/setup.sh, or "
        "pip install pyrealsense2 numpy into the Python umesh uses (UMESH_PYTHON); "
        "the wheel needs the system library libusb-1.0-0",
        3,
    )

MAGIC = b"UMRGBD01"
COLOR_FORMATS = {
    rs.format.rgb8: (3, False),
    rs.format.bgr8: (3, True),
    rs.format.rgba8: (4, False),
    rs.format.bgra8: (4, True),
}


def args(argv):
    a = {"file": None, "serial": None, "width": 640, "height": 480, "fps": 30, "realtime": False, "record": None}
    i = 0
    while i < len(argv):
        k = argv[i]
        if k == "--realtime":
            a["realtime"] = True
            i += 1
            continue
        if k not in ("--file", "--serial", "--width", "--height", "--fps", "--record") or i + 1 >= len(argv):
            fail(f"bridge: unknown or incomplete argument {k!r}")
        v = argv[i + 1]
        a[k[2:]] = int(v) if k in ("--width", "--height", "--fps") else v
        i += 2
    return a


def intrinsics_of(profile):
    k = profile.as_video_stream_profile().get_intrinsics()
    return k


def pinhole_warning(k, what):
    if any(abs(c) > 1e-6 for c in k.coeffs):
        say(warning=f"the {what} intrinsics carry lens distortion {list(k.coeffs)} ({k.model}); "
            "umesh uses the pinhole part only")


class Aligner:
    """Depth pixels moved into the colour camera: each depth pixel's footprint (its corners
    deprojected at its depth, moved by the depth-to-colour extrinsics, projected) filled in the
    colour image, the nearest surface kept; depth re-expressed along the colour camera's axis.
    A camera whose depth is already in the colour frame (same intrinsics, identity extrinsics)
    passes through unchanged."""

    def __init__(self, kd, kc, extr, units):
        self.kd, self.kc, self.units = kd, kc, units
        self.R = np.array(extr.rotation, dtype=np.float64).reshape(3, 3).T  # column-major
        self.t = np.array(extr.translation, dtype=np.float64)
        same = (kd.width, kd.height) == (kc.width, kc.height) and all(
            abs(a - b) <= 1e-9 * max(1.0, abs(a)) for a, b in [(kd.fx, kc.fx), (kd.fy, kc.fy), (kd.ppx, kc.ppx), (kd.ppy, kc.ppy)]
        )
        self.identity = same and np.allclose(self.R, np.eye(3), atol=1e-9) and np.allclose(self.t, 0, atol=1e-9)

    def __call__(self, d):
        if self.identity:
            return d
        kd, kc = self.kd, self.kc
        v, u = np.nonzero(d)
        z = d[v, u].astype(np.float64) * self.units

        def corner(off):
            p = np.stack([(u + off - kd.ppx) / kd.fx * z, (v + off - kd.ppy) / kd.fy * z, z])
            q = self.R @ p + self.t[:, None]
            with np.errstate(divide="ignore", invalid="ignore"):
                return q[0] / q[2] * kc.fx + kc.ppx, q[1] / q[2] * kc.fy + kc.ppy, q[2]

        u0, v0, zc = corner(-0.5)
        u1, v1, zc1 = corner(0.5)
        ok = (zc > 0) & (zc1 > 0) & np.isfinite(u0) & np.isfinite(u1) & np.isfinite(v0) & np.isfinite(v1)
        x0 = np.floor(np.minimum(u0, u1)[ok] + 0.5).astype(np.int64)
        x1 = np.floor(np.maximum(u0, u1)[ok] + 0.5).astype(np.int64)
        y0 = np.floor(np.minimum(v0, v1)[ok] + 0.5).astype(np.int64)
        y1 = np.floor(np.maximum(v0, v1)[ok] + 0.5).astype(np.int64)
        raw = np.clip(np.round(((zc + zc1) / 2)[ok] / self.units), 1, 65535).astype(np.uint32)
        big = np.uint32(1 << 20)
        out = np.full(kc.height * kc.width, big, dtype=np.uint32)
        # A footprint wider than 8 colour pixels is clipped: depth far coarser than colour.
        span = min(8, int(max((x1 - x0).max(initial=0), (y1 - y0).max(initial=0))) + 1)
        for oy in range(span):
            for ox in range(span):
                x, y = x0 + ox, y0 + oy
                m = (x <= x1) & (y <= y1) & (x >= 0) & (y >= 0) & (x < kc.width) & (y < kc.height)
                np.minimum.at(out, y[m] * kc.width + x[m], raw[m])
        out[out == big] = 0
        return out.astype(np.uint16).reshape(kc.height, kc.width)


class Emitter:
    def __init__(self, kd, kc, extr, units, color_fmt):
        self.align = Aligner(kd, kc, extr, units) if kc is not None else None
        self.k = kc if kc is not None else kd
        # Units are stored as float32 (0.001 reads 0.0010000000474974513): a whole number of
        # units per metre is taken as such.
        scale = 1.0 / units
        self.depth_scale = float(round(scale)) if abs(scale - round(scale)) < 1e-4 * scale else scale
        self.color_fmt = color_fmt
        self.frames = 0
        self.dropped = 0
        self.without_color = 0
        self.last_number = None
        self.first_size = None
        # Recordings played at their own rate: frames emitted at their timestamps.
        self.pace = False
        self.clock = None

    def emit(self, d, number, ts_ms, c=None, host_time=None):
        if self.pace:
            if self.clock is None:
                self.clock = (time.time(), ts_ms)
            due = self.clock[0] + (ts_ms - self.clock[1]) / 1000.0
            if due > time.time():
                time.sleep(due - time.time())
            host_time = None
        if self.last_number is not None and number > self.last_number + 1:
            self.dropped += number - self.last_number - 1
        self.last_number = number
        host_time = time.time() if host_time is None else host_time
        if self.align is not None:
            d = self.align(d)
        k = self.k
        h = {
            "width": k.width, "height": k.height, "fx": k.fx, "fy": k.fy, "cx": k.ppx, "cy": k.ppy,
            "timestamp_s": ts_ms / 1000.0, "depth_scale": self.depth_scale, "color": c is not None,
            "frame_number": int(number), "host_time_s": host_time,
        }
        body = [np.ascontiguousarray(d, dtype="<u2").tobytes()]
        if c is not None:
            bpp, bgr = COLOR_FORMATS[self.color_fmt]
            c = c.reshape(k.height, k.width, bpp)[:, :, :3]
            if bgr:
                c = c[:, :, ::-1]
            body.append(np.ascontiguousarray(c, dtype=np.uint8).tobytes())
        else:
            self.without_color += self.align is not None
        head = json.dumps(h).encode()
        out = sys.stdout.buffer
        out.write(MAGIC + struct.pack("<I", len(head)) + head)
        for b in body:
            out.write(b)
        out.flush()
        self.frames += 1


def list_devices():
    devs = []
    for d in rs.context().query_devices():
        info = lambda key: d.get_info(key) if d.supports(key) else None  # noqa: E731
        devs.append({
            "name": info(rs.camera_info.name), "serial": info(rs.camera_info.serial_number),
            "firmware": info(rs.camera_info.firmware_version), "usb": info(rs.camera_info.usb_type_descriptor),
        })
    print(json.dumps(devs))


def depth_units_of(sensor):
    if sensor.supports(rs.option.depth_units):
        return float(sensor.get_option(rs.option.depth_units))
    say(warning="the depth sensor does not state its depth units; 1 mm a unit assumed")
    return 0.001


def stream_file(a):
    path = a["file"]
    try:
        dev = rs.context().load_device(path)
    except RuntimeError as e:
        fail(f"{path}: not a RealSense recording librealsense can open (.bag or .db3): {e}")
    pb = dev.as_playback()
    # librealsense's own real-time playback follows the times the recorder received the
    # frames; the recording's rate is that of the frames' timestamps: read every frame and
    # pace them here instead.
    pb.set_real_time(False)
    # Every depth and colour profile recorded is opened: a recording may hold several.
    opened, streams = [], []
    depth_sensor = color_profile = None
    for s in dev.query_sensors():
        mine = []
        for p in s.get_stream_profiles():
            if not p.is_video_stream_profile():
                continue
            vp = p.as_video_stream_profile()
            streams.append(f"{p.stream_name()} {vp.width()}x{vp.height()} {p.format()}")
            if p.stream_type() == rs.stream.depth:
                depth_sensor = depth_sensor or s
                mine.append(p)
            elif p.stream_type() == rs.stream.color and p.format() in COLOR_FORMATS:
                color_profile = color_profile or p
                mine.append(p)
            elif p.stream_type() == rs.stream.color:
                say(warning=f"{path}: colour in {p.format()} is not read (rgb8, bgr8, rgba8 or bgra8)")
        if mine:
            opened.append((s, mine))
    if depth_sensor is None:
        fail(f"{path}: the recording has no depth stream (it holds: {', '.join(streams) or 'no video stream'}); umesh needs depth")
    units = depth_units_of(depth_sensor)
    q = queue.Queue(maxsize=16)
    stop = threading.Event()

    def callback(f):
        vf = f.as_video_frame()
        p = f.get_profile()
        kind = "depth" if p.stream_type() == rs.stream.depth else "color"
        item = (kind, np.asanyarray(vf.get_data()).copy(), f.get_frame_number(), f.get_timestamp(), vf.get_width(), vf.get_height(), p, time.time())
        while not stop.is_set():
            try:
                q.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    try:
        for s, profiles in opened:
            s.open(profiles)
            s.start(callback)
    except RuntimeError as e:
        fail(f"{path}: cannot play the recording: {e}")
    t0 = time.time()
    while pb.current_status() == rs.playback_status.stopped and time.time() - t0 < 2:
        time.sleep(0.001)
    em = None
    first = None
    tol_ms = 0.0
    depths, colors = [], []
    has_color = color_profile is not None

    def flush(final):
        # Pair each depth frame with the colour frame nearest in time (both queues in order).
        while depths and (colors or final or not has_color):
            dn, dts, d, dgot = depths[0]
            if not has_color or not colors:
                if has_color and not final:
                    return
                depths.pop(0)
                em.emit(d, dn, dts, host_time=dgot)
                continue
            cn, cts, c = colors[0]
            if abs(cts - dts) <= tol_ms:
                depths.pop(0)
                colors.pop(0)
                em.emit(d, dn, dts, c, host_time=dgot)
            elif cts < dts:
                colors.pop(0)
            else:
                depths.pop(0)
                em.emit(d, dn, dts, host_time=dgot)

    last_frame = time.time()
    try:
        while True:
            try:
                kind, data, number, ts, w, h, prof, got = q.get(timeout=0.05)
            except queue.Empty:
                if pb.current_status() == rs.playback_status.stopped and q.empty():
                    break
                if time.time() - last_frame > 10:
                    fail(f"{path}: no frame for 10 s and the playback has not ended: the file is damaged")
                continue
            last_frame = time.time()
            values = data.size if kind == "depth" else data.size // max(1, COLOR_FORMATS[prof.format()][0])
            if values != w * h:
                fail(f"{path}: {kind} frame {number} holds {values} pixels, its stream says {w}x{h}: the recording is damaged")
            pv = prof.as_video_stream_profile()
            if (pv.width(), pv.height()) != (w, h):
                fail(f"{path}: {kind} frame {number} is {w}x{h}, its stream is {pv.width()}x{pv.height()}: "
                     "the image size changes within the recording")
            if kind == "depth":
                if first is None:
                    first = (w, h)
                    kd = intrinsics_of(prof)
                    pinhole_warning(kd, "depth")
                    kc = extr = None
                    if has_color:
                        kc = intrinsics_of(color_profile)
                        pinhole_warning(kc, "colour")
                        try:
                            extr = prof.get_extrinsics_to(color_profile)
                        except RuntimeError:
                            say(warning=f"{path}: no depth-to-colour extrinsics recorded; depth taken as seen from the colour camera")
                            extr = rs.extrinsics()
                            extr.rotation, extr.translation = [1, 0, 0, 0, 1, 0, 0, 0, 1], [0, 0, 0]
                    em = Emitter(kd, kc, extr, units, color_profile.format() if has_color else None)
                    em.pace = bool(a["realtime"])
                    fps = prof.fps() or 30
                    tol_ms = 500.0 / fps
                    say(info=f"{path}: depth {kd.width}x{kd.height}" + (f", colour {kc.width}x{kc.height}" if kc else ", no colour")
                        + f", {fps} fps, {units * 1000:g} mm a depth unit")
                elif (w, h) != first:
                    fail(f"{path}: depth frame {number} is {w}x{h}, the frames before it {first[0]}x{first[1]}: "
                         "a recording must keep one depth size")
                depths.append((number, ts, data.reshape(h, w), got))
            elif em is not None or not depths:
                colors.append((number, ts, data))
            if em is not None:
                flush(False)
        if em is not None:
            flush(True)
    except BrokenPipeError:
        stop.set()
        end(0)
    finally:
        stop.set()
    if em is None or em.frames == 0:
        fail(f"{path}: the recording holds no depth frame")
    say(summary={"frames": em.frames, "dropped": em.dropped, "depth_without_color": em.without_color, "source": path})


def stream_device(a):
    ctx = rs.context()
    devs = list(ctx.query_devices())
    if not devs:
        fail("no RealSense camera is connected (check the USB 3 cable and, on Linux, librealsense's udev rules)", 4)
    serials = [d.get_info(rs.camera_info.serial_number) for d in devs]
    if a["serial"] and a["serial"] not in serials:
        fail(f"no RealSense camera with serial {a['serial']}: connected are {', '.join(serials)}", 4)
    pipe, cfg = rs.pipeline(), rs.config()
    if a["serial"]:
        cfg.enable_device(a["serial"])
    w, h, fps = a["width"], a["height"], a["fps"]
    cfg.enable_stream(rs.stream.depth, w, h, rs.format.z16, fps)
    cfg.enable_stream(rs.stream.color, w, h, rs.format.rgb8, fps)
    if a["record"]:
        # librealsense's own recorder: the session as the camera gave it, for later review.
        cfg.enable_record_to_file(a["record"])
    try:
        prof = pipe.start(cfg)
    except RuntimeError as e:
        fail(f"the camera cannot stream depth and colour at {w}x{h}, {fps} fps: {e}", 4)
    dp, cp = prof.get_stream(rs.stream.depth), prof.get_stream(rs.stream.color)
    kd, kc = intrinsics_of(dp), intrinsics_of(cp)
    pinhole_warning(kc, "colour")
    units = depth_units_of(prof.get_device().first_depth_sensor())
    em = Emitter(kd, kc, dp.get_extrinsics_to(cp), units, rs.format.rgb8)
    dev = prof.get_device()
    say(info=f"{dev.get_info(rs.camera_info.name)} {dev.get_info(rs.camera_info.serial_number)}: {w}x{h} at {fps} fps, "
        f"{units * 1000:g} mm a depth unit")
    try:
        while True:
            try:
                fs = pipe.wait_for_frames(5000)
            except RuntimeError as e:
                fail(f"the camera sent no frame for 5 s (unplugged, or the USB link dropped): {e}", 5)
            d, c = fs.get_depth_frame(), fs.get_color_frame()
            if not d:
                continue
            dd = np.asanyarray(d.get_data()).reshape(d.get_height(), d.get_width())
            cc = np.asanyarray(c.get_data()) if c else None
            em.emit(dd, d.get_frame_number(), d.get_timestamp(), cc)
    except BrokenPipeError:
        end(0)
    finally:
        try:
            pipe.stop()
        except RuntimeError:
            pass


def main():
    if len(sys.argv) < 2 or sys.argv[1] not in ("list", "stream"):
        fail("bridge: expected 'list' or 'stream'")
    if sys.argv[1] == "list":
        list_devices()
        return
    a = args(sys.argv[2:])
    try:
        if a["file"]:
            stream_file(a)
        else:
            stream_device(a)
    except BrokenPipeError:
        end(0)
    except Exception as e:  # one message, never a traceback
        fail(f"{a['file'] or 'camera'}: {type(e).__name__}: {e}")
    end(0)


main()
