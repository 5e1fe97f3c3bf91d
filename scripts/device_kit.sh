#!/usr/bin/env bash
# Packs, into .device/, what the lent 16-core GPU machine needs to run our SUMO servers and
# learner: it has Python 3.12 with a CUDA torch, numpy, scipy, matplotlib, tqdm and
# tensorboard, and reaches no package index. Run here (with network to PyPI), then carry the
# folder to the machine and run scripts/device_check.sh there (docs/learner-design.md, "On a GPU"):
#
#     bash scripts/device_kit.sh
#     run(command="bash scripts/device_check.sh", carry=[".device"], timeout_s=540)
#
# In it (about 50 MB: with the repository's own files, what a device call may carry is 64 MiB):
# - wheels/: the cp312 wheels of what the machine lacks (it has numpy, msgpack, cloudpickle);
# - sumo.tar.xz: libsumo's wheel unpacked (86 MB as a wheel), its libraries stripped of what
#   the dynamic linker does not read, the four BLAS/LAPACK builds it bundles (for GDAL's and
#   Armadillo's sake: network import, never the simulation) made one, OpenBLAS, by links; and
#   lib/, the X and GL libraries libsumo links that the machine lacks, from this Debian machine;
# - scenarios/: the built cf and cflc (no netconvert there; the cache is keyed by the files'
#   content, so they are reused).
set -euo pipefail
cd "$(dirname "$0")/.."

KIT=.device
PYTHON=.venv/bin/python
[ -x "$PYTHON" ] || bash scripts/setup.sh
SCRATCH=$(mktemp -d)
trap 'rm -rf "$SCRATCH"' EXIT

version() { "$PYTHON" -c "import importlib.metadata as m; print(m.version('$1'))"; }

rm -rf "$KIT"
mkdir -p "$KIT/wheels" "$KIT/scenarios"
mkdir -p .git/info
grep -qxF "/$KIT/" .git/info/exclude 2>/dev/null || echo "/$KIT/" >> .git/info/exclude

echo "== wheels for Python 3.12"
PACKAGES=()
for name in libsumo traci sumolib pyzmq msgspec gymnasium farama-notifications; do
    PACKAGES+=("$name==$(version "$name")")
done
"$PYTHON" -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.12 \
    --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 -d "$SCRATCH/wheels" "${PACKAGES[@]}"
mv "$SCRATCH"/wheels/*.whl "$KIT/wheels/"

echo "== libsumo and the system libraries it needs, stripped and packed"
SITE="$SCRATCH/sumo/site"
mkdir -p "$SITE" "$SCRATCH/sumo/lib"
"$PYTHON" -m zipfile -e "$KIT"/wheels/libsumo-*.whl "$SITE"
rm "$KIT"/wheels/libsumo-*.whl
find "$SITE" -name "*.so*" -type f -exec strip --strip-unneeded {} +
(
    cd "$SITE/libsumo.libs"
    openblas=$(ls libopenblasp-r0-*.so)
    for other in libopenblaso-r0-*.so libsatlas-*.so.* liblapack-*.so.* libblas-*.so.*; do
        ln -sf "$openblas" "$other"
    done
)
for lib in libX11.so.6 libXext.so.6 libXrender.so.1 libGL.so.1 libGLX.so.0 libGLdispatch.so.0 \
    libxcb.so.1 libXau.so.6 libXdmcp.so.6 libbsd.so.0 libmd.so.0 libatomic.so.1; do
    cp -L "/lib/x86_64-linux-gnu/$lib" "$SCRATCH/sumo/lib/"
done
tar -C "$SCRATCH/sumo" -cf - . | xz -9 -T0 > "$KIT/sumo.tar.xz"

echo "== built scenarios"
"$PYTHON" - "$KIT/scenarios" <<'PY'
import sys
from pathlib import Path

from sim_server.backends.sumo.scenarios import BUILTIN_SCENARIOS, build_road

for name in ("cf", "cflc"):  # with their default options: the folders a run reads
    scenario = BUILTIN_SCENARIOS[name]
    print(build_road(scenario, scenario.info().options, Path(sys.argv[1])).parent)
PY

du -sh "$KIT"
du -sh "$KIT"/*
