#!/usr/bin/env bash
# The main job on a fresh machine: set everything up (idempotent), then run aefabmap_demo:
# sample bags -> vocabularies + Chow-Liu trees -> ROS nodes on the test bag -> evaluation table.
# Extra arguments go to aefabmap_demo (e.g. --quick, --skip-ros, --out DIR).
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
bash "$ROOT/scripts/setup.sh"
export ROS_AUTOMATIC_DISCOVERY_RANGE=${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}
# The checkout's folders; a --out / --bags of the caller's comes later on the line and wins.
exec "${AEFABMAP_VENV:-$ROOT/.venv}/bin/aefabmap_demo" --out "$ROOT/output/demo" --bags "$ROOT/bags/generated" "$@"
