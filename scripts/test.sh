#!/usr/bin/env bash
# The README's test command: set-up, then every test of the workspace in the release
# profile (the profile the app and the benchmarks use, so dependencies build once).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$HOME/.cache/umesh-target}"
# Headless screenshots render through EGL (Mesa llvmpipe) unless told otherwise.
export WGPU_BACKEND="${WGPU_BACKEND:-gl}"
exec cargo test --release --workspace "$@"
