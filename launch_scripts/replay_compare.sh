#!/usr/bin/env bash
# Replay a ULog through the whole graph: recorder, metrics, twin, replay (each its own process).
#
#   launch_scripts/replay_compare.sh FLIGHT.ulg [PARAMS.yaml] [MODE] [RATE]
#
# PARAMS defaults to the log's SYS_AUTOSTART choice (as `rotortwin compare`), MODE closed|open
# (default closed), RATE 0 = as fast as the nodes keep up (default), 1 = real time, 20 = 20x.
# Writes under ROTORTWIN_RUN_DIR (default /tmp/rotortwin_run): NAME.log, NAME.pid, bag/ (MCAP),
# final_metrics.json, aligned.npz. Waits for the replay and the final metrics, prints the
# Table-2 summary and stops the nodes (stop_all.sh). While it runs, in another terminal:
#   ROS_DOMAIN_ID=$(cat /tmp/rotortwin_run/domain_id) .venv/bin/rotortwin monitor
# Ctrl-C stops everything it started.
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY="${ROTORTWIN_PYTHON:-$REPO/.venv/bin/python}"
HERE="$REPO/launch_scripts"
export ROTORTWIN_RUN_DIR="${ROTORTWIN_RUN_DIR:-/tmp/rotortwin_run}"
RUN_DIR="$ROTORTWIN_RUN_DIR"

usage() { sed -n '2,13p' "$0" | sed 's/^# \{0,1\}//'; exit "${1:-0}"; }
[ $# -ge 1 ] || usage 2
case "$1" in -h|--help) usage 0 ;; esac
FLIGHT="$(realpath "$1")"
PARAMS="${2:-}"
MODE="${3:-closed}"
RATE="${4:-0}"
[ -f "$FLIGHT" ] || { echo "replay_compare.sh: $FLIGHT: not found" >&2; exit 2; }

cd "$REPO"
PARAMS="$("$PY" -c 'import sys; from twin_nodes.graph import default_params_for as d; print(d(sys.argv[1], sys.argv[2] or None))' "$FLIGHT" "$PARAMS")" \
    || exit 2
PARAMS="$(realpath "$PARAMS")"
NMOT="$("$PY" -c 'import sys; from twin_nodes.vehicle.params import load_params; print(load_params(sys.argv[1]).rotors.count)' "$PARAMS")"

mkdir -p "$RUN_DIR"
rm -rf "$RUN_DIR/bag" "$RUN_DIR/final_metrics.json" "$RUN_DIR/aligned.npz" "$RUN_DIR/replay_stats.json"
if [ -z "${ROS_DOMAIN_ID:-}" ]; then
    export ROS_DOMAIN_ID=$(( (RANDOM % 200) + 1 ))
fi
echo "$ROS_DOMAIN_ID" > "$RUN_DIR/domain_id"
trap '"$HERE/stop_all.sh" "$RUN_DIR" >/dev/null' INT TERM

"$HERE/run_node.sh" recorder_node -p "out:=$RUN_DIR/bag"
"$HERE/run_node.sh" metrics_node -p "n_motors:=$NMOT" -p "mode:=$MODE" \
    -p "json_out:=$RUN_DIR/final_metrics.json" -p "aligned_out:=$RUN_DIR/aligned.npz"
"$HERE/run_node.sh" twin_node -p "params_file:=$PARAMS" -p "mode:=$MODE"
"$HERE/run_node.sh" ulog_replay -p "ulog:=$FLIGHT" -p "rate:=$RATE" \
    -p "wait_for:=['twin','metrics','recorder']" -p "stats_file:=$RUN_DIR/replay_stats.json"

echo "replaying $(basename "$FLIGHT") with $(basename "$PARAMS") ($MODE loop, rate $RATE) ..."
REPLAY_PID="$(cat "$RUN_DIR/ulog_replay.pid")"
while kill -0 "$REPLAY_PID" 2>/dev/null; do sleep 0.5; done
if [ -f "$RUN_DIR/replay_stats.json" ]; then  # written only by a replay that finished
    METRICS_PID="$(cat "$RUN_DIR/metrics.pid")"
    for _ in $(seq 1 600); do
        [ -f "$RUN_DIR/final_metrics.json" ] && break
        kill -0 "$METRICS_PID" 2>/dev/null || break
        sleep 0.2
    done
fi
sleep 0.5
"$HERE/stop_all.sh" "$RUN_DIR"
if [ ! -f "$RUN_DIR/final_metrics.json" ]; then
    echo "replay_compare.sh: no final metrics; see $RUN_DIR/*.log" >&2
    tail -n 5 "$RUN_DIR"/*.log >&2
    exit 1
fi
"$PY" -c 'import json, sys; from twin_nodes.twin.metrics import table2; print(table2(json.load(open(sys.argv[1]))))' \
    "$RUN_DIR/final_metrics.json"
echo "bag: $RUN_DIR/bag   metrics: $RUN_DIR/final_metrics.json   logs: $RUN_DIR/*.log"
