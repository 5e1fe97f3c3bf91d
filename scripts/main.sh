#!/usr/bin/env bash
# The main job on the embedded default (libsumo, scenario cf): build the scenario, start a SUMO
# server on a free loopback port, drive the IDM baseline through the bridge and print its summary.
# Extra arguments go to `agent-client drive` (e.g. --episodes 10).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"

log=$(mktemp -d)
sim-server --bind tcp://127.0.0.1:0 --backend sumo >"$log/server.out" 2>"$log/server.err" &
server=$!
trap 'kill "$server" 2>/dev/null; wait "$server" 2>/dev/null; rm -rf "$log"' EXIT

address=""
for _ in $(seq 600); do  # readiness line, at most 60 s
    address=$(sed -n 's/^listening on //p' "$log/server.out")
    [ -n "$address" ] && break
    kill -0 "$server" 2>/dev/null || { cat "$log/server.err"; exit 1; }
    sleep 0.1
done
[ -n "$address" ] || { echo "sim-server did not start"; cat "$log/server.err"; exit 1; }
echo "sim-server (SUMO, libsumo) is listening on $address"

agent-client drive --server "$address" --scenario cf --policy idm --episodes 5 "$@"
