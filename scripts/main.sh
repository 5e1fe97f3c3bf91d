#!/usr/bin/env bash
# The main job on the embedded default (libsumo, scenario cf), end to end through the bridge:
#   1. start a SUMO server on a free loopback port (waits for its readiness line),
#   2. calibrate IDM on the scenario's own human drivers,
#   3. train the recommended learner (TD3) until three greedy evaluations in a row meet
#      every target (or the episode cap),
#   4. evaluate the trained policy against the calibrated IDM on the same seeds,
# and print where the report is. Takes 5-20 minutes on 2 cores; shows progress throughout.
# Environment: EPISODES (training cap, default 100), EVAL_EPISODES (default 20), OUT.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"

out=${OUT:-runs/main-$(date +%Y%m%d-%H%M%S)}
mkdir -p "$out"
sim-server --bind tcp://127.0.0.1:0 --backend sumo >"$out/server.out" 2>"$out/server.log" &
server=$!
trap 'kill "$server" 2>/dev/null; wait "$server" 2>/dev/null' EXIT

address=""
for _ in $(seq 600); do  # readiness line, at most 60 s
    address=$(sed -n 's/^listening on //p' "$out/server.out")
    [ -n "$address" ] && break
    kill -0 "$server" 2>/dev/null || { cat "$out/server.log"; exit 1; }
    sleep 0.1
done
[ -n "$address" ] || { echo "sim-server did not start"; cat "$out/server.log"; exit 1; }
echo "== sim-server (SUMO, libsumo) is listening on $address"

echo "== 1/3 calibrating IDM on the human drivers of cf"
agent-client calibrate-idm --server "$address" --scenario cf --out "$out/idm.json"

echo "== 2/3 training the recommended learner (TD3) on cf"
agent-client train --server "$address" --scenario cf --out "$out/train" \
    --episodes "${EPISODES:-100}" --stop-when-converged

echo "== 3/3 evaluating the trained policy against the calibrated IDM"
agent-client evaluate --server "$address" --scenario cf --policy "$out/train/policy.pt" \
    --baseline "idm:$out/idm.json" --episodes "${EVAL_EPISODES:-20}" --out "$out/eval" \
    --run "$out/train"

echo
echo "report: $out/eval/report.md (plots and metrics.json beside it; training curves: $out/train/training.png)"
