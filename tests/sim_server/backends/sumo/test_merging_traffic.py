"""What the traffic around the ego does for it, and what the ego sees there, in real SUMO: a
change the route needs is signalled to the traffic when its gap is too small (SUMO's drivers make
room for it), and a leader on a junction is seen at its real gap."""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from pathlib import Path

import pytest
import sumo

from agent_client.drivers.mobil import IDMMobilDriver
from protocol.messages import EndReason, Observation, OptionValue
from sim_server.backends.sumo.backend import SumoBackend
from sim_server.backends.sumo.scenarios import CustomScenario

pytestmark = pytest.mark.sumo

SUMO_RAMP = Path(sumo.SUMO_HOME) / "tools" / "game" / "ramp.sumocfg"
"""SUMO's own motorway with an on-ramp and an off-ramp, as eclipse-sumo ships it."""


@pytest.fixture(scope="module")
def backend(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SumoBackend]:
    ramp = CustomScenario("ramp", SUMO_RAMP, "offramp")
    backend = SumoBackend(cache_dir=tmp_path_factory.mktemp("merging"), custom=(ramp,))
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
