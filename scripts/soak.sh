#!/usr/bin/env bash
# The test suite RUNS times in a row with a busy loop pinned to one core (taskset when present):
# proof that no test depends on the machine's speed. Usage: scripts/soak.sh [RUNS] [PYTHON]
set -euo pipefail
cd "$(dirname "$0")/.."
runs=${1:-3}
py=${2:-.venv/bin/python}
pin=()
command -v taskset >/dev/null 2>&1 && pin=(taskset -c 0)
"${pin[@]}" bash -c 'while :; do :; done' &
hog=$!
trap 'kill "$hog" 2>/dev/null || true' EXIT
bash scripts/ensure_ci_tools.sh
for i in $(seq 1 "$runs"); do
  echo "== soak: run $i of $runs ($("$py" --version 2>&1)), CPU hog on one core =="
  start=$(date +%s)
  "$py" -m pytest
  echo "== soak: run $i passed in $(( $(date +%s) - start )) s =="
done
echo "== soak: $runs of $runs runs passed with a CPU hog =="
