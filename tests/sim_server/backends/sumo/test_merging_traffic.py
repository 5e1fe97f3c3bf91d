"""What the traffic around the ego does for it, and what the ego sees there, in real SUMO: a
change the route needs is signalled to the traffic when its gap is too small (SUMO's drivers make
room for it), a leader on a junction or beyond one is seen at its real gap, and a road that must
give way has a stop line while foes with priority approach (protocol 1.7)."""

from __future__ import annotations

import itertools
import math
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
import sumo

from agent_client.drivers import mobil
from agent_client.drivers.mobil import IDMMobilDriver
from protocol.messages import ROAD_RANGE, EndReason, Observation, OptionValue
from sim_server.backends.sumo.backend import SumoBackend
from sim_server.backends.sumo.scenarios import CustomScenario, find_netconvert

pytestmark = pytest.mark.sumo

SUMO_RAMP = Path(sumo.SUMO_HOME) / "tools" / "game" / "ramp.sumocfg"
"""SUMO's own motorway with an on-ramp and an off-ramp, as eclipse-sumo ships it."""


RAMP_LENGTH = 250.0
"""m of the ramp that joins the motorway at a junction where it gives way (`write_yield_merge`)."""


def write_yield_merge(folder: Path) -> Path:
    """A one-lane ramp joining a one-lane road at a priority junction, where the ramp gives way
    (as Flow's merge and SMARTS's ``3lane_merge`` join theirs), 1,200 veh/h on the road; the
    ego's route ``ego`` comes from the ramp. Returns the .sumocfg."""
    (folder / "m.nod.xml").write_text(
        '<nodes><node id="w" x="0" y="0"/><node id="j" x="600" y="0" type="priority"/>'
        '<node id="e" x="1200" y="0"/><node id="r" x="400" y="-150"/></nodes>\n'
    )
    (folder / "m.edg.xml").write_text(
        '<edges><edge id="main" from="w" to="j" numLanes="1" speed="25" priority="2"/>'
        '<edge id="on" from="j" to="e" numLanes="1" speed="25" priority="2"/>'
        f'<edge id="ramp" from="r" to="j" numLanes="1" speed="16" priority="1" '
        f'length="{RAMP_LENGTH}"/></edges>\n'
    )
    subprocess.run(
        [find_netconvert(), "--node-files", str(folder / "m.nod.xml"),
         "--edge-files", str(folder / "m.edg.xml"), "--output-file", str(folder / "m.net.xml"),
         "--no-turnarounds", "true"],
        check=True, capture_output=True, timeout=60,
    )  # fmt: skip
    (folder / "m.rou.xml").write_text(
        '<routes><route id="through" edges="main on"/><route id="ego" edges="ramp on"/>'
        '<flow id="road" route="through" begin="0" end="3600" vehsPerHour="1200" '
        'departSpeed="max"/></routes>\n'
    )
    config = folder / "m.sumocfg"
    config.write_text(
        '<configuration><input><net-file value="m.net.xml"/><route-files value="m.rou.xml"/>'
        '</input><time><step-length value="0.1"/></time></configuration>\n'
    )
    return config


@pytest.fixture(scope="module")
def backend(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SumoBackend]:
    ramp = CustomScenario("ramp", SUMO_RAMP, "offramp")
    merge = CustomScenario("yield", write_yield_merge(tmp_path_factory.mktemp("yield")), "ego")
    backend = SumoBackend(cache_dir=tmp_path_factory.mktemp("merging"), custom=(ramp, merge))
    yield backend
    backend.close()


def drive_idm_mobil(
    backend: SumoBackend, scenario: str, seed: int, **options: OptionValue
) -> list[Observation]:
    """One episode of IDM + MOBIL; every observation."""
    info = {s.name: s for s in backend.scenarios()}[scenario]
    obs = backend.reset(scenario, seed, {**info.options, **options})
    driver, seen = IDMMobilDriver(), [obs]
    while not (obs.terminated or obs.truncated):
        acceleration, lane_change = driver.act(obs)
        obs = backend.step(obs.seq + 1, acceleration, lane_change)
        seen.append(obs)
    return seen


def test_dense_motorway_traffic_makes_room_for_the_merge_the_route_needs(
    backend: SumoBackend,
) -> None:
    """1,800 veh/h per lane and a 150 m acceleration lane: gaps wide enough for SUMO's gap check
    come rarely. Signalled, the change gets the room SUMO's drivers make for each other's (3 and 5
    of these 10 seeds stood at the lane end when a refused request went unsignalled)."""
    waited = 0
    for seed in range(10):
        seen = drive_idm_mobil(backend, "merge", seed, flow=1800.0, acceleration_lane=150.0,
                               main_lanes=2, ramp_flow=0.0)  # fmt: skip
        assert seen[-1].reason == EndReason.END_OF_ROAD, seed
        assert not any(o.events.collision for o in seen)
        waited += any(o.action.lane_change_refused == "gap_too_small" for o in seen)
        for before, after in itertools.pairwise(seen):  # what the protocol promises
            assert after.events.lane_change_started == (after.action.lane_change != 0)
            assert bool(after.action.lane_change_refused) == after.events.lane_change_refused
            if after.events.lane_change_started:
                assert before.ego.changing_lane == 0
                assert after.ego.changing_lane == after.action.requested_lane_change
    assert waited >= 5  # most found the gap beside them too small at first


def test_a_leader_standing_on_a_junction_within_the_min_gap_is_seen_at_its_real_gap(
    backend: SumoBackend,
) -> None:
    """SUMO's ramp, the off-ramp route: on these seeds a jam stands across the junction at the
    end of the off-ramp. SUMO reports a leader there closer than the ego's minGap at distance 0;
    read as minGap (2.5 m), IDM crept into it at 0.3 m/s and collided."""
    for seed in (200013, 200040):
        seen = drive_idm_mobil(backend, "ramp", seed)
        assert seen[-1].reason != EndReason.COLLISION, seed
        close = [o.neighbours.leader.gap for o in seen if o.neighbours.leader.present]
        assert min(close) < 2.5  # seen closer than the minGap


def test_the_gap_measured_from_positions_is_sumos_on_a_straight_road(
    backend: SumoBackend,
) -> None:
    """The measurement used for junction leaders agrees with SUMO's leader distance where both
    are defined."""
    info = {s.name: s for s in backend.scenarios()}["cf"]
    obs = backend.reset("cf", 3, dict(info.options))
    for seq in range(1, 50):
        obs = backend.step(seq, 0.0, 0)
    leader = obs.neighbours.leader
    assert leader.present
    measured = backend._bumper_gap("ego", leader.id)
    assert measured == pytest.approx(leader.gap, abs=0.05)


def test_a_road_that_gives_way_has_a_stop_line_while_foes_approach(
    backend: SumoBackend, monkeypatch: pytest.MonkeyPatch
) -> None:
    """From the ramp of a yield junction: the stop line is the end of the ramp whenever the way
    is closed; IDM + MOBIL waits there and merges on every seed. Blind to it (the driver of
    protocol 1.6), it collides with the road's traffic on some."""
    lines = []
    for seed in range(10):
        seen = drive_idm_mobil(backend, "yield", seed)
        assert seen[-1].reason == EndReason.END_OF_ROAD, seed
        lines += [o.road.stop_line for o in seen if o.road and o.road.stop_line < ROAD_RANGE]
    assert len(lines) > 100 and min(lines) < 5.0  # it waited right at the line
    assert max(lines) <= RAMP_LENGTH
    monkeypatch.setattr(mobil, "stop_line_acceleration", lambda params, obs: math.inf)
    blind = [drive_idm_mobil(backend, "yield", seed)[-1].reason for seed in range(10)]
    assert EndReason.COLLISION in blind
