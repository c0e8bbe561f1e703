#!/usr/bin/env bash
# The test command: sets everything up if needed (idempotent), then ruff, mypy and pytest.
# Extra arguments go to pytest, e.g. `scripts/test.sh -k fabmap -x`.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT"

bash scripts/setup.sh
VENV=${AEFABMAP_VENV:-$ROOT/.venv}

echo "[test] ruff"
"$VENV/bin/ruff" check .
echo "[test] mypy"
"$VENV/bin/mypy"
echo "[test] pytest (the 15 slowest tests are listed at the end)"
# Isolate ROS traffic: loopback discovery only, a domain of this run's own.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$((1 + $$ % 100))}
exec "$VENV/bin/pytest" -p no:cacheprovider --durations=15 "$@"
