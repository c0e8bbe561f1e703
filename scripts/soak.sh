#!/usr/bin/env bash
# Soak: the default launch (camera QoS, verification) plus the example backend (--backend) on a
# model, fed an RGB-D bag -- images with their depth, camera_info and odometry -- looped with best-effort
# sensor QoS at RATE times its speed (the demo's test bag is 10 Hz: RATE 5 = 50 Hz). Every 30 s the RSS of
# each node; at the end every node's counters, and the closures the verifier accepted against those the
# backend took (added) or refused.
# Usage: scripts/soak.sh MODEL_DIR BAG OUT_DIR [SECONDS] [RATE]   (venv: $AEFABMAP_VENV, default .venv)
#   scripts/soak.sh output/demo/models/autoencoder bags/generated/test/bag /tmp/soak 600 5
# The bag needs /image, /depth, /camera_info and /odom (aefabmap_synth writes them).
set -u
ROOT=$(cd "$(dirname "$0")/.." && pwd)
V=${AEFABMAP_VENV:-$ROOT/.venv}/bin
MODEL=$1; BAG=$2; OUT=$3; DURATION=${4:-600}; RATE=${5:-5}
NODES="feature_node quantizer_node fabmap_node verifier_node pose_graph_node"
rm -rf "$OUT"; mkdir -p "$OUT"
# A domain of its own, so another run on this machine neither feeds nor steals these nodes' messages.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$((1 + $$ % 100))}
# A 640x480 depth image is 600 KB: over Fast DDS's default 512 KB shared-memory segment, best-effort samples
# go out as UDP fragments and are mostly lost. The package's profile gives shared memory room for them.
export FASTRTPS_DEFAULT_PROFILES_FILE=${FASTRTPS_DEFAULT_PROFILES_FILE:-$ROOT/aefabmap_ros/config/fastdds_large_messages.xml}
"$V/aefabmap_launch" --model "$MODEL" --map "$OUT/map.npz" --backend --depth-topic /depth \
  --camera-info-topic /camera_info --odom-topic /odom > "$OUT/nodes.log" 2>&1 &
LP=$!
for _ in $(seq 1 240); do
  grep -q "fabmap_node]: receiving words" "$OUT/nodes.log" && grep -q "verifier_node]: receiving features" "$OUT/nodes.log" && break
  kill -0 $LP 2>/dev/null || { echo "ERROR: the launch ended at start-up (see $OUT/nodes.log)" >&2; exit 1; }
  sleep 1
done
"$V/aefabmap_replay" "$BAG" --topic /image --rate "$RATE" --loop --qos sensor_data \
  --with /depth --with /camera_info --with /odom --quiet > "$OUT/replay.log" 2>&1 &
RP=$!
for t in $(seq 0 30 "$DURATION"); do
  line="t=${t}s"
  for n in $NODES; do
    pid=$(pgrep -P "$LP" -f "aefabmap_ros.nodes.$n" | head -1)  # this launcher's children only
    rss=$(awk '/VmRSS/ {print int($2/1024)}' "/proc/$pid/status" 2>/dev/null)
    line="$line $n=${rss:-gone}MiB"
  done
  echo "$line" | tee -a "$OUT/rss.txt"
  [ "$t" -lt "$DURATION" ] && sleep 30
done
kill -INT $RP; wait $RP
kill -INT $LP; wait $LP; echo "launcher exit $?" | tee -a "$OUT/rss.txt"
for n in $NODES; do grep -E "\[$n\]: $n: " "$OUT/nodes.log" | tail -1 | sed 's/^.*\]: //' | tee -a "$OUT/rss.txt"; done
tail -3 "$OUT/replay.log" | tee -a "$OUT/rss.txt"
# The closures: accepted by the verifier (geometry, or tracking), then taken or refused by the backend.
count() { grep -E "\[$1\]: $1: " "$OUT/nodes.log" | tail -1 | grep -oE "(^|[ ,;])$2=[0-9]+" | grep -oE "[0-9]+$" || echo 0; }
accepted=$(( $(count verifier_node accepted) + $(count verifier_node accepted_by_tracking) ))
refused=$(( $(count verifier_node dropped_inconsistent_with_odometry) + $(count verifier_node dropped_odometry_never_came) ))
echo "closures: verifier accepted $accepted, refused by its odometry gate $refused; backend added" \
  "$(count pose_graph_node added), refused as inconsistent $(count pose_graph_node dropped_inconsistent_with_odometry)," \
  "unknown stamp $(count pose_graph_node dropped_unknown_stamp)" | tee -a "$OUT/rss.txt"
