"""A user's own map (real SUMO and netconvert): an OpenStreetMap export we write here, built into
a network once and cached; seeded traffic and ego trips per reset; a .sumocfg with random ego
trips."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from agent_client.drivers.mobil import IDMMobilDriver
from protocol.messages import EndReason, Observation, OptionValue
from sim_server.backends.sumo.backend import SumoBackend
from sim_server.backends.sumo.maps import (
    MapNetwork,
    MapOptions,
    MapScenario,
    background_trips,
    build_osm,
    map_name,
)
from sim_server.backends.sumo.scenarios import CustomScenario
from sim_server.errors import BackendError

pytestmark = pytest.mark.sumo

SPACING_DEG = 0.0018
"""About 200 m of latitude between two streets of the town."""


def write_town(path: Path, streets: int = 4) -> Path:
    """A small town as OpenStreetMap XML: `streets` x `streets` two-way streets 200 m apart, the
    middle ones secondary roads with traffic signals where they cross, the others residential;
    a footpath and a building that a car network leaves out."""
    nodes, ways = [], []
    lat0, lon0 = 48.0, 11.0
    signals = {(i, j) for i in (1, 2) for j in (1, 2)}

    def node_id(i: int, j: int) -> int:
        return 1 + i * streets + j

    for i in range(streets):
        for j in range(streets):
            tags = '<tag k="highway" v="traffic_signals"/>' if (i, j) in signals else ""
            lat, lon = lat0 + i * SPACING_DEG, lon0 + j * SPACING_DEG * 1.5
            nodes.append(
                f'<node id="{node_id(i, j)}" lat="{lat:.7f}" lon="{lon:.7f}">{tags}</node>'
            )
    way = 1000
    for i in range(streets):
        kind = "secondary" if i in (1, 2) else "residential"
        for refs in (
            [node_id(i, j) for j in range(streets)],
            [node_id(j, i) for j in range(streets)],
        ):
            nds = "".join(f'<nd ref="{r}"/>' for r in refs)
            ways.append(f'<way id="{way}">{nds}<tag k="highway" v="{kind}"/></way>')
            way += 1
    nodes.append(f'<node id="900" lat="{lat0 - 0.001:.7f}" lon="{lon0:.7f}"/>')
    ways.append(f'<way id="{way}"><nd ref="900"/><nd ref="1"/><tag k="highway" v="footway"/></way>')
    body = "\n".join(nodes + ways)
    path.write_text(
        f'<?xml version="1.0" encoding="UTF-8"?>\n<osm version="0.6">\n{body}\n</osm>\n'
    )
    return path


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("maps")


@pytest.fixture(scope="module")
def town(cache: Path, tmp_path_factory: pytest.TempPathFactory) -> MapNetwork:
    osm = write_town(tmp_path_factory.mktemp("osm") / "town.osm.xml")
    return MapNetwork.of(build_osm(osm, cache), cache)


@pytest.fixture(scope="module")
def backend(
    cache: Path, town: MapNetwork, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[SumoBackend]:
    scenario = MapScenario(
        "town", "a town", town, defaults={"ego_route_min": 300.0, "ego_route_max": 900.0}
    )
    folder = tmp_path_factory.mktemp("cfg")
    (folder / "town.rou.xml").write_text('<routes><vType id="car"/></routes>\n')
    (folder / "town.sumocfg").write_text(
        f'<configuration><input><net-file value="{town.net_file}"/>'
        '<route-files value="town.rou.xml"/></input><time><step-length value="0.1"/></time>'
        "</configuration>\n"
    )
    own = CustomScenario("own", folder / "town.sumocfg", "random")
    sumo = SumoBackend(cache_dir=cache, custom=(scenario, own))
    yield sumo
    sumo.close()


def drive(
    backend: SumoBackend, scenario: str, seed: int, **options: OptionValue
) -> list[Observation]:
    info = {s.name: s for s in backend.scenarios()}[scenario]
    obs = backend.reset(scenario, seed, {**info.options, **options})
    driver, seen = IDMMobilDriver(), [obs]
    while not (obs.terminated or obs.truncated):
        obs = backend.step(obs.seq + 1, *driver.act(obs))
        seen.append(obs)
    return seen


def test_an_osm_export_becomes_a_network_of_car_roads_with_its_signals(town: MapNetwork) -> None:
    graph = town.graph
    assert len(graph.roads) >= 40  # 4 x 4 streets, both ways, split at each crossing
    assert graph.traffic_lights >= 2  # the signals where the secondary roads cross
    assert all(road.speed > 0 and road.length > 0 for road in graph.roads.values())
    assert set(town.starts) & set(town.ends)


def test_the_built_network_is_cached_by_the_exports_content(cache: Path, tmp_path: Path) -> None:
    osm = write_town(tmp_path / "again.osm")
    first = build_osm(osm, cache)
    start = time.monotonic()
    assert build_osm(osm, cache) == first
    assert time.monotonic() - start < 1.0
    assert map_name(osm) == "again" and map_name(Path("city.net.xml.gz")) == "city"
    bigger = build_osm(write_town(tmp_path / "again2.osm", streets=5), cache)
    assert bigger != first


def test_a_seed_draws_its_background_trips(town: MapNetwork) -> None:
    own = MapOptions(traffic=30.0, truck_share=0.5)
    first, again, other = (background_trips(town, own, seed, 600.0) for seed in (1, 1, 2))
    assert first == again and first != other
    trips = first.splitlines()
    expected = 30.0 * town.graph.lane_km(sorted(set(town.starts) | set(town.ends))) / 3600 * 690
    assert 0.6 * expected < len(trips) < 1.4 * expected  # the first batch and 600 s of arrivals
    assert 0.3 < sum('type="truck"' in t for t in trips) / len(trips) < 0.7
    assert background_trips(town, MapOptions(traffic=0.0), 1, 600.0) == ""


def test_every_reset_drives_another_trip_of_the_asked_length(backend: SumoBackend) -> None:
    routes = []
    for seed in range(4):
        seen = drive(backend, "town", seed)
        first = seen[0].route
        assert first is not None and first.length >= 300.0
        assert seen[-1].reason == EndReason.END_OF_ROAD, seed
        assert seen[-1].route is not None and seen[-1].route.driven == len(first.edges)
        assert not any(o.events.red_light for o in seen)
        routes.append(first.edges)
    assert len(set(routes)) == 4


def test_a_fixed_trip_and_a_trip_the_network_cannot_give_are_handled(backend: SumoBackend) -> None:
    info = {s.name: s for s in backend.scenarios()}["town"]
    first = drive(backend, "town", 0)[0].route
    assert first is not None
    start, end = first.edges[0], first.edges[-1]
    fixed = drive(backend, "town", 7, ego_from=start, ego_to=end)[0].route
    assert fixed is not None and fixed.edges[0] == start and fixed.edges[-1] == end
    with pytest.raises(BackendError, match="no ego trip of 50000-60000 m"):
        backend.reset(
            "town", 1, {**info.options, "ego_route_min": 50000.0, "ego_route_max": 60000.0}
        )
    with pytest.raises(BackendError, match="no road 'nowhere'"):
        backend.reset("town", 1, {**info.options, "ego_from": "nowhere", "ego_to": end})


def test_a_user_config_gets_random_ego_trips_too(backend: SumoBackend) -> None:
    info = {s.name: s for s in backend.scenarios()}["own"]
    assert "ego_route_min" in info.options and "a trip drawn per seed" in info.description
    seen = drive(backend, "own", 3, ego_route_min=300.0, ego_route_max=900.0)
    assert seen[0].route is not None and seen[-1].reason == EndReason.END_OF_ROAD
