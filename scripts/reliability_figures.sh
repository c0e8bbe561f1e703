#!/usr/bin/env bash
# The reliability figures, from the tests that check them: malformed messages of every subscribed type per node
# (tried / counted by name / counted under another name / silently accepted / fatal), bad inputs tried /
# survived per node and per offline tool, faults injected (kill -9 mid-save, SIGTERM while busy, disk full
# during save, corrupt map and store files) / places lost, and the drops the nodes counted. Runs the tests
# marked `reliability` (about 10 min), prints the tables, writes them as JSON and as docs/reliability_figures.md.
# Usage: scripts/reliability_figures.sh [OUT.json] [DOC.md]   (venv: $AEFABMAP_VENV, default .venv)
# The 10-minute memory soak is separate: scripts/soak.sh.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT"
VENV=${AEFABMAP_VENV:-$ROOT/.venv}
OUT=${1:-reliability_figures.json}
DOC=${2:-docs/reliability_figures.md}
export RELIABILITY_COMMAND="scripts/reliability_figures.sh"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$((1 + $$ % 100))}
exec "$VENV/bin/pytest" -p no:cacheprovider -q -m reliability test --reliability-report "$OUT" \
  --reliability-markdown "$DOC"
