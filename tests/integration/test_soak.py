"""The soak benchmark runs (briefly) and finds no lost step."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_a_short_soak_loses_no_step_and_plots_memory(tmp_path: Path) -> None:
    out = tmp_path / "soak.json"
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "soak.py"), "--backend", "fake",
         "--episodes", "12", "--crash-every", "5", "--retry-every", "7", "--sample-every", "4",
         "--out", str(out)],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout + result.stderr
    soak = json.loads(out.read_text())
    assert soak["lost_steps"] == 0 and soak["episodes"] == 12 and soak["crashes"] == 2
    assert soak["retried_steps"] > 0 and len(soak["samples"]) >= 3
    assert out.with_suffix(".png").stat().st_size > 5_000
