#!/usr/bin/env bash
# The docker-compose.yml topology as local processes on loopback (docs/scaling.md): `fp merge` as the zenoh
# router on tcp/127.0.0.1:$PORT, $WORKERS `fp worker` clients, a recorder, and a publisher that replays
# $FRAMES frames of $SCENARIO paced by acknowledgements. Every process is stopped by its pid at the end.
#   deploy/compose/local.sh                          # 2 workers, 6 quick sinking-cylinder (2-D) frames
#   WORKERS=4 SCENARIO=sinking-sphere FRAMES=16 deploy/compose/local.sh
#   SHARD=fingerprint SCENARIO=sinking-sphere deploy/compose/local.sh   # fp merge --shard (frame by default)
set -euo pipefail
cd "$(dirname "$0")/../.."
FP="${FP:-.venv/bin/fp}"
PORT="${PORT:-7457}"; WORKERS="${WORKERS:-2}"; SCENARIO="${SCENARIO:-sinking-cylinder}"; FRAMES="${FRAMES:-6}"
RIG="${RIG:-sharded}"; OUT="${OUT:-out/compose}"; SHARD="${SHARD:-frame}"
HUB="tcp/127.0.0.1:$PORT"; CLIENT=(--mode client --connect "$HUB")
mkdir -p "$OUT"
pids=()
stop() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; for p in "${pids[@]}"; do wait "$p" 2>/dev/null || true; done; }
trap stop EXIT
wait_ready() { # $1: the node's stdout file; waits for its JSON "ready" line
  for _ in $(seq 600); do grep -q '"ready"' "$1" 2>/dev/null && return 0; sleep 0.2; done
  echo "no ready line in $1" >&2; return 1
}
"$FP" merge --rig "$RIG" --queue fifo --shard "$SHARD" --workers "$WORKERS" --mode router --listen "$HUB" >"$OUT/merger.out" 2>"$OUT/merger.log" &
pids+=($!)
for i in $(seq 1 "$WORKERS"); do
  "$FP" worker --rig "$RIG" --scenario "$SCENARIO" --name "w$i" "${CLIENT[@]}" >"$OUT/w$i.out" 2>"$OUT/w$i.log" &
  pids+=($!)
done
"$FP" record --rig "$RIG" -o "$OUT/sharded.mcap" "${CLIENT[@]}" >"$OUT/recorder.out" 2>"$OUT/recorder.log" &
pids+=($!)
wait_ready "$OUT/merger.out"; wait_ready "$OUT/recorder.out"
"$FP" publish --rig "$RIG" --scenario "$SCENARIO" --frames "$FRAMES" --pace ack --window $((2 * WORKERS)) \
  --wait-for processor,recorder --wait-timeout 300 "${CLIENT[@]}"
stop; trap - EXIT
tail -n 1 "$OUT/merger.out"
echo "recording: $OUT/sharded.mcap"
