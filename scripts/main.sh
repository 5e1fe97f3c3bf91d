#!/usr/bin/env bash
# The main job on the embedded default (libsumo), both of the paper's cases, end to end through
# the bridge, in one report:
#   1. start two SUMO servers on free loopback ports (waits for their readiness lines),
#   2. calibrate IDM on the human drivers of cf,
#   3. train the recommended learner (TD3) on cf until three greedy evaluations in a row meet
#      every target (or the time cap), and evaluate it against the calibrated IDM,
#   4. train the integrated car-following and lane-changing model on cflc, and evaluate it
#      against the cf policy (the paper's Fig. 13) and IDM,
#   5. write one report of both.
# Takes about 10-12 minutes on 2 cores; shows progress throughout.
# Environment: CF_MINUTES (training cap on cf, default 3), CFLC_MINUTES (default 5),
# EVAL_EPISODES (default 20), OUT.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"

out=${OUT:-runs/main-$(date +%Y%m%d-%H%M%S)}
episodes=${EVAL_EPISODES:-20}
mkdir -p "$out"
sim-server --bind tcp://127.0.0.1:0 --workers 2 --backend sumo \
    >"$out/server.out" 2>"$out/server.log" &
server=$!
trap 'kill "$server" 2>/dev/null; wait "$server" 2>/dev/null' EXIT

for _ in $(seq 1200); do  # two readiness lines, at most 120 s
    [ "$(grep -c '^listening on ' "$out/server.out")" -ge 2 ] && break
    kill -0 "$server" 2>/dev/null || { cat "$out/server.log"; exit 1; }
    sleep 0.1
done
mapfile -t servers < <(sed -n 's/^listening on //p' "$out/server.out")
[ "${#servers[@]}" -ge 2 ] || { echo "sim-server did not start"; cat "$out/server.log"; exit 1; }
echo "== two SUMO servers (libsumo) are listening on ${servers[*]}"
both=(--server "${servers[0]}" --server "${servers[1]}")

echo "== 1/5 calibrating IDM on the human drivers of cf"
agent-client calibrate-idm --server "${servers[0]}" --scenario cf --out "$out/idm.json"

echo "== 2/5 training the recommended learner (TD3) on cf"
agent-client train "${both[@]}" --scenario cf --out "$out/train-cf" --episodes 1000 \
    --minutes "${CF_MINUTES:-3}" --stop-when-converged
echo "== evaluating the cf policy against the calibrated IDM"
agent-client evaluate --server "${servers[0]}" --scenario cf --policy "$out/train-cf/policy.pt" \
    --baseline "idm:$out/idm.json" --episodes "$episodes" --out "$out/eval/cf" \
    --run "$out/train-cf"

echo "== 3/5 training the integrated car-following and lane-changing model on cflc"
agent-client train "${both[@]}" --scenario cflc --out "$out/train-cflc" --episodes 1000 \
    --minutes "${CFLC_MINUTES:-5}" --stop-when-converged
echo "== 4/5 evaluating it against the cf policy and IDM"
agent-client evaluate --server "${servers[0]}" --scenario cflc \
    --policy "$out/train-cflc/policy.pt" --baseline idm --cf-policy "$out/train-cf/policy.pt" \
    --episodes "$episodes" --out "$out/eval/cflc" --run "$out/train-cflc"

echo "== 5/5 one report of both cases"
agent-client report "$out/eval/cf" "$out/eval/cflc" --out "$out" \
    --title "The main job: car following on cf, car following and lane changing on cflc"
echo
echo "report: $out/report.md (the two evaluations in $out/eval/; training curves: $out/train-*/training.png)"
