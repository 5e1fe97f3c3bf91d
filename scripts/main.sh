#!/usr/bin/env bash
# The main job on the embedded default (libsumo), both of the paper's cases, end to end through
# the bridge, in one report. It starts four SUMO servers on free loopback ports, two to train
# on and two to evaluate on (and waits for their readiness lines), then:
#   1. calibrates IDM on the human drivers of cf,
#   2. trains the recommended learner (TD3) on cf with the defaults, which are the settings
#      measured best for it (configs/cf.toml spells them out), until three greedy evaluations
#      in a row meet every target (or the time cap), and evaluates it against the calibrated IDM,
#   3. trains the integrated car-following and lane-changing model on cflc (its defaults),
#   4. evaluates it against the cf policy (the paper's Fig. 13) and the strongest baselines,
#      IDM + MOBIL and SUMO's own driver, on the same seeds,
#   5. writes one report of both.
# Takes about 5 minutes on 2 cores (4.5 and 5.2 measured; at most 15); shows progress throughout.
# Environment: CF_MINUTES (training cap on cf, default 3), CFLC_MINUTES (default 8),
# EVAL_EPISODES (default 20), OUT.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"

out=${OUT:-runs/main-$(date +%Y%m%d-%H%M%S)}
episodes=${EVAL_EPISODES:-20}
mkdir -p "$out"
# Training steps on two tcp:// servers; greedy evaluations run in the background on two
# direct:// servers of their own, in the kernel's idle scheduling class (they get the CPU time
# training leaves), one worker process driving each (docs/learner.md, "Evaluations during
# training").
start_servers() {  # start_servers NAME SCHEME [ARGS]: two SUMO servers, addresses in NAME.out
    sim-server --bind "$2://127.0.0.1:0" --workers 2 --backend sumo "${@:3}" \
        >"$out/$1.out" 2>"$out/$1.log" &
    pids+=($!)
}
pids=()
trap 'kill "${pids[@]}" 2>/dev/null; wait "${pids[@]}" 2>/dev/null' EXIT
start_servers server tcp
start_servers eval-server direct --idle-priority
addresses() {  # addresses NAME: wait for its two readiness lines (at most 120 s), print them
    for _ in $(seq 1200); do
        [ "$(grep -c '^listening on ' "$out/$1.out")" -ge 2 ] && break
        kill -0 "${pids[@]}" 2>/dev/null || { cat "$out/$1.log"; exit 1; }
        sleep 0.1
    done
    sed -n 's/^listening on //p' "$out/$1.out"
}
mapfile -t servers < <(addresses server)
mapfile -t eval_servers < <(addresses eval-server)
[ "${#servers[@]}" -ge 2 ] || { echo "sim-server did not start"; cat "$out/server.log"; exit 1; }
[ "${#eval_servers[@]}" -ge 2 ] || { echo "sim-server did not start"; cat "$out/eval-server.log"; exit 1; }
echo "== four SUMO servers (libsumo) are listening: training on ${servers[*]}, evaluations on ${eval_servers[*]}"
training=(--server "${servers[0]}" --server "${servers[1]}"
      --eval-server "${eval_servers[0]}" --eval-server "${eval_servers[1]}")

echo "== 1/5 calibrating IDM on the human drivers of cf"
agent-client calibrate-idm --server "${servers[0]}" --scenario cf --out "$out/idm.json"

echo "== 2/5 training the recommended learner (TD3) on cf (its recommended settings: the defaults)"
agent-client train "${training[@]}" --scenario cf --out "$out/train-cf" --episodes 1000 \
    --minutes "${CF_MINUTES:-3}" --stop-when-converged
echo "== evaluating the cf policy against the calibrated IDM and SUMO's own driver"
agent-client evaluate --server "${eval_servers[0]}" --scenario cf --policy "$out/train-cf/policy.pt" \
    --baseline "idm:$out/idm.json" --reference sumo --episodes "$episodes" --out "$out/eval/cf" \
    --run "$out/train-cf"

echo "== 3/5 training the integrated car-following and lane-changing model on cflc"
agent-client train "${training[@]}" --scenario cflc \
    --out "$out/train-cflc" --episodes 1000 \
    --minutes "${CFLC_MINUTES:-8}" --stop-when-converged
echo "== 4/5 evaluating it against IDM + MOBIL, SUMO's own driver and the cf policy"
agent-client evaluate --server "${eval_servers[0]}" --scenario cflc \
    --policy "$out/train-cflc/policy.pt" --baseline idm+mobil --reference sumo \
    --cf-policy "$out/train-cf/policy.pt" \
    --episodes "$episodes" --out "$out/eval/cflc" --run "$out/train-cflc"

echo "== 5/5 one report of both cases"
agent-client report "$out/eval/cf" "$out/eval/cflc" --out "$out" \
    --title "The main job: car following on cf, car following and lane changing on cflc"
echo
echo "report: $out/report.md (the two evaluations in $out/eval/; training curves: $out/train-*/training.png)"
