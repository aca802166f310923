#!/usr/bin/env bash
# Render a calibration's HTML report in headless Chromium and save a screenshot (docs/report-screenshot.png).
#
#   bash benchmarks/html_screenshot.sh [OUT_DIR]
#
# Needs chromium (Debian: apt-get install -y chromium); without it the script says so and exits 0 having
# written the page only.  Simulates panda_weld (60 configurations, joint noise 1e-5 rad), calibrates it
# with --html, and renders the page with a fresh profile and no network traffic of the browser's own; a
# JavaScript or loading error in the page is printed by Chromium on stderr (--enable-logging=stderr) and
# makes this script fail.  PYTHON (default python3) runs the checkout's closedloop.
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-$(mktemp -d)}"
py="${PYTHON:-python3}"
mkdir -p "$out" docs
"$py" -m closedloop.cli.main simulate panda_weld --n 60 --seed 1 --out "$out/sim" --set noise=1e-5 --replace --quiet
"$py" -m closedloop.cli.main calibrate "$out/sim/nominal.urdf" "$out/sim/log.csv" \
  --loop weld:frame=panda_hand_tcp,name=fixture --report "$out/report.json" --html "$out/report.html" --quiet
browser="$(command -v chromium || command -v chromium-browser || command -v google-chrome || true)"
if [ -z "$browser" ]; then
  echo "no chromium found: page written to $out/report.html, no screenshot (apt-get install -y chromium)"
  exit 0
fi
profile="$(mktemp -d)"
trap 'rm -rf "$profile"' EXIT
"$browser" --headless --no-sandbox --disable-gpu --no-first-run --disable-background-networking \
  --disable-component-update --disable-sync --user-data-dir="$profile" --hide-scrollbars \
  --enable-logging=stderr --v=0 --window-size=1200,4600 --screenshot="$PWD/docs/report-screenshot.png" \
  "file://$(realpath "$out/report.html")" 2> "$out/chromium.log" || { cat "$out/chromium.log"; exit 1; }
if grep -E "Uncaught|ERR_FILE|Failed to load" "$out/chromium.log"; then
  echo "the page logged errors (above)"; exit 1
fi
"$py" - "$PWD/docs/report-screenshot.png" <<'PY'
import struct, sys
png = open(sys.argv[1], "rb").read()
assert png[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
w, h = struct.unpack(">II", png[16:24])
assert w >= 1000 and h >= 1000, (w, h)
print(f"screenshot {w}x{h} -> {sys.argv[1]}")
PY
