#!/usr/bin/env bash
# 10-minute soak (issue 16): the default launch (camera QoS, verification) on a model, a bag looped at
# 5x with best-effort sensor QoS; RSS of each node every 30 s, then every node's counters.
# Usage: scripts/soak.sh MODEL_DIR BAG OUT_DIR [SECONDS]   (venv: $AEFABMAP_VENV, default .venv)
set -u
ROOT=$(cd "$(dirname "$0")/.." && pwd)
V=${AEFABMAP_VENV:-$ROOT/.venv}/bin
MODEL=$1; BAG=$2; OUT=$3; DURATION=${4:-600}
rm -rf "$OUT"; mkdir -p "$OUT"
# A domain of its own, so another run on this machine neither feeds nor steals these nodes' messages.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$((1 + $$ % 100))}
"$V/aefabmap_launch" --model "$MODEL" --map "$OUT/map.npz" > "$OUT/nodes.log" 2>&1 &
LP=$!
for _ in $(seq 1 180); do
  grep -q "fabmap_node]: receiving words" "$OUT/nodes.log" && grep -q "verifier_node]: receiving features" "$OUT/nodes.log" && break
  sleep 1
done
"$V/aefabmap_replay" "$BAG" --topic /image --rate 5 --loop --qos sensor_data --quiet > "$OUT/replay.log" 2>&1 &
RP=$!
for t in $(seq 0 30 "$DURATION"); do
  line="t=${t}s"
  for n in feature_node quantizer_node fabmap_node verifier_node; do
    pid=$(pgrep -P "$LP" -f "aefabmap_ros.nodes.$n" | head -1)  # this launcher's children only
    rss=$(awk '/VmRSS/ {print int($2/1024)}' "/proc/$pid/status" 2>/dev/null)
    line="$line $n=${rss}MiB"
  done
  echo "$line" | tee -a "$OUT/rss.txt"
  [ "$t" -lt "$DURATION" ] && sleep 30
done
kill -INT $RP; wait $RP
kill -INT $LP; wait $LP; echo "launcher exit $?" | tee -a "$OUT/rss.txt"
grep -E "(feature|quantizer|fabmap|verifier)_node: " "$OUT/nodes.log" | tail -4 | tee -a "$OUT/rss.txt"
tail -3 "$OUT/replay.log" | tee -a "$OUT/rss.txt"
