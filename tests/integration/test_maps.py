"""Your own map in one command, through real processes: ``sim-server --osm`` on an OSM export we
write, ``agent-client drive --json`` reporting each trip (its route, the red lights passed);
the network cached for the next start; ``--net`` on the built network; the city built in."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import RunningServer, sim_server
from tests.sim_server.backends.sumo.test_maps import write_town

pytestmark = pytest.mark.sumo

TRIPS = ["--option", "ego_route_min=300", "--option", "ego_route_max=900"]


def drive_json(address: str, scenario: str, episodes: int, *extra: str) -> list[dict[str, object]]:
    result = subprocess.run(
        [sys.executable, "-m", "agent_client.cli.main", "drive", "--server", address,
         "--scenario", scenario, "--policy", "idm+mobil", "--episodes", str(episodes), "--json",
         *extra],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    return [json.loads(line) for line in result.stdout.splitlines()]


def test_an_osm_export_is_served_driven_and_cached(tmp_path: Path) -> None:
    osm = write_town(tmp_path / "mytown.osm.xml")
    cache = tmp_path / "cache"
    start = time.monotonic()
    with sim_server("--osm", str(osm), cache_dir=cache) as server:
        first_start = time.monotonic() - start
        rows = drive_json(server.address, "mytown", 2, *TRIPS)
    assert [r["reason"] for r in rows] == ["end_of_road", "end_of_road"]
    for row in rows:
        assert isinstance(row["route_length"], float) and row["route_length"] >= 300.0
        assert isinstance(row["route_edges"], str) and len(row["route_edges"].split()) >= 2
        assert row["red_lights"] == 0 and row["collisions"] == 0
    assert rows[0]["route_edges"] != rows[1]["route_edges"]  # a trip per seed
    built = list((cache / "av-bridge" / "scenarios" / "maps").glob("mytown-*/map.net.xml.gz"))
    assert len(built) == 1
    start = time.monotonic()
    with sim_server("--net", str(built[0]), "--scenario-name", "again", cache_dir=cache) as server:
        again = time.monotonic() - start
        assert drive_json(server.address, "again", 1, *TRIPS)[0]["reason"] == "end_of_road"
    assert first_start < 60.0 and again < first_start + 5.0


def test_the_city_reports_its_trips_and_red_lights(sumo_server: RunningServer) -> None:
    rows = drive_json(
        sumo_server.address, "urban", 2, "--option", "columns=3", "--option", "rows=3"
    )
    assert all(r["reason"] == "end_of_road" and r["red_lights"] == 0 for r in rows)
    assert all(r["route_length"] and r["route_edges"] for r in rows)
