#!/usr/bin/env bash
# Fly PX4 SITL against the rotortwin simulator link (lockstep HIL over TCP 4560 + instance).
#
#   launch_scripts/px4_sitl_twin.sh [--px4 DIR] [--params P.yaml] [--instance N] [--speed-factor F]
#                                   [--mission PLAN.yaml] [--no-ros]
#
# 1. starts `rotortwin bridge sim` (the TCP server PX4's simulator_mavlink connects to);
# 2. with --px4 DIR (a PX4-Autopilot checkout built with `make px4_sitl_default`), starts
#    PX4 SITL as airframe 10016 none_iris, which runs `simulator_mavlink start -c 4560+N`
#    (ROMFS/px4fmu_common/init.d-posix/px4-rc.simulator); without --px4, start PX4 yourself,
#    e.g. `make px4_sitl none_iris` in the PX4 tree;
# 3. with --mission, waits for PX4 on UDP 14540+N, uploads the plan and starts it (MAVSDK).
# Ctrl-C stops what this script started (by process id).
#
# NOT RUN against real PX4 on the machine this was written on (no PX4 build there): the
# bridge, the mission tool and the MAVLink exchange were tested against scripted/fake peers
# only. See docs/px4_sitl.md.
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
ROTORTWIN="${ROTORTWIN:-$REPO/.venv/bin/rotortwin}"
PX4_DIR=""
PARAMS=""
INSTANCE=0
SPEED="${PX4_SIM_SPEED_FACTOR:-1}"
MISSION=""
ROS_FLAG=""

usage() { sed -n '2,20p' "$0" | sed 's/^# \{0,1\}//'; exit "${1:-0}"; }

while [ $# -gt 0 ]; do
    case "$1" in
        --px4) PX4_DIR="$2"; shift 2 ;;
        --params) PARAMS="$2"; shift 2 ;;
        --instance) INSTANCE="$2"; shift 2 ;;
        --speed-factor) SPEED="$2"; shift 2 ;;
        --mission) MISSION="$2"; shift 2 ;;
        --no-ros) ROS_FLAG="--no-ros"; shift ;;
        -h|--help) usage 0 ;;
        *) echo "px4_sitl_twin.sh: unknown argument $1" >&2; usage 2 ;;
    esac
done

SIM_PORT=$((4560 + INSTANCE))
API_PORT=$((14540 + INSTANCE))
PIDS=()
cleanup() {
    for pid in "${PIDS[@]}"; do
        kill -TERM "$pid" 2>/dev/null || true  # background jobs of a script ignore SIGINT
    done
    for pid in "${PIDS[@]}"; do
        wait "$pid" 2>/dev/null || true
    done
}
trap cleanup EXIT INT TERM

BRIDGE_ARGS=(bridge sim --port "$SIM_PORT" --speed-factor "$SPEED")
[ -n "$PARAMS" ] && BRIDGE_ARGS+=(--params "$PARAMS")
[ -n "$ROS_FLAG" ] && BRIDGE_ARGS+=("$ROS_FLAG")
echo "[px4_sitl_twin] rotortwin ${BRIDGE_ARGS[*]}"
"$ROTORTWIN" "${BRIDGE_ARGS[@]}" &
PIDS+=($!)

if [ -n "$PX4_DIR" ]; then
    PX4_BIN="$PX4_DIR/build/px4_sitl_default/bin/px4"
    if [ ! -x "$PX4_BIN" ]; then
        echo "[px4_sitl_twin] $PX4_BIN not found: build PX4 first (make px4_sitl_default)" >&2
        exit 1
    fi
    echo "[px4_sitl_twin] PX4 SITL instance $INSTANCE, airframe 10016 none_iris, simulator TCP $SIM_PORT"
    (
        cd "$PX4_DIR"
        PX4_SYS_AUTOSTART=10016 PX4_SIM_MODEL=none_iris PX4_SIM_SPEED_FACTOR="$SPEED" \
            exec "$PX4_BIN" -i "$INSTANCE"
    ) &
    PIDS+=($!)
fi

if [ -n "$MISSION" ]; then
    echo "[px4_sitl_twin] waiting for PX4 on udpin://0.0.0.0:$API_PORT to upload $MISSION"
    until "$ROTORTWIN" mission upload "$MISSION" --url "udpin://0.0.0.0:$API_PORT" --timeout 30; do
        sleep 5
    done
    # PX4 refuses to arm until the EKF has converged (GPS fix, mag and baro checks pass)
    until "$ROTORTWIN" mission start --url "udpin://0.0.0.0:$API_PORT" --timeout 30; do
        sleep 5
    done
fi

wait "${PIDS[0]}"
