#!/usr/bin/env bash
# The project's test command: lint, format check, type check, then the whole test suite
# (unit tests and integration tests with real SUMO servers on loopback).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"
echo "== ruff check";  ruff check protocol sim_server agent_client tests benchmarks examples
echo "== ruff format"; ruff format --check protocol sim_server agent_client tests benchmarks examples
echo "== mypy";        mypy
echo "== pytest";      python -m pytest -q "$@"
