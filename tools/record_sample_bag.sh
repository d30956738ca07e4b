#!/usr/bin/env bash
# Record bags/stair_scan: a short stair-block scan through the real graph on the simulator.
#
# The reconstructor runs with the SIMULATOR'S TRUE PARAMETERS (labelled as such in the
# calibration file): this sample shows the data flow, it is not an accuracy result.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-bags/stair_scan}
PY=.venv/bin/python
TMP=$(mktemp -d)
trap 'kill -INT $GRAPH $REC 2>/dev/null || true; wait 2>/dev/null || true; rm -rf "$TMP"' EXIT
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$((RANDOM % 100 + 101))} ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
$PY - "$TMP/truth.yaml" <<'PYEOF'
import sys
from galvoscan.simulated_rig import truth_calibration
from galvoscan_sim import load_rig
from reconstructor import calibration_file
calibration_file.save(truth_calibration(load_rig('reference')), sys.argv[1])
PYEOF
cat > "$TMP/params.yaml" <<YAML
galvo_driver: {ros__parameters: {backend: sim, rig: reference, scene: stair_block, seed: 1}}
reconstructor: {ros__parameters: {calibration_file: $TMP/truth.yaml}}
YAML
.venv/bin/galvoscan run --one-process --params "$TMP/params.yaml" & GRAPH=$!
sleep 8
rm -rf "$OUT"
.venv/bin/galvoscan record -o "$OUT" camera/image_raw camera/camera_info galvo/state \
    stripe/centers points & REC=$!
sleep 3
.venv/bin/galvoscan scan --pattern raster --g1-pan 0 0 --g1-tilt -0.3 0.3 \
    --g2-tilt -0.2 0.4 --steps-tilt 12 --rate 50
sleep 2
kill -INT $REC; wait $REC || true
kill -INT $GRAPH; wait $GRAPH || true
du -sh "$OUT"
