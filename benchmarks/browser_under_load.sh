#!/usr/bin/env bash
# The browser suite N times in a row (default 5) beside two busy loops at nice 19, as issue 25 asks:
#   bash benchmarks/browser_under_load.sh [N]
# Prints one line per run (exit code, seconds, pytest's last line); the loops are stopped at the end.
set -u
cd "$(dirname "$0")/.."
PY=.venv/bin/python
N=${1:-5}
nice -n 19 $PY -c 'while True: pass' & L1=$!
nice -n 19 $PY -c 'while True: pass' & L2=$!
trap 'kill $L1 $L2 2>/dev/null' EXIT
for i in $(seq 1 "$N"); do
  s=$(date +%s)
  out=$(nice $PY -m pytest -q -m browser tests/viewer -rf -p no:cacheprovider 2>&1)
  rc=$?
  echo "run $i rc=$rc $(( $(date +%s) - s ))s $(echo "$out" | tail -1)"
  [ $rc -eq 0 ] || echo "$out" | grep -E "^FAILED|^ERROR"
done
