#!/usr/bin/env bash
# Fly issue 26's declared grids into a cache outside the repository, one flight at a time, nice'd.
#   tools/fly_grids.sh rotorpy [tuning|judging|judgeN|all]          -> ~/.cache/rotortwin/grids/rotorpy/<id>.ulg
#   tools/fly_grids.sh sih PX4_DIR [tuning|judging|judgeN|all]      -> ~/.cache/rotortwin/grids/sih/<id>/flight.ulg
# (PX4 SIH on instance 1, speed factor 5, lockstep; flights already there are skipped.)
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY="${ROTORTWIN_PYTHON:-$REPO/.venv/bin/python}"
CACHE="${ROTORTWIN_GRIDS:-$HOME/.cache/rotortwin/grids}"
cd "$REPO"
case "${1:-}" in
  rotorpy)
    exec nice -n 10 "$PY" -m twin_nodes.prove.grid_rotorpy fly --cache "$CACHE/rotorpy" --half "${2:-all}" ;;
  sih)
    PX4="${2:?PX4 dir}"; HALF="${3:-all}"
    MANIFEST=$("$PY" -c "
from twin_nodes.prove.grid_sih import BATCHES, GRID_PATH, REPO
print((BATCHES['$HALF'][1] if '$HALF' in BATCHES else GRID_PATH).relative_to(REPO))")
    IDS=$("$PY" -c "
from twin_nodes.prove.grid_sih import load_grid
print(' '.join(k for k, v in load_grid(half='$HALF').items() if '$HALF' in ('all', v['half'])))")
    for id in $IDS; do
      nice -n 10 "$PY" -m twin_nodes.mavlink.sih_flight --px4 "$PX4" --manifest "$MANIFEST" \
        --out "$CACHE/sih" --instance 1 --skip-existing --flight "$id" || echo "$id: NOT FLOWN (exit $?)" >&2
    done ;;
  *) sed -n '2,5p' "$0"; exit 2 ;;
esac
