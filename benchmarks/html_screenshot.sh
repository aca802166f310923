#!/usr/bin/env bash
# Render a calibration's HTML report in headless Chromium and save a screenshot (docs/report-screenshot.png).
#
#   bash benchmarks/html_screenshot.sh [OUT_DIR]
#
# Needs chromium (Debian: apt-get install -y chromium).  Simulates panda_weld (60 configurations, joint
# noise 1e-5 rad), calibrates it with --html, and renders the page; a JavaScript or loading error in the
# page is printed by Chromium on stderr (--enable-logging=stderr) and makes this script fail.
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-$(mktemp -d)}"
mkdir -p "$out" docs
closedloop simulate panda_weld --n 60 --seed 1 --out "$out/sim" --set noise=1e-5 --quiet
closedloop calibrate "$out/sim/nominal.urdf" "$out/sim/log.csv" --loop weld:frame=panda_hand_tcp,name=fixture \
  --report "$out/report.json" --html "$out/report.html" --quiet
chromium --headless=new --no-sandbox --disable-gpu --hide-scrollbars --enable-logging=stderr --v=0 \
  --window-size=1200,4600 --screenshot="$PWD/docs/report-screenshot.png" "file://$(realpath "$out/report.html")" \
  2> "$out/chromium.log" || { cat "$out/chromium.log"; exit 1; }
if grep -E "Uncaught|ERR_|Failed to load" "$out/chromium.log"; then
  echo "the page logged errors (above)"; exit 1
fi
python3 - "$PWD/docs/report-screenshot.png" <<'PY'
import struct, sys
png = open(sys.argv[1], "rb").read()
assert png[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
w, h = struct.unpack(">II", png[16:24])
print(f"screenshot {w}x{h} -> {sys.argv[1]}")
PY
