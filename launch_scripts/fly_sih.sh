#!/usr/bin/env bash
# Fly PX4 SIH (real PX4 firmware, its built-in simulator) with SIH parameters changed, as
# missions/sih_effects/manifest.yaml describes, and keep each flight as a prove flight:
# <out>/<id>/{flight.ulg (SIH_* scrubbed), truth.json, MANIFEST.md, px4.log}.
#
#   launch_scripts/fly_sih.sh --px4 DIR --out DIR --flight e09 e10 ...          # manifest flights
#   launch_scripts/fly_sih.sh --px4 DIR --out DIR --id e20 --mission M3 --sih SIH_Q_MAX=0.16
#   launch_scripts/fly_sih.sh --px4 DIR --out DIR --id c1 --mission my.plan.yaml  # no SIH change
#
# DIR: a PX4-Autopilot tree built with `make px4_sitl_default` (default $PX4_DIR). One flight at a
# time (instance 0: MAVLink UDP 14540). `rotortwin prove --source px4sih --sih-dir DIR` scores them.
# Options: --manifest M, --speed-factor F (default the manifest's 5), --instance N, --skip-existing,
# --logging P (a logging profile of the manifest's px4.logging.profiles, e.g. highrate: motors, rates,
# torque/thrust setpoints and sensor_combined every 4 ms; default: a flight's own logging:, else the list).
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY="${ROTORTWIN_PYTHON:-$REPO/.venv/bin/python}"
case "${1:-}" in -h|--help) sed -n '2,14p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;; esac
cd "$REPO"
exec "$PY" -m twin_nodes.mavlink.sih_flight "$@"
