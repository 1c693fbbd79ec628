#!/usr/bin/env bash
# The main job on a shipped flight: the twin beside the flight through the ROS 2 node graph
# (Table-2 metrics, MCAP, report), then missing-physics discovery on the same flight.
# usage: launch_scripts/demo.sh FLIGHT.ulg PARAMS.yaml OUTDIR
set -euo pipefail
cd "$(dirname "$0")/.."
FLIGHT=${1:-bags/sim_quadx_weak_motor3.ulg}
PARAMS=${2:-params/px4_sih_quadx.yaml}
OUT=${3:-out/demo}
BIN=${BIN:-.venv/bin}
mkdir -p "$OUT"
# --force: a second `make demo` replaces the demo's own outputs (rotortwin refuses to replace files without it)
echo "== twin vs flight through the node graph (replay -> twin -> metrics -> recorder)"
"$BIN/rotortwin" compare "$FLIGHT" --params "$PARAMS" --mode closed \
    --json "$OUT/compare.json" --mcap "$OUT/graph" --report "$OUT/compare_report" --force
echo "== missing-physics discovery"
"$BIN/rotortwin" discover "$FLIGHT" --params "$PARAMS" --json "$OUT/discover.json" \
    --report "$OUT/discover_report" --out-params "$OUT/refitted_params.yaml" --force
echo "== outputs in $OUT"
# the finding in one line, read from the discover JSON (any 'rotortwin discover --json' result works)
"$BIN/rotortwin" finding "$OUT/discover.json"
