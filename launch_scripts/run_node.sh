#!/usr/bin/env bash
# Start one rotortwin node in the background, with a pid file and a log under the run dir.
#
#   launch_scripts/run_node.sh NAME [ROS ARGS...]
#
# NAME: ulog_replay | twin_node | metrics_node | recorder_node (or replay | twin | metrics | recorder).
# The remaining arguments go after `--ros-args`, e.g.
#   launch_scripts/run_node.sh twin -p params_file:=params/px4_sih_quadx.yaml -p mode:=closed
# Environment: ROTORTWIN_RUN_DIR (default /tmp/rotortwin_run; pid files NAME.pid, logs NAME.log),
# ROS_DOMAIN_ID (default: the one in RUN_DIR/domain_id, else a random 1..200 written there),
# ROS_AUTOMATIC_DISCOVERY_RANGE (default LOCALHOST). Stop everything with stop_all.sh.
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY="${ROTORTWIN_PYTHON:-$REPO/.venv/bin/python}"
RUN_DIR="${ROTORTWIN_RUN_DIR:-/tmp/rotortwin_run}"

usage() { sed -n '2,11p' "$0" | sed 's/^# \{0,1\}//'; exit "${1:-0}"; }
[ $# -ge 1 ] || usage 2
case "$1" in -h|--help) usage 0 ;; esac

NAME="$1"; shift
case "$NAME" in
    replay|ulog_replay) MODULE=ulog_replay; NODE=ulog_replay ;;
    twin|twin_node) MODULE=twin_node; NODE=twin ;;
    metrics|metrics_node) MODULE=metrics_node; NODE=metrics ;;
    recorder|recorder_node|record) MODULE=recorder_node; NODE=recorder ;;
    *) echo "run_node.sh: unknown node '$NAME' (ulog_replay, twin_node, metrics_node, recorder_node)" >&2; exit 2 ;;
esac

mkdir -p "$RUN_DIR"
if [ -z "${ROS_DOMAIN_ID:-}" ]; then
    if [ -f "$RUN_DIR/domain_id" ]; then
        ROS_DOMAIN_ID="$(cat "$RUN_DIR/domain_id")"
    else
        ROS_DOMAIN_ID=$(( (RANDOM % 200) + 1 ))
        echo "$ROS_DOMAIN_ID" > "$RUN_DIR/domain_id"
    fi
fi
export ROS_DOMAIN_ID
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export PYTHONUNBUFFERED=1

if [ -f "$RUN_DIR/$NODE.pid" ] && kill -0 "$(cat "$RUN_DIR/$NODE.pid")" 2>/dev/null; then
    echo "run_node.sh: $NODE already running (pid $(cat "$RUN_DIR/$NODE.pid")); stop_all.sh first" >&2
    exit 1
fi
cd "$REPO"
# setsid: the node gets its own session, so a Ctrl-C in this terminal does not reach it;
# stop_all.sh sends it SIGINT by pid (the recorder finalises its bag on SIGINT).
setsid "$PY" -m "twin_nodes.nodes.$MODULE" --ros-args -r "__node:=$NODE" "$@" \
    > "$RUN_DIR/$NODE.log" 2>&1 < /dev/null &
echo $! > "$RUN_DIR/$NODE.pid"
echo "$NODE: pid $!, ROS_DOMAIN_ID $ROS_DOMAIN_ID, log $RUN_DIR/$NODE.log"
