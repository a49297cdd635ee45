#!/usr/bin/env bash
# Render N headless screenshots in a row, each in its own process (default 30, cycling the
# scenes), and report crashes and ERROR log lines: the check that headless rendering on Mesa's
# GL is clean (it used to log the SSAO shader error every time and abort now and then).
# Usage: bash scripts/screenshot_soak.sh [N]
set -uo pipefail
cd "$(dirname "$0")/.."
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$HOME/.cache/umesh-target}"
export WGPU_BACKEND="${WGPU_BACKEND:-gl}"
n="${1:-30}"
cargo build --release --quiet
bin="$CARGO_TARGET_DIR/release/umesh"
scenes=(phantom grid probes rehearsal camera jobs qa ar)
out=$(mktemp -d)
crashes=0
errors=0
for i in $(seq 1 "$n"); do
  scene=${scenes[$(( (i - 1) % ${#scenes[@]} ))]}
  if ! "$bin" screenshot --scene "$scene" --size 960x600 --out "$out/$i.png" > "$out/$i.log" 2>&1; then
    crashes=$((crashes + 1))
    echo "render $i ($scene): failed, see $out/$i.log"
  fi
  if grep -q "ERROR" "$out/$i.log"; then
    errors=$((errors + 1))
    echo "render $i ($scene): ERROR in the log: $(grep -m1 ERROR "$out/$i.log")"
  fi
done
echo "$n renders: $crashes failed, $errors with an ERROR line"
[ "$crashes" -eq 0 ] && [ "$errors" -eq 0 ]
