#!/usr/bin/env bash
# Stop every node started by run_node.sh / replay_compare.sh, cleanly.
#
#   launch_scripts/stop_all.sh [RUN_DIR]
#
# Sends SIGINT to each pid in RUN_DIR/*.pid (default $ROTORTWIN_RUN_DIR or /tmp/rotortwin_run):
# the recorder drains its queues and finalises the bag, the others exit. A process still alive
# after 10 s gets SIGTERM, after 5 more SIGKILL (a killed recorder's bag: `rotortwin record recover`).
# Only the recorded pids are signalled, never processes found by name.
set -uo pipefail

RUN_DIR="${1:-${ROTORTWIN_RUN_DIR:-/tmp/rotortwin_run}}"
shopt -s nullglob
pids=()
for f in "$RUN_DIR"/*.pid; do
    pid="$(cat "$f")"
    if kill -0 "$pid" 2>/dev/null; then
        kill -INT "$pid" && pids+=("$pid:$f") && echo "SIGINT -> $(basename "$f" .pid) (pid $pid)"
    else
        rm -f "$f"
    fi
done
[ ${#pids[@]} -gt 0 ] || { echo "stop_all.sh: nothing running under $RUN_DIR"; exit 0; }

wait_gone() {  # wait_gone SECONDS: wait until every pid has exited
    local until=$(( $(date +%s) + $1 ))
    while [ "$(date +%s)" -lt "$until" ]; do
        local alive=0
        for pf in "${pids[@]}"; do kill -0 "${pf%%:*}" 2>/dev/null && alive=1; done
        [ $alive -eq 0 ] && return 0
        sleep 0.2
    done
    return 1
}

if ! wait_gone 10; then
    for pf in "${pids[@]}"; do kill -0 "${pf%%:*}" 2>/dev/null && kill -TERM "${pf%%:*}"; done
    if ! wait_gone 5; then
        for pf in "${pids[@]}"; do
            kill -0 "${pf%%:*}" 2>/dev/null && kill -KILL "${pf%%:*}" && echo "SIGKILL -> pid ${pf%%:*}"
        done
    fi
fi
for pf in "${pids[@]}"; do rm -f "${pf#*:}"; done
echo "stopped; logs in $RUN_DIR"
