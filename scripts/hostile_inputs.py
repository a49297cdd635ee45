#!/usr/bin/env python3
"""Hostile inputs against the `umesh` command line: wrong outputs, absurd numbers, corrupt and
mismatched files. Every case must end in one clear refusal (non-zero exit, no panic) or finish
within the time limit; no input and no existing output may change on a refused run, and no
input on any run. Cases that exit 0 are listed for reading (silent nonsense is judged by eye).

    python3 scripts/hostile_inputs.py [--umesh PATH] [--work DIR] [--only SUBSTRING]

Needs a release build (`bash scripts/test.sh --no-run` or `cargo build --release`); takes
5-10 minutes on 2 cores. Exit status 1 when a case panicked, hung or damaged a file.
"""

import argparse
import gzip
import struct
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LIMIT_S = 120


def tree_hash(path):
    """Hash of a file or a folder's files (names and bytes); None when absent."""
    if not os.path.exists(path):
        return None
    h = hashlib.sha256()
    if os.path.isfile(path):
        h.update(open(path, "rb").read())
        return h.hexdigest()
    for dirpath, dirnames, filenames in os.walk(path):
        dirnames.sort()
        for f in sorted(filenames):
            p = os.path.join(dirpath, f)
            h.update(os.path.relpath(p, path).encode())
            h.update(open(p, "rb").read())
    return h.hexdigest()


class Campaign:
    def __init__(self, umesh, work):
        self.umesh, self.work = umesh, work
        self.results = []

    def run(self, args, timeout=LIMIT_S):
        t = time.time()
        try:
            p = subprocess.run([self.umesh] + args, capture_output=True, text=True, timeout=timeout, cwd=self.work)
            return p.returncode, p.stdout, p.stderr, time.time() - t
        except subprocess.TimeoutExpired:
            return None, "", "", time.time() - t

    def fixture(self, name, args):
        path = os.path.join(self.work, name)
        if not os.path.exists(path):
            rc, _, err, _ = self.run(args + ["--out", path], timeout=1800)
            if rc != 0:
                sys.exit(f"fixture {name} failed: {err.strip()[-2000:]}")
        return path

    def copy(self, src, name):
        dst = os.path.join(self.work, "cases", name)
        if os.path.exists(dst):
            shutil.rmtree(dst)
        shutil.copytree(src, dst)
        return dst

    def case(self, name, args, protect=(), expect="refuse"):
        """expect: refuse (non-zero exit wanted) or either (a right result is fine too)."""
        before = {p: tree_hash(p) for p in protect}
        rc, out, err, secs = self.run(args)
        after = {p: tree_hash(p) for p in protect}
        damaged = [p for p in protect if before[p] != after[p]]
        if rc is None:
            verdict = "hang"
        elif "panicked" in err or rc in (101, 134) or rc < 0:
            verdict = "panic"
        elif damaged:
            verdict = "damage"
        elif rc != 0:
            verdict = "refused" if err.strip() else "silent-failure"
        else:
            verdict = "ok" if expect == "either" else "accepted"
        line = (err.strip().splitlines() or [""])[-1][:200] if rc else (out.strip().splitlines() or [""])[0][:200]
        self.results.append({"case": name, "verdict": verdict, "exit": rc, "seconds": round(secs, 1), "says": line, "damaged": damaged})
        print(f"{verdict:>14}  {secs:6.1f} s  {name}: {line}", flush=True)


def corrupt_json(path, edit):
    v = json.load(open(path))
    edit(v)
    json.dump(v, open(path, "w"))


def scale_nifti(src, dst, k):
    """A NIfTI-1 file with its voxel sizes and sform scaled by k."""
    raw = bytearray(gzip.open(src).read())
    for i in range(1, 4):
        o = 76 + 4 * i
        struct.pack_into("<f", raw, o, struct.unpack_from("<f", raw, o)[0] * k)
    for i in range(12):
        o = 280 + 4 * i
        struct.pack_into("<f", raw, o, struct.unpack_from("<f", raw, o)[0] * k)
    gzip.open(dst, "wb").write(bytes(raw))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--umesh", default=os.path.expanduser("~/.cache/umesh-target/release/umesh"))
    ap.add_argument("--work", default="/tmp/umesh-hostile")
    ap.add_argument("--only", default="")
    a = ap.parse_args()
    os.makedirs(os.path.join(a.work, "cases"), exist_ok=True)
    c = Campaign(a.umesh, a.work)
    model = os.path.join(ROOT, "assets", "model")
    M = c.copy(model, "../model") if not os.path.exists(os.path.join(a.work, "model")) else os.path.join(a.work, "model")
    R = c.fixture("recording", ["rgbd", "synth", "--model", M, "--frames", "3", "--width", "160", "--height", "120"])
    D = c.fixture("dataset", ["dataset", "generate", "--samples", "6", "--shard-size", "3"])
    P = c.fixture(
        "patient", ["prepare", "--samples", "10", "--shard-size", "5", "--epochs", "1", "--check-frames", "3"]
    )
    S = c.fixture("surface", ["surface", "--step", "4"])
    seg = os.path.join(ROOT, "assets", "phantom.nii.gz")
    inputs = [M, R, D, P, S]
    new = lambda n: os.path.join(a.work, "cases", n)
    reg = ["register", "--model", M, "--recording", R, "--no-overlay"]
    cases = []

    def add(name, args, protect=inputs, expect="refuse", setup=None):
        cases.append((name, args, protect, expect, setup))

    # Outputs of one kind never replace another kind, nor the command's own inputs.
    add("register --out its recording", reg + ["--out", R])
    add("register --out a model", reg + ["--out", M])
    add("register --patient --out the patient's model", ["register", "--patient", P, "--recording", P + "/check/recording", "--out", P + "/model"])
    add("rgbd synth --out a model", ["rgbd", "synth", "--frames", "2", "--out", M])
    add("simulate --out a model", ["simulate", "--out", M])
    add("surface --out a recording", ["surface", "--out", R])
    add("dataset generate --out a model", ["dataset", "generate", "--samples", "2", "--out", M])
    add("train --out its dataset", ["train", "--dataset", D, "--out", D])
    add("train --out inside its dataset", ["train", "--dataset", D, "--out", D + "/model"])
    add("train --out a recording", ["train", "--dataset", D, "--out", R])
    add("train another dataset into a patient's model", ["train", "--dataset", D, "--out", P + "/model"])
    add("prepare --out a model", ["prepare", "--samples", "10", "--out", M])
    add("grid --out a dataset", ["grid", "--out", D])
    add("register --out a patient", reg + ["--out", P])
    add("rgbd synth --out a dataset", ["rgbd", "synth", "--frames", "2", "--out", D])
    # Numbers a run cannot finish with, or that mean nothing.
    for lr in ["NaN", "inf", "1e30", "0", "-1"]:
        add(f"train --learning-rate {lr}", ["train", "--dataset", D, "--out", new("t-lr"), f"--learning-rate={lr}", "--epochs", "1"])
    add("train --epochs 0", ["train", "--dataset", D, "--out", new("t-e0"), "--epochs", "0"])
    add("train --time-budget-min 1e30", ["train", "--dataset", D, "--out", new("t-tb"), "--epochs", "1", "--time-budget-min", "1e30"], expect="either")
    add("train --patience u64::MAX", ["train", "--dataset", D, "--out", new("t-pat"), "--epochs", "1", "--patience", "18446744073709551615"], expect="either")
    add("train --batch-size 0", ["train", "--dataset", D, "--out", new("t-b0"), "--batch-size", "0"])
    add("train --batch-size u64::MAX", ["train", "--dataset", D, "--out", new("t-bmax"), "--epochs", "1", "--batch-size", "18446744073709551615"], expect="either")
    add("train --channels 0", ["train", "--dataset", D, "--out", new("t-c0"), "--channels", "0"])
    add("train --channels 100000", ["train", "--dataset", D, "--out", new("t-cbig"), "--channels", "100000"])
    add("train --steps 40", ["train", "--dataset", D, "--out", new("t-s40"), "--steps", "40"])
    add("train --rest-views 2", ["train", "--dataset", D, "--out", new("t-rv"), "--rest-views", "2"])
    add("train --dataset missing", ["train", "--dataset", new("nothing"), "--out", new("t-miss")])
    for opt, v in [
        ("--correction-subspace", "1000"),
        ("--correction-subspace", "18446744073709551615"),
        ("--correction-updates", "100"),
        ("--correction-cg", "1000"),
        ("--frame-budget-ms", "-1"),
        ("--frame-budget-ms", "NaN"),
        ("--frame-budget-ms", "1e308"),
        ("--doubted-updates", "18446744073709551615"),
        ("--iterations", "0"),
        ("--iterations", "18446744073709551615"),
        ("--pose-bound-mm", "NaN"),
        ("--min-coverage", "2"),
        ("--depth-min-mm", "1e308"),
        ("--depth-max-mm", "-5"),
        ("--correction-form", "nonsense"),
        ("--pose", "nonsense"),
    ]:
        add(f"register {opt} {v}", reg + [f"{opt}={v}", "--out", new("reg-n")])
    add("register --correction-updates 0 --doubted-updates 3", reg + ["--correction-updates", "0", "--doubted-updates", "3", "--out", new("reg-d")])
    synth = ["rgbd", "synth", "--model", M, "--width", "160", "--height", "120"]
    for opt, v in [
        ("--poisson", "-0.9999"),
        ("--poisson", "0.4999999"),
        ("--poisson", "0.5"),
        ("--poisson", "NaN"),
        ("--young-pa", "0"),
        ("--young-pa", "1e308"),
        ("--frames", "0"),
        ("--frames", "18446744073709551615"),
        ("--width", "0"),
        ("--width", "100000"),
        ("--focal-px", "NaN"),
        ("--noise-mm", "-1"),
        ("--noise-mm", "1e30"),
        ("--load-scale", "1e30"),
        ("--load-scale", "NaN"),
        ("--fps", "0"),
        ("--markers", "0"),
        ("--markers", "18446744073709551615"),
        ("--cloud-points", "18446744073709551615"),
        ("--camera-motion-mm", "1e308"),
        ("--material", "rubber"),
        ("--attachment-shift-mm", "NaN,0,0"),
    ]:
        add(f"rgbd synth {opt} {v}", synth + ["--frames", "2", f"{opt}={v}", "--out", new("synth-n")] if opt != "--frames" else synth + [f"{opt}={v}", "--out", new("synth-n")])
    gen = ["dataset", "generate", "--shard-size", "2"]
    for opt, v in [
        ("--samples", "0"),
        ("--samples", "18446744073709551615"),
        ("--cell-size-mm", "0"),
        ("--cell-size-mm", "NaN"),
        ("--cell-size-mm", "0.01"),
        ("--cell-size-mm", "1e308"),
        ("--subdivisions", "100"),
        ("--pooling-steps", "18446744073709551615"),
        ("--shard-size", "0"),
        ("--target-displacement-mm", "1e308"),
        ("--target-displacement-mm", "-3"),
        ("--max-strain", "NaN"),
        ("--visible-fraction", "0"),
        ("--poisson", "0.5"),
        ("--poisson-range", "0.4,0.3"),
        ("--neo-hookean-fraction", "2"),
        ("--fix-distance-mm", "1e308"),
        ("--fov-deg", "0"),
        ("--fov-deg", "180"),
        ("--max-newton-iterations", "0"),
        ("--probes", "18446744073709551615"),
        ("--probe-radius-mm", "NaN"),
        ("--young-pa", "-1"),
        ("--loads", "nonsense"),
    ]:
        add(f"dataset generate {opt} {v}", gen + ["--samples", "2", f"{opt}={v}", "--out", new("gen-n")] if opt != "--samples" else gen + [f"{opt}={v}", "--out", new("gen-n")])
    add("grid --cell-size-mm 0.001", ["grid", "--cell-size-mm", "0.001", "--out", new("grid-n")])
    add("grid --max-voxels 0", ["grid", seg, "--max-voxels", "0"])
    add("simulate --young-pa NaN", ["simulate", "--young-pa=NaN", "--out", new("sim-n")])
    add("simulate --increments u64::MAX", ["simulate", "--increments", "18446744073709551615", "--out", new("sim-n")])
    add("surface --step 0", ["surface", "--step", "0", "--out", new("surf-n")])
    add("surface --step 100000", ["surface", "--step", "100000", "--out", new("surf-n")])
    add("eval --markers 0", ["eval", "--model", M, "--dataset", D, "--markers", "0"])
    add("eval --markers u64::MAX", ["eval", "--model", M, "--dataset", D, "--markers", "18446744073709551615"])
    add("prepare --time-budget-min 1e30", ["prepare", "--samples", "10", "--shard-size", "5", "--epochs", "1", "--check-frames", "3", "--time-budget-min", "1e30", "--out", P], protect=[M, R, D, S, P + "/model", P + "/dataset"], expect="either")
    add("simulate --increments 0", ["simulate", "--increments", "0", "--out", new("sim-n")])

    # Corrupt or edited files, each in its own copy.
    def model_case(name, edit, cmd=None):
        def setup():
            m = c.copy(M, "m-" + name.replace(" ", "-")[:40])
            edit(m)
            return m

        cases.append((f"model: {name}", cmd, None, "refuse", ("model", setup)))

    model_case("model.json not JSON", lambda m: open(m + "/model.json", "w").write("{not json"))
    model_case("weights truncated", lambda m: open(m + "/model.safetensors", "r+b").truncate(1000))
    model_case("weights missing", lambda m: os.remove(m + "/model.safetensors"))
    model_case("surface_step 100000", lambda m: corrupt_json(m + "/model.json", lambda v: v["dataset_config"].__setitem__("surface_step", 100000)))
    model_case("fixed distance 1e308", lambda m: corrupt_json(m + "/model.json", lambda v: v["dataset_config"].get("fixed", {}).__setitem__("distance_mm", 1e308)))
    model_case("confidence all zero", lambda m: corrupt_json(m + "/confidence.json", lambda v: v.update({k: 0 for k in v})))
    model_case("confidence at 1e308", lambda m: corrupt_json(m + "/confidence.json", lambda v: v.update({k: 1e308 for k in v if k.endswith("_mm")})))
    # The grid is rebuilt from the model's settings; its grid.npz is for other tools.
    def huge_correction(m):
        v = json.load(open(os.path.join(P, "model", "correction.json")))
        for form in v.values():
            if isinstance(form, dict):
                for k in form:
                    form[k] = 1e308
        json.dump(v, open(m + "/correction.json", "w"))

    model_case("correction.json figures 1e308", huge_correction)

    def rec_case(name, edit, expect="refuse"):
        def setup():
            r = c.copy(R, "r-" + name.replace(" ", "-")[:40])
            edit(r)
            return r

        cases.append((f"recording: {name}", None, None, expect, ("recording", setup)))

    def shear(r):
        lines = open(r + "/trajectory.log").read().splitlines()
        row = lines[1].split()
        row[1] = str(float(row[1]) + 0.5)
        lines[1] = " ".join(row)
        open(r + "/trajectory.log", "w").write("\n".join(lines) + "\n")

    rec_case("sheared pose", shear)
    # A damaged frame is skipped with its reason, the others registered against their own truth.
    rec_case("depth png truncated", lambda r: open(r + "/depth/00001.png", "r+b").truncate(100), expect="either")
    rec_case("depth png missing", lambda r: os.remove(r + "/depth/00001.png"), expect="either")
    rec_case("intrinsics negative focal", lambda r: corrupt_json(r + "/intrinsics.json", lambda v: v["intrinsic_matrix"].__setitem__(0, -525.0)))
    def nan_focal(r):
        text = open(r + "/intrinsics.json").read().replace("525.0", "NaN", 1)
        open(r + "/intrinsics.json", "w").write(text)

    rec_case("intrinsics NaN", nan_focal)
    rec_case("intrinsics wrong size", lambda r: corrupt_json(r + "/intrinsics.json", lambda v: v.__setitem__("width", 640)))
    rec_case("ground truth huge", lambda r: corrupt_json(r + "/ground_truth.json", lambda v: v["markers_rest_mm"][0].__setitem__(0, 1e300)))
    rec_case("ground truth not JSON", lambda r: open(r + "/ground_truth.json", "w").write("["))
    rec_case("trajectory empty", lambda r: open(r + "/trajectory.log", "w").write(""))
    rec_case("color frame of another size", expect="either", edit= lambda r: shutil.copy(os.path.join(ROOT, "assets", "model", "..", "..", "screenshots", [f for f in sorted(os.listdir(os.path.join(ROOT, "screenshots"))) if f.endswith(".png")][0]), r + "/color/00001.png"))

    def manifest_case(name, edit):
        def setup():
            d = c.copy(D, "d-" + name.replace(" ", "-")[:40])
            edit(d)
            return d

        cases.append((f"dataset: {name}", None, None, "refuse", ("dataset", setup)))

    def lie(d):
        corrupt_json(d + "/manifest.json", lambda v: v.__setitem__("samples", (v.get("samples") or []) + (v.get("samples") or [])[:1]) if isinstance(v.get("samples"), list) else v.__setitem__("samples", 600))

    manifest_case("manifest lists more samples", lie)
    manifest_case("manifest not JSON", lambda d: open(d + "/manifest.json", "w").write("{"))
    manifest_case("a shard truncated", lambda d: [open(os.path.join(d, f), "r+b").truncate(50) for f in sorted(os.listdir(d)) if f.endswith((".npz", ".bin", ".safetensors"))][:1])

    # Inputs that do not belong together.
    # The phantom at 80 % of its size (voxel sizes and affine scaled): another organ.
    small = new("phantom-small.nii.gz")
    scale_nifti(seg, small, 0.8)
    other = c.fixture("other-organ-recording", ["rgbd", "synth", small, "--frames", "2", "--width", "160", "--height", "120"])
    add("choose-correction on a recording of another organ", ["choose-correction", "--patient", P, "--recording", other])
    add("register --patient with another organ's recording", ["register", "--patient", P, "--recording", other, "--no-overlay", "--out", new("reg-other")])
    add("register --ground-truth of another recording", reg + ["--ground-truth", other + "/ground_truth.json", "--out", new("reg-gt")])
    add("register --intrinsics garbage", reg + ["--intrinsics", S + "/organ.obj", "--out", new("reg-int")])
    not_nifti = new("organ-mesh.nii.gz")
    shutil.copy(S + "/organ.obj", not_nifti)
    add("segmentation not NIfTI", ["grid", not_nifti])
    garbage = new("garbage.nii.gz")
    open(garbage, "wb").write(b"\x1f\x8b" + os.urandom(3000))
    add("segmentation random gzip", ["grid", garbage])
    empty = new("empty.obj")
    open(empty, "w").write("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    add("mesh with a NaN vertex", ["grid", empty, "--mesh-scale-mm", "1"])

    failed = 0
    for name, args, protect, expect, setup in cases:
        if a.only and a.only not in name:
            continue
        if setup:
            kind, f = setup
            x = f()
            if kind == "model":
                args = ["register", "--model", x, "--recording", R, "--no-overlay", "--out", new("reg-m")]
            elif kind == "recording":
                args = ["register", "--model", M, "--recording", x, "--no-overlay", "--out", new("reg-r")]
            else:
                args = ["train", "--dataset", x, "--out", new("t-d"), "--epochs", "1"]
            protect = inputs + [x]
        c.case(name, args, protect, expect)
    counts = {}
    for r in c.results:
        counts[r["verdict"]] = counts.get(r["verdict"], 0) + 1
    print(json.dumps(counts))
    json.dump(c.results, open(os.path.join(a.work, "results.json"), "w"), indent=1)
    failed = sum(counts.get(k, 0) for k in ("panic", "hang", "damage", "silent-failure"))
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
