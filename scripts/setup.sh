#!/usr/bin/env bash
# Installs what a fresh Debian machine with Rust 1.95 lacks for umesh. Idempotent.
# numpy for the NPZ interop test; Mesa's EGL and GL drivers for the headless screenshots
# (wgpu's GL backend on llvmpipe, surfaceless: no X server, no GPU needed).
set -euo pipefail
need=()
# Xvfb, xdotool and Vulkan's software driver for the test that drives the real window.
for p in ca-certificates pkg-config libegl1 libegl-mesa0 libgl1-mesa-dri xvfb xdotool mesa-vulkan-drivers libvulkan1; do
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
if ! command -v cargo >/dev/null; then
  echo "error: cargo (Rust 1.95) is required: https://rustup.rs" >&2
  exit 1
fi
