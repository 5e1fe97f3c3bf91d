#!/usr/bin/env bash
# Issue 35's GPU check, run on the lent 16-core GPU machine from the repository root, with the
# kit scripts/device_kit.sh packed into .device/ carried along: unpacks it (no package index
# there), checks that SUMO, ZeroMQ and torch with CUDA import, then measures in one run, over a
# `sim-server --pool N` of SUMO `cf` simulators, N independent IDM drivers against the learner
# with sampling processes, on the CPU and on the GPU (benchmarks/pool.py). Writes the JSON and
# the log under $OUT (the device tool's folder that comes back), else runs/device/.
#
#     bash scripts/device_check.sh [POOL] [SECONDS]     (default: 14 simulators, 20 s each)
set -euo pipefail
cd "$(dirname "$0")/.."

POOL=${1:-14}
SECONDS_EACH=${2:-20}
KIT=$PWD/.device
OUT=${OUT:-$PWD/runs/device}
STAGE=$(mktemp -d)
trap 'rm -rf "$STAGE"' EXIT
mkdir -p "$OUT"
[ -d "$KIT" ] || { echo "no $KIT: run bash scripts/device_kit.sh first, then carry .device" >&2; exit 2; }

echo "== unpacking the kit"
mkdir -p "$STAGE/site"
tar -xJf "$KIT/libsumo.tar.xz" -C "$STAGE/site"
for wheel in "$KIT"/wheels/*.whl; do
    python3 -m zipfile -e "$wheel" "$STAGE/site"
done
CACHE="${XDG_CACHE_HOME:-$HOME/.cache}/av-bridge/scenarios"
mkdir -p "$CACHE"
cp -r "$KIT/scenarios/." "$CACHE/"
export PYTHONPATH="$PWD:$STAGE/site${PYTHONPATH:+:$PYTHONPATH}"
export LD_LIBRARY_PATH="$KIT/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"

echo "== what this machine has"
nproc
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null || echo "no nvidia-smi"
python3 - <<'PY'
import platform

import libsumo  # noqa: F401
import torch
import zmq

print(f"python {platform.python_version()}, torch {torch.__version__}, zmq {zmq.zmq_version()}")
print(f"cuda: {torch.cuda.is_available()} {torch.cuda.get_device_name(0) if torch.cuda.is_available() else ''}")
PY

echo "== pool of $POOL: independent IDM drivers, then the learner on cpu and cuda"
python3 benchmarks/pool.py --pool "$POOL" --seconds "$SECONDS_EACH" --sampling processes \
    --device cpu cuda --cpu --out "$OUT/pool-$POOL-gpu-machine.json" 2>&1 | tee "$OUT/pool.log"
