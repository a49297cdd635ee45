#!/usr/bin/env bash
# Render a patient's report.html in headless Chromium to a PNG (checks that the page is
# self-contained: Chromium runs with networking off).
#   bash scripts/report_screenshot.sh PATIENT/ [out.png]
set -euo pipefail
patient="${1:?usage: report_screenshot.sh PATIENT/ [out.png]}"
out="${2:-$patient/report.png}"
if ! command -v chromium >/dev/null; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium
fi
profile=$(mktemp -d)
trap 'rm -rf "$profile"' EXIT
chromium --headless --no-sandbox --disable-gpu --disable-quic --no-first-run --disable-background-networking \
  --disable-component-update --disable-sync --user-data-dir="$profile" --window-size=1200,4000 \
  --screenshot="$(realpath -m "$out")" "file://$(realpath "$patient")/report.html" 2>/dev/null
test -s "$out"
echo "$out"
