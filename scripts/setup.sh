#!/usr/bin/env bash
# Create .venv and install the project with everything it needs (server, client, dev tools).
# Idempotent: reinstalls only when pyproject.toml changed since the last install.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    echo "setup: creating .venv with $($PYTHON --version)"
    "$PYTHON" -m venv .venv
fi
stamp=.venv/.av-bridge-installed
want=$(sha256sum pyproject.toml | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
    echo "setup: installing the project and its dependencies into .venv (first time: ~1-2 min)"
    .venv/bin/python -m pip install --quiet --upgrade pip
    # torch is pinned (==2.13.0, CPU build) in pyproject.toml so pip never pulls a CUDA build.
    .venv/bin/python -m pip install --quiet -e '.[all,dev]'
    echo "$want" > "$stamp"
fi
