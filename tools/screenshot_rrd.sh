#!/usr/bin/env bash
# Render a .rrd in the real Rerun viewer, headless, and save what a person would see as a PNG.
#
#   tools/screenshot_rrd.sh IN.rrd OUT.png [WIDTHxHEIGHT]      (default 1600x900)
#
# The viewer loads the recording with its default blueprint, draws the end of the timeline and quits.
# It renders on the CPU (Mesa llvmpipe through Vulkan) under a virtual X server; needs
#   apt-get install -y xvfb mesa-vulkan-drivers libvulkan1
# The viewer renders at 2x (3200x1800 for 1600x900, ~2.7 MB); the PNG is downscaled to the window size
# (~0.5 MB) with the repo's Python + OpenCV unless SCREENSHOT_FULL_RES=1.
# Environment: RERUN (viewer binary; default .venv/bin/rerun, else rerun on PATH),
#              PYTHON (default .venv/bin/python), SCREENSHOT_TIMEOUT_S (default 180), SCREENSHOT_FULL_RES.
set -euo pipefail

usage() { echo "usage: $0 IN.rrd OUT.png [WIDTHxHEIGHT]" >&2; exit 2; }
[[ $# -ge 2 && $# -le 3 ]] || usage
in_rrd=$1
out_png=$2
size=${3:-1600x900}
[[ -f $in_rrd ]] || { echo "error: $in_rrd does not exist (write one with --rerun save)" >&2; exit 2; }
[[ $size =~ ^[0-9]+x[0-9]+$ ]] || { echo "error: size must look like 1600x900, got $size" >&2; exit 2; }
[[ $out_png == *.png ]] || { echo "error: OUT must end in .png, got $out_png" >&2; exit 2; }

repo_root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
rerun_bin=${RERUN:-}
if [[ -z $rerun_bin ]]; then
  if [[ -x $repo_root/.venv/bin/rerun ]]; then rerun_bin=$repo_root/.venv/bin/rerun
  else rerun_bin=$(command -v rerun || true); fi
fi
[[ -n $rerun_bin && -x $rerun_bin ]] || { echo "error: no rerun viewer found (pip install rerun-sdk, or set RERUN=)" >&2; exit 2; }
command -v xvfb-run >/dev/null || {
  echo "error: xvfb-run not found: apt-get install -y xvfb mesa-vulkan-drivers libvulkan1" >&2; exit 2; }

verify_log=$(mktemp /tmp/screenshot_rrd_verify.XXXXXX.log)
if ! "$rerun_bin" rrd verify "$in_rrd" >"$verify_log" 2>&1; then
  echo "error: $in_rrd is not a readable Rerun recording (rerun rrd verify):" >&2
  tail -n 5 "$verify_log" >&2
  rm -f "$verify_log"
  exit 1
fi
rm -f "$verify_log"

width=${size%x*}
height=${size#*x}
mkdir -p "$(dirname "$out_png")"
out_abs=$(cd "$(dirname "$out_png")" && pwd)/$(basename "$out_png")
rm -f "$out_abs"
export XDG_RUNTIME_DIR=${XDG_RUNTIME_DIR:-$(mktemp -d /tmp/xdg-rerun.XXXXXX)}
mkdir -p "$XDG_RUNTIME_DIR" && chmod 700 "$XDG_RUNTIME_DIR"
log=$(mktemp /tmp/screenshot_rrd.XXXXXX.log)

# Screen a bit larger than the window so the window is never clipped.
status=0
timeout "${SCREENSHOT_TIMEOUT_S:-180}" xvfb-run -a -s "-screen 0 $((width + 64))x$((height + 64))x24" \
  "$rerun_bin" "$in_rrd" --window-size "$size" --screenshot-to "$out_abs" >"$log" 2>&1 || status=$?

if [[ ! -s $out_abs ]]; then
  echo "error: the viewer wrote no screenshot (exit $status); its output:" >&2
  tail -n 30 "$log" >&2
  exit 1
fi
rm -f "$log"

python_bin=${PYTHON:-$repo_root/.venv/bin/python}
if [[ ${SCREENSHOT_FULL_RES:-0} != 1 && -x $python_bin ]]; then
  "$python_bin" - "$out_abs" "$width" "$height" <<'PY'
import sys

import cv2

path, width, height = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
image = cv2.imread(path, cv2.IMREAD_UNCHANGED)
if image is not None and image.shape[1] > width:
    image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    cv2.imwrite(path, image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
PY
fi
echo "$out_abs"
