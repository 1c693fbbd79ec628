#!/usr/bin/env bash
# The SIH fleet proofs of issue 25 (missions/sih_effects/manifest.yaml) on flights already flown into a cache:
#   tools/sih_fleet_run.sh OUT [CACHE]     (CACHE default ~/.cache/rotortwin/sih_fleet, one folder per flight)
# Per fleet (p01-p18 on the patched SIH, s01-s32): `params from-ulog` on its unchanged first flights, `fleet discover
# --no-closed-loop` on all of them against that twin, `fleet report`, then tools/sih_fleet_proof.py; its lines end up
# in OUT/proof_<p|s>.txt. Fly the flights first with launch_scripts/fly_sih.sh --flight p01 ... s32 (docs/fleet.md).
set -u
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY="${ROTORTWIN_PYTHON:-$REPO/.venv/bin/python}"
E="${1:?OUT dir}"; F="${2:-$HOME/.cache/rotortwin/sih_fleet}"
mkdir -p "$E"; cd "$REPO"
export ROTORTWIN_DISCOVER_WORKERS=1
rc=0
for P in ${PREFIXES:-p s}; do
  case $P in p) FIRST="01 02 03 04 05"; ALL=$(seq -f "%02g" 1 18);; s) FIRST="01 02 03 04 05 06"; ALL=$(seq -f "%02g" 1 32);; esac
  "$PY" -m twin_nodes params from-ulog $(for i in $FIRST; do echo "$F/$P$i/flight.ulg"; done) --out "$E/twin_$P.yaml" > "$E/twin_$P.log" 2>&1 || { echo "twin $P failed: $E/twin_$P.log"; exit 2; }
  rm -rf "$E/cat_$P"
  "$PY" -m twin_nodes fleet discover $(for i in $ALL; do echo "$F/$P$i/flight.ulg"; done) --params "$E/twin_$P.yaml" \
    --no-closed-loop --workers 1 --catalog "$E/cat_$P" > "$E/fleet_$P.log" 2>&1 || { echo "fleet discover $P failed: $E/fleet_$P.log"; exit 2; }
  "$PY" -m twin_nodes fleet report "$E/cat_$P" --out "$E/report_$P" > "$E/report_$P.log" 2>&1 || { echo "fleet report $P failed"; exit 2; }
  "$PY" tools/sih_fleet_proof.py "$E/report_$P/report.json" --prefix $P > "$E/proof_$P.txt"; r=$?
  tail -1 "$E/proof_$P.txt"; [ $r -eq 0 ] || rc=1
done
exit $rc
