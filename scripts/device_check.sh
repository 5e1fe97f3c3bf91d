#!/usr/bin/env bash
# Issue 35's GPU check, run on the lent 16-core GPU machine from the repository root, with the
# kit that scripts/device_kit.sh packed into .device/ carried along:
#
#   1. unpacks the kit (there is no package index there) and puts it on the paths;
#   2. smoke test, a few seconds: a SUMO sim-server and one IDM episode through it (fails fast,
#      before the long part, where a library is missing);
#   3. says what the machine has (cores, GPU, torch and whether it sees CUDA);
#   4. over a `sim-server --pool N` of SUMO `cf` simulators, N independent IDM drivers against
#      the learner sampling in processes, on the CPU and on the GPU (benchmarks/pool.py).
#
# Writes the JSON and the logs under $OUT (the device tool's folder that comes back), else
# runs/device/.
#
#     bash scripts/device_check.sh [POOL] [SECONDS]     (default: 14 simulators, 20 s each)
#
# PYTHON names the interpreter (default python3: the machine's 3.12, with its CUDA torch).
set -euo pipefail
cd "$(dirname "$0")/.."

POOL=${1:-14}
SECONDS_EACH=${2:-20}
PYTHON=${PYTHON:-python3}
KIT=$PWD/.device
OUT=${OUT:-$PWD/runs/device}
STAGE=$(mktemp -d)
SERVER=
cleanup() {
    [ -n "$SERVER" ] && kill "$SERVER" 2>/dev/null
    rm -rf "$STAGE"
}
trap cleanup EXIT
mkdir -p "$OUT"
if [ ! -d "$KIT" ]; then
    echo "device_check: no $KIT: run bash scripts/device_kit.sh here first, and carry .device" >&2
    exit 2
fi

echo "== 1. unpacking the kit"
tar -xJf "$KIT/sumo.tar.xz" -C "$STAGE"  # site/ (libsumo) and lib/ (X and GL libraries)
for wheel in "$KIT"/wheels/*.whl; do
    "$PYTHON" -m zipfile -e "$wheel" "$STAGE/site"
done
CACHE="${XDG_CACHE_HOME:-$HOME/.cache}/av-bridge/scenarios"
mkdir -p "$CACHE"
cp -r "$KIT/scenarios/." "$CACHE/"
export PYTHONPATH="$PWD:$STAGE/site${PYTHONPATH:+:$PYTHONPATH}"
export LD_LIBRARY_PATH="$STAGE/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"

echo "== 2. smoke test: a SUMO server and one IDM episode through it"
"$PYTHON" -m sim_server.cli --bind tcp://127.0.0.1:0 --backend sumo --log-level WARNING \
    > "$STAGE/server.out" 2> "$OUT/smoke-server.log" &
SERVER=$!
ADDRESS=
for _ in $(seq 600); do  # the readiness line, within 60 s
    ADDRESS=$(sed -n 's/^listening on //p' "$STAGE/server.out")
    [ -n "$ADDRESS" ] && break
    kill -0 "$SERVER" 2>/dev/null || break
    sleep 0.1
done
if [ -z "$ADDRESS" ]; then
    echo "device_check: the SUMO server did not start:" >&2
    cat "$OUT/smoke-server.log" >&2
    exit 1
fi
"$PYTHON" -m agent_client drive --server "$ADDRESS" --scenario cf --policy idm --episodes 1
kill "$SERVER"
wait "$SERVER" 2>/dev/null || true
SERVER=

echo "== 3. what this machine has"
echo "cores: $(nproc)"
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null || echo "no nvidia-smi"
"$PYTHON" - <<'PY'
import platform

import torch

cuda = torch.cuda.is_available()
name = torch.cuda.get_device_name(0) if cuda else "none"
print(f"python {platform.python_version()}, torch {torch.__version__}, CUDA GPU: {name}")
PY

echo "== 4. a pool of $POOL: independent IDM drivers, then the learner on cpu and on cuda"
"$PYTHON" benchmarks/pool.py --pool "$POOL" --seconds "$SECONDS_EACH" --sampling processes \
    --device cpu cuda --cpu --out "$OUT/pool-$POOL-gpu-machine.json" 2>&1 | tee "$OUT/pool.log"
