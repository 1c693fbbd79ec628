#!/usr/bin/env bash
# Fly PX4 SITL against the rotortwin simulator link (lockstep HIL over TCP 4560 + instance).
#
#   launch_scripts/px4_sitl_twin.sh [--px4 DIR] [--params P.yaml] [--instance N] [--speed-factor F]
#                                   [--px4-speed-factor G] [--mission PLAN.yaml] [--repeat K] [--live]
#                                   [--foxglove [PORT]] [--out DIR] [--exit-when-done] [--no-ros]
#
# 1. starts `rotortwin bridge sim` (the TCP server PX4's simulator_mavlink connects to);
# 2. with --px4 DIR (a PX4-Autopilot checkout built with `make px4_sitl_default`), starts
#    PX4 SITL as airframe 10016 none_iris, which runs `simulator_mavlink start -c 4560+N`
#    (ROMFS/px4fmu_common/init.d-posix/px4-rc.simulator), with the high-rate logging profile
#    (SDLOG_PROFILE 17 = default set + bit 4 high rate: actuator_motors, attitude, rates at
#    control rate instead of 10 Hz, for control-rate comparison) and SDLOG_MODE 0 (a log per
#    flight, arm to disarm; SITL's rcS default 1 logs only from boot to the first disarm); any
#    PX4_PARAM_<NAME>=value in the environment is set too. Without --px4, start PX4 yourself;
#    --speed-factor F paces the simulator (0 = unpaced, as fast as PX4 answers). PX4 gets
#    PX4_SIM_SPEED_FACTOR=G (--px4-speed-factor; default F, or 20 when F is 0): PX4's rcS scales
#    its link-loss timeouts by it and saves them (COM_DL_LOSS_T = 10 G, COM_RC_LOSS_T and
#    COM_OF_LOSS_T = 0.5 G, COM_OBC_LOSS_T = 5 G), so 0 would set them to 0 ("connection to ground
#    station lost" many times a second) -- it is never passed (docs/px4_sitl.md);
# 3. with --mission, waits for PX4 on UDP 14540+N (MAVSDK), uploads the plan, starts it and waits
#    until the vehicle has landed and disarmed; --repeat K flies it K times in a row (nothing
#    restarted: the upload sets the current item back to 0);
# 4. with --live, runs `rotortwin live` on PX4's ground-station link (UDP 14550+N): a second twin,
#    in open loop, beside PX4's estimate, on its own ROS domain (link-loss flag, totals at the end
#    in OUT/live.json); --foxglove [PORT] (default 8765) serves its view (real, twin, errors) to
#    Foxglove, or without --live the simulator's /twin topics (layout: layouts/rotortwin.json).
# Logs go to --out DIR (default /tmp/rotortwin_px4_sitl): bridge.log, px4.log, live.log, live.json.
# --exit-when-done stops everything once the mission(s) are flown (else Ctrl-C).
# Ctrl-C stops what this script started (by process id).
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
ROTORTWIN="${ROTORTWIN:-$REPO/.venv/bin/rotortwin}"
PX4_DIR=""
PARAMS=""
INSTANCE=0
SPEED="${PX4_SIM_SPEED_FACTOR:-1}"
PX4_SPEED=""
MISSION=""
REPEAT=1
LIVE=0
FOXGLOVE=""
OUT="${ROTORTWIN_PX4_OUT:-/tmp/rotortwin_px4_sitl}"
EXIT_WHEN_DONE=0
ROS_FLAG=""

usage() { sed -n '2,30p' "$0" | sed 's/^# \{0,1\}//'; exit "${1:-0}"; }

while [ $# -gt 0 ]; do
    case "$1" in
        --px4) PX4_DIR="$2"; shift 2 ;;
        --params) PARAMS="$2"; shift 2 ;;
        --instance) INSTANCE="$2"; shift 2 ;;
        --speed-factor) SPEED="$2"; shift 2 ;;
        --px4-speed-factor) PX4_SPEED="$2"; shift 2 ;;
        --mission) MISSION="$2"; shift 2 ;;
        --repeat) REPEAT="$2"; shift 2 ;;
        --live) LIVE=1; shift ;;
        --foxglove)
            if [ $# -gt 1 ] && [[ "$2" =~ ^[0-9]+$ ]]; then FOXGLOVE="$2"; shift 2; else FOXGLOVE=8765; shift; fi ;;
        --out) OUT="$2"; shift 2 ;;
        --exit-when-done) EXIT_WHEN_DONE=1; shift ;;
        --no-ros) ROS_FLAG="--no-ros"; shift ;;
        -h|--help) usage 0 ;;
        *) echo "px4_sitl_twin.sh: unknown argument $1" >&2; usage 2 ;;
    esac
done

is_number() { [[ "$1" =~ ^[0-9]+([.][0-9]+)?$|^[.][0-9]+$ ]]; }
is_positive() { is_number "$1" && awk -v x="$1" 'BEGIN { exit !(x > 0) }'; }
if ! is_number "$SPEED"; then
    echo "px4_sitl_twin.sh: --speed-factor: expected a number >= 0 (0 = unpaced), got '$SPEED'" >&2; exit 2
fi
# what PX4 is told: its rcS multiplies (and saves) its link-loss timeouts by PX4_SIM_SPEED_FACTOR,
# so never 0; unpaced lockstep ran 1-13x real time here (docs/px4_sitl.md §5): 20 covers it
if [ -z "$PX4_SPEED" ]; then
    if is_positive "$SPEED"; then PX4_SPEED="$SPEED"; else PX4_SPEED=20; fi
fi
if ! is_positive "$PX4_SPEED"; then
    echo "px4_sitl_twin.sh: --px4-speed-factor: expected a number > 0, got '$PX4_SPEED'" >&2; exit 2
fi

mkdir -p "$OUT"
SIM_PORT=$((4560 + INSTANCE))
API_PORT=$((14540 + INSTANCE))
GCS_PORT=$((14550 + INSTANCE))
PIDS=()
cleanup() {
    # SIGTERM (background jobs of a script ignore SIGINT); every rotortwin process stops cleanly on
    # it (the live twin prints and writes its totals); SIGKILL after 20 s
    for pid in "${PIDS[@]}"; do
        kill -TERM "$pid" 2>/dev/null || true
    done
    for pid in "${PIDS[@]}"; do
        for _ in $(seq 1 20); do kill -0 "$pid" 2>/dev/null || break; sleep 1; done
        kill -KILL "$pid" 2>/dev/null || true
        wait "$pid" 2>/dev/null || true
    done
}
trap cleanup EXIT
trap 'exit 130' INT TERM

BRIDGE_ARGS=(bridge sim --port "$SIM_PORT" --speed-factor "$SPEED")
[ -n "$PARAMS" ] && BRIDGE_ARGS+=(--params "$PARAMS")
[ -n "$ROS_FLAG" ] && BRIDGE_ARGS+=("$ROS_FLAG")
echo "[px4_sitl_twin] rotortwin ${BRIDGE_ARGS[*]} (log $OUT/bridge.log)"
"$ROTORTWIN" "${BRIDGE_ARGS[@]}" >"$OUT/bridge.log" 2>&1 &
PIDS+=($!)

if [ -n "$FOXGLOVE" ] && [ "$LIVE" = 0 ]; then
    echo "[px4_sitl_twin] Foxglove (the simulator's /twin topics) on ws://127.0.0.1:$FOXGLOVE"
    "$ROTORTWIN" live foxglove --port "$FOXGLOVE" >"$OUT/foxglove.log" 2>&1 &
    PIDS+=($!)
fi

if [ -n "$PX4_DIR" ]; then
    PX4_BIN="$PX4_DIR/build/px4_sitl_default/bin/px4"
    if [ ! -x "$PX4_BIN" ]; then
        echo "[px4_sitl_twin] $PX4_BIN not found: build PX4 first (make px4_sitl_default)" >&2
        exit 1
    fi
    echo "[px4_sitl_twin] PX4 SITL instance $INSTANCE, airframe 10016 none_iris, simulator TCP $SIM_PORT," \
         "PX4_SIM_SPEED_FACTOR $PX4_SPEED (link-loss timeouts x $PX4_SPEED)," \
         "SDLOG_PROFILE ${PX4_PARAM_SDLOG_PROFILE:-17} (log $OUT/px4.log)"
    (
        cd "$PX4_DIR"
        PX4_SYS_AUTOSTART=10016 PX4_SIM_MODEL=none_iris PX4_SIM_SPEED_FACTOR="$PX4_SPEED" \
            PX4_PARAM_SDLOG_PROFILE="${PX4_PARAM_SDLOG_PROFILE:-17}" \
            PX4_PARAM_SDLOG_MODE="${PX4_PARAM_SDLOG_MODE:-0}" \
            exec "$PX4_BIN" -i "$INSTANCE" -d
    ) >"$OUT/px4.log" 2>&1 &
    PIDS+=($!)
fi

if [ "$LIVE" = 1 ]; then
    LIVE_ARGS=(live --url "udpin:0.0.0.0:$GCS_PORT" --json "$OUT/live.json")
    [ -n "$PARAMS" ] && LIVE_ARGS+=(--params "$PARAMS")
    # its own ROS domain (its /twin is the open-loop twin, not the simulator): Foxglove serves that one
    [ -n "$FOXGLOVE" ] && LIVE_ARGS+=(--foxglove "$FOXGLOVE")
    echo "[px4_sitl_twin] rotortwin ${LIVE_ARGS[*]} (log $OUT/live.log)"
    "$ROTORTWIN" "${LIVE_ARGS[@]}" >"$OUT/live.log" 2>&1 &
    PIDS+=($!)
fi

if [ -n "$MISSION" ]; then
    for k in $(seq 1 "$REPEAT"); do
        echo "[px4_sitl_twin] mission $k/$REPEAT: waiting for PX4 on udpin://0.0.0.0:$API_PORT to upload $MISSION"
        until "$ROTORTWIN" mission upload "$MISSION" --url "udpin://0.0.0.0:$API_PORT" --timeout 30; do
            sleep 5
        done
        # PX4 refuses to arm until the EKF has converged (GPS fix, mag and baro checks pass)
        until "$ROTORTWIN" mission start --url "udpin://0.0.0.0:$API_PORT" --timeout 30; do
            sleep 5
        done
        "$ROTORTWIN" mission wait --url "udpin://0.0.0.0:$API_PORT" --timeout 900
        echo "[px4_sitl_twin] mission $k/$REPEAT flown"
        sleep 5  # PX4 writes the log and settles before the next upload
    done
    if [ "$EXIT_WHEN_DONE" = 1 ]; then
        echo "[px4_sitl_twin] done: logs in $OUT"
        exit 0
    fi
fi

wait "${PIDS[0]}"
