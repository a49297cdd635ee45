#!/usr/bin/env bash
# Installs what a fresh Debian machine with Rust 1.95 lacks for umesh. Idempotent.
# numpy for the NPZ interop test; Mesa's EGL and GL drivers for the headless screenshots
# (wgpu's GL backend on llvmpipe, surfaceless: no X server, no GPU needed).
set -euo pipefail
need=()
# Xvfb, xdotool and Vulkan's software driver for the test that drives the real window.
# libusb for librealsense's Python wheel (RealSense cameras and recordings).
for p in ca-certificates pkg-config libegl1 libegl-mesa0 libgl1-mesa-dri xvfb xdotool mesa-vulkan-drivers libvulkan1 libusb-1.0-0; do
  dpkg -s "$p" >/dev/null 2>&1 || need+=("$p")
done
if [ ${#need[@]} -gt 0 ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need[@]}"
fi
# numpy, to check that the NPZ files load with numpy.load (the interop test).
if command -v python3 >/dev/null && ! python3 -c "import numpy" 2>/dev/null; then
  python3 -m pip install --quiet numpy 2>/dev/null || {
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq python3-numpy
  }
fi
# RealSense: librealsense's Python wrapper in a virtual environment of umesh's own (the
# bridge umesh runs for cameras and .db3/.bag recordings; docs/OPERATING_ROOM.md), with numpy
# and Pillow (the tests write RealSense recordings from umesh's synthetic ones).
venv="${UMESH_VENV:-$HOME/.cache/umesh-python}"
if command -v python3 >/dev/null && ! "$venv/bin/python" -c "import pyrealsense2, numpy, PIL" 2>/dev/null; then
  if ! python3 -m venv "$venv" 2>/dev/null; then
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq python3-venv
    python3 -m venv "$venv"
  fi
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check pyrealsense2 numpy pillow \
    || echo "warning: pyrealsense2 could not be installed into $venv: RealSense cameras and recordings are unavailable and their tests will say SKIPPED" >&2
fi
if ! command -v cargo >/dev/null; then
  echo "error: cargo (Rust 1.95) is required: https://rustup.rs" >&2
  exit 1
fi
