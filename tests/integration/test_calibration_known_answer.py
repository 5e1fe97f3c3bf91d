"""The known answer: `calibrate-idm` on a user's own scenario whose traffic is SUMO's IDM with
parameters chosen here must give those parameters back, and say how sure it is.

A real ``sim-server --sumocfg`` (libsumo) serves a 2 km single-lane road: a Poisson flow of
``car``s (SUMO's IDM with the parameters below, desired speeds spread by speedDev 0.1) and every
45 s a ``bus`` that stops for 8 s at 900 m, so that the cars queue, brake, stop and start again.
The calibration runs through the bridge as a user runs it (`agent-client calibrate-idm`), on the
default type (the most frequent among followers: ``car``, not ``bus``). At 0.1 s steps SUMO's IDM
takes one internal iteration per step, at 0.5 s two (its default stepping of 0.25 s).
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from agent_client.cli.main import main
from sim_server.backends.sumo.scenarios import find_netconvert
from tests.conftest import sim_server

pytestmark = [pytest.mark.sumo, pytest.mark.slow]

TRUTH = {"a": 1.2, "b": 2.0, "T": 1.4, "s0": 2.5, "delta": 4.0}
"""The cars' IDM (SUMO's accel, decel, tau, minGap, delta)."""
TOLERANCE = {"a": 0.25, "b": 0.25, "T": 0.10, "s0": 0.10}
"""Relative error allowed per parameter (the issue's: T and s0 within 10 %, a and b 25 %)."""
SPEED_LIMIT = 25.0
"""m/s on the road: each car's desired speed is its speedFactor (mean 1, sd 0.1) x this."""


def write_scenario(folder: Path, step_length: float) -> Path:
    """The road, the routes and a .sumocfg with `step_length`; returns the .sumocfg."""
    (folder / "road.nod.xml").write_text(
        '<nodes><node id="a" x="0" y="0"/><node id="b" x="2000" y="0"/></nodes>\n'
    )
    (folder / "road.edg.xml").write_text(
        f'<edges><edge id="road" from="a" to="b" numLanes="1" speed="{SPEED_LIMIT}"/></edges>\n'
    )
    subprocess.run(
        [find_netconvert(), "--node-files", str(folder / "road.nod.xml"),
         "--edge-files", str(folder / "road.edg.xml"), "--output-file", str(folder / "road.net.xml"),
         "--no-turnarounds", "true"],
        check=True, capture_output=True, timeout=60,
    )  # fmt: skip
    t = TRUTH
    (folder / "routes.rou.xml").write_text(
        "<routes>\n"
        f'  <vType id="car" carFollowModel="IDM" accel="{t["a"]}" decel="{t["b"]}" '
        f'tau="{t["T"]}" minGap="{t["s0"]}" delta="{t["delta"]}" speedFactor="1" speedDev="0.1" '
        'sigma="0"/>\n'
        '  <vType id="bus" vClass="bus" carFollowModel="IDM" accel="1.0" decel="2.0" tau="1.5" '
        'minGap="3" speedFactor="0.7" speedDev="0" sigma="0"/>\n'
        '  <route id="r" edges="road"/>\n'
        '  <flow id="cars" type="car" route="r" begin="0" end="3600" period="exp(0.4)" '
        'departSpeed="desired" departPos="base"/>\n'
        '  <flow id="buses" type="bus" route="r" begin="5" end="3600" period="45" '
        'departSpeed="desired">\n'
        '    <stop lane="road_0" endPos="900" duration="8"/>\n'
        "  </flow>\n"
        "</routes>\n"
    )
    config = folder / "idm.sumocfg"
    config.write_text(
        "<configuration>\n"
        '  <input><net-file value="road.net.xml"/><route-files value="routes.rou.xml"/></input>\n'
        f'  <time><step-length value="{step_length}"/></time>\n'
        "</configuration>\n"
    )
    return config


@pytest.mark.parametrize(("step_length", "iterations"), [(0.1, 1), (0.5, 2)])
def test_calibration_recovers_the_idm_of_the_scenarios_own_traffic(
    step_length: float,
    iterations: int,
    tmp_path: Path,
    scenario_cache: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    config = write_scenario(tmp_path, step_length)
    out = tmp_path / "idm.json"
    with sim_server(
        "--backend", "sumo", "--sumocfg", str(config), "--ego-route", "r",
        "--scenario-name", "idm_known", cache_dir=scenario_cache,
    ) as server:  # fmt: skip
        code = main(
            ["calibrate-idm", "--server", server.address, "--scenario", "idm_known",
             "--out", str(out), "--episodes", "3", "--seed", "11", "--bootstrap", "50"]
        )  # fmt: skip
    assert code == 0
    printed = capsys.readouterr().out
    assert "vehicle types among the followers: car (" in printed and "bus (" in printed
    assert f"wrote {out}" in printed and "90 % interval" in printed
    document = json.loads(out.read_text())
    data, fit, params = document["data"], document["fit"], document["params"]
    assert data["vehicle_type"] == "car" and set(data["types_seen"]) == {"car", "bus"}
    assert data["followers"] >= 60  # every car of three episodes, not one stand-in ego
    assert fit["update"] == "euler" and fit["iterations_per_step"] == iterations
    for name, tolerance in TOLERANCE.items():
        assert params[name] == pytest.approx(TRUTH[name], rel=tolerance), name
    for name, truth in TRUTH.items():  # says how sure it is, and is right to be
        low, high = document["intervals"][name]
        assert low - 1e-6 * truth <= truth <= high + 1e-6 * truth, (name, low, high)
    assert fit["at_bounds"] == [] and fit["undetermined"] == [] and fit["wide_intervals"] == []
    v0 = document["v0"]
    assert v0["determined"] >= v0["followers"] // 2
    assert 0.8 * SPEED_LIMIT < params["v0"] < 1.2 * SPEED_LIMIT
    assert fit["gap_rmse_m"] < 0.01
