"""The built-in corridors (merge, exit, lanedrop): geometry drawn per seed, options that fix it,
and the road ahead and the episode's end on them in real SUMO."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from agent_client.drivers.idm import IDMDriver
from protocol.messages import ROAD_RANGE, EndReason, Observation, OptionValue, Road
from sim_server.backends.options import TrafficOptions
from sim_server.backends.sumo.backend import SumoBackend
from sim_server.backends.sumo.corridors import (
    ACCELERATION_LANES,
    CORRIDORS,
    EXIT_DISTANCES,
    MERGE_LANES,
    MOTORWAY_SPEED,
    MOTORWAY_SPEEDS,
    ExitOptions,
    LaneDropOptions,
    MergeOptions,
)
from sim_server.backends.sumo.scenarios import EGO_ROUTE
from sim_server.errors import BackendError

JUNCTION_SLACK = 15.0
"""m: how far SUMO's lane lengths may differ from the drawn ones (junction shapes)."""


def network(name: str, seed: int, **options: OptionValue):  # type: ignore[no-untyped-def]
    scenario = CORRIDORS[name]
    own = scenario.OPTIONS[scenario.kind].parse({**scenario.info().options, **options})
    return scenario.network(own, TrafficOptions(), seed)


def edge_lengths(net) -> dict[str, float]:  # type: ignore[no-untyped-def]
    return {e: length for e, _, _, _, _, length in net.edges}


def test_the_geometry_is_drawn_from_the_seed_and_repeats_with_it() -> None:
    drawn = {seed: network("merge", seed) for seed in range(40)}
    assert network("merge", 7) == drawn[7]
    lanes = {n.edges[0][3] for n in drawn.values()}
    accelerations = {edge_lengths(n)["merge"] for n in drawn.values()}
    assert lanes == set(MERGE_LANES)
    assert accelerations == set(ACCELERATION_LANES)
    exits = {edge_lengths(network("exit", s))["main"] + edge_lengths(network("exit", s))["decel"]
             for s in range(40)}  # fmt: skip
    assert exits == set(EXIT_DISTANCES)
    for name in CORRIDORS:  # 100 km/h, or (0) every motorway edge at the seed's drawn limit
        assert motorway_limits(network(name, 5)) == {MOTORWAY_SPEED}, name
        limits = [motorway_limits(network(name, s, motorway_speed=0.0)) for s in range(40)]
        assert all(len(one) == 1 for one in limits), name
        assert set().union(*limits) == set(MOTORWAY_SPEEDS), name


def motorway_limits(net) -> set[float]:  # type: ignore[no-untyped-def]
    """The speed limits of the network's edges but the ramps (80 km/h)."""
    return {speed for edge, _, _, _, speed, _ in net.edges if "ramp" not in edge}


def test_an_option_fixes_what_it_sets_whatever_the_seed() -> None:
    for seed in range(10):
        merge = network("merge", seed, main_lanes=3, acceleration_lane=180.0)
        assert merge.edges[0][3] == 3 and edge_lengths(merge)["merge"] == 180.0
        assert merge.routes[EGO_ROUTE].startswith("ramp ")
        exit_ = network("exit", seed, exit_distance=700.0, deceleration_lane=150.0, ego_lane=1)
        assert edge_lengths(exit_)["main"] == 550.0 and exit_.depart_lane == "1"
        drop = network("lanedrop", seed, dropped_lane="left")
        assert [(a, b, i, j) for a, b, i, j in drop.connections] == [
            ("up", "down", 0, 0),
            ("up", "down", 1, 1),
        ]  # lane 2, the left one, leads nowhere
    assert network("merge", 0, ego_start="main").routes[EGO_ROUTE].startswith("main_up ")
    for name in CORRIDORS:
        assert motorway_limits(network(name, 3, motorway_speed=25.0)) == {25.0}


@pytest.mark.parametrize(
    ("kind", "options", "message"),
    [
        (MergeOptions, {"main_lanes": 1}, "main_lanes"),
        (MergeOptions, {"ego_start": "roof"}, "ego_start must be one of ramp, main"),
        (MergeOptions, {"acceleration_lane": 5.0}, ">= 20 m"),
        (ExitOptions, {"exit_distance": 150.0, "deceleration_lane": 100.0}, "at least 100 m"),
        (ExitOptions, {"exit_distance": 250.0}, "exit_distance >= 300"),  # a drawn lane: 200 m
        (ExitOptions, {"ego_lane": 4}, "ego_lane must be <= 3"),
        (LaneDropOptions, {"dropped_lane": "middle"}, "dropped_lane must be one of"),
        (LaneDropOptions, {"drop_distance": 50.0}, ">= 100 m"),
        (ExitOptions, {"motorway_speed": 2.0}, "motorway_speed must be 0 .drawn. or >= 5"),
    ],
)
def test_a_bad_geometry_is_refused_naming_the_option(
    kind: type, options: dict[str, OptionValue], message: str
) -> None:
    with pytest.raises(BackendError, match=message):
        kind.parse(options)


def test_every_corridor_announces_its_options_and_the_motorway_flow() -> None:
    for name, scenario in CORRIDORS.items():
        info = scenario.info()
        assert info.name == name and info.step_length == 0.1
        assert info.options["warmup"] == 60.0 and info.options["lane_end_patience"] == 10.0
        assert info.options["flow"] == (800.0 if name == "lanedrop" else 1000.0)
    assert "acceleration_lane" in CORRIDORS["merge"].info().options
    assert "exit_distance" in CORRIDORS["exit"].info().options


# --------------------------------------------------------------------------- in SUMO


@pytest.fixture(scope="module")
def sumo(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SumoBackend]:
    backend = SumoBackend(cache_dir=tmp_path_factory.mktemp("corridors"))
    yield backend
    backend.close()


def reset(sumo: SumoBackend, name: str, seed: int = 3, **options: OptionValue) -> Observation:
    info = {s.name: s for s in sumo.scenarios()}[name]
    return sumo.reset(name, seed, {**info.options, **options})


def drive(sumo: SumoBackend, obs: Observation, steps: int, lane_change: int = 0) -> Observation:
    """Drive with IDM (asking for `lane_change` at every step) until the episode ends or
    `steps` decisions have passed."""
    idm = IDMDriver()
    for _ in range(steps):
        if obs.terminated or obs.truncated:
            break
        obs = sumo.step(obs.seq + 1, idm.act(obs)[0], lane_change)
    return obs


@pytest.mark.sumo
def test_the_road_ahead_knows_the_exit_distance_and_the_lanes_to_cross(sumo: SumoBackend) -> None:
    obs = reset(sumo, "exit", main_lanes=3, exit_distance=800.0, deceleration_lane=200.0,
                ego_lane=2, flow=0.0)  # fmt: skip
    road = obs.road
    assert road is not None and obs.ego.lane == 2 and obs.ego.lane_count == 3
    to_exit = 800.0 - obs.ego.position  # from the ego's front to the end of the decel lane
    assert road.lanes_to_change == -2
    assert road.lane_end == pytest.approx(to_exit, abs=JUNCTION_SLACK)
    assert road.right_lane_end == pytest.approx(to_exit, abs=JUNCTION_SLACK)
    assert road.left_lane_end == 0.0  # no lane there
    later = drive(sumo, obs, 100)  # 10 s of lane keeping: the distance shrinks as it drives
    assert later.road is not None
    assert later.road.lane_end == pytest.approx(
        road.lane_end - (later.ego.position - obs.ego.position), abs=0.5
    )


@pytest.mark.sumo
def test_the_road_ahead_on_an_acceleration_lane_and_on_the_open_road(sumo: SumoBackend) -> None:
    obs = reset(sumo, "merge", main_lanes=2, acceleration_lane=250.0, ramp_length=150.0, flow=0.0,
                ramp_flow=0.0)  # fmt: skip
    ramp = obs.road  # on the ramp: nothing to do yet, but the end of the lane is in sight
    assert ramp is not None and ramp.lanes_to_change == 0
    assert ramp.lane_end == pytest.approx(150.0 + 250.0 - obs.ego.position, abs=JUNCTION_SLACK)
    while obs.ego.lane_count == 1:
        obs = drive(sumo, obs, 1)
    road = obs.road
    assert road is not None and obs.ego.lane == 0 and obs.ego.lane_count == 3
    assert road.lanes_to_change == 1 and road.left_lane_end == ROAD_RANGE
    assert 250.0 - JUNCTION_SLACK < road.lane_end <= 250.0
    assert reset(sumo, "cf").road == Road(ROAD_RANGE, 0, 0.0, 0.0)
    middle = reset(sumo, "cflc", seed=5)
    assert middle.road is not None and middle.road.lane_end == ROAD_RANGE


@pytest.mark.sumo
def test_keeping_a_lane_that_ends_ends_the_episode_at_the_lane_end(sumo: SumoBackend) -> None:
    obs = reset(sumo, "lanedrop", drop_distance=300.0, dropped_lane="right", ego_lane=0,
                flow=200.0, lane_end_patience=2.0)  # fmt: skip
    assert obs.road is not None and obs.road.lanes_to_change == 1
    last = drive(sumo, obs, 1000)
    assert last.terminated and last.reason == EndReason.LANE_END
    assert last.road is not None and last.road.lane_end < 15.0 and last.ego.speed < 1.0


@pytest.mark.sumo
def test_changing_to_a_lane_that_leads_on_reaches_the_end_of_the_route(sumo: SumoBackend) -> None:
    obs = reset(sumo, "lanedrop", drop_distance=600.0, dropped_lane="right", ego_lane=0,
                flow=100.0)  # fmt: skip
    obs = drive(sumo, obs, 30, lane_change=1)  # asked until it has started (a free road)
    assert obs.ego.lane == 1 or obs.ego.changing_lane == 1
    last = drive(sumo, obs, 2000)
    assert last.reason == EndReason.END_OF_ROAD


@pytest.mark.sumo
def test_the_leader_at_entry_is_waited_for_only_where_it_drives_the_egos_route(
    sumo: SumoBackend,
) -> None:
    """On the exit, a leader that drives through bounds nothing: no ceiling, no run-on."""
    through = reset(sumo, "exit", exit_share=0.0, ego_lane=0, exit_distance=600.0)
    last = drive(sumo, through, 3000, lane_change=-1)  # into the deceleration lane
    assert last.reason == EndReason.END_OF_ROAD and last.ceiling is None
    assert sumo._api.simulation.getTime() == pytest.approx(last.time)  # nothing simulated on
    shared = reset(sumo, "exit", exit_share=1.0, ego_lane=0, exit_distance=600.0)
    last = drive(sumo, shared, 3000, lane_change=-1)
    assert last.reason == EndReason.END_OF_ROAD
    assert last.ceiling is not None and last.ceiling.arrival_time is not None
    assert last.ceiling.arrival_time - last.time < 120.0


@pytest.mark.sumo
def test_every_corridor_builds_and_resets_on_several_seeds(
    sumo: SumoBackend, tmp_path: Path
) -> None:
    for name in CORRIDORS:
        for seed in range(3):
            obs = reset(sumo, name, seed=seed)
            assert obs.seq == 0 and obs.road is not None
